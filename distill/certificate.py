"""The student's A1-A3 constants from its weights (float64, metres), their sampled check, and Theorem 1's rho bound.

Conventions (the paper's, made precise):
- Frame: coordinates relative to the ego's position at planning time. phi is translation-equivariant
  (phi(w + c) = phi(w) + c), so gradients and Hessians are frame-free and A1 holds in any frame shifted likewise.
- Box (the planner's input set): |x| <= box.x, |y| <= box.y for every position in a window, per-step
  displacements |dx| <= box.dx, |dy| <= box.dy. Gradient and Hessian bounds hold on all of R^80; only A1 needs the box.
- Outputs: phi_{i,w}, i in V = other cars 1..N, w in {x, y}. Z enters a window through the ego slot, so
  A2 and A3 are w.r.t. the ego's 2 T_obs window coordinates: theta_w >= max-norm of d phi_{i,w} / d ego,
  L >= spectral norm of the Hessian of phi_{i,w} w.r.t. the ego inputs (the Lipschitz constant of its gradient).
Bounds: phi_{i,w} = cv_{i,w} + s_w tanh(a_k), a = W_L h_{L-1}(window), h_l = GELU(W_l h_{l-1}), first W with the
feature map folded in. Layer recursion (L_0 = 1, H_0 = 0): L_l = g1 ||W_l|| L_{l-1},
H_l = g1 ||W_l|| H_{l-1} + g2 r_l ||W_l|| L_{l-1}^2 (r_l largest row norm); per output row k of W_L:
|d a_k / d x_j| <= ||W_L[k]|| L_{L-1} ||W_1 e_j|| / ||W_1||, ||Hess a_k|| <= ||W_L[k]|| H_{L-1}, and the tanh head
gives ||Hess phi_k|| <= s_k (||Hess a_k|| + sup|tanh''| ||grad a_k||^2). cv does not depend on the ego's inputs.
"""
import json
import math
from pathlib import Path

import numpy as np

from core.jobs import UserError, model_file, recover, sha256
from core.rollout import SLOTS, T_OBS
from data import bicycle

G1, G2 = 1.1290, 0.7979  # sup|GELU'|, sup|GELU''| (safe for the erf and tanh forms)
G2_TANH = 0.7699  # sup|tanh''| = 4 / (3 sqrt 3)


def ego_columns(t_obs=T_OBS, m=SLOTS):
    """Indices of the ego's x, y in a window flattened (T_obs, SLOTS, 2)."""
    return np.array([t * m * 2 + c for t in range(t_obs) for c in range(2)])


def layer_recursion(Ws, spectral, row_norms):
    """(L_{L-1}, H_{L-1}): the layer recursion's gradient and Hessian bounds over the hidden layers Ws (the first on the
    ego's input columns), for numpy or torch weights through their `spectral` and `row_norms` functions."""
    lip, hess = 1.0, 0.0
    for W in Ws:
        n, r = spectral(W), row_norms(W).max()
        hess = G1 * n * hess + G2 * r * n * lip**2
        lip = G1 * n * lip
    return lip, hess


def head_L(s, row, lip, hess):
    """A3's L per output k (m^-1): s_k (||W_L[k]|| H_{L-1} + sup|tanh''| (||W_L[k]|| L_{L-1})^2), row = ||W_L[k]||."""
    return s * (row * hess + G2_TANH * (row * lip) ** 2)


def constants(weights, s, box):
    """s_x, s_y (A1), theta_x, theta_y (A2), L (A3) in metres from the student's float64 weights [(W, b)] and head s."""
    Ws = [W for W, _ in weights]
    W1 = Ws[0][:, ego_columns()]
    lip, hess = layer_recursion([W1, *Ws[1:-1]], lambda W: np.linalg.norm(W, 2), lambda W: np.linalg.norm(W, axis=1))
    row = np.linalg.norm(Ws[-1], axis=1)  # ||W_L[k]||, k = 2 (i - 1) + w
    entry = row * lip * np.linalg.norm(W1, axis=0).max() / np.linalg.norm(W1, 2)  # max |d a_k / d ego_j|
    theta = s * entry
    L_k = head_L(s, row, lip, hess)
    return {
        "s_x": box["x"] + box["dx"] + s[0], "s_y": box["y"] + box["dy"] + s[1],  # |last + velocity + s tanh|
        "theta_x": float(theta[0::2].max()), "theta_y": float(theta[1::2].max()), "L": float(L_k.max()),
    }


