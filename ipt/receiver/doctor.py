"""``ipt-receiver doctor``: the questions of a lab's first day, answered by the receiver itself.

One line per check, ``[ ok ]``, ``[FAIL]`` or ``[skip]``, then the check's name and what was found; a failing line
ends with what to do (``-> ...``). The checks: the receiver config loads; the cameras this computer has (V4L2
nodes with the modes their drivers advertise at the camera file's size and the configured rate, and picamera2
cameras with their sensor modes), and for a configured camera the pixel format it delivers and the rate measured
over :data:`MEASURE_S` seconds; ``camera.yaml`` against the frames' size; the arena file and its map hash (the
sender prints the same hash); the key file (there, closed to other users: the rule of :mod:`ipt.keyfile`); every
send target (parses, a UDP socket to it opens; nothing is sent); the compiled kernels load in this process; the
MAVLink link opens and a HEARTBEAT arrives within :data:`HEARTBEAT_TIMEOUT_S` (when one is configured); the clock
is synchronised (``timedatectl``, when the system has it). Exit status 0 when no check failed, 1 otherwise. A
check never raises: what went wrong (a camera that vanished, an unreadable file) is its line.

What the checks touch of the machine is in :class:`Probes`, so that the tests give each a fake.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import os
import socket
import stat
import struct
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ipt.errors import IptError

if TYPE_CHECKING:
    from ipt.config.camera_info import CameraInfo
    from ipt.config.receiver import ReceiverConfig
    from ipt.receiver.capture import CaptureSource

OK, FAIL, SKIP = "ok", "FAIL", "skip"
MEASURE_S = 2.0
"""Seconds of frames over which a configured camera's rate is measured."""
HEARTBEAT_TIMEOUT_S = 3.0
"""How long the MAVLink check waits for the autopilot's HEARTBEAT."""
MIN_RATE_FRACTION = 0.9
"""A camera measured below this fraction of the configured rate fails its check."""
PREFERRED_FORMATS = ("GREY", "YUYV", "MJPG")
"""V4L2 formats whose luma the receiver takes from the raw buffer (:mod:`~ipt.receiver.capture.pixelformats`),
best first: GREY is the luma itself, YUYV carries it uncompressed, MJPG must be decoded."""


class DoctorError(IptError):
    """A check could not be made (said in its line, never raised out of :func:`run_checks`)."""


@dataclass(frozen=True)
class Check:
    """One check's outcome: status, name, what was found, and what to do when it failed."""

    status: str
    name: str
    detail: str
    fix: str = ""

    def line(self) -> str:
        """The line printed for it."""
        tail = f" -> {self.fix}" if self.status == FAIL and self.fix else ""
        return f"[{self.status:^4}] {self.name}: {self.detail}{tail}"


@dataclass(frozen=True)
class Mode:
    """A mode a camera's driver advertises: pixel format, size and the highest rate it offers there."""

    fourcc: str
    width: int
    height: int
    max_fps: float

    def __str__(self) -> str:
        return f"{self.fourcc} {self.width}x{self.height}@{self.max_fps:g}"


# --- V4L2 modes through the driver's enumeration ioctls --------------------------------------------------


def _iowr(nr: int, size: int) -> int:
    return (3 << 30) | (size << 16) | (ord("V") << 8) | nr


_FMTDESC = struct.Struct("<III32sII12x")  # struct v4l2_fmtdesc (64 bytes)
_FRMSIZE = struct.Struct("<III6I8x")  # struct v4l2_frmsizeenum (44 bytes)
_FRMIVAL = struct.Struct("<IIIII6I8x")  # struct v4l2_frmivalenum (52 bytes)
VIDIOC_ENUM_FMT = _iowr(2, _FMTDESC.size)
VIDIOC_ENUM_FRAMESIZES = _iowr(74, _FRMSIZE.size)
VIDIOC_ENUM_FRAMEINTERVALS = _iowr(75, _FRMIVAL.size)
_DISCRETE = 1


def _enumerate(fd: int, request: int, layout: struct.Struct, *fields: int) -> Iterator[tuple[Any, ...]]:
    """The driver's answers to an enumeration ioctl, index 0, 1, ... until it says there are no more (the
    structure's leading 32-bit fields are the index and ``fields``, the rest zero)."""
    for index in range(256):
        buf = bytearray(layout.size)
        struct.pack_into(f"<{1 + len(fields)}I", buf, 0, index, *fields)
        try:
            fcntl.ioctl(fd, request, buf, True)
        except OSError as exc:
            if exc.errno == errno.EINVAL:
                return
            raise
        yield layout.unpack(bytes(buf))


