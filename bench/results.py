"""`results` (`make results`): every table and figure of the README's Results section, regenerated from scratch.

The existing jobs run in order through their Python `run` functions (each logs its own MLflow runs as usual): the dataset;
per training seed k the teacher, the student and the surrogate into <work_dir>/models/seed<k>; the interaction benchmark
per training; the planner's held-out batches (dense traffic, the headline; random merges; the Table II scenarios) of
every gradient source with both methods, once per training for the trained sources and once for cv and analytic; the
clairvoyant ceiling (bench/ceiling.py) on the same dense worlds, on the calibration scenarios and on Table II's worlds,
its per-world CSVs in <work_dir>/ceiling/; the step-time bench; one closed-loop showcase run with its snapshots and merge
animation. Then <out_dir>/README-results.md and <out_dir>/*.png are written from what those jobs returned and wrote, so
no figure is typed by hand.

The headline is the courteous-merge rate on dense traffic (data.outcomes: merged, no collision, nobody made to brake
harder than b_safe), beside the ceiling's and the never-yield ceiling's. Per dense world, no planner episode may merge
courteously where the ceiling did not, or sooner: the report counts the worlds where one did.

Intervals (95%): Wilson for rates, pooled over trainings and episodes; for means over episodes a percentile bootstrap
that resamples trainings, then episodes within each; for per-training figures (accuracy, interaction) a Student t
interval over trainings (none with one training).

Held-out seeds: planner and ceiling worlds use planner_seed + k; the job checks them against the dataset's episode seeds
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
import pandas as pd
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from bench import breakdown, ceiling
from bench.branches import heldout_seeds
from core import stats, validate
from core.jobs import CONF_DIR, UserError, console, guarded, job_config, mlflow_run, writable
from planner import compare
from planner.batch import progress
from planner.gradients import available, reads_models
from surrogate.evaluate import ENDS, metric

log = logging.getLogger(__name__)
TRAINED = tuple(s for s in available() if reads_models(s))  # gradient sources that read trained models (per training seed)
METHODS = ("admm", "nnmpc")
MODELS = ("cv", "teacher", "student")  # predictors of the accuracy table; cv from the cv_* metrics of the teacher's runs
GRADIENT_ROWS = {"surrogate": "", "student": "_student", "constant velocity (baseline)": "_cv",
                 "mean Jacobian (baseline)": "_mean"}  # the surrogate job's metrics per row: grad_rel_err, grad_rel_err_student, ...
SEARCHES = {"ceiling": "ceiling", "never_yield": "never-yield ceiling", "blind": "best fixed strategy"}  # the ceiling's
# searches and their row names; the dense ceiling's best fixed strategy only with results_preset.blind_episodes > 0


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
    p = cfg.results_preset
    n = max(p.episodes, p.table2_episodes, p.dense_episodes, p.calibration_episodes)
    seeds = heldout_seeds("planner_seed", cfg.planner_seed, n, interaction_cfg.dataset)
    lo = interaction_cfg.seed_offset
    hi = lo + interaction_cfg.states * interaction_cfg.branch.tries
    if seeds.start < hi and lo < seeds.stop:
        raise UserError(f"planner_seed={cfg.planner_seed}: planner seeds {seeds.start}..{seeds.stop - 1} overlap the "
                        f"interaction benchmark's {lo}..{hi - 1}; choose another planner_seed")
    return seeds


def ceiling_worlds(p) -> dict:
    """{scenario: worlds} of the preset p's ceiling runs: dense (the headline's worlds), the calibration scenarios and Table
    II's; a fixed scenario takes table2_episodes (its seed draws only the hidden decisions), a sampled one
    calibration_episodes."""
    out = {}
    for sc in dict.fromkeys(["dense", *p.calibration, *p.scenarios]):
        fixed = job_config("ceiling", [f"scenario={sc}"]).scenario._target_ == "data.scenarios.Scenario"
        out[sc] = p.dense_episodes if sc == "dense" else p.table2_episodes if fixed else p.calibration_episodes
    return out


def add_training(plan: Plan, tag: str, name, dataset: str, dataset_dir: Path, models: Path, runs: Path, extra, seed=0,
                 surrogate=True, iterates=None):
    """Add to `plan` the teacher, the student and (with `surrogate`) the surrogate trained on dataset_dir (of conf/dataset/
    option `dataset`) into `models` with training seed `seed`: jobs 'distill <model> <tag>' and 'surrogate <tag>', their
    run folders runs/distill-<model>-<name> and runs/surrogate-<name>; extra: each job's extra overrides by key
    (teacher, student, surrogate). With `iterates` (overrides of a `planner` batch), job 'iterates <tag>' first records
    the states that planner linearises at into runs/iterates-<name>, and the surrogate trains and is tested on them."""
    from distill import train
    from planner import cli as planner_cli
    from surrogate import cli as surrogate_cli

    common = [f"dataset={dataset}", f"dataset_dir={dataset_dir}", f"models_dir={models}", f"seed={seed}"]
    for model in ("teacher", "student"):
        plan.add(f"distill {model} {tag}", train.run, job_config("distill", [
            f"model={model}", *common, f"run_dir={runs / f'distill-{model}-{name}'}", "trainer.enable_progress_bar=false",
            *extra[model]]))
    if not surrogate:
        return
    recorded = []
    if iterates is not None:
        folder = runs / f"iterates-{name}"
        plan.add(f"iterates {tag}", planner_cli.run, job_config("planner", [
            *iterates, f"models_dir={models}", f"record_dir={folder / 'episodes'}", f"out_dir={folder}", "plots=false"]))
        recorded = [f"data.iterates={folder / 'episodes'}"]
    plan.add(f"surrogate {tag}", surrogate_cli.run, job_config("surrogate", [
        f"dataset_dir={dataset_dir}", f"models_dir={models}", f"seed={seed}", f"out_dir={runs / f'surrogate-{name}'}",
        *recorded, *extra["surrogate"]]))


def build_plan(cfg, work: Path):
    """The preset's jobs (Plan) and the planner batches' output folders {(scenario, source, seed k or None): folder}."""
    from bench import interaction, step_time
    from data import cli as data_cli
    from planner import cli as planner_cli
    from planner.setup import planner_config

    p = cfg.results_preset
    data_dir, plan, batches = work / "data", Plan(), {}
    dataset_dir = data_dir / p.dataset
    plan.add("make-dataset", data_cli.run, job_config("make_dataset", [f"dataset={p.dataset}", f"out_dir={data_dir}",
                                                                       "plot_episodes=0"]))
    models = lambda k: work / "models" / f"seed{k}"
    for k in p.training_seeds:
        add_training(plan, f"seed {k}", k, p.dataset, dataset_dir, models(k), work / "runs", p, seed=k, iterates=p.iterates)
    interaction_cfgs = {}
    for i, k in enumerate(p.training_seeds):
        sources = [s for s in p.interaction_sources if i == 0 or s in TRAINED]  # untrained ones once
        interaction_cfgs[k] = job_config("evaluate_interaction", [
            f"dataset={p.dataset}", f"models_dir={models(k)}", f"out_dir={work / 'interaction' / f'seed{k}'}",
            f"sources=[{','.join(sources)}]", *p.interaction])
        plan.add(f"evaluate-interaction seed {k}", interaction.run, interaction_cfgs[k])
    check_seeds(cfg, interaction_cfgs[p.training_seeds[0]])
    options = mpc_overrides(p.mpc_options)
    runs = [("dense", s, p.dense_episodes, extra) for extra in options for s in p.sources] + \
        [("random", s, p.episodes, []) for s in p.sources] + \
        [(sc, s, p.table2_episodes, extra) for sc in p.scenarios for extra in options for s in p.table2_sources]
    for scenario, source, episodes, extra in runs:
        for k in p.training_seeds if source in TRAINED else [None]:
            row = label(source, extra)
            folder = work / "planner" / scenario / row / (f"seed{k}" if k is not None else "untrained")
            batches[scenario, row, k] = folder
            plan.add(f"planner {scenario} {row}" + (f" seed {k}" if k is not None else ""), planner_cli.run, planner_config(scenario, [
                f"gradients={source}", "method=both", *extra, f"episodes={episodes}", f"seed={cfg.planner_seed}",
                f"models_dir={models(p.training_seeds[0] if k is None else k)}", f"out_dir={folder}", "plots=false",
                f"n_jobs={cfg.n_jobs}", f"backend={cfg.backend}", f"ray.address={cfg.ray.address or 'null'}", *p.planner]))
    for scenario, worlds in ceiling_worlds(p).items():
        plan.add(f"ceiling {scenario}", ceiling.run, job_config("ceiling", [
            f"scenario={scenario}", f"seed={cfg.planner_seed}", f"episodes={worlds}", f"n_jobs={cfg.n_jobs}",
            f"out_dir={work / 'ceiling'}", *([f"blind.episodes={p.blind_episodes}"] if scenario == "dense" else []),
            *p.ceiling]))
    if p.bench is not None:
        plan.add("bench step time", step_time.run, job_config("bench", [
            f"models_dir={models(p.training_seeds[0])}", f"states.path={work / 'bench' / 'states.npz'}", *p.bench]))
    show = OmegaConf.from_dotlist(list(p.showcase)).get("scenario", "two_lane")
    plan.add("showcase", planner_cli.run, planner_config(show, [
        "method=both", f"seed={cfg.planner_seed}", f"models_dir={models(p.training_seeds[0])}",
        f"out_dir={work / 'showcase'}", *[o for o in p.showcase if not o.startswith("scenario=")], *p.planner]))
    return plan, batches


def label(source: str, extra: list) -> str:
    """A batch's row name: the gradient source, with its conf/mpc/ option when not the paper's ("student courteous")."""
    mpc = [o.split("=", 1)[1] for o in extra if o.startswith("mpc=")]
    return " ".join([source, *mpc])


def mpc_overrides(options) -> list[list[str]]:
    """The planner overrides of each kind of row: none (the paper's step), then each conf/mpc/ option, ADMM alone."""
    return [[], *([f"mpc={m}", "method=admm"] for m in options)]


def with_options(sources, options) -> list[str]:
    """Row names of sources with the paper's step, then with each conf/mpc/ option ("student courteous")."""
    return [label(s, extra) for extra in mpc_overrides(options) for s in sources]


def methods(folder: Path) -> list[str]:
    """The methods (METHODS order) a batch's folder has episodes of: both, or ADMM alone for an mpc option's rows."""
    return [m for m in METHODS if any(folder.glob(f"episodes_{m}_*.csv"))]


def read_episodes(folder: Path, method: str) -> list[dict]:
    """The finished episodes of a batch's per-episode CSV (planner/batch.py) as {column: float}."""
    path = next(folder.glob(f"episodes_{method}_*.csv"))
    with open(path) as f:
        return [{k: float(v) for k, v in r.items() if k not in ("error", "notes")} for r in csv.DictReader(f)
                if r["crash"] == "0"]


def read_ceiling(work: Path, scenario: str) -> list[dict]:
    """The ceiling's per-world rows of `scenario` (bench/ceiling.py's CSV) as {column: float}, its policy names left out."""
    return breakdown.read(work / "ceiling" / f"ceiling_{scenario}.csv")


def ceiling_row(r: dict, worlds: list[dict], search: str, resamples: int, rng) -> dict:
    """A dense-table row of the ceiling's `search` (SEARCHES): its courteous rate (Wilson) and t_merge over courteous
    worlds (steps, Student t) as the ceiling job gave them (r), and the mean braking it imposed over its worlds (m/s^2,
    percentile bootstrap over worlds, as the planners' means)."""
    row = {k + e: r[f"{search}_{k}{e}"] for k in ("courteous", "t_merge") for e in ("", "_lo", "_hi")}
    b = np.array([w[f"{search}_b_imposed"] for w in worlds])
    row["b_imposed_max"] = float(b.mean()) if len(b) else float("nan")
    row["b_imposed_max_lo"], row["b_imposed_max_hi"] = stats.bootstrap([b], np.mean, resamples, rng)
    return {"trainings": 1, "episodes": len(worlds), **row}


def beaten(worlds: list[dict], episodes: list[dict]) -> set[int]:
    """Seeds of the episodes that merged courteously where the ceiling on the same world did not, or did later (steps)."""
    best = {int(w["seed"]): w["ceiling_t_merge"] if w["ceiling_courteous"] else np.inf for w in worlds}
    return {int(e["seed"]) for e in episodes if e["courteous"] and e["t_merge"] < best[int(e["seed"])]}


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


def gradient_row(runs: list[dict], suffix: str, keys) -> dict:
    """{key: (mean, lo, hi)} of one source's gradient scores (the surrogate job's metrics `key + suffix`): the t interval
    over trainings, or with one training the job's own interval over its planning states; NaN where not scored."""
    if len(runs) > 1:
        return over_trainings([{k: r.get(metric(k, suffix), np.nan) for k in keys} for r in runs], keys)
    out = {}
    for k in keys:
        if metric(k, suffix, "_lo") in runs[0]:
            out[k] = tuple(runs[0].get(metric(k, suffix, e), np.nan) for e in ENDS)
        else:  # a figure without an interval (jac_rel_err), or one not scored
            out[k] = (runs[0].get(metric(k, suffix), np.nan),) * 3
    return out


def batch_rows(cfg, batches, scenario, sources, rng) -> dict:
    """{(source, method): outcomes row} of one scenario's batches."""
    rows = {}
    for source in sources:
        folders = [f for (sc, s, _), f in batches.items() if sc == scenario and s == source]
        for m in methods(folders[0]):
            rows[source, m] = outcomes([read_episodes(f, m) for f in folders], cfg.bootstrap.resamples, rng)
    return rows


def pct(r: dict, k: str) -> str:
    """A rate's cell in %, with its interval; '-' for one the row does not have."""
    return fmt(100 * r.get(k, np.nan), ".1f", 100 * r.get(f"{k}_lo", np.nan), 100 * r.get(f"{k}_hi", np.nan))


def ci(r: dict, k: str, f=".1f") -> str:
    """A mean's cell, with its interval; '-' for one the row does not have."""
    return fmt(r.get(k, np.nan), f, r.get(f"{k}_lo", np.nan), r.get(f"{k}_hi", np.nan))


def size(r: dict) -> str:
    """The 'trainings x episodes' cell of a row."""
    return f"{r['trainings']} x {r['episodes'] // max(r['trainings'], 1)}"


def outcome_table(rows: dict, ceiling_run: dict | None = None) -> list[str]:
    """The Markdown table of batch outcomes, one line per (source, method); given the ceiling job's metrics on the same
    worlds (Table II), courteous merges lead and the ceiling's t_merge (steps) stands beside the planner's."""
    lead = [("courteous % [95% CI]", lambda r: pct(r, "courteous"))] if ceiling_run else []
    beside = [("ceiling t_merge steps [95% CI]", lambda r: ci(ceiling_run, "ceiling_t_merge"))] if ceiling_run else []
    columns = [*lead, ("merged % [95% CI]", lambda r: pct(r, "merged")), ("collision % [95% CI]", lambda r: pct(r, "collision")),
               ("t_merge steps [95% CI]", lambda r: ci(r, "t_merge")), *beside, ("C_max [95% CI]", lambda r: ci(r, "C_max")),
               ("d_min (m)", lambda r: fmt(r["d_min_m"])), ("fallbacks / episode [95% CI]", lambda r: ci(r, "fallbacks", ".2f")),
               ("step ms (median)", lambda r: fmt(r["step_ms_median"], ".1f"))]
    return markdown(["gradients", "method", "trainings x episodes", *(h for h, _ in columns)],
                    [[s, m.upper(), size(r), *(c(r) for _, c in columns)] for (s, m), r in rows.items()])


def dense_table(rows: dict) -> list[str]:
    """The Markdown table of the dense batch and the ceiling's rows (method ''), courteous merges first; '-' where a row
    has no such figure (the ceiling neither collides nor falls back)."""
    header = ["gradients", "method", "trainings x worlds", "courteous % [95% CI]", "merged % [95% CI]", "t_merge steps [95% CI]",
              "b_imposed_max m/s^2 [95% CI]", "collision % [95% CI]", "fallbacks / episode [95% CI]"]
    return markdown(header, [[s, m.upper() or "-", size(r), pct(r, "courteous"), pct(r, "merged"), ci(r, "t_merge"),
                              ci(r, "b_imposed_max", ".2f"), pct(r, "collision"), ci(r, "fallbacks", ".2f")]
                             for (s, m), r in rows.items()])


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


def braking_plot(values: dict, b_safe: float, b_max: float, path: Path):
    """Box plots, one per row of the dense table ({name: per-world largest braking imposed on another car, m/s^2}), with
    every world as a dot, b_safe (courteous) and b_max (the physical cap) marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2.0 + 0.9 * len(values), 4.5))
    jitter = np.random.default_rng(0)
    for i, v in enumerate(values.values()):
        if len(v):
            ax.boxplot([v], positions=[i], widths=0.5, showfliers=False)
            ax.plot(i + jitter.uniform(-0.15, 0.15, len(v)), v, ".", color="tab:blue", alpha=0.4, ms=4)
    ax.axhline(b_safe, color="tab:red", ls="--", lw=1, label=f"b_safe = {b_safe:g} m/s^2 (courteous)")
    ax.axhline(b_max, color="k", ls=":", lw=1, label=f"b_max = {b_max:g} m/s^2 (physical cap)")
    ax.set_xticks(np.arange(len(values)), list(values), rotation=30, ha="right")
    ax.set(xlim=(-0.6, len(values) - 0.4), ylabel="largest braking imposed on another car (m/s^2)",
           title="dense traffic: braking imposed per world")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def dense_section(cfg, out: dict, batches: dict, work: Path, dest: Path, rng) -> tuple[list[str], dict]:
    """The headline: the dense batch beside the ceiling's searches on the same worlds, the braking figure, the per-world
    check that no planner beat the ceiling (logged too), and the ceiling's calibration table; with the headline's rows."""
    p = cfg.results_preset
    worlds = read_ceiling(work, "dense")
    labels = with_options(p.sources, p.mpc_options)
    searches = {k: name for k, name in SEARCHES.items() if f"{k}_courteous" in out["ceiling dense"]}
    rows = {**batch_rows(cfg, batches, "dense", labels, rng),
            **{(name, ""): ceiling_row(out["ceiling dense"], worlds, k, cfg.bootstrap.resamples, rng)
               for k, name in searches.items()}}
    dense = {(s, k): f for (scen, s, k), f in batches.items() if scen == "dense"}
    braking = {f"{s} {m.upper()}": [e["b_imposed_max"] for (src, _), f in dense.items() if src == s for e in read_episodes(f, m)]
               for s, m in rows if m}
    braking.update({name: [w[f"{k}_b_imposed"] for w in worlds] for k, name in searches.items()})
    sc = job_config("ceiling", ["scenario=dense", *p.ceiling]).scenario
    braking_plot(braking, sc.b_safe, sc.b_max, dest / "b_imposed.png")
    beats = {(s, m, k): beaten(worlds, read_episodes(f, m)) for (s, k), f in dense.items() for m in methods(f)}
    beat = sorted(set().union(*beats.values()))
    detail = "; ".join(f"{s} {m.upper()}" + (f" training {k}" if k is not None else "") + f": seeds {sorted(v)}"
                       for (s, m, k), v in beats.items() if v)
    (log.warning if beat else log.info)("results: planner beat the ceiling on %d of %d dense worlds%s", len(beat),
                                        len(worlds), f" ({detail})" if detail else "")
    lines = ["## Dense traffic (headline)", "",
             f"`planner scenario=dense episodes={p.dense_episodes} method=both seed={cfg.planner_seed}` per gradient source and "
             "training, and `ceiling scenario=dense` on the same worlds: the clairvoyant ceiling searches cut-ins, gap acceptance and gap-targeting "
             "strategies on copies of each world with its true hidden decisions, the never-yield ceiling the same with every "
             "driver stubborn, the best fixed strategy the one search strategy with the most courteous merges on "
             f"{p.blind_episodes} other worlds (seeds {job_config('ceiling', []).blind.seed} on), driven blind on these "
             "(bench/ceiling.py). A merge is courteous when nothing collides and nobody brakes harder than "
             f"b_safe = {sc.b_safe:g} m/s^2. t_merge: over the planners' merged episodes, the ceiling's courteous worlds (its "
             "interval Student t); the ceiling's braking on a world it found no courteous merge in is its least-braking "
             "attempt's. Rows `<source> <option>` are ADMM with that conf/mpc/ option (`mpc=courteous`: courtesy rows, repair, "
             "wait and lean-in solves; planner.mpc), the others the paper's step (`mpc=paper`).", ""]
    lines += dense_table(rows)
    lines += ["![b_imposed](b_imposed.png)", "",
              f"Per-world check: planner beat the ceiling on {len(beat)} worlds of {len(worlds)} (a courteous merge the "
              "ceiling did not find on that world, or a faster one; any source, method and training)"
              + (f": {detail}." if detail else "."), ""]
    lines += ["Where each ADMM row falls short of the ceiling, world by world (bench/breakdown.py; in brackets: of them, "
              "the worlds where the ceiling merged courteously):", ""]
    lines += markdown(["gradients", *breakdown.OUTCOMES], [
        [s, *(f"{n} ({ok})" for n, ok in breakdown.breakdown(
            [e for (src, _), f in dense.items() if src == s for e in read_episodes(f, "admm")], worlds, sc.b_safe).values())]
        for s, m in rows if m == "admm"])
    lines += ["", *(f"- {c}: {what}" for c, what in breakdown.OUTCOMES.items()), ""]
    lines += ["## Ceiling calibration", "", f"`ceiling scenario=<scenario> seed={cfg.planner_seed}` (dense: the headline's "
              "run): how often the clairvoyant search merges courteously with the true hidden decisions and with every driver "
              "stubborn, and the largest braking of any other car with the ego held in its lane (a calm world: at most "
              "2 m/s^2).", ""]
    calibration = [(s, out[f"ceiling {s}"]) for s in p.calibration]
    lines += markdown(["scenario", "worlds", "ceiling courteous % [95% CI]", "never-yield courteous % [95% CI]",
                       "ceiling t_merge steps [95% CI]", "held in lane: largest braking (m/s^2)"],
                      [[s, f"{r['worlds']:.0f}", pct(r, "ceiling_courteous"), pct(r, "never_yield_courteous"),
                        ci(r, "ceiling_t_merge"), fmt(r["held_b_imposed_max"])] for s, r in calibration])
    return lines, rows


def accuracy_plot(dense: dict, gradients: dict, inter: dict, path: Path):
    """compare's figure (planner.compare.plot) from the report's own figures: per dense ADMM row, the gradient error of its
    source along ramps (the baselines as lines), its courteous-merge rate and its source's react_corr_jac, against the
    row's median MPC step (ms) on the dense worlds."""
    names = {v: k for k, v in GRADIENT_ROWS.items()}  # a surrogate-job suffix -> its row of the Gradients table
    base = {f"ramp_grad_rel_err{suffix}": gradients[names[suffix]]["ramp_grad_rel_err"][0] for suffix in ("_cv", "_mean")}
    rows = []
    for (name, method), r in dense.items():
        if method != "admm":
            continue
        source = name.split(" ", 1)[0]  # the row name's gradient source (label)
        suffix = compare.SOURCE_SUFFIX.get(source)
        grad = (np.nan,) * 3 if suffix is None else gradients[names[suffix]]["ramp_grad_rel_err"]
        rows.append({"gradients": name, "method": method, "step_ms_median": r["step_ms_median"],
                     "courteous_rate": r["courteous"], "courteous_lo": r["courteous_lo"], "courteous_hi": r["courteous_hi"],
                     **dict(zip((f"ramp_grad_rel_err{e}" for e in ENDS), grad)), **base,
                     "react_corr_jac": inter.get(source, {}).get("react_corr_jac", (np.nan,))[0],
                     "n_episodes": r["episodes"], "n_runs": r["trainings"]})
    compare.plot(pd.DataFrame(rows), path)


def command_line(p) -> str:
    """The command that wrote the results: `results` with its overrides (the preset's name outside a Hydra job)."""
    try:
        return " ".join(["results", *HydraConfig.get().overrides.task])
    except ValueError:
        return f"results results_preset={p.name}"


def report(cfg, out: dict, batches: dict, work: Path, dest: Path) -> Path:
    """Write dest/README-results.md and the figures from the jobs' outputs; returns the Markdown's path."""
    p = cfg.results_preset
    rng = np.random.default_rng(cfg.bootstrap.seed)
    seeds = list(p.training_seeds)
    head = [f"# Results (preset `{p.name}`)", "",
            f"Written by `{command_line(p)}` (bench/results.py); do not edit by hand. Dataset `{p.dataset}`; "
            f"training seeds {seeds}; held-out planner worlds from seed {cfg.planner_seed}. Brackets: 95% intervals "
            "(Wilson for rates over all trainings x episodes; bootstrap over trainings, then episodes, for episode means; "
            "Student t over trainings for per-training figures).", ""]
    d = {m: [out[f"distill {m} seed {k}"] for k in seeds] for m in ("teacher", "student")}
    acc = {"cv": over_trainings([{k[3:]: v for k, v in r.items() if k.startswith("cv_")} for r in d["teacher"]],
                                ("ade_1step_m", "ade_rollout_m", "fde_rollout_m", "ade_rollout_m_yield")),
           **{m: over_trainings(d[m], ("ade_1step_m", "ade_rollout_m", "fde_rollout_m", "ade_rollout_m_yield")) for m in d}}
    mm = lambda t: fmt(1e3 * t[0], ".1f", 1e3 * t[1], 1e3 * t[2])
    lines = ["## Predictors", "", f"Test split of `{p.dataset}`, other cars only, {cfg.paper.T_p}-step rollouts fed the "
             "recorded ego future.", ""]
    lines += markdown(["predictor", "ADE 1-step (mm)", "ADE rollout (mm)", "FDE rollout (mm)", "ADE rollout, yield episodes (mm)"],
                      [[m, *(mm(acc[m][k]) for k in ("ade_1step_m", "ade_rollout_m", "fde_rollout_m", "ade_rollout_m_yield"))]
                       for m in MODELS])
    grads = ("jac_rel_err", "grad_cosine", "grad_rel_err", "react_rel_err", "react_wrel_err", "ramp_grad_rel_err",
             "ramp_react_rel_err")
    rows = {name: gradient_row([out[f"surrogate seed {s}"] for s in seeds], suffix, grads) for name, suffix in GRADIENT_ROWS.items()}
    rows["student"]["jac_rel_err"] = over_trainings(d["student"], ("jac_rel_err",))["jac_rel_err"]  # its distill run's
    lines += ["## Gradients", "", "Against teacher autodiff on held-out planning states, beside the trivial baselines: "
              "constant velocity's Jacobian and the training set's mean Jacobian. The reaction part is the others' "
              "d p_i / dZ, where predicting no reaction scores 1; `weighted` pools the states' errors and reactions (sum of "
              "error norms over sum of reaction norms), so that states where the plan barely moves anyone do not dominate. "
              "`along ramps`: the same derivatives along plan changes the ego can drive (a change of speed from one step "
              "on), the ones the planner's steps take. Intervals: over trainings; with one training, over the surrogate "
              "job's planning states.", ""]
    lines += markdown(["source", "local Jacobian rel. error", "d b_i/dZ cosine", "d b_i/dZ rel. error", "reaction rel. error",
                       "reaction rel. error, weighted", "d b_i/dZ rel. error along ramps", "reaction rel. error along ramps"],
                      [[name, *(fmt(r[k][0], ".3f", *r[k][1:]) for k in grads)] for name, r in rows.items()])
    inter_runs = {}
    for k in seeds:
        for source, m in out[f"evaluate-interaction seed {k}"].items():
            inter_runs.setdefault(source, []).append(m)
    keys = ("react_corr", "react_gain", "react_hit", "react_corr_jac", "react_gain_jac", "react_hit_jac", "brake_corr",
            "brake_auc")
    inter = {s: over_trainings(v, keys) for s, v in inter_runs.items()}
    lines += ["## Interaction fidelity", "", "evaluate-interaction (bench/interaction.py): the response to paired ego plans "
              "on held-out counterfactual branches; `_jac` is the first-order response the planner linearises. `brake_*`: "
              "the hardest braking each plan imposes on another car, against the world's; brake_auc sorts the plans that "
              "force a driver (above b_safe) from the rest (0.5: no better than chance). `follower`: the courteous "
              "planner's nominal IDM follower, which judges braking for every source.", ""]
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
        lines += [f"## Table II: {scenario}", "", f"{p.table2_episodes} episode(s) per training from seed {cfg.planner_seed}; "
                  f"the ceiling's t_merge from `ceiling scenario={scenario}` on the same worlds.", ""]
        lines += outcome_table(batch_rows(cfg, batches, scenario, with_options(p.table2_sources, p.mpc_options), rng),
                               out[f"ceiling {scenario}"])
    lines += ["## Accuracy against speed", "", "Per ADMM row of the dense headline, against its median MPC step on those "
              "worlds: its gradient source's error of d b_i/dZ along ramps (the Gradients table; the baselines as lines), its "
              "courteous-merge rate, its source's first-order interaction fidelity (react_corr_jac). `compare` draws the "
              "same figure from the MLflow runs.", "", "![accuracy against speed](accuracy_vs_speed.png)", ""]
    if "bench step time" in out:
        b = out["bench step time"]
        names = [k[: -len("_ms_median")] for k in b if k.endswith("_ms_median")]
        lines += ["## MPC step time", "", "One MPC step per source on saved planning states, one thread (training seed "
                  f"{seeds[0]}).", ""]
        lines += markdown(["source", "median ms", "p95 ms", "ADMM iterations"],
                          [[n, fmt(b[f"{n}_ms_median"], ".1f"), fmt(b[f"{n}_ms_p95"], ".1f"), fmt(b[f"{n}_iters_mean"], ".1f")]
                           for n in names])
        ratios = [f"{k.removeprefix('ratio_').replace('_', '/', 1)} {v:.1f}x" for k, v in b.items()
                  if k.startswith("ratio_") and not k.startswith("ratio_ipopt_")]
        ipopt = [f"{n} {b[f'ratio_ipopt_{n}']:.2f}x (median cost gap {b[f'gap_{n}_median']:+.2%})"
                 for n in (k.removeprefix("ratio_ipopt_") for k in b if k.startswith("ratio_ipopt_"))]
        lines += [f"Median ratios: {', '.join(ratios)}. IPOPT's time over ADMM's on the same states (> 1: ADMM faster): "
                  f"{', '.join(ipopt) or 'n/a (no CasADi)'}. `make bench` prints where the time goes.", ""]
    for f in ("snapshots_admm.png", "merge_admm.gif", "snapshots_nnmpc.png", "merge_nnmpc.gif"):
        if (work / "showcase" / f).exists():
            shutil.copyfile(work / "showcase" / f, dest / f)
    lines += ["## A closed-loop run", "", f"`planner method=both {' '.join(p.showcase)} seed={cfg.planner_seed}`", "",
              "![snapshots](snapshots_admm.png) ![animation](merge_admm.gif)", "",
              "![snapshots](snapshots_nnmpc.png) ![animation](merge_nnmpc.gif)", ""]
    # the headline leads the report; its bootstrap draws follow the others' so that their intervals stay as they were
    dense_lines, dense_rows = dense_section(cfg, out, batches, work, dest, rng)
    accuracy_plot(dense_rows, rows, inter, dest / "accuracy_vs_speed.png")
    lines = head + dense_lines + lines
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
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Entry point of the `results` console script: overrides checked first (one line for a misspelt key)."""
    console("results", hydra_main)


if __name__ == "__main__":
    main()
