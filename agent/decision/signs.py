"""What the road signs the car has seen ask of it: a stop or a give-way at the next line, and the speed limit.

- **Stop and yield** are debounced (``confirm_frames`` frames in a row) and then apply to the next stop line:
  the one the stop-line track follows, or, with no bar seen, the line where the road design puts it
  (``RoadDesign.sign_before_stop_line_m`` beyond the sign), dead-reckoned by the car's travel. A stop is *made*
  once the car stands (under the world's full-stop speed, ``sim.spec.STOP_SPEED_MPS``) within ``full_stop_m`` of
  the line; the control ends when the car crosses the line (``entered``). Past it the car edges on to where the
  cross street is seen, short of its nearest lane (``edging_m``; buildings at the corner hide it from the line),
  and gives way there to what the corner cameras see (``agent.decision.cross_traffic``).
- **Signs are read with the car lined up on its road** (turned at most ``max_turned_deg`` from the lane it last
  drove along): which plates address the car is told by where they stand beside its road, and turning through a
  junction the camera sweeps across the plates of the junction's other arms, one of which stands where ours would
  for a moment (a stop sign read so stopped the car on the road turned into, a block before any line). The road
  turned into's own signs stand on past the junction and are read once the car is lined up on it.
- **The speed limit** is the last limit sign seen (debounced alike), kept until another is seen. Before any, the
  default for the kind of street, which the car measures from its lane lines: a dashed white line beside its
  lane means another lane in its direction (a multi-lane street: ``RoadDesign.multi_lane_limit_kmh``); a yellow
  centre line on its left and a solid edge line on its right mean one lane each way
  (``RoadDesign.single_lane_limit_kmh``); the kind most often measured over the last ``street_readings``
  readings holds while neither is seen, and the lower default before any is measured. One reading is not enough:
  where the lines end ahead (at a stop bar) a solid edge line is painted over only part of the view and is read
  as dashed, and a few such frames before the bar would make a single-lane street a two-lane one just when the
  junction's turn is placed by it (``JunctionGuidance``: the right turn's radius, the cross street's odds). The
  agent gives no reading at all with a stop line within the style's reading range, or inside a junction
  (``AgentDriver._street_lines_read``): a second of dashed readings while slowing for a stop sign outvotes the
  street's own.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass

from towndrive.agent.perception.lanes import LaneResult
from towndrive.agent.perception.signs import SignSeen
from towndrive.sim.spec import KMH, ROAD, STOP_SPEED_MPS, STOP_ZONE_M, RoadDesign


@dataclass(frozen=True)
class SignControlRules:
    confirm_frames: int = 2  # a sign counts once seen this many frames in a row
    full_stop_m: float = 2.0  # a full stop is made standing at most this far before the line (the world: STOP_ZONE_M)
    line_lost_m: float = 1.0  # a sign-inferred line this far behind the bumper is passed
    edge_margin_m: float = 2.0  # past the line, look from this far short of the cross street's nearest lane
    edge_lost_m: float = 10.0  # ... and stop edging this far past that place (the crossing is long over)
    max_turned_deg: float = 5.0  # signs are read only with the car turned at most this from its lane (a turn's sweep)
    street_readings: int = 20  # the kind of street is the one most of this many last readings told (a second or so)

    def __post_init__(self) -> None:
        if self.full_stop_m > STOP_ZONE_M:
            raise ValueError(f"full_stop_m {self.full_stop_m} is beyond the world's full-stop zone ({STOP_ZONE_M} m).")


def lanes_each_way(lanes: LaneResult | None) -> int | None:
    """The kind of street from the car's lane lines: 2 (or more) lanes each way, 1, or None (not told)."""
    if lanes is None or not lanes.detected:
        return None
    lines = [ln for ln in (lanes.left, lanes.right) if ln is not None]
    if any(ln.color == "white" and ln.style == "dashed" for ln in lines):
        return 2
    left, right = lanes.left, lanes.right
    if (left is not None and right is not None and left.color == "yellow" and right.color == "white"
            and right.style == "solid"):
        return 1
    return None


def lanes_to_kerb(lanes: LaneResult | None) -> int | None:
    """How many lanes lie between the car's lane and the kerb, from the line on its right: 0 when it is the road's
    solid white edge line, 1 when a dashed white line (another lane of ours beyond it); None when not told."""
    right = lanes.right if lanes is not None and lanes.detected else None
    if right is None or right.color != "white":
        return None
    return 0 if right.style == "solid" else 1 if right.style == "dashed" else None


