"""Episodes on worker processes (envs/parallel.py): the serial run's report and files, retries and failures.

Short blind autopilot episodes keep these fast; each parallel run still spawns two processes (a few seconds).
The drivers below are built by module-level factories, so the spawned workers can import them from this file.
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from towndrive.agent.autopilot import Autopilot
from towndrive.agent.drivers import make_driver
from towndrive.envs.drive_env import DriveConfig
from towndrive.envs.evaluation import evaluate
from towndrive.envs.parallel import DriverSpec, RunSummary, parse_workers

BLIND = DriveConfig(render_camera=False, max_time_s=6.0)


def options(k: int) -> dict[str, Any]:
    return {"town_seed": k % 2, "weather": ("noon", "dusk")[k % 2]}


class FaultyAutopilot:
    """The autopilot, except in episode ``bad``: there it kills its own process (once, the first time, leaving
    ``marker``) or raises (every time)."""

    name, privileged = "autopilot", True

    def __init__(self, bad: int, how: str, marker: str | None = None, **autopilot: Any) -> None:
        self.inner, self.bad, self.how, self.marker = Autopilot(**autopilot), bad, how, marker
        self.index, self.steps = -1, 0

    def set_episode_index(self, index: int) -> None:
        self.index = index
        self.inner.set_episode_index(index)

    def reset(self, env: Any) -> None:
        self.inner.reset(env)
        self.steps = 0

    @property
    def clean_action(self) -> Any:  # a recording's label: the autopilot's action without its steering noise
        return self.inner.clean_action

    def act(self, observation: dict[str, Any]) -> np.ndarray:
        self.steps += 1
        if self.index == self.bad and self.steps == 20:
            if self.how == "raise":
                raise RuntimeError(f"the test driver crashes in episode {self.bad}")
            if self.marker is not None and not os.path.exists(self.marker):
                Path(self.marker).touch()
                os.kill(os.getpid(), signal.SIGKILL)  # mid-episode, no clean-up: as the OOM killer does
        return self.inner.act(observation)


def faulty_driver(name: str, **kwargs: Any) -> FaultyAutopilot:
    return FaultyAutopilot(**kwargs)


def run(out: Path, driver: Any, workers: int, episodes: int = 3) -> dict:
    return evaluate(driver, BLIND, episodes, 500, out, video=False, options=options, plots=False, workers=workers)


@pytest.fixture(scope="module")
def serial(tmp_path_factory: pytest.TempPathFactory) -> dict:
    return run(tmp_path_factory.mktemp("serial"), make_driver("autopilot"), 1)


def test_workers_flag():
    assert parse_workers("3") == 3 and parse_workers("auto") == len(os.sched_getaffinity(0))
    for bad in ("0", "-1", "many"):
        with pytest.raises(ValueError, match="--workers"):
            parse_workers(bad)


def test_two_workers_give_the_serial_report(serial, tmp_path):
    parallel = run(tmp_path, DriverSpec.of(make_driver, "autopilot"), 2)
    assert json.dumps(parallel, sort_keys=True) == json.dumps(serial, sort_keys=True)
    assert [e["seed"] for e in parallel["episodes"]] == [500, 501, 502]
    assert (tmp_path / "table.md").read_text().startswith("# Closed-loop evaluation: autopilot")


def test_a_killed_worker_s_episode_is_retried_and_the_report_is_complete(serial, tmp_path):
    marker = tmp_path / "killed_once"
    summary = RunSummary()
    spec = DriverSpec.of(faulty_driver, "autopilot", bad=1, how="kill", marker=str(marker))
    parallel = evaluate(spec, BLIND, 3, 500, tmp_path / "out", video=False, options=options, plots=False, workers=2,
                        summary=summary)
    assert marker.exists() and summary.retried == 1 and not summary.failed
    assert json.dumps(parallel, sort_keys=True) == json.dumps(serial, sort_keys=True)


def test_an_episode_that_always_crashes_is_reported_failed_and_counted_as_zero(serial, tmp_path):
    summary = RunSummary()
    spec = DriverSpec.of(faulty_driver, "autopilot", bad=1, how="raise")
    metrics = evaluate(spec, BLIND, 3, 500, tmp_path, video=False, options=options, plots=False, workers=2,
                       summary=summary)
    failed = metrics["episodes"][1]
    assert "RuntimeError: the test driver crashes in episode 1" in failed["failed"]
    assert failed["driving_score"] == 0.0 and failed["route_completion"] == 0.0 and failed["seed"] == 501
    assert summary.retried == 1 and list(summary.failed) == [1]
    assert [metrics["episodes"][k] for k in (0, 2)] == [serial["episodes"][k] for k in (0, 2)]
    assert metrics["mean"]["failed"] == 1 and metrics["mean"]["episodes"] == 3
    assert "FAILED (counted as 0): RuntimeError" in (tmp_path / "table.md").read_text()


RECORD_FLAGS = ["--driver", "autopilot", "--episodes", "3", "--seconds", "5", "--width", "64", "--height", "48",
                "--noise", "--seed", "7", "--towns", "2"]
EPISODE_NAMES = ["episode_00000.h5", "episode_00001.h5", "episode_00002.h5"]


@pytest.fixture(scope="module")
def serial_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from towndrive.drive_cli import main

    folder = tmp_path_factory.mktemp("serial_recording")
    assert main(["--record", str(folder), *RECORD_FLAGS]) == 0
    assert sorted(p.name for p in folder.iterdir()) == EPISODE_NAMES
    return folder


def same_episodes(a_folder: Path, b_folder: Path) -> None:
    """Every dataset and every attribute of each episode file alike (the files' own timestamps aside)."""
    assert sorted(p.name for p in b_folder.iterdir()) == EPISODE_NAMES
    for name in EPISODE_NAMES:
        with h5py.File(a_folder / name) as a, h5py.File(b_folder / name) as b:
            keys: list[str] = []
            a.visit(lambda k, into=keys: into.append(k))
            assert keys and keys == [k for k in keys if k in b], name
            for key in keys:
                if isinstance(a[key], h5py.Dataset):
                    assert np.array_equal(a[key][()], b[key][()]), (name, key)
            assert {k: str(v) for k, v in a.attrs.items()} == {k: str(v) for k, v in b.attrs.items()}, name


def test_two_workers_record_the_serial_run_s_episode_files(serial_recording, tmp_path):
    from towndrive.drive_cli import main

    assert main(["--record", str(tmp_path / "parallel"), *RECORD_FLAGS, "--workers", "2"]) == 0
    same_episodes(serial_recording, tmp_path / "parallel")


def test_ray_recordings_come_home_through_the_object_store(serial_recording, ray_cluster, tmp_path, monkeypatch):
    """Under Ray each worker records into a scratch folder of its node (here: the cluster's TMPDIR, not the
    recording folder, as on a remote machine); the finished files are pulled home and the scratch copies deleted."""
    from towndrive.drive_cli import main
    from towndrive.envs import parallel

    shipped: list[tuple[str, str, int]] = []
    bring_home = parallel._bring_home

    def watched(ray: Any, actor: Any, shipment: Any, summary: RunSummary) -> None:
        shipped.extend(shipment.files)
        bring_home(ray, actor, shipment, summary)

    monkeypatch.setattr(parallel, "_bring_home", watched)
    monkeypatch.setattr(parallel, "CHUNK_BYTES", 64 * 1024)  # several chunks per file
    out = tmp_path / "ray"
    assert main(["--record", str(out), *RECORD_FLAGS, "--workers", "2", "--ray"]) == 0
    same_episodes(serial_recording, out)
    assert sorted(Path(home).name for _, home, _ in shipped) == EPISODE_NAMES
    for remote, home, size in shipped:
        assert Path(remote).is_relative_to(ray_cluster) and Path(home).parent == out  # a folder of the worker's
        assert not Path(remote).exists() and Path(home).stat().st_size == size > 64 * 1024  # ... deleted after
    assert not list(ray_cluster.glob("towndrive-ship-*")) and not list(out.glob("*.partial"))


def test_ray_recordings_through_a_shared_folder_are_moved_home(serial_recording, ray_cluster, tmp_path, capsys):
    from towndrive.drive_cli import main

    shared, out = tmp_path / "shared", tmp_path / "ray"
    assert main(["--record", str(out), *RECORD_FLAGS, "--workers", "2", "--ray", "--shared-dir", str(shared)]) == 0
    same_episodes(serial_recording, out)
    assert list(shared.iterdir()) == [] and not list(ray_cluster.glob("towndrive-ship-*"))
    # --shared-dir without --ray: one sentence, before anything runs
    assert main(["--record", str(tmp_path / "no"), *RECORD_FLAGS, "--shared-dir", str(shared)]) == 2
    assert "--shared-dir" in capsys.readouterr().err and not (tmp_path / "no").exists()


@pytest.fixture(scope="module")
def ray_cluster(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """One local 2-CPU Ray cluster for the Ray tests (skipped without towndrive[cluster]); its workers' temporary
    folder is ``node_tmp``, so that a test can see what a worker left behind on its node."""
    ray = pytest.importorskip("ray", reason="--ray needs towndrive[cluster]")
    import sys

    from ray import cloudpickle

    from towndrive.envs.parallel import THREAD_VARIABLES

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Ray's workers need not find this test file
    node_tmp = tmp_path_factory.mktemp("ray_node_tmp")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, object_store_memory=300 * 2**20,
             runtime_env={"env_vars": {**{k: "1" for k in THREAD_VARIABLES}, "TMPDIR": str(node_tmp)}})
    yield node_tmp
    ray.shutdown()


def test_ray_gives_the_serial_report_and_retries_a_killed_worker(serial, ray_cluster, tmp_path):
    """The same items as Ray tasks on a local 2-CPU cluster."""
    marker = tmp_path / "killed_once"
    summary = RunSummary()
    spec = DriverSpec.of(faulty_driver, "autopilot", bad=2, how="kill", marker=str(marker))
    metrics = evaluate(spec, BLIND, 3, 500, tmp_path / "out", video=False, options=options, plots=False, workers=2,
                       summary=summary, ray="local")
    assert marker.exists() and summary.retried == 1 and not summary.failed
    assert json.dumps(metrics, sort_keys=True) == json.dumps(serial, sort_keys=True)


@pytest.mark.parametrize("backend", ["workers", "ray, shared folder"])
def test_a_recording_worker_killed_mid_episode_leaves_nothing_in_the_retry_s_way(serial_recording, backend, tmp_path,
                                                                                request):
    """A worker SIGKILLed while it writes episode 1 cannot clean up its ``.partial``; the retry still records it."""
    from towndrive.drive_cli import RecordEpisode, check_args, episode_options, make_config, parse_args
    from towndrive.envs.parallel import run_items

    ray, shared = None, None
    if backend.startswith("ray"):
        request.getfixturevalue("ray_cluster")
        ray, shared = "local", tmp_path / "shared"
    out = tmp_path / "out"
    args = parse_args(["--record", str(out), *RECORD_FLAGS])
    check_args(args)
    config = make_config(args)
    items = [RecordEpisode(k, args.seed + k, episode_options(args, k), config, out / EPISODE_NAMES[k], True)
             for k in range(3)]
    marker = tmp_path / "killed_once"
    spec = DriverSpec.of(faulty_driver, "autopilot", bad=1, how="kill", marker=str(marker), noise=True,
                         noise_seed=args.seed)
    summary = RunSummary()
    results = run_items(items, spec, 2, summary=summary, ray=ray, progress=False, shared_dir=shared)
    assert marker.exists() and summary.retried == 1 and not summary.failed
    assert [r["path"] for r in results] == [str(out / name) for name in EPISODE_NAMES]
    same_episodes(serial_recording, out)
    if shared is not None:
        assert list(shared.iterdir()) == []
