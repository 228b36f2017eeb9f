"""`results` (`make results`): every table and figure of results/ (the README's headline among them), from scratch.

Three parts: the job plan (bench/results_plan.py: the dataset; the world's answers to the interactive step's own
candidates (bench/candidates.py); per training seed k the teacher, the student (distilled on the dataset, then on those
candidates' windows) and the surrogate into <work_dir>/models/seed<k>; the interaction benchmark per training; the
interactive step's verdicts (bench/verdicts.py) of every training's fidelity predictors on the same held-out states;
the planner's held-out batches (dense traffic, the headline; random merges; the Table II scenarios) of every gradient source with both methods, once per
training for the trained sources and once for cv and analytic; the cooperation sweep's dense batches at the other
levels, first training alone; after them, the clairvoyant ceiling on the same dense worlds, on the calibration scenarios,
on Table II's worlds and per cooperation level, every batch's runs on its scenario among its starts; the step-time bench;
one closed-loop showcase run), run in order through the jobs' Python `run` functions (each logs its own MLflow runs);
the tables (bench/results_tables.py, figures in bench/results_plots.py), computed from what those jobs returned and
wrote; the text (bench/results_text.md), the prose around them. Together they write <out_dir>/README-results.md and
<out_dir>/*.png, so no figure is typed by hand.

The headline is the courteous-merge rate on dense traffic (data.outcomes: merged, no collision, nobody made to brake
harder than b_safe), beside the ceiling's and the never-yield ceiling's. Per dense world, no planner episode may merge
courteously where the ceiling did not, or sooner: the report counts the worlds where one did (0 by construction: every
run is replayed as one of the ceiling's starts), and how often the search alone, without the runs, reached the final
value. Time to merge against the ceiling is a per-world ratio on the worlds both merged courteously on, bootstrapped.

Intervals (95%): Wilson for rates, pooled over trainings and episodes; for means over episodes a percentile bootstrap
that resamples trainings, then episodes within each, every table row on its own random stream (results_tables.stream);
for per-training figures (accuracy, interaction) a Student t interval over trainings (none with one training).

Held-out seeds: planner and ceiling worlds use planner_seed + k; the job checks them against the dataset's episode seeds
(data.dataset.episode_seeds) and the interaction benchmark's worlds (its seed_offset + k) before anything runs.

    results [results_preset=tiny|small|full] [out_dir=results] [n_jobs=-1] [backend=ray ray.address=auto]

Adding a section is three local edits, and moves no other section's figures:
  1. its jobs, if it needs new ones: `plan.add(label, job.run, job_config(...))` in results_plan.build_plan (the preset's
     knobs in conf/results_preset/small.yaml, with tiny's and full's values where they differ);
  2. a function `def my_section(r: Report) -> dict | list[dict]` below, returning the values its text needs (tables via
     results_tables.markdown; bootstraps on `r.stream("my_section", row, ...)`; `[]` to leave the section out), and its
     name in SECTIONS where it should appear;
  3. its prose in bench/results_text.md, opened by `<!-- section: my_section -->`, with `{value}` placeholders.
"""
import logging
import re
import shutil
from functools import cached_property
from pathlib import Path

import hydra
import numpy as np
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from bench import breakdown
from bench.results_plan import (
    INTERACTIVE,
    ORACLE,
    build_plan,
    dense_sources,
    label,
    swept,
    variants,
    verdict_judges,
    with_options,
)
from bench.results_plots import accuracy_plot, bar_plot, braking_plot, cooperation_plot, fidelity_plot
from bench.results_tables import (
    GRADIENT_ROWS,
    beaten,
    ceiling_row,
    ci,
    dense_table,
    gradient_row,
    markdown,
    methods,
    outcome_table,
    outcomes,
    over_trainings,
    paired_t_merge,
    pct,
    rank_correlation,
    rate,
    read_ceiling,
    read_episodes,
    size,
    stream,
    sweep_table,
    world_hits,
)
from core import validate
from core.jobs import CONF_DIR, console, guarded, job_config, mlflow_run, writable
from planner.compare import fmt

log = logging.getLogger(__name__)


