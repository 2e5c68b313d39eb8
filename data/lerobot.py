"""Convert between towndrive episodes and a LeRobotDataset v3 directory.

Why: LeRobotDataset is the format most robot-learning code reads demonstrations from, so a recording made here
trains there, and a dataset in that layout (with a front camera, steering and throttle) trains PilotNet here.
The layout is written with pyarrow and PyAV, from LeRobot's published v3.0 layout; the ``lerobot`` package is
neither needed nor imported. A v3 directory holds:

  meta/info.json                                   codebase_version "v3.0", fps, features (dtype, shape, names;
                                                   a video feature's stream facts), totals, path templates
  meta/stats.json                                  per feature: min, max, mean, std, count, q01 q10 q50 q90 q99
                                                   (cameras: per channel, shape (3, 1, 1), in [0, 1])
  meta/tasks.parquet                               one row per task string: task (the index), task_index
  meta/episodes/chunk-000/file-000.parquet         one row per episode: length, tasks, where its rows and video
                                                   segments are (data/..., videos/<key>/..., from/to timestamps),
                                                   its own statistics (stats/<feature>/<stat>)
  data/chunk-000/file-000.parquet                  one row per frame, one row group per episode
  videos/<camera>/chunk-000/file-000.mp4           each camera's frames, several episodes per file

What goes where: ``frames`` becomes ``observation.images.front``; ``stereo_right``, ``side_left`` and
``side_right`` their own cameras when recorded; ``observation.state`` is ``[speed_mps, command]``; ``action`` is
``[steer, throttle_brake]``; each ground-truth series ``truth/<name>`` becomes the feature ``truth.<name>``;
``timestamp`` is ``frame_index / fps``. The task of an episode says where it drove ("drive the route in town 3,
night"). Depth and segmentation are not exported (lossy video would change their values).

Both directions are all or nothing: everything is written into a hidden folder next to the destination and
renamed into place when complete, so a failure or a stop signal leaves no partial dataset.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from towndrive.data.episodes import (
    COMMAND_NAMES,
    TRUTH_FIELDS,
    EpisodeError,
    EpisodeWriter,
    episode_sources,
    read_episode,
)
from towndrive.data.video import Mp4Writer, VideoError, VideoSettings, probe, read_frames
from towndrive.extras import import_for

CODEBASE_VERSION = "v3.0"
FRONT = "observation.images.front"
CAMERAS = {"frames": FRONT, "stereo_right": "observation.images.stereo_right",
           "side_left": "observation.images.side_left", "side_right": "observation.images.side_right"}
STATE_NAMES = ["speed_mps", "command"]
ACTION_NAMES = ["steer", "throttle_brake"]
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
INDEX_FEATURES = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64", "index": "int64",
                  "task_index": "int64"}
_IMAGE_NAMES = ["height", "width", "channels"]


class LeRobotError(ValueError):
    """A LeRobot dataset that cannot be written or read; the message names the file and what to do."""


@dataclass(frozen=True)
class LeRobotSettings:
    """How a dataset is laid out: file sizes before the next file starts, and the video encoding."""

    video: VideoSettings = field(default_factory=VideoSettings)
    chunks_size: int = 1000  # files per chunk folder
    data_file_size_mb: int = 100  # a parquet file of frames grows to about this size, then the next one starts
    video_file_size_mb: int = 200  # an MP4 file grows to about this size, then the next one starts
    stats_frames_per_episode: int = 40  # frames of each episode sampled for a camera's statistics


def _pyarrow() -> Any:
    import_for("pyarrow.parquet", "LeRobot datasets")
    import pyarrow as pa
    import pyarrow.parquet as pq

    return pa, pq


# ----------------------------------------------------------------------------------------------------------------
# Destinations: written next to the destination, renamed into place


def check_destination(dst: Path) -> None:
    """A destination must be new or an empty folder (one sentence otherwise)."""
    dst = Path(dst)
    if dst.exists() and (not dst.is_dir() or any(dst.iterdir())):
        raise LeRobotError(f"{dst}: already exists and is not empty; give a new or empty folder.")


@contextlib.contextmanager
def staged(dst: Path) -> Iterator[Path]:
    """A hidden folder next to ``dst`` to write into; renamed to ``dst`` when the block ends well, deleted when not."""
    dst = Path(dst).absolute()
    check_destination(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dst.name}.", suffix=".partial", dir=dst.parent))
    try:
        yield tmp
        check_destination(dst)  # nobody wrote there meanwhile
        if dst.exists():
            dst.rmdir()
        os.replace(tmp, dst)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


# ----------------------------------------------------------------------------------------------------------------
# Statistics


def feature_stats(values: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's statistics of one feature: ``values`` is (N, D); every statistic has shape (D,)."""
    values = np.asarray(values, np.float64)
    finite = np.where(np.isfinite(values), values, np.nan)
    with np.errstate(all="ignore"), _quiet_nan():
        stats = {"min": np.nanmin(finite, axis=0), "max": np.nanmax(finite, axis=0),
                 "mean": np.nanmean(finite, axis=0), "std": np.nanstd(finite, axis=0),
                 "count": np.array([len(values)])}
        for key, q in QUANTILES.items():
            stats[key] = np.nanquantile(finite, q, axis=0)
    return stats


