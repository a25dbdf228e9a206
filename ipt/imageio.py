"""Image files in and out, for every tool: OpenCV decodes and encodes bytes, Python reads and writes the file.

OpenCV's ``imread``/``imwrite`` take the path as a C string and crash the process (SIGSEGV) on a name
that is not valid UTF-8, which Linux allows and Python carries as surrogate escapes. So no path is
ever handed to OpenCV: the file is read here (bounded and regular files only, :func:`ipt.fileio.read_bytes_file`)
and decoded with ``cv2.imdecode``; an image is encoded with ``cv2.imencode`` and written atomically
(:func:`ipt.fileio.atomic_path`), so a full disk is one line naming the file, and libpng has no file of
its own to complain about.

Image bombs: a PNG of a few hundred kilobytes can hold 20000x20000 pixels (1.2 GB once decoded as RGB).
Before anything is decoded, the size the file's header gives (read by Pillow, which parses only the
header; an uncompressed 24-bit BMP's is read here) is checked against a cap, :data:`MAX_IMAGE_PIXELS` unless the
caller gives its own (a camera's frames: the camera's size); a file over it is refused with one line, undecoded.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.fileio import atomic_path, read_bytes_file

U8 = npt.NDArray[np.uint8]

MAX_IMAGE_BYTES = 256 * 2**20
"""Largest image file read (a 16384x16384 PNG of noise is about 800 MB; real maps and photos are far smaller)."""

MAX_IMAGE_PIXELS = 50_000_000
"""Most pixels (width x height) an image may have, checked from its header before it is decoded: 50
megapixels admits every camera photo up to full-frame 45-megapixel bodies and the 24-megapixel photos a
lab projects, and keeps the decoded RGB image under 150 MB."""

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"})
"""File name endings (compared case-insensitively) taken for images in a folder."""

ImageMode = Literal["rgb", "grey", "unchanged"]
"""What :func:`read_image` returns: H×W×3 RGB, H×W grey, or the file's own channels and depth (OpenCV's
channel order, BGR)."""

_FLAGS: dict[str, int] = {"rgb": cv2.IMREAD_COLOR, "grey": cv2.IMREAD_GRAYSCALE, "unchanged": cv2.IMREAD_UNCHANGED}


class ImageError(IptError):
    """An image file cannot be read or written."""


def decode_image(data: bytes | memoryview, mode: ImageMode = "rgb") -> npt.NDArray[np.generic] | None:
    """``data`` (the bytes of an image file) decoded as ``mode`` asks, or ``None`` if OpenCV cannot decode it.

    An uncompressed 24-bit BMP (what ``ipt sim --frames-dir`` and the benchmarks write) is read here, as a
    view of its rows converted by ``cv2.cvtColor``: the same RGB as OpenCV's decoder gives, and as grey the
    BT.601 luma that ``cvtColor`` gives an RGB frame and a video's frames (OpenCV's BMP decoder converts
    to grey by its own rounding, up to one level apart, and at 1280×720 took 1.2 ms a frame against 0.2).
    """
    if not data:
        return None
    bmp = _plain_bmp(data)
    if bmp is not None:
        return _from_bgr(*bmp, mode)
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), _FLAGS[mode])
    except cv2.error:
        return None
    if img is None or img.size == 0:
        return None
    if mode == "rgb":
        return np.ascontiguousarray(cv2.cvtColor(img, cv2.COLOR_BGR2RGB), dtype=np.uint8)
    return np.asarray(img)


_BMP_INFO_HEADERS = frozenset({40, 108, 124})
"""The sizes of the BMP info headers (BITMAPINFOHEADER, V4, V5) that :func:`_plain_bmp` reads."""


def _plain_bmp(data: bytes | memoryview) -> tuple[U8, bool] | None:
    """The pixels of an uncompressed 24-bit BMP as a view of ``data`` (BGR, rows as stored) and whether the
    bottom row comes first (a positive height), or None for any other file, or one too short for its pixels:
    OpenCV's decoder then has it."""
    header = _plain_bmp_header(data)
    if header is None:
        return None
    offset, info, width, height = header
    rows, stride = abs(height), (3 * width + 3) & ~3
    if offset < 14 + info or len(data) < offset + stride * rows:
        return None
    stored = np.frombuffer(data, np.uint8, count=stride * rows, offset=offset).reshape(rows, stride)
    return stored[:, : 3 * width].reshape(rows, width, 3), height > 0