def step_s() -> float:
    """The world's step dt (s), the dense scenario's: every batch results draws drives it."""
    return float(job_config("planner", ["scenario=dense"]).scenario.params.dt)


TEXT = Path(__file__).with_name("results_text.md")
MODELS = ("cv", "teacher", "student")  # predictors of the accuracy table; cv from the cv_* metrics of the teacher's runs
ACCURACY = ("ade_1step_m", "ade_rollout_m", "fde_rollout_m", "ade_rollout_m_yield")
GRADIENTS = ("jac_rel_err", "grad_cosine", "grad_rel_err", "react_rel_err", "react_wrel_err", "ramp_grad_rel_err",
             "ramp_react_rel_err")
INTERACTION = ("react_corr", "react_gain", "react_hit", "react_corr_jac", "react_gain_jac", "react_hit_jac", "brake_corr",
               "brake_auc", "brake_fa")
FIDELITY = {"brake_auc": "interaction benchmark", "react_corr": "interaction benchmark",
            "good_kept": "bench.verdicts, the step's own candidates"}  # the scores the fidelity figure ranks predictors by
SEARCHES = {"ceiling": "ceiling", "never_yield": "never-yield ceiling", "blind": "best fixed strategy"}  # the ceiling's
# searches and their row names; the dense ceiling's best fixed strategy only with results_preset.blind_episodes > 0


class Report:
    """What the sections read: the config, the jobs' results by label (`out`), the planner batches' folders, the work
    folder and the report's folder (figures go there); tables more than one section shows are computed once."""

    def __init__(self, cfg, out: dict, batches: dict, work: Path, dest: Path):
        self.cfg, self.p, self.out, self.batches, self.work, self.dest = cfg, cfg.results_preset, out, batches, work, dest
        self.seeds = list(self.p.training_seeds)

    def stream(self, *names: str) -> np.random.Generator:
        """The random stream of one row of a section's table (results_tables.stream of bootstrap.seed)."""
        return stream(self.cfg.bootstrap.seed, *names)

    def batch_rows(self, scenario: str, sources) -> dict:
        """{(row, method): outcomes row} of one scenario's batches, each row's bootstrap on the stream (scenario, row,
        method)."""
        rows = {}
        for source in sources:
            folders = [f for (sc, s, _), f in self.batches.items() if sc == scenario and s == source]
            for m in methods(folders[0]):
                rows[source, m] = outcomes([read_episodes(f, m) for f in folders], self.cfg.bootstrap.resamples,
                                           self.stream(scenario, source, m))
        return rows

    @cached_property
    def dense_rows(self) -> dict:
        """The headline's rows: the dense batches, then the ceiling's searches on the same worlds (method '')."""
        worlds = read_ceiling(self.work, "dense")
        run = self.out["ceiling dense"]
        return {**self.batch_rows("dense", dense_sources(self.p)),
                **{(name, ""): ceiling_row(run, worlds, k, self.cfg.bootstrap.resamples, self.stream("dense", name))
                   for k, name in SEARCHES.items() if f"{k}_courteous" in run}}

    @cached_property
    def gradient_rows(self) -> dict:
        """{Gradients table row: {score: (mean, lo, hi)}} over the trainings' surrogate jobs; the student's local Jacobian
        error from its distill runs."""
        runs = [self.out[f"surrogate seed {k}"] for k in self.seeds]
        rows = {name: gradient_row(runs, suffix, GRADIENTS) for name, suffix in GRADIENT_ROWS.items()}
        student = [self.out[f"distill student seed {k}"] for k in self.seeds]
        rows["student"]["jac_rel_err"] = over_trainings(student, ("jac_rel_err",))["jac_rel_err"]
        return rows

    @cached_property
    def interaction(self) -> dict:
        """{source: {score: (mean, lo, hi)}} of the interaction benchmark over trainings."""
        runs = {}
        for k in self.seeds:
            for source, m in self.out[f"evaluate-interaction seed {k}"].items():
                runs.setdefault(source, []).append(m)
        return {s: over_trainings(v, INTERACTION) for s, v in runs.items()}


