"""Each frame's decision to the outside: a microcontroller on a serial port, and JSON lines for programs.

Seed 000 drove a TIVA board from the Jetson: an RGB LED took the lane's colour (green: lane clear, red: an
object in our lane) and a buzzer sounded on a warning. This module keeps that link, with a line protocol
small enough to parse on any microcontroller.

Serial line protocol (ASCII, one line per frame, at most 48 bytes, NMEA 0183 style)::

    $TDA,<seq>,<lane>,<warn>,<brake>,<steer>,<speed>,<light>*<CK>\\r\\n
    $TDA,417,R,FOB,62,-8,31,-*68     (frame 417: object in lane, FCW, braking 62%, 31 km/h)

    seq    frame counter 0-65535, wrapping; a gap tells the board that frames were dropped
    lane   G lane clear, R object in our lane (seed 000's red lane), N no lane found
    warn   warning letters in this order, or - for none: L lane departure, F forward collision,
           O object in lane, B braking hard (brake >= 50%)
    brake  brake command in % of full braking, 0-100 (0 while accelerating or coasting)
    steer  steering command in % of full lock, -100..100 (the action's sign: positive steers right)
    speed  own speed in km/h, integer
    light  the traffic light the controller obeys: R, Y, G, or - for none
    CK     XOR of every byte between '$' and '*', two uppercase hex digits

The board should: set the LED from ``lane``; sound the buzzer while ``warn`` contains F or O; ignore a line
whose checksum fails; and fall back to a safe state (LED blinking) when no valid line came for 0.5 s, because
silence means the Jetson stopped. At 115200 baud a 30 FPS stream uses about 12% of the link. The writer never
blocks the driving loop: a write that would wait is dropped and counted (``dropped``).

JSON lines: one object per frame with the same decision in full (``AlertFrame.as_dict``), including the
override reason and the per-stage timings, to a file or standard output (``-``).
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any, Protocol

WARNING_LETTERS = {"lane_departure": "L", "forward_collision": "F", "object_in_lane": "O", "hard_brake": "B"}
LANE_LETTERS = {"green": "G", "red": "R", "none": "N"}
LIGHT_LETTERS = {"red": "R", "yellow": "Y", "green": "G"}
HARD_BRAKE = 0.5
MAX_LINE = 48


@dataclass(frozen=True)
class AlertFrame:
    """One frame's decision, as the alert outputs see it."""

    frame: int
    time_s: float
    lane: str  # "green" (clear), "red" (object in our lane), "none" (no lane found)
    warnings: tuple[str, ...] = ()  # agent.decision.adas names: lane_departure, forward_collision, object_in_lane
    brake: float = 0.0  # 0..1
    steer: float = 0.0  # -1..1
    speed_mps: float = 0.0
    light: str | None = None  # red, yellow, green
    reason: str = ""
    timings_ms: dict[str, float] = field(default_factory=dict)
    details: tuple[str, ...] = ()  # the warnings as the agent words them ("COLLISION WARNING: car #4, TTC 1.2 s")

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["warnings"] = list(self.warnings)
        d["details"] = list(self.details)
        d["timings_ms"] = {k: round(v, 3) for k, v in self.timings_ms.items()}
        return d


def checksum(body: str) -> str:
    value = 0
    for byte in body.encode("ascii"):
        value ^= byte
    return f"{value:02X}"


def encode_line(a: AlertFrame) -> bytes:
    """The serial line of one frame (see module docstring), ending in CR LF."""
    names = set(a.warnings) | ({"hard_brake"} if a.brake >= HARD_BRAKE else set())
    warn = "".join(letter for name, letter in WARNING_LETTERS.items() if name in names) or "-"
    steer = int(round(100 * max(-1.0, min(1.0, a.steer))))
    brake = int(round(100 * max(0.0, min(1.0, a.brake))))
    speed = int(round(3.6 * a.speed_mps)) if math.isfinite(a.speed_mps) else 0
    body = (f"TDA,{a.frame % 65536},{LANE_LETTERS.get(a.lane, 'N')},{warn},{brake},{steer},{max(0, min(speed, 999))},"
            f"{LIGHT_LETTERS.get(a.light or '', '-')}")
    line = f"${body}*{checksum(body)}\r\n".encode("ascii")
    assert len(line) <= MAX_LINE
    return line


# Each numeric field's range in the protocol (module docstring); a line outside it is refused, checksum or not.
FIELD_RANGES = {"seq": (0, 65535), "brake_pct": (0, 100), "steer_pct": (-100, 100), "speed_kmh": (0, 999)}


