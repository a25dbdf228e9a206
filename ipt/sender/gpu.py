"""The GPU path: the ``ipt`` phases made by a fragment shader and drawn straight into the window.

The CPU path (:class:`~ipt.sender.modulator.IptModulator` into :class:`~ipt.sender.display.WindowSink`)
writes both phases of every input frame in memory (24 MB at 1920x2160) and the window copies each
output frame to the GPU. Here the input frame goes to the GPU once, as a texture, and for every projector
frame a fragment shader looks each tag pixel's pair up in the complete colour table (all 2^24 entries as
a 4096x4096 RG32UI texture, 128 MB of video memory) and writes that phase into the window's back buffer.
It is the same table as the CPU path's, so the frames are the CPU path's bit for bit (the tests check
it on Mesa's software renderer, llvmpipe). The CPU is left with the content and the overlay.

- :class:`GpuModulator` stands where a modulator does in the sender: it only resizes, and hands on the
  input frame with the phase each output frame wants (:class:`GpuFrame`).
- :class:`GlPhaseRenderer` holds the GL objects on one context and draws a phase into a framebuffer
  (the window's, or an offscreen one: :func:`render_phases`).
- :class:`GlWindowSink` is the window: pygame-ce with an OpenGL 3.3 context, vsync on, every flip timed
  like :class:`~ipt.sender.display.WindowSink`. All its SDL and GL calls run on one thread of its own, so
  that the context stays current there whatever thread the sender shows frames from.

moderngl is an optional dependency (``pip install 'ipt[gpu]'``). Anything that keeps the GPU path from
starting (no moderngl, no OpenGL 3.3, a shader or texture the driver refuses) is a :class:`GpuError` with
one line saying what; ``ipt-sender --gpu`` then modulates on the CPU instead.
"""

from __future__ import annotations

import math
import os
import queue
import sys
import threading
import time
import warnings
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.sender.display import PresentClock
from ipt.sender.modulator import resize_to
from ipt.sender.pairs import COLOURS
from ipt.sender.pairtable import PairTable, pair_table

U8 = npt.NDArray[np.uint8]

TABLE_SIDE: Final = 4096
"""The colour table as a square texture: entry ``i`` at texel (i mod 4096, i div 4096)."""

_NEEDS_MODERNGL: Final = "the GPU path needs moderngl: pip install 'ipt[gpu]'"

_VERTEX: Final = """
#version 330
in vec2 pos;
void main() { gl_Position = vec4(pos, 0.0, 1.0); }
"""

# texelFetch reads exact integers from the integer textures; the output code k is written as k / 255 into
# an 8-bit normalised buffer, which stores round(k / 255 * 255) = k. Image row 0 is the top of the picture,
# the framebuffer's row 0 its bottom.
_FRAGMENT: Final = """
#version 330
uniform usampler2D frame;
uniform isampler2D mask;
uniform usampler2D pairs;
uniform int phase;
uniform int height;
out vec4 colour;
void main() {
    ivec2 p = ivec2(int(gl_FragCoord.x), height - 1 - int(gl_FragCoord.y));
    uvec3 c = texelFetch(frame, p, 0).rgb;
    int m = texelFetch(mask, p, 0).r;
    uvec3 o = c;
    if (m != 0) {
        uint i = c.r | (c.g << 8) | (c.b << 16);
        uvec2 e = texelFetch(pairs, ivec2(int(i & 4095u), int(i >> 12)), 0).rg;
        uint up = e.x & 0xFFFFFFu;
        uint down = (e.x >> 24) | ((e.y & 0xFFFFu) << 8);
        uint v = (m * phase > 0) ? up : down;
        o = uvec3(v & 255u, (v >> 8) & 255u, (v >> 16) & 255u);
    }
    colour = vec4(vec3(o) / 255.0, 1.0);
}
"""


class GpuError(IptError):
    """The GPU path cannot start or has failed: no moderngl, no OpenGL 3.3, or the driver refused."""


def _moderngl() -> Any:
    try:
        import moderngl
    except ImportError:
        raise GpuError(_NEEDS_MODERNGL) from None
    return moderngl


@dataclass(frozen=True)
class GpuFrame:
    """An output frame of the GPU path before it is drawn: the input frame (overlay on it) and the phase."""

    rgb: U8
    sign: int


