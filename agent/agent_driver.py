"""The ``agent`` driver: PilotNet steers; perception and the rule-based controller decide the speed.

It sees only what a real car has: the camera frame (and the stereo pair when ``distance="stereo"`` and the
environment renders it), its own speed and the route command. Each frame:

1. **PilotNet** proposes the steering (``agent.pilotnet_driver.PilotNetModel``). Going straight through a
   junction, where there are no lines and PilotNet drifts, the car instead holds the approach lane's heading
   and its place across it, both measured from the lane fit before the stop line and dead-reckoned since.
2. **Detector** (YOLO-style, ONNX Runtime, then the pedestrian refiner of agent/perception/ped_refiner.py) every
   ``detect_every`` frames; **SORT** tracks vehicles and
   pedestrians (Kalman predictions on the frames in between); traffic lights are taken from the latest
   detections: the nearest light box hanging within ``light_max_lateral_m`` of the lane the car came along
   (its heading change since it began to turn is dead-reckoned from its own speed and steering) is ours.
3. **Lanes** (sliding windows in the bird's-eye view) and the **stop line** (distance to the bar).
4. **Distance** to each tracked object from box geometry, or stereo: the ground-plane distance of the box's
   bottom row through the camera intrinsics and mounting (exact for things standing on the road, but one
   image row is ``z^2 / (f h)`` metres of road: 4 m at 30 m), fused with the distance a known height
   gives (``f H / h_px``; a few per cent at any range, but wrong for an unusual size), each weighted by
   its variance. Closing and lateral speeds come from a least-squares fit over the track's last second.
   A vehicle that stands wholly to one side of the camera axis and does not move sideways draws its inner
   box edge from its far side: that edge is read at least the vehicle's width beyond its near face (a car
   waiting in the oncoming lane is not in our path). An object lost from view while in our path is kept
   where it was for a while; a person lost close in (the detector misses people who fill the frame, and
   beside the car's front is outside the view) is kept longer and does not drift.
   What is easy to fake is marked unconfirmed, and the controller stands for it only for a bounded time:
   a remembered object, a track the detector missed this frame (SORT coasting), and a person seen only at
   the image's side edge. At night a lit facade, a pole or the kerb's line where it meets the side edge
   scores as half a person, and with the car standing in a turn it stays there frame after frame; a real
   person at the edge walked there through the picture, so a person at the side edge is confirmed only
   while the same track was seen whole (clear of the side edges) within ``edge_confirm_s``, and a person
   seen only at the side edge is not remembered when lost (that memory turned a three-frame false box at
   the left edge into a person standing beside a car turning left, and re-armed with each new false box).
5. **Controller** (``agent.decision.controller``) and **ADAS** warnings (``agent.decision.adas``).

Per-stage timings (ms) for every frame are kept in ``timings``; the last frame's whole state in ``view``
(for overlays, ``agent.agent_overlay``); the episode's ADAS events in ``adas``.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agent.decision.adas import Adas, AdasConfig
from agent.decision.blind_spot import BlindSpot, BlindSpotConfig, MirrorMount
from agent.decision.controller import Controller, ControllerConfig, Decision, PerceivedObject, Scene
from agent.drivers import register
from agent.perception.classes import CLASSES, LIGHT_CLASSES
from agent.perception.detector import Detection, OnnxDetector
from agent.perception.lanes import BirdsEye, LaneDetector, LaneResult
from agent.perception.stop_line import StopLine, StopLineDetector
from agent.perception.tracking import Sort, SortConfig, Track
from agent.pilotnet_driver import DEFAULT_MODEL, PilotNetModel
from agent.shipped import DETECTOR_ONNX, REFINER_ONNX
from envs.drive_env import BLIND_SPOT_CAMERA, BLIND_SPOT_MOUNT_M, BLIND_SPOT_YAW_DEG
from sim.ego import EgoVehicle
from sim.render import CameraConfig

if TYPE_CHECKING:
    from envs.drive_env import DriveEnv

DEFAULT_DETECTOR = DETECTOR_ONNX
DEFAULT_REFINER = REFINER_ONNX
# Size priors (metres): typical heights, which unlike widths do not change with the viewing angle.
HEIGHT_PRIOR_M = {"car": 1.5, "truck": 2.8, "pedestrian": 1.75}
# The least depth a vehicle shows, whatever its yaw: its width (depth = L|sin| + W|cos| >= W). A vehicle wholly
# to one side of the camera axis draws its inner box edge from its far side, not from its near face.
DEPTH_PRIOR_M = {"car": 1.9, "truck": 2.3}
LIGHT_HOUSING_M = 2.1  # a signal head's height (three lamps)
LIGHT_HEAD_HEIGHT_M = 5.2  # town design: signal heads hang 5.2 m above the road on mast arms
TRACKED = ("car", "truck", "pedestrian")
STAGES = ("blind_spot", "pilotnet", "detector", "tracking", "lanes", "stop_line", "distance", "control", "adas")


TURN_ARC_START_M = 0.5  # town design: a junction's connectors start at its stop bars' far edge (0.5 m deep)


@lru_cache(maxsize=16)
def turn_path(command: int, setback_m: float, lane_offset_m: float, step_m: float = 0.2) -> tuple[np.ndarray, float]:
    """A junction turn in the approach frame (x along the approach lane from its stop bar's near edge, y to the
    right): 30 m of approach, the town's quarter circle from the bar's far edge (0.5 m on) into the same lane of
    the road turned into, then 30 m of that road; and the path length at which the arc ends. The lane's centre
    is ``lane_offset_m`` right of the road's centre line, so a right turn's radius is ``setback - offset`` and a
    left turn's ``setback + offset`` (``sim/town.py``, junction connectors)."""
    right = command == 2
    radius = setback_m - lane_offset_m if right else setback_m + lane_offset_m
    side = 1.0 if right else -1.0
    x0 = TURN_ARC_START_M
    before = np.arange(x0 - 30.0, x0, step_m)
    approach = np.stack([before, np.zeros(len(before))], axis=1)
    theta = np.arange(0.0, math.pi / 2, step_m / radius)
    arc = np.stack([x0 + radius * np.sin(theta), side * (radius - radius * np.cos(theta))], axis=1)
    end = np.array([x0 + radius, side * radius])
    along = np.arange(0.0, 30.0, step_m)
    exit_ = np.stack([np.full(len(along), end[0]), end[1] + side * along], axis=1)
    path = np.concatenate([approach, arc, exit_])
    path.setflags(write=False)
    return path, (len(approach) + len(arc)) * step_m


