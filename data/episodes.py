"""Recorded episodes: one HDF5 file per episode, written atomically.

Layout of an episode file (``T`` steps; ``frames[t]`` is what the driver saw when it chose ``actions[t]``):

  frames          uint8   (T, H, W, 3)  camera RGB, chunked one frame per chunk, gzip-compressed
  depth           float16 (T, H, W)     metric depth (optional)
  segmentation    int32   (T, H, W, 2)  semantic class, object id (optional)
  stereo_right    uint8   (T, H, W, 3)  right camera of the stereo pair (optional; ``frames`` is the left)
  side_left       uint8   (T, H, W, 3)  side cameras, ``attrs['side_camera_offset_m']`` left and right of
  side_right                            the centre camera (optional)
  actions         float32 (T, 2)        [steer, throttle_brake]
  speed           float32 (T,)          m/s
  command         int8    (T,)          0 follow, 1 left, 2 right, 3 straight
  truth/<name>    float32 (T,)          per-step ground truth (see ``TRUTH_FIELDS``)
  attrs           seed, town_seed, weather, driver, camera (JSON), project_version, dt_s, steps, ...

Every dataset carries its own description as attributes (layout version 2; ``DATASET_ATTRS``): ``unit``,
``dims`` (what each axis is), ``description``, and for codes ``codes`` (JSON: code -> meaning), so a file read
with any HDF5 tool says what it holds without this module. Why attributes on each dataset and not a table in
a document: a file outlives the code that wrote it and travels alone. Version 1 files (no dataset attributes)
still open; ``dataset_attrs`` answers for them from the same table.

A writer fills ``<name>.partial`` next to the final path and renames it when the episode ends, so a
half-written episode never carries an episode's name, and an interrupted recording keeps every
episode that finished. A ``.partial`` that is still there was left by a process that was killed (SIGKILL,
a power cut): ``list_partials`` finds them, ``python -m data summary`` reports them, and recording never
reuses their numbers.

The writer hands HDF5 a Python file object (``_Sink``) rather than a path. Why: when a write fails (a full
disk), HDF5 keeps the file open with unwritten data it retries at every later call and at interpreter exit,
where it crashes the process (exit 139). The sink never reports a failure to HDF5: it keeps the first OSError
and from then on drops every write, so HDF5 stays consistent and closes cleanly; the writer raises the kept
error after the step (or the close) that hit it, and the caller discards the file.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from towndrive.sim.spec import COMMAND_NAMES  # the route command's codes

TRUTH_FIELDS = ("ego_x", "ego_y", "ego_heading", "lane_offset_m", "route_progress_m", "next_light_state",
                "next_light_distance_m", "time_s")
EPISODE_GLOB = "episode_*.h5"
FORMAT_VERSION = 2  # 2: every dataset carries unit, dims, description (and codes); 1: bare datasets
LIGHT_STATE_NAMES = {0: "green", 1: "yellow", 2: "red", -1: "none"}  # truth/next_light_state (NaN: unknown)
_IMAGE_DIMS = "time, row (top to bottom), column (left to right), channel (R, G, B)"
_SERIES_DIMS = "time"

# What each dataset of an episode file holds: written as the dataset's attributes (layout version 2).
DATASET_ATTRS: dict[str, dict[str, Any]] = {
    "frames": {"unit": "8-bit sRGB", "dims": _IMAGE_DIMS,
               "description": "centre camera (the left one of the stereo pair), what the driver saw at each step"},
    "depth": {"unit": "m", "dims": "time, row, column",
              "description": "metric depth along the camera axis of the centre camera"},
    "segmentation": {"unit": "code", "dims": "time, row, column, (semantic class, object id)",
                     "description": "per-pixel semantic class (sim/objects.py SemanticClass) and object id (-1: none)"},
    "stereo_right": {"unit": "8-bit sRGB", "dims": _IMAGE_DIMS,
                     "description": "right camera of the stereo pair, camera.stereo_baseline_m right of frames"},
    "side_left": {"unit": "8-bit sRGB", "dims": _IMAGE_DIMS,
                  "description": "side camera side_camera_offset_m left of the centre camera, same heading"},
    "side_right": {"unit": "8-bit sRGB", "dims": _IMAGE_DIMS,
                   "description": "side camera side_camera_offset_m right of the centre camera, same heading"},
    "actions": {"unit": "1 (fraction of full range)", "dims": "time, (steer, throttle_brake)",
                "description": "the action at each step: steer in [-1, 1] (positive right, 1 = full lock), "
                               "throttle_brake in [-1, 1] (positive throttle, negative brake)"},
    "speed": {"unit": "m/s", "dims": _SERIES_DIMS, "description": "ego speed"},
    "command": {"unit": "code", "dims": _SERIES_DIMS, "codes": COMMAND_NAMES,
                "description": "route command at each step"},
    "truth/ego_x": {"unit": "m", "dims": _SERIES_DIMS, "description": "ego position east, town map frame"},
    "truth/ego_y": {"unit": "m", "dims": _SERIES_DIMS, "description": "ego position north, town map frame"},
    "truth/ego_heading": {"unit": "rad", "dims": _SERIES_DIMS,
                          "description": "ego heading, counter-clockwise from east, town map frame"},
    "truth/lane_offset_m": {"unit": "m", "dims": _SERIES_DIMS,
                            "description": "signed distance of the ego from its lane centre (NaN: off any lane)"},
    "truth/route_progress_m": {"unit": "m", "dims": _SERIES_DIMS, "description": "distance driven along the route"},
    "truth/next_light_state": {"unit": "code", "dims": _SERIES_DIMS, "codes": LIGHT_STATE_NAMES,
                               "description": "state of the next traffic light on the route (NaN: unknown)"},
    "truth/next_light_distance_m": {"unit": "m", "dims": _SERIES_DIMS,
                                    "description": "distance to the next light's stop line (NaN: no light)"},
    "truth/time_s": {"unit": "s", "dims": _SERIES_DIMS, "description": "simulated time since the episode began"},
}


class EpisodeError(ValueError):
    """A file that is not a readable episode; the message names the file and what to do."""


def project_version() -> str:
    try:
        return metadata.version("towndrive")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def truth_from_info(info: dict[str, Any]) -> dict[str, float]:
    """The per-step ground truth an episode keeps, from a ``DriveEnv`` info dict."""
    light = info.get("next_light")
    states = {"green": 0, "yellow": 1, "red": 2}
    return {
        "ego_x": info["ego"]["x"], "ego_y": info["ego"]["y"], "ego_heading": info["ego"]["heading"],
        "lane_offset_m": info["lane_offset_m"], "route_progress_m": info["route"]["progress_m"],
        "next_light_state": float(states[light["state"]]) if light else -1.0,
        "next_light_distance_m": float(light["distance_m"]) if light else float("nan"),
        "time_s": info["time_s"],
    }


class _Sink(io.RawIOBase):
    """A writable file for HDF5 that keeps its first write error and then drops writes (see the module docstring)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._raw = open(path, "w+b", buffering=0)  # noqa: SIM115 (closed by close())
        self.error: OSError | None = None

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        return self._raw.readinto(buffer) or 0

    def write(self, data: Any) -> int:
        if self.error is not None:
            return len(memoryview(data))
        try:
            return self._raw.write(data) or 0
        except OSError as exc:
            self.error = exc
            exc.filename = exc.filename or str(self.path)
            return len(memoryview(data))

    def seek(self, offset: int, whence: int = 0) -> int:
        return self._raw.seek(offset, whence)

    def tell(self) -> int:
        return self._raw.tell()

    def fileno(self) -> int:
        return self._raw.fileno()

    def truncate(self, size: int | None = None) -> int:
        if self.error is not None:
            return self._raw.tell() if size is None else size
        try:
            return self._raw.truncate(size)
        except OSError as exc:
            self.error = exc
            return self._raw.tell() if size is None else size

    def flush(self) -> None:
        if self.error is None and not self._raw.closed:
            try:
                self._raw.flush()
            except OSError as exc:
                self.error = exc

    def close(self) -> None:
        if self.error is None and not self._raw.closed:
            self.flush()
        super().close()  # calls flush() while the raw file is still open
        self._raw.close()


