"""`safety` (`make safety`): does any row's planner collide? Per row of `rows` (conf/safety.yaml `row`: its planner
overrides on scenario=dense method=admm) one planner batch on `worlds` fresh dense worlds (seeds `seed` on) and one on
`stubborn_worlds` worlds where no driver yields (scenario.cooperation=stubborn, seeds `stubborn_seed` on); both seed
ranges are checked clear of the dataset's episodes and of each other. Batches run on local processes or Ray
(`backend=ray ray.address=auto`: 10,000 worlds run the same way on a cluster), each an MLflow child of the job's run.

The table, computed from each batch's per-episode CSV: collisions with their Wilson 95% interval and the seeds that
collided, courteous merges (Wilson), fallbacks per episode (percentile bootstrap, as the batch's own), crashed episodes
(a crash is kept in the table, not fatal to the batch: tolerate_crashes) and the batch's wall time per world at its
n_jobs. Written with a CSV of the same figures to <out_dir>/safety.md, safety.csv as one set (core.jobs.staged) and
logged (experiment `safety`). A row whose models are missing fails the job before any batch (one line naming the
file): the claim is about every row, so none is skipped silently; `rows=[...]` leaves rows out. A collision or a crash
ends the job with exit 2 once the table is written, naming the first with its command.

    safety [worlds=500] [stubborn_worlds=100] [rows=[rules,interactive_cv]] [n_jobs=-1] [backend=ray ray.address=auto]
"""
import csv
import logging
import shlex
import time
from pathlib import Path

import hydra
import mlflow
import numpy as np
import pandas as pd
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from bench.branches import heldout_seeds
from bench.results_plan import check_clear
from bench.results_tables import markdown, pct
from core import stats, validate
from core.jobs import CONF_DIR, MissingModel, UserError, console, guarded, job_config, mlflow_run, staged, writable
from planner.batch import RESAMPLES
from planner.compare import fmt

log = logging.getLogger(__name__)
BASE = ["scenario=dense", "method=admm"]  # every row's set-up
SCHEMA = {"rows": validate.ListOf(validate.Text(), at_least=1), "worlds": validate.EPISODES, "seed": validate.SEED,
          "stubborn_worlds": validate.Int(0, validate.MAX_EPISODES), "stubborn_seed": validate.SEED,
          "models_dir": validate.Text(), "planner": validate.OVERRIDES, "n_jobs": validate.N_JOBS,
          "backend": validate.OneOf(("loky", "ray")), "ray.address": validate.Text(nullable=True),
          "out_dir": validate.Text(nullable=True)}


def batches(cfg) -> list[tuple[str, list[str], int]]:
    """[(name, planner overrides, worlds)]: per row its fresh worlds, then (stubborn_worlds > 0) its stubborn ones."""
    out = []
    for row in cfg.rows:
        common = [*BASE, *cfg.row[row], f"models_dir={cfg.models_dir}", *cfg.planner]
        out.append((row, [*common, f"seed={cfg.seed}"], cfg.worlds))
        if cfg.stubborn_worlds:
            out.append((f"{row}_stubborn", [*common, "scenario.cooperation=stubborn", f"seed={cfg.stubborn_seed}"],
                        cfg.stubborn_worlds))
    return out


def check(cfg) -> None:
    """One line for a bad size or row name, seeds that are the dataset's or overlap, or a row's missing model file,
    before any batch runs."""
    from planner.setup import setup

    validate.check(cfg, SCHEMA)
    unknown = [r for r in cfg.rows if r not in cfg.row]
    if unknown:
        raise UserError(f"rows={list(cfg.rows)}: {', '.join(unknown)} is not a row of `row` ({', '.join(cfg.row)})")
    fresh = heldout_seeds("seed", cfg.seed, cfg.worlds, cfg.dataset)
    stubborn = heldout_seeds("stubborn_seed", cfg.stubborn_seed, cfg.stubborn_worlds, cfg.dataset)
    check_clear("stubborn_seed", cfg.stubborn_seed, "the stubborn worlds", stubborn, {"fresh batch": fresh})
    for name, overrides, _ in batches(cfg):
        planner = job_config("planner", overrides)
        validate.check(planner, "planner")
        try:
            setup(planner)
        except MissingModel as e:
            raise UserError(f"row {name}: {e} (`make demo` trains every model the rows read; rows=[...] leaves a row "
                            "out)") from None


def episodes(folder: Path) -> pd.DataFrame:
    """Every episode of a batch's per-episode CSV (planner/batch.py), crashed ones included."""
    with open(next(folder.glob("episodes_admm_*.csv"))) as f:
        return pd.DataFrame(list(csv.DictReader(f)))


