"""The receiver's kernels built ahead of time into a plain extension module, which loads without numba.

Through numba, every process pays for its kernels before its first pair: importing numba and llvmlite, setting
up numba's compiler target and loading each kernel from its disk cache (0.35 s of processor time here, several
times that on a Pi), and each call then goes through numba's dispatcher. ``ipt-receiver warm``, once it has
filled numba's cache, builds the same kernels again with numba's ahead-of-time compiler (``numba.pycc``: LLVM,
then the system's C compiler for the module's glue) into ``ipt_kernels_<key>`` in ``$NUMBA_CACHE_DIR``, one
function per kernel for the argument types the pipeline passes (those numba's dispatchers hold after the warm
calls). A process that finds the module of its key loads it in a few milliseconds, without importing numba;
the results are the same to the bit (the same LLVM, the same code; the poses of whole replays compared).

The key (:func:`key`) covers what the module depends on: the receiver core's sources, numba's, llvmlite's,
numpy's and Python's versions (``kernelstamp.stamp_text``) and the processor (the module is built for the machine's own
CPU, as numba's JIT compiles for it: a module built on a Pi 5 is not loaded on a Pi 4).

An exported function converts its arguments without checking them (a float32 array where it was built for an
8-bit one is read as bytes, or ends the process), so :func:`fits` checks each call against the types it was
built for, and a call that does not fit goes to numba's JIT (:mod:`ipt.receiver.core.kernels`). Where no C
compiler is, the build fails with one line and the kernels run through numba's cache as before.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import importlib.machinery
import importlib.util
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from ipt.receiver.core.kernelstamp import stamp_text

PREFIX = "ipt_kernels_"
"""The built module's name is this and the key; its argument types are beside it in ``<name>.json``."""
_SCALARS: dict[str, tuple[type, ...]] = {
    "int": (int, np.integer),
    "float": (float, int, np.floating, np.integer),
    "bool": (bool, np.bool_),
}
"""What a scalar argument built as each kind accepts (what the exported function converts exactly)."""


class KernelBuildError(Exception):
    """The kernels could not be built ahead of time (no C compiler, no numba.pycc, an argument type it cannot
    check): one line, the kernels then run through numba's cache."""


@dataclass(frozen=True)
class Signature:
    """The arguments an exported kernel was built for: which are arrays (their dtype and dimensions, C-contiguous,
    aligned, writeable) and which scalars (their kind, see ``_SCALARS``)."""

    count: int
    arrays: tuple[tuple[int, np.dtype[Any], int], ...]
    scalars: tuple[tuple[int, tuple[type, ...]], ...]

    @staticmethod
    def from_json(items: Sequence[Sequence[Any]]) -> Signature:
        arrays: list[tuple[int, np.dtype[Any], int]] = []
        scalars: list[tuple[int, tuple[type, ...]]] = []
        for i, item in enumerate(items):
            if item[0] == "array":
                arrays.append((i, np.dtype(item[1]), int(item[2])))
            else:
                scalars.append((i, _SCALARS[item[0]]))
        return Signature(len(items), tuple(arrays), tuple(scalars))


def fits(args: tuple[Any, ...], signature: Signature) -> bool:
    """Whether ``args`` are exactly what the exported kernel was built for (else it would misread them)."""
    if len(args) != signature.count:
        return False
    for i, dtype, ndim in signature.arrays:
        value = args[i]
        if type(value) is not np.ndarray or value.dtype != dtype or value.ndim != ndim:
            return False
        flags = value.flags
        if not (flags.c_contiguous and flags.aligned and flags.writeable):
            return False
    return all(isinstance(args[i], kinds) for i, kinds in signature.scalars)


def cpu_fingerprint() -> str:
    """What this machine's processor is, for the key (Linux: /proc/cpuinfo's model and feature lines; elsewhere
    the architecture only, and the module is then built for a generic CPU of it, see :func:`build`)."""
    keys = ("model name", "flags", "cpu implementer", "cpu architecture", "cpu variant", "cpu part", "features")
    try:
        text = Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace")
    except OSError:
        return ""
    lines = {line.strip() for line in text.splitlines() if line.split(":", 1)[0].strip().lower() in keys}
    return "\n".join(sorted(lines))


def key() -> str:
    """This installation's and machine's key: a built module is loaded only by the same sources, versions and
    processor."""
    digest = hashlib.sha256((stamp_text() + "\n" + cpu_fingerprint()).encode())
    return digest.hexdigest()[:16]


def module_file(folder: Path, built_key: str) -> Path:
    suffix = importlib.machinery.EXTENSION_SUFFIXES[0]
    return folder / f"{PREFIX}{built_key}{suffix}"


def load(folder: Path) -> tuple[ModuleType, dict[str, Signature]] | None:
    """The kernels built for this key in ``folder`` and their signatures, or None (none built, or a partial or
    unreadable build: numba's JIT then, as without one)."""
    built_key = key()
    path = module_file(folder, built_key)
    try:
        described = json.loads(path.with_name(PREFIX + built_key + ".json").read_text(encoding="utf-8"))
        signatures = {name: Signature.from_json(items) for name, items in described["kernels"].items()}
        spec = importlib.util.spec_from_file_location(PREFIX + built_key, path)
        if spec is None or spec.loader is None:
            return None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except (OSError, ImportError, ValueError, KeyError, TypeError, IndexError):
        return None
    if any(not callable(getattr(module, name, None)) for name in signatures):
        return None
    return module, signatures


