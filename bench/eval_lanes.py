"""Lane and stop-line detection measured against the simulator's ground truth, per lighting preset.

    python bench/eval_lanes.py                       # 2 drives x 250 frames per preset, noon/dusk/overcast/night
    python bench/eval_lanes.py --frames 100 --episodes 1 --sheet docs/lanes_sheet.png

The autopilot drives with steering perturbations (so the car is not always centred); each frame is run
through the sliding-window detector, the Canny + Hough detector and the stop-line detector. Ground truth
(envs/perception_truth.py) is read only here, never by the detectors.

Figures:
- TuSimple accuracy (points within 5 px at 320 px wide = TuSimple's 20 px at 1280, divided by the cosine
  of the lane's angle), false-lane rate (FP / predicted lanes) and missed-lane rate (FN / true lanes),
  on frames where the ego is on a painted road (not inside a junction); image rows whose road is 3-30 m ahead;
- offset MAE against the painted-lane centre and against the lane model's centre (``World.lane_offset_m``),
  on frames with a detection, and how often there is one: for the middle of the painted lines
  (``LaneResult.offset_m``) and for the lane centre placed by the marking conventions
  (``LaneResult.centre_offset_m``: each line classified yellow / white and solid / dashed from the image);
- stop lines: detection rate of visible stop lines by distance, absolute distance error, false detections.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.agent.autopilot import Autopilot  # noqa: E402
from towndrive.agent.perception.lanes import BirdsEye, LaneDetector, LaneResult, draw_birdseye, draw_lanes  # noqa: E402
from towndrive.agent.perception.lanes_hough import HoughLaneDetector  # noqa: E402
from towndrive.agent.perception.stop_line import StopLine, StopLineDetector  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.envs.perception_truth import camera_pose, lane_truth, lane_z_range_rows, stop_line_truth, tusimple_frame  # noqa: E402
from towndrive.sim.scene_meshes import to_world  # noqa: E402

PRESETS = ("noon", "dusk", "overcast", "night")
STOP_BINS = ((3.0, 10.0), (10.0, 15.0), (15.0, 20.0))


def centre_truth_px(world, camera) -> np.ndarray:
    """Image points (N x 2) of the lane model's centre line 3-20 m ahead of the camera (for the pictures)."""
    if world.ego_lane is None:
        return np.zeros((0, 2))
    index, s0, _ = world.ego_lane
    lane = world.town.lane(index)
    s = np.arange(s0, min(lane.length, s0 + camera.mount_forward_m + 20.0), 0.5)
    p = np.array([lane.position(float(v), 0.0) for v in s]).reshape(-1, 2)
    uv, z = camera_pose(world, camera).project(to_world(p[:, 0], p[:, 1], 0.0))
    return uv[z >= 3.0]


def predicted_x(result: LaneResult, birdseye: BirdsEye, h_samples: np.ndarray) -> list[np.ndarray]:
    """Image x of each detected line at the evaluation rows (-2 outside the line's range), TuSimple style."""
    z = birdseye.ground_z_of_row(h_samples)
    out = []
    for line in (result.left, result.right):
        if line is None:
            continue
        zmax = min(birdseye.config.z_max_m, line.z_range_m[1] + 10.0)
        ok = np.isfinite(z) & (z >= birdseye.config.z_min_m - 1.0) & (z <= zmax)
        x = np.full(len(h_samples), -2.0)
        if ok.any():
            uv = birdseye.image_of_ground(line.x_at(z[ok]), z[ok])
            x[ok] = uv[:, 0]
        out.append(x)
    return out


