"""The scenario suite: seed 004's eight test cases (section 3.11), plus a yellow light too close to
stop for, a turn by command, and a turn announced while a car overtakes in the lane the turn needs.
Each scenario is deterministic (fixed town, placement, seed) and has a pass/fail rule checked on what happened.

All of them take place on the same approach to a four-way junction of the default town: the ego starts
on lane 0, ``START_BEFORE_STOP_M`` before the stop line, with no other traffic unless the scenario adds it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.ego import EgoVehicle
from towndrive.sim.objects import LightState, SemanticClass
from towndrive.sim.pedestrians import PedestrianCrowd
from towndrive.sim.routes import shortest_route
from towndrive.sim.town import OPPOSITE, Approach, Arm, Command, Edge, Town
from towndrive.sim.traffic import TownVehicle
from towndrive.sim.world import World, cached_town

if TYPE_CHECKING:
    from towndrive.envs.parallel import Worker

START_BEFORE_STOP_M = 55.0
APPROACH_NODE = (1, 1)
APPROACH_ARM = Arm.W  # traffic arrives from the west arm, driving east
OVERTAKER_BEHIND_M = 6.0  # centre to centre: without a look in the mirror, PilotNet moves into it


@dataclass
class ScenarioResult:
    name: str
    passed: bool
    detail: str
    time_s: float


@dataclass
class Log:
    """Per-step record a scenario's rule reads."""

    t: list[float] = field(default_factory=list)
    speed: list[float] = field(default_factory=list)
    light_distance: list[float] = field(default_factory=list)
    progress: list[float] = field(default_factory=list)
    lead_gap: list[float] = field(default_factory=list)
    infractions: list[str] = field(default_factory=list)
    edges: list[Edge] = field(default_factory=list)

    def before(self, time_s: float) -> Log:
        """The steps before a time (the infractions stay: they are counted over the whole run)."""
        n = sum(t < time_s for t in self.t)
        return Log(self.t[:n], self.speed[:n], self.light_distance[:n], self.progress[:n], self.lead_gap[:n],
                   self.infractions, self.edges[:n])


@dataclass
class Scenario:
    description: str
    duration_s: float
    setup: Callable[[World, Approach], dict[str, Any]]
    check: Callable[[Log, dict[str, Any]], tuple[bool, str]]
    weather: str = "noon"
    turn: Command = Command.STRAIGHT
    hook: Callable[[World, dict[str, Any]], None] | None = None


def exit_edge(town: Town, node: tuple[int, int], arm: Arm) -> Edge:
    frm = f"{node[0]}-{node[1]}{arm.name}o"
    return frm, next(iter(town.network.graph[frm]))


def build_world(config: DriveConfig, scenario: Scenario) -> tuple[World, Approach]:
    town = cached_town(config.world.town, config.town_seed)
    ap = town.approach_at(APPROACH_NODE, APPROACH_ARM)
    assert ap is not None
    travel_arm = OPPOSITE[APPROACH_ARM]  # straight on
    if scenario.turn == Command.LEFT:
        travel_arm = Arm.N
    elif scenario.turn == Command.RIGHT:
        travel_arm = Arm.S
    goal = shortest_route(town, ap.edge, exit_edge(town, APPROACH_NODE, travel_arm))[-1]
    lane = town.network.graph[ap.edge[0]][ap.edge[1]][0]
    world_cfg = replace(config.world, npc_count=0, pedestrian_count=0)
    world = World(town, world_cfg, seed=0, start=(ap.edge[0], ap.edge[1], 0),
                  start_s=lane.length - 0.5 - START_BEFORE_STOP_M - EgoVehicle.LENGTH / 2, goal=goal,
                  spawn_traffic=False)
    world.lights.force(ap.index, LightState.GREEN, until_s=1e9)
    return world, ap


# ---------------------------------------------------------------------------- the scenarios
def _lead_car(color: tuple[float, float, float]) -> Callable[[World, Approach], dict[str, Any]]:
    def setup(world: World, ap: Approach) -> dict[str, Any]:
        lane_index = (ap.edge[0], ap.edge[1], 0)
        s = world.town.lane(lane_index).local_coordinates(world.ego.position)[0] + 30.0
        npc = world.spawn_npc(lane_index, s, SemanticClass.CAR, color=color, target_speed=0.0)
        assert npc is not None
        npc.speed = 0.0
        return {"lead": npc}
    return setup


