"""Calibration tools: the camera's intrinsics (``ipt calibrate camera``) and the arena's projector-pixel-to-metre
scale (``ipt calibrate arena``)."""