class GpuModulator:
    """The ``ipt`` profile's stand-in for the GPU path: frames out are :class:`GpuFrame`, made into pixels
    by :class:`GlWindowSink`. Its colour table is the CPU path's (:func:`~ipt.sender.pairtable.pair_table`)."""

    profile = "ipt"

    def __init__(self, mask: npt.NDArray[np.int8], delta_l: float, clip_allowance_l8: float = 0.0) -> None:
        if mask.ndim != 2 or mask.dtype != np.int8:
            raise GpuError(f"the mask must be an H×W int8 array, got {mask.shape} {mask.dtype}")
        self.mask = np.ascontiguousarray(mask)
        self.height_px, self.width_px = mask.shape
        self.delta_l = float(delta_l)
        self.clip_allowance_l8 = float(clip_allowance_l8)
        self.pairs: PairTable = pair_table(self.delta_l, self.clip_allowance_l8)

    @property
    def table_complete(self) -> bool:
        """Every colour's pair is in the table (the shader needs them all)."""
        return self.pairs.complete

    def complete_table(self, cache_dir: os.PathLike[str] | None, log: Callable[[str], None]) -> str:
        """See :meth:`ipt.sender.modulator.IptModulator.complete_table`."""
        return self.pairs.complete_with_cache(cache_dir, log)

    def phases(self, frame_rgb: U8, out: Any = None) -> tuple[GpuFrame, GpuFrame]:
        """The two output frames of an input frame, to be drawn by :class:`GlWindowSink` (``out`` unused)."""
        rgb = np.ascontiguousarray(resize_to(frame_rgb, self.width_px, self.height_px))
        return GpuFrame(rgb, 1), GpuFrame(rgb, -1)


class GlPhaseRenderer:
    """The GL objects of the GPU path on context ``ctx`` (made current on the calling thread): the mask and
    the complete colour table as textures, the program, and a texture for input frames."""

    def __init__(self, ctx: Any, mask: npt.NDArray[np.int8], table: npt.NDArray[np.uint64]) -> None:
        mgl = _moderngl()
        if table.shape != (COLOURS,):
            raise GpuError(f"the colour table must have {COLOURS} entries, got {table.shape}")
        self.ctx = ctx
        self.height_px, self.width_px = mask.shape
        w, h = self.width_px, self.height_px
        try:
            if ctx.version_code < 330:
                raise GpuError(f"OpenGL {ctx.version_code / 100:.1f} is too old (3.3 is needed)")
            limit = int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 0))
            if limit < max(TABLE_SIDE, w, h):
                raise GpuError(f"textures are limited to {limit} px here, {max(TABLE_SIDE, w, h)} are needed")
            self.program = ctx.program(vertex_shader=_VERTEX, fragment_shader=_FRAGMENT)
            quad = np.array([-1, -1, 1, -1, -1, 1, 1, 1], np.float32)
            self.vbo = ctx.buffer(quad.tobytes())
            self.vao = ctx.vertex_array(self.program, [(self.vbo, "2f", "pos")])
            nearest = (mgl.NEAREST, mgl.NEAREST)  # integer textures sample nothing else
            self.mask_texture = ctx.texture((w, h), 1, np.ascontiguousarray(mask).tobytes(), dtype="i1")
            table_words = np.ascontiguousarray(table).view(np.uint32)  # little-endian: low word first
            self.table_texture = ctx.texture((TABLE_SIDE, TABLE_SIDE), 2, table_words.tobytes(), dtype="u4")
            self.frame_texture = ctx.texture((w, h), 3, dtype="u1")
            for texture in (self.mask_texture, self.table_texture, self.frame_texture):
                texture.filter = nearest
            self.program["frame"] = 0
            self.program["mask"] = 1
            self.program["pairs"] = 2
            self.program["height"] = h
        except GpuError:
            raise
        except Exception as exc:  # moderngl.Error and the driver's own: the GPU path cannot start
            raise GpuError(f"the GPU refused the phase shader or its textures ({exc})") from None
        self._uploaded: U8 | None = None

    def upload(self, rgb: U8) -> None:
        """Make ``rgb`` (H×W×3 uint8, the projector's size) the input frame (only if it is another array)."""
        if rgb is self._uploaded:
            return
        if rgb.shape != (self.height_px, self.width_px, 3) or rgb.dtype != np.uint8:
            raise GpuError(f"expected a {self.width_px}x{self.height_px} RGB frame, got {rgb.shape} {rgb.dtype}")
        self.frame_texture.write(np.ascontiguousarray(rgb).tobytes())
        self._uploaded = rgb

    def draw(self, sign: int, framebuffer: Any) -> None:
        """Draw the phase ``sign`` of the input frame into ``framebuffer``."""
        framebuffer.use()
        self.ctx.viewport = (0, 0, self.width_px, self.height_px)
        self.frame_texture.use(location=0)
        self.mask_texture.use(location=1)
        self.table_texture.use(location=2)
        self.program["phase"] = 1 if sign > 0 else -1
        self.vao.render(_moderngl().TRIANGLE_STRIP)

    def read(self, framebuffer: Any) -> U8:
        """The framebuffer's pixels as an H×W×3 image (row 0 at the top)."""
        data = framebuffer.read(viewport=(0, 0, self.width_px, self.height_px), components=3, alignment=1)
        pixels = np.frombuffer(data, np.uint8).reshape(self.height_px, self.width_px, 3)
        return np.ascontiguousarray(pixels[::-1])


