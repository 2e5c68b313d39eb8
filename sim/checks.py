"""One way to check a number given from outside (a reset option, a command-line flag, a config field).

Why: a bad number should stop at the boundary with one sentence naming the value and the range it must be in,
not travel inward and come out as a hang (a traffic density of 1e9), an OverflowError (inf), a ZeroDivisionError
(a camera 0 pixels wide) or silent truncation (a town seed of 1.5). Every layer uses this helper, so each range
is written once, next to what it protects, and every message reads the same way.
"""

from __future__ import annotations

import math
import numbers
from typing import Any


def check_number(name: str, value: Any, lo: float | None = None, hi: float | None = None, *,
                 integer: bool = False, lo_open: bool = False) -> Any:
    """``value`` as an int (``integer``) or a float if it is a finite real number in [lo, hi] (``lo_open``:
    (lo, hi]); otherwise ``ValueError``: "<name> must be <what> in <range>; got <value>." Bools are refused
    (True is not a number of towns); an integral float such as 3.0 is refused where an integer is asked for,
    since 3.5 would otherwise be truncated."""
    if integer:
        ok = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    else:
        ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    number: Any = None
    if ok:
        try:
            number = int(value) if integer else float(value)
        except (OverflowError, ValueError):
            ok = False
    if ok and not integer and not math.isfinite(number):
        ok = False
    if ok and lo is not None and (number < lo or (lo_open and number == lo)):
        ok = False
    if ok and hi is not None and number > hi:
        ok = False
    if not ok:
        raise ValueError(f"{name} must be {describe(lo, hi, integer, lo_open)}; got {value!r}.")
    return number


def describe(lo: float | None, hi: float | None, integer: bool = False, lo_open: bool = False) -> str:
    """The range in words: "an integer from 0 to 4294967295", "a number > 0 and <= 5", ..."""
    kind = "an integer" if integer else "a finite number"
    if lo is not None and hi is not None:
        return f"{kind} {'>' if lo_open else 'from'} {_fmt(lo)} {'and <=' if lo_open else 'to'} {_fmt(hi)}"
    if lo is not None:
        return f"{kind} {'>' if lo_open else '>='} {_fmt(lo)}"
    if hi is not None:
        return f"{kind} <= {_fmt(hi)}"
    return kind


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() else f"{x:g}"
