"""`compare`: prediction, gradient and interaction accuracy beside planning speed and outcomes, one row per comparable set-up.

Rows come from the `planner` experiment: runs equal in every param they logged (the planner's whole flattened config and
its set-up params: scenario, gradients, predictor, method, zstep, solver, seed, episodes), but the few in `ignore` that
never change an outcome, are pooled and listed in the row's `runs` column; a run's config of a method it was not (a
`method=both` run logs both) is not compared. A batch run counts as `episodes` episodes (the row's `n_episodes` sums
them): its `courteous`/`merged`/`collision` metrics are rates (95% Wilson intervals over the pooled episodes), the
others means; t_merge is averaged over merged episodes only. The table shows the `columns` params, then every other
param that differs between rows.

Accuracy columns belong to the row's predictor and gradient source: the latest `distill` run of its model (constant
velocity: the `cv_*` metrics that run logs beside its own; the analytic predictor is not measured), the latest
`surrogate` run for the surrogate's gradients, and the latest `interaction` run of the source (bench/interaction.py:
react_* for its rollout response, react_*_jac for its first-order response).

It prints a short table, the params that tell rows apart and the cells of SHORT (n_episodes, courteous-merge rate, t_merge,
fallbacks, gradient error, step time), and writes every column to compare.csv.
"""
import logging
import os
from pathlib import Path

import hydra
import numpy as np
import pandas as pd
from omegaconf import DictConfig

from core import stats, validate
from core.jobs import CONF_DIR, DEFAULT_TRACKING_URI, UserError, console, guarded, mlflow_run, open_experiment, options
from planner.gradients import predictor_of
from surrogate.evaluate import HEADLINE, metric

log = logging.getLogger(__name__)
GRADIENT = {"grad_cosine": ("grad_cosine", ""), "grad_rel_err": ("grad_rel_err", ""), "grad_rel_err_lo": ("grad_rel_err", "_lo"),
            "grad_rel_err_hi": ("grad_rel_err", "_hi"), "react_rel_err": ("react_rel_err", ""),
            "react_wrel_err": ("react_wrel_err", ""),
            "ramp_grad_rel_err": ("ramp_grad_rel_err", ""), "ramp_grad_rel_err_lo": ("ramp_grad_rel_err", "_lo"),
            "ramp_grad_rel_err_hi": ("ramp_grad_rel_err", "_hi"), "ramp_react_rel_err": ("ramp_react_rel_err", "")}
# column: (score, end) of d b_i/dZ against teacher autodiff on the surrogate job's held-out planning states, along single
# coordinates of Z and along ramps, plans the ego can drive; react_wrel_err weighs each state by its reaction's size
# (surrogate.evaluate)
ACCURACY = ["ade_1step_m", "ade_rollout_m", "jac_rel_err", *GRADIENT]
SOURCE_SUFFIX = {"surrogate": "", "student": "_student", "cv": "_cv"}  # a gradient source's d b_i/dZ scores in the surrogate
# job's metrics (grad_rel_err, grad_rel_err_student, ...; the surrogate over the student's values: scored_as); the other
# sources are not scored there
BASELINES = {"cv": "_cv", "mean Jacobian": "_mean"}  # the trivial gradient sources every row is shown against
MEANS = ("t_merge", "C_max", "admm_iters_mean", "fallbacks", "b_imposed_max")  # episode-weighted over the pooled runs
INTERACTION = ["react_corr", "react_gain", "react_hit", "react_corr_jac", "react_gain_jac", "react_hit_jac"]


def latest(runs: pd.DataFrame, param: str, value: str) -> pd.Series | None:
    """The newest finished run whose `param` equals `value`, or None."""
    col = f"params.{param}"
    if runs.empty or col not in runs:
        return None
    hit = runs[(runs[col] == value) & (runs["status"] == "FINISHED")]
    return None if hit.empty else hit.sort_values("start_time").iloc[-1]


def metrics_of(run: pd.Series | None, keys, prefix: str = "") -> dict:
    """{key: run's metric `prefix + key`} (NaN where absent or no run)."""
    return {k: np.nan if run is None else run.get(f"metrics.{prefix}{k}", np.nan) for k in keys}


def gradient_error(run: pd.Series | None, source: str) -> dict:
    """GRADIENT's columns of the Jacobian source the surrogate job scored as `source` ("" the surrogate, "_cv", "_mean",
    "_student"); NaN where absent."""
    return {col: np.nan if run is None else run.get(f"metrics.{metric(k, source, e)}", np.nan) for col, (k, e) in GRADIENT.items()}


