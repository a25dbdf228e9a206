"""What the flight recorder (``ipt-receiver run --record-frames``) costs at 640×360 and 120 FPS.

For each lossless codec: the processor time to encode one luma frame (and, for the recorder's own codecs,
to write it through :class:`~ipt.receiver.capture.framelog.FrameLogWriter` into a folder), the bytes per
frame, and the MB/s a 120 FPS camera makes of it; and the time to decode a frame back (the replay).

    .venv/bin/python benchmarks/framelog.py FLIGHT_FOLDER_OR_VIDEO_OR_RECORDING [--repeat 5] [--out DIR]

The frames are the luma of a video (e.g. ``ipt sim`` output's frames.mkv) or of a ``--record-frames``
folder. Simulated frames carry the simulator's camera noise; a real camera's noise and texture change the
ratios, so measure on its frames too.
"""

from __future__ import annotations

import argparse
import io
import sys
import tempfile
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ipt.receiver.capture import CapturedFrame
from ipt.receiver.capture.framelog import FRAMES_NAME, FrameLog, FrameLogWriter
from ipt.videoio import open_frames

FPS = 120.0


def _frames(path: Path) -> list[np.ndarray]:
    """The luma frames of a video, a simulated flight's folder, or a ``--record-frames`` folder."""
    if (path / "recording.json").exists():
        return [e.image for e in FrameLog(path).events() if e.image is not None]
    src = path / "frames.mkv" if path.is_dir() else path
    with open_frames(src, grey=True) as video:
        return [np.ascontiguousarray(f) for f in video]


def _row(name: str, cpu_s: float, n: int, total_bytes: int, raw_bytes: int, decode_ms: float | None) -> str:
    per = total_bytes / n
    dec = f"{decode_ms:6.2f}" if decode_ms is not None else "     -"
    return (
        f"| {name:22s} | {1e3 * cpu_s / n:6.2f} | {per / 1e3:7.1f} | {raw_bytes / per:4.2f} | {per * FPS / 1e6:5.1f} | "
        f"{dec} |"
    )


def _codec(frames: list[np.ndarray], name: str, encode: Callable[[np.ndarray], bytes]) -> str:
    t0 = time.process_time()
    total = sum(len(encode(f)) for f in frames)
    return _row(name, time.process_time() - t0, len(frames), total, frames[0].nbytes, None)


def _ffv1(frames: list[np.ndarray]) -> str:
    import av

    buf = io.BytesIO()
    h, w = frames[0].shape
    t0 = time.process_time()
    with av.open(buf, "w", format="matroska") as out:
        stream = out.add_stream("ffv1", rate=int(FPS))
        stream.width, stream.height, stream.pix_fmt = w, h, "gray"
        stream.options = {"threads": "1"}
        for f in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(f, format="gray")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    cpu = time.process_time() - t0
    return _row("FFV1 (PyAV, 1 thread)", cpu, len(frames), buf.getbuffer().nbytes, frames[0].nbytes, None)


def _recorder(frames: list[np.ndarray], codec: str, folder: Path) -> str:
    """Through the recorder itself: its thread's processor time per frame (encode + write), then the decode."""
    said: list[str] = []
    camera = Path(__file__).resolve().parent.parent / "ipt" / "config" / "camera.yaml"
    writer = FrameLogWriter(
        folder, {}, camera, say=said.append, codec=codec, max_mb=1e6, max_s=1e6, queue_frames=len(frames)
    )
    for k, f in enumerate(frames):
        writer.add(CapturedFrame(k, round(k / FPS * 1e6), f))
    writer.close()
    assert writer.frames == len(frames), said  # a queue as long as the run: nothing lost
    assert writer.lost == 0, said
    size = (folder / FRAMES_NAME).stat().st_size
    t0 = time.process_time()
    n = sum(e.image is not None for e in FrameLog(folder).events())
    decode_ms = 1e3 * (time.process_time() - t0) / n
    return _row(f"recorder {codec}", writer.encode_s, writer.frames, size, frames[0].nbytes, decode_ms)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("recording", type=Path)
    p.add_argument("--repeat", type=int, default=5, help="play the frames this many times (default 5)")
    p.add_argument("--out", type=Path, help="folder for the recorder's files (default: a temporary one)")
    args = p.parse_args(argv)
    frames = _frames(args.recording) * args.repeat
    h, w = frames[0].shape
    print(f"{len(frames)} luma frames of {w}x{h} ({frames[0].nbytes} bytes each), {FPS:g} FPS")
    print("| codec | CPU ms/frame | kB/frame | ratio | MB/s at 120 FPS | decode ms/frame |")
    print("|---|---|---|---|---|---|")
    print(_codec(frames, "raw (bytes only)", lambda f: f.tobytes()))
    print(_codec(frames, "zlib level 1", lambda f: zlib.compress(f.tobytes(), 1)))
    print(_ffv1(frames))
    with tempfile.TemporaryDirectory(dir=args.out) as tmp:
        for codec in ("raw", "zstd"):
            print(_recorder(frames, codec, Path(tmp) / codec))
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
