"""mpc=interactive: its candidates and choice judged by the predictor alone, on hand-built predictions of a ego
leaning in beside two target-lane cars (ahead and behind), and its config."""
from dataclasses import replace

import numpy as np
import pytest
from hydra.utils import instantiate
from test_surrogate import smooth_student

from core.jobs import UserError
from distill.models import StudentPredictor
from planner import cost, jit_interactive, mpc, step
from planner.gradients import ExactLocal, Source
from planner.setup import make, planner_config
from planner.strategy import (
    ACCEPT_DV,
    CHASE_HORIZON,
    CLEARANCE,
    K_Y,
    Chase,
    Interactive,
    Judged,
    Start,
    gaps,
    paces,
    steering,
    unseen,
)

DT = 0.2


class Scripted:
    """A predictor written by hand: every car keeps the velocity of its last two steps, except the one behind the ego
    (slot 2), which brakes at `brake` m/s^2 (down to a stop) from the step after the ego's centre is seen deeper than
    `trigger` m (0: it never reacts)."""

    name = "scripted"

    def __init__(self, brake=0.0, trigger=1.0):
        self.brake, self.trigger = brake, trigger

    def phi(self, window):
        nxt = 2.0 * window[:, -1] - window[:, -2]
        v = (window[:, -1, 2, 0] - window[:, -2, 2, 0]) / DT
        deep = (window[:, -1, 0, 1] > self.trigger) & (self.brake > 0)
        nxt[:, 2, 0] -= np.where(deep, np.minimum(self.brake * DT, v) * DT, 0.0)
        return nxt


def scripted(brake=0.0, trigger=1.0):
    """Scripted as a gradient source: its values by the predictor's own recursion, open or closed loop."""
    return Source("scripted", Scripted(brake, trigger))


def world(gap_ahead, gap_behind, v=5.0, lane_end=30.0):
    """Settings of mpc=interactive on dense and an observation: the ego in its lane (y 0) at v m/s, a target-lane car
    gap_ahead m ahead and a stream behind it, gap_behind m then every 9.5 m, all at v (too close for the safety shape's
    10.1 m: an ego that stopped would let the stream pass, but find no room in it); history at constant velocity. The
    ego's lane ends lane_end m ahead: at 30, too soon to race past the stream's front car and merge ahead of it."""
    s = make("dense", ["gradients=cv", "mpc=interactive", f"scenario.x_ref={lane_end}"])[2]
    k = np.arange(-7, 1)[:, None] * DT * v
    cars = [[0.0, 0.0], [gap_ahead, 4.0], [-gap_behind, 4.0], [-gap_behind - 9.5, 4.0], [-gap_behind - 19.0, 4.0]]
    history = np.array(cars)[None] + np.stack([k[:, 0], np.zeros(8)], 1)[:, None]
    return s, mpc.Observation(np.array([0.0, 0.0, 0.0, v]), np.zeros(2), history)


def track(s, z0, y_t, v_t, tau, k_y, x_t=None, tau_x=1.0):
    """Controls Delta, alpha (K, H) and states Z (K, 4H) of candidates steering to y_t (K, H) m with lateral gain k_y
    while their speed approaches v_t (K, H) m/s, closing on x_t where given (jit_interactive.track)."""
    x_t = np.full(y_t.shape, np.nan) if x_t is None else x_t
    return jit_interactive.track(np.asarray(z0, float), y_t, v_t, x_t, tau, tau_x, mpc.car(s, steering(s, k_y)))


def best(s, obs, source):
    """The name and verdict of the candidate the strategy ranks first."""
    names, *_, judged = s.strategy.ranked(s, obs, None, source)
    return names[0], judged[0]


def test_the_paces_a_candidate_may_follow_are_those_observed_and_the_gaps_between_target_lane_cars():
    s, obs = world(4.5, 4.5)
    obs.history[:, 2, 0] -= np.arange(-7, 1) * DT * 1.0  # the car behind drives at 4 m/s
    pace = paces(s, obs.history, 10, tau_x=2.0)
    assert list(pace) == ["stop", "own", "stream", "gap -24..-14 m", "gap -14..-4 m", "gap -4..+4 m"]
    assert pace["stream"][0] == pytest.approx(np.full(10, (4.0 + 3 * 5.0) / 4)) and np.isnan(pace["own"][1]).all()
    v, middle = pace["gap -4..+4 m"]  # between the car behind (4 m/s) and the one ahead (5 m/s)
    t = np.arange(1, 11) * DT
    assert v == pytest.approx(np.full(10, 4.5)) and middle == pytest.approx(0.5 * (-4.5 + 4.5) + 4.5 * t)
    assert list(paces(s, obs.history[:, :1], 10, 2.0)) == ["stop", "own"]  # nobody seen in the target lane


