"""`python -m bench.verdicts [overrides]`: does each predictor tell the interactive step the truth? The predictor's part
of mpc=interactive, apart from the step's.

At the states a closed loop visits on held-out dense worlds (the interactive step driven with the source `drive`, every
`every`-th step until the episode ends: the moments a step waits, leans, and merges), the interactive strategy's
candidate plans (planner.strategy.Interactive.plans) are judged by each source and by the world itself (the oracle: copies of that world with its true hidden decisions, the ego put on each plan). A
candidate is a *good merge* when it merges within the horizon with the others outside the safety shape and nobody
braking harder than mpc.b_courtesy. Per source, over every (state, candidate):
  good_kept    the share of truly good merges the source also judges good (1 - false_alarm; higher is better: the
               fidelity score of `make results`, which ranks predictors as the interactive step's closed loop does);
  false_alarm  the share of truly good merges the source refuses (why a step waits where it could merge);
  miss         the share of the other merging candidates it accepts as good (why a step forces or collides);
  brake_fa     the share of candidates where nobody truly brakes above 2 m/s^2 that it predicts braking above
               b_courtesy (issue 44's false-alarm rate);
  fa_unsafe, fa_braking  the share of truly good merges it refuses because it predicts a car inside the safety shape
               (b_i < 0), and because it predicts braking above b_courtesy (a refusal may have both reasons);
  fa_unsafe_merged  the share of truly good merges it refuses as unsafe only after the candidate has merged (a car of
               the target lane predicted into the ego once it is there: how the predictor follows a cut-in through);
  fa_unsafe_late  the share of truly good merges it refuses as unsafe with the first predicted contact beyond the
               paper's horizon T_p (the steps the models of `make demo` are trained to roll out; the step looks 25-50);
  brake_detect the share of candidates that truly make a driver brake harder than the scenario's b_safe (they force)
               where it predicts braking above b_courtesy (why a step that trusts it forces);
and per state, the candidate it ranks first (planner.strategy.Interactive.order):
  takes_good   a good merge, on the states where the world has one;
  takes_bad    a merge that is not good.
95% intervals: percentile bootstrap over states for the candidate shares, Wilson for the per-state ones.

The judges are the gradient sources of `sources` on the models of `models_dir`, then each entry of `variants`
({name, gradients, models_dir}: a source on the models of another folder, such as a graded training's or another
training seed's), beside the oracle; the states and the world's verdicts are computed once and shared by all of them.

    python -m bench.verdicts [worlds=10] [every=5] [drive=cv] [seed_offset=11000000] [sources=[cv,student,teacher,surrogate]]
        [variants=[{name: student_5pct, gradients: student, models_dir: <folder>}]]
"""
import csv
import sys
from pathlib import Path

import numpy as np
from omegaconf import ListConfig

from bench.branches import heldout_seeds
from core import stats, validate
from core.jobs import UserError, atomic_file, guarded, job_config, mlflow_run, writable
from core.rollout import b_i
from data.perception import observe
from planner import mpc, setup
from planner.gradients import available

FORCED = 2.0  # m/s^2: below this the world's drivers brake for nothing much (issue 44's false-alarm definition)
SCHEMA = {"sources": validate.ListOf(validate.GRADIENT_OPTIONS), "planner": validate.ListOf(validate.Text()),
          "models_dir": validate.Text(), "out_dir": validate.Text(), "seed_offset": validate.SEED,
          "worlds": validate.EPISODES, "every": validate.Int(1), "drive": validate.GRADIENT_OPTIONS,
          "resamples": validate.Int(1)}
VARIANT = ("name", "gradients", "models_dir")  # the keys of a variant
JUDGE = validate.OneOf(tuple(available(needs_world=False, hypotheses=False)))  # a variant's source: the oracle is the reference, not a judge


