"""``ipt-receiver warm``: the kernels compiled into numba's cache once, then loaded, never compiled again;
its stamp lets a later warm (the unit's ExecStartPre at every restart) return without importing numba."""

from __future__ import annotations

import subprocess
from pathlib import Path

from kernelenv import kernel_env, numba_imported, receiver_cli

from ipt.receiver.core.kernelcache import STAMP_NAME, stamp_text


def _warm(cache: Path, *flags: str) -> subprocess.CompletedProcess[str]:
    return receiver_cli(kernel_env(cache), "warm", *flags, timeout_s=600)


def test_warm_caches_every_kernel_then_returns_at_once(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    first = _warm(cache)
    assert first.returncode == 0, first.stdout + first.stderr[-2000:]
    assert "kernels: compiled, cache " + str(cache) in first.stdout, first.stdout
    assert (cache / STAMP_NAME).read_text(encoding="utf-8") == stamp_text()

    again = _warm(cache)
    assert again.returncode == 0
    assert "already cached" in again.stdout, again.stdout
    assert not numba_imported(again), "a warm with a matching stamp imported numba"

    # A stamp for something else (another ipt, numba or Python): everything is loaded again, from the
    # cache, and nothing compiles.
    (cache / STAMP_NAME).write_text("sources 0\n", encoding="utf-8")
    checked = _warm(cache)
    assert checked.returncode == 0, checked.stdout
    assert numba_imported(checked)
    assert " 0 compiled" in checked.stdout, checked.stdout
    assert " 0 loaded" not in checked.stdout, checked.stdout
    assert (cache / STAMP_NAME).read_text(encoding="utf-8") == stamp_text()

    forced = _warm(cache, "--force")
    assert " 0 compiled" in forced.stdout, forced.stdout


def test_warm_fails_when_the_cache_is_not_where_numba_cache_dir_says(tmp_path: Path) -> None:
    """An unusable $NUMBA_CACHE_DIR (here: below a file): numba caches elsewhere or not at all, which the
    unit's read-only venv and missing home would not allow; warm says so and exits 1, without a traceback."""
    blocked = tmp_path / "file"
    blocked.write_text("not a folder", encoding="utf-8")
    result = _warm(blocked / "cache")
    assert result.returncode == 1, result.stdout + result.stderr[-2000:]
    assert f"NUMBA_CACHE_DIR={blocked / 'cache'}" in result.stderr, result.stderr[-500:]
    assert "Traceback" not in result.stderr


def test_the_stamp_covers_the_cores_sources() -> None:
    """The stamp changes with any source of the receiver's core (where kernels are defined): a stamp that read
    an empty folder would call a stale cache warm."""
    import hashlib

    import ipt.receiver.core as core

    folder = Path(core.__file__).resolve().parent
    sources = sorted(folder.glob("*.py"))
    assert any(p.name == "kernels.py" for p in sources)
    digest = hashlib.sha256()
    for source in sources:
        digest.update(source.name.encode() + b"\0" + source.read_bytes())
    assert f"sources {digest.hexdigest()}" in stamp_text().splitlines()