class KerbLanes:
    """The lanes between ours and the kerb (``lanes_to_kerb``) as last read, kept only while they still describe the
    car's lane: a reading tells about the lane it was taken in, so it is forgotten once the car has moved sideways
    half a lane since (its own lane change, which may happen where no line on its right is read again) or has
    travelled ``forget_after_m`` without a fresh one (a lane change missed by dead reckoning, a road that changed)."""

    def __init__(self, forget_after_m: float = 25.0, lane_width_m: float = ROAD.lane_width_m) -> None:
        self.forget_after_m = forget_after_m
        self.shift_m = 0.5 * lane_width_m
        self.reset()

    def reset(self) -> None:
        self.count: int | None = None
        self._at = (0.0, 0.0)  # dead-reckoned position of the last reading
        self._heading = 0.0  # and the heading of the lane it was taken in

    def note(self, reading: int | None, pos: tuple[float, float], heading_rad: float) -> int | None:
        """Keep a fresh ``reading`` taken at ``pos`` in a lane heading ``heading_rad`` (the odometry's frame), or
        judge the one kept from the car's travel since; returns the count kept."""
        if reading is not None:
            self.count, self._at, self._heading = reading, (float(pos[0]), float(pos[1])), heading_rad
        elif self.count is not None:
            dx, dy = pos[0] - self._at[0], pos[1] - self._at[1]
            across = -dx * math.sin(self._heading) + dy * math.cos(self._heading)
            if math.hypot(dx, dy) > self.forget_after_m or abs(across) > self.shift_m:
                self.count = None
        return self.count

    def forget(self) -> None:
        self.count = None


class SignControl:
    """The signs' state across frames (module docstring)."""

    def __init__(self, rules: SignControlRules | None = None, road: RoadDesign = ROAD,
                 camera_to_front_m: float = 1.3) -> None:
        self.rules = rules or SignControlRules()
        self.road = road
        self.camera_to_front_m = camera_to_front_m
        self.reset()

    def reset(self) -> None:
        self.control: str | None = None  # "stop" or "yield": what the next stop line asks
        self.sign_line_m: float | None = None  # bumper to the line the sign puts, dead-reckoned
        self.stopped = False  # the full stop at this line is made
        self.edging_m: float | None = None  # past the line: bumper to where the cross street is seen from
        self.limit_kmh: float | None = None  # the last limit sign seen
        self.lanes_each_way: int | None = None  # the kind of street most of the last readings told
        self._streets: deque[int] = deque(maxlen=self.rules.street_readings)
        self._seen: tuple[str, int] | None = None
        self._count = 0

    def update(self, signs: list[SignSeen], lanes_each_way: int | None, speed_mps: float, dt: float,
               turned_rad: float = 0.0) -> None:
        """One frame: the car travelled ``speed x dt``; ``signs`` addressing it were seen (nearest first), with the
        car turned ``turned_rad`` from the lane it last drove along (``Odometry.turned``)."""
        if self.sign_line_m is not None:
            self.sign_line_m -= speed_mps * dt
        if self.edging_m is not None:
            self.edging_m -= speed_mps * dt
            if self.edging_m < -self.rules.edge_lost_m:
                self.edging_m = None
        if lanes_each_way is not None:
            self._streets.append(lanes_each_way)
            counts = Counter(self._streets)  # a tie goes to the latest reading
            self.lanes_each_way = max(counts, key=lambda kind: (counts[kind], kind == lanes_each_way))
        lined_up = abs(turned_rad) <= math.radians(self.rules.max_turned_deg)
        sign = signs[0] if signs and lined_up else None
        key = (sign.kind, sign.limit_kmh) if sign is not None else None
        self._count = self._count + 1 if key is not None and key == self._seen else (1 if key else 0)
        self._seen = key
        if sign is None or self._count < self.rules.confirm_frames:
            return
        if sign.kind == "limit":
            self.limit_kmh = float(sign.limit_kmh)
            return
        if self.control != sign.kind:
            self.control, self.stopped = sign.kind, False
        self.sign_line_m = sign.distance_m + self.road.sign_before_stop_line_m - self.camera_to_front_m

    def line_gap(self, tracked_m: float | None) -> float | None:
        """Bumper to the line the sign's control applies at: the tracked stop line, else the sign's."""
        if self.control is None:
            return None
        return tracked_m if tracked_m is not None else self.sign_line_m

    def note_speed(self, speed_mps: float, gap_m: float | None) -> bool:
        """Whether the full stop is made (now or before): the car stands within ``full_stop_m`` of the line."""
        if (not self.stopped and gap_m is not None and speed_mps < STOP_SPEED_MPS
                and gap_m <= self.rules.full_stop_m):
            self.stopped = True
        return self.stopped

    def passed(self, tracked_m: float | None) -> bool:
        """Whether the line the sign put is behind the bumper (no tracked bar to say so)."""
        return (self.control is not None and tracked_m is None and self.sign_line_m is not None
                and self.sign_line_m < -self.rules.line_lost_m)

    def entered(self, cross_street_m: float | None = None) -> None:
        """The car crossed the line: the stop or give-way is done, and the car edges on to where the cross street
        is seen (``cross_street_m`` beyond the line, less ``edge_margin_m``) to give way there."""
        if self.control is not None and cross_street_m is not None:
            self.edging_m = max(cross_street_m - self.rules.edge_margin_m, 0.0)
        self.control, self.sign_line_m, self.stopped = None, None, False

    def limit(self) -> tuple[str, float]:
        """The speed limit that applies (reason, m/s)."""
        if self.limit_kmh is not None:
            return f"limit {self.limit_kmh:.0f}", self.limit_kmh * KMH
        kmh = self.road.multi_lane_limit_kmh if self.lanes_each_way == 2 else self.road.single_lane_limit_kmh
        street = {2: "multi-lane street", 1: "single-lane street"}.get(self.lanes_each_way or 0, "street not known")
        return f"limit {kmh:.0f} ({street}, no sign seen)", kmh * KMH
