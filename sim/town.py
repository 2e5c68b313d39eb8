"""Procedural town: a grid of blocks joined by two-way streets with junctions, signals and signs.

The drivable lanes live in a highway-env ``RoadNetwork`` (``StraightLane`` and ``CircularLane``),
so IDM/MOBIL vehicles drive on it unchanged. Everything else the town holds (road surfaces,
markings, sidewalks, buildings, trees, light poles, crosswalks) is plain 2D geometry plus heights,
which the renderer turns into meshes and the world uses for collisions. The town knows nothing of
pybullet.

Layout: a grid of ``(blocks_x + 1) x (blocks_y + 1)`` nodes. The four outer corners are curved
bends; every other node is a junction (four arms inside, three on the border). Node names in the
network are ``"i-j" + arm + "i"|"o"``: the end of a road arriving at that node via that arm ("i")
or the start of a road leaving by it ("o").

Each grid line is one street: an arterial (two lanes each way) or a residential street (one lane
each way, with a parking strip where the style parks cars). Each junction has one control: signals,
an all-way stop, or priority for one street with the other stopping or giving way. The town's
style (``sim.town_style``) sets the mix; the classic style is arterials and signals everywhere.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import IntEnum

import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, LineType, StraightLane
from highway_env.road.road import RoadNetwork

from towndrive.sim.fillet_lane import FilletLane
from towndrive.sim.geometry import right_of, wrap_to_pi
from towndrive.sim.objects import CAR_COLORS
from towndrive.sim.path_filter import ROW_SIZE, lane_row, lanes_may_hold
from towndrive.sim.spec import COMMAND_NAMES, ROAD, VEHICLE
from towndrive.sim.town_style import CLASSIC, TownStyle, style_named
from towndrive.sim.town_warp import TownWarp, warp_town

LaneIndex = tuple[str, str, int]
LaneLocation = tuple[LaneIndex, float, float]  # lane index, longitudinal s, lateral offset
Edge = tuple[str, str]


class Arm(IntEnum):
    """Directions of the arms of a node, in the map frame (y down: S is +y)."""

    E = 0
    S = 1
    W = 2
    N = 3


ARM_VEC: dict[Arm, np.ndarray] = {
    Arm.E: np.array([1.0, 0.0]),
    Arm.S: np.array([0.0, 1.0]),
    Arm.W: np.array([-1.0, 0.0]),
    Arm.N: np.array([0.0, -1.0]),
}
OPPOSITE = {Arm.E: Arm.W, Arm.W: Arm.E, Arm.S: Arm.N, Arm.N: Arm.S}


class Command(IntEnum):
    """Route command given before an intersection (conditional imitation learning style)."""

    FOLLOW = 0
    LEFT = 1
    RIGHT = 2
    STRAIGHT = 3


assert {int(c): c.name.lower() for c in Command} == COMMAND_NAMES, "sim.spec.COMMAND_NAMES names the commands"


def lanes_for(command: Command, lane_count: int = 2) -> tuple[int, ...]:
    """Lanes a junction move may start from, on a road of ``lane_count`` lanes each way: left turns
    from the inner lane (0), right turns from the outer lane, straight from any. The network has every
    lane on every connector, but turning across another lane's straight traffic (or into an opposing
    left turn) is not allowed."""
    if command == Command.LEFT:
        return (0,)
    if command == Command.RIGHT:
        return (lane_count - 1,)
    return tuple(range(lane_count))


class Control(IntEnum):
    """What governs traffic entering a junction by one arm."""

    SIGNAL = 0  # a traffic light (the entry's ``approach``)
    ALL_WAY_STOP = 1  # stop, then go in turn: every arm of the junction stops
    STOP = 2  # stop, then give way to the priority street
    YIELD = 3  # give way to the priority street without having to stop
    PRIORITY = 4  # the priority street at a stop or yield junction: nothing to obey


class SignKind(IntEnum):
    STOP = 0
    YIELD = 1
    SPEED_LIMIT = 2


@dataclass(frozen=True)
class TownConfig:
    """Size and look of a town. Defaults make a 3x3-block town of about 300 m x 300 m."""

    blocks_x: int = 3
    blocks_y: int = 3
    block_size_m: float = 95.0
    block_jitter_m: float = 12.0
    lane_width_m: float = ROAD.lane_width_m
    sidewalk_width_m: float = 3.5
    bend_radius_m: float = 22.0
    stop_line_setback_m: float = ROAD.stop_line_setback_m
    park_probability: float = 0.15
    tree_spacing_m: float = 16.0
    outer_buildings: bool = True
    style: str = CLASSIC.name  # sim.town_style: the mix of streets, junctions, signs and scenery

    @classmethod
    def of_style(cls, name: str, **overrides: object) -> TownConfig:
        """The config of a named style, with its block size, trees and parks (other fields as given)."""
        style = style_named(name)
        fields: dict[str, object] = dict(style=style.name, block_size_m=style.block_size_m,
                                         block_jitter_m=style.block_jitter_m, tree_spacing_m=style.tree_spacing_m,
                                         park_probability=style.park_probability)
        fields.update(overrides)
        return cls(**fields)  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        style_named(self.style)
        if self.blocks_x < 1 or self.blocks_y < 1:
            raise ValueError("A town needs at least one block in each direction (blocks_x, blocks_y >= 1).")
        if self.block_size_m - self.block_jitter_m < 2 * self.stop_line_setback_m + 30:
            raise ValueError("block_size_m is too small for junctions and buildings; use at least 60 m.")


@dataclass(frozen=True)
class LaneInfo:
    """What a lane of the network is for."""

    kind: str  # "road", "connector" (inside a junction) or "bend" (curved town corner)
    node: tuple[int, int] | None  # the junction or bend a connector/bend belongs to
    command: Command  # the command that selects this lane at a junction (FOLLOW elsewhere)


@dataclass(frozen=True)
class Approach:
    """One signalled approach to a junction: its incoming road, stop line and traffic light."""

    index: int
    node: tuple[int, int]
    arm: Arm  # the arm the traffic arrives from
    edge: Edge  # the incoming road edge (ends at the stop line)
    stop_line_center: np.ndarray  # middle of the stop bar's near edge, map frame
    travel_heading: float  # heading of traffic arriving on this approach
    light_pole: np.ndarray  # pole foot
    light_head: np.ndarray  # head position (x, y)
    mount: str = "mast_arm"  # "mast_arm" (over the lanes), "far_pole" or "near_pole" (on a post at that corner)
    head_height_m: float = ROAD.signal_head_height_m  # the head's centre above the road


@dataclass(frozen=True)
class Entry:
    """One arm by which traffic enters a junction, whatever controls it (signalled ones have an approach)."""

    index: int
    node: tuple[int, int]
    arm: Arm
    edge: Edge  # the incoming road edge (ends at the stop or give-way line)
    line_center: np.ndarray  # middle of the stop or give-way line's near edge (where a stop is made)
    travel_heading: float
    control: Control
    approach: int  # the signalled approach (Control.SIGNAL), else -1
    lane_count: int  # lanes arriving


@dataclass(frozen=True)
class Sign:
    """A road sign on a post beside the road, facing the traffic it addresses."""

    index: int
    kind: SignKind
    position: np.ndarray  # post foot (x, y)
    facing: float  # heading of the traffic that reads it (the plate's face looks the other way)
    edge: Edge  # the road it stands on (stop/yield: the entry's road; limits: the road they start)
    value_kmh: int = 0  # speed limits: the posted limit
    plate_height_m: float = ROAD.sign_plate_height_m  # the plate's centre above the road
    plate_size_m: float = ROAD.sign_plate_size_m  # the plate's width


@dataclass(frozen=True)
class ParkedCar:
    """A car standing in a parking strip (static: part of the scenery and of the obstacles)."""

    position: np.ndarray
    heading: float
    length_m: float
    width_m: float
    height_m: float
    color: tuple[float, float, float]


@dataclass(frozen=True)
class Crosswalk:
    """A zebra crossing across one arm of a junction, kerb to kerb."""

    index: int
    node: tuple[int, int]
    arm: Arm
    start: np.ndarray  # waiting point on one kerb
    end: np.ndarray  # waiting point on the other kerb
    polygon: np.ndarray  # 4x2 painted area
    approach: int  # the approach whose traffic it crosses (its arm's incoming lanes)


@dataclass(frozen=True)
class Building:
    footprint: np.ndarray  # 4x2, axis aligned rectangle corners
    height_m: float
    color: tuple[float, float, float]


@dataclass(frozen=True)
class Tree:
    position: np.ndarray
    height_m: float
    canopy_radius_m: float
    color: tuple[float, float, float]


@dataclass
class Town:
    """A generated town: road network, lane metadata, signals, and static scenery."""

    config: TownConfig
    seed: int
    xs: np.ndarray
    ys: np.ndarray
    network: RoadNetwork
    lane_info: dict[LaneIndex, LaneInfo]
    approaches: list[Approach]
    crosswalks: list[Crosswalk]
    buildings: list[Building]
    trees: list[Tree]
    road_polygons: list[np.ndarray]  # convex asphalt pieces
    slab_polygons: list[np.ndarray]  # convex raised sidewalk/block pieces
    grass_polygons: list[np.ndarray]  # parks on top of slabs
    markings: dict[str, list[np.ndarray]]  # kind -> convex quads
    poles: list[np.ndarray] = field(default_factory=list)  # light pole feet (collision circles)
    entries: list[Entry] = field(default_factory=list)  # every junction arm, signalled or not
    signs: list[Sign] = field(default_factory=list)
    parked_cars: list[ParkedCar] = field(default_factory=list)
    speed_limits_kmh: dict[Edge, int] = field(default_factory=dict)  # posted limits by edge (none in classic towns)
    exit_lanes: dict[LaneIndex, int] = field(default_factory=dict)  # connector lane -> lane of the road it joins
    #   (only where the two streets have different lane counts; elsewhere a lane keeps its number)
    lane_width_m: float = 0.0  # every lane's width (drawn per town by the style; 0: the config's)
    warp: TownWarp | None = None  # how the square layout was bent (sim.town_warp); None: square
    kerb_outlines: list[np.ndarray] = field(default_factory=list)  # a bent town's slab outlines (else the slabs')
    _entry_by_edge: dict[Edge, Entry] = field(default_factory=dict, repr=False)
    _grid: dict[tuple[int, int], list[LaneIndex]] = field(default_factory=dict, repr=False)
    _approach_by_edge: dict[Edge, Approach] = field(default_factory=dict, repr=False)
    _lane_crosswalks: dict[LaneIndex, list[tuple[int, float, float]]] | None = field(default=None, repr=False)
    _cell_rows: dict[tuple[int, int], tuple[list[LaneIndex], list[AbstractLane], np.ndarray]] = field(
        default_factory=dict, repr=False, compare=False)
    _crosswalk_frames: list[tuple[np.ndarray, np.ndarray, float, float, np.ndarray]] | None = field(
        default=None, repr=False, compare=False)
    _entries_by_node: dict[tuple[int, int], list[Entry]] | None = field(default=None, repr=False, compare=False)

    GRID_CELL_M = 8.0
    POLE_RADIUS_M = 0.15
    TRUNK_RADIUS_M = 0.25
    LIGHT_HEAD_HEIGHT_M = ROAD.signal_head_height_m

    # ----------------------------------------------------------------- lanes
    @property
    def lane_width(self) -> float:
        return self.lane_width_m or self.config.lane_width_m

    def lane(self, index: LaneIndex) -> AbstractLane:
        return self.network.graph[index[0]][index[1]][index[2]]

    def lanes_near(self, position: np.ndarray) -> list[LaneIndex]:
        """Lanes that pass within about a lane width of a point (spatial hash, no full scan)."""
        key = (int(math.floor(position[0] / self.GRID_CELL_M)), int(math.floor(position[1] / self.GRID_CELL_M)))
        return self._grid.get(key, [])

    def locate(self, position: np.ndarray, heading: float | None = None) -> LaneLocation | None:
        """The lane a pose is on: (lane index, longitudinal s, lateral offset), or None off road.

        Among overlapping lanes (junctions), prefer the one whose direction best matches the
        heading, then the smallest lateral offset.
        """
        if heading is None:
            return self.locate_both(position, 0.0)[1]
        return self.locate_both(position, heading)[0]

    def locate_both(self, position: np.ndarray, heading: float) -> tuple[LaneLocation | None, LaneLocation | None]:
        """``locate`` with the heading and without it, in one pass over the nearby lanes (the world
        needs both for the ego every step). Lanes the point is clearly not on are skipped by a
        conservative compiled test first; the rest go through highway-env's exact geometry."""
        best: tuple[float, LaneIndex, float, float] | None = None
        nearest: tuple[float, LaneIndex, float, float] | None = None
        half = self.lane_width / 2
        indices, lanes, rows = self._cell_lanes(position)
        if not indices:
            return None, None
        keep = lanes_may_hold(float(position[0]), float(position[1]), rows, half + 0.05, 0.5)
        for index, lane, ok in zip(indices, lanes, keep, strict=True):
            if not ok:
                continue
            s, lat = lane.local_coordinates(position)
            if not (-0.5 <= s <= lane.length + 0.5) or abs(lat) > half + 0.05:
                continue
            cost = abs(lat)
            if nearest is None or cost < nearest[0]:
                nearest = (cost, index, float(s), float(lat))
            cost += 4.0 * abs(wrap_to_pi(lane.heading_at(s) - heading))
            if best is None or cost < best[0]:
                best = (cost, index, float(s), float(lat))
        return (None if best is None else best[1:]), (None if nearest is None else nearest[1:])

    def _cell_lanes(self, position: np.ndarray) -> tuple[list[LaneIndex], list[AbstractLane], np.ndarray]:
        """The spatial hash's lanes for a point's cell (as ``lanes_near``), the lane objects and their
        flat parameters, built once per cell."""
        key = (int(math.floor(position[0] / self.GRID_CELL_M)), int(math.floor(position[1] / self.GRID_CELL_M)))
        hit = self._cell_rows.get(key)
        if hit is None:
            indices = self._grid.get(key, [])
            lanes = [self.lane(i) for i in indices]
            rows = np.stack([lane_row(lane) for lane in lanes]) if lanes else np.zeros((0, ROW_SIZE))
            hit = (indices, lanes, rows)
            self._cell_rows[key] = hit
        return hit

    def on_road(self, position: np.ndarray, margin_m: float = 0.0) -> bool:
        """Whether a point is on asphalt: within some lane's width (plus a margin)."""
        half = self.lane_width / 2 + margin_m
        for index in self.lanes_near(position):
            lane = self.lane(index)
            s, lat = lane.local_coordinates(position)
            if -0.5 <= s <= lane.length + 0.5 and abs(lat) <= half:
                return True
        return False

    def lane_count(self, edge: Edge) -> int:
        return len(self.network.graph[edge[0]][edge[1]])

    def next_lane(self, index: LaneIndex, edge: Edge) -> LaneIndex:
        """The lane of ``edge`` that lane ``index`` runs on into (the same number unless the lane counts differ)."""
        k = self.exit_lanes.get(index, index[2])
        return (edge[0], edge[1], min(k, self.lane_count(edge) - 1))

    def entry_for_edge(self, edge: Edge) -> Entry | None:
        """The junction entry an incoming road edge leads to (None at bends)."""
        return self._entry_by_edge.get(edge)

    def entries_at(self, node: tuple[int, int]) -> list[Entry]:
        """The entries of one junction (indexed once)."""
        if self._entries_by_node is None:
            self._entries_by_node = {}
            for e in self.entries:
                self._entries_by_node.setdefault(e.node, []).append(e)
        return self._entries_by_node.get(node, [])

    def speed_limit_kmh(self, edge: Edge) -> int | None:
        """The posted limit on an edge, None where nothing is posted."""
        return self.speed_limits_kmh.get(edge)

    def approach_for_edge(self, edge: Edge) -> Approach | None:
        """The signalled approach an incoming road edge leads to, if any."""
        return self._approach_by_edge.get(edge)

    def approach_at(self, node: tuple[int, int], arm: Arm) -> Approach | None:
        """The approach arriving at a junction by one of its arms (None where the arm does not exist)."""
        for ap in self.approaches:
            if ap.node == node and ap.arm == arm:
                return ap
        return None

    def crosswalks_on(self, index: LaneIndex) -> list[tuple[int, float, float]]:
        """Crosswalks a lane runs across: (crosswalk index, s where it enters, s where it leaves)."""
        if self._lane_crosswalks is None:
            self._lane_crosswalks = _lane_crosswalks(self)
        return self._lane_crosswalks.get(index, [])

    def crosswalk_frames(self) -> list[tuple[np.ndarray, np.ndarray, float, float, np.ndarray]]:
        """``crosswalk_frame`` of every crossing plus the unit vector across it, built once: NPCs
        look at crossings every decision, and the frames never change."""
        if self._crosswalk_frames is None:
            frames = [crosswalk_frame(cw) for cw in self.crosswalks]
            self._crosswalk_frames = [(c, u, d, w, np.array([-u[1], u[0]])) for c, u, d, w in frames]
        return self._crosswalk_frames

    def road_lanes(self) -> list[LaneIndex]:
        """Lanes on plain road segments (spawn places)."""
        return [k for k, v in self.lane_info.items() if v.kind == "road"]

    def node_position(self, node: tuple[int, int]) -> np.ndarray:
        """A junction's or bend's centre (where its streets' centre lines cross)."""
        centre = np.array([float(self.xs[node[0]]), float(self.ys[node[1]])])
        return centre if self.warp is None else self.warp.point(centre)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the whole scene, scenery included."""
        m = 60.0
        if self.warp is None:
            return (float(self.xs[0] - m), float(self.ys[0] - m), float(self.xs[-1] + m), float(self.ys[-1] + m))
        corners = np.array([self.node_position(n) for n in ((0, 0), (len(self.xs) - 1, 0), (0, len(self.ys) - 1),
                                                            (len(self.xs) - 1, len(self.ys) - 1))])
        lo, hi = corners.min(axis=0) - m, corners.max(axis=0) + m
        return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


# --------------------------------------------------------------------------- generation
BUILDING_COLORS = [
    (0.78, 0.70, 0.58), (0.66, 0.40, 0.32), (0.85, 0.83, 0.78), (0.55, 0.58, 0.62),
    (0.72, 0.55, 0.42), (0.90, 0.78, 0.55), (0.45, 0.47, 0.52), (0.80, 0.62, 0.55),
    (0.62, 0.68, 0.72), (0.93, 0.90, 0.84),
]


def _node_name(node: tuple[int, int], arm: Arm, end: str) -> str:
    return f"{node[0]}-{node[1]}{arm.name}{end}"


def _arms(node: tuple[int, int], nx: int, ny: int) -> list[Arm]:
    i, j = node
    arms = []
    if i < nx:
        arms.append(Arm.E)
    if j < ny:
        arms.append(Arm.S)
    if i > 0:
        arms.append(Arm.W)
    if j > 0:
        arms.append(Arm.N)
    return arms


def _is_bend(node: tuple[int, int], nx: int, ny: int) -> bool:
    return node[0] in (0, nx) and node[1] in (0, ny)


def _arc_lane(center: np.ndarray, start: np.ndarray, end: np.ndarray, width: float) -> CircularLane:
    """A quarter-circle lane about ``center`` from ``start`` to ``end`` (both at the same radius)."""
    radius = float(np.linalg.norm(start - center))
    a0 = math.atan2(start[1] - center[1], start[0] - center[0])
    a1 = math.atan2(end[1] - center[1], end[0] - center[0])
    delta = wrap_to_pi(a1 - a0)
    return CircularLane(center, radius, a0, a0 + delta, clockwise=delta > 0, width=width,
                        line_types=(LineType.NONE, LineType.NONE))


def _sample_lane(lane: AbstractLane, lateral: float, step_m: float) -> np.ndarray:
    n = max(2, int(math.ceil(lane.length / step_m)) + 1)
    return np.array([lane.position(s, lateral) for s in np.linspace(0.0, lane.length, n)])


def _strip_quads(lane: AbstractLane, lat0: float, lat1: float, s0: float, s1: float, step_m: float) -> list[np.ndarray]:
    """Convex quads covering a lane-aligned strip between two lateral offsets."""
    straight = isinstance(lane, StraightLane)
    n = 1 if straight else max(1, int(math.ceil((s1 - s0) / step_m)))
    ss = np.linspace(s0, s1, n + 1)
    quads = []
    for a, b in zip(ss[:-1], ss[1:], strict=True):
        quads.append(np.array([lane.position(a, lat0), lane.position(b, lat0), lane.position(b, lat1), lane.position(a, lat1)]))
    return quads


def _dashes(lane: AbstractLane, lateral: float, half_width: float, dash: float, gap: float) -> list[np.ndarray]:
    quads = []
    s = gap / 2
    while s + dash <= lane.length:
        quads += _strip_quads(lane, lateral - half_width, lateral + half_width, s, s + dash, 1.5)
        s += dash + gap
    return quads


JUNCTION_KERB_RADIUS_M = 3.0


def _rounded_rect(x0: float, y0: float, x1: float, y1: float, radii: list[float], segments: int = 6) -> np.ndarray:
    """Convex polygon of a rectangle whose corners (TL, TR, BR, BL on the map) are rounded."""
    corners = [(x0, y0, 1, 1), (x1, y0, -1, 1), (x1, y1, -1, -1), (x0, y1, 1, -1)]
    pts = []
    for k, ((cx, cy, ix, iy), r) in enumerate(zip(corners, radii, strict=True)):
        centre = np.array([cx + ix * r, cy + iy * r])
        for t in np.linspace(math.pi + k * math.pi / 2, math.pi + (k + 1) * math.pi / 2, segments + 1):
            pts.append(centre + r * np.array([math.cos(t), math.sin(t)]))
    return np.array(pts)


def _rect(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


@dataclass(frozen=True)
class _Street:
    """One grid line's street: lanes each way, their width, the parking strip and the posted limit."""

    lanes: int
    lane_width_m: float
    parking_m: float
    limit_kmh: int | None

    @property
    def half_width_m(self) -> float:
        """Centre line to kerb."""
        return self.lanes * self.lane_width_m + self.parking_m

    @property
    def arterial(self) -> bool:
        return self.lanes == 2


