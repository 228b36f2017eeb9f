"""`python -m bench.candidates [overrides]`: the world's answers to the interactive step's own candidate plans, as a
training set in make-dataset's format (data/dataset.py: {train,val,test}.npz and meta.json in <out_dir>/<name>/).

On `worlds` dense worlds (seeds seed_offset, seed_offset + 1, ...; checked clear of the `dataset`'s episodes and of
the `reserved` seed ranges kept for evaluation), mpc=interactive driven by `drive` (world j by drive[j % len(drive)])
visits its states; at every `every`-th step, `per_state` of the step's candidates (planner.strategy.Interactive: the
open-loop `plans`, and with `closed` the closed-loop `chased` ones, driven against the world itself) are drawn, and the
world's answer to each is its copies' rollout with the ego put on the plan (planner.gradients.WorldModel, the oracle
of bench.verdicts: the drivers' true hidden decisions). An episode is one world: branch 0 its closed loop, branch
b >= 1 its b-th candidate (the closed loop up to the state, then the world's rollout under the plan), so the splits
are by world and distill's rollout term reads a candidate's whole horizon as a recorded future.

    python -m bench.candidates [worlds=40] [every=4] [per_state=6] [drive=[cv]] [seed_offset=30000000] [name=candidates]
"""
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from omegaconf import OmegaConf

from bench.branches import heldout_seeds
from bench.verdicts import visited
from core import validate
from core.jobs import UserError, check_overrides, guarded, job_config, mlflow_run, writable
from data import dataset
from planner import mpc, setup
from planner.gradients import WorldModel

SCHEMA = {"name": validate.Name(), "out_dir": validate.Text(), "models_dir": validate.Text(), "seed_offset": validate.SEED,
          "worlds": validate.EPISODES, "every": validate.Int(1), "per_state": validate.Int(1),
          "drive": validate.ListOf(validate.GRADIENT_OPTIONS, at_least=1), "closed": validate.Bool(),
          "planner": validate.ListOf(validate.Text()), "reserved": validate.ListOf(validate.ListOf(validate.SEED, length=2)),
          "dataset.T_obs": validate.Int(2, validate.MAX_T_OBS), "dataset.n_slots": validate.Int(1, validate.MAX_SLOTS), "dataset.split": validate.Fractions(3)}


def worlds(cfg) -> tuple:
    """(the worlds' seeds, {split: the indices of its worlds}): seeds clear of the dataset's episodes
    (bench.branches.heldout_seeds) and of every reserved range [first, last], no split empty; one UserError otherwise."""
    seeds = heldout_seeds("seed_offset", cfg.seed_offset, cfg.worlds, cfg.dataset)
    for i, span in enumerate(cfg.reserved):
        if span[0] > span[1]:
            raise UserError(f"reserved[{i}]={list(span)}: must be [first seed, last seed]")
        if seeds.start <= span[1] and span[0] < seeds.stop:
            raise UserError(f"seed_offset={cfg.seed_offset}, worlds={cfg.worlds}: seeds {seeds.start}-{seeds.stop - 1} "
                            f"overlap reserved[{i}]={list(span)} (seeds kept for evaluation); choose another seed_offset")
    which = dataset.assign(cfg.worlds, tuple(cfg.dataset.split), cfg.seed_offset)
    if min(len(e) for e in which.values()) == 0:
        raise UserError(f"worlds={cfg.worlds} leaves a split empty with dataset.split={list(cfg.dataset.split)}")
    return seeds, which


def judge(cfg, gradients: str):
    """(planner config, scenario, source, settings) of mpc=interactive with `gradients` on cfg.models_dir's models."""
    extra = ["predictor=oracle"] if gradients == "oracle" else []
    pc = setup.planner_config(cfg.scenario.name, [f"gradients={gradients}", *extra, "mpc=interactive", "method=admm",
                                                  f"models_dir={cfg.models_dir}", f"T_obs={cfg.dataset.T_obs}",
                                                  f"n_slots={cfg.dataset.n_slots}", *cfg.planner])
    return (pc, *setup.setup(pc))


def candidate_paths(cfg, oracle, world, seen, u_prev) -> list:
    """The ego's xy path (H, 2) (m) of every candidate of the interactive step at this state: the open-loop plans and,
    with cfg.closed, the closed-loop ones as they drive against the world itself."""
    _, _, source, s = oracle
    obs = mpc.Observation(world.states()[0], u_prev, seen.history)
    _, Delta, _, Z = s.strategy.open_loop.plans(s, obs, None)
    paths = list(Z.reshape(*Delta.shape, 4)[:, :, :2])
    if cfg.closed:
        source.predictor.world, source.predictor.ids = world, seen.ids
        _, c_Delta, _, c_Z, _ = s.strategy.closed_loop.chased(s, obs, source)
        paths += list(c_Z.reshape(*c_Delta.shape, 4)[:, :, :2])
    return paths


