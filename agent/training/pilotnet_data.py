"""PilotNet training data: frames from recorded episodes, selected, split by episode, balanced and augmented.

Every frame goes through ``agent.perception.pilotnet.preprocess`` once, when it is loaded, and is kept as uint8 YUV
66x200 (40 kB a frame). Augmentation then works on those small images:

* viewpoint shifts and rotations, as in the PilotNet paper: the image is re-projected as a camera moved
  ``shift_m`` to the side and turned ``yaw_rad``, assuming that what is below the horizon is flat ground and
  what is above it is far away; the steering label becomes the one that brings the car back onto the
  recorded path in two seconds (``corrected_steer``);
* horizontal flips, with the steering negated and the command mirrored (left <-> right);
* brightness and random shadows on the Y channel;
* side cameras, where an episode recorded them, with the same two-second correction for their offset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from towndrive.agent.perception.pilotnet import DEFAULT_CROP, INPUT_HEIGHT, INPUT_WIDTH, Crop, preprocess
from towndrive.data.episodes import EpisodeError, list_episodes, read_episode
from towndrive.sim.ego import EgoVehicle
from towndrive.sim.render import CameraConfig

RETURN_TIME_S = 2.0  # the paper: the corrected label steers the car back to the path in two seconds
MIN_RETURN_DISTANCE_M = 8.0  # at walking pace two seconds is too short a distance for a sane correction
MIRRORED_COMMAND = np.array([0, 2, 1, 3], np.int64)  # follow, left, right, straight -> follow, right, left, straight


# --------------------------------------------------------------------------- steering geometry
def corrected_steer(steer: np.ndarray | float, shift_m: np.ndarray | float, yaw_rad: np.ndarray | float,
                    speed_mps: np.ndarray | float) -> np.ndarray:
    """The steering that returns a car displaced ``shift_m`` to the right and turned ``yaw_rad`` to the right of
    the recorded pose onto the recorded path within ``RETURN_TIME_S`` (positive steer turns right).

    The path to get back is the arc y(s) = shift + yaw s + k s^2 / 2 with y(L) = 0 over L = speed x 2 s, so
    the extra curvature is k = -2 (shift + yaw L) / L^2; curvatures add, and the bicycle model turns
    curvature into a wheel angle by tan(angle) = k x length.
    """
    length = EgoVehicle.LENGTH
    distance = np.maximum(np.asarray(speed_mps, np.float64) * RETURN_TIME_S, MIN_RETURN_DISTANCE_M)
    extra = -2.0 * (np.asarray(shift_m) + np.asarray(yaw_rad) * distance) / distance**2
    wheel = np.arctan(np.tan(np.asarray(steer, np.float64) * EgoVehicle.MAX_STEER_RAD) + extra * length)
    return np.clip(wheel / EgoVehicle.MAX_STEER_RAD, -1.0, 1.0).astype(np.float32)


def input_intrinsics(camera: CameraConfig, crop: Crop = DEFAULT_CROP) -> np.ndarray:
    """The pinhole K of the preprocessed 200x66 image: the camera's K, cropped and scaled."""
    k = camera.intrinsics().copy()
    r0, r1 = crop.rows(camera.height)
    sx, sy = INPUT_WIDTH / camera.width, INPUT_HEIGHT / (r1 - r0)
    k[0] *= sx
    k[1, 2] -= r0
    k[1] *= sy
    # cv2.resize with INTER_AREA maps pixel centres: u' + 0.5 = (u + 0.5) s
    k[0, 2] += 0.5 * sx - 0.5
    k[1, 2] += 0.5 * sy - 0.5
    return k


