"""Physics, courtesy metrics, perception and the clairvoyant ceiling on hand-built worlds and the dense scenario."""
import numpy as np
import pandas as pd
import pytest
from hydra.utils import instantiate

from bench import ceiling
from conftest import compose_cfg
from data import outcomes, perception
from data.drivers import IDMDriver
from data.world import World, backfill


def scenario(name, *overrides):
    """The scenario `name` of the ceiling's config, with `scenario.k=v` overrides."""
    return instantiate(compose_cfg("ceiling", [f"scenario={name}", *overrides]).scenario, _convert_="all")


def lane_world(z, will_yield, **driver):
    """Two-lane world of states z (M, 4) with the two_lane scenario's road, bicycle and b_max, one driver per other car."""
    sc = scenario("two_lane")
    return World(sc.road, np.array(z, float), [IDMDriver(**driver) for _ in z[1:]], np.array(will_yield), sc.b_max,
                 params=sc.params)


def test_a_cut_in_with_no_room_brakes_at_exactly_b_max_and_collides():
    # the ego dropped into the follower's lane 0.2 m ahead of its bumper, both at 5 m/s: no braking can avoid it
    sc = scenario("two_lane")
    world = lane_world([[10.0 + sc.road.car_length + 0.2, 4.0, 0.0, 3.0], [10.0, 4.0, 0.0, 5.0]], [False, False])
    hits = []
    for _ in range(3):
        hits += world.step([0.0, 0.0])
    v = np.array([s[1, 3] for s in world.seen])
    assert -np.diff(v)[0] / sc.params.dt == pytest.approx(sc.b_max)  # plain IDM asks for far more
    assert (0, 1) in hits


def test_imposed_braking_courtesy_and_ttc_on_a_hand_built_episode():
    dt = 0.2
    states = np.zeros((4, 3, 4))
    states[:, 1, 3] = [5.0, 4.6, 3.8, 3.9]  # car 1 brakes at 2, then 4, then speeds up
    states[:, 2, 3] = [5.0, 5.0, 4.0, 3.0]  # car 2 brakes at 0, 5, 5
    assert outcomes.b_imposed_max(states, dt) == pytest.approx(5.0)
    assert outcomes.courteous(True, False, 5.0, 4.0) == 0.0
    assert outcomes.courteous(True, False, 3.9, 4.0) == 1.0
    assert outcomes.courteous(False, False, 0.0, 4.0) == 0.0 and outcomes.courteous(True, True, 0.0, 4.0) == 0.0
    road = scenario("two_lane").road
    z = np.array([[0.0, 4.0, 0.0, 6.0], [10.0, 4.0, 0.0, 4.0], [-8.0, 4.0, 0.0, 7.0], [5.0, 0.0, 0.0, 0.0]])
    # ahead: gap 10 - 3.6 at 2 m/s closing = 3.2 s; behind: 8 - 3.6 at 1 m/s = 4.4 s; car 3 is in another lane
    assert outcomes.ttc(z, road) == pytest.approx((10.0 - road.car_length) / 2.0)
    z[1, 3] = 7.0
    assert outcomes.ttc(z, road) == pytest.approx(8.0 - road.car_length)


def test_never_yield_copy_never_yields():
    sc = scenario("two_lane")
    world = sc.make_world(0)
    assert world.decisions()[1:].any()  # two_lane holds a cooperative driver
    stubborn = world.with_decisions(np.zeros(len(world.states()), bool))
    assert not stubborn.decisions().any() and world.decisions()[1:].any()  # a copy: the original keeps its drivers
    policy = ceiling.GapPolicy(sc.y_ref, sc.x_ref, 0, 1.8, 1.0, sc.road.car_length, sc.params)
    target = policy.pick(stubborn.states())
    for _ in range(30):
        stubborn.step(policy(stubborn.states(), target, 0))
        assert not stubborn.yielding.any()


def test_slots_are_the_nearest_cars_in_id_order_with_their_own_histories():
    sc = scenario("dense")
    world = sc.make_world(5)
    for _ in range(12):
        world.step([0.05, 1.0])  # the ego drifts forward and left: the nearest cars change
    z = world.states()
    seen = perception.observe(world, 4, 8)
    d = np.hypot(*(z[1:, :2] - z[0, :2]).T)
    assert list(seen.ids) == [0, *sorted(np.argsort(d)[:4] + 1)]
    past = np.array([s[:, :2] for s in world.seen[-8:]])
    assert np.array_equal(seen.history, past[:, seen.ids])  # every slot carries its own car's observed past
    fresh = sc.make_world(5)
    assert np.allclose(perception.observe(fresh, 4, 8).history[:, 0], backfill(fresh.states(), 8, sc.params.dt)[:, 0])


@pytest.mark.parametrize("name", ["dense", "dense_three_lane", "random", "two_lane", "three_lane"])
def test_traffic_is_calm_with_the_ego_held_in_its_lane(name):
    sc = scenario(name)
    for seed in range(3):
        assert ceiling.held_in_lane(sc.make_world(seed), sc, 60) <= 2.0, f"seed {seed}"


def test_a_stream_too_short_for_its_promise_is_one_clear_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        ceiling.run(compose_cfg("ceiling", ["scenario.followers=6", f"out_dir={tmp_path / 'out'}"]))
    assert e.value.code == 2 and not (tmp_path / "out").exists()
    assert capsys.readouterr().err.startswith("error: scenario.followers=6: the stream may reach only 2 m behind the ego")