def sampled(grad_fn, jac64_fn, windows, fd_step=1e-4, chunk=100):
    """Largest sampled theta_x, theta_y (autodiff gradients) and L (finite-difference Hessians) over `windows`.

    grad_fn(w) -> (next, J (B, SLOTS*2, T_obs*SLOTS*2)) by autodiff; jac64_fn(w) -> J (B, SLOTS*2, 2 T_obs) w.r.t. the ego's
    inputs only, in float64, differenced for the Hessians.
    """
    cols = ego_columns()
    _, J = grad_fn(windows)
    G = np.abs(J[:, 2:][:, :, cols])  # (n, 8, 16): others' rows, ego columns
    out = {"emp_theta_x_max": float(G[:, 0::2].max()), "emp_theta_y_max": float(G[:, 1::2].max())}
    steps = np.zeros((2 * len(cols),) + windows.shape[1:])
    for j, c in enumerate(cols):
        steps[2 * j].flat[c], steps[2 * j + 1].flat[c] = fd_step, -fd_step
    L_max = 0.0
    for i in range(0, len(windows), chunk):
        w = windows[i : i + chunk]
        Jp = jac64_fn((w[:, None] + steps[None]).reshape(-1, *w.shape[1:]))
        Jp = Jp[:, 2:].reshape(len(w), len(cols), 2, 8, len(cols))
        H = (Jp[:, :, 0] - Jp[:, :, 1]) / (2 * fd_step)  # (B, j, k, l): d/d ego_j of d phi_k / d ego_l
        H = H.transpose(0, 2, 1, 3)
        H = 0.5 * (H + H.transpose(0, 1, 3, 2))
        L_max = max(L_max, float(np.linalg.norm(H, ord=2, axis=(-2, -1)).max()))
    out["emp_theta_max"] = max(out["emp_theta_x_max"], out["emp_theta_y_max"])
    out["emp_L_max"] = L_max
    return out


def ratios(cert, emp):
    """Sampled / certified for theta_x, theta_y and L; every one must stay <= 1."""
    return {"ratio_theta_x": emp["emp_theta_x_max"] / cert["theta_x"], "ratio_theta_y": emp["emp_theta_y_max"] / cert["theta_y"],
            "ratio_L": emp["emp_L_max"] / cert["L"]}


def verify(cert, emp):
    """Raise a UserError when a sampled value exceeds its certified bound (the certificate would be wrong)."""
    bad = {k: v for k, v in ratios(cert, emp).items() if not v <= 1.0}
    if bad:
        raise UserError("certificate violated by sampled inputs: " + ", ".join(f"{k} = {v:.3g}" for k, v in bad.items()))


def admm_matrices(A_t, B_t, C_t, t_p):
    """The paper's eq. (6) block matrices A (4T_p, T_p), B (4T_p, T_p), C (4T_p, 4T_p) from one linearisation."""
    A = np.kron(np.eye(t_p), A_t[:, None])
    B = np.kron(np.eye(t_p), B_t[:, None])
    C = -np.eye(4 * t_p) + np.kron(np.eye(t_p, k=-1), C_t)
    return A, B, C


def smallest_positive_sv(X, tol=1e-12):
    """Smallest singular value above tol * the largest."""
    sv = np.linalg.svd(X, compute_uv=False)
    return float(sv[sv > tol * sv[0]].min())


