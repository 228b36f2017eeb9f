"""`cross-world` (`make cross-world`): models trained in one world, tested in the other.

The worlds (conf/scenario/ options, `worlds`) draw the same starts per seed and drive them with different traffic: ours
(`dense`: our IDM/MOBIL drivers, hidden willingness to yield, 3.6 m cars) and highway-env's (`highway`: its own vehicles,
nobody yielding in advance, 5 m cars; data/highway.py). Per world: a dataset and the teacher, student and surrogate
trained on it (the surrogate where a row needs it; or the models already in `models.<world>`). Then in each world, on the same held-out seeds: the
clairvoyant ceiling, ADMM with cv, ADMM with each world's student and surrogate, and the NNMPC baseline with each world's
student; and each world's predictors' accuracy on each world's test split. Writes <out_dir>/cross-world.md (95%
intervals as `results`: Wilson for rates, bootstrap over episodes for means) and logs it to MLflow (experiment
`cross-world`).

    cross-world [episodes.highway=200] [models.dense=models] [n_jobs=-1]
"""
import itertools
import logging
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig

from bench import ceiling
from bench.branches import heldout_seeds
from bench.results_plan import Plan, add_training
from bench.results_tables import (
    beaten,
    ceiling_row,
    dense_table,
    markdown,
    methods,
    outcomes,
    pct,
    read_ceiling,
    read_episodes,
)
from core import validate
from core.jobs import CONF_DIR, UserError, console, guarded, job_config, mlflow_run, writable

log = logging.getLogger(__name__)
ACCURACY = ("cv", "teacher", "student")  # predictors of the accuracy table


def models_dir(cfg, work: Path, world: str) -> Path:
    """Where the models trained in `world` are: cfg.models[world], or the job's own training's folder."""
    given = cfg.models.get(world)
    return Path(given) if given else work / "models" / world


def label(source: str, trained: str | None) -> str:
    """A row's name: the gradient source and the world its models were trained in ("student, trained in highway")."""
    return source if trained is None else f"{source}, trained in {trained}"


def build_plan(cfg, work: Path):
    """The jobs (Plan) and the planner batches' folders {(test world, row label): folder}."""
    from data import cli as data_cli
    from planner import cli as planner_cli
    from planner.gradients import reads_models
    from planner.setup import planner_config

    plan, batches = Plan(), {}
    for w in cfg.worlds:
        if cfg.models.get(w):
            continue
        data_dir, models = work / "data" / w, models_dir(cfg, work, w)
        plan.add(f"make-dataset {w}", data_cli.run, job_config("make_dataset", [
            f"scenario={w}", f"dataset={cfg.dataset.name}", f"out_dir={data_dir}", "plot_episodes=0"]))
        add_training(plan, w, w, cfg.dataset.name, data_dir / cfg.dataset.name, models, work / "runs", cfg,
                     surrogate="surrogate" in cfg.sources)
    for test in cfg.worlds:
        for source in cfg.sources:
            for trained in cfg.worlds if reads_models(source) else [None]:
                row = label(source, trained)
                folder = batches[test, row] = work / "planner" / test / row.replace(", trained in ", "-")
                method = "both" if source in cfg.nnmpc else "admm"
                plan.add(f"planner {test} {row}", planner_cli.run, planner_config(test, [
                    f"gradients={source}", f"method={method}", f"episodes={cfg.episodes[test]}", f"seed={cfg.seed}",
                    f"models_dir={models_dir(cfg, work, trained or cfg.worlds[0])}", f"out_dir={folder}", "plots=false",
                    f"n_jobs={cfg.n_jobs}", *cfg.planner]))
        plan.add(f"ceiling {test}", ceiling.run, job_config("ceiling", [
            f"scenario={test}", f"seed={cfg.seed}", f"episodes={cfg.ceiling_episodes[test]}", f"n_jobs={cfg.n_jobs}",
            f"out_dir={work / 'ceiling'}", *cfg.ceiling]))
    return plan, batches


def check(cfg):
    """One line for a world without a count, given models without their dataset, or held-out seeds that were a dataset's
    episodes."""
    validate.check(cfg, "cross_world")
    for w in cfg.worlds:
        for key in ("episodes", "ceiling_episodes"):
            if not isinstance(cfg[key].get(w), int) or cfg[key][w] < 1:
                raise UserError(f"{key}.{w}={cfg[key].get(w)}: every world of `worlds` needs a positive number of worlds")
        if cfg.models.get(w) and not cfg.data.get(w):
            raise UserError(f"models.{w}={cfg.models[w]}: give data.{w} too, the dataset those models were trained on")
        heldout_seeds("seed", cfg.seed, max(cfg.episodes[w], cfg.ceiling_episodes[w]), cfg.dataset)


def accuracy_rows(cfg, work: Path) -> list[list[str]]:
    """Rollout ADE (mm, other cars, T_p steps fed the recorded ego future) of each world's predictors on each world's
    test split; cv needs no training and appears once per test world."""
    from data.dataset import load
    from distill import metrics, models

    T_p, rows = cfg.paper.T_p, []
    for test in cfg.worlds:
        split = load(data_root(cfg, work, test), "test")
        for name in ACCURACY:
            for trained in [None] if name == "cv" else cfg.worlds:
                m = metrics.ade(models.load(name, models_dir(cfg, work, trained or test)), split, T_p)
                rows.append([test, label(name, trained), f"{1e3 * m['ade_1step_m']:.1f}", f"{1e3 * m['ade_rollout_m']:.1f}",
                             f"{1e3 * m['fde_rollout_m']:.1f}"])
    return rows


