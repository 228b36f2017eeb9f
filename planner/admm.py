"""Algorithm 1: ADMM over Delta (steering, rad), alpha (acceleration, m/s^2) and Z (states), state passed explicitly.

The step's maths (Problem: arrays and floats only) and its sub-problem solvers (Solvers: OSQP objects, the Z-step) are
held apart; every kernel takes (problem, solvers, state)."""
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from core.validate import Int, OneOf, Real, check_fields, rule
from planner.cost import Quadratic
from planner.dynamics import Dynamics
from planner.qp import BoxQP


class ADMMState(NamedTuple):
    """Iterate (Delta (T_p,), alpha (T_p,), Z (4T_p,), mu (4T_p,)) and the Z-step's own carried state (sqp's
    planner.zstep.ZState: trust radius and b_i's linearisation; None: start afresh)."""

    Delta: np.ndarray
    alpha: np.ndarray
    Z: np.ndarray
    mu: np.ndarray
    zstate: Any = None


@dataclass(frozen=True)
class Settings:
    """The solver's settings, the `mpc.admm` node of conf/mpc/ (the one home of every value): the penalty, the core that
    runs the maths, when admm_solve stops and the sub-problems' OSQP settings; each value checked here, one UserError
    naming the key."""

    rho: float = rule(Real(0, lo_open=True))  # ADMM penalty (mpc.admm.rho=certified: planner.setup resolves it)
    core: str = rule(OneOf(("compiled", "reference")))  # compiled (numba kernels, DAQP) | reference (numpy, OSQP)
    max_iters: int = rule(Int(1))  # ADMM iterations at most
    tol_F: float = rule(Real(0, lo_open=True))  # ||F|| (state units) to stop at
    tol_step: float = rule(Real(0, lo_open=True))  # iterate change (inf-norm) to stop at
    osqp: dict  # OSQP settings of every sub-problem

    def __post_init__(self):
        check_fields(self, "mpc.admm")


class Problem(NamedTuple):
    """One MPC step's maths: dynamics (dense A, B, C, D), the three cost blocks (dense P, q, r), rho, the input boxes
    (rad, m/s^2) and the state box z_lo, z_hi (4T_p,)."""

    dyn: Dynamics
    Phi_1: Quadratic
    Phi_2: Quadratic
    Phi_3: Quadratic
    rho: float
    delta_box: tuple
    a_box: tuple
    z_lo: np.ndarray
    z_hi: np.ndarray

    def J(self, st: ADMMState):
        """The paper's cost J = Phi_1(Delta) + Phi_2(alpha) + Phi_3(Z)."""
        return self.Phi_1(st.Delta) + self.Phi_2(st.alpha) + self.Phi_3(st.Z)


class Solvers(NamedTuple):
    """The sub-problem solvers set up once per MPC step for its Problem: the Delta and alpha box QPs and the Z-step,
    zstep(Z, mu, c_Z, zstate) -> (Z, zstate, info) (planner.zstep)."""

    delta_qp: BoxQP
    alpha_qp: BoxQP
    zstep: Any


def solvers(prob: Problem, zstep, safety, osqp_settings: dict) -> Solvers:
    """The Delta- and alpha-update box QPs (P = P_Phi + rho M'M, M = A or B; q set per iteration) and the Z-step built by
    `zstep(prob, safety, osqp_settings)`."""
    box_qp = lambda Phi, M, box: BoxQP(Phi.P + prob.rho * M.T @ M, Phi.q, *box, osqp_settings)
    return Solvers(box_qp(prob.Phi_1, prob.dyn.A, prob.delta_box), box_qp(prob.Phi_2, prob.dyn.B, prob.a_box),
                   zstep(prob, safety, osqp_settings))


def delta_update(prob: Problem, solvers: Solvers, st: ADMMState):
    """argmin_Delta Phi_1 + mu'A Delta + rho/2 ||A Delta - c_Delta||^2 on the box, c_Delta = A Delta^k - F^k."""
    A = prob.dyn.A
    c_Delta = A @ st.Delta - prob.dyn.F(st.Delta, st.alpha, st.Z)
    return solvers.delta_qp.solve(q=prob.Phi_1.q + A.T @ (st.mu - prob.rho * c_Delta))