def rho_bound(c, box, cost, t_p=8, n_others=SLOTS - 1, lambda_s=1.0, v=5.0, delta=0.0, a=0.0, *, params):
    """Theorem 1: rho > max{1, (1 + 2 sigma_min(C)) L_J M}, with Lemma 3's L_1, L_2, L_3, L_g; returns every term.

    Assumptions: the ego's own |x| <= box.x and |y| <= box.y over the horizon (x_max, y_max); one multiplier
    lambda_s per step and car (||lambda_s||_1 = T_p lambda_s); the bicycle `params` linearised at a straight drive at v.
    J is block-separable in (Delta, alpha, Z), so L_J is the largest of its blocks' gradient Lipschitz constants.
    M bounds the sub-minimisation maps H_1..H_3 = pseudo-inverses of A, B, C on their images (Lemma 2).
    """
    L1 = 2 * (c["theta_x"] * (1 + c["theta_x"]) + c["theta_y"] * (1 + c["theta_y"])
              + (box["x"] + box["y"] + c["s_x"] + c["s_y"]) * c["L"])
    L2, L3 = 2 * (1 + c["theta_x"]), 2 * (1 + c["theta_y"])
    L_g = t_p * (max(L1, L2) + max(L1, L3))
    D = np.eye(t_p) - np.eye(t_p, k=-1)  # steering / acceleration differences, the one before the horizon fixed
    L_phi1 = 2 * np.linalg.eigvalsh(cost["lambda_delta"] * np.eye(t_p) + cost["lambda_ddelta"] * D.T @ D).max()
    L_phi2 = 2 * np.linalg.eigvalsh(cost["lambda_a"] * np.eye(t_p) + cost["lambda_da"] * D.T @ D).max()
    L_phi3 = 2 * max(cost["lambda_div"], cost["lambda_v"])
    L_J = max(L_phi1, L_phi2, L_phi3 + n_others * t_p * lambda_s * L_g)
    A_t, B_t, C_t, _ = bicycle.linearize([0.0, 0.0, 0.0, v], delta, a, params)
    A, B, C = admm_matrices(A_t, B_t, C_t, t_p)
    sigma_C = smallest_positive_sv(C)
    M_sub = max(1 / smallest_positive_sv(A), 1 / smallest_positive_sv(B), 1 / sigma_C)
    return {"L_1": L1, "L_2": L2, "L_3": L3, "L_g": L_g, "L_J": float(L_J), "sigma_min_C": sigma_C, "M": M_sub,
            "rho_bound": float(max(1.0, (1 + 2 * sigma_C) * L_J * M_sub))}


# Region bounds. Over the planner's region (a box on the features P reads, in metres) every pre-activation z_l has an
# interval (exact for the first layer, interval arithmetic after), so each neuron's GELU' and GELU'' ranges replace the
# global sups. With K_l = d z_l / d ego (interval matrices) and g_l = d a_k / d h_l (intervals, backward):
#   grad a_k = w_k' J_{L-1} = W_1e' (GELU'(z_1) * g_1)   (both evaluated, the tighter taken per entry),
#   Hess a_k = sum_l K_l' diag(GELU''(z_l) * g_l) K_l,   bounded above and below in the Loewner order,
#   Hess phi_k = s_k (tanh'(a_k) Hess a_k + tanh''(a_k) grad a_k grad a_k').
GELU_ARGMIN = -0.7517915241  # GELU's minimiser
TANH2_CRIT = 0.6584789485  # |a| where tanh'' has its extrema, atanh(1 / sqrt 3)
KINDS = ("rel_x", "rel_y", "vel_x", "vel_y", "acc_x", "acc_y")


def feature_kinds(t_obs=T_OBS, m=SLOTS):
    """The region key of each of P's rows: others' relative last positions, last velocities, accelerations."""
    return ["rel_x", "rel_y"] * (m - 1) + ["vel_x", "vel_y"] * m + ["acc_x", "acc_y"] * (m * (t_obs - 2))


def feature_box(region):
    """(lo, hi) of the 78 metric features (P with unit scales) from the region's [low, high] ranges in metres per step^k."""
    missing = [k for k in KINDS if k not in region]
    if missing:
        raise UserError(f"model.certificate.region: missing {', '.join(missing)} (each a [low, high] range in metres)")
    lo = np.array([float(region[k][0]) for k in feature_kinds()])
    hi = np.array([float(region[k][1]) for k in feature_kinds()])
    if not np.all(lo <= hi):
        raise UserError("model.certificate.region: every range must be [low, high] with low <= high")
    return lo, hi


def metric_features():
    """P (78, 80) with unit scales: window (m) -> relative positions (m), velocities (m/step), accelerations (m/step^2)."""
    from distill.student import feature_map

    return feature_map(1.0, 1.0, 1.0)


def windows_from_features(F):
    """Windows (B, T_obs, SLOTS, 2) in metres, ego's last position at the origin, whose metric features are F (B, 78)."""
    w = (F @ np.linalg.pinv(metric_features()).T).reshape(len(F), T_OBS, SLOTS, 2)
    return w - w[:, -1:, :1]  # P is translation-invariant, so the shift keeps F