_CONTROL_DRAW = (Control.SIGNAL, Control.ALL_WAY_STOP, Control.STOP, Control.YIELD)
_MOUNTS = ("mast_arm", "far_pole", "near_pole")
POLE_HEAD_HEIGHT_M = 3.6  # a post-mounted head's centre above the road
CROSSWALK_GAP_M = 0.6  # kerb line of the crossing street to the zebra
CORNER_TO_ZEBRA_M = 0.3  # where corners are rounded wide (styles), the zebra starts this far past the rounding
POLE_FROM_KERB_M = 1.25  # a signal pole stands this far inside a corner's kerb (the classic corner's spacing)
STOP_BAR_GAP_M = 0.5  # zebra to the stop bar, at least
PARKED_SLOT_M = 6.0  # one parked car's share of the kerb
PARKING_CLEAR_M = 10.0  # no parking this near a road's ends (the junction's mouth)
LIMIT_SIGN_AFTER_M = 8.0  # a limit sign stands this far into the road it governs
STOP_SIGN_BEFORE_M = ROAD.sign_before_stop_line_m  # a stop or yield sign stands this far before the line
LIMIT_REPEAT_CHANCE = 0.3  # chance of a limit sign on a road where the limit does not change


def _streets(style: TownStyle, config: TownConfig, w: float, column_scale: float,
             mix: np.random.Generator) -> tuple[list[_Street], list[_Street]]:
    """The street of every column line (x = xs[i]) and row line (y = ys[j]); the ring's lines share one.

    ``column_scale``: columns are built this much wider across x, so that the skew (``sim.town_warp``), which
    leans them, leaves them their true width."""
    nx, ny = config.blocks_x, config.blocks_y

    def kinds(scale: float) -> tuple[_Street, _Street]:
        return (_Street(2, w * scale, 0.0, style.arterial_limit_kmh),
                _Street(1, w * scale, style.parking_strip_m * scale, style.residential_limit_kmh))

    def line(k: int, last: int, scale: float) -> _Street:
        arterial, residential = kinds(scale)
        if k in (0, last):
            return arterial if style.ring_arterial else residential
        return arterial if mix.random() < style.arterial_share else residential

    return [line(i, nx, column_scale) for i in range(nx + 1)], [line(j, ny, 1.0) for j in range(ny + 1)]


