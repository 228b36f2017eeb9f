"""Typed, range-checked job configs: one declarative schema per command, checked right after Hydra composed it.

`check(cfg, "planner")` raises one UserError "key=value: must be ..." for the first value outside its schema. A schema
maps a dotted key to a rule; a rule's `optional` lets the key be absent (keys only some config-group options have).
"""
import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from core.jobs import CONF_DIR, UserError, options

SEED_MAX = 2**32 - 1  # numpy and Lightning seeds are unsigned 32-bit
# Sizes bounded where memory or time would explode, each far above any recipe here (issue 74, S1):
MAX_T_P = 200  # steps: a dense cv step cost about 16, 41 and over 300 CPU-s at T_p 100, 200, 300 (ADMM's QPs grow as T_p^3)
MAX_EPISODES = 100_000  # a batch or a dataset holds every episode's records in memory
MAX_STEPS = 10_000  # steps of one episode (2000 s at dt 0.2 s), each step's record held
MAX_T_OBS = 21  # observed steps of a window
MAX_SLOTS = 50  # other cars in a window (the dense stream has 21 cars)
MAX_ITERS = 10_000  # solver iterations of one solve (ADMM's, a Z-step's): 50 ADMM iterations cost 20 CPU-s at T_p 200
MAX_SAMPLES = 1_000_000  # windows or states a job draws at once (a surrogate's Jacobian label: 6.4 kB at the default window)
MAX_FOLLOWERS = 1000  # cars of a dense stream (20 here): 10^7 drew 9 GB of drivers before its first step
MAX_WIDTH = 4096  # units of one network layer (256 the widest here): a teacher of 10^6 asked torch for 12 TB
MAX_DEPTH = 16  # layers of one network (3 the deepest here)
CORES = len(os.sched_getaffinity(0))  # the cores this process may run on: one worker process each, every worker its own models


@dataclass(frozen=True)
class Int:
    """An integer (not a bool) in [lo, hi], not one of `but`."""

    lo: int | None = None
    hi: int | None = None
    but: tuple = ()
    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return isinstance(v, int) and not isinstance(v, bool) and _within(v, self.lo, self.hi, False, False) and v not in self.but

    def allowed(self):
        return "an integer" + _bounds(self.lo, self.hi, False, False) + (f", not {', '.join(map(str, self.but))}" if self.but else "")


