"""`make bench`: wall time (ms) of one ADMM-NNMPC step per gradient source on the saved planning states, single-threaded,
beside the QP floor (the same ADMM with the safety linearisation frozen: no network calls, driven from Python as the
surrogate's and the teacher's solves are; cv and the student solve in one compiled call, below it) and the full-NLP baseline
(`solver=ipopt`: the same step as one CasADi NLP solved by IPOPT, from the same start) for every predictor it can write
(cv, analytic, student), with ADMM's speed-up over it and the cost gap; some sources also at a longer horizon
(`<source>-T16`) and with the multi-start
steps (`<source>-courteous`, `<source>-interactive`: mpc=courteous, mpc=interactive); each row also per scenario family of the states (two_lane, three_lane, held-out
dense worlds); then a profile of where a step's time goes (the one-call ADMM solve, other compiled kernels, DAQP solves,
Python), the paper step's of step_time.profile and the multi-start steps' of step_time.courteous and .interactive, each also split in
three (compiled solve, predictor calls, Python); logged to MLflow (`bench`).

    python -m bench.step_time [step_time.repeats=3] [states.per_scenario=15] [models_dir=models]   (conf/bench.yaml)

Sources are timed round-robin state by state, so a busy machine slows them alike and the ratios stay fair (the
-courteous, -interactive and -T16 rows are timed after them, round-robin among themselves); repeats pass over all the states again.
The cost gap
is (J_ADMM - J_IPOPT) / |J_IPOPT| on the states where neither fell back and J_IPOPT >= GAP_FLOOR (each solver's J of its
own plan; ADMM's satisfies the dynamics only to planner.admm.TOL_F, so it can come out below IPOPT's).
"""
import cProfile
import logging
import pstats
import re
import time
from collections import defaultdict
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig
from threadpoolctl import threadpool_limits

from bench.states import collect_kwargs, planning_states, settings, solver_step
from core import validate
from core.jobs import CONF_DIR, UserError, console, guarded, mlflow_run, open_experiment
from core.rollout import ego_xy
from planner import mpc
from planner.gradients import Source, available, source_class
from planner.setup import build, make, planner_config

log = logging.getLogger(__name__)
GAP_FLOOR = 1e-3  # J below which a relative cost gap means nothing (the plan is at the references)
MULTI = ("courteous", "interactive")  # the multi-start steps (conf/mpc/ options), each timed for the sources of
# step_time.<option> as rows <source>-<option>, beside that source's paper step


class Frozen(Source):
    """The QP floor's source: rollout values affine in the ego plan about one linearisation, Jacobian fixed (m, m/m)."""

    def __init__(self, values, grads, ego):
        super().__init__("floor", None)
        self.values0, self.grads, self.ego0 = values, grads, ego

    def values(self, history, ego_futures):
        """values0 + d values / d ego . (ego - ego0), (B, T_p, SLOTS, 2)."""
        d = np.asarray(ego_futures, float) - self.ego0
        return self.values0 + np.einsum("tmkse,bse->btmk", self.grads, d)

    def jacobian(self, history, ego_future):
        """The affine values and the frozen Jacobian (T_p, SLOTS, 2, T_p, 2)."""
        return self.values(history, np.asarray(ego_future)[None])[0], self.grads


def freeze(source, s: mpc.Settings, state) -> Frozen:
    """`source` linearised once at the plan an MPC step starts from (shifted warm start, or zero inputs rolled out)."""
    if state.warm is None:
        Z = mpc.simulate(state.obs.z0, np.zeros(s.T_p), np.zeros(s.T_p), s.params)
    else:
        Z = mpc.shift(state.warm).Z
    ego = ego_xy(Z, s.T_p)
    return Frozen(*source.jacobian(state.obs.history, ego), ego)


def log_bench(run_name, cfg: DictConfig, srcs: dict, n_states: int, metrics: dict):
    """One MLflow run in experiment `bench`: the bench config, each source's predictor, the metrics."""
    import mlflow

    predictors = {f"predictor_{n}": s.predictor.name for n, s in srcs.items()}
    with mlflow_run("bench", cfg, run_name=run_name, n_states=n_states, **predictors):
        mlflow.log_metrics(metrics)