def alpha_update(prob: Problem, solvers: Solvers, st: ADMMState):
    """argmin_alpha Phi_2 + mu'B alpha + rho/2 ||B alpha - c_alpha||^2 on the box, c_alpha = B alpha^k - F(Delta^{k+1}, ...)."""
    B = prob.dyn.B
    c_alpha = B @ st.alpha - prob.dyn.F(st.Delta, st.alpha, st.Z)
    return solvers.alpha_qp.solve(q=prob.Phi_2.q + B.T @ (st.mu - prob.rho * c_alpha))


def z_update(prob: Problem, solvers: Solvers, st: ADMMState):
    """argmin_Z Phi_3 + mu'CZ + rho/2 ||CZ - c_Z||^2 s.t. box and b_i(Z) >= 0, c_Z = C Z^k - F(Delta^{k+1}, alpha^{k+1}, Z^k)."""
    c_Z = prob.dyn.C @ st.Z - prob.dyn.F(st.Delta, st.alpha, st.Z)
    return solvers.zstep(st.Z, st.mu, c_Z, st.zstate)


def mu_update(prob: Problem, st: ADMMState):
    """mu + rho F(Delta, alpha, Z)."""
    return st.mu + prob.rho * prob.dyn.F(st.Delta, st.alpha, st.Z)


def admm_step(prob: Problem, solvers: Solvers, st: ADMMState):
    """One sweep Delta -> alpha -> Z -> mu; returns the new state and the Z-step's info."""
    st = st._replace(Delta=delta_update(prob, solvers, st))
    st = st._replace(alpha=alpha_update(prob, solvers, st))
    Z, zstate, info = z_update(prob, solvers, st)
    st = st._replace(Z=Z, zstate=zstate)
    return st._replace(mu=mu_update(prob, st)), info


class Solve(NamedTuple):
    """How an ADMM solve ended: iterations, why it stopped, ||F|| (state units), last iterate change, the Z-step's info."""

    iters: int
    reason: str
    F_norm: float
    change: float
    zinfo: dict


CONTINUE, CONVERGED, RESTART = 0, 1, 2  # stopped()'s verdicts


def stopped(F_norm, change, lin_offset, tol_F, tol_step):
    """Algorithm 1's stopping test after a sweep, one for both cores: CONVERGED when ||F|| <= tol_F, the iterate change
    (inf-norm) <= tol_step and the Z-step's b_i linearised within tol_step (m) of its result; RESTART the Z-step (zstate
    None: a fresh linearisation) when only that last test fails; else CONTINUE."""
    if F_norm <= tol_F and change <= tol_step:
        return CONVERGED if lin_offset <= tol_step else RESTART
    return CONTINUE


def admm_solve(prob: Problem, solvers: Solvers, st: ADMMState, max_iters, tol_F, tol_step):
    """Iterate admm_step until stopped() says CONVERGED, or max_iters.

    A Z-step that reuses a linearisation reports how far it lies (info `lin_offset`); converged on a stale one, the Z-step
    is restarted (zstate None), which makes it linearise afresh, so a converged plan is a fixed point of the exact model."""
    F_norm = change = np.inf
    info, k = {}, 0
    for k in range(1, max_iters + 1):
        new, info = admm_step(prob, solvers, st)
        change = float(max(np.max(np.abs(new.Delta - st.Delta)), np.max(np.abs(new.alpha - st.alpha)),
                           np.max(np.abs(new.Z - st.Z))))
        F_norm = float(np.linalg.norm(prob.dyn.F(new.Delta, new.alpha, new.Z)))
        verdict = stopped(F_norm, change, info.get("lin_offset", 0.0), tol_F, tol_step)
        if verdict == CONVERGED:
            return new, Solve(k, "converged", F_norm, change, info)
        st = new._replace(zstate=None) if verdict == RESTART else new
    return st, Solve(k, "max_iters", F_norm, change, info)
