"""The Z-update, argmin_Z Phi_3(Z) + mu'CZ + rho/2 ||CZ - c_Z||^2 s.t. the state box and b_i(Z) >= 0, chosen by the
`zstep` config group (conf/zstep/); `sqp` is trust-region sequential QP over the ego's x, y (m), each QP solved by DAQP
with the linearised b_i >= 0 as soft rows priced by the L1 slack penalty (planner.daqp_qp).

The SQP step is one kernel (sqp_update, numba's subset) that planner.admm's loop calls: compiled with it for the
predictors written as kernels (cv, the student), run from Python for the others. A Z-step is built once per MPC step
from (problem, safety) and gives the loop its `kernel()`; its class attribute `name` is the option's
name (MLflow param `zstep`)."""
from typing import NamedTuple

import numpy as np
from numba import njit
from numba.extending import overload, register_jitable

from core.jit_linalg import matvec, rmatvec
from core.jobs import STOPS
from planner import daqp_qp
from planner.daqp_qp import INF
from planner.safety import offset, safety_rows, trial_rows


class TrustRegion(NamedTuple):
    """The trust-region test of an SQP step on the merit function (Nocedal and Wright's Algorithm 4.1): a step is
    accepted when its actual decrease is at least `accept` times the predicted one (or the prediction is below `flat`:
    nothing left to gain); after one with at least `good` times it that reached `full` times the radius, the radius
    grows `grow` times; a rejected step shrinks it `shrink` times."""

    accept: float
    good: float
    full: float
    grow: float
    shrink: float
    flat: float


TRUST_REGION = TrustRegion(accept=0.1, good=0.75, full=0.99, grow=2.0, shrink=0.5, flat=1e-12)


@register_jitable(inline="always")
def verdict(actual, predicted, step, radius, tr, min_radius, max_radius):
    """The trust-region test of a step of size `step` (inf-norm, m) at radius `radius` (m): (accepted, next radius)."""
    if actual >= tr.accept * predicted or predicted <= tr.flat:
        if actual >= tr.good * predicted and step >= tr.full * radius:
            radius = min(tr.grow * radius, max_radius)
        return True, radius
    return False, max(tr.shrink * radius, min_radius)


class ZState(NamedTuple):
    """What the SQP Z-step carries from one ADMM iteration to the next (ADMMState.zstate; None: start afresh, the
    radius reset and b_i linearised anew): its trust radius (m) and b_i's linearisation (planner.safety.Lin)."""

    radius: float
    lin: tuple


class SQPSettings(NamedTuple):
    """Trust region on the ego's x, y (m), its bounds and growth, iteration cap, step tolerance (m), safety form; the
    values live in conf/zstep/sqp.yaml."""

    max_iters: int
    trust_radius: float
    min_radius: float
    max_radius: float
    tol: float
    mode: str  # hard: b_i >= 0 with an elastic slack; penalty: - lambda_s' b_i in the objective (eq. (11))
    lambda_s: float  # penalty-form multiplier (1/m^2 per constraint)
    slack_penalty: float  # L1 price of violating a linearised b_i >= 0 (per m^2)
    slack_tol: float  # slack (m^2) above which the linearisation counts as infeasible
    reuse_radius: float  # m: b_i's linearisation is reused while the ego's planned xy stay this close to where it was taken


class SQP(NamedTuple):
    """SQPSettings as the kernel reads them: numbers only (hard: mode == "hard"), the trust region's constants
    included."""

    max_iters: int
    trust_radius: float
    min_radius: float
    max_radius: float
    tol: float
    hard: bool
    lambda_s: float
    slack_penalty: float
    slack_tol: float
    reuse_radius: float
    trust: TrustRegion


def sqp(s: SQPSettings) -> SQP:
    """The kernel's SQP of SQPSettings s."""
    return SQP(int(s.max_iters), float(s.trust_radius), float(s.min_radius), float(s.max_radius), float(s.tol),
               s.mode == "hard", float(s.lambda_s), float(s.slack_penalty), float(s.slack_tol), float(s.reuse_radius),
               TRUST_REGION)


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


class ZKernel(NamedTuple):
    """What sqp_update reads: the data, the SQP settings, the predictor (planner.safety.Safety.kernel's), the rows
    (planner.safety.Rows) and the DAQP handle."""

    data: ZData
    sqp: SQP
    pred: object
    rows: object
    qp: object


class ZInfo(NamedTuple):
    """How a Z-update ended: SQP iterations, largest slack (m^2), whether it counts as infeasible, min b_i, min
    courtesy row, lin_offset (m: how far Z lies from where b_i was last linearised)."""

    sqp_iters: int
    slack: float
    infeasible: bool
    b_min: float
    c_min: float
    lin_offset: float


@njit(cache=True)
def z_start(data, mu, c_Z, Z):
    """The Z-update's linear term Phi_3's q + C'(mu - rho c_Z) and Z^k clipped to the state box (data: ZData)."""
    return data.q + rmatvec(data.C, mu - data.rho * c_Z), clip(Z, data.lo, data.hi)


