"""Where ``ipt demo`` used to live: the closed-loop demo is :mod:`ipt.sim.demo` now (it drives the simulator).

Only :mod:`ipt.cli` still imports it from here (the command line is changed with the sender's half of
issue 18); new code imports :mod:`ipt.sim.demo`.
"""

from __future__ import annotations

from ipt.sim.demo import run_demo

__all__ = ["run_demo"]
