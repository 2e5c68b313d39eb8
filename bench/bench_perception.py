"""Latency of each classic perception stage at 320x160 (p50, p95), on recorded simulator frames.

    python bench/bench_perception.py
    python bench/bench_perception.py --threads 2    # let OpenCV use two threads

Frames: 60 camera frames and stereo pairs from an autopilot drive at noon (town 0), cycled. OpenCV runs on
one thread by default (the machine is shared; it is also the honest figure for one core of a small board).
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.timing import measure  # noqa: E402
from towndrive.agent.autopilot import Autopilot  # noqa: E402
from towndrive.agent.perception.lanes import LaneDetector, lane_masks  # noqa: E402
from towndrive.agent.perception.lanes_hough import HoughLaneDetector  # noqa: E402
from towndrive.agent.perception.stereo import StereoDepth  # noqa: E402
from towndrive.agent.perception.stop_line import StopLineDetector  # noqa: E402
from towndrive.agent.perception.tracking import Sort  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.envs.perception_truth import object_boxes  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=300)
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)
    env = DriveEnv(DriveConfig(observe_stereo=True, observe_segmentation=True))
    driver = Autopilot()
    obs, info = env.reset(seed=3, options={"traffic_density": 2.0})
    driver.reset(env)
    frames, pairs, boxes = [], [], []
    for k in range(240):
        obs, _, terminated, truncated, info = env.step(driver.act(obs))
        if terminated or truncated:
            break
        if k % 4 == 0:
            frames.append(obs["image"])
            pairs.append(obs["stereo"])
            boxes.append(object_boxes(info)[0])
    env.close()
    cam = env.config.camera
    print(f"{len(frames)} frames at {cam.width}x{cam.height}, OpenCV threads: {args.threads}, "
          f"mean {np.mean([len(b) for b in boxes]):.1f} objects per frame")

    lanes = LaneDetector(cam)
    hough = HoughLaneDetector(cam)
    stop = StopLineDetector(cam)
    stereo = StereoDepth(cam)
    it = itertools.cycle(range(len(frames)))

    def nxt() -> int:
        return next(it)

    def warp_and_masks() -> None:
        bev = lanes.birdseye.warp(frames[nxt()])
        lane_masks(bev, lanes.config.thresholds, lanes.config.birdseye.px_per_m_x)

    def lanes_windows() -> None:
        lanes.reset()  # no previous fit: the full sliding-window search every call
        lanes.detect(frames[nxt()])

    def lanes_tracking() -> None:
        lanes.detect(frames[nxt()])  # consecutive frames: search around the previous fit when it holds

    def stop_line() -> None:
        k = nxt()
        stop.detect(frames[k], lane_results[k])

    lane_results = []
    lanes.reset()
    for f in frames:
        lane_results.append(lanes.detect(f))
    sort = Sort()

    def tracker() -> None:
        sort.update(boxes[nxt()])

    def disparity() -> None:
        pair = pairs[nxt()]
        stereo.disparity(pair[0], pair[1])

    disparities = [stereo.disparity(p[0], p[1]) for p in pairs]

    def depth_and_objects() -> None:
        k = nxt()
        stereo.object_distances(stereo.depth(disparities[k]), boxes[k])

    def refined_objects() -> None:
        k = nxt()
        stereo.object_distances_refined(pairs[k][0], pairs[k][1], disparities[k], boxes[k])

    stages = [
        ("bird's-eye warp + thresholds", warp_and_masks),
        ("lanes, sliding windows (no previous fit)", lanes_windows),
        ("lanes, frame to frame (search around previous fit)", lanes_tracking),
        ("lanes, Canny + Hough", lambda: hough.detect(frames[nxt()])),
        ("stop line (given the lane result)", stop_line),
        ("SORT update", tracker),
        ("stereo SGBM 3-way disparity", disparity),
        ("stereo depth + object distances", depth_and_objects),
        ("stereo object distances, refined (all boxes)", refined_objects),
    ]
    for name, fn in stages:
        lat = measure(fn, repeats=args.repeats, warmup=10)
        print(f"{name:52s} {lat}")


if __name__ == "__main__":
    main()
