"""Algorithm 1: ADMM over Delta (steering, rad), alpha (acceleration, m/s^2) and Z (states), state passed explicitly."""
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from planner.cost import Quadratic
from planner.dynamics import Dynamics
from planner.qp import BoxQP


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
    delta_qp: BoxQP
    alpha_qp: BoxQP
    zstep: Any  # zstep(Z, mu, c_Z, zstate) -> (Z, zstate, info), see planner.zstep

    def __post_init__(self):
        # dense copies of A, B, C: products with (4T_p x T_p) and (4T_p)^2 matrices from Python are ~5x faster dense
        self.A, self.B, self.C = (m.toarray() for m in (self.dyn.A, self.dyn.B, self.dyn.C))

    def F(self, Delta, alpha, Z):
        """Dynamics residual A Delta + B alpha + C Z + D (4T_p,) in state units."""
        return self.A @ Delta + self.B @ alpha + self.C @ Z + self.dyn.D

    def set_rho(self, rho):
        """A new penalty rho: the three sub-problems' Hessians follow; mu is the unscaled multiplier, so it stays valid."""
        self.delta_qp.set_P(self.Phi_1.P.toarray() + rho * self.A.T @ self.A)
        self.alpha_qp.set_P(self.Phi_2.P.toarray() + rho * self.B.T @ self.B)
        self.zstep.set_rho(rho)
        self.rho = rho

    def J(self, st: ADMMState):
        """The paper's cost J = Phi_1(Delta) + Phi_2(alpha) + Phi_3(Z)."""
        return self.Phi_1(st.Delta) + self.Phi_2(st.alpha) + self.Phi_3(st.Z)


def box_qp(Phi, M, rho, lo, hi, osqp_settings, closed_form):
    """The Delta- (M = A) or alpha-update (M = B) QP: P = P_Phi + rho M'M, box lo <= u <= hi; q set per iteration."""
    return BoxQP(Phi.P + rho * M.T @ M, Phi.q, lo, hi, osqp_settings, closed_form)


def delta_update(prob: Problem, st: ADMMState):
    """argmin_Delta Phi_1 + mu'A Delta + rho/2 ||A Delta - c_Delta||^2 on the box, c_Delta = A Delta^k - F^k."""
    A = prob.A
    c_Delta = A @ st.Delta - prob.F(st.Delta, st.alpha, st.Z)
    return prob.delta_qp.solve(q=prob.Phi_1.q + A.T @ (st.mu - prob.rho * c_Delta))


def alpha_update(prob: Problem, st: ADMMState):
    """argmin_alpha Phi_2 + mu'B alpha + rho/2 ||B alpha - c_alpha||^2 on the box, c_alpha = B alpha^k - F(Delta^{k+1}, ...)."""
    B = prob.B
    c_alpha = B @ st.alpha - prob.F(st.Delta, st.alpha, st.Z)
    return prob.alpha_qp.solve(q=prob.Phi_2.q + B.T @ (st.mu - prob.rho * c_alpha))


def z_update(prob: Problem, st: ADMMState):
    """argmin_Z Phi_3 + mu'CZ + rho/2 ||CZ - c_Z||^2 s.t. box and b_i(Z) >= 0, c_Z = C Z^k - F(Delta^{k+1}, alpha^{k+1}, Z^k)."""
    c_Z = prob.C @ st.Z - prob.F(st.Delta, st.alpha, st.Z)
    return prob.zstep(st.Z, st.mu, c_Z, st.zstate)


def mu_update(prob: Problem, st: ADMMState):
    """mu + rho F(Delta, alpha, Z)."""
    return st.mu + prob.rho * prob.F(st.Delta, st.alpha, st.Z)


def admm_step(prob: Problem, st: ADMMState):
    """One sweep Delta -> alpha -> Z -> mu; returns the new state and the Z-step's info."""
    st = st._replace(Delta=delta_update(prob, st))
    st = st._replace(alpha=alpha_update(prob, st))
    Z, zstate, info = z_update(prob, st)
    st = st._replace(Z=Z, zstate=zstate)
    return st._replace(mu=mu_update(prob, st)), info


class Solve(NamedTuple):
    """How an ADMM solve ended: iterations, why it stopped, ||F|| (state units), last iterate change, the Z-step's info,
    the final rho."""

    iters: int
    reason: str
    F_norm: float
    change: float
    zinfo: dict
    rho: float


class Balance(NamedTuple):
    """Residual balancing (Boyd et al. 2011, section 3.4.1), if enabled: rho times tau when ||r|| > mu ||s||, over tau
    when ||s|| > mu ||r||, kept in [rho_min, rho_max]; the values live in conf/planner.yaml (mpc.admm.balance_rho)."""

    enabled: bool
    mu: float
    tau: float
    rho_min: float
    rho_max: float


def dual_residual(prob: Problem, old: ADMMState, new: ADMMState):
    """||s||: how far Delta and alpha miss their own optimality with the new mu, rho [A'(B dalpha + C dZ); B'C dZ]
    (Boyd et al. 2011, section 3.3, for the three-block sweep)."""
    CdZ = prob.C @ (new.Z - old.Z)
    s_Delta = prob.A.T @ (prob.B @ (new.alpha - old.alpha) + CdZ)
    return prob.rho * float(np.sqrt(s_Delta @ s_Delta + np.sum((prob.B.T @ CdZ) ** 2)))


def balance(prob: Problem, r, s, b: Balance):
    """Residual balancing: a new rho for primal residual ||r|| = ||F|| and dual residual ||s||, applied to prob."""
    rho = prob.rho * b.tau if r > b.mu * s else prob.rho / b.tau if s > b.mu * r else prob.rho
    rho = min(max(rho, b.rho_min), b.rho_max)
    if rho != prob.rho:
        prob.set_rho(rho)


def admm_solve(prob: Problem, st: ADMMState, max_iters, tol_F, tol_step, balance_rho: Balance | None = None):
    """Iterate admm_step until ||F|| <= tol_F, the iterate change (inf-norm) <= tol_step and the Z-step's b_i linearised
    within tol_step (m) of its result, or max_iters; with balance_rho enabled, rho follows residual balancing.

    A Z-step that reuses a linearisation reports how far it lies (info `lin_offset`); converged on a stale one, the Z-step
    is restarted (zstate None), which makes it linearise afresh, so a converged plan is a fixed point of the exact model."""
    F_norm = change = np.inf
    info, k = {}, 0
    for k in range(1, max_iters + 1):
        new, info = admm_step(prob, st)
        change = float(max(np.max(np.abs(new.Delta - st.Delta)), np.max(np.abs(new.alpha - st.alpha)),
                           np.max(np.abs(new.Z - st.Z))))
        F_norm = float(np.linalg.norm(prob.F(new.Delta, new.alpha, new.Z)))
        if F_norm <= tol_F and change <= tol_step:
            if info.get("lin_offset", 0.0) <= tol_step:
                return new, Solve(k, "converged", F_norm, change, info, prob.rho)
            new = new._replace(zstate=None)
        elif balance_rho is not None and balance_rho.enabled:
            balance(prob, F_norm, dual_residual(prob, st, new), balance_rho)
        st = new
    return st, Solve(k, "max_iters", F_norm, change, info, prob.rho)
