"""Kinematic bicycle against closed forms, and its linearisation against finite differences."""
import numpy as np
import pytest

from data.bicycle import BicycleParams, linearize, slip_angle, step

P = BicycleParams(l_f=1.1, l_r=1.4, dt=0.2)


def test_straight_line_with_constant_acceleration():
    z = np.array([1.0, -2.0, 0.3, 4.0])
    a, k = 0.7, 25
    for _ in range(k):
        z = step(z, [0.0, a], P)
    dist = P.dt * (k * 4.0 + a * P.dt * k * (k - 1) / 2)  # sum of v_i * dt
    np.testing.assert_allclose(z, [1.0 + dist * np.cos(0.3), -2.0 + dist * np.sin(0.3), 0.3, 4.0 + a * P.dt * k], atol=1e-9)


def test_constant_turn_stays_on_its_circle():
    delta, v = 0.15, 6.0
    beta = slip_angle(delta, P)
    dpsi = P.dt * v / P.l_r * np.sin(beta)
    R = P.dt * v / (2 * np.sin(dpsi / 2))  # circumradius of the regular polygon the Euler steps trace
    theta0 = 0.0 + beta
    centre = np.array([0.0, 0.0]) + R * np.array([-np.sin(theta0 - dpsi / 2), np.cos(theta0 - dpsi / 2)])
    z = np.array([0.0, 0.0, 0.0, v])
    for k in range(1, 60):
        z = step(z, [delta, 0.0], P)
        assert np.hypot(*(z[:2] - centre)) == pytest.approx(R, rel=1e-9)
        assert z[2] == pytest.approx(k * dpsi)


@pytest.mark.parametrize("z,delta,a", [([3.0, 1.0, 0.2, 5.0], 0.1, 0.5), ([0.0, 4.0, -0.4, 2.0], -0.3, -1.0)])
def test_linearisation_matches_finite_differences(z, delta, a):
    z = np.array(z)
    A, B, C, D = linearize(z, delta, a, P)
    h = 1e-6
    np.testing.assert_allclose(A, (step(z, [delta + h, a], P) - step(z, [delta - h, a], P)) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(B, (step(z, [delta, a + h], P) - step(z, [delta, a - h], P)) / (2 * h), atol=1e-7)
    for j in range(4):
        e = np.eye(4)[j] * h
        np.testing.assert_allclose(C[:, j], (step(z + e, [delta, a], P) - step(z - e, [delta, a], P)) / (2 * h), atol=1e-7)
    # exact at the linearisation point, first-order accurate nearby
    np.testing.assert_allclose(A * delta + B * a + C @ z + D, step(z, [delta, a], P), atol=1e-12)
    dz = np.array([0.01, -0.02, 0.01, 0.05])
    err = np.abs(A * (delta + 0.01) + B * a + C @ (z + dz) + D - step(z + dz, [delta + 0.01, a], P)).max()
    assert err < 1e-3