@dataclass(frozen=True)
class AgentConfig:
    detect_every: int = 1  # run the detector on every k-th frame (SORT predicts in between)
    distance: str = "geometry"  # "geometry" (box and camera model) or "stereo" (needs DriveConfig.observe_stereo)
    stereo_max_m: float = 15.0  # beyond this the 0.12 m rig's disparity is under 1.3 px: use geometry
    score_threshold: float = 0.35
    light_score_threshold: float = 0.4
    light_max_lateral_m: float = 4.5  # our light hangs over the lane divider, within a lane of our axis
    light_line_tolerance_m: float = 5.0  # with the stop line measured, ours hangs 21 m beyond it, give or take this
    straight_steer: float = 0.08  # below this |steer| the car drives along its lane: the approach heading follows
    history_s: float = 1.0  # track history used for closing and lateral speeds
    lost_memory_s: float = 2.0  # an object lost while in our path and near is remembered this long
    lost_memory_m: float = 15.0  # ... when it was nearer than this (close in, the detector misses people)
    near_memory_s: float = 4.0  # a pedestrian lost this near, or at the image's edge, stays (not drifting) this
    near_memory_m: float = 7.0  # long: the detector misses people who fill the frame, and beside the car's
    #                             front, outside the 90-degree view, is where they go
    edge_confirm_s: float = 8.0  # a person at the image's side edge is confirmed this long after last seen whole
    whole_margin_px: float = 3.0  # a box this near the image's side edge may be cut: it does not show the whole
    still_lateral_mps: float = 0.3  # a vehicle moving sideways slower than this gets the depth prior
    # A whole person's box (cut neither at the top nor at the bottom) whose bottom row puts them at z is about
    # f x 1.75 m / z tall: height x z / (f x 1.75) fell in 0.83-1.12 for every true detection on the detector's
    # test split (1,545, within 40 m). Outside this range it is no person standing there (a kerb's edge line
    # at the image border was one, and held the car in a junction for 90 s). People in this world are all
    # 1.75 m tall; a world with children needs a lower bound.
    person_height_ratio: tuple[float, float] = (0.7, 1.4)
    junction_hold_m: float = 20.0  # going straight, this far past the stop line the car holds the approach
    #                                lane's heading and offset (no lines to steer by inside the junction)
    hold_heading_gain: float = 1.5  # steer per radian of heading error (about a 1 s time constant at 5 m/s)
    hold_offset_gain: float = 0.3  # steer per metre of dead-reckoned offset from the approach lane's centre
    hold_max_steer: float = 0.3
    turn_guidance: bool = True  # commanded turns inside a junction follow the town's turn arc (below)
    junction_setback_m: float = 12.0  # town design: connectors start this far from the junction centre, at the
    lane_width_m: float = 3.5  #        stop bar's far edge (the bar is 0.5 m deep); lanes 3.5 m wide
    turn_lookahead_m: float = 3.5  # pure pursuit of the arc from the rear axle (as the autopilot follows lanes):
    turn_lookahead_s: float = 0.4  # lookahead = this + turn_lookahead_s x speed
    turn_bar_seen_m: float = 12.0  # a turn is placed only by a stop bar seen this near
    road_min_confidence: float = 0.25  # a lane fit this sure measures the approach lane
    road_clear_m: float = 8.0  # the approach lane is measured only while the stop line is farther than this
    #                            (close to it, the crosswalk's stripes look like lane lines)
    clock: str = "wall"  # stage timings in wall-clock time, or "cpu": CPU time of this thread (load-independent)
    ldw_min_lane_confidence: float = 0.5  # lane departure is only judged on a well-seen lane
    light_box_pad_px: float = 1.0  # light boxes come out about a pixel taller than the housing (measured)
    row_sigma_px: float = 1.0  # box-edge uncertainty, for the geometry fusion
    prior_sigma: float = 0.12  # relative spread of the height prior
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    blind_spot: BlindSpotConfig = field(default_factory=BlindSpotConfig)
    adas: AdasConfig = field(default_factory=AdasConfig)
    sort: SortConfig = field(default_factory=SortConfig)


