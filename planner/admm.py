"""Algorithm 1: ADMM over Delta (steering, rad), alpha (acceleration, m/s^2) and Z (states), state passed explicitly."""
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from scipy import sparse

from planner.cost import Quadratic
from planner.dynamics import Dynamics
from planner.qp import QP


class ADMMState(NamedTuple):
    """Iterate (Delta (T_p,), alpha (T_p,), Z (4T_p,), mu (4T_p,)) and the Z-step's own carried state."""

    Delta: np.ndarray
    alpha: np.ndarray
    Z: np.ndarray
    mu: np.ndarray
    zstate: Any = None


@dataclass
class Problem:
    """One MPC step: dynamics, the three cost blocks, rho, and the sub-problem solvers set up once for it."""

    dyn: Dynamics
    Phi_1: Quadratic
    Phi_2: Quadratic
    Phi_3: Quadratic
    rho: float
    delta_qp: QP
    alpha_qp: QP
    zstep: Any  # zstep(Z, mu, c_Z, zstate) -> (Z, zstate, info), see planner.zstep

    def J(self, st: ADMMState):
        """The paper's cost J = Phi_1(Delta) + Phi_2(alpha) + Phi_3(Z)."""
        return self.Phi_1(st.Delta) + self.Phi_2(st.alpha) + self.Phi_3(st.Z)


def box_qp(Phi, M, rho, lo, hi, osqp_settings):
    """The Delta- (M = A) or alpha-update (M = B) QP: P = P_Phi + rho M'M fixed, box lo <= u <= hi; q set per iteration."""
    n = M.shape[1]
    return QP(Phi.P + rho * M.T @ M, Phi.q, sparse.eye(n, format="csc"), np.full(n, lo), np.full(n, hi), osqp_settings)


def delta_update(prob: Problem, st: ADMMState):
    """argmin_Delta Phi_1 + mu'A Delta + rho/2 ||A Delta - c_Delta||^2 on the box, c_Delta = A Delta^k - F^k."""
    A = prob.dyn.A
    c_Delta = A @ st.Delta - prob.dyn.F(st.Delta, st.alpha, st.Z)
    return prob.delta_qp.solve(q=prob.Phi_1.q + A.T @ (st.mu - prob.rho * c_Delta))


def alpha_update(prob: Problem, st: ADMMState):
    """argmin_alpha Phi_2 + mu'B alpha + rho/2 ||B alpha - c_alpha||^2 on the box, c_alpha = B alpha^k - F(Delta^{k+1}, ...)."""
    B = prob.dyn.B
    c_alpha = B @ st.alpha - prob.dyn.F(st.Delta, st.alpha, st.Z)
    return prob.alpha_qp.solve(q=prob.Phi_2.q + B.T @ (st.mu - prob.rho * c_alpha))


def z_update(prob: Problem, st: ADMMState):
    """argmin_Z Phi_3 + mu'CZ + rho/2 ||CZ - c_Z||^2 s.t. box and b_i(Z) >= 0, c_Z = C Z^k - F(Delta^{k+1}, alpha^{k+1}, Z^k)."""
    c_Z = prob.dyn.C @ st.Z - prob.dyn.F(st.Delta, st.alpha, st.Z)
    return prob.zstep(st.Z, st.mu, c_Z, st.zstate)


def mu_update(prob: Problem, st: ADMMState):
    """mu + rho F(Delta, alpha, Z)."""
    return st.mu + prob.rho * prob.dyn.F(st.Delta, st.alpha, st.Z)


def admm_step(prob: Problem, st: ADMMState):
    """One sweep Delta -> alpha -> Z -> mu; returns the new state and the Z-step's info."""
    st = st._replace(Delta=delta_update(prob, st))
    st = st._replace(alpha=alpha_update(prob, st))
    Z, zstate, info = z_update(prob, st)
    st = st._replace(Z=Z, zstate=zstate)
    return st._replace(mu=mu_update(prob, st)), info


class Solve(NamedTuple):
    """How an ADMM solve ended: iterations, why it stopped, ||F|| (state units), last iterate change, the Z-step's info."""

    iters: int
    reason: str
    F_norm: float
    change: float
    zinfo: dict


def admm_solve(prob: Problem, st: ADMMState, max_iters, tol_F, tol_step):
    """Iterate admm_step until ||F|| <= tol_F and the iterate change (inf-norm) <= tol_step, or max_iters."""
    F_norm = change = np.inf
    info, k = {}, 0
    for k in range(1, max_iters + 1):
        new, info = admm_step(prob, st)
        change = float(max(np.max(np.abs(new.Delta - st.Delta)), np.max(np.abs(new.alpha - st.alpha)),
                           np.max(np.abs(new.Z - st.Z))))
        st = new
        F_norm = float(np.linalg.norm(prob.dyn.F(st.Delta, st.alpha, st.Z)))
        if F_norm <= tol_F and change <= tol_step:
            return st, Solve(k, "converged", F_norm, change, info)
    return st, Solve(k, "max_iters", F_norm, change, info)