@contextlib.contextmanager
def _quiet_nan() -> Iterator[None]:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN column (unknown truth) has NaN statistics
        yield


def image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """Per-channel statistics of RGB frames (N, H, W, 3), scaled to [0, 1], each of shape (3, 1, 1)."""
    pixels = frames.reshape(-1, 3).astype(np.float32) / 255.0
    if len(pixels) > 200_000:  # quantiles from an even subsample: the same figures to three decimals, far cheaper
        pixels = pixels[:: len(pixels) // 200_000]
    stats = feature_stats(pixels)
    stats = {k: (v.reshape(3, 1, 1) if k != "count" else np.array([len(frames)])) for k, v in stats.items()}
    return stats


def _json_stats(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    def clean(x: Any) -> Any:
        if isinstance(x, list):
            return [clean(v) for v in x]
        return None if isinstance(x, float) and not math.isfinite(x) else x

    return {name: {k: clean(np.asarray(v).tolist()) for k, v in s.items()} for name, s in stats.items()}


# ----------------------------------------------------------------------------------------------------------------
# Export


@dataclass
class _Source:
    path: Path
    attrs: dict[str, Any]
    steps: int
    cameras: dict[str, tuple[int, ...]]  # episode dataset name -> frame shape


def task_of(attrs: dict[str, Any]) -> str:
    """The task string of an episode: where it drove."""
    town, weather = attrs.get("town_seed", -1), attrs.get("weather", "unknown")
    if town is None or int(town) < 0:
        return f"drive the route ({attrs.get('driver', 'unknown')} recording)"
    return f"drive the route in town {int(town)}, {weather}"


def _fps(sources: list[_Source]) -> int:
    dts = {float(s.attrs.get("dt_s", 0.05)) for s in sources}
    if len(dts) > 1:
        raise LeRobotError(f"the episodes were recorded at different time steps ({', '.join(map(str, sorted(dts)))} s); "
                           "a LeRobot dataset has one fps, so export them separately.")
    dt = dts.pop()
    fps = round(1.0 / dt) if dt > 0 else 0
    if fps < 1 or abs(fps * dt - 1.0) > 1e-6:
        raise LeRobotError(f"{sources[0].path}: a time step of {dt} s is not a whole number of frames per second, "
                           "which LeRobot's fps must be.")
    return fps


def _inspect(paths: list[Path]) -> list[_Source]:
    """Every episode checked before anything is written: readable, not empty, the same cameras at the same size."""
    sources = []
    for path in paths:
        ep = read_episode(path, load_frames=False)  # EpisodeError names a corrupt file
        try:
            with h5py.File(path, "r") as f:
                cameras = {name: tuple(f[name].shape[1:]) for name in CAMERAS if name in f}
        except OSError as exc:
            raise EpisodeError(f"{path}: cannot read this episode ({exc}); the file is corrupt.") from exc
        if ep.steps == 0:
            raise EpisodeError(f"{path}: the episode has no steps; delete it or leave it out.")
        sources.append(_Source(path, ep.attrs, ep.steps, cameras))
    first = sources[0]
    for s in sources[1:]:
        if s.cameras != first.cameras:
            raise LeRobotError(f"{s.path} has cameras {s.cameras} but {first.path} has {first.cameras}; every episode "
                               "of a LeRobot dataset has the same features, so export them separately.")
    return sources


class _VideoFiles:
    """One camera's MP4 files: episodes appended to the current file until it reaches the size limit."""

    def __init__(self, root: Path, key: str, fps: int, shape: tuple[int, ...], settings: LeRobotSettings) -> None:
        self.root, self.key, self.fps, self.settings = root, key, fps, settings
        self.height, self.width = shape[0], shape[1]
        self.file_index = -1
        self.writer: Mp4Writer | None = None
        self.paths: list[Path] = []

    def _next(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.file_index += 1
        chunk, file = divmod(self.file_index, self.settings.chunks_size)
        path = self.root / VIDEO_PATH.format(video_key=self.key, chunk_index=chunk, file_index=file)
        self.writer = Mp4Writer(path, self.fps, self.width, self.height, self.settings.video)
        self.paths.append(path)

    def begin_episode(self) -> dict[str, Any]:
        full = self.writer is not None and self.writer.path.stat().st_size >= self.settings.video_file_size_mb * 2**20
        if self.writer is None or full:
            self._next()
        assert self.writer is not None
        chunk, file = divmod(self.file_index, self.settings.chunks_size)
        return {f"videos/{self.key}/chunk_index": chunk, f"videos/{self.key}/file_index": file,
                f"videos/{self.key}/from_timestamp": self.writer.frames / self.fps}

    def end_episode(self) -> dict[str, Any]:
        assert self.writer is not None
        return {f"videos/{self.key}/to_timestamp": self.writer.frames / self.fps}

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def abort(self) -> None:
        if self.writer is not None:
            self.writer.abort()
            self.writer = None


def _features(sources: list[_Source]) -> dict[str, dict[str, Any]]:
    features: dict[str, dict[str, Any]] = {}
    for name, shape in sources[0].cameras.items():
        features[CAMERAS[name]] = {"dtype": "video", "shape": list(shape), "names": _IMAGE_NAMES}
    features["observation.state"] = {"dtype": "float32", "shape": [2], "names": STATE_NAMES}
    features["action"] = {"dtype": "float32", "shape": [2], "names": ACTION_NAMES}
    for name in TRUTH_FIELDS:
        features[f"truth.{name}"] = {"dtype": "float32", "shape": [1], "names": [name]}
    for name, dtype in INDEX_FEATURES.items():
        features[name] = {"dtype": dtype, "shape": [1], "names": None}
    return features


def _episode_columns(source: _Source, fps: int, episode_index: int, first_index: int, task_index: int,
                     ) -> dict[str, np.ndarray]:
    ep = read_episode(source.path, load_frames=False)
    n = ep.steps
    columns: dict[str, np.ndarray] = {
        "observation.state": np.stack([ep.speed.astype(np.float32), ep.command.astype(np.float32)], axis=1),
        "action": ep.actions.astype(np.float32),
    }
    for name in TRUTH_FIELDS:
        columns[f"truth.{name}"] = ep.truth.get(name, np.full(n, np.nan, np.float32)).astype(np.float32)
    frame_index = np.arange(n, dtype=np.int64)
    columns.update({"timestamp": (frame_index / fps).astype(np.float32), "frame_index": frame_index,
                    "episode_index": np.full(n, episode_index, np.int64),
                    "index": first_index + frame_index, "task_index": np.full(n, task_index, np.int64)})
    return columns


def _arrow_table(columns: dict[str, np.ndarray]) -> Any:
    pa, _ = _pyarrow()
    arrays, names = [], []
    for name, values in columns.items():
        if values.ndim == 2:  # a vector per frame: a fixed-size list, as LeRobot's (length, dtype) sequences
            flat = pa.array(values.reshape(-1), type=pa.from_numpy_dtype(values.dtype))
            arrays.append(pa.FixedSizeListArray.from_arrays(flat, values.shape[1]))
        else:
            arrays.append(pa.array(values, type=pa.from_numpy_dtype(values.dtype)))
        names.append(name)
    return pa.Table.from_arrays(arrays, names=names)


def _frames(path: Path, name: str, steps: int, block: int = 64) -> Iterator[np.ndarray]:
    """An episode's frames of one camera, read a block at a time."""
    try:
        with h5py.File(path, "r") as f:
            ds = f[name]
            for start in range(0, steps, block):
                yield from ds[start:start + block]
    except (OSError, ValueError, KeyError) as exc:
        raise EpisodeError(f"{path}: cannot read {name} ({exc}); the file is corrupt, re-record or delete it.") from exc


def export_lerobot(src: Path, dst: Path, settings: LeRobotSettings | None = None, progress: bool = False,
                   stop: Callable[[], None] | None = None) -> dict[str, Any]:
    """Write episodes (a folder, or one file) as a LeRobotDataset v3 directory ``dst`` (new or empty).
    Returns what was written: episodes, frames, fps and each camera's video bytes."""
    from tqdm import tqdm

    settings = settings or LeRobotSettings()
    pa, pq = _pyarrow()
    pd = import_for("pandas", "LeRobot datasets")
    check_destination(dst)
    sources = _inspect(episode_sources(src))
    fps = _fps(sources)
    features = _features(sources)
    tasks: dict[str, int] = {}
    for s in sources:
        tasks.setdefault(task_of(s.attrs), len(tasks))
    total = sum(s.steps for s in sources)
    bar = tqdm(total=total, desc="export-lerobot", unit="frame", disable=not progress)
    with staged(dst) as root:
        videos = {name: _VideoFiles(root, CAMERAS[name], fps, shape, settings) for name, shape in sources[0].cameras.items()}
        data_writer: Any = None
        data_file, data_bytes = -1, 0
        episodes: list[dict[str, Any]] = []
        all_columns: list[dict[str, np.ndarray]] = []
        camera_samples: dict[str, list[np.ndarray]] = {CAMERAS[n]: [] for n in sources[0].cameras}
        try:
            index = 0
            for k, source in enumerate(sources):
                task = task_of(source.attrs)
                columns = _episode_columns(source, fps, k, index, tasks[task])
                table = _arrow_table(columns)
                if data_writer is None or data_bytes >= settings.data_file_size_mb * 2**20:
                    if data_writer is not None:
                        data_writer.close()
                    data_file += 1
                    chunk, file = divmod(data_file, settings.chunks_size)
                    path = root / DATA_PATH.format(chunk_index=chunk, file_index=file)
                    path.parent.mkdir(parents=True, exist_ok=True)
                    data_writer, data_bytes = pq.ParquetWriter(str(path), table.schema, compression="snappy"), 0
                data_writer.write_table(table)  # one row group per episode
                data_bytes += table.nbytes
                chunk, file = divmod(data_file, settings.chunks_size)
                row: dict[str, Any] = {"episode_index": k, "tasks": [task], "length": source.steps,
                                       "data/chunk_index": chunk, "data/file_index": file,
                                       "dataset_from_index": index, "dataset_to_index": index + source.steps}
                sample_at = set(np.linspace(0, source.steps - 1, min(source.steps, settings.stats_frames_per_episode))
                                .round().astype(int).tolist())
                for name, video in videos.items():
                    row.update(video.begin_episode())
                    samples = []
                    assert video.writer is not None
                    for t, frame in enumerate(_frames(source.path, name, source.steps)):
                        video.writer.add(frame)
                        if t in sample_at:
                            samples.append(frame)
                        if name == "frames":
                            bar.update(1)
                            if stop is not None:
                                stop()
                    row.update(video.end_episode())
                    camera_samples[video.key].append(np.stack(samples))
                    for stat, value in image_stats(np.stack(samples)).items():
                        row[f"stats/{video.key}/{stat}"] = value.tolist()
                for name, values in columns.items():
                    for stat, value in feature_stats(values.reshape(len(values), -1)).items():
                        row[f"stats/{name}/{stat}"] = value.tolist()
                row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,
                            "towndrive/source": source.path.name, "towndrive/seed": int(source.attrs.get("seed", -1)),
                            "towndrive/town_seed": int(source.attrs.get("town_seed", -1)),
                            "towndrive/weather": str(source.attrs.get("weather", "unknown")),
                            "towndrive/driver": str(source.attrs.get("driver", "unknown"))})
                episodes.append(row)
                all_columns.append(columns)
                index += source.steps
            if data_writer is not None:
                data_writer.close()
            for video in videos.values():
                video.close()
        except BaseException:
            for video in videos.values():
                video.abort()
            if data_writer is not None:
                with contextlib.suppress(Exception):
                    data_writer.close()
            raise
        finally:
            bar.close()
        # Statistics of the whole dataset.
        stats: dict[str, dict[str, np.ndarray]] = {}
        for key, samples in camera_samples.items():
            stats[key] = image_stats(np.concatenate(samples))
            stats[key]["count"] = np.array([total])
        for name in all_columns[0]:
            values = np.concatenate([c[name] for c in all_columns])
            stats[name] = feature_stats(values.reshape(len(values), -1))
        # Metadata.
        meta = root / "meta"
        (meta / "episodes" / "chunk-000").mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist(episodes), str(root / EPISODES_PATH.format(chunk_index=0, file_index=0)))
        pd.DataFrame({"task_index": list(tasks.values())}, index=pd.Index(list(tasks), name="task")).to_parquet(
            meta / "tasks.parquet")
        for name, video in videos.items():
            facts = probe(video.paths[0])
            facts.pop("frames")
            features[CAMERAS[name]]["info"] = {**facts, "video.is_depth_map": False, "is_depth_map": False}
        info = {"codebase_version": CODEBASE_VERSION, "robot_type": "towndrive_car", "total_episodes": len(sources),
                "total_frames": total, "total_tasks": len(tasks), "chunks_size": settings.chunks_size,
                "data_files_size_in_mb": settings.data_file_size_mb,
                "video_files_size_in_mb": settings.video_file_size_mb, "fps": fps,
                "splits": {"train": f"0:{len(sources)}"}, "data_path": DATA_PATH,
                "video_path": VIDEO_PATH if videos else None, "features": features}
        (meta / "info.json").write_text(json.dumps(info, indent=2) + "\n")
        (meta / "stats.json").write_text(json.dumps(_json_stats(stats), indent=2) + "\n")
        video_bytes = {CAMERAS[n]: sum(p.stat().st_size for p in v.paths) for n, v in videos.items()}
    return {"episodes": len(sources), "frames": total, "fps": fps, "video_bytes": video_bytes}


