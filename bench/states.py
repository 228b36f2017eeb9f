"""A fixed set of planning states for benchmarks: the (observation, warm start) pairs that MPC steps saw in closed-loop
ADMM runs of each scenario family (two_lane, three_lane, and held-out dense worlds, the headline's), saved once to an
.npz so every benchmark (and every solver) plans from the same states.

    from bench.states import planning_states, settings, solver_step
    for st in planning_states():                       # collected on first use, then loaded from the .npz
        result = solver_step()(settings(st.scenario), st.obs, source, st.warm)
"""
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from core.jobs import UserError, atomic_file
from planner import admm, closed_loop, mpc
from planner.setup import build, planner_config, setup
from planner.setup import settings as mpc_settings

DEFAULT_PATH = Path("outputs/bench/states.npz")
SCENARIOS = ("two_lane", "three_lane", "dense")
DENSE_SEED = 2_000_000  # the held-out dense worlds, as make demo's and make ceiling's


class PlanningState(NamedTuple):
    """One MPC step's input: the scenario's name, the observation, and the previous plan (None: the episode's first step)."""

    scenario: str
    obs: mpc.Observation
    warm: admm.ADMMState | None


@lru_cache(maxsize=None)
def settings(scenario: str, overrides: tuple = ()) -> mpc.Settings:
    """The MPC settings the `planner` command would use on `scenario` with these overrides (cached: composing and building
    a config takes ~50 ms)."""
    cfg = planner_config(scenario, overrides)
    return mpc_settings(cfg, build(cfg.scenario))


@lru_cache(maxsize=None)
def solver_step(overrides: tuple = ()):
    """The step the `planner` command's solver would run with these overrides (conf/solver/; by default
    planner.step.mpc_step with the Z-step bound), called as step(settings(scenario), obs, source, warm); the same on every
    scenario (conf/solver/ and conf/zstep/ read no scenario value)."""
    return build(planner_config("two_lane", overrides).solver.step)


def collect(scenarios=SCENARIOS, per_scenario=15, gradients="analytic", seed=0, overrides=(), dense_seed=DENSE_SEED,
            dense_worlds=3) -> list[PlanningState]:
    """Drive each scenario closed loop with ADMM and `gradients` (world `seed`; dense: the dense_worlds worlds from seed
    dense_seed), keep `per_scenario` steps evenly spread over its runs."""
    out = []
    for name in scenarios:
        seen = []
        for world in range(dense_seed, dense_seed + dense_worlds) if name == "dense" else (seed,):
            cfg = planner_config(name, [f"gradients={gradients}", f"seed={world}", "method=admm", *overrides])
            scenario, source, s = setup(cfg)
            admm_step = build(cfg.solver.step)
            step = lambda obs, warm: seen.append((obs, warm)) or admm_step(s, obs, source, warm)
            closed_loop.drive(scenario.make_world(cfg.seed), step, source, scenario.x_ref, scenario.target_lane, cfg.T_obs,
                              cfg.max_steps, cfg.world, cfg.n_slots)
        keep = np.unique(np.linspace(0, len(seen) - 1, min(per_scenario, len(seen))).round().astype(int))
        out += [PlanningState(name, *seen[k]) for k in keep]
    return out


def save(states: list[PlanningState], path=DEFAULT_PATH, collected: str = ""):
    """Write the states to one .npz (atomically) with `collected`, how they were collected; a missing warm start is
    stored as NaN with has_warm = False."""
    T4 = len(next(st.warm for st in states if st.warm is not None).Z)
    warm = [st.warm or admm.ADMMState(*(np.full(n, np.nan) for n in (T4 // 4, T4 // 4, T4, T4))) for st in states]
    arrays = {"scenario": np.array([st.scenario for st in states]), "has_warm": np.array([st.warm is not None for st in states]),
              "collected": np.array(collected)}
    arrays.update({k: np.stack([getattr(st.obs, k) for st in states]) for k in mpc.Observation._fields})
    arrays.update({k: np.stack([getattr(w, k) for w in warm]) for k in ("Delta", "alpha", "Z", "mu")})
    atomic_file(Path(path), lambda tmp: np.savez(tmp, **arrays))


def read(path):
    """{name: array} of a saved states file; a damaged file is a UserError naming it."""
    try:
        with np.load(path) as f:
            return {k: f[k] for k in f.files}
    except Exception as e:  # numpy raises several types for a damaged file (BadZipFile, OSError, EOFError, ...)
        raise UserError(f"damaged planning states {path} ({type(e).__name__}: {e}); delete it to collect them again") from None


def load(path=DEFAULT_PATH) -> list[PlanningState]:
    """The states saved by `save`; a damaged file is a UserError naming it."""
    a = read(path)
    try:
        return [PlanningState(str(a["scenario"][i]), mpc.Observation(a["z0"][i], a["u_prev"][i], a["history"][i]),
                              admm.ADMMState(a["Delta"][i], a["alpha"][i], a["Z"][i], a["mu"][i]) if a["has_warm"][i] else None)
                for i in range(len(a["scenario"]))]
    except (KeyError, IndexError) as e:
        raise UserError(f"damaged planning states {path} ({type(e).__name__}: {e}); delete it to collect them again") from None


def collect_kwargs(cfg) -> dict:
    """`collect`'s arguments from the bench config's `states` node (conf/bench.yaml), the same for every bench."""
    st = cfg.states
    return {"per_scenario": st.per_scenario, "gradients": st.gradients, "seed": st.seed, "dense_seed": st.dense_seed,
            "dense_worlds": st.dense_worlds}


def planning_states(path=DEFAULT_PATH, **collect_kwargs) -> list[PlanningState]:
    """The saved states at `path`, collected (see `collect`) and saved there first if missing or collected otherwise
    (another scenario family, count, source or seed)."""
    collected = repr(sorted(collect_kwargs.items()))
    if not Path(path).exists() or str(read(path).get("collected", "")) != collected:
        save(collect(**collect_kwargs), path, collected)
    return load(path)
