"""The clairvoyant ceiling as a bound: a known open-loop merge it must match, recorded runs replayed exactly as further
starts, its inputs checked; and the cooperation levels of the hidden willingness (scenario.cooperation)."""
import numpy as np
import pandas as pd
import pytest
from hydra.utils import instantiate

from bench import ceiling
from conftest import compose_cfg
from core import stats
from core.jobs import UserError, build
from data import outcomes
from data.drivers import IDMDriver
from data.world import World

# A hand-built open lane beside the ego (nobody yields, nobody needs to): steer left 5 steps, straight 3, right 5, then
# straight; in the target lane (|y - 4| <= merge_tol = 1.2) at step 9.
KNOWN = np.array([[0.2, 0.0]] * 5 + [[0.0, 0.0]] * 3 + [[-0.2, 0.0]] * 5 + [[0.0, 0.0]] * 20)
# a library that cannot merge early: one cut-in at step 30, and gap policies asking for 50 m of clearance
SLOW = ["search.gaps=0", "search.y_lean=[1.8]", "search.clearance=[50.0]", "search.enter=[30]", "search.dv=[0.0]",
        "search.y_wait=[0.0]", "search.accept_dv=[0.0]"]


def scenario(name, *overrides):
    """The scenario `name` of the ceiling's config, with `scenario.k=v` overrides."""
    return instantiate(compose_cfg("ceiling", [f"scenario={name}", *overrides]).scenario, _convert_="all")


def open_lane(sc):
    """The ego at 5 m/s beside a 36 m gap in the target lane, three stubborn drivers at 5 m/s."""
    z = np.array([[9.2, 0.0, 0.0, 5.0], [32.0, 4.0, 0.0, 5.0], [-4.0, 4.0, 0.0, 5.0], [-12.0, 4.0, 0.0, 5.0]])
    return World(sc.road, z, [IDMDriver(v0=5.0) for _ in z[1:]], np.zeros(4, bool), sc.b_max, params=sc.params)


def test_the_known_merge_is_courteous_at_step_9_by_direct_simulation():
    sc = scenario("dense")
    w = open_lane(sc)
    states, hits = [w.states()], []
    for u in KNOWN:
        hits += w.step(u)
        states.append(w.states())
    y = np.array(states)[:, 0, 1]
    assert np.flatnonzero(np.abs(y - sc.y_ref) <= sc.merge_tol)[0] == 9 and not hits
    assert outcomes.b_imposed_max(states, sc.params.dt) <= sc.b_safe
    run = ceiling.replay(open_lane(sc), KNOWN, sc, 60)
    assert (run.courteous, run.t_merge, run.b_imposed) == (True, 9, outcomes.b_imposed_max(states, sc.params.dt))


def test_the_ceiling_merges_at_least_as_fast_as_a_known_open_loop_merge():
    sc = scenario("dense")
    cfg = compose_cfg("ceiling", ["scenario=dense"])
    alone, final = ceiling.search_world(open_lane(sc), sc, cfg, np.random.default_rng(0))
    assert alone is final and final.courteous and final.t_merge <= 9
    # a library too slow to find it alone: given the known controls as a start, the ceiling reaches them
    slow = compose_cfg("ceiling", ["scenario=dense", *SLOW, "refine.starts=0"])
    alone, final = ceiling.search_world(open_lane(sc), sc, slow, np.random.default_rng(0), [KNOWN])
    assert alone.t_merge > 30 and final.courteous and final.t_merge <= 9


def test_refinement_keeps_the_library_best_and_never_reverses():
    sc = scenario("dense")
    slow = compose_cfg("ceiling", ["scenario=dense", *SLOW, "refine.starts=0"])
    outs = ceiling.library(open_lane(sc), sc, slow)
    best = min((o for o in outs if o.courteous), key=lambda o: o.t_merge)
    cfg = compose_cfg("ceiling", ["scenario=dense", *SLOW, "refine.sigma=[0.0,3.0]"])
    refined = ceiling.refine(open_lane(sc), best, sc, cfg, np.random.default_rng(1), best)
    assert refined.courteous and refined.t_merge <= best.t_merge
    # a plan braking at -3 m/s^2 throughout: the ego stops and stays, it never drives backwards
    plan = ceiling.OpenLoop(controls=np.tile([0.0, -3.0], (40, 1)), merge_tol=sc.merge_tol, label="brake", y_ref=sc.y_ref,
                            x_ref=sc.x_ref, car_length=sc.road.car_length, params=sc.params)
    o = ceiling.rollout(open_lane(sc), plan, sc, 40, 10)
    assert not o.courteous and o.controls[:, 1].min() >= -3.0 and o.miss == pytest.approx(sc.y_ref - sc.merge_tol)


