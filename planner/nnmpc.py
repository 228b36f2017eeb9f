"""The NNMPC baseline (Bae et al. 2022): a finite set of lane-change curves plus keep-lane, each with several speed
profiles, rolled out with the same predictor, checked with the same b_i; the safe candidate of least J wins.

A lane change follows the quintic y(x) from the ego's y to the target over a length L (zero heading and curvature at
both ends, so its curvature is cubic in arc length to first order: a cubic spiral), tracked by pure pursuit.
"""
import numpy as np

from data import bicycle
from planner import admm
from planner.mpc import J_of, Observation, Settings, StepResult, fallback
from planner.safety import b_i


def lateral_path(x, x0, y0, y1, L):
    """y (m) of the quintic lane-change curve from (x0, y0) to y1 over length L (m)."""
    xi = np.clip((x - x0) / L, 0.0, 1.0)
    return y0 + (y1 - y0) * xi**3 * (10 - 15 * xi + 6 * xi**2)


def track(s: Settings, z0, y1, L, accel, lookahead=(2.0, 0.6)):
    """Controls (Delta, alpha) and states Z (4T_p,) following the curve to y1 with constant acceleration `accel`."""
    z, Delta, alpha, Z = np.asarray(z0, float), [], [], []
    wheelbase = s.params.l_f + s.params.l_r
    for _ in range(s.T_p):
        Ld = max(lookahead[0], lookahead[1] * z[3])
        target = lateral_path(z[0] + Ld, z0[0], z0[1], y1, L)
        bearing = np.arctan2(target - z[1], Ld) - z[2]
        d = float(np.clip(np.arctan(2 * wheelbase * np.sin(bearing) / Ld), *s.delta_box))
        a = float(np.clip(accel, (s.v_box[0] - z[3]) / s.params.dt, (s.v_box[1] - z[3]) / s.params.dt))
        z = bicycle.step(z, [d, a], s.params)
        Delta.append(d)
        alpha.append(a)
        Z.append(z)
    return np.array(Delta), np.array(alpha), np.concatenate(Z)


def candidates(s: Settings, z0, lengths, accels):
    """(Delta, alpha, Z) towards the current lane's centre (keep) and y_ref (change), every length (m) and acceleration."""
    targets = sorted({float(s.road.centre(s.road.lane_of(z0[1]))), float(s.y_ref)})
    return [track(s, z0, y1, L, a) for y1 in targets for L in lengths for a in accels]


def nnmpc_step(s: Settings, obs: Observation, source, warm, lengths=(8.0, 12.0, 16.0, 24.0, 32.0),
               accels=(-2.0, -1.0, 0.0, 1.0, 2.0)) -> StepResult:
    """One NNMPC step: the safe candidate of least J, or the fallback when none is safe."""
    if not (np.all(np.isfinite(obs.history)) and np.all(np.isfinite(obs.z0))):
        return fallback(s, obs, source, warm, "non-finite observation")
    cands = candidates(s, obs.z0, lengths, accels)
    egos = np.stack([np.reshape(Z, (s.T_p, 4))[:, :2] for _, _, Z in cands])
    values = source.values(obs.history, egos)
    b_min = np.array([b_i(v, s.R).min(initial=np.inf) for v in values])
    J = np.array([J_of(s, obs.u_prev, *c) for c in cands])
    safe = b_min >= 0.0
    if not safe.any():
        return fallback(s, obs, source, warm, f"no safe candidate (best min b_i {b_min.max():.2f} m^2)")
    k = int(np.argmin(np.where(safe, J, np.inf)))
    Delta, alpha, Z = cands[k]
    return StepResult(np.array([Delta[0], alpha[0]]), admm.ADMMState(Delta, alpha, Z, np.zeros(4 * s.T_p)), float(J[k]),
                      0, f"candidate {k} of {len(cands)}", 0.0, float(b_min[k]), 0.0, "")