@dataclass(frozen=True)
class Real:
    """A number in the interval from lo to hi, each end open or closed."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    finite: bool = True  # false: +-inf allowed (never NaN)
    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return _number(v) and (math.isfinite(v) if self.finite else not math.isnan(v)) and _within(v, self.lo, self.hi, self.lo_open, self.hi_open)

    def allowed(self):
        return "a number" + _bounds(self.lo, self.hi, self.lo_open, self.hi_open)


@dataclass(frozen=True)
class OneOf:
    """One of a fixed set of values."""

    choices: tuple
    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return isinstance(v, (str, int, float)) and not isinstance(v, bool) and v in self.choices

    def allowed(self):
        return "one of " + ", ".join(repr(c) if c == "" else str(c) for c in self.choices)


@dataclass(frozen=True)
class Either:
    """A value one of `rules` accepts."""

    rules: tuple
    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return any(r.ok(v) for r in self.rules)

    def allowed(self):
        return " or ".join(r.allowed() for r in self.rules)


@dataclass(frozen=True)
class Bool:
    """true or false."""

    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return isinstance(v, bool)

    def allowed(self):
        return "true or false"


@dataclass(frozen=True)
class Text:
    """A non-empty string (a name or a path)."""

    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return isinstance(v, str) and v.strip() != ""

    def allowed(self):
        return "a non-empty string"


@dataclass(frozen=True)
class Name:
    """A single path component (a folder or file name inside an output folder): not '.', '..', nor holding a separator."""

    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return isinstance(v, str) and v.strip() != "" and v not in (".", "..") and "/" not in v and "\\" not in v

    def allowed(self):
        return "a single folder name (no '/', not '.' or '..')"


@dataclass(frozen=True)
class Range:
    """[low, high] with lo <= low <= high <= hi (low < high when strict)."""

    lo: float | None = None
    hi: float | None = None
    strict: bool = False
    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return isinstance(v, (list, tuple)) and len(v) == 2 and all(_number(x) and math.isfinite(x) for x in v) \
            and (v[0] < v[1] if self.strict else v[0] <= v[1]) and all(_within(x, self.lo, self.hi, False, False) for x in v)

    def allowed(self):
        return f"[low, high] with low {'<' if self.strict else '<='} high, both numbers" + _bounds(self.lo, self.hi, False, False)


@dataclass(frozen=True)
class ListOf:
    """A list of values each obeying `item`, `length` long if given, at least `at_least` and at most `at_most` long."""

    item: object
    length: int | None = None
    at_least: int = 0
    at_most: int | None = None
    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return isinstance(v, list) and (self.length is None or len(v) == self.length) and len(v) >= self.at_least \
            and (self.at_most is None or len(v) <= self.at_most) and all(self.item.ok(x) for x in v)

    def allowed(self):
        least, most = f" of at least {self.at_least}" if self.at_least else "", f" of at most {self.at_most}" if self.at_most else ""
        size = f" of {self.length}" if self.length else least + (most.replace(" of", " and") if least else most)
        return f"a list{size}, each {self.item.allowed()}"


@dataclass(frozen=True)
class Fractions:
    """`n` fractions in (0, 1) that sum to 1."""

    n: int
    optional: bool = False
    nullable: bool = False

    def ok(self, v):
        return isinstance(v, list) and len(v) == self.n and all(_number(x) and 0 < x < 1 for x in v) and abs(sum(v) - 1) < 1e-9

    def allowed(self):
        return f"{self.n} fractions in (0, 1) summing to 1"


def _number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _within(v, lo, hi, lo_open, hi_open):
    return (lo is None or (v > lo if lo_open else v >= lo)) and (hi is None or (v < hi if hi_open else v <= hi))


def _bounds(lo, hi, lo_open, hi_open):
    if lo is not None and hi is not None:
        return f" in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}"
    if lo is not None:
        return f" {'>' if lo_open else '>='} {lo}"
    if hi is not None:
        return f" {'<' if hi_open else '<='} {hi}"
    return ""


_MISSING = object()


def _value(cfg, key):
    """The resolved plain value at `key`, or _MISSING; a broken interpolation is the user's error."""
    v = cfg
    for part in key.split("."):
        if not isinstance(v, DictConfig) or part not in v:
            return _MISSING
        try:
            v = v[part]
        except Exception as e:  # omegaconf raises several types for a broken interpolation
            raise UserError(f"{key}: {type(e).__name__}: {str(e).splitlines()[0]}") from None
    return OmegaConf.to_container(v, resolve=True) if isinstance(v, (DictConfig, ListConfig)) else v


def rule(r):
    """A dataclass field whose value must obey rule r (check_fields): the constraint sits on the field it constrains."""
    return field(metadata={"rule": r})


def check_fields(obj, prefix: str) -> None:
    """Raise one UserError 'prefix.key=value: must be ...' for the first field of dataclass `obj` whose value breaks the
    rule its metadata names (rule())."""
    for f in fields(obj):
        r, v = f.metadata.get("rule"), getattr(obj, f.name)
        if r is None or (v is None and r.nullable):
            continue
        if not r.ok(v):
            raise UserError(f"{prefix}.{f.name}={'null' if v is None else v}: must be {r.allowed()}{' or null' if r.nullable else ''}")


def check(cfg: DictConfig, schema) -> None:
    """Raise one UserError 'key=value: must be ...' for the first key of `schema` (a name in SCHEMAS or a dict) out of range."""
    for key, rule in (SCHEMAS[schema] if isinstance(schema, str) else schema).items():
        v = _value(cfg, key)
        if v is _MISSING:
            if rule.optional:
                continue
            raise UserError(f"{key} is missing from the config: it must be {rule.allowed()}")
        if v is None and rule.nullable:
            continue
        if not rule.ok(v):
            shown = "null" if v is None else v
            raise UserError(f"{key}={shown}: must be {rule.allowed()}{' or null' if rule.nullable else ''}")
    if "scenario.road.lanes" in (SCHEMAS[schema] if isinstance(schema, str) else schema):
        check_scenario(cfg)