def parse_line(line: bytes | str) -> dict[str, Any]:
    """The board's side, in Python (the reference for a C port): a line back into its fields.

    Raises ``ValueError`` (one sentence quoting the line) for anything but a line of the protocol: not text, not
    ASCII, too long, a wrong checksum, a field out of its spec (lane not G/R/N, warning letters not from LFOB in
    that order, a number with other characters than digits or out of ``FIELD_RANGES``, light not R/Y/G/-).
    """
    if not isinstance(line, bytes | bytearray | str):
        raise ValueError(f"an alert line is bytes or str, not {type(line).__name__}.")
    raw = bytes(line) if isinstance(line, bytes | bytearray) else line.encode("utf-8", "replace")
    if not raw.isascii():
        raise ValueError(f"not a TDA line (not ASCII): {raw[:MAX_LINE + 8]!r}")
    text = raw.decode("ascii").strip()
    if len(text) > MAX_LINE - 2:
        raise ValueError(f"not a TDA line (longer than {MAX_LINE} bytes): {text[:MAX_LINE + 8]!r}")
    if not text.startswith("$") or "*" not in text:
        raise ValueError(f"not a TDA line: {text!r}")
    body, ck = text[1:].rsplit("*", 1)
    if checksum(body) != ck.upper():
        raise ValueError(f"checksum mismatch in {text!r}")
    parts = body.split(",")
    if len(parts) != 8 or parts[0] != "TDA":
        raise ValueError(f"expected 8 fields starting with TDA: {text!r}")
    _, seq, lane, warn, brake, steer, speed, light = parts
    if lane not in LANE_LETTERS.values():
        raise ValueError(f"lane must be one of {'/'.join(LANE_LETTERS.values())}, got {lane!r} in {text!r}")
    order = "".join(WARNING_LETTERS.values())
    if warn != "-" and (not warn or "".join(c for c in order if c in warn) != warn):
        raise ValueError(f"warn must be '-' or letters of {order} in that order, got {warn!r} in {text!r}")
    if light != "-" and light not in LIGHT_LETTERS.values():
        raise ValueError(f"light must be one of {'/'.join(LIGHT_LETTERS.values())}/-, got {light!r} in {text!r}")
    out: dict[str, Any] = {"lane": lane, "warn": "" if warn == "-" else warn, "light": "" if light == "-" else light}
    for name, value in zip(FIELD_RANGES, (seq, brake, steer, speed), strict=True):
        lo, hi = FIELD_RANGES[name]
        digits = value[1:] if value.startswith("-") else value
        if not (digits.isdigit() and digits.isascii()) or not lo <= int(value) <= hi:
            raise ValueError(f"{name} must be an integer from {lo} to {hi}, got {value!r} in {text!r}")
        out[name] = int(value)
    return {k: out[k] for k in ("seq", "lane", "warn", "brake_pct", "steer_pct", "speed_kmh", "light")}


class AlertSink(Protocol):
    def send(self, alert: AlertFrame) -> None: ...

    def close(self) -> None: ...


class SerialAlerts:
    """The line protocol to a serial port (pyserial); ``port`` may be a device, a pty or a pyserial URL."""

    def __init__(self, port: str, baud: int = 115200) -> None:
        try:
            import serial  # pyserial
        except ImportError as exc:
            raise RuntimeError("Serial alerts need pyserial: pip install pyserial.") from exc
        self._timeout_error = serial.SerialTimeoutException
        try:
            self.port = serial.serial_for_url(port, baudrate=baud, timeout=0, write_timeout=0)
        except (serial.SerialException, ValueError) as exc:
            raise RuntimeError(f"Cannot open serial port {port} ({exc}); check the cable and the device name, and that "
                               "this user may use it (the dialout group).") from exc
        self.sent = 0
        self.dropped = 0

    def send(self, alert: AlertFrame) -> None:
        try:
            self.port.write(encode_line(alert))
            self.sent += 1
        except self._timeout_error:  # the board is not reading: drop, never stall the driving loop
            self.dropped += 1

    def close(self) -> None:
        self.port.close()


class JsonlAlerts:
    """One JSON object per frame, to a file or to standard output (``-``), flushed per line."""

    def __init__(self, target: str | Path) -> None:
        self._own = str(target) != "-"
        if self._own:
            Path(target).parent.mkdir(parents=True, exist_ok=True)
        self.stream: IO[str] = open(target, "w") if self._own else sys.stdout  # noqa: SIM115 - closed in close()

    def send(self, alert: AlertFrame) -> None:
        self.stream.write(json.dumps(alert.as_dict()) + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self._own:
            self.stream.close()


class Alerts:
    """Every configured output at once (``open_alerts``); nothing configured is a no-op."""

    def __init__(self, sinks: list[AlertSink]) -> None:
        self.sinks = sinks

    def send(self, alert: AlertFrame) -> None:
        for sink in self.sinks:
            sink.send(alert)

    def close(self) -> None:
        for sink in self.sinks:
            sink.close()


def open_alerts(serial_port: str | None = None, baud: int = 115200, jsonl: str | Path | None = None) -> Alerts:
    sinks: list[AlertSink] = []
    if serial_port:
        sinks.append(SerialAlerts(serial_port, baud))
    if jsonl:
        sinks.append(JsonlAlerts(jsonl))
    return Alerts(sinks)


def alert_from_view(view: Any, frame: int, timings_ms: dict[str, float] | None = None) -> AlertFrame:
    """The alert of one frame of the ``agent`` driver (its ``view``: lanes, decision, warnings).

    The lane is red when the controller has an object in our path (seed 000's rule), none when no lane line
    was found, green otherwise. The agent words its warnings for people (``agent.decision.adas.LABELS``: "OBJECT IN
    LANE: car #4 at 12.0 m"); the alert carries their kinds and keeps the words in ``details``.
    """
    from towndrive.agent.decision.adas import LABELS

    kinds = {label: kind for kind, label in LABELS.items()}
    decision = view.decision
    lanes = view.lanes
    if decision.in_path:
        lane = "red"
    elif lanes is None or not getattr(lanes, "detected", False):
        lane = "none"
    else:
        lane = "green"
    texts = tuple(str(w) for w in view.warnings)
    names = tuple(dict.fromkeys(kinds.get(w.split(":")[0].strip(), w) for w in texts))
    return AlertFrame(frame=frame, time_s=float(view.time_s), lane=lane, warnings=names,
                      brake=max(0.0, -float(decision.throttle_brake)), steer=float(decision.steer),
                      speed_mps=float(view.speed_mps), light=decision.light, reason=str(decision.reason),
                      timings_ms=dict(timings_ms or {}), details=texts)
