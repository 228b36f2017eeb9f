"""Prediction metrics on a dataset split, in metres, over the other cars (slots 1..N): 1-step and T_p-step rollout ADE/FDE.

The rollout is the planner's recursion (core.rollout.rollout) with the ego's recorded future fed in. The yield
subset holds the windows of episodes in which some driver brakes for the ego at least once. A predictor without
hypotheses is scored on the factual runs (data.dataset.factual); a hypothesis predictor (`hypothesis_quality`) under
each run's recorded decisions, on the flipped branches too, and its belief on the factual runs.
"""
import time

import numpy as np

from core.rollout import accelerations, rollout
from core.stats import auc
from data.dataset import REVEAL_LAGS_S as BELIEF_LAGS_S  # belief AUC this long after the ego first encroaches on a car (s)
from data.dataset import encroached as belief_cases
from data.dataset import factual, nearest_behind, reveal

BRAKE_JUDGE = {"forced": 4.0, "calm": 2.0, "alarm": 3.0}  # m/s^2: brake_scores' thresholds, evaluate-interaction's
# score.forced (b_safe), score.calm and score.alarm (b_courtesy), for the per-hypothesis braking on a dataset's runs


def chains(a: dict, t_p: int):
    """(starts (n,), chain (n, T_p)): every window whose run goes on T_p steps with the same cars in its slots, and the
    indices of those steps' windows."""
    runs = list(zip(a["episode"], a["branch"], a["step"]))  # a counterfactual branch is a run of its own
    key = {r: i for i, r in enumerate(runs)}
    starts, out = [], []
    for i, (e, b, s) in enumerate(runs):
        chain = [key.get((e, b, s + k)) for k in range(t_p)]
        if None not in chain and (a["ids"][chain] == a["ids"][i]).all():
            starts.append(i)
            out.append(chain)
    return np.array(starts, dtype=int), np.array(out, dtype=int).reshape(-1, t_p)


def rollout_cases(a: dict, t_p: int):
    """history (n, T_obs, SLOTS, 2), ego future (n, T_p, 2), others' future (n, T_p, N, 2), yield flag (n,) from split arrays:
    every window whose run goes on T_p steps with the same cars in its slots."""
    starts, chain = chains(a, t_p)
    futures = a["Y"][chain].astype(float)
    return a["X"][starts].astype(float), futures[:, :, 0], futures[:, :, 1:], yield_windows(a)[starts]


def yield_windows(a: dict):
    """(n,) bool: the window belongs to an episode where some other driver yields to the ego."""
    episodes = np.unique(a["episode"][a["yielding"][:, 1:].any(axis=1)])
    return np.isin(a["episode"], episodes)


def ade(predictor, a: dict, t_p: int, chunk=2048):
    """ade_1step_m, ade_rollout_m, fde_rollout_m on all factual windows and on the yield-episode subset (suffix _yield);
    a hypothesis predictor (one with .given) under each window's recorded decisions."""
    a = factual(a)
    given = (lambda idx: predictor.given(a["will_yield"][idx])) if hasattr(predictor, "given") else (lambda idx: predictor)
    X, Y = a["X"].astype(float), a["Y"].astype(float)
    pred = np.concatenate([given(slice(i, i + chunk)).phi(X[i : i + chunk]) for i in range(0, len(X), chunk)])
    e1 = np.linalg.norm(pred[:, 1:] - Y[:, 1:], axis=-1).mean(axis=1)
    hist, ego, others, yl = rollout_cases(a, t_p)
    out = rollout(given(chains(a, t_p)[0]).phi, hist, ego)[:, :, 1:]
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


def engaged_rollouts(predictor, a: dict, t_p: int, dt: float, flip=False):
    """Rollout error (n, N) in metres, mean over the T_p steps, of every window with a whole T_p-step future in its run
    (flipped branches too) under the run's recorded decisions (flip: the opposite ones; a predictor without .given: none),
    its decisions (n, N), which cars (n, N) the ego has encroached on by the horizon's end (where the hypothesis shows),
    and each car's hardest braking (m/s^2, >= 0) over the horizon, predicted and recorded (n, N) (steps of dt s)."""
    starts, chain = chains(a, t_p)
    hist, ego, others, _ = rollout_cases(a, t_p)
    hyp = a["will_yield"][starts].astype(float)
    phi = predictor.given(1.0 - hyp if flip else hyp).phi if hasattr(predictor, "given") else predictor.phi
    pred = rollout(phi, hist, ego)
    err = np.linalg.norm(pred[:, :, 1:] - others, axis=-1).mean(axis=1)
    brake = lambda values: np.maximum(0.0, -accelerations(values, hist, dt).min(axis=-1))  # noqa: E731
    return (err, hyp[:, 1:] > 0.5, a["since_encroach"][chain[:, -1]][:, 1:] >= 0, brake(pred),
            brake(a["Y"][chain].astype(float)))


def brake_scores(pred, true, forced: float, calm: float, alarm: float) -> dict:
    """brake_corr (Pearson's, 0 when either is constant), brake_auc (how well pred sorts the cases whose true braking
    exceeds `forced` from the rest: auc) and brake_fa (false alarms: the share of the cases whose true braking stays below
    `calm` predicted above `alarm`) of predicted against true hardest braking, same shapes, m/s^2."""
    p, t = np.ravel(pred), np.ravel(true)
    corr = float(np.corrcoef(p, t)[0, 1]) if p.std() > 0 and t.std() > 0 else 0.0
    quiet = p[t < calm]
    fa = float((quiet > alarm).mean()) if len(quiet) else float("nan")
    return {"brake_corr": corr, "brake_auc": auc(p, t > forced), "brake_fa": fa}


