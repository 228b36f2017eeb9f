"""Our Z-step (`zstep=sqp`, SQP + OSQP) against the paper's (`zstep=pygranso`, PyGranso BFGS-SQP), side by side:
wall time (ms) of one MPC step, its cost J and its plan's worst safety violation (m^2), per gradient source, on the
saved planning states of the step-time benchmark, single-threaded; ratios pygranso/sqp printed and logged (`bench`).

    python -m bench.zstep_compare [zstep_compare.per_scenario=4] [zstep_compare.sources=[student]] [models_dir=models]

PyGranso takes seconds per MPC step, so by default an evenly spread subset of the saved states is used (conf/bench.yaml).
"""
import logging
import time

import hydra
import numpy as np
from omegaconf import DictConfig

from bench.states import collect_kwargs, planning_states, settings, solver_step
from bench.step_time import log_bench, single_threaded, sources
from core.jobs import CONF_DIR, console, guarded, open_experiment
from core.rollout import b_i, ego_xy
from planner import mpc
from planner.pygranso_zstep import import_pygranso

log = logging.getLogger(__name__)
ZSTEPS = ("sqp", "pygranso")


def subset(states, per_scenario):
    """`per_scenario` states of each scenario, evenly spread over its saved ones (all when per_scenario <= 0)."""
    out = []
    for name in dict.fromkeys(st.scenario for st in states):
        mine = [st for st in states if st.scenario == name]
        keep = np.unique(np.linspace(0, len(mine) - 1, min(per_scenario, len(mine))).round().astype(int)) \
            if per_scenario > 0 else range(len(mine))
        out += [mine[k] for k in keep]
    return out


def violation(s: mpc.Settings, state, source, plan):
    """max(0, -min b_i) (m^2) of the plan's own states Z against the predictor's reaction to them."""
    if plan is None:
        return np.nan
    values = source.values(state.obs.history, ego_xy(plan.Z, s.T_p)[None])[0]
    return float(max(0.0, -b_i(values, s.R, s.stretch, s.shape).min(initial=np.inf)))


def step(state, source, zstep: str):
    """One MPC step with Z-step `zstep`: (ms, J, violation m^2, fell back, the Z-step's last stop reason)."""
    s, admm_step = settings(state.scenario, (f"zstep={zstep}",)), solver_step((f"zstep={zstep}",))
    t0 = time.perf_counter()
    result = admm_step(s, state.obs, source, state.warm)
    ms = 1e3 * (time.perf_counter() - t0)
    return ms, result.J, violation(s, state, source, result.plan), bool(result.fallback), result.zstop


def compare(srcs: dict, states) -> dict:
    """{(source, zstep): arrays ms, J, violation, fallback (n_states,) and the stop reasons}, zsteps round-robin per state."""
    out = {(n, z): [] for n in srcs for z in ZSTEPS}
    for state in states:
        for name, src in srcs.items():
            for z in ZSTEPS:
                out[name, z].append(step(state, src, z))
    return {k: {"ms": np.array([r[0] for r in v]), "J": np.array([r[1] for r in v]), "viol": np.array([r[2] for r in v]),
                "fallback": np.array([r[3] for r in v]), "stops": [r[4] for r in v]} for k, v in out.items()}


def summary(rows: dict) -> dict:
    """MLflow metrics per source and Z-step (ms median/p95, J mean, violation max, fallbacks) and pygranso vs sqp."""
    out = {}
    for (name, z), r in rows.items():
        out.update({f"{name}_{z}_ms_median": float(np.median(r["ms"])), f"{name}_{z}_ms_p95": float(np.percentile(r["ms"], 95)),
                    f"{name}_{z}_J_mean": float(np.nanmean(r["J"])), f"{name}_{z}_viol_max": float(np.nanmax(r["viol"])),
                    f"{name}_{z}_fallbacks": float(r["fallback"].sum())})
    for name in dict.fromkeys(n for n, _ in rows):
        sqp, pg = rows[name, "sqp"], rows[name, "pygranso"]
        both = ~(sqp["fallback"] | pg["fallback"])  # J of a fallback plan says nothing about the Z-step
        dJ = pg["J"][both] - sqp["J"][both]
        out.update({f"{name}_ratio_ms_pygranso_sqp": out[f"{name}_pygranso_ms_median"] / out[f"{name}_sqp_ms_median"],
                    f"{name}_dJ_mean": float(np.mean(dJ)) if both.any() else np.nan,
                    f"{name}_dJ_max_abs": float(np.max(np.abs(dJ))) if both.any() else np.nan,
                    f"{name}_both_solved": float(both.sum())})
    return out


def table(rows: dict, metrics: dict) -> str:
    """The printed comparison: one line per source and Z-step, then the ratios."""
    lines = [f"{'source':>10} {'zstep':>9} {'median ms':>10} {'p95 ms':>10} {'J mean':>9} {'viol max':>9} {'fallbacks':>9}"]
    for name, z in rows:
        k = f"{name}_{z}"
        lines.append(f"{name:>10} {z:>9} {metrics[k + '_ms_median']:>10.1f} {metrics[k + '_ms_p95']:>10.1f} "
                     f"{metrics[k + '_J_mean']:>9.3f} {metrics[k + '_viol_max']:>9.4f} {metrics[k + '_fallbacks']:>9.0f}")
    for name in dict.fromkeys(n for n, _ in rows):
        stops = sorted({s for s in rows[name, "pygranso"]["stops"] if s})
        lines.append(f"{name}: pygranso/sqp time {metrics[name + '_ratio_ms_pygranso_sqp']:.1f}x, J(pygranso) - J(sqp) "
                     f"mean {metrics[name + '_dJ_mean']:+.4f}, max |.| {metrics[name + '_dJ_max_abs']:.4f} over "
                     f"{metrics[name + '_both_solved']:.0f} states both solved; pygranso stops: {'; '.join(stops) or '-'}")
    return "\n".join(lines)


@guarded
def run(cfg: DictConfig) -> dict:
    """Load the saved states, step each with both Z-steps for every available source, log the table and to MLflow."""
    import_pygranso()  # one clear line if the extra is missing, before any work
    open_experiment("bench")  # and if the store is unusable
    only = list(cfg.zstep_compare.sources)
    with single_threaded(cfg):
        states = subset(planning_states(cfg.states.path, **collect_kwargs(cfg)), cfg.zstep_compare.per_scenario)
        srcs = {n: s for n, s in sources(cfg.models_dir).items() if not only or n in only}
        for src in srcs.values():  # warm-up: first calls pay for imports and allocations (PyGranso's import is done)
            step(states[0], src, "sqp")
        rows = compare(srcs, states)
    metrics = summary(rows)
    log.info("\n%s planning states (%s), one thread\n%s", len(states), ", ".join(sorted({st.scenario for st in states})),
             table(rows, metrics))
    log_bench("zstep_compare", cfg, srcs, len(states), metrics)
    return metrics


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="bench")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Console entry point (`python -m bench.zstep_compare`)."""
    console("bench", hydra_main)


if __name__ == "__main__":
    main()
