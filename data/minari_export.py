"""Write episodes as a Minari dataset (Farama's format for offline RL on Gymnasium environments).

Why: offline-RL and imitation code written against Minari loads a dataset by name (``minari.load_dataset``) and
gets Gymnasium spaces with it. The dataset has ``towndrive/Drive-v0``'s observation and action spaces for the
recorded camera size (image, speed, command; plus stereo and side cameras when recorded), and the env's id as its
evaluation environment.

What does not map one to one, and what is done instead:

* an episode of ``T`` steps holds ``T`` observations and ``T`` actions, but Minari wants the observation after the
  last action too, which was never recorded: the export keeps ``T`` observations and the first ``T - 1`` actions
  (``T - 1`` transitions), so nothing is invented;
* rewards were not recorded: they are zero, and the per-step ground truth (``infos``: progress along the route,
  lane offset, ...) is there to compute any reward from;
* the last transition is a truncation (the recording stopped), not a termination.

Needs the ``minari`` extra (``pip install 'towndrive[minari]'``). All or nothing: a failure removes the dataset.
"""

from __future__ import annotations

import shutil
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from towndrive.data.episodes import COMMAND_NAMES, EpisodeError, episode_sources, read_episode
from towndrive.extras import import_for

ENV_ID = "towndrive/Drive-v0"
CAMERA_KEYS = {"stereo_right": "stereo", "side_left": "side"}  # episode dataset -> the env's observation key
MAX_SPEED_MPS = 50.0  # the env's speed space


class MinariExportError(ValueError):
    """A Minari export that cannot be made; one sentence naming what and why."""


def observation_space(height: int, width: int, stereo: bool, side: bool) -> Any:
    """Drive-v0's observation space for a camera of ``width`` x ``height`` (the env's own, rebuilt here)."""
    from gymnasium import spaces

    obs: dict[str, Any] = {"image": spaces.Box(0, 255, (height, width, 3), np.uint8),
                           "speed": spaces.Box(0.0, MAX_SPEED_MPS, (1,), np.float32),
                           "command": spaces.Discrete(len(COMMAND_NAMES))}
    if stereo:
        obs["stereo"] = spaces.Box(0, 255, (2, height, width, 3), np.uint8)
    if side:
        obs["side"] = spaces.Box(0, 255, (2, height, width, 3), np.uint8)
    return spaces.Dict(obs)


def _buffer(path: Path, minari: Any, stereo: bool, side: bool, episode_id: int) -> Any:
    ep = read_episode(path)
    try:
        with h5py.File(path, "r") as f:
            left = f["frames"][()]
            extra = {name: f[name][()] for name in ("stereo_right", "side_left", "side_right") if name in f}
    except (OSError, KeyError, ValueError) as exc:
        raise EpisodeError(f"{path}: cannot read its frames ({exc}); the file is corrupt, re-record or delete it.") from exc
    n = ep.steps
    if n < 2:
        raise MinariExportError(f"{path}: an episode of {n} step(s) makes no transition; leave it out.")
    observations: dict[str, np.ndarray] = {
        "image": left, "speed": np.clip(ep.speed.reshape(n, 1), 0.0, MAX_SPEED_MPS).astype(np.float32),
        "command": ep.command.astype(np.int64)}
    if stereo:
        observations["stereo"] = np.stack([left, extra["stereo_right"]], axis=1)
    if side:
        observations["side"] = np.stack([extra["side_left"], extra["side_right"]], axis=1)
    infos = {name: values.astype(np.float32) for name, values in ep.truth.items()}
    truncations = np.zeros(n - 1, bool)
    truncations[-1] = True
    seed = ep.attrs.get("seed")
    return minari.data_collector.EpisodeBuffer(
        id=episode_id, seed=int(seed) if isinstance(seed, int) and seed >= 0 else None,
        options={"town_seed": int(ep.attrs.get("town_seed", -1)), "weather": str(ep.attrs.get("weather", "unknown"))},
        observations=observations, actions=ep.actions[: n - 1].astype(np.float32),
        rewards=np.zeros(n - 1, np.float64).tolist(), terminations=np.zeros(n - 1, bool).tolist(),
        truncations=truncations.tolist(), infos=infos)


def export_minari(src: Path, dataset_id: str, progress: bool = False, stop: Callable[[], None] | None = None) -> Path:
    """Write episodes (a folder, or one file) as the Minari dataset ``dataset_id``; returns its folder."""
    from tqdm import tqdm

    minari = import_for("minari", "towndrive data export-minari")
    from minari.dataset.minari_dataset import parse_dataset_id
    from minari.storage import get_dataset_path

    try:
        parse_dataset_id(dataset_id)
    except ValueError as exc:
        raise MinariExportError(f"{dataset_id!r} is not a Minari dataset id ({exc}); use e.g. towndrive/autopilot-v0.") from None
    if dataset_id in minari.list_local_datasets():
        raise MinariExportError(f"Minari dataset {dataset_id} already exists at {get_dataset_path(dataset_id)}; "
                                "pick another name or delete it with minari.delete_dataset.")
    paths = episode_sources(src)
    shapes, drivers = set(), set()
    for path in paths:
        drivers.add(str(read_episode(path, load_frames=False).attrs.get("driver", "unknown")))  # corrupt: stops here
        try:
            with h5py.File(path, "r") as f:
                shapes.add((tuple(f["frames"].shape[1:]), "stereo_right" in f, "side_left" in f and "side_right" in f))
        except (OSError, KeyError) as exc:
            raise EpisodeError(f"{path}: cannot read this episode ({exc}); the file is corrupt.") from exc
    if len(shapes) > 1:
        raise MinariExportError(f"the episodes in {src} differ in camera size or cameras; a Minari dataset has one "
                                "observation space, so export them separately.")
    (height, width, _), stereo, side = shapes.pop()
    import towndrive  # noqa: F401  (registers towndrive/Drive-v0, named as the evaluation env)

    description = ("towndrive episodes: camera frames, speed (m/s) and route command (0 follow, 1 left, 2 right, "
                   "3 straight); actions [steer, throttle_brake] in [-1, 1]. Rewards were not recorded (zero); "
                   "infos hold the per-step ground truth. The observation after the last action was not recorded, so "
                   "an episode of T steps has T - 1 transitions.")
    dataset = None
    bar = tqdm(total=len(paths), desc="export-minari", unit="episode", disable=not progress)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", category=UserWarning, module="minari")  # no author, e-mail or env_spec
            for k, path in enumerate(paths):
                buffer = _buffer(path, minari, stereo, side, k)
                if dataset is None:
                    dataset = minari.create_dataset_from_buffers(
                        dataset_id, [buffer], eval_env=ENV_ID, algorithm_name=", ".join(sorted(drivers)),
                        observation_space=observation_space(height, width, stereo, side),
                        action_space=_action_space(), description=description, **_lossless(minari))
                else:
                    dataset.update_dataset_from_buffer([buffer])
                bar.update(1)
                if stop is not None:
                    stop()
    except BaseException:
        shutil.rmtree(get_dataset_path(dataset_id), ignore_errors=True)
        raise
    finally:
        bar.close()
    return Path(get_dataset_path(dataset_id))


def _lossless(minari: Any) -> dict[str, Any]:
    """Frames stored as they are: Minari releases that can JPEG-encode images do so unless told not to."""
    import inspect

    return {"jpeg_encoding": False} if "jpeg_encoding" in inspect.signature(minari.create_dataset_from_buffers).parameters else {}


def _action_space() -> Any:
    from gymnasium import spaces

    return spaces.Box(-1.0, 1.0, (2,), np.float32)
