"""The GPU path on Mesa's software renderer (llvmpipe, through EGL): the same frames as the CPU path, bit for
bit, offscreen and in the window (SDL's offscreen video driver); the fallback to the CPU when it cannot start.

No GPU is needed: llvmpipe runs the same shader on the CPU. The tests need moderngl (dev extra) and Mesa's
EGL and software renderer (libegl1, libegl-mesa0, libgl1-mesa-dri; .ci/run installs them)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from ipt.config.models import ArenaConfig
from ipt.sender.content import GeneratedScene
from ipt.sender.gpu import GlPhaseRenderer, GlWindowSink, GpuError, GpuModulator, render_phases, standalone_context
from ipt.sender.modulator import IptModulator
from ipt.sender.pairtable import PairTable, default_cache_dir
from ipt.sender.photos import PanningPhotoScene
from ipt.sender.server import run_sender
from ipt.tagmap import grid_tag_map

U8 = npt.NDArray[np.uint8]
DELTA_L, ALLOWANCE = 4.0, 2.2  # the shipped arena's: its table is in the tests' cache (conftest)
ARENA = ArenaConfig.model_validate(
    {
        "projector": {"width_px": 320, "height_px": 288, "rate_hz": 60},
        "screen": {"width_m": 1.0, "height_m": 0.9},
        "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
        "modulation": {"delta_l": DELTA_L, "clip_allowance_l8": ALLOWANCE},
    }
)


def _gpu_modulator(mask: npt.NDArray[np.int8]) -> GpuModulator:
    gpu = GpuModulator(mask, DELTA_L, ALLOWANCE)
    gpu.complete_table(default_cache_dir(), lambda _: None)
    return gpu


def _frames(shape: tuple[int, int]) -> list[U8]:
    h, w = shape
    rng = np.random.default_rng(0)
    corners = np.array([[a, b, c] for a in (0, 255) for b in (0, 255) for c in (0, 255)], np.uint8)
    card = np.repeat(np.repeat(corners[None], h, axis=0), w // 8 + 1, axis=1)[:, :w]
    return [
        rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
        np.ascontiguousarray(card),
        PanningPhotoScene(w, h, seed=3).frame(40, 30.0),
        GeneratedScene(w, h).frame(5, 30.0),
    ]


def test_the_shader_makes_the_cpu_path_s_frames_bit_for_bit() -> None:
    rng = np.random.default_rng(1)
    mask = rng.integers(-1, 2, (288, 320)).astype(np.int8)
    gpu = _gpu_modulator(mask)
    cpu = IptModulator(mask, DELTA_L, clip_allowance_l8=ALLOWANCE)
    ctx = standalone_context()
    try:
        renderer = GlPhaseRenderer(ctx, mask, gpu.pairs.table)
        for k, rgb in enumerate(_frames(mask.shape)):
            plus, minus = render_phases(ctx, renderer, rgb)
            want = cpu.phases(rgb)
            assert np.array_equal(plus, want[0]), k
            assert np.array_equal(minus, want[1]), k
    finally:
        ctx.release()


def test_the_gpu_path_needs_the_whole_table_and_the_right_frames() -> None:
    mask = np.zeros((48, 64), np.int8)
    ctx = standalone_context()
    try:
        with pytest.raises(GpuError, match="entries"):
            GlPhaseRenderer(ctx, mask, np.zeros(10, np.uint64))
        renderer = GlPhaseRenderer(ctx, mask, np.zeros(1 << 24, np.uint64))
        with pytest.raises(GpuError, match="expected a 64x48 RGB frame"):
            renderer.upload(np.zeros((48, 63, 3), np.uint8))
    finally:
        ctx.release()
    lazy = GpuModulator(mask, DELTA_L, 3.3)  # a table nobody completed
    assert not lazy.table_complete
    with pytest.raises(GpuError, match="must be complete"):
        GlWindowSink(lazy).open()
    assert isinstance(lazy.pairs, PairTable)


@pytest.mark.asyncio
async def test_the_gpu_window_shows_the_sender_s_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SDL_VIDEODRIVER", "offscreen")  # SDL's headless driver, with GL through EGL
    mask = grid_tag_map(ARENA).render_mask()
    gpu = _gpu_modulator(mask)
    sink = GlWindowSink(gpu, fullscreen=False, rate_hz=60.0, capture=True)
    assert sink.open()  # the renderer's name: llvmpipe here, a GPU's where there is one
    scene = GeneratedScene(320, 288)
    lines: list[str] = []
    stats = await run_sender(
        ARENA,
        sink,
        scene,
        frames=8,
        listen=None,
        log=lines.append,
        install_signal_handlers=False,
        modulator=gpu,  # type: ignore[arg-type]
    )
    assert stats.frames == 8
    assert len(sink.captured) == 8
    cpu = IptModulator(mask, DELTA_L, clip_allowance_l8=ALLOWANCE)
    for j, frame in enumerate(sink.captured):
        plus, minus = cpu.phases(scene.frame(j // 2, 30.0))
        assert np.array_equal(frame, plus if j % 2 == 0 else minus), j
    assert stats.pacing is not None
    assert stats.pacing["presents"] == 8
    assert "repeated_vsyncs=" in lines[-1]


def _sender(*args: str, driver: str, cache: Path) -> subprocess.CompletedProcess[str]:
    env = {"SDL_VIDEODRIVER": driver, "SDL_AUDIODRIVER": "dummy", "XDG_CACHE_HOME": str(cache)}
    return subprocess.run(
        [sys.executable, "-m", "ipt.sender.cli", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **env},
    )


def test_ipt_sender_gpu_and_its_fallback(tmp_path: Path, xdg_cache_home: Path) -> None:
    arena = tmp_path / "arena.yaml"
    arena.write_text(
        "projector: {width_px: 320, height_px: 288, rate_hz: 60}\nscreen: {width_m: 1.0, height_m: 0.9}\n"
        "tag_map: {rows: 2, cols: 2, tag_size_px: 64}\nmodulation: {delta_l: 4, clip_allowance_l8: 2.2}\n",
        encoding="utf-8",
    )
    common = (
        "--config",
        str(arena),
        "--sink",
        "window",
        "--windowed",
        "--gpu",
        "--frames",
        "6",
        "--listen",
        "127.0.0.1:0",
    )
    on_gpu = _sender(*common, driver="offscreen", cache=xdg_cache_home)
    assert on_gpu.returncode == 0, on_gpu.stderr
    assert "ipt-sender: the GPU makes the phases (" in on_gpu.stderr
    assert "sink window (phases on the GPU)" in on_gpu.stderr
    assert "frames=6 " in on_gpu.stderr.splitlines()[-1]
    # No OpenGL in SDL's dummy driver: one line, and the CPU makes the phases.
    fallback = _sender(*common, driver="dummy", cache=xdg_cache_home)
    assert fallback.returncode == 0, fallback.stderr
    said = [ln for ln in fallback.stderr.splitlines() if "GPU" in ln]
    assert len(said) == 1, fallback.stderr
    assert said[0].startswith("ipt-sender: the GPU path cannot start (")
    assert said[0].endswith("; the CPU makes the phases")
    assert "frames=6 " in fallback.stderr.splitlines()[-1]
    wrong = _sender("--config", str(arena), "--sink", "null", "--gpu", driver="dummy", cache=xdg_cache_home)
    assert wrong.returncode == 2
    assert "error: --gpu is for --sink window (the GPU draws straight into the window)" in wrong.stderr
