"""Algorithm 1 for the compiled core (mpc.admm.core=compiled): planner.admm's sweep Delta -> alpha -> Z -> mu with its
arithmetic in numba kernels; DAQP solves a box QP whose unconstrained minimiser leaves the box, and the Z-step
(planner.jit_zstep) its QPs. With a predictor the core runs itself (cv, the student) the whole solve is one compiled
call, and so are all the solves of a multi-start step (admm_loops: one solve after another); with the others, whose
Jacobians come from Python, the same kernels are driven from Python. planner.admm stays the tested reference. The
one-call solve's layers (admm_loop, box_update, jit_zstep's z_update and safety_rows, jit_rollout's predicted) are
inlined by numba (inline="always"): compiled as separate functions, each layer re-optimised all the code linked
beneath it, and a fresh clone compiled for 46 s instead of 30."""
from typing import NamedTuple

import numpy as np
from numba import njit
from numba.typed import List

from planner import admm, daqp_qp
from planner.admm import CONVERGED, RESTART, ADMMState, Problem, Solve, Solvers
from planner.daqp_qp import NO_ROWS, DaqpBox, optimal
from planner.jit_linalg import matvec, rmatvec
from planner.jit_zstep import CompiledSQPZStep, Lin, ZData, ZInfo, ZKernel, z_update
from planner.zstep import ZState

SOLVES = np.zeros(1, np.int64)  # ADMM solves run by compiled_solves in this process (the bench's profile reads it)


class Box(NamedTuple):
    """A Delta or alpha update's box QP as the kernels read it: its P and P^-1, Phi's q and the box lo, hi."""

    P: np.ndarray
    P_inv: np.ndarray
    q: np.ndarray
    lo: np.ndarray
    hi: np.ndarray


def box(qp, q) -> Box:
    """The Box of a planner.qp.BoxQP (or its DaqpBox) with Phi's q, contiguous float64."""
    c = np.ascontiguousarray
    return Box(c(qp.P), c(qp.P_inv), c(q), c(qp.lo, float), c(qp.hi, float))


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
    """When admm_loop stops (planner.admm.Settings'): iteration cap, ||F|| (state units), iterate change (inf-norm)."""

    max_iters: int
    tol_F: float
    tol_step: float


