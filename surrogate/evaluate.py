"""Accuracy where the planner uses it: the composed d b_i / d Z on held-out planning states.

Every Jacobian source is composed with the same rollout values (the source predictor's phi, computed once, batched,
for all states), so the figures measure the gradient alone. The direct term of d b_i / d Z (the ego's own xy) is exact for every source; the `react_*`
figures isolate what the predictor contributes, d p_i / d Z of the other cars.
"""
import numpy as np

from core import stats
from core.rollout import b_i_jacobian, rollout_jacobian

ENDS = ("", "_lo", "_hi")  # a score's mean, then the ends of its 95% interval


def metric(key: str, source: str = "", end: str = "") -> str:
    """The logged name of a gradient score: `key` (grad_rel_err, ...) of the Jacobian source `source` ("" the surrogate,
    "_cv", "_mean", "_student"), its mean or an end of its interval (ENDS): metric("grad_rel_err", "_cv", "_lo")."""
    return f"{key}{source}{end}"


def replay(windows, nexts, Js):
    """A phi_jac for rollout_jacobian that hands back batched results (T_p, ...) step by step, checking each window."""
    steps = iter(zip(windows, nexts, Js))

    def phi_jac(window):
        w, nxt, J = next(steps)
        if not np.allclose(window[0], w, atol=1e-3):
            raise RuntimeError("rollout visited a window other than the precomputed one")
        return nxt[None], J[None]

    return phi_jac


def dZ(phi_jac, history, ego_future, R):
    """d b_i / d Z (N*T_p, 4*T_p) m^2/m and d p_i / d ego xy (T_p, N, 2, T_p, 2) of one planning state."""
    values, grads = rollout_jacobian(phi_jac, history, ego_future)
    return b_i_jacobian(values, grads, R)[1], grads[:, 1:]


def cosine(a, b):
    """Cosine similarity of two arrays, flattened."""
    return float(np.vdot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))


def relative(a, b):
    """||a - b|| / ||b||, flattened."""
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def gradient_accuracy(windows, nexts, J, J_hats: dict, histories, ego_futures, R):
    """Per Jacobian source name: grad_cosine, grad_rel_err, react_cosine, react_rel_err, each (mean, lo, hi) over the
    states (Student-t 95% interval).

    windows (n, T_p, T_obs, SLOTS, 2), nexts (n, T_p, SLOTS, 2) and the exact J (n, T_p, SLOTS*2, T_obs*SLOTS*2) are the source's on the
    windows its rollout visits; each of J_hats {name: (n, T_p, SLOTS*2, T_obs*SLOTS*2)} replaces J in the same rollout.
    """
    scores = {name: {"grad_cosine": [], "grad_rel_err": [], "react_cosine": [], "react_rel_err": []} for name in J_hats}
    for i, (history, ego_future) in enumerate(zip(histories, ego_futures)):
        G, react = dZ(replay(windows[i], nexts[i], J[i]), history, ego_future, R)
        for name, J_hat in J_hats.items():
            G_hat, react_hat = dZ(replay(windows[i], nexts[i], J_hat[i]), history, ego_future, R)
            s = scores[name]
            s["grad_cosine"].append(cosine(G_hat, G))
            s["grad_rel_err"].append(relative(G_hat, G))
            s["react_cosine"].append(cosine(react_hat, react))
            s["react_rel_err"].append(relative(react_hat, react))
    return {name: {k: stats.mean_ci(v) for k, v in s.items()} for name, s in scores.items()}

