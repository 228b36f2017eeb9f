"""The contingency step (issue 72 points 3, 4, 9): with a source that gives hypotheses of yielding with their
probabilities, mpc=interactive judges every candidate under each likely branch, accepts only what is safe and courteous
in all of them and ranks by the probability-weighted merge; the oracle knows=prior gives the world's hypotheses."""
import copy

import numpy as np
import pytest
from test_hypotheses import random_student
from test_interactive import DT, Scripted, world

from core.jobs import UserError
from core.rollout import SLOTS, react
from core.validate import PLANNER, check
from data import perception
from distill import models
from distill.models import TorchPredictor
from planner import strategy
from planner.gradients import Given, Hypotheses, Source, WorldModel
from planner.mpc import Observation
from planner.setup import make, planner_config
from planner.strategy import Branches, Judged, merged


class Hypothesised(Given, Source):
    """Scripted under hypotheses: the car behind the ego (slot 2) brakes at `brake` m/s^2 once the ego leans deeper
    than 1 m in a rollout whose hypothesis has it yield, else keeps its speed; its belief p, every other car's 0."""

    hypotheses = True

    def __init__(self, p, brake=1.5):
        super().__init__("scripted", Scripted())
        self.p, self.brake = p, brake

    def belief(self, history):
        return np.eye(SLOTS)[2] * self.p

    def react(self, history, ego_next, T, B):
        hyp = np.broadcast_to(self.belief(history) > 0.5, (B, SLOTS)) if self.hyp is None else self.hyp
        yields, stubborn = Scripted(self.brake), Scripted()
        phi = lambda window: np.where(hyp[:, 2, None, None] > 0.5, yields.phi(window), stubborn.phi(window))
        return react(phi, np.broadcast_to(history, (B, *np.shape(history))), ego_next, T)


def verdicts(s, obs, source):
    """{candidate name: verdict} of every candidate, and the names best first."""
    names, *_, judged = s.strategy.ranked(s, obs, None, source)
    return dict(zip(names, judged)), names


def test_branches_are_the_likely_combinations_of_the_nearest_undecided_cars_most_probable_first():
    obs = world(6.0, 3.0)[1]  # slots by distance: 2 (3 m behind), 1 (6 m ahead), 3, 4
    source = Hypothesised(0.5)
    source.belief = lambda history: np.array([0.0, 0.5, 0.5, 0.5, 0.95])
    hyp, w = Branches(0.1, 4).of(obs, source)
    assert w == pytest.approx([0.25] * 4)  # two cars at even odds; a third would make 8 of 1/8
    assert hyp[0].tolist() == [0, 0, 0, 0, 1]  # the plain rollout's: even odds not yielding, 0.95 yielding
    assert sorted(map(tuple, hyp[:, 1:3])) == [(0, 0), (0, 1), (1, 0), (1, 1)] and (hyp[:, 3:] == [0, 1]).all()
    hyp, w = Branches(0.1, 1).of(obs, source)
    assert hyp.tolist() == [[0, 0, 0, 0, 1]] and w.tolist() == [1.0]
    source.belief = lambda history: np.array([0.0, 0.3, 0.3, 0.3, 0.3])
    hyp, w = Branches(0.1, 4).of(obs, source)  # at most one of three cars yields: 0.343 and three of 0.147, the rest < 0.1
    assert len(w) == 4 and hyp[0].sum() == 0 and (hyp[1:].sum(1) == 1).all()
    assert w == pytest.approx(np.array([0.343, 0.147, 0.147, 0.147]) / 0.784)
    assert Branches(0.1, 4).of(obs, Source("cv", Scripted()))[0] is None  # no hypotheses: one branch


def test_merged_verdicts_are_the_worst_branch_s_safety_and_the_weighted_merge():
    never = 51
    a = [Judged(1.0, 1.0, 10, 5.0, 0.0, 2.0), Judged(2.0, 0.0, never, 1.0, 0.0, 3.0)]
    b = [Judged(-1.0, 4.0, 20, 5.0, 0.5, 2.0), Judged(3.0, 0.5, never, 1.0, 0.0, 5.0)]
    out = merged(a + b, np.array([0.75, 0.25]))
    assert out[0] == Judged(-1.0, 4.0, 12.5, 5.0, 0.5, 2.0)
    assert out[1] == Judged(2.0, 0.5, never, 1.0, 0.0, 3.5) and out[1].merge == never  # no merge in any: never, exactly
    assert merged(a, np.ones(1)) == a


def test_a_driver_seen_yielding_is_merged_ahead_of():
    """Belief 1 (shown): the branch is the yield, and the step merges into the gap ahead of it (9 m: nothing fits unless
    it yields, and the lane ends before the stream behind it has passed)."""
    s, obs = world(6.0, 3.0)
    judge = s.strategy.judge(s)
    judged, names = verdicts(s, obs, Hypothesised(1.0))
    assert judge.acceptable(s, judged[names[0]]) and judged[names[0]].merge < judge.never