def answers(world, paths):
    """Every car's xy (K, H, M, 2) (m) and hidden yielding flags (K, H, M) in copies of `world` with the ego put on
    each of K paths (H, 2): the oracle's rollout (planner.gradients.WorldModel; plans sharing a prefix share its steps)."""
    oracle, m = WorldModel("all"), len(world.states())
    oracle.world, oracle.ids = world, np.arange(m)
    paths = np.asarray(paths)
    flags = np.zeros((*paths.shape[:2], m), bool)
    xy = oracle.react(world.past_xy(1), lambda window, k: paths[:, k], paths.shape[1], len(paths), flags)
    return xy, flags


def world_windows(cfg, drivers, oracle, j: int, seed: int):
    """One world's windows (data.dataset.episode's results: X, Y, last observed step, yielding, ids, branch, stats):
    its closed loop by drivers[j % len] as branch 0, then each drawn candidate's as a branch of its own."""
    rng = np.random.default_rng([seed, 4])
    t_obs, n = cfg.dataset.T_obs, cfg.dataset.n_slots
    xy, flags, parts, states = [], [], [], 0
    for k, (world, seen, u_prev) in enumerate(visited(SimpleNamespace(every=1), drivers[j % len(drivers)], seed)):
        xy.append(world.states()[:, :2])  # every step: the closed loop's own windows and each candidate's past
        flags.append(world.yielding.copy())
        if k % cfg.every:
            continue
        states += 1
        paths = candidate_paths(cfg, oracle, world, seen, u_prev)
        drawn = sorted(rng.choice(len(paths), size=min(cfg.per_state, len(paths)), replace=False))
        for length in sorted({len(paths[i]) for i in drawn}):  # the two families' horizons differ
            c_xy, c_flags = answers(world, [paths[i] for i in drawn if len(paths[i]) == length])
            for c, f in zip(c_xy, c_flags):
                X, Y, last, yl, ids = dataset.windows(np.concatenate([xy, c]), np.concatenate([flags, f]), t_obs, n)
                keep = last >= k  # the earlier windows are the closed loop's own
                parts.append((X[keep], Y[keep], last[keep], yl[keep], ids[keep], len(parts) + 1))
    parts = [(*dataset.windows(np.array(xy), np.array(flags), t_obs, n), 0), *parts]
    cols = [np.concatenate([p[c] for p in parts]) for c in range(5)]
    branch = np.concatenate([np.full(len(p[0]), p[5]) for p in parts])
    return (*cols, branch, {"seed": seed, "drive": cfg.drive[j % len(cfg.drive)], "steps": len(xy), "states": states,
                            "candidates": len(parts) - 1, "windows": int(len(branch))})


def run(cfg) -> dict:
    """Build the dataset and save it to <out_dir>/<name>/ as one set (data.dataset.save); returns its meta."""
    t0 = time.perf_counter()
    seeds, which = worlds(cfg)
    root = writable(Path(cfg.out_dir), "out_dir") / cfg.name
    drivers = [judge(cfg, g) for g in cfg.drive]
    oracle = judge(cfg, "oracle")
    results = [world_windows(cfg, drivers, oracle, j, seed) for j, seed in enumerate(seeds)]
    splits = dataset.stack(results, which)
    meta = {"name": cfg.name, "seed": cfg.seed_offset, "seeds": [seeds.start, seeds.stop - 1], "T_obs": cfg.dataset.T_obs,
            "T_pred": 1, "N": cfg.dataset.n_slots, "dt": oracle[1].params.dt, "units": "m",
            "slots": "0 = ego; 1..N = the N other cars nearest the ego at the last observed step, in id order",
            "episodes": "one world each: branch 0 its mpc=interactive closed loop, branch b >= 1 the world's answer to "
                        "its b-th drawn candidate plan (bench.candidates)",
            "stats": {"worlds": cfg.worlds, **{k: int(sum(r[6][k] for r in results))
                                               for k in ("steps", "states", "candidates", "windows")}},
            "worlds": [r[6] for r in results], "build_s": round(time.perf_counter() - t0, 2),
            "config": OmegaConf.to_yaml(cfg, resolve=True)}
    return dataset.save(root, splits, meta)


@guarded
def main(overrides=()) -> dict:
    """Check the overrides, build and write the dataset, log its statistics to MLflow (experiment candidates), print
    one line; returns its meta."""
    import mlflow

    check_overrides("candidates", overrides)
    cfg = job_config("candidates", overrides)
    validate.check(cfg, SCHEMA)
    worlds(cfg)  # a clash or an empty split fails before the MLflow run opens
    with mlflow_run("candidates", cfg, run_name=f"candidates-{cfg.name}-worlds{cfg.worlds}-from{cfg.seed_offset}"):
        meta = run(cfg)
        mlflow.log_metrics({**meta["stats"], "build_s": meta["build_s"],
                            **{f"{s}_windows": v["windows"] for s, v in meta["splits"].items()}})
    s, per_split = meta["stats"], ", ".join(f"{k} {v['windows']}" for k, v in meta["splits"].items())
    print(f"{Path(cfg.out_dir) / cfg.name}: {s['windows']} windows ({per_split}) "
          f"from {s['candidates']} candidates at {s['states']} states of {s['worlds']} worlds (seeds {meta['seeds'][0]}-"
          f"{meta['seeds'][1]}), {meta['build_s']:.0f} s")
    return meta


if __name__ == "__main__":
    main(sys.argv[1:])