def source(gradients, models_dir, *overrides):
    """The gradient source the `planner` command builds for `gradients=...` (conf/gradients/) over models_dir."""
    return make("two_lane", [f"gradients={gradients}", f"models_dir={models_dir}", *overrides])[1]


def sources(models_dir) -> dict:
    """Every gradient source that runs outside the closed loop (conf/gradients/, the oracle not), over the trained
    models; the ones that differentiate any predictor (teacher autodiff, fd) over the analytic predictor (with its exact
    Jacobians as `analytic`) where the models are missing, the others then skipped."""
    out = {}
    for name in available(needs_world=False, hypotheses=False):
        try:
            out[name] = source(name, models_dir)  # onnxruntime sessions run on one thread already
        except UserError as e:
            if source_class(name).differentiates:  # the same maths over the built-in predictor keeps the ratios meaningful
                out[name] = source(name, models_dir, "predictor=analytic")
            log.info(f"{name}: {e}" + ("; using the analytic predictor" if name in out else "; skipped"))
    if "analytic" in out and out["teacher"].predictor.name != "analytic":
        del out["analytic"]  # only a stand-in for missing models
    return out


def ipopt_steps(srcs: dict, names) -> dict:
    """{ipopt-<name>: (step, source)}: solver=ipopt's step (conf/solver/ipopt.yaml) for each source of `names` present;
    none without CasADi."""
    try:
        from planner.ipopt import import_casadi

        import_casadi()
    except UserError as e:
        log.info(f"ipopt: {e}; skipped")
        return {}
    step = build(planner_config("two_lane", ["solver=ipopt"]).solver.step)
    return {f"ipopt-{name}": (step, srcs[name]) for name in names if name in srcs}


def fastest(runs: dict, states, repeats: int) -> dict:
    """{name: (ms (n_states,), iterations, fallbacks, J (n_states,), NaN where it fell back, scenario family
    (n_states,))} of runs {name: run(i, state) -> StepResult}: the fastest of `repeats` passes over all the states, each
    pass round-robin over the runs state by state, so a busy machine slows them alike and no run meets a state it has
    just planned (a source's memo of the step's windows, the surrogate's, would make that repeat nearly free)."""
    ms = {name: np.full(len(states), np.inf) for name in runs}
    results = {name: [None] * len(states) for name in runs}
    for _ in range(repeats):
        for i, state in enumerate(states):
            for name, run in runs.items():
                t0 = time.perf_counter()
                results[name][i] = run(i, state)
                ms[name][i] = min(ms[name][i], 1e3 * (time.perf_counter() - t0))
    families = np.array([state.scenario for state in states])
    return {name: (ms[name], float(np.mean([r.iters for r in res])), sum(bool(r.fallback) for r in res),
                   np.array([np.nan if r.fallback else r.J for r in res]), families) for name, res in results.items()}


def time_steps(srcs: dict, states, repeats: int, others: dict | None = None) -> dict:
    """fastest's entries for srcs {name: source} (ADMM's step), the QP floor and others {name: (step, source)} (another
    solver's)."""
    floors = [freeze(srcs["teacher"], settings(state.scenario), state) for state in states]
    step = lambda state, src, solver=solver_step(): solver(settings(state.scenario), state.obs, src, state.warm)
    runs = {name: lambda i, state, src=src: step(state, src) for name, src in srcs.items()}
    runs["floor"] = lambda i, state: step(state, floors[i])
    runs.update({name: lambda i, state, src=src, solver=solver: step(state, src, solver)
                 for name, (solver, src) in (others or {}).items()})
    return fastest(runs, states, repeats)


