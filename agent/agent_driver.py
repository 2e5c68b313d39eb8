"""The ``agent`` driver: PilotNet steers; perception and the rule-based controller decide the speed.

It sees only what a real car has: the camera frame (and the stereo pair when ``distance="stereo"`` and the
environment renders it), its own speed and the route command. ``AgentDriver`` holds no geometry of its own: it
wires stages, each an object with a small typed input and output, and times them. Each frame:

1. **Mirror look** (``agent.decision.blind_spot``): a lane change towards a vehicle in the blind spot is held.
2. **PilotNet** (``agent.perception.pilotnet``) proposes the steering.
3. **Detector** (YOLO-style, then the pedestrian refiner) every ``detect_every`` frames; **SORT** tracks
   vehicles and pedestrians (Kalman predictions on the frames in between).
4. **Lanes** (sliding windows in the bird's-eye view) and the **stop line** (distance to the bar).
5. **Objects** (``agent.perception.objects``): distance and speeds of each track from box geometry or stereo,
   what perception confirms; the **memory** of lost objects (``agent.perception.object_memory``); **our light**
   (``agent.decision.our_light``).
6. **Junction guidance** (``agent.decision.junction``, on ``agent.decision.odometry``): through a junction, the
   approach lane's heading going straight, the design's turn arc turning, in place of PilotNet.
7. **Controller** (``agent.decision.controller``) and **ADAS** warnings (``agent.decision.adas``).

The controller and the junction guidance share one stop-line track (``agent.decision.stop_line_track``).

**Both cores in one frame** (``AgentConfig.stage_threads``): the stages that do not depend on each other run at
the same time, because their libraries release the GIL (ONNX Runtime, OpenCV). The detector (with
its refiner) and then lanes and the stop line go to a worker thread while the calling thread takes the mirror
look and PilotNet; whichever thread is free first takes the lanes. Every stage still runs once per frame on the
same inputs and its results are consumed in the fixed order above, so the actions are bit for bit those of
the serial order (``stage_threads=1``, one stage after another on the calling thread). The simulator is only
ever called from the calling thread (the mirror look renders through it). The default, ``stage_threads=0``, times
both ways now and then and keeps the faster: on a machine whose other jobs hold both cores, a second thread only
waits for a core and one thread is faster (``StageThreadChoice``).

**Pipelined** (``AgentConfig.pipeline``, off by default): ``act`` starts the perception and decision of the
frame it is given on a thread of its own and returns the action decided on the frame before, so that the
simulator renders the next frame while the agent thinks, as a real car's stack runs with a frame of latency.
The mirror frame a look needs is rendered before the thread starts (``BlindSpot.plan`` says which).

Per-stage timings (ms) for every frame are kept in ``timings``; the last frame's whole state in ``view`` (for
overlays, ``agent.agent_overlay``); the episode's ADAS events in ``adas``. ``docs/design.md`` draws the flow.
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from towndrive.agent.decision.adas import Adas, AdasConfig
from towndrive.agent.decision.blind_spot import VEHICLES, BlindSpot, BlindSpotConfig, SideMount
from towndrive.agent.decision.controller import Controller, ControllerConfig, Decision, Scene
from towndrive.agent.decision.cross_traffic import CrossTraffic, CrossTrafficConfig
from towndrive.agent.decision.junction import JunctionGuidance, JunctionRules
from towndrive.agent.decision.lane_keep import LaneKeepRules, kept_steer
from towndrive.agent.decision.odometry import Odometry
from towndrive.agent.decision.our_light import LightRules, LightSeen, OurLight
from towndrive.agent.decision.signs import KerbLanes, lanes_each_way, lanes_to_kerb
from towndrive.agent.decision.stop_line_track import camera_to_bar_m
from towndrive.agent.decision.turn_end import TurnEnd, TurnEndRules
from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.classes import LIGHT_CLASSES
from towndrive.agent.perception.detector import Detection, OnnxDetector
from towndrive.agent.perception.exit_line import ExitLine, ExitLineFinder
from towndrive.agent.perception.lanes import LaneConfig, LaneDetector, LaneResult, lane_centre_of
from towndrive.agent.perception.model_view import ModelView
from towndrive.agent.perception.object_memory import MemoryRules, ObjectMemory
from towndrive.agent.perception.objects import TRACKED, ObjectEstimator, ObjectRules, PerceivedObject
from towndrive.agent.perception.pilotnet import DEFAULT_MODEL, PilotNetModel
from towndrive.agent.perception.signs import SignLocator, SignRules, SignSeen
from towndrive.agent.perception.stop_line import StopLine, StopLineDetector
from towndrive.agent.perception.tracking import Sort, SortConfig, Track
from towndrive.agent.perception.zebra import ZebraDetector, bar_checked
from towndrive.agent.shipped import DETECTOR_SIGNS_ONNX, REFINER_ONNX, SIGN_READER_ONNX
from towndrive.envs.driver_context import DriverContext
from towndrive.sim.spec import CAMERA, CORNERS, MIRRORS, ROAD, VEHICLE, CameraConfig, RoadDesign

DEFAULT_DETECTOR = DETECTOR_SIGNS_ONNX  # the six classes of cars, people and lights, and the road signs
DEFAULT_REFINER = REFINER_ONNX
DEFAULT_SIGN_READER = SIGN_READER_ONNX  # reads which sign a sign box holds (none with a six-class detector)
STAGES = ("blind_spot", "cross_traffic", "pilotnet", "detector", "tracking", "lanes", "stop_line", "distance", "control", "adas",
          "wait")  # wait: the calling thread waiting for the worker's stages (stage_threads > 1)


def _once_a_frame(render: Callable[[str], np.ndarray | None] | None) -> Callable[[str], np.ndarray | None] | None:
    """A corner camera's frames rendered at most once a side in a frame (the cross-traffic look and the look down
    the road turned into may both want one)."""
    if render is None:
        return None
    frames: dict[str, np.ndarray | None] = {}

    def frame(side: str) -> np.ndarray | None:
        if side not in frames:
            frames[side] = render(side)
        return frames[side]

    return frame


@dataclass(frozen=True)
class AgentConfig:
    detect_every: int = 1  # run the detector on every k-th frame (SORT predicts in between)
    distance: str = "geometry"  # "geometry" (box and camera model) or "stereo" (needs DriveConfig.observe_stereo)
    model_view: bool = True  # a camera unlike the trained rig is warped into its view (agent.perception.model_view)
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
    # f x 1.75 m / z tall: outside this range of height x z / (f x 1.75) it is no person standing there (a
    # kerb's edge line at the image border can pass for one and hold the car), and true detections lie well
    # inside it (docs/agent_rules.md). People in this world are all 1.75 m tall; a world with children needs
    # a lower bound.
    person_height_ratio: tuple[float, float] = (0.7, 1.4)
    # The ratio is read to a pixel or two at each of the box's rows, so its spread goes as one over the box's
    # height: a box h px tall must reach 1 - this / h of the prior's height (5,605 true detections within 40 m on
    # the test and validation splits, fixed and drawn rigs, kept (1 - ratio) x h under 8.1 px). Like the fixed
    # floor it assumes everyone is the prior's height: where heights vary, both must allow for the shortest. What
    # does not shrink with the box (a person's depth between the near foot and the head, the car's pitch) keeps
    # the floor at or under 1 - person_height_slack_share (a person 2.3 m away, 110 px tall, read 0.906).
    person_height_slack_px: float = 10.0
    person_height_slack_share: float = 0.15
    # A person's box cut by the image's bottom edge stands nearer than the last row's road; its top row, read at
    # that distance, shows at least the person's height (the head is above the camera). Under this fraction of
    # 1.75 m it is no person (true detections' whole boxes never fell under 0.83).
    cut_person_height_ratio: float = 0.8
    junction_hold_m: float = 20.0  # going straight, this far past the stop line the car holds the approach
    #                                lane's heading and offset (no lines to steer by inside the junction)
    hold_heading_gain: float = 1.5  # steer per radian of heading error (about a 1 s time constant at 5 m/s)
    hold_offset_gain: float = 0.3  # steer per metre of dead-reckoned offset from the approach lane's centre
    hold_max_steer: float = 0.3
    turn_guidance: bool = True  # commanded turns inside a junction follow the road design's turn arc
    turn_lookahead_m: float = 3.5  # pure pursuit of the arc from the rear axle (as the autopilot follows lanes):
    turn_lookahead_s: float = 0.4  # lookahead = this + turn_lookahead_s x speed
    turn_bar_seen_m: float = 12.0  # a turn is placed only by a stop bar this near (seen, or tracked there)
    turn_handover_deg: float = 60.0  # with a design that spreads, the camera's steering finishes the turn from here
    road_min_confidence: float = 0.25  # a lane fit this sure measures the approach lane
    road_clear_m: float = 8.0  # the approach lane is measured only while the stop line is farther than this
    #                            (close to it, the crosswalk's stripes look like lane lines)
    clock: str = "wall"  # stage timings in wall-clock time, or "cpu": CPU time of the thread that ran the stage
    stage_threads: int = 0  # threads for one frame's independent stages: 2 uses two cores, 1 runs them one after
    #                         another on the calling thread, 0 chooses the faster now and then (the actions are
    #                         the same either way)
    pipeline: bool = False  # act on frame t while the simulator renders frame t+1 (one frame of latency)
    ldw_min_lane_confidence: float = 0.5  # lane departure is only judged on a well-seen lane
    light_box_pad_px: float = 1.0  # light boxes come out about a pixel taller than the housing (measured)
    row_sigma_px: float = 1.0  # box-edge uncertainty, for the geometry fusion
    prior_sigma: float = 0.12  # relative spread of the height prior
    road: RoadDesign = ROAD  # road-design priors (sim.spec): a deployment profile may set a real road's
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    blind_spot: BlindSpotConfig = field(default_factory=BlindSpotConfig)
    cross_traffic: CrossTrafficConfig = field(default_factory=CrossTrafficConfig)  # the corner cameras at lines
    lane_keep: LaneKeepRules = field(default_factory=LaneKeepRules)  # bounds on PilotNet's steering off its lane
    turn_end: TurnEndRules = field(default_factory=TurnEndRules)  # PilotNet follows the road once a turn is over
    signs: SignRules = field(default_factory=SignRules)  # which detected signs address the car
    adas: AdasConfig = field(default_factory=AdasConfig)
    sort: SortConfig = field(default_factory=SortConfig)


class StageThreadChoice:
    """One thread or two for a frame's stages, whichever is faster on this machine now: every ``period`` frames,
    ``trial`` frames with each, then the one with the lower median wall-clock time until the next trial. Two
    threads win when a core is free; when other jobs hold both cores, the second thread only waits for one (and
    each hand-over between the threads waits with it). Only the speed depends on the choice, never the actions."""

    def __init__(self, period: int = 400, trial: int = 15) -> None:
        self.period, self.trial = period, trial
        self.frame = -10  # the first trial after a few frames (the first runs of ONNX Runtime are slow)
        self.samples: dict[int, list[float]] = {1: [], 2: []}
        self.chosen = 2

    def now(self) -> int:
        """The number of threads for this frame."""
        k = self.frame % self.period
        self.frame += 1
        if k < 2 * self.trial:
            return 1 if k < self.trial else 2
        if k == 2 * self.trial and all(self.samples.values()):
            one, two = (float(np.median(self.samples[n])) for n in (1, 2))
            self.chosen = 1 if one < two else 2
            self.samples = {1: [], 2: []}
        return self.chosen

    def took(self, threads: int, seconds: float) -> None:
        """A frame's wall-clock time with ``threads``, counted while trying."""
        if (self.frame - 1) % self.period < 2 * self.trial:
            self.samples[threads].append(seconds)


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
    steered_path: np.ndarray | None = None  # a junction arc's path where one steers (Scene.steered_path)