def command_line(p) -> str:
    """The command that wrote the results: `results` with its overrides (the preset's name outside a Hydra job)."""
    try:
        return " ".join(["results", *HydraConfig.get().overrides.task])
    except ValueError:
        return f"results results_preset={p.name}"


def head(r: Report) -> dict:
    """The title and how to read the brackets."""
    return {"preset": r.p.name, "command": command_line(r.p), "dataset": r.p.dataset, "seeds": r.seeds,
            "planner_seed": r.cfg.planner_seed}


def dense(r: Report) -> dict:
    """The headline: the dense batch beside the ceiling's searches on the same worlds, the braking figure, the per-world
    check that no planner beat the ceiling (logged too) and where each ADMM row falls short."""
    p, worlds = r.p, read_ceiling(r.work, "dense")
    run = r.out["ceiling dense"]
    searches = {k: name for k, name in SEARCHES.items() if f"{k}_courteous" in run}
    folders = {(s, k): f for (scen, s, k), f in r.batches.items() if scen == "dense"}
    braking = {f"{s} {m.upper()}": [e["b_imposed_max"] for (src, _), f in folders.items() if src == s
                                    for e in read_episodes(f, m)] for s, m in r.dense_rows if m}
    braking.update({name: [w[f"{k}_b_imposed"] for w in worlds] for k, name in searches.items()})
    sc = job_config("ceiling", ["scenario=dense", *p.ceiling]).scenario
    braking_plot(braking, sc.b_safe, sc.b_max, r.dest / "b_imposed.png")
    beats = {(s, m, k): beaten(worlds, read_episodes(f, m)) for (s, k), f in folders.items() for m in methods(f)}
    beat = sorted(set().union(*beats.values()))
    detail = "; ".join(f"{s} {m.upper()}" + (f" training {k}" if k is not None else "") + f": seeds {sorted(v)}"
                       for (s, m, k), v in beats.items() if v)
    (log.warning if beat else log.info)("results: planner beat the ceiling on %d of %d dense worlds%s", len(beat),
                                        len(worlds), f" ({detail})" if detail else "")
    paired = {(s, m): paired_t_merge(worlds, [e for (src, _), f in folders.items() if src == s for e in read_episodes(f, m)],
                                     r.cfg.bootstrap.resamples, r.stream("dense", "paired", s, m)) for s, m in r.dense_rows if m}
    paired = markdown(["row", "worlds both merged courteously", "t_merge over the ceiling's, mean per world [95% CI]"],
                      [[f"{s} {m.upper()}", str(v["pairs"]), ci(v, "ratio", ".2f")] for (s, m), v in paired.items()])
    short = markdown(["gradients", *breakdown.OUTCOMES], [
        [s, *(f"{n} ({ok})" for n, ok in breakdown.breakdown(
            [e for (src, _), f in folders.items() if src == s for e in read_episodes(f, "admm")], worlds, sc.b_safe).values())]
        for s, m in r.dense_rows if m == "admm"])
    reached = sum(w["search_courteous"] == w["ceiling_courteous"] and w["search_t_merge"] == w["ceiling_t_merge"]
                  for w in worlds)
    return {"episodes": p.dense_episodes, "planner_seed": r.cfg.planner_seed, "blind_episodes": p.blind_episodes,
            "starts": int(sum(w["starts"] for w in worlds)), "reached": reached,
            "blind_seed": job_config("ceiling", []).blind.seed, "b_safe": sc.b_safe,
            "table": "\n".join(dense_table(r.dense_rows)), "beat": len(beat), "worlds": len(worlds),
            "detail": f": {detail}" if detail else "", "breakdown": "\n".join(short), "paired": "\n".join(paired),
            "outcomes": "\n".join(f"- {c}: {what}" for c, what in breakdown.OUTCOMES.items())}


def calibration(r: Report) -> dict:
    """The ceiling's courteous rates with true and stubborn drivers, and the calm world's braking, per scenario."""
    runs = [(s, r.out[f"ceiling {s}"]) for s in r.p.calibration]
    table = markdown(["scenario", "worlds", "ceiling courteous % [95% CI]", "never-yield courteous % [95% CI]",
                      "ceiling t_merge steps [95% CI]", "held in lane: largest braking (m/s^2)"],
                     [[s, f"{c['worlds']:.0f}", pct(c, "ceiling_courteous"), pct(c, "never_yield_courteous"),
                       ci(c, "ceiling_t_merge"), fmt(c["held_b_imposed_max"])] for s, c in runs])
    return {"planner_seed": r.cfg.planner_seed, "table": "\n".join(table)}


