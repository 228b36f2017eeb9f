"""Algorithm 1 for the compiled core (mpc.core=compiled): planner.admm's sweep Delta -> alpha -> Z -> mu with its
arithmetic in numba kernels; DAQP solves a box QP whose unconstrained minimiser leaves the box, and the Z-step
(planner.jit_zstep) its QPs. planner.admm stays the tested reference."""
import numpy as np
from numba import njit

from planner.admm import ADMMState, Problem, Solve, Solvers
from planner.daqp_qp import DaqpBox
from planner.jit_linalg import matvec, rmatvec


@njit(cache=True)
def F(A, B, C, D, Delta, alpha, Z):
    """Dynamics residual (4T_p,) in state units (m, m, rad, m/s)."""
    return matvec(A, Delta) + matvec(B, alpha) + matvec(C, Z) + D


@njit(cache=True)
def box_minimiser(P_inv, q, lo, hi):
    """The unconstrained minimiser -P^-1 q of 1/2 x'Px + q'x and whether it lies in the box [lo, hi]."""
    x = -matvec(P_inv, q)
    inside = True
    for i in range(len(x)):
        inside = inside and lo[i] <= x[i] <= hi[i]
    return x, inside


@njit(cache=True)
def delta_update(A, B, C, D, P_inv, q, rho, lo, hi, Delta, alpha, Z, mu):
    """argmin_Delta Phi_1 + mu'A Delta + rho/2 ||A Delta - c_Delta||^2, c_Delta = A Delta^k - F^k, when the box is
    inactive; (minimiser, inside the box, the QP's linear term)."""
    c_Delta = matvec(A, Delta) - F(A, B, C, D, Delta, alpha, Z)
    lin = q + rmatvec(A, mu - rho * c_Delta)
    x, inside = box_minimiser(P_inv, lin, lo, hi)
    return x, inside, lin


@njit(cache=True)
def alpha_update(A, B, C, D, P_inv, q, rho, lo, hi, Delta, alpha, Z, mu):
    """argmin_alpha Phi_2 + mu'B alpha + rho/2 ||B alpha - c_alpha||^2, c_alpha = B alpha^k - F(Delta^{k+1}, ...), when
    the box is inactive; (minimiser, inside the box, the QP's linear term)."""
    c_alpha = matvec(B, alpha) - F(A, B, C, D, Delta, alpha, Z)
    lin = q + rmatvec(B, mu - rho * c_alpha)
    x, inside = box_minimiser(P_inv, lin, lo, hi)
    return x, inside, lin


@njit(cache=True)
def z_residual(A, B, C, D, Delta, alpha, Z):
    """c_Z = C Z^k - F(Delta^{k+1}, alpha^{k+1}, Z^k), the Z-update's target."""
    return matvec(C, Z) - F(A, B, C, D, Delta, alpha, Z)


@njit(cache=True)
def inf_norm(a, b):
    """max |a - b|."""
    out = 0.0
    for i in range(len(a)):
        out = max(out, abs(a[i] - b[i]))
    return out


@njit(cache=True)
def mu_update(A, B, C, D, rho, Delta, alpha, Z, mu, old_Delta, old_alpha, old_Z):
    """mu + rho F(Delta, alpha, Z), with the stopping tests' ||F|| (state units) and iterate change (inf-norm over
    Delta, alpha, Z against the sweep's start)."""
    residual = F(A, B, C, D, Delta, alpha, Z)
    change = max(inf_norm(Delta, old_Delta), inf_norm(alpha, old_alpha), inf_norm(Z, old_Z))
    return mu + rho * residual, np.sqrt(np.sum(residual * residual)), change


def box_solve(qp: DaqpBox, update):
    """The box QP's minimiser from an update kernel's (minimiser, inside, linear term): the closed form, or DAQP's
    (warm-started across the MPC step) when the box is active."""
    x, inside, lin = update
    return x if inside else qp.solve(lin)


def admm_solve(prob: Problem, solvers: Solvers, st: ADMMState, max_iters, tol_F, tol_step):
    """planner.admm.admm_solve with the compiled kernels: sweeps until ||F|| <= tol_F, the iterate change <= tol_step
    and the Z-step's b_i linearised within tol_step (m) of its result, or max_iters."""
    dyn = tuple(np.ascontiguousarray(M) for M in prob.dyn)
    d_qp, a_qp = DaqpBox(solvers.delta_qp), DaqpBox(solvers.alpha_qp)
    Delta, alpha, Z, mu, zstate = st
    F_norm = step = np.inf
    info, k = {}, 0
    for k in range(1, max_iters + 1):
        new_Delta = box_solve(d_qp, delta_update(*dyn, d_qp.P_inv, prob.Phi_1.q, prob.rho, d_qp.lo, d_qp.hi, Delta, alpha, Z, mu))
        new_alpha = box_solve(a_qp, alpha_update(*dyn, a_qp.P_inv, prob.Phi_2.q, prob.rho, a_qp.lo, a_qp.hi, new_Delta, alpha,
                                                 Z, mu))
        new_Z, zstate, info = solvers.zstep(Z, mu, z_residual(*dyn, new_Delta, new_alpha, Z), zstate)
        mu, F_norm, step = mu_update(*dyn, prob.rho, new_Delta, new_alpha, new_Z, mu, Delta, alpha, Z)
        Delta, alpha, Z = new_Delta, new_alpha, new_Z
        if F_norm <= tol_F and step <= tol_step:
            if info.get("lin_offset", 0.0) <= tol_step:
                return ADMMState(Delta, alpha, Z, mu, zstate), Solve(k, "converged", F_norm, step, info)
            zstate = None
    return ADMMState(Delta, alpha, Z, mu, zstate), Solve(k, "max_iters", F_norm, step, info)