def test_a_candidate_leans_to_its_depth_briskly_and_never_past_it():
    """The lean is the nudge: a candidate that overshoots its depth enters the safety shape of the car beside and is
    judged unsafe; one that creeps asks for room seconds late. With the heading loop at the world drivers' gain (2.0)
    a lateral gain of 1.2 overshoots 1.9 m by 2 cm, and at the world drivers' lateral gain 0.6 the lean takes 25 steps."""
    s, obs = world(4.5, 4.5)
    H, lean = 30, 1.9
    y = track(s, obs.z0, np.full((1, H), lean), np.full((1, H), 5.0), 1.0, K_Y)[2].reshape(H, 4)[:, 1]
    assert y.max() <= lean + 1e-3 and np.all(np.diff(y) >= -1e-9)  # never past the depth, never back
    assert np.argmax(y >= lean - 0.1) + 1 <= 14  # within 0.1 m of it in 2.8 s
    z = np.array([0.0, lean, 0.0, 5.0])  # from the lean, into the target lane: in as the episode counts it within 4 steps
    y = track(s, z, np.full((1, H), s.y_ref), np.full((1, H), 5.0), 1.0, K_Y)[2].reshape(H, 4)[:, 1]
    assert y.max() <= s.y_ref + 1e-3 and np.argmax(np.abs(y - s.y_ref) <= s.merge_tol) + 1 <= 4


def test_the_shifted_plan_goes_on_beyond_t_p_as_the_candidates_drive():
    """The plan applied last step is a candidate again, rolled out over the whole horizon: one that ends in the target
    lane settles on its centre, one that ends leaning holds its lean; holding the last steering angle instead turned the
    ego in a circle."""
    s, obs = world(8.0, 8.0, lane_end=120.0)
    history = obs.history.copy()
    history[:, 0, 1] = 1.9
    obs = obs._replace(z0=np.array([0.0, 1.9, 0.0, 5.0]), history=history)
    names, Delta, alpha, Z, _ = s.strategy.ranked(s, obs, None, scripted())
    H = s.strategy.horizon
    for name, y_end in (("merge after 0, gap -8..+8 m", s.y_ref), ("lean, stream", 1.9)):
        k = names.index(name)
        warm = mpc.planned(s, obs.z0, Delta[k], alpha[k], Z[k])
        _, _, z = s.strategy.open_loop.shifted(s, obs._replace(z0=Z[k, :4]), warm, H)  # a step on, where the plan took the ego
        tail = z.reshape(H, 4)[s.T_p:]
        assert z.shape == (1, 4 * H) and np.abs(tail[-5:, 1] - y_end).max() < 0.05 and np.abs(tail[:, 2]).max() <= 0.25


def test_a_gap_targeting_candidate_closes_on_the_gap_s_middle():
    s, obs = world(4.5, 4.5)
    H = 40
    x_t = np.full((1, H), -10.0) + 5.0 * np.arange(1, H + 1) * DT  # a middle 10 m behind, moving at 5 m/s
    Z = track(s, obs.z0, np.zeros((1, H)), np.full((1, H), 5.0), 1.0, K_Y, x_t, tau_x=2.0)[2].reshape(H, 4)
    assert Z[-1, 0] - x_t[0, -1] == pytest.approx(0.0, abs=1.0) and Z[:, 3].min() >= 0.0  # dropped back, never reversed
    assert abs(Z[0, 0] - x_t[0, 0]) > 9.0


def test_a_predictor_that_sees_the_driver_behind_yield_merges_where_constant_velocity_waits():
    s, obs = world(6.0, 3.0)  # 9 m between the two: the shape needs 10.1 m, so nothing fits unless the car behind yields
    name, verdict = best(s, obs, scripted())  # constant velocity: nobody reacts
    assert verdict.merge == s.strategy.judge(s).never and s.strategy.judge(s).acceptable(s, verdict)
    name, verdict = best(s, obs, scripted(brake=1.5))  # it yields, gently, to a lean
    assert verdict.merge < s.strategy.judge(s).never and s.strategy.judge(s).acceptable(s, verdict)


