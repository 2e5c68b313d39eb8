"""The facts the simulator and the agent both rely on: the sensor rig, the car, and the road-design priors.

Why one module: the simulator renders from the camera the agent computes with, moves the car whose size and
steering the agent dead-reckons with, and builds towns to the design the agent expects (lane width, where a
stop bar and a signal head stand). Each of these numbers lives here once; the simulator builds from them and
the agent reads them, and a deployment profile can override the road priors for a real road.

This module imports nothing of the simulator (no pybullet, no highway-env), so the car's runtime code may use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from towndrive.sim.checks import check_number

IMAGE_PX = (8, 4096)  # smallest and largest camera width or height, in pixels


def check_image_size(name: str, value: object) -> int:
    """A camera width or height: an integer in ``IMAGE_PX`` (0 pixels would divide by zero in the projection)."""
    return check_number(name, value, *IMAGE_PX, integer=True)


@dataclass(frozen=True)
class CameraConfig:
    """A forward pinhole camera rigidly mounted on the vehicle."""

    width: int = 320
    height: int = 160
    hfov_deg: float = 90.0
    mount_height_m: float = 1.3
    mount_forward_m: float = 1.0  # ahead of the vehicle centre
    pitch_deg: float = -4.0  # negative looks down
    near_m: float = 0.5
    far_m: float = 250.0
    stereo: bool = False
    stereo_baseline_m: float = 0.12  # ZED-like

    def __post_init__(self) -> None:
        check_image_size("camera width", self.width)
        check_image_size("camera height", self.height)
        check_number("camera hfov_deg", self.hfov_deg, 0.0, 179.0, lo_open=True)
        check_number("camera near_m", self.near_m, 0.0, None, lo_open=True)
        check_number("camera far_m", self.far_m, self.near_m, 1e5, lo_open=True)

    @property
    def focal_px(self) -> float:
        """Square-pixel focal length from the horizontal field of view."""
        return (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view implied by hfov and the aspect ratio (what pybullet's projection takes)."""
        return math.degrees(2 * math.atan((self.height / 2) / self.focal_px))

    def intrinsics(self) -> np.ndarray:
        """3x3 K so that ``K @ [X, Y, Z]`` (camera frame: x right, y down, z forward) lands on TinyRenderer's pixel.

        TinyRenderer samples pixel column u at viewport x = u (not u + 0.5) and stores rows bottom-up,
        so image row v samples viewport y = v + 1 from the top: the principal point is (W/2, H/2 - 1).
        tests/test_env.py checks this against the metric depth of the ground plane.
        """
        f = self.focal_px
        return np.array([[f, 0.0, self.width / 2], [0.0, f, self.height / 2 - 1.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class MirrorRig:
    """The blind-spot cameras under each door mirror: where they sit on the car and where they look.

    Turned 115 degrees from straight ahead with a 120-degree view, they see from 55 degrees off the car's axis
    (beside the front wheel) round to 175 degrees (the next lane behind), where a forward camera is blind."""

    camera: CameraConfig = CameraConfig(hfov_deg=120.0, mount_height_m=1.0, mount_forward_m=0.0, pitch_deg=-10.0,
                                        far_m=60.0)
    ahead_m: float = 1.0  # ahead of the car's centre
    out_m: float = 1.0  # out to the side
    yaw_deg: float = 115.0  # from straight ahead, towards the side


@dataclass(frozen=True)
class CornerRig:
    """The cross-traffic cameras at the front corners: where they sit on the car and where they look.

    Turned 75 degrees from straight ahead with a 60-degree view, they see from 45 degrees off the car's axis
    (where the forward camera's view ends) round to 105 degrees: the cross street either way, from a give-way
    or stop line and while edging towards it, where a car coming 30 m down it stands 70-85 degrees off the axis.
    A narrower view than the mirror cameras' gives such a car the pixels to be detected."""

    camera: CameraConfig = CameraConfig(hfov_deg=60.0, mount_height_m=1.0, mount_forward_m=0.0, pitch_deg=-2.0,
                                        far_m=90.0)
    ahead_m: float = 2.1  # ahead of the car's centre (the front bumper is 2.3 m ahead)
    out_m: float = 0.8  # out to the side
    yaw_deg: float = 75.0  # from straight ahead, towards the side


@dataclass(frozen=True)
class VehicleSpec:
    """The ego car: highway-env's kinematic bicycle model with these dimensions and limits."""

    length_m: float = 4.6  # also the bicycle model's wheelbase: curvature = tan(delta) / length
    width_m: float = 1.9
    height_m: float = 1.5
    max_steer_rad: float = 0.6  # steer 1 turns the wheels this far
    max_accel_mps2: float = 3.5  # what throttle 1 gives
    max_brake_mps2: float = 8.0  # what brake 1 (throttle_brake -1) gives
    drag_mps2: float = 0.15
    max_speed_mps: float = 25.0

    @property
    def min_turn_radius_m(self) -> float:
        """The tightest circle the car can drive (full lock): roads must not turn tighter."""
        return self.length_m / math.tan(self.max_steer_rad)


@dataclass(frozen=True)
class SignalMount:
    """Where one kind of signal head hangs, relative to the approach it governs."""

    beyond_stop_line_m: float  # along the approach, past the stop bar's far edge (negative: before it)
    lateral_m: float  # right of the centre of the lane the agent drives (the inner one of two)
    height_m: float  # the head's centre above the road

    def __post_init__(self) -> None:
        check_number("signal mount beyond_stop_line_m", self.beyond_stop_line_m, -10.0, 80.0)
        check_number("signal mount lateral_m", self.lateral_m, -20.0, 20.0)
        check_number("signal mount height_m", self.height_m, 2.0, 12.0)


# What governs a junction's arm, as a driver sees it: its light, a stop sign, a give-way sign, or nothing (its road
# has priority). The kinds the road design's cross-street odds are kept by.
CONTROL_KINDS = ("signal", "stop", "yield", "none")


@dataclass(frozen=True)
class CrossStreetOdds:
    """How often the cross street has two lanes each way at one kind of junction as the car sees it: what governs
    its arm (``CONTROL_KINDS``) and its own road's lanes each way. A car that stops or gives way usually enters a
    larger street; one with priority crosses a smaller one."""

    control: str
    our_lanes: int
    two_lane_share: float
    junctions: int  # how many the share was measured on (to pool kinds the car could not tell apart)

    def __post_init__(self) -> None:
        if self.control not in CONTROL_KINDS:
            raise ValueError(f"cross street odds control must be one of {', '.join(CONTROL_KINDS)}; got "
                             f"{self.control!r}.")
        check_number("cross street odds our_lanes", self.our_lanes, 1, 2)
        check_number("cross street odds two_lane_share", self.two_lane_share, 0.0, 1.0)
        check_number("cross street odds junctions", self.junctions, 1, 1_000_000)


COUNT_DOUBT = 0.05  # a lane count at least this likely is one a turn is kept within reach of (hedged_reach)


def hedged_reach(options: list[tuple[float, float, float, float]], within_m: float | None) -> float:
    """A turn's reach over the cross street's lane counts that may be, each given as (weight, the reach of the lane
    the turn goes into on that count, and the nearest and farthest reach of that count's lanes in our direction):
    the weighted mean (the least squared error), moved where it can be to within ``within_m`` of every count's lanes.
    A turn that ends among the lanes of its direction, whichever they are, stays on the road; one that misses them
    by more leaves it, however likely the count it was aimed at. So a right turn whose cross street may have one
    lane keeps near that lane's place, which on two lanes is the inner one, rather than aiming at a kerb lane that
    is off the road if the count was guessed wrong. A count less likely than ``COUNT_DOUBT`` is not kept in reach:
    the turn would give up the likely count's lane for it."""
    total = sum(w for w, *_ in options)
    expected = sum(w * target for w, target, *_ in options) / total
    if within_m is None:
        return expected
    doubt = COUNT_DOUBT * total
    lo = max(near for w, _, near, _ in options if w >= doubt) - within_m
    hi = min(far for w, _, _, far in options if w >= doubt) + within_m
    return expected if lo > hi else min(max(expected, lo), hi)


def right_turn_lanes_from_kerb(lanes_to_kerb: int, cross_lanes: int) -> int:
    """How many lanes off the cross street's kerb a right turn ends, from ``lanes_to_kerb`` lanes off ours: as many,
    as far as the cross street has lanes (``sim/town.py``'s connectors keep a right turn's lane counted from the
    kerb; from the inner lane of two, the inner lane, one lane each way or two)."""
    return min(lanes_to_kerb, cross_lanes - 1)


@dataclass(frozen=True)
class TurnReach:
    """Where the lane a turn goes into crosses our lane's centre line, beyond the near zebra's far edge (measured
    along our lane), on a cross street of ``cross_lanes`` lanes each way. The zebra lies at the cross street's
    kerb, so this leaves out how far the junction's centre is; what is left depends on the cross street's lanes
    (a right turn goes into its kerb lane, which a single-lane street's parking strip pushes farther; a left
    turn, beyond its centre line, into its inner lane)."""

    cross_lanes: int
    left_m: float
    right_m: float

    def __post_init__(self) -> None:
        check_number("turn reach cross_lanes", self.cross_lanes, 1, 4)
        check_number("turn reach left_m", self.left_m, 0.0, 60.0)
        check_number("turn reach right_m", self.right_m, 0.0, 60.0)


@dataclass(frozen=True)
class TurnRadius:
    """A right turn's radius from the kerb lane of a road of ``our_lanes`` lanes each way into a cross street of
    ``cross_lanes``. It goes round the corner's kerb at the nearer of the two lanes' distances from their kerbs, and
    a parking strip puts a single-lane street's lane farther out: so it depends on both roads' lanes (a turn from
    a two-lane road is as tight as its kerb lane, whatever it turns into)."""

    our_lanes: int
    cross_lanes: int
    right_m: float

    def __post_init__(self) -> None:
        check_number("turn radius our_lanes", self.our_lanes, 1, 4)
        check_number("turn radius cross_lanes", self.cross_lanes, 1, 4)
        check_number("turn radius right_m", self.right_m, 3.0, 60.0)


# A signalled junction's cycle, each axis in turn: green, yellow, then red on both while the junction clears.
LIGHT_GREEN_S = 14.0
LIGHT_YELLOW_S = 3.0
LIGHT_ALL_RED_S = 1.5


@dataclass(frozen=True)
class RoadDesign:
    """How the default towns are built, and so what the agent assumes of a road it has not measured."""

    # A number with an ``_sd_m`` beside it is a prior: its mean and how far it spreads between junctions of
    # this design (``sim.road_priors`` measures a town style's); the agent corrects it by what it measures.
    lane_width_m: float = 3.5
    lane_width_sd_m: float = 0.0
    stop_line_setback_m: float = 12.0  # junction centre to a stop bar's far edge, where the connectors start
    stop_line_setback_sd_m: float = 0.0
    zebra_to_centre_m: float = 7.6  # junction centre to the near zebra's far edge (cross street half + kerb gap)
    zebra_to_centre_sd_m: float = 0.0
    # A turn's radius (left: from the inner lane; right: from the kerb lane); None: the quarter circle from the
    # stop bar into the same lane of the road turned into (the classic design). With a radius, the turn runs
    # straight on past the bar and bends where an arc of that radius meets the lane turned into.
    left_turn_radius_m: float | None = None
    right_turn_radius_m: float | None = None
    # ... the right turn's by both roads' lanes each way (``TurnRadius``); empty, or a pairing not listed: the one
    # above.
    right_turn_radii: tuple[TurnRadius, ...] = ()
    # A right turn goes into the cross street's kerb lane: beyond the stop bar's far edge lie a gap, the zebra, the
    # kerb, any parking strip and half a lane, whatever the cross street's lane count (its centre line lies one or
    # two lanes farther, a count not seen before the turn). None: the classic design's kerb lane, the setback less
    # one and a half lane widths.
    kerb_lane_reach_m: float | None = None  # the stop bar's far edge to where that lane's centre line crosses ours
    kerb_lane_reach_sd_m: float = 0.0
    # With the near zebra measured, both turns are placed from its far edge (``TurnReach``, by the cross street's
    # lanes each way, which is not seen before the turn: expected over ``cross_street_odds``). Empty: the two priors
    # above place them.
    turn_reaches: tuple[TurnReach, ...] = ()
    cross_street_odds: tuple[CrossStreetOdds, ...] = ()
    # Straight on through a junction, the far side's lane lies where the approach lane carried on would, give or
    # take this across and this turned (a winding street's junction shifts and bends it); 0: exactly there.
    far_lane_shift_sd_m: float = 0.0
    far_lane_turn_sd_deg: float = 0.0
    stop_bar_depth_m: float = 0.5  # the painted bar's depth along the lane
    crosswalk_depth_m: float = 3.0  # a zebra's depth along the road it crosses (the length of its stripes)
    # Where our signal head hangs: on a mast arm over the incoming lanes, across the junction. A design with
    # other mounts (posts at a corner) lists them in ``other_signal_mounts``: where heads hang is a kind, not a
    # number that spreads, so each kind is one mode of the prior.
    signal_head_height_m: float = 5.2  # signal heads hang this high above the road on mast arms
    signal_housing_height_m: float = 2.1  # a three-lamp head's housing
    # A light stays red at most this long (the other axis's green and yellow, and both all-reds: ``sim.lights``):
    # a red seen has ended by then, whether or not its head is still in view.
    longest_red_s: float = LIGHT_GREEN_S + LIGHT_YELLOW_S + 2 * LIGHT_ALL_RED_S
    yellow_s: float = LIGHT_YELLOW_S  # and a yellow this long
    light_beyond_stop_line_m: float = 21.0  # our light stands across the junction (measured 21.4 m beyond the bar)
    light_lateral_m: float = 1.75  # our head right of our lane's centre (over the incoming lanes' middle)
    other_signal_mounts: tuple[SignalMount, ...] = ()
    sign_before_stop_line_m: float = 2.5  # a stop or yield sign's post stands this far before the bar's near edge
    sign_plate_size_m: float = 0.75  # a sign plate's width (stop, yield, speed limit)
    sign_plate_height_m: float = 2.1  # the plate's centre above the road
    # The limit a driver assumes where no limit sign was seen, by the kind of street (what a town style posts on
    # its arterials, two lanes each way, and its residential streets, one lane each way).
    multi_lane_limit_kmh: float = 50.0
    single_lane_limit_kmh: float = 30.0

    def __post_init__(self) -> None:  # real roads lie well inside these ranges
        check_number("road lane_width_m", self.lane_width_m, 2.0, 6.0)
        check_number("road stop_line_setback_m", self.stop_line_setback_m, 3.0, 60.0)
        check_number("road stop_bar_depth_m", self.stop_bar_depth_m, 0.1, 2.0)
        check_number("road crosswalk_depth_m", self.crosswalk_depth_m, 1.0, 8.0)
        check_number("road signal_head_height_m", self.signal_head_height_m, 2.0, 12.0)
        check_number("road signal_housing_height_m", self.signal_housing_height_m, 0.3, 3.0)
        check_number("road longest_red_s", self.longest_red_s, 1.0, 600.0)
        check_number("road yellow_s", self.yellow_s, 0.5, 30.0)
        check_number("road light_beyond_stop_line_m", self.light_beyond_stop_line_m, 0.0, 80.0)
        check_number("road sign_before_stop_line_m", self.sign_before_stop_line_m, 0.0, 20.0)
        check_number("road sign_plate_size_m", self.sign_plate_size_m, 0.2, 2.0)
        check_number("road sign_plate_height_m", self.sign_plate_height_m, 0.5, 6.0)
        check_number("road multi_lane_limit_kmh", self.multi_lane_limit_kmh, 5.0, 200.0)
        check_number("road single_lane_limit_kmh", self.single_lane_limit_kmh, 5.0, 200.0)
        check_number("road zebra_to_centre_m", self.zebra_to_centre_m, 1.0, 40.0)
        check_number("road light_lateral_m", self.light_lateral_m, -20.0, 20.0)
        if self.kerb_lane_reach_m is not None:
            check_number("road kerb_lane_reach_m", self.kerb_lane_reach_m, 0.0, 60.0)
        for name in ("left_turn_radius_m", "right_turn_radius_m"):
            radius = getattr(self, name)
            if radius is not None:
                check_number(f"road {name}", radius, 3.0, 60.0)
        for name in ("lane_width_sd_m", "stop_line_setback_sd_m", "zebra_to_centre_sd_m", "kerb_lane_reach_sd_m",
                     "far_lane_shift_sd_m"):
            check_number(f"road {name}", getattr(self, name), 0.0, 20.0)
        check_number("road far_lane_turn_sd_deg", self.far_lane_turn_sd_deg, 0.0, 45.0)

    @property
    def kerb_lane_reach(self) -> float:
        """The stop bar's far edge to the centre of the lane a right turn goes into (its prior's mean)."""
        if self.kerb_lane_reach_m is not None:
            return self.kerb_lane_reach_m
        return self.stop_line_setback_m - 1.5 * self.lane_width_m

    @property
    def zebra_beyond_bar_m(self) -> float:
        """A stop bar's near edge to the far edge of the zebra beyond it, along the lane (the priors' means: the
        setback and the bar's depth, less the zebra's distance from the junction's centre)."""
        return self.stop_line_setback_m + self.stop_bar_depth_m - self.zebra_to_centre_m

    def two_lane_share(self, control: str | None, our_lanes: int | None) -> float:
        """How likely the cross street has two lanes each way at a junction whose arm ``control`` governs, on a
        road of ``our_lanes`` lanes each way (None: not seen). Kinds never measured pool the nearest ones."""
        odds: list[CrossStreetOdds] = []
        for c, n in ((control, our_lanes), (control, None), (None, our_lanes), (None, None)):
            odds = [o for o in self.cross_street_odds if c in (None, o.control) and n in (None, o.our_lanes)]
            if odds:
                break
        junctions = sum(o.junctions for o in odds)
        return sum(o.two_lane_share * o.junctions for o in odds) / junctions if junctions else 0.5

    def turn_reach(self, left: bool, two_lane_share: float, within_m: float | None = None,
                   lanes_to_kerb: int = 0) -> float | None:
        """The zebra's far edge to where the lane turned into crosses ours (``TurnReach``), expected over the cross
        street's lane count (one or two lanes each way, two with ``two_lane_share``), and with ``within_m`` kept
        within it of every count's lanes where it can be (``hedged_reach``). None when the design has no reach for
        a count that may be (``turn_reach_options``)."""
        options = self.turn_reach_options(left, two_lane_share, lanes_to_kerb)
        return None if options is None else hedged_reach(options, within_m)

    def turn_reach_options(self, left: bool, two_lane_share: float,
                           lanes_to_kerb: int = 0) -> list[tuple[float, float, float, float]] | None:
        """``hedged_reach``'s options beyond the zebra, one per lane count that may be: a left turn goes into the
        inner lane; a right turn from ``lanes_to_kerb`` lanes off our kerb ends ``right_turn_lanes_from_kerb`` off
        the cross street's. None when the design has no reach for a count that may be."""
        reaches = {r.cross_lanes: r for r in self.turn_reaches}
        weights = {1: 1.0 - two_lane_share, 2: two_lane_share}
        if any(w > 0 and n not in reaches for n, w in weights.items()):
            return None
        options = []
        for n, w in weights.items():
            if w > 0:
                near = reaches[n].left_m if left else reaches[n].right_m  # the inner lane, the kerb lane
                lanes = 0 if left else right_turn_lanes_from_kerb(lanes_to_kerb, n)
                options.append((w, near + lanes * self.lane_width_m, near, near + (n - 1) * self.lane_width_m))
        return options

    def right_turn_radius(self, our_lanes: int | None, cross_odds: dict[int, float]) -> float | None:
        """A right turn's radius from the kerb lane of a road of ``our_lanes`` lanes each way (None: not seen),
        expected over the cross street's lane count (``cross_odds``: count to its probability): each count's
        ``TurnRadius``, or ``right_turn_radius_m`` where the pairing is not listed."""
        radii = {(r.our_lanes, r.cross_lanes): r.right_m for r in self.right_turn_radii}
        each = [(p, radii.get((our_lanes, n), self.right_turn_radius_m)) for n, p in cross_odds.items() if p > 0]
        if our_lanes is None or not each or any(r is None for _, r in each):
            return self.right_turn_radius_m
        return sum(p * r for p, r in each) / sum(p for p, _ in each)  # type: ignore[operator]

    @property
    def signal_mounts(self) -> tuple[SignalMount, ...]:
        """Every place the design hangs a signal head: the mast arm of the scalar fields, then the others."""
        main = SignalMount(self.light_beyond_stop_line_m, self.light_lateral_m, self.signal_head_height_m)
        return (main, *self.other_signal_mounts)


# The rules of the road as the world judges them and every driver obeys them (``sim.rules``, ``sim.traffic``, the
# autopilot and the camera-only agent read them here, so the numbers cannot drift apart).
STOP_SPEED_MPS = 0.1  # under this a vehicle stands (a full stop)
STOP_ZONE_M = 3.0  # a full stop counts with the front bumper this far before the line, at most
YIELD_APPROACH_MPS = 4.0  # the speed at a give-way line a driver can still stop from (and look)
YIELD_GAP_S = 5.0  # the gap a driver at a stop or give-way line accepts in priority traffic
CURVE_LATERAL_ACCEL_MPS2 = 2.0  # comfortable lateral acceleration in turns and bends
CURVE_BRAKE_MPS2 = 2.5  # how hard one slows down ahead of a turn or a lower limit
KMH = 1 / 3.6  # m/s per km/h


WEATHERS = ("dusk", "night", "noon", "overcast")  # the lighting presets (sim.render.LIGHTING_PRESETS), sorted
# The route command's codes (the observation's "command", sim.town.Command): what each number asks for.
COMMAND_NAMES = {0: "follow", 1: "left", 2: "right", 3: "straight"}
COMMAND_CODES = {name: code for code, name in COMMAND_NAMES.items()}
STEP_S = 0.05  # the simulation's time step (WorldConfig.dt_s)
EPISODE_S = 180.0  # an episode's time limit (DriveConfig.max_time_s)
CAMERA = CameraConfig()
MIRRORS = MirrorRig()
CORNERS = CornerRig()
VEHICLE = VehicleSpec()
ROAD = RoadDesign()
# The forward camera to the front bumper along the car's axis (1.3 m with the default rig).
CAMERA_TO_FRONT_M = round(VEHICLE.length_m / 2 - CAMERA.mount_forward_m, 6)
