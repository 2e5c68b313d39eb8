"""The look over the shoulder before a lane change, through the door-mirror cameras.

Why: the forward camera sees 45 degrees either side of the axis, so a car overtaking in the next lane is
invisible from a few metres behind our rear bumper until it is well past our front, and PilotNet moves into the
lane a turn needs as soon as the route announces the turn, whether that lane is free or not. The agent looks
through the blind-spot cameras (``DriveEnv.blind_spot_frame``), left and right in turn every few frames, and
more often on the side of a pending lane change (a left or right command, no turn under way yet, no solid line
on that side), and runs the detector on the picture. A vehicle seen in the zone beside and up to 6 m behind
holds a lane change towards it (PilotNet is asked to follow its lane): for ``memory_s`` after it was last seen
alongside, and the car eases off so the other one passes (a car right beside fills the mirror camera's picture
and is not detected, but it crossed the zone behind first, and the route may announce the turn only when it is
already alongside); for ``behind_memory_s`` after it was last seen behind.

On by default (``BlindSpotConfig(enabled=False)`` turns it off); without it the agent fails the
``overtaken_before_turn`` scenario. The zone ends close behind, a vehicle last seen behind holds the change only
briefly, and only one alongside caps the speed: a car that follows rather than overtakes is merged in front of
(it brakes for us). Waiting for every follower, and easing off for it, keeps the car beside traffic that slows
for the same junction, and the turn is then taken from the wrong lane, across that traffic. What went wrong
without these rules: ``docs/agent_rules.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from towndrive.agent.perception.detector import Detection

if TYPE_CHECKING:
    from towndrive.agent.perception.box_geometry import BoxGeometry
    from towndrive.agent.perception.lanes import LaneResult

VEHICLES = ("car", "truck")


@dataclass(frozen=True)
class BlindSpotConfig:
    enabled: bool = True
    look_every: int = 2  # frames between looks on the side of a pending lane change
    idle_every: int = 5  # otherwise, frames between looks (left and right in turn)
    score_threshold: float = 0.4
    zone_ahead_m: float = 3.0  # the zone, from the car's centre: this far ahead ...
    zone_behind_m: float = 6.0  # ... to this far behind: a vehicle farther back, or one that follows rather than
    #                              overtakes and falls back there, is merged in front of (it brakes for us)
    zone_near_m: float = 1.5  # ... and from this far out from the car's centre line (its side is 0.95 m out)
    zone_far_m: float = 6.0  # ... to this far (the next lane's centre is 3.5 m out)
    beside_m: float = -3.0  # seen at least this far forward, a vehicle is alongside or about to be
    memory_s: float = 3.0  # a vehicle last seen alongside holds the change this long (it fills the picture there)
    behind_memory_s: float = 1.0  # ... one last seen behind, this long
    yield_speed_mps: float = 5.0  # while one is alongside, cruise no faster (town traffic runs at 8 m/s and passes)


@dataclass(frozen=True)
class SideMount:
    """Where a camera turned to the side sits (the blind-spot cameras, ``envs.drive_env.blind_spot_pose``; the
    cross-traffic cameras, ``corner_pose``): ahead of the car's centre, out to the side, and turned this far from
    the car's axis towards the side."""

    ahead_m: float
    out_m: float
    yaw_deg: float

    def in_ground_frame(self, side: str, camera_ahead_m: float) -> tuple[float, float, float]:
        """The camera on ``side`` in the forward camera's ground frame (that camera ``camera_ahead_m`` ahead of the
        car's centre): metres right of it and ahead of it, and radians turned right of its axis."""
        sign = 1.0 if side == "right" else -1.0
        return sign * self.out_m, self.ahead_m - camera_ahead_m, sign * math.radians(self.yaw_deg)


def side_camera_ground(geometry: BoxGeometry, mount: SideMount, det: Detection, side: str) -> tuple[float, float]:
    """A vehicle detected by a camera turned to ``side``: its near face on the ground, in the car's frame (metres
    ahead of the car's centre, metres out from its centre line on ``side``)."""
    x0, _, x1, _ = det.box
    z = geometry.distance(det.box, det.name)
    x = geometry.lateral(0.5 * (x0 + x1), z)  # right of the camera's axis
    a = math.radians(mount.yaw_deg)
    # Looking out at angle a from the car's axis, the right camera's right-hand side points back (and in); the
    # left camera is its mirror image, so its picture's left points back.
    if side == "left":
        x = -x
    return mount.ahead_m + z * math.cos(a) - x * math.sin(a), mount.out_m + z * math.sin(a) + x * math.cos(a)