def test_a_chasing_candidate_enters_once_the_predicted_clearance_opens():
    s, obs = world(6.0, 3.0)
    H = max(CHASE_HORIZON, s.T_p)
    for source, merges in ((scripted(), False), (scripted(brake=1.5), True)):
        names, Delta, alpha, Z, values = s.strategy.closed_loop.chased(s, obs, source)
        judged = s.strategy.judge(s).verdicts(s, obs, values, Delta, alpha, Z)
        beside = [k for k, n in enumerate(names) if n.startswith("chase gap -3..+6 m")]
        assert len(beside) == len(CLEARANCE)  # one per clearance, all chasing the gap the ego is beside
        good = [k for k in beside if judged[k].merge < s.strategy.judge(s).never and s.strategy.judge(s).acceptable(s, judged[k])]
        assert bool(good) == merges  # at constant velocity the gap never opens: whoever enters it breaks the shape
        for k in good:  # it steered in only after the car behind had dropped back by the clearance asked for
            ego, back = Z[k].reshape(H, 4), values[k, :, 2, 0]
            turned = np.flatnonzero(ego[:, 1] > s.strategy.lean + 0.05)[0]
            room = ego[turned - 1, 0] - back[turned - 1] - s.road.car_length
            assert room >= CLEARANCE[beside.index(k)] - 1e-9


def test_a_predictor_that_sees_the_cut_in_force_the_driver_behind_refuses_the_gap_constant_velocity_takes():
    s, obs = world(5.5, 5.5)  # 11 m: room enough at constant velocity
    name, verdict = best(s, obs, scripted())
    assert verdict.merge < s.strategy.judge(s).never and verdict.braking == pytest.approx(0.0, abs=1e-9)
    name, verdict = best(s, obs, scripted(brake=6.0, trigger=2.0))  # entering its lane makes it brake at 6 m/s^2
    assert verdict.merge == s.strategy.judge(s).never and verdict.braking <= s.b_courtesy


class Trained(Scripted):
    """Scripted as if learned: the rollouts `mpc.strategy.trust` cuts short."""

    fitted = True


def test_a_trained_predictor_s_rollout_is_read_for_trust_steps_then_every_other_car_holds_its_velocity():
    s, obs = world(6.0, 3.0)
    s = replace(s, strategy=replace(s.strategy, trust=3))
    rng = np.random.default_rng(0)
    values = rng.normal(size=(4, 10, 5, 2)).cumsum(axis=1)
    held = s.strategy.judge(s).held(Source("trained", Trained()), obs.history, values)
    assert np.array_equal(held[:, :3], values[:, :3]) and np.array_equal(held[:, :, 0], values[:, :, 0])  # the ego's own plan kept
    for h in range(3, 10):  # beyond: on at the velocity of the third step, by hand
        assert held[:, h, 1:] == pytest.approx(values[:, 2, 1:] + (h - 2) * (values[:, 2, 1:] - values[:, 1, 1:]))
    assert s.strategy.judge(s).held(scripted(), obs.history, values) is values  # a written model is read whole
    short = values[:, :3]  # no step beyond the trusted ones
    assert s.strategy.judge(s).held(Source("trained", Trained()), obs.history, short) is short
    s1 = replace(s, strategy=replace(s.strategy, trust=1))  # from the first step: its velocity from the last seen position
    one = s1.strategy.judge(s1).held(Source("trained", Trained()), obs.history, values)
    assert one[:, 4, 1:] == pytest.approx(values[:, 0, 1:] + 4 * (values[:, 0, 1:] - obs.history[-1, 1:]))


def test_a_trained_predictor_is_rolled_out_only_over_the_trusted_steps_with_the_same_verdict_values():
    """predict runs the rollout over `trust` steps only: the same values as the whole rollout held after the fact."""
    s, obs = world(6.0, 3.0)
    s = replace(s, strategy=replace(s.strategy, trust=3))
    source, asked = Source("trained", Trained()), []
    rollout = source.values
    source.values = lambda history, ego: asked.append(ego.shape[1]) or rollout(history, ego)
    names, Delta, alpha, Z = s.strategy.open_loop.plans(s, obs, None)
    whole = s.strategy.judge(s).held(source, obs.history, rollout(obs.history, Z.reshape(len(Z), -1, 4)[:, :, :2]))
    assert np.array_equal(s.strategy.judge(s).predict(obs, source, Z), whole) and asked == [3]


