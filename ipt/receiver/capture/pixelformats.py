"""A V4L2 camera's raw frames to luma, without OpenCV's conversion to BGR.

OpenCV's V4L2 backend converts every frame to BGR unless ``CAP_PROP_CONVERT_RGB`` is turned off; the
receiver's pipeline then takes the luma again. With the conversion off the backend hands over the driver's
buffer as it is, and this module takes the luma from it:

- ``GREY`` (8-bit mono, "Y8"): an H×W array, already the luma;
- ``YUYV`` (4:2:2 packed, Y0 U Y1 V): an H×W×2 array whose first channel is the luma, limited range as
  UVC cameras send it (stretched to full range, as OpenCV's conversion to BGR does);
- ``MJPG`` (a JPEG per frame): a 1×N array of the JPEG's bytes, decoded by libjpeg straight to grey (it
  skips the chroma and the colour conversion).

Pure: arrays in, arrays (or ``None`` for a JPEG that does not decode) out.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from ipt.videoio import expand_limited_luma

U8 = npt.NDArray[np.uint8]

#: V4L2 pixel formats (fourcc) whose luma is taken here; any other goes through OpenCV's conversion.
RAW_LUMA_FORMATS = ("GREY", "YUYV", "MJPG")


class PixelFormatError(ValueError):
    """A raw buffer that does not have the shape its format and the frame size give."""


def raw_luma(raw: npt.NDArray[np.generic], fourcc: str, width: int, height: int) -> U8 | None:
    """The full-range luma (H×W uint8) of a raw ``fourcc`` buffer as OpenCV's V4L2 backend hands it over
    with ``CAP_PROP_CONVERT_RGB`` off; ``None`` if an ``MJPG`` frame does not decode (a damaged JPEG).
    :class:`PixelFormatError` if the buffer is not a frame of that format and size."""
    buf = np.asarray(raw)
    if buf.dtype != np.uint8:
        raise PixelFormatError(f"{fourcc} frame: expected 8-bit data, got {buf.dtype}")
    if fourcc == "MJPG":
        data = buf.reshape(-1)
        if data.size < 4:
            return None
        try:
            grey = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
        except cv2.error:
            return None
        if grey is None:
            return None
        if grey.shape != (height, width):
            raise PixelFormatError(f"MJPG frame is {grey.shape[1]}x{grey.shape[0]}, expected {width}x{height}")
        return np.asarray(grey, dtype=np.uint8)
    if fourcc == "GREY":
        if buf.size != width * height:
            raise PixelFormatError(f"GREY frame: {buf.size} bytes, {width}x{height} needs {width * height}")
        return np.ascontiguousarray(buf.reshape(height, width))
    if fourcc == "YUYV":
        if buf.size != 2 * width * height:
            raise PixelFormatError(f"YUYV frame: {buf.size} bytes, {width}x{height} needs {2 * width * height}")
        return expand_limited_luma(buf.reshape(height, width, 2)[:, :, 0])
    raise PixelFormatError(f"{fourcc}: not a format whose luma is taken here ({', '.join(RAW_LUMA_FORMATS)})")


def yuyv_from_rgb(rgb: U8) -> U8:
    """An RGB frame as a camera's YUYV buffer (H×W×2, limited-range BT.601, chroma averaged over pixel
    pairs): for tests and benchmarks, which have no camera."""
    yuv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2YUV).astype(np.float32)  # full range
    y = 16 + yuv[:, :, 0] * 219 / 255
    u = 128 + (yuv[:, :, 1] - 128) * 224 / 255
    v = 128 + (yuv[:, :, 2] - 128) * 224 / 255
    h, w = y.shape
    out = np.empty((h, w, 2), np.float32)
    out[:, :, 0] = y
    out[:, 0::2, 1] = (u[:, 0::2] + u[:, 1::2]) / 2
    out[:, 1::2, 1] = (v[:, 0::2] + v[:, 1::2]) / 2
    return np.clip(np.round(out), 0, 255).astype(np.uint8)