def figures(rows: pd.DataFrame, wall_s: float) -> dict:
    """A batch's table figures from its episodes: counts, collision seeds, rates (Wilson 95%) and fallbacks per episode
    (bootstrap 95%) over the finished episodes, wall seconds per world."""
    done = rows[rows["crash"] == "0"]
    finished = [{k: float(done[k].iloc[i]) for k in ("collision", "courteous", "merged", "fallbacks", "t_merge", "C_max",
                                                        "b_imposed_max")} for i in range(len(done))]
    hit = done[done["collision"].astype(float) > 0]
    return {"worlds": len(rows), "finished": len(done), "collisions": len(hit), "crashes": len(rows) - len(done),
            "collision_seeds": " ".join(hit["seed"]), "crash_seeds": " ".join(rows[rows["crash"] != "0"]["seed"]),
            **stats.outcomes([finished], RESAMPLES, seed=0), "s_per_world": wall_s / len(rows)}


def table(results: dict, n_jobs: int) -> str:
    """The Markdown table of {batch name: figures}."""
    header = ["row", "worlds", "collisions", "collision % [95% CI]", "collided (seeds)", "courteous % [95% CI]",
              "fallbacks per episode [95% CI]", "crashes", f"wall s per world (n_jobs={n_jobs})"]
    cells = [[name, str(r["worlds"]), str(r["collisions"]), pct(r, "collision"), r["collision_seeds"] or "-",
              pct(r, "courteous"), fmt(r["fallbacks"], ".2f", r["fallbacks_lo"], r["fallbacks_hi"]), str(r["crashes"]),
              f"{r['s_per_world']:.1f}"] for name, r in results.items()]
    return "\n".join(markdown(header, cells))


@guarded
def run(cfg: DictConfig) -> dict:
    """Every batch (module doc), the table written and logged; returns {batch name: figures}."""
    from planner import cli as planner_cli

    check(cfg)
    out_dir = writable(Path(cfg.out_dir or HydraConfig.get().runtime.output_dir), "out_dir")
    results, commands = {}, {}
    with mlflow_run("safety", cfg, run_name=f"safety-{cfg.worlds}+{cfg.stubborn_worlds}"):
        for name, overrides, worlds in batches(cfg):
            job = [*overrides, f"episodes={worlds}", f"n_jobs={cfg.n_jobs}", f"backend={cfg.backend}",
                   f"ray.address={'null' if cfg.ray.address is None else cfg.ray.address}", f"out_dir={out_dir / name}",
                   "plots=false", "tolerate_crashes=true"]
            t0 = time.perf_counter()
            planner_cli.run(job_config("planner", job))
            results[name] = figures(episodes(out_dir / name), time.perf_counter() - t0)
            commands[name] = overrides
            log.info("safety: %s, %d worlds: %d collisions, %d crashes, %.1f s per world", name, worlds,
                     results[name]["collisions"], results[name]["crashes"], results[name]["s_per_world"])
        text = table(results, cfg.n_jobs)
        with staged(out_dir) as stage:
            (stage / "safety.md").write_text(text)
            pd.DataFrame([{"row": k, **v} for k, v in results.items()]).to_csv(stage / "safety.csv", index=False)
        mlflow.log_metrics({f"{name}.{k}": float(v) for name, r in results.items() for k, v in r.items()
                            if isinstance(v, (int, float)) and np.isfinite(v)})
        mlflow.log_artifact(str(out_dir / "safety.md"))
        mlflow.log_artifact(str(out_dir / "safety.csv"))
    log.info("safety, %d fresh worlds from seed %d and %d stubborn from %d per row:\n%s\nin %s", cfg.worlds, cfg.seed,
             cfg.stubborn_worlds, cfg.stubborn_seed, text, out_dir / "safety.md")
    bad = [(name, kind, seed) for name, r in results.items() for kind in ("collision", "crash")
           for seed in r[f"{kind}_seeds"].split()]
    if bad:
        name, kind, seed = bad[0]
        again = " ".join(shlex.quote(o) for o in commands[name] if not o.startswith("seed="))
        raise UserError(f"{len(bad)} collisions or crashes (first: {kind} of {name} in world {seed}: `planner {again} "
                        f"seed={seed}`); see {out_dir / 'safety.md'}")
    return results


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="safety")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Entry point of the `safety` console script: overrides checked first (one line for a misspelt key)."""
    console("safety", hydra_main)