def test_a_yield_predicted_beyond_the_trusted_steps_does_not_open_the_gap():
    """The scripted driver yields only once the lean is 1 m deep, some steps in: reading 2 steps, the step sees the
    driver behind at its old speed and waits, as with constant velocity; reading all, it merges
    (test_a_predictor_that_sees_the_driver_behind_yield_merges_where_constant_velocity_waits)."""
    s, obs = world(6.0, 3.0)
    s = replace(s, strategy=replace(s.strategy, trust=2))
    name, verdict = best(s, obs, Source("trained", Trained(brake=1.5)))
    assert verdict.merge == s.strategy.judge(s).never


def test_phi_3_prices_the_deviation_from_a_path_step_by_step_and_a_number_as_a_constant_path():
    s = make("dense", ["gradients=cv", "mpc=interactive"])[2]
    rng = np.random.default_rng(0)
    Z, y, v = rng.normal(size=4 * s.T_p), tuple(rng.normal(size=s.T_p)), tuple(rng.normal(size=s.T_p))
    w = s.weights
    want = w.lambda_div * np.sum((Z[1::4] - y) ** 2) + w.lambda_v * np.sum((Z[3::4] - v) ** 2)
    assert cost.Phi_3(s.T_p, w, y, v)(Z) == pytest.approx(want)
    assert cost.Phi_3(s.T_p, w, 4.0, 5.0)(Z) == pytest.approx(cost.Phi_3(s.T_p, w, (4.0,) * s.T_p, (5.0,) * s.T_p)(Z))


def test_admm_refines_a_candidate_along_its_own_path_not_across_to_its_end_state():
    s, obs = world(8.0, 8.0, lane_end=120.0)  # room to merge: the best candidates steer in
    source, zstep = make("dense", ["gradients=cv"])[1], instantiate(planner_config("dense", ["gradients=cv"]).solver.step).keywords["zstep"]
    start = s.strategy.candidates(s, obs, None, source)[0]
    path = start.plan.Z.reshape(s.T_p, 4)
    assert start.aim.y_ref == tuple(path[:, 1]) and start.aim.v_ref == tuple(path[:, 3])
    history = obs.history.copy()
    history[:, 0, 1] = 1.9  # leaning already: a candidate that holds the lean 6 steps, then enters
    obs = obs._replace(z0=np.array([0.0, 1.9, 0.0, 5.0]), history=history)
    names, Delta, alpha, Z, _ = s.strategy.ranked(s, obs, None, source)
    k = names.index("merge after 6, gap -8..+8 m")
    path, plan = Z[k].reshape(s.T_p, 4), mpc.planned(s, obs.z0, Delta[k], alpha[k], Z[k])
    along = replace(s, y_ref=tuple(path[:, 1]), v_ref=tuple(path[:, 3]))
    end = replace(s, y_ref=float(path[-1, 1]), v_ref=float(path[-1, 3]))  # aimed at where it ends: cuts across
    deviation = [np.abs(step.solve_all(s, obs, source, [Start("", plan, aim, 0)], zstep)[0][0].plan.Z[1::4] - path[:, 1]).max()
                 for aim in (along, end)]
    assert deviation[0] < 0.15 < 0.4 < deviation[1]  # rounds the corner where it enters; the end aim crosses at once


@pytest.mark.parametrize("front,enters", [(6.0, True), (16.0, False)])
def test_a_gap_beyond_the_seen_cars_ends_where_an_unseen_car_may_be(front, enters):
    s, obs = world(front, 3.0, lane_end=200.0)  # seen: `front` m ahead; 3, 12.5 and 22 m behind, 4 m across
    ahead, behind, v = unseen(s, obs.history)
    along = np.sqrt(22.0**2 + 4.0**2 - (s.y_ref - 0.0) ** 2)  # the farthest seen car's distance, along the target lane
    assert (ahead, behind, v) == pytest.approx((along, -along, 5.0))
    assert [name for name, *_ in gaps(s, obs.history)][-1] == f"+{front:.0f}..unseen m"
    names, Delta, alpha, Z, values = s.strategy.closed_loop.chased(s, obs, scripted())
    H = max(CHASE_HORIZON, s.T_p)
    entered = 0
    for k in (k for k, n in enumerate(names) if n.startswith(f"chase gap +{front:.0f}..unseen m")):
        ego, car = Z[k].reshape(H, 4), values[k, :, 1, 0]
        turned = np.flatnonzero(ego[:, 1] > s.strategy.lean + 0.05)
        if len(turned):  # it steered in only with the clearance asked for to the seen car and to one at the bound
            t = turned[0] - 1
            bound = ahead + 5.0 * (t + 1) * DT  # where it stands when the policy decides the step after t
            assert min(bound - ego[t, 0], ego[t, 0] - car[t]) - s.road.car_length >= CLEARANCE[entered] - 1e-9
            entered += 1
    # 16.4 m between the seen car and the bound: room for the ego at every clearance; 6.4 m: none (an open road would have)
    assert entered == (len(CLEARANCE) if enters else 0)


