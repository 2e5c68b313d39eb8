"""Steering through a junction, where there are no lines to follow.

Going straight, the car holds the approach lane's heading and its place across it (``Odometry``); where the design
spreads, once the far side's centre line is read, the lane beside it instead (a winding street's far side is
shifted). Turning, it steers its centre, the point whose distance from the lane the safety driver judges, along the
road design's turn (a rear axle pursuing the arc would put the centre outside it by a quarter of the wheelbase
squared over the arc's diameter, 0.2 m on a 12 m arc): straight on past the stop bar, then an arc into the same
lane of the road turned into (with no radius in the design, the quarter circle from the bar's far edge). The turn
is placed by the stop bar tracked by the controller (``StopLineTrack``) and the approach lane measured before it.
How far the lane turned into lies beyond the bar is the design's setback (a prior, ``sim.spec.RoadDesign``),
corrected by where the zebra beyond the bar ends: the zebra's far edge lies a cross
street's half width and a kerb gap before the junction's centre, which spreads less between junctions than the
setback does. The lane offset is the lane width the lane finder measured, where the design lets widths differ. With the zebra
measured, the lane turned into is placed from its far edge instead (the zebra lies at the cross street's kerb): by
the design's reach for the cross street's lanes each way, a count not seen before the turn, so expected over its
odds at the kind of junction the car sees (``RoadDesign.two_lane_share``: who stops enters a larger street).
Where the design's numbers spread, a turn planned so still misses the lane turned into by a metre or two when the
cross street's lane count was guessed wrong. So once the road turned into is in view, it is read
(``agent.perception.exit_line``): through the corner camera on the turn's side from the arc's start (``exit_look``),
through the forward camera from 20 degrees of a right turn, 50 of a left turn (``exit_expected_rad``). Its centre
line places its inner lane half a lane width to the line's right in the direction of travel, whatever the count,
and the line's direction, weighed against
the zebra's by how much of the line is in view, gives the turn's angle (a line seen short is far off, and its
direction, carried back across the junction, would misplace the lane by a metre or more). A left turn goes into that
lane; a right turn into the kerb lane, as many lanes short of it as the street has lanes beyond the first: the line's
distance beyond the zebra tells the count a little, the white line a lane to its right (solid beside a single lane,
dashed between two) much more (``exit_odds``), kept within reach of the single lane while that count is in doubt
(``sim.spec.hedged_reach``: a two-lane kerb lane is off the road on a single-lane street, the single lane's place is
the inner lane on a two-lane one). A right turn keeps its lane counted from the kerb, as the town's
connectors do (``sim.spec.right_turn_lanes_from_kerb``): from the inner lane of two (a lane change before the turn
held) it goes into the inner lane, whatever the count, on an arc a lane wider than the kerb lane's. The arc is
re-placed on that lane and leads the whole turn; once the car is on it, a reading moves the arc's end and not where
it began (an arc begun later, as a tighter radius would have it, lies beyond a car already turning, which steers
back out and then cannot follow it round), unless the car has turned at most ``exit_restart_max_deg``: it then goes
on straight to the later start (the arc's start is committed as the car reaches it, often before the road turned
into is read, and from the priors it lies metres short when the cross street's lane count was guessed wrong).
Where the road turned into is never read, the arc leads only until the car faces that road (``turn_handover_deg``)
and PilotNet, which sees it, finishes the turn. An exact design's arc leads to the end.
Where junctions are not square, the arc turns by the cross street's angle, read from the zebra beyond the bar (its
edges run along the cross street), into the lane whose centre line crosses the approach lane's where the road
design's reach puts it.
Once the road turned into places the arc and leaves no lane count in doubt, the arc's radius is the controller's
too (``arc_radius_m``), which drives the arc at its curve speed; while a count is in doubt, at the turn speed, so
that the reading settles before the car reaches the arc's start; where the road turned into is not read (an exact
design), at the turn speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from towndrive.agent.decision.odometry import Odometry
from towndrive.agent.decision.priors import fused, junction_widening_m
from towndrive.agent.decision.stop_line_track import StopLineTrack, camera_to_bar_m
from towndrive.agent.perception.exit_line import ExitLine
from towndrive.agent.perception.stop_line import StopLine
from towndrive.sim.spec import ROAD, VEHICLE, RoadDesign, hedged_reach, right_turn_lanes_from_kerb


@lru_cache(maxsize=64)
def turn_path(command: int, reach_m: float, bar_depth_m: float = ROAD.stop_bar_depth_m,
              radius_m: float | None = None, step_m: float = 0.2, angle_deg: float = 90.0) -> tuple[np.ndarray, float]:
    """A junction turn in the approach frame (x along the approach lane from its stop bar's near edge, y to the
    right): 30 m of approach, straight on past the bar's far edge (``bar_depth_m`` on), an arc into the lane of the
    road turned into, whose centre line crosses the approach lane's ``reach_m`` beyond the bar's far edge at
    ``angle_deg`` (the heading change of the turn), then 30 m of that road; and the path length at which the arc
    ends. With no ``radius_m`` the arc is the quarter circle from the bar with that radius (``sim/town.py``,
    classic junction connectors); with one (at most what fits), the arc tangent to both lanes, after a straight
    lead-in (styled towns' fillets)."""
    half = math.radians(angle_deg) / 2
    radius, x0 = arc_placement(reach_m, bar_depth_m, radius_m, angle_deg)
    side = 1.0 if command == 2 else -1.0
    before = np.arange(x0 - 30.0, x0, step_m)
    approach = np.stack([before, np.zeros(len(before))], axis=1)
    theta = np.arange(0.0, 2 * half, step_m / radius)
    arc = np.stack([x0 + radius * np.sin(theta), side * (radius - radius * np.cos(theta))], axis=1)
    end = np.array([x0 + radius * math.sin(2 * half), side * (radius - radius * math.cos(2 * half))])
    along = np.arange(0.0, 30.0, step_m)
    exit_ = end + along[:, None] * np.array([math.cos(2 * half), side * math.sin(2 * half)])
    path = np.concatenate([approach, arc, exit_])
    path.setflags(write=False)
    return path, (len(approach) + len(arc)) * step_m


def arc_placement(reach_m: float, bar_depth_m: float, radius_m: float | None, angle_deg: float) -> tuple[float, float]:
    """``turn_path``'s arc: its radius (``radius_m``, at most the largest whose arc starts at the bar's far edge;
    that one with none) and where along the approach it begins."""
    half = math.radians(angle_deg) / 2
    fits = reach_m / math.tan(half)
    radius = fits if radius_m is None else min(radius_m, fits)
    return radius, bar_depth_m + reach_m - radius * math.tan(half)


def arc_from_pose(command: int, centre: tuple[float, float], heading_rad: float, reach_m: float, bar_depth_m: float,
                  radius_m: float, angle_deg: float, step_m: float = 0.2,
                  back_m: float = 5.0) -> tuple[np.ndarray, float, float, float] | None:
    """The rest of a turn from where the car is (``turn_path``'s frame: its centre and heading from the approach
    lane): straight on along its heading, then an arc of ``radius_m`` onto the lane turned into (whose centre line
    crosses the approach lane's ``reach_m`` beyond the bar's far edge at ``angle_deg``), tighter where there is no
    longer room for that radius (never under the car's smallest), then 30 m of that lane; ``back_m`` of the
    heading's line behind the car first. Returns the path, the path length at which its arc begins and ends, and
    its radius; None when the car already heads along the lane turned into, or past it."""
    side = 1.0 if command == 2 else -1.0
    x, y, h = centre[0], side * centre[1], side * heading_rad  # the turn taken to the right
    th = math.radians(angle_deg)
    rem = th - h
    if rem <= math.radians(1.0):
        return None
    # where the car's line of travel meets the lane turned into's centre line, through (bar depth + reach, 0)
    a = np.array([[math.cos(h), -math.cos(th)], [math.sin(h), -math.sin(th)]])
    if abs(np.linalg.det(a)) < 1e-9:
        return None
    t = float(np.linalg.solve(a, np.array([bar_depth_m + reach_m - x, -y]))[0])
    if t <= 0.0:
        return None
    tan_half = math.tan(rem / 2)
    radius = radius_m if radius_m * tan_half <= t else max(VEHICLE.min_turn_radius_m, t / tan_half)
    lead = max(0.0, t - radius * tan_half)
    u = np.array([math.cos(h), math.sin(h)])
    before = np.array([x, y]) + np.arange(-back_m, lead, step_m)[:, None] * u
    start = np.array([x, y]) + lead * u
    middle = start + radius * np.array([-math.sin(h), math.cos(h)])
    phi = h + np.arange(0.0, rem, step_m / radius)
    arc = middle + radius * np.stack([np.sin(phi), -np.cos(phi)], axis=1)
    end = middle + radius * np.array([math.sin(th), -math.cos(th)])
    exit_ = end + np.arange(0.0, 30.0, step_m)[:, None] * np.array([math.cos(th), math.sin(th)])
    path = np.concatenate([before, arc, exit_]) * np.array([1.0, side])
    return path, len(before) * step_m, (len(before) + len(arc)) * step_m, radius


def _right_of(yaw: float) -> np.ndarray:
    """The unit vector to the right of a heading (the odometry frame's y points right of its x)."""
    return np.array([-math.sin(yaw), math.cos(yaw)])


def _across_along(d: np.ndarray, yaw: float) -> tuple[float, float]:
    """A displacement of the odometry frame to the right of a heading and along it."""
    c, s = math.cos(yaw), math.sin(yaw)
    return float(d[0] * -s + d[1] * c), float(d[0] * c + d[1] * s)


MAX_SLIP_RAD = math.atan(math.tan(VEHICLE.max_steer_rad) / 2)  # the bicycle model's centre at full lock
ZEBRA_SD_M = 0.4  # spread of one junction's zebra readings (a band's edge at 5-15 m, a row of the view or two)
EXIT_SD_M = 0.4  # spread of the road turned into's reach as read in the turn (bench/turn_arc.py, single-lane streets)
LANE_WIDTH_SD_M = 0.15  # spread of the lane finder's width once both lines were seen
# The direction of the road turned into's centre line as read spreads with how little of it is in view (far off,
# its paint smears along the line of sight and pulls a short line's direction towards it): about this many
# degrees times square metres over its length squared, and no less than the floor (bench/turn_arc.py: 10 degrees
# at 3.5 m, 3 at 7 m, 1.5 at 11 m, 0.4 beyond 17 m). The cross street's angle read from the zebra before the turn
# spreads ``ZEBRA_ANGLE_SD_DEG``; unread, the junction's angle is anywhere within ``skew_max_deg`` of square.
EXIT_ANGLE_SD_DEG_M2 = 150.0
EXIT_ANGLE_SD_FLOOR_DEG = 0.4
ZEBRA_ANGLE_SD_DEG = 1.5
# The white line a lane right of the road turned into's centre line (``ExitLine.divider_fill``): painted over at
# least this share of its length seen, it is a single lane's solid edge line, else the dashed divider of two lanes
# (bench/turn_arc.py: 0.7 or more in 94-100 % of frames beside single lanes, in none beside two, whose 95th
# percentile is 0.56); the median of a turn's readings is taken as right this often.
DIVIDER_SOLID_FILL = 0.7
DIVIDER_RIGHT = 0.95
# The far side's lane as read going straight (``JunctionGuidance.far_lane``), across and turned: on rendered suburb
# crossings at noon the line lay within 0.07 m and 0.8 degrees of the town's; at dusk and at night it is read from
# paint that smears and takes the light's hue, and a line other than the centre line can pass (a metre off).
FAR_SD_M = 0.3
FAR_ANGLE_SD_DEG = 1.5


@dataclass(frozen=True)
class JunctionRules:
    junction_hold_m: float = 20.0  # going straight, this far past the stop line the car holds the approach lane
    hold_heading_gain: float = 1.5  # steer per radian of heading error (about a 1 s time constant at 5 m/s)
    hold_offset_gain: float = 0.3  # steer per metre of dead-reckoned offset from the approach lane's centre
    hold_max_steer: float = 0.3
    turn_guidance: bool = True  # commanded turns inside a junction follow the turn arc
    turn_lookahead_m: float = 3.5  # the arc takes over with the rear axle this + s x speed before the bar's far edge
    turn_lookahead_s: float = 0.4
    turn_offset_gain: float = 0.5  # the car's centre heads back onto the arc at atan(this x its offset in metres)
    turn_bar_seen_m: float = 12.0  # a turn is placed only by a stop bar this near (seen, or tracked from a reading)
    # ... and only while the car still runs along the approach lane: turned farther than this from it, a "bar" ahead
    # is paint across the road being turned into (its zebra, a stop line of another arm), not the approach's bar
    place_max_turned_deg: float = 20.0
    # With a design whose numbers spread, the arc (dead-reckoned from priors) leads the turn only this far; the
    # camera's steering finishes it, facing the road turned into. An exact design's arc leads to the end.
    turn_handover_deg: float = 60.0
    # The cross street's angle, from the zebra beyond the bar (``Zebra.tilt``): read only with the bar this near
    # (the stripes' ends are sharp), taken as the median of at least this many readings, within this of square.
    skew_bar_max_m: float = 7.0
    skew_min_readings: int = 3
    skew_max_deg: float = 20.0
    # The road turned into, read in the turn (``agent.perception.exit_line``): looked for while the car has turned
    # between these (it is in view, and the arc still leads), taken as the median of the last readings once there
    # are this many; a reading this far from the reach planned before the turn is something else.
    exit_min_turned_deg: float = 20.0
    exit_max_turned_deg: float = 80.0
    exit_corner_max_turned_deg: float = 45.0  # the corner camera looks down the road turned into up to this far round
    # A reading of the road turned into that puts the arc's start farther on moves it there while the car has
    # turned at most this (it goes on straight to it; farther round, it could not follow the later arc)
    exit_restart_max_deg: float = 10.0
    # Farther round, a reading that would stretch the arc from where it began to a radius this much larger than the
    # design's re-places the rest of the turn from the car's pose instead (``arc_from_pose``); a re-placed turn is
    # re-placed again when the reach read moves this far
    replace_radius_m: float = 1.0
    replace_reach_m: float = 0.3
    exit_min_readings: int = 3
    exit_last_readings: int = 5
    exit_max_shift_m: float = 5.0
    exit_leads_to_end: bool = True  # once the road turned into is measured, the arc leads the whole turn
    # Going straight, the far side's centre line, read as the road turned into is: once read (the median of the
    # last readings, at least ``exit_min_readings``), the hold keeps to the lane beside it instead of the approach
    # lane's line, which a junction of a winding street shifts and bends. A reading farther across than this from
    # the approach lane's line, or turned more than this from its heading, is something else.
    far_max_shift_m: float = 2.0
    far_max_turn_deg: float = 10.0


class JunctionGuidance:
    """The straight hold and the turn arc (module docstring); ``placed`` once a stop bar ahead is located."""

    def __init__(self, rules: JunctionRules, line: StopLineTrack, odometry: Odometry, camera_to_centre_m: float,
                 road: RoadDesign = ROAD) -> None:
        self.rules = rules
        self.road = road  # lane width, stop-bar setback and depth: where the turn arc runs
        self.line = line
        self.odo = odometry
        self.camera_to_centre_m = camera_to_centre_m  # the camera's mount ahead of the car's centre
        self.reset()

    def reset(self) -> None:
        self.setback_m = self.road.stop_line_setback_m  # the design's setback, corrected by the zebra
        self.lane_width_m = self.road.lane_width_m  # the design's lane width, corrected by the lane finder
        self._holding = False  # the straight hold applied on the last frame
        self._far: list[tuple[float, float, float]] = []  # going straight: the far side's lane (a point, heading)
        self.forget()

    def forget(self) -> None:
        """Done with this junction: the next one is measured afresh (the straight hold still uses this one's
        setback until then)."""
        # the stop bar ahead (x, y, road yaw) and the command of the turn once it has begun (0: not yet)
        self.junction: tuple[float, float, float, int] | None = None
        self._by_track = False  # placed by the tracked bar, never read within turn_bar_seen_m (note)
        self._zebra_m: list[float] = []  # bar's far edge to the zebra's far edge, as measured at this junction
        self._skew: list[float] = []  # the cross street's angle from square (rad, positive: its right arm leans
        #                               away from us), as measured at this junction
        self.control: str | None = None  # what governs our arm (sim.spec.CONTROL_KINDS), as seen before the bar
        self.our_lanes: int | None = None  # our road's lanes each way, as the lane lines told before the bar
        self.lanes_to_kerb = 0  # lanes between ours and the kerb, as the lane lines told before the bar
        self._exit: list[tuple[float, float]] = []  # (reach, turn angle in degrees) read from the road turned into
        self._exit_fix: tuple[float, float] | None = None  # ... their medians, once there are enough readings
        self._fills: list[float] = []  # the white line beside it: how much of it is painted (ExitLine.divider_fill)
        self._arc_start_m: float | None = None  # where the arc begins (approach frame), once the car is on it
        # the rest of the turn re-placed from the car's pose (``arc_from_pose``), and the reach and angle it was
        # placed for
        self._replaced: tuple[tuple[np.ndarray, float, float, float], float, float] | None = None
        # the path the arc steered along on the last frame, from the point nearest the car's centre to the arc's
        # end, and the car's centre and heading (approach frame)
        self._steered: tuple[np.ndarray, np.ndarray, float] | None = None
        self.arc_ahead_m: float | None = None  # the car's centre to where the planned arc begins (negative: on it)
        self.arc_radius_m: float | None = None  # its radius, where the road turned into places it (``turn_steer``)

    @property
    def skew_rad(self) -> float:
        """The cross street's measured angle from square (0 until measured, and for an exact design)."""
        if not self.design_spreads or len(self._skew) < self.rules.skew_min_readings:
            return 0.0
        limit = math.radians(self.rules.skew_max_deg)
        return float(np.clip(np.median(self._skew), -limit, limit))

    @property
    def design_spreads(self) -> bool:
        """Whether the road design's turn numbers are priors with a spread (the arc is then only as good as they)."""
        return self.road.stop_line_setback_sd_m > 0 or self.road.lane_width_sd_m > 0

    @property
    def placed(self) -> bool:
        return self.junction is not None

    @property
    def arc_leads(self) -> bool:
        """Whether a turn's arc is under way (it steers the car until it hands over or the turn ends)."""
        return self.junction is not None and self.junction[3] != 0

    def hold(self, command: int) -> float | None:
        """Going straight through a junction, the steer that keeps the approach lane's heading and our place
        across it; None when this does not apply. Not in a turn under way here: its arc finishes it, and the route's
        command, which announces the next junction once the car is leaving this one, may already say straight
        (held to the approach lane's heading then, a turning car was swung back across the oncoming lanes)."""
        line, cfg, odo = self.line, self.rules, self.odo
        # the configured hold is for the classic design; a wider junction (a longer setback) is held longer
        hold_m = cfg.junction_hold_m + junction_widening_m(self.setback_m)
        inside = line.ignore_light_m > line.junction_ignore_m - hold_m
        self._holding = command == 3 and inside and odo.road_yaw is not None and not self.arc_leads
        if not self._holding:
            self._far = []
            return None
        assert odo.road_yaw is not None
        heading, offset = odo.yaw - odo.road_yaw, odo.road_offset
        far = self.far_lane
        if far is not None:  # the far side's lane, read: where it lies and runs from the approach lane carried on,
            x, y, yaw = far  # weighed against how far the design lets it lie and turn, each by its spread
            turn = math.remainder(yaw - odo.road_yaw, 2 * math.pi)
            across, _ = _across_along(odo.pos - np.array([x, y]), yaw)
            shift = offset - across  # the far lane's centre, right of the approach lane's line
            road = self.road
            heading -= fused(0.0, math.radians(road.far_lane_turn_sd_deg), turn, math.radians(FAR_ANGLE_SD_DEG))
            offset -= fused(0.0, road.far_lane_shift_sd_m, shift, FAR_SD_M)
        steer = -(cfg.hold_heading_gain * heading + cfg.hold_offset_gain * offset)
        return float(np.clip(steer, -cfg.hold_max_steer, cfg.hold_max_steer))

    @property
    def far_lane(self) -> tuple[float, float, float] | None:
        """Going straight through a junction, the far side's lane as read (a point on its centre line in the
        odometry frame, and its heading), once there are enough readings; else None."""
        return self._settled(self._far)  # type: ignore[return-value]

    def _settled(self, readings: list[tuple[float, ...]]) -> tuple[float, ...] | None:
        """The median of the last ``exit_last_readings`` readings, once there are ``exit_min_readings``."""
        cfg = self.rules
        if len(readings) < cfg.exit_min_readings:
            return None
        return tuple(float(v) for v in np.median(np.array(readings[-cfg.exit_last_readings:]), axis=0))

    def note(self, stop: StopLine | None, zebra_far_m: float | None = None, lane_width_m: float | None = None,
             zebra_tilt: float | None = None, control: str | None = None, our_lanes: int | None = None,
             lanes_to_kerb: int | None = None) -> None:
        """Where the stop bar ahead lies in the odometry frame (the approach lane's centre at the bar's near edge),
        from the tracked bar and the approach lane measured before it. Only a bar within ``turn_bar_seen_m`` of the
        camera places a turn (farther readings are a metre or so off): seen there, or tracked there by odometry
        from the last reading when the camera loses the bar short of it (paint under low sun, the lane lines that
        bound the search gone), which is as good as that reading, if it is no glimpse
        (``StopLineTrack.bar_confirmed``) and until it is forgotten as one; without a placed bar PilotNet alone turns, late
        and wide, and the car is not known to be turning (a lane change towards the turn is then thought to be
        pending, and the mirror's look may hold it mid-turn). ``zebra_far_m``: the camera to the
        far edge of the zebra beyond the bar this frame; ``lane_width_m``: the lane width the lane finder
        measured (both correct the design's priors, module docstring); ``zebra_tilt``: the slope of the zebra's
        edges (dz/dx in the camera's ground frame), the cross street's direction; ``control``: what governs our
        arm as seen this frame (a light or a sign, "none" when neither); ``our_lanes``: our road's lanes each way
        as last measured (both tell how likely the cross street has two lanes, ``RoadDesign.two_lane_share``);
        ``lanes_to_kerb``: lanes between ours and the kerb as the line on our right told while the car was in the
        lane it drives in now (which lane of the cross street a right turn goes into,
        ``right_turn_lanes_from_kerb``); None when not known: the kerb lane, as a right turn is made from."""
        line, odo, road = self.line, self.odo, self.road
        if (self._by_track and self.junction is not None and self.junction[3] == 0 and line.ignore_light_m <= 0
                and not line.stop_line_measured):
            self.junction = None  # the bar it was placed by, never read near, was forgotten as a glimpse: so is it
        if line.ignore_light_m > 0 or not line.stop_line_measured or line.stop_line is None or odo.road_yaw is None:
            return
        if self.junction is None and abs(odo.turned) > math.radians(self.rules.place_max_turned_deg):
            return
        near = stop is not None and stop.distance_m <= self.rules.turn_bar_seen_m
        if near:
            self._by_track = False
        elif self.junction is None:
            if not (line.bar_confirmed and camera_to_bar_m(line) <= self.rules.turn_bar_seen_m):
                return
            self._by_track = True
        if stop is not None:  # still before the bar: not yet turning
            if control is not None and (self.control in (None, "none") or control != "none"):
                self.control = control  # a light or a sign seen once governs the arm
            self.our_lanes = our_lanes if our_lanes is not None else self.our_lanes
            self.lanes_to_kerb = lanes_to_kerb if lanes_to_kerb is not None else 0  # not known: the kerb lane
            if lane_width_m is not None and math.isfinite(lane_width_m):
                self.lane_width_m = fused(road.lane_width_m, road.lane_width_sd_m, lane_width_m, LANE_WIDTH_SD_M)
        if stop is not None or line.bar_confirmed:  # the zebra beyond the bar, read from this frame's or the tracked
            bar_m = stop.distance_m if stop is not None else camera_to_bar_m(line)
            if zebra_far_m is not None:
                self._zebra_m.append(zebra_far_m - bar_m - road.stop_bar_depth_m)
            if zebra_tilt is not None and bar_m <= self.rules.skew_bar_max_m:
                # in the approach lane's frame: the camera is turned (yaw - road_yaw) to the right of it
                self._skew.append(math.atan(zebra_tilt) - (odo.yaw - odo.road_yaw))
            measured = float(np.median(self._zebra_m)) + road.zebra_to_centre_m if self._zebra_m else None
            self.setback_m = fused(road.stop_line_setback_m, road.stop_line_setback_sd_m, measured,
                                   math.hypot(road.zebra_to_centre_sd_m, ZEBRA_SD_M))
        ahead = camera_to_bar_m(line) + self.camera_to_centre_m  # car centre to the bar
        u = np.array([math.cos(odo.road_yaw), math.sin(odo.road_yaw)])
        right = np.array([-u[1], u[0]])
        bar = odo.pos - odo.road_offset * right + ahead * u
        self.junction = (float(bar[0]), float(bar[1]), odo.road_yaw, 0)

    @property
    def exit_measured(self) -> bool:
        """Whether the road turned into has been read in this turn (``note_exit``)."""
        return self._exit_fix is not None

    def _in_bar_frame(self, point: np.ndarray) -> tuple[float, float]:
        """A point of the odometry frame along the approach lane from the stop bar's near edge, and right of it."""
        assert self.junction is not None
        bx, by, road_yaw, _ = self.junction
        c, s = math.cos(road_yaw), math.sin(road_yaw)
        dx, dy = float(point[0]) - bx, float(point[1]) - by
        return dx * c + dy * s, -dx * s + dy * c

    def turn_reach_m(self, command: int) -> float:
        """The stop bar's far edge to where the lane turned into crosses our lane's centre line: as read in the
        turn from the road turned into (``note_exit``), else as planned before it (``planned_reach_m``). A left
        turn goes into the inner lane the read places. A right turn goes into the lane ``right_turn_lanes_from_kerb``
        off the kerb, a lane short of the inner one for each lane between, over the counts the read leaves
        (``exit_odds``), kept within ``lane_room_m`` of each count's lanes (``hedged_reach``): where one lane may
        be, near the inner lane's place, which is that lane."""
        return self._turn_reach(command)[0]

    def _turn_reach(self, command: int) -> tuple[float, float]:
        """``turn_reach_m``, and how far keeping within reach of every count's lanes moved it from the expected
        reach (``hedged_reach``)."""
        if self._exit_fix is None:
            return self._planned(command)
        inner = self._exit_fix[0]
        if command != 2:
            return inner, 0.0
        w = self.lane_width_m
        options = [(p, inner - (n - 1 - right_turn_lanes_from_kerb(self.lanes_to_kerb, n)) * w,
                    inner - (n - 1) * w, inner) for n, p in self.exit_odds().items()]
        hedged = hedged_reach(options, self.lane_room_m)
        return hedged, hedged - hedged_reach(options, None)

    def exit_odds(self) -> dict[int, float]:
        """How likely the road turned into has one lane each way or two, as its centre line read in the turn tells
        ({1: 1} before it is read): the zebra lies at the cross street's near kerb, so the centre line lies farther
        beyond it on a two-lane street (two lanes) than on a single-lane one (a lane and a parking strip). Each
        count's design reach (``RoadDesign.turn_reaches``, the kerb lane's plus the lanes between) is weighed against
        the line's distance beyond the zebra, from the odds of the kind of junction seen; with no zebra measured,
        those odds alone."""
        if self._exit_fix is None or not self.road.turn_reaches:
            return {1: 1.0}
        share = float(np.clip(self.road.two_lane_share(self.control, self.our_lanes), 0.01, 0.99))
        beyond = self._exit_fix[0] - float(np.median(self._zebra_m)) if self._zebra_m else None
        sd = math.hypot(EXIT_SD_M, ZEBRA_SD_M)

        solid = (float(np.median(self._fills)) >= DIVIDER_SOLID_FILL
                 if len(self._fills) >= self.rules.exit_min_readings else None)

        def log_odds(n: int, right_m: float) -> float:
            prior = math.log(share if n == 2 else 1.0 - share)
            if solid is not None:  # a solid line beside the centre line: one lane; a dashed one: two
                prior += math.log(DIVIDER_RIGHT if solid == (n == 1) else 1.0 - DIVIDER_RIGHT)
            if beyond is None:
                return prior
            return prior - 0.5 * ((beyond - right_m - (n - 1) * self.lane_width_m) / sd) ** 2

        counts = {r.cross_lanes: log_odds(r.cross_lanes, r.right_m) for r in self.road.turn_reaches
                  if r.cross_lanes in (1, 2)}  # the odds are of one or two
        if not counts:
            return {1: 1.0}
        top = max(counts.values())
        total = sum(math.exp(v - top) for v in counts.values())
        return {n: math.exp(v - top) / total for n, v in counts.items()}

    def cross_odds(self) -> dict[int, float]:
        """How likely the cross street has one lane each way or two: as the road turned into tells once read
        (``exit_odds``), else as the kind of junction seen does (``RoadDesign.two_lane_share``)."""
        if self._exit_fix is not None and self.road.turn_reaches:
            return self.exit_odds()
        share = self.road.two_lane_share(self.control, self.our_lanes)
        return {1: 1.0 - share, 2: share}

    def turn_angle_deg(self, command: int) -> float:
        """The turn's heading change: as read from the road turned into, else from the cross street's angle read
        from the zebra (90 degrees in a square junction)."""
        return self._exit_fix[1] if self._exit_fix is not None else self.planned_angle_deg(command)

    @property
    def reads_lane_count(self) -> bool:
        """Whether the road turned into's lane count is read (``ExitLine.divider_fill``): in a right turn under way,
        whose lane is the kerb lane; a left turn's inner lane and the straight hold do not depend on it."""
        return self.junction is not None and self.junction[3] == 2

    @property
    def lane_room_m(self) -> float:
        """How far the car's centre may be off its lane's centre with the car still inside the lane."""
        return max(0.0, (self.lane_width_m - VEHICLE.width_m) / 2)

    @property
    def cross_street_m(self) -> float:
        """The stop bar's far edge to where the cross street's nearest lane begins (the kerb lane a right turn goes
        into, less half a lane): beyond the zebra measured here by the nearest the design's lane counts put that
        lane, else by the kerb lane's prior."""
        if self._zebra_m and self.road.turn_reaches:
            beyond = min(r.right_m for r in self.road.turn_reaches)
            return float(np.median(self._zebra_m)) + beyond - 0.5 * self.lane_width_m
        return self.road.kerb_lane_reach - 0.5 * self.lane_width_m

    def planned_reach_m(self, command: int) -> float:
        """The reach planned before the turn: beyond the zebra measured here by the design's reach expected over
        the cross street's lane count, kept where it can be within ``lane_room_m`` of each count's lanes (either
        count may be, and a turn that leaves the road is no better for having been the likelier guess), else from
        the priors (left turns: half a lane beyond the junction's centre; right turns: the kerb lane's own
        prior)."""
        return self._planned(command)[0]

    def _planned(self, command: int) -> tuple[float, float]:
        """``planned_reach_m``, and how far keeping within reach of every count's lanes moved it (0 from the
        priors)."""
        options = self.road.turn_reach_options(command == 1, self.road.two_lane_share(self.control, self.our_lanes),
                                               lanes_to_kerb=self.lanes_to_kerb)
        if self._zebra_m and options is not None:
            hedged = hedged_reach(options, self.lane_room_m)
            return float(np.median(self._zebra_m)) + hedged, hedged - hedged_reach(options, None)
        if command == 2:
            return self.road.kerb_lane_reach + self.lanes_to_kerb * self.lane_width_m, 0.0
        return self.setback_m + 0.5 * self.lane_width_m, 0.0

    def exit_expected_rad(self) -> float | None:
        """While a turn's arc leads with a design that spreads and the car has turned far enough to see the road
        turned into: the direction that road's centre line should run in the camera's ground frame (from the
        forward axis, positive right); going straight under the hold, the far side's, along the approach lane; else
        None (nothing to look for)."""
        cfg = self.rules
        if self._reads_far_side:
            assert self.odo.road_yaw is not None
            return self.odo.road_yaw - self.odo.yaw  # going straight: the far side runs on as the approach did
        planned = self._exit_planned()
        if planned is None:
            return None
        direction, heading, _ = planned
        if not math.radians(cfg.exit_min_turned_deg) <= abs(heading) <= math.radians(cfg.exit_max_turned_deg):
            return None
        return direction

    def exit_look(self) -> tuple[str, float] | None:
        """While a turn's arc leads with a design that spreads and the car has turned less than
        ``exit_corner_max_turned_deg``: the side whose corner camera looks down the road turned into, and the
        direction that road's centre line should run from the car's axis (positive right); else None. The forward
        camera sees that road only once the car has turned ``exit_min_turned_deg`` (a left turn's, farther round,
        later still); the corner camera on the turn's side is turned out towards it from the arc's start."""
        planned = self._exit_planned()
        if planned is None or abs(planned[1]) > math.radians(self.rules.exit_corner_max_turned_deg):
            return None
        direction, _, command = planned
        return ("right" if command == 2 else "left"), direction

    def _exit_planned(self) -> tuple[float, float, int] | None:
        """While a turn's arc leads with a design that spreads: the direction the road turned into should run from
        the car's axis (positive right), how far the car has turned and the turn's command; else None."""
        if not self.design_spreads or self.junction is None or not self.arc_leads:
            return None
        command = self.junction[3]
        heading = self.odo.yaw - self.junction[2]
        angle = math.radians(self.planned_angle_deg(command))
        return (angle if command == 2 else -angle) - heading, heading, command

    def far_corridor(self) -> tuple[float, float, float] | None:
        """Going straight under the hold with a design that spreads: where the far side's centre line should lie
        in the camera's ground frame (a point on the approach road's centre line carried on, half a lane left of
        our lane, and how far across a reading may be, ``far_max_shift_m``); else None."""
        odo = self.odo
        if not self._reads_far_side:
            return None
        assert odo.road_yaw is not None
        centre = odo.pos - (odo.road_offset + 0.5 * self.lane_width_m) * _right_of(odo.road_yaw)
        yaw = odo.yaw
        d = centre - (odo.pos + self.camera_to_centre_m * np.array([math.cos(yaw), math.sin(yaw)]))
        return (*_across_along(d, yaw), self.rules.far_max_shift_m)

    @property
    def _reads_far_side(self) -> bool:
        """Whether the far side's centre line is looked for: going straight under the hold (last frame's), with a
        design that spreads and does not put the far side's lane exactly where the approach lane carried on lies."""
        return (self.design_spreads and self.road.far_lane_shift_sd_m > 0 and self._holding and not self.arc_leads
                and self.odo.road_yaw is not None)

    def planned_angle_deg(self, command: int) -> float:
        """The turn's heading change as planned before it, from the zebra's slope (90 degrees when square)."""
        skew = math.degrees(self.skew_rad)  # a right turn is that much less than square, a left turn more
        return 90.0 - skew if command == 2 else 90.0 + skew

    def note_exit(self, line: ExitLine | None) -> None:
        """Place the lane turned into from the road turned into's centre line seen this frame (in the camera's
        ground frame, ``ExitLineFinder``): its inner lane lies half a lane width to the line's right in the
        direction of travel, whatever the cross street's lane count; where that lane's centre line crosses ours is
        the turn's reach, and its direction the turn's angle."""
        cfg = self.rules
        if line is not None and self._reads_far_side:
            self._note_far(line)
            return
        if line is None or self.junction is None or not self.arc_leads:
            return
        _, _, road_yaw, command = self.junction
        yaw = self.odo.yaw
        along, across = self._in_bar_frame(self._seen_at(line))
        runs = line.direction_rad + (yaw - road_yaw)  # in the approach frame, from its axis (positive right)
        if abs(math.sin(runs)) < math.sin(math.radians(90.0 - cfg.skew_max_deg - 10.0)):
            return  # nearly along our road: not a cross street
        # its direction weighed against the cross street's angle read before the turn, each by its spread: a line
        # seen short is far off and its direction is little to go by, and its distance across magnifies that error
        planned = math.radians(self.planned_angle_deg(command)) * (1.0 if command == 2 else -1.0)
        planned_sd = ZEBRA_ANGLE_SD_DEG if len(self._skew) >= cfg.skew_min_readings else cfg.skew_max_deg / math.sqrt(3)
        line_sd = max(EXIT_ANGLE_SD_FLOOR_DEG, EXIT_ANGLE_SD_DEG_M2 / max(line.length_m, 1e-3) ** 2)
        runs = fused(planned, math.radians(planned_sd), runs, math.radians(line_sd))
        along -= 0.5 * self.lane_width_m * math.sin(runs)  # the inner lane's centre line
        across += 0.5 * self.lane_width_m * math.cos(runs)
        reach = along - across * math.cos(runs) / math.sin(runs) - self.road.stop_bar_depth_m
        if abs(reach - self.planned_reach_m(command)) > cfg.exit_max_shift_m:
            return
        self._exit.append((reach, math.degrees(runs if command == 2 else -runs)))
        if line.divider_fill is not None:
            self._fills.append(line.divider_fill)
        fix = self._settled(self._exit)
        if fix is not None:
            self._exit_fix = (fix[0], fix[1])

    def _seen_at(self, line: ExitLine) -> np.ndarray:
        """Where a line seen this frame lies (its paint's middle, in the camera's ground frame) in the odometry
        frame."""
        yaw = self.odo.yaw
        ahead, right = np.array([math.cos(yaw), math.sin(yaw)]), _right_of(yaw)
        return self.odo.pos + (self.camera_to_centre_m + line.point[1]) * ahead + line.point[0] * right

    def _note_far(self, line: ExitLine) -> None:
        """Going straight, the far side's centre line seen this frame: our lane lies half a lane width to its right
        (the agent keeps to the inner lane), where the approach lane's line, carried on, would be give or take a
        winding street's shift."""
        odo, cfg = self.odo, self.rules
        assert odo.road_yaw is not None
        runs = odo.yaw + line.direction_rad  # in the odometry frame
        if abs(math.remainder(runs - odo.road_yaw, 2 * math.pi)) > math.radians(cfg.far_max_turn_deg):
            return
        point = self._seen_at(line) + 0.5 * self.lane_width_m * _right_of(runs)
        # across the approach lane's line: the car is road_offset right of it
        shift = float((point - odo.pos) @ _right_of(odo.road_yaw)) + odo.road_offset
        if abs(shift) > cfg.far_max_shift_m:
            return
        self._far.append((float(point[0]), float(point[1]), runs))

    def turn_steer(self, command: int, speed: float) -> float | None:
        """Turning at a junction, the steer that keeps the car's centre on the turn arc from our lane to the same
        lane of the road we turn into; None when this does not apply."""
        cfg, odo = self.rules, self.odo
        self._steered, self.arc_ahead_m, self.arc_radius_m = None, None, None
        if self.junction is None or not cfg.turn_guidance:
            return None
        _, _, road_yaw, started = self.junction
        if started:  # a turn under way is finished, whatever the route says next (leaving the junction, the
            command = started  # command already announces the next one)
        elif command not in (1, 2):
            if self.line.ignore_light_m > 0:  # through this junction another way: its bar is behind us
                self.forget()
            return None
        # Left turns into the inner lane, right turns into the kerb lane (as planned, or as the road turned into
        # tells once read). Taken from another lane, the arc still ends in a lane of the road turned into: it is
        # placed from our own lane, and its radius is the tighter one.
        reach, hedge = self._turn_reach(command)
        heading = odo.yaw - road_yaw
        half = VEHICLE.length_m / 2
        # the rear axle, along the approach and right of it: in highway-env's bicycle model it moves along the
        # car's heading on a curve of curvature tan(delta) / length
        along, across = self._in_bar_frame(odo.pos)
        here = np.array([along - half * math.cos(heading), across - half * math.sin(heading)])
        radius = (self.road.left_turn_radius_m if command == 1
                  else self.road.right_turn_radius(self.our_lanes, self.cross_odds()))
        angle = round(self.turn_angle_deg(command), 1)
        half_turn = math.radians(angle) / 2
        if command == 2 and radius is not None:  # the design's is the kerb lane's: a lane farther out, a lane wider;
            # a reach hedged farther out moves the arc's end, not its start (a later start, on the kerb lane's
            # radius, lags the junction's lanes and runs wide of them in the turn)
            radius += self.lanes_to_kerb * self.lane_width_m + hedge / math.tan(half_turn)
        _, planned_start = arc_placement(reach, self.road.stop_bar_depth_m, radius, angle)
        if (self._arc_start_m is not None and self.exit_measured
                and abs(heading) <= math.radians(cfg.exit_restart_max_deg) and planned_start > self._arc_start_m):
            self._arc_start_m, self._replaced = None, None  # read before the car has turned much: it goes on
            #                                                  straight to the later start
        design = radius
        if self._arc_start_m is not None:  # on the arc: a new reading moves its end, not where it began (a start
            # moved on lags the car already turning there, which steers back out and cannot catch the turn again)
            radius = round(max(VEHICLE.min_turn_radius_m,
                               (self.road.stop_bar_depth_m + reach - self._arc_start_m) / math.tan(half_turn)), 2)
            self._replace(command, reach, angle, design, radius, (along, across), heading)
        start = self._arc_start_m if self._arc_start_m is not None else planned_start
        if self._replaced is None:
            path, arc_end = turn_path(command, round(reach, 2), self.road.stop_bar_depth_m, radius, angle_deg=angle)
            self.arc_ahead_m = start - along
        else:
            path, arc_begins, arc_end, radius = self._replaced[0]
            self.arc_ahead_m = arc_begins - float(np.hypot(*(path[1] - path[0]))) * int(
                np.argmin(np.sum((path - np.array([along, across])) ** 2, axis=1)))
        # Placed by the road turned into, its lane count settled (no count in doubt moves the plan: ``hedge``), the
        # arc is driven at its curve speed; while in doubt, at the turn speed, which leaves the reading time to
        # settle before the arc's start is committed; unread (an exact design's arc), at the turn speed.
        if self.exit_measured and abs(hedge) < 1e-6:
            self.arc_radius_m = (radius if self._replaced is not None
                                 else arc_placement(reach, self.road.stop_bar_depth_m, radius, angle)[0])
        lookahead = cfg.turn_lookahead_m + cfg.turn_lookahead_s * speed
        if here[0] < self.road.stop_bar_depth_m - lookahead:  # not yet: the lookahead point is still before the arc
            return None
        leads_on = cfg.exit_leads_to_end and self.exit_measured
        if started and self.design_spreads and not leads_on and abs(heading) > math.radians(cfg.turn_handover_deg):
            self._turned_off()  # facing the road turned into: the camera's steering finishes the turn
            return None
        step = float(np.hypot(*(path[1] - path[0])))
        nearest = int(np.argmin(np.sum((path - here) ** 2, axis=1)))
        if nearest * step > arc_end + 6.0:  # out of the turn, lined up on the road turned into: the lines lead again
            self._turned_off() if started else self.forget()
            return None
        if not started:
            self.junction = (self.junction[0], self.junction[1], road_yaw, command)
        if self._arc_start_m is None and self.design_spreads and along >= start:  # the car's centre, which the
            self._arc_start_m = start  # arc leads, has reached it (an exact design's arc never moves)
        delta, on = self._centre_on_path(path, np.array([along, across]), heading)
        self._steered = (path[on:int(arc_end / step) + 1], np.array([along, across]), heading)
        return float(np.clip(delta / VEHICLE.max_steer_rad, -1.0, 1.0))

    def _replace(self, command: int, reach: float, angle: float, design: float | None, stretched: float,
                 centre: tuple[float, float], heading: float) -> None:
        """On the arc, where the reach read would stretch it from where it began to a radius well over the design's
        (a start committed for the likelier lane count, the farther lane read after the car has turned too far to go
        on straight to a later start): the rest of the turn from the car's pose, on the design's radius
        (``arc_from_pose``). The stretched arc, tangent to the same two lines on a larger radius, cuts inside the
        corner by (R - r) x (1 / cos(turn / 2) - 1), a metre on a right turn read 2.4 m of radius out. A reading
        that tightens the arc leaves it (tighter, it stays outside the corner, and a reading that flips between the
        counts mid-turn would otherwise swing the car from one lane's arc to the other's). Kept until the reach or
        the angle read moves again."""
        cfg = self.rules
        if design is None or not self.design_spreads:
            return
        if self._replaced is not None:
            _, placed_reach, placed_angle = self._replaced
            if abs(reach - placed_reach) <= cfg.replace_reach_m and abs(angle - placed_angle) <= 1.0:
                return
        elif stretched - design <= cfg.replace_radius_m:
            return  # a tighter arc from the same start stays outside the corner
        placed = arc_from_pose(command, centre, heading, reach, self.road.stop_bar_depth_m, design, angle)
        if placed is not None:
            self._replaced = (placed, reach, angle)

    def steered_path(self, ahead_m: float) -> np.ndarray | None:
        """The turn's path the car is steered along this frame (``turn_steer``) as (x, z) points in the camera's
        ground frame, from the car's centre on to the arc's end, at most ``ahead_m`` along it, or until it runs back
        towards the camera; None when no arc steers. What lies on it, not on the lane lines the camera sees
        mid-junction (the road turned into, seen across the corner), is in the car's way; beyond the arc the road
        turned into is the camera's to see (a winding street does not run on along the arc's end)."""
        if self._steered is None or len(self._steered[0]) < 2:
            return None
        path, centre, heading = self._steered  # from the point nearest the car's centre on
        step = float(np.hypot(*(path[1] - path[0])))
        d = path[:int(ahead_m / step) + 1] - centre
        z = d[:, 0] * math.cos(heading) + d[:, 1] * math.sin(heading) - self.camera_to_centre_m
        x = -d[:, 0] * math.sin(heading) + d[:, 1] * math.cos(heading)
        rising = np.diff(z) > 1e-6
        end = len(z) if rising.all() else int(np.argmin(rising)) + 1
        if end < 2:
            return None
        return np.stack([x[:end], z[:end]], axis=1)

    def _turned_off(self) -> None:
        """The turn is done with: the approach road it was planned on is behind the car (``Odometry.leave_road``)."""
        self.odo.leave_road()
        self.forget()

    def _centre_on_path(self, path: np.ndarray, centre: np.ndarray, heading: float) -> tuple[float, int]:
        """The wheel angle that keeps the car's centre on ``path``. In the bicycle model the centre moves at the
        slip angle beta off the heading, tan(beta) = tan(delta) / 2, so the wheels set its direction of travel at
        once: along the path where it is nearest, turned back towards it by the centre's offset from it. On an arc
        the heading then lags the path's by beta and the rear axle runs inside the arc; pursuing the arc with the
        rear axle instead puts the centre outside it by (length / 2)^2 / (2 x radius). Also the index of the path's
        point nearest the centre."""
        i = min(len(path) - 2, int(np.argmin(np.sum((path - centre) ** 2, axis=1))))
        d = path[i + 1] - path[i]
        tangent = math.atan2(d[1], d[0])
        offset = float((centre - path[i]) @ _right_of(tangent))  # right of the path
        course = tangent - math.atan(self.rules.turn_offset_gain * offset)
        beta = math.remainder(course - heading, 2 * math.pi)
        return math.atan(2.0 * math.tan(float(np.clip(beta, -MAX_SLIP_RAD, MAX_SLIP_RAD)))), i
