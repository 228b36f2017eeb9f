"""`results` (`make results`): every table and figure of the README's Results section, regenerated from scratch.

The existing jobs run in order through their Python `run` functions (each logs its own MLflow runs as usual): the dataset;
per training seed k the teacher, the student and the surrogate into <work_dir>/models/seed<k>; the interaction benchmark
per training; the planner's held-out batches (random merges and the Table II scenarios) of every gradient source with both
methods, once per training for the trained sources and once for cv and analytic; the step-time bench; one closed-loop
showcase run with its snapshots and merge animation. Then <out_dir>/README-results.md and <out_dir>/*.png are written
from what those jobs returned and wrote, so no figure is typed by hand.

Intervals (95%): Wilson for rates, pooled over trainings and episodes; for means over episodes a percentile bootstrap
that resamples trainings, then episodes within each; for per-training figures (accuracy, interaction) a Student t
interval over trainings (none with one training).

Held-out seeds: planner worlds use planner_seed + k; the job checks them against the dataset's episode seeds
(data.dataset.episode_seeds) and the interaction benchmark's worlds (its seed_offset + k) before anything runs.

    results [results_preset=tiny|small|full] [out_dir=results] [n_jobs=-1] [backend=ray ray.address=auto]
"""
import csv
import logging
import shutil
import time
from pathlib import Path

import hydra
import numpy as np
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from bench.branches import heldout_seeds
from core import stats, validate
from core.jobs import CONF_DIR, UserError, guarded, mlflow_run, writable
from planner.batch import progress
from planner.gradients import available, reads_models

log = logging.getLogger(__name__)
TRAINED = tuple(s for s in available() if reads_models(s))  # gradient sources that read trained models (per training seed)
METHODS = ("admm", "nnmpc")
MODELS = ("cv", "teacher", "student")  # predictors of the accuracy table; cv from the cv_* metrics of the teacher's runs


def job_config(name: str, overrides) -> DictConfig:
    """The config of job `name` (conf/<name>.yaml) with Hydra overrides, composed as its console script would."""
    if GlobalHydra.instance().is_initialized():
        return compose(name, overrides=list(overrides))
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(name, overrides=list(overrides))


class Plan:
    """The job list of a preset: (label, thunk) pairs run in order under one progress bar, results kept by label."""

    def __init__(self):
        self.steps, self.out = [], {}

    def add(self, label, fn, *args):
        self.steps.append((label, fn, args))

    def run(self):
        bar = progress(None, len(self.steps), "results")
        with bar:
            for label, fn, args in self.steps:
                bar.set_postfix_str(label)
                t0 = time.perf_counter()
                self.out[label] = fn(*args)
                log.info("results: %s done in %.1f s", label, time.perf_counter() - t0)
                bar.update()
        return self.out


def check_seeds(cfg, interaction_cfg) -> range:
    """The planner's held-out world seeds; a UserError if one was a dataset episode's or an interaction benchmark world's."""
    n = max(cfg.results_preset.episodes, cfg.results_preset.table2_episodes)
    seeds = heldout_seeds("planner_seed", cfg.planner_seed, n, interaction_cfg.dataset)
    lo = interaction_cfg.seed_offset
    hi = lo + interaction_cfg.states * interaction_cfg.branch.tries
    if seeds.start < hi and lo < seeds.stop:
        raise UserError(f"planner_seed={cfg.planner_seed}: planner seeds {seeds.start}..{seeds.stop - 1} overlap the "
                        f"interaction benchmark's {lo}..{hi - 1}; choose another planner_seed")
    return seeds