POS = Real(0, lo_open=True)  # > 0
NONNEG = Real(0)
PROB = Real(0, 1)
SEED = Int(0, SEED_MAX)
N_JOBS = Int(-1, CORES, but=(0,))  # joblib: -1 every core (of a Ray cluster too), never 0, never more processes than cores
HORIZON = Int(1, MAX_T_P)
WIDTH = Int(1, MAX_WIDTH)  # units of a layer
WIDTHS = ListOf(WIDTH, at_least=1, at_most=MAX_DEPTH)  # units of each layer
EPISODES = Int(1, MAX_EPISODES)
COST = ("lambda_div", "lambda_v", "lambda_delta", "lambda_a", "lambda_ddelta", "lambda_da")
# the predictors that load a trained model of their own from models_dir (conf/predictor/): the ones `distill` trains
TRAINED_PREDICTORS = tuple(n for n in options("predictor")
                           if "${models_dir}" in OmegaConf.to_yaml(OmegaConf.load(Path(CONF_DIR) / "predictor" / f"{n}.yaml")))
# of those, the ones that give one prediction, not one per hypothesis of yielding: what a surrogate learns
POINT_PREDICTORS = tuple(n for n in TRAINED_PREDICTORS if not n.endswith("_hyp"))

PAPER = {  # conf/paper/table1.yaml, shared by distill, surrogate and planner
    "paper.T_p": HORIZON, "paper.rho": POS, **{f"paper.cost.{k}": NONNEG for k in COST},
    "paper.safety.r": POS, "paper.safety.r_i": POS, "paper.safety.eps": NONNEG, "paper.lambda_s": NONNEG,
}

SCENARIO = {  # conf/scenario/: the physics and the courtesy threshold every scenario shares, the dense stream's promise
    "scenario.b_max": POS, "scenario.b_safe": POS, "scenario.merge_tol": POS, "scenario.x_ref": Real(), "scenario.platoon_x": Real(), "scenario.followers": Int(1, MAX_FOLLOWERS, optional=True),
    "scenario.min_behind_s": Real(0, optional=True), "scenario.safety_stretch": Real(1, optional=True),
    "scenario.road.lanes": Int(2), **{f"scenario.road.{k}": POS for k in ("lane_width", "car_length", "car_width")},
    **{f"scenario.params.{k}": POS for k in ("dt", "l_f", "l_r")}, "scenario.v_ref": NONNEG,
    "scenario.ego.x": Real(), "scenario.ego.y": Real(), "scenario.ego.psi": Real(), "scenario.ego.v": NONNEG,
    "scenario.lanes_choices": ListOf(Int(2), at_least=1, optional=True),  # a merge needs a lane to merge into
    **{f"scenario.{k}": Range(0, optional=True) for k in ("speed_range", "gap_factor_range", "v0_factor_range", "beside_range")},
    **{f"scenario.{k}": Range(optional=True) for k in ("ego_offset_range", "ego_dv_range")},
}


def check_scenario(cfg: DictConfig) -> None:
    """One UserError for a scenario whose values each pass SCENARIO but not together: the ego's start off the road
    (its narrowest: the fewest lanes it may draw) or at or past the end of its lane (x_ref: an episode of no step), or a
    fixed scenario without drivers."""
    sc = OmegaConf.to_container(cfg.scenario, resolve=True)
    if "ego_offset_range" in sc and "beside_range" not in sc:  # random: beside the platoon's front car, offset drawn
        start, key = sc["platoon_x"] + sc["ego_offset_range"][1], "scenario.platoon_x + scenario.ego_offset_range[1]"
    else:  # fixed and dense: where scenario.ego puts it
        start, key = sc["ego"]["x"], "scenario.ego.x"
    if not start < sc["x_ref"]:
        raise UserError(f"scenario.x_ref={sc['x_ref']:g}: the ego's lane must end ahead of its start ({key} = {start:g} m), "
                        "or an episode ends before its first step")
    lanes = min(sc.get("lanes_choices") or [sc["road"]["lanes"]])
    half, y = sc["road"]["lane_width"] / 2, sc["ego"]["y"]
    if not -half <= y <= (lanes - 1) * 2 * half + half:
        raise UserError(f"scenario.ego.y={y}: the ego must start on the road, y in [{-half:g}, {(2 * lanes - 1) * half:g}] m "
                        f"({lanes} lanes of {2 * half:g} m)")
    if not sc.get("drivers") and "driver_ranges" not in sc:
        raise UserError(f"scenario.drivers={sc.get('drivers')}: scenario={sc['name']} needs at least one driver to merge among")