def standalone_context() -> Any:
    """An offscreen OpenGL context (EGL: a GPU, or Mesa's software renderer without one)."""
    mgl = _moderngl()
    try:
        return mgl.create_standalone_context(require=330, backend="egl")
    except Exception as exc:
        raise GpuError(
            f"no OpenGL 3.3 context could be made ({exc}); without a GPU, Mesa's software renderer gives one "
            "(Debian: apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri)"
        ) from None


def render_phases(ctx: Any, renderer: GlPhaseRenderer, rgb: U8) -> tuple[U8, U8]:
    """Both phases of ``rgb`` drawn offscreen on ``ctx`` and read back (what the window would show)."""
    w, h = renderer.width_px, renderer.height_px
    fbo = ctx.framebuffer(color_attachments=[ctx.texture((w, h), 4)])
    try:
        renderer.upload(rgb)
        out = []
        for sign in (1, -1):
            renderer.draw(sign, fbo)
            out.append(renderer.read(fbo))
        return out[0], out[1]
    finally:
        fbo.release()


class _GlThread:
    """One daemon thread running calls in order: SDL windows and GL contexts belong to the thread that made
    them, so every call on them goes through here."""

    def __init__(self) -> None:
        self._jobs: queue.SimpleQueue[tuple[Future[Any], Callable[[], Any]] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="ipt-gl", daemon=True)
        self._thread.start()

    def call(self, fn: Callable[[], Any]) -> Any:
        fut: Future[Any] = Future()
        self._jobs.put((fut, fn))
        return fut.result()

    def stop(self) -> None:
        self._jobs.put(None)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            fut, fn = job
            try:
                fut.set_result(fn())
            except BaseException as exc:
                fut.set_exception(exc)