def variants(cfg) -> list:
    """cfg.variants, each {name, gradients, models_dir} under a name no source, the oracle or another variant has; one
    UserError naming the entry otherwise."""
    if not isinstance(cfg.variants, ListConfig):
        raise UserError(f"variants={cfg.variants}: must be a list of {{name, gradients, models_dir}}")
    taken = {*cfg.sources, "oracle"}
    for i, v in enumerate(cfg.variants):
        where = f"variants[{i}]"
        if not hasattr(v, "keys") or set(v.keys()) != set(VARIANT):
            raise UserError(f"{where}={v}: must be {{name: <judge's name>, gradients: <source>, models_dir: <folder>}}")
        if not validate.Text().ok(v.name) or v.name in taken:
            raise UserError(f"{where}.name={v.name}: must be a name that no source, the oracle or another variant has")
        if not JUDGE.ok(v.gradients):
            raise UserError(f"{where}.gradients={v.gradients}: must be {JUDGE.allowed()}")
        if not validate.Text().ok(v.models_dir):
            raise UserError(f"{where}.models_dir={v.models_dir}: must be {validate.Text().allowed()}")
        taken.add(v.name)
    return list(cfg.variants)


def sources(cfg) -> dict:
    """{name: (source, settings)} on mpc=interactive of every source in cfg.sources whose models exist (the others
    skipped, as evaluate-interaction skips them, with one line), every variant (a UserError naming it where its models
    do not load: it was asked for by folder) and the oracle."""
    judges = [(name, name, cfg.models_dir, None) for name in cfg.sources]
    judges += [(v.name, v.gradients, v.models_dir, f"variants[{i}].models_dir") for i, v in enumerate(variants(cfg))]
    out = {}
    for name, gradients, models_dir, key in [*judges, ("oracle", "oracle", cfg.models_dir, None)]:
        over = [f"gradients={gradients}", "mpc=interactive", f"models_dir={models_dir}", *cfg.planner]
        pc = setup.planner_config(cfg.scenario.name, over + (["predictor=oracle"] if name == "oracle" else []))
        try:
            out[name] = setup.setup(pc)[1:]
        except UserError as e:
            if key is not None:
                raise UserError(f"{key}={models_dir}: {e}") from e
            print(f"{name}: skipped ({e})")
    return out


def verdicts(source, s, obs, plans) -> tuple:
    """(good merge (K,), merges within the horizon (K,), braking (K,) m/s^2, order, unsafe (K,): b_i < 0, unsafe only
    once merged (K,), unsafe first beyond T_p (K,)) of the K candidate plans (Delta, alpha, Z) as `source` judges them
    (planner.strategy.Judge's steps)."""
    judge = s.strategy.judge(s)
    values = judge.predict(obs, source, plans[2])  # kept, to say where a predicted collision comes
    judged = judge.verdicts(s, obs, values, *plans)
    merge = np.array([j.merge for j in judged])
    merges = merge < judge.never
    good = merges & [judge.acceptable(s, j) for j in judged]
    inside = np.array([(b_i(v, s.R, s.stretch, s.shape) < 0.0).any(axis=0) for v in values])  # (K, H): someone inside
    unsafe = inside.any(axis=1)
    first = inside.argmax(axis=1) + 1  # steps count from 1, as Judged.merge
    return (good, merges, np.array([j.braking for j in judged]), judge.order(s, judged), unsafe,
            unsafe & (first >= merge), unsafe & (first > s.T_p))


def visited(cfg, driver, seed: int):
    """(world, what the planner sees, the previous control) at every cfg.every-th step of the closed loop that
    `driver` ((planner config, scenario, source, settings) of mpc=interactive with cfg.drive) drives on world `seed`:
    its recorded controls replayed on a fresh copy."""
    pc, scenario, source, s = driver
    ep = setup.drive(pc, scenario, source, s, "admm", seed)
    world, u_prev = scenario.make_world(seed), np.zeros(2)
    for k, u in enumerate(ep.controls):
        if k % cfg.every == 0:
            yield world, observe(world, pc.n_slots, pc.T_obs), u_prev
        world.step(u)
        u_prev = u