def build_plan(cfg, work: Path):
    """The preset's jobs (Plan) and the planner batches' output folders {(scenario, source, seed k or None): folder}."""
    from bench import interaction, step_time
    from data import cli as data_cli
    from distill import train
    from planner import cli as planner_cli
    from planner.setup import planner_config
    from surrogate import cli as surrogate_cli

    p = cfg.results_preset
    data_dir, plan, batches = work / "data", Plan(), {}
    dataset_dir = data_dir / p.dataset
    plan.add("make-dataset", data_cli.run, job_config("make_dataset", [f"dataset={p.dataset}", f"out_dir={data_dir}",
                                                                       "plot_episodes=0"]))
    models = lambda k: work / "models" / f"seed{k}"
    for k in p.training_seeds:
        common = [f"dataset={p.dataset}", f"dataset_dir={dataset_dir}", f"models_dir={models(k)}", f"seed={k}"]
        for model in ("teacher", "student"):
            plan.add(f"distill {model} seed {k}", train.run, job_config("distill", [
                f"model={model}", *common, f"run_dir={work / 'runs' / f'distill-{model}-{k}'}", "trainer.enable_progress_bar=false",
                *p[model]]))
        plan.add(f"surrogate seed {k}", surrogate_cli.run, job_config("surrogate", [
            f"dataset_dir={dataset_dir}", f"models_dir={models(k)}", f"seed={k}", f"out_dir={work / 'runs' / f'surrogate-{k}'}",
            *p.surrogate]))
    interaction_cfgs = {}
    for i, k in enumerate(p.training_seeds):
        sources = [s for s in p.interaction_sources if i == 0 or s in TRAINED]  # untrained ones once
        interaction_cfgs[k] = job_config("evaluate_interaction", [
            f"dataset={p.dataset}", f"models_dir={models(k)}", f"out_dir={work / 'interaction' / f'seed{k}'}",
            f"sources=[{','.join(sources)}]", *p.interaction])
        plan.add(f"evaluate-interaction seed {k}", interaction.run, interaction_cfgs[k])
    check_seeds(cfg, interaction_cfgs[p.training_seeds[0]])
    runs = [("random", s, p.episodes) for s in p.sources] + [(sc, s, p.table2_episodes) for sc in p.scenarios
                                                              for s in p.table2_sources]
    for scenario, source, episodes in runs:
        for k in p.training_seeds if source in TRAINED else [None]:
            folder = work / "planner" / scenario / source / (f"seed{k}" if k is not None else "untrained")
            batches[scenario, source, k] = folder
            plan.add(f"planner {scenario} {source}" + (f" seed {k}" if k is not None else ""), planner_cli.run, planner_config(scenario, [
                f"gradients={source}", "method=both", f"episodes={episodes}", f"seed={cfg.planner_seed}",
                f"models_dir={models(p.training_seeds[0] if k is None else k)}", f"out_dir={folder}", "plots=false",
                f"n_jobs={cfg.n_jobs}", f"backend={cfg.backend}", f"ray.address={cfg.ray.address or 'null'}", *p.planner]))
    if p.bench is not None:
        plan.add("bench step time", step_time.run, job_config("bench", [
            f"models_dir={models(p.training_seeds[0])}", f"states.path={work / 'bench' / 'states.npz'}", *p.bench]))
    show = OmegaConf.from_dotlist(list(p.showcase)).get("scenario", "two_lane")
    plan.add("showcase", planner_cli.run, planner_config(show, [
        "method=both", f"seed={cfg.planner_seed}", f"models_dir={models(p.training_seeds[0])}",
        f"out_dir={work / 'showcase'}", *[o for o in p.showcase if not o.startswith("scenario=")], *p.planner]))
    return plan, batches


def read_episodes(folder: Path, method: str) -> list[dict]:
    """The finished episodes of a batch's per-episode CSV (planner/batch.py) as {column: float}."""
    path = next(folder.glob(f"episodes_{method}_*.csv"))
    with open(path) as f:
        return [{k: float(v) for k, v in r.items() if k not in ("error", "notes")} for r in csv.DictReader(f)
                if r["crash"] == "0"]