def steps_with(srcs: dict, names, states, overrides: tuple, repeats: int, suffix: str) -> dict:
    """fastest's entries {<name><suffix>: ...} for the sources `names` with the planner overrides `overrides` (after
    one warm-up step each per scenario family: a new set-up pays on its first call, and composing a family's settings
    about 100 ms)."""
    runs = {f"{name}{suffix}": lambda i, state, src=srcs[name]: solver_step()(settings(state.scenario, overrides), state.obs,
                                                                               src, state.warm) for name in names}
    firsts = {state.scenario: i for i, state in reversed(list(enumerate(states)))}
    for run in runs.values():
        for i in firsts.values():
            run(i, states[i])
    return fastest(runs, states, repeats)


def variants(cfg: DictConfig, srcs: dict, states) -> dict:
    """The sources of cfg.step_time.<option> with mpc=<option> for each multi-start step of MULTI (`<name>-<option>`) and of cfg.step_time.horizon at its T_p
    (`<name>-T<T_p>`, on states collected at that horizon beside cfg.states.path)."""
    st, h = cfg.step_time, cfg.step_time.horizon
    out = {}
    for option in MULTI:
        out.update(steps_with(srcs, [n for n in st[option] if n in srcs], states, (f"mpc={option}",), st.repeats,
                              f"-{option}"))
    names = [n for n in h.sources if n in srcs]
    if names:
        overrides, path = (f"paper.T_p={h.T_p}",), Path(cfg.states.path)
        long = planning_states(path.with_name(f"{path.stem}_T{h.T_p}{path.suffix}"), **collect_kwargs(cfg),
                               overrides=overrides)
        out.update(steps_with(srcs, names, long, overrides, st.repeats, f"-T{h.T_p}"))
    return out


def cost_gap(J_admm, J_ipopt) -> np.ndarray:
    """(J_ADMM - J_IPOPT) / |J_IPOPT| on the states where both planned (no fallback) and J_IPOPT >= GAP_FLOOR."""
    ok = np.isfinite(J_admm) & np.isfinite(J_ipopt) & (np.abs(J_ipopt) >= GAP_FLOOR)
    return (J_admm[ok] - J_ipopt[ok]) / np.abs(J_ipopt[ok])


def kernels() -> set:
    """The profile keys (file, line, name) of the numba kernels (the ADMM solve's, the interactive search's): cProfile sees a dispatcher call as its
    Python function's, and a call of its compiled entry point (planner.admm.typed_call) as a built-in method's."""
    from planner import admm, daqp_qp, jit_chase, jit_interactive, jit_rollout, safety, zstep

    funcs = [f.py_func for m in (admm, daqp_qp, jit_chase, jit_interactive, jit_rollout, safety, zstep)
             for f in vars(m).values() if hasattr(f, "py_func")]
    return ({(f.__code__.co_filename, f.__code__.co_firstlineno, f.__name__) for f in funcs}
            | {("~", 0, f"<built-in method {f.__module__}.{f.__name__}>") for f in funcs})


def kernel_name(key) -> str:
    """The function name of a kernel's profile key (kernels)."""
    return key[2].removesuffix(">").rsplit(".", 1)[-1] if key[0] == "~" else key[2]


def part(key, compiled=frozenset()) -> str:
    """The part of an MPC step a profiled function belongs to: the one-call ADMM solve, DAQP solves called from Python,
    other compiled kernels (keys in `compiled`), its library, or its file in this repository (Python)."""
    file, _, name = key
    if key in compiled:
        return {"admm_loops": "ADMM solve, one compiled call (numba + DAQP)",
                "solve": "DAQP solves called from Python"}.get(kernel_name(key), "compiled kernels (numba)")
    if file == "~":  # a C function: name it by the extension it belongs to
        return next((lib for lib in ("onnxruntime", "osqp", "daqp", "torch") if lib in name), "numpy / builtins")
    if "site-packages/" in file:
        return file.split("site-packages/")[1].split("/")[0]
    tail = file.split("/")
    return "/".join(tail[-2:])


