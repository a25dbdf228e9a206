"""The receiver's inner loops, compiled (numba): the map tracker's, the alignment's and the pair difference's.

- **The tracker** (:mod:`ipt.receiver.core.track`): one Gauss-Newton step projects a few hundred edge samples,
  reads the difference image along each sample's normal and finds the step's sub-pixel offset. Written as
  numpy array operations, that is some sixty small array calls per step (~1 ms at 640×360, most of it call
  overhead); here it is two loops over the samples (~0.1 ms). The difference's noise level
  (:func:`ipt.receiver.core.track.slope_noise`) gathers its sampled slopes here too.
- **The alignment** (:func:`ipt.receiver.core.imagealign.refine_homography`): a Lucas-Kanade step's readings at
  the samples (the earlier frame and its gradients, for the second-order step), residuals and rows of the
  linear system in one pass (:func:`align_system`; it costs what the first-order step did with remap and
  numpy, 1.2–2.2 ms a pair).
- **The pair difference** (:func:`ipt.receiver.core.demodulator.pair_difference`): the brightness match's samples
  and the difference, its valid pixels and its changed ones in one pass over the image each
  (:func:`sample_pair`, :func:`difference_pass`) instead of numpy's eight.

The loops themselves, as plain Python, live with what they are for (:mod:`~ipt.receiver.core.trackkernels`,
:mod:`~ipt.receiver.core.alignkernels`, :mod:`~ipt.receiver.core.diffkernels`); this module compiles them
(:func:`ensure`, :func:`warm`) and is how the stages call them.

Where ``ipt-receiver warm`` has built them ahead of time (:mod:`~ipt.receiver.core.kernelbuild`: a plain extension
module in ``$NUMBA_CACHE_DIR``), they are loaded from there without importing numba, and a call whose arguments
are not what they were built for goes to numba instead.

Pure: arrays in, arrays out. Where numba cannot compile (no executable memory), the tracker's kernels run as
plain Python (correct, only slower) and the others as the numpy operations they replace (a pass over every
pixel in plain Python would take seconds).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ipt.receiver.core import alignkernels, diffkernels, sparsekernels, sparseloop, trackkernels
from ipt.receiver.core.kernelbuild import Signature, fits

COMPILED = True
"""Whether the kernels below are compiled (False: numba is unavailable and they run as Python, or as numpy
where they have a fallback); known once :func:`ensure` has run."""

NOT_COMPILED_BECAUSE: str | None = None
"""Why the kernels are not compiled (numba's import error), or None."""
NOT_CACHED_BECAUSE: str | None = None
"""Why numba keeps no disk cache of the kernels (no writable cache folder: set ``NUMBA_CACHE_DIR``), or None."""
AHEAD: str | None = None
"""The module the kernels were loaded from, built ahead of time by ``ipt-receiver warm``, or None (numba's)."""

_lock = threading.Lock()
_ready = threading.Event()
_dispatchers: list[Any] = []
"""numba's dispatcher of every compiled kernel, the helpers included (for :func:`status`)."""


class _Kernel:
    """A kernel, compiled on first use (or by :func:`ensure`, e.g. in :func:`warm_in_background`), so that
    importing this module does not import numba (a quarter of a second) on a daemon's start-up path."""

    def __init__(self, fn: Callable[..., Any], fallback: Callable[..., Any] | None = None) -> None:
        self.py_func = fn
        self.fallback = fallback
        """What runs where numba cannot compile, if not ``fn`` itself: the same result with numpy."""
        self.compiled: Any = None
        self.ahead: Any = None
        """The kernel built ahead of time (:func:`ensure`), for arguments that fit ``signature`` only."""
        self.signature: Signature | None = None
        self.not_fitting = 0
        """Calls whose arguments were not what the ahead-of-time build is for (they went to numba)."""

    def __call__(self, *args: Any) -> Any:
        if self.ahead is not None and fits(args, self.signature):  # type: ignore[arg-type]
            return self.ahead(*args)
        if self.compiled is None:
            ensure()
            if self.ahead is not None and fits(args, self.signature):  # type: ignore[arg-type]
                return self.ahead(*args)
            self._compile()
        if self.ahead is not None:
            self.not_fitting += 1
        return self.compiled(*args)

    def _compile(self) -> None:
        with _lock:
            _compile_dense()


def _jit(fn: Callable[..., Any], inline: bool = False) -> Any:
    """``fn`` compiled by numba (cached on disk where possible), else ``fn`` itself; ``inline``: compiled into
    its callers (a small helper called per pixel: a call that passes arrays costs their reference counts)."""
    global COMPILED, NOT_COMPILED_BECAUSE, NOT_CACHED_BECAUSE
    try:
        import numba
    except (ImportError, OSError) as exc:  # OSError: llvmlite refused executable memory
        COMPILED = False
        NOT_COMPILED_BECAUSE = f"{type(exc).__name__}: {exc}"
        return fn
    options: dict[str, Any] = {"nogil": True, "inline": "always"} if inline else {"nogil": True}
    try:
        compiled = numba.njit(cache=True, **options)(fn)
    except RuntimeError as exc:  # no writable cache location: compile in every process
        NOT_CACHED_BECAUSE = str(exc)
        compiled = numba.njit(**options)(fn)
    _dispatchers.append(compiled)
    return compiled


def ensure() -> None:
    """Load the kernels, once per process: built ahead of time where ``ipt-receiver warm`` built them for this
    installation (``$NUMBA_CACHE_DIR``), else compiled by numba (or loaded from its disk cache)."""
    with _lock:
        if _ready.is_set():
            return
        if not _load_ahead():
            _compile_dense()
        _ready.set()


def compile_with_numba() -> None:
    """Every kernel compiled by numba (or loaded from its disk cache), whatever was built ahead of time: what
    ``ipt-receiver warm`` fills numba's cache with and then builds ahead from."""
    with _lock:
        _compile_dense()
        _compile_sparse()
        _ready.set()


def _load_ahead() -> bool:
    """The kernels built ahead for this key in ``$NUMBA_CACHE_DIR``, if there: whether they were loaded."""
    global AHEAD
    folder = os.environ.get("NUMBA_CACHE_DIR")
    if not folder:
        return False
    from ipt.receiver.core import kernelbuild

    found = kernelbuild.load(Path(folder))
    if found is None:
        return False
    module, signatures = found
    if set(signatures) != set(BY_NAME):
        return False
    for name, kernel in BY_NAME.items():
        kernel.signature = signatures[name]  # before ``ahead``: a call on another thread reads them unlocked
        kernel.ahead = getattr(module, name)
    AHEAD = str(module.__file__)
    return True


_dense_compiled = False


def _compile_dense() -> None:
    """The dense way's kernels compiled by numba (the caller holds ``_lock``)."""
    global _dense_compiled
    if _dense_compiled:
        return
    # The kernels call bilinear, slopes (which calls bilinear) and system_row: each must be compiled
    # before its callers, and be trackkernels' global when they are.
    trackkernels.bilinear = _jit(trackkernels.bilinear_py)
    trackkernels.slopes = _jit(trackkernels.slopes_py)
    trackkernels.system_row = _jit(trackkernels.system_row_py)
    for kernel in (
        measure,
        peaks,
        band_signs,
        cell_agreement,
        slopes_sampled,
        align_system,
        sample_pair,
        difference_pass,
    ):
        kernel.compiled = _jit(kernel.py_func)
        if not COMPILED and kernel.fallback is not None:
            kernel.compiled = kernel.fallback
    _dense_compiled = True


measure = _Kernel(trackkernels.measure)
peaks = _Kernel(trackkernels.peaks)
band_signs = _Kernel(trackkernels.band_signs)
cell_agreement = _Kernel(trackkernels.cell_agreement)
slopes_sampled = _Kernel(trackkernels.slopes_sampled)
align_system = _Kernel(alignkernels.align_system, alignkernels.align_system_numpy)
sample_pair = _Kernel(diffkernels.sample_pair, diffkernels.sample_pair_numpy)
difference_pass = _Kernel(diffkernels.difference_pass, diffkernels.difference_pass_numpy)


class _SparseKernel(_Kernel):
    """The sparse tracker's kernel (:mod:`ipt.receiver.core.sparse`): compiled (or loaded from the cache) apart
    from the others on its first use, after the first pose (which the dense way finds), so that it adds nothing
    to a daemon's start-up; ``ipt-receiver warm`` compiles it ahead (:func:`warm_sparse`)."""

    def _compile(self) -> None:
        with _lock:
            _compile_dense()  # (numba's availability is known from here on)
            _compile_sparse()


def _compile_sparse() -> None:
    """The sparse tracker's kernels compiled by numba (the caller holds ``_lock``)."""
    if sparse_profiles.compiled is not None:
        return
    # Each helper before its callers, as sparsekernels' global when they compile.
    sparsekernels.distort = _jit(sparsekernels.distort_py, inline=True)
    sparsekernels.distort_point = _jit(sparsekernels.distort_point_py, inline=True)
    sparsekernels.bilinear_u8 = _jit(sparsekernels.bilinear_u8_py, inline=True)
    sparsekernels.project_floor = _jit(sparsekernels.project_floor_py, inline=True)
    sparsekernels.read_profile = _jit(sparsekernels.read_profile_py, inline=True)
    sparsekernels.edge_row = _jit(sparsekernels.edge_row_py, inline=True)
    sparsekernels.detrend = _jit(sparsekernels.detrend_py, inline=True)
    sparsekernels.centred_moments = _jit(sparsekernels.centred_moments_py, inline=True)
    sparsekernels.own_step = _jit(sparsekernels.own_step_py, inline=True)
    sparsekernels.normal = _jit(sparsekernels.normal_py)
    sparsekernels.residuals = _jit(sparsekernels.residuals_py)
    sparsekernels.cholesky_solve = _jit(sparsekernels.cholesky_solve_py)
    solve, mom, prof = (_jit(kernel.py_func) for kernel in (sparse_solve_step, sparse_moments, sparse_profiles))
    # The fit's iterations call the three (:mod:`~ipt.receiver.core.sparseloop`'s globals when it compiles).
    sparseloop.solve_step, sparseloop.moments, sparseloop.profiles = solve, mom, prof
    for name in sparseloop.HELPERS:
        setattr(sparseloop, name, _jit(getattr(sparseloop, name + "_py"), inline=True))
    sparse_iterate.compiled = _jit(sparse_iterate.py_func)
    sparse_solve_step.compiled, sparse_moments.compiled = solve, mom
    sparse_profiles.compiled = prof  # last: the flag


sparse_profiles = _SparseKernel(sparsekernels.profiles)
sparse_moments = _SparseKernel(sparsekernels.moments)
sparse_solve_step = _SparseKernel(sparsekernels.solve_step)
sparse_iterate = _SparseKernel(sparseloop.iterate)


def sparse_iterate_compiled() -> bool:
    """Whether :data:`sparse_iterate` runs compiled (ahead of time, or by numba: compiled now if not yet); else
    :func:`~ipt.receiver.core.sparse.fit_sparse` keeps its own loop around the three kernels."""
    kernel = BY_NAME["sparse_iterate"]  # (the kernel itself, wherever a caller's name for it points)
    if kernel.ahead is not None or kernel.compiled is not None:
        return COMPILED
    ensure()
    if kernel.ahead is None:
        with _lock:
            _compile_dense()
            _compile_sparse()
    return COMPILED


BY_NAME: dict[str, _Kernel] = {
    "measure": measure,
    "peaks": peaks,
    "band_signs": band_signs,
    "cell_agreement": cell_agreement,
    "slopes_sampled": slopes_sampled,
    "align_system": align_system,
    "sample_pair": sample_pair,
    "difference_pass": difference_pass,
    "sparse_profiles": sparse_profiles,
    "sparse_moments": sparse_moments,
    "sparse_solve_step": sparse_solve_step,
    "sparse_iterate": sparse_iterate,
}
"""Every kernel by the name its ahead-of-time build exports it under."""


def warm() -> None:
    """Compile the kernels now (or load them from numba's disk cache: a fraction of a second), so that the
    first frame a camera delivers does not wait seconds for the compiler."""
    image = np.zeros((8, 8), np.float32)
    one = np.zeros((1, 3))
    rt = np.eye(3)
    t = np.array([0.0, 0.0, 1.0])
    k = np.eye(3)
    no_mask = np.zeros((0, 0), np.uint8)
    measure(one, one, np.ones(1), rt, t, k, image, no_mask, 2, 1.0, 2, np.zeros(6))
    peaks(np.zeros((1, 4), np.float32), np.zeros(1, np.int64), np.ones(2), np.ones(1))
    band_signs(np.zeros((1, 4), np.float32), np.zeros(1, np.int64), 2)
    cell_agreement(image, k, rt, t, one, np.zeros(1, np.int64), np.ones(1), np.ones(1, np.bool_), np.ones(2), no_mask)
    slopes_sampled(image, no_mask)
    slopes_sampled(image, np.zeros((8, 8), np.uint8))
    ints = np.zeros(1, np.int64)
    u8 = np.zeros((8, 8), np.uint8)
    sample_pair(u8, u8, u8, u8, 4)
    difference_pass(u8, u8, u8, u8, 1.0, 0.0, 1.0, image, u8.copy(), u8.copy())
    f32 = np.zeros(1, np.float32)
    align_system(
        image, image, image, no_mask, rt, ints, ints, f32, f32, f32, 0.1, 0.5, 3.0, np.zeros((1, 8)), np.zeros(1)
    )


def warm_sparse() -> None:
    """Compile (or load from numba's disk cache) the sparse tracker's kernels now, with the argument types its
    fits pass (the default tracker's: ``ipt-receiver warm`` leaves none to compile in flight). An edge sample out
    of view: no profile is read, the solve finds nothing to solve."""
    one = np.array([[1e3, 1e3, 0.0]])
    eye, t = np.eye(3), np.array([0.0, 0.0, 1.0])
    u8 = np.zeros((8, 8), np.uint8)
    idx, pk, pj, a_rows = sparse_profiles(one, one, eye, t, eye, t, eye, np.zeros(5), u8, u8, 4, 3.0, 3)
    n, width = len(idx), pk.shape[1]
    model = np.zeros(width)
    gram, uy, yy = sparse_moments(pk, pj, np.zeros(n), 1.0, 0.0, model, model, 1.0, np.zeros((n, 2)), False)
    sparse_solve_step(gram, uy, yy, a_rows, np.ones(n, np.bool_), np.zeros(6), 1.0, 0.0, False, width)
    reals, counts, flags = np.ones(10), np.full(9, 4, np.int64), np.ones(4, np.bool_)
    sparse_iterate(
        *(one, one, np.zeros(1), eye.copy(), t.copy(), eye.copy(), t.copy(), eye, np.zeros(5), u8, u8),
        *(np.array([1.0, 0.0]), np.zeros(6), np.zeros(2), np.zeros((2, width)), np.zeros((2, width)), reals, counts),
        flags,
    )


_warming = False


def warm_in_background() -> None:
    """Start :func:`warm` on a thread of its own (once per process): a daemon's start-up (sockets, the
    camera, the AprilTag helper) goes on meanwhile, and the first pair or track waits for it only if it is
    not done."""
    global _warming
    with _lock:
        if _warming or _ready.is_set():
            return
        _warming = True
    threading.Thread(target=warm, name="ipt-kernels", daemon=True).start()
