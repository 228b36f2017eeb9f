"""Algorithm 1: ADMM over Delta (steering, rad), alpha (acceleration, m/s^2) and Z (states), state passed explicitly.

The sweep Delta -> alpha -> Z -> mu is one loop (admm_loop) in numba's subset: compiled whole, with the SQP Z-step
(planner.zstep.sqp_update), for the predictors written as kernels (cv, the student; admm_loops runs all the solves of
a multi-start step in one call), and run by Python over the same compiled kernels for the others, whose Jacobians come
from Python. The box QPs of the Delta- and alpha-updates are solved in closed form when their unconstrained minimiser
lies in the box, else by DAQP (planner.daqp_qp). The one-call solve's layers are inlined by numba (inline="always"):
compiled as separate functions, each layer re-optimised all the code linked beneath it, and a fresh clone compiled
for 46 s instead of 30."""
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numba import njit
from numba.extending import register_jitable
from numba.typed import List

from core import jobs
from core.jit_linalg import matvec, rmatvec
from core.validate import MAX_ITERS, Int, Real, check_fields, rule
from planner import daqp_qp
from planner.cost import Quadratic
from planner.daqp_qp import NO_ROWS, optimal
from planner.dynamics import Dynamics
from planner.safety import Lin, no_lin
from planner.zstep import ZData, ZInfo, ZKernel, ZState, stop_requested, z_update

TOL_F = 1.0e-3  # ||F|| (state units) at which a solve may stop (with TOL_STEP)
TOL_STEP = 1.0e-3  # iterate change (inf-norm) at which a solve may stop (with TOL_F)
SOLVES = np.zeros(1, np.int64)  # ADMM solves run by compiled_solves in this process (the bench's profile reads it)


@dataclass(frozen=True)
class Settings:
    """The solver's settings, the `mpc.admm` node of conf/mpc/ (the one home of every value): the penalty and when
    admm_solve stops (within max_iters, at TOL_F and TOL_STEP); each value checked here, one UserError naming the key."""

    rho: float = rule(Real(0, lo_open=True))  # ADMM penalty (mpc.admm.rho=certified: planner.setup resolves it)
    max_iters: int = rule(Int(1, MAX_ITERS))  # ADMM iterations at most

    def __post_init__(self):
        check_fields(self, "mpc.admm")


class ADMMState(NamedTuple):
    """Iterate (Delta (T_p,), alpha (T_p,), Z (4T_p,), mu (4T_p,)) and the Z-step's own carried state (sqp's
    planner.zstep.ZState: trust radius and b_i's linearisation; None: start afresh)."""

    Delta: np.ndarray
    alpha: np.ndarray
    Z: np.ndarray
    mu: np.ndarray
    zstate: Any = None


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


class Box(NamedTuple):
    """A Delta or alpha update's box QP min 1/2 x'Px + q'x on lo <= x <= hi: P = P_Phi + rho M'M (M = A or B), its
    inverse, Phi's q and the box."""

    P: np.ndarray
    P_inv: np.ndarray
    q: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


class Solvers(NamedTuple):
    """What one MPC step's Problem is solved with: the Delta- and alpha-updates' Boxes and the Z-step (planner.zstep
    conf/zstep/ class: `kernel()` gives the loop its Z-update, `safety` the step's rows)."""

    delta_qp: Box
    alpha_qp: Box
    zstep: Any


def box(Phi: Quadratic, M, rho, bounds) -> Box:
    """The Box of a Delta- or alpha-update, contiguous float64; P inverted once per step (scipy's cho_factor and
    cho_solve: 4x the time in argument checks at 8 x 8)."""
    c, P = np.ascontiguousarray, Phi.P + rho * M.T @ M
    return Box(c(P, float), c(np.linalg.inv(P)), c(Phi.q, float), np.full(len(P), bounds[0], float),
               np.full(len(P), bounds[1], float))


def solvers(prob: Problem, zstep, safety) -> Solvers:
    """The Delta- and alpha-update Boxes and the Z-step built by `zstep(prob, safety)`."""
    return Solvers(box(prob.Phi_1, prob.dyn.A, prob.rho, prob.delta_box),
                   box(prob.Phi_2, prob.dyn.B, prob.rho, prob.a_box), zstep(prob, safety))


class Iterate(NamedTuple):
    """admm_loop's iterate: Delta, alpha, Z, mu and the Z-step's carried state (radius m, fresh: start afresh, lin)."""

    Delta: np.ndarray
    alpha: np.ndarray
    Z: np.ndarray
    mu: np.ndarray
    radius: float
    fresh: bool
    lin: Lin