class EpisodeWriter:
    """Streams one episode to ``<path>.partial``; ``close()`` renames it into place, ``discard()`` deletes it.
    A failed write (a full disk) raises the ``OSError`` from ``append`` or ``close``; ``discard()`` then still
    works."""

    def __init__(self, path: Path, metadata_attrs: dict[str, Any]) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(self.path.name + ".partial")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.tmp.exists():  # a leftover of a killed recording: report it, never overwrite it
            raise FileExistsError(f"{self.tmp} is left over from an interrupted recording; "
                                  "see python -m data summary --delete-partial.")
        self._sink = _Sink(self.tmp)
        self._datasets: dict[str, h5py.Dataset] = {}  # kept open: closing one each step hides write errors
        try:
            self._file = h5py.File(self._sink, "w")
            self._file.attrs["format_version"] = FORMAT_VERSION
            self._file.attrs["project_version"] = project_version()
            for key, value in metadata_attrs.items():
                self._file.attrs[key] = json.dumps(value) if isinstance(value, dict | list) else value
        except BaseException:
            self.discard()
            raise
        self.steps = 0

    def _check(self) -> None:
        """Raise the sink's write error, which HDF5 may have swallowed (errors while freeing objects are not raised)."""
        if self._sink.error is not None:
            raise self._sink.error

    def _dataset(self, name: str, sample: np.ndarray, compress: bool) -> h5py.Dataset:
        ds = self._datasets.get(name)
        if ds is not None:
            return ds
        shape = (0, *sample.shape)
        kwargs: dict[str, Any] = {"maxshape": (None, *sample.shape), "chunks": (1, *sample.shape) if compress else True}
        if compress:
            kwargs.update(compression="gzip", compression_opts=1, shuffle=True)
        ds = self._datasets[name] = self._file.create_dataset(name, shape=shape, dtype=sample.dtype, **kwargs)
        for key, value in describe(name).items():
            ds.attrs[key] = json.dumps({str(k): v for k, v in value.items()}) if isinstance(value, dict) else value
        return ds

    def append(self, observation: dict[str, Any], action: np.ndarray, info: dict[str, Any] | None = None,
               truth: dict[str, float] | None = None) -> None:
        """Add one step: the observation the driver saw, the action it took, and the step's ground truth, from
        the env's ``info`` or given as ``truth`` (a value per ``TRUTH_FIELDS`` name, NaN where unknown)."""
        rows: dict[str, tuple[np.ndarray, bool]] = {
            "frames": (np.asarray(observation["image"], np.uint8), True),
            "actions": (np.asarray(action, np.float32).reshape(2), False),
            "speed": (np.asarray(observation["speed"], np.float32).reshape(()), False),
            "command": (np.asarray(observation["command"], np.int8).reshape(()), False),
        }
        if "depth" in observation:
            rows["depth"] = (np.asarray(observation["depth"], np.float16), True)
        if "segmentation" in observation:
            rows["segmentation"] = (np.asarray(observation["segmentation"], np.int32), True)
        if "stereo" in observation:
            rows["stereo_right"] = (np.asarray(observation["stereo"][1], np.uint8), True)
        if "side" in observation:
            rows["side_left"] = (np.asarray(observation["side"][0], np.uint8), True)
            rows["side_right"] = (np.asarray(observation["side"][1], np.uint8), True)
        if truth is None:
            if info is None:
                raise ValueError("append needs the step's info or its truth.")
            truth = truth_from_info(info)
        for key, value in truth.items():
            rows[f"truth/{key}"] = (np.asarray(value, np.float32).reshape(()), False)
        for name, (value, compress) in rows.items():
            ds = self._dataset(name, value, compress)
            ds.resize(self.steps + 1, axis=0)
            ds[self.steps] = value
        self._check()
        self.steps += 1

    def close(self, extra_attrs: dict[str, Any] | None = None) -> Path:
        """Finish the episode: write the summary attributes, flush to disk and rename the file into place."""
        for key, value in (extra_attrs or {}).items():
            self._file.attrs[key] = json.dumps(value) if isinstance(value, dict | list) else value
        self._file.attrs["steps"] = self.steps
        self._datasets.clear()
        self._file.close()
        self._check()
        try:
            os.fsync(self._sink.fileno())
        except OSError as exc:
            self._sink.error = exc
            raise
        self._sink.close()
        os.replace(self.tmp, self.path)
        return self.path

    def discard(self) -> None:
        """Drop a half-written episode (interrupted, or failed); never raises for the file's own state."""
        self._datasets.clear()
        file = getattr(self, "_file", None)
        if self._sink.error is None:
            self._sink.error = OSError("discarded")  # nothing more needs to reach the disk
        if file is not None and file.id.valid:
            file.close()
        if not self._sink.closed:
            self._sink.close()
        self.tmp.unlink(missing_ok=True)


