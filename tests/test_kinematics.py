"""The velocity fit: exact on exact motion, honest covariances on noisy poses, and it forgets on a reset."""

from __future__ import annotations

import cv2
import numpy as np

from ipt.geometry import rot_z
from ipt.receiver.core.kinematics import MIN_POSES, WINDOW_US, VelocityFit

V = np.array([0.8, -0.3, 0.1])
W = np.array([0.05, -0.02, 0.6])  # rad/s about the arena axes


def _rotation(t_s: float) -> np.ndarray:
    m, _ = cv2.Rodrigues((W * t_s).reshape(3, 1))
    return np.asarray(m) @ rot_z(0.3)


def _feed(fit: VelocityFit, times_us: list[int], noise_m: float = 0.0, rng: np.random.Generator | None = None) -> None:
    for t in times_us:
        p = np.array([0.2, 0.1, 0.8]) + V * t * 1e-6
        if rng is not None:
            p = p + rng.normal(0.0, noise_m, 3)
        cov = np.eye(3) * max(noise_m, 1e-4) ** 2
        fit.add(t, p, _rotation(t * 1e-6), cov, np.eye(3) * 1e-6)


def test_exact_motion_gives_the_exact_twist() -> None:
    fit = VelocityFit()
    _feed(fit, [8333 * k for k in range(14)])
    twist = fit.twist()
    assert twist is not None
    assert twist.time_us == 8333 * 13
    np.testing.assert_allclose(twist.velocity_mps, V, atol=1e-9)
    np.testing.assert_allclose(twist.angular_velocity_radps, W, atol=1e-6)
    assert twist.poses == 13  # the oldest fell out of the 100 ms window


def test_too_few_poses_or_too_short_a_span_give_nothing() -> None:
    fit = VelocityFit()
    _feed(fit, [0, 8333])
    assert fit.twist() is None  # two poses
    fit = VelocityFit()
    _feed(fit, [0, 4000, 8000, 12000])
    assert fit.twist() is None  # 12 ms < 15 ms
    fit = VelocityFit()
    _feed(fit, [0, 8333, 16666])
    assert MIN_POSES == 3
    assert fit.twist() is not None


def test_a_gap_time_going_back_or_clear_start_afresh() -> None:
    fit = VelocityFit()
    _feed(fit, [0, 8333, 16666, 25000])
    _feed(fit, [25000 + WINDOW_US + 1])
    assert len(fit) == 1
    _feed(fit, [1000])
    assert len(fit) == 1
    fit.clear()
    assert len(fit) == 0
    assert fit.twist() is None


def test_the_covariance_is_honest_on_noisy_poses() -> None:
    """Over many noisy tracks the squared error normalised by the reported covariance averages 3 (3 axes)."""
    rng = np.random.default_rng(7)
    nees = []
    for _ in range(400):
        fit = VelocityFit()
        _feed(fit, [8333 * k for k in range(12)], noise_m=0.002, rng=rng)
        twist = fit.twist()
        assert twist is not None
        err = twist.velocity_mps - V
        nees.append(float(err @ np.linalg.inv(twist.velocity_cov) @ err))
    mean = float(np.mean(nees))
    assert 2.4 < mean < 3.6, mean
    std = float(np.sqrt(np.mean(np.diag(twist.velocity_cov))))
    assert 0.02 < std < 0.1, std  # 2 mm poses over 92 ms: a few cm/s


def test_velocity_of_a_point_adds_the_rotation() -> None:
    fit = VelocityFit()
    _feed(fit, [8333 * k for k in range(12)])
    twist = fit.twist()
    assert twist is not None
    d = np.array([0.0, 0.0, -0.1])
    v, cov = twist.velocity_of_point(d)
    np.testing.assert_allclose(v, V + np.cross(W, d), atol=1e-6)
    assert np.all(np.linalg.eigvalsh(cov) >= np.linalg.eigvalsh(twist.velocity_cov).min() - 1e-15)
