"""Does every dependency of ipt install from binary wheels on 64-bit Raspberry Pi OS (aarch64 Linux)?

    python benchmarks/aarch64_wheels.py [--python 3.11,3.13] [--extras display,gpu,ros2]

For each Python version (3.11: Raspberry Pi OS Bookworm; 3.13: Trixie), ``pip download
--only-binary=:all:`` resolves the declared dependencies of pyproject.toml (``[project] dependencies``)
together, with their own dependencies, for ``--platform manylinux_2_17_aarch64`` ... ``manylinux_2_36_aarch64``
(glibc 2.36 is Bookworm's; pip takes the newest wheel that fits one of them) into a temporary folder, as
pip on a Pi would choose them. Wheels only: a package with nothing but a source archive for that platform
fails the resolution, which is then repeated dependency by dependency to name it. Each extra is resolved
the same way on its own. The resolved versions are compared with those installed here (the ones the tests
ran with): none may be older. Prints one JSON object; exit status 0 when every core dependency resolved.
Downloads some 150 MB per Python version (into a temporary folder, removed at the end).
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import re
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
GLIBC_MINORS = (17, 26, 27, 28, 31, 34, 35, 36)
"""manylinux_2_X tags tried: 2_17 is manylinux2014; 2_36 is Bookworm's glibc (Trixie has 2.41)."""
WHEEL_NAME = re.compile(r"^(?P<name>[^-]+)-(?P<version>[^-]+)-")


def _platform_args() -> list[str]:
    args = []
    for minor in GLIBC_MINORS:
        args += ["--platform", f"manylinux_2_{minor}_aarch64"]
    return [*args, "--platform", "manylinux2014_aarch64", "--platform", "linux_aarch64"]


def _download(requirements: list[str], python: str, dest: Path, no_deps: bool = False) -> tuple[bool, str]:
    cmd = [sys.executable, "-m", "pip", "download", "--only-binary=:all:", "--python-version", python,
           "--implementation", "cp", *_platform_args(), "--dest", str(dest), "--quiet",
           "--disable-pip-version-check"]  # fmt: skip
    if no_deps:
        cmd.append("--no-deps")
    result = subprocess.run([*cmd, *requirements], capture_output=True, text=True, check=False, timeout=1800)
    errors = [ln for ln in result.stderr.splitlines() if ln.startswith("ERROR")]
    return result.returncode == 0, " ".join(errors)[:400]


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _resolved(dest: Path) -> dict[str, str]:
    found = {}
    for wheel in dest.glob("*.whl"):
        m = WHEEL_NAME.match(wheel.name)
        if m:
            found[_normal(m.group("name"))] = m.group("version")
    return found


def _older_than_here(resolved: dict[str, str]) -> dict[str, dict[str, str]]:
    """Resolved versions older than the installed ones (a plain numeric comparison of the release parts)."""

    def key(version: str) -> tuple[int, ...]:
        return tuple(int(p) for p in re.findall(r"\d+", version.split("+")[0])[:4])

    older = {}
    for name, version in resolved.items():
        try:
            here = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            continue
        if key(version) < key(here):
            older[name] = {"resolved": version, "installed_here": here}
    return older


def check(python: str, core: list[str], extras: dict[str, list[str]]) -> dict[str, Any]:
    out: dict[str, Any] = {"python": python}
    with tempfile.TemporaryDirectory(prefix="ipt-wheels-") as tmp:
        ok, error = _download(core, python, Path(tmp))
        out["core_ok"] = ok
        if ok:
            resolved = _resolved(Path(tmp))
            out["core_resolved"] = dict(sorted(resolved.items()))
            out["older_than_installed_here"] = _older_than_here(resolved)
        else:
            out["core_error"] = error
            failing = {}
            for req in core:
                with tempfile.TemporaryDirectory(prefix="ipt-wheel-") as one:
                    one_ok, one_error = _download([req], python, Path(one), no_deps=True)
                    if not one_ok:
                        failing[req] = one_error
            out["core_failing"] = failing
    for extra, reqs in extras.items():
        with tempfile.TemporaryDirectory(prefix="ipt-wheels-") as tmp:
            ok, error = _download(reqs, python, Path(tmp), no_deps=True)
            out[f"extra_{extra}"] = {"ok": ok, **({} if ok else {"error": error})}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    parser.add_argument("--python", default="3.11,3.13", help="Python versions (default 3.11,3.13)")
    parser.add_argument("--extras", default="display,gpu,ros2", help="extras to check on their own ('' for none)")
    args = parser.parse_args()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    core = [str(r) for r in project["dependencies"]]
    optional = project.get("optional-dependencies", {})
    extras = {e: [str(r) for r in optional[e]] for e in args.extras.split(",") if e}
    results = [check(v, core, extras) for v in args.python.split(",")]
    print(json.dumps({"platforms": _platform_args()[1::2], "core": core, "results": results}, indent=1))
    return 0 if all(r["core_ok"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