@dataclass
class LightSeen:
    state: str  # "red", "yellow", "green"
    box: tuple[float, float, float, float]
    distance_m: float
    score: float


@dataclass
class AgentView:
    """The last frame's perception and decision (what the overlay draws)."""

    image: np.ndarray
    time_s: float
    speed_mps: float
    command: int
    lanes: LaneResult | None
    stop_line: StopLine | None
    objects: list[PerceivedObject]
    tracks: list[Track]
    light: LightSeen | None
    decision: Decision
    warnings: list[str]
    lane_centre: np.ndarray | None
    lane_width_m: float
    blind_spot: tuple[bool, bool] = (False, False)  # a vehicle in the left, right mirror camera's zone lately


class BoxGeometry:
    """Where a box's object stands, from the pinhole camera model and the flat road (see module docstring)."""

    def __init__(self, camera: CameraConfig, row_sigma_px: float = 1.0, prior_sigma: float = 0.12) -> None:
        self.camera = camera
        self.k = camera.intrinsics()
        self.f = float(self.k[0, 0])
        self.birdseye = BirdsEye(camera)
        self.row_sigma = row_sigma_px
        self.prior_sigma = prior_sigma

    def cut(self, box: np.ndarray | tuple[float, ...]) -> tuple[bool, bool]:
        """Whether the box is cut off by the image's top edge (its height says nothing) and by its bottom edge
        (its bottom row is not where the object meets the road)."""
        return float(box[1]) <= 0.5, float(box[3]) >= self.camera.height - 1.5

    def distance(self, box: np.ndarray | tuple[float, ...], kind: str) -> float:
        """Forward ground distance (m) from the camera to the object's near face."""
        x0, y0, x1, y1 = (float(v) for v in box)
        z_ground = float(self.birdseye.ground_z_of_row(np.array([y1]))[0])
        height_px = y1 - y0
        z_size = self.f * HEIGHT_PRIOR_M.get(kind, 1.5) / height_px if height_px >= 2 else math.nan
        cut_top, cut_bottom = self.cut(box)
        if cut_top:
            z_size = math.nan
        if cut_bottom and math.isfinite(z_ground):  # nearer than the last row
            return min(z_size, z_ground) if math.isfinite(z_size) else z_ground
        if not math.isfinite(z_ground) or z_ground <= 0:
            return z_size
        if not math.isfinite(z_size):
            return z_ground
        var_g = (z_ground ** 2 / (self.f * self.camera.mount_height_m) * self.row_sigma) ** 2
        var_s = (z_size * self.row_sigma / height_px) ** 2 + (self.prior_sigma * z_size) ** 2
        return (z_ground / var_g + z_size / var_s) / (1.0 / var_g + 1.0 / var_s)

    def height_ratio(self, box: np.ndarray | tuple[float, ...], kind: str) -> float:
        """The box's height over the height the kind's prior height would have where its bottom row meets the
        road: about 1 for a whole object standing there; nan when the box is cut at the top or bottom, or its
        bottom row is not on the road."""
        if any(self.cut(box)):
            return math.nan
        y0, y1 = float(box[1]), float(box[3])
        z = float(self.birdseye.ground_z_of_row(np.array([y1]))[0])
        if not math.isfinite(z) or z <= 0:
            return math.nan
        return z * (y1 - y0) / (self.f * HEIGHT_PRIOR_M.get(kind, 1.5))

    def lateral(self, u_px: float, z_m: float) -> float:
        """Metres right of the camera axis of image column ``u_px`` at forward distance ``z_m``."""
        return (u_px - float(self.k[0, 2])) * z_m / self.f


def lane_centre_of(lanes: LaneResult, z0: float) -> np.ndarray | None:
    """The lane centre (a, b, c) holding the car: the detected lane, or its neighbour when the car is over a line."""
    if not lanes.detected:
        return None
    w = lanes.lane_width_m
    if lanes.left is not None and lanes.right is not None:
        centre = 0.5 * (lanes.left.coeffs + lanes.right.coeffs)
    elif lanes.left is not None:
        centre = lanes.left.coeffs + np.array([0.0, 0.0, w / 2])
    else:
        assert lanes.right is not None
        centre = lanes.right.coeffs - np.array([0.0, 0.0, w / 2])
    centre = np.asarray(centre, float).copy()
    at_car = float(np.polyval(centre, z0))
    centre[2] -= round(at_car / w) * w
    return centre


