"""Camera formats without a detour through RGB: a V4L2 camera's GREY, YUYV and MJPG buffers, a Pi camera's
YUV420 Y plane, videos and image folders read as luma; and the pipeline giving the same poses from them
as from the RGB frames of the same scene.

No camera is attached here: OpenCV's V4L2 capture object is stood in for by a driver that hands over what
OpenCV's backend does (BGR with ``CAP_PROP_CONVERT_RGB`` on, the raw buffer with it off), made from real
rendered frames; picamera2 by a stand-in module with its calls.
"""

from __future__ import annotations

import sys
import types
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np
import pytest

from ipt.config.camera_info import load_camera_info
from ipt.config.models import ArenaConfig, ConfigError, PipelineConfig, load_arena_config
from ipt.config.receiver import CameraControls, ReceiverConfig, with_overrides
from ipt.receiver.capture import (
    MAX_UNDECODABLE_IN_A_ROW,
    CaptureError,
    DeviceCapture,
    PiCamera2Capture,
    VideoCapture,
    v4l2,
)
from ipt.receiver.capture.pixelformats import raw_luma, yuyv_from_rgb
from ipt.receiver.core.pipeline import FrameResult, Pipeline
from ipt.receiver.daemon import make_source
from ipt.receiver.detect.detector import pipeline_detector
from ipt.tagmap import grid_tag_map
from ipt.tum import read_tum
from ipt.videoio import open_frames

FPS = 120.0
W, H = 640, 360


@pytest.fixture(scope="module")
def frames(short_flight: Path) -> list[np.ndarray]:
    with open_frames(short_flight / "frames.mkv") as src:
        return list(src)


def _fourcc(text: str) -> float:
    return float(sum(ord(c) << 8 * i for i, c in enumerate(text)))


