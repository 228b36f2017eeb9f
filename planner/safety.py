"""Eq. (6)-(8) for one MPC step: b_i(Z) >= 0 against the gradient source's predictions, linearised with its Jacobian,
and optionally the courtesy rows c_i(Z) = a_i + b_c >= 0: nobody predicted to brake harder than b_c under the plan.

The rows about a linearisation are one kernel (safety_rows, numba's subset): compiled inside the ADMM solve for the
predictors written as kernels (cv, the student: a Predictor), run from Python for the others (a Safety, whose Jacobian
comes from Python)."""
from typing import NamedTuple

import numpy as np
from numba import njit
from numba.extending import overload, register_jitable

from core.rollout import accelerations, b_i, ego_xy
from planner.jit_rollout import compiled_chain, compiled_jacobian, compiled_params, predicted, rows_affine


class Predictor(NamedTuple):
    """A compiled predictor as planner.jit_rollout.predicted takes it (Ws, bs, s) with the step's observed history
    (T_obs, SLOTS, 2) and its last two x (2, SLOTS) for the courtesy rows."""

    Ws: object
    bs: object
    s: np.ndarray
    history: np.ndarray
    x_obs: np.ndarray


class Rows(NamedTuple):
    """The rows as planner.jit_rollout.rows_affine writes them: R (m), stretch, shape p, dt (s), b_c (m/s^2), whether
    there are courtesy rows, and the number of b_i rows."""

    R: float
    stretch: float
    p: float
    dt: float
    b_c: float
    courtesy: bool
    n_b: int


class Lin(NamedTuple):
    """A linearisation of the rows: the ego xy (T_p, 2) it was taken at, the rollout values (T_p, SLOTS, 2), their
    derivative d values / d ego xy (T_p, SLOTS, 2, T_p, 2), and whether one has been taken."""

    ego0: np.ndarray
    values0: np.ndarray
    grads: np.ndarray
    taken: bool


@njit(cache=True)
def offset(Z, ego0):
    """max |ego xy in Z - ego0| (m) over the horizon and x, y; Z (4T_p,), ego0 (T_p, 2)."""
    out = 0.0
    for t in range(len(ego0)):
        out = max(out, abs(Z[4 * t] - ego0[t, 0]), abs(Z[4 * t + 1] - ego0[t, 1]))
    return out


def jacobian_of(pred, ego):
    """Rollout values (T_p, SLOTS, 2) and d values / d ego xy (T_p, SLOTS, 2, T_p, 2) under the ego xy (T_p, 2): from
    Python, a Safety's source's; compiled (the overload below), the kernel predictor's."""
    values, grads = pred.jacobian(pred.history, ego)
    return np.ascontiguousarray(values, float), np.ascontiguousarray(grads, float)


@overload(jacobian_of, inline="always")
def _jacobian_of(pred, ego):
    return lambda pred, ego: predicted(pred.Ws, pred.bs, pred.s, pred.history, ego)


@register_jitable(inline="always")
def safety_rows(pred, rows, lin, Z, reuse_radius):
    """The rows at Z (b_i, then courtesy) and their d / d Z about the linearisation `lin`, taken anew from the predictor
    where Z's ego xy lie more than reuse_radius (m) from it (or none was taken). Returns (b, Jb, lin)."""
    now = lin
    if not lin.taken or offset(Z, lin.ego0) > reuse_radius:
        ego0 = Z.reshape(-1, 4)[:, :2].copy()
        values0, grads = jacobian_of(pred, ego0)
        now = Lin(ego0, values0, grads, True)
    b, Jb = rows_affine(Z, now.ego0, now.values0, now.grads, rows.R, rows.stretch, rows.p, pred.x_obs, rows.dt, rows.b_c,
                        rows.courtesy)
    return b, Jb, now


def trial_rows(pred, rows, lin, Z, reuse_radius):
    """The rows at a trial plan Z: (b, Jb, lin, whether Jb is theirs); from Python, Safety.trial's; compiled (the
    overload below), linearised there, since a kernel predictor's values come with their Jacobian."""
    return pred.trial(rows, lin, Z, reuse_radius)