def _street_of(arm: Arm, node: tuple[int, int], cols: list[_Street], rows: list[_Street]) -> _Street:
    """The street an arm of a node lies on (E/W arms on the node's row, N/S arms on its column)."""
    return rows[node[1]] if arm in (Arm.E, Arm.W) else cols[node[0]]


def _cross_street(arm: Arm, node: tuple[int, int], cols: list[_Street], rows: list[_Street]) -> _Street:
    """The other street at a node: the one an arm's traffic crosses."""
    return cols[node[0]] if arm in (Arm.E, Arm.W) else rows[node[1]]


def _junction_controls(style: TownStyle, node: tuple[int, int], arms: list[Arm], cols: list[_Street],
                       rows: list[_Street], border: bool, mix: np.random.Generator) -> dict[Arm, Control]:
    """Each arm's control at one junction, drawn from the style's mix for the pairing of its streets."""
    row, col = rows[node[1]], cols[node[0]]
    pair = (style.arterial_pair if row.arterial and col.arterial
            else style.residential_pair if not row.arterial and not col.arterial else style.mixed_pair)
    weights = np.array(pair.weights(), float)
    kind = _CONTROL_DRAW[int(mix.choice(len(weights), p=weights / weights.sum()))] if weights.sum() > 0 else Control.SIGNAL
    if kind in (Control.SIGNAL, Control.ALL_WAY_STOP):
        return {a: kind for a in arms}
    # Priority junction: the arterial has priority over a residential street; between equals, the street
    # that runs through a T-junction, else one drawn.
    if row.arterial != col.arterial:
        major_row = row.arterial
    elif border:
        major_row = sum(a in (Arm.E, Arm.W) for a in arms) == 2
    else:
        major_row = bool(mix.random() < 0.5)
    return {a: Control.PRIORITY if (a in (Arm.E, Arm.W)) == major_row else kind for a in arms}


