"""The full agent's overlay, as in the seeds' figures: the lane area (green, or red when an object is in it),
tracked boxes with ids and distances, the light state, the steering (PilotNet's and the one applied), the
controller's reason, the ADAS warnings and the blind-spot indicators.

Drawing is split from the driver so that videos, sheets and the README picture all draw the same thing
from an ``AgentView`` (the driver keeps the last one).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from towndrive.agent.overlays import draw_detections
from towndrive.agent.perception.classes import CLASSES
from towndrive.agent.perception.detector import Detection
from towndrive.agent.perception.lanes import BirdsEye
from towndrive.sim.spec import COMMAND_NAMES

if TYPE_CHECKING:
    from towndrive.agent.agent_driver import AgentView

LANE_FREE = (60, 220, 90)
LANE_BLOCKED = (235, 40, 40)
LIGHT_RGB = {"red": (255, 40, 40), "yellow": (255, 210, 0), "green": (40, 230, 90)}
BLIND_SPOT_RGB = (255, 170, 0)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def lane_polygon(view: AgentView, birdseye: BirdsEye) -> np.ndarray | None:
    """Image polygon (N x 2) of the lane area the controller uses: a junction arc's path where one steers, else the
    lane found, or the steering arc."""
    from towndrive.agent.decision.controller import ControllerConfig

    lanes = view.lanes
    cfg = birdseye.config
    far = cfg.z_max_m
    if lanes is not None and lanes.left is not None and lanes.right is not None:
        far = min(far, max(lanes.left.z_range_m[1], lanes.right.z_range_m[1], 12.0))
    zz = np.linspace(cfg.z_min_m, far, 24)
    if view.steered_path is not None:  # a junction's arc steers: its path (as the controller takes it)
        x, z = view.steered_path[:, 0], view.steered_path[:, 1]
        zz = np.linspace(max(cfg.z_min_m, float(z[0])), max(cfg.z_min_m + 1.0, min(cfg.z_max_m, float(z[-1]))), 24)
        centre = np.interp(zz, z, x)
        half = ControllerConfig().path_half_width_m
    elif view.lane_centre is not None:
        centre = np.polyval(view.lane_centre, zz)
        half = view.lane_width_m / 2
    else:  # no lane: the corridor the current steering drives (as the controller assumes)
        ctrl = view.decision
        c = ControllerConfig()
        curvature = np.tan(ctrl.steer * c.max_steer_rad) / c.wheelbase_m
        centre = 0.5 * curvature * zz ** 2
        half = c.path_half_width_m
    left = birdseye.image_of_ground(centre - half, zz)
    right = birdseye.image_of_ground(centre + half, zz)
    return np.concatenate([left, right[::-1]])


def _text(img: np.ndarray, text: str, org: tuple[int, int], color: tuple[int, int, int], size: float = 0.45) -> None:
    """Text on a half-dark band (an outline drawn with a thicker pen drifts from the glyphs on long lines)."""
    (tw, th), base = cv2.getTextSize(text, FONT, size, 1)
    x, y = org
    x0, y0, x1, y1 = max(0, x - 3), max(0, y - th - 3), min(img.shape[1], x + tw + 3), min(img.shape[0], y + base + 1)
    if x1 > x0 and y1 > y0:
        img[y0:y1, x0:x1] = (img[y0:y1, x0:x1] * 0.45).astype(np.uint8)
    cv2.putText(img, text, org, FONT, size, color, 1, cv2.LINE_AA)


def draw_agent(view: AgentView, birdseye: BirdsEye, scale: int = 2) -> np.ndarray:
    """The camera frame with the agent's overlay, upscaled by ``scale`` (RGB, a new array)."""
    frame = view.image.copy()
    decision = view.decision
    blocked = bool(decision.in_path)
    poly = lane_polygon(view, birdseye)
    if poly is not None and np.isfinite(poly).all():
        layer = frame.copy()
        cv2.fillPoly(layer, [np.round(poly).astype(np.int32)], LANE_BLOCKED if blocked else LANE_FREE)
        frame = cv2.addWeighted(layer, 0.35, frame, 0.65, 0)
    dets, ids, dists = [], [], []
    for o in view.objects:
        dets.append(Detection(o.box, CLASSES.index(o.kind), 1.0))
        ids.append(o.track_id)
        dists.append(o.distance_m)
    if view.light is not None:
        dets.append(Detection(view.light.box, CLASSES.index(f"light_{view.light.state}"), view.light.score))
        ids.append(None)
        dists.append(view.light.distance_m)
    out = draw_detections(frame, dets, scale, ids, dists, show_scores=False)
    for o in view.objects:  # objects in our path: a thick red frame
        if o.track_id in decision.in_path:
            x0, y0, x1, y1 = (int(round(v * scale)) for v in o.box)
            cv2.rectangle(out, (x0 - 1, y0 - 1), (x1 + 1, y1 + 1), LANE_BLOCKED, 2)
    h, w = out.shape[:2]
    # Speed, target and the reason.
    _text(out, f"{view.speed_mps * 3.6:4.1f} km/h  target {decision.target_speed_mps * 3.6:4.1f}  "
               f"accel {decision.accel_mps2:+.1f}  {COMMAND_NAMES.get(view.command, view.command)}", (8, 18), (255, 255, 255))
    override = decision.reason != "cruise" and not decision.reason.startswith("cruise")
    _text(out, decision.reason, (8, 38), (255, 220, 60) if override else (220, 220, 220))
    if decision.stop_line_gap_m is not None:
        _text(out, f"stop line {decision.stop_line_gap_m:4.1f} m", (8, 58), (255, 255, 255))
    if decision.holding:
        _text(out, "HOLD", (8, 78), (255, 220, 60))
    # Light state, top right.
    state = decision.light
    cx, cy = w - 22, 22
    cv2.circle(out, (cx, cy), 14, (30, 30, 30), -1, cv2.LINE_AA)
    if state is not None:
        cv2.circle(out, (cx, cy), 11, LIGHT_RGB[state], -1, cv2.LINE_AA)
    if state is not None:
        label = f"our light: {state}"
    elif view.light is not None:  # seen this frame, not yet confirmed (or ignored inside the junction)
        label = f"our light: {view.light.state}?"
    else:
        label = "no light for our lane"
    _text(out, label, (w - 44 - int(6.2 * len(label)), 27), (255, 255, 255), 0.4)
    # Steering: PilotNet's proposal (thin white) and the applied command (thick yellow).
    bar_y, bar_half = h - 14, w // 4
    cv2.line(out, (w // 2 - bar_half, bar_y), (w // 2 + bar_half, bar_y), (200, 200, 200), 1, cv2.LINE_AA)
    cv2.line(out, (w // 2, bar_y - 6), (w // 2, bar_y + 6), (200, 200, 200), 1)
    px = int(w // 2 + decision.pilot_steer * bar_half)
    cv2.line(out, (px, bar_y - 8), (px, bar_y + 8), (255, 255, 255), 1, cv2.LINE_AA)
    sx = int(w // 2 + decision.steer * bar_half)
    cv2.line(out, (sx, bar_y - 8), (sx, bar_y + 8), (255, 220, 60), 3, cv2.LINE_AA)
    _text(out, f"steer {decision.steer:+.2f}", (w // 2 + bar_half + 8, bar_y + 5), (255, 220, 60), 0.4)
    # Blind-spot indicators (as in a door mirror): an amber arrow at the picture's edge on a side whose mirror
    # camera saw a vehicle beside or behind lately.
    for lit, sign, x in ((view.blind_spot[0], -1, 10), (view.blind_spot[1], 1, w - 10)):
        if lit:
            tip = np.array([[x, h // 2], [x - sign * 14, h // 2 - 12], [x - sign * 14, h // 2 + 12]], np.int32)
            cv2.fillPoly(out, [tip], BLIND_SPOT_RGB, cv2.LINE_AA)
    # Warnings: red banners above the steering bar.
    for k, text in enumerate(view.warnings):
        y = h - 36 - 22 * k
        (tw, th), _ = cv2.getTextSize(text, FONT, 0.5, 1)
        cv2.rectangle(out, (6, y - th - 6), (14 + tw, y + 5), (200, 20, 20), -1)
        cv2.putText(out, text, (10, y), FONT, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out
