"""Make docs/contact_sheet.png: the camera at noon, dusk, overcast and night, a red light at a
junction, a car ahead, a pedestrian on a crosswalk, and the top-down map; and docs/town_styles.png:
each town style in each weather, from an approach that shows what the style's junctions look like
(classic: a mast-arm signal; downtown: a signal on a post; suburb: a stop sign), with the map around
the car. Run from the repo root: ``python docs/make_contact_sheet.py`` (``--only styles`` or
``--only classic`` for one of the two).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.objects import LightState, SemanticClass
from towndrive.sim.topdown import TopDownMap
from towndrive.sim.town import Control, SignKind, Town

TILE = (320, 160)


def place(env: DriveEnv, lane_index: tuple[str, str, int], s: float) -> None:
    world = env.world
    assert world is not None
    lane = world.town.lane(lane_index)
    world.ego.position = lane.position(s, 0.0)
    world.ego.heading = lane.heading_at(s)


def shot(env: DriveEnv, weather: str, setup) -> np.ndarray:
    env.reset(seed=0, options={"weather": weather, "traffic_density": 0.0})
    setup(env)
    obs, *_ = env.step(np.array([0.0, -1.0], dtype=np.float32))
    return obs["image"]


def classic_sheet() -> None:
    env = DriveEnv(DriveConfig())
    env.reset(seed=0)
    town = env.world.town
    ap = town.approaches[6]
    lane_index = (ap.edge[0], ap.edge[1], 0)
    lane = town.lane(lane_index)

    def before_red(e: DriveEnv) -> None:
        place(e, lane_index, lane.length - 28.0)
        e.world.lights.force(ap.index, LightState.RED, until_s=99.0)

    def car_ahead(e: DriveEnv) -> None:
        place(e, lane_index, 10.0)
        e.world.spawn_npc(lane_index, 24.0, SemanticClass.CAR, color=(0.75, 0.08, 0.08), target_speed=0.0)
        e.world.spawn_npc((ap.edge[0], ap.edge[1], 1), 21.0, SemanticClass.TRUCK, color=(0.9, 0.9, 0.9),
                          target_speed=0.0)

    def pedestrian(e: DriveEnv) -> None:
        cw = town.crosswalks[ap.index]
        place(e, lane_index, lane.length - 11.0)
        e.world.lights.force(ap.index, LightState.RED, until_s=99.0)
        from towndrive.sim.pedestrians import PedestrianCrowd

        e.world.crowd = PedestrianCrowd(town, 2, np.random.default_rng(1), 1000)
        for k, ped in enumerate(e.world.crowd.peds):
            t = 0.35 + 0.3 * k
            ped.position = cw.start + (cw.end - cw.start) * t
            ped.heading = float(np.arctan2(*(cw.end - cw.start)[::-1]))
            ped.state, ped.crosswalk = "waiting", cw.index

    tiles = [
        ("noon", shot(env, "noon", before_red)),
        ("dusk", shot(env, "dusk", car_ahead)),
        ("overcast", shot(env, "overcast", car_ahead)),
        ("night", shot(env, "night", before_red)),
        ("red light at a junction", shot(env, "noon", before_red)),
        ("car and van ahead", shot(env, "noon", car_ahead)),
        ("pedestrians on a crosswalk", shot(env, "noon", pedestrian)),
    ]
    env.reset(seed=0)
    for _ in range(40):
        env.step(np.array([0.0, 0.0], dtype=np.float32))
    top = TopDownMap(town, pixels_per_m=1.2).render(env.world)
    top = cv2.resize(top, (TILE[1] * top.shape[1] // top.shape[0], TILE[1]), interpolation=cv2.INTER_AREA)
    canvas_top = np.zeros((TILE[1], TILE[0], 3), np.uint8)
    x0 = (TILE[0] - top.shape[1]) // 2
    canvas_top[:, max(0, x0):max(0, x0) + min(TILE[0], top.shape[1])] = top[:, :TILE[0]]
    tiles.append(("top-down map", canvas_top))
    rows = []
    for r in range(0, len(tiles), 2):
        row = []
        for label, img in tiles[r:r + 2]:
            img = cv2.resize(img, TILE, interpolation=cv2.INTER_LINEAR).copy()
            cv2.putText(img, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(img, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
            row.append(img)
        rows.append(np.concatenate(row, axis=1))
    sheet = np.concatenate(rows, axis=0)
    out = Path(__file__).with_name("contact_sheet.png")
    cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    print(f"wrote {out}")
    env.close()


STYLE_WEATHERS = ("dusk", "night", "noon", "overcast")
STYLE_TOWN_SEED = 5000  # the first town of every style's test split (sim/splits.py)


def style_view(town: Town, style: str) -> tuple[tuple[str, str, int], float, int, str]:
    """Where to stand in a style's town: (lane, s, approach to hold red or -1, caption). Classic: before a mast-arm
    signal; downtown: before a post-mounted signal; suburb: before a stop sign with its sign in view."""
    if style == "suburb":
        entry = next(e for e in town.entries if e.control in (Control.STOP, Control.ALL_WAY_STOP)
                     and any(g.kind == SignKind.STOP and g.edge == e.edge for g in town.signs))
        lane = (entry.edge[0], entry.edge[1], town.lane_count(entry.edge) - 1)
        return lane, town.lane(lane).length - 9.0, -1, "stop sign"
    mount = "mast_arm" if style == "classic" else "far_pole"
    ap = next(a for a in town.approaches if a.mount == mount and town.lane_count(a.edge) == 2)
    lane = (ap.edge[0], ap.edge[1], 0)
    return lane, town.lane(lane).length - (24.0 if mount == "mast_arm" else 14.0), ap.index, \
        mount.replace("_", " ") + " signal"


def style_sheet() -> None:
    """Rows: classic, downtown, suburb; columns: the four weathers and the map around the car."""
    rows = []
    for style in ("classic", "downtown", "suburb"):
        env = DriveEnv(DriveConfig(town_seed=STYLE_TOWN_SEED))
        options = {"town_style": style, "traffic_density": 0.0}
        env.reset(seed=0, options=options)
        assert env.world is not None
        lane_index, s, approach, caption = style_view(env.world.town, style)

        def setup(e: DriveEnv, lane_index=lane_index, s=s, approach=approach) -> None:
            place(e, lane_index, s)
            if approach >= 0:
                e.world.lights.force(approach, LightState.RED, until_s=99.0)

        tiles: list[tuple[str, np.ndarray]] = []
        for weather in STYLE_WEATHERS:
            tiles.append((f"{style}, {weather}: {caption}", styled_shot(env, weather, options, setup)))
        top = TopDownMap(env.world.town, pixels_per_m=3.0).render_around(env.world, size_px=TILE[0], radius_m=40.0)
        tiles.append((f"{style}: map", top[TILE[0] // 4: TILE[0] // 4 + TILE[1]]))
        rows.append(np.concatenate([label(img, text) for text, img in tiles], axis=1))
        env.close()
    out = Path(__file__).with_name("town_styles.png")
    cv2.imwrite(str(out), cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR))
    print(f"wrote {out}")


def styled_shot(env: DriveEnv, weather: str, options: dict, setup: Callable[[DriveEnv], None]) -> np.ndarray:
    env.reset(seed=0, options={**options, "weather": weather})
    setup(env)
    obs, *_ = env.step(np.array([0.0, -1.0], dtype=np.float32))
    return obs["image"]


def label(img: np.ndarray, text: str) -> np.ndarray:
    """A tile with its caption in white on a dark band (an outline drawn thicker would run wider than the text)."""
    img = cv2.resize(img, TILE, interpolation=cv2.INTER_LINEAR).copy()
    (w, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.42, 1)
    img[2:h + 10, 2:w + 12] = (img[2:h + 10, 2:w + 12] * 0.35).astype(np.uint8)
    cv2.putText(img, text, (6, h + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--only", choices=("classic", "styles"), default=None)
    args = ap.parse_args()
    if args.only != "styles":
        classic_sheet()
    if args.only != "classic":
        style_sheet()
    return 0


if __name__ == "__main__":
    sys.exit(main())