@overload(trial_rows, inline="always")
def _trial_rows(pred, rows, lin, Z, reuse_radius):
    def linearised(pred, rows, lin, Z, reuse_radius):
        b, Jb, lin = safety_rows(pred, rows, lin, Z, reuse_radius)
        return b, Jb, lin, True

    return linearised


def no_lin(T_p, slots) -> Lin:
    """A Lin of the shapes of T_p steps and `slots` slots with none taken."""
    return Lin(np.zeros((T_p, 2)), np.zeros((T_p, slots, 2)), np.zeros((T_p, slots, 2, T_p, 2)), False)


class Safety:
    """The constraint rows of one MPC step, b_i(Z) (N*T_p, m^2) then, with `courtesy` = (dt s, b_c m/s^2), c_i(Z)
    (N*T_p, m/s^2): the gradient source's predictions from `history`, radius R (m) across the road and stretch * R
    along it, shape exponent p (core.rollout.b_i). A linearisation (Lin) is returned to the caller, who carries it (the
    Z-step, in ADMM's state) for nearby plans to reuse."""

    def __init__(self, source, history, R, T_p, courtesy=None, stretch=1.0, p=2.0):
        self.source, self.history, self.R, self.T_p = source, np.ascontiguousarray(history, float), R, T_p
        self.stretch, self.p = stretch, p
        self.courtesy = courtesy
        self.n_b = (self.history.shape[1] - 1) * T_p  # b_i rows; the courtesy rows follow
        self.rows = self.n_b * (2 if courtesy else 1)
        self.x_obs = np.ascontiguousarray(self.history[-2:, :, 0])
        dt, b_c = courtesy or (1.0, 0.0)  # unread without courtesy rows
        self.spec = Rows(float(R), float(stretch), float(p), float(dt), float(b_c), bool(courtesy), self.n_b)
        self.params = compiled_params(source)  # planner.jit_rollout.predicted's (Ws, bs, s), or None: Python-side Jacobians
        # (history, ego xy) -> (values, d values / d ego xy): compiled, the compiled chain rule over Python-side local
        # Jacobians, or the source's own
        self.jacobian = compiled_jacobian(source) or compiled_chain(source) or source.jacobian

    def kernel(self):
        """The predictor as the kernels read it: a compiled Predictor, or this Safety (its Jacobian from Python)."""
        return self if self.params is None else Predictor(*self.params, self.history, self.x_obs)

    def __call__(self, Z):
        """The rows at Z (b_i flattened, then the courtesy rows), from the predictor's values only."""
        values = self.source.values(self.history, ego_xy(Z, self.T_p)[None])[0]
        b = b_i(values, self.R, self.stretch, self.p).reshape(-1)
        if not self.courtesy:
            return b
        dt, b_c = self.courtesy
        return np.concatenate([b, (accelerations(values, self.history, dt) + b_c).reshape(-1)])

    def offset(self, Z, lin):
        """How far (m, largest over the horizon and x, y) the ego's planned xy in Z lie from the linearisation lin's."""
        return np.inf if lin is None or not lin.taken else offset(Z, lin.ego0)

    def trial(self, rows, lin, Z, reuse_radius):
        """trial_rows from Python: within reuse_radius of lin, or for a source whose values come with the Jacobian at
        little extra cost (`joint`), linearised at Z (kept, since an accepted step is linearised next); else the values
        only (Jb None)."""
        if self.offset(Z, lin) <= reuse_radius or self.source.joint:
            return (*safety_rows(self, rows, lin, Z, reuse_radius), True)
        return self(Z), None, lin, False

    def linearize(self, Z, lin=None, reuse_radius=0.0):
        """The rows at Z (rows,), their derivative d / d Z (rows, 4T_p) and the Lin they come from: lin while the ego's
        plan stays within reuse_radius (m) of where it was taken (0: only at the same plan), else a new one from the
        gradient source (None: none yet)."""
        Z = np.ascontiguousarray(Z, float)
        return safety_rows(self, self.spec, no_lin(self.T_p, self.history.shape[1]) if lin is None else lin, Z,
                           reuse_radius)
