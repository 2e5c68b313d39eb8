"""Zebra-crossing detection (agent/perception/zebra.py) measured against the town's crosswalks, per town style
and lighting preset.

    python bench/eval_zebra.py                              # classic/downtown/suburb x noon/dusk/night, ~2-3 min
    python bench/eval_zebra.py --styles suburb --weathers noon --towns 3 --frames 900

Why: the far edge of the near-side zebra anchors where the junction starts, and towns place it 0.9-5.5 m past
the stop bar; this says how well the camera finds it, and how often it reports one that is not there.

The privileged autopilot drives validation-split towns (``sim.splits``); on every frame the camera-only chain
runs (lanes -> stop line -> zebra, the stop line's distance gating the zebra). A frame is scored when the
camera has moved at least ``--spacing`` metres since the last scored frame (the autopilot waits at red
lights) and the stop (or give-way) line of the entry the car approaches is 3-20 m ahead
(``envs.perception_truth.zebra_truth``: the crosswalk of that entry where the car's forward ray crosses it).
Figures per style and weather:

- detection rate: frames with a detection among frames whose true zebra starts within 7 m past the line;
- far-edge error: median and 90th percentile of |detected - true| far edge (m) over those detections;
- false detections: a zebra reported where the truth has none within 7 m past the line (the ray misses the
  painted area, e.g. on a bend), and, separately, a zebra reported on a road whose junction line is more
  than 35 m ahead (``open road``), where nothing should be seen (frames inside junctions are not scored);
- the stop line in the same frames (it gates the zebra and places the junction): read within 0.5 m of the
  true line, read at the zebra's near edge instead (within ``ZEBRA_EDGE_M`` of it, and more than 0.5 m from
  the line), read elsewhere, or not read; by the kind of line (a stop bar, a give-way line of teeth).
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

from towndrive.agent.drivers import make_driver  # noqa: E402
from towndrive.agent.perception.lanes import LaneDetector  # noqa: E402
from towndrive.agent.perception.stop_line import StopLine, StopLineDetector  # noqa: E402
from towndrive.agent.perception.zebra import ZebraDetector  # noqa: E402
from towndrive.envs.drive_env import DriveConfig, DriveEnv  # noqa: E402
from towndrive.envs.perception_truth import ZebraTruth, zebra_truth  # noqa: E402
from towndrive.sim.splits import split_towns  # noqa: E402
from towndrive.sim.town import Control, TownConfig  # noqa: E402
from towndrive.sim.world import World, WorldConfig  # noqa: E402

STYLES = ("classic", "downtown", "suburb")
WEATHERS = ("noon", "dusk", "night")
BAR_WINDOW_M = (3.0, 20.0)  # scored frames: the car's own line this far ahead of the camera
AFTER_BAR_M = 7.0  # a true zebra starts at most this far past the line
OPEN_ROAD_M = 35.0  # on a road whose line is farther than this no zebra is in view (the view ends at 30 m)
LINE_OK_M = 0.5  # a stop line read this near the true one is right
ZEBRA_EDGE_M = 0.8  # ... read this near the zebra's near edge (and not right) is the zebra taken for the line


class ZebraTally:
    """Counts and far-edge errors of one style and weather."""

    def __init__(self) -> None:
        self.present = self.detected = self.absent = self.false = self.open_frames = self.open_false = 0
        self.errors: list[float] = []
        self.cost_s: list[float] = []

    def add(self, det, truth) -> None:
        if math.isfinite(truth.bar_m) and truth.bar_m > OPEN_ROAD_M:
            self.open_frames += 1
            self.open_false += det is not None
            return
        if not BAR_WINDOW_M[0] <= truth.bar_m <= BAR_WINDOW_M[1]:
            return
        if math.isfinite(truth.near_m) and truth.near_m - truth.bar_m <= AFTER_BAR_M:
            self.present += 1
            if det is not None:
                self.detected += 1
                self.errors.append(abs(det.far_m - truth.far_m))
        else:
            self.absent += 1
            self.false += det is not None

    def row(self) -> str:
        e = np.array(self.errors)
        med = f"{np.median(e):4.2f}" if len(e) else " nan"
        p90 = f"{np.percentile(e, 90):4.2f}" if len(e) else " nan"
        return (f"detected {self.detected:4d}/{self.present:<4d} ({self.detected / max(1, self.present):4.0%})  "
                f"far-edge |err| median {med} m p90 {p90} m  "
                f"false {self.false}/{self.absent} (no zebra past the line), {self.open_false}/{self.open_frames} (open road)")


class LineTally:
    """The stop line's readings of one style and weather, by the kind of line (module docstring)."""

    def __init__(self) -> None:
        self.counts: dict[str, dict[str, int]] = {}

    def add(self, stop: StopLine | None, truth: ZebraTruth, kind: str) -> None:
        if not BAR_WINDOW_M[0] <= truth.bar_m <= BAR_WINDOW_M[1]:
            return
        if stop is None:
            outcome = "none"
        elif abs(stop.distance_m - truth.bar_m) <= LINE_OK_M:
            outcome = "right"
        elif math.isfinite(truth.near_m) and abs(stop.distance_m - truth.near_m) <= ZEBRA_EDGE_M:
            outcome = "zebra"
        else:
            outcome = "other"
        tally = self.counts.setdefault(kind, {"right": 0, "zebra": 0, "other": 0, "none": 0})
        tally[outcome] += 1

    def row(self) -> str:
        return "  ".join(f"{kind}: right {c['right']}, zebra {c['zebra']}, other {c['other']}, none {c['none']}"
                         for kind, c in sorted(self.counts.items()))