def cooperation(r: Report) -> list[dict]:
    """The cooperation sweep on the first cooperation_episodes dense worlds: per level, the ceiling's two searches and
    every dense row of the first training; its figure. None without levels."""
    levels, n = list(r.p.cooperation), r.p.cooperation_episodes
    if not levels:
        return []
    seeds = set(range(r.cfg.planner_seed, r.cfg.planner_seed + n))  # mixed: the headline's first n worlds
    first = r.seeds[0]
    swept_rows, rates = with_options(r.p.sources, r.p.mpc_options), {}
    for c in levels:
        key, worlds = ("dense", read_ceiling(r.work, "dense")) if c == "mixed" else (swept(c), read_ceiling(r.work, "dense", c))
        for k, name in list(SEARCHES.items())[:2]:
            rates.setdefault(name, {})[c] = rate([w[f"{k}_courteous"] for w in worlds if int(w["seed"]) in seeds])
        for (sc, row, training), folder in r.batches.items():
            if sc == key and training in (None, first) and row in swept_rows:  # not the oracle's, nor the fidelity rows
                for m in methods(folder):
                    hits = [e["courteous"] for e in read_episodes(folder, m) if int(e["seed"]) in seeds]
                    rates.setdefault(f"{row} {m.upper()}", {})[c] = rate(hits)
    cooperation_plot(rates, levels, r.dest / "cooperation.png")
    return [{"worlds": n, "planner_seed": r.cfg.planner_seed, "training": first,
             "levels": ", ".join(levels), "table": "\n".join(sweep_table(rates, levels))}]


def predictors(r: Report) -> dict:
    """The predictors' test-split errors (mm) over trainings; cv's from the teacher's runs."""
    d = {m: [r.out[f"distill {m} seed {k}"] for k in r.seeds] for m in ("teacher", "student")}
    acc = {"cv": over_trainings([{k.removesuffix("_cv"): v for k, v in run.items() if k.endswith("_cv")} for run in d["teacher"]],
                                ACCURACY), **{m: over_trainings(d[m], ACCURACY) for m in d}}
    mm = lambda t: fmt(1e3 * t[0], ".1f", 1e3 * t[1], 1e3 * t[2])
    table = markdown(["predictor", "ADE 1-step (mm)", "ADE rollout (mm)", "FDE rollout (mm)",
                      "ADE rollout, yield episodes (mm)"], [[m, *(mm(acc[m][k]) for k in ACCURACY)] for m in MODELS])
    return {"dataset": r.p.dataset, "T_p": r.cfg.paper.T_p, "table": "\n".join(table)}


def gradients(r: Report) -> dict:
    """Each gradient source's d b_i/dZ against teacher autodiff, beside the baselines."""
    table = markdown(["source", "local Jacobian rel. error", "d b_i/dZ cosine", "d b_i/dZ rel. error", "reaction rel. error",
                      "reaction rel. error, weighted", "d b_i/dZ rel. error along ramps", "reaction rel. error along ramps"],
                     [[name, *(fmt(row[k][0], ".3f", *row[k][1:]) for k in GRADIENTS)]
                      for name, row in r.gradient_rows.items()])
    return {"table": "\n".join(table)}


def interaction(r: Report) -> dict:
    """The interaction benchmark's scores per source."""
    table = markdown(["source", *INTERACTION], [[s, *(fmt(v[k][0], ".3f", *v[k][1:]) for k in INTERACTION)]
                                                for s, v in r.interaction.items()])
    return {"table": "\n".join(table)}


