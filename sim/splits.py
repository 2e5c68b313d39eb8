"""Named town-seed ranges for training, validation and test, the same for every town style.

Why: numbers from different papers or runs only compare when they come from the same towns, and a
model tuned on its test towns reports a number it has not earned. A (style, town seed) pair is one
town, so each style has the same three ranges of seeds: train on ``train``, tune on ``validation``,
report ``test`` once. The towns the project's own development used (seeds 100-104 and 300-304) lie
in ``train``.
"""

from __future__ import annotations

TOWN_SPLITS: dict[str, range] = {
    "train": range(0, 4000),
    "validation": range(4000, 5000),
    "test": range(5000, 6000),
}


def split_towns(split: str, count: int, first: int | None = None) -> range:
    """``count`` town seeds of a split from ``first`` (default the split's first); one sentence if the split is
    unknown or the towns do not all lie in it. A later start gives towns of the same split not driven before, e.g.
    a second test run after the first was reported."""
    seeds = TOWN_SPLITS.get(split)
    if seeds is None:
        raise ValueError(f"unknown split {split!r}; the splits are {', '.join(TOWN_SPLITS)}.")
    start = seeds.start if first is None else first
    if count < 1 or start not in seeds or start + count - 1 not in seeds:
        raise ValueError(f"the {split} split holds towns {seeds.start}-{seeds.stop - 1}; asked for {count} from {start}.")
    return range(start, start + count)


def split_of(town_seed: int) -> str | None:
    """The split a town seed belongs to (None above the last)."""
    return next((name for name, seeds in TOWN_SPLITS.items() if town_seed in seeds), None)
