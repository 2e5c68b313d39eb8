"""ADAS warnings (seed 000): lane departure, forward collision by time to collision, and object in lane.

They warn; they do not act (the controller acts). Each warning is an *event* with a start and an end time,
so a report can say how often and for how long the driver would have been warned, and a video can show
the banner while it lasts. A condition must hold for ``confirm_frames`` frames to open an event (one
noisy frame is not a warning) and be absent for ``release_s`` to close it (a flickering detection is one
event, not ten).

- **Lane departure** (LDW): the car's side is within ``ldw_margin_m`` of a lane line, or will cross it
  within ``ldw_tlc_s`` at its current lateral speed (time to line crossing, TLC). Not under
  ``ldw_min_speed_mps``, and not while the route command asks for a turn (the turn signal is on).
- **Forward collision** (FCW): an object in our path closes in with a time to collision (bumper gap /
  closing speed) under ``fcw_ttc_s``.
- **Object in lane**: anything in our path within ``object_in_lane_m`` (the seed's red lane).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from towndrive.agent.perception.objects import PerceivedObject

KINDS = ("lane_departure", "forward_collision", "object_in_lane")


@dataclass(frozen=True)
class AdasConfig:
    ldw_min_speed_mps: float = 4.0
    ldw_margin_m: float = 0.2  # the car's side this close to a line
    ldw_tlc_s: float = 0.7  # ... or crossing it within this time
    car_half_width_m: float = 0.95
    fcw_ttc_s: float = 2.5
    fcw_min_closing_mps: float = 0.5
    object_in_lane_m: float = 30.0
    camera_to_front_m: float = 1.3
    confirm_frames: int = 2
    release_s: float = 0.5
    max_events: int = 500  # per episode, to keep reports small


@dataclass
class AdasEvent:
    kind: str
    start_s: float
    end_s: float | None
    detail: str  # the worst moment: e.g. "car #3, TTC 1.4 s"
    worst: float = math.inf  # the figure the detail describes (smaller is worse)

    def as_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "start_s": round(self.start_s, 2),
                "end_s": None if self.end_s is None else round(self.end_s, 2), "detail": self.detail}


@dataclass
class _Pending:
    frames: int = 0
    last_true_s: float = -math.inf
    event: AdasEvent | None = None


@dataclass
class Adas:
    """Warnings from perception; ``update`` per frame returns the active warnings' texts."""

    config: AdasConfig = field(default_factory=AdasConfig)

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.events: list[AdasEvent] = []
        self._state = {k: _Pending() for k in KINDS}
        self._last_offset: tuple[float, float] | None = None  # (time, offset)
        self._lateral_mps = 0.0

    def update(self, time_s: float, speed_mps: float, lane_offset_m: float, lane_width_m: float,
               in_path: list[PerceivedObject], turning: bool = False) -> list[str]:
        cfg = self.config
        found: dict[str, tuple[float, str]] = {}  # kind -> (figure, detail)
        # Lane departure.
        if math.isfinite(lane_offset_m):
            if self._last_offset is not None and time_s > self._last_offset[0]:
                rate = (lane_offset_m - self._last_offset[1]) / (time_s - self._last_offset[0])
                if abs(lane_offset_m - self._last_offset[1]) < 0.5 * lane_width_m:  # not a jump to the next lane
                    self._lateral_mps = 0.7 * self._lateral_mps + 0.3 * rate
            self._last_offset = (time_s, lane_offset_m)
            side = "right" if lane_offset_m > 0 else "left"
            room = lane_width_m / 2 - abs(lane_offset_m) - cfg.car_half_width_m
            towards = self._lateral_mps * math.copysign(1.0, lane_offset_m)
            tlc = room / towards if towards > 1e-3 else math.inf
            if speed_mps >= cfg.ldw_min_speed_mps and not turning and (room < cfg.ldw_margin_m or tlc < cfg.ldw_tlc_s):
                found["lane_departure"] = (max(room, 0.0), f"{side}, {max(room, 0.0):.2f} m to the line, TLC {tlc:.1f} s")
        else:
            self._last_offset = None
        # Forward collision and object in lane.
        for obj in in_path:
            gap = obj.distance_m - cfg.camera_to_front_m
            if obj.closing_speed_mps >= cfg.fcw_min_closing_mps:
                ttc = max(gap, 0.0) / obj.closing_speed_mps
                if ttc < cfg.fcw_ttc_s and ttc < found.get("forward_collision", (math.inf, ""))[0]:
                    found["forward_collision"] = (ttc, f"{obj.kind} #{obj.track_id}, TTC {ttc:.1f} s")
            if gap < cfg.object_in_lane_m and gap < found.get("object_in_lane", (math.inf, ""))[0]:
                found["object_in_lane"] = (gap, f"{obj.kind} #{obj.track_id} at {gap:.1f} m")
        active = []
        for kind in KINDS:
            st = self._state[kind]
            if kind in found:
                figure, detail = found[kind]
                st.frames += 1
                st.last_true_s = time_s
                if st.event is None and st.frames >= cfg.confirm_frames:
                    st.event = AdasEvent(kind, time_s, None, detail, figure)
                    if len(self.events) < cfg.max_events:
                        self.events.append(st.event)
                elif st.event is not None and figure < st.event.worst:
                    st.event.detail, st.event.worst = detail, figure
            else:
                st.frames = 0
                if st.event is not None and time_s - st.last_true_s >= cfg.release_s:
                    st.event.end_s = st.last_true_s
                    st.event = None
            if st.event is not None:
                active.append(f"{LABELS[kind]}: {found[kind][1] if kind in found else st.event.detail}")
        return active

    def close(self, time_s: float) -> None:
        """End the events still open (at the end of an episode)."""
        for st in self._state.values():
            if st.event is not None:
                st.event.end_s = time_s
                st.event = None

    def summary(self) -> dict[str, Any]:
        """Counts and total seconds per kind, and the events themselves (for the evaluation report)."""
        out: dict[str, Any] = {"counts": dict.fromkeys(KINDS, 0), "seconds": dict.fromkeys(KINDS, 0.0)}
        for e in self.events:
            out["counts"][e.kind] += 1
            if e.end_s is not None:
                out["seconds"][e.kind] = round(out["seconds"][e.kind] + e.end_s - e.start_s, 2)
        out["events"] = [e.as_dict() for e in self.events]
        return out


LABELS = {"lane_departure": "LANE DEPARTURE", "forward_collision": "COLLISION WARNING",
          "object_in_lane": "OBJECT IN LANE"}