def test_ceiling_merges_where_a_known_strategy_works_and_fails_where_none_can():
    cfg = compose_cfg("ceiling", ["scenario=dense", "search.gaps=1", "search.y_lean=[1.8]", "search.clearance=[1.0]",
                                  "search.enter=[0, 10]", "search.dv=[0.0]", "search.y_wait=[0.0]", "search.accept_dv=[0.0]"])
    sc = scenario("dense")
    # one wide gap beside the ego: entering needs nobody to yield
    open_lane = lane_world([[9.2, 0.0, 0.0, 5.0], [30.0, 4.0, 0.0, 5.0], [2.0, 4.0, 0.0, 5.0], [-6.0, 4.0, 0.0, 5.0]],
                           [False] * 4, v0=5.0)
    best = ceiling.search_world(open_lane, sc, cfg)[1]
    assert best.courteous and best.t_merge < 20
    # bumper to bumper, nobody yields, and the lane ends 10 m ahead: no courteous merge exists
    closed = lane_world([[9.2, 0.0, 0.0, 5.0]] + [[x, 4.0, 0.0, 5.0] for x in np.arange(40.0, -40.0, -4.0)],
                        [False] * 21, v0=5.0, T=0.1, s0=0.4)
    walled = instantiate(compose_cfg("ceiling", ["scenario=dense", "scenario.x_ref=20"]).scenario, _convert_="all")
    assert not ceiling.search_world(closed, walled, cfg)[1].courteous


def test_the_best_fixed_strategy_is_chosen_on_other_worlds_and_driven_on_the_batch(tmp_path, capsys):
    tiny = ["search.gaps=0", "search.y_lean=[1.8]", "search.clearance=[1.0]", "search.enter=[1000]", "search.dv=[0.0]",
            "search.y_wait=[0.0]", "search.accept_dv=[-10.0]", "n_jobs=1"]  # a cut-in that never turns in, and two
    cfg = compose_cfg("ceiling", [*tiny, "episodes=2", "blind.episodes=3", f"out_dir={tmp_path / 'out'}"])
    sc = scenario("dense")
    names = [p.name for p in ceiling.policies(sc, cfg.search)]
    assert len(names) == 3 and names[0].startswith("cut in at step 1000")
    hits = np.array([ceiling.courteous_strategies(sc, cfg, 3_000_000 + k) for k in range(3)])
    assert not hits[:, 0].any() and hits.any()  # the cut-in never merges; the gap-takers do somewhere
    policy, share = ceiling.blind_strategy(sc, cfg)
    best = names.index(policy.name)
    assert share == hits.mean(0).max() and hits[:, best].mean() == share and best != 0
    r = ceiling.run(cfg)
    rows = pd.read_csv(tmp_path / "out" / "ceiling_dense.csv")
    assert set(rows["blind_policy"]) == {names[best]} and r["blind_courteous"] == rows["blind_courteous"].mean()
    # chosen on the batch's own worlds it would know them: refused, nothing written
    with pytest.raises(SystemExit) as e:
        ceiling.run(compose_cfg("ceiling", [*tiny, "episodes=2", "blind.seed=2000001", "blind.episodes=3",
                                            f"out_dir={tmp_path / 'again'}"]))
    assert e.value.code == 2 and not (tmp_path / "again").exists()
    assert capsys.readouterr().err.strip().endswith("error: blind.seed=2000001: its 3 worlds overlap the batch's (seed "
                                                    "2000000, 2 episodes); the strategy must be chosen on other worlds")


def test_gap_acceptance_turns_in_ahead_of_a_car_stopped_for_it_and_never_reverses():
    sc = scenario("dense")
    policy = ceiling.AcceptPolicy(y_ref=sc.y_ref, x_ref=sc.x_ref, y_wait=1.8, dv=-10.0, clearance=0.5,
                                  car_length=sc.road.car_length, params=sc.params)
    ego = [20.0, 1.8, 0.3, 0.0]  # waiting at a standstill, leaning in
    front = [28.0, 4.0, 0.0, 5.0]  # room ahead
    for v_back, turns in [(0.0, True), (5.0, False)]:  # the car beside, its front past the ego's rear
        delta, a = policy(np.array([ego, front, [17.0, 4.0, 0.0, v_back]]), None, 0)
        assert (a > 0.0) == turns and (delta > 0.0) == turns
    # IDM asks for full braking behind a stopped car 0.5 m ahead: at 0.1 m/s the ego stops within the step, not reverses
    stopped_ahead = [20.0 + sc.road.car_length + 0.5, 4.0, 0.0, 0.0]
    _, a = policy(np.array([[20.0, 1.8, 0.3, 0.1], stopped_ahead, [17.0, 4.0, 0.0, 0.0]]), None, 0)
    assert a == pytest.approx(-0.1 / sc.params.dt)


def test_ceiling_refuses_the_predictor_world(capsys):
    with pytest.raises(SystemExit) as e:
        ceiling.run(compose_cfg("ceiling", ["world=predictor", "episodes=1"]))
    assert e.value.code == 2
    assert capsys.readouterr().err.strip() == "error: world=predictor: the ceiling searches copies of the true world; " \
                                               "it needs world=reactive"