@dataclass
class Stages:
    """The perception and decision stages of one episode, built for one camera (``AgentDriver.build_stages``)."""

    lanes: LaneDetector
    stop: StopLineDetector
    geometry: BoxGeometry
    objects: ObjectEstimator
    memory: ObjectMemory
    light: OurLight
    odometry: Odometry
    junction: JunctionGuidance
    blind_spot: BlindSpot
    turn_end: TurnEnd
    cross_traffic: CrossTraffic
    stereo: Any = None  # agent.perception.stereo.StereoDepth with distance="stereo"
    signs: SignLocator | None = None  # the road signs addressing the car (agent.perception.signs)
    zebra: ZebraDetector | None = None  # the zebra beyond the stop bar, where the road design's setback may vary
    exit_line: ExitLineFinder | None = None  # the road turned into, read in a turn where the design spreads
    exit_corner: ExitLineFinder | None = None  # ... and through the corner camera on the turn's side


class AgentDriver:
    """PilotNet + perception + rule-based controller (see module docstring). Not privileged.

    ``net`` (``steer(rgb, command)``) and ``detect`` (``detect(rgb) -> detections``) are the networks; a
    deployment profile passes its own (other backends) instead of the shipped ones, and its module rates as a
    ``stage_hook`` that wraps the stages once they are built. ``refiner`` and ``sign_reader`` are the second stages
    run on the shipped detector's pedestrian and sign boxes (None: without)."""

    name = "agent"
    privileged = False

    def __init__(self, model: str | Path = DEFAULT_MODEL, detector: str | Path = DEFAULT_DETECTOR,
                 backend: str = "onnx", config: AgentConfig | None = None, threads: int = 1,
                 refiner: str | Path | None = DEFAULT_REFINER, net: Any = None,
                 sign_reader: str | Path | None = DEFAULT_SIGN_READER,
                 detect: Callable[[np.ndarray], list[Detection]] | None = None,
                 stage_hook: Callable[[Stages], Stages] | None = None, **overrides: Any) -> None:
        self.config = replace(config or AgentConfig(), **overrides) if overrides else (config or AgentConfig())
        if self.config.distance not in ("geometry", "stereo"):
            raise ValueError(f"Unknown distance method {self.config.distance!r}; use 'geometry' or 'stereo'.")
        if self.config.clock not in ("wall", "cpu"):
            raise ValueError(f"Unknown clock {self.config.clock!r}; use 'wall' or 'cpu'.")
        self._now = time.thread_time if self.config.clock == "cpu" else time.perf_counter
        if self.config.detect_every < 1:
            raise ValueError("detect_every must be at least 1 (1 = detect on every frame).")
        if self.config.stage_threads not in (0, 1, 2):
            raise ValueError(f"stage_threads must be 0 (the faster), 1 (serial) or 2; got {self.config.stage_threads}.")
        self._threads = StageThreadChoice() if self.config.stage_threads == 0 else None
        self.net = net if net is not None else PilotNetModel(model, backend, threads)
        if detect is None:
            if not Path(detector).is_file():
                raise FileNotFoundError(f"Detector model {detector} not found; train and export one with "
                                        "`python train.py detector train` and `python train.py detector export`.")
            detect = OnnxDetector(detector, self.config.score_threshold, threads=threads, refiner=refiner,
                                  signs=sign_reader)
        self.detector = detect
        # The main frame's detection (on the worker) and the mirror's (on the calling thread) may overlap: ONNX
        # Runtime sessions may be run from two threads at once; any other backend (a profile's TensorRT context)
        # is used by one thread at a time.
        self._detector_lock = contextlib.nullcontext() if getattr(detect, "thread_safe", False) else threading.Lock()
        self.controller = Controller(self.config.controller, VEHICLE.max_accel_mps2, VEHICLE.max_brake_mps2,
                                     self.config.road)
        self.adas = Adas(self.config.adas)
        self.sort = Sort(self.config.sort)
        self.timings: list[dict[str, float]] = []
        self.view: AgentView | None = None
        self._look: Callable[[str], np.ndarray] | None = None  # the blind-spot camera, where there is one
        self.stage_hook = stage_hook  # wraps the stages once built (a profile's module rates)
        self._mirror_camera = MIRRORS.camera
        self._corner: Callable[[str], np.ndarray] | None = None  # the cross-traffic cameras, where there are some
        self._corner_camera = CORNERS.camera
        self._cross = ("", False)  # this frame's cross traffic (Scene.cross_traffic, cross_unknown)
        self._model_view: ModelView | None = None  # a camera unlike the trained rig, warped into its view
        self._pools: dict[str, ThreadPoolExecutor] = {}  # made on first use, in the process that uses them
        self._pool_pid = -1
        self._pending: Future | None = None  # pipelined: the frame being worked on
        self._primed = False  # pipelined: the episode's first frame has been decided
        self._last_action = np.zeros(2, np.float32)
        self._last_view: AgentView | None = None  # the last frame worked on (pipelined: newer than ``view``)
        self._setup(CAMERA, 0.05)

    def build_stages(self, camera: CameraConfig) -> Stages:
        """The stages for ``camera``, parameterised from the configuration (a profile may wrap any of them)."""
        cfg = self.config
        geometry = BoxGeometry(camera, cfg.row_sigma_px, cfg.prior_sigma)
        stereo = None
        if cfg.distance == "stereo":
            from towndrive.agent.perception.stereo import StereoDepth

            stereo = StereoDepth(camera)
        odometry = Odometry(cfg.straight_steer, cfg.road_min_confidence, cfg.road_clear_m,
                            new_road_min_confidence=cfg.turn_end.min_confidence,  # the turn is over, as TurnEnd says
                            new_road_aligned_deg=cfg.turn_end.aligned_deg)
        junction = JunctionGuidance(JunctionRules(
            junction_hold_m=cfg.junction_hold_m, hold_heading_gain=cfg.hold_heading_gain,
            hold_offset_gain=cfg.hold_offset_gain, hold_max_steer=cfg.hold_max_steer, turn_guidance=cfg.turn_guidance,
            turn_lookahead_m=cfg.turn_lookahead_m, turn_lookahead_s=cfg.turn_lookahead_s,
            turn_bar_seen_m=cfg.turn_bar_seen_m, turn_handover_deg=cfg.turn_handover_deg),
            self.controller.line, odometry, camera.mount_forward_m, cfg.road)
        mirror = BoxGeometry(self._mirror_camera, cfg.row_sigma_px, cfg.prior_sigma)
        corner = BoxGeometry(self._corner_camera, cfg.row_sigma_px, cfg.prior_sigma)
        return Stages(
            lanes=LaneDetector(camera, LaneConfig(lane_width_prior_m=cfg.road.lane_width_m)),
            stop=StopLineDetector(camera), geometry=geometry,
            objects=ObjectEstimator(geometry, ObjectRules(cfg.history_s, cfg.still_lateral_mps, cfg.edge_confirm_s,
                                                          cfg.whole_margin_px, cfg.person_height_ratio,
                                                          cfg.person_height_slack_px, cfg.person_height_slack_share,
                                                          cfg.cut_person_height_ratio, cfg.stereo_max_m), stereo),
            memory=ObjectMemory(geometry, MemoryRules(cfg.lost_memory_s, cfg.lost_memory_m, cfg.near_memory_s,
                                                      cfg.near_memory_m)),
            light=OurLight(geometry, LightRules(cfg.light_score_threshold, cfg.light_max_lateral_m,
                                                cfg.light_line_tolerance_m, light_box_pad_px=cfg.light_box_pad_px),
                           cfg.road),
            odometry=odometry, junction=junction, turn_end=TurnEnd(cfg.turn_end),
            cross_traffic=CrossTraffic(corner, SideMount(CORNERS.ahead_m, CORNERS.out_m, CORNERS.yaw_deg),
                                       cfg.cross_traffic, cfg.road),
            blind_spot=BlindSpot(mirror, SideMount(MIRRORS.ahead_m, MIRRORS.out_m, MIRRORS.yaw_deg), cfg.blind_spot),
            stereo=stereo, signs=SignLocator(geometry, cfg.signs, cfg.road),
            zebra=ZebraDetector(camera) if cfg.road.stop_line_setback_sd_m > 0 else None,
            exit_line=ExitLineFinder(camera) if junction.design_spreads else None,
            exit_corner=ExitLineFinder(self._corner_camera) if junction.design_spreads else None)

    def _setup(self, camera: CameraConfig, dt: float) -> None:
        self.camera = camera
        self.dt = dt
        stages = self.build_stages(camera)
        self.stages = self.stage_hook(stages) if self.stage_hook is not None else stages

    def reset(self, context: DriverContext | Any) -> None:
        """Start an episode: only the sensor rig and the time step are read (``DriverContext``), never a world."""
        context = DriverContext.of(context)
        self._drain()
        if self.config.distance == "stereo" and not context.stereo:
            raise ValueError("The agent's stereo distance needs the stereo pair: use DriveConfig(observe_stereo=True, "
                             "camera=CameraConfig(stereo=True)), or distance='geometry'.")
        # The mirror cameras, where the env has them (a recorded episode or a plain camera source has not).
        self._mirror_camera = context.mirror_camera or MIRRORS.camera
        self._look = context.mirror_frame if self.config.blind_spot.enabled else None
        self._corner_camera = context.corner_camera or CORNERS.camera
        self._corner = context.corner_frame if self.config.cross_traffic.enabled else None
        view = ModelView(context.camera) if self.config.model_view else None
        self._model_view = view if view is not None and view.needed else None
        self._setup(view.camera if view is not None else context.camera, context.dt_s)
        self.adas.reset()
        self.timings = []
        self.view = self._last_view = None
        self._zebra_far_m: float | None = None  # this frame's zebra far edge (camera to it), when looked for
        self._zebra_tilt: float | None = None  # ... and the slope of its edges (the cross street's direction)
        self._bar_tracked_m: float | None = None  # camera to the tracked bar this frame (the zebra's look, unread)
        self._zebra_look = ""  # the zebra ahead looked for this frame, before the bar is placed (_zebra_look_wanted)
        self._arm_governed = False  # a light or a sign seen governing the arm ahead since the last junction
        self._exit_expected: float | None = None  # in a turn, the direction the road turned into should run
        self._exit_seen: ExitLine | None = None  # ... and its centre line as seen this frame
        self._exit_cornered: ExitLine | None = None  # ... and through the corner camera
        self._stop_made_s: float | None = None  # when the car made its full stop at the stop line it is at
        self._far_corridor: tuple[float, float, float] | None = None  # going straight, where the far side's lies
        self._read_count = False  # in a right turn: the road turned into's lane count is read too
        self._frame = 0
        self._restart()

    def on_intervention(self) -> None:
        """The safety driver took over and put the car back on its lane: what was tracked and dead-reckoned
        (stop line, lights, objects, the junction's arc) describes the place the car left, so it starts afresh,
        as a car's system does when it is engaged again. The episode's timings and warnings stay. Whether the
        bumper was past a stop line is kept: the safety driver leaves the car inside the junction then, perhaps
        mid-turn (``TurnEnd.engaged_mid_turn``)."""
        inside = self.controller.line.in_junction  # (before the restart forgets it)
        self._drain()
        self._setup(self.camera, self.dt)
        self._restart()
        self.stages.turn_end.reset(engaged_again=True, inside_junction=inside)

    def _restart(self) -> None:
        """Forget every tracked and dead-reckoned state."""
        self.controller.reset()
        self.sort.reset()
        st = self.stages
        for stage in (st.blind_spot, st.cross_traffic, st.objects, st.memory, st.odometry, st.junction, st.turn_end):
            stage.reset()
        self._lights: list[Detection] = []
        self._signs: list[SignSeen] = []
        self._kerb_lanes = KerbLanes(lane_width_m=self.config.road.lane_width_m)  # read clear of a stop bar

    @property
    def _turn_placed(self) -> bool:
        """Whether the car is in a junction turn or has one placed ahead: a left or right command is then no lane
        change to look over the shoulder for (``BlindSpot.plan``)."""
        return self.stages.junction.placed or self.stages.turn_end.engaged_mid_turn

    # Stage shortcuts kept for overlays, profiles and tests.
    lanes = property(lambda self: self.stages.lanes)
    stop = property(lambda self: self.stages.stop)
    geometry = property(lambda self: self.stages.geometry)
    stereo = property(lambda self: self.stages.stereo)
    blind_spot = property(lambda self: self.stages.blind_spot)

    def light_distance(self, box: tuple[float, float, float, float]) -> float:
        """Ground distance (m) to a signal head (``OurLight.distance``)."""
        return self.stages.light.distance(box)

    # ------------------------------------------------------------------ the driver
    def act(self, observation: dict[str, Any]) -> np.ndarray:
        if not self.config.pipeline:
            return self._finish(*self._act(observation, self._look, self._corner))
        # Pipelined: the frame before must be done (its state is this frame's); the mirror frame this frame will
        # look at is rendered here, on the caller's thread; the frame is worked on while the caller steps, and
        # the action decided on the frame before is returned. The first frame of an episode is decided at once,
        # and its action is given again on the second.
        earlier = self._pending.result() if self._pending is not None else None
        look = self._look
        if look is not None:
            st = self.stages
            _, side = st.blind_spot.plan(self._frame, int(observation["command"]), self._turn_placed,
                                         self._last_view.lanes if self._last_view is not None else None)
            frame = look(side) if side is not None else None
            look = (lambda _side: frame) if frame is not None else self._refuse_look
        corner = self._corner
        if corner is not None:
            side = self._corner_side()
            seen = corner(side) if side is not None else None
            corner = (lambda asked: seen if asked == side else None) if seen is not None else None
        job = self._pool("pipeline").submit(self._act, observation, look, corner)
        if earlier is not None:
            self._pending = job
            return self._finish(*earlier)
        if self._primed:  # the second frame of an episode: the first frame's action again
            self._pending = job
            return self._last_action
        self._primed = True
        return self._finish(*job.result())

    def _finish(self, action: np.ndarray, view: AgentView, times: dict[str, float]) -> np.ndarray:
        self.view = view
        self.timings.append(times)
        self._last_action = action
        return action

    @staticmethod
    def _refuse_look(side: str) -> np.ndarray:
        raise RuntimeError(f"The mirror look on the {side} was not planned (BlindSpot.plan and check disagree).")

    def _drain(self) -> None:
        """Wait for a pipelined frame still being worked on (its action is dropped: the episode moved on)."""
        self._primed = False
        if self._pending is not None:
            pending, self._pending = self._pending, None
            pending.result()

    def _pool(self, name: str) -> ThreadPoolExecutor:
        """A one-thread executor, made in the process that uses it (a forked worker gets threads of its own)."""
        if self._pool_pid != os.getpid():
            self._pools, self._pool_pid = {}, os.getpid()
        pool = self._pools.get(name)
        if pool is None:
            if name == "stages":
                # The two stage threads hold both cores: OpenCV's own worker threads (they wait actively between
                # calls) would only fight them over the small bird's-eye images. ONNX Runtime runs one thread per
                # call already (``threads``); numba's kernels here are serial.
                import cv2

                cv2.setNumThreads(1)
            pool = self._pools[name] = ThreadPoolExecutor(1, thread_name_prefix=f"agent-{name}")
        return pool

    @staticmethod
    def _settle(*jobs: Future | None) -> None:
        """Cancel the jobs not started and wait for the others (their results and errors are dropped)."""
        for job in jobs:
            if job is not None and not job.cancel():
                wait([job])

    def _timed(self, stage: str, times: dict[str, float], fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)``, its time added to ``times[stage]`` (measured on the thread that runs it)."""
        t0 = self._now()
        out = fn(*args)
        times[stage] = times.get(stage, 0.0) + (self._now() - t0) * 1000.0
        return out

    def _detect_started(self, started: threading.Event, times: dict[str, float], image: np.ndarray) -> list[Detection]:
        started.set()
        return self._timed("detector", times, self._detect, image)

    def _detect(self, image: np.ndarray) -> list[Detection]:
        with self._detector_lock:
            return self.detector(image)

    def _detect_vehicles(self, image: np.ndarray) -> list[Detection]:
        """The mirror look's detection: only vehicles are read, so only they are looked for where the detector
        can (``detect_only``: the pedestrian refiner is not run)."""
        only = getattr(self.detector, "detect_only", None)
        with self._detector_lock:
            return only(image, VEHICLES) if only is not None else self.detector(image)

    def _lanes_and_stop(self, image: np.ndarray, times: dict[str, float]) -> tuple[LaneResult, StopLine | None]:
        lanes = self._timed("lanes", times, self.stages.lanes.detect, image)
        stop = self._timed("stop_line", times, self.stages.stop.detect, image, lanes)
        zebra = self.stages.zebra
        self._zebra_far_m = None
        self._zebra_tilt = None
        ahead, stand_in = None, self._zebra_look == "stand-in"
        # on an arm a light or sign governs, the look only checks a bar read (the zebra stands in for none there)
        looked = zebra is not None and (stand_in or (self._zebra_look == "check" and stop is not None))
        if looked:
            ahead = self._timed("zebra", times, zebra.detect, image, lanes, None)
            stop = bar_checked(stop, ahead, self.config.road, self.config.turn_bar_seen_m if stand_in else None)
        bar_m = stop.distance_m if stop is not None else self._bar_tracked_m
        if zebra is not None and bar_m is not None and bar_m <= self.config.turn_bar_seen_m:
            # the look's zebra is the nearest: if it lies beyond the bar it is the one looked for, and where the look
            # found none there is none beyond the bar either
            seen = (ahead if looked and (ahead is None or zebra.beyond_bar(ahead.near_m, bar_m))
                    else self._timed("zebra", times, zebra.detect, image, lanes, bar_m))
            self._zebra_far_m = None if seen is None else seen.far_m
            self._zebra_tilt = None if seen is None else seen.tilt
        finder, expected = self.stages.exit_line, self._exit_expected
        self._exit_seen = (None if finder is None or expected is None
                           else self._timed("exit_line", times, finder.find, image, expected, self._far_corridor,
                                            self._read_count))
        return lanes, stop

    def _corner_side(self) -> str | None:
        """The corner camera looked through this frame: the cross-traffic look's side while that is wanted, else
        the turn's side while the road turned into is looked for (``JunctionGuidance.exit_look``), else none."""
        if self._cross_wanted():
            return CrossTraffic.side_to_look(self._frame)
        look = self.stages.junction.exit_look() if self.stages.exit_corner is not None else None
        return look[0] if look is not None else None

    def _look_down_exit(self, corner: Callable[[str], np.ndarray | None] | None) -> ExitLine | None:
        """In a turn, the road turned into's centre line as the corner camera on the turn's side sees it, in the
        forward camera's ground frame (None: not looked for, not in this frame, or not found)."""
        finder, look = self.stages.exit_corner, self.stages.junction.exit_look()
        if corner is None or finder is None or look is None:
            return None
        side, direction = look
        frame = corner(side)
        if frame is None:  # the frame rendered for the cross-traffic look is the other side's
            return None
        x, z, yaw = self.stages.cross_traffic.mount.in_ground_frame(side, self.camera.mount_forward_m)
        line = finder.find(frame, direction - yaw, None, self._read_count)
        return line.seen_from(x, z, yaw) if line is not None else None

    def _cross_wanted(self) -> bool:
        """Whether to look through a corner camera this frame: a stop or give-way line within ``look_from_m``, or
        the car past one edging to where the cross street is seen (``agent.decision.cross_traffic``)."""
        signs = self.controller.signs
        if signs.edging_m is not None:
            return True
        gap = signs.line_gap(self.controller.stop_line)
        return gap is not None and gap <= self.config.cross_traffic.look_from_m

    def _look_across(self, t: float, corner: Callable[[str], np.ndarray | None] | None) -> None:
        """The corner cameras' look, when wanted: one side a frame, in turn; this frame's cross traffic."""
        st, odo, signs = self.stages, self.stages.odometry, self.controller.signs
        if signs.stopped and self._stop_made_s is None:
            self._stop_made_s = t  # our full stop at a stop line: who came to theirs after it goes after us
        elif signs.control is None and signs.edging_m is None:
            self._stop_made_s = None
        side = CrossTraffic.side_to_look(self._frame)
        frame = corner(side) if corner is not None and self._cross_wanted() else None
        if frame is None:
            self._cross = ("", False)
            return
        pose = (float(odo.pos[0]), float(odo.pos[1]), float(odo.yaw))
        st.cross_traffic.update(t, side, self._detect_vehicles(frame), pose)
        self._cross = (st.cross_traffic.priority(t, pose, self._stop_made_s), st.cross_traffic.unknown(t, pose))

    def _act(self, observation: dict[str, Any], look: Callable[[str], np.ndarray] | None,
             corner: Callable[[str], np.ndarray | None] | None = None) -> tuple[np.ndarray, AgentView, dict[str, float]]:
        t_start, t_wall = self._now(), time.perf_counter()
        times: dict[str, float] = {}
        clock = t_start

        def lap(stage: str) -> None:
            nonlocal clock
            now = self._now()
            times[stage] = times.get(stage, 0.0) + (now - clock) * 1000.0
            clock = now

        st, odo = self.stages, self.stages.odometry
        image = observation["image"]
        if self._model_view is not None:
            image = self._model_view(image)
        speed = float(observation["speed"][0])
        command = int(observation["command"])
        t = self._frame * self.dt
        run = self._frame % self.config.detect_every == 0
        self._exit_expected = st.junction.exit_expected_rad()  # the lane finder's thread reads them
        line = self.controller.line  # the tracked bar, moved on by this frame's travel: where the zebra lies beyond
        self._bar_tracked_m = (camera_to_bar_m(line) - speed * self.dt
                               if line.bar_confirmed and not line.in_junction else None)  # confirmed: a bar tracked
        self._far_corridor = st.junction.far_corridor()
        self._zebra_look = self._zebra_look_wanted(command)
        self._read_count = st.junction.reads_lane_count
        # Two cores: the detector, then lanes and the stop line, on the worker while this thread looks in the
        # mirror and runs PilotNet (each stage's own thread times it); else all on this thread, in this order.
        threads = self._threads.now() if self._threads is not None else self.config.stage_threads
        worker = self._pool("stages") if threads > 1 else None
        detected: Future | None = None
        lane_job: Future | None = None
        if worker is not None:
            started = threading.Event()
            if run:
                detected = worker.submit(self._detect_started, started, times, image)
            lane_job = worker.submit(self._lanes_and_stop, image, times)
            if run and look is not None and st.blind_spot.plan(
                    self._frame, command, self._turn_placed,
                    self._last_view.lanes if self._last_view is not None else None)[1] is not None:
                # The mirror render holds the GIL for milliseconds: let the worker reach ONNX Runtime (which
                # runs without it) first, so the two overlap.
                started.wait(0.05)
        try:
            held = None
            if look is not None:
                held = st.blind_spot.check(t, self._frame, command, self._turn_placed,
                                           self._last_view.lanes if self._last_view is not None else None, look,
                                           self._detect_vehicles)
            lap("blind_spot")
            corner = _once_a_frame(corner)
            self._look_across(t, corner)
            lap("cross_traffic")
            self._exit_cornered = self._look_down_exit(corner)
            lap("exit_corner")
            seen = self._model_view.for_pilotnet(image) if self._model_view is not None else image
            last = self._last_view
            net_command = st.turn_end.command(command, odo.turned, last.lanes if last is not None else None,
                                              st.junction.arc_leads, speed * self.dt, st.junction.placed)
            pilot = float(self.net.steer(seen, 0 if held else net_command))  # held: follow the lane, do not change it
            lap("pilotnet")
        except BaseException:
            self._settle(detected, lane_job)  # the worker's stages must not outlive this frame
            raise
        self._frame += 1
        if worker is not None:
            assert lane_job is not None
            clock = self._now()
            if lane_job.cancel():  # the worker has not started them (the detector takes longer): run them here
                lanes, stop = self._lanes_and_stop(image, times)
                clock = self._now()
            else:
                lanes, stop = lane_job.result()
            dets = detected.result() if detected is not None else None
            lap("wait")
        else:
            dets = self._timed("detector", times, self._detect, image) if run else None
            clock = self._now()
        times.setdefault("detector", 0.0)
        if dets is not None:
            self._lights = [d for d in dets if d.name in LIGHT_CLASSES]
            self._signs = st.signs.read(dets) if st.signs is not None else []
            movers = [d for d in dets if d.name in TRACKED]
            boxes = np.array([d.box for d in movers], float).reshape(-1, 4)
            labels = np.array([d.cls for d in movers], int)
            tracks = self.sort.update(boxes, labels)
        else:
            tracks = self.sort.predict()
        lap("tracking")
        if worker is None:
            lanes, stop = self._lanes_and_stop(image, times)
            clock = self._now()
        depth = None
        if st.stereo is not None and "stereo" in observation:
            pair = observation["stereo"]
            if self._model_view is not None:
                pair = [self._model_view(p) for p in pair]
            depth = st.stereo.depth(st.stereo.disparity(pair[0], pair[1]))
        objects = st.memory.recall(st.objects.update(tracks, t, depth, speed, odo.turn), speed, odo.turn, self.dt,
                                   st.objects.expired)
        light = st.light.choose(self._lights, self.controller.line, odo.turned)
        lap("distance")
        z_car = -self.camera.mount_forward_m
        centre = lane_centre_of(lanes, z_car)
        odo.measure_road(centre, lanes.confidence, self.controller.line, z_car)
        st.junction.note_exit(self._exit_seen)
        st.junction.note_exit(self._exit_cornered)
        hold = st.junction.hold(command)
        if st.turn_end.ended:
            self.controller.line.leave_junction(self.config.turn_end.light_ignore_m)
        turn = st.junction.turn_steer(net_command, speed)  # no new arc once the turn is over
        steered = st.junction.steered_path(self.controller.config.lookahead_m)  # None unless the arc steers
        decision = self._decide(speed, command, pilot, hold, turn, held, objects, light, stop, lanes, centre, steered)
        if net_command != command and not held and hold is None and turn is None:
            decision.reason += "; the turn is over: PilotNet follows the road turned into"
        # as measured this frame, where the car is
        signs = self.controller.signs
        control = "signal" if light is not None else (signs.control or "none")
        self._note_lanes_to_kerb(lanes)
        st.junction.note(stop, self._zebra_far_m, lanes.boundary_width_m, self._zebra_tilt, control,
                         signs.lanes_each_way, self._kerb_lanes.count)
        odo.advance(speed, decision.steer, command, self.dt)
        lap("control")
        in_path = st.memory.note(objects, decision.in_path, st.objects.edge_only)
        offset = lanes.offset_m if lanes.confidence >= self.config.ldw_min_lane_confidence else math.nan
        warnings = self.adas.update(t, speed, offset, lanes.lane_width_m, in_path, turning=command in (1, 2))
        lap("adas")
        times["total"] = (self._now() - t_start) * 1000.0
        view = AgentView(image, t, speed, command, lanes, stop, objects, tracks, light, decision, warnings,
                         centre, lanes.lane_width_m,
                         (st.blind_spot.holding(t, "left"), st.blind_spot.holding(t, "right")), steered)
        self._last_view = view
        if self._threads is not None:
            self._threads.took(threads, time.perf_counter() - t_wall)
        return decision.action(), view, times

    def _zebra_look_wanted(self, command: int) -> str:
        """Whether this frame looks for the zebra ahead before the bar is placed (``zebra.bar_checked``): "" not, "check"
        to check the bar read against it, "stand-in" to let it stand in for a bar where nothing governs our arm.
        Only approaching a turn (a straight hold needs no bar), in a town whose design spreads (a zebra detector),
        with the car still along its lane."""
        st, line, last = self.stages, self.controller.line, self._last_view
        if line.in_junction:
            self._arm_governed = False  # the next arm is judged afresh
        elif (self.controller.signs.control is not None or st.junction.control not in (None, "none")
              or (last is not None and (last.light is not None or last.decision.light is not None))):
            self._arm_governed = True  # a light or a sign seen once governs the arm (a light's box comes and goes)
        if (st.zebra is None or command not in (1, 2) or line.in_junction
                or abs(st.odometry.turned) > math.radians(st.junction.rules.place_max_turned_deg)):
            return ""
        return "check" if self._arm_governed else "stand-in"

    def _street_lines_read(self) -> bool:
        """Whether the lane lines in view tell about the street the car drives along: not inside a junction (the
        road left behind is not the road ahead, and a turn sweeps the view across the other arms' lines), and no
        stop line, tracked or put by a sign, within ``coverage_z_max_m`` (a line's style is read from its paint
        that far ahead; a bar nearer cuts the solid edge line short, read as dashed, and beyond it lie the
        junction's and the cross street's lines)."""
        line = self.controller.line
        if line.in_junction:
            return False
        ahead = line.stop_line if line.stop_line is not None else self.controller.signs.sign_line_m
        return ahead is None or ahead > self.stages.lanes.config.markings.coverage_z_max_m

    def _note_lanes_to_kerb(self, lanes: LaneResult) -> None:
        """Remember how many lanes lie between ours and the kerb (``lanes_to_kerb``) as the line on our right tells,
        read only where the lines tell about our street (``_street_lines_read``). Kept while the car is still in
        the lane it was read in (``KerbLanes``); forgotten inside a junction: the road left behind is not the road
        ahead."""
        odo = self.stages.odometry
        if self.controller.line.in_junction:
            self._kerb_lanes.forget()
            return
        kerb = lanes_to_kerb(lanes) if self._street_lines_read() else None
        self._kerb_lanes.note(kerb, (float(odo.pos[0]), float(odo.pos[1])),
                              odo.road_yaw if odo.road_yaw is not None else odo.yaw)

    def _decide(self, speed: float, command: int, pilot: float, hold: float | None, turn: float | None,
                held: str | None, objects: list[PerceivedObject], light: LightSeen | None, stop: StopLine | None,
                lanes: LaneResult, centre: np.ndarray | None, steered: np.ndarray | None = None) -> Decision:
        """The controller's decision on this frame's scene, with the junction's steering in place of PilotNet's
        where it applies (its arc, ``steered``, is then the car's path), and the reason saying so."""
        net_steer = pilot
        guard = None
        if hold is not None:
            pilot = hold
        elif turn is not None:
            pilot = turn
        else:
            line = self.controller.line
            turn_due = command in (1, 2) and (self.stages.junction.placed or (
                line.stop_line is not None and line.stop_line < self.config.lane_keep.turn_bar_m))
            guard = kept_steer(self.config.lane_keep, pilot, lanes, speed, turn_due)
            if guard is not None:
                pilot = guard[0]
        lane_range = min(30.0, lanes.reach_m(30.0))
        held_why = self.stages.blind_spot.reason(held) if held else ""
        caps = ([(held_why, self.config.blind_spot.yield_speed_mps)]
                if held and self.stages.blind_spot.alongside(held) else [])  # let it pass; a follower is merged in front of
        scene = Scene(speed, objects, light.state if light else None, light.distance_m if light else None,
                      stop.distance_m if stop is not None else None, centre, max(lane_range, 8.0),
                      turning=command in (1, 2), turn_left=command == 1, turned_rad=self.stages.odometry.turned,
                      speed_caps=caps, signs=self._signs,
                      lanes_each_way=lanes_each_way(lanes) if self._street_lines_read() else None,
                      light_in_view_m=light.in_view_m if light else 0.0,
                      steered_path=steered, arc_ahead_m=self.stages.junction.arc_ahead_m,
                      arc_radius_m=self.stages.junction.arc_radius_m,
                      cross_traffic=self._cross[0], cross_unknown=self._cross[1],
                      cross_street_m=self.stages.junction.cross_street_m)
        decision = self.controller.step(scene, pilot, self.dt)
        if hold is not None:  # the steering was overridden too: say so, and keep what PilotNet proposed
            decision.pilot_steer = net_steer
            decision.reason += "; straight through the junction on the approach lane's heading"
        elif turn is not None:
            decision.pilot_steer = net_steer
            decision.reason += "; turning along the junction's arc"
        elif guard is not None:
            decision.pilot_steer = net_steer
            decision.reason += f"; {guard[1]}: steered back along the lane"
        if held and not decision.reason.startswith(held_why):  # the cap did not govern: say why PilotNet followed
            decision.reason += f"; {held_why}"
        return decision

    # ------------------------------------------------------------------ reports
    @property
    def reason(self) -> str:
        """Why the last action was taken (the controller's reason), "" before the first frame; evaluation
        reports keep it with every infraction and take-over."""
        return self.view.decision.reason if self.view is not None else ""

    def adas_summary(self) -> dict[str, Any]:
        """The episode's ADAS events (closes the open ones); the evaluation report stores this per episode."""
        self._drain()
        self.adas.close(self._frame * self.dt)
        return self.adas.summary()

    def overlay(self, scale: int = 2) -> np.ndarray | None:
        """The last frame with the agent's overlay (``agent.agent_overlay.draw_agent``), or None before the first."""
        if self.view is None:
            return None
        from towndrive.agent.agent_overlay import draw_agent

        return draw_agent(self.view, self.lanes.birdseye, scale)
