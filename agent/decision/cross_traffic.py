"""Cross traffic at give-way and stop lines, through the cross-traffic cameras at the front corners.

Why: the forward camera sees 45 degrees either side of the car's axis. At a give-way or stop line a car coming
down the priority street 30 m off stands 70-85 degrees off the axis, and where buildings stand at the corner it
comes into view only once the car's nose nears the cross street. The agent looks through the corner cameras
(``DriveEnv.corner_frame``, ``sim.spec.CornerRig``), left and right in turn, while a stop or give-way lies ahead
within ``look_from_m`` and while it edges towards the cross street past the line (``SignControl.edging_m``); it
runs the vehicle detector on the picture, places each vehicle on the ground (``side_camera_ground``) in the
odometry's frame, which the car's own motion does not move, and follows it from look to look. A vehicle that
moves across our way towards it and would reach it within ``gap_s`` (the gap every driver at such a line gives,
``sim.spec.YIELD_GAP_S``) is priority traffic the car waits for; so, for ``stopped_wait_s``, is one that came
so and stopped or slowed to a crawl (a car whose path our nose is near stops for it, and goes on as soon as we
stand; one stopped for a person on a crossing farther off goes on once they are over: going then puts us in front
of it). "Would reach it" is judged as if a car slower than the street's speed pulled away again at once
(``resume_accel_mps2``, up to ``RoadDesign.single_lane_limit_kmh``): our own car, starting from the line, needs
three or four seconds to clear a two-lane street, and a car standing or slowing 25 m off is there in that time
once it goes, while at its speed of the moment it would take ten. Parked cars, cars that stand longer, and cars
driving away from our way are not waited for. Nor is a car that came to a stand at its own line (farther than
``arrival_clear_m`` from our way) after our full stop at ours: at an all-way stop who stopped first goes first, and
it waits for us (letting it go first, we both waited, until the world's drivers take the turn from a first in
line that does not go). When it came to a stand is backdated to its first sighting within ``stand_sigmas`` of its
reading's standard error of where it stands: the fitted speed falls under the threshold a fit's window late.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from towndrive.agent.decision.blind_spot import VEHICLES, SideMount, side_camera_ground
from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.detector import Detection
from towndrive.sim.spec import KMH, ROAD, VEHICLE, YIELD_GAP_S, RoadDesign

SIDES = ("left", "right")


@dataclass(frozen=True)
class CrossTrafficConfig:
    enabled: bool = True
    look_from_m: float = 15.0  # look from this far before a stop or give-way line
    score_threshold: float = 0.4
    match_m: float = 4.0  # a sighting this near where a track is expected is the same vehicle
    history_s: float = 1.5  # a track's velocity is fitted to its sightings this recent
    forget_s: float = 0.8  # a track not seen for this long is dropped
    min_span_s: float = 0.3  # a velocity needs sightings at least this far apart
    min_speed_mps: float = 1.5  # slower than this across our way, a vehicle is standing (or parked)
    gap_s: float = YIELD_GAP_S  # moving towards our way, it has priority if it would reach it within this
    path_half_m: float = VEHICLE.width_m / 2 + 1.0  # our way: this far either side of the car's centre line
    range_m: float = 70.0  # sightings farther off are not placed well enough to count
    unknown_near_m: float = 45.0  # a vehicle this near whose motion is not told yet is waited for (briefly)
    stopped_wait_s: float = 3.0  # one that came towards our way and stands is waited for this long after it came
    stand_sigmas: float = 2.0  # one stands since its readings came within this many of their standard errors
    stand_min_m: float = 1.0  # (``BoxGeometry.distance_sd``), and at least this, of where it stands
    arrival_clear_m: float = VEHICLE.length_m  # one that came to a stand after our full stop, farther than this
    #                                            from our way, stands at its own line and waits its turn after us
    resume_accel_mps2: float = 3.0  # how hard a car standing or slower than the street's speed may pull away
    #                                 (highway-env's IDM a, the world's drivers' own)


@dataclass
class CrossTrack:
    """One vehicle followed across looks: its sightings (time, x, y) in the odometry's frame."""

    side: str
    seen: list[tuple[float, float, float]] = field(default_factory=list)
    came_s: float = -math.inf  # when it was last seen moving towards our way
    stood_s: float = math.inf  # when it came to a stand since (inf: moving, or never seen standing)
    _fit: tuple[tuple[float, int], tuple[np.ndarray, np.ndarray] | None] | None = None  # (now, sightings) -> fit

    def velocity(self, now_s: float, config: CrossTrafficConfig) -> tuple[np.ndarray, np.ndarray] | None:
        """Its latest position and its velocity (a straight-line fit), when seen long enough to tell (fitted once
        per time and sightings: matching, ``unknown`` and ``priority`` ask on the same look)."""
        key = (now_s, len(self.seen))
        if self._fit is None or self._fit[0] != key:
            self._fit = key, self._fitted(now_s, config)
        return self._fit[1]

    def _fitted(self, now_s: float, config: CrossTrafficConfig) -> tuple[np.ndarray, np.ndarray] | None:
        recent = [s for s in self.seen if s[0] >= now_s - config.history_s]
        if len(recent) < 3 or recent[-1][0] - recent[0][0] < config.min_span_s:
            return None
        t, x, y = (np.array(v) for v in zip(*recent, strict=True))
        vx, x0 = np.polyfit(t - t[-1], x, 1)
        vy, y0 = np.polyfit(t - t[-1], y, 1)
        return np.array([x0, y0]), np.array([vx, vy])