# ----------------------------------------------------------------------------------------------------------------
# Import


def _index_of(names: list[str] | None, wanted: tuple[str, ...]) -> int | None:
    for i, name in enumerate(names or []):
        if str(name).lower() in wanted:
            return i
    return None


def _load_info(src: Path) -> dict[str, Any]:
    path = Path(src) / "meta" / "info.json"
    if not path.is_file():
        raise LeRobotError(f"{path}: no such file; a LeRobot dataset folder holds meta/info.json.")
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise LeRobotError(f"{path}: not valid JSON ({exc}).") from None
    version = str(info.get("codebase_version", ""))
    if not version.startswith("v3."):
        raise LeRobotError(f"{path}: the dataset is LeRobot {version or 'without a version'}; only v3.x is read, so "
                           "convert it with LeRobot's v3.0 conversion script first.")
    return info


def import_lerobot(src: Path, dst: Path, camera: str | None = None, progress: bool = False,
                   stop: Callable[[], None] | None = None) -> list[Path]:
    """Write each episode of a LeRobot v3 dataset as a towndrive episode into ``dst`` (new or empty); returns the
    new paths. The dataset needs a camera stored as video and an ``action`` whose names include the steering
    (``steer`` or ``steering``, in [-1, 1]) and the throttle (``throttle_brake``, or ``throttle`` with an optional
    ``brake``); ``observation.state`` names ``speed_mps`` and ``command`` are used when present."""
    from tqdm import tqdm

    _, pq = _pyarrow()
    src = Path(src)
    check_destination(dst)
    info = _load_info(src)
    features: dict[str, dict[str, Any]] = info.get("features", {})
    videos = [k for k, f in features.items() if f.get("dtype") == "video"]
    key = camera or (FRONT if FRONT in videos else (videos[0] if len(videos) == 1 else None))
    if key is None or key not in videos:
        found = ", ".join(videos) or "none"
        raise LeRobotError(f"{src}: the dataset has no camera {camera or FRONT} stored as video (video features: "
                           f"{found}); name one with --camera.")
    action = features.get("action")
    names = action.get("names") if action else None
    if isinstance(names, dict):  # some datasets name the axes {"motors": [...]}
        names = next(iter(names.values()), None)
    steer_at = _index_of(names, ("steer", "steering"))
    tb_at = _index_of(names, ("throttle_brake",))
    throttle_at = _index_of(names, ("throttle",))
    brake_at = _index_of(names, ("brake",))
    if action is None or steer_at is None or (tb_at is None and throttle_at is None):
        raise LeRobotError(f"{src}: the dataset's action {'names ' + str(names) if action else 'is missing and'} "
                           "does not name the steering (steer) and the throttle (throttle_brake or throttle), "
                           "which PilotNet trains on.")
    state = features.get("observation.state")
    state_names = state.get("names") if state else None
    speed_at = _index_of(state_names if isinstance(state_names, list) else None, ("speed_mps", "speed"))
    command_at = _index_of(state_names if isinstance(state_names, list) else None, ("command",))
    fps = int(info["fps"])
    episodes = _read_table(pq, sorted((src / "meta" / "episodes").glob("chunk-*/file-*.parquet")), src / "meta/episodes")
    data_template = info.get("data_path", DATA_PATH)
    video_template = info.get("video_path", VIDEO_PATH)
    total = int(sum(episodes["length"]))
    bar = tqdm(total=total, desc="import-lerobot", unit="frame", disable=not progress)
    written: list[Path] = []
    shape = features[key].get("shape", [0, 0, 3])
    cache: dict[Path, Any] = {}
    try:
        with staged(dst) as root:
            for row in range(len(episodes["episode_index"])):
                ep = {name: values[row] for name, values in episodes.items()}
                length = int(ep["length"])
                data_path = src / data_template.format(chunk_index=int(ep["data/chunk_index"]),
                                                       file_index=int(ep["data/file_index"]))
                if data_path not in cache:
                    cache.clear()
                    cache[data_path] = _read_table(pq, [data_path], data_path)
                rows = cache[data_path]
                mask = np.asarray(rows["episode_index"]) == int(ep["episode_index"])
                if int(mask.sum()) != length:
                    raise LeRobotError(f"{data_path}: episode {ep['episode_index']} has {int(mask.sum())} rows, "
                                       f"meta/episodes says {length}; the dataset is inconsistent.")
                actions = np.asarray(rows["action"], np.float32)[mask].reshape(length, -1)
                steer = actions[:, steer_at]
                if tb_at is not None:
                    tb = actions[:, tb_at]
                else:
                    tb = actions[:, throttle_at] - (actions[:, brake_at] if brake_at is not None else 0.0)
                if not (np.all(np.isfinite(steer)) and np.all(np.abs(steer) <= 1.0) and np.all(np.abs(tb) <= 1.0)):
                    raise LeRobotError(f"{data_path}: episode {ep['episode_index']} has steering or throttle outside "
                                       "[-1, 1]; scale them to [-1, 1] first.")
                n_state = (np.asarray(rows["observation.state"], np.float32)[mask].reshape(length, -1)
                           if "observation.state" in rows else None)
                speed = n_state[:, speed_at] if n_state is not None and speed_at is not None else np.full(length, np.nan)
                command = (n_state[:, command_at].round().astype(np.int8) if n_state is not None and command_at is not None
                           else np.zeros(length, np.int8))
                if np.any(~np.isin(command, list(COMMAND_NAMES))):
                    raise LeRobotError(f"{data_path}: episode {ep['episode_index']} has commands outside "
                                       f"{sorted(COMMAND_NAMES)}.")
                truth = {name: (np.asarray(rows[f"truth.{name}"], np.float32)[mask] if f"truth.{name}" in rows
                                else np.full(length, np.nan, np.float32)) for name in TRUTH_FIELDS}
                if "truth.time_s" not in rows:
                    truth["time_s"] = (np.arange(length) / fps).astype(np.float32)
                video_path = src / video_template.format(video_key=key, chunk_index=int(ep[f"videos/{key}/chunk_index"]),
                                                         file_index=int(ep[f"videos/{key}/file_index"]))
                start = round(float(ep[f"videos/{key}/from_timestamp"]) * fps)
                try:
                    frames = read_frames(video_path, start, length)
                except (VideoError, FileNotFoundError) as exc:
                    raise LeRobotError(f"{video_path}: cannot read episode {ep['episode_index']} ({exc}).") from None
                attrs = {"driver": str(ep.get("towndrive/driver", "lerobot_import")), "source": str(src.absolute()),
                         "seed": int(ep.get("towndrive/seed", -1)), "town_seed": int(ep.get("towndrive/town_seed", -1)),
                         "weather": str(ep.get("towndrive/weather", "unknown")), "dt_s": 1.0 / fps,
                         "camera": {"width": int(frames.shape[2]), "height": int(frames.shape[1])},
                         "task": str(list(ep.get("tasks") or [""])[0]), "lerobot_episode_index": int(ep["episode_index"]),
                         "lerobot_camera": key}
                if list(frames.shape[1:]) != list(shape):
                    raise LeRobotError(f"{video_path}: frames are {frames.shape[1:]}, info.json says {shape}.")
                writer = EpisodeWriter(root / f"episode_{row:05d}.h5", attrs)
                try:
                    for t in range(length):
                        writer.append({"image": frames[t], "speed": speed[t:t + 1], "command": command[t]},
                                      np.array([steer[t], tb[t]], np.float32),
                                      truth={name: float(values[t]) for name, values in truth.items()})
                        bar.update(1)
                        if stop is not None:
                            stop()
                    writer.close({"steps_done": length})
                except BaseException:
                    writer.discard()
                    raise
                written.append(Path(dst) / f"episode_{row:05d}.h5")
    finally:
        bar.close()
    return written


def _read_table(pq: Any, paths: list[Path], where: Path) -> dict[str, list[Any]]:
    """Parquet files as columns of Python values (one dict of lists)."""
    if not paths:
        raise LeRobotError(f"{where}: no parquet files; the dataset is incomplete.")
    columns: dict[str, list[Any]] = {}
    for path in paths:
        try:
            table = pq.read_table(str(path))
        except (OSError, ValueError) as exc:
            raise LeRobotError(f"{path}: cannot read this parquet file ({exc}); the dataset is corrupt.") from None
        for name in table.column_names:
            columns.setdefault(name, []).extend(table.column(name).to_pylist())
    return columns
