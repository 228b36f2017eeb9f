"""Compiled (numba) Remark-2 rollout with its exact chain rule for the predictors the compiled core runs itself (constant
velocity and the GELU student from its float64 weights), and b_i with its Jacobian about a linearisation; the layouts of
core.rollout (metres throughout), which stays the tested reference."""
from functools import lru_cache

import numpy as np
from numba import njit

from core.jit_linalg import matmul, matvec
from core.rollout import rollout_jacobian
from distill.student import cv_phi_jac, phi_jac, typed


@njit(cache=True)
def chain_rule(Js, T_obs):
    """d values / d ego plan (T_p, SLOTS, 2, T_p, 2) from the local Jacobians Js (T_p, SLOTS*2, T_obs*SLOTS*2) of the
    windows a rollout visits; as core.rollout.chain_rule, skipping the window rows no plan step has reached yet."""
    T_p, rows, cols = Js.shape
    dwindow = np.zeros((cols, 2 * T_p))
    out = np.zeros((T_p, rows, 2 * T_p))
    for tau in range(T_p):
        first = (T_obs - min(tau, T_obs)) * rows  # rows above hold history: zero derivative
        out[tau, 0, 2 * tau] = out[tau, 1, 2 * tau + 1] = 1.0  # the ego slot is the plan itself
        if first < cols:
            dnext = matmul(Js[tau, 2:, first:], dwindow[first:])
            for r in range(rows - 2):
                for c in range(2 * T_p):
                    out[tau, r + 2, c] = dnext[r, c]
        for r in range(cols):  # the window moves on by one step: its rows shift up, the new step enters at the bottom
            for c in range(2 * T_p):
                dwindow[r, c] = dwindow[r + rows, c] if r < cols - rows else out[tau, r - cols + rows, c]
    return out.reshape(T_p, rows // 2, 2, T_p, 2)


@njit(cache=True)
def step_window(window, nxt, ego):
    """The next window (T_obs, SLOTS, 2): drop the oldest step, append nxt with the ego slot set to the plan's xy."""
    T_obs, M, _ = window.shape
    out = np.empty_like(window)
    for t in range(T_obs):
        for m in range(M):
            for k in range(2):
                out[t, m, k] = window[t + 1, m, k] if t < T_obs - 1 else (ego[k] if m == 0 else nxt[m, k])
    return out


@njit(cache=True)
def keep(Js, values, tau, J, window):
    """Store step tau's local Jacobian J and its window's last step (the rollout's values at tau)."""
    for r in range(J.shape[0]):
        for c in range(J.shape[1]):
            Js[tau, r, c] = J[r, c]
    for m in range(window.shape[1]):
        for k in range(2):
            values[tau, m, k] = window[-1, m, k]


@njit(cache=True)
def cv_rollout(history, ego):
    """Constant-velocity rollout values (T_p, SLOTS, 2) and d values / d ego plan (T_p, SLOTS, 2, T_p, 2)."""
    T_p = len(ego)
    T_obs, M, _ = history.shape
    values, Js, window = np.empty((T_p, M, 2)), np.empty((T_p, 2 * M, T_obs * 2 * M)), history
    for tau in range(T_p):
        nxt, J = cv_phi_jac(window)
        window = step_window(window, nxt, ego[tau])
        keep(Js, values, tau, J, window)
    return values, chain_rule(Js, T_obs)


@njit(cache=True)
def student_rollout(Ws, bs, s, history, ego):
    """The student's rollout values (T_p, SLOTS, 2) and d values / d ego plan (T_p, SLOTS, 2, T_p, 2)."""
    T_p = len(ego)
    T_obs, M, _ = history.shape
    values, Js, window = np.empty((T_p, M, 2)), np.empty((T_p, 2 * M, T_obs * 2 * M)), history
    for tau in range(T_p):
        nxt, J = phi_jac(Ws, bs, s, window)
        window = step_window(window, nxt, ego[tau])
        keep(Js, values, tau, J, window)
    return values, chain_rule(Js, T_obs)


@njit(cache=True, inline="always")
def predicted(Ws, bs, s, history, ego):
    """Rollout values (T_p, SLOTS, 2) and d values / d ego plan (T_p, SLOTS, 2, T_p, 2) of a predictor the compiled core
    runs itself (compiled_params): constant velocity when s is empty, else the student from its float64 weights."""
    if len(s) == 0:
        return cv_rollout(history, ego)
    return student_rollout(Ws, bs, s, history, ego)


@lru_cache(maxsize=1)
def cv_params():
    """`predicted`'s placeholders for constant velocity: one 1 x 1 layer, no head scale."""
    return typed([np.zeros((1, 1))]), typed([np.zeros(1)]), np.zeros(0)


KERNELS = {"cv": lambda predictor: cv_params(), "student": lambda predictor: predictor.kernel,
           "student_hyp": lambda predictor: predictor.kernel}  # `predicted`'s weights per compiled predictor


def compiled_params(source):
    """`predicted`'s (Ws, bs, s) for a source that declares it runs compiled (planner.gradients: cv, the student); None
    for the others, whose Jacobians come from Python."""
    return values_params(source.predictor) if source.compiled else None


def values_params(predictor):
    """`predicted`'s (Ws, bs, s) for a predictor whose rollout the compiled core writes (cv, the student), whichever
    source differentiates it (the surrogate over the student: the values compiled, the Jacobians learned); else None."""
    name = getattr(predictor, "name", None)
    return KERNELS[name](predictor) if name in KERNELS else None


def compiled_jacobian(source):
    """jacobian(history, ego) -> (values, d values / d ego) compiled for the sources of compiled_params; None for the
    others, whose own `jacobian` the compiled core calls."""
    params = compiled_params(source)
    if params is None:
        return None
    return lambda history, ego: predicted(*params, np.ascontiguousarray(history, float), np.ascontiguousarray(ego, float))


def values(source, history, ego):
    """The predictor's rollout values (T_p, SLOTS, 2) under one ego plan's xy (T_p, 2): by the compiled rollout for a
    source that runs compiled (values and J in ~0.1 ms), else from the source's own rollout."""
    compiled = compiled_jacobian(source)
    return compiled(history, ego)[0] if compiled else source.values(history, ego[None])[0]


def compiled_chain(source):
    """jacobian(history, ego) for a source whose local Jacobians come from Python (planner.gradients: another exact
    predictor, a fused surrogate export): its windows' values and Jacobians as the source has them, composed by the
    compiled chain_rule; None for the others (autodiff, differences: their own `jacobian`)."""
    phi_jac = source.local_jacobians()
    return None if phi_jac is None else lambda history, ego: rollout_jacobian(phi_jac, history, ego, chain=chain_rule)


@njit(cache=True)
def affine_values(Z, ego0, values0, grads):
    """The rollout values (T_p, SLOTS, 2) at the plan Z (4T_p,), affine about a linearisation (ego0 (T_p, 2), values0,
    grads (T_p, SLOTS, 2, T_p, 2)); the ego slot moves exactly with Z."""
    T_p, M = values0.shape[0], values0.shape[1]
    d = (Z.reshape(T_p, 4)[:, :2] - ego0).reshape(-1)
    return values0 + matvec(grads.reshape(T_p * M * 2, T_p * 2), d).reshape(T_p, M, 2)


@njit(cache=True)
def rows_affine(Z, ego0, values0, grads, R, stretch, p, x_obs, dt, b_c, courtesy):
    """The Safety's rows at the plan Z (4T_p,) and their d / d Z (rows, 4T_p), with the others' rollout values affine
    about a linearisation (ego0, values0 (T_p, SLOTS, 2), grads (T_p, SLOTS, 2, T_p, 2)), the ego slot moving exactly
    with Z: b_i (N*T_p, m^2; core.rollout.b_i's shape: R m, stretch, p), then with `courtesy` c_i = a_i + b_c (N*T_p, m/s^2; x_obs (2, SLOTS): the last two
    observed x, dt s). As core.rollout.b_i_jacobian and courtesy_jacobian, causal blocks only."""
    T_p, M = values0.shape[0], values0.shape[1]
    N = M - 1
    n_b = N * T_p
    values = affine_values(Z, ego0, values0, grads)
    a_x, w_x = stretch * R, 1.0 / stretch**2
    b, Jb = np.empty(2 * n_b if courtesy else n_b), np.zeros((2 * n_b if courtesy else n_b, 4 * T_p))
    for n in range(N):
        for t in range(T_p):
            row = n * T_p + t
            g0, g1 = values[t, 0, 0] - values[t, n + 1, 0], values[t, 0, 1] - values[t, n + 1, 1]
            if p == 2.0:
                b[row], w0, w1 = g0 * g0 * w_x + g1 * g1 - R * R, w_x, 1.0
            else:  # core.rollout.shape_weights
                u0, u1 = abs(g0) / a_x, abs(g1) / R
                S = u0**p + u1**p
                b[row] = R * R * S ** (2.0 / p) - R * R
                w0 = R * R * S ** (2.0 / p - 1.0) * u0 ** (p - 2.0) / (a_x * a_x)
                w1 = S ** (2.0 / p - 1.0) * u1 ** (p - 2.0)
            if courtesy:
                x_1 = values[t - 1, n + 1, 0] if t >= 1 else x_obs[1, n + 1]
                x_2 = values[t - 2, n + 1, 0] if t >= 2 else x_obs[t, n + 1]
                b[n_b + row] = (values[t, n + 1, 0] - 2.0 * x_1 + x_2) / dt**2 + b_c
            for s_ in range(t + 1):  # a rollout is causal: step t's values never depend on later plan steps
                for e in range(2):
                    Jb[row, 4 * s_ + e] = 2.0 * (g0 * w0 * (grads[t, 0, 0, s_, e] - grads[t, n + 1, 0, s_, e])
                                                 + g1 * w1 * (grads[t, 0, 1, s_, e] - grads[t, n + 1, 1, s_, e]))
                    if courtesy:
                        d = grads[t, n + 1, 0, s_, e]
                        if t >= 1:
                            d -= 2.0 * grads[t - 1, n + 1, 0, s_, e]
                        if t >= 2:
                            d += grads[t - 2, n + 1, 0, s_, e]
                        Jb[n_b + row, 4 * s_ + e] = d / dt**2
    return b, Jb
