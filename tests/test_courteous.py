"""mpc=courteous: the safeguard's repair of plans that miss the check, the Rules strategy's starts and choice, and its
config; the courtesy rows' values and derivatives are checked in test_compiled_core."""
import re
from dataclasses import replace

import numpy as np
import pytest

from conftest import compose_cfg
from core.jobs import UserError
from core.rollout import b_i
from planner import admm, mpc, safeguard, step
from planner.safety import Safety
from planner.setup import make
from planner.strategy import FOLLOWER, Paper, Start


@pytest.fixture(scope="module")
def beside():
    """mpc=courteous settings and cv on two_lane, the ego leaning in by 1.9 m at 5 m/s level with a car in the target
    lane: on the edge of the safety shape (R = 2.1 m across)."""
    _, source, s = make("two_lane", ["gradients=cv", "mpc=courteous"])
    z0 = np.array([0.0, 1.9, 0.0, 5.0])
    cars = np.array([[0.5, 4.0], [60.0, 4.0], [80.0, 4.0], [100.0, 4.0]])
    history = np.stack([np.vstack([z0[:2], cars]) - [5.0 * 0.2 * k, 0.0] for k in range(7, -1, -1)])
    return s, source, mpc.Observation(z0, np.zeros(2), history)


@pytest.mark.parametrize("steer", [0.05, 0.07])
def test_repair_turns_a_miss_of_centimetres_into_a_plan_that_passes_with_the_least_change(beside, steer):
    s, source, obs = beside
    Delta, alpha = np.full(s.T_p, steer), np.zeros(s.T_p)  # drifting at the car beside
    b_min, Z = safeguard.plan_safe(s, obs, source, Delta, alpha)
    assert -0.5 < b_min < -safeguard.CHECK_TOL  # 2.1 m across: 0.5 m^2 is 12 cm
    fixed, b_fixed, _ = safeguard.repaired(s, obs, source, Safety(source, obs.history, s.R, s.T_p, stretch=s.stretch, p=s.shape),
                                  admm.ADMMState(Delta, alpha, Z, np.zeros(4 * s.T_p)))
    assert b_fixed == pytest.approx(safeguard.plan_safe(s, obs, source, fixed.Delta, fixed.alpha)[0])
    assert b_fixed >= safeguard.REPAIR_MARGIN - 0.05 and np.allclose(fixed.Z, mpc.simulate(obs.z0, fixed.Delta, fixed.alpha, s.params))
    assert 0.0 < np.abs(fixed.Delta - Delta).max() < 0.15 and fixed.Delta[0] < steer  # steered a little less
    safe = np.full(s.T_p, -0.1)  # steering away: a plan that passes is left alone
    b_safe, Z = safeguard.plan_safe(s, obs, source, safe, alpha)
    out = safeguard.repaired(s, obs, source, Safety(source, obs.history, s.R, s.T_p, stretch=s.stretch, p=s.shape), admm.ADMMState(safe, alpha, Z, 0 * Z))
    assert out[1] == pytest.approx(b_safe, abs=1e-6) and np.allclose(out[0].Delta, safe, atol=1e-6)