def _line_kind(world: World) -> str:
    """What the town paints where the car's road enters its junction: a bar, a give-way line, or no line."""
    entry = world.town.entry_for_edge(world.ego_lane[0][:2]) if world.ego_lane is not None else None
    if entry is None or entry.control == Control.PRIORITY:
        return "no line"
    return "give-way" if entry.control == Control.YIELD else "bar"


def run(styles: list[str], weathers: list[str], towns: int, frames: int, spacing_m: float, seed: int) -> None:
    total = ZebraTally()
    costs: list[float] = []
    for style in styles:
        env = DriveEnv(DriveConfig(world=WorldConfig(town=TownConfig.of_style(style)), max_time_s=1e9,
                                   terminate_on_infraction=False, terminate_on_route_deviation=False))
        cam = env.config.camera
        lanes_d, stop_d, zebra_d = LaneDetector(cam), StopLineDetector(cam), ZebraDetector(cam)
        for weather in weathers:
            tally, lines = ZebraTally(), LineTally()
            t0 = time.perf_counter()
            for k, town_seed in enumerate(split_towns("validation", towns)):
                obs, _ = env.reset(seed=seed + k, options={"town_seed": town_seed, "weather": weather})
                driver = make_driver("autopilot")
                driver.reset(env)
                lanes_d.reset()
                stop_d.reset()
                last: np.ndarray | None = None
                for _ in range(frames):
                    obs, _, terminated, truncated, _ = env.step(driver.act(obs))
                    if terminated or truncated:
                        break
                    rgb = obs["image"]
                    lanes = lanes_d.detect(rgb)
                    stop = stop_d.detect(rgb, lanes)
                    c0 = time.perf_counter()
                    det = zebra_d.detect(rgb, lanes, stop.distance_m if stop is not None else None)
                    costs.append(time.perf_counter() - c0)
                    world = env.world
                    assert world is not None
                    here = world.ego.position
                    if last is not None and float(np.linalg.norm(here - last)) < spacing_m:
                        continue
                    last = here.copy()
                    truth = zebra_truth(world, cam)
                    tally.add(det, truth)
                    total.add(det, truth)
                    lines.add(stop, truth, _line_kind(world))
            print(f"{style:9s} {weather:6s} {tally.row()}  [{time.perf_counter() - t0:.0f} s]", flush=True)
            print(f"{'':16s} stop line: {lines.row()}", flush=True)
        env.close()
    print(f"{'all':16s} {total.row()}")
    c = np.array(costs) * 1e3
    print(f"zebra detector cost per 320x160 frame: median {np.median(c):.3f} ms, p90 {np.percentile(c, 90):.3f} ms "
          f"(n={len(c)}, one OpenCV thread)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--styles", default=",".join(STYLES))
    ap.add_argument("--weathers", default=",".join(WEATHERS))
    ap.add_argument("--towns", type=int, default=2, help="validation towns per style and weather (one drive each)")
    ap.add_argument("--frames", type=int, default=600, help="frames per drive")
    ap.add_argument("--spacing", type=float, default=0.5, help="metres the camera moves between scored frames")
    ap.add_argument("--seed", type=int, default=11)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    run(args.styles.split(","), args.weathers.split(","), args.towns, args.frames, args.spacing, args.seed)


if __name__ == "__main__":
    main()
