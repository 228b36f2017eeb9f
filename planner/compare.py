"""`compare`: prediction, gradient and interaction accuracy beside planning speed and outcomes, one row per comparable set-up.

Rows come from the `planner` experiment: runs equal in every param they logged (the planner's whole flattened config and
its set-up params: scenario, gradients, predictor, method, zstep, solver, seed, episodes), but the few in `ignore` that
never change an outcome, are pooled and listed in the row's `runs` column; a run's config of a method it was not (a
`method=both` run logs both) is not compared. A batch run counts as `episodes` episodes (the row's `n_episodes` sums
them): its `courteous`/`merged`/`collision` metrics are rates (95% Wilson intervals over the pooled episodes), the
others means; t_merge is averaged over merged episodes only. The table shows the `columns` params, then every other
param that differs between rows.

Accuracy columns belong to the row's predictor and gradient source: the latest `distill` run of its model (constant
velocity: the `*_cv` metrics that run logs beside its own; a hypothesis model: its belief_* too; the analytic predictor is not measured), the latest
`surrogate` run for the surrogate's gradients, and the latest `interaction` run of the source (bench/interaction.py:
react_* for its rollout response, react_*_jac for its first-order response).

It prints a short table, the params that tell rows apart and the cells of SHORT (n_episodes, courteous-merge rate, t_merge,
fallbacks, gradient error, step time), and writes every column to compare.csv.
"""
import logging
from pathlib import Path

import hydra
import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from core import stats, validate
from core.jobs import (
    CONF_DIR,
    MODEL_FILES,
    UserError,
    console,
    guarded,
    mlflow_run,
    model_runs,
    open_experiment,
    options,
    tracking_uri,
)
from planner.gradients import predictor_of
from planner.report import MLFLOW_NAMES
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
BELIEF = ["belief_brier", "belief_brier_ratio", "belief_auc_0.8s"]  # a hypothesis model's belief: Brier, its ratio to the prior's, AUC 0.8 s in
ACCURACY = ["ade_1step_m", "ade_rollout_m", *BELIEF, "jac_rel_err", *GRADIENT]
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


def metrics_of(run: pd.Series | None, keys, suffix: str = "") -> dict:
    """{key: run's metric `key + suffix`} (NaN where absent or no run)."""
    return {k: np.nan if run is None else run.get(f"metrics.{k}{suffix}", np.nan) for k in keys}


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
    """Accuracy columns of a row: its predictor's ADE (m) and its belief's calibration (hypothesis models), its gradient's
    error against teacher autodiff beside the trivial baselines' on the same states (grad_rel_err_cv, grad_rel_err_mean,
    react_rel_err_mean), the source's interaction scores."""
    row = {k: np.nan for k in ACCURACY}
    if predictor in validate.TRAINED_PREDICTORS:  # a model with a `distill` run of its own
        row.update(metrics_of(latest(distill_runs, "model", predictor), ("ade_1step_m", "ade_rollout_m", *BELIEF)))
    elif predictor == "cv":  # every distill run evaluates constant velocity on its test split beside its own model
        row.update(metrics_of(latest(distill_runs, "model", "teacher"), ("ade_1step_m", "ade_rollout_m"), "_cv"))
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


ACCURACY_LOGGED = (*ACCURACY, *(metric(k, b) for k in HEADLINE for b in BASELINES.values()), *INTERACTION)
# what a planner run logs of its source's accuracy (source_link), compare's columns of the same names


def same_models(runs: pd.DataFrame, files: dict) -> pd.DataFrame:
    """The runs whose logged model hashes (params sha256.<file>) agree with `files` ({file: sha256}) on every file both
    name."""
    keep = pd.Series(True, index=runs.index)
    for f, digest in files.items():
        col = f"params.sha256.{f}"
        if col in runs:
            keep &= runs[col].isna() | (runs[col] == digest)
    return runs[keep]