DATASET = {
    "dataset.name": Name(), "dataset.episodes": EPISODES, "dataset.steps": Int(2, MAX_STEPS), "dataset.T_obs": Int(2, MAX_T_OBS),
    "dataset.n_slots": Int(1, MAX_SLOTS),
    "dataset.seed": SEED, "dataset.split": Fractions(3), "dataset.n_jobs": N_JOBS,
}

MAKE_DATASET = {
    **DATASET, **PAPER, **SCENARIO, "out_dir": Text(), "plot_episodes": Int(0),
    **{f"dataset.policy.{k}": PROB for k in ("p_keep_lane", "p_reckless")},
    **{f"dataset.policy.{k}": Range(0) for k in ("t_start", "y_nudge", "hold", "retry_after", "need_dx", "v_change_t",
                                                  "align_gain", "k_y")},
    **{f"dataset.policy.{k}": Range() for k in ("dv_cruise", "dv_cruise2")},
    "dataset.branches.points": Int(0, MAX_STEPS), "dataset.branches.reach": POS, "dataset.branches.steps": HORIZON,
    "dataset.branches.y_push": Range(0), "dataset.branches.dv": Range(0), "dataset.branches.cut_in": Bool(),
    "dataset.branches.flip": Bool(optional=True), "dataset.branches.y_lean": Range(0, optional=True),
}

TRAINER = {
    "trainer.max_epochs": Int(1), "trainer.devices": Int(1), "trainer.log_every_n_steps": Int(1),
    "trainer.accelerator": OneOf(("cpu", "gpu", "cuda", "mps", "auto")), "trainer.enable_progress_bar": Bool(optional=True),
    "trainer.gradient_clip_val": Real(0, optional=True, nullable=True),
    "trainer.callbacks.early_stopping.patience": Int(0, optional=True),
}

DISTILL = {
    **TRAINER, **PAPER, "model.name": OneOf(("teacher", "student", "teacher_hyp", "student_hyp")), "model.epochs": Int(1), "seed": SEED, "threads": Int(1, nullable=True),
    "eval_split": OneOf(("train", "val", "test")), "dataset_dir": Text(), "eval_dir": Text(), "models_dir": Text(), "run_dir": Text(),
    "ckpt_path": Text(nullable=True), "init_from": Text(nullable=True), "dataset.name": Name(),
    "model.data.batch_size": Int(1), "model.task.lr": POS, "model.task.weight_decay": NONNEG, "model.task.scale_m": POS,
    "model.teacher": OneOf(("teacher", "teacher_hyp"), optional=True),
    **{f"model.task.{k}": Real(0, optional=True) for k in ("jac_weight", "ego_jac_weight", "spectral_weight", "rollout_weight", "contrast_weight",
                                                              "cert_weight", "brake_weight", "belief_weight")},
    **{f"model.task.{k}": Real(0, lo_open=True, optional=True) for k in ("rollout_scale_m", "brake_scale", "dt")},
    "model.data.horizon": Int(1, MAX_T_P, optional=True),
    **{f"model.net.{k}": Either((WIDTH, WIDTHS), optional=True) for k in ("hidden", "pool", "decoder", "belief")},  # the nets' layer sizes
    "model.data.perturbed_copies": Int(0, optional=True), "model.data.contrast_groups": Int(0, optional=True),
    "model.data.rollout_groups": Int(0, optional=True), "model.data.projections": Int(1, optional=True),
    "model.data.hard_braking": Real(0, lo_open=True, optional=True), "model.data.hard_weight": Real(0, lo_open=True, optional=True),
    "model.data.whole_weight": Real(0, lo_open=True, optional=True),
    "model.data.encroached_weight": Real(0, optional=True),
    "model.data.fraction": Real(0, 1, lo_open=True, optional=True),
    "model.certificate.samples": Int(1, MAX_SAMPLES, optional=True), "model.certificate.fd_step_m": Real(0, lo_open=True, optional=True),
    "model.certificate.rho_used": Real(0, lo_open=True, optional=True), "model.certificate.T_p": Int(1, MAX_T_P, optional=True),
    "model.certificate.planner.v_max": Real(0, lo_open=True, optional=True),
    "model.certificate.planner.y_margin": Real(0, optional=True),
}

