"""`evaluate-interaction`: the counterfactual interaction benchmark, one MLflow run per source (experiment `interaction`).

From held-out branch states (bench/branches.py) each pair of ego plans A, B is executed in two copies of the world; the
others' true response is their xy under B minus under A (T_p, N, 2), metres. Each source is scored on
  - its rollout response: its Remark-2 rollout under B minus under A, the ego slot filled with the executed ego xy;
  - its first-order response (`*_jac`): d rollout / d ego plan at A times (ego B - ego A), what the planner linearises;
the `reference` row is the world's own drivers with their latched decisions to yield re-drawn from the prior
(Bernoulli(eta_coop)) and the response averaged over the draws: how predictable the response is without hidden decisions.

Scores over all pairs, cars, steps and both coordinates:
  react_corr  Pearson correlation of predicted and true response components (0 when the prediction is constant);
  react_gain  least-squares slope of predicted on true through the origin, <p, t> / <t, t>: 1 is the right magnitude
              along the truth, 0 no response (or one uncorrelated with it);
  react_hit   over every (pair, car) whose true response peaks above score.threshold over T_p, the share whose peak error
              max_t |p_t - t_t| is within score.tolerance of that peak;
and, with score.resamples > 0, 95% bootstrap intervals of react_corr, react_gain and the brake_* scores below over the
branch states (*_lo, *_hi).

The braking each plan imposes, the hardest deceleration of any other car over T_p (m/s^2; the planner's courtesy rows
and its choice judge plans by it), is scored per plan (two per pair) against the world's:
  brake_corr  Pearson correlation of predicted and true hardest braking;
  brake_auc   how well it sorts the plans that force a driver (true braking above score.forced) from the rest: the
              probability that a forcing plan is predicted to impose more than a tolerated one (ties half; cv 0.5);
  brake_fa    false alarms: the share of the plans whose true braking stays below score.calm that are predicted to
              impose more than score.alarm (the step's b_courtesy): the merges a predictor would refuse for nothing.
The `follower` row is what the courteous planner judges a gap by whatever the predictor (planner.strategy.Rules.follower_braking):
a nominal IDM driver behind the executed ego plan, on constant-velocity positions; its braking scores, no response.

    evaluate-interaction [sources=[cv,analytic,reference]] [states=34] [models_dir=models]
"""
import csv
import logging
import time
from pathlib import Path

import hydra
import numpy as np
from hydra.utils import instantiate
from omegaconf import DictConfig

from bench.branches import KINDS, Pair, execute, make_pairs
from core import validate
from core.jobs import CONF_DIR, MissingModel, UserError, console, guarded, mlflow_run, open_experiment, writable
from core.rollout import braking as hardest_braking
from core.stats import bootstrap
from distill.metrics import brake_scores
from planner.gradients import available

log = logging.getLogger(__name__)

REFERENCE = "reference"
FOLLOWER = "follower"
SOURCES = available(needs_world=False, hypotheses=False)  # conf/gradients/ but the oracle (it reads the planner's
# running world) and the hypothesis sources (one rollout per hypothesis: their scores are per hypothesis, issue 72)
POS = validate.Real(0, lo_open=True)
SCHEMA = {
    "sources": validate.ListOf(validate.OneOf((*SOURCES, REFERENCE, FOLLOWER)), at_least=1), "models_dir": validate.Text(),
    "out_dir": validate.Text(), "seed_offset": validate.SEED, "states": validate.Int(1), "n_slots": validate.Int(1, validate.MAX_SLOTS), "T_p": validate.HORIZON,
    "branch.min_steps": validate.Int(0), "branch.max_steps": validate.Int(0), "branch.reach": POS,
    "branch.tries": validate.Int(1), "plans.kinds": validate.ListOf(validate.OneOf(KINDS)),
    "plans.y_push": validate.Range(0), "plans.dv": validate.Range(0), "plans.delay": validate.ListOf(validate.Int(0), 2),
    "plans.k_y": POS, "plans.a_bounds": validate.Range(strict=True), "reference.draws": validate.Int(1),
    "score.threshold": validate.Real(0), "score.tolerance": validate.Real(0), "score.resamples": validate.Int(0),
    "score.forced": POS, "score.calm": POS, "score.alarm": POS,
    "dataset.seed": validate.SEED, "dataset.episodes": validate.EPISODES,
}


