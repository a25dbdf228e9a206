"""The kernels built ahead of time by ``ipt-receiver warm`` (:mod:`ipt.receiver.core.kernelbuild`): a later
process loads them without numba and poses exactly as numba's kernels do; a call they were not built for goes
to numba; where no C compiler is, warm still succeeds with numba's cache."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from kernelenv import kernel_env, numba_imported, receiver_cli

from ipt.receiver.core import kernelbuild, kernels
from ipt.receiver.core.kernelbuild import Signature, fits


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache folder after ``ipt-receiver warm``: numba's cache and the module built ahead of time."""
    cache = tmp_path_factory.mktemp("kernels") / "cache"
    warm = receiver_cli(kernel_env(cache), "warm")
    assert warm.returncode == 0, warm.stdout + warm.stderr[-3000:]
    assert "built ahead of time into " + str(cache) in warm.stdout, warm.stdout
    return cache


def _replay(env: dict[str, str], flight: Path, out: Path) -> subprocess.CompletedProcess[str]:
    return receiver_cli(
        env, "replay", "--camera", str(flight / "camera.yaml"), "--video", str(flight / "frames.mkv"),
        "--fps", "120", "--output", str(out),
    )  # fmt: skip


def test_a_replay_loads_the_built_kernels_without_numba_and_poses_to_the_bit(
    built: Path, short_flight: Path, tmp_path: Path
) -> None:
    ahead = _replay(kernel_env(built), short_flight, tmp_path / "ahead.tum")
    assert ahead.returncode == 0, ahead.stderr[-3000:]
    assert "kernels: built ahead of time, loaded from " + str(built) in ahead.stdout, ahead.stdout
    assert "not as built" not in ahead.stdout
    assert not numba_imported(ahead), "numba was imported although the kernels were built ahead"

    # The same cache without the built module: numba's kernels, loaded from its cache.
    jit_cache = tmp_path / "jit"
    shutil.copytree(built, jit_cache, ignore=shutil.ignore_patterns(kernelbuild.PREFIX + "*"))
    jit = _replay(kernel_env(jit_cache), short_flight, tmp_path / "jit.tum")
    assert jit.returncode == 0, jit.stderr[-3000:]
    assert "kernels: compiled, cache " + str(jit_cache) in jit.stdout, jit.stdout
    assert numba_imported(jit)

    poses = (tmp_path / "ahead.tum").read_bytes()
    assert poses.count(b"\n") > 40, "too few poses to compare"
    assert poses == (tmp_path / "jit.tum").read_bytes()


_UNDER_WX = """
import ctypes, os, sys
if ctypes.CDLL(None, use_errno=True).prctl(65, 1, 0, 0, 0) != 0:  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN
    sys.exit(77)
os.execv(sys.argv[1], sys.argv[1:])
"""


def test_the_built_kernels_run_under_wx(built: Path, short_flight: Path, tmp_path: Path) -> None:
    """Under W^X (the kernel's PR_SET_MDWE, as ``MemoryDenyWriteExecute=yes``) numba's kernels cannot load and fall
    back to numpy; the module built ahead is a file mapped as it is, and runs: the same poses as without W^X."""
    command = [sys.executable, "-c", _UNDER_WX, sys.executable, "-m", "ipt.receiver.cli", "replay",
               "--camera", str(short_flight / "camera.yaml"), "--video", str(short_flight / "frames.mkv"),
               "--fps", "120"]  # fmt: skip
    under = subprocess.run(
        [*command, "--output", str(tmp_path / "wx.tum")],
        capture_output=True, text=True, env=kernel_env(built), timeout=600, check=False,
    )  # fmt: skip
    if under.returncode == 77:
        pytest.skip(f"this kernel ({os.uname().release}) has no PR_SET_MDWE")
    assert under.returncode == 0, under.stderr[-3000:]
    assert "kernels: built ahead of time, loaded from " + str(built) in under.stdout, under.stdout
    free = _replay(kernel_env(built), short_flight, tmp_path / "free.tum")
    assert free.returncode == 0, free.stderr[-3000:]
    assert (tmp_path / "wx.tum").read_bytes() == (tmp_path / "free.tum").read_bytes()