@dataclass
class Episode:
    """An episode read back into memory (frames are loaded lazily only if asked)."""

    path: Path
    attrs: dict[str, Any]
    actions: np.ndarray
    speed: np.ndarray
    command: np.ndarray
    truth: dict[str, np.ndarray]
    frames: np.ndarray | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        return len(self.actions)


def read_episode(path: Path, load_frames: bool = True) -> Episode:
    """Read an episode file; a missing or corrupt file raises ``EpisodeError`` naming it."""
    path = Path(path)
    if not path.exists():
        raise EpisodeError(f"{path}: no such episode file; check the path (episodes are named {EPISODE_GLOB}).")
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: _attr(v) for k, v in f.attrs.items()}
            missing = [k for k in ("frames", "actions", "speed", "command") if k not in f]
            if missing:
                raise EpisodeError(f"{path}: not an episode file (missing {', '.join(missing)}); re-record it.")
            ep = Episode(path, attrs, f["actions"][()], f["speed"][()], f["command"][()],
                         {k: f["truth"][k][()] for k in f.get("truth", {})})
            if load_frames:
                ep.frames = f["frames"][()]
                for name in ("depth", "segmentation", "stereo_right", "side_left", "side_right"):
                    if name in f:
                        ep.extras[name] = f[name][()]
            return ep
    except EpisodeError:
        raise
    except (OSError, KeyError, ValueError) as exc:
        raise EpisodeError(f"{path}: cannot read this episode ({exc}); the file is corrupt or not HDF5, "
                           "re-record or delete it.") from exc


