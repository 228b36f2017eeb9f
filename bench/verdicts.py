"""`python -m bench.verdicts [overrides]`: does each predictor tell the interactive step the truth? The predictor's part
of mpc=interactive, apart from the step's.

At held-out branch states of dense worlds (bench/branches.py: an exploratory ego driven to a moment where interaction is
possible), the interactive strategy's candidate plans (planner.strategy.Interactive.plans) are judged by each source and
by the world itself (the oracle: copies of that world with its true hidden decisions, the ego put on each plan). A
candidate is a *good merge* when it merges within the horizon with the others outside the safety shape and nobody
braking harder than mpc.b_courtesy. Per source, over every (state, candidate):
  false_alarm  the share of truly good merges the source refuses (why a step waits where it could merge);
  miss         the share of the other merging candidates it accepts as good (why a step forces or collides);
  brake_fa     the share of candidates where nobody truly brakes above 2 m/s^2 that it predicts braking above
               b_courtesy (issue 44's false-alarm rate);
and per state, the candidate it ranks first (planner.strategy.Interactive.order):
  takes_good   a good merge, on the states where the world has one;
  takes_bad    a merge that is not good.
95% intervals: percentile bootstrap over states for the candidate shares, Wilson for the per-state ones.

    python -m bench.verdicts [states=30] [seed_offset=11000000] [sources=[cv,student,teacher,surrogate]]
"""
import csv
import sys
from pathlib import Path

import numpy as np

from bench.branches import branch_state, heldout_seeds
from core import stats, validate
from core.jobs import UserError, atomic_file, guarded, job_config, writable
from planner import mpc, setup

FORCED = 2.0  # m/s^2: below this the world's drivers brake for nothing much (issue 44's false-alarm definition)
SCHEMA = {"sources": validate.ListOf(validate.GRADIENT_OPTIONS), "planner": validate.ListOf(validate.Text()),
          "models_dir": validate.Text(), "out_dir": validate.Text(), "seed_offset": validate.SEED,
          "states": validate.Int(1), "branch.min_steps": validate.Int(0), "branch.max_steps": validate.Int(0),
          "branch.reach": validate.POS, "branch.tries": validate.Int(1), "resamples": validate.Int(1)}


def sources(cfg) -> dict:
    """{name: (source, settings)} of every source in cfg.sources whose models exist (the others skipped, as
    evaluate-interaction skips them, with one line) and the oracle, on mpc=interactive."""
    out = {}
    for name in [*cfg.sources, "oracle"]:
        over = [f"gradients={name}", "mpc=interactive", f"models_dir={cfg.models_dir}", *cfg.planner]
        pc = setup.planner_config(cfg.scenario.name, over + (["predictor=oracle"] if name == "oracle" else []))
        try:
            out[name] = setup.setup(pc)[1:]
        except UserError as e:
            print(f"{name}: skipped ({e})")
    return out


def verdicts(source, s, obs, plans) -> tuple:
    """(good merge (K,), merges within the horizon (K,), braking (K,) m/s^2, order) of the K candidate plans as `source`
    judges them."""
    judged = s.strategy.judge(s, obs, source, *plans)
    b_c = np.inf if s.b_courtesy is None else s.b_courtesy
    good = np.array([j.b_min >= 0.0 and j.braking <= b_c and j.merge <= s.strategy.horizon for j in judged])
    merges = np.array([j.merge <= s.strategy.horizon for j in judged])
    return good, merges, np.array([j.braking for j in judged]), s.strategy.order(s, judged)