def _plain_bmp_header(data: bytes | memoryview) -> tuple[int, int, int, int] | None:
    """(pixel offset, info header size, width, height as stored: negative for rows top first) of an uncompressed
    24-bit BMP's header, or None for any other file."""
    if len(data) < 54 or bytes(data[:2]) != b"BM":
        return None
    offset, info, width, height, planes, bits, compression = struct.unpack_from("<IIiiHHI", data, 10)
    if info not in _BMP_INFO_HEADERS or planes != 1 or bits != 24 or compression != 0 or width <= 0 or height == 0:
        return None
    return offset, info, width, height


def _from_bgr(rows: U8, bottom_up: bool, mode: ImageMode) -> U8:
    """A BMP's stored BGR rows as the image ``mode`` asks, top row first, in memory of its own (``rows`` is a
    view of a buffer that the next read overwrites)."""
    if mode == "unchanged":
        return np.array(rows[::-1] if bottom_up else rows, np.uint8, order="C")  # a copy: never the buffer
    converted = cv2.cvtColor(rows, cv2.COLOR_BGR2RGB if mode == "rgb" else cv2.COLOR_BGR2GRAY)
    return np.asarray(cv2.flip(converted, 0) if bottom_up else converted, np.uint8)


#: :func:`header_size` first parses this many leading bytes: a header is there unless a JPEG's metadata (a
#: large EXIF thumbnail) comes before its frame header, and then the whole file is parsed.
HEADER_PREFIX_BYTES = 1 << 16


def header_size(data: bytes | memoryview) -> tuple[int, int] | None:
    """(width, height) as the header of the image file ``data`` gives it, without decoding its pixels; None
    when Pillow knows no such format (OpenCV may still decode it) or the header is damaged.

    Pillow's format plugins are asked in turn, as ``PIL.Image.open`` does, but without its own bomb check
    (which would refuse a large image before saying its size): only the header is parsed, first from the
    file's first :data:`HEADER_PREFIX_BYTES` (parsing a header reads no further than it, so a size found
    there is the whole file's), else from the whole file.
    """
    bmp = _plain_bmp_header(data)
    if bmp is not None:  # (the benchmarks' frames: Pillow's import and its parse of each frame spared)
        return bmp[2], abs(bmp[3])
    from PIL import Image  # Pillow comes with matplotlib; loaded only when an image is read

    # Pillow's common formats first (BMP, GIF, JPEG, PPM, PNG: a camera's frames), as ``Image.open`` does:
    # loading all of its plugins costs a tenth of a second, on a restarted daemon's way to its first pose.
    Image.preinit()
    found = _header_size(data)
    if found is None:
        Image.init()
        found = _header_size(data)
    return found


def _header_size(data: bytes | memoryview) -> tuple[int, int] | None:
    """:func:`header_size` by the Pillow plugins loaded so far."""
    from PIL import Image

    prefix = bytes(data[:16])
    plugins = []
    for fmt in list(Image.ID):
        factory, accept = Image.OPEN[fmt]
        try:
            said = accept(prefix) if accept is not None else True
        except Exception:
            continue
        if said and not isinstance(said, str):  # a string: "this format, but Pillow cannot open it"
            plugins.append(factory)
    if len(data) > HEADER_PREFIX_BYTES:
        found = _parsed_size(plugins, bytes(data[:HEADER_PREFIX_BYTES]))
        if found is not None:
            return found
    return _parsed_size(plugins, data)