def test_the_choice_puts_predicted_excess_braking_first_then_a_merge_then_the_starts_order(beside):
    s = beside[0]

    def plan(J, braking, y_end, rank=0):  # a StepResult whose plan ends at lateral position y_end (m)
        Z = np.zeros(4 * s.T_p)
        Z[-3] = y_end
        return mpc.StepResult(np.zeros(2), admm.ADMMState(None, None, Z, None), J, 1, "converged", 0.0, 0.0, 0.0, "",
                              braking=braking, values=values), rank

    values = np.tile([[0.0, 0.0], [-200.0, 0.0]], (s.T_p, 2, 1))  # nobody behind the ego: the follower brakes for none

    merge, wait = 4.0, 1.8  # y_ref = 4 m: in the target lane; leaning in, still in the ego's lane
    forcing, waiting, gentle = plan(1.0, 9.0, merge), plan(5.0, 0.5, wait, 1), plan(4.0, 2.9, merge)  # braking m/s^2
    obs = mpc.Observation(np.array([0.0, wait, 0.0, 5.0]), np.zeros(2), np.tile(values[:1], (8, 1, 1)))
    pick = lambda *named: s.strategy.choose(s, obs, [(Start(n, None, s, rank), r) for n, (r, rank) in named])[0].name
    assert pick(("force", forcing), ("wait", waiting)) == "wait"
    assert pick(("wait", waiting), ("gentle", gentle)) == "gentle"  # both under b_courtesy: the merge
    assert pick(("force", forcing), ("worse", plan(0.5, 9.5, merge))) == "force"
    assert pick(("merge", plan(9.0, 0.0, merge)), ("cheaper merge", plan(8.0, 0.0, merge))) == "cheaper merge"
    # without a merge the first start's plan, not the cheapest: the shifted plan's J pulls towards the gap
    shifted = plan(1.0, 0.0, 1.9, s.strategy.candidates(s, obs, None, None)[0].rank)
    assert pick(("shifted", shifted), ("lean", plan(7.0, 0.0, wait, 1)), ("lane", plan(6.0, 0.0, 0.0, 2))) == "lean"
    # the lean start's plan lost (failed, or imposes braking): the shifted plan leans on instead of dropping back
    assert pick(("shifted", shifted), ("lane", plan(6.0, 0.0, 0.0, 2))) == "shifted"
    assert pick(("only", forcing)) == "only"
    # cv predicts no braking, but the nominal follower, a car 2 m behind the plan's end in the lane it enters, would
    car = lambda k: [[0.0, wait], [-10.0 + 5.0 * s.params.dt * k, 4.0], [-200.0, 0.0], [-200.0, 0.0]]
    seen = obs._replace(history=np.array([car(k) for k in range(-7, 1)]))
    forced = plan(1.0, 0.0, merge)[0]._replace(values=np.array([car(k) for k in range(1, s.T_p + 1)]))
    held = waiting[0]._replace(values=forced.values)
    chosen = s.strategy.choose(s, seen, [(Start("force", None, s, 0), forced), (Start("wait", None, s, 1), held)])
    assert chosen[0].name == "wait" and chosen[1].follower_braking == 0.0
    assert s.strategy.follower_braking(s, seen, forced.plan.Z, forced.values) > 9.0


def _idm(v, gap, v_lead, v0=7.0, T=0.4, s0=1.2, a_max=2.0, b=2.0, delta=4.0):
    """IDM's acceleration (m/s^2) written out from Treiber et al. (2000), independently of data.drivers."""
    s_star = s0 + max(0.0, v * T + v * (v - v_lead) / (2.0 * (a_max * b) ** 0.5))
    return a_max * (1.0 - (v / v0) ** delta - (s_star / gap) ** 2)


def test_the_nominal_follower_brakes_as_idm_behind_a_plan_that_enters_its_lane_and_only_then(beside):
    s, dt = beside[0], beside[0].params.dt
    z0 = np.array([0.0, 1.8, 0.0, 5.0])
    T = np.arange(1, s.T_p + 1)
    y = np.minimum(1.8 + 0.5 * T, 4.0)  # the plan enters the target lane (centre 4 m) at step 1 (y 2.3 m: lane 1)
    Z = np.stack([5.0 * dt * T, y, 0 * T, np.full(s.T_p, 5.0)], 1).ravel()
    behind, ahead = -6.0, 20.0  # x of a car behind the ego at 6 m/s and one ahead at 4 m/s at t = 0 (m)
    track = lambda x0, v, k: [x0 + v * dt * k, 4.0]
    far = [-200.0, 0.0]  # parked far behind in the ego's lane: free road for IDM, no braking
    values = np.array([[Z[4 * (k - 1):4 * (k - 1) + 2], track(behind, 6.0, k), track(ahead, 4.0, k), far, far]
                       for k in T])
    history = np.array([[z0[:2], track(behind, 6.0, k), track(ahead, 4.0, k), far, far] for k in range(-7, 1)])
    obs = mpc.Observation(z0, np.zeros(2), history)
    # the nominal follower of mpc=courteous: IDM with the cautious end of the dense drivers' headway and gap
    want = max(0.0, max(-_idm(6.0, 5.0 * dt * k - (behind + 6.0 * dt * k) - 3.6, 5.0, T=0.5, s0=1.6) for k in T))
    assert want > 4.0  # closing in at 1 m/s from 2.4 m: a forced merge by IDM, which cv predicts as no braking at all
    assert s.strategy.follower_braking(s, obs, Z, values) == pytest.approx(want, rel=1e-9)
    in_lane = Z.reshape(-1, 4).copy()
    in_lane[:, 1] = 1.8  # the same plan leaning, not entering: nobody follows it
    assert s.strategy.follower_braking(s, obs, in_lane.ravel(), values) == 0.0
    leaving = values.copy()
    leaving[:, 1, 1] = 1.9  # predicted out of the lane already; last seen in the lane the plan enters, so it still counts
    assert s.strategy.follower_braking(s, obs, Z, leaving) == pytest.approx(want, rel=1e-9)  # (the world has a car changing
    # lanes follow the leaders of both)
    inside = obs._replace(z0=np.array([0.0, 2.1, 0.0, 5.0]))  # halfway in: the lane it enters is its own now
    assert s.strategy.follower_braking(s, inside, Z, values) == pytest.approx(want, rel=1e-9)
    assert isinstance(make("two_lane", ["gradients=cv"])[2].strategy, Paper)  # the paper's step judges no gap