class ViewpointWarp:
    """Re-projects preprocessed frames as seen from a camera shifted sideways and turned (flat-world model)."""

    def __init__(self, camera: CameraConfig, crop: Crop = DEFAULT_CROP) -> None:
        self.k = input_intrinsics(camera, crop)
        self.k_inv = np.linalg.inv(self.k)
        self.height_m = camera.mount_height_m
        pitch = math.radians(camera.pitch_deg)  # negative looks down
        c, s = math.cos(pitch), math.sin(pitch)
        # camera (x right, y down, z forward) -> level frame: rotate about x by the pitch
        self.cam_to_level = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
        u, v = np.meshgrid(np.arange(INPUT_WIDTH, dtype=np.float64), np.arange(INPUT_HEIGHT, dtype=np.float64))
        rays = self.k_inv @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
        self.rays_level = self.cam_to_level @ rays  # 3 x N, in the virtual camera's level frame

    def maps(self, shift_m: float, yaw_rad: float) -> tuple[np.ndarray, np.ndarray]:
        """cv2.remap maps: for each pixel of the virtual view, where to sample the recorded one."""
        cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
        # virtual level frame -> recorded level frame: turned right by yaw about the vertical (y) axis
        yaw = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
        rays = yaw @ self.rays_level
        ground = rays[1] > 1e-3
        points = rays.copy()  # far away: a direction
        t = self.height_m / np.where(ground, rays[1], 1.0)
        points[:, ground] = rays[:, ground] * t[ground] + np.array([[shift_m], [0.0], [0.0]])
        cam = self.cam_to_level.T @ points
        pix = self.k @ cam
        z = np.where(np.abs(pix[2]) < 1e-9, 1e-9, pix[2])
        map_x = (pix[0] / z).reshape(INPUT_HEIGHT, INPUT_WIDTH).astype(np.float32)
        map_y = (pix[1] / z).reshape(INPUT_HEIGHT, INPUT_WIDTH).astype(np.float32)
        return map_x, map_y

    def __call__(self, yuv: np.ndarray, shift_m: float, yaw_rad: float) -> np.ndarray:
        map_x, map_y = self.maps(shift_m, yaw_rad)
        return cv2.remap(yuv, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


# --------------------------------------------------------------------------- loading
@dataclass
class FrameSet:
    """Preprocessed frames and their labels, with the episode each came from."""

    images: np.ndarray  # N x 66 x 200 x 3 uint8 YUV
    steer: np.ndarray  # N float32, the label (with the side-camera correction already applied)
    speed: np.ndarray  # N float32 m/s
    command: np.ndarray  # N int64
    episode: np.ndarray  # N int, index into ``episode_paths``
    episode_paths: list[Path] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.steer)

    def subset(self, mask: np.ndarray) -> FrameSet:
        return FrameSet(self.images[mask], self.steer[mask], self.speed[mask], self.command[mask], self.episode[mask],
                        self.episode_paths)


def load_frames(folders: list[Path], min_speed_mps: float = 1.0, side_cameras: bool = True,
                crop: Crop = DEFAULT_CROP, workers: int = 0) -> FrameSet:
    """Read every episode in ``folders``: frames where the car moves (standing still teaches nothing about
    steering), preprocessed, with their steering labels; side-camera frames too, when recorded.

    ``workers`` > 0 reads and preprocesses the episodes in that many processes (spawned: each imports its own
    libraries and opens the HDF5 files it reads, which an h5py handle inherited through a fork would not survive);
    the result is the same, in the same order."""
    paths: list[Path] = []
    for folder in folders:
        found = list_episodes(Path(folder))
        if not found:
            raise EpisodeError(f"{folder}: no episodes in this folder; record some with drive.py --record {folder}.")
        paths += found
    read = partial(_episode_views, min_speed_mps=min_speed_mps, side_cameras=side_cameras, crop=crop)
    bar = partial(tqdm, total=len(paths), desc="loading episodes", unit="episode", mininterval=2.0)
    if workers > 0 and len(paths) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(min(workers, len(paths)), mp_context=mp.get_context("spawn")) as pool:
            episodes = list(bar(pool.map(read, paths)))
    else:
        episodes = [read(path) for path in bar(paths)]
    images, steer, speed, command, episode = [], [], [], [], []
    for index, views in enumerate(episodes):
        for view_images, view_steer, view_speed, view_command in views:
            images.append(view_images)
            steer.append(view_steer)
            speed.append(view_speed)
            command.append(view_command)
            episode.append(np.full(len(view_steer), index))
    return FrameSet(np.concatenate(images), np.concatenate(steer), np.concatenate(speed), np.concatenate(command),
                    np.concatenate(episode), paths)


def _episode_views(path: Path, min_speed_mps: float, side_cameras: bool,
                   crop: Crop) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """One episode's kept frames per camera: (preprocessed images, steering labels, speeds, commands)."""
    ep = read_episode(path)
    assert ep.frames is not None
    keep = np.flatnonzero(ep.speed >= min_speed_mps)
    views: list[tuple[np.ndarray, float]] = [(ep.frames, 0.0)]
    offset = float(ep.attrs.get("side_camera_offset_m", 0.0) or 0.0)
    if side_cameras and offset > 0 and "side_left" in ep.extras:
        views += [(ep.extras["side_left"], -offset), (ep.extras["side_right"], offset)]
    out = []
    for frames, shift in views:
        images = (np.stack([preprocess(frames[t], crop) for t in keep]) if len(keep) else
                  np.zeros((0, INPUT_HEIGHT, INPUT_WIDTH, 3), np.uint8))
        label = ep.actions[keep, 0]
        steer = corrected_steer(label, shift, 0.0, ep.speed[keep]) if shift else label.astype(np.float32)
        out.append((images, steer, ep.speed[keep].astype(np.float32), ep.command[keep].astype(np.int64)))
    return out


