"""The job plan of `results` (bench/results.py): which jobs run, in which order, with which overrides, and where each
writes; the report's sections read the jobs' results by label and the planner batches' folders."""
import logging
import shutil
import time
from pathlib import Path

from omegaconf import ListConfig, OmegaConf

from bench import ceiling
from bench.branches import heldout_seeds
from core import validate
from core.jobs import UserError, job_config
from data.drivers import COOPERATION
from planner.batch import progress
from planner.gradients import available, reads_models

log = logging.getLogger(__name__)
TRAINED = tuple(s for s in available(hypotheses=False) if reads_models(s))  # gradient sources that read trained models
# (per training seed); the hypothesis models are not yet among results' trainings
PRESET = {"results_preset.cooperation": validate.ListOf(validate.OneOf(tuple(COOPERATION))),
          "results_preset.cooperation_episodes": validate.EPISODES,
          "results_preset.oracle_episodes": validate.Int(0, validate.MAX_EPISODES),
          "results_preset.oracle_n_slots": validate.ListOf(validate.Int(1, validate.MAX_SLOTS)),
          # the oracle reads the running world: the interaction benchmark cannot score it, nor so place it on the figure
          "results_preset.fidelity_sources": validate.ListOf(validate.OneOf(available(needs_world=False, hypotheses=False))),
          "results_preset.verdicts": validate.OVERRIDES, "results_preset.verdicts_seed": validate.SEED}
ORACLE = ["mpc=interactive", "method=admm", "predictor=oracle"]  # the dense row whose predictor is the world itself
INTERACTIVE = ["mpc=interactive", "method=admm"]  # the fidelity figure's rows: the interactive step, ADMM alone
VARIANT = ("name", "model", "overrides")  # the keys of a fidelity variant
VARIANT_MODELS = ("teacher", "student")


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
    n = max(p.episodes, p.table2_episodes, p.dense_episodes, p.calibration_episodes, p.cooperation_episodes)
    seeds = heldout_seeds("planner_seed", cfg.planner_seed, n, interaction_cfg.dataset)
    other = interaction_worlds(interaction_cfg)
    if seeds.start < other.stop and other.start < seeds.stop:
        raise UserError(f"planner_seed={cfg.planner_seed}: planner seeds {seeds.start}..{seeds.stop - 1} overlap the "
                        f"interaction benchmark's {other.start}..{other.stop - 1}; choose another planner_seed")
    return seeds


def interaction_worlds(interaction_cfg) -> range:
    """The world seeds the interaction benchmark may draw its branch states from."""
    return range(interaction_cfg.seed_offset, interaction_cfg.seed_offset + interaction_cfg.states * interaction_cfg.branch.tries)


def verdict_judges(p, source: str) -> list[str]:
    """The names of a fidelity source's judges in the verdicts job, one per training that trains it: the first
    training's under the source's own name, training k's `<source>_seed<k>`; an untrained source's once."""
    return [source, *(f"{source}_seed{k}" for k in p.training_seeds[1:])] if source in TRAINED else [source]


def verdicts_config(cfg, work: Path, models, fidelity: list):
    """The `python -m bench.verdicts` job of the fidelity figure: every fidelity source of every training and every
    fidelity variant (verdict_judges' names) judged on the same states of results_preset.verdicts_seed's worlds, the
    planner batches' overrides first; a UserError naming results_preset.verdicts for a bad value there."""
    from bench import verdicts

    p = cfg.results_preset
    first = p.training_seeds[0]
    job = job_config("verdicts", [
        f"dataset={p.dataset}", f"models_dir={models(first)}", f"out_dir={work / 'verdicts'}",
        f"seed_offset={p.verdicts_seed}", f"sources=[{','.join(p.fidelity_sources)}]",
        f"resamples={cfg.bootstrap.resamples}", *p.verdicts])
    # set, not overrides: a list of dicts and the planner's quoted overrides
    job.variants = [{"name": name, "gradients": s, "models_dir": str(models(k))} for s in p.fidelity_sources
                    for k, name in zip(p.training_seeds[1:], verdict_judges(p, s)[1:])]
    job.variants += [{"name": v.name, "gradients": v.model, "models_dir": str(variant_models(work, v.name, first))}
                     for v in fidelity]
    job.planner = [*p.planner, *job.planner]
    try:
        validate.check(job, verdicts.SCHEMA)
        verdicts.variants(job)
    except UserError as e:
        raise UserError(f"results_preset.verdicts: {e}") from e
    return job


