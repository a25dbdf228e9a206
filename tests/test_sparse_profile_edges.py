"""A sparse profile near the image's edge (ipt/receiver/core/sparsekernels.py, ``read_profile``): where its middle is
inside by the profile's reach no point is checked, so the answer must be the one a check of every point gives: the
profile is read (the same values) exactly when all of its points and lines are inside, compiled and as Python."""

from __future__ import annotations

import numpy as np
import pytest

from ipt.receiver.core import kernels, sparsekernels

W, H, WIDTH, LINES = 48, 36, 9, 3
K = np.array([[100.0, 0.0, 20.0], [0.0, 100.0, 15.0], [0.0, 0.0, 1.0]])
R, T = np.eye(3), np.array([0.0, 0.0, 1.0])  # floor (x, y) in metres -> pixel (100 x + 20, 100 y + 15)
LAMS = (np.arange(WIDTH) - WIDTH // 2) / (WIDTH // 2)


def _reference(image: np.ndarray, ox: float, oy: float, dx: float, dy: float) -> np.ndarray | None:
    """Every point of the profile checked, then read (no lens: the points lie on a straight line)."""
    mid = np.array([100 * ox + 20, 100 * oy + 15])
    half = np.array([100 * dx, 100 * dy]) * (WIDTH // 2)
    along = np.array([-half[1], half[0]]) / np.hypot(*half)
    values = np.empty(WIDTH)
    for o, lam in enumerate(LAMS):
        total = 0.0
        for line in range(LINES):
            u, v = mid + lam * half + (line - LINES // 2) * along
            if not (0.0 <= u < W - 1 and 0.0 <= v < H - 1):
                return None
            x0, y0, fx, fy = int(u), int(v), u - int(u), v - int(v)
            top = image[y0, x0] * (1 - fx) + image[y0, x0 + 1] * fx
            bottom = image[y0 + 1, x0] * (1 - fx) + image[y0 + 1, x0 + 1] * fx
            total += top * (1 - fy) + bottom * fy
        values[o] = total / LINES
    return values


@pytest.mark.parametrize("compiled", [False, True])
def test_a_profile_is_read_exactly_when_every_point_of_it_is_inside_the_image(compiled: bool) -> None:
    if compiled:
        assert kernels.sparse_iterate_compiled()  # (compiles the profile's reader too)
    read = sparsekernels.read_profile if compiled else sparsekernels.read_profile_py
    rng = np.random.default_rng(7)
    image = rng.integers(0, 256, (H, W), dtype=np.uint8)
    out = np.zeros((1, WIDTH), np.float32)
    outcomes = {True: 0, False: 0}
    for _ in range(3000):
        u, v = rng.uniform(-3, W + 2), rng.uniform(-3, H + 2)  # the middle: well inside, near an edge, outside
        angle, step_px = rng.uniform(0, 2 * np.pi), rng.uniform(0.3, 2.5)
        ox, oy = (u - 20) / 100, (v - 15) / 100
        dx, dy = step_px * np.cos(angle) / 100, step_px * np.sin(angle) / 100
        expected = _reference(image, ox, oy, dx, dy)
        got = read(image, R, T, K, np.zeros(5), ox, oy, dx, dy, u, v, LINES, out, 0, LAMS)
        assert got == (expected is not None), (u, v, angle, step_px)
        if expected is not None:
            np.testing.assert_allclose(out[0], expected, rtol=0, atol=1e-3)
        outcomes[got] += 1
    assert outcomes[True] > 1000  # both kinds, many near the edges
    assert outcomes[False] > 300
