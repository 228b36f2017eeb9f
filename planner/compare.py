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

A run that records iterates for the surrogate's training (record_dir) is a data job and no row. Each row gets a short
label (gradients/method/mpc/scenario, then only what tells rows apart: labels), which names its marker in compare.png.
It prints a short table, the params that tell rows apart and the cells of SHORT (n_episodes, courteous-merge rate, t_merge,
fallbacks, gradient error, step time), writes every column to compare.csv, and logs to MLflow the table without the
columns equal in every row (those as the run's every_row.<column> params): the label, outcomes, speed, accuracy first.
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
    """One row per combination of the compared params (param_frame) of the runs that evaluate (not those recording
    iterates: record_dir, counted in df.attrs["recorded"]): its short `label` first, the runs pooled, episode-weighted
    outcomes with 95% intervals, median step times, accuracy. Its param columns, `columns` then every other that differs
    between rows, are listed in df.attrs["params"]."""
    runs = planner_runs[planner_runs["status"] == "FINISHED"].copy() if not planner_runs.empty else planner_runs
    if "tags.mlflow.parentRunId" in runs:  # a parent run (method=both, a sweep) holds no episodes of its own
        runs = runs[~runs["run_id"].isin(set(runs["tags.mlflow.parentRunId"].dropna()))]
    recorded = runs["params.record_dir"].notna() & (runs["params.record_dir"] != "None") if "params.record_dir" in runs \
        else pd.Series(False, index=runs.index)
    runs = runs[~recorded]  # a run that records its iterates (record_dir) makes a data set: no evaluation to compare
    if runs.empty:
        raise UserError("no finished planner runs in the MLflow store: run `planner` first"
                        + (f" ({int(recorded.sum())} only recorded iterates: record_dir)" if recorded.any() else ""))
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
    df.insert(0, "label", labels(df, params))
    df.attrs["params"], df.attrs["recorded"] = params, int(recorded.sum())
    return df


SHOWN = ("gradients", "method", "mpc", "scenario")  # what every set-up's label says
PER_PANEL = 6  # set-ups a panel draws: more get a row of panels per six
ID_PREFIXES = ("sha256.", "model_run.")  # params holding a hash or a run id: a label shows their first 8 characters


def labels(df: pd.DataFrame, params) -> list[str]:
    """Each row's short label: its SHOWN values joined by '/', then those of `params` that tell rows apart beyond them
    (a param the SHOWN values determine, such as the predictor of a gradient source, adds nothing): seed and episodes
    as one seed range, a model file's hash or run id as its first 8 characters."""
    head = [c for c in SHOWN if c in df]
    follows = lambda c: bool(head) and df.groupby(head, dropna=False)[c].nunique(dropna=False).max() <= 1
    extra = [c for c in params if c in df and c not in head and df[c].nunique() > 1 and not follows(c)]
    seeds = any(c in extra for c in ("seed", "episodes")) and "seed" in df

    def one(r: pd.Series) -> str:
        parts = [seed_range(r)] if seeds else []
        for c in extra:
            if c in ("seed", "episodes"):
                continue
            short = c.startswith(ID_PREFIXES) and r[c] != "-"
            parts.append(f"{c.split('.', 1)[1] if short else c}={str(r[c])[:8] if short else r[c]}")
        name = "/".join(str(r[c]) for c in head if r[c] != "-")
        return f"{name} ({', '.join(parts)})" if parts else name

    return [one(r) for _, r in df.iterrows()]


def seed_range(r: pd.Series) -> str:
    """A row's episode seeds: 'seed s', or 'seeds s-e' for a batch (its `episodes` param > 0)."""
    n = int(r["episodes"]) if str(r.get("episodes", "-")).isdigit() else 0
    return f"seeds {r['seed']}-{int(r['seed']) + n - 1}" if n and str(r["seed"]).isdigit() else f"seed {r['seed']}"


def shared(df: pd.DataFrame, params) -> dict:
    """{param: value} of `params` equal in every row (a model's hash or run id and '-' left out): what a figure's title
    and the compare run's params say once instead of on every row."""
    return {c: df[c].iloc[0] for c in params if c in df and df[c].nunique(dropna=False) == 1 and df[c].iloc[0] != "-"
            and not c.startswith(ID_PREFIXES)}


def plot(df: pd.DataFrame, path: Path, same: dict | None = None):
    """Against median MPC step time (ms), one numbered marker per row (its `label` and episode count in the key below
    the panels), PER_PANEL rows a panel: gradient error (relative error of d b_i/dZ against teacher autodiff along
    ramps, 95% interval, the trivial baselines as lines; along single coordinates for runs scored before the ramps),
    courteous-merge rate with its 95% Wilson interval, and interaction fidelity of the gradient (react_corr_jac); a
    panel no row has a value for is left out. `same`: the params every row shares, said once in the title."""
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    g = "ramp_grad_rel_err" if df["ramp_grad_rel_err"].notna().any() else "grad_rel_err"
    panels = [p for p in (g, "courteous_rate", "react_corr_jac") if df[p].notna().any()] or ["courteous_rate"]
    chunks = [range(i, min(i + PER_PANEL, len(df))) for i in range(0, len(df), PER_PANEL)]
    key_rows = -(-len(df) // len(panels))  # the key's lines: one column of entries per panel
    fig, axes = plt.subplots(len(chunks), len(panels), figsize=(6.2 * len(panels), 4.8 * len(chunks) + 0.6 + 0.2 * key_rows),
                             squeeze=False, layout="constrained", sharex=True)
    cmap = plt.get_cmap("tab10")
    markers = "osD^v<>"
    handles = []
    for row, chunk in zip(axes, chunks):
        for ax, col in zip(row, panels):
            for k, i in enumerate(chunk):
                r = df.iloc[i]
                x, y = r["step_median_ms"], r[col]
                if not (np.isfinite(x) and np.isfinite(y)):
                    continue
                lo, hi = {g: (f"{g}_lo", f"{g}_hi"), "courteous_rate": ("courteous_lo", "courteous_hi")}.get(col, (None, None))
                bar = [[y - r[lo]], [r[hi] - y]] if lo and np.isfinite(r[lo]) else None
                ax.errorbar(x, y, yerr=bar, capsize=4, color=cmap(k), marker=markers[k], ms=7, ls="none")
                ax.annotate(str(i + 1), (x, y), xytext=(5, 3), textcoords="offset points", fontsize=8, color=cmap(k))
            ax.set(xscale="log", xlabel="median MPC step (ms)")
            ax.margins(x=0.15, y=0.08)  # room for the numbers beside the outermost markers
            ax.axvline(200, color="tab:red", ls=":", lw=1, label="real time (one 0.2 s step)")
            ax.grid(alpha=0.3)
            if col == g:
                for (name, s), ls in zip(BASELINES.items(), ("--", ":")):
                    level = df[f"{g}{s}"].dropna()
                    if len(level):
                        ax.axhline(level.iloc[0], color="k", ls=ls, lw=1, label=f"{name} (baseline)")
                ax.set(ylabel="rel. error of d b_i/dZ vs teacher autodiff" + (" (ramps)" if g != "grad_rel_err" else ""),
                       title="gradient error vs speed")
            elif col == "courteous_rate":
                ax.set(ylabel="courteous-merge rate (95% Wilson interval)", ylim=(-0.05, 1.05), title="outcome vs speed")
            else:
                ax.set(ylabel="react_corr_jac (first-order response vs world's)", ylim=(-1.05, 1.05),
                       title="interaction fidelity vs speed")
            ax.legend(fontsize=7.5, loc="best")
        handles += [Line2D([], [], color=cmap(k), marker=markers[k], ls="none") for k in range(len(chunk))]
    fig.legend(handles, [f"{i + 1}: {df['label'].iloc[i]}, {df['n_episodes'].iloc[i]} ep" for i in range(len(df))],
               loc="outside lower center", ncol=len(panels), fontsize=8, frameon=False)
    same = same or {}
    seeds = lambda: seed_range(same) if "episodes" in same else f"seeds from {same['seed']}"  # batches of other sizes
    said = ", ".join(seeds() if k == "seed" else f"{k}={v}" for k, v in same.items()
                     if k not in SHOWN and not (k == "episodes" and "seed" in same))
    title = f"{len(df)} set-ups, {int(df['n_episodes'].sum())} episodes; each labelled gradients/method/mpc/scenario" + \
        (f"; every set-up: {said}" if said else "")
    fig.suptitle("\n".join(textwrap.wrap(title, int(12 * 6.2 * len(panels)))), fontsize=9)  # 9 pt: 14 characters an inch
    fig.savefig(path, dpi=110)
    plt.close(fig)


def logged(df: pd.DataFrame, params) -> tuple[pd.DataFrame, dict]:
    """The table compare logs to MLflow (log_table) and the values it leaves out: `label` first, then the outcome, speed
    and accuracy columns, the params that tell rows apart and the runs; a column with one value in every row (of a
    table of several rows; of one row: its params and its empty cells) is left out and returned as {column: value}
    (those no run logged, NaN or '-', not at all)."""
    order = ["label", *(c for c in df if c not in params and c not in ("label", "runs")), *params, "runs"]
    constant = lambda c: df[c].nunique(dropna=False) == 1 and (len(df) > 1 or c in params or df[c].isna().all())
    out = [c for c in order if c == "label" or not constant(c)]
    return df[out], {c: df[c].iloc[0] for c in order if c not in out and pd.notna(df[c].iloc[0]) and df[c].iloc[0] != "-"}


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
    plot(df, out / "compare.png", shared(df, group_by))
    experiment = "" if cfg.experiment == "planner" else f"{cfg.experiment}-"
    name = f"compare-{experiment}{OmegaConf.select(cfg, 'scenario.name') or 'all'}-{int(df['n_runs'].sum())}runs"
    with mlflow_run("compare", cfg, run_name=name, recorded_runs_left_out=df.attrs["recorded"]):
        import mlflow

        table_, same = logged(df, group_by)
        mlflow.log_params({f"every_row.{k}": v for k, v in same.items()})  # said once, not in each row of the table
        mlflow.log_table(table_.astype(object).where(table_.notna(), None), "compare_table.json")  # MLflow's table view
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