def fidelity(r: Report) -> list[dict]:
    """Better prediction, better planning: each fidelity row's courteous rate and t_merge on the dense worlds (its
    batches over trainings) against its predictor's fidelity (FIDELITY: the interaction benchmark's scores, the verdicts
    job's good_kept), Spearman's rank correlation of each score with the courteous rate over the rows that score has,
    its interval a bootstrap over worlds; the figure. None without fidelity rows."""
    # good_kept over the source's judges, one per training: a t interval over trainings, with one the job's own
    kept = lambda names: gradient_row([r.out["verdicts"].get(n, {}) for n in names], "", ("good_kept",))
    scores = {label(s, INTERACTIVE): {**r.interaction[s], **kept(verdict_judges(r.p, s))} for s in r.p.fidelity_sources}
    scores |= {label(v.name, INTERACTIVE): {**over_trainings([r.out[f"evaluate-interaction {v.name}"][v.model]],
                                                             INTERACTION), **kept([v.name])} for v in variants(r.p)}
    if not scores:
        return []
    rows = r.batch_rows("dense", scores)
    episodes = {name: [e for (sc, s, _), f in r.batches.items() if sc == "dense" and s == name for e in read_episodes(f, "admm")]
                for name in scores}
    seeds = sorted({int(e["seed"]) for eps in episodes.values() for e in eps})
    rhos, n = {}, {}
    for score in FIDELITY:
        scored = [name for name in scores if np.isfinite(scores[name][score][0])]
        hits, counts = world_hits({name: episodes[name] for name in scored}, seeds)
        rhos[score] = rank_correlation([scores[name][score][0] for name in scored], hits, counts,
                                       r.cfg.bootstrap.resamples, r.stream("fidelity", score))
        n[score] = len(scored)
    oracle = r.dense_rows.get((label("oracle", ORACLE), "admm"))
    fidelity_plot({name: {**scores[name], "row": rows[name, "admm"]} for name in scores}, rhos, FIDELITY, oracle,
                  r.dest / "fidelity.png", f"{len(seeds)} held-out dense worlds (seeds from {r.cfg.planner_seed})",
                  step_s())
    table = markdown(["predictor", "trainings x worlds", *(f"{k} [95% CI]" for k in FIDELITY), "courteous % [95% CI]",
                      "t_merge steps [95% CI]"],
                     [[name, size(rows[name, "admm"]), *(fmt(scores[name][k][0], ".3f", *scores[name][k][1:]) for k in FIDELITY),
                       pct(rows[name, "admm"], "courteous"), ci(rows[name, "admm"], "t_merge")] for name in scores])
    judged, reference = job_config("verdicts", [f"seed_offset={r.p.verdicts_seed}", *r.p.verdicts]), r.out["verdicts"]["oracle"]
    return [{"episodes": r.p.dense_episodes, "planner_seed": r.cfg.planner_seed, "resamples": r.cfg.bootstrap.resamples,
             "table": "\n".join(table), "worlds": len(seeds), "verdict_worlds": judged.worlds,
             "verdict_seed": judged.seed_offset, "every": judged.every, "states": reference["states"],
             "with_good": reference["states_with_good"],
             "rhos": "; ".join(f"{k}: rho = {fmt(rhos[k][0], '.2f', *rhos[k][1:])} over {n[k]} predictors" for k in FIDELITY)
             + " ('-': undefined, every rate or every score equal)" * any(np.isnan(v[0]) for v in rhos.values()),
             "oracle": "" if oracle is None else (
                 f"The oracle row (`oracle interactive`, the world itself as predictor: courteous {pct(oracle, 'courteous')} % "
                 f"on the first {oracle['episodes']} of these worlds) is the figure's dashed line and stays out of the "
                 "correlation: the interaction benchmark cannot score the running world as a predictor, and good_kept "
                 "takes its verdicts as the truth.")}]


def random_merges(r: Report) -> dict:
    """The random merges' outcomes and their bar figures."""
    rows = r.batch_rows("random", r.p.sources)
    figs = {"merge_rate.png": ("merged", "merge rate (%)", 100.0), "t_merge.png": ("t_merge", "t_merge (s)", step_s()),
            "fallbacks.png": ("fallbacks", "fallbacks per episode", 1.0)}
    for name, (key, ylabel, scale) in figs.items():
        bar_plot(rows, key, ylabel, f"random merges: {ylabel}, 95% CI", r.dest / name, scale)
    return {"episodes": r.p.episodes, "planner_seed": r.cfg.planner_seed, "table": "\n".join(outcome_table(rows)),
            "figures": "\n".join(f"![{k}]({k})" for k in figs)}


