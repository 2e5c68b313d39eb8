"""The picture the models were trained on, from a camera that differs: another field of view, pitch or size.

Why: PilotNet and the detector learnt from the simulator's rig (``sim.spec.CAMERA``: 90 degrees, pitched 4 degrees
down, 320 x 160). A car whose camera sees 100 degrees shows the road narrower and the kerbs nearer the middle, and
PilotNet, which steers by where the lines fall in the picture, steers wrong. A camera that only differs by a turn
about its own centre and by its lens is one homography away from the trained one, ``K_model R K_camera^-1``, exact
for every depth (as driving stacks warp their camera into a fixed "model frame" before the network). The agent then
works in the model's frame: the warped picture, the trained field of view and pitch, and the car's own mounting
height and position (the geometry uses the true height). A different height is not a rotation: the road below the
horizon is one more homography away, the road plane's (``lanes.ground_homography``), and PilotNet, which steers by
the lines on the road, gets the road as the trained rig would see it (``for_pilotnet``); what stands on the road is
bent by it, so the detector keeps the first picture. A narrower lens than the trained one leaves black borders; a
wider one is cropped to the trained view.
"""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from towndrive.agent.perception.lanes import ground_homography, horizon_row, pitch_rotation
from towndrive.sim.spec import CAMERA, CameraConfig


def model_camera(camera: CameraConfig, trained: CameraConfig = CAMERA) -> CameraConfig:
    """The camera the agent works in: the trained rig's lens, pitch and picture size at ``camera``'s mounting."""
    return replace(camera, hfov_deg=trained.hfov_deg, pitch_deg=trained.pitch_deg, width=trained.width,
                   height=trained.height)


class ModelView:
    """Warps ``camera``'s pictures into ``model_camera(camera)``'s (identity when they agree)."""

    def __init__(self, camera: CameraConfig, trained: CameraConfig = CAMERA) -> None:
        self.camera = model_camera(camera, trained)
        same = (camera.hfov_deg, camera.pitch_deg, camera.width, camera.height) == (
            self.camera.hfov_deg, self.camera.pitch_deg, self.camera.width, self.camera.height)
        self.homography: np.ndarray | None = None if same else (
            self.camera.intrinsics() @ pitch_rotation(self.camera.pitch_deg) @ pitch_rotation(camera.pitch_deg).T
            @ np.linalg.inv(camera.intrinsics()))
        # the road from this height to the trained one, in the model's frame (same lens and pitch: same horizon)
        trained_height = replace(self.camera, mount_height_m=trained.mount_height_m)
        self.road_homography: np.ndarray | None = None if camera.mount_height_m == trained.mount_height_m else (
            ground_homography(trained_height) @ np.linalg.inv(ground_homography(self.camera)))
        self.below_horizon_row = min(max(int(math.ceil(horizon_row(self.camera))) + 1, 0), self.camera.height)

    @property
    def needed(self) -> bool:
        """Whether the camera differs from the trained rig at all."""
        return self.homography is not None or self.road_homography is not None

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if self.homography is None:
            return image
        return cv2.warpPerspective(image, self.homography, (self.camera.width, self.camera.height),
                                   flags=cv2.INTER_LINEAR)

    def for_pilotnet(self, image: np.ndarray) -> np.ndarray:
        """A picture in the model's frame (``__call__``'s), its road below the horizon as seen from the trained
        height."""
        if self.road_homography is None:
            return image
        # a higher camera's last row meets the road farther off: the nearest road repeats its last row
        road = cv2.warpPerspective(image, self.road_homography, (self.camera.width, self.camera.height),
                                   flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out = image.copy()
        out[self.below_horizon_row:] = road[self.below_horizon_row:]
        return out
