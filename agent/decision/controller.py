"""The rule-based controller: PilotNet steers, and these rules override the speed from what perception sees.

Seed 004's controller "doesn't follow the predictions of the trained model and takes the decision of
stopping the car"; here every such decision is one rule with a reason string, and the rules are written
against a small perception interface (``Scene``) so they can be unit-tested on synthetic inputs.

Why it is built this way:

- **One longitudinal law.** Every reason to slow down is a *constraint*: a point ahead to stop short of
  (a stop line, a car's rear bumper, a pedestrian), its speed, and the gap to keep. Each gives an
  Intelligent Driver Model acceleration; the car takes the smallest, and the constraint that gave it is
  the override reason. IDM brakes early and smoothly, and it resumes by itself when a constraint
  goes away (the light turns green, the car ahead drives off, the pedestrian has crossed).
- **Gentle limits.** Acceleration is capped (and its rise is jerk-limited), braking is capped at a
  comfortable level unless a constraint cannot be met that way (then up to the car's full brake, and the
  reason says "hard brake"), steering changes at most ``steer_rate_per_s`` per second.
- **Stop lines by odometry**: the stop bar ahead is one track (``agent.decision.stop_line_track``), counted
  down by the car's own travel between readings and shared with the junction guidance.
- **Lights are debounced** (a state needs ``light_confirm_frames`` frames, one against the cycle's order, green,
  yellow, red, that lets the car go ``light_out_of_cycle_frames``, and so does a green after a red taken less than
  ``light_min_phase_s`` before: a phase lasts seconds; a light unseen for ``light_memory_s`` is forgotten, a red
  whose head beside the line left the picture as the car stopped only once the longest red has surely passed,
  ``RoadDesign.longest_red_s``, and a yellow stopped for there only once the red after it has), and
  the yellow decision is taken once, when the yellow appears, by the line (where the car stops may be farther
  back, ``near_side_head_m``): stop if the stop needs no more than the comfortable deceleration, else go on
  (before a commanded turn,
  which slows the car for the turn at or past the line, stop unless even the full brake cannot or
  the line is a second away at turn speed); a red after a "go on"
  yellow, or a red that could not be stopped for even with the full brake, is driven through
  (the car is already committed), and the reason says so.
- **Once past the stop line**, the junction's light is ignored for ``junction_ignore_m`` metres: it stands
  across the junction, and a light that turns red while the car is inside the junction means clear it.
- **What is in our path** is decided laterally, at each object's distance, against a corridor: the lane
  centre from the lane detector when it found one, else the arc the current steering drives. Objects
  outside the corridor (other lanes) get no reaction; pedestrians get a wider corridor, and a pedestrian
  whose lateral motion brings them into it within ``entering_horizon_s`` counts as in the path; driving straight
  on, so does a vehicle crossing our road that would be in the corridor about when the car gets to it
  (``cuts_across``).
- **No endless hold on what perception does not confirm.** A person remembered after the detector lost them,
  or one the detector reports only at the image's side edge (a lit facade or a kerb there at night looks like
  half a person, and nothing the camera sees can refute it while the car stands), is stopped for like any
  other, but the car stands for such an object at most ``unconfirmed_hold_s`` (summed over whichever
  unconfirmed objects hold it); then it creeps on at ``creep_speed_mps``, so the view changes and perception
  looks again every frame, and a person the detector confirms stops it as always (what went wrong without
  it: ``docs/agent_rules.md``).
- **No endless wait behind a parked car that leaves room.** A still vehicle wholly to one side whose inner
  edge reaches into the corridor's margin but clears the car's body by ``squeeze_clear_m`` stops the car like
  any other; after standing ``squeeze_after_s`` for such vehicles it creeps past at ``creep_speed_mps``,
  looking again every frame (``Controller.grazes``).

- **Signs** (``agent.decision.signs``): a stop sign asks a full stop within ``SignControlRules.full_stop_m`` of the
  next line (speed under the world's ``STOP_SPEED_MPS``), then the car goes once no moving vehicle is within
  ``priority_near_m`` (other than one driving away ahead in our lane) and nobody confirmed stands on the crossing
  beyond the line; a yield line is approached at ``YIELD_APPROACH_MPS`` and stopped at only for such traffic. The
  last limit sign seen (else the default for the street the lane lines tell) caps the cruise speed.
- **Oncoming traffic before a left turn**: turning left, the car waits at the stop line (past it, or with none, where
  it is) while a vehicle in the oncoming lanes would reach the camera within ``oncoming_horizon_s``, as the
  world's drivers do (``sim.traffic.oncoming_conflict``), until it has turned ``oncoming_commit_deg`` (then it is
  in the way and clears the junction). Objects are read in the approach lane's frame (``Scene.turned_rad``).
- **Bends ahead**: the lane fit's curvature, where the fit reaches ``bend_min_range_m``, caps the speed at
  sqrt(a_lat / curvature) (a_lat: ``sim.spec.CURVE_LATERAL_ACCEL_MPS2``, the autopilot's) before the car steers
  into the bend; a curvature that grows is taken at what it grows to in ``bend_horizon_s``.
- **Commanded turns** at ``junction_turn_speed_mps`` on the junction's arc, and before a planned arc no slower
  than braking by its start needs (``Controller._turn_cap``): the autopilot's curve profile, so a wide junction's
  mouth is crossed at speed.

Distances in ``Scene`` are measured from the camera along the ground; the controller converts them to
the gap ahead of the front bumper with ``camera_to_front_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from towndrive.agent.decision.odometry import in_approach_frame
from towndrive.agent.decision.signs import SignControl, SignControlRules
from towndrive.agent.decision.stop_line_track import LIGHT_STATES, NEXT_IN_CYCLE, StopLineTrack, camera_to_bar_m
from towndrive.agent.perception.objects import PerceivedObject
from towndrive.agent.perception.signs import SignSeen
from towndrive.sim.idm import idm_acceleration
from towndrive.sim.spec import (
    CAMERA_TO_FRONT_M,
    CURVE_BRAKE_MPS2,
    CURVE_LATERAL_ACCEL_MPS2,
    ROAD,
    STOP_SPEED_MPS,
    VEHICLE,
    YIELD_APPROACH_MPS,
    RoadDesign,
)

VEHICLE_KINDS = ("car", "truck")


def stop_decel_mps2(speed_mps: float, gap_m: float) -> float:
    """The constant deceleration that stops a car at ``speed_mps`` within ``gap_m`` (a gap under 5 cm counts as
    5 cm: a point at or behind the bumper asks for a large one, not an infinite one)."""
    return speed_mps * speed_mps / (2.0 * max(gap_m, 0.05))


def toward_zero(value: float, by: float) -> float:
    """``value`` moved ``by`` nearer zero, not past it: a speed less what its reading's scatter could make up."""
    return math.copysign(max(abs(value) - by, 0.0), value)


