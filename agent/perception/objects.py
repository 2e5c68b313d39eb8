"""What perception reports of the objects it tracks, and how a track becomes one: distance, extent, speeds, trust.

Each SORT track of a vehicle or person becomes a ``PerceivedObject`` in the camera's ground frame: its distance
from box geometry (or stereo, near), its lateral extent, and its closing and lateral speeds from a least-squares
fit over the track's last second, each with its standard error (how far the readings scatter about the fit: a
car standing 20 m off reads a metre or two nearer or farther from frame to frame, a speed of a metre a second that
is not there). A vehicle standing wholly to one side of the camera axis and not moving
sideways draws its inner box edge from its far side: that edge is read the vehicle's depth beyond its near face,
its length when the box's width says it stands lengthwise (parked at the kerb), else its width (a car waiting in
the oncoming lane is not in our path, and a parked one is as far from it as it is).

What is easy to fake is marked unconfirmed (the controller stands for it only for a bounded time): a track the
detector missed this frame (SORT coasting), and a person seen only at the image's side edge. A real person at
the edge walked there through the picture, so a person at the side edge is confirmed only while the same track
was seen whole (clear of the side edges) within ``edge_confirm_s``. Why: at night a lit facade, a pole or the
kerb's line where it meets the side edge scores as half a person, and with the car standing in a turn it stays
there frame after frame (``docs/agent_rules.md``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from towndrive.agent.perception.box_geometry import DEPTH_PRIOR_M, LENGTH_PRIOR_M, BoxGeometry, at_side_edge
from towndrive.agent.perception.classes import CLASSES
from towndrive.agent.perception.tracking import Track

TRACKED = ("car", "truck", "pedestrian")
# While the car stands, a track the detector does not confirm (coasting, or a person seen only at the image's side
# edge) for this many frames in a row expires: standing, the camera sees the same picture frame after frame, so
# nothing can refute a false box, and waiting longer only holds the car (docs/agent_rules.md). Once the car moves
# it is reported again, stale (the controller passes it at creeping pace, looking every frame); a whole detection
# of the same track makes it an ordinary object again.
UNCONFIRMED_STANDING_FRAMES = 40  # 2 s at the 20 Hz step
STANDING_MPS = 0.5  # the car stands below this speed (as the controller's standstill_mps)
LENGTHWISE_MEMORY_S = 1.0  # a lengthwise judgement is kept this long of driving while the box is cut (we may turn)
SIDE_LATERAL_SPAN_S = 0.5  # history over which a vehicle beside us is judged moving sideways or not
TRACK_STATE_KEEP_S = 0.5  # a track's history and judgements are kept this long while SORT does not report it
STILL_ALONG_MPS = 1.5  # a vehicle beside us whose fitted speed along our axis is under this is taken as standing


@dataclass
class PerceivedObject:
    """One tracked object as perception sees it, in the camera's ground frame."""

    track_id: int
    kind: str  # "car", "truck", "pedestrian"
    distance_m: float  # forward, camera to the object's nearest point on the ground
    lateral_left_m: float  # the object's left edge, right of the camera axis (negative: left)
    lateral_right_m: float  # its right edge
    closing_speed_mps: float = 0.0  # how fast the distance shrinks (positive: approaching)
    lateral_speed_mps: float = 0.0  # positive: moving right
    box: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    unseen_s: float = 0.0  # > 0: no longer detected, remembered where it was last (see agent_driver)
    confirmed: bool = True  # False: detected, but only in a way that is easy to fake (see agent_driver)
    stale: bool = False  # unconfirmed for UNCONFIRMED_STANDING_FRAMES while the car stood: passed at creeping pace
    closing_speed_sd_mps: float = 0.0  # the closing speed's standard error (its fit's scatter)
    lateral_speed_sd_mps: float = 0.0  # the lateral speed's standard error

    @property
    def unconfirmed(self) -> bool:
        """Whether perception does not confirm the object this frame (remembered, or not confirmed)."""
        return self.unseen_s > 0 or not self.confirmed

    @property
    def lateral_m(self) -> float:
        return 0.5 * (self.lateral_left_m + self.lateral_right_m)