def source_link(gradients: str, predictor: str) -> tuple[dict, dict]:
    """(params, metrics) a planner run logs to tie it to its models' runs: model_run.<file> = the id of the run that made
    each model file this process read (core.jobs.model_runs), and the source's accuracy (ACCURACY_LOGGED: its
    predictor's ADE, its gradient error against teacher autodiff, its interaction scores) from those runs, from the
    newest runs of the source where none made them (cv), and from interaction runs over the same model files."""
    made = model_runs(MODEL_FILES)
    ids = {r.info.run_id for r in made.values()}
    distill, surrogate = search("distill"), search("surrogate")
    linked = lambda runs: runs[runs["run_id"].isin(ids)] if not runs.empty and runs["run_id"].isin(ids).any() else \
        same_models(runs, MODEL_FILES)
    acc = accuracy(gradients, predictor, linked(distill), linked(surrogate), same_models(search("interaction"), MODEL_FILES))
    return ({f"model_run.{f}": r.info.run_id for f, r in made.items()},
            {k: float(v) for k, v in acc.items() if k in ACCURACY_LOGGED and np.isfinite(v)})


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
    if "tags.mlflow.parentRunId" in runs:  # a parent run (method=both, a sweep) holds no episodes of its own
        runs = runs[~runs["run_id"].isin(set(runs["tags.mlflow.parentRunId"].dropna()))]
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
        logged = lambda r, m: r.get(f"metrics.{MLFLOW_NAMES.get(m, m)}", np.nan)
        pooled = stats.outcomes([[{"n": n, **{m: logged(r, m) for m in (*stats.RATES, *MEANS)}}
                                  for n, (_, r) in zip(w, g.iterrows())]], means=MEANS, weight="n")
        for m in stats.RATES:
            row[f"{m}_rate"], row[f"{m}_lo"], row[f"{m}_hi"] = pooled[m], pooled[f"{m}_lo"], pooled[f"{m}_hi"]
        # no intervals: the runs log no spread within their batches
        row.update({MLFLOW_NAMES.get(m, m): pooled[m] for m in MEANS})
        row["d_min_m"] = float(g["metrics.d_min_m"].min()) if "metrics.d_min_m" in g else np.nan
        for m in ("step_median_ms", "step_p95_ms"):
            row[m] = float(g[f"metrics.{m}"].median()) if f"metrics.{m}" in g else np.nan
        gradients, predictor = row.get("gradients", "-"), row.get("predictor", "-")
        if predictor == "-":  # a run older than the `predictor` param: its gradient source's default predictor
            predictor = predictor_of(gradients) if gradients in options("gradients") else gradients
        row.update(accuracy(gradients, predictor, distill_runs, surrogate_runs, interaction_runs))
        # what the runs themselves logged of their source's accuracy (linked by model hash: source_link) comes first
        row.update({k: g[f"metrics.{k}"].dropna().iloc[0] for k in row if k in ACCURACY_LOGGED
                    and f"metrics.{k}" in g and g[f"metrics.{k}"].notna().any()})
        row["runs"] = " ".join(sorted(r[:8] for r in g["run_id"])) if "run_id" in g else ""
        rows.append(row)
    df = pd.DataFrame(rows)
    params = [*columns, *(p for p in group_by if p not in columns and df[p].nunique() > 1)]
    df = df[params + [c for c in df.columns if c not in group_by]].sort_values(params).reset_index(drop=True)
    df.attrs["params"] = params
    return df


SHOWN = ("gradients", "method", "mpc", "scenario")  # what a marker's label says first


def label(r: pd.Series, varying) -> str:
    """A row's marker label: its gradient source, method, mpc and scenario, then each other grouping param that varies
    across rows (a model hash shortened to 8 characters)."""
    head = "/".join(str(r[c]) for c in SHOWN if c in r and r[c] != "-")
    short = lambda c: str(r[c])[:8] if c.startswith("sha256.") else str(r[c])
    rest = ", ".join(f"{c.removeprefix('sha256.')}={short(c)}" for c in varying if c not in SHOWN)
    return f"{head} ({rest})" if rest else head