def run(cfg) -> dict:
    """{source: scores} over cfg.states held-out branch states; writes <out_dir>/verdicts.csv."""
    scenario = setup.setup(setup.planner_config(cfg.scenario.name, ["gradients=cv"]))[0]
    judges = sources(cfg)
    seeds = heldout_seeds("seed_offset", cfg.seed_offset, cfg.states * cfg.branch.tries, cfg.dataset)
    per_state = {name: [] for name in judges}
    for seed in seeds:
        state = branch_state(scenario, cfg.dataset.policy, seed, cfg.branch, np.random.default_rng([seed, 3]), cfg.n_slots)
        if state is None:
            continue
        _, world, seen = state
        obs = mpc.Observation(world.states()[0], np.zeros(2), seen.history)
        s = judges["oracle"][1]
        names, Delta, alpha, Z, _ = s.strategy.plans(s, obs, None)
        judges["oracle"][0].predictor.world, judges["oracle"][0].predictor.ids = world, seen.ids
        true_good, true_merge, true_brake, true_order = verdicts(*judges["oracle"], obs, (Delta, alpha, Z))
        for name, (source, s_) in judges.items():
            good, merges, brake, order = verdicts(source, s_, obs, (Delta, alpha, Z))
            per_state[name].append({"seed": seed, "good": good, "merges": merges, "true_good": true_good,
                                    "true_merge": true_merge, "brake": brake, "true_brake": true_brake, "first": order[0],
                                    "b_c": s_.b_courtesy})
        if len(per_state["oracle"]) == cfg.states:
            break
    else:
        raise UserError(f"only {len(per_state['oracle'])} of states={cfg.states} branch states found; raise branch.tries")
    return {name: scores(rows, cfg.resamples, cfg.seed_offset) for name, rows in per_state.items()}


def scores(rows, resamples: int, seed: int) -> dict:
    """The module doc's scores with their 95% intervals (x_lo, x_hi) over one source's per-state rows."""
    share = lambda x: float(np.mean(x)) if len(x) else float("nan")
    cand = {"false_alarm": [~r["good"][r["true_good"]] for r in rows],
            "miss": [r["good"][r["true_merge"] & ~r["true_good"]] for r in rows],
            "brake_fa": [r["brake"][r["true_brake"] < FORCED] > r["b_c"] for r in rows]}
    out = {"states": len(rows)}
    for k, groups in cand.items():
        out[k] = share(np.concatenate(groups).astype(float))
        out[f"{k}_lo"], out[f"{k}_hi"] = stats.bootstrap(groups, share, resamples, seed)
    has_good = [r for r in rows if r["true_good"].any()]
    firsts = {"takes_good": (sum(bool(r["true_good"][r["first"]]) for r in has_good), len(has_good)),
              "takes_bad": (sum(bool(r["merges"][r["first"]] and r["good"][r["first"]] and not r["true_good"][r["first"]])
                                for r in rows), len(rows))}
    for k, (hits, n) in firsts.items():
        out[k] = hits / n if n else float("nan")
        out[f"{k}_lo"], out[f"{k}_hi"] = stats.wilson(hits, n)
    out["states_with_good"] = len(has_good)
    return out


def write(path: Path, table: dict) -> None:
    """verdicts.csv (one row per source), staged so a failed run keeps the last one."""
    keys = list(next(iter(table.values())))

    def rows(tmp):
        with open(tmp, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["source", *keys])
            w.writerows([name, *(f"{row[k]:.4g}" for k in keys)] for name, row in table.items())
    atomic_file(path, rows)


@guarded
def main(overrides=()) -> dict:
    """Score, write <out_dir>/verdicts.csv, print the table; returns it."""
    cfg = job_config("verdicts", overrides)
    validate.check(cfg, SCHEMA)
    path = writable(Path(cfg.out_dir), "out_dir") / "verdicts.csv"
    table = run(cfg)
    write(path, table)
    pct = lambda r, k: f"{100 * r[k]:.1f} [{100 * r[k + '_lo']:.1f}, {100 * r[k + '_hi']:.1f}]"
    print(f"{cfg.states} held-out branch states of {cfg.scenario.name} (seeds from {cfg.seed_offset}); "
          f"{table['oracle']['states_with_good']} have a good merge by the world's verdict; {path}")
    print("| source | false alarm % | miss % | brake false alarm % | takes a good merge % | takes a bad merge % |")
    print("|---|---|---|---|---|---|")
    for name, r in table.items():
        print(f"| {name} | {pct(r, 'false_alarm')} | {pct(r, 'miss')} | {pct(r, 'brake_fa')} | {pct(r, 'takes_good')} "
              f"| {pct(r, 'takes_bad')} |")
    return table


if __name__ == "__main__":
    main(sys.argv[1:])
