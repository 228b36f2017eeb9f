"""The compiled core's Z-step (mpc.core=compiled): planner.zstep's trust-region SQP with its arithmetic in numba kernels,
b_i from the compiled rollouts (planner.jit_rollout) and each QP solved by DAQP with the linearised b_i >= 0 as soft
rows priced by the L1 slack penalty (planner.daqp_qp), so the slack needs no variables of its own. For the predictors
the core runs itself (cv, the student) the whole SQP is one kernel (z_update, called inside planner.jit_admm's
compiled loop); for the others (their Jacobians from Python) CompiledSQPZStep drives the same kernels from Python."""
from functools import partial

import numpy as np
from numba import njit

from core.rollout import ego_xy
from planner import daqp_qp
from planner.daqp_qp import INF, SoftQP
from planner.jit_linalg import matvec, rmatvec
from planner.jit_rollout import compiled_chain, compiled_jacobian, compiled_params, predicted, rows_affine
from planner.safety import Safety
from planner.zstep import SQPZStep


class CompiledSafety(Safety):
    """Safety with b_i and its Jacobian from a compiled kernel and, for cv and the student, compiled rollouts (other
    Python-side local Jacobians composed by the compiled chain rule)."""

    def __init__(self, source, history, R, T_p, courtesy=None, stretch=1.0, p=2.0):
        super().__init__(source, history, R, T_p, courtesy, stretch, p)
        self.history = np.ascontiguousarray(self.history)
        self.x_obs = np.ascontiguousarray(self.history[-2:, :, 0])
        self.params = compiled_params(source)  # planner.jit_rollout.predicted's (Ws, bs, s), or None: Python-side Jacobians
        self.jacobian = compiled_jacobian(source) or compiled_chain(source) or source.jacobian
        self._last = None  # (Z, the linearisation, (rows, d rows / d Z)) of the last `reused`

    def offset(self, Z):
        """How far (m, largest over the horizon and x, y) the ego's planned xy in Z lie from the last linearisation's."""
        return np.inf if self._lin is None else offset(Z, self._lin[0])

    def reused(self, Z):
        """The rows (b_i, then courtesy) and their d / d Z about the last linearisation (see Safety.reused); the last
        result is kept, since the SQP step linearises an accepted trial plan again."""
        if self._last is None or self._last[0] is not Z or self._last[1] is not self._lin:
            dt, b_c = self.courtesy or (1.0, 0.0)  # unread without courtesy rows
            self._last = (Z, self._lin, rows_affine(Z, *self._lin, self.R, self.stretch, self.p, self.x_obs, dt, b_c,
                                                       bool(self.courtesy)))
        return self._last[2]

    def linearize(self, Z, reuse_radius=0.0):
        """As Safety.linearize, with the new linearisation's derivative stored contiguous for the kernels."""
        if self.offset(Z) > reuse_radius:
            ego = np.ascontiguousarray(ego_xy(Z, self.T_p))
            values, grads = self.jacobian(self.history, ego)
            self._lin = (ego, np.ascontiguousarray(values), np.ascontiguousarray(grads))
        return self.reused(Z)


@njit(cache=True)
def offset(Z, ego0):
    """max |ego xy in Z - ego0| (m) over the horizon and x, y; Z (4T_p,), ego0 (T_p, 2)."""
    out = 0.0
    for t in range(len(ego0)):
        out = max(out, abs(Z[4 * t] - ego0[t, 0]), abs(Z[4 * t + 1] - ego0[t, 1]))
    return out


@njit(cache=True)
def clip(x, lo, hi):
    """x clipped to the box [lo, hi]."""
    out = np.empty_like(x)
    for i in range(len(x)):
        out[i] = min(max(x[i], lo[i]), hi[i])
    return out


@njit(cache=True)
def z_start(q_3, C, rho, mu, c_Z, Z, lo, hi):
    """The Z-update's linear term Phi_3's q + C'(mu - rho c_Z) and Z^k clipped to the state box."""
    return q_3 + rmatvec(C, mu - rho * c_Z), clip(Z, lo, hi)


@njit(cache=True)
def z_trial(x, Jb, c_lo, lo, hi, hard):
    """The QP's solution as a trial Z (clipped to the state box, met by DAQP only to its tolerance) and the largest
    violation of a linearised b_i row (m^2, 0 in penalty form)."""
    slack = 0.0
    if hard:
        rows = matvec(Jb, x)
        for i in range(len(rows)):
            slack = max(slack, c_lo[i] - rows[i])
    return clip(x, lo, hi), slack


