"""The paper's Remark 2 recursion over T_p steps, its exact chain rule from local Jacobians, and eq. (8)'s b_i on it.

A predictor maps a window (B, T_obs, SLOTS, 2) of past xy (metres, ego in slot 0) to the next xy (B, SLOTS, 2).
Over the horizon the ego slot is filled from the candidate plan, the other slots from the predictor's own output.
"""
import numpy as np

T_OBS = 8  # observed steps in a predictor's window (paper: T_obs)
SLOTS = 5  # vehicles in a window: the ego (slot 0) and N = 4 others


def _xp(a):
    """numpy or torch, whichever `a` belongs to, so one recursion serves training (torch) and planning (numpy)."""
    if type(a).__module__.startswith("torch"):
        import torch

        return torch
    return np


def rollout(phi, history, ego_future):
    """Predicted xy of every slot (B, T_p, SLOTS, 2): history (B, T_obs, SLOTS, 2), ego_future (B, T_p, 2) = ego xy at 1..T_p."""
    return react(phi, history, lambda window, tau: ego_future[:, tau], ego_future.shape[1])


def react(phi, history, ego_next, T):
    """Predicted xy of every slot (B, T, SLOTS, 2) over T steps from history (B, T_obs, SLOTS, 2), the ego's xy at each
    step tau + 1 given by ego_next(window (B, T_obs, SLOTS, 2) ending at step tau, tau) -> (B, 2): a plan fixed in
    advance, or a feedback policy that answers the others' predicted moves (closed loop)."""
    xp = _xp(history)
    window, out = history, []
    for tau in range(T):
        nxt = xp.concatenate([ego_next(window, tau)[:, None, :], phi(window)[:, 1:]], axis=1)
        out.append(nxt)
        window = xp.concatenate([window[:, 1:], nxt[:, None]], axis=1)
    return xp.stack(out, axis=1)