def check_verdicts(job, planner: range, interaction_cfg) -> range:
    """The verdicts' world seeds; one UserError naming results_preset.verdicts_seed if they were the dataset's, the
    planner's or the interaction benchmark's."""
    seeds = heldout_seeds("results_preset.verdicts_seed", job.seed_offset, job.worlds, job.dataset)
    check_clear("results_preset.verdicts_seed", job.seed_offset, "the verdicts' worlds", seeds,
                {"planner": planner, "interaction benchmark": interaction_worlds(interaction_cfg)})
    return seeds


def check_clear(key: str, value, what: str, seeds: range, others: dict) -> None:
    """One UserError naming `key`=value if `seeds` (`what`) overlap one of others' {name: seed range}."""
    for name, other in others.items():
        if seeds.start < other.stop and other.start < seeds.stop:
            raise UserError(f"{key}={value}: {what} {seeds.start}..{seeds.stop - 1} overlap the {name}'s "
                            f"{other.start}..{other.stop - 1}; choose another {key}")


def candidates_config(cfg, work: Path, others: dict):
    """The `python -m bench.candidates` job (None without results_preset.candidates): the world's answers to the
    interactive step's own candidates, the windows every student is distilled further on (add_training's `step`),
    their worlds clear of the dataset's episodes and of others' {name: seed range}, driven by sources that need no
    trained model (the job runs before any training); one UserError naming results_preset.candidates otherwise."""
    from bench import candidates

    p = cfg.results_preset
    if p.candidates is None:
        return None
    job = job_config("candidates", [f"dataset={p.dataset}", f"out_dir={work / 'data'}", "name=candidates",
                                    *p.candidates])
    try:
        validate.check(job, candidates.SCHEMA)
        trained = [s for s in job.drive if s in TRAINED]
        if trained:
            raise UserError(f"drive={list(job.drive)}: {', '.join(trained)} needs trained models, and this job runs "
                            f"before any training; drive with sources that need none (cv, analytic)")
        seeds, _ = candidates.worlds(job)
        check_clear("seed_offset", job.seed_offset, "the candidates' worlds", seeds, others)
    except UserError as e:
        raise UserError(f"results_preset.candidates: {e}") from e
    return job


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
                 surrogate=True, iterates=None, trained=("teacher", "student"), step=None):
    """Add to `plan` the `trained` models (the teacher, the student) and (with `surrogate`) the surrogate trained on dataset_dir (of conf/dataset/
    option `dataset`) into `models` with training seed `seed`: jobs 'distill <model> <tag>' and 'surrogate <tag>', their
    run folders runs/distill-<model>-<name> and runs/surrogate-<name>; extra: each job's extra overrides by key
    (teacher, student, surrogate). With `step` (the folder of bench.candidates' windows, the fine-tune's overrides), the
    student is distilled on dataset_dir in job 'distill student on the dataset <tag>', then from those weights on the
    interactive step's own states in 'distill student <tag>' (scored on dataset_dir's test split, as the first).
    With `iterates` (overrides of a `planner` batch), job 'iterates <tag>' first records the states that planner
    linearises at into runs/iterates-<name>, and the surrogate trains and is tested on them."""
    from distill import train
    from planner import cli as planner_cli
    from surrogate import cli as surrogate_cli

    common = [f"dataset={dataset}", f"dataset_dir={dataset_dir}", f"models_dir={models}", f"seed={seed}"]
    for model in trained:
        tuned = model == "student" and step is not None
        plan.add(f"distill {model} {'on the dataset ' if tuned else ''}{tag}", train.run, job_config("distill", [
            f"model={model}", *common, f"run_dir={runs / f'distill-{model}-{name}'}", "trainer.enable_progress_bar=false",
            *extra[model]]))
        if tuned:
            windows, overrides = step
            plan.add(f"distill student {tag}", train.run, job_config("distill", [
                "model=student", f"dataset={dataset}", f"dataset_dir={windows}", f"eval_dir={dataset_dir}",
                f"models_dir={models}", f"seed={seed}", f"init_from={models / 'student.ckpt'}",
                f"run_dir={runs / f'distill-student-step-{name}'}", "trainer.enable_progress_bar=false", *extra[model],
                *overrides]))
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


