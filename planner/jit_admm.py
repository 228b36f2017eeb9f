"""Algorithm 1 for the compiled core (mpc.core=compiled): planner.admm's sweep Delta -> alpha -> Z -> mu with its
arithmetic in numba kernels; DAQP solves a box QP whose unconstrained minimiser leaves the box, and the Z-step
(planner.jit_zstep) its QPs. With a predictor the core runs itself (cv, the student) the whole solve is one compiled
call (admm_loop); with the others, whose Jacobians come from Python, the same kernels are driven from Python.
planner.admm stays the tested reference. The one-call solve's thin layers (box_update, jit_zstep's z_update and
safety_rows, jit_rollout's predicted) are inlined by numba (inline="always"): compiled as separate functions, each
layer re-optimised all the code linked beneath it, and a fresh clone compiled for 46 s instead of 30."""
import numpy as np
from numba import njit

from planner import daqp_qp
from planner.admm import ADMMState, Problem, Solve, Solvers
from planner.daqp_qp import NO_ROWS, DaqpBox, optimal
from planner.jit_linalg import matvec, rmatvec
from planner.jit_zstep import CompiledSQPZStep, z_update


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


@njit(cache=True, inline="always")
def box_update(qp, cold, P, lo, hi, update):
    """The box QP's minimiser from an update kernel's (minimiser, inside, linear term): the closed form, or DAQP's
    (handle qp) when the box [lo, hi] is active; (x, DAQP's exit flag (1 for the closed form), whether DAQP was called)."""
    x, inside, lin = update
    if inside:
        return x, 1, False
    x, flag = daqp_qp.solve(qp, cold, P, lin, lo, hi, NO_ROWS[0], NO_ROWS[1])
    return x, flag, True


@njit(cache=True)
def admm_loop(dyn, d_box, a_box, zp, sqp, pred, rows_of, n_b, z_qp, lin, Delta, alpha, Z, mu, radius, fresh, max_iters,
              tol_F, tol_step):
    """admm_solve's sweeps as one kernel for a compiled predictor (planner.jit_zstep.z_update): dyn = (A, B, C, D);
    d_box, a_box = (P, P^-1, Phi's q, box lo, hi, DAQP handle) of the Delta and alpha updates; the Z-step's zp, sqp, pred, rows_of,
    n_b, handle z_qp and linearisation lin as z_update's; (radius, fresh) its carried state. Returns (Delta, alpha, Z,
    mu, radius, fresh, lin, iterations, converged, ||F||, iterate change, the last Z-step's info, DAQP's exit flag)."""
    A, B, C, D = dyn
    P_1, P_1_inv, q_1, lo_1, hi_1, d_qp = d_box
    P_2, P_2_inv, q_2, lo_2, hi_2, a_qp = a_box
    d_cold, a_cold, z_cold = True, True, True
    F_norm = step = np.inf
    info = (0, 0.0, np.inf, np.inf, np.inf)
    k, flag = 0, 1
    for k in range(1, max_iters + 1):
        new_Delta, flag, called = box_update(d_qp, d_cold, P_1, lo_1, hi_1, delta_update(A, B, C, D, P_1_inv, q_1, zp[3], lo_1, hi_1,
                                                                             Delta, alpha, Z, mu))
        d_cold = d_cold and not called
        if flag < 1:
            break
        new_alpha, flag, called = box_update(a_qp, a_cold, P_2, lo_2, hi_2, alpha_update(A, B, C, D, P_2_inv, q_2, zp[3], lo_2, hi_2,
                                                                             new_Delta, alpha, Z, mu))
        a_cold = a_cold and not called
        if flag < 1:
            break
        new_Z, radius, lin, info, flag = z_update(zp, sqp, pred, rows_of, n_b, z_qp, z_cold, lin, Z, mu,
                                                      z_residual(A, B, C, D, new_Delta, new_alpha, Z), radius, fresh)
        z_cold, fresh = False, False
        if flag < 1:
            break
        mu, F_norm, step = mu_update(A, B, C, D, zp[3], new_Delta, new_alpha, new_Z, mu, Delta, alpha, Z)
        Delta, alpha, Z = new_Delta, new_alpha, new_Z
        if F_norm <= tol_F and step <= tol_step:
            if info[4] <= tol_step:
                return Delta, alpha, Z, mu, radius, fresh, lin, k, True, F_norm, step, info, flag
            fresh = True
    return Delta, alpha, Z, mu, radius, fresh, lin, k, False, F_norm, step, info, flag


