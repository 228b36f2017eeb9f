"""`compare`: prediction and gradient accuracy beside planning speed and outcomes, one row per gradient source and method.

Rows come from the `planner` experiment grouped by run params (a Hydra multirun sweep lines up by itself);
accuracy columns come from the latest `distill` run of each model and the latest `surrogate` run.
A batch run counts as `episodes` episodes: its `merged`/`collision` metrics are rates, the others means;
t_merge is averaged over merged episodes only.
"""
import logging
import os
from pathlib import Path

import hydra
import numpy as np
import pandas as pd
from omegaconf import DictConfig

from core.jobs import CONF_DIR, DEFAULT_TRACKING_URI, UserError, guarded, mlflow_run

OUTCOMES = ["merged", "collision", "t_merge", "C_max", "d_min_m", "step_ms_median", "step_ms_p95", "admm_iters_mean", "fallbacks"]
log = logging.getLogger(__name__)
ACCURACY = ["ade_1step_m", "ade_rollout_m", "jac_rel_err", "grad_cosine", "grad_rel_err"]


def latest(runs: pd.DataFrame, param: str, value: str) -> pd.Series | None:
    """The newest finished run whose `param` equals `value`, or None."""
    col = f"params.{param}"
    if runs.empty or col not in runs:
        return None
    hit = runs[(runs[col] == value) & (runs["status"] == "FINISHED")]
    return None if hit.empty else hit.sort_values("start_time").iloc[-1]


def accuracy(gradients: str, distill_runs: pd.DataFrame, surrogate_runs: pd.DataFrame) -> dict:
    """Accuracy columns for a gradient source: the predictor's ADE and the gradient's error vs teacher autodiff."""
    model = "student" if gradients == "student" else "teacher"
    row = {k: np.nan for k in ACCURACY}
    pred = latest(distill_runs, "model", model)
    if pred is not None:
        row.update({k: pred.get(f"metrics.{k}", np.nan) for k in ("ade_1step_m", "ade_rollout_m", "jac_rel_err")})
    if gradients in ("teacher", "fd"):  # the teacher's autodiff is the reference (exact by definition); fd is not measured
        row.update(jac_rel_err=np.nan, grad_cosine=np.nan, grad_rel_err=np.nan)
    if gradients == "surrogate":
        sur = latest(surrogate_runs, "source", "teacher")
        if sur is not None:
            row.update({k: sur.get(f"metrics.{k}", np.nan) for k in ("jac_rel_err", "grad_cosine", "grad_rel_err")})
    return row


def table(planner_runs: pd.DataFrame, distill_runs: pd.DataFrame, surrogate_runs: pd.DataFrame, group_by) -> pd.DataFrame:
    """One row per combination of `group_by` params: episode-weighted outcomes, median step times, accuracy."""
    runs = planner_runs[planner_runs["status"] == "FINISHED"].copy()
    missing = [p for p in group_by if f"params.{p}" not in runs]
    if runs.empty or missing:
        raise UserError("no finished planner runs with params " + ", ".join(group_by) + " in the MLflow store: run `planner` first")
    n = runs["metrics.episodes"].fillna(1.0) if "metrics.episodes" in runs else pd.Series(1.0, index=runs.index)
    runs["n"] = n
    rows = []
    for key, g in runs.groupby([f"params.{p}" for p in group_by], dropna=False):
        w = g["n"]
        row = dict(zip(group_by, key if isinstance(key, tuple) else (key,)))
        row["episodes"] = int(w.sum())
        for m in ("merged", "collision"):
            col = g.get(f"metrics.{m}")
            row[f"{m}_rate"] = float(np.average(col, weights=w)) if col is not None and col.notna().all() else np.nan
        for m in ("t_merge", "C_max", "admm_iters_mean", "fallbacks"):
            col = g.get(f"metrics.{m}")
            # t_merge means something only for merges: a run that never merged logs the steps it drove
            wm = w * g["metrics.merged"].fillna(0.0) if m == "t_merge" and "metrics.merged" in g else w
            ok = col.notna() & (wm > 0) if col is not None else None
            row[m] = float(np.average(col[ok], weights=wm[ok])) if ok is not None and ok.any() else np.nan
        row["d_min_m"] = float(g["metrics.d_min_m"].min()) if "metrics.d_min_m" in g else np.nan
        for m in ("step_ms_median", "step_ms_p95"):
            row[m] = float(g[f"metrics.{m}"].median()) if f"metrics.{m}" in g else np.nan
        row.update(accuracy(row.get("gradients", ""), distill_runs, surrogate_runs))
        rows.append(row)
    return pd.DataFrame(rows).sort_values(list(group_by)).reset_index(drop=True)


def plot(df: pd.DataFrame, path: Path):
    """Accuracy (1 - cosine of d b_i/dZ) and merge rate against median MPC step time, a point per row."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for _, r in df.iterrows():
        label = "/".join(str(r[c]) for c in ("gradients", "method", "zstep") if c in r)
        x, err = r["step_ms_median"], 1.0 - r["grad_cosine"]
        if np.isfinite(err):
            axes[0].scatter(x, max(err, 1e-6))
            axes[0].annotate(label, (x, max(err, 1e-6)), fontsize=7)
        axes[1].scatter(x, r["merged_rate"])
        axes[1].annotate(label, (x, r["merged_rate"]), fontsize=7)
    axes[0].set(xscale="log", yscale="log", xlabel="median MPC step (ms)", ylabel="1 - cos(d b_i/dZ, teacher autodiff)",
                title="gradient accuracy vs speed")
    axes[1].set(xscale="log", xlabel="median MPC step (ms)", ylabel="merge rate", ylim=(-0.05, 1.05), title="outcome vs speed")
    for ax in axes:
        ax.axvline(200, color="tab:red", ls=":", lw=1)  # real time: one 0.2 s step
        ax.grid(alpha=0.3)
    fig.tight_layout()
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


@guarded
def run(cfg: DictConfig) -> pd.DataFrame:
    """Build the table, print it, write compare.csv and compare.png, log both to MLflow (experiment `compare`)."""
    df = table(search(cfg.experiment, cfg.scenario), search("distill"), search("surrogate"), list(cfg.group_by))
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    df.to_csv(out / "compare.csv", index=False)
    plot(df, out / "compare.png")
    with mlflow_run("compare", cfg):
        import mlflow

        mlflow.log_artifact(str(out / "compare.csv"))
        mlflow.log_artifact(str(out / "compare.png"))
    with pd.option_context("display.width", 200, "display.max_columns", 30, "display.precision", 3):
        log.info("\n%s", df.to_string(index=False))
    log.info("wrote %s and %s", out / "compare.csv", out / "compare.png")
    return df


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="compare")
def main(cfg: DictConfig) -> None:
    run(cfg)
