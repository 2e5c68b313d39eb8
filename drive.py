"""Run a driver in the simulator headless and keep what it saw.

Default: the privileged lane keeper drives one route in the default town (seed 0) and writes
``out/drive/video.mp4`` (camera beside a top-down map), a few camera frames as PNG and a
``summary.json``. Later issues add drivers, recording and evaluation here.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from sim.render import LIGHTING_PRESETS


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--driver", default="lane_keeper", choices=["lane_keeper"], help="who drives")
    p.add_argument("--seed", type=int, default=0, help="episode seed (traffic, start and route)")
    p.add_argument("--town-seed", type=int, default=0, help="which town to generate")
    p.add_argument("--weather", default="noon", choices=sorted(LIGHTING_PRESETS), help="lighting preset")
    p.add_argument("--seconds", type=float, default=60.0, help="longest episode, simulated seconds")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=160)
    p.add_argument("--out", type=Path, default=Path("out/drive"), help="output folder")
    p.add_argument("--frames", type=int, default=4, help="how many camera frames to save as PNG")
    p.add_argument("--no-video", action="store_true", help="skip the MP4")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import cv2
    import imageio.v2 as imageio
    from tqdm import tqdm

    from agent.lane_keeper import PrivilegedLaneKeeper
    from envs.drive_env import DriveConfig, DriveEnv
    from sim.render import CameraConfig

    config = DriveConfig(camera=CameraConfig(width=args.width, height=args.height), town_seed=args.town_seed,
                         weather=args.weather, max_time_s=args.seconds)
    env = DriveEnv(config, render_mode="rgb_array")
    driver = PrivilegedLaneKeeper()
    args.out.mkdir(parents=True, exist_ok=True)
    obs, info = env.reset(seed=args.seed)
    driver.reset()
    steps = int(args.seconds / config.world.dt_s)
    save_at = set(np.linspace(0, steps - 1, args.frames).astype(int).tolist()) if args.frames > 0 else set()
    writer = None if args.no_video else imageio.get_writer(args.out / "video.mp4", fps=env.metadata["render_fps"],
                                                            codec="libx264", quality=7, macro_block_size=8)
    t0 = time.perf_counter()
    total_reward = 0.0
    saved = []
    k = 0
    try:
        for k in tqdm(range(steps), desc="driving", unit="step"):
            assert env.world is not None
            obs, reward, terminated, truncated, info = env.step(driver.act(env.world))
            total_reward += reward
            if writer is not None:
                writer.append_data(env.render())
            if k in save_at:
                path = args.out / f"frame_{k:05d}.png"
                cv2.imwrite(str(path), cv2.cvtColor(obs["image"], cv2.COLOR_RGB2BGR))
                saved.append(path.name)
            if terminated or truncated:
                break
    finally:
        if writer is not None:
            writer.close()
        env.close()
    wall = time.perf_counter() - t0
    summary = {
        "driver": args.driver, "seed": args.seed, "town_seed": args.town_seed, "weather": args.weather,
        "steps": k + 1, "sim_time_s": info["time_s"], "wall_time_s": round(wall, 2),
        "steps_per_s": round((k + 1) / wall, 1), "reward": round(total_reward, 3),
        "route_completion": round(info["route"]["completion"], 4), "distance_m": round(info["distance_m"], 1),
        "infractions": info["infraction_counts"], "frames": saved,
        "video": None if args.no_video else "video.mp4",
    }
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
