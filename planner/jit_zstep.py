"""The compiled core's Z-step (mpc.admm.core=compiled): planner.zstep's trust-region SQP with its arithmetic in numba kernels,
b_i from the compiled rollouts (planner.jit_rollout) and each QP solved by DAQP with the linearised b_i >= 0 as soft
rows priced by the L1 slack penalty (planner.daqp_qp), so the slack needs no variables of its own. For the predictors
the core runs itself (cv, the student) the whole SQP is one kernel (z_update, called inside planner.jit_admm's
compiled loop); for the others (their Jacobians from Python) CompiledSQPZStep drives the same kernels from Python."""
from functools import partial
from typing import NamedTuple

import numpy as np
from numba import njit

from core.rollout import ego_xy
from planner import daqp_qp
from planner.daqp_qp import INF, SoftQP
from planner.jit_linalg import matvec, rmatvec
from planner.jit_rollout import compiled_chain, compiled_jacobian, compiled_params, predicted, rows_affine
from planner.safety import Safety
from planner.zstep import SQPSettings, SQPZStep, TrustRegion, ZState
from planner.zstep import verdict as trust_test


class ZData(NamedTuple):
    """The Z-update's data for one MPC step: H = P_3 + rho C'C, Phi_3's q, C, rho, the state box lo, hi (4T_p,) and
    which entries the trust region bounds (the ego's x, y)."""

    H: np.ndarray
    q: np.ndarray
    C: np.ndarray
    rho: float
    lo: np.ndarray
    hi: np.ndarray
    xy: np.ndarray


class SQP(NamedTuple):
    """planner.zstep.SQPSettings as the kernels read them: numbers only (hard: mode == "hard"), its trust region's
    constants included (sqp() builds it from the one SQPSettings both cores read)."""

    max_iters: int
    trust_radius: float
    min_radius: float
    max_radius: float
    tol: float
    hard: bool
    lambda_s: float
    slack_penalty: float
    reuse_radius: float
    trust: TrustRegion


def sqp(s: SQPSettings) -> SQP:
    """The kernels' SQP of SQPSettings s."""
    return SQP(int(s.max_iters), float(s.trust_radius), float(s.min_radius), float(s.max_radius), float(s.tol),
               s.mode == "hard", float(s.lambda_s), float(s.slack_penalty), float(s.reuse_radius),
               TrustRegion(*(float(v) for v in s.trust_region)))


class Predictor(NamedTuple):
    """A compiled predictor as planner.jit_rollout.predicted takes it (Ws, bs, s) with the step's observed history
    (T_obs, SLOTS, 2) and its last two x (2, SLOTS) for the courtesy rows."""

    Ws: object
    bs: object
    s: np.ndarray
    history: np.ndarray
    x_obs: np.ndarray


class Rows(NamedTuple):
    """The Safety's rows as planner.jit_rollout.rows_affine writes them: R (m), stretch, shape p, dt (s), b_c (m/s^2),
    whether there are courtesy rows, and the number of b_i rows."""

    R: float
    stretch: float
    p: float
    dt: float
    b_c: float
    courtesy: bool
    n_b: int


class Lin(NamedTuple):
    """A linearisation of the rows (planner.safety.Safety's: ego xy (T_p, 2), values, d values / d ego xy) and whether
    one has been taken."""

    ego0: np.ndarray
    values0: np.ndarray
    grads: np.ndarray
    taken: bool


class ZKernel(NamedTuple):
    """What z_update reads: the data, the SQP settings, the compiled predictor, the rows and the DAQP handle."""

    data: ZData
    sqp: SQP
    pred: Predictor
    rows: Rows
    qp: object


class ZInfo(NamedTuple):
    """How a Z-update ended: SQP iterations, largest slack (m^2), min b_i, min courtesy row, lin_offset (m)."""

    sqp_iters: int
    slack: float
    b_min: float
    c_min: float
    lin_offset: float


trust_verdict = njit(cache=True, inline="always")(trust_test)  # planner.zstep.verdict, compiled: one test, both cores


