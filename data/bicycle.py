"""Kinematic bicycle of Kong et al. (2015): state z = [x, y, psi, v] (m, m, rad, m/s), input u = [delta, a] (rad, m/s^2)."""
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BicycleParams:
    """Geometry and step of the bicycle: l_f, l_r axle distances from the centre of mass (m), dt step (s)."""

    l_f: float
    l_r: float
    dt: float


def slip_angle(delta, p: BicycleParams):
    """Slip angle beta (rad) at the centre of mass for front steering delta (rad)."""
    return np.arctan(p.l_r / (p.l_f + p.l_r) * np.tan(delta))


def step(z, u, p: BicycleParams):
    """One forward-Euler step z(tau+1) = f(delta, a, z); z (..., 4), u (..., 2) -> (..., 4). Speed may go negative."""
    z = np.asarray(z, dtype=float)
    u = np.asarray(u, dtype=float)
    x, y, psi, v = z[..., 0], z[..., 1], z[..., 2], z[..., 3]
    beta = slip_angle(u[..., 0], p)
    heading = psi + beta
    # filled column by column: np.stack's and moveaxis' overhead was a fifth of a compiled MPC step (18 steps of 1 car)
    out = np.empty(np.broadcast(x, beta).shape + (4,))  # np.broadcast_shapes costs microseconds more
    out[..., 0] = x + p.dt * v * np.cos(heading)
    out[..., 1] = y + p.dt * v * np.sin(heading)
    out[..., 2] = psi + p.dt * v / p.l_r * np.sin(beta)
    out[..., 3] = v + p.dt * u[..., 1]
    return out


def linearize(z_tilde, delta_tilde, a_tilde, p: BicycleParams):
    """The paper's eq. (5): f ~ A~ delta + B~ a + C~ z + D~ about (delta~, a~, z~); returns A~ (4,), B~ (4,), C~ (4,4), D~ (4,)."""
    _, _, psi, v = np.asarray(z_tilde, dtype=float)
    k = p.l_r / (p.l_f + p.l_r)
    tan_d = np.tan(delta_tilde)
    beta = np.arctan(k * tan_d)
    dbeta = k / np.cos(delta_tilde) ** 2 / (1.0 + (k * tan_d) ** 2)
    c, s = np.cos(psi + beta), np.sin(psi + beta)
    dt = p.dt
    A = np.array([-dt * v * s * dbeta, dt * v * c * dbeta, dt * v / p.l_r * np.cos(beta) * dbeta, 0.0])
    B = np.array([0.0, 0.0, 0.0, dt])
    C = np.array(
        [
            [1.0, 0.0, -dt * v * s, dt * c],
            [0.0, 1.0, dt * v * c, dt * s],
            [0.0, 0.0, 1.0, dt / p.l_r * np.sin(beta)],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    f = step(z_tilde, [delta_tilde, a_tilde], p)
    D = f - A * delta_tilde - B * a_tilde - C @ np.asarray(z_tilde, dtype=float)
    return A, B, C, D
