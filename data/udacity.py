"""Convert between towndrive episodes and the Udacity self-driving-car simulator's recording layout.

A Udacity recording is a folder holding ``driving_log.csv`` and ``IMG/``. Each CSV row is
``center, left, right, steering, throttle, brake, speed``: three image paths (often absolute paths from the
machine that recorded them; they are resolved by file name inside ``IMG/``), steering in [-1, 1] (positive =
right, full lock 25 degrees), throttle and brake in [0, 1], speed in mph. The original simulator writes no
header; a ``center,left,right,steering,throttle,brake,speed`` header is accepted too.

Conventions of the conversion:

* steering is copied unchanged both ways (both use -1..1, positive = right). The full-lock angle differs
  (Udacity 25 degrees, towndrive ``EgoVehicle.MAX_STEER_RAD`` = 0.6 rad = 34.4 degrees), so the same number is
  a different wheel angle; imported episodes carry ``steer_full_lock_deg = 25`` to say so.
* ``throttle_brake = throttle - brake``; on export ``throttle = max(tb, 0)``, ``brake = max(-tb, 0)``.
* speed: mph * 0.44704 = m/s.
* import keeps the center camera only (an episode has one ``frames`` array); when the log names distinct side
  images the episode's attrs say ``side_cameras_available = True``. Export writes the center image only and
  repeats its path in the left and right columns.
* floats are written with the shortest text that reads back to the same float32, so actions round-trip exactly.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path, PureWindowsPath
from typing import Any

import cv2
import h5py
import numpy as np

from towndrive.data.episodes import EpisodeError, EpisodeWriter, episode_sources, next_episode_path, read_episode
from towndrive.sim.checks import check_number

MPH_TO_MPS = 0.44704
LOG_NAME = "driving_log.csv"
HEADER = ("center", "left", "right", "steering", "throttle", "brake", "speed")
STEER_FULL_LOCK_DEG = 25.0
RUN_GAP_S = 1.0  # a gap longer than this between Udacity image time stamps starts a new episode
_STAMP = re.compile(r"(\d{4})_(\d{2})_(\d{2})_(\d{2})_(\d{2})_(\d{2})_(\d{3})")
_EXPORTED = re.compile(r"^center_(.+)_(\d{5,})\.jpg$")
# Valid range of each number column (speed: the simulator's top speed is about 30 mph; 250 leaves room).
RANGES = {"steering": (-1.0, 1.0), "throttle": (0.0, 1.0), "brake": (0.0, 1.0), "speed": (0.0, 250.0)}


class UdacityError(ValueError):
    """A Udacity recording that cannot be read; the message names the file (and line) and what to do."""


@dataclass
class LogRow:
    line: int
    center: Path
    left: Path | None
    right: Path | None
    steering: float
    throttle: float
    brake: float
    speed_mph: float


def read_log(src_folder: Path) -> list[LogRow]:
    """Parse ``driving_log.csv`` and resolve every image it names (raises ``UdacityError`` naming file and line)."""
    src = Path(src_folder)
    log = src / LOG_NAME
    if not log.is_file():
        raise UdacityError(f"{log}: no such file; a Udacity recording folder holds {LOG_NAME} and IMG/.")
    rows: list[LogRow] = []
    with open(log, newline="", encoding="utf-8-sig") as f:
        reader = csv.reader(f)
        for fields in _decoded(reader, log):
            line = reader.line_num
            fields = [x.strip() for x in fields]
            if not any(fields):
                continue
            if line == 1 and [x.lower() for x in fields[:7]] == list(HEADER):
                continue
            if len(fields) < 7:
                raise UdacityError(f"{log} line {line}: expected 7 columns ({','.join(HEADER)}), found {len(fields)}.")
            numbers = []
            for name, text in zip(HEADER[3:], fields[3:7], strict=True):
                try:
                    value = float(text)
                except ValueError:
                    raise UdacityError(f"{log} line {line}: {name} is {text!r}, not a number.") from None
                try:
                    check_number(f"{log} line {line}: {name}", value, *RANGES[name])
                except ValueError as exc:
                    raise UdacityError(str(exc).replace(f"got {value!r}", f"got {text!r}")) from None
                numbers.append(value)
            center = _resolve(src, fields[0], log, line, "center")
            left = _resolve(src, fields[1], log, line, "left", required=False)
            right = _resolve(src, fields[2], log, line, "right", required=False)
            rows.append(LogRow(line, center, left, right, *numbers))
    if not rows:
        raise UdacityError(f"{log}: no data rows; record some driving first.")
    return rows


def _decoded(reader: Any, log: Path) -> Any:
    """The CSV rows; text that is not UTF-8 is one error naming the file and the line."""
    while True:
        try:
            yield next(reader)
        except StopIteration:
            return
        except UnicodeDecodeError as exc:
            raise UdacityError(f"{log} near line {reader.line_num + 1}: not UTF-8 text (byte {exc.object[exc.start]:#x}); "
                               "save the log as UTF-8.") from None


def _resolve(src: Path, text: str, log: Path, line: int, column: str, required: bool = True) -> Path | None:
    """An image named in the log: ``IMG/<file name>`` first (paths from other machines), then the path as written."""
    if not text:
        if required:
            raise UdacityError(f"{log} line {line}: the {column} image path is empty.")
        return None
    candidates = [src / "IMG" / PureWindowsPath(text).name]  # PureWindowsPath splits on both / and \
    literal = Path(text)
    candidates.append(literal if literal.is_absolute() else src / literal)
    for path in candidates:
        if path.is_file():
            return path
    if required:
        raise UdacityError(f"{log} line {line}: {column} image {text!r} not found (looked for {candidates[0]}).")
    return None


def split_runs(rows: list[LogRow]) -> list[list[LogRow]]:
    """Contiguous runs: a new run starts where exported episode names change or step numbers jump, or where
    Udacity time stamps go back or pause for more than ``RUN_GAP_S``; names without either pattern form one run."""
    runs: list[list[LogRow]] = []
    prev: tuple[str, Any] | None = None
    for row in rows:
        key = _run_key(row.center.name)
        if not runs or not _continues(prev, key):
            runs.append([])
        runs[-1].append(row)
        prev = key
    return runs


def _run_key(name: str) -> tuple[str, Any]:
    match = _EXPORTED.match(name)
    if match:
        return ("exported", (match.group(1), int(match.group(2))))
    match = _STAMP.search(name)
    if match:
        try:
            stamp = datetime(*(int(g) for g in match.groups()[:6]), int(match.group(7)) * 1000)
            return ("stamp", stamp.timestamp())
        except ValueError:
            pass
    return ("other", None)


def _continues(prev: tuple[str, Any] | None, key: tuple[str, Any]) -> bool:
    if prev is None or prev[0] != key[0]:
        return prev is None
    if key[0] == "exported":
        return prev[1][0] == key[1][0] and key[1][1] == prev[1][1] + 1
    if key[0] == "stamp":
        return 0.0 <= key[1] - prev[1] <= RUN_GAP_S
    return True


def import_udacity(src_folder: Path, dst_folder: Path, dt_s: float = 0.05, progress: bool = False,
                   stop: Callable[[], None] | None = None) -> list[Path]:
    """Write one episode per contiguous run of a Udacity recording into ``dst_folder``; returns the new paths.

    All or nothing: the whole log is checked before anything is written, and if a frame fails to load, a write
    fails (a full disk) or ``stop()`` raises (a stop signal), the episodes written by this call are removed again.
    """
    from tqdm import tqdm

    src = Path(src_folder).resolve()
    rows = read_log(src)
    runs = split_runs(rows)
    log = src / LOG_NAME
    written: list[Path] = []
    writer: EpisodeWriter | None = None
    bar = tqdm(total=len(rows), desc="import", unit="frame", disable=not progress)
    try:
        for run in runs:
            first = _load_rgb(run[0].center, log, run[0].line)
            height, width = first.shape[:2]
            side = any((r.left is not None and r.left != r.center) or (r.right is not None and r.right != r.center)
                       for r in run)
            attrs = {"driver": "udacity_import", "source": str(src), "seed": -1, "town_seed": -1, "weather": "unknown",
                     "camera": {"width": width, "height": height}, "dt_s": float(dt_s),
                     "side_cameras_available": bool(side), "steer_full_lock_deg": STEER_FULL_LOCK_DEG,
                     "source_lines": [run[0].line, run[-1].line]}
            writer = EpisodeWriter(next_episode_path(dst_folder), attrs)
            for t, row in enumerate(run):
                image = first if t == 0 else _load_rgb(row.center, log, row.line)
                if image.shape != first.shape:
                    raise UdacityError(f"{log} line {row.line}: image {row.center.name} is {image.shape[1]}x"
                                       f"{image.shape[0]}, the run started at {width}x{height}; resize the images.")
                observation = {"image": image, "speed": np.array([row.speed_mph * MPH_TO_MPS]), "command": 0}
                action = np.array([row.steering, row.throttle - row.brake], np.float32)
                writer.append(observation, action, _unknown_truth(t * dt_s))
                bar.update(1)
                if stop is not None:
                    stop()
            path = writer.close({"steps_done": writer.steps})
            writer = None
            written.append(path)
            _unknown_light(path)
    except BaseException:
        if writer is not None:
            writer.discard()
        for path in written:
            path.unlink(missing_ok=True)
        raise
    finally:
        bar.close()
    return written


def _load_rgb(path: Path, log: Path, line: int) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise UdacityError(f"{log} line {line}: cannot decode image {path}; the file is corrupt or not an image.")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def _unknown_truth(time_s: float) -> dict[str, Any]:
    """An info dict for ``truth_from_info`` with nothing known but the time."""
    nan = float("nan")
    return {"ego": {"x": nan, "y": nan, "heading": nan}, "lane_offset_m": nan, "route": {"progress_m": nan},
            "next_light": None, "time_s": time_s}


def _unknown_light(path: Path) -> None:
    """``truth_from_info`` writes -1 ("no light ahead") when there is no light; for imports it is unknown: NaN."""
    with h5py.File(path, "r+") as f:
        if "truth/next_light_state" in f:
            f["truth/next_light_state"][...] = np.nan


def export_udacity(src: Path, dst_folder: Path, progress: bool = False, stop: Callable[[], None] | None = None) -> int:
    """Write episodes (a folder of them, or one ``.h5`` file) as a Udacity recording; returns the frames written.

    Images go to ``dst/IMG/center_<episode>_<step>.jpg`` and rows to ``dst/driving_log.csv`` (no header, absolute
    paths like the original simulator; the left and right columns repeat the center path). ``dst`` must not
    already hold a ``driving_log.csv``. A corrupt episode stops the export with an ``EpisodeError`` naming it;
    then, or when a write fails or ``stop()`` raises, every image this call wrote is removed again.
    """
    from tqdm import tqdm

    paths = episode_sources(src)
    dst = Path(dst_folder).resolve()
    log = dst / LOG_NAME
    if log.exists():
        raise UdacityError(f"{log}: already exists; export into an empty folder (or delete it first).")
    episodes = [read_episode(p, load_frames=False) for p in paths]  # check every file before writing anything
    (dst / "IMG").mkdir(parents=True, exist_ok=True)
    tmp = log.with_name(log.name + ".partial")
    count = 0
    images: list[Path] = []  # written by this call, removed again if it fails
    bar = tqdm(total=sum(ep.steps for ep in episodes), desc="export", unit="frame", disable=not progress)
    try:
        with open(tmp, "w", newline="") as f:
            out = csv.writer(f)
            for ep in episodes:
                try:
                    h5 = h5py.File(ep.path, "r")
                except OSError as exc:
                    raise EpisodeError(f"{ep.path}: cannot read this episode ({exc}).") from exc
                with h5:
                    frames = h5["frames"]
                    for t in range(ep.steps):
                        image = dst / "IMG" / f"center_{ep.path.stem}_{t:05d}.jpg"
                        try:
                            frame = frames[t]
                        except (OSError, ValueError) as exc:
                            raise EpisodeError(f"{ep.path}: cannot read frame {t} ({exc}); the file is corrupt.") from exc
                        ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(frame, cv2.COLOR_RGB2BGR),
                                                [cv2.IMWRITE_JPEG_QUALITY, 95])
                        if not ok:
                            raise UdacityError(f"{ep.path}: frame {t} cannot be encoded as JPEG.")
                        images.append(image)
                        image.write_bytes(jpeg.tobytes())  # OSError (a full disk) names the errno, unlike imwrite
                        steer, tb = (float(v) for v in ep.actions[t])
                        out.writerow([image, image, image, _num(steer), _num(max(tb, 0.0)), _num(max(-tb, 0.0)),
                                      _num(float(ep.speed[t]) / MPH_TO_MPS)])
                        count += 1
                        bar.update(1)
                        if stop is not None:
                            stop()
        tmp.replace(log)
    except BaseException:
        tmp.unlink(missing_ok=True)
        for image in images:
            image.unlink(missing_ok=True)
        raise
    finally:
        bar.close()
    return count


def _num(value: float) -> str:
    """Shortest decimal text that reads back (through float32) to the same float32."""
    return np.format_float_positional(np.float32(value), trim="-") if value != 0 else "0"