def reliability(p, y, bins=10):
    """(mean belief, observed yield rate, count) per equal-width bin of the belief p in [0, 1], labels y."""
    k = np.minimum((np.asarray(p) * bins).astype(int), bins - 1)
    rows = [(p[k == b].mean(), y[k == b].mean(), int((k == b).sum())) for b in range(bins) if (k == b).any()]
    return np.array(rows).reshape(-1, 3)


def plot_reliability(p, y, prior, path, title):
    """The reliability curve of beliefs p against labels y, the constant prior's point marked, saved to path (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = reliability(p, y)
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ax.plot([0, 1], [0, 1], color="grey", lw=0.8, label="calibrated")
    ax.scatter(r[:, 0], r[:, 1], s=8 + 60 * r[:, 2] / r[:, 2].max(), zorder=3, label="belief (size: windows)")
    ax.plot(r[:, 0], r[:, 1])
    ax.scatter([prior], [y.mean()], marker="x", color="k", zorder=4, label=f"constant prior {prior:.2f}")
    ax.set(xlabel="p(yields | window)", ylabel="observed yield rate", xlim=(0, 1), ylim=(0, 1), title=title)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def yield_prior(a: dict) -> float:
    """The population's yield rate (-): the share of yielders among the cars a split's factual windows see encroached."""
    _, _, _, y = belief_cases(a)
    return float(y.mean()) if len(y) else 0.5


def hypothesis_quality(predictor, a: dict, t_p: int, prior: float, dt: float, mean=None, plot=None):
    """A hypothesis predictor's figures on split arrays `a`: rollout error (m) per hypothesis on the runs of that label
    for the cars the ego encroaches on (ade_rollout_m_yielders / _stubborn), the same given the opposite hypothesis
    (suffix _opposite) and, for the same cars, a mean predictor's (suffix _mean) and cv's (_cv); the braking scores
    (brake_scores, BRAKE_JUDGE) of those cars' hardest braking under their own hypothesis (brake_auc_yielders,
    brake_fa_yielders, brake_corr_yielders, _stubborn; the cars braking harder than 1 m/s^2 in n_brake_cases_*); the belief's Brier
    score on the factual encroached cars against the constant `prior`'s (belief_brier, belief_brier_prior, their ratio),
    its AUC at each of BELIEF_LAGS_S after the first encroachment (steps of dt s) and over all (belief_auc), and on the
    car nearest behind the ego alone (belief_auc_nearest_*: data.dataset.nearest_behind), beside the
    AUC of the world's own per-step yielding flag there (seen_auc_*: what a predictor told each decision once shown
    would score, the data's reveal: `shown`, the yielding has visibly cut the car's acceleration); plot: a path for the
    reliability figure."""
    from distill.predictors import ConstantVelocity

    out = {}
    err, yields, engaged, brake, brake_true = engaged_rollouts(predictor, a, t_p, dt)
    opposite = engaged_rollouts(predictor, a, t_p, dt, flip=True)[0]
    others = {"cv": ConstantVelocity(), **({"mean": mean} if mean is not None else {})}
    for label, cars in (("yielders", engaged & yields), ("stubborn", engaged & ~yields)):
        out[f"ade_rollout_m_{label}"] = float(err[cars].mean()) if cars.any() else float("nan")
        out[f"ade_rollout_m_{label}_opposite"] = float(opposite[cars].mean()) if cars.any() else float("nan")
        out[f"n_cars_{label}"] = int(cars.sum())
        out.update({f"{k}_{label}": v for k, v in brake_scores(brake[cars], brake_true[cars], **BRAKE_JUDGE).items()})
        out[f"n_brake_cases_{label}"] = int((brake_true[cars] > 1.0).sum())
        for name, p in others.items():
            e = engaged_rollouts(p, a, t_p, dt)[0]
            out[f"ade_rollout_m_{label}_{name}"] = float(e[cars].mean()) if cars.any() else float("nan")
    w, j, since, y = belief_cases(a)
    p = np.concatenate([predictor.belief(a["X"][w[i:i + 4096]].astype(float))[np.arange(len(w[i:i + 4096])), j[i:i + 4096]]
                        for i in range(0, len(w), 4096)]) if len(w) else np.zeros(0)
    out["n_belief_cases"] = int(len(w))
    out["belief_prior"] = prior
    out["belief_brier"] = float(np.mean((p - y) ** 2)) if len(w) else float("nan")
    out["belief_brier_prior"] = float(np.mean((prior - y) ** 2)) if len(w) else float("nan")
    out["belief_brier_ratio"] = out["belief_brier"] / out["belief_brier_prior"] if len(w) and out["belief_brier_prior"] else float("nan")
    out["belief_auc"] = auc(p, y)
    out.update({k.replace("reveal_", "seen_"): v for k, v in reveal(a, dt).items() if k.startswith(("reveal_auc", "reveal_brier"))})
    nearest = nearest_behind(a, w, j)
    for lag in BELIEF_LAGS_S:
        at = since == int(round(lag / dt))
        out[f"belief_auc_{lag:.1f}s"] = auc(p[at], y[at])
        out[f"n_belief_cases_{lag:.1f}s"] = int(at.sum())
        out[f"belief_auc_nearest_{lag:.1f}s"] = auc(p[at & nearest], y[at & nearest])
    if plot is not None and len(w):
        plot_reliability(p, y.astype(float), prior, plot, f"{predictor.name}: belief on encroached cars")
    return out