def test_the_nominal_follower_is_no_more_tolerant_than_any_dense_driver_on_headway_and_gap():
    ranges = compose_cfg("planner", ["scenario=dense"]).scenario.driver_ranges
    assert (FOLLOWER.T, FOLLOWER.s0) == (max(ranges.T), max(ranges.s0))


def _stream(s, back_x, back_v, back_a, front_v=5.0):
    """An observation with the ego leaning in at 1 m/s, a target-lane car ahead at front_v and one behind at back_x (m)
    now, driving at back_v (m/s) and accelerating at back_a (m/s^2) over the observed steps."""
    k = np.arange(-7, 1) * s.params.dt
    ego = np.stack([1.0 * k, np.full(8, 1.9)], 1)
    front = np.stack([8.0 + front_v * k, np.full(8, 4.0)], 1)
    back = np.stack([back_x + back_v * k + 0.5 * back_a * k**2, np.full(8, 4.0)], 1)
    far = np.stack([np.full(8, -60.0), np.full(8, 4.0)], 1)
    return mpc.Observation(np.array([0.0, 1.9, 0.0, 1.0]), np.zeros(2), np.stack([ego, front, back, far, far], 1))


@pytest.mark.parametrize("back_x, back_v, back_a, v_lean", [
    (-3.0, 3.0, -2.0, 4.2),  # braking for the ego: the lean aims at its speed over the last step (3.2 m/s) + 1 m/s
    (-3.0, 4.0, 0.0, 5.0),  # 1 m/s slower than the car ahead: yielding too
    (-3.0, 5.0, 0.0, None),  # with the stream: let it pass, at the lean's own speed
    (-8.0, 3.0, -2.0, None),  # braking, but beyond KEEP_AHEAD.near (6 m)
])
def test_a_lean_beside_a_car_seen_yielding_keeps_ahead_of_it_and_otherwise_keeps_its_speed(beside, back_x, back_v, back_a, v_lean):
    s = beside[0]
    obs = _stream(s, back_x, back_v, back_a)
    starts = {st.name.split(",")[0]: st.aim.v_ref for st in s.strategy.candidates(s, obs, None, None)[1:]}
    own = s.strategy.starts[0][2]
    assert starts == {"y +1.9 m": pytest.approx(own if v_lean is None else v_lean, abs=1e-9), "y +0.0 m": s.v_ref}


def test_a_courteous_step_reports_its_solve_and_the_paper_step_has_none_of_it(beside):
    s, source, obs = beside
    result = step.mpc_step(s, obs, source, None, _sqp())
    assert result.fallback == "" and ", from " in result.reason and result.c_min >= 0.0  # cv predicts no braking at all
    assert result.braking == 0.0
    paper = make("two_lane", ["gradients=cv"])[2]
    assert paper.b_courtesy is None and paper.repair_iters == 0 and len(paper.strategy.candidates(paper, obs, None, None)) == 1
    assert "from" not in step.mpc_step(paper, obs, source, None, _sqp()).reason


def _sqp():
    """The bound sqp Z-step of the planner's config."""
    from hydra.utils import instantiate

    from planner.setup import planner_config

    return instantiate(planner_config("two_lane", ["gradients=cv"]).solver.step).keywords["zstep"]


