"""Shared vocabulary between the world and the renderer: semantic classes, light states, and the
snapshot of a moving object. The world fills these in; the renderer only reads them.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class SemanticClass(IntEnum):
    """Per-pixel class ids of the segmentation map (channel 0)."""

    SKY = 0
    GROUND = 1  # grass, parks
    ROAD = 2
    LANE_MARKING = 3  # centre, divider and edge lines
    STOP_LINE = 4
    CROSSWALK = 5
    SIDEWALK = 6
    BUILDING = 7
    VEGETATION = 8
    POLE = 9  # light poles and mast arms
    TRAFFIC_LIGHT = 10  # the light's housing
    TRAFFIC_LAMP = 11  # the three lamps of a light (lit or dark)
    CAR = 12
    TRUCK = 13
    PEDESTRIAN = 14
    STOP_SIGN = 15  # a sign's plate (its post is POLE)
    YIELD_SIGN = 16
    SPEED_LIMIT_SIGN = 17


CAR_COLORS = [  # body colours of cars, moving and parked
    (0.75, 0.08, 0.08), (0.08, 0.20, 0.60), (0.92, 0.92, 0.90), (0.10, 0.10, 0.11), (0.55, 0.56, 0.58),
    (0.85, 0.65, 0.10), (0.10, 0.42, 0.20), (0.35, 0.55, 0.80), (0.60, 0.30, 0.10), (0.95, 0.45, 0.65),
]

LIGHT_ID_BASE = 10000  # segmentation object id of approach k's traffic light: LIGHT_ID_BASE + k
# Segmentation object id of the town's sign k: SIGN_ID_BASE + k. Below LIGHT_ID_BASE, so that code which takes
# every id from LIGHT_ID_BASE up for a light stays right; a town has at most MAX_SIGNS signs.
SIGN_ID_BASE = 9000
MAX_SIGNS = LIGHT_ID_BASE - SIGN_ID_BASE


class LightState(IntEnum):
    GREEN = 0
    YELLOW = 1
    RED = 2


@dataclass(frozen=True)
class ObjectSnapshot:
    """A moving object as the renderer and ground truth see it, in the map frame.

    ``object_id`` is unique within a world and stable over an episode; it is what the
    segmentation map's channel 1 holds for the object's pixels.
    """

    object_id: int
    kind: SemanticClass  # CAR, TRUCK or PEDESTRIAN
    x: float
    y: float
    heading: float
    length_m: float
    width_m: float
    height_m: float
    color: tuple[float, float, float]  # body (vehicles) or shirt (pedestrians), 0..1 RGB


_new = object.__new__


def snapshot_of(object_id: int, kind: SemanticClass, x: float, y: float, heading: float, length_m: float,
                width_m: float, height_m: float, color: tuple[float, float, float]) -> ObjectSnapshot:
    """``ObjectSnapshot(...)`` without the frozen dataclass's ``__init__``, which sets each field through
    ``object.__setattr__`` (0.9 µs a snapshot; the world builds forty every step). The result is the same
    object: same class, same fields, equal and hashing alike."""
    snap = _new(ObjectSnapshot)
    snap.__dict__.update(object_id=object_id, kind=kind, x=x, y=y, heading=heading, length_m=length_m,
                         width_m=width_m, height_m=height_m, color=color)
    return snap
