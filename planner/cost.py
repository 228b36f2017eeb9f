"""The paper's cost J = Phi_1(Delta) + Phi_2(alpha) + Phi_3(Z) as exact quadratic forms (Table I weights)."""
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np


@dataclass(frozen=True)
class Weights:
    """Table I: lambda_div (1/m^2), lambda_v (s^2/m^2), lambda_delta, lambda_ddelta (1/rad^2), lambda_a, lambda_da (s^4/m^2);
    the values live in conf/paper/table1.yaml."""

    lambda_div: float
    lambda_v: float
    lambda_delta: float
    lambda_a: float
    lambda_ddelta: float
    lambda_da: float


class Quadratic(NamedTuple):
    """f(x) = 1/2 x'Px + q'x + r with P dense symmetric (fixed per weights: shared, never modified in place)."""

    P: np.ndarray
    q: np.ndarray
    r: float

    def __call__(self, x):
        """Value of the form at x."""
        return float(0.5 * x @ (self.P @ x) + self.q @ x + self.r)


def input_cost(T_p, lam, lam_rate, previous):
    """Phi_1 (or Phi_2): sum lam u(tau)^2 + lam_rate (u(tau) - u(tau-1))^2, u(-1) = `previous` (the last applied input)."""
    P, diff = _input_form(T_p, lam, lam_rate)
    e0 = np.zeros(T_p)
    e0[0] = previous
    return Quadratic(P, -2.0 * lam_rate * (diff.T @ e0), lam_rate * previous**2)


@lru_cache(maxsize=64)
def _input_form(T_p, lam, lam_rate):
    """P of input_cost and its difference operator: fixed per weights, so built once."""
    diff = np.eye(T_p) - np.eye(T_p, k=-1)  # row tau: u(tau) - u(tau-1), u(-1) in q
    return 2.0 * (lam * np.eye(T_p) + lam_rate * diff.T @ diff), diff


def Phi_1(T_p, w: Weights, delta_prev):
    """Steering effort and rate (rad)."""
    return input_cost(T_p, w.lambda_delta, w.lambda_ddelta, delta_prev)


def Phi_2(T_p, w: Weights, a_prev):
    """Acceleration effort and jerk (m/s^2)."""
    return input_cost(T_p, w.lambda_a, w.lambda_da, a_prev)


@lru_cache(maxsize=64)  # the same every MPC step of a run; callers never modify P or q in place
def Phi_3(T_p, w: Weights, y_ref, v_ref):
    """Lateral deviation from y_ref (m) and speed error from v_ref (m/s) over z(1..T_p), each reference one number or a
    path of T_p (a tuple: hashable for the cache); Z stacks [x, y, psi, v]."""
    S_y, S_v = np.eye(4 * T_p)[1::4], np.eye(4 * T_p)[3::4]  # pick y(tau), v(tau) out of Z
    P = 2.0 * (w.lambda_div * S_y.T @ S_y + w.lambda_v * S_v.T @ S_v)
    y, v = (np.broadcast_to(np.asarray(ref, dtype=float), T_p) for ref in (y_ref, v_ref))
    q = -2.0 * (w.lambda_div * S_y.T @ y + w.lambda_v * S_v.T @ v)
    return Quadratic(P, q, float(w.lambda_div * y @ y + w.lambda_v * v @ v))