@njit(cache=True)
def z_qp(lin_q, Z, b, Jb, radius, lo, hi, xy, hard, lambda_s):
    """The SQP step's QP data at Z: linear term (penalty form: minus lambda_s sum_i d b_i / d Z), the state box cut to
    the trust region on the ego's x, y (m), and the rows' lower bounds Jb Z - b (hard form; -INF: no row bound)."""
    f, q_lo, q_hi = lin_q.copy(), np.empty(len(Z)), np.empty(len(Z))
    for j in range(len(Z)):
        if not hard:
            f[j] -= lambda_s * Jb[:, j].sum()
        tr = radius if xy[j] else INF
        q_lo[j], q_hi[j] = max(lo[j], Z[j] - tr, -INF), min(hi[j], Z[j] + tr, INF)
    c_lo = matvec(Jb, Z) - b if hard else np.full(len(b), -INF)
    return f, q_lo, q_hi, c_lo


@njit(cache=True)
def merit(H, lin_q, Z, b, hard, slack_penalty, lambda_s):
    """1/2 Z'HZ + lin_q'Z plus the L1 violation price (hard) or - lambda_s sum b_i (penalty)."""
    value = np.sum(Z * (0.5 * matvec(H, Z) + lin_q))
    safety = 0.0
    for i in range(len(b)):
        safety += slack_penalty * max(0.0, -b[i]) if hard else -lambda_s * b[i]
    return value + safety


@njit(cache=True)
def verdict(H, lin_q, Z, Z_new, b, Jb, b_new, radius, hard, slack_penalty, lambda_s, max_radius, min_radius):
    """Trust-region test of a step Z -> Z_new: (accepted, next radius (m), step size (inf-norm, m)), as SQPZStep."""
    here = merit(H, lin_q, Z, b, hard, slack_penalty, lambda_s)
    predicted = here - merit(H, lin_q, Z_new, b + matvec(Jb, Z_new - Z), hard, slack_penalty, lambda_s)
    actual = here - merit(H, lin_q, Z_new, b_new, hard, slack_penalty, lambda_s)
    step = 0.0
    for i in range(len(Z)):
        step = max(step, abs(Z_new[i] - Z[i]))
    if actual >= 0.1 * predicted or predicted <= 1e-12:
        if actual >= 0.75 * predicted and step >= 0.99 * radius:
            radius = min(2.0 * radius, max_radius)
        return True, radius, step
    return False, max(0.5 * radius, min_radius), step


@njit(cache=True, inline="always")
def safety_rows(pred, rows_of, lin, Z, reuse_radius):
    """CompiledSafety.linearize as a kernel: the rows at Z and their d / d Z about the linearisation `lin` (ego0, values0,
    grads, taken), taken anew from the compiled predictor pred = (Ws, bs, s, history, x_obs) where Z's ego xy lie more
    than reuse_radius (m) from it; rows_of = (R, stretch, p, dt, b_c, courtesy) as rows_affine's. Returns (b, Jb, lin)."""
    Ws, bs, s, history, x_obs = pred
    R, stretch, p, dt, b_c, courtesy = rows_of
    ego0, values0, grads, taken = lin
    if not taken or offset(Z, ego0) > reuse_radius:
        ego0 = Z.reshape(-1, 4)[:, :2].copy()
        values0, grads = predicted(Ws, bs, s, history, ego0)
        lin = (ego0, values0, grads, True)
    b, Jb = rows_affine(Z, ego0, values0, grads, R, stretch, p, x_obs, dt, b_c, courtesy)
    return b, Jb, lin