@dataclass(frozen=True)
class ControllerConfig:
    speed_limit_mps: float = 8.0  # cruise speed: the town's limit
    lateral_accel_mps2: float = CURVE_LATERAL_ACCEL_MPS2  # in a bend, at most sqrt(a / curvature) (the autopilot's)
    bend_min_range_m: float = 12.0  # the lane fit tells a bend ahead only when it reaches this far
    bend_smoothing: float = 0.3  # weight of this frame's curvature ahead in its running average
    bend_horizon_s: float = 1.0  # a growing curvature ahead is taken at what it grows to in this time
    signs: SignControlRules = SignControlRules()
    priority_near_m: float = 30.0  # at a stop or give-way line, a moving vehicle this near (not driving away
    priority_min_speed_mps: float = 1.0  # ahead of us) has priority; slower than this it is not moving ...
    priority_speed_sigmas: float = 2.0  # ... its speeds taken this many standard errors nearer zero (the fit's
    #                                     scatter: a standing car 20 m off reads 1 m/s from its box's jitter)
    yield_settle_m: float = 3.0  # at a give-way line, down to YIELD_APPROACH_MPS this far before the stop point
    edge_speed_mps: float = 2.0  # past a stop or give-way line, reach where the cross street is seen this slowly
    edge_looks: int = 4  # ... and look through the corner cameras this many frames there (both sides) before going
    edge_settle_s: float = 0.6  # ... waiting at most this long there for a vehicle whose motion is not told yet
    edge_arrived_m: float = 0.5  # ... "there": within this of the place
    crossing_depth_m: float = 8.0  # a person within this beyond the line, across the road, is on the crossing
    oncoming_horizon_s: float = 5.0  # a left turn waits while oncoming traffic would reach the camera within this
    oncoming_commit_deg: float = 20.0  # ... until the car has turned this far (then it clears the junction)
    oncoming_line_m: float = 15.0  # ... at a stop line this near (or, past it or with none, where it is)
    max_accel_mps2: float = 3.0  # acceleration limit: highway-env's IDM a, as the NPCs and the autopilot
    jerk_mps3: float = 4.0  # how fast the acceleration may rise
    comfortable_brake_mps2: float = 3.0  # normal braking limit
    max_brake_mps2: float = 8.0  # the car's full brake, for constraints comfort cannot meet
    steer_rate_per_s: float = 1.5  # largest change of the steer command per second (0: off)
    headway_s: float = 1.2  # time headway to a lead vehicle (IDM T)
    lead_min_gap_m: float = 3.0  # bumper gap kept to a stopped vehicle
    pedestrian_min_gap_m: float = 4.0  # ... and to a pedestrian in the path
    stop_line_min_gap_m: float = 0.3  # IDM s0 before the stop point
    stop_line_target_m: float = 0.8  # the stop point's distance before the line (the car ends 0.8-1.9 m short)
    hold_margin_m: float = 0.8  # within this of the stop point at walking pace, brake to a standstill
    camera_to_front_m: float = CAMERA_TO_FRONT_M  # the rig's camera to the front bumper (sim.spec)
    path_half_width_m: float = 1.3  # half the car (0.95 m) and a margin: an object overlapping this is in our path
    pedestrian_margin_m: float = 0.9  # extra corridor width for people on the move (they step out)
    standing_pedestrian_margin_m: float = 0.0  # ... and for people standing still (a car's width and 0.35 m clear)
    entering_horizon_s: float = 2.5  # a pedestrian whose motion enters the corridor within this counts
    min_lateral_speed_mps: float = 0.3  # slower lateral motion is not "entering" (box jitter)
    crossing_min_lateral_speed_mps: float = 1.0  # a vehicle moving sideways slower than this is not crossing
    crossing_margin_s: float = 1.0  # a crossing vehicle in the corridor this near the time we reach it is in the way
    crossing_hold_s: float = 1.0  # ... and stays so this long unless it has crossed (``_still_crossing``)
    lookahead_m: float = 45.0  # objects farther than this are ignored
    light_confirm_frames: int = 2
    # A light runs green, yellow, red, green: a change against that order that lets the car go (a green read during
    # a yellow) is a misread until seen this many frames in a row (a flicker of green in a yellow had the car decide
    # the yellow afresh, metres from the line, and go on into the red); a red is taken as soon as ever
    light_out_of_cycle_frames: int = 8
    light_min_phase_s: float = 1.0  # a green after a red taken less than this before is as doubtful (a yellow misread
    #                                 red for two frames, then green for two, undid the decision to stop for it)
    line_jump_m: float = 1.5  # a stop-line reading this much farther than the tracked line is suspect ...
    line_jump_frames: int = 3  # ... until seen this many frames in a row where odometry puts it
    line_unseen_forget_s: float = 1.0  # a tracked bar still this far off (below) and unseen this long was not one:
    line_unseen_far_m: float = 6.0  #    a real bar in range is found again frame after frame as the car nears it
    line_inferred_revert_m: float = 3.0  # a bar read ahead (line_jump_frames in a row, at least line_jump_m off)
    #                                      within this travel after the car "entered" a junction by a line only
    #                                      inferred from the light is the real one: the car is not in it yet
    light_memory_s: float = 1.0
    red_memory_s: float = 4.0  # a red is kept longer: not seeing the light is no reason to go
    light_fallback_margin_m: float = 2.0  # stop this much earlier when the bar was never seen
    red_no_line_speed_mps: float = 4.0  # approach speed under a red light whose stop line is unknown
    near_side_head_m: float = 5.0  # a head at most this far past the line stands at it (a post): kept in view
    yellow_commit_s: float = 1.0  # turning: a yellow this near in time at the car's speed is driven through
    junction_turn_speed_mps: float = 3.0  # turning at a junction: the 90-degree camera sees the crosswalk of the
    #                                       arm we turn into only when the car already points at it
    junction_turn_steer: float = 0.25  # |steer| above which a commanded turn counts as under way
    turn_approach_brake_mps2: float = CURVE_BRAKE_MPS2  # the slowing before a planned turn arc (_turn_cap) ...
    turn_approach_lead_s: float = 1.0  # ... to the turn speed this long before the arc at that speed
    junction_ignore_m: float = 30.0  # after crossing the stop line, the junction's light no longer applies
    wheelbase_m: float = VEHICLE.length_m  # highway-env's bicycle model: curvature = tan(delta) / length
    half_width_m: float = VEHICLE.width_m / 2
    sweep_margin_m: float = 0.3  # kept clear of the body's swept ring, beyond a person's box
    sweep_min_steer: float = 0.25  # the body's sweep is checked only in a turn steered at least this hard
    unconfirmed_hold_s: float = 5.0  # longest standstill for objects perception does not confirm (module docstring)
    creep_speed_mps: float = 1.0  # ... after which the car creeps past them at this speed, looking again every frame
    standstill_mps: float = 0.5  # below this the car counts as holding (for unconfirmed_hold_s)
    unconfirmed_reset_s: float = 1.0  # the bounded hold starts afresh once no unconfirmed object is in our path this long
    squeeze_after_s: float = 4.0  # standing this long for a still vehicle that only grazes the corridor, creep past
    squeeze_clear_m: float = 0.1  # ... when its inner edge clears our body's side by at least this
    max_steer_rad: float = VEHICLE.max_steer_rad
    idm_a_mps2: float = 3.0  # IDM a
    idm_b_mps2: float = 2.5  # IDM b (comfortable deceleration in the dynamic term)
    idm_delta: float = 4.0