def chain_rule(J):
    """d values / d ego plan (..., T_p, SLOTS, 2, T_p, 2) of a rollout from the local Jacobians J (..., T_p, SLOTS*2,
    T_obs*SLOTS*2) of the T_p windows it visits (rows: next xy flattened, columns: the window flattened, C order); exact
    through the window shift, the ego slot's derivative the identity on its own step. numpy or torch alike."""
    xp = _xp(J)
    *lead, t_p, rows, cols = J.shape
    batch = 0.0 * J[..., :1, :1, 0]  # zeros (..., 1, 1): broadcasting with it gives the leading axes, traceable by ONNX
    dwindow = batch + xp.zeros((cols, 2 * t_p), dtype=J.dtype)  # d window / d ego plan, rows as J's columns
    units = xp.zeros((t_p, 2, 2 * t_p), dtype=J.dtype)  # d ego xy(tau) / d ego plan
    for tau in range(t_p):
        units[tau, 0, 2 * tau] = units[tau, 1, 2 * tau + 1] = 1.0
    out = []
    for tau in range(t_p):
        dnext = xp.concatenate([batch + units[tau], (J[..., tau, :, :] @ dwindow)[..., 2:, :]], axis=-2)
        out.append(dnext)
        dwindow = xp.concatenate([dwindow[..., rows:, :], dnext], axis=-2)
    out = xp.stack(out, axis=-3)  # (..., T_p, SLOTS*2, 2*T_p)
    if xp is np:
        return out.reshape(*lead, t_p, rows // 2, 2, t_p, 2)
    return out.unflatten(-1, (t_p, 2)).unflatten(-3, (rows // 2, 2))  # a traced reshape would fix the batch size


def rollout_jacobian(phi_jac, history, ego_future, chain=None):
    """Rollout values (T_p, SLOTS, 2) and their derivative w.r.t. the ego plan (T_p, SLOTS, 2, T_p, 2), for one planning state.

    phi_jac(window (1, T_obs, SLOTS, 2)) -> (next (1, SLOTS, 2), J (1, SLOTS*2, T_obs*SLOTS*2)) supplies the local values and
    Jacobians (autodiff, analytic, a surrogate, or differences); composed by chain_rule, or by chain(Js, T_obs) (the
    compiled planner core's).
    """
    history = np.asarray(history, dtype=float)
    ego_future = np.asarray(ego_future, dtype=float)
    t_obs, m, _ = history.shape
    window, values, Js = history, [], []
    for tau in range(len(ego_future)):
        nxt, J = phi_jac(window[None])
        nxt = np.asarray(nxt, dtype=float).reshape(m, 2).copy()
        nxt[0] = ego_future[tau]
        values.append(nxt)
        Js.append(np.asarray(J, dtype=float).reshape(m * 2, t_obs * m * 2))
        window = np.concatenate([window[1:], nxt[None]], axis=0)
    return np.stack(values), chain_rule(np.stack(Js)) if chain is None else chain(np.stack(Js), t_obs)


def ego_xy(Z, T_p):
    """The ego's planned x, y (T_p, 2) in m from the stacked states Z (4T_p,) = [x, y, psi, v] per step."""
    return Z.reshape(T_p, 4)[:, :2]


def b_i(values, R, stretch=1.0, p=2.0):
    """d_i (N, T_p) in m^2: (dx / stretch)^2 + dy^2 - R^2 between the ego's and car i's centres, R = r + r_i + eps (m);
    values (T_p, SLOTS, 2). At stretch 1 the paper's circle, eq. (6); above 1 an ellipse stretch * R long along the road,
    for bodies longer than they are wide. With p > 2 the same semi-axes on a superellipse, R^2 (|dx / (stretch R)|^p +
    |dy / R|^p)^(2/p) - R^2, which hugs two rectangular bodies more closely: p = 2 is the ellipse."""
    sq = (values[:, :1] - values[:, 1:]) ** 2
    if p == 2.0:
        return (sq[..., 0] / stretch**2 + sq[..., 1]).T - R**2  # numpy, torch or CasADi alike: PyGranso back-propagates through it
    S = (sq[..., 0] / (stretch * R) ** 2) ** (p / 2) + (sq[..., 1] / R**2) ** (p / 2)  # |u|^p as (u^2)^(p/2): no abs
    return (R**2 * S ** (2 / p)).T - R**2


def b_i_jacobian(values, grads, R, stretch=1.0, p=2.0):
    """b_i (N*T_p,) and d b_i / d Z (N*T_p, 4T_p), from rollout values (T_p, SLOTS, 2) and d values / d ego xy (T_p, SLOTS, 2, T_p, 2)."""
    T_p = len(values)
    gap = values[:, :1] - values[:, 1:]  # (T_p, N, 2)
    w = shape_weights(gap, R, stretch, p)  # d b_i / d gap = 2 w gap
    dgap = grads[:, :1] - grads[:, 1:]  # (T_p, N, 2, T_p, 2)
    db = 2.0 * np.einsum("tnk,tnkse->ntse", gap * w, dgap)  # (N, T_p, T_p, 2): d b_i(t) / d ego xy(s)
    n = db.shape[0]
    dZ = np.zeros((n, T_p, T_p, 4))
    dZ[..., :2] = db  # b depends on Z only through the ego's x, y
    return b_i(values, R, stretch, p).reshape(-1), dZ.reshape(n * T_p, 4 * T_p)


def shape_weights(gap, R, stretch=1.0, p=2.0):
    """w (..., 2) with d b_i / d gap = 2 w gap for gaps (..., 2) (m) ego minus car: (1 / stretch^2, 1) on the ellipse;
    on the superellipse R^2 S^(2/p - 1) |u|^(p - 2) / a^2 per axis, u = gap / a, a = (stretch R, R), S = sum |u|^p."""
    if p == 2.0:
        return np.array([1.0 / stretch**2, 1.0])
    a = np.array([stretch * R, R])
    u = np.abs(gap / a)
    return R**2 * (u**p).sum(-1, keepdims=True) ** (2 / p - 1) * u ** (p - 2) / a**2


def accelerations(values, history, dt):
    """The others' accelerations along the road (..., N, T_p) in m/s^2 over a rollout: second differences of their x,
    the last two observed steps first; values (..., T_p, SLOTS, 2), history (..., T_obs, SLOTS, 2), step dt (s)."""
    x = np.concatenate([history[..., -2:, 1:, 0], values[..., 1:, 0]], axis=-2)  # (..., T_p + 2, N)
    return np.swapaxes((x[..., 2:, :] - 2.0 * x[..., 1:-1, :] + x[..., :-2, :]) / dt**2, -1, -2)


def braking(values, history, dt):
    """The hardest braking (m/s^2, >= 0) of another car over each rollout values (..., T_p, SLOTS, 2) that follows the
    observed history (T_obs, SLOTS, 2) or (..., T_obs, SLOTS, 2), steps of dt (s)."""
    a = accelerations(values, np.broadcast_to(history, np.shape(values)[:-3] + np.shape(history)[-3:]), dt)
    return np.maximum(0.0, -a.min(axis=(-2, -1), initial=0.0))


def courtesy_jacobian(values, grads, history, dt, b_c):
    """Courtesy rows c_i = a_i + b_c (N*T_p,) in m/s^2, >= 0 when the plan makes nobody brake harder than b_c (m/s^2),
    and d c_i / d Z (N*T_p, 4T_p), from rollout values (T_p, SLOTS, 2) and d values / d ego xy (T_p, SLOTS, 2, T_p, 2);
    rows ordered as b_i_jacobian's."""
    T_p, n = len(values), values.shape[1] - 1
    g = np.concatenate([np.zeros((2, n, T_p, 2)), grads[:, 1:, 0]])  # d x_i / d ego xy, observed steps first
    da = (g[2:] - 2.0 * g[1:-1] + g[:-2]) / dt**2  # (T_p, N, T_p, 2)
    dZ = np.zeros((n, T_p, T_p, 4))
    dZ[..., :2] = da.transpose(1, 0, 2, 3)
    return (accelerations(values, history, dt) + b_c).reshape(-1), dZ.reshape(n * T_p, 4 * T_p)