def plot(df: pd.DataFrame, path: Path, group_by=()):
    """Against median MPC step time (ms), one marker per row, each labelled beside it (label) with its episode count:
    gradient error (relative error of d b_i/dZ against teacher autodiff along ramps, 95% interval, the trivial baselines
    as lines; along single coordinates for runs scored before the ramps), courteous-merge rate with its 95% Wilson
    interval, and interaction fidelity of the gradient (react_corr_jac); a panel no row has a value for is left out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    varying = [c for c in group_by if c in df and df[c].nunique() > 1]
    g = "ramp_grad_rel_err" if df["ramp_grad_rel_err"].notna().any() else "grad_rel_err"
    panels = [p for p in (g, "courteous_rate", "react_corr_jac") if df[p].notna().any()] or ["courteous_rate"]
    fig, axes = plt.subplots(1, len(panels), figsize=(6.2 * len(panels), 5.2), squeeze=False)
    cmap = plt.get_cmap("tab10")
    markers = "osD^v<>Ph*X"
    for ax, col in zip(axes[0], panels):
        for i, (_, r) in enumerate(df.iterrows()):
            x, y = r["step_median_ms"], r[col]
            if not (np.isfinite(x) and np.isfinite(y)):
                continue
            lo, hi = {g: (f"{g}_lo", f"{g}_hi"), "courteous_rate": ("courteous_lo", "courteous_hi")}.get(col, (None, None))
            bar = [[y - r[lo]], [r[hi] - y]] if lo and np.isfinite(r[lo]) else None
            ax.errorbar(x, y, yerr=bar, capsize=4, color=cmap(i % 10), marker=markers[i % len(markers)], ms=7, ls="none")
            ax.annotate(f"{label(r, varying)}, {r['n_episodes']} ep", (x, y), xytext=(6, 4), textcoords="offset points",
                        fontsize=7.5, color=cmap(i % 10))
        ax.set(xscale="log", xlabel="median MPC step (ms)")
        ax.axvline(200, color="tab:red", ls=":", lw=1, label="real time (one 0.2 s step)")
        ax.grid(alpha=0.3)
    for ax, col in zip(axes[0], panels):
        if col == g:
            for (name, s), ls in zip(BASELINES.items(), ("--", ":")):
                level = df[f"{g}{s}"].dropna()
                if len(level):
                    ax.axhline(level.iloc[0], color="k", ls=ls, lw=1, label=f"{name} (baseline)")
            ax.set(ylabel="relative error of d b_i/dZ vs teacher autodiff" + (" (along ramps)" if g != "grad_rel_err" else ""),
                   title="gradient error vs speed")
        elif col == "courteous_rate":
            ax.set(ylabel="courteous-merge rate (share of episodes, 95% Wilson interval)", ylim=(-0.05, 1.05),
                   title="outcome vs speed")
        else:
            ax.set(ylabel="react_corr_jac (first-order response vs the world's, correlation)", ylim=(-1.05, 1.05),
                   title="interaction fidelity vs speed")
        ax.legend(fontsize=8, loc="best")
    fig.suptitle(f"{len(df)} set-ups, {int(df['n_episodes'].sum())} episodes: each marker gradients/method/mpc/scenario",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def search(experiment: str, scenario=None) -> pd.DataFrame:
    """All runs of an MLflow experiment (empty frame if it does not exist), optionally of one scenario."""
    import mlflow

    mlflow.set_tracking_uri(tracking_uri())
    if mlflow.get_experiment_by_name(experiment) is None:
        return pd.DataFrame()
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
         "t_merge s": lambda r: fmt(r["t_merge_s"], ".1f"),
         "fallbacks": lambda r: fmt(r["fallbacks"]),
         "grad error": gradient_cell,
         "step ms med/p95": lambda r: f"{fmt(r['step_median_ms'], '.1f')}/{fmt(r['step_p95_ms'], '.1f')}"}
# the printed table's outcome columns (compare.csv has every column): what each row's source bought, at what speed;
# t_merge in s, fallbacks per episode, grad error: d b_i/dZ against teacher autodiff (gradient_cell)


def short(df: pd.DataFrame, params) -> pd.DataFrame:
    """The printed table: the row's `params` (a model file's sha256 as its first 8 characters), then SHORT's cells."""
    shown = df[params].astype(str).apply(lambda col: col.str[:8] if col.name.startswith("sha256.") else col)
    return pd.concat([shown, pd.DataFrame({c: df.apply(f, axis=1) for c, f in SHORT.items()})], axis=1)


@guarded
def run(cfg: DictConfig) -> pd.DataFrame:
    """Build the table, print it, write compare.csv and compare.png, log both to MLflow (experiment `compare`)."""
    validate.check(cfg, "compare")
    open_experiment("compare")  # one line if the store is unusable, before the searches
    df = table(search(cfg.experiment, OmegaConf.select(cfg, "scenario.name")), search("distill"), search("surrogate"), list(cfg.columns),
               search("interaction"), list(cfg.ignore))
    group_by = df.attrs["params"]
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "compare.csv", index=False)
    plot(df, out / "compare.png", group_by)
    name = f"compare-{cfg.experiment}-{OmegaConf.select(cfg, 'scenario.name') or 'every scenario'}"
    with mlflow_run("compare", cfg, run_name=name):
        import mlflow

        mlflow.log_table(df.astype(object).where(df.notna(), None), "compare_table.json")  # MLflow's own table view
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
