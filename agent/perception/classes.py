"""The detector's classes: the names, their order (the network's output channels) and the lights' states.

Why a module of its own: the detector, the refiner, the overlays and the auto-labeller all speak of class ``k``;
the car's code must not import the auto-labeller (which needs the renderer and the town) to learn what ``k`` is.

The road signs came later and are appended, so the first six channels mean what they always did: a detector
trained before them (six class channels) still decodes (its classes are the first six, ``classes_of_model``), and
its weights carry over to the ten-class head (``train.py detector train --init``). A speed limit's value is part
of its class (one class per posted value the towns use), so the detector reads it in one pass; ``SIGN_CLASS_OF``
is the one place that says which sign is which class.
"""

from __future__ import annotations

CLASSES: tuple[str, ...] = ("car", "truck", "pedestrian", "light_red", "light_yellow", "light_green",
                            "stop_sign", "yield_sign", "speed_limit_30", "speed_limit_50")
LIGHT_CLASSES: tuple[str, ...] = CLASSES[3:6]
SIGN_CLASSES: tuple[str, ...] = CLASSES[6:10]
STATE_OF_CLASS = {"light_red": "red", "light_yellow": "yellow", "light_green": "green"}

# (sign kind, posted value in km/h; 0 for signs without one) -> class name. The kind is the name of the
# simulator's ``SignKind`` in lower case (this module may not import the simulator's town code).
SIGN_CLASS_OF: dict[tuple[str, int], str] = {
    ("stop", 0): "stop_sign",
    ("yield", 0): "yield_sign",
    ("speed_limit", 30): "speed_limit_30",
    ("speed_limit", 50): "speed_limit_50",
}
# A speed-limit class -> its value in km/h (what a driver reading the detections wants).
LIMIT_OF_CLASS: dict[str, int] = {name: value for (kind, value), name in SIGN_CLASS_OF.items() if kind == "speed_limit"}


def sign_class(kind: str, value_kmh: int = 0) -> str | None:
    """The class name of a sign of ``kind`` ("stop", "yield", "speed_limit") and value; None when the detector
    has no class for it (a limit of a value no town posted when it was trained)."""
    kind = kind.lower()
    return SIGN_CLASS_OF.get((kind, int(value_kmh) if kind == "speed_limit" else 0))


def classes_of_model(channels: int) -> tuple[str, ...]:
    """The classes of a detector whose head has ``channels`` class channels: the first ``channels`` of
    ``CLASSES`` (the signs were appended, so an older model is a prefix). Raises for any other count."""
    if not 1 <= channels <= len(CLASSES):
        raise ValueError(f"A detector with {channels} class channels does not match the classes {CLASSES} "
                         "(or a prefix of them); retrain it.")
    return CLASSES[:channels]
