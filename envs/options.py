"""The valid values of ``DriveEnv.reset``'s options and of the episode settings drive.py passes on to it.

Why a module of its own: the environment checks its reset options and drive.py checks its flags against the
same ranges (``--traffic`` is the ``traffic_density`` option, ``--town-seed`` the ``town_seed`` one), so each
range is written once, here, and a bad value gets the same one sentence from either door.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from towndrive.sim.checks import check_number
from towndrive.sim.render import LIGHTING_PRESETS
from towndrive.sim.town import Town

RESET_OPTIONS = ("town_seed", "town_style", "weather", "traffic_density", "start", "goal", "world")
MAX_TOWN_SEED = 2**32 - 1  # NumPy's seeds are non-negative
# Up to 5x the default traffic (80 cars, 120 pedestrians); the densest data set used 2.5x. Far beyond it the
# spawner cannot place the cars and a reset would search for room for ever.
MAX_TRAFFIC_DENSITY = 5.0


def town_seed(value: Any, name: str = "town_seed") -> int:
    return check_number(name, value, 0, MAX_TOWN_SEED, integer=True)


def traffic_density(value: Any, name: str = "traffic_density") -> float:
    return check_number(name, value, 0.0, MAX_TRAFFIC_DENSITY)


def weather(value: Any, name: str = "weather") -> str:
    if not isinstance(value, str) or value not in LIGHTING_PRESETS:
        raise ValueError(f"Unknown {name} {value!r}; choose one of {', '.join(sorted(LIGHTING_PRESETS))}.")
    return value


def episode_seconds(value: Any, name: str = "max_time_s") -> float:
    return check_number(name, value, 0.0, None, lo_open=True)


def start_lane(town: Town, value: Any) -> tuple[str, str, int]:
    """A lane index of ``town`` (from node, to node, lane number), as World takes it."""
    lane = _tuple(value, 3)
    if lane is None or lane not in town.lane_info:
        example = town.road_lanes()[0]
        raise ValueError(f"start must be a lane index of town {town.seed} such as {example!r} "
                         f"(see town.road_lanes()); got {value!r}.")
    return lane  # type: ignore[return-value]


def goal_edge(town: Town, value: Any) -> tuple[str, str]:
    """A road of ``town`` (from node, to node), as World takes it."""
    edge = _tuple(value, 2)
    graph = town.network.graph
    if edge is None or edge[0] not in graph or edge[1] not in graph[edge[0]]:
        example = town.road_lanes()[0][:2]
        raise ValueError(f"goal must be an edge of town {town.seed} such as {example!r}; got {value!r}.")
    return edge  # type: ignore[return-value]


def _tuple(value: Any, n: int) -> tuple | None:
    if isinstance(value, str | bytes) or not isinstance(value, Sequence) or len(value) != n:
        return None
    try:
        out = tuple(value)
        hash(out)
    except TypeError:
        return None
    if n == 3 and not (isinstance(out[2], int) and not isinstance(out[2], bool)):
        return None
    return out


def check_reset_options(options: dict[str, Any] | None) -> dict[str, Any]:
    """The options with numbers checked and normalised (``start`` and ``goal`` are checked against the town in
    ``DriveEnv.reset``, once it is known); unknown names and bad values raise one ``ValueError`` sentence."""
    if options is not None and not isinstance(options, dict):
        raise ValueError(f"options must be a dict or None; got {type(options).__name__}.")
    options = dict(options or {})
    unknown = sorted(set(options) - set(RESET_OPTIONS), key=str)
    if unknown:
        raise ValueError(f"Unknown reset option(s) {unknown}; the options are {', '.join(RESET_OPTIONS)}.")
    if "town_seed" in options:
        options["town_seed"] = town_seed(options["town_seed"])
    if "traffic_density" in options:
        options["traffic_density"] = traffic_density(options["traffic_density"])
    if "weather" in options:
        options["weather"] = weather(options["weather"])
    if "town_style" in options:
        from towndrive.sim.town_style import style_named

        if not isinstance(options["town_style"], str):
            raise ValueError(f"town_style must be a style name; got {options['town_style']!r}.")
        style_named(options["town_style"])
    if "world" in options:
        from towndrive.sim.world import World

        if not isinstance(options["world"], World):
            raise ValueError(f"world must be a sim.world.World; got {type(options['world']).__name__}.")
    return options