def table2(r: Report) -> list[dict]:
    """One section per Table II scenario: its batches beside the ceiling's t_merge on the same worlds."""
    rows = lambda sc: r.batch_rows(sc, with_options(r.p.table2_sources, r.p.mpc_options))
    return [{"scenario": sc, "episodes": r.p.table2_episodes, "planner_seed": r.cfg.planner_seed,
             "table": "\n".join(outcome_table(rows(sc), r.out[f"ceiling {sc}"]))} for sc in r.p.scenarios]


def accuracy(r: Report) -> dict:
    """compare's figure from the report's own tables."""
    accuracy_plot(r.dense_rows, r.gradient_rows, r.interaction, r.dest / "accuracy_vs_speed.png")
    return {}


def step_time(r: Report) -> list[dict]:
    """The step-time bench's medians, p95s and ratios; no section without a bench."""
    if "bench step time" not in r.out:
        return []
    b = r.out["bench step time"]
    names = [k[: -len("_ms_median")] for k in b if k.endswith("_ms_median")]
    table = markdown(["source", "median ms", "p95 ms", "ADMM iterations"],
                     [[n, fmt(b[f"{n}_ms_median"], ".1f"), fmt(b[f"{n}_ms_p95"], ".1f"), fmt(b[f"{n}_iters_mean"], ".1f")]
                      for n in names])
    ratios = [f"{k.removeprefix('ratio_').replace('_', '/', 1)} {v:.1f}x" for k, v in b.items()
              if k.startswith("ratio_") and not k.startswith("ratio_ipopt_")]
    ipopt = [f"{n} {b[f'ratio_ipopt_{n}']:.2f}x (median cost gap {b[f'gap_{n}_median']:+.2%})"
             for n in (k.removeprefix("ratio_ipopt_") for k in b if k.startswith("ratio_ipopt_"))]
    return [{"seed": r.seeds[0], "table": "\n".join(table), "ratios": ", ".join(ratios),
             "ipopt": ", ".join(ipopt) or "n/a (no CasADi)"}]


def showcase(r: Report) -> dict:
    """The closed-loop run's snapshots and animations, copied beside the report."""
    for f in ("snapshots_admm.png", "merge_admm.gif", "snapshots_nnmpc.png", "merge_nnmpc.gif"):
        if (r.work / "showcase" / f).exists():
            shutil.copyfile(r.work / "showcase" / f, r.dest / f)
    return {"overrides": " ".join(r.p.showcase), "planner_seed": r.cfg.planner_seed}


# the report's sections in order: (name of its block in results_text.md, the function returning its values)
SECTIONS = [("head", head), ("dense", dense), ("calibration", calibration), ("cooperation", cooperation),
            ("predictors", predictors), ("gradients", gradients), ("interaction", interaction), ("fidelity", fidelity),
            ("random", random_merges), ("table2", table2), ("accuracy", accuracy), ("bench", step_time),
            ("showcase", showcase)]


def texts(path: Path = TEXT) -> dict:
    """{section name: its prose template} of results_text.md (what precedes the first section is the file's comment)."""
    parts = re.split(r"^<!-- section: (\S+) -->\n", path.read_text(), flags=re.M)
    return dict(zip(parts[1::2], parts[2::2]))


def render(r: Report, sections=SECTIONS, prose: dict | None = None) -> str:
    """The report's Markdown: each section's template (`prose`, by default results_text.md's) filled with its values, once
    per instance, in `sections`' order."""
    prose = prose or texts()
    parts = []
    for name, fn in sections:
        values = fn(r)
        parts += [prose[name].format(**v) for v in (values if isinstance(values, list) else [values])]
    return "".join(parts).rstrip("\n") + "\n"


def report(cfg, out: dict, batches: dict, work: Path, dest: Path) -> Path:
    """Write dest/README-results.md and the figures from the jobs' outputs; returns the Markdown's path."""
    path = dest / "README-results.md"
    path.write_text(render(Report(cfg, out, batches, work, dest)))
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