def in_region(windows, lo, hi, tol=1e-9):
    """Which windows (B, T_obs, SLOTS, 2) have all their metric features inside [lo, hi]."""
    F = np.asarray(windows, dtype=float).reshape(len(windows), -1) @ metric_features().T
    return np.all((F >= lo - tol) & (F <= hi + tol), axis=1)


def _gelu(a):
    """GELU(a), float64."""
    from scipy.special import erf

    return 0.5 * a * (1.0 + erf(a / np.sqrt(2.0)))


def _gelu1(a):
    """GELU'(a)."""
    from scipy.special import erf

    return 0.5 * (1.0 + erf(a / np.sqrt(2.0))) + a * np.exp(-0.5 * a * a) / np.sqrt(2.0 * np.pi)


def _gelu2(a):
    """GELU''(a) = pdf(a) (2 - a^2)."""
    return np.exp(-0.5 * a * a) / np.sqrt(2.0 * np.pi) * (2.0 - a * a)


def _tanh1(a):
    """tanh'(a)."""
    return 1.0 - np.tanh(a) ** 2


def _tanh2(a):
    """tanh''(a)."""
    t = np.tanh(a)
    return -2.0 * t * (1.0 - t * t)


def _range(f, lo, hi, crit):
    """Range [min, max] of a smooth scalar f over each [lo, hi], from the end points and the critical points inside."""
    pts = [lo, hi] + [np.clip(np.full_like(lo, c), lo, hi) for c in crit]
    vals = np.stack([f(p) for p in pts])
    return vals.min(0), vals.max(0)


def _mul(alo, ahi, blo, bhi):
    """Interval product, elementwise (broadcasting)."""
    p = np.stack(np.broadcast_arrays(alo * blo, alo * bhi, ahi * blo, ahi * bhi))
    return p.min(0), p.max(0)


def _matmul(W, lo, hi):
    """W @ [lo, hi] for an interval vector or matrix (centre-radius form, exact for one interval factor)."""
    c, r = (lo + hi) / 2, (hi - lo) / 2
    c, r = W @ c, np.abs(W) @ r
    return c - r, c + r


def preactivation_bounds(weights, lo, hi):
    """Intervals [(zlo, zhi)] of every layer's pre-activation (last: the head's a) over metric features in [lo, hi]."""
    W1 = weights[0][0] @ np.linalg.pinv(metric_features())  # the first layer on metric features (P has full row rank)
    zlo, zhi = _matmul(W1, lo, hi)
    out = [(zlo + weights[0][1], zhi + weights[0][1])]
    for W, b in weights[1:]:
        hlo, hhi = _range(_gelu, *out[-1], [GELU_ARGMIN])
        zlo, zhi = _matmul(W, hlo, hhi)
        out.append((zlo + b, zhi + b))
    return out


def _lambda_bounds(Klo, Khi, vlo, vhi):
    """Upper bound of lambda_max and lower bound of lambda_min of K' diag(v) K over K in [Klo, Khi], v in [vlo, vhi]."""
    Kc, Kr = (Klo + Khi) / 2, (Khi - Klo) / 2
    if not Kr.any():  # K exact: K' diag(v) K lies between K' diag(vlo) K and K' diag(vhi) K
        return np.linalg.eigvalsh(Kc.T @ (vhi[:, None] * Kc))[-1], np.linalg.eigvalsh(Kc.T @ (vlo[:, None] * Kc))[0]

    def sq_norm(p):
        """max ||diag(sqrt p) K||^2 over the interval K, p >= 0."""
        q = np.sqrt(p)[:, None]
        return (np.linalg.norm(q * Kc, 2) + np.linalg.norm(q * Kr, 2)) ** 2

    return sq_norm(np.maximum(vhi, 0.0)), -sq_norm(np.maximum(-vlo, 0.0))