@dataclass(frozen=True)
class ObjectRules:
    """How tracks become objects (the agent's configuration fills these in)."""

    history_s: float = 1.0  # track history used for closing and lateral speeds
    still_lateral_mps: float = 0.3  # a vehicle moving sideways slower than this gets the depth prior
    edge_confirm_s: float = 8.0  # a person at the image's side edge is confirmed this long after last seen whole
    whole_margin_px: float = 3.0  # a box this near the image's side edge may be cut: it does not show the whole
    person_height_ratio: tuple[float, float] = (0.7, 1.4)  # a whole person's box height over the prior's
    person_height_slack_px: float = 10.0  # ... and at least 1 - this / box height (see plausible_person) ...
    person_height_slack_share: float = 0.15  # ... or 1 - this, whichever is lower
    cut_person_height_ratio: float = 0.8  # the least height a person's box cut at the bottom shows, over the prior's
    stereo_max_m: float = 15.0  # beyond this stereo disparity is too small: use geometry


def slope(t: list[float], v: list[float]) -> tuple[float, float]:
    """The least-squares rate of change of ``v`` over times ``t`` and its standard error (from the scatter of
    the readings about the line; 0 with fewer than three)."""
    tt = np.asarray(t, float) - np.mean(t)
    vv = np.asarray(v, float) - np.mean(v)
    sxx = float((tt ** 2).sum())
    rate = float((tt * vv).sum() / sxx)
    if len(tt) < 3:
        return rate, 0.0
    residual = vv - rate * tt
    return rate, math.sqrt(float((residual ** 2).sum()) / (len(tt) - 2) / sxx)