class GlWindowSink:
    """The projector window of the GPU path (see the module doc); frames are :class:`GpuFrame`.

    :meth:`open` makes the window, the context and the textures (call it before frames are due, with the
    colour table complete); a :class:`GpuError` from it means the GPU path cannot be used here. ``capture``
    keeps a copy of each frame drawn, read back before the flip (for tests).
    """

    name = "window"
    retries = False  # a lost GL context is not opened again: the run ends, and systemd restarts it
    paced = True
    threaded = True
    borrows = False
    close_timeout_s = 0.5

    def __init__(
        self,
        modulator: GpuModulator,
        display_index: int = 0,
        fullscreen: bool = True,
        title: str = "ipt-sender",
        rate_hz: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
        capture: bool = False,
    ) -> None:
        if display_index < 0:
            raise GpuError(f"display index must be >= 0, got {display_index}")
        self.modulator = modulator
        self.display_index = display_index
        self.fullscreen = fullscreen
        self.title = title
        self.rate_hz = rate_hz
        self.clock = clock
        self.capture = capture
        self.captured: list[U8] = []
        self.presents = PresentClock(1.0 / rate_hz)
        self.renderer: GlPhaseRenderer | None = None
        self._gl = _GlThread()
        self._pg: Any = None
        self._ctx: Any = None
        self._quit = False
        self._closed = False

    def pacing(self) -> dict[str, Any]:
        """What the flips showed (see :class:`~ipt.sender.display.PresentClock`)."""
        return self.presents.summary()

    def open(self) -> str:
        """Open the window and set up the GPU (on the GL thread); returns the renderer's name."""
        if not self.modulator.table_complete:
            raise GpuError("the colour table must be complete before the GPU path starts")
        try:
            result: str = self._gl.call(self._open)
        except GpuError:
            self._gl.call(self._release)
            raise
        return result

    def _open(self) -> str:
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        try:
            import pygame
        except ImportError:
            raise GpuError("the window needs pygame-ce: pip install 'ipt[display]'") from None
        mgl = _moderngl()
        pg: Any = pygame
        self._pg = pg
        w, h = self.modulator.width_px, self.modulator.height_px
        try:
            pg.display.init()
            count = pg.display.get_num_displays()
            if self.display_index >= count:
                raise GpuError(f"display {self.display_index} does not exist ({count} found)")
            pg.display.set_caption(self.title)
            pg.display.gl_set_attribute(pg.GL_CONTEXT_MAJOR_VERSION, 3)
            pg.display.gl_set_attribute(pg.GL_CONTEXT_MINOR_VERSION, 3)
            pg.display.gl_set_attribute(pg.GL_CONTEXT_PROFILE_MASK, pg.GL_CONTEXT_PROFILE_CORE)
            flags = pg.OPENGL | pg.DOUBLEBUF | (pg.FULLSCREEN if self.fullscreen else 0)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                pg.display.set_mode((w, h), flags, display=self.display_index, vsync=1)
            for warning in caught:
                print(f"ipt-sender: window: {warning.message}", file=sys.stderr)
            if self.fullscreen:
                pg.mouse.set_visible(False)
        except pg.error as exc:
            raise GpuError(f"cannot open an OpenGL window on display {self.display_index}: {exc}") from None
        try:
            self._ctx = mgl.create_context(require=330)
        except Exception as exc:
            raise GpuError(f"no OpenGL 3.3 context on display {self.display_index} ({exc})") from None
        self.renderer = GlPhaseRenderer(self._ctx, self.modulator.mask, self.modulator.pairs.table)
        hz = _refresh_hz(pg)
        if hz is not None and abs(hz - self.rate_hz) > 0.02 * self.rate_hz:
            self.presents = PresentClock(1.0 / hz)
        return str(self._ctx.info.get("GL_RENDERER", "unknown renderer"))

    def show(self, frame: GpuFrame, index: int) -> None:
        if self._closed:
            raise GpuError("show() after the window was closed")
        if self.renderer is None:
            raise GpuError("the GPU window was not opened")
        self._gl.call(lambda: self._show(frame))

    def _show(self, frame: GpuFrame) -> None:
        pg, renderer = self._pg, self.renderer
        assert renderer is not None
        for event in pg.event.get():
            if event.type == pg.QUIT or (event.type == pg.KEYDOWN and event.key in (pg.K_ESCAPE, pg.K_q)):
                self._quit = True
        try:
            renderer.upload(frame.rgb)
            renderer.draw(frame.sign, self._ctx.screen)
            if self.capture:
                self.captured.append(renderer.read(self._ctx.screen))
            pg.display.flip()  # with vsync: waits for the next refresh
        except GpuError:
            raise
        except Exception as exc:
            raise GpuError(f"the GPU window failed ({exc})") from None
        self.presents.add(self.clock())

    def _release(self) -> None:
        if self._ctx is not None:
            self._ctx.release()
            self._ctx = None
        if self._pg is not None:
            self._pg.display.quit()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._gl.call(self._release)
        finally:
            self._gl.stop()

    def abort(self) -> None:
        self.close()

    @property
    def quit_requested(self) -> bool:
        return self._quit


def _refresh_hz(pg: Any) -> float | None:
    try:
        hz = float(pg.display.get_current_refresh_rate())
    except (AttributeError, pg.error):
        return None
    return hz if math.isfinite(hz) and hz > 0 else None
