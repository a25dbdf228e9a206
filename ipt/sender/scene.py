"""The old name of :mod:`ipt.sender.overlay` (the AR overlay was called the "AR scene").

Kept only for ``ipt/demo.py`` and ``tests/test_demo.py``, which another change is moving at the same
time; they switch to :mod:`ipt.sender.overlay` when it is merged, and this module goes.
"""

from ipt.sender.overlay import DEFAULT_MAX_VEHICLES, PALETTE, ArOverlay, heading_rad

ArScene = ArOverlay

__all__ = ["DEFAULT_MAX_VEHICLES", "PALETTE", "ArOverlay", "ArScene", "heading_rad"]