def profile(step, src, s_of, states) -> tuple[dict, dict]:
    """Where one source's MPC step spends its time: ({part: ms per step of own time}, {network calls, OSQP and DAQP
    solves, ADMM solves in compiled calls and those calls: per step}) under cProfile (which inflates Python-heavy parts; the split, not the total, is what it shows)."""
    from planner import admm as solver
    from planner import daqp_qp

    prof, solves, admm = cProfile.Profile(), int(daqp_qp.SOLVES[0]), int(solver.SOLVES[0])
    for state in states:
        prof.runcall(step, s_of(state.scenario), state.obs, src, state.warm)
    solves = int(daqp_qp.SOLVES[0]) - solves  # counted inside the compiled calls too, which cProfile cannot see into
    admm = int(solver.SOLVES[0]) - admm  # a compiled call may hold several solves (a multi-start step's)
    calls = defaultdict(float, {"DAQP solves": solves / len(states)} if solves else {})
    calls.update({"one-call ADMM solves": admm / len(states)} if admm else {})
    stats = pstats.Stats(prof).stats  # {(file, line, name): (primitive calls, calls, own s, cumulative s, callers)}
    ms, compiled = defaultdict(float), kernels()
    for key, (_, n, own, _, _) in stats.items():
        ms[part(key, compiled)] += 1e3 * own / len(states)
        if key[2] == "run" and "onnxruntime" in key[0]:  # InferenceSession.run, once per call (its C parts are not)
            calls["onnxruntime calls"] += n / len(states)
        if key[0] == "~" and "solve" in key[2] and "osqp" in key[2]:
            calls["OSQP solves"] += n / len(states)
        if key in compiled and kernel_name(key) == "admm_loops":
            calls["compiled ADMM calls"] += n / len(states)
        if key in compiled and kernel_name(key) == "solve":
            calls["DAQP solves called from Python"] += n / len(states)
    return dict(sorted(ms.items(), key=lambda kv: -kv[1])), dict(calls)


COMPILED = ("ADMM solve, one compiled call (numba + DAQP)", "DAQP solves called from Python", "compiled kernels (numba)",
            "daqp", "osqp")  # the parts that are solver code (a compiled predictor's rollout runs inside them)
PREDICTOR = ("onnxruntime", "torch", "distill/", "surrogate/")  # the parts (or their prefixes) that are a predictor's own


def split(ms: dict) -> dict:
    """A profile's own time per part (ms per step) in three: the compiled solve (numba, DAQP, OSQP; cv's and the
    student's rollouts run inside it), predictor calls (onnxruntime, torch, the predictors' Python) and the rest, Python."""
    out = dict.fromkeys(("compiled solve", "predictor calls", "Python"), 0.0)
    for k, v in ms.items():
        out["compiled solve" if k in COMPILED else "predictor calls" if k.startswith(PREDICTOR) else "Python"] += v
    return out