def variants(p) -> list:
    """The preset's fidelity_variants, each {name, model: teacher | student, overrides: [distill overrides]} with a name
    no gradient source or other variant has; one UserError naming the entry otherwise."""
    taken = set(available())
    for i, v in enumerate(p.fidelity_variants):
        where = f"results_preset.fidelity_variants[{i}]"
        if not hasattr(v, "keys") or set(v.keys()) != set(VARIANT):
            raise UserError(f"{where}={v}: must be {{name: <folder name>, model: teacher|student, overrides: [...]}}")
        if not validate.Name().ok(v.name) or " " in v.name or v.name in taken:
            raise UserError(f"{where}.name={v.name}: must be a folder name without spaces that no gradient source or "
                            f"other variant has")
        if v.model not in VARIANT_MODELS:
            raise UserError(f"{where}.model={v.model}: must be one of {', '.join(VARIANT_MODELS)}")
        if not isinstance(v.overrides, ListConfig) or not all(isinstance(o, str) for o in v.overrides):
            raise UserError(f"{where}.overrides={v.overrides}: must be a list of `distill` overrides")
        taken.add(v.name)
    return list(p.fidelity_variants)


def check_fidelity(p) -> None:
    """One UserError for a fidelity source the interaction benchmark does not score (its fidelity is that benchmark's)."""
    missing = [s for s in p.fidelity_sources if s not in p.interaction_sources]
    if missing:
        raise UserError(f"results_preset.fidelity_sources: {', '.join(missing)} not in results_preset.interaction_sources "
                        f"(the figure's fidelity is the interaction benchmark's); add them there")


