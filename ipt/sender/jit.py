"""Compiling the colour pairs' kernels with numba, and the three LLVM operations they need.

:func:`jit` compiles a pure-Python function (nogil, cached on disk where it can); where numba cannot run
(not installed, or executable memory forbidden) it gives a stand-in that raises :class:`JitError` and
says why in :data:`JIT_UNAVAILABLE`, so that everything else (the ``paper`` profile) still imports.
:func:`intrinsics` makes the unaligned 32-bit load and store and the prefetch of the frame kernels
(:mod:`ipt.sender.framekernel`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ipt.errors import IptError


class JitError(IptError):
    """A compiled kernel was called where numba cannot compile."""


JIT_UNAVAILABLE: str | None = None
"""Why numba cannot compile here (e.g. memory that is both writable and executable is forbidden, as
under systemd's MemoryDenyWriteExecute), or None if it can; set by the first :func:`jit` that finds
out. Read it as ``ipt.sender.pairs.JIT_UNAVAILABLE``, which is settled once the kernels are made."""


def _unavailable(*_args: Any) -> Any:
    raise JitError(f"the ipt modulation profile needs numba, but {JIT_UNAVAILABLE}")


def jit(fn: Callable[..., Any]) -> Any:
    """``fn`` compiled by numba (nogil, so worker threads run in parallel); cached on disk if possible.

    Where numba cannot run, a stand-in that raises :class:`JitError` when called, so that the module
    (and the ``paper`` profile) still imports.
    """
    global JIT_UNAVAILABLE
    try:
        import numba
    except (ImportError, OSError) as exc:  # OSError: llvmlite refused executable memory
        JIT_UNAVAILABLE = f"numba cannot compile here ({type(exc).__name__}: {exc})"
        return _unavailable
    try:
        return numba.njit(nogil=True, cache=True)(fn)
    except RuntimeError:  # no writable cache location: compile in every process
        return numba.njit(nogil=True)(fn)


def intrinsics() -> tuple[Any, Any, Any]:
    """Three LLVM operations numba does not offer: an unaligned 32-bit load and store at a byte offset of a
    uint8 array, and a prefetch of an array element (no bounds checks: the kernel keeps them in range)."""
    try:
        from llvmlite import ir
        from numba import types
        from numba.core import cgutils as numba_cgutils
        from numba.extending import intrinsic
    except (ImportError, OSError):
        return _unavailable, _unavailable, _unavailable
    cgutils: Any = numba_cgutils  # untyped

    def pointer(context: Any, builder: Any, array_type: Any, array: Any, index: Any) -> Any:
        ary = context.make_array(array_type)(context, builder, array)
        return cgutils.get_item_pointer(context, builder, array_type, ary, [index], wraparound=False)

    @intrinsic
    def load_u32(typingctx: Any, array: Any, index: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            ptr = pointer(context, builder, signature.args[0], args[0], args[1])
            return builder.load(builder.bitcast(ptr, ir.IntType(32).as_pointer()), align=1)

        return types.uint32(array, index), codegen

    @intrinsic
    def store_u32(typingctx: Any, array: Any, index: Any, value: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            ptr = pointer(context, builder, signature.args[0], args[0], args[1])
            word = context.cast(builder, args[2], signature.args[2], types.uint32)
            builder.store(word, builder.bitcast(ptr, ir.IntType(32).as_pointer()), align=1)
            return context.get_dummy_value()

        return types.void(array, index, value), codegen

    @intrinsic
    def prefetch(typingctx: Any, array: Any, index: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            ptr = pointer(context, builder, signature.args[0], args[0], args[1])
            i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
            fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
            fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0i8")
            # read, keep in all cache levels, data cache
            builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
            return context.get_dummy_value()

        return types.void(array, index), codegen

    return load_u32, store_u32, prefetch