def data_root(cfg, work: Path, world: str) -> Path:
    """The dataset folder of `world`: the job's own, or cfg.data[world] beside models given in cfg.models."""
    given = cfg.data.get(world)
    return Path(given) if given else work / "data" / world / cfg.dataset.name


def world_table(cfg, batches: dict, work: Path, test: str, rng) -> tuple[list[str], dict]:
    """The outcome table of one test world (the ceiling's row, then every batch's rows: ADMM, and NNMPC where run) and
    the per-world check that no row merged courteously where the ceiling did not, or sooner."""
    worlds = read_ceiling(work, test)
    searched = {int(w["seed"]) for w in worlds}
    rows = {("ceiling", ""): ceiling_row(ceiling.aggregate(worlds), worlds, "ceiling", cfg.bootstrap.resamples, rng)}
    beats = {}
    for (w, row), folder in batches.items():
        if w == test:
            for m in methods(folder):
                episodes = read_episodes(folder, m)
                rows[row, m] = outcomes([episodes], cfg.bootstrap.resamples, rng)
                beats[row, m] = beaten(worlds, [e for e in episodes if int(e["seed"]) in searched])
    detail = "; ".join(f"{row} {m.upper()}: seeds {sorted(s)}" for (row, m), s in beats.items() if s)
    verdict = (f"Per-world check on the ceiling's {len(worlds)} worlds: a row merged courteously where the ceiling did not, "
               f"or sooner, on {len(set().union(*beats.values()))} of them" + (f" ({detail})." if detail else "."))
    return [*dense_table(rows), verdict, ""], rows


def verdicts(rows: dict, test: str, cfg) -> list[str]:
    """Plain sentences for each model whose courteous or collision rate in `test` differs between its trainings with
    intervals that do not overlap."""
    lines = []
    for source, m in itertools.product(cfg.sources, ("admm", "nnmpc")):
        here = rows.get((label(source, test), m))  # None for an untrained source or a method not run
        for other in (w for w in cfg.worlds if w != test and here is not None):
            r = rows[label(source, other), m]
            for key, what in (("courteous", "courteous merges"), ("collision", "collisions")):
                if r[f"{key}_hi"] < here[f"{key}_lo"] or here[f"{key}_hi"] < r[f"{key}_lo"]:
                    lines.append(f"- In {test}, {source} ({m.upper()}) trained in {other}: {pct(r, key)}% {what}, "
                                 f"against {pct(here, key)}% trained in {test}; the intervals do not overlap.")
    return lines or [f"- In {test}, no model's courteous-merge or collision rate differs between its trainings with "
                     "intervals that do not overlap."]


def report(cfg, batches: dict, work: Path, dest: Path) -> Path:
    """Write dest/cross-world.md from what the jobs wrote in `work`; returns its path."""
    rng = np.random.default_rng(cfg.bootstrap.seed)
    lines = ["# Cross-world results", "",
             "Written by `cross-world` (bench/cross_world.py, `make cross-world`); do not edit by hand. Worlds: "
             + ", ".join(f"`{w}` ({cfg.episodes[w]} planner worlds, {cfg.ceiling_episodes[w]} ceiling worlds)" for w in cfg.worlds)
             + f", held-out seeds from {cfg.seed}. Models: "
             + ", ".join(f"{w}: `{models_dir(cfg, work, w)}`" for w in cfg.worlds)
             + ". Brackets: 95% intervals (Wilson for rates, bootstrap over episodes for means, Student t for the "
             "ceiling's t_merge). A merge is courteous when nothing collides and nobody brakes harder than b_safe.", ""]
    lines += ["## Prediction accuracy across worlds", "", "Each world's predictors on each world's test split (other cars, "
              "T_p-step rollouts fed the recorded ego future), mm.", ""]
    lines += markdown(["test world", "predictor", "ADE 1-step", "ADE rollout", "FDE rollout"], accuracy_rows(cfg, work))
    for test in cfg.worlds:
        table, rows = world_table(cfg, batches, work, test, rng)
        lines += [f"## Planning in `{test}`", "", f"`planner scenario={test} episodes={cfg.episodes[test]} seed={cfg.seed}` "
                  f"per row (ADMM with the paper's step; NNMPC: the baseline), `ceiling scenario={test} "
                  f"episodes={cfg.ceiling_episodes[test]}` on the first of the same worlds.", ""]
        lines += table + verdicts(rows, test, cfg) + [""]
    path = dest / "cross-world.md"
    path.write_text("\n".join(lines))
    return path


@guarded
def run(cfg: DictConfig) -> Path:
    """Train (where needed), plan and search in every world, write the report, log it; returns the Markdown's path."""
    check(cfg)
    dest, work = writable(Path(cfg.out_dir), "out_dir"), writable(Path(cfg.work_dir), "work_dir")
    plan, batches = build_plan(cfg, work)
    log.info("cross-world: %d jobs; work in %s", len(plan.steps), work)
    plan.run()
    path = report(cfg, batches, work, dest)
    with mlflow_run("cross-world", cfg, run_name="cross-world"):
        import mlflow

        mlflow.log_artifact(str(path), "results")
    log.info("wrote %s", path)
    return path


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="cross_world")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Entry point of the `cross-world` console script: overrides checked first (one line for a misspelt key)."""
    console("cross_world", hydra_main)


if __name__ == "__main__":
    main()