SURROGATE = {
    **PAPER, "source": OneOf(POINT_PREDICTORS), "jacobian": OneOf(("autodiff", "central")), "central_h": POS, "fused": Bool(),
    "dataset_dir": Text(), "models_dir": Text(), "seed": SEED,
    **{f"data.{k}": Int(1, MAX_SAMPLES) for k in ("dataset_windows", "plan_states", "val_dataset_windows", "val_plan_states",
                                                  "test_plan_states", "batch_size", "state_batch")},
    "network.hidden": Int(1, MAX_WIDTH), "network.depth": Int(1, MAX_DEPTH), "network.absolute": OneOf(("", "y", "xy")),
    "module.lr": POS, "module.weight_decay": NONNEG, "module.composed": NONNEG, "data.iterates": Text(nullable=True), "data.iterate_states": Int(1, MAX_SAMPLES), "data.test_iterate_episodes": Int(1),
    "trainer.max_epochs": Int(1), "trainer.devices": Int(1), "trainer.log_every_n_steps": Int(1),
    "timing.repeats": Int(1), "timing.budget_s": POS, "timing.predictors": ListOf(OneOf(POINT_PREDICTORS)),
    "states.T_p": HORIZON, "states.shift_x": NONNEG, "states.shift_y": NONNEG, "states.p_shift": PROB,
    "states.p_mid_lane_change": PROB, "states.lane_width": POS, "states.plan_y": Real(), "states.speed_factor": Range(0),
    "states.jitter": NONNEG, "states.p_jitter": PROB,
}

PLANNER = {  # the keys of a group option other options lack are optional (zstep, gradients, method, predictor)
    **PAPER, **SCENARIO, "world": OneOf(("reactive", "predictor")), "linearize": OneOf(("last_observed", "along_plan")), "seed": SEED,
    "episodes": Int(0, MAX_EPISODES), "n_jobs": N_JOBS, "backend": OneOf(("loky", "ray")), "ray.address": Text(nullable=True),
    "models_dir": Text(), "out_dir": Text(nullable=True), "max_steps": Int(1, MAX_STEPS),
    "T_obs": Int(2, MAX_T_OBS), "n_slots": Int(1, MAX_SLOTS), "plots": Bool(), "record_dir": Text(nullable=True), "tolerate_crashes": Bool(),
    # mpc: the values planner.mpc.Settings and planner.strategy check on their fields, but for the nodes they take whole
    "mpc.admm.rho": Either((POS, OneOf(("certified",)))), "mpc.strategy.horizon": Int(1, MAX_T_P, optional=True),
    "zstep.settings.reuse_radius": Real(0, optional=True),
    **{f"zstep.settings.{k}": Int(1, MAX_ITERS, optional=True) for k in ("max_iters", "maxit")},
    **{f"zstep.settings.{k}": Real(0, lo_open=True, optional=True) for k in (
        "trust_radius", "min_radius", "max_radius", "tol", "slack_penalty", "slack_tol", "opt_tol", "viol_ineq_tol", "mu0",
        "infeasible_tol")},
    "zstep.settings.mode": OneOf(("hard", "penalty"), optional=True), "zstep.settings.lambda_s": Real(0, optional=True),
    "zstep.settings.limited_mem_size": Int(0, optional=True), "zstep.settings.warm_hessian": Bool(optional=True),
    "zstep.settings.maxclocktime": Real(0, lo_open=True, finite=False, optional=True),
    "gradients.h": Real(0, lo_open=True, optional=True),
    "method.nnmpc.lengths": ListOf(POS, optional=True), "method.nnmpc.accels": ListOf(Real(), optional=True),
    **{f"predictor.{k}": Real(0, lo_open=True, optional=True) for k in ("d_react", "s_lat", "s_ahead", "view", "s_view")},
    "predictor.slowdown": Real(0, optional=True), "predictor.knows": OneOf(("all", "seen", "prior"), optional=True),
}

GRADIENT_OPTIONS = OneOf(tuple(options("gradients")))  # a gradient source: an option of conf/gradients/
OVERRIDES = ListOf(Text())  # Hydra overrides passed on to a job