@dataclass
class Scene:
    """Everything the controller is told about one frame."""

    speed_mps: float
    objects: list[PerceivedObject] = field(default_factory=list)
    light: str | None = None  # this frame's light state for our lane, None when none is seen
    light_distance_m: float | None = None  # camera to the light head, along the ground
    stop_line_m: float | None = None  # camera to the stop bar's near edge, when seen this frame
    lane_centre: np.ndarray | None = None  # (a, b, c): lane centre x = a z^2 + b z + c, camera ground frame
    lane_range_m: float = 30.0  # how far the lane fit is valid; beyond, it is continued straight
    # Where the car is steered along something other than its lane (a junction's turn arc): that path's centre as
    # (x, z) points in the camera ground frame, z increasing; it, not the lane fit, is then our path as far as it
    # goes.
    steered_path: np.ndarray | None = None
    turning: bool = False  # the route command asks for a left or right turn at the next junction
    arc_ahead_m: float | None = None  # the car's centre to where the junction's planned turn arc begins (<0: on it)
    arc_radius_m: float | None = None  # ... its radius, once the road turned into places it and tells its lane count
    turn_left: bool = False  # ... a left turn
    turned_rad: float = 0.0  # heading change since the car last drove along its lane (odometry; positive right)
    speed_caps: list[tuple[str, float]] = field(default_factory=list)  # other limits: (reason, m/s)
    signs: list[SignSeen] = field(default_factory=list)  # signs addressing us this frame (nearest first)
    lanes_each_way: int | None = None  # the kind of street the lane lines tell (agent.decision.signs)
    light_in_view_m: float = 0.0  # camera to the light head below which it leaves the picture
    # Past a stop or give-way line (agent.decision.cross_traffic): what the corner cameras say forbids crossing
    # ("" when nothing), whether a vehicle is seen there whose motion is not told yet, and the stop bar's far edge
    # to where the cross street's nearest lane begins (where to look from, JunctionGuidance.cross_street_m).
    cross_traffic: str = ""
    cross_unknown: bool = False
    cross_street_m: float | None = None


@dataclass
class Constraint:
    """A point ahead to stop short of."""

    reason: str
    gap_m: float  # bumper to the point
    speed_mps: float  # the point's own speed along our path
    min_gap_m: float
    headway_s: float
    accel_mps2: float = 0.0
    hard: bool = False  # comfortable braking cannot meet it
    hold: bool = False  # at the point at walking pace: brake to a standstill and stay
    unconfirmed: bool = False  # from an object perception does not confirm (held for at most unconfirmed_hold_s)
    grazing: bool = False  # from a still vehicle only at the corridor's edge (held for at most squeeze_after_s)


@dataclass
class HoldClock:
    """How long the car has stood for one kind of object that holds it only for a bounded time: it runs while the
    car stands for such an object, keeps its count while one is in our path (creeping goes on, and a false box
    that comes and goes does not restart it), and restarts once none has been for ``reset_s``."""

    held_s: float = 0.0
    _none_s: float = 0.0  # since one was last in our path

    def update(self, in_path: bool, standing_for: bool, dt: float, reset_s: float) -> None:
        if in_path:
            self._none_s = 0.0
        else:
            self._none_s += dt
            if self._none_s > reset_s:
                self.held_s = 0.0
        if standing_for:
            self.held_s += dt


@dataclass
class Decision:
    """What the controller did this frame, and why."""

    steer: float
    throttle_brake: float
    accel_mps2: float
    target_speed_mps: float
    pilot_steer: float
    reason: str  # "cruise" when nothing overrides PilotNet and the cruise speed
    constraints: list[Constraint]
    light: str | None  # the debounced light state that applies, None when none does
    stop_line_gap_m: float | None  # bumper to the stop line (odometry-tracked), None when unknown
    in_path: list[int]  # track ids in (or entering) our path
    lead_id: int | None  # the object the governing constraint comes from
    holding: bool

    def action(self) -> np.ndarray:
        return np.array([self.steer, self.throttle_brake], np.float32)