def _axes(yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """The car's ahead and right unit vectors in the odometry's frame (yaw turns right)."""
    return np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])


class CrossTraffic:
    """Vehicles on the cross street, from detections in the corner cameras' frames (module docstring)."""

    def __init__(self, geometry: BoxGeometry, mount: SideMount, config: CrossTrafficConfig | None = None,
                 road: RoadDesign = ROAD) -> None:
        self.geometry = geometry
        self.mount = mount
        self.config = config or CrossTrafficConfig()
        self.street_speed_mps = road.single_lane_limit_kmh * KMH  # what a slower car may speed up to
        self.reset()

    def reset(self) -> None:
        self.tracks: list[CrossTrack] = []

    @staticmethod
    def side_to_look(frame: int) -> str:
        return SIDES[frame % 2]

    def update(self, t: float, side: str, detections: list[Detection], pose: tuple[float, float, float]) -> None:
        """Take one look on ``side`` with the car at ``pose`` (x, y, yaw in the odometry's frame; yaw turns right)."""
        cfg = self.config
        self.tracks = [k for k in self.tracks if k.seen[-1][0] >= t - cfg.forget_s]
        x, y, yaw = pose
        ahead_v, right_v = _axes(yaw)
        taken: set[int] = set()
        for d in detections:
            if d.name not in VEHICLES or d.score < cfg.score_threshold:
                continue
            ahead, out = side_camera_ground(self.geometry, self.mount, d, side)
            if not (math.isfinite(ahead) and math.isfinite(out)) or math.hypot(ahead, out) > cfg.range_m:
                continue
            right = out if side == "right" else -out
            p = np.array([x, y]) + ahead * ahead_v + right * right_v
            best, best_m = None, cfg.match_m
            for i, k in enumerate(self.tracks):
                if k.side != side or i in taken:
                    continue
                fit = k.velocity(t, cfg)
                expected = fit[0] + fit[1] * (t - k.seen[-1][0]) if fit is not None else np.array(k.seen[-1][1:])
                gap = float(np.linalg.norm(p - expected))
                if gap < best_m:
                    best, best_m = i, gap
            if best is None:
                self.tracks.append(CrossTrack(side, [(t, float(p[0]), float(p[1]))]))
                taken.add(len(self.tracks) - 1)
            else:
                self.tracks[best].seen.append((t, float(p[0]), float(p[1])))
                taken.add(best)

    def unknown(self, t: float, pose: tuple[float, float, float]) -> bool:
        """Whether a vehicle is seen within ``unknown_near_m`` whose motion is not told yet (a track too young)."""
        cfg = self.config
        here = np.array(pose[:2])
        return any(k.seen[-1][0] >= t - cfg.forget_s and k.velocity(t, cfg) is None
                   and float(np.linalg.norm(np.array(k.seen[-1][1:]) - here)) <= cfg.unknown_near_m
                   for k in self.tracks)

    def reach_s(self, distance_m: float, speed_mps: float) -> float:
        """How soon a vehicle ``distance_m`` from our way, coming at ``speed_mps``, could be there: pulling away at
        ``resume_accel_mps2`` from that speed up to the street's (a faster one keeps its own)."""
        a, top = self.config.resume_accel_mps2, max(speed_mps, self.street_speed_mps)
        to_top_m = (top * top - speed_mps * speed_mps) / (2.0 * a)
        if distance_m <= to_top_m:
            return (math.sqrt(speed_mps * speed_mps + 2.0 * a * distance_m) - speed_mps) / a
        return (top - speed_mps) / a + (distance_m - to_top_m) / top

    def priority(self, t: float, pose: tuple[float, float, float], stop_made_s: float | None = None) -> str:
        """What forbids crossing now ("" when nothing): a vehicle moving across our way towards it that could reach
        it within ``gap_s`` (``reach_s``), or one that came so and stands or crawls, for ``stopped_wait_s``, unless
        it came to a stand at its own line after our full stop (made at ``stop_made_s``): it arrived after us."""
        cfg = self.config
        x, y, yaw = pose
        ahead_v, right_v = _axes(yaw)
        for k in self.tracks:
            if k.seen[-1][0] < t - cfg.forget_s:
                continue
            fit = k.velocity(t, cfg)
            if fit is None:
                continue
            p, v = fit
            rel = p + v * (t - k.seen[-1][0]) - np.array([x, y])
            ahead, right = float(rel @ ahead_v), float(rel @ right_v)
            v_right = float(v @ right_v)
            if ahead < -VEHICLE.length_m / 2:
                continue  # behind us
            where = "from the left" if right < 0 else "from the right"
            to_way_m = max(0.0, abs(right) - cfg.path_half_m)
            range_m = math.hypot(ahead, right)
            if self._note_stand(k, p, abs(v_right), range_m, t):
                if stop_made_s is not None and k.stood_s > stop_made_s and to_way_m > cfg.arrival_clear_m:
                    continue  # it came to its line after we had stopped at ours: our turn first
                if t - k.came_s < cfg.stopped_wait_s and self.reach_s(to_way_m, 0.0) < cfg.gap_s:
                    return f"cross traffic {where} stopped {range_m:.0f} m off: letting it go first"
                continue  # standing (or parked)
            if right * v_right > 0:
                continue  # moving away from our way
            k.came_s = t
            time_s = self.reach_s(to_way_m, abs(v_right))
            if time_s < cfg.gap_s:
                return f"cross traffic {where} {range_m:.0f} m off, {time_s:.1f} s away"
        return ""

    def _note_stand(self, k: CrossTrack, p: np.ndarray, speed_across_mps: float, range_m: float, t: float) -> bool:
        """Whether a track stands (or crawls): slower across our way than ``min_speed_mps``; and note since when
        (``stood_s``, reset once it moves): since its first sighting within ``stand_sigmas`` of its reading's
        standard error (``BoxGeometry.distance_sd``) of where it stands (its fitted speed falls under the
        threshold only a fit's window later)."""
        cfg = self.config
        if speed_across_mps >= cfg.min_speed_mps:
            k.stood_s = math.inf
            return False
        if math.isinf(k.stood_s):
            near_m = max(cfg.stand_min_m, cfg.stand_sigmas * self.geometry.distance_sd(range_m, "car"))
            k.stood_s = t
            for seen_s, sx, sy in reversed(k.seen):
                if math.hypot(sx - p[0], sy - p[1]) >= near_m:
                    break
                k.stood_s = seen_s
        return True