class Tally:
    """Running sums of one detector's lane figures."""

    def __init__(self) -> None:
        self.acc: list[float] = []
        self.fp = self.fn = self.n_pred = self.n_gt = 0
        self.err_model: list[float] = []
        self.err_painted: list[float] = []
        self.err_in_lane: list[float] = []  # painted-centre error while the car is within 1 m of it (not changing lanes)
        self.centre_model: list[float] = []  # the same for centre_offset_m (lane centre by marking conventions)
        self.centre_painted: list[float] = []
        self.frames = self.with_offset = 0
        self.radius: list[tuple[float, float]] = []  # (true |R|, estimated |R|) on bends

    def add(self, result: LaneResult, pred: list[np.ndarray], gt, h_samples: np.ndarray, thresh_px: float) -> None:
        if not gt.on_road:
            return
        f = tusimple_frame(pred, gt.lanes_x, h_samples, thresh_px)
        if f.n_gt:
            self.acc.append(f.accuracy)
        self.fp += f.false_positives
        self.fn += f.false_negatives
        self.n_pred += f.n_pred
        self.n_gt += f.n_gt
        self.frames += 1
        if result.detected and math.isfinite(result.offset_m):
            self.with_offset += 1
            if math.isfinite(gt.radius_m):
                self.radius.append((gt.radius_m, abs(result.curvature_radius_m)))
            if math.isfinite(gt.offset_m):
                self.err_model.append(abs(result.offset_m - gt.offset_m))
            if math.isfinite(gt.painted_offset_m):
                self.err_painted.append(abs(result.offset_m - gt.painted_offset_m))
                if abs(gt.painted_offset_m) <= 1.0:
                    self.err_in_lane.append(abs(result.offset_m - gt.painted_offset_m))
            if math.isfinite(result.centre_offset_m):
                if math.isfinite(gt.offset_m):
                    self.centre_model.append(abs(result.centre_offset_m - gt.offset_m))
                if math.isfinite(gt.painted_offset_m):
                    self.centre_painted.append(abs(result.centre_offset_m - gt.painted_offset_m))

    def row(self) -> str:
        acc = np.mean(self.acc) if self.acc else float("nan")
        fpr = self.fp / max(1, self.n_pred)
        fnr = self.fn / max(1, self.n_gt)
        mp = np.mean(self.err_painted) if self.err_painted else float("nan")
        mm = np.mean(self.err_model) if self.err_model else float("nan")
        med = np.median(self.err_painted) if self.err_painted else float("nan")
        il = np.mean(self.err_in_lane) if self.err_in_lane else float("nan")
        centre = ""
        if self.centre_model:
            centre = (f" | lane centre by marking conventions: offset MAE vs lane model {np.mean(self.centre_model):5.3f} m "
                      f"(median {np.median(self.centre_model):5.3f}, p95 {np.percentile(self.centre_model, 95):5.3f}), "
                      f"vs painted centre {np.mean(self.centre_painted):5.3f} m")
        return (f"acc {acc:5.3f} FP {fpr:5.3f} FN {fnr:5.3f} | offset MAE vs painted centre {mp:5.3f} m (median {med:5.3f}, "
                f"in lane {il:5.3f}), vs lane model {mm:5.3f} m | offset given in {self.with_offset / max(1, self.frames):4.0%} "
                f"of {self.frames} road frames" + centre + self._radius())

    def _radius(self) -> str:
        if not self.radius:
            return ""
        r = np.array(self.radius)
        curved = np.isfinite(r[:, 1])
        if not curved.any():
            return f" | bends: no curvature estimated (n={len(r)})"
        rel = np.abs(r[curved, 1] - r[curved, 0]) / r[curved, 0]
        return (f" | bends (R {r[:, 0].min():.0f}-{r[:, 0].max():.0f} m): radius error median {np.median(rel):.0%} "
                f"(n={len(r)}, {1 - curved.mean():.0%} fitted straight)")