def test_a_recorded_planner_run_replays_to_its_own_outcome_and_bounds_the_ceiling(tmp_path):
    from planner import report, setup

    seed = 3_000_011
    pcfg = compose_cfg("planner", ["scenario=dense", "gradients=cv", "mpc=courteous", "method=admm", "plots=false",
                                   "max_steps=40", f"seed={seed}"])
    sc, source, s = setup.setup(pcfg)
    ep = setup.drive(pcfg, sc, source, s, "admm", seed=seed)
    report.write_csv(ep, tmp_path / f"steps_{seed}.csv")
    m = report.metrics(ep, sc)
    controls = ceiling.recorded([str(tmp_path / "steps_{seed}.csv")], [seed, seed + 1])
    assert [len(c) for c in controls[seed]] == [len(ep.rows)] and controls[seed + 1] == []
    run = ceiling.replay(sc.make_world(seed), controls[seed][0], sc, 40)
    assert (run.courteous, run.t_merge) == (bool(m["courteous"]), int(m["t_merge"]) if m["courteous"] else 40)
    assert run.b_imposed == m["b_imposed_max"]
    world = sc.make_world(seed)  # the states themselves, bit for bit
    for u in controls[seed][0]:
        world.step(u)
    np.testing.assert_array_equal(world.states(), ep.states[-1])
    # the job with that CSV as a start: the ceiling's row is at least the run
    cfg = compose_cfg("ceiling", ["scenario=dense", *SLOW, "refine.starts=0", "max_steps=40", f"seed={seed}", "episodes=1",
                                  "n_jobs=1", f"starts=['{tmp_path}/steps_{{seed}}.csv']", f"out_dir={tmp_path / 'out'}"])
    ceiling.run(cfg)
    row = pd.read_csv(tmp_path / "out" / "ceiling_dense.csv").iloc[0]
    assert row["starts"] == 1 and row["ceiling_courteous"] >= m["courteous"]
    if m["courteous"]:
        assert row["ceiling_t_merge"] <= m["t_merge"]


def test_bad_starts_are_one_clear_line(tmp_path, capsys):
    with pytest.raises(UserError, match="has no {seed}"):
        ceiling.recorded([str(tmp_path / "steps.csv")], [1])
    with pytest.raises(UserError, match=r"names no file for seeds 1\.\.2"):
        ceiling.recorded([str(tmp_path / "steps_{seed}.csv")], [1, 2])
    pd.DataFrame({"step": [1], "x": [0.0]}).to_csv(tmp_path / "steps_1.csv", index=False)
    with pytest.raises(UserError, match="steps_1.csv: no delta and a columns"):
        ceiling.recorded([str(tmp_path / "steps_{seed}.csv")], [1, 2])
    with pytest.raises(SystemExit) as e:
        ceiling.run(compose_cfg("ceiling", ["refine.elites=20", "refine.samples=4", f"out_dir={tmp_path / 'out'}"]))
    assert e.value.code == 2 and not (tmp_path / "out").exists()
    assert capsys.readouterr().err.strip().endswith("error: refine.elites=20: more than the 4 samples it picks from")


# dense, random and two_lane worlds as they were before scenario.cooperation existed (git 23ca2f8): hidden decisions,
# the sum of every start state and of every driver's eta_coop
BEFORE = {("dense", 2000000): ("0011100100000011001111", -574.704008152, 9.324177784),
          ("dense", 2000001): ("0100011100100010000000", -272.100855697, 6.167405414),
          ("dense", 3000007): ("0010111111010000001101", -376.679642321, 8.699077109),
          ("random", 2000000): ("00111", 82.031173482, 2.786345277),
          ("random", 3000007): ("00001", 89.637230461, 1.161512212),
          ("two_lane", 2000000): ("00010", 86.27580394, 1.5)}