def _fourcc(code: int) -> str:
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4)).strip()


def v4l2_modes(node: Path) -> list[Mode]:
    """Every (format, discrete size) the V4L2 node advertises, with the highest rate it offers there."""
    fd = os.open(node, os.O_RDWR | os.O_NONBLOCK)
    try:
        modes = []
        for fmt in _enumerate(fd, VIDIOC_ENUM_FMT, _FMTDESC, 1):  # V4L2_BUF_TYPE_VIDEO_CAPTURE
            pixfmt = fmt[4]
            for size in _enumerate(fd, VIDIOC_ENUM_FRAMESIZES, _FRMSIZE, pixfmt):
                if size[2] != _DISCRETE:
                    continue
                w, h = size[3], size[4]
                best = 0.0
                for ival in _enumerate(fd, VIDIOC_ENUM_FRAMEINTERVALS, _FRMIVAL, pixfmt, w, h):
                    num, den = ival[5], ival[6]  # discrete, or a stepwise range's minimum interval
                    if num:
                        best = max(best, den / num)
                modes.append(Mode(_fourcc(pixfmt), w, h, best))
        return modes
    finally:
        os.close(fd)


def picamera2_modes() -> list[tuple[str, list[Mode]]] | None:
    """The picamera2 cameras with their sensor modes (``None``: picamera2 is not installed)."""
    try:
        from picamera2 import Picamera2
    except ImportError:
        return None
    out = []
    for i, info in enumerate(Picamera2.global_camera_info()):
        cam = Picamera2(i)
        try:
            modes = [
                Mode(str(m.get("format", "?")), int(m["size"][0]), int(m["size"][1]), float(m.get("fps", 0.0)))
                for m in cam.sensor_modes
            ]
        finally:
            cam.close()
        out.append((f"picamera2:{i} {info.get('Model', '?')}", modes))
    return out


def _run_command(argv: list[str]) -> str | None:
    """A command's standard output, or ``None`` if it is missing or fails."""
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


def _open_camera(cfg: ReceiverConfig, camera: CameraInfo) -> CaptureSource:
    from ipt.receiver.capture import DeviceCapture, PiCamera2Capture

    spec, grey = cfg.source_spec, cfg.pipeline.luminance_only
    assert spec.device is not None
    kind = DeviceCapture if spec.kind == "device" else PiCamera2Capture
    return kind(spec.device, camera.width_px, camera.height_px, cfg.fps, controls=cfg.camera_controls, grey=grey)


@dataclass
class Probes:
    """What the checks touch of the machine (the tests replace these)."""

    dev_dir: Path = Path("/dev")
    sysfs_dir: Path = Path("/sys/class/video4linux")
    v4l2_modes: Callable[[Path], list[Mode]] = v4l2_modes
    picamera2: Callable[[], list[tuple[str, list[Mode]]] | None] = picamera2_modes
    open_camera: Callable[[ReceiverConfig, CameraInfo], CaptureSource] = _open_camera
    clock: Callable[[], float] = time.monotonic
    measure_s: float = MEASURE_S
    run_command: Callable[[list[str]], str | None] = _run_command
    heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S
    kernels_compiled: Callable[[], bool] | None = None
    """Whether the kernels load compiled (default: :func:`_kernels_compiled`, in this process)."""


@dataclass
class _Found:
    """What one check learns for the next ones."""

    frame_size: tuple[int, int] | None = None
    frame_size_from: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


# --- the checks --------------------------------------------------------------------------------------------


def run_checks(config_path: Path, probes: Probes | None = None) -> list[Check]:
    """Every check, in order; never raises."""
    return list(iter_checks(config_path, probes))