@pytest.mark.parametrize("override", ["solver=ipopt", "zstep=pygranso"])
def test_courtesy_rows_with_a_solver_that_cannot_hold_them_is_one_line(override):
    with pytest.raises(UserError, match=r"^mpc=courteous has courtesy rows, which only solver=admm with zstep=sqp solves"):
        make("two_lane", ["gradients=cv", "mpc=courteous", override])


def test_the_breakdown_puts_each_world_in_one_class_against_the_ceiling():
    from bench import breakdown

    ep = lambda seed, merged=1.0, t=30.0, b=2.0, hit=0.0, falls=0.0: {
        "seed": seed, "merged": merged, "t_merge": t, "b_imposed_max": b, "collision": hit, "fallbacks": falls}
    worlds = [{"seed": k, "ceiling_courteous": float(k != 5), "ceiling_t_merge": 25.0 if k != 5 else 60.0} for k in range(7)]
    episodes = [ep(0), ep(1, t=33.0), ep(2, b=6.0), ep(3, merged=0.0, t=60.0, falls=12), ep(4, merged=0.0, t=60.0),
                ep(5, t=50.0), ep(6, hit=1.0, b=9.0), ep(7)]  # seed 7: no ceiling world, left out
    counts = breakdown.breakdown(episodes, worlds, 4.0)
    assert counts == {"courteous": (2, 1), "too slow": (1, 1), "forced": (1, 1), "collision": (1, 1),
                      "fallback loop": (1, 1), "ran out of road": (1, 1)}


def test_with_a_predictor_that_expects_hard_braking_the_courteous_step_waits_where_the_others_force():
    """two_lane, world 2,000,000: the analytic predictor made to expect a car to brake hard for an ego cutting in ahead
    of it (slowdown 0.6: up to 15 m/s^2 at 5 m/s). The courteous step's courtesy rows and its waiting solve keep the
    ego out of the gap; the paper's step with the same predictor, and with cv, force it."""
    from data import outcomes
    from planner.setup import drive, planner_config, setup

    def braking(*overrides):
        cfg = planner_config("two_lane", ["seed=2000000", *overrides])
        scenario, source, s = setup(cfg)
        ep = drive(cfg, scenario, source, s, "admm")
        return outcomes.b_imposed_max(ep.states, scenario.params.dt), scenario

    waits, scenario = braking("gradients=analytic", "predictor.slowdown=0.6", "mpc=courteous")
    assert waits <= 1.0  # nobody brakes for it: it never took the gap
    assert braking("gradients=analytic", "predictor.slowdown=0.6")[0] == pytest.approx(scenario.b_max)
    assert braking("gradients=cv")[0] == pytest.approx(scenario.b_max)


def test_a_superellipse_that_does_not_cover_the_bodies_is_one_line_and_the_courteous_one_covers_them():
    s = make("dense", ["gradients=cv", "mpc=courteous"])[2]
    dx, dy = 1.8 + 1.8 * np.cos(0.25) + 0.8 * np.sin(0.25), 0.8 + 1.8 * np.sin(0.25) + 0.8 * np.cos(0.25)  # by hand
    assert b_i(np.array([[[0.0, 0.0], [dx, dy]]]), s.R, s.stretch, s.shape)[0, 0] <= 0  # the corner lies inside
    assert b_i(np.array([[[0.0, 0.0], [0.0, 2.11]]]), s.R, s.stretch, s.shape)[0, 0] > 0  # leaning 1.9 m beside a car
    with pytest.raises(UserError, match=r"^mpc.shape=6 with R=2.1 m and mpc.stretch=2.4 does not cover two 3.6 x 1.6 m "
                                        r"bodies with the ego yawed up to 0.4 rad \(mpc.psi_box\)"):
        make("dense", ["gradients=cv", "mpc=courteous", "mpc.psi_box=[-0.4,0.4]"])


@pytest.mark.parametrize("starts", ["[[1.6,0.0]]", "[[1.8,-1.0,-1.0]]", "[[1.8,true,0.0]]", "[[nan,0.0,1.0]]"])
def test_a_start_that_is_not_offset_acceleration_speed_is_one_line(starts):
    with pytest.raises(UserError, match=r"^mpc.strategy.starts: \[.*\] must be \[offset m, a m/s\^2, v m/s >= 0 or null\]$"):
        make("dense", ["gradients=cv", "mpc=courteous", f"mpc.strategy.starts={starts}"])


