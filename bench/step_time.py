"""`make bench`: wall time (ms) of one ADMM-NNMPC step per gradient source on the saved planning states, single-threaded,
beside the QP floor (the same ADMM with the safety linearisation frozen: no network calls), logged to MLflow (`bench`).

    python -m bench.step_time [step_time.repeats=3] [states.per_scenario=15] [models_dir=models]   (conf/bench.yaml)

Sources are timed round-robin state by state, so a busy machine slows them alike and the ratios stay fair.
"""
import logging
import time

import hydra
import numpy as np
from omegaconf import DictConfig
from threadpoolctl import threadpool_limits

from bench.states import planning_states, settings
from core.jobs import CONF_DIR, UserError, guarded, mlflow_run
from core.rollout import ego_xy
from planner import mpc
from planner.setup import make

log = logging.getLogger(__name__)
RATIOS = (("teacher", "surrogate"), ("teacher", "student"), ("surrogate", "floor"), ("student", "floor"))


class Frozen:
    """The QP floor's source: rollout values affine in the ego plan about one linearisation, Jacobian fixed (m, m/m)."""

    name = "floor"

    def __init__(self, values, grads, ego):
        self.values0, self.grads, self.ego0 = values, grads, ego

    def values(self, history, ego_futures):
        """values0 + d values / d ego . (ego - ego0), (B, T_p, M, 2)."""
        d = np.asarray(ego_futures, float) - self.ego0
        return self.values0 + np.einsum("tmkse,bse->btmk", self.grads, d)

    def jacobian(self, history, ego_future):
        """The affine values and the frozen Jacobian (T_p, M, 2, T_p, 2)."""
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
    """Every gradient source available: teacher (autodiff), student, surrogate, fd over the trained models; over the
    analytic predictor (with its exact Jacobians as `analytic`) for the ones whose models are missing."""
    out = {}
    for name in ("teacher", "student", "surrogate", "fd", "analytic"):
        try:
            out[name] = source(name, models_dir)  # onnxruntime sessions run on one thread already
        except UserError as e:
            if name in ("teacher", "fd"):  # the same maths over the built-in predictor keeps the ratios meaningful
                out[name] = source(name, models_dir, "predictor=analytic")
            log.info(f"{name}: {e}" + ("; using the analytic predictor" if name in out else "; skipped"))
    if "analytic" in out and out["teacher"].predictor.name != "analytic":
        del out["analytic"]  # only a stand-in for missing models
    return out


def time_steps(srcs: dict, states, repeats: int) -> dict:
    """{name: (ms (n_states,), ADMM iterations, fallbacks)}: the fastest of `repeats` runs of each step, round-robin."""
    reference = srcs["teacher"]
    ms = {name: [] for name in [*srcs, "floor"]}
    iters = {name: [] for name in ms}
    falls = {name: 0 for name in ms}
    for state in states:
        s = settings(state.scenario)
        per_state = {**srcs, "floor": freeze(reference, s, state)}
        for name, src in per_state.items():
            best = np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                result = mpc.mpc_step(s, state.obs, src, state.warm)
                best = min(best, 1e3 * (time.perf_counter() - t0))
            ms[name].append(best)
            iters[name].append(result.iters)
            falls[name] += bool(result.fallback)
    return {name: (np.array(ms[name]), float(np.mean(iters[name])), falls[name]) for name in ms}


def summary(timings: dict) -> dict:
    """MLflow metrics: <source>_ms_median, <source>_ms_p95, <source>_iters_mean, <source>_fallbacks and the ratios."""
    out = {}
    for name, (ms, iters, falls) in timings.items():
        out.update({f"{name}_ms_median": float(np.median(ms)), f"{name}_ms_p95": float(np.percentile(ms, 95)),
                    f"{name}_iters_mean": iters, f"{name}_fallbacks": float(falls)})
    for a, b in RATIOS:
        if a in timings and b in timings:
            out[f"ratio_{a}_{b}"] = out[f"{a}_ms_median"] / out[f"{b}_ms_median"]
    return out


def table(timings: dict, srcs: dict, metrics: dict, repeats: int, states) -> str:
    """The printed result: one line per source (and the floor), then the ratios."""
    lines = [f"{len(states)} planning states ({', '.join(sorted({st.scenario for st in states}))}), one thread, "
             f"fastest of {repeats}",
             f"{'source':>10} {'predictor':>10} {'median ms':>10} {'p95 ms':>10} {'ADMM iters':>11} {'fallbacks':>10}"]
    for name in timings:
        pred = srcs[name].predictor.name if name in srcs else "frozen"
        lines.append(f"{name:>10} {pred:>10} {metrics[f'{name}_ms_median']:>10.1f} {metrics[f'{name}_ms_p95']:>10.1f} "
                     f"{metrics[f'{name}_iters_mean']:>11.1f} {metrics[f'{name}_fallbacks']:>10.0f}")
    for a, b in RATIOS:
        key = f"ratio_{a}_{b}"
        lines.append(f"{a}/{b}: " + (f"{metrics[key]:.1f}x" if key in metrics else f"n/a ({b if a in srcs else a} missing)"))
    return "\n".join(lines)


def single_threaded(cfg: DictConfig):
    """threadpoolctl's limit on the BLAS/OpenMP pools and torch's own, both to cfg.threads, for the block."""
    import torch

    torch.set_num_threads(cfg.threads)
    return threadpool_limits(limits=cfg.threads)


@guarded
def run(cfg: DictConfig) -> dict:
    """Collect or load the states, time every source and the floor, log the table and the ratios and to MLflow."""
    with single_threaded(cfg):
        states = planning_states(cfg.states.path, per_scenario=cfg.states.per_scenario, gradients=cfg.states.gradients,
                                 seed=cfg.states.seed)
        srcs = sources(cfg.models_dir)
        for src in srcs.values():  # warm-up: first calls pay for imports, allocations and onnxruntime's graph setup
            mpc.mpc_step(settings(states[0].scenario), states[0].obs, src, states[0].warm)
        timings = time_steps(srcs, states, cfg.step_time.repeats)
    metrics = summary(timings)
    log.info("\n%s", table(timings, srcs, metrics, cfg.step_time.repeats, states))
    log_bench("step_time", cfg, srcs, len(states), metrics)
    return metrics


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="bench")
def main(cfg: DictConfig) -> None:
    """Console entry point (`python -m bench.step_time`)."""
    run(cfg)


if __name__ == "__main__":
    main()
