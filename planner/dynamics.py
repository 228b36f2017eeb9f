"""Eq. (5): the bicycle linearised into F(Delta, alpha, Z) = A Delta + B alpha + C Z + D = 0 with its block structure."""
from typing import NamedTuple

import numpy as np

from data import bicycle


class Dynamics(NamedTuple):
    """The block matrices A (4T_p, T_p), B (4T_p, T_p), C (4T_p, 4T_p) and D (4T_p,), dense: their products with
    vectors from Python are ~5x faster dense than sparse at these sizes."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray

    def F(self, Delta, alpha, Z):
        """Dynamics residual (4T_p,) in state units (m, m, rad, m/s)."""
        return self.A @ Delta + self.B @ alpha + self.C @ Z + self.D


def linearize(z0, delta_prev, a_prev, params: bicycle.BicycleParams, T_p: int, plan=None):
    """A, B, C, D about the last observed (delta~, a~, z~ = z0), or, given plan = (Delta, alpha, Z), about each planned step.

    The paper's first block of D reads D~ - C~ z(0); the sign that makes z(1) = A~ delta(0) + B~ a(0) + C~ z(0) + D~
    hold is +, used here.
    """
    if plan is None:
        blocks = [bicycle.linearize(z0, delta_prev, a_prev, params)] * T_p
    else:
        Delta, alpha, Z = plan
        states = np.vstack([z0, np.reshape(Z, (T_p, 4))[:-1]])
        blocks = [bicycle.linearize(z, d, a, params) for z, d, a in zip(states, Delta, alpha)]
    # Filled by index arrays: scipy's block_diag/bmat over 2 T_p small blocks took ~10 ms per MPC step. Column-major, as
    # the dense copies of scipy's CSC matrices were: BLAS sums in that layout's order, so the plans stay bit for bit.
    rows, tau = np.arange(4 * T_p), np.repeat(np.arange(T_p), 4)
    A, B, C = (np.zeros((4 * T_p, n), order="F") for n in (T_p, T_p, 4 * T_p))
    A[rows, tau] = np.concatenate([b[0] for b in blocks])
    B[rows, tau] = np.concatenate([b[1] for b in blocks])
    C[rows, rows] = -1.0  # -I on the block diagonal, C~ of step tau at block (tau, tau - 1)
    r, c = np.divmod(np.arange(16), 4)
    C[(4 * np.arange(1, T_p)[:, None] + r).ravel(), (4 * np.arange(T_p - 1)[:, None] + c).ravel()] = \
        np.array([b[2].ravel() for b in blocks[1:]]).reshape(-1)  # empty for T_p = 1: concatenate refuses no blocks
    D = np.concatenate([b[3] for b in blocks])
    D[:4] += blocks[0][2] @ np.asarray(z0, float)
    return Dynamics(A, B, C, D)