class Loop(NamedTuple):
    """How admm_loop ended: the last iterate, iterations, converged, ||F||, iterate change, the last Z-step's ZInfo and
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
def delta_update(dyn, box, rho, Delta, alpha, Z, mu):
    """argmin_Delta Phi_1 + mu'A Delta + rho/2 ||A Delta - c_Delta||^2, c_Delta = A Delta^k - F^k, when the box is
    inactive; (minimiser, inside the box, the QP's linear term)."""
    A = dyn[0]
    c_Delta = matvec(A, Delta) - F(dyn, Delta, alpha, Z)
    lin = box.q + rmatvec(A, mu - rho * c_Delta)
    x, inside = box_minimiser(box.P_inv, lin, box.lo, box.hi)
    return x, inside, lin


@njit(cache=True)
def alpha_update(dyn, box, rho, Delta, alpha, Z, mu):
    """argmin_alpha Phi_2 + mu'B alpha + rho/2 ||B alpha - c_alpha||^2, c_alpha = B alpha^k - F(Delta^{k+1}, ...), when
    the box is inactive; (minimiser, inside the box, the QP's linear term)."""
    B = dyn[1]
    c_alpha = matvec(B, alpha) - F(dyn, Delta, alpha, Z)
    lin = box.q + rmatvec(B, mu - rho * c_alpha)
    x, inside = box_minimiser(box.P_inv, lin, box.lo, box.hi)
    return x, inside, lin


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


stopped = njit(cache=True, inline="always")(admm.stopped)  # planner.admm's test, compiled: one test, both cores


@njit(cache=True, inline="always")
def box_update(qp, cold, box, update):
    """The box QP's minimiser from an update kernel's (minimiser, inside, linear term): the closed form, or DAQP's
    (handle qp) when the Box is active; (x, DAQP's exit flag (1 for the closed form), whether DAQP was called)."""
    x, inside, lin = update
    if inside:
        return x, 1, False
    x, flag = daqp_qp.solve(qp, cold, box.P, lin, box.lo, box.hi, NO_ROWS[0], NO_ROWS[1])
    return x, flag, True


@njit(cache=True, inline="always")
def admm_loop(dyn, boxes, handles, zk, it, stop):
    """admm_solve's sweeps as one kernel for a compiled predictor (planner.jit_zstep.z_update): dyn = (A, B, C, D);
    boxes, handles: the Delta and alpha updates' Box and DAQP handle; zk: the Z-step's ZKernel; it: the Iterate to
    start from; stop: Stop. Returns a Loop."""
    (d_box, a_box), (d_qp, a_qp) = boxes, handles
    Delta, alpha, Z, mu, radius, fresh, lin = it
    rho = zk.data.rho
    d_cold, a_cold, z_cold = True, True, True
    F_norm = step = np.inf
    info = ZInfo(0, 0.0, np.inf, np.inf, np.inf)
    k, flag = 0, 1
    for k in range(1, stop.max_iters + 1):
        new_Delta, flag, called = box_update(d_qp, d_cold, d_box, delta_update(dyn, d_box, rho, Delta, alpha, Z, mu))
        d_cold = d_cold and not called
        if flag < 1:
            break
        new_alpha, flag, called = box_update(a_qp, a_cold, a_box, alpha_update(dyn, a_box, rho, new_Delta, alpha, Z, mu))
        a_cold = a_cold and not called
        if flag < 1:
            break
        new_Z, radius, lin, info, flag = z_update(zk, z_cold, lin, Z, mu, z_residual(dyn, new_Delta, new_alpha, Z), radius,
                                                  fresh)
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
def admm_loops(dyn, boxes, handles, zk, it, stop):
    """admm_loop for every start of a multi-start step in one call, one start after another (the DAQP handles start
    cold in each): the arguments as admm_loop's, each array stacked over the starts on a leading axis (zk: its data
    only; stop: Stop of arrays). Returns a typed list of Loop, one per start."""
    out = List()
    for k in range(len(it.Delta)):
        lin = Lin(it.lin.ego0[k], it.lin.values0[k], it.lin.grads[k], it.lin.taken[k])
        d = zk.data
        data = ZData(d.H[k], d.q[k], d.C[k], d.rho[k], d.lo[k], d.hi[k], d.xy[k])
        out.append(admm_loop((dyn[0][k], dyn[1][k], dyn[2][k], dyn[3][k]), (pick_box(boxes[0], k), pick_box(boxes[1], k)),
                             handles, ZKernel(data, zk.sqp, zk.pred, zk.rows, zk.qp),
                             Iterate(it.Delta[k], it.alpha[k], it.Z[k], it.mu[k], it.radius[k], it.fresh[k], lin),
                             Stop(stop.max_iters[k], stop.tol_F[k], stop.tol_step[k])))
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
    from st, and its shared ones (the DAQP handles, the Z-step's ZKernel)."""
    zs, c = solvers.zstep, np.ascontiguousarray
    T_p, slots = len(st.Delta), zs.safety.history.shape[1]
    if st.zstate is None:  # no linearisation yet: placeholders of its shapes, `taken` False
        radius, lin = zs.sqp.trust_radius, Lin(np.zeros((T_p, 2)), np.zeros((T_p, slots, 2)),
                                               np.zeros((T_p, slots, 2, T_p, 2)), False)
    else:
        radius, lin = st.zstate.radius, Lin(*st.zstate.lin, True)
    z_qp = daqp_qp.shared("z", len(zs.data.H), zs.safety.rows, zs.sqp.hard, zs.sqp.slack_penalty)  # hard form: elastic (soft) rows
    start = Iterate(c(st.Delta, float), c(st.alpha, float), c(st.Z, float), c(st.mu, float), float(radius),
                    st.zstate is None, lin)
    boxes = box(solvers.delta_qp, prob.Phi_1.q), box(solvers.alpha_qp, prob.Phi_2.q)
    handles = tuple(daqp_qp.shared(role, len(b.lo)) for role, b in zip(("delta", "alpha"), boxes))
    own = (tuple(c(M) for M in prob.dyn), boxes, zs.data, start, Stop(int(max_iters), float(tol_F), float(tol_step)))
    return own, (handles, zs.kernel(z_qp))


def together(solvers: Solvers) -> bool:
    """Whether a solve runs as one compiled call: its Z-step a CompiledSQPZStep over a compiled predictor."""
    return isinstance(solvers.zstep, CompiledSQPZStep) and solvers.zstep.safety.params is not None


def compiled_solves(solves) -> list:
    """admm_loop's Loop for every solve of `solves`, compiled_solve's arguments (Problem, Solvers, ADMMState, max_iters,
    tol_F, tol_step) each, all in one call of admm_loops: their Z-steps `together` and alike but for their data."""
    args = [loop_args(*solve) for solve in solves]
    SOLVES[0] += len(solves)
    (dyn, boxes, data, start, stop), (handles, zk) = stacked([a[0] for a in args]), args[0][1]
    if any(a[1][1].sqp != zk.sqp or a[1][1].rows != zk.rows for a in args):
        raise ValueError("the starts' Z-steps differ in their settings or rows")
    return list(typed_call(admm_loops, dyn, boxes, handles, zk._replace(data=data), start, stop))


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
        compiled = kernel.overloads.get(tuple(map(kernel.typeof_pyval, args)))  # None: numba converted the arguments
        ENTRIES[key] = kernel if compiled is None else compiled.entry_point
        return out
    return ENTRIES[key](*args)


def solved(out: Loop, solvers: Solvers):
    """(ADMMState, Solve) of admm_loop's Loop for a solve with these solvers; SolverFailure if DAQP failed in it."""
    it, info, zs = out.it, out.info, solvers.zstep
    optimal(it.Z, out.flag)
    zinfo = {**info._asdict(), "infeasible": info.slack > zs.s.slack_tol}
    zstate = None if it.fresh else ZState(it.radius, it.lin[:3])
    return (ADMMState(it.Delta, it.alpha, it.Z, it.mu, zstate),
            Solve(out.iters, "converged" if out.converged else "max_iters", out.F_norm, out.change, zinfo))


def compiled_solve(prob: Problem, solvers: Solvers, st: ADMMState, max_iters, tol_F, tol_step):
    """admm_solve in one compiled call (the Z-step a CompiledSQPZStep over a compiled predictor)."""
    return solved(compiled_solves([(prob, solvers, st, max_iters, tol_F, tol_step)])[0], solvers)


def box_solve(qp: DaqpBox, update):
    """The box QP's minimiser from an update kernel's (minimiser, inside, linear term): the closed form, or DAQP's
    (warm-started across the MPC step) when the box is active."""
    x, inside, lin = update
    return x if inside else qp.solve(lin)


def admm_solve(prob: Problem, solvers: Solvers, st: ADMMState, max_iters, tol_F, tol_step):
    """planner.admm.admm_solve with the compiled kernels: sweeps until ||F|| <= tol_F, the iterate change <= tol_step
    and the Z-step's b_i linearised within tol_step (m) of its result, or max_iters; one compiled call (compiled_solve)
    when the core runs the predictor itself."""
    if together(solvers):
        return compiled_solve(prob, solvers, st, max_iters, tol_F, tol_step)
    dyn = tuple(np.ascontiguousarray(M) for M in prob.dyn)
    d_qp, a_qp = DaqpBox(solvers.delta_qp), DaqpBox(solvers.alpha_qp)
    d_box, a_box = box(solvers.delta_qp, prob.Phi_1.q), box(solvers.alpha_qp, prob.Phi_2.q)
    Delta, alpha, Z, mu, zstate = st
    F_norm = step = np.inf
    info, k = {}, 0
    for k in range(1, max_iters + 1):
        new_Delta = box_solve(d_qp, delta_update(dyn, d_box, prob.rho, Delta, alpha, Z, mu))
        new_alpha = box_solve(a_qp, alpha_update(dyn, a_box, prob.rho, new_Delta, alpha, Z, mu))
        new_Z, zstate, info = solvers.zstep(Z, mu, z_residual(dyn, new_Delta, new_alpha, Z), zstate)
        mu, F_norm, step = mu_update(dyn, prob.rho, new_Delta, new_alpha, new_Z, mu, Delta, alpha, Z)
        Delta, alpha, Z = new_Delta, new_alpha, new_Z
        verdict = admm.stopped(F_norm, step, info.get("lin_offset", 0.0), tol_F, tol_step)
        if verdict == CONVERGED:
            return ADMMState(Delta, alpha, Z, mu, zstate), Solve(k, "converged", F_norm, step, info)
        zstate = None if verdict == RESTART else zstate
    return ADMMState(Delta, alpha, Z, mu, zstate), Solve(k, "max_iters", F_norm, step, info)