def test_doctor_says_the_kernels_are_built_ahead(built: Path, tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "doctor"],
        capture_output=True, text=True, env=kernel_env(built), timeout=300, check=False, cwd=tmp_path,
    )  # fmt: skip
    lines = [line for line in result.stdout.splitlines() if "] kernels:" in line]
    assert len(lines) == 1, result.stdout + result.stderr[-2000:]
    assert lines[0].startswith("[ ok ] kernels: built ahead of time, loaded without numba"), lines[0]
    assert str(built) in lines[0]


def test_each_built_kernel_gives_numbas_result_to_the_bit(built: Path) -> None:
    """Every kernel the module exports, on the arguments ``kernels.warm`` passes and on a frame-sized pair:
    the same arrays, to the bit, as numba's kernel."""
    found = kernelbuild.load(built)
    assert found is not None, f"the build in {built} does not load"
    module, signatures = found
    assert set(signatures) == set(kernels.BY_NAME)
    kernels.compile_with_numba()
    rng = np.random.default_rng(7)
    a, b = (rng.integers(0, 256, (360, 640), dtype=np.uint8) for _ in range(2))
    out_ahead = (np.zeros((360, 640), np.float32), np.zeros_like(a), np.zeros_like(a))
    out_jit = tuple(np.zeros_like(x) for x in out_ahead)
    args = (a, b, a, b, 1.02, 0.5, 6.0)
    module.difference_pass(*args, *out_ahead)
    kernels.difference_pass.compiled(*args, *out_jit)
    for x, y in zip(out_ahead, out_jit, strict=True):
        assert x.tobytes() == y.tobytes()
    for x, y in zip(module.sample_pair(a, b, a, b, 4), kernels.sample_pair.compiled(a, b, a, b, 4), strict=True):
        assert x.tobytes() == y.tobytes()
    image = rng.normal(0.0, 10.0, (360, 640)).astype(np.float32)
    mask = (rng.random((360, 640)) > 0.2).astype(np.uint8)
    assert module.slopes_sampled(image, mask).tobytes() == kernels.slopes_sampled.compiled(image, mask).tobytes()


def test_fits_takes_only_what_the_kernel_was_built_for() -> None:
    signature = Signature.from_json([["array", "|u1", 2], ["array", "<f8", 1], ["int"], ["float"], ["bool"]])
    u8, f8 = np.zeros((4, 6), np.uint8), np.zeros(5)
    assert fits((u8, f8, 3, 2.5, True), signature)
    assert fits((u8, f8, np.int64(3), 2, np.bool_(False)), signature)  # an int where a float is: exact
    assert not fits((u8, f8, 3, 2.5), signature)  # too few
    assert not fits((u8[:, ::2], f8, 3, 2.5, True), signature)  # not contiguous
    assert not fits((u8.astype(np.float32), f8, 3, 2.5, True), signature)  # another dtype
    assert not fits((u8[None], f8, 3, 2.5, True), signature)  # another number of dimensions
    frozen = u8.copy()
    frozen.flags.writeable = False
    assert not fits((frozen, f8, 3, 2.5, True), signature)  # read-only
    assert not fits((u8, f8, 3.5, 2.5, True), signature)  # a float where an int is
    assert not fits((u8, [0.0] * 5, 3, 2.5, True), signature)  # not an array


