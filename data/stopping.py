"""Stopping a long write cleanly: SIGINT, SIGTERM and SIGHUP become a flag the write loop checks.

Why: ``timeout``, ``docker stop``, systemd and cluster schedulers send SIGTERM, a closed terminal sends SIGHUP,
and by default both kill Python on the spot, leaving a half-written ``.partial`` file and saying nothing. Raising
from the handler is no better: Python runs it wherever the main thread is, and inside a garbage-collection or
weakref callback the exception is printed and swallowed. So the handler only records the signal; the loop calls
``check()`` between steps, which raises ``Stopped``, and the caller keeps what finished and drops the rest. A
second signal of any of the three acts as it normally would (the handlers are restored after the first).
"""

from __future__ import annotations

import signal
from types import FrameType, TracebackType
from typing import Any

SIGNALS = tuple(s for s in (getattr(signal, n, None) for n in ("SIGINT", "SIGTERM", "SIGHUP")) if s is not None)


class Stopped(Exception):
    """A stop signal arrived; ``exit_code`` is the shell's 128 + signal number."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        self.name = signal.Signals(signum).name
        self.exit_code = 128 + signum
        super().__init__(f"stopped by {self.name}")


class StopSignals:
    """``with StopSignals() as stop: ... stop.check() ...`` (installs nothing outside the main thread)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        try:
            for s in SIGNALS:
                self._previous[s] = signal.signal(s, self._handle)
        except ValueError:  # not the main thread: signals stay as they are
            self.restore()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.restore()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.signum = signum
        self.restore()

    def restore(self) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous.clear()

    @property
    def requested(self) -> bool:
        return self.signum is not None

    def check(self) -> None:
        """Raise ``Stopped`` if a stop signal has arrived."""
        if self.signum is not None:
            raise Stopped(self.signum)


def describe_os_error(exc: OSError) -> str:
    """An OSError in a few words for a one-sentence report: "the disk is full", else its own text."""
    import errno

    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return "the disk is full (no space left on device)"
    if exc.errno == errno.EFBIG:
        return "the file grew past the size limit"
    text = exc.strerror or str(exc)
    return text.strip().splitlines()[0] if text.strip() else type(exc).__name__
