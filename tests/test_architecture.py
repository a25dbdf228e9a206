"""The sender and the receiver run on different machines: neither may import the other."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


def _loaded_ipt_modules(module: str) -> list[str]:
    code = f"import json, sys, {module}; print(json.dumps(sorted(m for m in sys.modules if m.startswith('ipt'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    loaded: list[str] = json.loads(out.stdout)
    return loaded


@pytest.mark.parametrize(
    "module",
    [
        "ipt.receiver.cli",
        "ipt.receiver.daemon",
        "ipt.receiver.pipeline",
        "ipt.receiver.replay",
        "ipt.receiver.ros2",
        "ipt.receiver.record",
    ],
)
def test_receiver_does_not_import_the_sender(module: str) -> None:
    loaded = _loaded_ipt_modules(module)
    assert module in loaded
    assert [m for m in loaded if m.startswith("ipt.sender")] == []


@pytest.mark.parametrize("module", ["ipt.sender.cli", "ipt.sender.server", "ipt.sender.modulator"])
def test_sender_does_not_import_the_receiver(module: str) -> None:
    loaded = _loaded_ipt_modules(module)
    assert module in loaded
    assert [m for m in loaded if m.startswith("ipt.receiver")] == []