def _describe(argtypes: Sequence[Any]) -> list[list[Any]]:
    """numba's argument types as the JSON that :meth:`Signature.from_json` reads; only types :func:`fits` can
    check exactly (C-contiguous arrays of plain numbers, 64-bit integers and floats, booleans)."""
    from numba.core import types
    from numba.np.numpy_support import as_dtype

    described: list[list[Any]] = []
    for t in argtypes:
        if isinstance(t, types.Array) and t.layout == "C" and t.aligned and t.mutable:
            described.append(["array", as_dtype(t.dtype).str, t.ndim])
        elif t == types.int64:
            described.append(["int"])
        elif t == types.float64:
            described.append(["float"])
        elif t == types.boolean:
            described.append(["bool"])
        else:
            raise KernelBuildError(f"an argument of type {t} cannot be checked before a call: not built")
    return described


def build(folder: Path, dispatchers: Mapping[str, Any]) -> Path:
    """Build ``dispatchers`` (numba's, each with the one signature its warm calls compiled) ahead of time into
    ``folder``; the module's path. Other builds there (of older sources or versions) are removed."""
    built_key = key()
    target = module_file(folder, built_key)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # numba.pycc is "pending deprecation"
            import llvmlite.binding as llvm

            pycc: Any = importlib.import_module("numba.pycc")  # (typed loosely: numba's own hints are partial)
            pycc_compiler: Any = importlib.import_module("numba.pycc.compiler")
    except ImportError as exc:
        raise KernelBuildError(f"not built ahead of time: no numba.pycc here ({exc})") from exc
    described: dict[str, list[list[Any]]] = {}
    exports: list[tuple[str, Any, Any]] = []
    for name, dispatcher in dispatchers.items():
        if len(dispatcher.signatures) != 1:
            raise KernelBuildError(f"kernel {name} has {len(dispatcher.signatures)} signatures, not one: not built")
        (argtypes,) = dispatcher.signatures
        described[name] = _describe(argtypes)
        exports.append((name, dispatcher.overloads[argtypes].signature, dispatcher.py_func))
    try:
        folder.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix=".build-", dir=folder))
    except OSError as exc:
        raise KernelBuildError(f"not built ahead of time: cannot write in {folder} ({exc.strerror})") from exc
    flags, temporary, tmpdir = pycc_compiler.Flags, tempfile.tempdir, os.environ.get("TMPDIR")
    try:
        # numba.pycc's scratch folders (the compiler check's, the build's) and the C compiler's own files in the
        # folder this can write, as under the unit (ProtectSystem=strict) only the cache folder may be
        tempfile.tempdir = os.environ["TMPDIR"] = str(work)
        cc = pycc.CC(PREFIX + built_key, source_module=__name__)
        cc.output_dir = str(work)
        cc.verbose = False
        # The machine's own CPU, as numba's JIT compiles for (a generic one where it cannot be told apart).
        cc.target_cpu = llvm.get_host_cpu_name() if cpu_fingerprint() else ""
        for name, signature, py_func in exports:
            cc.export(name, signature)(py_func)

        class _ReleasingTheGil(flags):  # type: ignore[misc, valid-type]
            """As the JIT kernels (``nogil=True``): the capture thread runs while a kernel does."""

            def __init__(self, *args: Any, **kwargs: Any) -> None:
                super().__init__(*args, **kwargs)
                self.release_gil = True

        pycc_compiler.Flags = _ReleasingTheGil
        with warnings.catch_warnings(), open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):
            warnings.simplefilter("ignore")
            cc.compile()
        built = work / Path(cc.output_file).name
        (work / "signatures.json").write_text(json.dumps({"kernels": described}), encoding="utf-8")
        os.replace(work / "signatures.json", target.with_name(PREFIX + built_key + ".json"))
        os.replace(built, target)
    except Exception as exc:  # the C compiler's or LLVM's failure: one line, numba's cache still serves
        text = str(exc).strip()
        install = "install gcc and Python's headers (apt install gcc python3-dev), then ipt-receiver warm --force"
        if "without the compiler" in text:  # numba.pycc's own check for a working C compiler
            why = f"no working C compiler: {install}"
        elif type(exc).__name__ in ("CompileError", "LinkError", "DistutilsExecError"):
            why = f"the C compiler failed ({text.splitlines()[0] if text else ''}): {install}"
        else:
            why = f"{type(exc).__name__}: {text.splitlines()[0] if text else ''}"
        raise KernelBuildError(f"not built ahead of time ({why}); numba's cache serves") from exc
    finally:
        pycc_compiler.Flags, tempfile.tempdir = flags, temporary
        if tmpdir is None:
            os.environ.pop("TMPDIR", None)
        else:
            os.environ["TMPDIR"] = tmpdir
        shutil.rmtree(work, ignore_errors=True)
    for old in folder.glob(PREFIX + "*"):
        if not old.name.startswith(PREFIX + built_key):
            with contextlib.suppress(OSError):
                old.unlink()
    return target
