"""MP4 video of camera frames, written and read with PyAV (FFmpeg's libraries, installed from a pip wheel).

Why video: a camera stream compresses far better as H.264 than as frame-by-frame gzip (see ``bench/README.md``:
several times smaller at 320x160), and LeRobot datasets keep their cameras as MP4 files holding several episodes
each. Why these settings: H.264 in yuv420p is what every decoder reads (browsers, torchcodec, PyAV, OpenCV);
``crf`` 18 keeps a frame within a few grey levels of the original; a keyframe every ``gop_frames`` frames bounds
what a reader decodes to reach any one frame (LeRobot's readers seek to a timestamp and decode forward).

Frames get presentation times ``k / fps`` (a constant frame rate), so frame ``k`` of a file sits at ``k / fps``
seconds and an episode that starts at frame ``k0`` of a file starts at ``k0 / fps``.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from towndrive.extras import import_for


@dataclass(frozen=True)
class VideoSettings:
    """How camera frames are encoded."""

    codec: str = "libx264"  # FFmpeg encoder; streams read back as "h264"
    crf: int = 18  # constant rate factor: lower is larger and closer to the original
    gop_frames: int = 10  # a keyframe at least every this many frames
    preset: str = "medium"
    pix_fmt: str = "yuv420p"


def _av() -> Any:
    return import_for("av", "Writing and reading MP4 video")


class VideoError(ValueError):
    """A video that cannot be written or read; the message names the file."""


class Mp4Writer:
    """Appends RGB frames (H, W, 3 uint8) to one MP4 file at a constant frame rate."""

    def __init__(self, path: Path, fps: int, width: int, height: int, settings: VideoSettings = VideoSettings()) -> None:
        if width % 2 or height % 2:
            raise VideoError(f"{path}: frames of {width}x{height} cannot be encoded as {settings.pix_fmt} video; "
                             "width and height must be even.")
        av = _av()
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.frames = 0
        self._container = av.open(str(self.path), mode="w", format="mp4")
        stream = self._container.add_stream(settings.codec, rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, settings.pix_fmt
        stream.time_base = Fraction(1, fps)
        stream.codec_context.gop_size = settings.gop_frames
        stream.options = {"crf": str(settings.crf), "preset": settings.preset}
        self._stream = stream
        self._av = av

    def add(self, rgb: np.ndarray) -> None:
        frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb, np.uint8), format="rgb24")
        frame.pts = self.frames
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()

    def abort(self) -> None:
        """Close without caring whether the file is complete (the caller deletes it)."""
        with contextlib.suppress(Exception):  # an incomplete file is thrown away anyway
            self._container.close()


def read_frames(path: Path, start_frame: int = 0, count: int | None = None) -> np.ndarray:
    """Frames ``start_frame .. start_frame + count`` of an MP4 file as RGB (N, H, W, 3) uint8; all by default.
    Frames are matched by presentation time (frame ``k`` at ``k / fps``), as LeRobot's readers do."""
    av = _av()
    path = Path(path)
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            rate = stream.average_rate or stream.base_rate
            out: list[np.ndarray] = []
            if start_frame > 0:
                container.seek(int(start_frame / rate / stream.time_base), stream=stream, backward=True)
            for frame in container.decode(stream):
                index = round(float(frame.pts * stream.time_base * rate)) if frame.pts is not None else None
                if index is None or index < start_frame:
                    continue
                out.append(frame.to_ndarray(format="rgb24"))
                if count is not None and len(out) >= count:
                    break
    except av.error.FFmpegError as exc:
        raise VideoError(f"{path}: cannot decode this video ({exc}); the file is corrupt or not a video.") from exc
    if count is not None and len(out) < count:
        raise VideoError(f"{path}: holds {start_frame + len(out)} frames, {start_frame + count} were expected.")
    if not out:
        return np.zeros((0, 0, 0, 3), np.uint8)
    return np.stack(out)


def probe(path: Path) -> dict[str, Any]:
    """The stream facts LeRobot keeps in ``info.json`` for a video feature."""
    av = _av()
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return {"video.height": stream.height, "video.width": stream.width, "video.codec": stream.codec.canonical_name,
                "video.pix_fmt": stream.pix_fmt, "video.fps": int(stream.base_rate or stream.average_rate),
                "video.channels": 3, "frames": stream.frames, "has_audio": bool(container.streams.audio)}
