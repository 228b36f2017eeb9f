"""Batch statistics: `planner scenario=random episodes=N` drives N seeded episodes (seeds seed .. seed+N-1) in parallel
with joblib and logs one MLflow run per method: rates, means, step-time percentiles, a per-episode CSV, histograms.

An episode that raises is recorded as a crash with its message in the CSV; the batch goes on. Rates and means are
over the episodes that finished; `episodes` counts all N, so `compare` weights the run by its size.
"""
import csv
import logging
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from joblib import Parallel, delayed  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from core.jobs import mlflow_run  # noqa: E402
from planner import report, setup  # noqa: E402

FIGURES = {"t_merge": "t_merge (steps, merged episodes)", "C_max": "C_max", "d_min_m": "d_min (m)",
           "step_ms": "MPC step wall time (ms, every step)", "admm_iters_mean": "ADMM iterations (episode mean)",
           "fallbacks": "fallbacks per episode"}
_WORKER = {}  # per process: the config it was set up for, and its (scenario, source, settings)
log = logging.getLogger(__name__)


def worker_setup(cfg):
    """planner.setup.setup(cfg), once per worker process (models load once), torch on one thread: the workers fill the cores."""
    key = OmegaConf.to_yaml(cfg)
    if _WORKER.get("key") != key:
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(1)
        _WORKER.update(key=key, value=setup.setup(cfg))
    return _WORKER["value"]


def episode(cfg_dict: dict, method: str, seed: int):
    """(CSV row, per-step wall times ms, iterations of the non-fallback steps) of one episode; never raises."""
    try:
        cfg = OmegaConf.create(cfg_dict)
        scenario, source, s = worker_setup(cfg)
        ep = setup.drive(cfg, scenario, source, s, method, seed=seed)
        m = report.metrics(ep, scenario.y_ref, scenario.x_ref, cfg.merge_tol)
        finite = np.isfinite(ep.states).all() and np.isfinite(ep.controls).all() and \
            np.isfinite([m[k] for k in ("t_merge", "C_max", "d_min_m")]).all()
        row = {"seed": seed, **m, "crash": 0, "nan": int(not finite), "error": "",
               "notes": "; ".join(ep.notes)}
        return row, [r["step_ms"] for r in ep.rows], [r["iterations"] for r in ep.rows if not r["fallback"]]
    except Exception as e:  # one bad episode must not kill a thousand: count it and carry its message
        return {"seed": seed, "crash": 1, "nan": 0, "error": f"{type(e).__name__}: {e}"[:500]}, [], []


def aggregate(rows, step_ms, iters) -> dict:
    """The run's metrics from the per-episode rows and the pooled per-step wall times (ms) and iterations."""
    done = [r for r in rows if not r["crash"]]
    col = lambda k: np.array([r[k] for r in done], float)
    merged = col("merged").astype(bool) if done else np.zeros(0, bool)
    safe = lambda f, a: float(f(a)) if len(a) else float("nan")
    return {"episodes": float(len(rows)), "crashes": float(len(rows) - len(done)), "nans": float(sum(r["nan"] for r in rows)),
            "merged": safe(np.mean, merged), "collision": safe(np.mean, col("collision") if done else []),
            "t_merge": safe(np.mean, col("t_merge")[merged] if done else []), "C_max": safe(np.nanmean, col("C_max") if done else []),
            "d_min_m": safe(np.min, col("d_min_m") if done else []), "fallbacks": safe(np.mean, col("fallbacks") if done else []),
            "step_ms_median": safe(np.median, step_ms), "step_ms_p95": safe(lambda a: np.percentile(a, 95), step_ms),
            "admm_iters_mean": safe(np.mean, iters)}


def write_csv(rows, path):
    """One row per episode: seed, outcome metrics, crash (0/1) with its error message, nan (0/1), notes."""
    fields = list(dict.fromkeys(k for r in sorted(rows, key=lambda r: r["crash"]) for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)


def histograms(rows, step_ms, out_dir, tag, title):
    """One PNG per figure in FIGURES: its distribution over the finished episodes (step_ms: over every step)."""
    done = [r for r in rows if not r["crash"]]
    paths = []
    for key, label in FIGURES.items():
        if key == "step_ms":
            values = np.asarray(step_ms, float)
        else:
            values = np.array([r[key] for r in done if key != "t_merge" or r["merged"]], float)
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.hist(values[np.isfinite(values)], bins=30, color="tab:blue", alpha=0.8)
        ax.set(xlabel=label, ylabel="count", title=f"{title}\n{label}, n = {np.isfinite(values).sum()}")
        fig.tight_layout()
        paths.append(out_dir / f"hist_{tag}_{key}.png")
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)
    return paths


def drive_all(cfg, method: str) -> list:
    """[episode(...)] for seeds cfg.seed .. cfg.seed + cfg.episodes - 1, over cfg.n_jobs joblib processes."""
    cfg_dict = OmegaConf.to_container(cfg, resolve=True)
    seeds = range(cfg.seed, cfg.seed + cfg.episodes)
    return Parallel(n_jobs=cfg.n_jobs)(delayed(episode)(cfg_dict, method, seed) for seed in seeds)


def record(cfg, scenario, source, s, method: str, out: list, out_dir) -> dict:
    """Aggregate drive_all's output, write the CSV and histograms to out_dir, log one MLflow run; returns its metrics."""
    import mlflow

    rows = [o[0] for o in out]
    step_ms = [t for o in out for t in o[1]]
    r = aggregate(rows, step_ms, [k for o in out for k in o[2]])
    tag = f"{method}_{source.name}_{scenario.name}"
    title = f"{scenario.name}, {method}, gradients={source.name}: {len(rows)} episodes"
    csv_path = out_dir / f"episodes_{tag}.csv"
    write_csv(rows, csv_path)
    plots = histograms(rows, step_ms, out_dir, tag, title) if cfg.plots else []
    with mlflow_run("planner", cfg, run_name=f"batch-{method}-{source.name}-{scenario.name}", method=method,
                    episodes=len(rows), **setup.run_params(scenario, source, s, cfg.seed)):
        mlflow.log_metrics(r)
        mlflow.log_artifact(str(csv_path))
        for p in plots:
            mlflow.log_artifact(str(p), "plots")
    for e in sorted({row["error"] for row in rows if row["crash"]}):
        log.info(f"[{method}] crash: {e}")
    log.info(f"[{method}] {title}: merged {r['merged']:.1%}, collision {r['collision']:.1%}, t_merge {r['t_merge']:.1f} "
          f"steps, d_min {r['d_min_m']:.2f} m, step {r['step_ms_median']:.1f} ms median / {r['step_ms_p95']:.1f} p95, "
          f"{r['fallbacks']:.2f} fallbacks per episode, {r['crashes']:.0f} crashes, {r['nans']:.0f} NaN episodes; "
          f"outputs in {out_dir}")
    return r


def run(cfg, scenario, source, s, methods, out_dir) -> dict:
    """Drive cfg.episodes episodes per method, write and log each method's batch; returns {method: metrics}."""
    return {m: record(cfg, scenario, source, s, m, drive_all(cfg, m), out_dir) for m in methods}
