"""Windows a planner asks about: dataset windows whose newest ego positions follow another plan, and random box windows.

Inside the planner's rollout the last k ego positions of a window come from the candidate plan, so they drift
from what was driven: a lateral rate, a speed change and a longitudinal offset; the others' newest positions are
the predictor's own outputs, which we mimic by scaling their speeds. All quantities in metres and metres per step.
"""
import numpy as np


def planner_like(window, rng, lat_rate, dv, dx, other_speed):
    """Perturbed copies (B, T_obs, SLOTS, 2) of dataset windows; rates in m/step, offsets in m, other_speed a fraction."""
    w = np.array(window, dtype=float, copy=True)
    b, t_obs, m, _ = w.shape
    k = rng.integers(1, t_obs + 1, size=b)  # how many of the newest ego positions come from the plan
    steps = np.clip(np.arange(t_obs)[None] - (t_obs - k[:, None]) + 1, 0, None)  # (B, T_obs) steps into the plan
    w[:, :, 0, 1] += rng.uniform(-lat_rate, lat_rate, (b, 1)) * steps
    w[:, :, 0, 0] += rng.uniform(-dv, dv, (b, 1)) * steps + rng.uniform(-dx, dx, (b, 1)) * (steps > 0)
    scale = 1.0 + rng.uniform(-other_speed, other_speed, (b, 1, m - 1, 1))
    w[:, :, 1:] = w[:, :1, 1:] + scale * (w[:, :, 1:] - w[:, :1, 1:])
    return w


def box_windows(n, rng, box, t_obs=8, m=5):
    """Off-distribution windows (n, T_obs, SLOTS, 2) inside the certificate's box: random positions, speeds, accelerations."""
    start = np.stack([rng.uniform(-box["x"], box["x"], (n, m)), rng.uniform(-box["y"], box["y"], (n, m))], -1)
    v0 = np.stack([rng.uniform(0.0, box["dx"], (n, m)), rng.uniform(-box["dy"], box["dy"], (n, m))], -1)
    acc = rng.normal(0.0, 0.05, (n, t_obs - 1, m, 2))
    vel = np.clip(v0[:, None] + np.cumsum(acc, axis=1), [0.0, -box["dy"]], [box["dx"], box["dy"]])
    w = np.concatenate([start[:, None], start[:, None] + np.cumsum(vel, axis=1)], axis=1)
    # keep the window inside the box by shifting each car's track back when it drifts out
    lo, hi = w.min(axis=1, keepdims=True), w.max(axis=1, keepdims=True)
    lim = np.array([box["x"], box["y"]])
    return w - np.clip(hi - lim, 0, None) + np.clip(-lim - lo, 0, None)