def iter_checks(config_path: Path, probes: Probes | None = None) -> Iterator[Check]:
    """Every check, in order, each as soon as it is made; never raises."""
    from ipt.config.receiver import load_receiver_config

    p = probes if probes is not None else Probes()
    cfg: ReceiverConfig | None = None
    try:
        cfg = load_receiver_config(config_path)
    except (IptError, OSError, ValueError) as exc:
        yield Check(FAIL, "config", str(exc), f"fix {config_path}, or give another with --config")
    if cfg is not None:
        yield Check(OK, "config", f"{config_path}: source {cfg.source}, {len(cfg.send)} send target(s)")
    early: list[Check] = []
    camera = _camera_info(cfg, early)
    yield from early
    found = _Found()
    yield from _guarded("cameras", lambda: _cameras(cfg, camera, p))
    if cfg is not None and camera is not None:
        yield from _guarded("camera rate", lambda: _camera_rate(cfg, camera, p, found))
        yield from _guarded("camera.yaml", lambda: _camera_size(cfg, camera, found))
    if cfg is not None:
        yield from _guarded("arena", lambda: [_arena(cfg)])
        yield from _guarded("key", lambda: [_key(cfg)])
        for target in cfg.send:
            yield from _guarded(f"send {target}", lambda: [_send_target(target)])  # noqa: B023 (called at once)
    yield from _guarded("kernels", lambda: [_kernels(p)])
    if cfg is not None:
        yield from _guarded("mavlink", lambda: [_mavlink(cfg, p)])
    yield from _guarded("clock", lambda: [_clock(p)])


def _guarded(name: str, make: Callable[[], list[Check]]) -> list[Check]:
    """A check's lines; a failure it did not foresee becomes its line, not a traceback."""
    try:
        return make()
    except Exception as exc:
        return [Check(FAIL, name, f"the check itself failed: {type(exc).__name__}: {exc}", "report this as a bug")]


def _camera_info(cfg: ReceiverConfig | None, checks: list[Check]) -> CameraInfo | None:
    from ipt.config.camera_info import load_camera_info

    if cfg is None:
        return None
    try:
        return load_camera_info(cfg.camera)
    except (IptError, OSError) as exc:
        checks.append(Check(FAIL, "camera.yaml", str(exc), "give the camera_info file of this camera (camera:)"))
        return None


def _fitting(modes: list[Mode], camera: CameraInfo | None, fps: float | None) -> list[Mode]:
    return [
        m
        for m in modes
        if (camera is None or (m.width, m.height) == (camera.width_px, camera.height_px))
        and (fps is None or m.max_fps >= fps * 0.99)
    ]


def _cameras(cfg: ReceiverConfig | None, camera: CameraInfo | None, p: Probes) -> list[Check]:
    """One line per camera found, with its modes at the configured size and rate."""
    fps = cfg.fps if cfg is not None else None
    want = f"{camera.width_px}x{camera.height_px}" if camera is not None else "any size"
    at = f"{want} at {fps:g} FPS or more" if fps is not None else want
    spec = cfg.source_spec if cfg is not None else None
    lines = []
    nodes = sorted((n for n in p.dev_dir.glob("video*") if n.name[5:].isdigit()), key=lambda n: int(n.name[5:]))
    for node in nodes:
        name = f"device:{node.name[5:]}"
        configured = spec is not None and spec.kind == "device" and spec.device == int(node.name[5:])
        try:
            modes = p.v4l2_modes(node)
        except OSError as exc:
            status = FAIL if configured else SKIP
            lines.append(Check(status, f"camera {name}", f"{node}: {exc.strerror or exc}", _NODE_FIX))
            continue
        lines.append(_camera_line(name, str(node), modes, camera, fps, at, cfg, configured))
    cams = p.picamera2()
    for label, modes in cams or []:
        index = int(label.split()[0].split(":")[1])
        configured = spec is not None and spec.kind == "picamera2" and spec.device == index
        lines.append(_camera_line(label.split()[0], label, modes, camera, fps, at, cfg, configured))
    wants_camera = spec is not None and spec.kind in ("device", "picamera2")
    configured_seen = any(c.name == f"camera {spec}" for c in lines) if spec is not None else False
    if not lines or (wants_camera and not configured_seen):
        what = "no V4L2 camera" if not nodes else f"{len(nodes)} V4L2 node(s)"
        pc = "picamera2 not installed" if cams is None else f"{len(cams)} picamera2 camera(s)"
        if wants_camera:
            lines.append(Check(FAIL, "cameras", f"{what}, {pc}; the config's source {spec} is not here", _CAM_FIX))
        else:
            why = f"the config's source is {spec}: none needed" if spec is not None else "no config to say which"
            lines.append(Check(SKIP, "cameras", f"{what}, {pc} ({why})"))
    return lines


_NODE_FIX = "is the camera in use by another program, or is this user not in the video group?"
_CAM_FIX = "plug the camera in (ipt-receiver --list-cameras) and set source: device:N or picamera2[:N]"


