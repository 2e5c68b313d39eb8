"""How objects move as perception reads them: our own turn is not their motion (``ObjectEstimator``), and a
vehicle lost close in is not taken to drive at us (``ObjectMemory``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.classes import CLASSES
from towndrive.agent.perception.object_memory import MemoryRules, ObjectMemory
from towndrive.agent.perception.objects import ObjectEstimator, ObjectRules, PerceivedObject
from towndrive.agent.perception.tracking import Track
from towndrive.sim.spec import CAMERA

DT = 0.05
CAR = CLASSES.index("car")


def box_of_face(geometry: BoxGeometry, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The box of a 1.5 m tall face between two ground points (x right, z ahead, camera frame)."""
    (u0, v0), (u1, v1) = geometry.birdseye.image_of_ground(np.array([left[0], right[0]]), np.array([left[1], right[1]]))
    z = min(left[1], right[1])
    bottom = max(v0, v1)
    return np.array([min(u0, u1), bottom - geometry.f * 1.5 / z, max(u0, u1), bottom])


def in_camera_frame(point: np.ndarray, turned_rad: float) -> np.ndarray:
    """A point fixed on the ground, seen after the camera turned ``turned_rad`` to the right about itself."""
    c, s = math.cos(turned_rad), math.sin(turned_rad)
    return np.array([c * point[0] - s * point[1], s * point[0] + c * point[1]])


@pytest.mark.parametrize("car_mps", [0.0, -3.0])
def test_our_own_turn_is_not_read_as_a_car_s_sideways_motion(car_mps: float) -> None:
    """Turning right at 0.4 rad/s, a car standing across our axis 12 m ahead drifts left across the view at about 5 m/s: read so,
    a car waiting beside a junction seemed to cross our path. With the turn taken out, a standing car reads still
    and one driving left at 3 m/s reads so."""
    geometry = BoxGeometry(CAMERA)
    est = ObjectEstimator(geometry, ObjectRules())
    rate = 0.4
    for k in range(9):  # 0.4 s, the box across our axis all the while
        t = k * DT
        shift = car_mps * t
        left = in_camera_frame(np.array([-1.0 + shift, 12.0]), rate * t)  # its side, 4.5 m, across the axis
        right = in_camera_frame(np.array([3.5 + shift, 12.0]), rate * t)
        box = box_of_face(geometry, left, right)
        objs = est.update([Track(1, box, 10, 10, 0, CAR)], t, None, 0.0, rate * DT if k else 0.0)
    assert objs[0].lateral_speed_mps == pytest.approx(car_mps, abs=0.5)


def test_a_vehicle_lost_close_in_while_we_stand_is_not_taken_to_pass_under_the_car() -> None:
    """A car crossing just ahead fills the bottom of the frame and is lost, its box's last readings closing at
    8 m/s. Kept at that speed, it passed under the car within a third of a second and left our path while it
    stood in front; it is kept where it was (it is never taken to come at us)."""
    memory = ObjectMemory(BoxGeometry(CAMERA), MemoryRules())
    lost = PerceivedObject(4, "car", 2.0, -0.1, 2.0, 8.0, -3.0, (0.0, 60.0, 320.0, 160.0))
    memory.recall([], 0.2, 0.0, DT)
    memory.in_path_seen = {4: lost}
    for _ in range(int(1.5 / DT)):
        ghosts = memory.recall([], 0.0, 0.0, DT)
        memory.in_path_seen = {}
    assert len(ghosts) == 1 and ghosts[0].distance_m == pytest.approx(2.0, abs=0.05)
