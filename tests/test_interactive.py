"""mpc=interactive: its candidates and choice judged by the predictor alone, on hand-built predictions of a ego
leaning in beside two target-lane cars (ahead and behind), and its config."""
import numpy as np
import pytest

from planner import mpc, step
from planner.setup import make
from planner.strategy import Interactive, Judged, paces, track

DT = 0.2


class Scripted:
    """A predictor written by hand: the cars keep their observed speed, except the one behind the ego (slot 2), which
    brakes at `brake` m/s^2 from the first step the ego's plan leans deeper than `trigger` m (0: it never reacts)."""

    name = "scripted"

    def __init__(self, brake=0.0, trigger=1.0):
        self.brake, self.trigger = brake, trigger

    def values(self, history, egos):
        v = (history[-1] - history[-2]) / DT  # (SLOTS, 2)
        out = []
        for ego in np.asarray(egos):
            H = len(ego)
            xy = history[-1] + np.arange(1, H + 1)[:, None, None] * DT * v  # (H, SLOTS, 2)
            leaned = np.flatnonzero(ego[:, 1] > self.trigger)
            if self.brake and len(leaned):
                k0 = leaned[0]
                t = np.clip(np.arange(1, H + 1) - k0, 0, None) * DT  # time since it began to brake (s)
                vb = v[2, 0]
                stop = vb / self.brake
                xy[:, 2, 0] -= 0.5 * self.brake * np.minimum(t, stop) ** 2 + np.maximum(t - stop, 0.0) * 0.0
            xy[:, 0] = ego
            out.append(xy)
        return np.array(out)


def world(gap_ahead, gap_behind, v=5.0):
    """Settings of mpc=interactive on dense and an observation: the ego in its lane (y 0) at v m/s, a target-lane car
    gap_ahead m ahead and a stream behind it, gap_behind m then every 9.5 m, all at v (too close for the safety shape's
    10.1 m: an ego that stopped would let the stream pass, but find no room in it); history at constant velocity."""
    s = make("dense", ["gradients=cv", "mpc=interactive"])[2]
    k = np.arange(-7, 1)[:, None] * DT * v
    cars = [[0.0, 0.0], [gap_ahead, 4.0], [-gap_behind, 4.0], [-gap_behind - 9.5, 4.0], [-gap_behind - 19.0, 4.0]]
    history = np.array(cars)[None] + np.stack([k[:, 0], np.zeros(8)], 1)[:, None]
    return s, mpc.Observation(np.array([0.0, 0.0, 0.0, v]), np.zeros(2), history)


def best(s, obs, source):
    """The name and verdict of the candidate the strategy ranks first."""
    names, Delta, alpha, Z, _ = s.strategy.plans(s, obs, None)
    judged = s.strategy.judge(s, obs, source, Delta, alpha, Z)
    k = s.strategy.order(s, judged)[0]
    return names[k], judged[k]


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


def test_a_gap_targeting_candidate_closes_on_the_gap_s_middle():
    s, obs = world(4.5, 4.5)
    H = 40
    x_t = np.full((1, H), -10.0) + 5.0 * np.arange(1, H + 1) * DT  # a middle 10 m behind, moving at 5 m/s
    Z = track(s, obs.z0, np.zeros((1, H)), np.full((1, H), 5.0), 1.0, x_t, tau_x=2.0)[2].reshape(H, 4)
    assert Z[-1, 0] - x_t[0, -1] == pytest.approx(0.0, abs=1.0) and Z[:, 3].min() >= 0.0  # dropped back, never reversed
    assert abs(Z[0, 0] - x_t[0, 0]) > 9.0


def test_a_predictor_that_sees_the_driver_behind_yield_merges_where_constant_velocity_waits():
    s, obs = world(6.0, 3.0)  # 9 m between the two: the shape needs 10.1 m, so nothing fits unless the car behind yields
    name, verdict = best(s, obs, Scripted())  # constant velocity: nobody reacts
    assert not name.startswith("merge") and verdict.merge == s.strategy.horizon + 1 and verdict.b_min >= 0
    name, verdict = best(s, obs, Scripted(brake=1.5))  # it yields, gently, to a lean
    assert name.startswith("merge after") and verdict.merge <= s.strategy.horizon and verdict.braking <= s.b_courtesy
    assert verdict.b_min >= 0.0


def test_a_predictor_that_sees_the_cut_in_force_the_driver_behind_refuses_the_gap_constant_velocity_takes():
    s, obs = world(5.5, 5.5)  # 11 m: room enough at constant velocity
    name, verdict = best(s, obs, Scripted())
    assert name.startswith("merge after 0") and verdict.braking == pytest.approx(0.0, abs=1e-9)
    name, verdict = best(s, obs, Scripted(brake=6.0, trigger=2.0))  # entering its lane makes it brake at 6 m/s^2
    assert not name.startswith("merge") and verdict.braking <= s.b_courtesy


def test_the_order_puts_safe_and_courteous_first_then_the_earliest_merge_then_J():
    s = world(4.5, 4.5)[0]
    judged = [Judged(-1.0, 0.0, 3, 1.0), Judged(1.0, 5.0, 2, 1.0), Judged(1.0, 1.0, 9, 5.0), Judged(1.0, 1.0, 9, 4.0),
              Judged(1.0, 0.0, 16, 0.0), Judged(-0.5, 0.0, 1, 0.0)]
    assert s.strategy.order(s, judged) == [3, 2, 4, 1, 5, 0]


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
    from core.jobs import UserError
    with pytest.raises(UserError, match="^" + message.replace("[", r"\[").replace("]", r"\]")):
        make("dense", ["gradients=cv", "mpc=interactive", override])


def test_interactive_is_its_own_strategy_beside_rules():
    assert isinstance(make("dense", ["gradients=cv", "mpc=interactive"])[2].strategy, Interactive)
