"""Top-down map view drawn with OpenCV, for people and videos (not for drivers).

The static town is drawn once into a cached image (parked cars and signs included: they never move);
each frame copies it and draws the lights, vehicles, pedestrians, the ego and its route on top. Signs
are symbols a person knows at a glance: a red octagon for stop, a red-rimmed triangle point down for
yield, a red-rimmed disc for a limit (with its number where the map is large enough to read it).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np

from towndrive.sim.geometry import rect_corners
from towndrive.sim.town import Sign, SignKind, Town

if TYPE_CHECKING:
    from towndrive.sim.world import World

LIGHT_BGR = {0: (60, 200, 60), 1: (40, 210, 240), 2: (50, 50, 230)}  # green, yellow, red (BGR)
MARKING_RGB = {"dashed_white": (235, 235, 235), "solid_white": (235, 235, 235),
               "solid_yellow": (240, 200, 40), "stop_line": (250, 250, 250), "crosswalk": (250, 250, 250),
               "yield_line": (250, 250, 250)}
SIGN_RED, SIGN_WHITE, SIGN_DARK = (205, 25, 30), (250, 250, 250), (20, 20, 20)
SIGN_RADIUS_M = 1.6  # a sign's symbol on the map (bigger than the plate, so that it shows)


class TopDownMap:
    """Renders a town (and optionally a world's moving parts) as an RGB image."""

    def __init__(self, town: Town, pixels_per_m: float = 2.0) -> None:
        self.town = town
        self.ppm = pixels_per_m
        xmin, ymin, xmax, ymax = town.extent
        self.origin = np.array([xmin, ymin])
        self.size = (int((xmax - xmin) * self.ppm), int((ymax - ymin) * self.ppm))
        self._static = self._draw_static()

    def to_px(self, pts: np.ndarray) -> np.ndarray:
        """Map-frame metres to integer pixel coordinates (OpenCV drawing is in int32)."""
        return np.round((np.asarray(pts) - self.origin) * self.ppm).astype(np.int32)

    def _poly(self, img: np.ndarray, poly: np.ndarray, rgb: tuple[int, int, int]) -> None:
        cv2.fillConvexPoly(img, self.to_px(poly), rgb, lineType=cv2.LINE_AA)

    def _draw_static(self) -> np.ndarray:
        t = self.town
        img = np.zeros((self.size[1], self.size[0], 3), np.uint8)
        img[:] = (96, 140, 72)
        for p in t.road_polygons:
            self._poly(img, p, (62, 62, 66))
        for p in t.slab_polygons:
            self._poly(img, p, (178, 176, 170))
        for p in t.grass_polygons:
            self._poly(img, p, (104, 158, 80))
        for kind, quads in t.markings.items():
            for q in quads:
                self._poly(img, q, MARKING_RGB[kind])
        for b in t.buildings:
            c = tuple(int(255 * v * 0.85) for v in b.color)
            self._poly(img, b.footprint, c)
            cv2.polylines(img, [self.to_px(b.footprint)], True, (70, 70, 70), 1)
        for car in t.parked_cars:
            corners = rect_corners(car.position, car.heading, car.length_m, car.width_m)
            self._poly(img, corners, tuple(int(255 * c) for c in car.color))
            cv2.polylines(img, [self.to_px(corners)], True, (40, 40, 40), 1, lineType=cv2.LINE_AA)
        for tr in t.trees:
            cv2.circle(img, tuple(self.to_px(tr.position)), max(2, int(tr.canopy_radius_m * self.ppm)),
                       (40, 110, 40), -1, lineType=cv2.LINE_AA)
        for sign in t.signs:
            self._sign(img, sign)
        return img

    def _sign(self, img: np.ndarray, sign: Sign) -> None:
        """One sign's symbol at its post, upright on the image whatever way the sign faces."""
        r = max(3.0, SIGN_RADIUS_M * self.ppm)
        c = (np.asarray(sign.position) - self.origin) * self.ppm
        if sign.kind == SignKind.STOP:
            ring = [c + r * np.array([math.cos(a), math.sin(a)]) for a in math.pi / 8 + np.arange(8) * math.pi / 4]
            cv2.fillConvexPoly(img, np.round(np.array(ring)).astype(np.int32), SIGN_RED, lineType=cv2.LINE_AA)
            if r >= 5:
                cv2.polylines(img, [np.round(np.array(ring)).astype(np.int32)], True, SIGN_WHITE, 1, cv2.LINE_AA)
        elif sign.kind == SignKind.YIELD:
            tri = np.round([c + r * np.array([math.cos(a), math.sin(a)])
                            for a in (math.pi / 2, math.pi / 2 + 2 * math.pi / 3, math.pi / 2 + 4 * math.pi / 3)])
            cv2.fillConvexPoly(img, tri.astype(np.int32), SIGN_WHITE, lineType=cv2.LINE_AA)
            cv2.polylines(img, [tri.astype(np.int32)], True, SIGN_RED, max(1, int(r / 4)), cv2.LINE_AA)
        else:
            centre, radius = (int(round(c[0])), int(round(c[1]))), int(round(r))
            cv2.circle(img, centre, radius, SIGN_WHITE, -1, cv2.LINE_AA)
            cv2.circle(img, centre, radius, SIGN_RED, max(1, radius // 4), cv2.LINE_AA)
            if radius >= 6:  # a number smaller than this is a smudge
                text = str(sign.value_kmh)
                scale = 0.07 * radius
                (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_PLAIN, scale, 1)
                cv2.putText(img, text, (centre[0] - tw // 2, centre[1] + th // 2), cv2.FONT_HERSHEY_PLAIN, scale,
                            SIGN_DARK, 1, cv2.LINE_AA)

    def render(self, world: World | None = None) -> np.ndarray:
        """The whole town with the world's current state, as an RGB uint8 image."""
        img = self._static.copy()
        if world is None:
            return img
        r = max(2, int(0.6 * self.ppm))
        for ap in self.town.approaches:
            state = int(world.lights.state(ap.index))
            rgb = LIGHT_BGR[state][::-1]
            cv2.circle(img, tuple(self.to_px(ap.light_head)), r, rgb, -1, lineType=cv2.LINE_AA)
        route = world.ego_route_polyline()
        if route is not None and len(route) > 1:
            cv2.polylines(img, [self.to_px(route)], False, (80, 170, 255), max(1, int(self.ppm)), lineType=cv2.LINE_AA)
        for v in world.npcs:
            corners = rect_corners(v.position, v.heading, v.LENGTH, v.WIDTH)
            self._poly(img, corners, tuple(int(255 * c) for c in v.color))
        for p in world.pedestrians:
            cv2.circle(img, tuple(self.to_px(p.position)), max(2, int(0.4 * self.ppm)), (230, 60, 200), -1)
        ego = world.ego
        self._poly(img, rect_corners(ego.position, ego.heading, ego.LENGTH, ego.WIDTH), (255, 255, 255))
        tip = self.to_px(ego.position + 0.5 * ego.LENGTH * np.array([np.cos(ego.heading), np.sin(ego.heading)]))
        cv2.circle(img, tuple(tip), max(1, int(0.4 * self.ppm)), (255, 40, 40), -1)
        return img

    def render_around(self, world: World, size_px: int = 320, radius_m: float = 40.0) -> np.ndarray:
        """A square crop centred on the ego (north-up), for side-by-side videos."""
        full = self.render(world)
        centre = self.to_px(world.ego.position)
        half = int(radius_m * self.ppm)
        pad = cv2.copyMakeBorder(full, half, half, half, half, cv2.BORDER_CONSTANT, value=(96, 140, 72))
        crop = pad[centre[1]:centre[1] + 2 * half, centre[0]:centre[0] + 2 * half]
        return cv2.resize(crop, (size_px, size_px), interpolation=cv2.INTER_AREA)