def test_a_candidate_that_cannot_stop_before_the_lane_s_end_is_refused():
    s, obs = world(6.0, 3.0)
    end = s.lane_end
    H = s.strategy.horizon
    Delta, alpha, Z = track(s, obs.z0 + np.array([end - 28.0, 0, 0, 0]), np.zeros((2, H)),
                            np.array([np.full(H, 5.0), np.zeros(H)]), 1.0, K_Y)
    values = scripted().values(obs.history, Z.reshape(2, H, 4)[:, :, :2])  # the others far behind, at constant velocity
    held, stopped = s.strategy.judge(s).verdicts(s, obs, values, Delta, alpha, Z)
    ego = Z[0].reshape(H, 4)
    reach = ego[:, 0] + ego[:, 3] ** 2 / (-2.0 * s.a_box[0]) - end  # braking as hard as it may
    assert held.overrun == pytest.approx(reach.max()) and not s.strategy.judge(s).acceptable(s, held)
    assert stopped.overrun == 0.0 and s.strategy.judge(s).acceptable(s, stopped)


def test_the_order_puts_safe_and_courteous_first_then_the_earliest_merge_then_J():
    s = world(4.5, 4.5)[0]
    judged = [Judged(-1.0, 0.0, 3, 1.0), Judged(1.0, 5.0, 2, 1.0), Judged(1.0, 1.0, 9, 5.0), Judged(1.0, 1.0, 9, 4.0),
              Judged(1.0, 0.0, 16, 0.0), Judged(-0.5, 0.0, 1, 0.0)]
    assert s.strategy.judge(s).order(s, judged) == [3, 2, 4, 1, 5, 0]


def test_candidates_that_merge_within_no_horizon_go_by_the_most_room_then_j():
    s = world(4.5, 4.5)[0]
    never = s.strategy.judge(s).never
    judged = [Judged(1.0, 0.0, never, 1.0, room=-3.0), Judged(1.0, 0.0, never, 2.0, room=5.0), Judged(1.0, 0.0, 30, 9.0),
              Judged(1.0, 0.0, never, 0.5, room=5.0), Judged(-1.0, 0.0, never, 0.0, room=50.0)]
    assert s.strategy.judge(s).order(s, judged) == [2, 3, 1, 0, 4]


def test_a_merged_ego_has_only_open_loop_candidates_and_no_room_to_look_for():
    s, obs = world(6.0, 9.0)
    obs.history[:, 0, 1] = s.y_ref
    obs = mpc.Observation(np.array([0.0, s.y_ref, 0.0, 5.0]), np.zeros(2), obs.history)
    names, *_, judged = s.strategy.ranked(s, obs, None, make("dense", ["gradients=cv"])[1])
    assert names and all(n.startswith("merged") for n in names) and all(j.merge == 1 for j in judged)


def test_the_room_beside_a_candidate_is_the_widest_target_lane_opening_at_its_x():
    """The car behind in the target lane drops back from 4 to 8 m behind the ego, the one ahead stays 10 m ahead, a car
    in the ego's own lane sits beside it and another target-lane car is far ahead: on the superellipse's axis b_i is
    dx^2 / stretch^2 - R^2, so the room is its value at the widest opening, 8 m."""
    s = world(4.5, 4.5)[0]
    t = np.arange(3.0)
    values = np.zeros((1, 3, 5, 2))
    values[0, :, 1] = np.stack([10.0 + 0 * t, 4.0 + 0 * t], -1)  # ahead, target lane
    values[0, :, 2] = np.stack([-4.0 - 2.0 * t, 4.0 + 0 * t], -1)  # behind, dropping back
    values[0, :, 3] = np.stack([0.0 * t, 0.0 * t], -1)  # beside the ego in its own lane: no part of the room
    values[0, :, 4] = np.stack([100.0 + 0 * t, 4.1 + 0 * t], -1)
    Z = np.zeros((1, 12))  # the ego stays at x = 0, in its lane (y = 0)
    assert s.stretch > 1 and s.y_ref == 4.0
    assert jit_interactive.room(values, Z, s.strategy.judge(s).kernel(s)) == pytest.approx([8.0**2 / s.stretch**2 - s.R**2])


