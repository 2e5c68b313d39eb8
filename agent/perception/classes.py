"""The detector's classes: the names, their order (the network's output channels) and the lights' states.

Why a module of its own: the detector, the refiner, the overlays and the auto-labeller all speak of class ``k``;
the car's code must not import the auto-labeller (which needs the renderer and the town) to learn what ``k`` is.
"""

from __future__ import annotations

CLASSES: tuple[str, ...] = ("car", "truck", "pedestrian", "light_red", "light_yellow", "light_green")
LIGHT_CLASSES: tuple[str, ...] = CLASSES[3:]
STATE_OF_CLASS = {"light_red": "red", "light_yellow": "yellow", "light_green": "green"}
