"""Make docs/contact_sheet.png: the camera at noon, dusk, overcast and night, a red light at a
junction, a car ahead, a pedestrian on a crosswalk, and the top-down map. Run from the repo root:
``python docs/make_contact_sheet.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from towndrive.envs.drive_env import DriveConfig, DriveEnv
from towndrive.sim.objects import LightState, SemanticClass
from towndrive.sim.topdown import TopDownMap

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


def main() -> int:
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