class Stop(NamedTuple):
    """When admm_loop stops (Settings'): iteration cap, ||F|| (state units), iterate change (inf-norm)."""

    max_iters: int
    tol_F: float
    tol_step: float


class Loop(NamedTuple):
    """How admm_loop ended: the last iterate, iterations, converged, ||F||, iterate change, the last Z-step's info and
    DAQP's last exit flag."""

    it: Iterate
    iters: int
    converged: bool
    F_norm: float
    change: float
    info: ZInfo
    flag: int


@njit(cache=True)
def F(dyn, Delta, alpha, Z):
    """Dynamics residual (4T_p,) in state units (m, m, rad, m/s); dyn = (A, B, C, D)."""
    A, B, C, D = dyn
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
def input_update(M, u, box, rho, residual, mu):
    """argmin_u Phi + mu'M u + rho/2 ||M u - c||^2, c = M u^k - F (u = Delta with M = A, or alpha with M = B; F the
    dynamics residual), when the box is inactive; (minimiser, inside the box, the QP's linear term)."""
    c = matvec(M, u) - residual
    lin = box.q + rmatvec(M, mu - rho * c)
    x, inside = box_minimiser(box.P_inv, lin, box.lo, box.hi)
    return x, inside, lin


@njit(cache=True)
def delta_update(dyn, box, rho, Delta, alpha, Z, mu):
    """The Delta-update: input_update with M = A, c_Delta = A Delta^k - F(Delta^k, alpha^k, Z^k)."""
    return input_update(dyn[0], Delta, box, rho, F(dyn, Delta, alpha, Z), mu)


@njit(cache=True)
def alpha_update(dyn, box, rho, Delta, alpha, Z, mu):
    """The alpha-update: input_update with M = B, c_alpha = B alpha^k - F(Delta^{k+1}, alpha^k, Z^k)."""
    return input_update(dyn[1], alpha, box, rho, F(dyn, Delta, alpha, Z), mu)


@njit(cache=True)
def z_residual(dyn, Delta, alpha, Z):
    """c_Z = C Z^k - F(Delta^{k+1}, alpha^{k+1}, Z^k), the Z-update's target."""
    return matvec(dyn[2], Z) - F(dyn, Delta, alpha, Z)


@njit(cache=True)
def inf_norm(a, b):
    """max |a - b|."""
    out = 0.0
    for i in range(len(a)):
        out = max(out, abs(a[i] - b[i]))
    return out


@njit(cache=True)
def mu_update(dyn, rho, Delta, alpha, Z, mu, old_Delta, old_alpha, old_Z):
    """mu + rho F(Delta, alpha, Z), with the stopping tests' ||F|| (state units) and iterate change (inf-norm over
    Delta, alpha, Z against the sweep's start)."""
    residual = F(dyn, Delta, alpha, Z)
    change = max(inf_norm(Delta, old_Delta), inf_norm(alpha, old_alpha), inf_norm(Z, old_Z))
    return mu + rho * residual, np.sqrt(np.sum(residual * residual)), change


CONTINUE, CONVERGED, RESTART = 0, 1, 2  # stopped()'s verdicts


@register_jitable(inline="always")
def stopped(F_norm, change, lin_offset, tol_F, tol_step):
    """Algorithm 1's stopping test after a sweep: CONVERGED when ||F|| <= tol_F, the iterate change (inf-norm) <=
    tol_step and the Z-step's b_i linearised within tol_step (m) of its result; RESTART the Z-step (a fresh
    linearisation) when only that last test fails, so that a converged plan is a fixed point of the exact model; else
    CONTINUE."""
    if F_norm <= tol_F and change <= tol_step:
        return CONVERGED if lin_offset <= tol_step else RESTART
    return CONTINUE


@register_jitable(inline="always")
def box_update(qp, cold, box, update):
    """The box QP's minimiser from an update kernel's (minimiser, inside, linear term): the closed form, or DAQP's
    (handle qp) when the Box is active; (x, DAQP's exit flag (1 for the closed form), whether DAQP was called)."""
    x, inside, lin = update
    if inside:
        return x, 1, False
    x, flag = daqp_qp.solve(qp, cold, box.P, lin, box.lo, box.hi, NO_ROWS[0], NO_ROWS[1])
    return x, flag, True