def _parsed_size(plugins: list[Any], data: bytes | memoryview) -> tuple[int, int] | None:
    for factory in plugins:
        try:
            with factory(io.BytesIO(data), "") as img:
                width, height = img.size
        except Exception:
            continue
        return int(width), int(height)
    return None


def too_many_pixels(
    data: bytes | memoryview, max_pixels: int = MAX_IMAGE_PIXELS, limit: str | None = None
) -> str | None:
    """Why the image file ``data`` is refused undecoded (its header gives more than ``max_pixels`` pixels;
    ``limit`` names the cap in the sentence), or None."""
    size = header_size(data)
    if size is None or size[0] * size[1] <= max_pixels:
        return None
    w, h = size
    limit = limit if limit is not None else f"the {max_pixels / 1e6:g} megapixels an image may have"
    return f"{w}x{h} pixels ({w * h / 1e6:.1f} megapixels), more than {limit}; not decoded"


def image_from_bytes(
    data: bytes | memoryview, path: str | Path, mode: ImageMode = "rgb", error: type[Exception] = ImageError
) -> U8:
    """The bytes ``data`` of the image file ``path`` decoded as :func:`read_image` does (no pixel check)."""
    img = decode_image(data, mode)
    if img is None:
        raise error(f"{path}: not an image OpenCV can read")
    if img.dtype != np.uint8:
        raise error(f"{path}: a {img.dtype} image; 8-bit images only")
    return np.ascontiguousarray(img, dtype=np.uint8)


def read_image(
    path: str | Path, mode: ImageMode = "rgb", error: type[Exception] = ImageError, max_pixels: int = MAX_IMAGE_PIXELS
) -> U8:
    """The 8-bit image in ``path``: H×W×3 RGB (``"rgb"``, grey becomes RGB), H×W (``"grey"``) or as stored
    (``"unchanged"``, 8-bit files only). Any problem is ``error`` with one line naming the file; an image
    whose header gives more than ``max_pixels`` pixels is refused before it is decoded."""
    p = Path(path)
    data = read_bytes_file(p, error, "an image file", max_bytes=MAX_IMAGE_BYTES)
    if (why := too_many_pixels(data, max_pixels)) is not None:
        raise error(f"{p}: {why}")
    return image_from_bytes(data, p, mode, error)


def encode_image(image: npt.NDArray[np.generic], suffix: str = ".png") -> bytes:
    """``image`` (grey, or BGR as OpenCV stores colour) as the bytes of a ``suffix`` file (``.png``, ``.jpg``, ...)."""
    try:
        ok, buf = cv2.imencode(suffix, image)
    except cv2.error as exc:
        raise ImageError(f"cannot encode a {suffix} image: {str(exc).strip().splitlines()[-1]}") from None
    if not ok:
        raise ImageError(f"cannot encode a {suffix} image of shape {image.shape} {image.dtype}")
    return bytes(buf)


def write_image(
    path: str | Path, image: npt.NDArray[np.generic], error: type[Exception] = ImageError, *, suffix: str | None = None
) -> None:
    """Write ``image`` (grey, or BGR) to ``path`` atomically, in the format ``suffix`` names (``".png"``, ...;
    default: the one ``path`` ends with, PNG for any other ending).

    A file that cannot be written (no such folder, a full or read-only disk) is a
    :class:`~ipt.fileio.WriteError` naming ``path``; an image the format cannot hold is ``error``.
    """
    p = Path(path)
    if suffix is None:
        suffix = p.suffix.lower() if p.suffix.lower() in IMAGE_SUFFIXES else ".png"
    try:
        data = encode_image(image, suffix)
    except ImageError as exc:
        raise error(f"{p}: {exc}") from None
    with atomic_path(p) as tmp:
        tmp.write_bytes(data)
