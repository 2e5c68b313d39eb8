"""Stereo depth measured against the simulator's depth: D1-all and object distance error by range.

    python bench/eval_stereo.py                       # ZED-like 0.12 m baseline, 4 presets x 4 drives x 20 frames
    python bench/eval_stereo.py --baseline 0.3        # a wider automotive rig
    python bench/eval_stereo.py --picture docs/stereo_disparity.png

Ground truth: the left camera's metric z-depth (rendered again with the pair), disparity = f B / Z; sky
has no ground truth. D1 (KITTI 2015): a pixel is wrong if its disparity is off by more than 3 px and
more than 5 %. "D1-all" fills pixels without a match by KITTI's background interpolation first, so every
ground-truth pixel counts; "D1 valid" counts only matched pixels, and "density" is their share.
Object distances: cars, trucks and pedestrians with at least 60 pixels in the left frame, boxes from
the segmentation map; the truth is the median true depth over the object's own pixels. Two estimates:
"median", the median stereo depth over the box's centre (``StereoDepth.object_distance``, what the
agent's stereo mode uses), and "refined", the nearest disparity mode in the box refined by matching the
object's pixels (``object_distances_refined``). The refined estimate's settings were chosen on drives with
``--seed 61 --episodes 6``; the default seeds (21-24) are the held-out evaluation.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.autopilot import Autopilot  # noqa: E402
from towndrive.agent.perception.stereo import StereoConfig, StereoDepth, colorize, fill_invalid  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.envs.perception_truth import boxes_from_segmentation, d1_all, stereo_truth  # noqa: E402

PRESETS = ("noon", "dusk", "overcast", "night")
RANGES = ((0.0, 5.0), (5.0, 10.0), (10.0, 20.0), (20.0, 40.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=20, help="frames per drive (one every --every steps)")
    ap.add_argument("--episodes", type=int, default=4, help="drives per preset (seeds seed, seed + 1, ...)")
    ap.add_argument("--every", type=int, default=6)
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--baseline", type=float, default=None, help="stereo baseline in metres (default: the camera's)")
    ap.add_argument("--width", type=int, default=None, help="camera width in pixels (height = width / 2; default 320)")
    ap.add_argument("--presets", default=",".join(PRESETS), help="comma-separated lighting presets")
    ap.add_argument("--picture", type=Path, default=None)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    cam = DriveConfig().camera
    cam = replace(cam, stereo=True, stereo_baseline_m=args.baseline if args.baseline else cam.stereo_baseline_m)
    if args.width:
        cam = replace(cam, width=args.width, height=args.width // 2)
    presets = [p for p in args.presets.split(",") if p]
    env = DriveEnv(DriveConfig(camera=cam, observe_stereo=True, terminate_on_infraction=False,
                               terminate_on_route_deviation=False))
    stereo = StereoDepth(cam, StereoConfig(num_disparities=16 * max(3, round(48 * cam.width / 320 / 16))))
    print(f"rig: {cam.width}x{cam.height}, f = {cam.focal_px:.0f} px, baseline {cam.stereo_baseline_m:.2f} m "
          f"(1 px of disparity = {cam.focal_px * cam.stereo_baseline_m:.1f} m); SGBM 3-way, "
          f"{stereo.config.num_disparities} disparities, block {stereo.config.block_size}")
    all_err: list[tuple[float, float, float, tuple[int, int]]] = []
    all_d1: list[tuple[float, ...]] = []
    pictures = []
    for preset in presets:
        d1s: list[tuple[float, ...]] = []
        errs: list[tuple[float, float, float, tuple[int, int]]] = []
        t0 = time.perf_counter()
        for episode in range(args.episodes):
            driver = Autopilot()
            obs, _ = env.reset(seed=args.seed + episode, options={"weather": preset, "traffic_density": 3.0})
            driver.reset(env)
            for k in range(args.frames * args.every):
                obs, _, terminated, truncated, _ = env.step(driver.act(obs))
                if terminated or truncated:
                    obs, _ = env.reset(seed=args.seed + 100 + k, options={"weather": preset, "traffic_density": 3.0})
                    driver.reset(env)
                if k % args.every:
                    continue
                assert env.world is not None and env.renderer is not None
                truth = stereo_truth(env.renderer, env.world, cam, preset)
                if not np.array_equal(truth.left, obs["stereo"][0]):
                    raise RuntimeError("the re-rendered left image differs from the observation; ground truth would not match")
                disp = stereo.disparity(obs["stereo"][0], obs["stereo"][1])
                valid_gt = truth.disparity_px > 0
                matched = disp > 0
                both = valid_gt & matched
                err = np.abs(disp - truth.disparity_px)[both]
                d1s.append((d1_all(fill_invalid(disp), truth.disparity_px, valid_gt),
                            d1_all(disp, truth.disparity_px, both), float(both.sum()) / max(1, int(valid_gt.sum())),
                            float(err.mean()) if len(err) else np.nan, float((err > 1.0).mean()) if len(err) else np.nan))
                depth = stereo.depth(disp)
                boxes, ids, oid = boxes_from_segmentation(truth.segmentation, min_pixels=60)
                refined = stereo.object_distances_refined(obs["stereo"][0], obs["stereo"][1], disp, boxes)
                for box, i, z_ref in zip(boxes, ids, refined, strict=True):
                    true_m = float(np.median(truth.depth_m[oid == i]))
                    errs.append((true_m, stereo.object_distance(depth, box), float(z_ref), (episode, int(i))))
                if (args.picture is not None and episode == 0 and len(pictures) < len(presets)
                        and k == args.every * (args.frames // 2)):
                    pictures.append(_picture(obs["stereo"][0], disp, truth.disparity_px, boxes, refined, preset))
        d1 = np.array(d1s)
        print(f"[{preset}] {len(d1s)} frames in {time.perf_counter() - t0:.0f} s: D1-all {d1[:, 0].mean():.2%}, "
              f"D1 valid {d1[:, 1].mean():.2%}, density {d1[:, 2].mean():.1%}, end-point error {np.nanmean(d1[:, 3]):.2f} px, "
              f"off by > 1 px {np.nanmean(d1[:, 4]):.1%}")
        print("  objects, median:  " + _ranges(errs, 1))
        print("  objects, refined: " + _ranges(errs, 2))
        all_err += errs
        all_d1 += d1s
    d1 = np.array(all_d1)
    print(f"[all] D1-all {d1[:, 0].mean():.2%} (target < 5%), D1 valid {d1[:, 1].mean():.2%}, density {d1[:, 2].mean():.1%}, "
          f"end-point error {np.nanmean(d1[:, 3]):.2f} px, off by > 1 px {np.nanmean(d1[:, 4]):.1%}")
    print("  objects, median:  " + _ranges(all_err, 1))
    print("  objects, refined: " + _ranges(all_err, 2))
    print("  seed 000's ZED: about 0.1 m indoors (2.6-10 m), 0.5-1 m outdoors up to 20 m")
    env.close()
    if pictures:
        args.picture.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.picture), cv2.cvtColor(np.concatenate(pictures, axis=0), cv2.COLOR_RGB2BGR))
        print(f"picture: {args.picture}")


def _ranges(errs: list[tuple[float, float, float, tuple[int, int]]], which: int) -> str:
    """Per range: boxes, objects, the share measured, MAE, median error, of estimate ``which`` (1 median, 2 refined)."""
    parts = []
    for lo, hi in RANGES:
        sel = [(row[0], row[which], row[3]) for row in errs if lo <= row[0] < hi]
        if not sel:
            continue
        ok = [(t, e) for t, e, _ in sel if np.isfinite(e)]
        n_obj = len({o for _, _, o in sel})
        if not ok:
            parts.append(f"{lo:.0f}-{hi:.0f} m: {len(sel)} boxes, none measured")
            continue
        ae = np.abs([e - t for t, e in ok])
        rel = np.abs([(e - t) / t for t, e in ok])
        parts.append(f"{lo:.0f}-{hi:.0f} m: {len(sel)} boxes of {n_obj} objects, measured {len(ok) / len(sel):.0%}, "
                     f"MAE {ae.mean():.2f} m, median {np.median(ae):.2f} m ({np.median(rel):.1%})")
    return "; ".join(parts)


def _picture(left: np.ndarray, disp: np.ndarray, truth: np.ndarray, boxes: np.ndarray, distances: np.ndarray,
             preset: str) -> np.ndarray:
    """Left image with boxes and (refined) stereo distances | estimated disparity | true disparity."""
    top = float(np.percentile(truth[truth > 0], 99)) if (truth > 0).any() else 1.0
    img = left.copy()
    for b, d in zip(boxes, distances, strict=True):
        x0, y0, x1, y1 = (int(v) for v in b)
        cv2.rectangle(img, (x0, y0), (x1, y1), (255, 255, 0), 1)
        cv2.putText(img, f"{d:.1f}m", (x0, max(8, y0 - 2)), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (255, 255, 0), 1, cv2.LINE_AA)
    cv2.putText(img, preset, (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([img, colorize(disp, top), colorize(truth, top)], axis=1)


if __name__ == "__main__":
    main()
