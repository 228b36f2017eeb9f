"""Accuracy where the planner uses it: the composed d b_i / d Z on held-out planning states.

Every Jacobian source is composed with the same rollout values (the source predictor's phi, computed once, batched,
for all states), so the figures measure the gradient alone. The direct term of d b_i / d Z (the ego's own xy) is exact for every source; the `react_*`
figures isolate what the predictor contributes, d p_i / d Z of the other cars.

The `ramp_*` figures score the same derivatives along plan changes the ego can drive (`ramps`: a change of speed from
one step on) instead of along single coordinates of Z. The difference matters: a predictor reads velocities and
accelerations, so its derivative along a zig-zag of one step is large and changes within centimetres, while along a
ramp the teacher's first-order response matches its own rollout's (docs/archive/2026-11-studies.md, "The gradient the planner needs").
"""
import numpy as np

from core import stats
from core.rollout import b_i_jacobian, rollout_jacobian

ENDS = ("", "_lo", "_hi")  # a score's mean, then the ends of its 95% interval
HEADLINE = ("grad_rel_err", "react_rel_err", "react_wrel_err", "ramp_grad_rel_err", "ramp_react_rel_err")  # the scores
# reported for a source beside the same scores of the baselines (the job's log line, compare's baseline columns)


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


def ramps(T_p):
    """(T_p, T_p) m: column k is the ego's change of position at steps 1..T_p when its speed changes by 1 m per step
    from step k + 1 on."""
    k = np.arange(T_p)
    return np.maximum(0.0, k[:, None] - k[None, :] + 1.0)


def along_ramps(G):
    """A derivative d / d (ego xy) (..., T_p, 2) -> its value along each ramp (..., T_p, 2), per axis: G @ ramps(T_p).
    numpy or torch alike."""
    B = ramps(G.shape[-2])
    if type(G).__module__.startswith("torch"):
        import torch

        return torch.einsum("...sa,sk->...ka", G, torch.as_tensor(B, dtype=G.dtype))
    return np.einsum("...sa,sk->...ka", G, B)


def dZ(phi_jac, history, ego_future, R):
    """d b_i / d Z (N*T_p, 4*T_p) m^2/m and d p_i / d ego xy (T_p, N, 2, T_p, 2) of one planning state."""
    values, grads = rollout_jacobian(phi_jac, history, ego_future)
    return b_i_jacobian(values, grads, R)[1], grads[:, 1:]


def views(G, react):
    """{key: derivative} scored for one state: d b_i / d Z and the reaction along single coordinates, and both along
    ramps (d b_i / d Z's columns of the ego's xy; those of psi and v are zero)."""
    T_p = react.shape[-2]
    xy = G.reshape(len(G), T_p, 4)[..., :2]
    return {"grad": G, "react": react, "ramp_grad": along_ramps(xy), "ramp_react": along_ramps(react)}


def cosine(a, b):
    """Cosine similarity of two arrays, flattened."""
    return float(np.vdot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))


def relative(a, b):
    """||a - b|| / ||b||, flattened."""
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def weighted(errors, truths, resamples=1000, seed=0):
    """(sum errors / sum truths, lo, hi): the states' relative errors weighted by the size of the truth, with the 95%
    percentile-bootstrap interval over states. Unlike the mean of per-state ratios it is not dominated by states where
    the truth is nearly zero (a reaction of a car the plan does not touch)."""
    pairs = [np.array([[e, t]]) for e, t in zip(errors, truths)]
    ratio = lambda a: a[:, 0].sum() / max(a[:, 1].sum(), 1e-300)
    lo, hi = stats.bootstrap(pairs, ratio, resamples, seed, within=False)
    return ratio(np.concatenate(pairs)), float(lo), float(hi)


def gradient_accuracy(windows, nexts, J, J_hats: dict, histories, ego_futures, R):
    """Per Jacobian source name: grad_cosine, grad_rel_err, react_cosine, react_rel_err and their ramp_* twins (the
    module's doc), each (mean, lo, hi) over the states (Student-t 95% interval); and each *_wrel_err, the relative error
    weighted by the truth's size (`weighted`).

    windows (n, T_p, T_obs, SLOTS, 2), nexts (n, T_p, SLOTS, 2) and the exact J (n, T_p, SLOTS*2, T_obs*SLOTS*2) are the source's on the
    windows its rollout visits; each of J_hats {name: (n, T_p, SLOTS*2, T_obs*SLOTS*2)} replaces J in the same rollout, or
    {name: (windows, nexts, J)} is another predictor's rollout with Jacobians on its windows (the surrogate over the
    student's values), scored against the source's: its values' error counts too.
    """
    scores = {name: {} for name in J_hats}
    norms = {name: {} for name in J_hats}  # key: [(||error||, ||truth||) per state]
    rollouts = {name: hat if isinstance(hat, tuple) else (windows, nexts, hat) for name, hat in J_hats.items()}
    for i, (history, ego_future) in enumerate(zip(histories, ego_futures)):
        truth = views(*dZ(replay(windows[i], nexts[i], J[i]), history, ego_future, R))
        for name, (w, nxt, J_hat) in rollouts.items():
            hat = views(*dZ(replay(w[i], nxt[i], J_hat[i]), history, ego_future, R))
            for key, exact in truth.items():
                scores[name].setdefault(f"{key}_cosine", []).append(cosine(hat[key], exact))
                scores[name].setdefault(f"{key}_rel_err", []).append(relative(hat[key], exact))
                norms[name].setdefault(key, []).append((np.linalg.norm(hat[key] - exact), np.linalg.norm(exact)))
    out = {name: {k: stats.mean_ci(v) for k, v in s.items()} for name, s in scores.items()}
    for name, per_key in norms.items():
        out[name].update({f"{key}_wrel_err": weighted(*zip(*pairs)) for key, pairs in per_key.items()})
    return out
