"""The NNMPC baseline (Bae et al. 2022): a finite set of lane-change curves plus keep-lane, each with several speed
profiles, rolled out with the same predictor, checked with the same b_i; the safe candidate of least J wins.

A lane change follows the quintic y(x) from the ego's y to the target over a length L (zero heading and curvature at
both ends, so its curvature is cubic in arc length to first order: a cubic spiral), tracked by pure pursuit.
"""
import numpy as np

from core.rollout import b_i, ego_xy
from data import bicycle
from planner import admm
from planner.mpc import Observation, Settings, StepResult, costs
from planner.safeguard import fallback, observed


def lateral_path(x, x0, y0, y1, L):
    """y (m) of the quintic lane-change curve from (x0, y0) to y1 over length L (m)."""
    xi = np.clip((x - x0) / L, 0.0, 1.0)
    return y0 + (y1 - y0) * xi**3 * (10 - 15 * xi + 6 * xi**2)


def track(s: Settings, z0, y1, L, accel, lookahead=(2.0, 0.6)):
    """Controls Delta, alpha (K, T_p) and states Z (K, 4T_p) of K candidates following the curves to y1 (K,) over
    lengths L (K,) by pure pursuit, each with its constant acceleration accel (K,)."""
    z = np.repeat(np.asarray(z0, float)[None], len(y1), 0)
    Delta, alpha, Z = [], [], []
    wheelbase = s.params.l_f + s.params.l_r
    for _ in range(s.T_p):
        Ld = np.maximum(lookahead[0], lookahead[1] * z[:, 3])
        target = lateral_path(z[:, 0] + Ld, z0[0], z0[1], y1, L)
        bearing = np.arctan2(target - z[:, 1], Ld) - z[:, 2]
        d = np.clip(np.arctan(2 * wheelbase * np.sin(bearing) / Ld), *s.delta_box)
        a = np.clip(accel, (s.v_box[0] - z[:, 3]) / s.params.dt, (s.v_box[1] - z[:, 3]) / s.params.dt)
        z = bicycle.step(z, np.stack([d, a], -1), s.params)
        Delta.append(d)
        alpha.append(a)
        Z.append(z)
    return np.stack(Delta, 1), np.stack(alpha, 1), np.concatenate(Z, 1)


def candidates(s: Settings, z0, lengths, accels):
    """(Delta, alpha, Z) towards the current lane's centre (keep) and y_ref (change), every length (m) and acceleration."""
    targets = sorted({float(s.road.centre(s.road.lane_of(z0[1]))), float(s.y_ref)})
    y1, L, a = (np.array(v, float).ravel() for v in np.meshgrid(targets, lengths, accels, indexing="ij"))
    return list(zip(*track(s, z0, y1, L, a)))


def nnmpc_step(s: Settings, obs: Observation, source, warm, lengths, accels) -> StepResult:
    """One NNMPC step over lane-change lengths (m) and accelerations (m/s^2): the safe candidate of least J, or the fallback
    when none is safe."""
    if not observed(obs):
        return fallback(s, obs, source, warm, "non-finite observation")
    cands = candidates(s, obs.z0, lengths, accels)
    egos = np.stack([ego_xy(Z, s.T_p) for _, _, Z in cands])
    values = source.values(obs.history, egos)
    b_min = np.array([b_i(v, s.R, s.stretch, s.shape).min(initial=np.inf) for v in values])
    Phi_1, Phi_2, Phi_3 = costs(s, obs.u_prev)
    J = np.array([Phi_1(Delta) + Phi_2(alpha) + Phi_3(Z) for Delta, alpha, Z in cands])
    safe = b_min >= 0.0
    if not safe.any():
        return fallback(s, obs, source, warm, f"no safe candidate (best min b_i {b_min.max():.2f} m^2)")
    k = int(np.argmin(np.where(safe, J, np.inf)))
    Delta, alpha, Z = cands[k]
    return StepResult(u=np.array([Delta[0], alpha[0]]), plan=admm.ADMMState(Delta, alpha, Z, np.zeros(4 * s.T_p)),
                      J=float(J[k]), iters=0, reason=f"candidate {k} of {len(cands)}", F_norm=0.0, b_min=float(b_min[k]),
                      slack=0.0, fallback="")