@njit(cache=True)
def clip(x, lo, hi):
    """x clipped to the box [lo, hi]."""
    out = np.empty_like(x)
    for i in range(len(x)):
        out[i] = min(max(x[i], lo[i]), hi[i])
    return out


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
def step_verdict(H, lin_q, Z, Z_new, b, Jb, b_new, radius, sqp):
    """Trust-region test of a step Z -> Z_new on the merit: (accepted, next radius (m), step size (inf-norm, m))."""
    here = merit(H, lin_q, Z, b, sqp)
    predicted = here - merit(H, lin_q, Z_new, b + matvec(Jb, Z_new - Z), sqp)
    actual = here - merit(H, lin_q, Z_new, b_new, sqp)
    step = 0.0
    for i in range(len(Z)):
        step = max(step, abs(Z_new[i] - Z[i]))
    accepted, radius = verdict(actual, predicted, step, radius, sqp.trust, sqp.min_radius, sqp.max_radius)
    return accepted, radius, step


@njit(cache=True)
def stop_requested(signals):
    """Whether a stop signal arrived: `signals` is core.jobs.SIGNALS, the numbers of the signals Python's handler has
    seen since the last stop was consumed, one byte each, then zeros. A long compiled loop polls it once per iteration
    and returns early; Python raises the stop (core.jobs.guarded) once the call has returned."""
    for b in signals:
        if b == 0:
            return False
        if b == STOPS[0] or b == STOPS[1]:
            return True
    return False


@register_jitable(inline="always")
def sqp_update(zk, cold, lin, Z, mu, c_Z, radius, fresh, signals):
    """Z_{k+1} from Z_k by trust-region SQP (zk: ZKernel); cold: the DAQP handle's first solve this ADMM solve; fresh:
    start afresh (radius trust_radius, b_i linearised at Z); signals: core.jobs.SIGNALS (stop_requested: the steps
    end early). Returns (Z, radius, lin, ZInfo, DAQP's exit flag)."""
    data, sqp = zk.data, zk.sqp
    if fresh:
        radius = sqp.trust_radius
    lin_q, Z = z_start(data, mu, c_Z, Z)
    b, Jb, lin = safety_rows(zk.pred, zk.rows, lin, Z, 0.0 if fresh else sqp.reuse_radius)
    b_Z, slack, its, flag = b, 0.0, 0, 1
    while its < sqp.max_iters and not stop_requested(signals):
        its += 1
        f, q_lo, q_hi, c_lo = z_qp(lin_q, Z, b, Jb, radius, data, sqp)
        x, flag = daqp_qp.solve(zk.qp, cold, data.H, f, q_lo, q_hi, Jb, c_lo)
        cold = False
        if flag < 1:
            break
        Z_new, slack = z_trial(x, Jb, c_lo, data, sqp.hard)
        b_new, Jb_new, lin, linear = trial_rows(zk.pred, zk.rows, lin, Z_new, sqp.reuse_radius)
        accepted, radius, step = step_verdict(data.H, lin_q, Z, Z_new, b, Jb, b_new, radius, sqp)
        if accepted:
            Z, b_Z = Z_new, b_new
            if step < sqp.tol:
                break
            if linear:  # an accepted trial linearised where it stands
                b, Jb = b_new, Jb_new
            else:
                b, Jb, lin = safety_rows(zk.pred, zk.rows, lin, Z, sqp.reuse_radius)
    b_min, c_min = np.inf, np.inf
    for i in range(len(b_Z)):
        if i < zk.rows.n_b:
            b_min = min(b_min, b_Z[i])
        else:
            c_min = min(c_min, b_Z[i])
    return Z, radius, lin, ZInfo(its, slack, slack > sqp.slack_tol, b_min, c_min, offset(Z, lin.ego0)), flag


def z_update(zk, cold, lin, Z, mu, c_Z, radius, fresh, signals):
    """The Z-update planner.admm's loop calls, sqp_update's arguments and results: from Python, sqp_update for a
    ZKernel, else the Z-step's own `update` (zstep=pygranso: Python code, where a signal is raised as it arrives);
    compiled (the overload below), sqp_update."""
    if isinstance(zk, ZKernel):
        return sqp_update(zk, cold, lin, Z, mu, c_Z, radius, fresh, signals)
    return zk.update(cold, lin, Z, mu, c_Z, radius, fresh)


@overload(z_update, inline="always")
def _z_update(zk, cold, lin, Z, mu, c_Z, radius, fresh, signals):
    return sqp_update


class SQPZStep:
    """The SQP Z-step of one MPC step: its ZData, the kernel's SQP and the step's Safety."""

    name = "sqp"

    def __init__(self, prob, safety, settings: SQPSettings):
        """The Z-step of Problem `prob` and its Safety with the SQP settings."""
        self.safety, self.s, self.sqp = safety, settings, sqp(settings)
        c = np.ascontiguousarray
        self.data = ZData(c(prob.Phi_3.P + prob.rho * (prob.dyn.C.T @ prob.dyn.C)), c(prob.Phi_3.q), c(prob.dyn.C),
                          float(prob.rho), c(prob.z_lo), c(prob.z_hi),
                          np.tile([True, True, False, False], len(prob.z_lo) // 4))

    def kernel(self) -> ZKernel:
        """This Z-step as sqp_update reads it, with the process's DAQP handle for its QPs (soft rows in the hard form)."""
        qp = daqp_qp.shared("z", len(self.data.H), self.safety.rows, self.sqp.hard, self.sqp.slack_penalty)
        return ZKernel(self.data, self.sqp, self.safety.kernel(), self.safety.spec, qp)