class CompiledSafety(Safety):
    """Safety with b_i and its Jacobian from a compiled kernel and, for cv and the student, compiled rollouts (other
    Python-side local Jacobians composed by the compiled chain rule)."""

    def __init__(self, source, history, R, T_p, courtesy=None, stretch=1.0, p=2.0):
        super().__init__(source, history, R, T_p, courtesy, stretch, p)
        self.history = np.ascontiguousarray(self.history)
        self.x_obs = np.ascontiguousarray(self.history[-2:, :, 0])
        self.params = compiled_params(source)  # planner.jit_rollout.predicted's (Ws, bs, s), or None: Python-side Jacobians
        self.jacobian = compiled_jacobian(source) or compiled_chain(source) or source.jacobian
        self._last = None  # (Z, the linearisation, (rows, d rows / d Z)) of the last `reused`: a cache, not state

    def offset(self, Z, lin):
        """How far (m, largest over the horizon and x, y) the ego's planned xy in Z lie from the linearisation lin's."""
        return np.inf if lin is None else offset(Z, lin[0])

    def reused(self, Z, lin):
        """The rows (b_i, then courtesy) and their d / d Z about the linearisation lin (see Safety.reused); the last
        result is kept, since the SQP step linearises an accepted trial plan again."""
        if self._last is None or self._last[0] is not Z or self._last[1] is not lin:
            dt, b_c = self.courtesy or (1.0, 0.0)  # unread without courtesy rows
            self._last = (Z, lin, rows_affine(Z, *lin, self.R, self.stretch, self.p, self.x_obs, dt, b_c,
                                              bool(self.courtesy)))
        return self._last[2]

    def linearize(self, Z, lin=None, reuse_radius=0.0):
        """As Safety.linearize, with a new linearisation's derivative stored contiguous for the kernels."""
        if self.offset(Z, lin) > reuse_radius:
            ego = np.ascontiguousarray(ego_xy(Z, self.T_p))
            values, grads = self.jacobian(self.history, ego)
            lin = (ego, np.ascontiguousarray(values), np.ascontiguousarray(grads))
        return (*self.reused(Z, lin), lin)


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
def z_start(data, mu, c_Z, Z):
    """The Z-update's linear term Phi_3's q + C'(mu - rho c_Z) and Z^k clipped to the state box (data: ZData)."""
    return data.q + rmatvec(data.C, mu - data.rho * c_Z), clip(Z, data.lo, data.hi)


@njit(cache=True)
def z_trial(x, Jb, c_lo, data, hard):
    """The QP's solution as a trial Z (clipped to the state box, met by DAQP only to its tolerance) and the largest
    violation of a linearised b_i row (m^2, 0 in penalty form)."""
    slack = 0.0
    if hard:
        rows = matvec(Jb, x)
        for i in range(len(rows)):
            slack = max(slack, c_lo[i] - rows[i])
    return clip(x, data.lo, data.hi), slack


@njit(cache=True)
def z_qp(lin_q, Z, b, Jb, radius, data, sqp):
    """The SQP step's QP data at Z: linear term (penalty form: minus lambda_s sum_i d b_i / d Z), the state box cut to
    the trust region on the ego's x, y (m), and the rows' lower bounds Jb Z - b (hard form; -INF: no row bound)."""
    f, q_lo, q_hi = lin_q.copy(), np.empty(len(Z)), np.empty(len(Z))
    for j in range(len(Z)):
        if not sqp.hard:
            f[j] -= sqp.lambda_s * Jb[:, j].sum()
        tr = radius if data.xy[j] else INF
        q_lo[j], q_hi[j] = max(data.lo[j], Z[j] - tr, -INF), min(data.hi[j], Z[j] + tr, INF)
    c_lo = matvec(Jb, Z) - b if sqp.hard else np.full(len(b), -INF)
    return f, q_lo, q_hi, c_lo