@register_jitable(inline="always")
def admm_loop(dyn, boxes, handles, zk, rho, it, stop, signals):
    """Algorithm 1's sweeps Delta -> alpha -> Z -> mu from the Iterate `it` until stopped() says CONVERGED, or
    stop.max_iters (Stop), or a stop signal arrives (signals: core.jobs.SIGNALS, planner.zstep.stop_requested);
    dyn = (A, B, C, D); boxes, handles: the Delta and alpha updates' Box and DAQP handle; zk: the Z-update's
    (planner.zstep.z_update). Returns a Loop."""
    (d_box, a_box), (d_qp, a_qp) = boxes, handles
    Delta, alpha, Z, mu, radius, fresh, lin = it
    d_cold, a_cold, z_cold = True, True, True
    F_norm = step = np.inf
    info = ZInfo(0, 0.0, False, np.inf, np.inf, np.inf)
    k, flag = 0, 1
    while k < stop.max_iters and not stop_requested(signals):
        k += 1
        new_Delta, flag, called = box_update(d_qp, d_cold, d_box, delta_update(dyn, d_box, rho, Delta, alpha, Z, mu))
        d_cold = d_cold and not called
        if flag < 1:
            break
        new_alpha, flag, called = box_update(a_qp, a_cold, a_box, alpha_update(dyn, a_box, rho, new_Delta, alpha, Z, mu))
        a_cold = a_cold and not called
        if flag < 1:
            break
        new_Z, radius, lin, info, flag = z_update(zk, z_cold, lin, Z, mu, z_residual(dyn, new_Delta, new_alpha, Z), radius,
                                                  fresh, signals)
        z_cold, fresh = False, False
        if flag < 1:
            break
        mu, F_norm, step = mu_update(dyn, rho, new_Delta, new_alpha, new_Z, mu, Delta, alpha, Z)
        Delta, alpha, Z = new_Delta, new_alpha, new_Z
        verdict = stopped(F_norm, step, info.lin_offset, stop.tol_F, stop.tol_step)
        if verdict == CONVERGED:
            return Loop(Iterate(Delta, alpha, Z, mu, radius, fresh, lin), k, True, F_norm, step, info, flag)
        fresh = verdict == RESTART
    return Loop(Iterate(Delta, alpha, Z, mu, radius, fresh, lin), k, False, F_norm, step, info, flag)


@njit(cache=True)
def pick_box(b, k):
    """Start k's Box of Boxes stacked over the starts."""
    return Box(b.P[k], b.P_inv[k], b.q[k], b.lo[k], b.hi[k])


@njit(cache=True)
def admm_loops(dyn, boxes, handles, zk, it, stop, signals):
    """admm_loop for every start of a multi-start step in one call, one start after another (the DAQP handles start
    cold in each): the arguments as admm_loop's, each array stacked over the starts on a leading axis (zk: its data
    only, rho its data's; stop: Stop of arrays; signals as it is). Returns a typed list of Loop, one per start."""
    out = List()
    for k in range(len(it.Delta)):
        lin = Lin(it.lin.ego0[k], it.lin.values0[k], it.lin.grads[k], it.lin.taken[k])
        d = zk.data
        data = ZData(d.H[k], d.q[k], d.C[k], d.rho[k], d.lo[k], d.hi[k], d.xy[k])
        out.append(admm_loop((dyn[0][k], dyn[1][k], dyn[2][k], dyn[3][k]), (pick_box(boxes[0], k), pick_box(boxes[1], k)),
                             handles, ZKernel(data, zk.sqp, zk.pred, zk.rows, zk.qp), data.rho,
                             Iterate(it.Delta[k], it.alpha[k], it.Z[k], it.mu[k], it.radius[k], it.fresh[k], lin),
                             Stop(stop.max_iters[k], stop.tol_F[k], stop.tol_step[k]), signals))
    return out


def stacked(items):
    """NamedTuples (or tuples) of arrays and numbers, nested alike, as one of their kind with each leaf stacked over the
    items on a new leading axis (np.array: a start of another shape raises ValueError)."""
    first = items[0]
    if isinstance(first, tuple):
        fields = [stacked([item[i] for item in items]) for i in range(len(first))]
        return type(first)(*fields) if hasattr(first, "_fields") else tuple(fields)
    if len(items) == 1:  # a view: one solve's arrays as they are
        return np.ascontiguousarray(np.asarray(first)[None])
    return np.array(items)  # np.stack's result in a fifth to a third of its time (it checks and expands each item)