def split_by_episode(frames: FrameSet, validation_fraction: float, seed: int) -> tuple[FrameSet, FrameSet]:
    """Train and validation sets that share no episode (neighbouring frames are near copies, so a split by
    frame would measure memory, not generalisation)."""
    n = len(frames.episode_paths)
    order = np.random.default_rng(seed).permutation(n)
    n_val = max(1, int(round(validation_fraction * n))) if n > 1 else 0
    val_episodes = np.zeros(n, bool)
    val_episodes[order[:n_val]] = True
    is_val = val_episodes[frames.episode]
    return frames.subset(~is_val), frames.subset(is_val)


def balance_weights(steer: np.ndarray, bins: int = 21, max_boost: float = 8.0) -> np.ndarray:
    """Sampling weights that flatten the steering histogram: mostly-straight driving would otherwise teach
    the network to go straight. A bin's frames are boosted by mean count / bin count, at most ``max_boost``
    times, and thinned the same way; weights sum to 1."""
    edges = np.linspace(-1.0, 1.0, bins + 1)
    which = np.clip(np.digitize(steer, edges) - 1, 0, bins - 1)
    counts = np.bincount(which, minlength=bins).astype(np.float64)
    mean = counts[counts > 0].mean()
    per_bin = np.clip(mean / np.maximum(counts, 1.0), 1.0 / max_boost, max_boost)
    w = per_bin[which]
    return w / w.sum()


# --------------------------------------------------------------------------- augmentation
@dataclass(frozen=True)
class Augment:
    """Probabilities and ranges of the augmentations (all drawn from the caller's generator)."""

    viewpoint_p: float = 0.5
    max_shift_m: float = 0.8
    max_yaw_rad: float = math.radians(6.0)
    flip_p: float = 0.5
    brightness: tuple[float, float] = (0.6, 1.35)
    shadow_p: float = 0.3


class Augmenter:
    """Applies ``Augment`` to one preprocessed sample, returning the new image, steering and command."""

    def __init__(self, camera: CameraConfig, config: Augment = Augment(), crop: Crop = DEFAULT_CROP) -> None:
        self.config = config
        self.warp = ViewpointWarp(camera, crop)

    def __call__(self, rng: np.random.Generator, yuv: np.ndarray, steer: float, speed: float,
                 command: int) -> tuple[np.ndarray, float, int]:
        c = self.config
        img = yuv
        if rng.random() < c.viewpoint_p:
            shift = float(rng.uniform(-c.max_shift_m, c.max_shift_m))
            yaw = float(rng.uniform(-c.max_yaw_rad, c.max_yaw_rad))
            img = self.warp(img, shift, yaw)
            steer = float(corrected_steer(steer, shift, yaw, speed))
        if rng.random() < c.flip_p:
            img = img[:, ::-1]
            steer = -steer
            command = int(MIRRORED_COMMAND[command])
        img = img.astype(np.float32)
        img[..., 0] *= rng.uniform(*c.brightness)
        if rng.random() < c.shadow_p:
            img[..., 0] *= _shadow_mask(rng, float(rng.uniform(0.45, 0.8)))
        return np.clip(img, 0, 255).astype(np.uint8), steer, command


def _shadow_mask(rng: np.random.Generator, darkness: float) -> np.ndarray:
    """1 everywhere except a random quadrilateral band across the image, which is ``darkness``."""
    x_top, x_bottom = rng.uniform(0, INPUT_WIDTH, 2), rng.uniform(0, INPUT_WIDTH, 2)
    poly = np.array([[min(x_top), 0], [max(x_top), 0], [max(x_bottom), INPUT_HEIGHT], [min(x_bottom), INPUT_HEIGHT]],
                    np.int32)
    mask = np.ones((INPUT_HEIGHT, INPUT_WIDTH), np.float32)
    cv2.fillConvexPoly(mask, poly, darkness)
    return mask