RESULTS = {
    **PAPER, "out_dir": Text(), "work_dir": Text(), "n_jobs": N_JOBS, "backend": OneOf(("loky", "ray")),
    "ray.address": Text(nullable=True), "planner_seed": SEED, "bootstrap.resamples": Int(1), "bootstrap.seed": SEED,
    "results_preset.name": Text(), "results_preset.dataset": OneOf(tuple(options("dataset"))),
    "results_preset.training_seeds": ListOf(SEED, at_least=1),
    **{f"results_preset.{k}": OVERRIDES for k in ("teacher", "student", "surrogate", "iterates", "planner", "interaction", "showcase")},
    "results_preset.bench": ListOf(Text(), nullable=True), "results_preset.candidates": ListOf(Text(), nullable=True),
    "results_preset.student_step": OVERRIDES,
    **{f"results_preset.{k}": ListOf(GRADIENT_OPTIONS) for k in ("sources", "table2_sources")},
    "results_preset.scenarios": ListOf(OneOf(tuple(options("scenario")))),
    "results_preset.episodes": EPISODES, "results_preset.table2_episodes": EPISODES,
    "results_preset.interaction_sources": ListOf(OneOf((*GRADIENT_OPTIONS.choices, "reference", "follower"))),
    "results_preset.dense_episodes": EPISODES, "results_preset.calibration_episodes": EPISODES,
    "results_preset.blind_episodes": Int(0, MAX_EPISODES),
    "results_preset.calibration": ListOf(OneOf(tuple(options("scenario")))), "results_preset.ceiling": OVERRIDES,
}

COMPARE = {
    "out_dir": Text(), "experiment": Text(), "columns": ListOf(Text(), at_least=1), "ignore": ListOf(Text()),
}

BENCH = {
    "models_dir": Text(), "threads": Int(1), "states.path": Text(), "states.per_scenario": Int(1),
    "states.gradients": GRADIENT_OPTIONS, "states.seed": SEED, "states.dense_seed": SEED, "states.dense_worlds": Int(1),
    "step_time.repeats": Int(1), "step_time.courteous": ListOf(GRADIENT_OPTIONS),
    "step_time.interactive": ListOf(GRADIENT_OPTIONS),
    "step_time.profile": ListOf(GRADIENT_OPTIONS), "zstep_compare.per_scenario": Int(0),
    "step_time.horizon.T_p": HORIZON, "step_time.horizon.sources": ListOf(GRADIENT_OPTIONS),
    "zstep_compare.sources": ListOf(GRADIENT_OPTIONS), "step_time.ipopt": ListOf(GRADIENT_OPTIONS),
    "step_time.ratios": ListOf(ListOf(OneOf((*GRADIENT_OPTIONS.choices, "floor")), 2)),
}

CEILING = {
    **SCENARIO, "world": OneOf(("reactive", "predictor")), "seed": SEED, "episodes": EPISODES, "n_jobs": N_JOBS,
    "max_steps": Int(1, MAX_STEPS), "out_dir": Text(nullable=True), "search.gaps": Int(0),
    "search.y_lean": ListOf(POS, at_least=1), "search.clearance": ListOf(NONNEG, at_least=1), "search.settle": Int(0),
    "search.enter": ListOf(Int(0)), "search.dv": ListOf(Real()),
    "search.y_wait": ListOf(Real(), at_least=1), "search.accept_dv": ListOf(Real()), "blind.seed": SEED,
    "blind.episodes": Int(0, MAX_EPISODES),
}

CROSS_WORLD = {
    "worlds": ListOf(OneOf(tuple(options("scenario"))), at_least=1),
    **{k: OVERRIDES for k in ("teacher", "student", "surrogate", "planner", "ceiling")},
    "sources": ListOf(GRADIENT_OPTIONS, at_least=1), "nnmpc": ListOf(GRADIENT_OPTIONS), "seed": SEED, "n_jobs": N_JOBS,
    "bootstrap.resamples": Int(1), "bootstrap.seed": SEED, "out_dir": Text(), "work_dir": Text(),
}

SCHEMAS = {"make_dataset": MAKE_DATASET, "distill": DISTILL, "surrogate": SURROGATE, "planner": PLANNER, "results": RESULTS,
           "compare": COMPARE, "bench": BENCH, "ceiling": CEILING, "cross_world": CROSS_WORLD}
