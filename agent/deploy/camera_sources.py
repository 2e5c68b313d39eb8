"""Real camera frames for the agent: a video file, a USB camera, a Jetson CSI camera, or a recorded episode.

Every source yields ``CameraFrame``s whose ``image`` is what the simulator gives the agent: uint8 RGB at the
profile's size (320x160 by default). A camera's frame has another aspect (16:9), so it is centre-cropped to
the agent's aspect first (keeping the whole width where it can, dropping sky and bonnet rows) and then
resized; ``Profile.camera_config()`` gives the field of view that results. A ZED stereo camera delivers
both eyes side by side in one frame (left | right); ``stereo="side-by-side"`` splits it, and ``right`` holds
the right eye, cropped and resized the same way.

A CSI camera on a Jetson is read through GStreamer (``nvarguscamerasrc``), which needs an OpenCV built with
GStreamer (JetPack's is; the pip wheel ``opencv-python-headless`` is not): ``csi_pipeline`` writes the
pipeline string and opening it elsewhere is one clear error.

Recorded episodes (``data/episodes`` HDF5 files) are a source too: they carry the speed and route command
of every frame, which a video file does not, so the agent can be replayed on them exactly.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

if TYPE_CHECKING:
    from towndrive.agent.deploy.profiles import Profile


@dataclass
class CameraFrame:
    """One frame as the agent takes it."""

    index: int
    time_s: float
    image: np.ndarray  # uint8 H x W x 3 RGB (the left eye for stereo)
    right: np.ndarray | None = None  # the right eye, same size, when the source is stereo
    speed_mps: float | None = None  # known for recorded episodes only
    command: int | None = None  # known for recorded episodes only


def fit_frame(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """Centre-crop ``rgb`` to the aspect ``width:height``, then resize to it (INTER_AREA: no aliasing)."""
    h, w = rgb.shape[:2]
    if (w, h) == (width, height):
        return rgb
    target = width / height
    if w / h > target:  # too wide: crop columns
        cw = int(round(h * target))
        x0 = (w - cw) // 2
        rgb = rgb[:, x0:x0 + cw]
    elif w / h < target:  # too tall: crop rows
        ch = int(round(w / target))
        y0 = (h - ch) // 2
        rgb = rgb[y0:y0 + ch]
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def split_side_by_side(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A ZED-style frame (left eye | right eye) into its two halves."""
    w = frame.shape[1]
    if w % 2:
        raise ValueError(f"A side-by-side stereo frame has an even width; got {w} px. Is the source really stereo?")
    return frame[:, : w // 2], frame[:, w // 2:]


def csi_pipeline(sensor_id: int = 0, capture_width: int = 1280, capture_height: int = 720, fps: int = 30,
                 flip_method: int = 0, width: int | None = None, height: int | None = None) -> str:
    """The GStreamer pipeline for a Jetson CSI camera (Argus) into OpenCV's appsink, BGR frames, newest only."""
    w, h = width or capture_width, height or capture_height
    return (f"nvarguscamerasrc sensor-id={sensor_id} ! video/x-raw(memory:NVMM), width={capture_width}, "
            f"height={capture_height}, framerate={fps}/1, format=NV12 ! nvvidconv flip-method={flip_method} ! "
            f"video/x-raw, width={w}, height={h}, format=BGRx ! videoconvert ! video/x-raw, format=BGR ! "
            "appsink drop=1 max-buffers=1")


def gstreamer_available() -> bool:
    info = cv2.getBuildInformation()
    return any("GStreamer" in line and "YES" in line for line in info.splitlines())


class OpenCVSource:
    """Frames from a ``cv2.VideoCapture`` (file, USB device or GStreamer pipeline), fitted to the agent's size."""

    def __init__(self, capture: Any, what: str, width: int = 320, height: int = 160, stereo: str = "none",
                 fps: float | None = None) -> None:
        if not capture.isOpened():
            raise RuntimeError(f"Cannot open {what}.")
        self.capture = capture
        self.what = what
        self.width, self.height = width, height
        self.stereo = stereo
        self.fps = fps or capture.get(cv2.CAP_PROP_FPS) or 30.0
        self.index = 0
        self.eye_size: tuple[int, int] | None = None  # (width, height) of one delivered eye, once a frame was read

    def read(self) -> CameraFrame | None:
        ok, bgr = self.capture.read()
        if not ok or bgr is None:
            return None
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        right = None
        if self.stereo == "side-by-side":
            rgb, right_raw = split_side_by_side(rgb)
            right = fit_frame(right_raw, self.width, self.height)
        self.eye_size = (rgb.shape[1], rgb.shape[0])  # for Profile.camera_config
        frame = CameraFrame(self.index, self.index / self.fps, fit_frame(rgb, self.width, self.height), right)
        self.index += 1
        return frame

    def __iter__(self) -> Iterator[CameraFrame]:
        while (frame := self.read()) is not None:
            yield frame

    def close(self) -> None:
        self.capture.release()

    def __enter__(self) -> OpenCVSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def video_source(path: str | Path, width: int = 320, height: int = 160, stereo: str = "none") -> OpenCVSource:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"Video file {path} not found.")
    return OpenCVSource(cv2.VideoCapture(str(path)), f"video file {path} (is it a video OpenCV can decode?)",
                        width, height, stereo)


