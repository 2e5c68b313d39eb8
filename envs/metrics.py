"""Closed-loop driving metrics, CARLA Leaderboard style, plus NVIDIA's autonomy.

Per episode:
  route_completion     % of the route's length driven along the route (0-100); 100 once the car has arrived
                       (within ``sim.world.ROUTE_ARRIVAL_M`` of the end, where the episode ends)
  infraction_penalty   product of the Leaderboard multipliers, once per infraction:
                       pedestrian collision 0.50, vehicle 0.60, static object 0.65, red light 0.70,
                       stop sign 0.80, failed to yield 0.70, speeding 0.90 (kinds without a multiplier, e.g.
                       wrong way, count 1.0); and once per safety-driver take-over,
                       ``EvaluationRules.takeover_penalty`` (0.70)
  driving_score        route_completion x infraction_penalty (0-100)
  infractions_per_km   every infraction kind, per kilometre driven
  autonomy             (1 - interventions x 6 s / elapsed s) x 100, at least 0
  mean_abs_lane_offset_m, mean_speed_mps
  standing_clear_s     seconds stood still with nothing in the path by ground truth (``envs.standing``)
  longest_clear_hold_s the longest such standstill without a break
  events               every infraction and take-over: kind, time, place, the other party (id and kind), the
                       light it concerns, the ego's speed, and the driver's reason when the driver gives one
  failed               only on an episode that could not be run (its worker crashed twice, or the driver
                       raised): the error; it counts as route completion and driving score 0 (never dropped,
                       as Bench2Drive counts a missing route as 0), its other figures are NaN

The intervention rule: a safety driver takes over when the car is more than 1 m off its lane centre
(measured outside the band between the centres of its direction's lanes, so that a lane change is not
a departure), makes an episode-ending infraction (collision, leaving the road) or deviates from the
route. Each take-over counts once and puts the car back on its route lane at a standstill, clear of
other cars, and the episode goes on; a driver with an ``on_intervention()`` method is told, so that what
it tracked or dead-reckoned about the place the car left starts afresh (as a car's system does when it
is engaged again).

Why a take-over costs score: CARLA has no safety driver; there a car that leaves its lanes or is stuck
after a collision ends its route, losing the rest of it. A take-over here lets the route go on, so
without a cost a route that needed a human would score like a clean one. 0.70 is the Leaderboard 2.0
multiplier for the other "the agent could not go on by itself" events (scenario timeout, minimum speed).

CARLA Leaderboard 2.0 rules, each off by default and chosen with ``EvaluationRules``:
  blocked_limit_s      "agent blocked": a car that has not moved (speed under 0.5 m/s) for this long ends
                       its route there (the Leaderboard uses 180 s); an ``agent_blocked`` event, no multiplier
  min_speed            "minimum speed": over each ``min_speed_section_m`` of route, the car's mean speed
                       against the mean speed of the vehicles within 50 m (steps with any); slower by a
                       ratio r < 1 multiplies by 0.7 + 0.3 r (the Leaderboard's formula)
  hold_timeout_s       the analogue of the Leaderboard's scenario timeout: standing this long with nothing
                       in the path (``envs.standing``) is a ``hold_timeout`` event, multiplier 0.70, and the
                       count starts again
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# The Leaderboard's multipliers; stop_sign is its "stop infraction" (0.80). The Leaderboard has neither of the
# other two rules of unsignalled towns, so: failed_to_yield 0.70, as a red light (both put the car in front of
# traffic that has the right of way; Leaderboard 2.0 also charges 0.70 for not yielding to an emergency vehicle);
# speeding 0.90, once per stretch over the limit: a rule broken with no other party at a conflict point, so it
# costs less than a rolled stop (0.80), but every stretch counts, so a car that speeds on every street pays often.
PENALTY = {"collision_pedestrian": 0.50, "collision_vehicle": 0.60, "collision_static": 0.65, "red_light": 0.70,
           "stop_sign": 0.80, "failed_to_yield": 0.70, "speeding": 0.90, "hold_timeout": 0.70}
INTERVENTION_INFRACTIONS = {"collision_pedestrian", "collision_vehicle", "collision_static", "off_road",
                            "route_deviation"}
INTERVENTION_OFFSET_M = 1.0
INTERVENTION_COST_S = 6.0
MIN_SPEED_RADIUS_M = 50.0  # the "surrounding traffic" of the minimum-speed rule
BLOCKED_SPEED_MPS = 0.5  # below this the car counts as not moving, for the agent-blocked rule


@dataclass(frozen=True)
class EvaluationRules:
    """What a take-over costs and which CARLA Leaderboard 2.0 rules apply (see the module docstring)."""

    takeover_penalty: float = 0.70
    blocked_limit_s: float | None = None  # the Leaderboard: 180.0
    min_speed: bool = False
    min_speed_section_m: float = 50.0
    hold_timeout_s: float | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.takeover_penalty <= 1.0:
            raise ValueError(f"takeover_penalty must be in [0, 1]; got {self.takeover_penalty}.")
        for name in ("blocked_limit_s", "hold_timeout_s"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be a positive number of seconds or None; got {value}.")
        if not self.min_speed_section_m > 0:
            raise ValueError(f"min_speed_section_m must be positive; got {self.min_speed_section_m}.")


@dataclass
class EpisodeTrace:
    """What one evaluation episode did, step by step (kept for metrics, plots and tables)."""

    seed: int
    route_total_m: float
    dt_s: float
    x: list[float] = field(default_factory=list)
    y: list[float] = field(default_factory=list)
    speed: list[float] = field(default_factory=list)
    steer: list[float] = field(default_factory=list)
    lane_offset: list[float] = field(default_factory=list)
    infractions: list[dict[str, Any]] = field(default_factory=list)
    interventions: list[float] = field(default_factory=list)  # times, seconds
    standing_clear: list[bool] = field(default_factory=list)  # per step: standing with nothing in the path
    events: list[dict[str, Any]] = field(default_factory=list)  # infractions and take-overs, in time order
    takeover_penalty: float = 0.70
    audit: dict[str, Any] | None = None  # envs.audit's comparison, when the evaluation ran it
    route_progress_m: float = 0.0
    route_completion: float = 0.0  # 0-1, the world's: 1 once the car has arrived
    distance_m: float = 0.0
    town_seed: int = 0
    weather: str = "noon"
    town_style: str = "classic"

    def add_step(self, info: dict[str, Any], action: np.ndarray, standing_clear: bool = False) -> None:
        """Keep one step's figures; ``standing_clear``: the car stood with nothing in its path (``envs.standing``)."""
        self.standing_clear.append(standing_clear)
        self.x.append(info["ego"]["x"])
        self.y.append(info["ego"]["y"])
        self.speed.append(info["ego"]["speed_mps"])
        self.steer.append(float(action[0]))
        self.lane_offset.append(info["lane_offset_m"])
        self.infractions += info["infractions"]
        self.route_progress_m = info["route"]["progress_m"]
        self.route_completion = info["route"]["completion"]
        self.distance_m = info["distance_m"]

    @property
    def elapsed_s(self) -> float:
        return len(self.speed) * self.dt_s


