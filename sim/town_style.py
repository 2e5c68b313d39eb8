"""Town styles: named recipes for the kind of place a town seed grows into.

Why: towns that are all one design teach drivers and detectors that design. A style says what mix
of streets, junction controls, signal mounts, lane widths, block sizes, buildings, trees and parked
cars a town has; the seed then draws one town from it. The style's name and numbers are part of the
town's recipe (``TownConfig.style``), so a (style, seed) pair always gives the same town.
``classic`` is the original town: arterials everywhere, signalised junctions with mast arms, no
posted limits, no parked cars; its towns are the same as before styles existed.
"""

from __future__ import annotations

from dataclasses import dataclass

from towndrive.sim.checks import check_number
from towndrive.sim.spec import ROAD


@dataclass(frozen=True)
class ControlMix:
    """Weights of the junction controls drawn for one pairing of street types (normalised when drawn)."""

    signal: float = 1.0
    all_way_stop: float = 0.0
    side_stop: float = 0.0  # the minor street stops, the major one has priority
    side_yield: float = 0.0  # the minor street gives way, the major one has priority

    def weights(self) -> list[float]:
        return [self.signal, self.all_way_stop, self.side_stop, self.side_yield]


@dataclass(frozen=True)
class SignalMounts:
    """Weights of where a junction's signal heads hang (one mount per junction)."""

    mast_arm: float = 1.0  # over the lanes, on an arm from the far-right corner
    far_pole: float = 0.0  # on a post at the far-right corner
    near_pole: float = 0.0  # on a post at the near-right corner, beside the stop line

    def weights(self) -> list[float]:
        return [self.mast_arm, self.far_pole, self.near_pole]


@dataclass(frozen=True)
class TownStyle:
    """What a style's towns are made of. Ranges are (low, high) and drawn per town or per street."""

    name: str
    block_size_m: float = 95.0
    block_jitter_m: float = 12.0
    lane_width_range_m: tuple[float, float] = (ROAD.lane_width_m, ROAD.lane_width_m)  # one width per town
    arterial_share: float = 1.0  # chance that an inner grid line is an arterial (else residential)
    ring_arterial: bool = True  # the ring road around the town
    arterial_pair: ControlMix = ControlMix()  # junction of two arterials
    mixed_pair: ControlMix = ControlMix()  # arterial meets residential street
    residential_pair: ControlMix = ControlMix()  # two residential streets
    mounts: SignalMounts = SignalMounts()
    setback_extra_m: tuple[float, float] | None = None  # stop bar beyond the crossing; None: the fixed default
    corner_radius_m: float | None = None  # the kerb's radius at junction corners (None: the classic 3 m); the
    #   right turns go round it, and the zebras start where it ends
    arterial_limit_kmh: int | None = None  # posted limits; None: nothing posted
    residential_limit_kmh: int | None = None
    parking_strip_m: float = 0.0  # residential streets' parking strip along each kerb (0: none)
    parked_per_100m: float = 0.0  # parked cars per 100 m of parking strip
    building_height_m: tuple[float, float] = (6.0, 14.0)
    building_centre_extra_m: float = 34.0  # extra height towards the town centre
    building_colors: tuple[tuple[float, float, float], ...] = ()  # empty: the classic palette
    tree_spacing_m: float = 16.0
    park_probability: float = 0.15
    skew_deg: tuple[float, float] = (0.0, 0.0)  # columns lean by this much (either way): junctions meet at 90 +- it
    bow_m: tuple[float, float] = (0.0, 0.0)  # rows and columns arch by this much (either way) mid-town

    def __post_init__(self) -> None:
        lo, hi = self.lane_width_range_m
        check_number(f"style {self.name} lane width", lo, 2.8, 4.0)
        check_number(f"style {self.name} lane width", hi, lo, 4.0)
        check_number(f"style {self.name} arterial_share", self.arterial_share, 0.0, 1.0)
        check_number(f"style {self.name} parking_strip_m", self.parking_strip_m, 0.0, 3.0)
        check_number(f"style {self.name} skew", self.skew_deg[0], 0.0, 25.0)
        check_number(f"style {self.name} skew", self.skew_deg[1], self.skew_deg[0], 25.0)
        check_number(f"style {self.name} bow", self.bow_m[0], 0.0, 30.0)
        check_number(f"style {self.name} bow", self.bow_m[1], self.bow_m[0], 30.0)


CLASSIC = TownStyle("classic")

DOWNTOWN = TownStyle(
    "downtown",
    block_size_m=82.0,
    block_jitter_m=10.0,
    lane_width_range_m=(3.25, 3.75),
    arterial_share=0.7,
    arterial_pair=ControlMix(signal=1.0),
    mixed_pair=ControlMix(signal=0.6, side_stop=0.25, side_yield=0.15),
    residential_pair=ControlMix(all_way_stop=1.0),
    mounts=SignalMounts(mast_arm=0.4, far_pole=0.35, near_pole=0.25),
    setback_extra_m=(0.5, 4.0),
    corner_radius_m=6.5,
    arterial_limit_kmh=50,
    residential_limit_kmh=30,
    parking_strip_m=2.2,
    parked_per_100m=3.0,
    building_height_m=(12.0, 26.0),
    building_centre_extra_m=60.0,
    building_colors=((0.55, 0.58, 0.62), (0.42, 0.46, 0.52), (0.70, 0.72, 0.74), (0.36, 0.50, 0.62),
                     (0.80, 0.78, 0.72), (0.62, 0.52, 0.46), (0.30, 0.33, 0.38), (0.58, 0.66, 0.74)),
    tree_spacing_m=22.0,
    park_probability=0.08,
    skew_deg=(0.0, 12.0),
)

SUBURB = TownStyle(
    "suburb",
    block_size_m=112.0,
    block_jitter_m=14.0,
    lane_width_range_m=(3.0, 3.4),
    arterial_share=0.2,
    arterial_pair=ControlMix(signal=1.0),
    mixed_pair=ControlMix(signal=0.2, side_stop=0.5, side_yield=0.3),
    residential_pair=ControlMix(all_way_stop=0.5, side_stop=0.25, side_yield=0.25),
    mounts=SignalMounts(mast_arm=0.3, far_pole=0.7),
    setback_extra_m=(0.5, 5.0),
    corner_radius_m=7.0,
    arterial_limit_kmh=50,
    residential_limit_kmh=30,
    parking_strip_m=2.2,
    parked_per_100m=5.0,
    building_height_m=(4.5, 8.5),
    building_centre_extra_m=4.0,
    building_colors=((0.93, 0.88, 0.76), (0.85, 0.72, 0.60), (0.78, 0.83, 0.86), (0.90, 0.90, 0.86),
                     (0.72, 0.60, 0.48), (0.88, 0.80, 0.70), (0.70, 0.76, 0.66), (0.95, 0.93, 0.90)),
    tree_spacing_m=11.0,
    park_probability=0.22,
    bow_m=(8.0, 20.0),  # winding streets (a bow's slope narrows a street by cos(slope): 2 % at most)
)

STYLES: dict[str, TownStyle] = {s.name: s for s in (CLASSIC, DOWNTOWN, SUBURB)}


def style_named(name: str) -> TownStyle:
    """The style of that name, or one sentence naming the styles there are."""
    style = STYLES.get(name)
    if style is None:
        raise ValueError(f"unknown town style {name!r}; the styles are {', '.join(sorted(STYLES))}.")
    return style