def load_source(name: str, models_dir):
    """The planner's gradient source `name` over its own predictor (conf/gradients/<name>.yaml), models from models_dir;
    a UserError if its model files are missing."""
    from planner.setup import build, planner_config

    return build(planner_config(overrides=[f"gradients={name}", f"models_dir={models_dir}"]).gradients)


def rollout_response(source, pair: Pair):
    """The source's rollout under plan B minus under plan A (T_p, N, 2), m, the ego slot the executed ego xy."""
    out = source.values(pair.history, pair.ego)
    return out[1, :, 1:] - out[0, :, 1:]


def first_order_response(source, pair: Pair):
    """The source's d rollout / d ego plan at plan A times (ego B - ego A): (T_p, N, 2), m."""
    _, grads = source.jacobian(pair.history, pair.ego[0])
    return np.einsum("tmkse,se->tmk", grads, pair.ego[1] - pair.ego[0])[:, 1:]


def braking(xy, history, dt):
    """core.rollout.braking of each rollout xy (..., T_p, SLOTS, 2), each step's, to 1e-6 m/s^2: rounding noise must not
    rank plans."""
    return hardest_braking(xy, history, dt).round(6)


def reference_response(pair: Pair, draws: int, rng: np.random.Generator):
    """The world's own response (T_p, N, 2), m, and braking under plans A and B (2,), m/s^2, averaged over `draws`
    re-draws of the drivers' decisions to yield; both plans of a draw share its decisions."""
    out, brakes = [], []
    for _ in range(draws):
        world = pair.world.redrawn(rng)
        xy = np.stack([execute(world, u, pair.ids)[0] for u in pair.controls])
        out.append(xy[1, :, 1:] - xy[0, :, 1:])
        brakes.append(braking(xy, pair.history, pair.world.params.dt))
    return np.mean(out, axis=0), np.mean(brakes, axis=0)


def follower_braking(s, pair: Pair):
    """The braking (2,) in m/s^2 that the planner's nominal follower (planner.strategy.Rules.follower_braking, Settings s) judges
    plans A and B to impose, on constant-velocity positions of the others, the ego's speed from its executed xy."""
    from planner import mpc

    dt, T_p = pair.world.params.dt, pair.xy.shape[1]
    cv = pair.history[-1] + np.arange(1, T_p + 1)[:, None, None] * (pair.history[-1] - pair.history[-2])
    out = []
    for ego in pair.ego:
        x = np.concatenate([pair.history[-1:, 0, 0], ego[:, 0]])
        Z = np.stack([ego[:, 0], ego[:, 1], np.zeros(T_p), np.diff(x) / dt], 1).ravel()
        out.append(s.strategy.follower_braking(s, mpc.Observation(np.zeros(4), np.zeros(2), pair.history), Z, cv))
    return np.array(out)


def peaks(response):
    """Peak over T_p of each car's response norm (P, N), m, from responses (P, T_p, N, 2)."""
    return np.linalg.norm(response, axis=-1).max(axis=1)


def corr_gain(pred, true) -> tuple[float, float]:
    """react_corr and react_gain of predicted against true responses of the same shape, in m (module doc)."""
    p, t = np.ravel(pred), np.ravel(true)
    corr = float(np.corrcoef(p, t)[0, 1]) if p.std() > 0 and t.std() > 0 else 0.0
    gain = float(p @ t / (t @ t)) if t @ t > 0 else float("nan")
    return corr, gain


def scores(pred, true, threshold: float, tolerance: float) -> dict:
    """react_corr, react_gain, react_hit of predicted against true responses, both (P, T_p, N, 2) in m (module doc)."""
    corr, gain = corr_gain(pred, true)
    peak = peaks(true)
    real = peak > threshold
    err = peaks(np.asarray(pred) - true)
    hit = float(np.mean(err[real] <= tolerance * peak[real])) if real.any() else float("nan")
    return {"react_corr": corr, "react_gain": gain, "react_hit": hit}