@pytest.mark.parametrize("override,message", [
    ("mpc.repair_iters=-1", "mpc.repair_iters=-1: must be an integer >= 0"),
    ("mpc.b_courtesy=-2", "mpc.b_courtesy=-2: must be a number > 0 or null"),
    ("mpc.b_courtesy=nan", "mpc.b_courtesy=nan: must be a number > 0 or null"),
    ("mpc.T_p=0", "mpc.T_p=0: must be an integer in [1, 200]"),
])
def test_every_bad_value_of_the_step_is_one_line_naming_its_key(override, message):
    with pytest.raises(UserError, match="^" + re.escape(message) + "$"):
        make("dense", ["gradients=cv", "mpc=courteous", override])


@pytest.fixture(scope="module")
def clear_road():
    """mpc=courteous settings and cv on two_lane, the ego alone in lane 0 at 5 m/s, every other car far ahead."""
    _, source, s = make("two_lane", ["gradients=cv", "mpc=courteous"])
    z0 = np.array([0.0, 0.0, 0.0, 5.0])
    cars = np.array([[200.0, 4.0], [230.0, 4.0], [260.0, 4.0], [290.0, 4.0]])
    history = np.stack([np.vstack([z0[:2], cars]) - [5.0 * 0.2 * k, 0.0] for k in range(7, -1, -1)])
    return s, source, mpc.Observation(z0, np.zeros(2), history)


def test_a_plan_whose_car_yaws_beyond_what_the_safety_shape_covers_is_refused_then_repaired_within_it(clear_road):
    s, source, obs = clear_road
    Delta, alpha = np.full(s.T_p, 0.45), np.zeros(s.T_p)  # a hard left turn: far from any car, far beyond psi_box
    b_min, Z = safeguard.plan_safe(s, obs, source, Delta, alpha)
    psi = Z[2::4][:safeguard.CHECK_STEPS]
    assert b_min > 0 and psi.max() > s.psi_box[1] + 0.05  # b_i alone would pass it
    assert safeguard.yaw_excess(s, Z) == pytest.approx(psi.max() - s.psi_box[1])
    result, why = step.offered(s, obs, source, mpc.planned(s, obs.z0, Delta, alpha))
    assert result is None and re.search(r"yaw 0\.\d\d rad beyond mpc\.psi_box", why)
    fixed, _, _ = safeguard.repaired(s, obs, source, Safety(source, obs.history, s.R, s.T_p, stretch=s.stretch, p=s.shape),
                                     admm.ADMMState(Delta, alpha, Z, np.zeros(4 * s.T_p)))
    rolled = mpc.simulate(obs.z0, fixed.Delta, fixed.alpha, s.params)  # the bicycle itself, not the repair's linearisation
    assert np.abs(rolled[2::4][:safeguard.CHECK_STEPS]).max() <= s.psi_box[1] + safeguard.YAW_TOL


def test_the_paper_s_ellipse_leaves_the_yaw_to_its_config(clear_road):
    s, source, obs = clear_road
    Z = mpc.simulate(obs.z0, np.full(s.T_p, 0.45), np.zeros(s.T_p), s.params)
    assert safeguard.yaw_excess(replace(s, shape=2.0), Z) == 0.0 < safeguard.yaw_excess(s, Z)


def test_courtesy_rows_end_once_the_ego_is_wholly_inside_the_target_lane(clear_road):
    s, _, _ = clear_road
    lane_y, margin = s.lane_y, (s.road.lane_width - s.road.car_width) / 2
    assert mpc.courtesy(s, [0.0, 0.0, 0.0, 5.0]) == (s.params.dt, s.b_courtesy)  # still in its own lane
    assert mpc.courtesy(s, [0.0, lane_y - margin - 0.05, 0.0, 5.0]) is not None  # a wheel still over the line
    assert mpc.courtesy(s, [0.0, lane_y - margin + 0.05, 0.0, 5.0]) is None
    assert mpc.courtesy(replace(s, b_courtesy=None), [0.0, 0.0, 0.0, 5.0]) is None