def test_a_call_not_as_built_goes_to_numba(built: Path) -> None:
    """A strided view where the module was built for a contiguous image: numba compiles for it, and the
    result is the contiguous image's."""
    script = """
import numpy as np
from ipt.receiver.core import kernelcache, kernels
rng = np.random.default_rng(3)
image = rng.normal(0.0, 10.0, (40, 120)).astype(np.float32)
mask = np.ones((40, 60), np.uint8)
view = image[:, ::2]
a = kernels.slopes_sampled(np.ascontiguousarray(view), mask)
b = kernels.slopes_sampled(view, mask)
assert kernels.AHEAD is not None
assert len(a) > 100 and np.array_equal(a, b)
print(kernelcache.status().line())
"""
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=kernel_env(built), timeout=600, check=False
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "built ahead of time" in result.stdout
    assert "1 call not as built went to numba" in result.stdout


@pytest.mark.skipif(
    hasattr(os, "sched_getaffinity") and len(os.sched_getaffinity(0)) < 2,
    reason="two threads run at once only on two cores (this process may use one: taskset)",
)
def test_a_built_kernel_lets_other_threads_run(built: Path) -> None:
    """Built as numba's (``nogil``): while one thread is in a kernel, another runs Python (the live daemon's
    capture thread). A kernel that held the GIL would stop this thread for the whole of each call."""
    found = kernelbuild.load(built)
    assert found is not None
    module = found[0]
    big = np.random.default_rng(1).integers(0, 256, (4000, 4000), dtype=np.uint8)
    outs = (np.zeros(big.shape, np.float32), np.zeros_like(big), np.zeros_like(big))
    durations: list[float] = []

    def work() -> None:
        for _ in range(6):
            t0 = time.perf_counter()
            module.difference_pass(big, big, big, big, 1.0, 0.0, 6.0, *outs)
            durations.append(time.perf_counter() - t0)

    work()  # alone (the first call touches the outputs' pages)
    one_call_s = float(np.median(durations[1:]))
    worker = threading.Thread(target=work)
    ticks = [time.perf_counter()]
    worker.start()
    while worker.is_alive():
        ticks.append(time.perf_counter())
    worker.join()
    stalls = int(np.count_nonzero(np.diff(ticks) > 0.5 * one_call_s))
    assert stalls <= 2, f"this thread stood still {stalls} times for half a call ({one_call_s * 1e3:.1f} ms) or more"


def test_warm_without_a_c_compiler_says_so_and_numbas_cache_serves(built: Path, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    shutil.copytree(built, cache, ignore=shutil.ignore_patterns(kernelbuild.PREFIX + "*", "*.stamp"))
    warm = receiver_cli(kernel_env(cache, CC="/bin/false"), "warm")
    assert warm.returncode == 0, warm.stdout + warm.stderr[-2000:]
    assert "not built ahead of time (no working C compiler" in warm.stdout, warm.stdout
    assert "Traceback" not in warm.stderr
    assert not list(cache.glob(kernelbuild.PREFIX + "*")), "a partial build was left behind"


def test_a_broken_or_foreign_build_is_not_loaded(tmp_path: Path) -> None:
    key = kernelbuild.key()
    module = kernelbuild.module_file(tmp_path, key)
    assert kernelbuild.load(tmp_path) is None  # nothing built
    module.write_bytes(b"not a shared library")
    module.with_name(kernelbuild.PREFIX + key + ".json").write_text('{"kernels": {}}', encoding="utf-8")
    assert kernelbuild.load(tmp_path) is None  # not loadable
    module.with_name(kernelbuild.PREFIX + key + ".json").write_text("{", encoding="utf-8")
    assert kernelbuild.load(tmp_path) is None  # its signatures unreadable


def test_the_key_names_what_the_module_is_compiled_against() -> None:
    """numpy's version is in the stamp (and so the key): the module is compiled against numpy's C interface, and
    an upgraded numpy must not load a module built for another."""
    import importlib.metadata

    from ipt.receiver.core.kernelstamp import stamp_text

    lines = stamp_text().splitlines()
    for name in ("numba", "llvmlite", "numpy"):
        assert f"{name} {importlib.metadata.version(name)}" in lines
    assert len(kernelbuild.key()) == 16
