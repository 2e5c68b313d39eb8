"""``Drive-v0``: drive the ego car through the town from first-person camera frames.

Observation (a Dict):
  ``image``    camera RGB, uint8 H x W x 3 (default 320 x 160)
  ``speed``    ego speed in m/s, float32 shape (1,)
  ``command``  route command, int: 0 follow lane, 1 left, 2 right, 3 straight
  and, when asked for in ``DriveConfig``: ``depth`` (metres, float32 H x W), ``segmentation``
  (int32 H x W x 2: semantic class, object id), ``stereo`` (uint8 2 x H x W x 3: left, right) and
  ``side`` (uint8 2 x H x W x 3: cameras ``side_camera_offset_m`` to the left and right of the centre one,
  as NVIDIA's data-collection car had, for behavioural-cloning data with a steering correction).
  ``DriveEnv.blind_spot_frame(side)`` renders, on request, the camera under the left or right door mirror
  looking back along the car's side (a blind-spot camera): drivers that change lanes look before they do.
  ``DriveEnv.corner_frame(side)`` renders the cross-traffic camera at the left or right front corner, looking
  along the cross street (``sim.spec.CornerRig``): drivers at give-way and stop lines look before they go.

Action: Box([-1, -1], [1, 1]) = ``[steer, throttle_brake]``.

Reward per step (documented, simple, dense):
  + route progress in metres / 10
  - 0.02 x |lane offset in metres|
  - 10 on a terminal infraction (collision with a vehicle, pedestrian or static object; leaving the road)
  - 5 for running a red light, - 2 for entering the wrong way or deviating from the route.

Termination: a terminal infraction, route deviation (if ``terminate_on_route_deviation``), or the end
of the route. Truncation: ``max_time_s`` or ``max_distance_m``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from towndrive.envs.options import MAX_TOWN_SEED, check_reset_options, episode_seconds, goal_edge, start_lane
from towndrive.envs.options import town_seed as check_town_seed
from towndrive.sim.checks import check_number
from towndrive.sim.objects import LIGHT_ID_BASE, LightState, SemanticClass
from towndrive.sim.render import LIGHTING_PRESETS, CameraConfig, CameraFrame, SceneRenderer
from towndrive.sim.render_kernels import object_boxes
from towndrive.sim.spec import CORNERS, EPISODE_S, MIRRORS
from towndrive.sim.topdown import TopDownMap
from towndrive.sim.town import Command, Control, SignKind, TownConfig
from towndrive.sim.world import TERMINAL_INFRACTIONS, World, WorldConfig, cached_town

INFRACTION_REWARD = {"red_light": -5.0, "stop_sign": -4.0, "failed_to_yield": -5.0, "speeding": -1.0, "wrong_way": -2.0,
                     "route_deviation": -2.0}
# Lower-case names by value, one table per enum (IntEnum members of different enums compare equal as ints).
_CLASS_NAMES = {int(c): c.name.lower() for c in SemanticClass}
_LIGHT_NAMES = {int(s): s.name.lower() for s in LightState}
_COMMAND_NAMES = {int(c): c.name.lower() for c in Command}
_CONTROL_NAMES = {int(c): c.name.lower() for c in Control}
_SIGN_NAMES = {int(k): k.name.lower() for k in SignKind}
SIGNS_NEAR_M = 60.0  # info["signs"]: the signs this near that face the car


# The blind-spot cameras: under each door mirror (1.0 m ahead of the car's centre, 1.0 m out, 1.0 m up), turned
# 115 degrees from straight ahead with a 120-degree view: they see from 55 degrees off the car's axis (beside the
# front wheel) round to 175 degrees (the next lane behind), where a forward camera is blind.
BLIND_SPOT_CAMERA = MIRRORS.camera  # the rig lives in sim.spec
BLIND_SPOT_MOUNT_M = (MIRRORS.ahead_m, MIRRORS.out_m)  # (ahead of the car's centre, out to the side)
BLIND_SPOT_YAW_DEG = MIRRORS.yaw_deg


def side_camera_pose(pose: tuple[float, float, float], side: str, ahead_m: float, out_m: float,
                     yaw_deg: float) -> tuple[float, float, float]:
    """The (x, y, heading) of a camera ``ahead_m`` ahead of the centre of a car at ``pose`` and ``out_m`` out to
    ``side`` ("left" or "right"), turned ``yaw_deg`` towards that side (right is +90 degrees, as
    ``SceneRenderer.camera_position`` has it)."""
    if side not in ("left", "right"):
        raise ValueError(f"Unknown side {side!r}; use 'left' or 'right'.")
    x, y, h = pose
    sign = 1.0 if side == "right" else -1.0
    return (x + ahead_m * math.cos(h) - sign * out_m * math.sin(h),
            y + ahead_m * math.sin(h) + sign * out_m * math.cos(h), h + sign * math.radians(yaw_deg))


def blind_spot_pose(pose: tuple[float, float, float], side: str) -> tuple[float, float, float]:
    """The (x, y, heading) of the blind-spot camera on ``side`` of a car at ``pose``."""
    return side_camera_pose(pose, side, *BLIND_SPOT_MOUNT_M, BLIND_SPOT_YAW_DEG)


def corner_pose(pose: tuple[float, float, float], side: str) -> tuple[float, float, float]:
    """The (x, y, heading) of the cross-traffic camera at the front corner on ``side`` of a car at ``pose``."""
    return side_camera_pose(pose, side, CORNERS.ahead_m, CORNERS.out_m, CORNERS.yaw_deg)


@dataclass(frozen=True)
class DriveConfig:
    """Everything an episode is made of. Defaults: the default town at noon with traffic."""

    world: WorldConfig = field(default_factory=WorldConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    town_seed: int = 0
    weather: str = "noon"
    render_camera: bool = True  # False: no pictures at all (image is zeros), for fast non-visual use
    render_processes: int = 1  # >1: each frame's TinyRenderer work is shared with helper processes, one per extra
    #                            core (the same frames; see sim.render.SceneRenderer); pays only with free cores
    observe_depth: bool = False
    observe_segmentation: bool = False
    observe_stereo: bool = False
    observe_side_cameras: bool = False
    side_camera_offset_m: float = 0.6
    blind_spot_camera: CameraConfig = field(default_factory=lambda: BLIND_SPOT_CAMERA)
    corner_camera: CameraConfig = field(default_factory=lambda: CORNERS.camera)
    max_time_s: float = EPISODE_S
    max_distance_m: float = 3000.0
    terminate_on_route_deviation: bool = True
    terminate_on_infraction: bool = True  # False: collisions and leaving the road are penalised but the episode
    #                                       goes on (closed-loop evaluation with a safety driver)
    image_only: bool = False  # the observation is the camera image alone (a Box), for CnnPolicy and Gymnasium's
    #                           image wrappers; speed and command are then in info (ego.speed_mps, command)


class DriveEnv(gym.Env):
    """The town as a Gymnasium environment. See the module docstring for spaces and reward."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 20}

    def __init__(self, config: DriveConfig | None = None, render_mode: str | None = None, **overrides: Any) -> None:
        config = config or DriveConfig()
        if overrides:
            config = replace(config, **overrides)
        if config.weather not in LIGHTING_PRESETS:
            raise ValueError(f"Unknown weather {config.weather!r}; choose one of {sorted(LIGHTING_PRESETS)}.")
        episode_seconds(config.max_time_s, "max_time_s")
        check_number("render_processes", config.render_processes, 1, 16, integer=True)
        check_town_seed(config.town_seed, "town_seed")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"Unknown render_mode {render_mode!r}; use 'rgb_array' or 'human'.")
        self.config = config
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / config.world.dt_s))}
        cam = config.camera
        obs: dict[str, spaces.Space] = {
            "image": spaces.Box(0, 255, (cam.height, cam.width, 3), np.uint8),
            "speed": spaces.Box(0.0, 50.0, (1,), np.float32),
            "command": spaces.Discrete(len(Command)),
        }
        if config.observe_depth:
            obs["depth"] = spaces.Box(0.0, cam.far_m, (cam.height, cam.width), np.float32)
        if config.observe_segmentation:
            obs["segmentation"] = spaces.Box(-1, 2**31 - 1, (cam.height, cam.width, 2), np.int32)
        if config.observe_stereo:
            obs["stereo"] = spaces.Box(0, 255, (2, cam.height, cam.width, 3), np.uint8)
        if config.observe_side_cameras:
            obs["side"] = spaces.Box(0, 255, (2, cam.height, cam.width, 3), np.uint8)
        self._dict_space = spaces.Dict(obs)
        self.observation_space: spaces.Space = obs["image"] if config.image_only else self._dict_space
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.world: World | None = None
        self.renderer: SceneRenderer | None = None
        self._renderer_town: int | None = None
        self._topdown: TopDownMap | None = None
        self.weather = config.weather
        self.frame: CameraFrame | None = None
        self._window: Any = None
        self._last_progress = 0.0
        self._episode_over = False
        self._closed = False

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        """Start an episode. ``options`` may set ``town_seed``, ``town_style`` (``sim.town_style``: the
        style's town config replaces the configured one), ``weather``, ``traffic_density`` (multiplies NPCs
        and pedestrians), ``start`` (lane index), ``goal`` (edge) and ``world`` (a ready-made World, used by
        scenarios)."""
        self._require_open()
        if seed is not None:
            check_number("seed", seed, 0, MAX_TOWN_SEED, integer=True)
        options = check_reset_options(options)  # before anything changes: a bad option leaves the env as it was
        super().reset(seed=seed)
        episode_seed = int(self.np_random.integers(2**31 - 1))
        town_seed = options.get("town_seed", self.config.town_seed)
        self.weather = options.get("weather", self.config.weather)
        wcfg = self.config.world
        if "town_style" in options and options["town_style"] != wcfg.town.style:
            wcfg = replace(wcfg, town=TownConfig.of_style(options["town_style"]))
        density = options.get("traffic_density", 1.0)
        if density != 1.0:
            wcfg = replace(wcfg, npc_count=int(round(wcfg.npc_count * density)),
                           pedestrian_count=int(round(wcfg.pedestrian_count * density)))
        if "world" in options:
            self.world = options["world"]
        else:
            town = cached_town(wcfg.town, town_seed)
            kwargs: dict[str, Any] = {}
            if "start" in options:
                kwargs["start"] = start_lane(town, options["start"])
            if "goal" in options:
                kwargs["goal"] = goal_edge(town, options["goal"])
            self.world = World(town, wcfg, episode_seed, **kwargs)
        world = self.world
        assert world is not None
        if self.config.render_camera and (self.renderer is None or self._renderer_town != id(world.town)):
            if self.renderer is not None:
                self.renderer.close()
            self.renderer = SceneRenderer(world.town, seed=world.town.seed, processes=self.config.render_processes)
            self._renderer_town = id(world.town)
            self._topdown = None
        self._last_progress = world.route_progress_m
        self._episode_over = False
        obs = self._observe()
        return obs, self._info([])

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        world = self._require_world()
        if self._episode_over:  # Gymnasium's contract: after terminated or truncated, reset() comes next
            raise RuntimeError("The episode has ended (terminated or truncated); call reset() before step() again.")
        action = np.asarray(action, dtype=np.float32).reshape(-1)
        if action.shape != (2,) or not np.all(np.isfinite(action)):
            raise ValueError(f"Action must be two finite numbers [steer, throttle_brake]; got {action!r}.")
        new = world.step(action)
        progress = world.route_progress_m
        reward = (progress - self._last_progress) / 10.0
        self._last_progress = progress
        offset = world.lane_offset_m()
        if math.isfinite(offset):
            reward -= 0.02 * abs(offset)
        terminated = False
        for inf in new:
            if inf.kind in TERMINAL_INFRACTIONS:
                reward -= 10.0
                terminated = terminated or self.config.terminate_on_infraction
            else:
                reward += INFRACTION_REWARD.get(inf.kind, 0.0)
                if inf.kind == "route_deviation" and self.config.terminate_on_route_deviation:
                    terminated = True
        if world.route_done:
            terminated = True
        truncated = not terminated and (world.time_s >= self.config.max_time_s
                                        or world.distance_m >= self.config.max_distance_m)
        self._episode_over = terminated or truncated
        obs = self._observe()
        info = self._info(new)
        if self.render_mode == "human":
            self.render()
        return obs, float(reward), terminated, truncated, info

    def blind_spot_frame(self, side: str) -> np.ndarray:
        """RGB from the blind-spot camera on ``side`` ("left" or "right") now, for a driver about to change
        lanes (rendered on request: most frames need no look). The next step's own frame is the same as without it."""
        return self._side_frame(blind_spot_pose(self._pose(), side), self.config.blind_spot_camera, "blind-spot")

    def corner_frame(self, side: str) -> np.ndarray:
        """RGB from the cross-traffic camera at the front corner on ``side`` ("left" or "right") now, for a driver
        at a give-way or stop line (rendered on request, as ``blind_spot_frame``)."""
        return self._side_frame(corner_pose(self._pose(), side), self.config.corner_camera, "cross-traffic")

    def _side_frame(self, at: tuple[float, float, float], cam: CameraConfig, name: str) -> np.ndarray:
        world = self._require_world()
        if self.renderer is None:
            raise RuntimeError(f"The {name} camera needs the renderer: DriveConfig(render_camera=True).")
        x, y, heading = at
        self.renderer.sync(world.object_snapshots(), world.lights.states, view=(x, y, heading, cam.hfov_deg, cam.far_m))
        return self.renderer.render((x, y, heading), cam, self.weather).rgb

    def render(self) -> np.ndarray | None:
        """Camera view beside a top-down map around the ego (``rgb_array``), or shown in a window (``human``)."""
        self._require_open()
        if self.render_mode is None:
            return None
        image = self.composite()
        if self.render_mode == "rgb_array":
            return image
        self._show(image)
        return None

    def close(self) -> None:
        self._closed = True
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
        if self._window is not None:
            import pygame

            pygame.display.quit()
            self._window = None

    # ------------------------------------------------------------------ pictures
    def composite(self) -> np.ndarray:
        """The camera frame scaled to 320 px wide next to a matching top-down crop."""
        import cv2

        cam = self.frame.rgb if self.frame is not None else np.zeros((160, 320, 3), np.uint8)
        h = int(round(cam.shape[0] * 320 / cam.shape[1]))
        cam = cv2.resize(cam, (320, h), interpolation=cv2.INTER_LINEAR)
        return np.concatenate([cam, self.map_view(h)], axis=1)

    def map_view(self, size_px: int) -> np.ndarray:
        """The top-down map, 35 m around the car, ``size_px`` square (the ground truth beside the camera)."""
        world = self._require_world()
        if self._topdown is None or self._topdown.town is not world.town:  # a new town, camera or not
            self._topdown = TopDownMap(world.town, pixels_per_m=3.0)
        return self._topdown.render_around(world, size_px=size_px, radius_m=35.0)

    def _show(self, image: np.ndarray) -> None:
        import pygame

        if self._window is None:
            pygame.display.init()  # the window only: no audio device (headless machines have none)
            self._window = pygame.display.set_mode((image.shape[1] * 2, image.shape[0] * 2))
            pygame.display.set_caption("Drive-v0")
        surf = pygame.surfarray.make_surface(np.ascontiguousarray(image.transpose(1, 0, 2)))
        self._window.blit(pygame.transform.scale(surf, self._window.get_size()), (0, 0))
        pygame.event.pump()
        pygame.display.flip()

    # ------------------------------------------------------------------ internals
    def _require_open(self) -> None:
        if self._closed:
            raise RuntimeError("This DriveEnv is closed; make a new one (a closed env has no renderer to draw with).")

    def _require_world(self) -> World:
        self._require_open()
        if self.world is None:
            raise RuntimeError("Call reset() before step() or render().")
        return self.world

    def _pose(self) -> tuple[float, float, float]:
        ego = self._require_world().ego
        return float(ego.position[0]), float(ego.position[1]), float(ego.heading)

    def observe(self) -> Any:
        """The observation of the world as it is now: after it was changed between steps (a safety driver's
        take-over carries the car back onto its lane), the driver must see where the car is, not the last step's
        frame."""
        return self._observe()

    def _observe(self) -> Any:
        world = self._require_world()
        cfg = self.config
        cam = cfg.camera
        obs: dict[str, Any] = {
            "speed": np.array([world.ego.speed], dtype=np.float32),
            "command": int(world.command()),
        }
        if cfg.render_camera and self.renderer is not None:
            x, y, heading = self._pose()
            self.renderer.sync(world.object_snapshots(), world.lights.states, view=(x, y, heading, cam.hfov_deg, cam.far_m))
            if cfg.observe_stereo:
                left, right = self.renderer.render_stereo(self._pose(), cam, self.weather)
                obs["stereo"] = np.stack([left.rgb, right.rgb])
            if cfg.observe_side_cameras:
                obs["side"] = np.stack([self.renderer.render(self._pose(), cam, self.weather, lateral_m=d).rgb
                                        for d in (-cfg.side_camera_offset_m, cfg.side_camera_offset_m)])
            self.frame = self.renderer.render(self._pose(), cam, self.weather)
            obs["image"] = self.frame.rgb
            if cfg.observe_depth:
                obs["depth"] = self.frame.depth_m.astype(np.float32)
            if cfg.observe_segmentation:
                obs["segmentation"] = self.frame.segmentation.astype(np.int32)
        else:
            self.frame = None
            obs["image"] = np.zeros((cam.height, cam.width, 3), np.uint8)
            if cfg.observe_depth:
                obs["depth"] = np.full((cam.height, cam.width), cam.far_m, np.float32)
            if cfg.observe_segmentation:
                obs["segmentation"] = np.zeros((cam.height, cam.width, 2), np.int32)
            if cfg.observe_stereo:
                obs["stereo"] = np.zeros((2, cam.height, cam.width, 3), np.uint8)
            if cfg.observe_side_cameras:
                obs["side"] = np.zeros((2, cam.height, cam.width, 3), np.uint8)
        picked = {k: obs[k] for k in self._dict_space.spaces}
        return picked["image"] if self.config.image_only else picked

    def _visible_objects(self) -> list[dict[str, Any]]:
        """Every moving object and traffic light with pixels in the frame: class, id, position, 2D box."""
        world = self._require_world()
        if self.frame is None:
            return []
        boxes = self.frame.object_boxes
        uniq, x0, y0, x1, y1, counts = boxes if boxes is not None else object_boxes(self.frame.segmentation[..., 1])
        if len(uniq) == 0:
            return []
        snaps = {s.object_id: s for s in world.object_snapshots()}
        ex, ey = float(world.ego.position[0]), float(world.ego.position[1])
        out = []
        # Python ints from the arrays in one go each (the values int() of each element would give)
        for oid, bx0, by0, bx1, by1, n in zip(uniq.tolist(), x0.tolist(), y0.tolist(), x1.tolist(), y1.tolist(),
                                              counts.tolist(), strict=True):
            if oid >= LIGHT_ID_BASE:
                ap = world.town.approaches[oid - LIGHT_ID_BASE]
                x, y, heading = float(ap.light_head[0]), float(ap.light_head[1]), ap.travel_heading + math.pi
                cls, extra = SemanticClass.TRAFFIC_LIGHT, {"state": _LIGHT_NAMES[world.lights.state(ap.index)],
                                                          "approach": ap.index}
            elif oid in snaps:
                s = snaps[oid]
                x, y, heading, cls, extra = s.x, s.y, s.heading, s.kind, {}
            else:
                continue
            out.append({"id": oid, "class": _CLASS_NAMES[cls], "x": x, "y": y, "heading": float(heading),
                        "distance_m": float(math.hypot(x - ex, y - ey)), "bbox": [bx0, by0, bx1 + 1, by1 + 1],
                        "pixels": n, **extra})
        return out

    def _info(self, new_infractions: list) -> dict[str, Any]:
        world = self._require_world()
        ego = world.ego
        nl = world.next_light()
        nc = world.next_control()
        lane = world.ego_lane
        return {
            "time_s": world.time_s,
            "ego": {"x": float(ego.position[0]), "y": float(ego.position[1]), "heading": float(ego.heading),
                    "speed_mps": float(ego.speed)},
            "lane_index": None if lane is None else list(lane[0]),
            "lane_offset_m": world.lane_offset_m(),
            "lane_band_offset_m": world.lane_band_offset_m(),
            "command": _COMMAND_NAMES[world.command()],
            "next_light": None if nl is None else {"approach": nl.approach, "state": _LIGHT_NAMES[nl.state],
                                                   "distance_m": float(nl.distance_m)},
            "next_control": None if nc is None else {"kind": _CONTROL_NAMES[nc.control], "distance_m": float(nc.distance_m),
                                                     "entry": nc.entry, "approach": nc.approach},
            "signs": [{"id": g.index, "kind": _SIGN_NAMES[g.kind], "value_kmh": g.value_kmh or None,
                       "x": float(g.position[0]), "y": float(g.position[1]), "distance_m": d}
                      for g, d in world.signs_near(SIGNS_NEAR_M)],
            "speed_limit_kmh": world.speed_limit_here_kmh(),
            "objects": self._visible_objects(),
            "infractions": [inf.__dict__.copy() for inf in new_infractions],
            "infraction_counts": _count(world.infractions),
            "route": {"progress_m": world.route_progress_m, "total_m": world.route_total_m,
                      "completion": world.route_completion},
            "distance_m": world.distance_m,
            "weather": self.weather,
            "town_seed": world.town.seed,
            "town_style": world.town.config.style,
        }


def _count(infractions: list) -> dict[str, int]:
    out: dict[str, int] = {}
    for inf in infractions:
        out[inf.kind] = out.get(inf.kind, 0) + 1
    return out