def _camera_line(
    name: str,
    where: str,
    modes: list[Mode],
    camera: CameraInfo | None,
    fps: float | None,
    at: str,
    cfg: ReceiverConfig | None,
    configured: bool,
) -> Check:
    fitting = _fitting(modes, camera, fps)
    role = " (the configured source)" if configured else ""
    if not fitting:
        status = FAIL if configured else SKIP
        near = ", ".join(str(m) for m in modes[:6]) or "none advertised"
        fix = f"choose a size and rate it offers ({near}) and calibrate at that size"
        return Check(status, f"camera {name}", f"{where}{role}: no mode at {at}", fix)
    fourcc = cfg.camera_controls.fourcc if cfg is not None else None
    rank = {f: i for i, f in enumerate(PREFERRED_FORMATS)}
    formats = sorted({m.fourcc for m in fitting}, key=lambda f: rank.get(f, len(rank)))
    use: str | None
    if name.startswith("picamera2"):
        use = "YUV420 (its Y plane is the luma)"
    elif fourcc is not None:
        use = fourcc if fourcc in formats else None
    else:
        use = f"{formats[0]} (set camera_controls.fourcc: {formats[0]} so that the driver does not pick another)"
    if use is None:
        fix = f"set camera_controls.fourcc to one of {', '.join(formats)}"
        return Check(FAIL if configured else SKIP, f"camera {name}", f"{where}{role}: no {fourcc} at {at}", fix)
    listed = ", ".join(str(m) for m in fitting)
    return Check(OK, f"camera {name}", f"{where}{role}: at {at}: {listed}; the receiver would use {use}")


def _camera_rate(cfg: ReceiverConfig, camera: CameraInfo, p: Probes, found: _Found) -> list[Check]:
    """Open the configured camera, read frames for ``measure_s`` seconds and measure their rate."""
    spec = cfg.source_spec
    if spec.kind not in ("device", "picamera2"):
        return [Check(SKIP, "camera rate", f"the source is {spec}: no camera to measure")]
    name = f"camera {spec} rate"
    try:
        source = p.open_camera(cfg, camera)
        source.open()
    except Exception as exc:
        return [Check(FAIL, name, f"cannot open: {_describe(exc)}", _CAM_FIX)]
    times_us: list[int] = []
    try:
        end = p.clock() + p.measure_s
        while p.clock() < end:
            frame = source.read()
            if frame is None:
                break
            times_us.append(frame.capture_time_us)
            h, w = frame.image.shape[:2]
            found.frame_size, found.frame_size_from = (w, h), f"{spec}'s frames"
    except Exception as exc:
        got = f"after {len(times_us)} frames" if times_us else "before the first frame"
        return [Check(FAIL, name, f"the camera stopped giving frames {got}: {_describe(exc)}", _GONE_FIX)]
    finally:
        with contextlib.suppress(Exception):
            source.close()
    if len(times_us) < 2:
        return [Check(FAIL, name, f"{len(times_us)} frames in {p.measure_s:g} s", _GONE_FIX)]
    rate = (len(times_us) - 1) / max((times_us[-1] - times_us[0]) * 1e-6, 1e-9)
    fmt = getattr(source, "raw_format", None) or ("YUV420" if spec.kind == "picamera2" else "converted by OpenCV")
    detail = f"{rate:.1f} FPS measured over {len(times_us)} frames, pixel format {fmt}"
    if cfg.fps is not None and rate < MIN_RATE_FRACTION * cfg.fps:
        fix = "shorten the exposure (camera_controls.exposure_us), choose a mode that offers the rate, or lower fps"
        return [Check(FAIL, name, f"{detail}, below the configured {cfg.fps:g}", fix)]
    return [Check(OK, name, detail)]


_GONE_FIX = "check the cable and the camera's power (a USB camera on a powered hub), then run doctor again"


def _camera_size(cfg: ReceiverConfig, camera: CameraInfo, found: _Found) -> list[Check]:
    """``camera.yaml``'s size against the frames the source gives."""
    spec = cfg.source_spec
    if found.frame_size is None and spec.kind in ("video", "images") and spec.path is not None:
        from ipt.videoio import open_frames

        with open_frames(spec.path, grey=True) as src:
            found.frame_size, found.frame_size_from = (src.width, src.height), str(spec.path)
    want = (camera.width_px, camera.height_px)
    shown = f"{cfg.camera}: {want[0]}x{want[1]}"
    k = cfg.pipeline.demodulation.binning(camera)
    if k > 1:  # (what the pipeline does with such a camera: said where its size is checked)
        work = camera.binned(k)
        shown += f" (binned {k}x{k}: posed at {work.width_px}x{work.height_px}, pipeline.demodulation.work_width_px)"
    if spec.kind == "sim":
        return [Check(OK, "camera.yaml", f"{shown} (the simulator renders at the camera file's size)")]
    if found.frame_size is None:
        return [Check(SKIP, "camera.yaml", f"{shown}; no frames to compare with (the camera did not open)")]
    if found.frame_size != want:
        got = f"{found.frame_size[0]}x{found.frame_size[1]}"
        fix = "calibrate at the size the camera delivers (ipt calibrate), or ask for the calibrated size"
        return [Check(FAIL, "camera.yaml", f"{shown} but {found.frame_size_from} are {got}", fix)]
    return [Check(OK, "camera.yaml", f"{shown}, as {found.frame_size_from}")]