class Controller:
    """The rules (see module docstring). Call ``reset()`` per episode and ``step(scene, steer, dt)`` per frame."""

    def __init__(self, config: ControllerConfig | None = None, max_accel_mps2: float = VEHICLE.max_accel_mps2,
                 max_brake_mps2: float = VEHICLE.max_brake_mps2, road: RoadDesign = ROAD) -> None:
        self.config = config or ControllerConfig()
        self.road = road  # the road-design priors (where lights stand beyond the stop line)
        self.vehicle_accel = max_accel_mps2  # what throttle 1 gives
        self.vehicle_brake = max_brake_mps2  # what brake 1 (throttle_brake -1) gives
        self.line = StopLineTrack(self.config, self.road)  # the stop bar ahead (shared with the junction guidance)
        self.signs = SignControl(self.config.signs, self.road, self.config.camera_to_front_m)
        self.reset()

    def reset(self) -> None:
        self.last_steer = 0.0
        self.last_accel = 0.0
        self.line.reset()
        self.light_state: str | None = None
        self._light_candidate: str | None = None
        self._light_count = 0
        self._light_unseen_s = math.inf
        self._light_age_s = math.inf  # how long the light's state has been the one taken
        self._yellow_go: bool | None = None  # the yellow decision, taken once per yellow
        self._view_back_m = 0.0  # stop this far before the line to keep our light's head in the picture
        self._edge_s, self._edge_frames = 0.0, 0  # time and frames spent where the cross street is seen
        self.note = ""  # why a seen light does not stop the car (shown as the reason when nothing else acts)
        self.unconfirmed_clock = HoldClock()  # standstill for unconfirmed objects in our path (module docstring)
        self.grazed_clock = HoldClock()  # standstill for still vehicles grazing the corridor (``grazes``)
        self.signs.reset()
        self._cruise = self.config.speed_limit_mps  # the cruise speed under the limit that applies
        self.bend_curvature = 0.0  # the curvature ahead (1/m), smoothed
        self._bend_rate = 0.0  # its growth (1/m per s), smoothed
        self._crossing: dict[int, float] = {}  # vehicles judged crossing our path: how long the judgement holds

    # The stop-line track's figures, read and set as the controller's own (tests and overlays use them).
    stop_line = property(lambda self: self.line.stop_line, lambda self, v: setattr(self.line, "stop_line", v))
    stop_line_measured = property(lambda self: self.line.stop_line_measured,
                                  lambda self, v: setattr(self.line, "stop_line_measured", v))
    ignore_light_m = property(lambda self: self.line.ignore_light_m,
                              lambda self, v: setattr(self.line, "ignore_light_m", v))

    # ------------------------------------------------------------------ geometry
    def path_centre(self, scene: Scene, z_m: float, steer: float, kind: str = "car") -> float:
        """Lateral position of our path's centre at ``z_m`` ahead of the camera, as an object of ``kind`` is judged
        against it: along the path steered where there is one, else (and beyond its end) the lane fit, else the
        steered path continued straight, else the arc the steering drives. People are judged as before against the
        lane fit, and in a tight turn against the ring the body sweeps (``in_sweep``): at the inner side of a turn,
        where the arc runs, a person's box is often cut by the image's edge and read a metre or two nearer the
        middle than the person stands (a night left turn held for 4 s for someone on the kerb)."""
        cfg = self.config
        path = scene.steered_path if kind != "pedestrian" else None
        if path is not None and (z_m <= path[-1, 1] or scene.lane_centre is None):
            x, z = path[:, 0], path[:, 1]
            if z_m <= z[-1]:
                return float(np.interp(z_m, z, x))
            slope = (x[-1] - x[-2]) / max(z[-1] - z[-2], 1e-6)
            return float(x[-1] + slope * (z_m - z[-1]))
        if scene.lane_centre is not None:
            a, b, c = (float(v) for v in scene.lane_centre)
            z0 = min(z_m, scene.lane_range_m)
            x = a * z0 * z0 + b * z0 + c
            if z_m > z0:  # beyond the fit: straight on along its last direction
                x += (2 * a * z0 + b) * (z_m - z0)
            return x
        curvature = math.tan(steer * cfg.max_steer_rad) / cfg.wheelbase_m
        return 0.5 * curvature * z_m * z_m

    def _bar_hidden(self, scene: Scene, steer: float) -> bool:
        """Whether a vehicle in our path stands between the camera and the tracked stop bar (a car waiting at it
        hides its paint: not seeing the bar then says nothing against it). Only a bar read from paint is asked
        about (``StopLineTrack.update`` uses the answer for no other): on most frames nothing is looked at."""
        if not self.line.stop_line_measured or self.line.stop_line is None:
            return False
        bar_m = camera_to_bar_m(self.line)
        return any(o.kind in VEHICLE_KINDS and o.distance_m < bar_m and self.overlaps(scene, o, steer)
                   for o in scene.objects)

    def overlaps(self, scene: Scene, obj: PerceivedObject, steer: float) -> bool:
        """Whether the object's lateral extent overlaps the corridor at its distance (people: wider)."""
        cfg = self.config
        centre = self.path_centre(scene, obj.distance_m, steer, obj.kind)
        half = cfg.path_half_width_m + self.margin(scene, obj)
        return obj.lateral_right_m >= centre - half and obj.lateral_left_m <= centre + half

    def margin(self, scene: Scene, obj: PerceivedObject) -> float:
        """The corridor's extra width for an object: none for a vehicle; for a person on the move the full
        ``pedestrian_margin_m`` (they step out); for one standing still (waiting on the kerb) only
        ``standing_pedestrian_margin_m``: a standing person blocks what would brush them, as the world's own
        drivers judge it, and the entering test catches them the moment they move towards the corridor."""
        cfg = self.config
        if obj.kind != "pedestrian":
            return 0.0
        still = (abs(obj.lateral_speed_mps) < cfg.min_lateral_speed_mps
                 and abs(obj.closing_speed_mps - scene.speed_mps) < cfg.min_lateral_speed_mps)
        return cfg.standing_pedestrian_margin_m if still else cfg.pedestrian_margin_m

    def in_sweep(self, scene: Scene, obj: PerceivedObject, steer: float) -> bool:
        """Whether a person stands where the car's body will pass if it keeps this steering.

        In a tight turn the body does not follow the camera's arc: it turns about a point level with the rear
        bumper (the "axle" of highway-env's bicycle model, ``wheelbase_m`` behind the front), and its inner side
        cuts the corner (a person on the kerb side of a right turn, beside or just ahead of the front wheel, is
        outside the corridor yet gets hit). The body sweeps a ring about that point, from the inner side's
        radius to the outer front corner's; a person within it (and the margin) in the first quarter turn
        counts as in our path, even beside the car (remembered after leaving the camera's view)."""
        cfg = self.config
        if obj.kind != "pedestrian" or scene.lane_centre is not None or abs(steer) < cfg.sweep_min_steer:
            return False
        side = 1.0 if steer > 0 else -1.0
        radius = cfg.wheelbase_m / math.tan(abs(steer) * cfg.max_steer_rad)
        front = cfg.wheelbase_m  # the front bumper, ahead of the turning point's level
        dz = obj.distance_m + front - cfg.camera_to_front_m  # the object, ahead of that level
        if dz < 0:
            return False
        # Lateral extent measured towards the turn's side (a left turn mirrored into a right one).
        lo, hi = sorted((side * obj.lateral_left_m, side * obj.lateral_right_m))
        if lo > radius:  # beyond the turning point: the car has already turned a quarter by then
            return False
        far = math.hypot(radius - lo, dz)  # the object's farthest and nearest points from the turning point
        near = math.hypot(max(radius - hi, 0.0), dz)
        ring_in = radius - cfg.half_width_m - cfg.sweep_margin_m
        ring_out = math.hypot(radius + cfg.half_width_m, front) + cfg.sweep_margin_m
        return near <= ring_out and far >= ring_in

    def grazes(self, scene: Scene, obj: PerceivedObject, steer: float) -> float | None:
        """For a still vehicle wholly to one side of the camera axis and of our path's centre whose inner edge
        overlaps the corridor but clears our body's side by ``squeeze_clear_m``: that clearance; else None.

        The corridor keeps a margin beyond the body for what moves; a vehicle standing in that margin (parked a
        little out from the kerb, or read nearer than it is: a depth prior puts the inner edge on the near side)
        leaves room to pass, and drivers squeeze past at walking pace rather than wait behind it for ever."""
        cfg = self.config
        if obj.kind == "pedestrian" or obj.unconfirmed or obj.distance_m <= 0:
            return None
        if abs(obj.lateral_speed_mps) >= cfg.min_lateral_speed_mps or scene.speed_mps - obj.closing_speed_mps >= 0.5:
            return None
        centre = self.path_centre(scene, obj.distance_m, steer, obj.kind)
        if obj.lateral_left_m > max(centre, 0.0):
            gap = obj.lateral_left_m - centre
        elif obj.lateral_right_m < min(centre, 0.0):
            gap = centre - obj.lateral_right_m
        else:
            return None
        clear = gap - cfg.half_width_m
        return clear if clear >= cfg.squeeze_clear_m else None

    def in_path(self, scene: Scene, obj: PerceivedObject, steer: float) -> bool:
        """Whether the object overlaps the corridor at its distance, or a pedestrian walks into it, or a vehicle
        crosses it as the car gets there (``cuts_across``, ``_still_crossing``)."""
        cfg = self.config
        if obj.distance_m <= 0 or obj.distance_m > cfg.lookahead_m:
            return False
        centre = self.path_centre(scene, obj.distance_m, steer, obj.kind)
        half = cfg.path_half_width_m + self.margin(scene, obj)
        lo, hi = centre - half, centre + half
        if obj.lateral_right_m >= lo and obj.lateral_left_m <= hi:
            return True
        if obj.kind != "pedestrian":
            return self.cuts_across(scene, obj, steer, lo, hi) or self._still_crossing(obj, lo, hi)
        if abs(obj.lateral_speed_mps) < cfg.min_lateral_speed_mps:
            return False
        # Entering: moving towards the corridor and reaching it within the horizon.
        shift = obj.lateral_speed_mps * cfg.entering_horizon_s
        if obj.lateral_right_m < lo and shift > 0:
            return obj.lateral_right_m + shift >= lo
        if obj.lateral_left_m > hi and shift < 0:
            return obj.lateral_left_m + shift <= hi
        return False

    def cuts_across(self, scene: Scene, obj: PerceivedObject, steer: float, lo: float, hi: float) -> bool:
        """Whether a vehicle beside the corridor ``lo``..``hi`` (its edges at its distance) crosses it while the
        car gets there: moving sideways towards it (its speed taken ``priority_speed_sigmas`` standard errors
        nearer zero) faster than along our road, it is inside the corridor within ``entering_horizon_s`` and
        during the time the car's front reaches its distance, give or take ``crossing_margin_s`` (one that has
        crossed by then, or enters after the car has passed, is no conflict). Only while the car drives straight:
        its path is then the corridor straight ahead."""
        cfg = self.config
        if obj.unconfirmed or abs(steer) > cfg.junction_turn_steer:
            return False
        lateral = toward_zero(obj.lateral_speed_mps, cfg.priority_speed_sigmas * obj.lateral_speed_sd_mps)
        along = scene.speed_mps - obj.closing_speed_mps  # its speed along our heading
        if abs(lateral) < max(cfg.crossing_min_lateral_speed_mps, abs(along)):
            return False  # not moving across our road (one driving off beside us edges sideways as it goes)
        if obj.lateral_right_m < lo and lateral > 0:  # from the left
            enter, leave = lo - obj.lateral_right_m, hi - obj.lateral_left_m
        elif obj.lateral_left_m > hi and lateral < 0:  # from the right
            enter, leave = obj.lateral_left_m - hi, obj.lateral_right_m - lo
        else:
            return False
        t_in, t_out = enter / abs(lateral), leave / abs(lateral)
        gap = max(obj.distance_m - cfg.camera_to_front_m, 0.0)
        t_us = gap / max(scene.speed_mps, cfg.crossing_min_lateral_speed_mps)
        crossing = (t_in <= cfg.entering_horizon_s and t_in <= t_us + cfg.crossing_margin_s
                    and t_out >= t_us - cfg.crossing_margin_s)
        if crossing:
            self._crossing[obj.track_id] = cfg.crossing_hold_s
        return crossing

    def _still_crossing(self, obj: PerceivedObject, lo: float, hi: float) -> bool:
        """A vehicle judged crossing our path within ``crossing_hold_s``, beside the corridor ``lo``..``hi`` and
        not yet wholly past its far side, stays in our path: a car on its way across does not stop, though its
        sideways speed, read from a box that grows and is cut as it nears, may drop out of one frame's reading."""
        if obj.track_id not in self._crossing:
            return False
        return ((obj.lateral_left_m > hi and obj.lateral_speed_mps <= 0)
                or (obj.lateral_right_m < lo and obj.lateral_speed_mps >= 0))

    # ------------------------------------------------------------------ lights and stop lines
    def _update_light(self, scene: Scene, dt: float) -> None:
        cfg = self.config
        seen = scene.light if scene.light in LIGHT_STATES else None
        self._light_age_s += dt
        if seen is not None and scene.light_distance_m is not None and self.stop_line is not None:
            # Where the car may stop and still see the head (it turns green while the car waits): the head stands
            # (camera distance - bumper distance to the line) past the line, which travel does not change.
            # Only a head at the line (a near-side post) is kept in view: one across the junction is seen anyway.
            head_from_line = scene.light_distance_m - self.stop_line
            near_side = head_from_line - cfg.camera_to_front_m <= cfg.near_side_head_m
            self._view_back_m = max(0.0, scene.light_in_view_m - head_from_line) if near_side else 0.0
        if seen is None:
            self._light_unseen_s += dt
            self._light_count = 0
            memory = cfg.red_memory_s if self.light_state == "red" else cfg.light_memory_s
            # A head beside the line leaves the picture when the car stops nearer than it can be seen from (braking
            # for a light seen late): a red is kept until it has surely ended (the longest red since it was seen), a
            # yellow stopped for until the red that follows it has (the yellow and the longest red).
            stopping = self.light_state == "red" or (self.light_state == "yellow" and self._yellow_go is False)
            if stopping and self._view_back_m > 0.0 and self.stop_line is not None:
                lasts = self.road.longest_red_s + (self.road.yellow_s if self.light_state == "yellow" else 0.0)
                memory = max(memory, lasts - (self._light_age_s - self._light_unseen_s))
            if self._light_unseen_s > memory:
                self.light_state, self._light_candidate, self._yellow_go = None, None, None
                if not self.line.stop_line_measured:
                    # A line inferred from that light has nothing left to stand on: passing it would put the car
                    # "in the junction" short of the real one, whose bar and light it would then ignore.
                    self.line.stop_line = None
            return
        self._light_unseen_s = 0.0
        if seen == self._light_candidate:
            self._light_count += 1
        else:
            self._light_candidate, self._light_count = seen, 1
        # a red is taken at once whatever it follows; a state against the cycle that lets the car go is suspect, and
        # so is a green straight after a red only just taken (a phase lasts seconds)
        against_cycle = self.light_state not in (None, seen) and NEXT_IN_CYCLE[self.light_state] != seen
        too_soon = self.light_state == "red" and self._light_age_s < cfg.light_min_phase_s
        suspect = seen != "red" and (against_cycle or (seen == "green" and too_soon))
        if self._light_count >= (cfg.light_out_of_cycle_frames if suspect else cfg.light_confirm_frames):
            if seen == "green":
                self._yellow_go = None  # a new cycle: the next yellow is decided afresh
            if seen != self.light_state:
                self._light_age_s = 0.0
            self.light_state = seen

    def _light_constraint(self, speed: float, turning: bool = False) -> Constraint | None:
        """The stop constraint of a red or yellow light, if it applies; ``self.note`` says why not when it does not."""
        cfg = self.config
        self.note = ""
        state = self.light_state if self.ignore_light_m <= 0 else None
        if state not in ("red", "yellow"):
            return None
        if self.stop_line is None:
            if state == "red":  # a red light but no stop line yet: approach slowly until the bar is found
                return Constraint("red light, stop line not seen: slow approach", math.inf,
                                  cfg.red_no_line_speed_mps, 0.0, 0.0)
            self.note = "yellow light, stop line not seen"
            return None
        # Whether the car can stop for the light is judged by the line, the legal stop. Where it stops: before the
        # line, far enough back that our light stays in the picture (it turns green while the car waits), braking
        # harder than is comfortable if need be, unless the car is past that point or not even the brake stops it
        # there (then at the line).
        line_gap = self.stop_line - cfg.stop_line_target_m
        need = stop_decel_mps2(speed, line_gap)  # deceleration to stop at the line
        back = self.stop_line - self._view_back_m
        fits = stop_decel_mps2(speed, back) <= 0.9 * cfg.max_brake_mps2
        gap = back if -1.0 < back < line_gap and fits else line_gap  # the stop point
        if state == "yellow":
            if self._yellow_go is None:
                # Turning, the car slows for the turn at or past the line anyway, and would cross it on red:
                # it stops unless even the full brake cannot, or the line is less than ``yellow_commit_s`` away at
                # the turn speed, or at its own speed when slower (a car standing at the line stays there).
                commit_m = min(speed, cfg.junction_turn_speed_mps) * cfg.yellow_commit_s
                self._yellow_go = (need > 0.9 * cfg.max_brake_mps2 or (speed > STOP_SPEED_MPS and line_gap < commit_m)
                                   if turning else need > cfg.comfortable_brake_mps2)
            if self._yellow_go:
                self.note = "yellow light: too close to stop comfortably, going on"
                return None
            return Constraint(f"yellow light: stop {self.stop_line:.1f} m ahead", gap, 0.0, cfg.stop_line_min_gap_m, 0.5)
        if (self._yellow_go and need > cfg.comfortable_brake_mps2) or need > 0.9 * cfg.max_brake_mps2:
            self.note = "red light: too close to stop, clearing the junction"  # braking would stop inside it
            return None
        return Constraint(f"red light: stop {self.stop_line:.1f} m ahead", gap, 0.0, cfg.stop_line_min_gap_m, 0.5)

    # ------------------------------------------------------------------ signs and bends
    def _sign_constraint(self, scene: Scene, speed: float, steer: float) -> Constraint | None:
        """The stop or give-way a seen sign asks at the next line (``agent.decision.signs``): a full stop, then
        go once nothing with priority is near and nobody is on the crossing; a give-way line is approached at
        ``YIELD_APPROACH_MPS`` (a speed one can stop from) and stopped at only for such traffic."""
        cfg, signs = self.config, self.signs
        gap = signs.line_gap(self.stop_line)
        if signs.control is None:
            return None
        what = "stop sign" if signs.control == "stop" else "yield"
        if gap is None:
            return Constraint(f"{what}, stop line not seen: slow approach", math.inf, cfg.red_no_line_speed_mps, 0.0, 0.0)
        point = gap - cfg.stop_line_target_m
        if signs.control == "stop" and not signs.note_speed(speed, gap):
            return Constraint(f"stop sign: full stop {gap:.1f} m ahead", point, 0.0, cfg.stop_line_min_gap_m, 0.5)
        wait = self._priority_traffic(scene, gap, steer)
        if wait:
            need = stop_decel_mps2(speed, point)
            if signs.control == "yield" and need > 0.9 * cfg.max_brake_mps2:
                self.note = f"yield: {wait}, too close to stop, going on"
                return None
            return Constraint(f"{what}: waiting, {wait}", point, 0.0, cfg.stop_line_min_gap_m, 0.5)
        if signs.control == "yield":
            # The speed is a cap (IDM runs a little above it while slowing): aim to be at the approach speed
            # yield_settle_m before the point.
            cap = math.sqrt(YIELD_APPROACH_MPS ** 2 + 2.0 * CURVE_BRAKE_MPS2 * max(point - cfg.yield_settle_m, 0.0))
            return Constraint(f"yield: {min(cap, self._cruise):.1f} m/s to the line, looking", math.inf, cap, 0.0, 0.0)
        self.note = "stop sign: full stop made, clear: going"
        return None

    def _edge_constraint(self, scene: Scene, speed: float, dt: float) -> Constraint | None:
        """Past a stop or give-way line, towards where the cross street is seen (``SignControl.edging_m``): slow
        enough to stop there; once the corner cameras see priority traffic, stopped where comfortable braking
        does (that place then ends the edging), and done once they have looked ``edge_looks`` frames in a row there
        and seen none (module docstring): after a vehicle with priority, both sides are looked at afresh."""
        cfg, signs = self.config, self.signs
        ahead = signs.edging_m
        if ahead is None:
            return None
        if scene.cross_traffic:
            self._edge_s, self._edge_frames = 0.0, 0
            # Seen: no need to edge on (farther on, a car turning out of the cross street needs the room); stop
            # where comfortable braking does.
            stop_m = min(max(ahead, 0.0), speed * speed / (2.0 * cfg.comfortable_brake_mps2))
            signs.edging_m = stop_m
            return Constraint(f"give way: {scene.cross_traffic}, waiting where it is seen",
                              stop_m + cfg.stop_line_min_gap_m, 0.0, cfg.stop_line_min_gap_m, 0.5)
        if ahead > cfg.edge_arrived_m:
            self._edge_s, self._edge_frames = 0.0, 0
        else:
            self._edge_s += dt
            self._edge_frames += 1
            settled = not scene.cross_unknown or self._edge_s >= cfg.edge_settle_s
            if self._edge_frames >= cfg.edge_looks and settled:
                signs.edging_m = None
                self.note = "give way: the cross street is clear, going"
                return None
        cap = math.sqrt(cfg.edge_speed_mps ** 2 + 2.0 * CURVE_BRAKE_MPS2 * max(ahead, 0.0))
        return Constraint(f"give way: {min(cap, self._cruise):.1f} m/s to where the cross street is seen, looking",
                          math.inf, cap, 0.0, 0.0)

    def _priority_traffic(self, scene: Scene, gap: float, steer: float) -> str:
        """What forbids going from a stop or give-way line now ("" when nothing): a vehicle near that moves and
        is not driving away ahead of us (crossing, or coming towards us), or a person on the crossing beyond the
        line (across the road: our lanes and the oncoming ones). Only what the detector confirms counts."""
        cfg = self.config
        if scene.cross_traffic:
            return scene.cross_traffic
        line_cam = gap + cfg.camera_to_front_m
        lanes = self.signs.lanes_each_way or 2
        left = -(2 * lanes - 0.5) * self.road.lane_width_m  # the road's far kerb, from our lane's centre
        right = 0.5 * self.road.lane_width_m + 0.5
        for o in scene.objects:
            if o.unconfirmed:
                continue
            if o.kind == "pedestrian":
                if (o.distance_m <= line_cam + cfg.crossing_depth_m and o.lateral_right_m >= left
                        and o.lateral_left_m <= right):
                    return f"pedestrian #{o.track_id} on the crossing"
                continue
            along = scene.speed_mps - o.closing_speed_mps  # its speed along our heading (positive: away)
            lateral = o.lateral_speed_mps
            k = cfg.priority_speed_sigmas
            if math.hypot(toward_zero(along, k * o.closing_speed_sd_mps),
                          toward_zero(lateral, k * o.lateral_speed_sd_mps)) < cfg.priority_min_speed_mps:
                continue  # standing, or its motion within the readings' scatter
            if along > 0 and abs(lateral) < along and self.overlaps(scene, o, steer):
                continue  # driving away ahead of us, in our lane
            if math.hypot(o.distance_m, o.lateral_m) <= cfg.priority_near_m:
                return f"{o.kind} #{o.track_id} with priority {o.distance_m:.0f} m ahead"
        return ""

    def _oncoming_constraint(self, scene: Scene, speed: float) -> Constraint | None:
        """Before an unprotected left turn: a stop at the line (or, past it or with none once the turn is under way,
        where the car is) while oncoming traffic would reach us within ``oncoming_horizon_s`` (module docstring)."""
        cfg = self.config
        if not scene.turn_left or -scene.turned_rad > math.radians(cfg.oncoming_commit_deg):
            return None
        line = self.stop_line
        if line is not None and line <= cfg.oncoming_line_m:
            gap = line - cfg.stop_line_target_m
        elif line is None and (self.line.in_junction or (scene.lane_centre is None
                                                         and abs(self.last_steer) > cfg.junction_turn_steer)):
            gap = speed * speed / (2.0 * cfg.comfortable_brake_mps2) + cfg.stop_line_min_gap_m  # stop where it is
        else:
            return None
        w = self.road.lane_width_m
        far = -((self.signs.lanes_each_way or 2) + 0.5) * w - 1.0  # beyond the oncoming lanes' far side
        for o in scene.objects:
            if o.kind == "pedestrian" or o.unconfirmed:
                continue
            x, z = in_approach_frame(o.lateral_m, o.distance_m, scene.turned_rad)
            approach = o.closing_speed_mps - scene.speed_mps  # its own speed towards us
            if not far <= x <= -0.5 * w or approach < cfg.priority_min_speed_mps or abs(o.lateral_speed_mps) > approach:
                continue
            if z / approach < cfg.oncoming_horizon_s:
                return Constraint(f"left turn: waiting for oncoming {o.kind} #{o.track_id}, {z / approach:.1f} s away",
                                  gap, 0.0, cfg.stop_line_min_gap_m, 0.5)
        return None

    def _bend_cap(self, scene: Scene, dt: float) -> float:
        """The speed a bend ahead allows, sqrt(a_lat / curvature): the lane fit's curvature (``2a`` of
        x = a z^2 + b z + c, where it reaches ``bend_min_range_m`` or farther), smoothed, taken at what it grows
        to in ``bend_horizon_s`` while it grows (the fit sees more of the bend as the car nears it)."""
        cfg = self.config
        kappa = 0.0
        if scene.lane_centre is not None and scene.lane_range_m >= cfg.bend_min_range_m:
            kappa = abs(2.0 * float(scene.lane_centre[0]))
        before = self.bend_curvature
        self.bend_curvature += cfg.bend_smoothing * (kappa - before)
        rate = (self.bend_curvature - before) / dt if dt > 0 else 0.0
        self._bend_rate += cfg.bend_smoothing * (rate - self._bend_rate)
        ahead = self.bend_curvature + max(self._bend_rate, 0.0) * cfg.bend_horizon_s
        return math.sqrt(cfg.lateral_accel_mps2 / ahead) if ahead > 1e-6 else math.inf

    # ------------------------------------------------------------------ the step
    def step(self, scene: Scene, pilot_steer: float, dt: float) -> Decision:
        cfg = self.config
        speed = max(0.0, float(scene.speed_mps))
        steer = float(np.clip(pilot_steer, -1.0, 1.0))
        if cfg.steer_rate_per_s > 0:
            step = cfg.steer_rate_per_s * dt
            steer = min(self.last_steer + step, max(self.last_steer - step, steer))
        self.last_steer = steer
        self._update_light(scene, dt)
        self.signs.update(scene.signs, scene.lanes_each_way, speed, dt, scene.turned_rad)
        if self.line.update(scene.speed_mps, scene.stop_line_m, scene.light, scene.light_distance_m, dt,
                            self._bar_hidden(scene, steer)):
            self.light_state, self._light_candidate, self._yellow_go = None, None, None  # in the junction
            self._view_back_m = 0.0
            self.signs.entered(scene.cross_street_m)
        elif self.signs.passed(self.stop_line):
            self.signs.entered(scene.cross_street_m)

        limit_why, limit = self.signs.limit()
        self._cruise = min(cfg.speed_limit_mps, limit)  # the cruise speed under the limit that applies
        curvature = abs(math.tan(steer * cfg.max_steer_rad)) / cfg.wheelbase_m  # of the arc being steered
        target = min(self._cruise, math.sqrt(cfg.lateral_accel_mps2 / max(curvature, 1e-6)))
        constraints: list[Constraint] = []
        in_path: list[int] = []
        ids: dict[int, int] = {}  # constraint index -> track id
        caps = list(scene.speed_caps)  # speed limits (reason, m/s): no point to stop at
        bend = self._bend_cap(scene, dt)
        if bend < self._cruise:
            caps.append((f"bend ahead: {bend:.1f} m/s", bend))
        turn = self._turn_cap(scene, steer)
        if turn < self._cruise:
            caps.insert(0, (f"turning at a junction: {turn:.1f} m/s", turn))
        constraints += [self._cap(why, cap, speed, target) for why, cap in caps]
        light = self._light_constraint(speed, scene.turning)
        note = self.note
        sign = self._sign_constraint(scene, speed, steer)
        edge = self._edge_constraint(scene, speed, dt)
        self.note = note or self.note
        for c in (light, sign, edge, self._oncoming_constraint(scene, speed)):
            if c is None:
                continue
            if math.isinf(c.gap_m):  # a speed cap, not a point to stop at
                c.accel_mps2 = self._idm(speed, min(target, c.speed_mps), None, 0.0, 0.0, 0.0)
            constraints.append(c)
        creep = self.unconfirmed_clock.held_s >= cfg.unconfirmed_hold_s
        self._crossing = {k: v - dt for k, v in self._crossing.items() if v > dt}
        for obj in scene.objects:
            swept = self.in_sweep(scene, obj, steer)  # a person where the body will pass, corridor or not
            if not swept and not self.in_path(scene, obj, steer):
                continue
            in_path.append(obj.track_id)
            gap = max(obj.distance_m - cfg.camera_to_front_m, 0.0)
            if obj.kind == "pedestrian":
                what = ("in our path" if self.overlaps(scene, obj, steer) and obj.distance_m > 0
                        else "in the turn's sweep" if swept else "entering our path")
                if obj.unconfirmed and (creep or obj.stale):
                    c = self._cap(f"pedestrian #{obj.track_id} {what} not confirmed for "
                                  f"{self.unconfirmed_clock.held_s:.0f} s: creeping at {cfg.creep_speed_mps:.1f} m/s",
                                  cfg.creep_speed_mps, speed, target, unconfirmed=True)
                else:
                    c = Constraint(f"pedestrian #{obj.track_id} {what} at {gap:.1f} m: stop", gap, 0.0,
                                   cfg.pedestrian_min_gap_m, 0.5, unconfirmed=obj.unconfirmed)
            else:
                lead_speed = max(0.0, speed - obj.closing_speed_mps)
                verb = "stopped" if lead_speed < 0.5 else "following"
                clear = self.grazes(scene, obj, steer)
                if clear is not None and self.grazed_clock.held_s >= cfg.squeeze_after_s:
                    c = self._cap(f"{obj.kind} #{obj.track_id} standing {clear:.1f} m clear of our side: creeping "
                                  f"past at {cfg.creep_speed_mps:.1f} m/s", cfg.creep_speed_mps, speed, target,
                                  grazing=True)
                else:
                    what = (f"ahead at {gap:.1f} m: {verb}" if self.overlaps(scene, obj, steer)
                            else f"crossing our path at {gap:.1f} m: stop")
                    c = Constraint(f"{obj.kind} #{obj.track_id} {what}", gap, lead_speed,
                                   cfg.lead_min_gap_m, cfg.headway_s, grazing=clear is not None)
            ids[len(constraints)] = obj.track_id
            constraints.append(c)

        accel, reason, governing = self._idm(speed, target, None, 0.0, 0.0, 0.0), "cruise", None
        holding = False
        for k, c in enumerate(constraints):
            if not math.isinf(c.gap_m):
                c.accel_mps2 = self._idm(speed, target, c.gap_m, speed - c.speed_mps, c.min_gap_m, c.headway_s)
                room = c.gap_m - c.min_gap_m
                c.hard = c.speed_mps < speed and stop_decel_mps2(speed, room) > cfg.comfortable_brake_mps2
                if room < cfg.hold_margin_m and c.speed_mps < 0.5 and speed < 1.0:
                    c.hold = True  # IDM creeps towards a standstill: near the point, brake and stay
                    c.accel_mps2 = min(c.accel_mps2, -cfg.comfortable_brake_mps2)
            if c.accel_mps2 < accel:
                accel, reason, governing = c.accel_mps2, c.reason, k
        if governing is not None and not constraints[governing].hard:
            # A speed cap (the turn) may ask for more than a stop point does, but only comfortable braking;
            # a stop point that comfort cannot meet still gets the brake it needs, and gives the reason.
            urgent = [k for k, c in enumerate(constraints) if c.hard and c.accel_mps2 < -cfg.comfortable_brake_mps2]
            if urgent:
                governing = min(urgent, key=lambda k: constraints[k].accel_mps2)
                reason = constraints[governing].reason
        hard = governing is not None and constraints[governing].hard
        holding = governing is not None and constraints[governing].hold
        standing_for = constraints[governing] if governing is not None and speed < cfg.standstill_mps else None
        self.unconfirmed_clock.update(any(c.unconfirmed for c in constraints),
                                      standing_for is not None and standing_for.unconfirmed, dt, cfg.unconfirmed_reset_s)
        self.grazed_clock.update(any(c.grazing for c in constraints),
                                 standing_for is not None and standing_for.grazing, dt, cfg.unconfirmed_reset_s)
        if holding:
            reason += " (holding)"
        if accel > 0:  # gentle: capped, and rising at most jerk x dt per frame
            accel = min(accel, cfg.max_accel_mps2, max(self.last_accel, 0.0) + cfg.jerk_mps3 * dt)
        accel = max(accel, -(cfg.max_brake_mps2 if hard else cfg.comfortable_brake_mps2))
        if hard and accel < -cfg.comfortable_brake_mps2:
            reason += " (hard brake)"
        if reason == "cruise" and self.note:
            reason = self.note
        elif reason == "cruise" and target < 0.9 * self._cruise:
            reason = f"cruise, {target:.1f} m/s in the turn"
        elif reason == "cruise" and (self._cruise < cfg.speed_limit_mps or self.signs.limit_kmh is not None):
            reason = f"cruise, {limit_why}"
        self.last_accel = accel
        throttle = accel / self.vehicle_accel if accel >= 0 else accel / self.vehicle_brake
        return Decision(steer, float(np.clip(throttle, -1.0, 1.0)), float(accel), float(target), float(pilot_steer),
                        reason, constraints, self.light_state if self.ignore_light_m <= 0 else None,
                        self.stop_line, in_path, ids.get(governing) if governing is not None else None, holding)

    def _turn_cap(self, scene: Scene, steer: float) -> float:
        """The speed of a commanded turn: on the junction's arc, its curve speed, sqrt(``lateral_accel_mps2`` x radius),
        where the road turned into has placed it (``Scene.arc_radius_m``), else ``junction_turn_speed_mps``; before
        it, where the arc is planned, at most what braking at ``turn_approach_brake_mps2`` brings down to that by
        the arc's start (the autopilot's curve-speed profile). With no arc planned, the turn speed once the lane
        lines end or the car steers into the turn."""
        cfg = self.config
        if not scene.turning:
            return math.inf
        if scene.arc_ahead_m is not None:  # (the speed follows its cap a moment late: at the turn speed a second early)
            turn = cfg.junction_turn_speed_mps
            if scene.arc_radius_m is not None:  # an arc placed by what the camera sees is driven at its curve speed
                turn = max(turn, math.sqrt(cfg.lateral_accel_mps2 * scene.arc_radius_m))
            room = scene.arc_ahead_m - turn * cfg.turn_approach_lead_s
            return math.sqrt(turn ** 2 + 2.0 * cfg.turn_approach_brake_mps2 * max(0.0, room))
        if scene.lane_centre is None or abs(steer) > cfg.junction_turn_steer:
            return cfg.junction_turn_speed_mps
        return math.inf

    def _cap(self, reason: str, cap_mps: float, speed: float, target: float, unconfirmed: bool = False,
             grazing: bool = False) -> Constraint:
        """A speed cap (no point to stop at): IDM towards the lower of the cap and the target speed."""
        return Constraint(reason, math.inf, cap_mps, 0.0, 0.0, self._idm(speed, min(target, cap_mps), None, 0.0, 0.0,
                                                                          0.0), unconfirmed=unconfirmed, grazing=grazing)

    def _idm(self, speed: float, target: float, gap: float | None, closing: float, min_gap: float,
             headway: float) -> float:
        """Intelligent Driver Model acceleration towards ``target`` with an optional bumper ``gap``."""
        cfg = self.config
        return idm_acceleration(speed, target, gap, closing, a_max=cfg.idm_a_mps2, b=cfg.idm_b_mps2,
                                min_gap_m=min_gap, headway_s=headway, delta=cfg.idm_delta)