def scored_as(gradients: str, predictor: str | None = None) -> str | None:
    """The surrogate job's metric suffix of a gradient source's d b_i/dZ scores over a predictor (by default its own:
    the surrogate's, the student's values); None where the job does not score it."""
    predictor = predictor or (predictor_of(gradients) if gradients in options("gradients") else gradients)
    return "_over_student" if (gradients, predictor) == ("surrogate", "student") else SOURCE_SUFFIX.get(gradients)


def accuracy(gradients: str, predictor: str, distill_runs: pd.DataFrame, surrogate_runs: pd.DataFrame,
             interaction_runs: pd.DataFrame) -> dict:
    """Accuracy columns of a row: its predictor's ADE (m), its gradient's error against teacher autodiff beside the
    trivial baselines' on the same states (grad_rel_err_cv, grad_rel_err_mean, react_rel_err_mean), the source's
    interaction scores."""
    row = {k: np.nan for k in ACCURACY}
    if predictor in validate.TRAINED_PREDICTORS:  # a model with a `distill` run of its own
        row.update(metrics_of(latest(distill_runs, "model", predictor), ("ade_1step_m", "ade_rollout_m")))
    elif predictor == "cv":  # every distill run evaluates constant velocity on its test split beside its own model
        row.update(metrics_of(latest(distill_runs, "model", "teacher"), ("ade_1step_m", "ade_rollout_m"), "cv_"))
    if gradients == "student":  # the student's Jacobian against the teacher's, measured by its distill run
        row.update(metrics_of(latest(distill_runs, "model", "student"), ("jac_rel_err",)))
    scored = latest(surrogate_runs, "source", "teacher")  # the surrogate job scores each source's d b_i/dZ on its states
    if gradients == "surrogate":
        row.update(metrics_of(scored, ("jac_rel_err",)))
    suffix = scored_as(gradients, predictor)
    if suffix is not None:
        row.update(gradient_error(scored, suffix))
    for s in BASELINES.values():
        row.update({metric(k, s): v for k, v in gradient_error(scored, s).items() if k in HEADLINE})
    row.update(metrics_of(latest(interaction_runs, "source", gradients), INTERACTION))
    return row


def param_frame(runs: pd.DataFrame, columns, ignore) -> pd.DataFrame:
    """Every param the runs logged but those in `ignore` (a key or a prefix of keys), and every one of `columns`, as
    strings: '-' where a run did not log it (older runs) or where it configures a method the run was not."""
    ignored = lambda p: any(p == i or p.startswith(f"{i}.") for i in ignore)
    logged = [c[len("params."):] for c in runs.columns if c.startswith("params.")]
    keys = list(dict.fromkeys([*columns, *(p for p in logged if not ignored(p))]))
    frame = pd.DataFrame({p: runs[f"params.{p}"].fillna("-") if f"params.{p}" in runs else "-" for p in keys}, index=runs.index)
    if "method" in frame:
        for p in keys:
            if p.startswith("method."):
                frame.loc[frame["method"] != p.split(".")[1], p] = "-"
    return frame


def table(planner_runs: pd.DataFrame, distill_runs: pd.DataFrame, surrogate_runs: pd.DataFrame, columns,
          interaction_runs: pd.DataFrame | None = None, ignore=()) -> pd.DataFrame:
    """One row per combination of the compared params (param_frame): the runs pooled, episode-weighted outcomes with 95%
    intervals, median step times, accuracy. Its param columns, `columns` then every other that differs between rows,
    are listed in df.attrs["params"]."""
    runs = planner_runs[planner_runs["status"] == "FINISHED"].copy() if not planner_runs.empty else planner_runs
    if runs.empty:
        raise UserError("no finished planner runs in the MLflow store: run `planner` first")
    interaction_runs = pd.DataFrame() if interaction_runs is None else interaction_runs
    keys = param_frame(runs, columns, ignore)
    group_by = list(keys.columns)
    runs["n"] = runs["metrics.episodes"].fillna(1.0) if "metrics.episodes" in runs else 1.0
    rows = []
    for key, g in runs.groupby([keys[p] for p in group_by]):
        w = g["n"]
        row = dict(zip(group_by, key if isinstance(key, tuple) else (key,)))
        row["n_runs"] = len(g)
        row["n_episodes"] = int(w.sum())
        pooled = stats.outcomes([[{"n": n, **{m: r.get(f"metrics.{m}", np.nan) for m in (*stats.RATES, *MEANS)}}
                                  for n, (_, r) in zip(w, g.iterrows())]], means=MEANS, weight="n")
        for m in stats.RATES:
            row[f"{m}_rate"], row[f"{m}_lo"], row[f"{m}_hi"] = pooled[m], pooled[f"{m}_lo"], pooled[f"{m}_hi"]
        row.update({m: pooled[m] for m in MEANS})  # no intervals: the runs log no spread within their batches
        row["d_min_m"] = float(g["metrics.d_min_m"].min()) if "metrics.d_min_m" in g else np.nan
        for m in ("step_ms_median", "step_ms_p95"):
            row[m] = float(g[f"metrics.{m}"].median()) if f"metrics.{m}" in g else np.nan
        gradients, predictor = row.get("gradients", "-"), row.get("predictor", "-")
        if predictor == "-":  # a run older than the `predictor` param: its gradient source's default predictor
            predictor = predictor_of(gradients) if gradients in options("gradients") else gradients
        row.update(accuracy(gradients, predictor, distill_runs, surrogate_runs, interaction_runs))
        row["runs"] = " ".join(sorted(r[:8] for r in g["run_id"])) if "run_id" in g else ""
        rows.append(row)
    df = pd.DataFrame(rows)
    params = [*columns, *(p for p in group_by if p not in columns and df[p].nunique() > 1)]
    df = df[params + [c for c in df.columns if c not in group_by]].sort_values(params).reset_index(drop=True)
    df.attrs["params"] = params
    return df