def loop_args(prob: Problem, solvers: Solvers, st: ADMMState, max_iters, tol_F, tol_step):
    """admm_loop's per-start arguments (dyn, boxes, the Z-step's ZData, the Iterate to start from, Stop) for a solve
    from st, and its shared ones (the DAQP handles, the Z-update's kernel)."""
    c, zk = np.ascontiguousarray, solvers.zstep.kernel()
    history = solvers.zstep.safety.history
    radius, lin = (0.0, no_lin(len(st.Delta), history.shape[1])) if st.zstate is None else st.zstate  # fresh: reset
    start = Iterate(c(st.Delta, float), c(st.alpha, float), c(st.Z, float), c(st.mu, float), float(radius),
                    st.zstate is None, lin)
    boxes = solvers.delta_qp, solvers.alpha_qp
    handles = tuple(daqp_qp.shared(role, len(b.lo)) for role, b in zip(("delta", "alpha"), boxes))
    own = (tuple(c(M) for M in prob.dyn), boxes, getattr(zk, "data", None), start,
           Stop(int(max_iters), float(tol_F), float(tol_step)))
    return own, (handles, zk)


def compiled(solvers: Solvers) -> bool:
    """Whether a solve runs as one compiled call: its Z-step the SQP over a predictor written as kernels."""
    return getattr(solvers.zstep.safety, "params", None) is not None and hasattr(solvers.zstep, "sqp")


def compiled_solves(solves) -> list:
    """admm_loop's Loop for every solve of `solves`, admm_solve's arguments (Problem, Solvers, ADMMState, max_iters,
    tol_F, tol_step) each, all in one call of admm_loops: their Z-steps `compiled` and alike but for their data."""
    args = [loop_args(*solve) for solve in solves]
    SOLVES[0] += len(solves)
    (dyn, boxes, data, start, stop), (handles, zk) = stacked([a[0] for a in args]), args[0][1]
    if any(a[1][1].sqp != zk.sqp or a[1][1].rows != zk.rows for a in args):
        raise ValueError("the starts' Z-steps differ in their settings or rows")
    return list(typed_call(admm_loops, dyn, boxes, handles, zk._replace(data=data), start, stop, jobs.SIGNALS))


def structure(x):
    """What numba's type of an argument depends on, hashable: an array's dtype, dimensions, layout and flags, a tuple's
    class and its items', a typed list's own numba type, else the Python type."""
    if isinstance(x, np.ndarray):
        f = x.flags
        return x.dtype.num, x.ndim, f.c_contiguous, f.f_contiguous, f.writeable, f.aligned
    if isinstance(x, tuple):
        return type(x), *map(structure, x)
    if isinstance(x, List):
        return x._numba_type_
    return type(x)


ENTRIES = {}  # typed_call's compiled entry points by (kernel, structure of the arguments)


def typed_call(kernel, *args):
    """kernel(*args) for a numba kernel, numba's typing of the arguments done once per structure of them: numba types
    every argument of every call in Python, 0.25 ms for admm_loops' hundred-odd arrays (a tenth of a paper step), where
    their structure takes 0.03 ms; then the kernel's compiled entry point for those types is called directly."""
    key = (kernel, structure(args))
    if key not in ENTRIES:
        out = kernel(*args)  # typed, and compiled or loaded from numba's cache, as any call
        entry = kernel.overloads.get(tuple(map(kernel.typeof_pyval, args)))  # None: numba converted the arguments
        ENTRIES[key] = kernel if entry is None else entry.entry_point
        return out
    return ENTRIES[key](*args)


def solved(out: Loop):
    """(ADMMState, Solve) of admm_loop's Loop; SolverFailure if DAQP failed in it."""
    it, info = out.it, out.info
    optimal(it.Z, out.flag)
    zstate = None if it.fresh else ZState(it.radius, it.lin)
    return (ADMMState(it.Delta, it.alpha, it.Z, it.mu, zstate),
            Solve(out.iters, "converged" if out.converged else "max_iters", out.F_norm, out.change, info._asdict()))


class Solve(NamedTuple):
    """How an ADMM solve ended: iterations, why it stopped, ||F|| (state units), last iterate change, the Z-step's info."""

    iters: int
    reason: str
    F_norm: float
    change: float
    zinfo: dict


def admm_solve(prob: Problem, solvers: Solvers, st: ADMMState, max_iters, tol_F, tol_step):
    """Algorithm 1 from st: (ADMMState, Solve); one compiled call where the Z-step's predictor is written as kernels,
    else admm_loop run from Python."""
    if compiled(solvers):
        return solved(compiled_solves([(prob, solvers, st, max_iters, tol_F, tol_step)])[0])
    (dyn, boxes, _, start, stop), (handles, zk) = loop_args(prob, solvers, st, max_iters, tol_F, tol_step)
    return solved(admm_loop(dyn, boxes, handles, zk, prob.rho, start, stop, jobs.SIGNALS))