def test_an_interactive_step_solves_and_reports_which_candidate_it_applied():
    s, obs = world(4.5, 4.5)
    _, source, _ = make("dense", ["gradients=cv", "mpc=interactive"])
    from hydra.utils import instantiate

    from planner.setup import planner_config
    zstep = instantiate(planner_config("dense", ["gradients=cv"]).solver.step).keywords["zstep"]
    result = step.mpc_step(s, obs, source, None, zstep)
    assert result.fallback == "" and ", from " in result.reason and np.all(np.isfinite(result.u))


@pytest.mark.parametrize("override,message", [("mpc.strategy.horizon=0", "mpc.strategy.horizon=0: must be an integer >= 1"),
                                              ("mpc.strategy.merge_steps=[]", "mpc.strategy.merge_steps=[]: must be a list of at least 1")])
def test_a_bad_interactive_value_is_one_line(override, message):
    with pytest.raises(UserError, match="^" + message.replace("[", r"\[").replace("]", r"\]")):
        make("dense", ["gradients=cv", "mpc=interactive", override])


def test_interactive_is_its_own_strategy_beside_rules():
    assert isinstance(make("dense", ["gradients=cv", "mpc=interactive"])[2].strategy, Interactive)


def accepting(back_x, back_v, dv=-10.0, clearance=0.5):
    """One accepting candidate (Chase with a finite dv), the ego standing leaned in at (0, 1.9) beside a target-lane car
    8 m ahead at 5 m/s and one at back_x m moving at back_v m/s, asked for its first step: (policy, steering rad)."""
    s = world(6.0, 3.0, lane_end=200.0)[0]
    policy = Chase(s, [0.0, 1.9, 0.0, 0.0], [(0, 0)], [1.9], [clearance], 0.0, 200.0, (60.0, -60.0, 5.0), [dv], 1)
    k = np.arange(-7, 1) * DT
    cars = [np.stack([0.0 * k, np.full(8, 1.9)], 1), np.stack([8.0 + 5.0 * k, np.full(8, 4.0)], 1),
            np.stack([back_x + back_v * k, np.full(8, 4.0)], 1)]
    policy(np.stack(cars, 1)[None], 0)
    return s, policy, float(policy.Delta[0, 0])


def test_an_accepting_candidate_steers_in_once_the_car_behind_has_stopped_for_it_or_left_room():
    s = world(6.0, 3.0)[0]
    L = s.road.car_length
    _, _, held = accepting(-(L + 0.3), 5.0)  # 0.3 m behind it and still moving: it keeps leaning
    _, _, stopped = accepting(-(L + 0.3), 0.0)  # the same car stopped for it: it steers in
    _, _, room = accepting(-(L + 0.6), 5.0)  # moving, but 0.6 m behind: the clearance of 0.5 m it asks for
    assert held == pytest.approx(0.0, abs=1e-3) and stopped > 0.05 and room > 0.05
    _, _, tight = accepting(-(L + 0.6), 5.0, clearance=1.0)  # asking for 1 m: not yet
    assert tight == pytest.approx(0.0, abs=1e-3)


@pytest.mark.parametrize("dv,v", [(-10.0, 0.0), (-3.0, 2.0), (0.0, 5.0)])
def test_an_accepting_candidate_holds_the_nearby_stream_s_speed_plus_dv_never_below_a_standstill(dv, v):
    _, policy, _ = accepting(-(3.6 + 0.3), 5.0, dv=dv)  # the stream near it drives at 5 m/s; the ego stands still
    assert policy.alpha[0, 0] == pytest.approx(min(v - 0.0, 3.0))  # tau = 1 s, within a_box


