"""IPT: indoor localisation of drones from fiducial tags hidden in a projected video.

The package is laid out after the signal chain (see README and docs/architecture):
``ipt.config`` (settings), ``ipt.tagmap`` (the map both sides share), ``ipt.sender`` (modulation on the
projector PC), ``ipt.receiver`` (demodulation, detection and pose on the drone), ``ipt.sim`` (the
simulated arena) and ``ipt.eval`` (accuracy against ground truth).
"""

__version__ = "0.1.0"