def region_constants(weights, s, lo, hi):
    """theta_x, theta_y (A2), L (A3) in metres over the region's metric features [lo, hi], by interval bounds."""
    cols = ego_columns()
    Z = preactivation_bounds(weights, lo, hi)
    hidden = [(W, _range(_gelu1, zl, zh, [np.sqrt(2), -np.sqrt(2)]), _range(_gelu2, zl, zh, [0.0, 2.0, -2.0]))
              for (W, _), (zl, zh) in zip(weights[:-1], Z[:-1])]
    # forward: K_l = d z_l / d ego and J_l = d h_l / d ego, interval matrices (width, 16)
    K, J = [], None
    for W, (d1lo, d1hi), _ in hidden:
        Klo, Khi = (W[:, cols], W[:, cols]) if J is None else _matmul(W, *J)
        K.append((Klo, Khi))
        J = _mul(d1lo[:, None], d1hi[:, None], Klo, Khi)
    WL = weights[-1][0]
    theta, L = np.zeros(len(WL)), np.zeros(len(WL))
    for k, w in enumerate(WL):
        glo, ghi = _matmul(w[None], *J)
        g = [(w, w)]  # g_l = d a_k / d h_l, from the last hidden layer back
        for (W, (d1lo, d1hi), _) in hidden[:0:-1]:
            ulo, uhi = _mul(d1lo, d1hi, *g[-1])
            g.append(_matmul(W.T, ulo, uhi))
        g = g[::-1]
        blo, bhi = _matmul(hidden[0][0][:, cols].T, *_mul(*hidden[0][1], *g[0]))
        glo, ghi = np.maximum(glo, blo), np.minimum(ghi, bhi)  # both enclose the gradient
        grad = np.maximum(np.abs(glo), np.abs(ghi)).ravel()
        up = low = 0.0
        for (_, _, (d2lo, d2hi)), (Klo, Khi), (gl, gh) in zip(hidden, K, g):
            u, v = _lambda_bounds(Klo, Khi, *_mul(d2lo, d2hi, gl, gh))
            up, low = up + u, low + v
        alo, ahi = Z[-1][0][k:k + 1], Z[-1][1][k:k + 1]
        t1lo, t1hi = _range(_tanh1, alo, ahi, [0.0])
        t2lo, t2hi = _range(_tanh2, alo, ahi, [TANH2_CRIT, -TANH2_CRIT])
        g2 = float(grad @ grad)
        H_up = max(t1hi[0] * up, t1lo[0] * up) + max(t2hi[0], 0.0) * g2
        H_low = min(t1hi[0] * low, t1lo[0] * low) + min(t2lo[0], 0.0) * g2
        theta[k] = s[k] * t1hi[0] * grad.max()
        L[k] = s[k] * max(H_up, -H_low)
    return {"theta_x": float(theta[0::2].max()), "theta_y": float(theta[1::2].max()), "L": float(L.max())}


