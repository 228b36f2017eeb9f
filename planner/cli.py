"""`planner`: closed-loop merges with ADMM-NNMPC and/or NNMPC; metrics, per-step CSV and plots to MLflow (`planner`).

`planner --gradients=surrogate` (or `--gradients surrogate`) is the same as the Hydra override `gradients=surrogate`.
The heavy imports (torch, numba, MLflow) wait until the config is composed, so `planner --help` answers at once.
"""
import logging
import os
import sys
from contextlib import nullcontext
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from core.jobs import CONF_DIR, check_overrides, guarded

log = logging.getLogger(__name__)
OmegaConf.register_new_resolver("pid", os.getpid, replace=True)  # hydra.run.dir: one folder per process


def translate(argv):
    """argv with `--gradients=X` / `--gradients X` turned into the Hydra override `gradients=X`."""
    out, args = [], iter(argv)
    for a in args:
        if a == "--gradients":
            out.append(f"gradients={next(args, '')}")
        elif a.startswith("--gradients="):
            out.append(a[2:])
        else:
            out.append(a)
    return out


def ui_hint(run_id: str, experiment_id: str) -> str:
    """Where to see a run: the `mlflow ui` command for this store and the run's path in it."""
    from core.jobs import tracking_uri

    return f"mlflow ui --backend-store-uri {tracking_uri()}  then  http://127.0.0.1:5000/#/experiments/{experiment_id}/runs/{run_id}"


@guarded
def run(cfg: DictConfig) -> dict:
    """Drive, log and summarise (cfg.episodes > 0: batch statistics, see planner.batch); returns {method: metrics}. Each
    method's MLflow run is open while it drives, so a stopped episode ends it KILLED; several methods' runs are the
    children of one parent run."""
    import mlflow
    from hydra.core.hydra_config import HydraConfig

    from core import validate
    from core.jobs import local_models_dir, mlflow_run, open_experiment, writable
    from planner import batch, compare, report
    from planner.closed_loop import check_others
    from planner.setup import run_params, setup

    validate.check(cfg, "planner")
    given = {"models_dir": cfg.models_dir}  # logged as given, a URI or a folder
    cfg.models_dir = local_models_dir(cfg.models_dir)  # a runs:/ or models:/ URI: its model files, downloaded once
    scenario, source, s = setup(cfg)
    out_dir = writable(Path(cfg.out_dir or HydraConfig.get().runtime.output_dir), "out_dir")
    if cfg.record_dir:
        writable(Path(cfg.record_dir), "record_dir")  # now, not after the first episode was driven
    check_others(scenario.make_world(cfg.seed), cfg.world, cfg.n_slots)
    open_experiment("planner")  # an unusable store fails now, not after the episodes
    link, accuracy = compare.source_link(source.name, source.predictor.name)
    params = {**run_params(scenario, source, cfg), **link, **given}
    if cfg.mpc.admm.rho == "certified":  # the number the certificate gave, not the word
        params["mpc.admm.rho"] = s.admm.rho
    methods = list(cfg.method)
    name = report.run_name("+".join(methods) if len(methods) > 1 else methods[0], source, cfg, scenario)
    with mlflow_run("planner", cfg, run_name=name, **params, method="+".join(methods)) if len(methods) > 1 else \
            nullcontext() as parent:
        if parent is not None:
            mlflow.log_metrics(accuracy)
        if cfg.episodes:
            results, runs = batch.run(cfg, scenario, source, s, methods, out_dir, params, accuracy)
        else:
            results, runs = drive_each(cfg, scenario, source, s, methods, out_dir, params, accuracy)
    experiment = mlflow.get_experiment_by_name("planner").experiment_id
    for m, run_id in runs.items():
        log.info("[%s] MLflow run %s: %s", m, run_id, ui_hint(run_id, experiment))
    return results


def drive_each(cfg, scenario, source, s, methods, out_dir, params, accuracy) -> tuple[dict, dict]:
    """One episode per method, each in its MLflow run: ({method: metrics}, {method: run id})."""
    import mlflow

    from core.jobs import mlflow_run
    from planner import report
    from planner.setup import drive

    title = f"{scenario.name}, gradients={source.name}, predictor={source.predictor.name}, world={cfg.world}"
    episodes, results, run_ids = {}, {}, {}
    for m in methods:
        with mlflow_run("planner", cfg, run_name=report.run_name(m, source, cfg, scenario), **{**params, "method": m}) as run_:
            run_ids[m] = run_.info.run_id
            ep = episodes[m] = drive(cfg, scenario, source, s, m)
            results[m] = report.metrics(ep, scenario)
            csv_path = out_dir / f"steps_{m}.csv"
            report.write_csv(ep, csv_path)
            mlflow.log_metrics({**report.mlflow_metrics(results[m], scenario.params.dt), **accuracy})
            mlflow.log_artifact(str(csv_path))
            own = report.figures({m: ep}, scenario.road, scenario.x_ref, scenario.y_ref, out_dir, title) if cfg.plots else []
            rendered = scenario.render(cfg.seed, ep.states, out_dir / f"render_{m}.gif") if cfg.plots else None
            for p in own + ([rendered] if rendered else []):
                mlflow.log_artifact(str(p), "plots")
            if ep.notes:
                mlflow.set_tag("notes", "; ".join(ep.notes))
        reasons = sorted({r["fallback"] for r in ep.rows if r["fallback"]})
        for note in ep.notes + [f"fallback: {r}" for r in reasons]:
            log.info("[%s] %s", m, note)
    if cfg.plots and len(episodes) > 1:  # the methods side by side, in each method's run
        shared = report.figures(episodes, scenario.road, scenario.x_ref, scenario.y_ref, out_dir, title, animation=False)
        client = mlflow.MlflowClient()
        for run_id in run_ids.values():
            for p in shared:
                client.log_artifact(run_id, str(p), "plots")
    log.info("%s, seed %s; outputs in %s", title, cfg.seed, out_dir)
    log.info("\n%s", report.table({f"{scenario.name}/{m}": r for m, r in results.items()}))
    return results, run_ids


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="planner")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


@guarded
def prepare(argv):
    """The argv Hydra will read: --gradients translated, config-group options and keys checked."""
    argv = translate(argv)
    check_overrides("planner", argv[1:])
    return argv


def main() -> None:
    """Console entry point."""
    sys.argv = prepare(sys.argv)
    hydra_main()