def test_the_oracle_steps_plans_that_share_a_prefix_once_and_predicts_each_as_its_own_world_copy():
    from data import perception
    from planner.gradients import WorldModel
    scenario = make("dense", ["gradients=cv"])[0]
    world = scenario.make_world(3)
    for _ in range(8):
        world.step(np.array([0.0, 0.0]))
    z, seen, T = world.states(), perception.observe(world, 4, 8), 10
    ego = z[0, :2] + np.arange(1, T + 1)[:, None] * np.array([z[0, 3] * DT, 0.0])  # straight on at its speed
    plans = np.stack([ego, ego + np.where(np.arange(T) >= 4, 0.3, 0.0)[:, None] * [0, 1], ego * [1, 0] + [0, 1.5]])
    plans[1, 7:, 0] -= 0.5  # plans 0 and 1 share 4 steps; plan 2 none
    oracle = WorldModel("all")
    oracle.world, oracle.ids = world, seen.ids
    pred = oracle.react(seen.history, lambda window, k: plans[:, k], T, 3)
    for plan, p in zip(plans, pred):  # each plan on its own copy, step by step
        w, xy0 = world.copy(), z[0, :2]
        for k, xy in enumerate(plan):
            d = xy - (xy0 if k == 0 else plan[k - 1])
            w.step_to(np.array([*xy, np.arctan2(d[1], d[0]), np.hypot(*d) / DT]))
            assert np.array_equal(w.states()[seen.ids, :2], p[k])
    assert np.array_equal(world.states(), z)


def test_chase_drives_its_candidates_together_as_each_alone():
    s, obs = world(6.0, 3.0, lane_end=120.0)
    lean = 1.9
    combos = [(f, b, c, np.nan) for _, f, b in gaps(s, obs.history) for c in CLEARANCE]
    combos += [(0, 0, c, dv) for dv in ACCEPT_DV for c in CLEARANCE]
    source, H = scripted(brake=3.0), 50

    def driven(rows):
        """Delta, alpha (K, H), Z (K, 4H) and the predicted values of the candidates `rows` of combos, driven together."""
        front, back, clear, dv = zip(*[combos[k] for k in rows])
        policy = Chase(s, obs.z0, list(zip(front, back)), [lean] * len(rows), clear, 0.0, s.lane_end, unseen(s, obs.history),
                       dv, H)
        return source.drive(obs.history, policy, H)

    together = driven(range(len(combos)))
    for k in range(len(combos)):
        for both, alone in zip(together, driven([k])):
            assert np.array_equal(both[k:k + 1], alone)
    y = together[2].reshape(len(combos), H, 4)[:, -1, 1]
    assert 0 < np.sum(np.abs(y - s.y_ref) < 0.5) < len(combos)  # some candidates entered and followed, others did not


@pytest.mark.parametrize("predictor", ["cv", "student"])
def test_the_compiled_search_ranks_and_judges_its_candidates_as_the_python_reference(predictor):
    """For the sources the compiled core runs (cv, the student) the candidates' bicycle rollouts, predicted rollouts,
    Chase and verdicts are planner.jit_interactive's: the same candidates in the same order, their plans and verdicts
    equal to rounding, as planner.strategy's numpy code gives for the same predictor as a plain Source."""
    s, obs = world(6.0, 3.0, lane_end=120.0)
    obs.history[:, 2, 0] -= np.arange(-7, 1) ** 2 * DT**2 * 0.5  # the car behind has been braking at 1 m/s^2: the student reacts
    warm = mpc.planned(s, obs.z0, *(u[0] for u in mpc.lane_plans(s, obs.z0, [0.0])))  # a previous plan: the shifted candidate too
    source = make("dense", ["gradients=cv"])[1] if predictor == "cv" else ExactLocal("student", StudentPredictor(smooth_student()))
    reference = Source(predictor, source.predictor)
    assert source.compiled and not reference.compiled
    compiled, python = (s.strategy.ranked(s, obs, warm, src) for src in (source, reference))
    assert compiled[0] == python[0]  # names, best first
    for a, b in zip(compiled[1:4], python[1:4]):
        assert np.allclose(a, b, rtol=0.0, atol=1e-9)
    judged, expected = np.array(compiled[4], float), np.array(python[4], float)
    assert np.allclose(judged, expected, rtol=1e-12, atol=1e-9)
    merged = judged[:, 2] < s.strategy.judge(s).never
    assert 0 < merged.sum() < len(judged) and any(n.startswith(("chase", "accept")) for n in np.array(compiled[0])[merged])
