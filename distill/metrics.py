"""Prediction metrics on a dataset split, in metres, over the other cars (slots 1..N): 1-step and T_p-step rollout ADE/FDE.

The rollout is the planner's recursion (core.rollout.rollout) with the ego's recorded future fed in. The yield
subset holds the windows of episodes in which some driver brakes for the ego at least once.
"""
import time

import numpy as np

from core.rollout import rollout


def rollout_cases(a: dict, t_p: int):
    """history (n, T_obs, SLOTS, 2), ego future (n, T_p, 2), others' future (n, T_p, N, 2), yield flag (n,) from split arrays:
    every window whose run goes on T_p steps with the same cars in its slots."""
    runs = list(zip(a["episode"], a["branch"], a["step"]))  # a counterfactual branch is a run of its own
    key = {r: i for i, r in enumerate(runs)}
    starts, futures = [], []
    for i, (e, b, s) in enumerate(runs):
        chain = [key.get((e, b, s + k)) for k in range(t_p)]
        if None not in chain and (a["ids"][chain] == a["ids"][i]).all():
            starts.append(i)
            futures.append(a["Y"][chain])
    starts, futures = np.array(starts, dtype=int), np.array(futures, dtype=float).reshape(-1, t_p, *a["Y"].shape[1:])
    return a["X"][starts].astype(float), futures[:, :, 0], futures[:, :, 1:], yield_windows(a)[starts]


def yield_windows(a: dict):
    """(n,) bool: the window belongs to an episode where some other driver yields to the ego."""
    episodes = np.unique(a["episode"][a["yielding"][:, 1:].any(axis=1)])
    return np.isin(a["episode"], episodes)


def ade(predictor, a: dict, t_p: int, chunk=2048):
    """ade_1step_m, ade_rollout_m, fde_rollout_m on all windows and on the yield-episode subset (suffix _yield)."""
    X, Y = a["X"].astype(float), a["Y"].astype(float)
    pred = np.concatenate([predictor.phi(X[i : i + chunk]) for i in range(0, len(X), chunk)])
    e1 = np.linalg.norm(pred[:, 1:] - Y[:, 1:], axis=-1).mean(axis=1)
    hist, ego, others, yl = rollout_cases(a, t_p)
    out = rollout(predictor.phi, hist, ego)[:, :, 1:]
    ek = np.linalg.norm(out - others, axis=-1).mean(axis=2)  # (n, T_p)
    y1 = yield_windows(a)
    m = {"ade_1step_m": e1.mean(), "ade_rollout_m": ek.mean(), "fde_rollout_m": ek[:, -1].mean()}
    m.update({"ade_1step_m_yield": e1[y1].mean(), "ade_rollout_m_yield": ek[yl].mean(), "fde_rollout_m_yield": ek[yl, -1].mean()})
    return {k: float(v) for k, v in m.items()}


def jac_rel_err(predictor, reference, windows):
    """||J - J_ref||_F / ||J_ref||_F over the others' rows of all windows stacked, overall and on the ego's input columns.

    Stacked rather than averaged per window: windows where the reference's interaction gradient is nearly zero
    (cars far from the ego) would otherwise dominate the ego-column figure.
    """
    _, J = predictor.phi_jac(windows)
    _, R = reference.phi_jac(windows)
    J, R = J[:, 2:].reshape(len(J), 8, -1, 5, 2), R[:, 2:].reshape(len(R), 8, -1, 5, 2)  # (B, 8 rows, T_obs, SLOTS, 2)
    rel = lambda a, b: np.linalg.norm(a - b) / np.linalg.norm(b)
    return {"jac_rel_err": float(rel(J, R)), "jac_rel_err_ego": float(rel(J[..., 0, :], R[..., 0, :]))}


def time_us(fn, arg, repeats=200, budget_s=float("inf")):
    """Median wall time of fn(arg) in microseconds, after a warm-up; stops early once budget_s seconds are spent."""
    fn(arg)
    times = []
    while len(times) < repeats and sum(times) < budget_s:
        t0 = time.perf_counter()
        fn(arg)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e6)


def forward_us(predictor, window, repeats=200):
    """Median wall time of one phi call on a single window, microseconds."""
    return time_us(predictor.phi, np.asarray(window[:1], dtype=float), repeats)