def needs_intervention(info: dict[str, Any]) -> bool:
    """The safety driver's rule (see module docstring)."""
    offset = info["lane_band_offset_m"]
    if not math.isfinite(offset) or offset > INTERVENTION_OFFSET_M:
        return True
    return any(inf["kind"] in INTERVENTION_INFRACTIONS for inf in info["infractions"])


def infraction_multiplier(infraction: dict[str, Any]) -> float:
    """The score multiplier of one infraction: its own (minimum speed) or its kind's."""
    return float(infraction.get("penalty", PENALTY.get(infraction["kind"], 1.0)))


def infraction_penalty(infractions: list[dict[str, Any]]) -> float:
    """The infraction penalty (the driving score's multiplier, before take-overs): the product of the multipliers."""
    penalty = 1.0
    for inf in infractions:
        penalty *= infraction_multiplier(inf)
    return penalty


def episode_metrics(trace: EpisodeTrace) -> dict[str, Any]:
    counts: dict[str, int] = {}
    for inf in trace.infractions:
        counts[inf["kind"]] = counts.get(inf["kind"], 0) + 1
    penalty = infraction_penalty(trace.infractions)
    penalty *= trace.takeover_penalty ** len(trace.interventions)
    completion = 100.0 * trace.route_completion
    km = trace.distance_m / 1000.0
    offsets = np.abs(np.array([o for o in trace.lane_offset if math.isfinite(o)]))
    elapsed = max(trace.elapsed_s, 1e-6)
    return {
        "seed": trace.seed,
        "town_seed": trace.town_seed,
        "town_style": trace.town_style,
        "weather": trace.weather,
        "route_completion": round(completion, 3),
        "infraction_penalty": round(penalty, 6),
        "driving_score": round(completion * penalty, 3),
        "infractions": counts,
        "infractions_per_km": {k: round(v / km, 4) for k, v in counts.items()} if km > 0 else {},
        "interventions": len(trace.interventions),
        "autonomy": round(max(0.0, 1.0 - len(trace.interventions) * INTERVENTION_COST_S / elapsed) * 100.0, 3),
        "mean_abs_lane_offset_m": round(float(offsets.mean()) if len(offsets) else float("nan"), 4),
        "mean_speed_mps": round(float(np.mean(trace.speed)) if trace.speed else 0.0, 4),
        "distance_km": round(km, 4),
        "elapsed_s": round(elapsed, 2),
        "standing_clear_s": round(sum(trace.standing_clear) * trace.dt_s, 2),
        "longest_clear_hold_s": round(_longest_run(trace.standing_clear) * trace.dt_s, 2),
        "events": trace.events,
        **({"audit": trace.audit} if trace.audit is not None else {}),
    }