def usb_source(device: int = 0, capture_width: int = 1280, capture_height: int = 720, fps: int = 30, width: int = 320,
               height: int = 160, stereo: str = "none") -> OpenCVSource:
    cap = cv2.VideoCapture(device, cv2.CAP_V4L2) if hasattr(cv2, "CAP_V4L2") else cv2.VideoCapture(device)
    cap.set(cv2.CAP_PROP_FRAME_WIDTH, capture_width)
    cap.set(cv2.CAP_PROP_FRAME_HEIGHT, capture_height)
    cap.set(cv2.CAP_PROP_FPS, fps)
    cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not a queue of old ones
    return OpenCVSource(cap, f"USB camera /dev/video{device} (is it plugged in, and free?)", width, height, stereo, fps)


def csi_source(sensor_id: int = 0, capture_width: int = 1280, capture_height: int = 720, fps: int = 30,
               flip_method: int = 0, width: int = 320, height: int = 160, stereo: str = "none") -> OpenCVSource:
    if not gstreamer_available():
        raise RuntimeError("This OpenCV has no GStreamer support, which a CSI camera needs: on a Jetson use JetPack's "
                           "OpenCV (python3 -c 'import cv2; print(cv2.getBuildInformation())' shows GStreamer: YES), "
                           "and uninstall pip's opencv-python-headless in that environment.")
    # nvvidconv scales on the GPU to twice the agent's size, which keeps the crop and resize cheap.
    scale = max(2 * height / capture_height, 2 * width / capture_width)
    pipe = csi_pipeline(sensor_id, capture_width, capture_height, fps, flip_method,
                        int(round(capture_width * scale / 2)) * 2, int(round(capture_height * scale / 2)) * 2)
    return OpenCVSource(cv2.VideoCapture(pipe, cv2.CAP_GSTREAMER), f"CSI camera {sensor_id} ({pipe})", width, height,
                        stereo, fps)


class EpisodeSource:
    """The frames of a recorded episode (HDF5, ``data.episodes``), with its speed and command per frame."""

    def __init__(self, path: str | Path, width: int = 320, height: int = 160) -> None:
        import h5py

        from towndrive.data.episodes import read_episode

        self.path = Path(path)
        ep = read_episode(self.path, load_frames=False)  # validates the file, names it when it is not an episode
        self.speed, self.command = ep.speed, ep.command
        self.dt = float(ep.attrs.get("dt_s", 0.05))
        self.file = h5py.File(self.path, "r")
        self.frames = self.file["frames"]
        self.right = self.file.get("stereo_right")
        self.width, self.height = width, height
        self.fps = 1.0 / self.dt
        self.index = 0
        self.eye_size: tuple[int, int] | None = (self.frames.shape[2], self.frames.shape[1])

    def read(self) -> CameraFrame | None:
        k = self.index
        if k >= len(self.frames):
            return None
        self.index += 1
        right = fit_frame(self.right[k], self.width, self.height) if self.right is not None else None
        return CameraFrame(k, k * self.dt, fit_frame(self.frames[k], self.width, self.height), right,
                           float(self.speed[k]), int(self.command[k]))

    def __iter__(self) -> Iterator[CameraFrame]:
        while (frame := self.read()) is not None:
            yield frame

    def close(self) -> None:
        self.file.close()

    def __enter__(self) -> EpisodeSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_source(profile: Profile) -> OpenCVSource | EpisodeSource:
    """The profile's camera source (``camera.source``: video, usb, csi or episode)."""
    from towndrive.agent.deploy.profiles import resolve

    c = profile.camera
    if c.source == "video":
        return video_source(resolve(str(c.path)), c.width, c.height, c.stereo)
    if c.source == "episode":
        return EpisodeSource(resolve(str(c.path)), c.width, c.height)
    if c.source == "usb":
        return usb_source(c.device, c.capture_width, c.capture_height, c.fps, c.width, c.height, c.stereo)
    if c.source == "csi":
        return csi_source(c.sensor_id, c.capture_width, c.capture_height, c.fps, c.flip_method, c.width, c.height,
                          c.stereo)
    raise ValueError(f"camera.source {c.source!r} is the simulator's camera; run drive.py without a real source.")
