"""The memory of objects perception lost: what was in our path, or a person beside the car, stays for a while.

Why: close in, the detector misses what fills much of the frame (a pedestrian a few metres ahead), and a car must
not drive on because its detector blinked. An object lost while in our path and near stays where it was last seen
(relative to the ground: the car's own travel brings it nearer and its turning moves it across) for
``lost_memory_s`` (a vehicle keeps the speed it was seen to have along our heading: its gap closes as our own speed
less that, so a car lost while we brake behind it does not come on at the speed we closed on it with);
a person lost close in, or at the image's edge (beside the car's front is outside the view), is
kept ``near_memory_s`` and does not drift. A person near the car who leaves the view at its side edge is
remembered too, in or out of our path: a turn towards that side sweeps the car's body over where they went. A
person seen only at the side edge is not remembered: nothing confirmed them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from towndrive.agent.perception.box_geometry import BoxGeometry, at_side_edge
from towndrive.agent.perception.objects import PerceivedObject


@dataclass(frozen=True)
class MemoryRules:
    lost_memory_s: float = 2.0  # an object lost while in our path and near is remembered this long
    lost_memory_m: float = 15.0  # ... when it was nearer than this
    near_memory_s: float = 4.0  # a pedestrian lost this near, or at the image's edge, stays (not drifting) this long
    near_memory_m: float = 7.0


class ObjectMemory:
    """Recalls lost objects (``recall``) and notes what to recall next frame (``note``)."""

    def __init__(self, geometry: BoxGeometry, rules: MemoryRules) -> None:
        self.geometry = geometry
        self.rules = rules
        self.reset()

    def reset(self) -> None:
        self.lost: dict[int, PerceivedObject] = {}  # objects lost in our path, remembered for a while
        self._speed: float | None = None  # our speed on the last frame, which the closing speeds kept were taken at
        self.in_path_seen: dict[int, PerceivedObject] = {}  # last frame's seen objects in our path
        self.at_side: dict[int, PerceivedObject] = {}  # last frame's near people at the image's side edge

    def recall(self, objects: list[PerceivedObject], speed: float, turn_rad: float, dt: float,
               expired: set[int] | frozenset[int] = frozenset()) -> list[PerceivedObject]:
        """``objects`` plus those noted last frame that are no longer detected, moved by the car's travel and its
        heading change ``turn_rad`` (positive to the right) since last frame. Tracks ``expired`` (perception
        dropped them, unconfirmed while the car stood) are not remembered."""
        cfg = self.rules
        cos_t, sin_t = math.cos(turn_rad), math.sin(turn_rad)
        for tid in expired:
            self.lost.pop(tid, None)
            self.in_path_seen.pop(tid, None)
            self.at_side.pop(tid, None)
        seen = {o.track_id for o in objects}
        self._speed, before = speed, self._speed
        for tid, o in self.in_path_seen.items():
            if tid not in seen and o.distance_m < cfg.lost_memory_m:
                self.lost[tid] = o
        for tid, o in self.at_side.items():  # walked out of view beside the car: where a turn's sweep goes
            if tid not in seen and tid not in self.lost:
                self.lost[tid] = o
        out = list(objects)
        for tid in list(self.lost):
            o = self.lost[tid]
            near = o.kind == "pedestrian" and (o.distance_m < cfg.near_memory_m or self._at_border(o.box))
            if tid in seen or o.unseen_s + dt > (cfg.near_memory_s if near else cfg.lost_memory_s):
                del self.lost[tid]
                continue
            if o.kind == "pedestrian":
                closing, along = o.closing_speed_mps, speed * dt
            else:  # its own speed along our heading (our speed then less its closing speed) is kept, but never
                # towards us: close in, a box cut by the frame's bottom reads as coming on fast, and the car lost
                # would pass under ours and leave our path while it stands in front (it is kept where it was)
                own = max((speed if before is None else before) - o.closing_speed_mps, 0.0)
                closing = speed - own
                along = closing * dt
            # Near, a person's box is cut or wrong and its sideways "speed" is perspective, not walking.
            shift = o.lateral_speed_mps * dt if o.kind == "pedestrian" and not near else 0.0
            # Our own turn moves it across the view: a point ahead drifts left as we turn right.
            z = o.distance_m - along
            xc = 0.5 * (o.lateral_left_m + o.lateral_right_m) + shift
            shift += xc * cos_t - z * sin_t - xc
            z = xc * sin_t + z * cos_t
            ghost = PerceivedObject(tid, o.kind, z, o.lateral_left_m + shift, o.lateral_right_m + shift,
                                    closing, o.lateral_speed_mps, o.box, o.unseen_s + dt,
                                    closing_speed_sd_mps=o.closing_speed_sd_mps, lateral_speed_sd_mps=o.lateral_speed_sd_mps)
            self.lost[tid] = ghost
            out.append(ghost)
        return out

    def note(self, objects: list[PerceivedObject], in_path: list[int], edge_only: set[int]) -> list[PerceivedObject]:
        """Keep what ``recall`` brings back next frame if it is lost: the seen objects in our path (track ids
        ``in_path``), and the people near the car at the image's side edge, but none of ``edge_only`` (seen only
        at the side edge). Returns the objects in our path (seen or remembered)."""
        in_path_objects = [o for o in objects if o.track_id in in_path]
        seen = [o for o in objects if o.unseen_s == 0.0 and o.track_id not in edge_only and not o.stale]
        self.in_path_seen = {o.track_id: o for o in seen if o.track_id in in_path}
        width = self.geometry.camera.width
        self.at_side = {o.track_id: o for o in seen if o.kind == "pedestrian"
                         and o.distance_m < self.rules.near_memory_m and at_side_edge(o.box, width)}
        return in_path_objects

    def _at_border(self, box: tuple[float, float, float, float]) -> bool:
        """Whether a box touches the image's bottom or side edge (the object goes on beyond the frame)."""
        return self.geometry.cut(box)[1] or at_side_edge(box, self.geometry.camera.width)
