"""The projected image as a pinhole camera above the floor sees it, for tests that render their own views."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.models import ArenaConfig
from ipt.receiver.core.pose import rt_of
from ipt.tagmap import arena_to_pixel_matrix

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]


def render_view(
    img: U8,
    arena: ArenaConfig,
    camera_matrix: F64,
    position_m: F64,
    r_arena_cam: F64,
    size: tuple[int, int] = (640, 360),
) -> U8:
    """``img`` (projector pixels) as the undistorted camera at ``position_m`` turned by ``r_arena_cam`` sees it
    on the floor, ``size`` (w, h) pixels, bilinear."""
    rvec, tvec = rt_of(position_m, r_arena_cam)
    r_cam, _ = cv2.Rodrigues(rvec)
    floor_to_cam = camera_matrix @ np.column_stack([r_cam[:, 0], r_cam[:, 1], tvec])
    edge_to_centre = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    h = floor_to_cam @ np.linalg.inv(arena_to_pixel_matrix(arena)) @ edge_to_centre
    return np.asarray(cv2.warpPerspective(img, h, size, flags=cv2.INTER_LINEAR), np.uint8)