def run(cfg, judges=None) -> dict:
    """{source: scores} over the states visited on cfg.worlds held-out worlds by `judges` (default sources(cfg));
    writes <out_dir>/verdicts.csv."""
    path = writable(Path(cfg.out_dir), "out_dir") / "verdicts.csv"
    judges = judges or sources(cfg)
    pc = setup.planner_config(cfg.scenario.name, [f"gradients={cfg.drive}", "mpc=interactive", "method=admm",
                                                  f"models_dir={cfg.models_dir}", *cfg.planner])
    driver = (pc, *setup.setup(pc))  # built once: the closed loop of every world
    per_state = {name: [] for name in judges}
    for seed in heldout_seeds("seed_offset", cfg.seed_offset, cfg.worlds, cfg.dataset):
        for world, seen, u_prev in visited(cfg, driver, seed):
            obs = mpc.Observation(world.states()[0], u_prev, seen.history)
            s = judges["oracle"][1]
            plans = s.strategy.open_loop.plans(s, obs, None)[1:4]
            judges["oracle"][0].predictor.world, judges["oracle"][0].predictor.ids = world, seen.ids
            true_good, true_merge, true_brake, *_ = verdicts(*judges["oracle"], obs, plans)
            for name, (source, s_) in judges.items():
                good, merges, brake, order, unsafe, merged, late = verdicts(source, s_, obs, plans)
                per_state[name].append({"seed": seed, "good": good, "merges": merges, "true_good": true_good,
                                        "true_merge": true_merge, "brake": brake, "true_brake": true_brake,
                                        "first": order[0], "b_c": s_.b_courtesy, "b_safe": cfg.scenario.b_safe,
                                        "unsafe": unsafe, "unsafe_merged": merged, "unsafe_late": late})
    table = {name: scores(rows, cfg.resamples, cfg.seed_offset) for name, rows in per_state.items()}
    write(path, table)
    return table


def scores(rows, resamples: int, seed: int) -> dict:
    """The module doc's scores with their 95% intervals (x_lo, x_hi) over one source's per-state rows."""
    share = lambda x: float(np.mean(x)) if len(x) else float("nan")
    cand = {"good_kept": [r["good"][r["true_good"]] for r in rows], "false_alarm": [~r["good"][r["true_good"]] for r in rows],
            "miss": [r["good"][r["true_merge"] & ~r["true_good"]] for r in rows],
            "brake_fa": [r["brake"][r["true_brake"] < FORCED] > r["b_c"] for r in rows],
            "fa_unsafe": [r["unsafe"][r["true_good"]] for r in rows],
            "fa_braking": [r["brake"][r["true_good"]] > r["b_c"] for r in rows],
            "fa_unsafe_merged": [r["unsafe_merged"][r["true_good"]] for r in rows],
            "fa_unsafe_late": [r["unsafe_late"][r["true_good"]] for r in rows],
            "brake_detect": [r["brake"][r["true_brake"] > r["b_safe"]] > r["b_c"] for r in rows]}
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
    """Score, write <out_dir>/verdicts.csv, print the table, log both to MLflow (experiment verdicts: each score as
    <source>.<score>); returns it."""
    import mlflow

    cfg = job_config("verdicts", overrides)
    validate.check(cfg, SCHEMA)
    judges = sources(cfg)  # a bad source or variant fails before the MLflow run opens
    with mlflow_run("verdicts", cfg, run_name=f"verdicts-{cfg.drive}-worlds{cfg.worlds}-from{cfg.seed_offset}"):
        table = run(cfg, judges)
        mlflow.log_metrics({f"{name}.{k}": v for name, r in table.items() for k, v in r.items() if np.isfinite(v)})
        mlflow.log_artifact(str(Path(cfg.out_dir) / "verdicts.csv"))
    pct = lambda r, k: f"{100 * r[k]:.1f} [{100 * r[k + '_lo']:.1f}, {100 * r[k + '_hi']:.1f}]"
    print(f"{table['oracle']['states']} states that mpc=interactive with {cfg.drive} visits on {cfg.worlds} held-out "
          f"{cfg.scenario.name} worlds (seeds from {cfg.seed_offset}), every {cfg.every}th step; "
          f"{table['oracle']['states_with_good']} have a good merge by the world's verdict; {cfg.out_dir}/verdicts.csv")
    print("| source | false alarm % | of them unsafe % | unsafe once merged % | unsafe beyond T_p % | for braking % "
          "| miss % | brake false alarm % | forcing detected % | takes a good merge % | takes a bad merge % |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, r in table.items():
        print(f"| {name} | {pct(r, 'false_alarm')} | {pct(r, 'fa_unsafe')} | {pct(r, 'fa_unsafe_merged')} "
              f"| {pct(r, 'fa_unsafe_late')} "
              f"| {pct(r, 'fa_braking')} | {pct(r, 'miss')} | {pct(r, 'brake_fa')} | {pct(r, 'brake_detect')} "
              f"| {pct(r, 'takes_good')} | {pct(r, 'takes_bad')} |")
    return table


if __name__ == "__main__":
    main(sys.argv[1:])