def test_an_undecided_driver_is_asked_by_a_lean_never_bet_on_by_a_cut_in(monkeypatch):
    """At 0.7 a single branch (the more probable: it yields) takes a plan that would force the driver if it is stubborn;
    the contingency step leans in, safe and courteous under both hypotheses, and merges in the yield branch."""
    s, obs = world(6.0, 3.0)
    judge = s.strategy.judge(s)
    under = [verdicts(s, obs, Hypothesised(p))[0] for p in (0.0, 1.0)]  # each hypothesis alone
    with monkeypatch.context() as m:
        m.setattr(strategy, "BRANCHES", Branches(strategy.BRANCHES.p_min, 1))
        bet = verdicts(s, obs, Hypothesised(0.7))[1][0]
    assert not judge.acceptable(s, under[0][bet])  # the bet forces the stubborn driver
    names, Delta, alpha, Z, judged = s.strategy.ranked(s, obs, None, Hypothesised(0.7))
    assert all(judge.acceptable(s, u[names[0]]) for u in under) and under[1][names[0]].merge < judge.never
    assert Z[0].reshape(-1, 4)[:, 1].max() > 1.0  # it leans: the driver's cue
    assert judged[0].merge == pytest.approx(0.7 * under[1][names[0]].merge + 0.3 * under[0][names[0]].merge)


def gapped(lane_end=120.0, v=5.0):
    """world(6, 3) with a gap behind the driver behind the ego: 14 m to the next car (room for the ego's shape), the
    ego's lane long enough to drop back to it."""
    s = make("dense", ["gradients=cv", "mpc=interactive", f"scenario.x_ref={lane_end}"])[2]
    k = np.arange(-7, 1)[:, None] * DT * v
    cars = [[0.0, 0.0], [6.0, 4.0], [-3.0, 4.0], [-17.0, 4.0], [-26.5, 4.0]]
    history = np.array(cars)[None] + np.stack([k[:, 0], np.zeros(8)], 1)[:, None]
    return s, Observation(np.array([0.0, 0.0, 0.0, v]), np.zeros(2), history)


def test_a_driver_shown_stubborn_is_let_pass_and_the_next_gap_taken():
    s, obs = gapped()
    judge = s.strategy.judge(s)
    judged, names = verdicts(s, obs, Hypothesised(0.0))
    assert names[0].endswith("gap -17..-3 m") and judge.acceptable(s, judged[names[0]])  # behind it
    assert verdicts(s, obs, Hypothesised(1.0))[1][0].startswith("chase gap -3..+6 m")  # a yielder: the gap ahead of it


def oracle_world(yields: bool, prior: float, seed=7, nudge=10):
    """A dense world whose drivers all have eta_coop = prior and are stubborn but the one behind the ego (j), which
    yields or not, after `nudge` steps of the ego leaning in: (world, j, observation)."""
    from dataclasses import replace as with_field

    from data.dataset import Intervention
    scenario = make("dense", ["gradients=cv"])[0]
    w = scenario.make_world(seed)
    w.drivers = [with_field(d, eta_coop=prior) for d in w.drivers]
    z = w.states()
    behind = np.flatnonzero((w.road.lane_of(z[:, 1]) == 1) & (z[:, 0] < z[0, 0]))
    j = int(behind[np.argmax(z[behind, 0])])
    w = w.with_decisions(np.arange(len(z)) == j if yields else np.zeros(len(z), bool))
    ego = Intervention(0.5 * scenario.y_ref, float(z[0, 3]))
    for _ in range(nudge):
        w.step(ego(w))
    seen = perception.observe(w, 4, 8)
    return w, j, seen, Observation(w.states()[0].copy(), np.zeros(2), seen.history)


def oracle(knows, w, ids):
    """(settings, the oracle knowing `knows`) of mpc=interactive on dense, reading world w with slots ids."""
    _, source, s = make("dense", ["gradients=oracle", "predictor=oracle", f"predictor.knows={knows}", "mpc=interactive"])
    source.predictor.world, source.predictor.ids = w, ids
    return s, source


def test_the_prior_oracle_knows_a_shown_yield_and_gives_the_population_s_prior_to_the_undecided():
    w, j, seen, obs = oracle_world(True, 0.7)
    assert w.shown[j]
    s, source = oracle("prior", w, seen.ids)
    assert source.hypotheses and not oracle("seen", w, seen.ids)[1].hypotheses
    assert source.predictor.prior() == pytest.approx(0.7)
    p = source.belief(obs.history)
    assert p[0] == 0.0 and p[list(seen.ids).index(j)] == 1.0 and sorted(p[1:])[:-1] == pytest.approx([0.7] * 3)
    truth = verdicts(s, obs, oracle("all", w, seen.ids)[1])[0]
    pick = verdicts(s, obs, source)[1][0]
    assert s.strategy.judge(s).acceptable(s, truth[pick]) and truth[pick].merge < s.strategy.judge(s).never