def _arena(cfg: ReceiverConfig) -> Check:
    from ipt.config.models import load_arena_config
    from ipt.maphash import map_hash
    from ipt.tagmap import grid_tag_map

    try:
        tag_map = grid_tag_map(load_arena_config(cfg.arena))
    except IptError as exc:
        return Check(FAIL, "arena", str(exc), "use the arena file the sender uses (the same file, copied)")
    detail = f"{cfg.arena}: {len(tag_map.tags)} tags, map hash sha256:{map_hash(tag_map)}"
    return Check(OK, "arena", detail + " (the sender prints its own at start: they must be equal)")


def _key(cfg: ReceiverConfig) -> Check:
    """The key file: there, a regular file, closed to other users, a key the receiver accepts (the one rule of
    :func:`ipt.keyfile.read_key_file`, which the sender and the daemon apply too)."""
    from ipt.keyfile import KeyFileError, read_key_file

    path = cfg.auth_key_file
    if path is None:
        return Check(SKIP, "key", "no auth_key_file: the pose packets go unauthenticated")
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        fix = f"copy the sender's key file to {path} (chmod 600)"
        return Check(FAIL, "key", f"{path}: {exc.strerror or exc}", fix)
    try:
        key = read_key_file(path)
    except KeyFileError as exc:
        private = not stat.S_IMODE(mode) & 0o007
        fix = "write a key of 16 bytes or more (e.g. head -c 32 /dev/urandom)" if private else f"chmod o-rwx {path}"
        return Check(FAIL, "key", str(exc), fix)
    return Check(OK, "key", f"{path}: {len(key)} bytes, mode {stat.S_IMODE(mode):o}")


def _send_target(text: str) -> Check:
    """A send target parses and a UDP socket to it opens (connected, nothing sent)."""
    from ipt.config.receiver import parse_host_port

    name = f"send {text}"
    try:
        host, port = parse_host_port(text)
    except ValueError as exc:
        return Check(FAIL, name, str(exc), "write it as HOST:PORT, e.g. 192.168.1.10:9870")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        family, kind, proto, _, addr = infos[0]
        with socket.socket(family, kind, proto) as s:
            s.connect(addr)
            local = s.getsockname()
    except OSError as exc:
        return Check(FAIL, name, f"cannot open a UDP socket to it: {exc.strerror or exc}", _SEND_FIX)
    return Check(OK, name, f"a UDP socket to it opens (from {local[0]}:{local[1]}; nothing sent)")


_SEND_FIX = "check the address and that this computer has a route to it (ip route get HOST)"


def _kernels_compiled() -> bool:
    from ipt.receiver.core import kernels

    kernels.ensure()
    kernels.warm()
    return kernels.COMPILED


def _kernels(p: Probes) -> Check:
    t0 = time.monotonic()
    compiled = (p.kernels_compiled or _kernels_compiled)()
    took = f"{time.monotonic() - t0:.2f} s"
    if not compiled:
        fix = "numba cannot compile here (no executable memory?): see docs/raspberry-pi.md (MemoryDenyWriteExecute)"
        return Check(FAIL, "kernels", f"not compiled: they run as Python/numpy, several times slower ({took})", fix)
    from ipt.receiver.core import kernels

    if kernels.AHEAD is not None:
        return Check(OK, "kernels", f"built ahead of time, loaded without numba ({took}; {kernels.AHEAD})")
    cache = os.environ.get("NUMBA_CACHE_DIR") or "numba's default, __pycache__ beside the sources"
    ahead = "; not built ahead: `ipt-receiver warm` builds them into $NUMBA_CACHE_DIR where gcc and python3-dev are"
    return Check(OK, "kernels", f"compiled kernels load in this process ({took}; cache: {cache}{ahead})")