@register("agent")
class AgentDriver:
    """PilotNet + perception + rule-based controller (see module docstring). Not privileged."""

    name = "agent"
    privileged = False

    def __init__(self, model: str | Path = DEFAULT_MODEL, detector: str | Path = DEFAULT_DETECTOR,
                 backend: str = "onnx", config: AgentConfig | None = None, threads: int = 1,
                 refiner: str | Path | None = DEFAULT_REFINER, **overrides: Any) -> None:
        from dataclasses import replace

        self.config = replace(config or AgentConfig(), **overrides) if overrides else (config or AgentConfig())
        if self.config.distance not in ("geometry", "stereo"):
            raise ValueError(f"Unknown distance method {self.config.distance!r}; use 'geometry' or 'stereo'.")
        if self.config.clock not in ("wall", "cpu"):
            raise ValueError(f"Unknown clock {self.config.clock!r}; use 'wall' or 'cpu'.")
        self._now = time.thread_time if self.config.clock == "cpu" else time.perf_counter
        if self.config.detect_every < 1:
            raise ValueError("detect_every must be at least 1 (1 = detect on every frame).")
        self.net = PilotNetModel(model, backend, threads)
        if not Path(detector).is_file():
            raise FileNotFoundError(f"Detector model {detector} not found; train and export one with "
                                    "`python train.py detector train` and `python train.py detector export`.")
        self.detector = OnnxDetector(detector, self.config.score_threshold, threads=threads, refiner=refiner)
        self.controller = Controller(self.config.controller, EgoVehicle.MAX_ACCEL_MPS2, EgoVehicle.MAX_BRAKE_MPS2)
        self.adas = Adas(self.config.adas)
        self.sort = Sort(self.config.sort)
        self.timings: list[dict[str, float]] = []
        self.view: AgentView | None = None
        self._look: Callable[[str], np.ndarray] | None = None  # the blind-spot camera, where there is one
        self._mirror_camera = BLIND_SPOT_CAMERA
        self._setup(CameraConfig(), 0.05)

    def _setup(self, camera: CameraConfig, dt: float) -> None:
        self.camera = camera
        self.dt = dt
        self.lanes = LaneDetector(camera)
        self.stop = StopLineDetector(camera)
        self.geometry = BoxGeometry(camera, self.config.row_sigma_px, self.config.prior_sigma)
        self.blind_spot = BlindSpot(BoxGeometry(self._mirror_camera, self.config.row_sigma_px, self.config.prior_sigma),
                                    MirrorMount(*BLIND_SPOT_MOUNT_M, BLIND_SPOT_YAW_DEG), self.config.blind_spot)
        self.stereo = None
        if self.config.distance == "stereo":
            from agent.perception.stereo import StereoDepth

            self.stereo = StereoDepth(camera)

    def reset(self, env: DriveEnv) -> None:
        """Start an episode: only the env's configuration (camera, time step) is read, never its world."""
        cfg = env.config
        if self.config.distance == "stereo" and not cfg.observe_stereo:
            raise ValueError("The agent's stereo distance needs the stereo pair: use DriveConfig(observe_stereo=True, "
                             "camera=CameraConfig(stereo=True)), or distance='geometry'.")
        # The mirror cameras, where the env has them (a recorded episode or a plain camera source has not).
        self._mirror_camera = getattr(cfg, "blind_spot_camera", BLIND_SPOT_CAMERA)
        look = getattr(env, "blind_spot_frame", None)
        self._look = look if getattr(cfg, "render_camera", False) and self.config.blind_spot.enabled else None
        self._setup(cfg.camera, cfg.world.dt_s)
        self.adas.reset()
        self.timings = []
        self.view = None
        self._frame = 0
        self._restart()

    def on_intervention(self) -> None:
        """The safety driver took over and put the car back on its lane: what was tracked and dead-reckoned
        (stop line, lights, objects, the junction's arc) describes the place the car left, so it starts afresh,
        as a car's system does when it is engaged again. The episode's timings and warnings stay."""
        self._setup(self.camera, self.dt)
        self._restart()

    def _restart(self) -> None:
        """Forget every tracked and dead-reckoned state."""
        self.controller.reset()
        self.sort.reset()
        self.blind_spot.reset()
        self._lights: list[Detection] = []
        self._history: dict[int, deque[tuple[float, float, float]]] = {}
        self._lost: dict[int, PerceivedObject] = {}  # objects lost in our path, remembered for a while
        self._in_path: dict[int, PerceivedObject] = {}  # last frame's seen objects in our path
        self._at_side: dict[int, PerceivedObject] = {}  # last frame's near people at the image's side edge
        self._whole_at: dict[int, float] = {}  # track id -> when a person's track was last seen whole
        self._edge_only: set[int] = set()  # this frame's people seen only at the image's side edge
        self._turn = 0.0  # the heading change of the last frame (rad, positive to the right)
        self._yaw = 0.0  # dead-reckoned heading (rad, positive to the right) from our own speed and steering
        self._road_yaw: float | None = None  # the approach lane's heading in the same frame, from the lane fit
        self._road_offset = 0.0  # metres right of the approach lane's centre (measured, then dead-reckoned)
        self._approach_yaw = 0.0  # the heading the car had while it last drove along its lane
        self._pos = np.zeros(2)  # dead-reckoned position of the car's centre (x ahead at yaw 0, y right)
        # the stop bar ahead (x, y, road yaw) and the command of the turn once it has begun (0: not yet)
        self._junction: tuple[float, float, float, int] | None = None

    # ------------------------------------------------------------------ perception helpers
    def _objects(self, tracks: list[Track], t: float, depth: np.ndarray | None) -> list[PerceivedObject]:
        out = []
        self._edge_only = set()
        alive = set()
        for tr in tracks:
            kind = CLASSES[tr.label] if 0 <= tr.label < len(CLASSES) else ""
            if kind not in TRACKED:
                continue
            box = np.asarray(tr.box, float)
            if kind == "pedestrian" and not self._plausible_person(box):
                continue
            z = self.geometry.distance(box, kind)
            if depth is not None and self.stereo is not None:
                zs = self.stereo.object_distance(depth, box)
                if math.isfinite(zs) and zs < self.config.stereo_max_m:
                    z = zs
            if not math.isfinite(z) or z <= 0:
                continue
            xl, xr = self.geometry.lateral(box[0], z), self.geometry.lateral(box[2], z)
            hist = self._history.setdefault(tr.track_id, deque())
            hist.append((t, z, 0.5 * (xl + xr)))
            while hist and hist[0][0] < t - self.config.history_s:
                hist.popleft()
            alive.add(tr.track_id)
            closing, lateral = 0.0, 0.0
            known = len(hist) >= 4 and hist[-1][0] - hist[0][0] >= 0.2  # enough history for speeds
            if known:
                arr = np.array(hist)
                tt = arr[:, 0] - arr[:, 0].mean()
                denom = float((tt ** 2).sum())
                closing = -float((tt * (arr[:, 1] - arr[:, 1].mean())).sum()) / denom
                lateral = float((tt * (arr[:, 2] - arr[:, 2].mean())).sum()) / denom
            if kind in DEPTH_PRIOR_M and known and abs(lateral) < self.config.still_lateral_mps:
                # Wholly to one side: the inner edge's ray meets the vehicle at least its width beyond the near
                # face (exact for a crossing car, still conservative for one alongside, which shows its length).
                cx = float(self.geometry.k[0, 2])
                if box[0] > cx:
                    xl = self.geometry.lateral(box[0], z + DEPTH_PRIOR_M[kind])
                elif box[2] < cx:
                    xr = self.geometry.lateral(box[2], z + DEPTH_PRIOR_M[kind])
            out.append(PerceivedObject(tr.track_id, kind, float(z), float(xl), float(xr), closing, lateral,
                                       (float(box[0]), float(box[1]), float(box[2]), float(box[3])),
                                       confirmed=self._confirmed(tr, kind, t)))
        for tid in list(self._history):
            if tid not in alive:
                del self._history[tid]
        for tid in list(self._whole_at):
            if tid not in alive:
                del self._whole_at[tid]
        return out

    def _confirmed(self, track: Track, kind: str, t: float) -> bool:
        """Whether the detector confirms this track this frame: it matched a detection (not SORT coasting on
        its prediction), and a person at the image's side edge was seen whole lately (module docstring)."""
        whole = kind != "pedestrian" or self._seen_whole(track, t)
        if not whole:
            self._edge_only.add(track.track_id)
        return whole and track.time_since_update == 0

    def _seen_whole(self, track: Track, t: float) -> bool:
        """Whether a person's box is clear of the image's side edges, or its track was seen so (detected, not
        predicted) within ``edge_confirm_s``."""
        if not self._at_side_edge(track.box, self.config.whole_margin_px):
            if track.time_since_update == 0:
                self._whole_at[track.track_id] = t
            return True
        return t - self._whole_at.get(track.track_id, -math.inf) <= self.config.edge_confirm_s

    def _plausible_person(self, box: np.ndarray) -> bool:
        """Whether a pedestrian box's size agrees with where its bottom row meets the road (see
        ``AgentConfig.person_height_ratio``); a box cut by the image's top or bottom edge is not judged."""
        ratio = self.geometry.height_ratio(box, "pedestrian")
        lo, hi = self.config.person_height_ratio
        return not math.isfinite(ratio) or lo <= ratio <= hi

    def _remember(self, objects: list[PerceivedObject], speed: float) -> list[PerceivedObject]:
        """Add the objects that were in our path and near last frame but are no longer detected.

        Close in, the detector misses what fills much of the frame (a pedestrian a few metres ahead), and a
        car must not drive on because its detector blinked: such an object stays where it was last seen
        (relative to the ground: the car's own travel brings it nearer and its turning moves it across) for
        ``lost_memory_s``. A person near the car who leaves the view at its side edge is remembered too, in or
        out of our path: a turn towards that side sweeps the car's body over where they went."""
        cfg, dt = self.config, self.dt
        cos_t, sin_t = math.cos(self._turn), math.sin(self._turn)  # our heading change since last frame
        seen = {o.track_id for o in objects}
        for tid, o in self._in_path.items():
            if tid not in seen and o.distance_m < cfg.lost_memory_m:
                self._lost[tid] = o
        for tid, o in self._at_side.items():  # walked out of view beside the car: where a turn's sweep goes
            if tid not in seen and tid not in self._lost:
                self._lost[tid] = o
        out = list(objects)
        for tid in list(self._lost):
            o = self._lost[tid]
            near = o.kind == "pedestrian" and (o.distance_m < cfg.near_memory_m or self._at_border(o.box))
            if tid in seen or o.unseen_s + dt > (cfg.near_memory_s if near else cfg.lost_memory_s):
                del self._lost[tid]
                continue
            along = speed * dt if o.kind == "pedestrian" else o.closing_speed_mps * dt
            # Near, a person's box is cut or wrong and its sideways "speed" is perspective, not walking.
            shift = o.lateral_speed_mps * dt if o.kind == "pedestrian" and not near else 0.0
            # Our own turn moves it across the view: a point ahead drifts left as we turn right.
            z = o.distance_m - along
            xc = 0.5 * (o.lateral_left_m + o.lateral_right_m) + shift
            shift += xc * cos_t - z * sin_t - xc
            z = xc * sin_t + z * cos_t
            ghost = PerceivedObject(tid, o.kind, z, o.lateral_left_m + shift, o.lateral_right_m + shift,
                                    o.closing_speed_mps, o.lateral_speed_mps, o.box, o.unseen_s + dt)
            self._lost[tid] = ghost
            out.append(ghost)
        return out

    def _note_seen(self, objects: list[PerceivedObject], decision: Decision) -> list[PerceivedObject]:
        """Keep what ``_remember`` recalls next frame if it is lost: the seen objects in our path, and the people
        near the car at the image's side edge, but no person seen only there. Returns the objects in our path
        (seen or remembered)."""
        in_path = [o for o in objects if o.track_id in decision.in_path]
        # A person seen only at the side edge is not remembered: nothing confirmed them (a track still coasting
        # on a real detection is, as the detector misses what fills the frame).
        seen = [o for o in objects if o.unseen_s == 0.0 and o.track_id not in self._edge_only]
        self._in_path = {o.track_id: o for o in seen if o.track_id in decision.in_path}
        self._at_side = {o.track_id: o for o in seen if o.kind == "pedestrian"
                         and o.distance_m < self.config.near_memory_m and self._at_side_edge(o.box)}
        return in_path

    def _at_side_edge(self, box: tuple[float, float, float, float] | np.ndarray, margin_px: float = 0.5) -> bool:
        """Whether a box touches the image's left or right edge, within ``margin_px`` (the object is leaving
        the view sideways, or is cut by its edge)."""
        return float(box[0]) <= margin_px or float(box[2]) >= self.camera.width - 1.0 - margin_px

    def _at_border(self, box: tuple[float, float, float, float]) -> bool:
        """Whether a box touches the image's bottom or side edge (the object goes on beyond the frame)."""
        return self.geometry.cut(box)[1] or self._at_side_edge(box)

    def light_distance(self, box: tuple[float, float, float, float]) -> float:
        """Ground distance (m) to a signal head from how far above the horizon its box's centre is (the head
        hangs at a known height), or from its height in pixels when it is too near the horizon for that."""
        x0, y0, x1, y1 = box
        k = self.geometry.k
        above_axis = math.atan((float(k[1, 2]) - 0.5 * (y0 + y1)) / self.geometry.f)
        elevation = above_axis + math.radians(self.camera.pitch_deg)
        if elevation > math.radians(2.0):
            return (LIGHT_HEAD_HEIGHT_M - self.camera.mount_height_m) / math.tan(elevation)
        return self.geometry.f * LIGHT_HOUSING_M / max(y1 - y0 - self.config.light_box_pad_px, 1.0)

    def _odometry(self, speed: float, steer: float, command: int) -> None:
        """Integrate our heading from the speed and the steering just sent (highway-env's bicycle model).
        While the car follows its lane, the approach heading follows it; once it steers into a commanded
        turn, the approach heading stays: lights are then judged in the frame of the lane it came along."""
        beta = math.atan(0.5 * math.tan(steer * EgoVehicle.MAX_STEER_RAD))
        self._pos += speed * self.dt * np.array([math.cos(self._yaw + beta), math.sin(self._yaw + beta)])
        self._turn = speed * math.sin(beta) / (EgoVehicle.LENGTH / 2) * self.dt
        self._yaw += self._turn
        if self._road_yaw is not None:
            self._road_offset += speed * math.sin(self._yaw + beta - self._road_yaw) * self.dt
        if command not in (1, 2) or abs(steer) < self.config.straight_steer:
            self._approach_yaw = self._yaw

    def _measure_road(self, centre: np.ndarray | None, confidence: float) -> None:
        """Keep the approach lane's heading (in the odometry frame) and our offset from its centre, from a
        confident lane fit taken well before the stop line."""
        ctl = self.controller
        if (centre is None or confidence < self.config.road_min_confidence or ctl.ignore_light_m > 0
                or (ctl.stop_line is not None and ctl.stop_line < self.config.road_clear_m)):
            return
        z0 = -self.camera.mount_forward_m
        heading = self._yaw + math.atan(float(np.polyval(np.polyder(centre), z0)))
        self._road_yaw = heading if self._road_yaw is None else self._road_yaw + 0.2 * (heading - self._road_yaw)
        self._road_offset = -float(np.polyval(centre, z0))

    def _junction_hold(self, command: int) -> float | None:
        """Going straight through a junction (no lines to follow), the steer that keeps the approach lane's
        heading and our place across it; None when this does not apply."""
        ctl, cfg = self.controller, self.config
        inside = ctl.ignore_light_m > ctl.config.junction_ignore_m - cfg.junction_hold_m
        if command != 3 or not inside or self._road_yaw is None:
            return None
        steer = -(cfg.hold_heading_gain * (self._yaw - self._road_yaw) + cfg.hold_offset_gain * self._road_offset)
        return float(np.clip(steer, -cfg.hold_max_steer, cfg.hold_max_steer))

    def _note_junction(self, stop: StopLine | None) -> None:
        """Where the stop bar ahead lies in the odometry frame (the approach lane's centre at the bar's near
        edge), from the controller's tracked bar and the approach lane measured before it. Only a bar seen
        within ``turn_bar_seen_m`` of the camera places a turn (farther readings are a metre or so off)."""
        ctl = self.controller
        if ctl.ignore_light_m > 0 or not ctl.stop_line_measured or ctl.stop_line is None or self._road_yaw is None:
            return
        if self._junction is None and (stop is None or stop.distance_m > self.config.turn_bar_seen_m):
            return
        ahead = ctl.stop_line + ctl.config.camera_to_front_m + self.camera.mount_forward_m  # car centre to the bar
        u = np.array([math.cos(self._road_yaw), math.sin(self._road_yaw)])
        right = np.array([-u[1], u[0]])
        bar = self._pos - self._road_offset * right + ahead * u
        self._junction = (float(bar[0]), float(bar[1]), self._road_yaw, 0)

    def _turn_steer(self, command: int, speed: float) -> float | None:
        """Turning at a junction (no lines to follow), the steer that pursues the town's turn arc from our lane
        to the same lane of the road we turn into; None when this does not apply."""
        cfg, ctl = self.config, self.controller
        if self._junction is None or not cfg.turn_guidance:
            return None
        bx, by, road_yaw, started = self._junction
        if started:  # a turn under way is finished, whatever the route says next (leaving the junction, the
            command = started  # command already announces the next one)
        elif command not in (1, 2):
            if ctl.ignore_light_m > 0:  # through this junction another way: its bar is behind us
                self._junction = None
            return None
        # Town rule: left turns from the inner lane (0), right turns from the outer one (1). Taken from the other
        # lane, this arc still ends in a lane of the road turned into: the arc is placed from our own lane, and
        # a right turn's radius from the outer lane (or a left turn's from the inner) is the tighter one.
        k = 0 if command == 1 else 1
        u = np.array([math.cos(road_yaw), math.sin(road_yaw)])
        heading = self._yaw - road_yaw
        half = EgoVehicle.LENGTH / 2
        rel = self._pos - np.array([bx, by])
        # the rear axle, along the approach and right of it: in highway-env's bicycle model it moves along the
        # car's heading on a curve of curvature tan(delta) / length
        here = np.array([float(rel @ u) - half * math.cos(heading), float(rel[0] * -u[1] + rel[1] * u[0])
                         - half * math.sin(heading)])
        path, arc_end = turn_path(command, cfg.junction_setback_m, (k + 0.5) * cfg.lane_width_m)
        lookahead = cfg.turn_lookahead_m + cfg.turn_lookahead_s * speed
        if here[0] < TURN_ARC_START_M - lookahead:  # not yet: the lookahead point is still before the arc
            return None
        step = float(np.hypot(*(path[1] - path[0])))
        nearest = int(np.argmin(np.sum((path - here) ** 2, axis=1)))
        if nearest * step > arc_end + 6.0:  # out of the turn, lined up on the road turned into: the lines lead again
            self._junction = None
            return None
        if not started:
            self._junction = (bx, by, road_yaw, command)
        target = path[min(len(path) - 1, nearest + int(round(lookahead / step)))]
        alpha = math.atan2(target[1] - here[1], target[0] - here[0]) - heading
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        # Pure pursuit: the arc from the rear axle through the target has curvature 2 sin(alpha) / lookahead.
        delta = math.atan(2.0 * EgoVehicle.LENGTH * math.sin(alpha) / lookahead)
        return float(np.clip(delta / EgoVehicle.MAX_STEER_RAD, -1.0, 1.0))

    def _blind_spot_check(self, t: float, command: int) -> str | None:
        """Look through a mirror camera when it is time (``agent.decision.blind_spot``); the side of a pending lane change
        that is held, else None. Pending: a left or right command, no junction turn placed yet, and no solid line
        seen on that side last frame (a solid line there is the road's edge or centre line: no lane to go to)."""
        if self._look is None:
            return None
        cfg = self.config.blind_spot
        side = {1: "left", 2: "right"}.get(command)
        if side is not None and self._junction is not None:
            side = None
        if side is not None and self.view is not None:
            line = self.view.lanes.left if side == "left" else self.view.lanes.right
            if line is not None and line.style == "solid":
                side = None
        look = None
        if side is not None and self._frame % cfg.look_every == 0:
            look = side
        elif side is None and self._frame % cfg.idle_every == 0:
            look = ("left", "right")[(self._frame // cfg.idle_every) % 2]
        if look is not None:
            self.blind_spot.update(t, look, self.detector(self._look(look)))
        return side if self.blind_spot.holding(t, side) else None

    def _light(self) -> LightSeen | None:
        """Our light: the nearest confident light box whose head hangs near our lane.

        Positions are turned back into the frame of the approach lane (by the heading change since the car
        began to turn): as the camera swings into a turn before the stop line, the cross street's light (green
        while ours is red) comes to hang over the camera axis, but not over the lane we came along.
        Once the stop line has been measured, ours must also hang where the town puts it, about 21 m beyond
        the line: the cross street's head on the near right corner hangs over our lane's edge, 12 m nearer,
        lit green while ours is red (measured: 21.4 m beyond the line for ours, 9.5 m for that one).
        A box cut by the top of the image is a light beside the car (the cross street's, seen edge-on at
        night): never ours, which stands across the junction, well inside the picture."""
        best = None
        ctl = self.controller
        expected = None
        if ctl.stop_line_measured and ctl.stop_line is not None:
            expected = ctl.stop_line + ctl.config.camera_to_front_m + ctl.config.light_beyond_stop_line_m
        turned = self._yaw - self._approach_yaw
        cos_t, sin_t = math.cos(turned), math.sin(turned)
        for d in self._lights:
            x0, y0, x1, y1 = d.box
            if d.score < self.config.light_score_threshold or y1 - y0 < 2 or y0 <= 1.0:
                continue
            z_cam = self.light_distance(d.box)
            x_cam = self.geometry.lateral(0.5 * (x0 + x1), z_cam)
            lateral, z = x_cam * cos_t + z_cam * sin_t, z_cam * cos_t - x_cam * sin_t
            if abs(lateral) > self.config.light_max_lateral_m:
                continue
            if expected is not None and abs(z - expected) > self.config.light_line_tolerance_m:
                continue
            if best is None or z < best.distance_m:
                best = LightSeen(d.name.removeprefix("light_"), d.box, z, d.score)
        return best

    # ------------------------------------------------------------------ the driver
    def act(self, observation: dict[str, Any]) -> np.ndarray:
        t_start = self._now()
        times: dict[str, float] = {}
        clock = t_start

        def lap(stage: str) -> None:
            nonlocal clock
            now = self._now()
            times[stage] = times.get(stage, 0.0) + (now - clock) * 1000.0
            clock = now

        image = observation["image"]
        speed = float(observation["speed"][0])
        command = int(observation["command"])
        t = self._frame * self.dt
        held = self._blind_spot_check(t, command)
        lap("blind_spot")
        pilot = float(self.net.steer(image, 0 if held else command))  # held: follow the lane, do not change it
        lap("pilotnet")
        run = self._frame % self.config.detect_every == 0
        self._frame += 1
        times["detector"] = 0.0
        if run:
            dets = self.detector(image)
            lap("detector")
            self._lights = [d for d in dets if d.name in LIGHT_CLASSES]
            movers = [d for d in dets if d.name in TRACKED]
            boxes = np.array([d.box for d in movers], float).reshape(-1, 4)
            labels = np.array([d.cls for d in movers], int)
            tracks = self.sort.update(boxes, labels)
        else:
            tracks = self.sort.predict()
        lap("tracking")
        lanes = self.lanes.detect(image)
        lap("lanes")
        stop = self.stop.detect(image, lanes)
        lap("stop_line")
        depth = None
        if self.stereo is not None and "stereo" in observation:
            pair = observation["stereo"]
            depth = self.stereo.depth(self.stereo.disparity(pair[0], pair[1]))
        objects = self._remember(self._objects(tracks, t, depth), speed)
        light = self._light()
        lap("distance")
        centre = lane_centre_of(lanes, -self.camera.mount_forward_m)
        self._measure_road(centre, lanes.confidence)
        hold = self._junction_hold(command)
        turn = self._turn_steer(command, speed)
        net_steer = pilot
        if hold is not None:
            pilot = hold
        elif turn is not None:
            pilot = turn
        lane_range = min(30.0, max((ln.z_range_m[1] for ln in (lanes.left, lanes.right) if ln is not None), default=30.0))
        held_why = self.blind_spot.reason(held) if held else ""
        caps = ([(held_why, self.config.blind_spot.yield_speed_mps)]
                if held and self.blind_spot.alongside(held) else [])  # let it pass; a follower is merged in front of
        scene = Scene(speed, objects, light.state if light else None, light.distance_m if light else None,
                      stop.distance_m if stop is not None else None, centre, max(lane_range, 8.0),
                      turning=command in (1, 2), speed_caps=caps)
        decision = self.controller.step(scene, pilot, self.dt)
        if hold is not None:  # the steering was overridden too: say so, and keep what PilotNet proposed
            decision.pilot_steer = net_steer
            decision.reason += "; straight through the junction on the approach lane's heading"
        elif turn is not None:
            decision.pilot_steer = net_steer
            decision.reason += "; turning along the junction's arc"
        if held and not decision.reason.startswith(held_why):  # the cap did not govern: say why PilotNet followed
            decision.reason += f"; {held_why}"
        self._note_junction(stop)  # the bar as measured this frame, where the car is this frame
        self._odometry(speed, decision.steer, command)
        lap("control")
        in_path = self._note_seen(objects, decision)
        offset = lanes.offset_m if lanes.confidence >= self.config.ldw_min_lane_confidence else math.nan
        warnings = self.adas.update(t, speed, offset, lanes.lane_width_m, in_path, turning=command in (1, 2))
        lap("adas")
        times["total"] = (self._now() - t_start) * 1000.0
        self.timings.append(times)
        self.view = AgentView(image, t, speed, command, lanes, stop, objects, tracks, light, decision, warnings,
                              centre, lanes.lane_width_m,
                              (self.blind_spot.holding(t, "left"), self.blind_spot.holding(t, "right")))
        return decision.action()

    # ------------------------------------------------------------------ reports
    @property
    def reason(self) -> str:
        """Why the last action was taken (the controller's reason), "" before the first frame; evaluation
        reports keep it with every infraction and take-over."""
        return self.view.decision.reason if self.view is not None else ""

    def adas_summary(self) -> dict[str, Any]:
        """The episode's ADAS events (closes the open ones); the evaluation report stores this per episode."""
        self.adas.close(self._frame * self.dt)
        return self.adas.summary()

    def overlay(self, scale: int = 2) -> np.ndarray | None:
        """The last frame with the agent's overlay (``agent.agent_overlay.draw_agent``), or None before the first."""
        if self.view is None:
            return None
        from agent.agent_overlay import draw_agent

        return draw_agent(self.view, self.lanes.birdseye, scale)
