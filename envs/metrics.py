"""Closed-loop driving metrics, CARLA Leaderboard style, plus NVIDIA's autonomy.

Per episode:
  route_completion     % of the route's length driven along the route (0-100)
  infraction_penalty   product of the Leaderboard multipliers, once per infraction:
                       pedestrian collision 0.50, vehicle 0.60, static object 0.65, red light 0.70,
                       stop-line violation 0.80 (kinds without a multiplier, e.g. wrong way, count 1.0)
  driving_score        route_completion x infraction_penalty (0-100)
  infractions_per_km   every infraction kind, per kilometre driven
  autonomy             (1 - interventions x 6 s / elapsed s) x 100, at least 0
  mean_abs_lane_offset_m, mean_speed_mps
  standing_clear_s     seconds stood still with nothing in the path by ground truth (``envs.standing``)
  longest_clear_hold_s the longest such standstill without a break

The intervention rule: a safety driver takes over when the car is more than 1 m off its lane centre
(measured outside the band between the centres of its direction's lanes, so that a lane change is not
a departure), makes an episode-ending infraction (collision, leaving the road) or deviates from the
route. Each take-over counts once and puts the car back on its route lane at a standstill, clear of
other cars, and the episode goes on; a driver with an ``on_intervention()`` method is told, so that what
it tracked or dead-reckoned about the place the car left starts afresh (as a car's system does when it
is engaged again).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

PENALTY = {"collision_pedestrian": 0.50, "collision_vehicle": 0.60, "collision_static": 0.65, "red_light": 0.70,
           "stop_line": 0.80}
INTERVENTION_INFRACTIONS = {"collision_pedestrian", "collision_vehicle", "collision_static", "off_road",
                            "route_deviation"}
INTERVENTION_OFFSET_M = 1.0
INTERVENTION_COST_S = 6.0


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
    route_progress_m: float = 0.0
    distance_m: float = 0.0
    town_seed: int = 0
    weather: str = "noon"

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


def episode_metrics(trace: EpisodeTrace) -> dict[str, Any]:
    counts: dict[str, int] = {}
    for inf in trace.infractions:
        counts[inf["kind"]] = counts.get(inf["kind"], 0) + 1
    penalty = 1.0
    for kind, n in counts.items():
        penalty *= PENALTY.get(kind, 1.0) ** n
    completion = 100.0 * min(1.0, trace.route_progress_m / max(trace.route_total_m, 1e-6))
    km = trace.distance_m / 1000.0
    offsets = np.abs(np.array([o for o in trace.lane_offset if math.isfinite(o)]))
    elapsed = max(trace.elapsed_s, 1e-6)
    return {
        "seed": trace.seed,
        "town_seed": trace.town_seed,
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
    }


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
    mean["distance_km"] = round(total_km, 4)
    mean["episodes"] = len(per_episode)
    return mean


def markdown_table(driver: str, per_episode: list[dict[str, Any]], mean: dict[str, Any]) -> str:
    head = ("| episode (seed, town, weather) | route completion % | penalty | driving score | autonomy % | interventions "
            "| mean abs offset m | mean speed m/s | infractions |")
    lines = [f"# Closed-loop evaluation: {driver}", "", head, "|" + "---|" * 9]
    for e in per_episode:
        inf = ", ".join(f"{k} {v}" for k, v in sorted(e["infractions"].items())) or "none"
        where = f"{e['seed']}, {e.get('town_seed', '')}, {e.get('weather', '')}"
        lines.append(f"| {where} | {e['route_completion']:.1f} | {e['infraction_penalty']:.3f} | "
                     f"{e['driving_score']:.1f} | {e['autonomy']:.1f} | {e['interventions']} | "
                     f"{e['mean_abs_lane_offset_m']:.3f} | {e['mean_speed_mps']:.2f} | {inf} |")
    inf = ", ".join(f"{k} {v}" for k, v in sorted(mean["infractions"].items())) or "none"
    lines.append(f"| **mean** | {mean['route_completion']:.1f} | {mean['infraction_penalty']:.3f} | "
                 f"**{mean['driving_score']:.1f}** | {mean['autonomy']:.1f} | {mean['interventions']} | "
                 f"{mean['mean_abs_lane_offset_m']:.3f} | {mean['mean_speed_mps']:.2f} | {inf} |")
    return "\n".join(lines) + "\n"
