"""Repair of a plan whose controls, rolled out on the nonlinear bicycle, miss the safety check by a little: ADMM stops
with a small dynamics residual F, so its Z meets b_i >= 0 while the rollout of its (Delta, alpha) may not. One repair
step moves the controls least, in the metric of the cost's input blocks, so that the rollout linearised about itself
(single shooting) meets b_i >= margin and keeps the ego's yaw within psi_box over the checked steps (where the safety
shape covers the two bodies: planner.mpc.check_shape)."""
import numpy as np
from scipy import sparse

from planner import dynamics
from planner.qp import QP


def shooting(z0, Delta, alpha, Z, params, T_p):
    """d Z / d [Delta; alpha] (4T_p, 2T_p) of the rollout Z of the controls, from eq. (5) linearised along it:
    F = A Delta + B alpha + C Z + D = 0 gives dZ = -C^-1 (A dDelta + B dalpha)."""
    dyn = dynamics.linearize(z0, Delta[0], alpha[0], params, T_p, (Delta, alpha, Z))
    return -np.linalg.solve(dyn.C, np.hstack([dyn.A, dyn.B]))


# OSQP's settings for the repair QP: tolerances an order below ADMM's (1e-3), its own rho adapted every 25 iterations,
# not by timing, so that a repair is deterministic
OSQP = {"eps_abs": 1.0e-4, "eps_rel": 1.0e-4, "max_iter": 4000, "polishing": False, "adaptive_rho_interval": 25}


def repair_step(z0, Delta, alpha, Z, b, Jb, params, W, delta_box, a_box, psi_box, steps, margin):
    """Controls (Delta, alpha) moved least in the metric W (2T_p, 2T_p) so that b + Jb dZ >= margin (m^2) and the yaw
    psi + dpsi stays within psi_box (rad) over the first `steps` plan steps, within the input boxes (rad, m/s^2); b
    (N*T_p,), Jb (N*T_p, 4T_p) at the rollout Z. Raises planner.qp.SolverFailure when no such move exists."""
    T_p = len(Delta)
    rows = (np.arange(len(b)) % T_p) < steps
    S = shooting(z0, Delta, alpha, Z, params, T_p)
    yaw = 4 * np.arange(min(steps, T_p)) + 2  # psi's place in each checked step's [x, y, psi, v]
    u = np.concatenate([Delta, alpha])
    lo = np.concatenate([np.full(T_p, delta_box[0]), np.full(T_p, a_box[0])]) - u
    hi = np.concatenate([np.full(T_p, delta_box[1]), np.full(T_p, a_box[1])]) - u
    G = sparse.vstack([sparse.eye(2 * T_p), sparse.csc_matrix(Jb[rows] @ S), sparse.csc_matrix(S[yaw])], format="csc")
    l = np.concatenate([lo, margin - b[rows], psi_box[0] - Z[yaw]])
    h = np.concatenate([hi, np.full(int(rows.sum()), np.inf), psi_box[1] - Z[yaw]])
    du = QP(W, np.zeros(2 * T_p), G, l, h, OSQP).solve()
    return Delta + du[:T_p], alpha + du[T_p:]