def outcomes(per_training: list[list[dict]], resamples: int, rng) -> dict:
    """One table row from the episodes of each training: rates with Wilson intervals, means with bootstrap intervals."""
    eps = [e for t in per_training for e in t]
    row = {"trainings": len(per_training), "episodes": len(eps), **stats.outcomes(per_training, resamples, rng)}
    row["d_min_m"] = min((e["d_min_m"] for e in eps), default=float("nan"))
    row["step_ms_median"] = float(np.median([e["step_ms_median"] for e in eps])) if eps else float("nan")
    return row


def fmt(v, f=".2f", lo=None, hi=None) -> str:
    """A cell: the value, with its interval in brackets when it has one wider than nothing; '-' for NaN."""
    if v is None or not np.isfinite(v):
        return "-"
    if lo is None or not np.isfinite(lo) or hi - lo <= 0:
        return f"{v:{f}}"
    return f"{v:{f}} [{lo:{f}}, {hi:{f}}]"


def markdown(header, rows) -> list[str]:
    """A Markdown table."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows), ""]


def over_trainings(values: list[dict], keys) -> dict:
    """{key: (mean, lo, hi)} over the trainings' dicts (t interval)."""
    return {k: stats.mean_ci([v.get(k, np.nan) for v in values]) for k in keys}


def batch_rows(cfg, batches, scenario, sources, rng) -> dict:
    """{(source, method): outcomes row} of one scenario's batches."""
    rows = {}
    for source in sources:
        folders = [f for (sc, s, _), f in batches.items() if sc == scenario and s == source]
        for m in METHODS:
            rows[source, m] = outcomes([read_episodes(f, m) for f in folders], cfg.bootstrap.resamples, rng)
    return rows


def outcome_table(rows: dict) -> list[str]:
    """The Markdown table of batch outcomes, one line per (source, method)."""
    header = ["gradients", "method", "trainings x episodes", "merged % [95% CI]", "collision % [95% CI]",
              "t_merge steps [95% CI]", "C_max [95% CI]", "d_min (m)", "fallbacks / episode [95% CI]", "step ms (median)"]
    pct = lambda r, k: fmt(100 * r[k], ".1f", 100 * r[f"{k}_lo"], 100 * r[f"{k}_hi"])
    ci = lambda r, k, f=".1f": fmt(r[k], f, r[f"{k}_lo"], r[f"{k}_hi"])
    return markdown(header, [[s, m.upper(), f"{r['trainings']} x {r['episodes'] // max(r['trainings'], 1)}", pct(r, "merged"),
                              pct(r, "collision"), ci(r, "t_merge"), ci(r, "C_max"), fmt(r["d_min_m"]),
                              ci(r, "fallbacks", ".2f"), fmt(r["step_ms_median"], ".1f")] for (s, m), r in rows.items()])