def _clock(p: Probes) -> Check:
    answer = p.run_command(["timedatectl", "show", "--property=NTPSynchronized", "--value"])
    if answer is None:
        return Check(SKIP, "clock", "the system does not report synchronisation (timedatectl absent or unanswered)")
    if answer.strip() == "yes":
        return Check(OK, "clock", "synchronised (timedatectl: NTPSynchronized=yes)")
    fix = "turn on time synchronisation: sudo timedatectl set-ntp true (and a reachable NTP server)"
    return Check(FAIL, "clock", f"not synchronised (timedatectl: NTPSynchronized={answer.strip()})", fix)


def _describe(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, IptError) else f"{type(exc).__name__}: {exc}"


def _mavlink(cfg: ReceiverConfig, p: Probes) -> Check:
    if cfg.mavlink.link is None:
        return Check(SKIP, "mavlink", "no mavlink.link configured")
    name = f"mavlink {cfg.mavlink.link}"
    try:
        return asyncio.run(_heartbeat(cfg, name, p.heartbeat_timeout_s))
    except IptError as exc:
        return Check(FAIL, name, str(exc), "check mavlink.link and the autopilot's telemetry port settings")


async def _heartbeat(cfg: ReceiverConfig, name: str, timeout_s: float) -> Check:
    """Open the link, send our HEARTBEAT once a second, and wait for one from another component."""
    from ipt.receiver.outputs.mavlink.links import SerialPort, UdpLink, load_dialect

    spec = cfg.mavlink.link_spec
    assert spec is not None
    d = load_dialect(cfg.mavlink.dialect)
    mav = d.MAVLink(None, srcSystem=cfg.mavlink.system_id, srcComponent=cfg.mavlink.component_id)
    parser = d.MAVLink(None)
    loop = asyncio.get_running_loop()
    heard: asyncio.Future[Any] = loop.create_future()
    errors: list[str] = []

    def on_bytes(data: bytes) -> None:
        with contextlib.suppress(Exception):  # garbage on the line is not a HEARTBEAT
            for msg in parser.parse_buffer(data) or []:
                mine = (msg.get_srcSystem(), msg.get_srcComponent()) == (
                    cfg.mavlink.system_id,
                    cfg.mavlink.component_id,
                )
                if msg.get_type() == "HEARTBEAT" and not mine and not heard.done():
                    heard.set_result(msg)

    link: UdpLink | SerialPort
    if spec.kind == "udpout":
        link = UdpLink(spec, on_bytes, lambda exc: errors.append(_describe(exc)))
        await link.open(loop)
    else:
        link = SerialPort(spec, on_bytes, errors.append)
        link.open(loop)
    ours = mav.heartbeat_encode(d.MAV_TYPE_ONBOARD_CONTROLLER, d.MAV_AUTOPILOT_INVALID, 0, 0, d.MAV_STATE_STANDBY)
    start = time.monotonic()
    try:
        while not heard.done() and time.monotonic() - start < timeout_s:
            link.send(ours.pack(mav))
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(
                    asyncio.shield(heard), min(1.0, max(0.0, timeout_s - (time.monotonic() - start)))
                )
    finally:
        link.close()
    if not heard.done():
        said = f" (the link said: {errors[-1]})" if errors else ""
        fix = "is the autopilot on, and this link its telemetry port (SERIALn_PROTOCOL=2, or the SITL's UDP port)?"
        return Check(FAIL, name, f"the link opens but no HEARTBEAT came within {timeout_s:g} s{said}", fix)
    msg = heard.result()
    took = time.monotonic() - start
    who = f"system {msg.get_srcSystem()} component {msg.get_srcComponent()}, autopilot type {msg.autopilot}"
    return Check(OK, name, f"HEARTBEAT from {who} after {took:.2f} s")


def main_lines(config_path: Path, out: Callable[[str], None], probes: Probes | None = None) -> int:
    """Run the checks, print a line for each (as it comes) and a summary; the exit status (0: all passed)."""
    checks = []
    for c in iter_checks(config_path, probes):
        checks.append(c)
        out(c.line())
    failed = [c for c in checks if c.status == FAIL]
    out(
        f"doctor: {len(checks)} checks, {len(failed)} failed"
        + (f" ({', '.join(c.name for c in failed)})" if failed else "")
    )
    return 1 if failed else 0


__all__ = [
    "Check",
    "DoctorError",
    "Mode",
    "Probes",
    "iter_checks",
    "main_lines",
    "picamera2_modes",
    "run_checks",
    "v4l2_modes",
]