def region_samples(lo, hi, n, rng):
    """Windows whose metric features are corners of [lo, hi] (first half) and uniform inside it (second half)."""
    corners = np.where(rng.random((n // 2, len(lo))) < 0.5, lo, hi)
    inside = rng.uniform(lo, hi, (n - n // 2, len(lo)))
    return windows_from_features(np.concatenate([corners, inside]))



def tightest(global_c, region_c):
    """Both bounds hold on the region, so the certificate there is the smaller of each: theta_x, theta_y, L."""
    return {**global_c, **{k: min(global_c[k], region_c[k]) for k in ("theta_x", "theta_y", "L")}}


# Per scenario. The planner's frame is the ego's position at planning time (b_i is translation-invariant), so Lemma 3's
# x_max, y_max are how far the ego can get within the horizon, and A1's s_x, s_y follow from the region: the others'
# next positions are the ego's last one plus rel + vel + the head's s.
def scenario_setting(sc):
    """(lanes, lane width m, ego start speeds m/s, BicycleParams) of a scenario config: its widest road; for random
    merges the slowest and the fastest ego start (data.scenarios.RandomScenario: platoon speed + offset, >= 0.5 m/s)."""
    lanes = max(sc.get("lanes_choices", [sc["road"]["lanes"]]))
    if "speed_range" in sc:
        speeds = tuple(max(0.5, sc["speed_range"][k] + sc["ego_dv_range"][k]) for k in (0, 1))
    else:
        speeds = (sc["ego"]["v"],)
    params = bicycle.BicycleParams(**{k: sc["params"][k] for k in ("l_f", "l_r", "dt")})
    return lanes, float(sc["road"]["lane_width"]), tuple(map(float, speeds)), params


def scenario_region(region, lanes, lane_width, y_margin):
    """The region with the rel_y its road allows: others' centres on its lanes, the ego's within y_margin of them (m)."""
    reach = (lanes - 1) * lane_width + y_margin
    return {**region, "rel_y": [-reach, reach]}


def lemma3_extent(region, s, lanes, lane_width, y_margin, v_max, t_p, dt):
    """x_max, y_max (the ego's reach over the horizon) and A1's s_x, s_y (the others' next positions), metres."""
    x_max = v_max * t_p * dt
    y_max = (lanes - 1) * lane_width + 2 * y_margin
    reach = {k: max(abs(b) for b in region[k]) for k in ("rel_x", "rel_y", "vel_x", "vel_y")}
    return {"x_max": x_max, "y_max": y_max, "s_x": x_max + reach["rel_x"] + reach["vel_x"] + s[0],
            "s_y": y_max + reach["rel_y"] + reach["vel_y"] + s[1]}


def per_scenario(weights, s, glob, region, scenarios, planner, cost, t_p, lambda_s):
    """Certificate and Theorem 1 terms on each scenario's region and speed: {name: {theta_x, ..., rho_bound, region}}.

    sigma_min(C) and M depend on the linearisation speed v; over a range of starts the largest bound is kept.
    """
    out = {}
    for name, sc in scenarios.items():
        lanes, width, speeds, params = scenario_setting(sc)
        reg = scenario_region(region, lanes, width, planner["y_margin"])
        c = tightest(glob, region_constants(weights, s, *feature_box(reg)))
        ext = lemma3_extent(reg, s, lanes, width, planner["y_margin"], planner["v_max"], t_p, params.dt)
        c.update(s_x=ext["s_x"], s_y=ext["s_y"])
        terms = [{**rho_bound(c, {"x": ext["x_max"], "y": ext["y_max"]}, cost, t_p, lambda_s=lambda_s, v=v, params=params),
                  "v": v} for v in speeds]
        c.update(max(terms, key=lambda t: t["rho_bound"]))
        out[name] = {**c, "x_max": ext["x_max"], "y_max": ext["y_max"], "region": reg}
    return out


def certified_rho(path, scenario):
    """Theorem 1's rho bound for `scenario` from the student's certificate.json; a one-line UserError when unusable."""
    path = Path(path)
    recover(path.parent)  # the student's set a stopped distill committed but did not finish moving in
    if not path.is_file():
        raise UserError(f"mpc.admm.rho=certified: no certificate at {path}; run `distill model=student` first")
    try:
        doc = json.loads(model_file(path).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise UserError(f"mpc.admm.rho=certified: {path} is not a readable certificate ({type(e).__name__}: {e}); "
                        "rerun `distill model=student`") from None
    scenarios = doc.get("scenarios") if isinstance(doc, dict) else None
    if not isinstance(scenarios, dict):
        raise UserError(f"mpc.admm.rho=certified: {path} has no `scenarios` object; rerun `distill model=student`")
    if scenario not in scenarios:
        raise UserError(f"mpc.admm.rho=certified: {path} has no bound for scenario {scenario} "
                        f"(it certifies {', '.join(scenarios) or 'none'}); rerun `distill model=student`")
    bound = scenarios[scenario].get("rho_bound") if isinstance(scenarios[scenario], dict) else None
    rho = float(bound) if isinstance(bound, (int, float)) and not isinstance(bound, bool) else math.nan
    if not (math.isfinite(rho) and rho > 0):
        raise UserError(f"mpc.admm.rho=certified: the certified rho for {scenario} in {path} is {bound}, not a usable penalty "
                        "(a number > 0)")
    check_certifies(path, doc)
    return rho


def check_certifies(path: Path, doc: dict) -> None:
    """One UserError unless the student files a certificate records by sha256 (`certifies`: {file name: hex digest}) lie
    beside it with those bytes: a certificate holds only for the weights it was computed from."""
    files = doc.get("certifies")
    if not isinstance(files, dict) or not files:
        raise UserError(f"mpc.admm.rho=certified: {path} does not record the student it certifies (its sha256); rerun "
                        "`distill model=student`")
    for name, digest in files.items():
        beside = path.parent / name
        if not beside.is_file():
            raise UserError(f"mpc.admm.rho=certified: {path} certifies {beside}, which is not there; rerun `distill model=student`")
        if sha256(beside) != digest:
            raise UserError(f"mpc.admm.rho=certified: {path} certifies another {name} (sha256 {str(digest)[:8]}) than "
                            f"{beside} ({sha256(beside)[:8]}): a student trained since; rerun `distill model=student`")