def describe(name: str) -> dict[str, Any]:
    """What dataset ``name`` of an episode holds (unit, dims, description, codes); a name not in the layout
    (a dataset added by a later version) gets an empty description."""
    return dict(DATASET_ATTRS.get(name, {}))


def dataset_attrs(path: Path) -> dict[str, dict[str, Any]]:
    """Each dataset's description in an episode file: its own attributes (version 2 and later), or, for a
    version 1 file, which carries none, the layout's description of the same name."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            names: list[str] = []
            f.visititems(lambda name, obj: names.append(name) if isinstance(obj, h5py.Dataset) else None)
            found = {name: {k: _attr(v) for k, v in f[name].attrs.items()} for name in names}
    except OSError as exc:
        raise EpisodeError(f"{path}: cannot read this episode ({exc}); the file is corrupt or not HDF5, "
                           "re-record or delete it.") from exc
    return {name: attrs or describe(name) for name, attrs in found.items()}


def _attr(value: Any) -> Any:
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str) and value[:1] in "{[":
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    if isinstance(value, np.generic):
        return value.item()
    return value


def episode_sources(src: Path) -> list[Path]:
    """The episodes a converter reads: every finished episode of a folder, or one episode file."""
    src = Path(src)
    if src.is_dir():
        paths = list_episodes(src)
        if not paths:
            raise EpisodeError(f"{src}: no {EPISODE_GLOB} files to export.")
        return paths
    if src.is_file():
        return [src]
    raise EpisodeError(f"{src}: no such episode file or dataset folder.")


def list_episodes(folder: Path) -> list[Path]:
    """Finished episodes in a folder, in name order (``.partial`` files are not episodes)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise EpisodeError(f"{folder}: no such dataset folder; record one with drive.py --record {folder}.")
    return sorted(folder.glob(EPISODE_GLOB))


def list_partials(folder: Path) -> list[Path]:
    """``.partial`` files in a folder: episodes (or exports) whose writer was killed before it could finish or
    clean up. A running recording has one too, so delete them only when nothing is writing into the folder."""
    folder = Path(folder)
    return sorted(folder.glob("*.partial")) if folder.is_dir() else []


def next_episode_path(folder: Path) -> Path:
    """The next ``episode_NNNNN.h5`` name in a folder, after every finished episode and every ``.partial``
    leftover (recording appends to a dataset and never writes over a leftover)."""
    names = [p.name.split(".")[0] for p in (*Path(folder).glob(EPISODE_GLOB), *Path(folder).glob(EPISODE_GLOB + ".partial"))]
    existing = [int(n.split("_")[1]) for n in names if n.split("_")[1].isdigit()]
    return Path(folder) / f"episode_{(max(existing) + 1) if existing else 0:05d}.h5"