def failed_episode_metrics(seed: int, town_seed: int, weather: str, error: str) -> dict[str, Any]:
    """The figures of an episode that could not be run: zero score and completion, the error, nothing measured."""
    nan = float("nan")
    return {"seed": seed, "town_seed": town_seed, "weather": weather, "route_completion": 0.0,
            "infraction_penalty": nan, "driving_score": 0.0, "infractions": {}, "infractions_per_km": {},
            "interventions": 0, "autonomy": nan, "mean_abs_lane_offset_m": nan, "mean_speed_mps": nan,
            "distance_km": 0.0, "elapsed_s": 0.0, "standing_clear_s": 0.0, "longest_clear_hold_s": 0.0,
            "events": [], "failed": error}


def _longest_run(flags: list[bool]) -> int:
    """The longest run of consecutive True values."""
    best = run = 0
    for flag in flags:
        run = run + 1 if flag else 0
        best = max(best, run)
    return best


def aggregate(per_episode: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over episodes; infractions per km over the total distance."""
    keys = ["route_completion", "infraction_penalty", "driving_score", "autonomy", "mean_abs_lane_offset_m",
            "mean_speed_mps"]
    mean = {k: round(float(np.nanmean([e[k] for e in per_episode])), 4) for k in keys}
    total_km = sum(e["distance_km"] for e in per_episode)
    totals: dict[str, int] = {}
    for e in per_episode:
        for kind, n in e["infractions"].items():
            totals[kind] = totals.get(kind, 0) + n
    mean["infractions"] = totals
    mean["infractions_per_km"] = {k: round(v / total_km, 4) for k, v in totals.items()} if total_km > 0 else {}
    mean["interventions"] = sum(e["interventions"] for e in per_episode)
    mean["standing_clear_s"] = round(sum(e.get("standing_clear_s", 0.0) for e in per_episode), 2)
    mean["longest_clear_hold_s"] = max((e.get("longest_clear_hold_s", 0.0) for e in per_episode), default=0.0)
    audits = [e["audit"] for e in per_episode if "audit" in e]
    if audits:
        from towndrive.envs.audit import merge

        mean["audit"] = merge(audits)
    mean["distance_km"] = round(total_km, 4)
    mean["episodes"] = len(per_episode)
    failed = sum("failed" in e for e in per_episode)
    if failed:
        mean["failed"] = failed
    return mean


def markdown_table(driver: str, per_episode: list[dict[str, Any]], mean: dict[str, Any]) -> str:
    head = ("| episode (seed, town, weather) | route completion % | penalty | driving score | autonomy % | interventions "
            "| mean abs offset m | mean speed m/s | standing clear s | infractions |")
    lines = [f"# Closed-loop evaluation: {driver}", "", head, "|" + "---|" * 10]
    for e in per_episode:
        inf = ", ".join(f"{k} {v}" for k, v in sorted(e["infractions"].items())) or "none"
        if "failed" in e:
            inf = f"FAILED (counted as 0): {e['failed']}"
        where = f"{e['seed']}, {e.get('town_seed', '')}, {e.get('weather', '')}"
        lines.append(f"| {where} | {e['route_completion']:.1f} | {e['infraction_penalty']:.3f} | "
                     f"{e['driving_score']:.1f} | {e['autonomy']:.1f} | {e['interventions']} | "
                     f"{e['mean_abs_lane_offset_m']:.3f} | {e['mean_speed_mps']:.2f} | "
                     f"{e.get('standing_clear_s', 0.0):.1f} | {inf} |")
    inf = ", ".join(f"{k} {v}" for k, v in sorted(mean["infractions"].items())) or "none"
    if mean.get("failed"):
        inf += f"; {mean['failed']} episode(s) failed"
    lines.append(f"| **mean** | {mean['route_completion']:.1f} | {mean['infraction_penalty']:.3f} | "
                 f"**{mean['driving_score']:.1f}** | {mean['autonomy']:.1f} | {mean['interventions']} | "
                 f"{mean['mean_abs_lane_offset_m']:.3f} | {mean['mean_speed_mps']:.2f} | "
                 f"{mean.get('standing_clear_s', 0.0):.1f} | {inf} |")
    if any(e.get("events") for e in per_episode):
        lines += ["", "## Events", "", "Replay one up to its moment with `python drive.py --driver NAME --evaluate --seed SEED "
                  "--town-seed TOWN --weather WEATHER --until TIME` (and the evaluation's other options, e.g. --traffic).",
                  ""]
        for e in per_episode:
            if not e.get("events"):
                continue
            lines.append(f"Episode {e['seed']} (town {e.get('town_seed', '')}, {e.get('weather', '')}):")
            lines.append("")
            lines += [f"- {describe_event(ev)}" for ev in e["events"]]
            lines.append("")
    if "audit" in mean:
        lines += ["", "## Audit of the infraction detectors (envs.audit)", "",
                  "| kind | confirmed | reported, not confirmed | missed |", "|---|---|---|---|"]
        lines += [f"| {kind} | {c['confirmed']} | {c['unconfirmed']} | {c['missed']} |" for kind, c in mean["audit"].items()]
    return "\n".join(lines) + "\n"


def describe_event(event: dict[str, Any]) -> str:
    """One line for an event: when, what, where, with whom, how fast, the driver's reason, its clip."""
    parts = [f"{event['time_s']:.2f} s **{event['kind']}** at ({event['x']:.1f}, {event['y']:.1f})"]
    if event.get("other_kind"):
        parts.append(f"{event['other_kind']} #{event['other_id']}")
    if event.get("approach", -1) >= 0:
        parts.append(f"light and stop bar of approach {event['approach']}")
    if "speed_mps" in event:
        parts.append(f"{event['speed_mps'] * 3.6:.1f} km/h")
    if event.get("why"):
        parts.append(event["why"])
    if event.get("reason"):
        parts.append(f"driver: \"{event['reason']}\"")
    if event.get("clip"):
        parts.append(f"clip `{event['clip']}`")
    return ", ".join(parts)