def label(r: pd.Series, varying) -> str:
    """A row's legend label: its gradient source and method, then every other grouping param that varies across rows."""
    head = "/".join(str(r[c]) for c in ("gradients", "method") if c in r)
    rest = ", ".join(f"{c}={r[c]}" for c in varying if c not in ("gradients", "method"))
    return f"{head} ({rest})" if rest else head


def plot(df: pd.DataFrame, path: Path, group_by=()):
    """Three panels against median MPC step time, one marker per row with a legend: gradient error (relative error of
    d b_i/dZ against teacher autodiff along ramps, 95% interval, the trivial baselines as lines; along single
    coordinates for runs scored before the ramps), courteous-merge rate with its 95%
    Wilson interval, interaction fidelity of the gradient (react_corr_jac)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    varying = [c for c in group_by if c in df and df[c].nunique() > 1]
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2))
    cmap = plt.get_cmap("tab10" if len(df) <= 10 else "tab20")
    markers = "osD^v<>Ph*X"
    handles = []
    g = "ramp_grad_rel_err" if df["ramp_grad_rel_err"].notna().any() else "grad_rel_err"
    for i, (_, r) in enumerate(df.iterrows()):
        style = dict(color=cmap(i % cmap.N), marker=markers[i % len(markers)], ms=7, ls="none")
        x = r["step_ms_median"]
        err = r[g]
        if np.isfinite(err):
            bar = [[err - r[f"{g}_lo"]], [r[f"{g}_hi"] - err]]
            axes[0].errorbar(x, err, yerr=bar if np.isfinite(r[f"{g}_lo"]) else None, capsize=4, **style)
        yerr = [[r["courteous_rate"] - r["courteous_lo"]], [r["courteous_hi"] - r["courteous_rate"]]]
        h = axes[1].errorbar(x, r["courteous_rate"], yerr=yerr if np.isfinite(r["courteous_lo"]) else None, capsize=4, **style)
        if np.isfinite(r["react_corr_jac"]):
            axes[2].plot(x, r["react_corr_jac"], **style)
        handles.append((h, f"{label(r, varying)}: {r['n_episodes']} ep, {r['n_runs']} run{'s' * (r['n_runs'] > 1)}"))
    for (name, s), ls in zip(BASELINES.items(), ("--", ":")):
        level = df[f"{g}{s}"].dropna()
        if len(level):
            axes[0].axhline(level.iloc[0], color="k", ls=ls, lw=1, label=f"{name} (baseline)")
            axes[0].legend(fontsize=8)
    axes[0].set(xscale="log", ylabel="rel. error of d b_i/dZ vs teacher autodiff" + (" (along ramps)" if g != "grad_rel_err" else ""),
                title="gradient error vs speed")
    axes[1].set(xscale="log", ylabel="courteous-merge rate (95% Wilson interval)", ylim=(-0.05, 1.05), title="outcome vs speed")
    axes[2].set(xscale="log", ylabel="react_corr_jac (first-order response vs true)", ylim=(-1.05, 1.05),
                title="interaction fidelity vs speed")
    for ax in axes:
        ax.set_xlabel("median MPC step (ms)")
        ax.axvline(200, color="tab:red", ls=":", lw=1)  # real time: one 0.2 s step
        ax.grid(alpha=0.3)
    fig.legend([h for h, _ in handles], [t for _, t in handles], loc="lower center", ncol=min(3, len(handles)), fontsize=8,
               frameon=False)
    fig.tight_layout(rect=(0, 0.06 * (1 + (len(handles) - 1) // 3), 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def search(experiment: str, scenario=None) -> pd.DataFrame:
    """All runs of an MLflow experiment (empty frame if it does not exist), optionally of one scenario."""
    import mlflow

    mlflow.set_tracking_uri(os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_TRACKING_URI))
    runs = mlflow.search_runs(experiment_names=[experiment])
    if scenario and not runs.empty and "params.scenario" in runs:
        runs = runs[runs["params.scenario"] == scenario]
    return runs


def fmt(v, f=".2f", lo=None, hi=None) -> str:
    """A cell: the value, with its interval in brackets when it has one wider than nothing; '-' for NaN."""
    if v is None or not np.isfinite(v):
        return "-"
    if lo is None or not np.isfinite(lo) or hi - lo <= 0:
        return f"{v:{f}}"
    return f"{v:{f}} [{lo:{f}}, {hi:{f}}]"


def gradient_cell(r: pd.Series) -> str:
    """A row's gradient error against teacher autodiff with its interval: along ramps, or along single coordinates for
    runs scored before the ramps."""
    g = "ramp_grad_rel_err" if np.isfinite(r["ramp_grad_rel_err"]) else "grad_rel_err"
    return fmt(r[g], ".3f", r[f"{g}_lo"], r[f"{g}_hi"])


SHORT = {"n_episodes": lambda r: str(r["n_episodes"]),
         "courteous % [95% CI]": lambda r: fmt(100 * r["courteous_rate"], ".1f", 100 * r["courteous_lo"], 100 * r["courteous_hi"]),
         "t_merge": lambda r: fmt(r["t_merge"], ".1f"),
         "fallbacks": lambda r: fmt(r["fallbacks"]),
         "grad error": gradient_cell,
         "step ms med/p95": lambda r: f"{fmt(r['step_ms_median'], '.1f')}/{fmt(r['step_ms_p95'], '.1f')}"}
# the printed table's outcome columns (compare.csv has every column): what each row's source bought, at what speed;
# t_merge in steps, fallbacks per episode, grad error: d b_i/dZ against teacher autodiff (gradient_cell)


def short(df: pd.DataFrame, params) -> pd.DataFrame:
    """The printed table: the row's `params`, then SHORT's cells."""
    return pd.concat([df[params].astype(str), pd.DataFrame({c: df.apply(f, axis=1) for c, f in SHORT.items()})], axis=1)


@guarded
def run(cfg: DictConfig) -> pd.DataFrame:
    """Build the table, print it, write compare.csv and compare.png, log both to MLflow (experiment `compare`)."""
    validate.check(cfg, "compare")
    open_experiment("compare")  # one line if the store is unusable, before the searches
    df = table(search(cfg.experiment, cfg.scenario), search("distill"), search("surrogate"), list(cfg.columns),
               search("interaction"), list(cfg.ignore))
    group_by = df.attrs["params"]
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "compare.csv", index=False)
    plot(df, out / "compare.png", group_by)
    with mlflow_run("compare", cfg):
        import mlflow

        mlflow.log_artifact(str(out / "compare.csv"))
        mlflow.log_artifact(str(out / "compare.png"))
    lead = [c for c in cfg.columns if c in df]
    # a param that follows from the `columns` ones (method.nnmpc.* with method) adds nothing to the printed table
    follows = lambda c: c not in lead and bool(lead) and df.groupby(lead, dropna=False)[c].nunique().max() <= 1
    shown = [c for c in group_by if (df[c].nunique() > 1 and not follows(c)) or c in ("gradients", "method", "mpc")]
    same = {c: df[c].iloc[0] for c in group_by if c not in shown and df[c].nunique() == 1 and df[c].iloc[0] != "-"}
    g = "ramp_grad_rel_err" if df["ramp_grad_rel_err"].notna().any() else "grad_rel_err"
    baselines = ", ".join(f"{name} {fmt(df[f'{g}{s}'].dropna().iloc[0], '.3f')}" for name, s in BASELINES.items()
                          if df[f"{g}{s}"].notna().any())
    log.info("every row: %s%s\n%s", ", ".join(f"{k}={v}" for k, v in same.items()),
             f"; d b_i/dZ error of the baselines: {baselines}" if baselines else "",
             short(df, shown).to_string(index=False))
    log.info("wrote %s (all columns) and %s", out / "compare.csv", out / "compare.png")
    return df


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="compare")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Console entry point."""
    console("compare", hydra_main)