def intervals(pred, true, states, resamples: int, suffix: str = "", seed: int = 0, score=None) -> dict:
    """95% percentile-bootstrap intervals {<name>_lo, <name>_hi} of score(pred, true) -> {name: value}, pred and true
    indexed by pair first (default: react_corr<suffix> and react_gain<suffix> of responses (P, T_p, N, 2)), resampling
    branch states: the pairs of one state (states: (P,) labels) share its world, so they are drawn together. Real
    responses are rare (about 6% of pairs), so the scores move by tenths between state sets."""
    score = score or (lambda p, t: dict(zip((f"react_corr{suffix}", f"react_gain{suffix}"), corr_gain(p, t))))
    names = list(score(pred, true))
    members = [np.flatnonzero(states == k) for k in np.unique(states)]
    lo, hi = bootstrap(members, lambda idx: list(score(pred[idx], true[idx]).values()), resamples, seed, within=False)
    return {**{f"{n}_lo": v for n, v in zip(names, lo)}, **{f"{n}_hi": v for n, v in zip(names, hi)}}


def predict(name: str, pairs: list[Pair], cfg) -> dict | None:
    """{"": rollout responses, "_jac": first-order responses} (P, T_p, N, 2) of source `name`, the reference's rollout
    only, the follower none; with "braking" (P, 2) under plans A and B, m/s^2. None (with one log line) when its model
    files are missing."""
    if name == REFERENCE:
        out = [reference_response(p, cfg.reference.draws, np.random.default_rng([p.seed, 4])) for p in pairs]
        return {"": np.stack([r for r, _ in out]), "braking": np.stack([b for _, b in out])}
    if name == FOLLOWER:
        from planner.setup import make

        s = make(cfg.scenario.name, ["mpc=courteous", "gradients=cv"])[2]  # cv: no model files needed
        return {"braking": np.stack([follower_braking(s, p) for p in pairs])}
    try:
        source = load_source(name, cfg.models_dir)
    except MissingModel as e:  # not trained yet; a damaged model is the UserError it raises
        log.warning(f"{name}: skipped ({e})")
        return None
    return {"": np.stack([rollout_response(source, p) for p in pairs]),
            "_jac": np.stack([first_order_response(source, p) for p in pairs]),
            "braking": np.stack([braking(source.values(p.history, p.ego), p.history, p.world.params.dt) for p in pairs])}


