"""The detector's classes: the names, their order (the network's output channels) and the lights' states.

Why a module of its own: the detector, the refiner, the overlays and the auto-labeller all speak of class ``k``;
the car's code must not import the auto-labeller (which needs the renderer and the town) to learn what ``k`` is.

The road signs (channels 6-9) were appended after the first six, so a detector trained before them (six class
channels) still decodes: its classes are the first six of ``CLASSES`` (``classes_of_model``).
"""

from __future__ import annotations

CLASSES: tuple[str, ...] = ("car", "truck", "pedestrian", "light_red", "light_yellow", "light_green",
                            "stop_sign", "yield_sign", "speed_limit_30", "speed_limit_50")
LIGHT_CLASSES: tuple[str, ...] = CLASSES[3:6]
SIGN_CLASSES: tuple[str, ...] = CLASSES[6:10]
STATE_OF_CLASS = {"light_red": "red", "light_yellow": "yellow", "light_green": "green"}
LIMIT_OF_CLASS = {"speed_limit_30": 30, "speed_limit_50": 50}  # km/h


def classes_of_model(channels: int) -> tuple[str, ...]:
    """The classes of a detector whose head has ``channels`` class channels: the first ``channels`` of
    ``CLASSES`` (the signs were appended, so an older model is a prefix). Raises for any other count."""
    if not 1 <= channels <= len(CLASSES):
        raise ValueError(f"A detector with {channels} class channels does not match the classes {CLASSES} "
                         "(or a prefix of them); retrain it.")
    return CLASSES[:channels]
