"""The receiver's pure per-frame stages: camera frames (arrays and capture times) in, poses and the
reason for each frame without one out — lightness, alignment, difference, track, pose, gates, bridge and
the pipeline that strings them together; and the compiled kernels' loops with their disk cache
(``kernels``, ``kernelcache``: ``ipt-receiver warm``)."""