class StopTally:
    def __init__(self) -> None:
        self.bins = {b: [0, 0] for b in STOP_BINS}  # visible GT frames, detected within 2 m
        self.errors: list[tuple[float, float]] = []  # (gt distance, abs error)
        self.false = self.frames = 0

    def add(self, det: StopLine | None, truth) -> None:
        self.frames += 1
        gt = truth.distance_m
        near = math.isfinite(gt) and gt <= 30.0
        if det is not None and (not near or abs(det.distance_m - gt) > 2.0):
            self.false += 1
        if not (near and truth.visible):
            return
        for lo, hi in STOP_BINS:
            if lo <= gt < hi:
                self.bins[(lo, hi)][0] += 1
                if det is not None and abs(det.distance_m - gt) <= 2.0:
                    self.bins[(lo, hi)][1] += 1
                    self.errors.append((gt, abs(det.distance_m - gt)))

    def row(self) -> str:
        parts = []
        for (lo, hi), (n, k) in self.bins.items():
            errs = [e for g, e in self.errors if lo <= g < hi]
            mae = np.mean(errs) if errs else float("nan")
            parts.append(f"{lo:.0f}-{hi:.0f} m: {k}/{n} ({k / max(1, n):.0%}) MAE {mae:.2f} m")
        n_all = sum(n for n, _ in self.bins.values())
        k_all = sum(k for _, k in self.bins.values())
        mae_all = np.mean([e for _, e in self.errors]) if self.errors else float("nan")
        p95 = np.percentile([e for _, e in self.errors], 95) if self.errors else float("nan")
        return (f"detected {k_all}/{n_all} ({k_all / max(1, n_all):.0%}) within 20 m, error MAE {mae_all:.2f} m "
                f"p95 {p95:.2f} m; " + "; ".join(parts) + f"; false detections {self.false}/{self.frames} frames")


def run(frames: int, episodes: int, seed: int, sheet: Path | None) -> None:
    env = DriveEnv(DriveConfig(observe_depth=True, observe_segmentation=True, max_time_s=1e9,
                               terminate_on_infraction=False, terminate_on_route_deviation=False))
    cam = env.config.camera
    h_samples = lane_z_range_rows(cam, 3.0, 30.0)
    thresh_px = 20.0 * cam.width / 1280.0
    windows = LaneDetector(cam)
    hough = HoughLaneDetector(cam)
    stop = StopLineDetector(cam)
    tiles: list[np.ndarray] = []
    totals = {"windows": Tally(), "hough": Tally(), "stop": StopTally()}
    for preset in PRESETS:
        tally = {"windows": Tally(), "hough": Tally(), "stop": StopTally()}
        shots = 0
        t0 = time.perf_counter()
        for episode in range(episodes):
            driver = Autopilot(noise=True, noise_seed=seed + episode, noise_every_s=(1.0, 3.0), noise_steer=0.12,
                               noise_duration_s=0.5)
            obs, info = env.reset(seed=seed + episode, options={"weather": preset})
            driver.reset(env)
            windows.reset()
            hough.reset()
            stop.reset()
            for k in range(frames):
                obs, _, terminated, truncated, info = env.step(driver.act(obs))
                if terminated or truncated:
                    obs, info = env.reset(seed=seed + 100 + k, options={"weather": preset})
                    driver.reset(env)
                    windows.reset()
                    hough.reset()
                    stop.reset()
                rgb = obs["image"]
                res = windows.detect(rgb, keep_images=sheet is not None)
                res_h = hough.detect(rgb)
                sl = stop.detect(rgb, res)
                assert env.world is not None and env.renderer is not None
                gt = lane_truth(env.world, cam, env.renderer.ground_map, obs["depth"], h_samples)
                st = stop_line_truth(env.world, cam, obs["segmentation"])
                for name, r, det in (("windows", res, windows), ("hough", res_h, hough)):
                    pred = predicted_x(r, det.birdseye, h_samples)
                    tally[name].add(r, pred, gt, h_samples, thresh_px)
                    totals[name].add(r, pred, gt, h_samples, thresh_px)
                tally["stop"].add(sl, st)
                totals["stop"].add(sl, st)
                if sheet is not None and episode == 0 and shots < 2 and (k == frames // 3 or (shots == 1 and (
                        sl is not None or k == frames - 1))):
                    tiles.append(_tile(rgb, res, sl, gt, st, windows.birdseye, h_samples, preset,
                                       centre_truth_px(env.world, cam)))
                    shots += 1
        dt = time.perf_counter() - t0
        print(f"[{preset}] {episodes} x {frames} frames in {dt:.0f} s")
        print(f"  sliding windows : {tally['windows'].row()}")
        print(f"  canny + hough   : {tally['hough'].row()}")
        print(f"  stop line       : {tally['stop'].row()}")
    print("[all presets]")
    print(f"  sliding windows : {totals['windows'].row()}")
    print(f"  canny + hough   : {totals['hough'].row()}")
    print(f"  stop line       : {totals['stop'].row()}")
    env.close()
    if sheet is not None and tiles:
        rows = [np.concatenate(tiles[i:i + 2], axis=1) for i in range(0, len(tiles) - 1, 2)]
        sheet.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(sheet), cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
        print(f"contact sheet: {sheet}")


