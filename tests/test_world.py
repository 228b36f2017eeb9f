"""Drivers and the merge world: IDM equilibrium, no collisions in plain traffic, yielding vs stubborn drivers."""
import numpy as np
import pytest
from hydra.utils import instantiate

from conftest import compose_cfg
from data.dataset import rollout
from data.drivers import IDMDriver
from data.policies import ProbePolicy
from data.world import World, overlap


def scenario(name, **overrides):
    return instantiate(compose_cfg("make_dataset", [f"scenario={name}"] + [f"scenario.{k}={v}" for k, v in overrides.items()]).scenario,
                       _convert_="all")


TWO_LANE = scenario("two_lane")  # its road, bicycle and b_max, read only


def test_idm_equilibrium_gap_is_a_rest_point_and_is_reached():
    d = IDMDriver(v0=7.0, T=0.4, s0=1.2)
    s_eq = d.equilibrium_gap(5.0)
    assert d.acceleration(5.0, s_eq, 5.0) == pytest.approx(0.0, abs=1e-9)
    road = TWO_LANE.road
    leader = IDMDriver(v0=5.0)
    z = np.array([[-200.0, 0.0, 0.0, 0.0], [50.0, 4.0, 0.0, 5.0], [30.0, 4.0, 0.0, 5.0]])  # ego parked far behind
    world = World(road, z, [leader, d], np.zeros(3, bool), TWO_LANE.b_max, TWO_LANE.params)
    for _ in range(600):
        world.step([0.0, 0.0])
    gap = world.z[1, 0] - world.z[2, 0] - road.car_length
    assert gap == pytest.approx(s_eq, rel=0.02)
    assert world.z[2, 3] == pytest.approx(5.0, rel=0.01)


def test_plain_traffic_never_collides():
    sc = scenario("random")
    for seed in range(12):
        states, _, world, _ = rollout(sc, ProbePolicy(y_ref=sc.y_ref, keep_lane=True, v_target=4.0), seed, 80)
        assert world.collisions == [], f"seed {seed}"
        assert len(states) == 81


def test_overlap_detects_touching_bodies_only():
    road = TWO_LANE.road
    length, width = road.car_length, road.car_width
    a = np.array([0.0, 0.0, 0.0, 0.0])
    assert overlap(a, np.array([length - 0.1, 0.0, 0.0, 0.0]), road)
    assert not overlap(a, np.array([length + 0.1, 0.0, 0.0, 0.0]), road)
    assert not overlap(a, np.array([0.0, width + 0.1, 0.0, 0.0]), road)
    assert overlap(a, np.array([2.0, 1.5, 0.3, 0.0]), road)


def x_behind_gap(sc, nudge: bool):
    """Position (m) after 6 s of the car behind the ego's slot (slot 3), with the ego nudging or staying."""
    policy = ProbePolicy(y_ref=sc.y_ref, keep_lane=not nudge, t_start=0.2, y_nudge=1.6, hold=100.0, v_target=5.0)
    states, flags, world, _ = rollout(sc, policy, seed=0, steps=30)
    assert world.collisions == []
    return states[-1, 3, 0], flags["yielding"]


def test_yielding_driver_opens_a_gap_when_nudged():
    sc = scenario("two_lane")
    stay, _ = x_behind_gap(sc, nudge=False)
    nudged, yielding = x_behind_gap(sc, nudge=True)
    assert yielding[:, 3].any() and not yielding[:, [1, 2]].any()  # cars ahead of the ego never yield
    assert nudged < stay - 1.5


def test_stubborn_driver_holds_its_gap_when_nudged():
    sc = scenario("two_lane")
    sc.drivers = [dict(d, eta_coop=0.0) for d in sc.drivers]
    stay, _ = x_behind_gap(sc, nudge=False)
    nudged, yielding = x_behind_gap(sc, nudge=True)
    assert not yielding.any()
    assert nudged == pytest.approx(stay, abs=1e-6)


def test_three_lane_yielder_moves_left_when_nudged():
    sc = scenario("three_lane")
    policy = ProbePolicy(y_ref=sc.y_ref, t_start=0.2, y_nudge=1.6, hold=100.0)
    states, _, world, _ = rollout(sc, policy, seed=0, steps=40)
    assert world.collisions == []
    assert states[-1, 3, 1] > 6.0  # the yielding car changed into the leftmost lane (centre y = 8 m)
    keep = rollout(sc, ProbePolicy(y_ref=sc.y_ref, keep_lane=True), seed=0, steps=40)[0]
    assert np.abs(keep[:, 1:, 1] - 4.0).max() < 0.1  # without the nudge nobody moves


def yielder_world(ego_y, dx=8.0, **driver):
    """Ego standing dx m ahead of one yielding car (lane 1), at lateral position ego_y (m)."""
    z = np.array([[dx, ego_y, 0.0, 0.0], [0.0, 4.0, 0.0, 5.0]])
    return World(TWO_LANE.road, z, [IDMDriver(**driver)], np.array([False, True]), TWO_LANE.b_max, TWO_LANE.params)


def test_response_follows_the_encroachment_depth_with_a_first_order_lag():
    d = IDMDriver()
    for ego_y in (0.5, 1.6, 1.9):
        world = yielder_world(ego_y)
        w = float(np.clip((d.d_react - (4.0 - ego_y)) / d.d_ramp, 0.0, 1.0))
        for k in range(1, 11):
            world.respond()  # the scene stands still: the perceived encroachment is w at every step
            assert world.response[1] == pytest.approx(w * (1 - (1 - world.params.dt / d.t_ramp) ** k))
    stubborn = yielder_world(1.9)
    stubborn.will_yield[:] = False
    stubborn.respond()  # it withholds the same response: it keeps its own acceleration, and an observer sees it refuse
    assert stubborn.response[1] == pytest.approx(w * world.params.dt / d.t_ramp)  # w: the last (1.9 m) lean
    assert not stubborn.yielding[1] and not stubborn.refused[1]
    idm = stubborn.idm_to(1, stubborn.leader(1, int(stubborn.target_lane[1])))
    assert stubborn.acceleration(1) == idm
    stubborn.response[1] = 1.0
    assert stubborn.acceleration(1) == idm and stubborn.refused[1] and not stubborn.shown[1]


def test_response_starts_after_the_reaction_delay():
    world = yielder_world(0.0, reaction_delay=0.6, dx=3.0)
    world.step([0.0, 0.0])
    world.z[0, 1] = 1.9  # the ego jumps from its lane centre to 2.1 m from the car's lane centre at t = 0.2 s
    world.seen[-1] = world.z.copy()
    started = []
    for _ in range(6):
        world.step([0.0, 0.0])
        started.append(bool(world.response[1] > 0))
    assert started == [False, False, False, True, True, True]  # the step at t = 0.2 + 0.6 s is the first to see it


def test_yielder_gives_way_gradually_with_the_nudge_depth():
    sc = scenario("two_lane")
    stay, _ = x_behind_gap(sc, nudge=False)
    lost = []
    for y_nudge in np.arange(1.0, 2.01, 0.2):
        policy = ProbePolicy(y_ref=sc.y_ref, t_start=0.2, y_nudge=float(y_nudge), hold=100.0, v_target=5.0)
        lost.append(stay - rollout(sc, policy, seed=0, steps=30)[0][-1, 3, 0])
    assert lost[0] == pytest.approx(0.0, abs=1e-6)  # 1.0 m from the lane border: outside d_react
    assert np.all(np.diff(lost) >= -1e-6) and lost[-1] > 1.5
    assert np.diff(lost).max() < 0.6 * lost[-1]  # no single threshold carries the response
