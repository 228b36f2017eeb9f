"""The one place DAQP (a dual active-set solver for small dense QPs) is called, by planner.admm's loop: the Delta- and
alpha-update box QPs when their closed-form minimiser leaves the box, and the Z-step's QPs with b_i's linearisation as
soft constraints priced by an L1 penalty, warm-started from the last working set within one ADMM solve.

DAQP's C functions are called from numba (`solve`), so a whole ADMM solve runs as one compiled call (planner.admm):
the library is the daqp wheel's own extension module, its structs laid out as daqp 0.11's csrc/include/types.h (the
version is pinned; tests/test_compiled_core.py checks these solves against daqp.Model's)."""
import ctypes
import weakref
from functools import lru_cache
from typing import NamedTuple

import daqp
import llvmlite.binding
import numpy as np
from numba import njit, types

from planner.qp import SolverFailure

INF = 1e30  # DAQP's infinity: bounds at or beyond it are absent
SOFT_RHO = 1e6  # DAQP's reciprocal quadratic weight on a soft violation s: s^2 / (2 SOFT_RHO) is negligible beside the L1 price
SOFT = 8  # DAQP's sense flag of a soft constraint
UPDATE_RINV, UPDATE_M, UPDATE_V, UPDATE_D, UPDATE_SENSE = 1, 2, 4, 8, 16  # daqp_update_ldp's mask bits (constants.h)
WORK_SENSE = 8  # DAQPWorkspace.sense (the working set) in int64 words: after qp*, n, m, ms, M*, dupper*, dlower*, Rinv*, v*
QP_SENSE = 7  # DAQPProblem.sense in int64 words: after n, m, ms, H*, f*, A*, bupper*, blower*
RES_EXITFLAG = 8  # DAQPResult.exitflag in int32 words: after x*, lam*, fval, soft_slack

SOLVES = np.zeros(1, np.int64)  # DAQP solves in this process, counted by every handle (the bench's profile reads it)

llvmlite.binding.load_library_permanently(daqp.__file__)  # numba links the symbols below by name, also from its cache
_lib = ctypes.CDLL(daqp.__file__)
_update = types.ExternalFunction("daqp_update_ldp", types.int32(types.int32, types.uint64, types.uint64))
_solve = types.ExternalFunction("daqp_solve", types.void(types.uint64, types.uint64))


class Handle(NamedTuple):
    """One DAQP workspace and the arrays its problem struct points at, all owned here; numba reads and writes them."""

    work: np.ndarray  # DAQPWorkspace (int64 words, more than its size)
    qp: np.ndarray  # DAQPProblem (int64 words)
    res: np.ndarray  # DAQPResult (int64 words), x and lam pointing at the arrays below
    x: np.ndarray  # (n,) the solution
    H: np.ndarray  # (n, n)
    f: np.ndarray  # (n,)
    A: np.ndarray  # (rows, n)
    bu: np.ndarray  # (n + rows,) [box; rows] upper bounds, the rows' absent
    bl: np.ndarray  # (n + rows,)
    sense: np.ndarray  # (n + rows,) int32: the cold start's constraint senses
    calls: np.ndarray  # SOLVES, the process-wide count every handle adds its solves to


def _free(address: int):
    """Release what DAQP allocated inside the workspace at `address`."""
    _lib.free_daqp_workspace(ctypes.c_void_p(address))
    _lib.free_daqp_ldp(ctypes.c_void_p(address))


def handle(n: int, rows: int = 0, soft: bool = False, price: float = 0.0) -> Handle:
    """A DAQP workspace for min 1/2 x'Hx + f'x s.t. a box on x (n,) and `rows` rows c_lo <= Ax, soft (priced `price`
    per unit of violation) or hard; set up on a placeholder H, since each ADMM solve's first `solve` (cold) sets its own."""
    m = n + rows
    h = Handle(np.zeros(1024, np.int64), np.zeros(10, np.int64), np.zeros(8, np.int64), np.zeros(n), np.eye(n),
               np.zeros(n), np.zeros((rows, n)), np.full(m, INF), np.full(m, -INF),
               np.concatenate([np.zeros(n), np.full(rows, SOFT if soft else 0)]).astype(np.int32), SOLVES)
    h.qp.view(np.int32)[:3] = n, m, n
    h.qp[2:8] = [a.ctypes.data for a in (h.H, h.f, h.A, h.bu, h.bl, h.sense)]
    h.res[0] = h.x.ctypes.data  # res.lam stays NULL: no multipliers wanted
    work = ctypes.c_void_p(h.work.ctypes.data)
    _lib.allocate_daqp_settings(work)
    # by address: an argument holding the array would keep it alive for ever; numpy clears an array's weak references
    # before it frees its buffer, so the workspace is still readable when _free runs
    weakref.finalize(h.work, _free, h.work.ctypes.data)
    if _lib.setup_daqp_main(ctypes.c_void_p(h.qp.ctypes.data), work, ctypes.byref(ctypes.c_double()), 0) < 0:
        raise SolverFailure(f"DAQP could not set up a QP of {n} variables and {rows} rows")
    if soft:
        rho, w = np.full(m, SOFT_RHO), np.full(m, float(price))
        p = lambda a: ctypes.c_void_p(a.ctypes.data)
        if not _lib.daqp_set_soft_weights(work, p(rho), p(rho), p(w), p(w)):
            raise SolverFailure("this daqp build has no per-constraint soft weights")
    return h


@lru_cache(maxsize=None)
def shared(role: str, n: int, rows: int = 0, soft: bool = False, price: float = 0.0) -> Handle:
    """One `handle` per role and shape for a whole process: for planner.admm's solves, each of which starts
    it cold and is done with it when it returns (setting up a workspace costs about as much as a tenth of a step)."""
    return handle(n, rows, soft, price)


@njit(cache=True)
def solve(h, cold, H, f, lo, hi, A, c_lo):
    """The minimiser x (n,) of 1/2 x'Hx + f'x on the box lo <= x <= hi with rows c_lo <= Ax, and DAQP's exit flag (1:
    optimal; 2: with soft rows violated; < 1: failed, x NaN). cold: a new H (factorised) and the working set reset, as a
    fresh set-up; else H is the last cold solve's and the last working set starts the solve (daqp.Model.update)."""
    n = len(f)
    h.calls[0] += 1
    h.f[:] = f
    h.bu[:n] = hi
    h.bl[:n] = lo
    if len(c_lo):
        h.A[:, :] = A
        h.bl[n:] = c_lo
    mask = UPDATE_M | UPDATE_V | UPDATE_D | UPDATE_SENSE
    if cold:
        h.H[:, :] = H
        h.qp[QP_SENSE] = h.sense.ctypes.data
        mask |= UPDATE_RINV
    else:
        h.qp[QP_SENSE] = h.work[WORK_SENSE]
    flag = _update(mask, h.work.ctypes.data, h.qp.ctypes.data)
    if flag >= 0:
        _solve(h.res.ctypes.data, h.work.ctypes.data)
        flag = h.res.view(np.int32)[RES_EXITFLAG]
    x = h.x.copy()
    if flag < 1 or not np.isfinite(np.sum(x)):
        x[:] = np.nan
        flag = min(flag, 0)
    return x, flag


def optimal(x, flag):
    """x if DAQP found an optimum (1; 2: with soft constraints violated), else SolverFailure naming its exit flag."""
    if flag < 1:
        raise SolverFailure(f"DAQP exit flag {flag}")
    return x


NO_ROWS = (np.zeros((0, 1)), np.zeros(0))  # A, c_lo of a box QP
