"""Recording and evaluation throughput.

Recording: frames per second written to disk by ``EpisodeWriter`` alone (frames already rendered; the
disk and compression cost), and end to end (autopilot driving, rendering and writing), at 200x66 and
320x160. Evaluation: episodes per minute of ``drive.py --evaluate`` work (autopilot, seeded routes with
traffic; the video is off, as it is written for the first episode only), with and without the camera.

Run: ``python bench/bench_recording.py``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.autopilot import Autopilot  # noqa: E402
from towndrive.data.episodes import EpisodeWriter  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.envs.evaluation import run_episode  # noqa: E402
from towndrive.sim.render import CameraConfig  # noqa: E402


def record_frames(camera: CameraConfig, steps: int, folder: Path) -> tuple[float, float, float]:
    """(writer-only frames/s, end-to-end frames/s, MB per 1000 frames)."""
    env = DriveEnv(DriveConfig(camera=camera))
    driver = Autopilot()
    obs, info = env.reset(seed=1)
    driver.reset(env)
    samples = []
    t0 = time.perf_counter()
    writer = EpisodeWriter(folder / "episode_00000.h5", {"seed": 1})
    write_time = 0.0
    for _ in range(steps):
        action = driver.act(obs)
        tw = time.perf_counter()
        writer.append(obs, action, info)
        write_time += time.perf_counter() - tw
        samples.append((obs, action, info))
        obs, _, term, trunc, info = env.step(action)
        if term or trunc:
            obs, info = env.reset(seed=2)
            driver.reset(env)
    path = writer.close()
    end_to_end = steps / (time.perf_counter() - t0)
    env.close()
    size_mb = os.path.getsize(path) / 1e6
    return steps / write_time, end_to_end, 1000 * size_mb / steps


def episodes_per_minute(render: bool, episodes: int, seed: int) -> tuple[float, float]:
    config = replace(DriveConfig(render_camera=render, camera=CameraConfig(width=200, height=66)),
                     terminate_on_infraction=False, terminate_on_route_deviation=False)
    env = DriveEnv(config)
    t0 = time.perf_counter()
    sim_s = 0.0
    for k in range(episodes):
        sim_s += run_episode(env, Autopilot(), seed + k).elapsed_s
    wall = time.perf_counter() - t0
    env.close()
    return 60.0 * episodes / wall, sim_s / episodes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--episodes", type=int, default=3)
    args = ap.parse_args()
    print(f"Recording ({args.steps} steps each, gzip level 1 per frame):")
    print(f"{'camera':>10} {'writer frames/s':>16} {'end-to-end frames/s':>20} {'MB per 1000 frames':>19}")
    for w, h in ((200, 66), (320, 160)):
        with tempfile.TemporaryDirectory() as tmp:
            writer_fps, e2e_fps, mb = record_frames(CameraConfig(width=w, height=h), args.steps, Path(tmp))
        print(f"{f'{w}x{h}':>10} {writer_fps:16.0f} {e2e_fps:20.1f} {mb:19.1f}")
    print(f"\nEvaluation (autopilot, {args.episodes} seeded routes with traffic, no video):")
    for render in (True, False):
        epm, mean_s = episodes_per_minute(render, args.episodes, 100)
        label = "camera 200x66" if render else "no camera"
        print(f"{label:>14}: {epm:6.2f} episodes/min (mean episode {mean_s:.0f} s simulated)")
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    sys.exit(main())
