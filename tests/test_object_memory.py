"""The memory of lost objects (``agent.perception.object_memory``): a vehicle lost in our path keeps its own speed,
so its remembered gap closes with our own travel less its, whatever our speed does after it was lost."""

from __future__ import annotations

from towndrive.agent.perception.box_geometry import BoxGeometry
from towndrive.agent.perception.object_memory import MemoryRules, ObjectMemory
from towndrive.agent.perception.objects import PerceivedObject
from towndrive.sim.spec import CAMERA

DT = 0.05


def test_a_standing_car_lost_while_we_brake_stays_where_it_stands() -> None:
    memory = ObjectMemory(BoxGeometry(CAMERA), MemoryRules())
    speed, truth = 2.0, 6.0  # we close on a standing car 6 m ahead at 2 m/s
    car = PerceivedObject(7, "car", truth, -0.9, 0.9, closing_speed_mps=speed)
    memory.note(memory.recall([car], speed, 0.0, DT), [7], set())  # seen
    ghost = None
    for _ in range(30):  # lost; we brake to a stop in 0.5 s and stand
        speed = max(0.0, speed - 4.0 * DT)
        truth -= speed * DT
        out = memory.recall([], speed, 0.0, DT)
        memory.note(out, [o.track_id for o in out], set())
        ghost = next(o for o in out if o.track_id == 7)
    assert ghost is not None and ghost.unconfirmed
    assert abs(ghost.distance_m - truth) < 0.15  # not 3 m nearer, as closing on at 2 m/s would put it
    assert abs(ghost.closing_speed_mps) < 1e-9  # both standing


def test_a_lead_car_lost_at_our_speed_keeps_its_gap() -> None:
    memory = ObjectMemory(BoxGeometry(CAMERA), MemoryRules())
    car = PerceivedObject(3, "car", 10.0, -0.9, 0.9, closing_speed_mps=0.0)  # ahead, at our 8 m/s
    memory.note(memory.recall([car], 8.0, 0.0, DT), [3], set())
    for _ in range(20):
        out = memory.recall([], 8.0, 0.0, DT)
        memory.note(out, [o.track_id for o in out], set())
    assert abs(out[0].distance_m - 10.0) < 1e-6
