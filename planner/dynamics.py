"""Eq. (5): the bicycle linearised into F(Delta, alpha, Z) = A Delta + B alpha + C Z + D = 0 with its block structure."""
from typing import NamedTuple

import numpy as np
from scipy import sparse

from data import bicycle


class Dynamics(NamedTuple):
    """The block matrices A (4T_p, T_p), B (4T_p, T_p), C (4T_p, 4T_p) sparse, D (4T_p,)."""

    A: sparse.csc_matrix
    B: sparse.csc_matrix
    C: sparse.csc_matrix
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
        points = [(z0, delta_prev, a_prev)] * T_p
    else:
        Delta, alpha, Z = plan
        states = np.vstack([z0, np.reshape(Z, (T_p, 4))[:-1]])
        points = list(zip(states, Delta, alpha))
    blocks = [bicycle.linearize(z, d, a, params) for z, d, a in points]
    A = sparse.block_diag([b[0][:, None] for b in blocks], format="csc")
    B = sparse.block_diag([b[1][:, None] for b in blocks], format="csc")
    C = [[None] * T_p for _ in range(T_p)]
    for tau in range(T_p):
        C[tau][tau] = -sparse.eye(4)
        if tau:
            C[tau][tau - 1] = sparse.csc_matrix(blocks[tau][2])
    D = np.concatenate([b[3] for b in blocks])
    D[:4] += blocks[0][2] @ np.asarray(z0, float)
    return Dynamics(A, B, sparse.bmat(C, format="csc"), D)