class _V4l2:
    """Stands in for ``cv2.VideoCapture`` on a V4L2 camera sending ``fourcc`` frames made from ``rgb``;
    ``damaged`` frame numbers come as a JPEG cut short (OpenCV's backend then fails ``retrieve``)."""

    def __init__(self, fourcc: str, rgb: list[np.ndarray], damaged: frozenset[int] = frozenset()) -> None:
        self.fourcc, self.rgb, self.damaged = fourcc, rgb, damaged
        self.props: dict[int, float] = {cv2.CAP_PROP_FOURCC: _fourcc(fourcc)}
        self.convert = True
        self.k = -1

    def isOpened(self) -> bool:
        return True

    def set(self, prop: int, value: float) -> bool:
        if prop == cv2.CAP_PROP_CONVERT_RGB:
            self.convert = bool(value)
        elif prop != cv2.CAP_PROP_FOURCC:  # the driver keeps its own format
            self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return self.props.get(prop, -1.0)

    def grab(self) -> bool:
        self.k += 1
        return True

    def _raw(self) -> np.ndarray:
        rgb = self.rgb[self.k % len(self.rgb)]
        if self.fourcc == "GREY":
            return np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
        if self.fourcc == "YUYV":
            return yuyv_from_rgb(rgb)
        ok, jpeg = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        data = jpeg.reshape(1, -1)
        return data[:, : data.shape[1] // 3] if self.k in self.damaged else data

    def retrieve(self) -> tuple[bool, np.ndarray | None]:
        raw = self._raw()
        if not self.convert:
            return True, raw
        if self.fourcc == "GREY":
            return True, cv2.cvtColor(raw, cv2.COLOR_GRAY2BGR)
        if self.fourcc == "YUYV":
            return True, cv2.cvtColor(raw, cv2.COLOR_YUV2BGR_YUYV)
        bgr = cv2.imdecode(raw.reshape(-1), cv2.IMREAD_COLOR) if self.k not in self.damaged else None
        return bgr is not None, bgr

    def release(self) -> None:
        pass


def _device(monkeypatch: pytest.MonkeyPatch, driver: _V4l2, grey: bool) -> DeviceCapture:
    monkeypatch.setattr(v4l2.cv2, "VideoCapture", lambda index, api: driver)
    src = DeviceCapture(0, W, H, FPS, controls=CameraControls(fourcc=driver.fourcc), grey=grey, clock=lambda: 1.0)
    src.open()
    return src


def _captured(src: DeviceCapture, n: int) -> list[np.ndarray]:
    try:
        return [f.image for f in (src.read() for _ in range(n)) if f is not None]
    finally:
        src.close()


def _run(short_flight: Path, images: list[np.ndarray]) -> list[FrameResult]:
    camera = load_camera_info(short_flight / "camera.yaml")
    tag_map = grid_tag_map(load_arena_config(short_flight / "arena.yaml"))
    p = Pipeline(tag_map, camera, PipelineConfig(), 60.0, pipeline_detector(PipelineConfig().detector, tag_map.by_id))
    try:
        out: list[FrameResult] = []
        for k, image in enumerate(images):
            out += p.process(k, image, round(k / FPS * 1e6))
        return out + p.flush()
    finally:
        p.close()


@pytest.mark.parametrize("fourcc", ["GREY", "YUYV", "MJPG"])
def test_v4l2_grey_frames_are_the_luma_of_opencvs_rgb(
    monkeypatch: pytest.MonkeyPatch, frames: list[np.ndarray], fourcc: str
) -> None:
    rgb = _captured(_device(monkeypatch, _V4l2(fourcc, frames[:3]), grey=False), 3)
    src = _device(monkeypatch, _V4l2(fourcc, frames[:3]), grey=True)
    assert src.raw_format == fourcc  # OpenCV's conversion is off: the buffers are decoded here
    grey = _captured(src, 3)
    for g, c in zip(grey, rgb, strict=True):
        assert g.shape == (H, W)
        assert c.shape == (H, W, 3)
        diff = np.abs(g.astype(int) - cv2.cvtColor(c, cv2.COLOR_RGB2GRAY))
        # GREY is exact; YUYV differs by the rounding of OpenCV's conversion to BGR and back; MJPG by
        # libjpeg's chroma upsampling, which grey decoding skips.
        assert diff.max() <= {"GREY": 0, "YUYV": 2, "MJPG": 3}[fourcc]
        assert diff.mean() < 0.3


def test_other_v4l2_formats_go_through_opencvs_conversion(monkeypatch: pytest.MonkeyPatch, frames: list) -> None:  # type: ignore[type-arg]
    driver = _V4l2("YUYV", frames[:2])
    driver.fourcc = "YUYV"
    driver.props[cv2.CAP_PROP_FOURCC] = _fourcc("NV12")  # a format not decoded here
    src = _device(monkeypatch, driver, grey=True)
    assert src.raw_format is None
    assert driver.convert
    (g,) = _captured(src, 1)
    assert g.shape == (H, W)


def test_damaged_mjpg_frames_are_skipped_counted_then_a_failure(monkeypatch: pytest.MonkeyPatch, frames: list) -> None:  # type: ignore[type-arg]
    for grey in (True, False):
        src = _device(monkeypatch, _V4l2("MJPG", frames[:4], damaged=frozenset({1, 2})), grey=grey)
        got = [src.read() for _ in range(3)]
        assert [f.index for f in got if f is not None] == [0, 3, 4]  # frames 1 and 2 keep their numbers
        assert src.skipped == 2
        assert src.last_skipped is not None
        assert "frame 2" in src.last_skipped
        src.close()
    always = _V4l2("MJPG", frames[:1], damaged=frozenset(range(1000)))
    src = _device(monkeypatch, always, grey=True)
    with pytest.raises(CaptureError, match=f"{MAX_UNDECODABLE_IN_A_ROW} frames in a row cannot be decoded"):
        src.read()
    src.close()


def test_a_frame_of_another_size_reopens_the_camera(monkeypatch: pytest.MonkeyPatch, frames: list) -> None:  # type: ignore[type-arg]
    small = [np.ascontiguousarray(cv2.resize(frames[0], (320, 180)))]
    for fourcc in ("GREY", "YUYV", "MJPG"):
        src = _device(monkeypatch, _V4l2(fourcc, small), grey=True)
        with pytest.raises(CaptureError, match=r"320|expected|needs"):
            src.read()
        src.close()


@pytest.mark.parametrize("fourcc", ["MJPG", "YUYV"])
def test_the_pipeline_gives_the_same_poses_from_the_luma_as_from_rgb(
    monkeypatch: pytest.MonkeyPatch, short_flight: Path, frames: list[np.ndarray], fourcc: str
) -> None:
    n = 40
    rgb = _captured(_device(monkeypatch, _V4l2(fourcc, frames[:n]), grey=False), n)
    grey = _captured(_device(monkeypatch, _V4l2(fourcc, frames[:n]), grey=True), n)
    from_rgb = {r.index: r.pose for r in _run(short_flight, rgb) if r.pose is not None}
    from_grey = {r.index: r.pose for r in _run(short_flight, grey) if r.pose is not None}
    assert len(from_rgb) >= 0.8 * n
    assert abs(len(from_grey) - len(from_rgb)) <= 2
    common = sorted(from_rgb.keys() & from_grey.keys())
    assert len(common) >= len(from_rgb) - 2
    apart_mm = [1e3 * float(np.linalg.norm(from_grey[k].position_m - from_rgb[k].position_m)) for k in common]
    if fourcc == "MJPG":  # libjpeg's grey is the luma of its colour output to within rounding
        # Rounding moves a pixel by a level at most; most poses do not move. A few single-frame poses do, by
        # up to a few millimetres: one that rests on few edges (the view over the landing pad's border) is
        # that sensitive, and its own error against the truth is of that size too.
        assert float(np.median(apart_mm)) < 0.2, f"median {float(np.median(apart_mm)):.2f} mm"
        assert sum(a > 1.0 for a in apart_mm) <= 2, sorted(apart_mm)[-4:]
        assert max(apart_mm) < 10.0, f"poses from the luma up to {max(apart_mm):.2f} mm from those from RGB"
        return
    # YUYV: OpenCV's conversion to BGR rounds and clips each pixel's colour, which moves its luma by up to
    # 2 levels (0.2 on average) in a pattern that follows the modulated colours; single-frame poses move
    # by about a millimetre with it. The Y plane is the camera's own luma: its poses are as close to the
    # truth as those from RGB.
    assert float(np.median(apart_mm)) < 1.0
    truth = read_tum(short_flight / "groundtruth.tum")

    def median_error_mm(poses: dict[int, Any]) -> float:
        return 1e3 * float(np.median([np.linalg.norm(p.position_m - truth.positions_m[k]) for k, p in poses.items()]))

    # Per frame the two differ by about a millimetre either way (0.2-13 mm from the truth on these 38 frames):
    # the medians of 38 such errors differ by a few tenths by chance (0.28 mm once the bridge changed).
    assert median_error_mm(from_grey) <= median_error_mm(from_rgb) + 0.5


class _Request:
    def __init__(self, array: np.ndarray) -> None:
        self.array = array

    def make_array(self, name: str) -> np.ndarray:
        assert name == "main"
        return self.array

    def get_metadata(self) -> dict[str, Any]:
        return {}

    def release(self) -> None:
        pass


def test_picamera2_grey_takes_the_y_plane_of_full_range_yuv420(monkeypatch: pytest.MonkeyPatch) -> None:
    log: dict[str, Any] = {}
    stride = 704  # rows padded as libcamera pads them
    y = np.random.default_rng(0).integers(0, 256, (H, W), dtype=np.uint8)
    buffer = np.full((H * 3 // 2, stride), 128, np.uint8)
    buffer[:H, :W] = y

    class Picamera2:
        def __init__(self, index: int) -> None:
            pass

        def create_video_configuration(self, **kw: Any) -> dict[str, Any]:
            log["config"] = kw
            return kw

        def configure(self, config: dict[str, Any]) -> None:
            pass

        def start(self) -> None:
            pass

        def capture_request(self) -> _Request:
            return _Request(buffer)

        def stop(self) -> None:
            pass

        def close(self) -> None:
            pass

    class ColorSpace:
        @staticmethod
        def Sycc() -> str:
            return "sycc"

    picamera2 = types.ModuleType("picamera2")
    picamera2.Picamera2 = Picamera2  # type: ignore[attr-defined]
    libcamera = types.ModuleType("libcamera")
    libcamera.ColorSpace = ColorSpace  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "picamera2", picamera2)
    monkeypatch.setitem(sys.modules, "libcamera", libcamera)
    src = PiCamera2Capture(0, W, H, FPS, grey=True, clock=lambda: 1.0)
    src.open()
    frame = src.read()
    src.close()
    assert log["config"]["main"] == {"size": (W, H), "format": "YUV420"}
    assert log["config"]["colour_space"] == "sycc"  # full range: the Y plane is the luma as RGB's is
    assert frame is not None
    assert frame.image.flags.c_contiguous
    np.testing.assert_array_equal(frame.image, y)
    buffer = np.zeros((H, W), np.uint8)  # not YUV420's 1.5 heights
    src.open()
    with pytest.raises(CaptureError, match="YUV420"):
        src.read()
    src.close()


def test_videos_and_image_folders_read_as_luma(short_flight: Path, frames: list, tmp_path: Path) -> None:  # type: ignore[type-arg]
    with open_frames(short_flight / "frames.mkv", grey=True) as src:
        grey = [f for _, f in zip(range(4), src, strict=False)]
    for g, rgb in zip(grey, frames, strict=False):
        np.testing.assert_array_equal(g, cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))

    # A YUV video (limited range): its Y plane, stretched to full range, is the luma of its RGB frames.
    path = tmp_path / "mpeg4.mkv"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("mpeg4", rate=120)
        stream.width, stream.height, stream.pix_fmt, stream.bit_rate = W, H, "yuv420p", 20_000_000
        for rgb in frames[:4]:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")))
        out.mux(stream.encode(None))
    with open_frames(path, grey=True) as src:
        luma = list(src)
    with open_frames(path) as src:
        decoded = list(src)
    for g, rgb in zip(luma, decoded, strict=True):
        assert g.shape == (H, W)
        diff = np.abs(g.astype(int) - cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
        assert diff.mean() < 1.5  # the RGB route rounds and clips the chroma; the Y plane does not
        assert np.percentile(diff, 99) <= 4

    folder = tmp_path / "jpegs"
    folder.mkdir()
    for k, rgb in enumerate(frames[:3]):
        cv2.imwrite(str(folder / f"{k}.jpg"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    src_cap = VideoCapture(folder, FPS, realtime=False, size=(W, H), images_only=True, grey=True)
    src_cap.open()
    try:
        first = src_cap.read()
    finally:
        src_cap.close()
    assert first is not None
    np.testing.assert_array_equal(first.image, cv2.imread(str(folder / "0.jpg"), cv2.IMREAD_GRAYSCALE))


def test_the_daemon_asks_its_sources_for_luma_when_the_pipeline_needs_nothing_else(short_flight: Path) -> None:
    import threading

    base = ReceiverConfig(arena=Path("a.yaml"), camera=short_flight / "camera.yaml")
    camera = load_camera_info(short_flight / "camera.yaml")
    for source, kind in (("device:0", DeviceCapture), ("picamera2", PiCamera2Capture)):
        cfg = with_overrides(base, source=source)
        made = make_source(cfg, ArenaConfig(), camera, threading.Event())
        assert isinstance(made, kind)
        assert made.grey
    video = with_overrides(base, source=f"video:{short_flight / 'frames.mkv'}")
    recording = make_source(video, ArenaConfig(), camera, threading.Event())
    assert isinstance(recording, VideoCapture)
    assert recording.grey
    paper = with_overrides(video, pipeline=PipelineConfig.profile("paper").model_dump())
    assert not paper.pipeline.luminance_only  # CIELAB lightness needs the colours
    in_colour = make_source(paper, ArenaConfig(), camera, threading.Event())
    assert isinstance(in_colour, VideoCapture)
    assert not in_colour.grey


def test_camera_format_names_are_checked_and_aliases_taken() -> None:
    base = ReceiverConfig(arena=Path("a.yaml"), camera=Path("c.yaml"))
    assert with_overrides(base, camera_controls={"fourcc": "Y800"}).camera_controls.fourcc == "GREY"
    assert with_overrides(base, camera_controls={"fourcc": "YUY2"}).camera_controls.fourcc == "YUYV"
    assert with_overrides(base, camera_controls={"fourcc": "MJPG"}).camera_controls.fourcc == "MJPG"
    for bad in ("MJPEG", "YU\x00V", "yuyv "):
        with pytest.raises(ConfigError, match="fourcc"):
            with_overrides(base, camera_controls={"fourcc": bad})


def test_raw_luma_rejects_buffers_of_the_wrong_size() -> None:
    from ipt.receiver.capture.pixelformats import PixelFormatError

    with pytest.raises(PixelFormatError, match="GREY"):
        raw_luma(np.zeros(10, np.uint8), "GREY", W, H)
    with pytest.raises(PixelFormatError, match="YUYV"):
        raw_luma(np.zeros((H, W), np.uint8), "YUYV", W, H)
    assert raw_luma(np.zeros((1, 2), np.uint8), "MJPG", W, H) is None