def test_the_prior_oracle_learns_a_stubborn_decision_once_the_driver_has_ignored_the_lean():
    """A stubborn driver keeps its acceleration where its yielding would have cut it by SHOWN_BRAKE: the world marks it
    refused (its decision shows), the prior oracle's belief in it falls from the prior to 0, and its rollouts drive it
    stubborn; before any lean it is undecided, at the prior."""
    w, j, seen, obs = oracle_world(False, 0.7, nudge=0)
    assert not w.decided()[j]
    s, source = oracle("prior", w, seen.ids)
    assert source.belief(obs.history)[list(seen.ids).index(j)] == pytest.approx(0.7)
    w, j, seen, obs = oracle_world(False, 0.7)
    assert w.refused[j] and not w.shown[j] and w.decided()[j]
    s, source = oracle("prior", w, seen.ids)
    assert source.belief(obs.history)[list(seen.ids).index(j)] == 0.0
    assert not source.predictor.start().will_yield[j]


@pytest.mark.parametrize("knows", ["prior", "seen"])
def test_an_oracle_that_cannot_see_a_stubborn_decision_never_forces_it(knows):
    """The driver behind is stubborn and the ego has leaned beside it for 2 s: the step the prior (0.7: it more likely
    yields) or the seen oracle judges takes a plan the true world finds safe and courteous."""
    w, j, seen, obs = oracle_world(False, 0.7)
    s, source = oracle(knows, w, seen.ids)
    truth = verdicts(s, obs, oracle("all", w, seen.ids)[1])[0]
    assert s.strategy.judge(s).acceptable(s, truth[verdicts(s, obs, source)[1][0]])


def test_the_prior_oracle_rolls_each_hypothesis_out_as_its_own_world_sharing_steps_until_they_differ():
    """Rollouts under different hypotheses step one world until a driver they differ on responds to the ego; each
    equals the rollout of a world with those decisions. An unknown knows is one error naming the key."""
    w, j, seen, obs = oracle_world(False, 0.5, nudge=3)
    z, T = w.states(), 25
    ego = z[0, :2] + np.arange(1, T + 1)[:, None] * np.array([z[0, 3] * DT, 0.0])
    lean = ego + np.minimum(np.arange(1, T + 1), 8)[:, None] * [0, 0.25]
    plans = np.stack([ego, lean, lean, lean])
    hyp = np.array([[0, 0, 0, 0, 0], [0, 1, 1, 1, 1], [0, 0, 0, 0, 0], [0, 1, 0, 1, 0]], float)
    prior = WorldModel("prior")
    prior.world, prior.ids = w, seen.ids
    out = prior.react(seen.history, lambda window, k: plans[:, k], T, len(plans), hyp=hyp)
    for b in range(len(plans)):
        alone = WorldModel("all")
        alone.world, alone.ids = prior.start(hyp[b]), seen.ids
        assert np.array_equal(out[b], alone.react(seen.history, lambda window, k: plans[b:b + 1, k], T, 1)[0])
    assert np.abs(out[1] - out[2]).max() > 0.01  # the lean met a yielder in one, not in the other
    with pytest.raises(UserError, match="predictor.knows"):
        check(planner_config("dense", ["gradients=oracle", "predictor=oracle", "predictor.knows=some"]), PLANNER)


class TorchUnder(Given, Source):
    """The reference for Hypotheses: the hypothesis network in float64 torch, each rollout under its own hypotheses."""

    def phi(self, window):
        return TorchPredictor("reference", models.Given(self.predictor, self.hyp)).phi(window)


def test_the_hypothesis_source_rolls_every_branch_out_compiled_as_the_network_under_it_and_plans_the_most_probable():
    """gradients=student_hyp: open-loop values and closed-loop candidates under hypotheses given per rollout (two
    distinct, interleaved) are those of the float64 torch network fed each rollout's hypotheses; a step plans under the
    history's most probable hypotheses (belief > 0.5)."""
    w, j, seen, obs = oracle_world(False, 0.5, nudge=3)
    s = make("dense", ["gradients=cv", "mpc=interactive"])[2]
    student = random_student()
    source = Hypotheses("student_hyp", student)
    reference = TorchUnder("reference", copy.deepcopy(student.module).double())
    hyp = np.array([[0, 1, 0, 1, 0], [0, 0, 0, 0, 0]] * 3, float)
    z = obs.z0
    ego = z[:2] + np.arange(1, 13)[:, None] * [z[3] * DT, 0.0] + np.linspace(0, 1.5, 6)[:, None, None] * [0, 1]
    np.testing.assert_allclose(source.given(hyp).values(obs.history, ego), reference.given(hyp).values(obs.history, ego),
                               atol=1e-5)  # the fixed student shifts its float32 bias in float32
    compiled, torch_ = (s.strategy.closed_loop.chased(s, obs, src, hyp[:2]) for src in (source, reference))
    assert compiled[0] == torch_[0] and len(compiled[0]) > 0
    for a, b in zip(compiled[1:], torch_[1:]):
        np.testing.assert_allclose(a, b, atol=1e-5)
    step = source.at(obs.history)
    likely = (source.belief(obs.history) > 0.5).astype(float)
    assert step.hyp is None and step.compiled
    np.testing.assert_allclose(step.values(obs.history, ego), reference.given(np.tile(likely, (6, 1))).values(obs.history, ego),
                               atol=1e-5)