def _check_stop_behind(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    stopped = [g for v, g in zip(log.speed, log.lead_gap, strict=True) if v < 0.1 and math.isfinite(g)]
    if log.infractions:
        return False, f"infractions: {log.infractions}"
    if not stopped:
        return False, f"never stopped (min speed {min(log.speed):.2f} m/s)"
    gap = stopped[-1]
    return 1.0 <= gap <= 8.0, f"stopped {gap:.1f} m behind the car (want 1-8 m)"


def _drive_away_hook(world: World, ctx: dict[str, Any]) -> None:
    if world.time_s >= ctx.setdefault("go_at_s", 10.0):
        ctx["lead"].target_speed = 9.0


def _check_resume(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    before = log.before(ctx["go_at_s"])
    if not (before.speed and min(before.speed) < 0.1):
        return False, "did not stop behind the car before it left"
    moved = log.progress[-1] - log.progress[len(before.t)] if len(log.t) > len(before.t) else 0.0
    return (moved >= 20.0 and not log.infractions, f"moved {moved:.0f} m after the car left (want >= 20 m); "
            f"infractions: {log.infractions or 'none'}")


def _red(world: World, ap: Approach) -> dict[str, Any]:
    world.lights.force(ap.index, LightState.RED, until_s=1e9)
    return {"ap": ap}


def _check_stop_line(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    if "red_light" in log.infractions:
        return False, "ran the red light"
    stops = [d for v, d in zip(log.speed, log.light_distance, strict=True) if v < 0.1 and math.isfinite(d)]
    if not stops:
        return False, f"never stopped (min speed {min(log.speed):.2f} m/s)"
    return 0.0 <= stops[-1] <= 2.0, f"stopped {stops[-1]:.2f} m before the stop line (want 0-2 m)"


def _red_then_green(world: World, ap: Approach) -> dict[str, Any]:
    world.lights.force(ap.index, LightState.RED, until_s=12.0)
    return {"ap": ap, "green_at_s": 12.0}


def _green_after_hook(world: World, ctx: dict[str, Any]) -> None:
    if world.time_s >= ctx["green_at_s"] and not ctx.get("turned"):
        world.lights.force(ctx["ap"].index, LightState.GREEN, until_s=1e9)
        ctx["turned"] = True


def _check_red_then_green(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    ok, detail = _check_stop_line(log.before(ctx["green_at_s"]), ctx)
    if not ok:
        return False, detail
    crossed = log.edges[-1] != ctx["ap"].edge
    return crossed and not log.infractions, f"{detail}; drove on after green: {crossed}"


def _quiet(world: World, ap: Approach) -> dict[str, Any]:
    return {}


def _check_clean_progress(min_m: float) -> Callable[[Log, dict[str, Any]], tuple[bool, str]]:
    def check(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
        moved = log.progress[-1] - log.progress[0]
        return (moved >= min_m and not log.infractions,
                f"drove {moved:.0f} m along the route (want >= {min_m:.0f}); infractions: {log.infractions or 'none'}")
    return check


def _passing_cars(world: World, ap: Approach) -> dict[str, Any]:
    town = world.town
    ego_s = town.lane((ap.edge[0], ap.edge[1], 0)).local_coordinates(world.ego.position)[0]
    # a faster car overtaking in the next lane of our direction, and one coming the other way
    world.spawn_npc((ap.edge[0], ap.edge[1], 1), max(ego_s - 15.0, 2.0), SemanticClass.CAR,
                    color=(0.1, 0.2, 0.6), target_speed=12.0)
    node, west = APPROACH_NODE, (APPROACH_NODE[0] - 1, APPROACH_NODE[1])
    opposite = (f"{node[0]}-{node[1]}Wo", f"{west[0]}-{west[1]}Ei", 0)  # the same road, the other way
    world.spawn_npc(opposite, 5.0, SemanticClass.TRUCK, color=(0.9, 0.9, 0.9), target_speed=9.0)
    return {}


def _check_no_stop(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    t = np.array(log.t)
    cruising = np.array(log.speed)[t > 5.0]
    low = float(cruising.min()) if cruising.size else 0.0
    return low > 5.0 and not log.infractions, f"lowest speed after 5 s {low:.1f} m/s (want > 5: no stop)"


def _pedestrian(world: World, ap: Approach) -> dict[str, Any]:
    town = world.town
    lane = town.lane((ap.edge[0], ap.edge[1], 0))
    s = lane.local_coordinates(world.ego.position)[0] + 22.0
    kerb = lane.position(s, 1.5 * town.lane_width + 0.4)  # on our kerb (lane 0's centre is half a lane in)
    far = lane.position(s, -2.5 * town.lane_width - 0.4)  # the far kerb
    world.crowd = PedestrianCrowd(town, 1, np.random.default_rng(0), 1000)
    ped = world.crowd.peds[0]
    ped.position, ped.heading, ped.state, ped.target = kerb.copy(), 0.0, "crossing", far.copy()
    ped.speed_mps = 1.1
    ped.yields = False  # it walks on whatever comes: the car must stop
    return {"ped": ped}


def _check_pedestrian(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    if "collision_pedestrian" in log.infractions:
        return False, "hit the pedestrian"
    stopped = min(log.speed) < 0.1
    moved = log.progress[-1] - log.progress[int(np.argmin(log.speed))]
    return (stopped and moved > 10.0 and not log.infractions,
            f"stopped for the pedestrian: {stopped}; drove {moved:.0f} m after (want > 10)")


def _yellow_close(world: World, ap: Approach) -> dict[str, Any]:
    world.ego.speed = 8.0
    return {"ap": ap, "switched_at": None}


def _yellow_hook(world: World, ctx: dict[str, Any]) -> None:
    light = world.next_light()
    if ctx["switched_at"] is None and light is not None and light.distance_m < 7.0:
        world.lights.force(ctx["ap"].index, LightState.YELLOW, until_s=1e9)
        ctx["switched_at"] = world.time_s
        ctx["red_at"] = world.time_s + 3.0
    if ctx.get("red_at") is not None and world.time_s >= ctx["red_at"]:
        world.lights.force(ctx["ap"].index, LightState.RED, until_s=1e9)


def _check_yellow(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    if ctx["switched_at"] is None:
        return False, "never came within 7 m of the stop line"
    if "red_light" in log.infractions:
        return False, "ran the red light"
    went = log.edges[-1] != ctx["ap"].edge
    return went, f"went on through the yellow (too close to stop comfortably): {went}"


def _overtaken(world: World, ap: Approach) -> dict[str, Any]:
    """A faster car in the next lane (the one a right turn needs), a little behind us: it comes alongside as
    the route announces the turn, out of the forward camera's view."""
    town = world.town
    ego_s = town.lane((ap.edge[0], ap.edge[1], 0)).local_coordinates(world.ego.position)[0]
    npc = world.spawn_npc((ap.edge[0], ap.edge[1], 1), max(ego_s - OVERTAKER_BEHIND_M, 2.0), SemanticClass.CAR,
                          color=(0.85, 0.85, 0.8), target_speed=9.0)
    assert npc is not None
    npc.speed = 8.0
    world.ego.speed = 7.0
    return {"lead": npc}


def _check_turn(log: Log, ctx: dict[str, Any]) -> tuple[bool, str]:
    goal = ctx["goal"]
    reached = goal in log.edges
    return reached and not log.infractions, f"took the turn onto {goal}: {reached}; infractions: {log.infractions or 'none'}"


SCENARIOS: dict[str, Scenario] = {
    "car_ahead": Scenario("a stopped car ahead in our lane: stop 1-8 m behind it", 20.0,
                          _lead_car((0.75, 0.08, 0.08)), _check_stop_behind),
    "car_drives_away": Scenario("the car ahead drives away after 10 s: resume", 28.0, _lead_car((0.08, 0.2, 0.6)),
                                _check_resume, hook=_drive_away_hook),
    "red_light": Scenario("a red light: stop 0-2 m before the stop line", 20.0, _red, _check_stop_line),
    "red_then_green": Scenario("the red light turns green at 12 s: drive on", 24.0, _red_then_green,
                               _check_red_then_green, hook=_green_after_hook),
    "night": Scenario("night driving: follow the route through the junction", 16.0, _quiet,
                      _check_clean_progress(80.0), weather="night"),
    "car_other_lane": Scenario("cars passing in the other lanes: do not stop", 14.0, _passing_cars, _check_no_stop),
    "unusual_colour_car": Scenario("a stopped car of an unusual colour (pink): stop behind it", 20.0,
                                   _lead_car((1.0, 0.25, 0.85)), _check_stop_behind),
    "pedestrian_crossing": Scenario("a pedestrian crosses our road ahead: stop, then go on", 28.0, _pedestrian,
                                    _check_pedestrian),
    "yellow_too_close": Scenario("the light turns yellow 7 m before the stop line at 8 m/s: go on", 12.0,
                                 _yellow_close, _check_yellow, hook=_yellow_hook),
    "turn_left": Scenario("a left turn at the junction, by command", 20.0, _quiet, _check_turn, turn=Command.LEFT),
    "overtaken_before_turn": Scenario("a right turn from the inner lane while a faster car overtakes in the outer one: "
                                      "no collision", 24.0, _overtaken, _check_turn, turn=Command.RIGHT),
}


def run_scenario(name: str, driver: Any, config: DriveConfig, out: Path | None = None, video: bool = False) -> ScenarioResult:
    """Run one scenario with a driver; returns whether it passed and why."""
    scenario = SCENARIOS[name]
    config = replace(config, weather=scenario.weather, max_time_s=scenario.duration_s,
                     terminate_on_route_deviation=False)
    world, ap = build_world(config, scenario)
    ctx = scenario.setup(world, ap)
    ctx["goal"] = world.route[-1]
    env = DriveEnv(config, render_mode="rgb_array")
    writer = None
    if video and out is not None:
        from towndrive.envs.evaluation import video_writer

        out.mkdir(parents=True, exist_ok=True)
        writer = video_writer(out / f"{name}.mp4", env.metadata["render_fps"])
    log = Log()
    try:
        obs, info = env.reset(seed=0, options={"world": world})
        driver.reset(env)
        lead = ctx.get("lead")
        done = False
        while not done:
            if scenario.hook is not None:
                scenario.hook(world, ctx)
            obs, _, terminated, truncated, info = env.step(driver.act(obs))
            done = terminated or truncated
            log.t.append(info["time_s"])
            log.speed.append(info["ego"]["speed_mps"])
            light = info["next_light"]
            log.light_distance.append(light["distance_m"] if light and light["approach"] == ap.index else math.nan)
            log.progress.append(info["route"]["progress_m"])
            log.lead_gap.append(_bumper_gap(world, lead) if isinstance(lead, TownVehicle) else math.nan)
            log.infractions += [inf["kind"] for inf in info["infractions"]]
            log.edges.append(tuple(info["lane_index"][:2]) if info["lane_index"] else ("", ""))
            if writer is not None:
                from towndrive.envs.evaluation import video_frame

                writer.append_data(video_frame(env, driver, info, name))
    finally:
        if writer is not None:
            writer.close()
        env.close()
    passed, detail = scenario.check(log, ctx)
    return ScenarioResult(name, bool(passed), detail, log.t[-1] if log.t else 0.0)


@dataclass(frozen=True)
class ScenarioItem:
    """One scenario as a work item (``envs.parallel``): the scenario's name, the config and where its video goes."""

    index: int
    name: str
    config: DriveConfig
    out: Path | None = None
    video: bool = False

    def run(self, worker: Worker) -> ScenarioResult:
        return run_scenario(self.name, worker.driver, self.config, self.out, self.video)

    def failed(self, error: str) -> ScenarioResult:
        return ScenarioResult(self.name, False, f"could not be run: {error}", 0.0)


def run_scenarios(names: list[str], driver: Any, config: DriveConfig, out: Path | None = None, video: bool = False,
                  workers: int = 1, ray: str | None = None) -> list[ScenarioResult]:
    """Run scenarios in order: here with ``driver``, or on ``workers`` processes or Ray (``driver`` a ``DriverSpec``)."""
    from towndrive.envs.parallel import DriverSpec, run_items

    items = [ScenarioItem(k, name, config, out, video) for k, name in enumerate(names)]
    if workers > 1 or ray is not None:
        if not isinstance(driver, DriverSpec):
            raise ValueError("run_scenarios(workers > 1) builds a driver in each worker: give a DriverSpec.")
        return run_items(items, driver, workers, f"scenarios ({workers} workers)", ray=ray)
    return [run_scenario(name, driver.build() if isinstance(driver, DriverSpec) else driver, config, out, video)
            for name in names]  # a spec: a fresh driver per scenario, as the command line has always done


def _bumper_gap(world: World, npc: TownVehicle) -> float:
    ego = world.ego
    return float(math.hypot(*(npc.position - ego.position)) - (npc.LENGTH + ego.LENGTH) / 2)


def format_results(driver: str, results: list[ScenarioResult]) -> str:
    lines = [f"Scenarios with driver {driver}:", "", "| scenario | result | detail |", "|---|---|---|"]
    for r in results:
        lines.append(f"| {r.name} | {'PASS' if r.passed else 'FAIL'} | {r.detail} |")
    lines.append("")
    lines.append(f"{sum(r.passed for r in results)} passed, {sum(not r.passed for r in results)} failed")
    return "\n".join(lines)