class BlindSpot:
    """Vehicles in the zone beside and behind the car, from detections in a blind-spot camera frame."""

    def __init__(self, geometry: BoxGeometry, mount: SideMount, config: BlindSpotConfig | None = None) -> None:
        self.geometry = geometry
        self.mount = mount
        self.config = config or BlindSpotConfig()
        self.reset()

    def reset(self) -> None:
        self.until_s = {"left": -math.inf, "right": -math.inf}  # a change towards the side is held until then
        self.nearest: dict[str, tuple[float, float]] = {}  # (ahead, out) of the last vehicle seen in each zone

    def position(self, det: Detection, side: str) -> tuple[float, float]:
        """The detected vehicle's near face on the ground, in the car's frame (``side_camera_ground``)."""
        return side_camera_ground(self.geometry, self.mount, det, side)

    def in_zone(self, ahead: float, out: float) -> bool:
        cfg = self.config
        return -cfg.zone_behind_m <= ahead <= cfg.zone_ahead_m and cfg.zone_near_m <= out <= cfg.zone_far_m

    def update(self, t: float, side: str, detections: list[Detection]) -> list[tuple[float, float]]:
        """Take one look on ``side``; returns the positions of the vehicles found in its zone."""
        found = []
        for d in detections:
            if d.name in VEHICLES and d.score >= self.config.score_threshold:
                ahead, out = self.position(d, side)
                if math.isfinite(ahead) and self.in_zone(ahead, out):
                    found.append((ahead, out))
        if found:
            self.nearest[side] = max(found)  # the one farthest forward: the one we would move into
            beside = self.nearest[side][0] >= self.config.beside_m
            self.until_s[side] = t + (self.config.memory_s if beside else self.config.behind_memory_s)
        return found

    def alongside(self, side: str) -> bool:
        """Was the last vehicle seen on ``side`` alongside (or about to be), rather than following?"""
        near = self.nearest.get(side)
        return near is not None and near[0] >= self.config.beside_m

    def holding(self, t: float, side: str | None) -> bool:
        """Is a lane change towards ``side`` held at time ``t``?"""
        return side is not None and t < self.until_s[side]

    def reason(self, side: str) -> str:
        near = self.nearest.get(side)
        where = "" if near is None else f" ({-near[0]:.0f} m back when last seen)"
        return f"vehicle in the {side} blind spot{where}: lane change held"

    def plan(self, frame: int, command: int, junction_placed: bool,
             lanes: LaneResult | None) -> tuple[str | None, str | None]:
        """The side of a pending lane change (or None) and the side ``check`` looks through on ``frame`` (or None).
        Pending: a left or right command, no junction turn placed yet, and no solid line seen on that side last
        frame (``lanes``; a solid line there is the road's edge or centre line: no lane to go to). A caller that
        must render the mirror frame ahead of time (the agent's pipelined mode) asks here which one."""
        cfg = self.config
        side = {1: "left", 2: "right"}.get(command)
        if side is not None and junction_placed:
            side = None
        if side is not None and lanes is not None:
            line = lanes.left if side == "left" else lanes.right
            if line is not None and line.style == "solid":
                side = None
        looked = None
        if side is not None and frame % cfg.look_every == 0:
            looked = side
        elif side is None and frame % cfg.idle_every == 0:
            looked = ("left", "right")[(frame // cfg.idle_every) % 2]
        return side, looked

    def check(self, t: float, frame: int, command: int, junction_placed: bool, lanes: LaneResult | None,
              look: Callable[[str], np.ndarray], detect: Callable[[np.ndarray], list[Detection]]) -> str | None:
        """Look through a mirror camera when it is time (``plan``); the side of a pending lane change that is
        held, else None. ``detect`` need only find vehicles: nothing else in the picture is read."""
        side, looked = self.plan(frame, command, junction_placed, lanes)
        if looked is not None:
            self.update(t, looked, detect(look(looked)))
        return side if self.holding(t, side) else None