class ObjectEstimator:
    """Tracks in, ``PerceivedObject`` out (module docstring); keeps each track's recent history."""

    def __init__(self, geometry: BoxGeometry, rules: ObjectRules, stereo: object | None = None) -> None:
        self.geometry = geometry
        self.rules = rules
        self.stereo = stereo
        self.reset()

    def reset(self) -> None:
        # t, z, the lateral reading (bearing or centre) and what it is
        # per track: (time, distance, lateral reading, how it was read, our heading then)
        self._history: dict[int, deque[tuple[float, float, float, tuple[int, float], float]]] = {}
        self._heading = 0.0  # our heading (rad, positive right) summed over the frames' turns
        self._whole_at: dict[int, float] = {}  # track id -> when a person's track was last seen whole
        self._standing_unconfirmed: dict[int, int] = {}  # track id -> frames in a row unconfirmed, the car standing
        self._lengthwise: dict[int, float] = {}  # track id -> when last judged lengthwise along the camera axis
        self._alive_at: dict[int, float] = {}  # track id -> when last among this stage's tracks
        self.expired: set[int] = set()  # this frame's tracks dropped for that (UNCONFIRMED_STANDING_FRAMES)
        self.edge_only: set[int] = set()  # this frame's people seen only at the image's side edge

    def update(self, tracks: list[Track], t: float, depth: np.ndarray | None,
               speed_mps: float = math.inf, turn_rad: float = 0.0) -> list[PerceivedObject]:
        """The tracks as objects; ``speed_mps``, the car's own speed, expires what stays unconfirmed while it
        stands (``UNCONFIRMED_STANDING_FRAMES``); ``turn_rad``, our heading change since the last frame (positive
        right), is taken out of their sideways motion."""
        out = []
        self._heading += turn_rad
        self.edge_only = set()
        self.expired = set()
        standing = speed_mps < STANDING_MPS
        alive = set()
        geometry, rules = self.geometry, self.rules
        for tr in tracks:
            kind = CLASSES[tr.label] if 0 <= tr.label < len(CLASSES) else ""
            if kind not in TRACKED:
                continue
            box = np.asarray(tr.box, float)
            if kind == "pedestrian" and not self.plausible_person(box):
                continue
            z = geometry.distance(box, kind)
            if depth is not None and self.stereo is not None:
                zs = self.stereo.object_distance(depth, box)  # type: ignore[attr-defined]
                if math.isfinite(zs) and zs < rules.stereo_max_m:
                    z = zs
            if not math.isfinite(z) or z <= 0:
                continue
            xl, xr = geometry.lateral(box[0], z), geometry.lateral(box[2], z)
            # A vehicle wholly to one side is followed by its inner edge where its far inner corner stands (its
            # depth beyond the near face): that point stays put while a still vehicle's box grows and is cut as
            # we near it, where the box's centre read at the near face drifts towards our axis (half a metre a
            # second, passing a parked car at 3 m/s) and made it look as if it were pulling out.
            cx = float(geometry.k[0, 2])
            side = (1 if box[0] > cx else -1 if box[2] < cx else 0) if kind in DEPTH_PRIOR_M else 0
            judged = geometry.lengthwise(box, z, kind) if side else None  # on a whole box; kept while cut
            if judged:
                self._lengthwise[tr.track_id] = t
            elif judged is False:
                self._lengthwise.pop(tr.track_id, None)
            if standing and tr.track_id in self._lengthwise:
                self._lengthwise[tr.track_id] = t  # standing, our heading does not turn: the judgement holds
            elif t - self._lengthwise.get(tr.track_id, -math.inf) > LENGTHWISE_MEMORY_S:
                self._lengthwise.pop(tr.track_id, None)  # our own heading may have turned since
            depth_m = (LENGTH_PRIOR_M if tr.track_id in self._lengthwise else DEPTH_PRIOR_M).get(kind, 0.0)
            # beside the axis: the inner edge's ray (lateral metres per metre of depth); else the box's centre
            bearing = geometry.lateral(box[0] if side > 0 else box[2], 1.0) if side else 0.5 * (xl + xr)
            mode = (side, depth_m)
            hist = self._history.setdefault(tr.track_id, deque())
            hist.append((t, z, bearing, mode, self._heading))
            while hist and hist[0][0] < t - rules.history_s:
                hist.popleft()
            alive.add(tr.track_id)
            closing, lateral, closing_sd, lateral_sd = 0.0, 0.0, 0.0, 0.0
            known = len(hist) >= 4 and hist[-1][0] - hist[0][0] >= 0.2  # enough history for speeds
            same = [h for h in hist if h[3] == mode]  # lateral motion only from readings of the same point
            # a side vehicle's bearing moves a pixel or two in 0.2 s at 7 m/s, as much as the box's edge jitters:
            # its sideways motion is judged over half a second
            known_lateral = len(same) >= 4 and same[-1][0] - same[0][0] >= (SIDE_LATERAL_SPAN_S if side else 0.2)
            if known:
                rate, closing_sd = slope([h[0] for h in hist], [h[1] for h in hist])
                closing = -rate
            if known_lateral:
                # Each reading as seen from our heading now: turning right since, a still point's bearing has
                # moved left by the angle turned (without this, every car beside a turn seemed to cross it).
                readings = [h[2] - (self._heading - h[4]) * h[1] for h in same]
                if side:
                    # x = bearing x depth. The bearing is read to a pixel; the inner edge's depth at each reading
                    # is today's plus what was closed since: our own speed for a vehicle standing along our axis
                    # (a box's distance wanders by a metre while we near it at 7 m/s: differentiated, that reads
                    # as a vehicle moving sideways), else its fitted closing speed. (The rate of the bearing times
                    # today's depth lags: half a second back the bearing turned more slowly, and a parked car
                    # passed at 5 m/s seemed to move sideways at 0.3 m/s.)
                    along = speed_mps - closing if math.isfinite(speed_mps) else math.inf
                    approach = speed_mps if abs(along) < STILL_ALONG_MPS else closing
                    readings = [(h[2] - (self._heading - h[4])) * (z + depth_m + (t - h[0]) * approach) for h in same]
                lateral, lateral_sd = slope([h[0] for h in same], readings)
            still = known_lateral and abs(lateral) < rules.still_lateral_mps
            if side and (still or tr.track_id in self._lengthwise):
                # Wholly to one side: its inner edge is where the far inner corner stands. Lengthwise, its length
                # beyond the near face, from the first frame and moving or not: the box's shape tells it, and a
                # car along our axis cannot move sideways faster than its yaw lets it (a cutting-in car's far
                # inner corner is its nose, the nearest point to our path). Standing across, once seen still,
                # its width (the least depth a vehicle can show); one moving across keeps the near face.
                if side > 0:
                    xl = bearing * (z + depth_m)
                else:
                    xr = bearing * (z + depth_m)
            confirmed = self._confirmed(tr, kind, t)
            # Confirmed by a detection this frame: matched, and a person's box clear of the side edges (seen
            # whole lately is not enough here: standing, the same cut box comes back frame after frame).
            whole_now = tr.time_since_update == 0 and (
                kind != "pedestrian" or not at_side_edge(box, geometry.camera.width, rules.whole_margin_px))
            count = self._standing_unconfirmed.get(tr.track_id, 0)
            count = 0 if whole_now else (count + 1 if standing else count)
            self._standing_unconfirmed[tr.track_id] = count
            stale = count >= UNCONFIRMED_STANDING_FRAMES
            if stale and standing:
                self.expired.add(tr.track_id)
                self.edge_only.discard(tr.track_id)
                continue
            out.append(PerceivedObject(tr.track_id, kind, float(z), float(xl), float(xr), closing, lateral,
                                       (float(box[0]), float(box[1]), float(box[2]), float(box[3])),
                                       confirmed=confirmed and not stale, stale=stale,
                                       closing_speed_sd_mps=closing_sd, lateral_speed_sd_mps=lateral_sd))
        # A track's state outlives a frame or two without it: SORT leaves out a track it coasts on for a few
        # frames, and the same track coming back must still count as seen whole (a person who walked up to the
        # car and out at the image's edge was otherwise taken for a box seen only at the edge, and forgotten).
        for tid in alive:
            self._alive_at[tid] = t
        gone = {tid for tid, at in self._alive_at.items() if t - at > TRACK_STATE_KEEP_S}
        for state in (self._history, self._standing_unconfirmed, self._whole_at, self._lengthwise, self._alive_at):
            for tid in gone.intersection(state):
                del state[tid]
        return out

    def _confirmed(self, track: Track, kind: str, t: float) -> bool:
        """Whether the detector confirms this track this frame: it matched a detection (not SORT coasting on
        its prediction), and a person at the image's side edge was seen whole lately."""
        whole = kind != "pedestrian" or self._seen_whole(track, t)
        if not whole:
            self.edge_only.add(track.track_id)
        return whole and track.time_since_update == 0

    def _seen_whole(self, track: Track, t: float) -> bool:
        """Whether a person's box is clear of the image's side edges, or its track was seen so (detected, not
        predicted) within ``edge_confirm_s``."""
        if not at_side_edge(track.box, self.geometry.camera.width, self.rules.whole_margin_px):
            if track.time_since_update == 0:
                self._whole_at[track.track_id] = t
            return True
        return t - self._whole_at.get(track.track_id, -math.inf) <= self.rules.edge_confirm_s

    def plausible_person(self, box: np.ndarray) -> bool:
        """Whether a pedestrian box's size agrees with where its bottom row meets the road (a box cut by the
        image's top edge is not judged; one cut at the bottom must reach up to a standing person's head). People
        in this world are all 1.75 m tall, and the ratio of box height to the prior's stays near 1 for true
        detections (``docs/agent_rules.md``).

        The ratio is read from pixels: the box's top and bottom rows, and the bottom row's road distance, each a
        pixel or two off. Both errors shrink as the box grows (the distance's share is ``z / (f h_cam)`` per
        row, and z itself is ``f H / h``), so that part of the ratio's spread goes as one over the box's height
        in pixels. What does not shrink with the box stays: the bottom row is the near foot's front, the top the
        head, a person's depth apart, and the car pitches (``person_height_slack_share``). A tall box must come
        that close to the prior's height: at least ``1 - max(person_height_slack_px / h, slack_share)``. Near,
        the fixed floor alone let through a box 0.64-0.75 of a person's height over paint by the image's left
        edge, where true detections 60 px tall or more never fell under 0.91 (one 2.3 m away, 110 px, 0.906)."""
        ratio = self.geometry.height_ratio(box, "pedestrian")
        lo, hi = self.rules.person_height_ratio
        if math.isfinite(ratio):
            height_px = float(box[3]) - float(box[1])
            slack = max(self.rules.person_height_slack_px / height_px, self.rules.person_height_slack_share)
            return max(lo, 1.0 - slack) <= ratio <= hi
        cut = self.geometry.cut_height_ratio(box, "pedestrian")
        return not math.isfinite(cut) or cut >= self.rules.cut_person_height_ratio