def copy_teacher(models: Path, folder: Path) -> None:
    """Copy the training's teacher checkpoint into a student variant's models folder, the teacher it distils."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(models / "teacher.ckpt", folder / "teacher.ckpt")


def variant_models(work: Path, name: str, k) -> Path:
    """The models folder of fidelity variant `name`, training seed k."""
    return work / "models" / "variants" / name / f"seed{k}"


def build_plan(cfg, work: Path):
    """The preset's jobs (Plan) and the planner batches' output folders {(scenario, row, seed k or None): folder}; the
    cooperation sweep's batches under scenario swept(level), of the first training alone."""
    from bench import candidates, interaction, step_time, verdicts
    from data import cli as data_cli
    from planner import cli as planner_cli
    from planner.setup import planner_config

    p = cfg.results_preset
    validate.check(cfg, PRESET)
    check_fidelity(p)
    fidelity = variants(p)
    if "mixed" in p.cooperation and p.cooperation_episodes > p.dense_episodes:
        raise UserError(f"results_preset.cooperation_episodes={p.cooperation_episodes}: the sweep's mixed level reads the "
                        f"headline's first worlds, and it has {p.dense_episodes} (results_preset.dense_episodes)")
    if p.oracle_episodes > p.dense_episodes:
        raise UserError(f"results_preset.oracle_episodes={p.oracle_episodes}: the oracle row drives the headline's first "
                        f"worlds, and it has {p.dense_episodes} (results_preset.dense_episodes)")
    data_dir, plan, batches = work / "data", Plan(), {}
    dataset_dir = data_dir / p.dataset
    plan.add("make-dataset", data_cli.run, job_config("make_dataset", [f"dataset={p.dataset}", f"out_dir={data_dir}",
                                                                       "plot_episodes=0"]))
    models = lambda k: work / "models" / f"seed{k}"
    first_seed = p.training_seeds[0]
    interaction_cfgs = {k: job_config("evaluate_interaction", [
        f"dataset={p.dataset}", f"models_dir={models(k)}", f"out_dir={work / 'interaction' / f'seed{k}'}",
        f"sources=[{','.join(s for s in p.interaction_sources if i == 0 or s in TRAINED)}]",  # untrained ones once
        *p.interaction]) for i, k in enumerate(p.training_seeds)}
    planner_seeds = check_seeds(cfg, interaction_cfgs[first_seed])
    judged = verdicts_config(cfg, work, models, fidelity)
    windows = candidates_config(cfg, work, {
        "planner": planner_seeds, "interaction benchmark": interaction_worlds(interaction_cfgs[first_seed]),
        "verdicts job": check_verdicts(judged, planner_seeds, interaction_cfgs[first_seed])})
    step = None
    if windows is not None:
        plan.add("candidates", candidates.run, windows)
        step = (Path(windows.out_dir) / windows.name, list(p.student_step))
    for k in p.training_seeds:
        add_training(plan, f"seed {k}", k, p.dataset, dataset_dir, models(k), work / "runs", p, seed=k, iterates=p.iterates,
                     step=step)
    for v in fidelity:  # the graded trainings, first training seed alone; a student variant distils that training's teacher
        folder = variant_models(work, v.name, first_seed)
        if v.model == "student":
            plan.add(f"copy teacher {v.name}", copy_teacher, models(first_seed), folder)
        add_training(plan, f"{v.name} seed {first_seed}", f"{v.name}-{first_seed}", p.dataset, dataset_dir, folder,
                     work / "runs", {v.model: [*p[v.model], *v.overrides]}, seed=first_seed, surrogate=False,
                     trained=(v.model,), step=step)
    for k in p.training_seeds:
        plan.add(f"evaluate-interaction seed {k}", interaction.run, interaction_cfgs[k])
    for v in fidelity:
        plan.add(f"evaluate-interaction {v.name}", interaction.run, job_config("evaluate_interaction", [
            f"dataset={p.dataset}", f"models_dir={variant_models(work, v.name, first_seed)}",
            f"out_dir={work / 'interaction' / v.name}", f"sources=[{v.model}]", *p.interaction]))
    plan.add("verdicts", verdicts.run, judged)  # good_kept: one job, every training and variant judged on the same states
    options = mpc_overrides(p.mpc_options)
    every, first = list(p.training_seeds), list(p.training_seeds[:1])
    runs = [("dense", s, p.dense_episodes, extra, every) for extra in options for s in p.sources] + \
        [("random", s, p.episodes, [], every) for s in p.sources] + \
        [(sc, s, p.table2_episodes, extra, every) for sc in p.scenarios for extra in options for s in p.table2_sources] + \
        [(swept(c), s, p.cooperation_episodes, extra, first) for c in fresh_levels(p) for extra in options for s in p.sources] + \
        [("dense", "oracle", p.oracle_episodes, extra, first) for extra in oracles(p)]
    # the fidelity figure's rows: the headline's `<source> interactive` where it runs, else a batch of their own on its worlds
    runs += [r for r in (("dense", s, p.dense_episodes, INTERACTIVE, every) for s in p.fidelity_sources) if r not in runs]
    runs += [("dense", v.name, p.dense_episodes, INTERACTIVE, first) for v in fidelity]
    model_of = {v.name: v.model for v in fidelity}  # a variant's row: its model's gradient source, from its own folder
    starts = {}  # {batches' scenario key: their per-step CSVs' templates}, the ceiling's recorded starts
    for key, source, episodes, extra, trainings in runs:
        scenario, *level = key.split(" cooperation=")
        for k in trainings if source in TRAINED or source in model_of else [None]:
            row = label(source, extra)
            folder = work / "planner" / key.replace(" cooperation=", "_") / row / (f"seed{k}" if k is not None else "untrained")
            batches[key, row, k] = folder
            trained = variant_models(work, source, k) if source in model_of else models(p.training_seeds[0] if k is None else k)
            overrides = [f"gradients={model_of.get(source, source)}", "method=both", *extra,
                         *(f"scenario.cooperation={c}" for c in level), f"episodes={episodes}", f"seed={cfg.planner_seed}",
                         f"models_dir={trained}", f"out_dir={folder}", "plots=false",
                         f"n_jobs={cfg.n_jobs}", f"backend={cfg.backend}", f"ray.address={cfg.ray.address or 'null'}", *p.planner]
            job = planner_config(scenario, overrides)
            plan.add(f"planner {key} {row}" + (f" seed {k}" if k is not None else ""), planner_cli.run, job)
            # each method's per-step CSVs (planner/batch.py), the methods as the planner reads them
            starts.setdefault(key, []).extend(str(folder / "steps" / f"{m}_{{seed}}.csv") for m in job.method)
    # after every batch: their runs are the ceiling's further starts, so no run can beat it on its world
    for scenario, worlds in ceiling_worlds(p).items():
        extra = [f"blind.episodes={p.blind_episodes}"] if scenario == "dense" else []
        plan.add(f"ceiling {scenario}", ceiling.run,
                 ceiling_config(cfg, [f"scenario={scenario}", f"episodes={worlds}", f"out_dir={work / 'ceiling'}", *extra],
                                starts.get(scenario, [])))
    for c in fresh_levels(p):
        plan.add(f"ceiling {swept(c)}", ceiling.run, ceiling_config(cfg, [
            "scenario=dense", f"scenario.cooperation={c}", f"episodes={p.cooperation_episodes}",
            f"out_dir={work / 'ceiling' / f'dense_{c}'}"], starts[swept(c)]))
    if p.bench is not None:
        plan.add("bench step time", step_time.run, job_config("bench", [
            f"models_dir={models(p.training_seeds[0])}", f"states.path={work / 'bench' / 'states.npz'}", *p.bench]))
    show = OmegaConf.from_dotlist(list(p.showcase)).get("scenario", "two_lane")
    plan.add("showcase", planner_cli.run, planner_config(show, [
        "method=both", f"seed={cfg.planner_seed}", f"models_dir={models(p.training_seeds[0])}",
        f"out_dir={work / 'showcase'}", *[o for o in p.showcase if not o.startswith("scenario=")], *p.planner]))
    return plan, batches