def scatter(path: Path, name: str, true, preds: dict, metrics: dict):
    """Predicted against true response components (m), one panel per response kind, written to `path` (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(preds), figsize=(5 * len(preds), 4.6), squeeze=False)
    lim = 1.05 * max(float(np.abs(true).max()), *(float(np.abs(p).max()) for p in preds.values()), 0.1)
    for ax, (suffix, pred) in zip(axes[0], preds.items()):
        for k, (coord, color) in enumerate((("x", "tab:blue"), ("y", "tab:orange"))):
            ax.scatter(true[..., k].ravel(), pred[..., k].ravel(), s=4, alpha=0.4, color=color, label=f"{coord} components")
        ax.plot([-lim, lim], [-lim, lim], "k--", lw=0.8, label="predicted = true")
        ax.set(xlim=(-lim, lim), ylim=(-lim, lim), aspect="equal")
        ax.set_xlabel("true response (m)")
        ax.set_ylabel("predicted response (m)")
        kind = "first-order (J . plan difference)" if suffix == "_jac" else "rollout difference"
        ax.set_title(f"{name}, {kind}\ncorr {metrics['react_corr' + suffix]:.3f}, gain {metrics['react_gain' + suffix]:.3f}, "
                     f"hit {metrics['react_hit' + suffix]:.3f}", fontsize=9)
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def benchmark_stats(pairs: list[Pair], true, threshold: float) -> dict:
    """What every run of one benchmark shares: pair count, how many (pair, car) responses are real, per kind the share of
    pairs with a real response."""
    real = peaks(true) > threshold  # (P, N)
    out = {"n_pairs": len(pairs), "n_real_responses": int(real.sum()), "real_pair_share": float(real.any(axis=1).mean())}
    for kind in sorted({p.kind for p in pairs}):
        mask = np.array([p.kind == kind for p in pairs])
        out[f"real_pair_share_{kind}"] = float(real[mask].any(axis=1).mean())
    return out


def write_table(path: Path, table: dict):
    """interaction.csv: one row per source, its react_* scores (with their intervals where computed), brake_* scores
    and seconds."""
    cols = [f"react_{k}{s}{e}" for s in ("", "_jac") for k in ("corr", "gain", "hit")
            for e in (("", "_lo", "_hi") if k != "hit" else ("",))] + \
        [f"brake_{k}{e}" for k in ("corr", "auc", "fa") for e in ("", "_lo", "_hi")] + ["seconds"]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["source", *cols])
        for name, m in table.items():
            w.writerow([name, *(f"{m[c]:.4f}" if c in m else "" for c in cols)])


@guarded
def run(cfg: DictConfig) -> dict:
    """Build the branches, score every available source, log one MLflow run each; returns {source: metrics}."""
    import mlflow

    validate.check(cfg, SCHEMA)
    bounds = {"branch.min_steps, branch.max_steps": (cfg.branch.min_steps, cfg.branch.max_steps), "plans.delay": cfg.plans.delay}
    for key, (low, high) in bounds.items():
        if low > high:
            raise UserError(f"{key} = {low}, {high}: the low end is above the high end")
    out = writable(Path(cfg.out_dir), "out_dir")
    open_experiment("interaction")  # an unusable store fails now, not after the branches
    scenario = instantiate(cfg.scenario, _convert_="all")
    t0 = time.perf_counter()
    pairs = make_pairs(scenario, dict(cfg.dataset.policy), cfg)
    true = np.stack([p.response for p in pairs])
    true_braking = np.stack([braking(p.xy, p.history, p.world.params.dt) for p in pairs])
    states = np.array([f"{p.seed}/{p.step}" for p in pairs])
    common = {**benchmark_stats(pairs, true, cfg.score.threshold), "n_forcing_plans": int((true_braking > cfg.score.forced).sum())}
    log.info(f"{len(pairs)} pairs from {cfg.states} held-out branch states (seeds from {cfg.seed_offset}) in "
             f"{time.perf_counter() - t0:.1f} s; pairs with a real response (> {cfg.score.threshold} m): "
             f"{common['real_pair_share']:.1%} (" + ", ".join(f"{k[16:]} {v:.1%}" for k, v in common.items()
                                                               if k.startswith("real_pair_share_")) + "); plans "
             f"that make a driver brake harder than {cfg.score.forced} m/s^2: {common['n_forcing_plans']} of {2 * len(pairs)}")
    table, judge = {}, dict(forced=cfg.score.forced, calm=cfg.score.calm, alarm=cfg.score.alarm)
    for name in cfg.sources:
        t0 = time.perf_counter()
        preds = predict(name, pairs, cfg)
        if preds is None:
            continue
        brakes = preds.pop("braking")
        metrics = brake_scores(brakes, true_braking, **judge)
        metrics.update({f"{k}{suffix}": v for suffix, pred in preds.items()
                        for k, v in scores(pred, true, cfg.score.threshold, cfg.score.tolerance).items()})
        if cfg.score.resamples:
            for suffix, pred in preds.items():
                metrics.update(intervals(pred, true, states, cfg.score.resamples, suffix))
            metrics.update(intervals(brakes, true_braking, states, cfg.score.resamples,
                                     score=lambda p, t: brake_scores(p, t, **judge)))
        metrics["seconds"] = time.perf_counter() - t0
        with mlflow_run("interaction", cfg, run_name=f"interaction-{name}", source=name):
            mlflow.log_metrics({**metrics, **common})
            if preds:  # the follower predicts no response
                png = out / f"scatter_{name}.png"
                scatter(png, name, true, preds, metrics)
                mlflow.log_artifact(str(png))
        table[name] = metrics
        log.info(f"{name:>9}: " + ", ".join(f"{k} {v:.3f}" for k, v in metrics.items()))
    write_table(out / "interaction.csv", table)
    log.info(f"table: {out / 'interaction.csv'}")
    return table


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="evaluate_interaction")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Console entry point."""
    console("evaluate_interaction", hydra_main)