def _tile(rgb: np.ndarray, res: LaneResult, sl: StopLine | None, gt, st, be: BirdsEye, h_samples: np.ndarray,
          preset: str, centre_px: np.ndarray) -> np.ndarray:
    """Camera with lanes (green area, red/blue fits, magenta ground-truth points of the painted lines, dashed
    yellow: the lane centre by marking conventions, white dots: the lane model's centre, orange stop line)
    beside the bird's-eye mask (white / yellow paint) with sliding windows (green) and fits."""
    img = draw_lanes(rgb, res, be)
    for u, v in centre_px:
        cv2.circle(img, (int(round(u)), int(round(v))), 1, (255, 255, 255), -1)
    for x in gt.lanes_x:
        for xx, yy in zip(x, h_samples, strict=True):
            if xx >= 0:
                cv2.circle(img, (int(round(xx)), int(yy)), 1, (255, 0, 255), -1)
    if sl is not None:
        xs = np.array([-1.5, 1.5])
        uv = be.image_of_ground(xs, np.full(2, sl.distance_m))
        cv2.line(img, tuple(np.round(uv[0]).astype(int)), tuple(np.round(uv[1]).astype(int)), (255, 140, 0), 2)
    big = cv2.resize(img, (640, 320), interpolation=cv2.INTER_LINEAR)
    text = (f"{preset} painted {res.offset_m:+.2f} m (true {gt.painted_offset_m:+.2f}), lane {res.centre_offset_m:+.2f} m "
            f"(true {gt.offset_m:+.2f})") if res.detected else f"{preset} no lane"
    cv2.putText(big, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    kinds = [f"{name} {ln.style} {ln.color}" for name, ln in (("L", res.left), ("R", res.right)) if ln is not None]
    cv2.putText(big, ", ".join(kinds), (6, 312), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    if sl is not None or math.isfinite(st.distance_m):
        stxt = f"stop line {sl.distance_m:.1f} m" if sl is not None else "stop line: none"
        cv2.putText(big, stxt + f" (true {st.distance_m:.1f} m)", (6, 38), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1,
                    cv2.LINE_AA)
    # The bird's-eye panel shows a fresh search (histogram + sliding windows) on this frame; the running
    # detector usually searched around its previous fit instead (drawn as a band in draw_birdseye).
    fresh = LaneDetector(be.camera).detect(rgb, keep_images=True)
    bev = draw_birdseye(fresh, be)
    bev = cv2.resize(bev, (int(round(bev.shape[1] * 320 / bev.shape[0])), 320), interpolation=cv2.INTER_NEAREST)
    return np.concatenate([big, bev], axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=250, help="frames per drive")
    ap.add_argument("--episodes", type=int, default=2, help="drives per preset (seeds seed, seed + 1, ...)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--sheet", type=Path, default=None, help="write a contact sheet of detections here")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    run(args.frames, args.episodes, args.seed, args.sheet)


if __name__ == "__main__":
    main()