def bar_plot(rows: dict, key: str, ylabel: str, title: str, path: Path, scale=1.0):
    """Grouped bars (a group per source, a bar per method) of rows[...][key] with its 95% interval as error bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sources = list(dict.fromkeys(s for s, _ in rows))
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(sources), 4))
    for j, m in enumerate(METHODS):
        x = np.arange(len(sources)) + (j - 0.5) * 0.38
        v = np.array([rows[s, m][key] for s in sources]) * scale
        lo = np.array([rows[s, m][f"{key}_lo"] for s in sources]) * scale
        hi = np.array([rows[s, m][f"{key}_hi"] for s in sources]) * scale
        err = np.nan_to_num(np.abs(np.vstack([v - lo, hi - v])))
        ax.bar(x, np.nan_to_num(v), width=0.36, yerr=err, capsize=4, label=m.upper(), color=("tab:red", "tab:purple")[j],
               alpha=0.8)
    ax.set_xticks(np.arange(len(sources)), sources)
    ax.set(ylabel=ylabel, title=title)
    ax.legend()
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fidelity_plot(inter: dict, speed: dict, path: Path):
    """Interaction fidelity of each gradient source (react_corr_jac, mean and 95% interval over trainings) against its
    median MPC step time on the random batches (ms)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for i, (source, (v, lo, hi)) in enumerate(inter.items()):
        if source in speed and np.isfinite(v):
            err = [[v - lo], [hi - v]] if hi > lo else None
            ax.errorbar(speed[source], v, yerr=err, fmt="os^Dv"[i % 5], ms=8, capsize=4, label=source, color=f"C{i}")
    ax.set(xscale="log", xlabel="median MPC step, ADMM, random merges (ms)", ylim=(-1.05, 1.05),
           ylabel="react_corr_jac (first-order response vs true)", title="interaction fidelity vs step time")
    ax.axvline(200, color="tab:red", ls=":", lw=1, label="real time (0.2 s)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(cfg, out: dict, batches: dict, work: Path, dest: Path) -> Path:
    """Write dest/README-results.md and the figures from the jobs' outputs; returns the Markdown's path."""
    p = cfg.results_preset
    rng = np.random.default_rng(cfg.bootstrap.seed)
    seeds = list(p.training_seeds)
    lines = [f"# Results (preset `{p.name}`)", "",
             f"Written by `results results_preset={p.name}` (bench/results.py); do not edit by hand. Dataset `{p.dataset}`; "
             f"training seeds {seeds}; held-out planner worlds from seed {cfg.planner_seed}. Brackets: 95% intervals "
             "(Wilson for rates over all trainings x episodes; bootstrap over trainings, then episodes, for episode means; "
             "Student t over trainings for per-training figures).", ""]
    d = {m: [out[f"distill {m} seed {k}"] for k in seeds] for m in ("teacher", "student")}
    acc = {"cv": over_trainings([{k[3:]: v for k, v in r.items() if k.startswith("cv_")} for r in d["teacher"]],
                                ("ade_1step_m", "ade_rollout_m", "fde_rollout_m", "ade_rollout_m_yield")),
           **{m: over_trainings(d[m], ("ade_1step_m", "ade_rollout_m", "fde_rollout_m", "ade_rollout_m_yield")) for m in d}}
    mm = lambda t: fmt(1e3 * t[0], ".1f", 1e3 * t[1], 1e3 * t[2])
    lines += ["## Predictors", "", f"Test split of `{p.dataset}`, other cars only, {cfg.paper.T_p}-step rollouts fed the "
              "recorded ego future.", ""]
    lines += markdown(["predictor", "ADE 1-step (mm)", "ADE rollout (mm)", "FDE rollout (mm)", "ADE rollout, yield episodes (mm)"],
                      [[m, *(mm(acc[m][k]) for k in ("ade_1step_m", "ade_rollout_m", "fde_rollout_m", "ade_rollout_m_yield"))]
                       for m in MODELS])
    sur = over_trainings([out[f"surrogate seed {k}"] for k in seeds], ("jac_rel_err", "grad_cosine", "grad_rel_err"))
    stu = over_trainings(d["student"], ("jac_rel_err",))
    lines += ["## Gradients", "", "Against teacher autodiff on held-out planning states.", ""]
    lines += markdown(["source", "local Jacobian rel. error", "d b_i/dZ cosine", "d b_i/dZ rel. error"],
                      [["surrogate", *(fmt(sur[k][0], ".3f", *sur[k][1:]) for k in ("jac_rel_err", "grad_cosine", "grad_rel_err"))],
                       ["student", fmt(stu["jac_rel_err"][0], ".3f", *stu["jac_rel_err"][1:]), "-", "-"]])
    inter_runs = {}
    for k in seeds:
        for source, m in out[f"evaluate-interaction seed {k}"].items():
            inter_runs.setdefault(source, []).append(m)
    keys = ("react_corr", "react_gain", "react_hit", "react_corr_jac", "react_gain_jac", "react_hit_jac")
    inter = {s: over_trainings(v, keys) for s, v in inter_runs.items()}
    lines += ["## Interaction fidelity", "", "evaluate-interaction (bench/interaction.py): the response to paired ego plans "
              "on held-out counterfactual branches; `_jac` is the first-order response the planner linearises.", ""]
    lines += markdown(["source", *keys], [[s, *(fmt(v[k][0], ".3f", *v[k][1:]) for k in keys)] for s, v in inter.items()])
    random_rows = batch_rows(cfg, batches, "random", p.sources, rng)
    lines += ["## Random merges", "", f"`planner scenario=random episodes={p.episodes} method=both seed={cfg.planner_seed}` "
              "per gradient source and training (cv and analytic need none).", ""]
    lines += outcome_table(random_rows)
    figs = {"merge_rate.png": ("merged", "merge rate (%)", 100.0), "t_merge.png": ("t_merge", "t_merge (steps of 0.2 s)", 1.0),
            "fallbacks.png": ("fallbacks", "fallbacks per episode", 1.0)}
    for name, (key, ylabel, scale) in figs.items():
        bar_plot(random_rows, key, ylabel, f"random merges: {ylabel}, 95% CI", dest / name, scale)
    lines += [f"![{k}]({k})" for k in figs] + [""]
    for scenario in p.scenarios:
        lines += [f"## Table II: {scenario}", "", f"{p.table2_episodes} episode(s) per training from seed {cfg.planner_seed}.", ""]
        lines += outcome_table(batch_rows(cfg, batches, scenario, p.table2_sources, rng))
    speed = {s: random_rows[s, "admm"]["step_ms_median"] for s in p.sources}
    fidelity_plot({s: v["react_corr_jac"] for s, v in inter.items()}, speed, dest / "interaction_vs_step_time.png")
    lines += ["## Interaction fidelity against step time", "", "![interaction](interaction_vs_step_time.png)", ""]
    if "bench step time" in out:
        b = out["bench step time"]
        names = [k[: -len("_ms_median")] for k in b if k.endswith("_ms_median")]
        lines += ["## MPC step time", "", "One MPC step per source on saved planning states, one thread (training seed "
                  f"{seeds[0]}).", ""]
        lines += markdown(["source", "median ms", "p95 ms", "ADMM iterations"],
                          [[n, fmt(b[f"{n}_ms_median"], ".0f"), fmt(b[f"{n}_ms_p95"], ".0f"), fmt(b[f"{n}_iters_mean"], ".1f")]
                           for n in names])
    for f in ("snapshots_admm.png", "merge_admm.gif", "snapshots_nnmpc.png", "merge_nnmpc.gif"):
        if (work / "showcase" / f).exists():
            shutil.copyfile(work / "showcase" / f, dest / f)
    lines += ["## A closed-loop run", "", f"`planner method=both {' '.join(p.showcase)} seed={cfg.planner_seed}`", "",
              "![snapshots](snapshots_admm.png) ![animation](merge_admm.gif)", "",
              "![snapshots](snapshots_nnmpc.png) ![animation](merge_nnmpc.gif)", ""]
    path = dest / "README-results.md"
    path.write_text("\n".join(lines))
    return path


@guarded
def run(cfg: DictConfig) -> Path:
    """Run the preset's jobs, write the report, log it (experiment `results`); returns the Markdown's path."""
    validate.check(cfg, "results")
    dest = writable(Path(cfg.out_dir), "out_dir")
    work = writable(Path(cfg.work_dir), "work_dir")
    plan, batches = build_plan(cfg, work)
    log.info("results preset %s: %d jobs; work in %s, report in %s", cfg.results_preset.name, len(plan.steps), work, dest)
    out = plan.run()
    path = report(cfg, out, batches, work, dest)
    with mlflow_run("results", cfg, run_name=f"results-{cfg.results_preset.name}"):
        import mlflow

        figures = sorted([*dest.glob("*.png"), *dest.glob("*.gif")])
        for f in [path, *figures]:
            mlflow.log_artifact(str(f), "results")
    log.info("wrote %s and %d figures", path, len(figures))
    return path


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="results")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