def compiled_solve(prob: Problem, solvers: Solvers, st: ADMMState, max_iters, tol_F, tol_step):
    """admm_solve in one call of admm_loop (the Z-step a CompiledSQPZStep over a compiled predictor)."""
    zs, c = solvers.zstep, np.ascontiguousarray
    safety, s = zs.safety, zs.s
    dyn = tuple(c(M) for M in prob.dyn)
    box = lambda qp, q, role: (c(qp.P), c(qp.P_inv), c(q), c(qp.lo, float), c(qp.hi, float),
                               daqp_qp.shared(role, len(qp.lo)))
    zp = (zs.H, c(zs.Phi_3.q), zs.C, float(prob.rho), c(zs.lo), c(zs.hi), zs.xy)
    sqp = (s.max_iters, s.trust_radius, s.min_radius, s.max_radius, s.tol, zs.hard, s.lambda_s, s.slack_penalty,
           s.reuse_radius)
    dt, b_c = safety.courtesy or (1.0, 0.0)  # unread without courtesy rows
    pred = (*safety.params, safety.history, safety.x_obs)
    rows_of = (float(safety.R), float(safety.stretch), float(safety.p), float(dt), float(b_c), bool(safety.courtesy))
    T_p, M = len(st.Delta), safety.history.shape[1]
    lin = (np.zeros((T_p, 2)), np.zeros((T_p, M, 2)), np.zeros((T_p, M, 2, T_p, 2)), False)
    z_qp = daqp_qp.shared("z", len(zs.H), safety.rows, zs.hard, float(s.slack_penalty))  # hard form: elastic (soft) rows
    (Delta, alpha, Z, mu, radius, fresh, lin, k, converged, F_norm, step, info, flag) = admm_loop(
        dyn, box(solvers.delta_qp, prob.Phi_1.q, "delta"), box(solvers.alpha_qp, prob.Phi_2.q, "alpha"), zp, sqp, pred,
        rows_of, safety.n_b, z_qp, lin, c(st.Delta, float), c(st.alpha, float), c(st.Z, float), c(st.mu, float),
        float(s.trust_radius if st.zstate is None else st.zstate), st.zstate is None, int(max_iters), float(tol_F),
        float(tol_step))
    optimal(Z, flag)
    if lin[3]:
        safety._lin = lin[:3]
    its, slack, b_min, c_min, lin_offset = info
    zinfo = {"sqp_iters": its, "slack": slack, "infeasible": slack > s.slack_tol, "b_min": b_min, "c_min": c_min,
             "lin_offset": lin_offset}
    state = ADMMState(Delta, alpha, Z, mu, None if fresh else radius)
    return state, Solve(k, "converged" if converged else "max_iters", F_norm, step, zinfo)


def box_solve(qp: DaqpBox, update):
    """The box QP's minimiser from an update kernel's (minimiser, inside, linear term): the closed form, or DAQP's
    (warm-started across the MPC step) when the box is active."""
    x, inside, lin = update
    return x if inside else qp.solve(lin)


def admm_solve(prob: Problem, solvers: Solvers, st: ADMMState, max_iters, tol_F, tol_step):
    """planner.admm.admm_solve with the compiled kernels: sweeps until ||F|| <= tol_F, the iterate change <= tol_step
    and the Z-step's b_i linearised within tol_step (m) of its result, or max_iters; one compiled call (compiled_solve)
    when the core runs the predictor itself."""
    if isinstance(solvers.zstep, CompiledSQPZStep) and solvers.zstep.safety.params is not None:
        return compiled_solve(prob, solvers, st, max_iters, tol_F, tol_step)
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