@njit(cache=True, inline="always")
def z_update(zp, sqp, pred, rows_of, n_b, qp, cold, lin, Z, mu, c_Z, radius, fresh):
    """CompiledSQPZStep.__call__ as one kernel for a compiled predictor: Z_{k+1} from Z_k by trust-region SQP.

    zp = (H, Phi_3's q, C, rho, state box lo, hi, trust-region mask); sqp = SQPSettings' numbers (max_iters,
    trust_radius, min_radius, max_radius, tol, hard, lambda_s, slack_penalty, reuse_radius); qp: the Z-step's DAQP handle
    (cold: its first solve this ADMM solve); lin: the Z-step's linearisation (safety_rows); fresh: start afresh (radius
    trust_radius, b_i linearised at Z). Returns (Z, radius, lin, (SQP iterations, largest slack m^2, min b_i, min
    courtesy row, lin_offset m), DAQP's exit flag)."""
    H, q_3, C, rho, lo, hi, xy = zp
    max_iters, trust_radius, min_radius, max_radius, tol, hard, lambda_s, slack_penalty, reuse_radius = sqp
    if fresh:
        radius = trust_radius
    lin_q, Z = z_start(q_3, C, rho, mu, c_Z, Z, lo, hi)
    b, Jb, lin = safety_rows(pred, rows_of, lin, Z, 0.0 if fresh else reuse_radius)
    b_Z, slack, its, flag = b, 0.0, 0, 1
    for its in range(1, max_iters + 1):
        f, q_lo, q_hi, c_lo = z_qp(lin_q, Z, b, Jb, radius, lo, hi, xy, hard, lambda_s)
        x, flag = daqp_qp.solve(qp, cold, H, f, q_lo, q_hi, Jb, c_lo)
        cold = False
        if flag < 1:
            break
        Z_new, slack = z_trial(x, Jb, c_lo, lo, hi, hard)
        b_new, Jb_new, lin = safety_rows(pred, rows_of, lin, Z_new, reuse_radius)
        accepted, radius, step = verdict(H, lin_q, Z, Z_new, b, Jb, b_new, radius, hard, slack_penalty, lambda_s,
                                         max_radius, min_radius)
        if accepted:
            Z, b_Z = Z_new, b_new
            if step < tol:
                break
            b, Jb = b_new, Jb_new  # an accepted trial was linearised where it stands
    b_min, c_min = np.inf, np.inf
    for i in range(len(b_Z)):
        if i < n_b:
            b_min = min(b_min, b_Z[i])
        else:
            c_min = min(c_min, b_Z[i])
    return Z, radius, lin, (its, slack, b_min, c_min, offset(Z, lin[0])), flag


class CompiledSQPZStep:
    """planner.zstep.SQPZStep (same settings, same iterates to the QP solvers' tolerances) with numba kernels and DAQP."""

    name = SQPZStep.name

    def __init__(self, prob, safety, osqp_settings, settings):
        """The Z-step of Problem `prob` with the SQP settings; osqp_settings unused (every Z-step takes them)."""
        self.C, self.rho, self.safety, self.s = np.ascontiguousarray(prob.dyn.C), prob.rho, safety, settings
        self.lo, self.hi = prob.z_lo, prob.z_hi
        self.Phi_3 = prob.Phi_3
        self.H = np.ascontiguousarray(prob.Phi_3.P + prob.rho * (prob.dyn.C.T @ prob.dyn.C))
        self.xy = np.tile([True, True, False, False], len(self.lo) // 4)
        self.hard = settings.mode == "hard"
        self.qp = SoftQP(self.H, settings.slack_penalty, self.hard, safety.rows)

    def merit(self, Z, lin_q, b):
        """Quadratic part plus the safety term at Z with b_i = b (see SQPZStep.merit)."""
        return merit(self.H, lin_q, Z, b, self.hard, self.s.slack_penalty, self.s.lambda_s)

    def __call__(self, Z, mu, c_Z, zstate=None):
        """Z_{k+1} from Z_k as SQPZStep.__call__; info: SQP iterations, max slack (m^2), infeasible, min b_i, lin_offset."""
        s = self.s
        radius = s.trust_radius if zstate is None else zstate
        lin_q, Z = z_start(self.Phi_3.q, self.C, self.rho, mu, c_Z, Z, self.lo, self.hi)
        b, Jb = self.safety.linearize(Z, 0.0 if zstate is None else s.reuse_radius)
        b_Z, slack, its = b, 0.0, 0
        for its in range(1, s.max_iters + 1):
            f, lo, hi, c_lo = z_qp(lin_q, Z, b, Jb, radius, self.lo, self.hi, self.xy, self.hard, s.lambda_s)
            Z_new, slack = z_trial(self.qp.solve(f, lo, hi, Jb, c_lo), Jb, c_lo, self.lo, self.hi, self.hard)
            b_new = self.safety.trial(Z_new, s.reuse_radius)
            accepted, radius, step = verdict(self.H, lin_q, Z, Z_new, b, Jb, b_new, radius, self.hard, s.slack_penalty,
                                             s.lambda_s, s.max_radius, s.min_radius)
            if accepted:
                Z, b_Z = Z_new, b_new
                if step < s.tol:
                    break
                b, Jb = self.safety.linearize(Z, s.reuse_radius)
        return Z, radius, {"sqp_iters": its, "slack": slack, "infeasible": slack > s.slack_tol,
                           "b_min": float(b_Z[:self.safety.n_b].min(initial=np.inf)),
                           "c_min": float(b_Z[self.safety.n_b:].min(initial=np.inf)), "lin_offset": self.safety.offset(Z)}


def compiled(zstep):
    """The compiled counterpart of a bound Z-step class (conf/zstep/): sqp's is CompiledSQPZStep with the same settings;
    another (pygranso, which differentiates through torch) runs as it is."""
    if getattr(zstep, "func", None) is SQPZStep:
        return partial(CompiledSQPZStep, *zstep.args, **zstep.keywords)
    return zstep