@njit(cache=True)
def merit(H, lin_q, Z, b, sqp):
    """1/2 Z'HZ + lin_q'Z plus the L1 violation price (hard) or - lambda_s sum b_i (penalty)."""
    value = np.sum(Z * (0.5 * matvec(H, Z) + lin_q))
    safety = 0.0
    for i in range(len(b)):
        safety += sqp.slack_penalty * max(0.0, -b[i]) if sqp.hard else -sqp.lambda_s * b[i]
    return value + safety


@njit(cache=True)
def verdict(H, lin_q, Z, Z_new, b, Jb, b_new, radius, sqp):
    """Trust-region test of a step Z -> Z_new (planner.zstep.verdict on the merit): (accepted, next radius (m), step
    size (inf-norm, m))."""
    here = merit(H, lin_q, Z, b, sqp)
    predicted = here - merit(H, lin_q, Z_new, b + matvec(Jb, Z_new - Z), sqp)
    actual = here - merit(H, lin_q, Z_new, b_new, sqp)
    step = 0.0
    for i in range(len(Z)):
        step = max(step, abs(Z_new[i] - Z[i]))
    accepted, radius = trust_verdict(actual, predicted, step, radius, sqp.trust, sqp.min_radius, sqp.max_radius)
    return accepted, radius, step


@njit(cache=True, inline="always")
def safety_rows(pred, rows, lin, Z, reuse_radius):
    """CompiledSafety.linearize as a kernel: the rows at Z and their d / d Z about the linearisation `lin`, taken anew
    from the compiled predictor where Z's ego xy lie more than reuse_radius (m) from it. Returns (b, Jb, lin)."""
    if not lin.taken or offset(Z, lin.ego0) > reuse_radius:
        ego0 = Z.reshape(-1, 4)[:, :2].copy()
        values0, grads = predicted(pred.Ws, pred.bs, pred.s, pred.history, ego0)
        lin = Lin(ego0, values0, grads, True)
    b, Jb = rows_affine(Z, lin.ego0, lin.values0, lin.grads, rows.R, rows.stretch, rows.p, pred.x_obs, rows.dt, rows.b_c,
                        rows.courtesy)
    return b, Jb, lin


@njit(cache=True, inline="always")
def z_update(zk, cold, lin, Z, mu, c_Z, radius, fresh):
    """CompiledSQPZStep.__call__ as one kernel for a compiled predictor (zk: ZKernel): Z_{k+1} from Z_k by trust-region
    SQP; cold: the DAQP handle's first solve this ADMM solve; fresh: start afresh (radius trust_radius, b_i linearised
    at Z). Returns (Z, radius, lin, ZInfo, DAQP's exit flag)."""
    data, sqp = zk.data, zk.sqp
    if fresh:
        radius = sqp.trust_radius
    lin_q, Z = z_start(data, mu, c_Z, Z)
    b, Jb, lin = safety_rows(zk.pred, zk.rows, lin, Z, 0.0 if fresh else sqp.reuse_radius)
    b_Z, slack, its, flag = b, 0.0, 0, 1
    for its in range(1, sqp.max_iters + 1):
        f, q_lo, q_hi, c_lo = z_qp(lin_q, Z, b, Jb, radius, data, sqp)
        x, flag = daqp_qp.solve(zk.qp, cold, data.H, f, q_lo, q_hi, Jb, c_lo)
        cold = False
        if flag < 1:
            break
        Z_new, slack = z_trial(x, Jb, c_lo, data, sqp.hard)
        b_new, Jb_new, lin = safety_rows(zk.pred, zk.rows, lin, Z_new, sqp.reuse_radius)
        accepted, radius, step = verdict(data.H, lin_q, Z, Z_new, b, Jb, b_new, radius, sqp)
        if accepted:
            Z, b_Z = Z_new, b_new
            if step < sqp.tol:
                break
            b, Jb = b_new, Jb_new  # an accepted trial was linearised where it stands
    b_min, c_min = np.inf, np.inf
    for i in range(len(b_Z)):
        if i < zk.rows.n_b:
            b_min = min(b_min, b_Z[i])
        else:
            c_min = min(c_min, b_Z[i])
    return Z, radius, lin, ZInfo(its, slack, b_min, c_min, offset(Z, lin.ego0)), flag