def test_mixed_cooperation_is_the_default_and_leaves_every_world_as_it_was():
    for (name, seed), (decisions, z_sum, eta_sum) in BEFORE.items():
        for sc in (scenario(name), scenario(name, "scenario.cooperation=mixed")):
            w = sc.make_world(seed)
            assert "".join(str(int(b)) for b in w.decisions()) == decisions, (name, seed)
            assert w.states().sum() == pytest.approx(z_sum, abs=1e-8)
            assert sum(d.eta_coop for d in w.drivers) == pytest.approx(eta_sum, abs=1e-8)


def test_cooperation_levels_set_the_hidden_decisions_and_nothing_else():
    mixed = scenario("dense")
    for level, eta in (("stubborn", 0.0), ("willing", 1.0)):
        sc = scenario("dense", f"scenario.cooperation={level}")
        for seed in (2000000, 2000001, 3000007):
            w, m = sc.make_world(seed), mixed.make_world(seed)
            assert not w.decisions()[0] and (w.decisions()[1:] == bool(eta)).all()
            assert {d.eta_coop for d in w.drivers} == {eta}
            np.testing.assert_array_equal(w.states(), m.states())  # the same start, speeds and drivers otherwise
            assert [d.__dict__ | {"eta_coop": 0} for d in w.drivers] == [d.__dict__ | {"eta_coop": 0} for d in m.drivers]
            assert (w.redrawn(np.random.default_rng(0)).decisions()[1:] == bool(eta)).all()  # the prior agrees
    # the fixed scenarios' drivers too: two_lane's cooperative driver stops yielding
    assert not scenario("two_lane", "scenario.cooperation=stubborn").make_world(0).decisions().any()
    with pytest.raises(UserError, match="scenario.cooperation=polite: must be one of stubborn, mixed, willing"):
        build(compose_cfg("ceiling", ["scenario.cooperation=polite"]).scenario)


def test_the_paired_t_merge_ratio_resamples_worlds_not_medians():
    planner, ceiling_t = np.array([40.0, 33.0, 30.0, 60.0]), np.array([20.0, 33.0, 30.0, 30.0])
    mean, lo, hi = stats.paired_ratio(planner, ceiling_t, 2000, seed=0)
    assert mean == pytest.approx(1.5)  # (2 + 1 + 1 + 2) / 4; the ratio of medians would be 36.5 / 31.5
    assert 1.0 <= lo < mean < hi <= 2.0  # every resample's mean lies between the smallest and largest ratio
    draws, by_hand = np.random.default_rng(0), []  # the same resamples by hand: 4 worlds drawn with replacement
    for _ in range(2000):
        draws.integers(1, size=1)  # the group drawn (there is one: the worlds)
        by_hand.append(np.mean((planner / ceiling_t)[draws.integers(4, size=4)]))
    assert [lo, hi] == pytest.approx(np.percentile(by_hand, [2.5, 97.5]))
    assert all(np.isnan(stats.paired_ratio([], [], 100, seed=0)))


def test_ceiling_on_ray_gives_the_rows_of_local_processes(tmp_path):
    ray = pytest.importorskip("ray")
    tiny = ["search.gaps=0", "search.y_lean=[1.8]", "search.clearance=[1.0]", "search.enter=[4]", "search.dv=[0.0]",
            "search.y_wait=[1.8]", "search.accept_dv=[-10.0]", "refine.iterations=1", "refine.samples=3", "refine.elites=1",
            "episodes=2", "seed=2000000", "max_steps=40"]
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        ceiling.run(compose_cfg("ceiling", [*tiny, "backend=ray", "n_jobs=2", f"out_dir={tmp_path / 'ray'}"]))
    finally:
        ray.shutdown()
    ceiling.run(compose_cfg("ceiling", [*tiny, "n_jobs=1", f"out_dir={tmp_path / 'loky'}"]))
    on_ray, local = (pd.read_csv(tmp_path / d / "ceiling_dense.csv").drop(columns="cpu_seconds") for d in ("ray", "loky"))
    pd.testing.assert_frame_equal(on_ray, local)
    assert list(local["seed"]) == [2000000, 2000001]