LEFT_TURN_RADIUS_M = 10.0  # a left turn's arc: this plus the lane's offset from the centre line
TURN_RADIUS_MARGIN = 1.15  # no turn tighter than the car's full-lock circle times this


def _turn_lane(corner_centre: np.ndarray, start: np.ndarray, heading_in: float, end: np.ndarray, heading_out: float,
               width: float, radius_m: float | None) -> AbstractLane:
    """A fillet of ``radius_m`` (straight on past the stop line, round the corner, straight out); with no radius
    (classic junctions, bends) the quarter circle about ``corner_centre`` where start and end lie on one, else
    the largest fillet."""
    if radius_m is None and abs(float(np.linalg.norm(start - corner_centre)) -
                                float(np.linalg.norm(end - corner_centre))) < 1e-9:
        return _arc_lane(corner_centre, start, end, width)
    return FilletLane(start, heading_in, end, heading_out, width, radius_m)


def generate_town(config: TownConfig | None = None, seed: int = 0) -> Town:
    """Build a town from a config and a seed; the same pair always gives the same town.

    The style's draws (streets, controls, mounts, setbacks, signs, parked cars) come from their own
    generator, so the classic style draws exactly what it always drew from the main one."""
    config = config or TownConfig()
    style = style_named(config.style)
    rng = np.random.default_rng(seed)
    mix = np.random.default_rng([seed, 30])
    nx, ny = config.blocks_x, config.blocks_y
    w = config.lane_width_m if style.name == CLASSIC.name else round(float(mix.uniform(*style.lane_width_range_m)), 2)
    skew = float(mix.uniform(*style.skew_deg)) * (1.0 if mix.random() < 0.5 else -1.0) if style.skew_deg[1] > 0 else 0.0
    bows = tuple(float(mix.uniform(*style.bow_m)) * (1.0 if mix.random() < 0.5 else -1.0)
                 if style.bow_m[1] > 0 else 0.0 for _ in range(2))
    cols, rows = _streets(style, config, w, 1.0 / math.cos(math.radians(skew)), mix)
    sw = config.sidewalk_width_m
    rc = config.bend_radius_m
    palette = list(style.building_colors) or BUILDING_COLORS

    steps_x = config.block_size_m + rng.uniform(-config.block_jitter_m, config.block_jitter_m, nx)
    steps_y = config.block_size_m + rng.uniform(-config.block_jitter_m, config.block_jitter_m, ny)
    xs = np.concatenate([[0.0], np.cumsum(steps_x)])
    ys = np.concatenate([[0.0], np.cumsum(steps_y)])

    def centre(node: tuple[int, int]) -> np.ndarray:
        return np.array([xs[node[0]], ys[node[1]]])

    nodes = [(i, j) for i in range(nx + 1) for j in range(ny + 1)]
    corner = style.corner_radius_m or JUNCTION_KERB_RADIUS_M  # kerb radius at junction corners
    zebra_gap = CROSSWALK_GAP_M if style.corner_radius_m is None else corner + CORNER_TO_ZEBRA_M
    # Stop-line setbacks, per junction arm: beyond the crossing street's kerb (and its corner), its zebra and a gap.
    setback: dict[tuple[tuple[int, int], Arm], float] = {}
    controls: dict[tuple[int, int], dict[Arm, Control]] = {}
    mounts: dict[tuple[int, int], str] = {}
    for node in nodes:
        arms = _arms(node, nx, ny)
        if _is_bend(node, nx, ny):
            for a in arms:
                setback[(node, a)] = rc
            continue
        extra = None if style.setback_extra_m is None else float(mix.uniform(*style.setback_extra_m))
        for a in arms:
            if extra is None:
                setback[(node, a)] = config.stop_line_setback_m
            else:
                need = _cross_street(a, node, cols, rows).half_width_m + zebra_gap + ROAD.crosswalk_depth_m
                setback[(node, a)] = round(need + STOP_BAR_GAP_M + extra, 2)
        controls[node] = _junction_controls(style, node, arms, cols, rows, len(arms) == 3, mix)
        if Control.SIGNAL in controls[node].values():
            mw = np.array(style.mounts.weights(), float)
            mounts[node] = _MOUNTS[int(mix.choice(len(mw), p=mw / mw.sum()))]

    def attach(node: tuple[int, int], arm: Arm) -> float:
        return setback[(node, arm)]

    def turn_radius(node: tuple[int, int], arm_in: Arm, arm_out: Arm, k_in: int, k_out: int,
                    command: Command) -> float | None:
        """A turn's design radius at a junction of a styled town (None: the classic quarter circle). A right turn
        goes round the corner's kerb arc at its lanes' distance from the kerbs (never tighter than the car can)."""
        if style.name == CLASSIC.name or _is_bend(node, nx, ny):
            return None
        s_in, s_out = _street_of(arm_in, node, cols, rows), _street_of(arm_out, node, cols, rows)
        if command == Command.LEFT:
            return LEFT_TURN_RADIUS_M + (k_in + 0.5) * s_in.lane_width_m
        clear_in = s_in.half_width_m - (k_in + 0.5) * s_in.lane_width_m
        clear_out = s_out.half_width_m - (k_out + 0.5) * s_out.lane_width_m
        return max(corner + min(clear_in, clear_out), VEHICLE.min_turn_radius_m * TURN_RADIUS_MARGIN)

    network = RoadNetwork()
    lane_info: dict[LaneIndex, LaneInfo] = {}
    exit_lanes: dict[LaneIndex, int] = {}
    road_polys: list[np.ndarray] = []
    markings: dict[str, list[np.ndarray]] = {"dashed_white": [], "solid_white": [], "solid_yellow": [],
                                              "stop_line": [], "crosswalk": [], "yield_line": []}
    line_half = 0.07

    def add_markings(lanes: list[AbstractLane], street: _Street, with_centre: bool) -> None:
        """Markings of one direction of a road: its half of the centre line, lane dividers and edge line
        (at the lane's edge where a parking strip lies beyond it)."""
        lane0, outer = lanes[0], lanes[-1]
        lw = street.lane_width_m
        if with_centre:
            markings["solid_yellow"] += _strip_quads(lane0, -lw / 2 + 0.06, -lw / 2 + 0.06 + 2 * line_half, 0, lane0.length, 2.0)
        for k in range(1, len(lanes)):
            markings["dashed_white"] += _dashes(lanes[k - 1], lw / 2, line_half, 3.0, 6.0)
        edge = lw / 2 - 2 * line_half if street.parking_m > 0 else lw / 2 - 0.35
        markings["solid_white"] += _strip_quads(outer, edge, edge + 2 * line_half, 0, outer.length, 2.0)

    # Roads between neighbouring nodes, both directions.
    speed_limits: dict[Edge, int] = {}
    street_of_edge: dict[Edge, _Street] = {}
    for node in nodes:
        for arm in _arms(node, nx, ny):
            street = _street_of(arm, node, cols, rows)
            d = ARM_VEC[arm]
            nbr = (node[0] + int(d[0]), node[1] + int(d[1]))
            a = centre(node) + d * attach(node, arm)
            b = centre(nbr) - d * attach(nbr, OPPOSITE[arm])
            r = right_of(d)
            lw = street.lane_width_m
            lanes = [StraightLane(a + r * (k + 0.5) * lw, b + r * (k + 0.5) * lw, width=w,
                                  line_types=(LineType.NONE, LineType.NONE)) for k in range(street.lanes)]
            frm, to = _node_name(node, arm, "o"), _node_name(nbr, OPPOSITE[arm], "i")
            street_of_edge[(frm, to)] = street
            for k, lane in enumerate(lanes):
                network.add_lane(frm, to, lane)
                lane_info[(frm, to, k)] = LaneInfo("road", None, Command.FOLLOW)
            road_polys += _strip_quads(lanes[0], -lw / 2, street.half_width_m - lw / 2, 0, lanes[0].length, 2.0)
            add_markings(lanes, street, with_centre=True)
            if street.limit_kmh is not None:
                speed_limits[(frm, to)] = street.limit_kmh

    # Junction connectors, bends, stop lines, crosswalks, lights, signs.
    approaches: list[Approach] = []
    entries: list[Entry] = []
    crosswalks: list[Crosswalk] = []
    signs: list[Sign] = []
    poles: list[np.ndarray] = []
    for node in nodes:
        c = centre(node)
        arms = _arms(node, nx, ny)
        bend = _is_bend(node, nx, ny)
        for a in arms:
            travel = -ARM_VEC[a]
            n_in, w_in = _street_of(a, node, cols, rows).lanes, _street_of(a, node, cols, rows).lane_width_m
            for b in arms:
                if b == a:
                    continue
                out_dir = ARM_VEC[b]
                n_out, w_out = _street_of(b, node, cols, rows).lanes, _street_of(b, node, cols, rows).lane_width_m
                if np.allclose(out_dir, travel):
                    command = Command.STRAIGHT
                elif np.allclose(out_dir, right_of(travel)):
                    command = Command.RIGHT
                else:
                    command = Command.LEFT
                frm, to = _node_name(node, a, "i"), _node_name(node, b, "o")
                for k in range(n_in):
                    # Left turns keep to the inner lanes, right turns to the outer ones.
                    k_out = min(k, n_out - 1) if command != Command.RIGHT else min(max(k + n_out - n_in, 0), n_out - 1)
                    start = c + ARM_VEC[a] * attach(node, a) + right_of(travel) * (k + 0.5) * w_in
                    end = c + out_dir * attach(node, b) + right_of(out_dir) * (k_out + 0.5) * w_out
                    if command == Command.STRAIGHT:
                        lane: AbstractLane = StraightLane(start, end, width=w, line_types=(LineType.NONE, LineType.NONE))
                    else:
                        lane = _turn_lane(c + ARM_VEC[a] * attach(node, a) + out_dir * attach(node, b), start,
                                          math.atan2(travel[1], travel[0]), end, math.atan2(out_dir[1], out_dir[0]), w,
                                          turn_radius(node, a, b, k, k_out, command))
                    network.add_lane(frm, to, lane)
                    lane_info[(frm, to, k)] = LaneInfo("bend" if bend else "connector", node,
                                                      Command.FOLLOW if bend else command)
                    if k_out != k:
                        exit_lanes[(frm, to, k)] = k_out
                if bend:
                    street = _street_of(a, node, cols, rows)
                    lanes = [network.graph[frm][to][k] for k in range(n_in)]
                    road_polys += _strip_quads(lanes[0], -w_in / 2, street.half_width_m - w_in / 2, 0, lanes[0].length, 2.0)
                    add_markings(lanes, street, with_centre=True)
        if bend:
            continue
        # Junction asphalt: a rectangle out to the stop lines (kerb-side corners lie under the slabs).
        ext = {arm: (attach(node, arm) if arm in arms else _cross_street(arm, node, cols, rows).half_width_m)
               for arm in Arm}
        road_polys.append(_rect(c[0] - ext[Arm.W], c[1] - ext[Arm.N], c[0] + ext[Arm.E], c[1] + ext[Arm.S]))
        for a in arms:
            u, r = ARM_VEC[a], right_of(ARM_VEC[a])
            travel = -u
            tr = right_of(travel)
            street = _street_of(a, node, cols, rows)
            half_arm = street.half_width_m
            half_cross = _cross_street(a, node, cols, rows).half_width_m
            dist = attach(node, a)
            control = controls[node][a]
            # Stop bar (or give-way line) across the incoming lanes, on the approach side of the lane end.
            near = c + u * (dist + ROAD.stop_bar_depth_m)
            far = c + u * dist
            lanes_w = street.lanes * street.lane_width_m  # the incoming lanes, together
            inner, outer = tr * 0.1, tr * (lanes_w - 0.1)
            if control == Control.YIELD:
                markings["yield_line"] += [np.array([far + tr * t, near + tr * (t + 0.3), near + tr * (t + 0.6)])
                                           for t in np.arange(0.15, lanes_w - 0.6, 0.9)]
            elif control != Control.PRIORITY:
                markings["stop_line"].append(np.array([far + inner, near + inner, near + outer, far + outer]))
            # Zebra across the whole arm, between the crossing street and the stop bar.
            cw0, cw1 = half_cross + zebra_gap, half_cross + zebra_gap + ROAD.crosswalk_depth_m
            for lat in np.arange(-half_arm + 0.4, half_arm - 0.3, 1.0):
                q0, q1 = c + u * cw0 + r * lat, c + u * cw1 + r * lat
                markings["crosswalk"].append(np.array([q0, q1, q1 + r * 0.5, q0 + r * 0.5]))
            mid = c + u * (cw0 + cw1) / 2
            kerb = half_arm + sw / 2
            approach_edge = (_node_name((node[0] + int(u[0]), node[1] + int(u[1])), OPPOSITE[a], "o"),
                             _node_name(node, a, "i"))
            line_centre = c + u * (dist + ROAD.stop_bar_depth_m) + tr * (lanes_w / 2)
            approach_index = -1
            if control == Control.SIGNAL:
                mount = mounts[node]
                if style.corner_radius_m is None:
                    far_corner = c + travel * (half_cross + sw / 2) + tr * (half_arm + sw / 2)
                else:  # on the sidewalk behind the rounded kerb, as far from it as the classic corner's pole
                    kerb_centre = c + travel * (half_cross + corner) + tr * (half_arm + corner)
                    far_corner = kerb_centre - (travel + tr) / math.sqrt(2) * (corner - POLE_FROM_KERB_M)
                if mount == "mast_arm":  # over the middle of the incoming lanes, from the far-right corner
                    pole, head, height = far_corner, c + travel * float((far_corner - c) @ travel) + tr * (lanes_w / 2), \
                        ROAD.signal_head_height_m
                elif mount == "far_pole":
                    pole, head, height = far_corner, far_corner - tr * 0.45, POLE_HEAD_HEIGHT_M
                else:  # near_pole: beside the stop line, on the right
                    pole = c + u * (dist + ROAD.stop_bar_depth_m + 1.0) + tr * (half_arm + 0.8)
                    head, height = pole - tr * 0.45, POLE_HEAD_HEIGHT_M
                poles.append(pole)
                ap = Approach(len(approaches), node, a, approach_edge, line_centre, math.atan2(travel[1], travel[0]),
                              pole, head, mount, height)
                approaches.append(ap)
                approach_index = ap.index
            entries.append(Entry(len(entries), node, a, approach_edge, line_centre, math.atan2(travel[1], travel[0]),
                                 control, approach_index, street.lanes))
            if control in (Control.STOP, Control.ALL_WAY_STOP, Control.YIELD):
                kind = SignKind.YIELD if control == Control.YIELD else SignKind.STOP
                post = c + u * (dist + ROAD.stop_bar_depth_m + STOP_SIGN_BEFORE_M) + tr * (half_arm + 0.7)
                signs.append(Sign(len(signs), kind, post,
                                  math.atan2(travel[1], travel[0]), approach_edge))
            crosswalks.append(Crosswalk(len(crosswalks), node, a, mid - r * kerb, mid + r * kerb,
                                        np.array([c + u * cw0 - r * half_arm, c + u * cw1 - r * half_arm,
                                                  c + u * cw1 + r * half_arm, c + u * cw0 + r * half_arm]),
                                        approach_index))

    # Posted limits: a sign where a road leaves a junction at which streets of other limits meet (and now
    # and then where none do); connectors and bends carry the higher limit of the roads they join.
    if speed_limits:
        for node in nodes:
            if _is_bend(node, nx, ny):
                continue
            arms = _arms(node, nx, ny)
            limits = {_street_of(a, node, cols, rows).limit_kmh for a in arms}
            for b in arms:
                street = _street_of(b, node, cols, rows)
                if street.limit_kmh is None or (len(limits) == 1 and mix.random() >= LIMIT_REPEAT_CHANCE):
                    continue
                d = ARM_VEC[b]
                edge = (_node_name(node, b, "o"), _node_name((node[0] + int(d[0]), node[1] + int(d[1])), OPPOSITE[b], "i"))
                lane = network.graph[edge[0]][edge[1]][0]
                at = lane.position(LIMIT_SIGN_AFTER_M, street.half_width_m - street.lane_width_m / 2 + 0.7)
                signs.append(Sign(len(signs), SignKind.SPEED_LIMIT, at, math.atan2(d[1], d[0]), edge, street.limit_kmh))
        arriving: dict[str, list[str]] = {}  # node -> the nodes whose edges end there
        for frm, tos in network.graph.items():
            for to in tos:
                arriving.setdefault(to, []).append(frm)
        for frm, tos in network.graph.items():
            for to in tos:
                if (frm, to) in speed_limits:
                    continue
                before = [speed_limits.get((f, frm)) for f in arriving.get(frm, [])]
                after = [speed_limits.get((to, t)) for t in network.graph.get(to, {})]
                known = [v for v in before + after if v is not None]
                if known:
                    speed_limits[(frm, to)] = max(known)

    # Parked cars along the parking strips of residential streets (both sides, clear of the junctions).
    parked: list[ParkedCar] = []
    if style.parked_per_100m > 0:
        chance = min(1.0, style.parked_per_100m * PARKED_SLOT_M / 100.0)
        for (frm, to, k), info in sorted(lane_info.items()):
            street_lanes = len(network.graph[frm][to])
            if info.kind != "road" or k != street_lanes - 1:
                continue
            lane = network.graph[frm][to][k]
            street = street_of_edge[(frm, to)]
            if street.parking_m <= 0:
                continue
            s = PARKING_CLEAR_M
            while s + PARKED_SLOT_M < lane.length - PARKING_CLEAR_M:
                if mix.random() < chance:
                    length = float(mix.uniform(4.0, 4.8))
                    jitter = float(mix.uniform(-0.4, 0.4))
                    pos = lane.position(s + PARKED_SLOT_M / 2 + jitter, street.lane_width_m / 2 + street.parking_m / 2)
                    color = CAR_COLORS[int(mix.integers(len(CAR_COLORS)))]
                    parked.append(ParkedCar(pos, float(lane.heading_at(s)), length, 1.85, 1.5, color))
                s += PARKED_SLOT_M

    # Blocks: raised slabs (sidewalk level), parks, buildings and street trees.
    slab_polys: list[np.ndarray] = []
    grass_polys: list[np.ndarray] = []
    buildings: list[Building] = []
    trees: list[Tree] = []
    centre_xy = np.array([xs[-1] / 2, ys[-1] / 2])
    max_r = float(np.linalg.norm(centre_xy)) + 1.0
    ring_half = rows[0].half_width_m  # the ring's half width (its columns are wider across x when skewed)

    def bend_of(node: tuple[int, int]) -> np.ndarray | None:
        """``[arc centre, inward]`` of a bend node, None for junctions."""
        if not _is_bend(node, nx, ny):
            return None
        inward = np.array([1.0 if node[0] == 0 else -1.0, 1.0 if node[1] == 0 else -1.0])
        return np.array([centre(node) + inward * rc, inward])

    h_lo, h_hi = style.building_height_m

    def setback_along(i: int, j: int, arm: Arm) -> float:
        """Where a block side's street trees start: clear of the junction's stop line (classic: one setback)."""
        if style.setback_extra_m is None or _is_bend((i, j), nx, ny):
            return config.stop_line_setback_m
        return setback[((i, j), arm)]

    def add_building_row(x0: float, y0: float, x1: float, y1: float, along_x: bool, depth_max: float,
                         front_at_min: bool, forbid: list[np.ndarray]) -> None:
        """Place buildings along one side of a rectangle, fronts on one of its edges."""
        length = (x1 - x0) if along_x else (y1 - y0)
        pos = 0.0
        while pos < length - 8.0:
            frontage = min(float(rng.uniform(10, 24)), length - pos)
            depth = min(float(rng.uniform(12, 22)), depth_max)
            if along_x:
                bx0, bx1 = x0 + pos, x0 + pos + frontage
                by0, by1 = (y0, y0 + depth) if front_at_min else (y1 - depth, y1)
            else:
                by0, by1 = y0 + pos, y0 + pos + frontage
                bx0, bx1 = (x0, x0 + depth) if front_at_min else (x1 - depth, x1)
            rect = _rect(bx0, by0, bx1, by1)
            bc = rect.mean(axis=0)
            if not any(_cuts_bend(rect, f, rc - ring_half - sw - 0.5) for f in forbid):
                closeness = 1.0 - float(np.linalg.norm(bc - centre_xy)) / max_r
                height = float(rng.uniform(h_lo, h_hi) + rng.uniform(0, style.building_centre_extra_m) * closeness ** 2)
                color = palette[int(rng.integers(len(palette)))]
                buildings.append(Building(rect, height, color))
            pos += frontage + float(rng.uniform(0.5, 4.0))

    def add_street_trees(p0: np.ndarray, p1: np.ndarray, forbid: list[np.ndarray]) -> None:
        length = float(np.linalg.norm(p1 - p0))
        direction = (p1 - p0) / max(length, 1e-9)
        s = float(rng.uniform(4, config.tree_spacing_m))
        while s < length - 4:
            pos = p0 + direction * s
            if rng.random() < 0.8 and not any(_cuts_bend(pos[None, :], f, rc - ring_half - 1.5) for f in forbid):
                trees.append(Tree(pos, float(rng.uniform(4.5, 7.5)), float(rng.uniform(1.6, 2.6)),
                                  (0.18 + 0.1 * float(rng.random()), 0.42 + 0.15 * float(rng.random()), 0.16)))
            s += config.tree_spacing_m * float(rng.uniform(0.8, 1.3))

    for i in range(nx):
        for j in range(ny):
            x0, x1 = xs[i] + cols[i].half_width_m, xs[i + 1] - cols[i + 1].half_width_m
            y0, y1 = ys[j] + rows[j].half_width_m, ys[j + 1] - rows[j + 1].half_width_m
            corners = [(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)]
            forbid = [p for p in (bend_of(n) for n in corners) if p is not None]
            # Slab: the block rectangle with rounded kerbs (tight at junctions, wide at bends).
            radii = []
            for n in corners:
                radii.append(rc - ring_half if _is_bend(n, nx, ny) else corner)
            poly = _rounded_rect(x0, y0, x1, y1, radii)
            slab_polys.append(poly)
            ix0, iy0, ix1, iy1 = x0 + sw + 0.5, y0 + sw + 0.5, x1 - sw - 0.5, y1 - sw - 0.5
            if rng.random() < config.park_probability:
                grass_polys.append(_rect(x0 + sw, y0 + sw, x1 - sw, y1 - sw))
                for _ in range(int(rng.integers(6, 12))):
                    pos = np.array([rng.uniform(ix0 + 2, ix1 - 2), rng.uniform(iy0 + 2, iy1 - 2)])
                    if not any(_cuts_bend(pos[None, :], f, rc - ring_half - sw - 2.0) for f in forbid):
                        trees.append(Tree(pos, float(rng.uniform(5, 9)), float(rng.uniform(2.0, 3.2)),
                                          (0.16, 0.40 + 0.15 * float(rng.random()), 0.14)))
            else:
                row_depth = min(22.0, (iy1 - iy0) / 2 - 1.0)
                side_depth = (ix1 - ix0) / 2 - 1.0
                add_building_row(ix0, iy0, ix1, iy1, True, row_depth, True, forbid)
                add_building_row(ix0, iy0, ix1, iy1, True, row_depth, False, forbid)
                add_building_row(ix0, iy0 + row_depth + 1.5, ix1, iy1 - row_depth - 1.5, False, side_depth, True, forbid)
                add_building_row(ix0, iy0 + row_depth + 1.5, ix1, iy1 - row_depth - 1.5, False, side_depth, False, forbid)
            kerb = 1.0
            dx0, dx1 = setback_along(i, j, Arm.E), setback_along(i + 1, j, Arm.W)
            add_street_trees(np.array([x0 + dx0, y0 + kerb]), np.array([x1 - dx1, y0 + kerb]), forbid)
            dx0, dx1 = setback_along(i, j + 1, Arm.E), setback_along(i + 1, j + 1, Arm.W)
            add_street_trees(np.array([x0 + dx0, y1 - kerb]), np.array([x1 - dx1, y1 - kerb]), forbid)
            dy0, dy1 = setback_along(i, j, Arm.S), setback_along(i, j + 1, Arm.N)
            add_street_trees(np.array([x0 + kerb, y0 + dy0]), np.array([x0 + kerb, y1 - dy1]), forbid)
            dy0, dy1 = setback_along(i + 1, j, Arm.S), setback_along(i + 1, j + 1, Arm.N)
            add_street_trees(np.array([x1 - kerb, y0 + dy0]), np.array([x1 - kerb, y1 - dy1]), forbid)

    # Outside the ring road: a sidewalk along it and a row of buildings facing it.
    X0, X1 = xs[0] - cols[0].half_width_m, xs[-1] + cols[-1].half_width_m
    Y0, Y1 = ys[0] - ring_half, ys[-1] + ring_half
    outer_sides = [
        _rect(xs[0] + rc, Y0 - sw, xs[-1] - rc, Y0),
        _rect(xs[0] + rc, Y1, xs[-1] - rc, Y1 + sw),
        _rect(X0 - sw, ys[0] + rc, X0, ys[-1] - rc),
        _rect(X1, ys[0] + rc, X1 + sw, ys[-1] - rc),
    ]
    slab_polys += outer_sides
    for node in [(0, 0), (nx, 0), (nx, ny), (0, ny)]:
        bend = bend_of(node)
        assert bend is not None
        bc = bend[0]
        outward = centre(node) - bc
        mid = math.atan2(outward[1], outward[0])
        r0, r1 = rc + ring_half, rc + ring_half + sw
        angs = np.linspace(mid - math.pi / 4, mid + math.pi / 4, 7)
        for a0, a1 in zip(angs[:-1], angs[1:], strict=True):
            u0, u1 = np.array([math.cos(a0), math.sin(a0)]), np.array([math.cos(a1), math.sin(a1)])
            slab_polys.append(np.array([bc + u0 * r0, bc + u1 * r0, bc + u1 * r1, bc + u0 * r1]))
    if config.outer_buildings:
        gap = 2.0
        add_building_row(xs[0] + rc, Y0 - sw - gap - 22, xs[-1] - rc, Y0 - sw - gap, True, 20, False, [])
        add_building_row(xs[0] + rc, Y1 + sw + gap, xs[-1] - rc, Y1 + sw + gap + 22, True, 20, True, [])
        add_building_row(X0 - sw - gap - 22, ys[0] + rc, X0 - sw - gap, ys[-1] - rc, False, 20, False, [])
        add_building_row(X1 + sw + gap, ys[0] + rc, X1 + sw + gap + 22, ys[-1] - rc, False, 20, True, [])
    # Trees are not allowed on the asphalt (bend inner corners, junction stubs), nor on a sign or a parked car.
    town = Town(config, seed, xs, ys, network, lane_info, approaches, crosswalks, buildings, [],
                road_polys, slab_polys, grass_polys, markings, poles, entries, signs, parked, speed_limits, exit_lanes, w)
    if skew or bows != (0.0, 0.0):
        warp = TownWarp(skew, bows[0], bows[1], (float(xs[0]), float(ys[0]), float(xs[-1]), float(ys[-1])))
        warp_town(town, warp)
        trees = [replace(t, position=warp.point(t.position)) for t in trees]
    _index_lanes(town)
    town.trees = [t for t in trees if not town.on_road(t.position, margin_m=0.4)
                  and not any(float(np.linalg.norm(t.position - g.position)) < 1.0 for g in town.signs)]
    town._approach_by_edge = {ap.edge: ap for ap in town.approaches}
    town._entry_by_edge = {e.edge: e for e in town.entries}
    return town