def ceiling_config(cfg, overrides: list, starts: list):
    """A `ceiling` job on the planner's held-out worlds with `overrides` and the preset's, on the batches' backend, with
    the recorded runs' per-step CSV templates `starts`."""
    job = job_config("ceiling", [*overrides, f"seed={cfg.planner_seed}", f"n_jobs={cfg.n_jobs}", f"backend={cfg.backend}",
                                 f"ray.address={cfg.ray.address or 'null'}", *cfg.results_preset.ceiling])
    job.starts = starts  # set, not an override: the folders' names have spaces ("cv courteous")
    return job


def swept(level: str) -> str:
    """The batches' and ceiling's key of a cooperation level of the sweep on dense worlds: "dense cooperation=willing"."""
    return f"dense cooperation={level}"


def fresh_levels(p) -> list[str]:
    """The sweep's levels that run batches of their own: mixed, the dense scenario's own drivers, is the headline's."""
    return [c for c in p.cooperation if c != "mixed"]


def label(source: str, extra: list) -> str:
    """A batch's row name: the gradient source, with its conf/mpc/ option when not the paper's ("student courteous") and
    the cars it sees when not the planner's ("oracle interactive 8 cars")."""
    mpc = [o.split("=", 1)[1] for o in extra if o.startswith("mpc=")]
    seen = [f"{o.split('=', 1)[1]} cars" for o in extra if o.startswith("n_slots=")]
    return " ".join([source, *mpc, *seen])


def mpc_overrides(options) -> list[list[str]]:
    """The planner overrides of each kind of row: none (the paper's step), then each conf/mpc/ option, ADMM alone."""
    return [[], *([f"mpc={m}", "method=admm"] for m in options)]


def with_options(sources, options) -> list[str]:
    """Row names of sources with the paper's step, then with each conf/mpc/ option ("student courteous")."""
    return [label(s, extra) for extra in mpc_overrides(options) for s in sources]


def dense_sources(p) -> list[str]:
    """Row names of the preset p's dense batches: with_options's, then the oracle's interactive step where it runs."""
    return with_options(p.sources, p.mpc_options) + [label("oracle", extra) for extra in oracles(p)]


def oracles(p) -> list[list[str]]:
    """The planner overrides of the preset p's oracle rows: ORACLE with the planner's perception, then seeing each of
    oracle_n_slots nearest cars (the world as predictor takes any number; the trained models take the dataset's)."""
    return [ORACLE, *(ORACLE + [f"n_slots={n}"] for n in p.oracle_n_slots)] if p.oracle_episodes > 0 else []