def profile_key(source: str, part_name: str) -> str:
    """The MLflow metric name of a profile entry: profile_<source>_<part>, characters MLflow refuses replaced by _."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", f"profile_{source}_{part_name}")


def profile_table(name: str, ms: dict, calls: dict, top: int = 8) -> str:
    """The printed profile: the `top` parts by own time per step, then the call counts."""
    total = sum(ms.values())
    lines = [f"profile of {name}'s step (cProfile, {total:.1f} ms per step under the profiler; own time per part):"]
    lines += [f"  {k:>32} {v:8.2f} ms {v / total:6.1%}" for k, v in list(ms.items())[:top]]
    lines += [f"  {k}: {v:.1f} per step" for k, v in calls.items() if v]
    lines.append("  split: " + ", ".join(f"{k} {v:.1f} ms ({v / total:.0%})" for k, v in split(ms).items()))
    return "\n".join(lines)


def multi_start(timings: dict) -> list:
    """[(<source>-<option>, <source>)]: each multi-start row (MULTI) with its source's paper step, the ratio issue 47
    targets."""
    paper = lambda name: re.sub(f"-({'|'.join(MULTI)})$", "", name)
    return [(name, paper(name)) for name in timings if paper(name) != name and paper(name) in timings]


def pairs(timings: dict, st: DictConfig) -> list:
    """The (a, b) of the ratios a/b to print and log: st.ratios, each also of the multi-start rows where a and b both have
    one (surrogate-interactive / student-interactive), then every multi-start row over its paper step (multi_start)."""
    extended = [(f"{a}-{m}", f"{b}-{m}") for a, b in st.ratios for m in MULTI if {f"{a}-{m}", f"{b}-{m}"} <= timings.keys()]
    return [*map(tuple, st.ratios), *extended, *multi_start(timings)]


def summary(timings: dict, st: DictConfig) -> dict:
    """MLflow metrics: <source>_ms_median, <source>_ms_p95, <source>_ms_p99 (the 200 ms control period's test; on a few
    dozen states, near their slowest), the first two also per scenario family (<source>_ms_median_<family>),
    <source>_iters_mean, <source>_fallbacks and the ratios of st.ratios, of the multi-start rows (multi_start) and of
    st.ipopt (cfg.step_time)."""
    out = {}
    for name, (ms, iters, falls, _, families) in timings.items():
        out.update({f"{name}_ms_median": float(np.median(ms)), f"{name}_ms_p95": float(np.percentile(ms, 95)),
                    f"{name}_ms_p99": float(np.percentile(ms, 99)),
                    f"{name}_iters_mean": iters, f"{name}_fallbacks": float(falls)})
        for family in np.unique(families):  # scenario families apart: dense states plan against more cars at once
            of = ms[families == family]
            out.update({f"{name}_ms_median_{family}": float(np.median(of)), f"{name}_ms_p95_{family}": float(np.percentile(of, 95))})
    for a, b in pairs(timings, st):
        if a in timings and b in timings:
            out[f"ratio_{a}_{b}"] = out[f"{a}_ms_median"] / out[f"{b}_ms_median"]
    for name in st.ipopt:
        if f"ipopt-{name}" in timings:
            gap = cost_gap(timings[name][3], timings[f"ipopt-{name}"][3])
            out[f"ratio_ipopt_{name}"] = out[f"ipopt-{name}_ms_median"] / out[f"{name}_ms_median"]
            out.update({f"gap_{name}_median": float(np.median(gap)) if len(gap) else np.nan, f"gap_{name}_states": float(len(gap)),
                        f"gap_{name}_ipopt_lower": float(np.sum(gap > 0))})
    return out


def table(timings: dict, srcs: dict, metrics: dict, states, st: DictConfig) -> str:
    """The printed result: one line per source (and the floor), then the ratios of st.ratios, of the multi-start rows
    and of st.ipopt."""
    lines = [f"{len(states)} planning states ({', '.join(sorted({state.scenario for state in states}))}), one thread, "
             f"fastest of {st.repeats}",
             f"{'source':>19} {'predictor':>10} {'median ms':>10} {'p95 ms':>10} {'p99 ms':>10} {'ADMM iters':>11} {'fallbacks':>10}"]
    for name in timings:
        base = re.sub(f"-({'|'.join(MULTI)}|T\\d+)$", "", name.removeprefix("ipopt-"))  # the source of ipopt-, -courteous, ... rows
        pred = srcs[base].predictor.name if base in srcs else "frozen"
        lines.append(f"{name:>19} {pred:>10} {metrics[f'{name}_ms_median']:>10.1f} {metrics[f'{name}_ms_p95']:>10.1f} {metrics[f'{name}_ms_p99']:>10.1f} "
                     f"{metrics[f'{name}_iters_mean']:>11.1f} {metrics[f'{name}_fallbacks']:>10.0f}")
    families = sorted({f for *_, fams in timings.values() for f in fams})
    lines.append(f"{'per family':>19} " + " ".join(f"{f + ' median / p95 ms':>24}" for f in families))
    for name in timings:
        lines.append(f"{name:>19} " + " ".join(f"{metrics[f'{name}_ms_median_{f}']:>13.1f} / {metrics[f'{name}_ms_p95_{f}']:<8.1f}"
                                               if f"{name}_ms_median_{f}" in metrics else f"{'-':>24}" for f in families))
    for a, b in pairs(timings, st):
        key = f"ratio_{a}_{b}"
        lines.append(f"{a}/{b}: " + (f"{metrics[key]:.1f}x" if key in metrics else f"n/a ({b if a in srcs else a} missing)"))
    firsts = {k.removesuffix("_first_ms"): v for k, v in metrics.items() if k.endswith("_first_ms")}
    if firsts:
        lines.append("first step in this process (the kernels from numba's cache, sessions and NLPs built): "
                     + ", ".join(f"{k} {v:.0f} ms" for k, v in firsts.items()))
    for name in st.ipopt:
        if f"ratio_ipopt_{name}" in metrics:
            m = lambda k: metrics[k.format(name)]
            lines.append(f"ADMM vs IPOPT, {name}: {m('{}_ms_median'):.1f} vs {m('ipopt-{}_ms_median'):.1f} ms median, "
                         f"IPOPT/ADMM time {m('ratio_ipopt_{}'):.2f} (> 1: ADMM faster); cost gap (J_ADMM - J_IPOPT)/J_IPOPT median "
                         f"{m('gap_{}_median'):+.2%} on {m('gap_{}_states'):.0f} states both planned "
                         f"(IPOPT lower on {m('gap_{}_ipopt_lower'):.0f})")
    return "\n".join(lines)


def single_threaded(cfg: DictConfig):
    """threadpoolctl's limit on the BLAS/OpenMP pools and torch's own, both to cfg.threads, for the block."""
    import torch

    torch.set_num_threads(cfg.threads)
    return threadpool_limits(limits=cfg.threads)


@guarded
def run(cfg: DictConfig) -> dict:
    """Collect or load the states, time every source and the floor, log the table and the ratios and to MLflow."""
    validate.check(cfg, "bench")
    open_experiment("bench")  # an unusable store fails now, not after the timing
    with single_threaded(cfg):
        states = planning_states(cfg.states.path, **collect_kwargs(cfg))
        srcs = sources(cfg.models_dir)
        others = ipopt_steps(srcs, cfg.step_time.ipopt)
        # warm-up: first calls pay for imports, loading the compiled kernels from numba's cache, allocations,
        # onnxruntime's graph setup and building the IPOPT NLPs; the very first step of each is reported
        first = {}
        for name, (step, src) in {**{n: (solver_step(), src) for n, src in srcs.items()}, **others}.items():
            for scenario in sorted({st.scenario for st in states}):
                st = next(st for st in states if st.scenario == scenario)
                t0 = time.perf_counter()
                step(settings(scenario), st.obs, src, st.warm)
                first.setdefault(f"{name}_first_ms", 1e3 * (time.perf_counter() - t0))
        timings = time_steps(srcs, states, cfg.step_time.repeats, others)
        timings.update(variants(cfg, srcs, states))
        profiles = {name: profile(solver_step(), srcs[name], settings, states) for name in cfg.step_time.profile
                    if name in srcs}
        for option in MULTI:  # the multi-start steps: where their time goes
            s_of = lambda scenario, o=option: settings(scenario, (f"mpc={o}",))
            profiles.update({f"{name}-{option}": profile(solver_step(), srcs[name], s_of, states)
                             for name in cfg.step_time[option] if name in srcs})
    metrics = {**summary(timings, cfg.step_time), **first}
    log.info("\n%s", table(timings, srcs, metrics, states, cfg.step_time))
    for name, (ms, calls) in profiles.items():
        log.info("\n%s", profile_table(name, ms, calls))
        metrics.update({profile_key(name, k): v for k, v in {**ms, **calls, **split(ms)}.items()})
    log_bench("step_time", cfg, srcs, len(states), metrics)
    return metrics


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="bench")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Console entry point (`python -m bench.step_time`)."""
    console("bench", hydra_main)


if __name__ == "__main__":
    main()
