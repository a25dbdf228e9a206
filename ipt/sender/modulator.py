"""Modulation: hide the tag map in the video as a 60 Hz lightness flicker (the paper's Algorithm 1).

Pure: frames and the mask in, frames out. Output frame ``j`` carries ``+ΔL`` on white tag pixels (and
``-ΔL`` on black ones) when ``j`` is even and the opposite when it is odd, so phases keep alternating
across input frames whatever ``N = f_o / f_i`` is. The flicker fuses for people; a camera that subtracts
two frames of opposite phase sees ``±2ΔL`` on the tags.

Profiles:
- ``paper``: Algorithm 1 as published, in 8-bit CIELAB (OpenCV's 8-bit Lab: L scaled to 0..255).
"""

from __future__ import annotations

from fractions import Fraction

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError

U8 = npt.NDArray[np.uint8]


class ModulationError(IptError):
    """The modulation settings or an input frame are unusable."""


def phase_sign(output_index: int) -> int:
    """+1 for output frames that add ΔL on white tag pixels (even indices), -1 for the others."""
    return 1 if output_index % 2 == 0 else -1


def frames_per_input(input_rate_hz: float, output_rate_hz: float) -> int:
    """N = f_o / f_i, which Algorithm 1 needs to be a whole number."""
    # 1001 keeps NTSC rates exact: 60000/1001 over 30000/1001 is 2.
    ratio = Fraction(output_rate_hz).limit_denominator(1001) / Fraction(input_rate_hz).limit_denominator(1001)
    if ratio.denominator != 1 or ratio < 1:
        raise ModulationError(
            f"output rate {output_rate_hz:g} Hz is not a whole multiple of the input rate {input_rate_hz:g} Hz"
        )
    return int(ratio)


class PaperModulator:
    """Algorithm 1: resize, RGB→CIELAB, duplicate N times, L ± ΔL·T_mask with alternating sign, clip, back.

    ``mask`` is T_mask (+1 white tag pixel, -1 black, 0 untouched) at the output resolution.
    """

    profile = "paper"

    def __init__(self, mask: npt.NDArray[np.int8], delta_l: float) -> None:
        if not 0 < delta_l <= 127:
            raise ModulationError(f"ΔL must be in (0, 127] 8-bit L units, got {delta_l}")
        self.height_px, self.width_px = mask.shape
        self.delta_l = delta_l
        # ΔL·T_mask in 8-bit L units, rounded once (Algorithm 1 works on 8-bit L).
        self._offset_l = np.rint(mask.astype(np.float32) * np.float32(delta_l)).astype(np.int16)

    def prepare(self, frame_rgb: U8) -> U8:
        """Resize an input frame to the output resolution and convert it to 8-bit CIELAB (steps 3-4)."""
        if frame_rgb.ndim != 3 or frame_rgb.shape[2] != 3 or frame_rgb.dtype != np.uint8:
            raise ModulationError(f"expected an H×W×3 uint8 RGB frame, got {frame_rgb.shape} {frame_rgb.dtype}")
        if frame_rgb.shape[:2] != (self.height_px, self.width_px):
            frame_rgb = cv2.resize(frame_rgb, (self.width_px, self.height_px), interpolation=cv2.INTER_AREA)
        return np.asarray(cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2Lab), dtype=np.uint8)

    def phase_frame(self, lab: U8, sign: int, region: tuple[int, int, int, int] | None = None) -> U8:
        """One output frame: L + sign·ΔL·T_mask, clipped to 0..255, back to RGB (steps 7-10).

        With ``region = (x0, y0, x1, y1)``, ``lab`` is that region of the prepared frame and only it is
        modulated (the simulator asks for the part of the floor the camera sees).
        """
        offset = self._offset_l
        if region is not None:
            x0, y0, x1, y1 = region
            offset = offset[y0:y1, x0:x1]
        if lab.shape[:2] != offset.shape:
            raise ModulationError(f"frame region {lab.shape[:2]} does not match the mask region {offset.shape}")
        out = lab.copy()
        lightness = lab[:, :, 0].astype(np.int16)
        if sign > 0:
            lightness += offset
        else:
            lightness -= offset
        np.clip(lightness, 0, 255, out=lightness)
        out[:, :, 0] = lightness.astype(np.uint8)
        return np.asarray(cv2.cvtColor(out, cv2.COLOR_Lab2RGB), dtype=np.uint8)

    def modulate(self, frame_rgb: U8, first_output_index: int, count: int) -> list[U8]:
        """The ``count`` output frames of one input frame, starting at output index ``first_output_index``."""
        lab = self.prepare(frame_rgb)
        return [self.phase_frame(lab, phase_sign(first_output_index + i)) for i in range(count)]