class CompiledSQPZStep:
    """planner.zstep.SQPZStep (same settings, same iterates to the QP solvers' tolerances) with numba kernels and DAQP."""

    name = SQPZStep.name

    def __init__(self, prob, safety, osqp_settings, settings):
        """The Z-step of Problem `prob` with the SQP settings; osqp_settings unused (every Z-step takes them)."""
        self.safety, self.s, self.sqp = safety, settings, sqp(settings)
        C = np.ascontiguousarray(prob.dyn.C)
        self.data = ZData(np.ascontiguousarray(prob.Phi_3.P + prob.rho * (prob.dyn.C.T @ prob.dyn.C)),
                          np.ascontiguousarray(prob.Phi_3.q), C, float(prob.rho), np.ascontiguousarray(prob.z_lo),
                          np.ascontiguousarray(prob.z_hi), np.tile([True, True, False, False], len(prob.z_lo) // 4))
        self.qp = SoftQP(self.data.H, settings.slack_penalty, self.sqp.hard, safety.rows)

    def merit(self, Z, lin_q, b):
        """Quadratic part plus the safety term at Z with b_i = b (see SQPZStep.merit)."""
        return merit(self.data.H, lin_q, Z, b, self.sqp)

    def __call__(self, Z, mu, c_Z, zstate: ZState | None = None):
        """Z_{k+1} from Z_k and the next ZState as SQPZStep.__call__; info: SQP iterations, max slack (m^2), infeasible,
        min b_i, lin_offset."""
        d, s = self.data, self.sqp
        radius, lin = (s.trust_radius, None) if zstate is None else zstate
        lin_q, Z = z_start(d, mu, c_Z, Z)
        b, Jb, lin = self.safety.linearize(Z, lin, 0.0 if zstate is None else s.reuse_radius)
        b_Z, slack, its = b, 0.0, 0
        for its in range(1, s.max_iters + 1):
            f, lo, hi, c_lo = z_qp(lin_q, Z, b, Jb, radius, d, s)
            Z_new, slack = z_trial(self.qp.solve(f, lo, hi, Jb, c_lo), Jb, c_lo, d, s.hard)
            b_new, lin = self.safety.trial(Z_new, lin, s.reuse_radius)
            accepted, radius, step = verdict(d.H, lin_q, Z, Z_new, b, Jb, b_new, radius, s)
            if accepted:
                Z, b_Z = Z_new, b_new
                if step < s.tol:
                    break
                b, Jb, lin = self.safety.linearize(Z, lin, s.reuse_radius)
        return Z, ZState(radius, lin), {"sqp_iters": its, "slack": slack, "infeasible": slack > self.s.slack_tol,
                                        "b_min": float(b_Z[:self.safety.n_b].min(initial=np.inf)),
                                        "c_min": float(b_Z[self.safety.n_b:].min(initial=np.inf)),
                                        "lin_offset": self.safety.offset(Z, lin)}

    def kernel(self, qp) -> ZKernel:
        """This Z-step as z_update reads it, with the DAQP handle qp; for a compiled predictor's safety only."""
        sf = self.safety
        dt, b_c = sf.courtesy or (1.0, 0.0)  # unread without courtesy rows
        rows = Rows(float(sf.R), float(sf.stretch), float(sf.p), float(dt), float(b_c), bool(sf.courtesy), sf.n_b)
        return ZKernel(self.data, self.sqp, Predictor(*sf.params, sf.history, sf.x_obs), rows, qp)


def compiled(zstep):
    """The compiled counterpart of a bound Z-step class (conf/zstep/): sqp's is CompiledSQPZStep with the same settings;
    another (pygranso, which differentiates through torch) runs as it is."""
    if getattr(zstep, "func", None) is SQPZStep:
        return partial(CompiledSQPZStep, *zstep.args, **zstep.keywords)
    return zstep