def _cuts_bend(points: np.ndarray, bend: np.ndarray, radius: float) -> bool:
    """Whether any point lies in a bend's corner square but outside its inner kerb circle.

    ``bend`` is ``[centre, inward]``: the bend's arc centre and the (+-1, +-1) direction from the
    town corner to it. The block slab is rounded there, so such a point would hang over the road.
    """
    centre, inward = bend
    for p in np.atleast_2d(points):
        rel = p - centre
        if rel[0] * inward[0] < 0 and rel[1] * inward[1] < 0 and float(np.linalg.norm(rel)) > radius:
            return True
    return False


def crosswalk_frame(cw: Crosswalk) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Centre, unit vector along the arm, half depth (along the arm) and half width (across) of a crossing."""
    centre = cw.polygon.mean(axis=0)
    along = cw.polygon[1] - cw.polygon[0]
    depth = float(np.linalg.norm(along))
    return centre, along / depth, depth / 2, float(np.linalg.norm(cw.polygon[2] - cw.polygon[1])) / 2


def _lane_crosswalks(town: Town) -> dict[LaneIndex, list[tuple[int, float, float]]]:
    """For every lane, the crosswalks it crosses and where (sampled every 0.25 m)."""
    frames = [crosswalk_frame(cw) for cw in town.crosswalks]
    centres = np.array([f[0] for f in frames])
    out: dict[LaneIndex, list[tuple[int, float, float]]] = {}
    for frm, tos in town.network.graph.items():
        for to, lanes in tos.items():
            for k, lane in enumerate(lanes):
                ss = np.arange(0.0, lane.length + 0.25, 0.25)
                pts = np.array([lane.position(s, 0.0) for s in ss])
                mid = pts.mean(axis=0)
                reach = lane.length / 2 + 12.0
                for c in np.nonzero(np.hypot(*(centres - mid).T) < reach)[0]:
                    centre, u, half_depth, half_width = frames[c]
                    d = pts - centre
                    inside = (np.abs(d @ u) <= half_depth) & (np.abs(d @ np.array([-u[1], u[0]])) <= half_width)
                    if inside.any():
                        hit = ss[inside]
                        out.setdefault((frm, to, k), []).append((int(c), float(hit.min()), float(hit.max())))
    return out


def _index_lanes(town: Town) -> None:
    """Fill the spatial hash: every cell within a lane width of a lane lists that lane."""
    cell = Town.GRID_CELL_M
    reach = town.lane_width
    grid: dict[tuple[int, int], set[LaneIndex]] = {}
    for frm, tos in town.network.graph.items():
        for to, lanes in tos.items():
            for k, lane in enumerate(lanes):
                for p in _sample_lane(lane, 0.0, 2.0):
                    for dx in (-reach, 0.0, reach):
                        for dy in (-reach, 0.0, reach):
                            key = (int(math.floor((p[0] + dx) / cell)), int(math.floor((p[1] + dy) / cell)))
                            grid.setdefault(key, set()).add((frm, to, k))
    town._grid = {k: sorted(v) for k, v in grid.items()}
