"""`make bench`: wall time (ms) of one ADMM-NNMPC step per gradient source on the saved planning states, single-threaded,
beside the QP floor (the same ADMM with the safety linearisation frozen: no network calls), logged to MLflow (`bench`).

    python -m bench.step_time [--per-scenario 15] [--repeats 1] [--models-dir models]

Sources are timed round-robin state by state, so a busy machine slows them alike and the ratios stay fair.
"""
import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy and torch start their thread pools

import argparse  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from bench.states import DEFAULT_PATH, planning_states, settings  # noqa: E402
from core.jobs import UserError, guarded, mlflow_run  # noqa: E402
from core.rollout import ego_xy  # noqa: E402
from planner import mpc  # noqa: E402
from planner.gradients import make_source  # noqa: E402

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


def log_bench(run_name, settings: dict, srcs: dict, n_states: int, metrics: dict):
    """One MLflow run in experiment `bench`: the settings (one thread), each source's predictor, the metrics."""
    import mlflow

    predictors = {f"predictor_{n}": s.predictor.name for n, s in srcs.items()}
    cfg = OmegaConf.create({**settings, "threads": 1})
    with mlflow_run("bench", cfg, run_name=run_name, n_states=n_states, **predictors):
        mlflow.log_metrics(metrics)


def sources(models_dir) -> dict:
    """Every gradient source available: teacher (autodiff), student, surrogate, fd over the trained models; over the
    analytic predictor (with its exact Jacobians as `analytic`) for the ones whose models are missing."""
    out = {}
    for name in ("teacher", "student", "surrogate", "fd", "analytic"):
        try:
            out[name] = make_source(name, "auto", models_dir)  # onnxruntime sessions run on one thread already
        except UserError as e:
            if name in ("teacher", "fd"):  # the same maths over the built-in predictor keeps the ratios meaningful
                out[name] = make_source(name, "analytic", models_dir)
            print(f"{name}: {e}" + ("; using the analytic predictor" if name in out else "; skipped"))
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
                result = mpc.admm_step(s, state.obs, src, state.warm)
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


@guarded
def run(per_scenario=15, repeats=1, models_dir="models", states_path=DEFAULT_PATH) -> dict:
    """Collect or load the states, time every source and the floor, print the table and the ratios, log to MLflow."""
    import torch

    torch.set_num_threads(1)
    states = planning_states(states_path, per_scenario=per_scenario)
    srcs = sources(models_dir)
    for name, src in srcs.items():  # warm-up: first calls pay for imports, allocations and onnxruntime's graph setup
        mpc.admm_step(settings(states[0].scenario), states[0].obs, src, states[0].warm)
    timings = time_steps(srcs, states, repeats)
    metrics = summary(timings)
    print(f"{len(states)} planning states ({', '.join(sorted({st.scenario for st in states}))}), one thread, "
          f"fastest of {repeats}")
    print(f"{'source':>10} {'predictor':>10} {'median ms':>10} {'p95 ms':>10} {'ADMM iters':>11} {'fallbacks':>10}")
    for name in timings:
        pred = srcs[name].predictor.name if name in srcs else "frozen"
        print(f"{name:>10} {pred:>10} {metrics[f'{name}_ms_median']:>10.1f} {metrics[f'{name}_ms_p95']:>10.1f} "
              f"{metrics[f'{name}_iters_mean']:>11.1f} {metrics[f'{name}_fallbacks']:>10.0f}")
    for a, b in RATIOS:
        key = f"ratio_{a}_{b}"
        print(f"{a}/{b}: " + (f"{metrics[key]:.1f}x" if key in metrics else f"n/a ({b if a in srcs else a} missing)"))
    log_bench("step_time", {"per_scenario": per_scenario, "repeats": repeats, "models_dir": models_dir,
                            "states": str(states_path)}, srcs, len(states), metrics)
    return metrics


def main():
    """Console entry point (`python -m bench.step_time`)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--per-scenario", type=int, default=15, help="planning states kept per scenario when collecting")
    p.add_argument("--repeats", type=int, default=1, help="time each step this many times, keep the fastest")
    p.add_argument("--models-dir", default="models")
    p.add_argument("--states", type=Path, default=DEFAULT_PATH, help="saved states (.npz); collected first if missing")
    a = p.parse_args()
    run(a.per_scenario, a.repeats, a.models_dir, a.states)


if __name__ == "__main__":
    main()
