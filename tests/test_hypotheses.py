"""Hypothesis predictors (issue 72): the student's certificate holds under every fixed hypothesis, the hypothesis is an
input that changes the prediction, ONNX answers as torch does for the new inputs and outputs, the belief learnt from
the world's latched decisions rises on a recorded yield, and the distill jobs for both models run and log."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from conftest import BOX, REGION, compose_cfg
from data.dataset import Intervention
from data.perception import observe
from distill import certificate, metrics
from distill.export import export_onnx, load_onnx
from distill.models import HypothesisPredictor, TorchPredictor, probe_window
from distill.student import HypothesisStudent
from distill.tasks import belief_bce
from distill.teacher import HypothesisTeacher
from distill.train import hypotheses


@pytest.fixture(scope="module")
def student():
    """random_student()."""
    return random_student()


def random_student():
    """A random hypothesis student whose head is far from linear and whose hypothesis inputs weigh heavily."""
    torch.manual_seed(0)
    net = HypothesisStudent([12, 10], [0.5, 0.25], pos_scale=10.0, vel_scale=0.5, acc_scale=0.05, belief=[8])
    torch.nn.init.normal_(net.layers[-1].weight, std=0.8)
    with torch.no_grad():
        net.layers[0].weight[:, -4:].normal_(std=2.0)
    return HypothesisPredictor("student_hyp", net.eval())


def windows(n, seed):
    """Plausible windows (n, 8, 5, 2): the probe window with each car's positions and speeds perturbed."""
    rng = np.random.default_rng(seed)
    w = np.repeat(probe_window(), n, axis=0)
    return w + rng.normal(0, 1.0, (n, 1, 5, 2)) + np.arange(8)[None, :, None, None] * rng.normal(0, 0.1, (n, 1, 5, 2))


def test_every_hypothesis_is_certified_and_the_certificate_holds_for_it(student):
    """A hypothesis shifts only the first layer's bias: the global constants are the same for all 16, and under each the
    sampled gradients and finite-difference Hessians stay within its global and its region certificate; the numpy path
    under a hypothesis is the torch network's, and the hypothesis changes the prediction."""
    net, X = student.module, windows(40, 1)
    lo, hi = certificate.feature_box(REGION)
    inside = certificate.region_samples(lo, hi, 40, np.random.default_rng(2))
    globs, outputs = [], []
    for h in hypotheses(4):
        given = student.given(h)
        glob = certificate.constants(given.weights, given.s, BOX)
        globs.append([glob[k] for k in ("theta_x", "theta_y", "L")])
        region = certificate.tightest(glob, certificate.region_constants(given.weights, given.s, lo, hi))
        autodiff = TorchPredictor("student_hyp", given.module).phi_jac
        jac = lambda w: given.jac_cols(w, certificate.ego_columns())  # noqa: E731
        certificate.verify(glob, certificate.sampled(autodiff, jac, np.concatenate([X, inside])))
        certificate.verify(region, certificate.sampled(autodiff, jac, inside))
        with torch.no_grad():
            torch_next = net(torch.tensor(X, dtype=torch.float32), torch.tensor(np.tile(h, (len(X), 1)), dtype=torch.float32))
        np.testing.assert_allclose(given.phi(X), torch_next.double().numpy(), atol=1e-4)
        outputs.append(given.phi(X))
    np.testing.assert_allclose(globs, np.tile(globs[0], (len(globs), 1)), rtol=1e-12)
    assert np.abs(outputs[0] - outputs[-1]).max() > 1e-3  # nobody against everybody yielding


def test_a_violated_bound_under_one_hypothesis_is_caught(student):
    """The check can fail: a certificate shrunk below what one hypothesis's samples show is rejected."""
    given = student.given(hypotheses(4)[-1])
    glob = certificate.constants(given.weights, given.s, BOX)
    emp = certificate.sampled(TorchPredictor("student_hyp", given.module).phi_jac,
                              lambda w: given.jac_cols(w, certificate.ego_columns()), windows(20, 3))
    with pytest.raises(Exception, match="certificate violated"):
        certificate.verify({**glob, "L": 0.5 * emp["emp_L_max"]}, emp)


@pytest.mark.parametrize("name", ["teacher_hyp", "student_hyp"])
def test_onnx_answers_as_torch_under_hypotheses_with_the_belief(tmp_path, name):
    torch.manual_seed(1)
    if name == "teacher_hyp":
        net = HypothesisTeacher(16, 16, [32], [16], pos_scale=10.0, vel_scale=0.5, acc_scale=0.05)
        torch.nn.init.normal_(net.decoder[-1].weight, std=0.5)
    else:
        net = HypothesisStudent([16], [0.5, 0.25], pos_scale=10.0, vel_scale=0.5, acc_scale=0.05, belief=[8])
        torch.nn.init.normal_(net.layers[-1].weight, std=0.5)
    predictor = HypothesisPredictor(name, net.eval())
    export_onnx(net, tmp_path / f"{name}.onnx", 8, 5)
    onnx = load_onnx(name, tmp_path)
    X = windows(7, 4)
    hyp = np.random.default_rng(5).integers(0, 2, (7, 5)).astype(float)
    nxt, belief = onnx.answers(X, hyp)
    np.testing.assert_allclose(nxt, predictor.given(hyp).phi(X), atol=1e-4)
    np.testing.assert_allclose(belief, predictor.belief(X), atol=1e-5)
    assert np.abs(nxt - onnx.answers(X, 1.0 - hyp)[0]).max() > 1e-4  # the hypothesis input is in the graph
    assert (belief[:, 0] == 0).all() and ((belief[:, 1:] > 0) & (belief[:, 1:] < 1)).all()


def nudged(seed, yields, steps=14):
    """A dense world whose car just behind the ego in the target lane holds decision `yields`, the ego nudging towards
    its lane at its own speed: per step the predictor's window, that car's slot (None when out of the slots), the steps
    since the ego first encroached on it (-1 before), and its speed (m/s)."""
    sc = instantiate(compose_cfg("make_dataset").scenario, _convert_="all")
    world = sc.make_world(seed)
    z = world.states()
    behind = np.flatnonzero((world.road.lane_of(z[:, 1]) == 1) & (z[:, 0] < z[0, 0]))
    j = int(behind[np.argmax(z[behind, 0])])
    decisions = world.decisions()
    decisions[j] = yields
    world = world.with_decisions(decisions)
    ego = Intervention(0.55 * sc.y_ref, float(z[0, 3]))
    out, first = [], -1
    for k in range(steps):
        world.step(ego(world))
        first = k if first < 0 and world.encroachments()[j] > 0 else first
        seen = observe(world, 4, 8)
        slot = np.flatnonzero(seen.ids == j)
        out.append((seen.history, int(slot[0]) if len(slot) else None, k - first if first >= 0 else -1, world.states()[j, 3]))
    return out


def cases(seeds):
    """Windows (n, 8, 5, 2), slots (n,), steps since the first encroachment (n,), labels (n,) and whether the decision
    shows (n,) (the car's speed under the two decisions more than 0.3 m/s apart) of both decisions of each seed's car
    behind, at the steps where that car is in the slots under both."""
    rows = []
    for s in seeds:
        runs = [nudged(s, yields) for yields in (True, False)]
        for (h1, j1, s1, v1), (h0, j0, s0, v0) in zip(*runs):
            if j1 is not None and j0 is not None:
                rows += [(h1, j1, s1, True, abs(v1 - v0) > 0.3), (h0, j0, s0, False, abs(v1 - v0) > 0.3)]
    return tuple(np.array(c) for c in zip(*rows))


def test_the_belief_rises_on_a_recorded_yield_and_stays_low_on_a_stubborn_driver():
    """A small hypothesis teacher's belief head trained by the job's loss (belief_bce) on the world's own histories of
    a nudging ego, each driver behind it holding both decisions in turn, is scored on held-out worlds: where the
    driver that yields has braked for the ego, its belief is the higher one of the pair, and before the first
    encroachment the two are the same (the history cannot tell them apart)."""
    torch.manual_seed(0)
    X, j, since, y, _ = cases(range(100, 140))
    net = HypothesisTeacher(32, 32, [32], [32], pos_scale=10.0, vel_scale=0.5, acc_scale=0.05)
    target = np.zeros((len(X), 5))
    target[np.arange(len(X)), j] = y
    weight = np.zeros((len(X), 5))
    weight[np.arange(len(X)), j] = 1.0
    T = [torch.tensor(a, dtype=torch.float32) for a in (X, target, weight)]
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    rng = np.random.default_rng(0)
    for _ in range(300):
        b = rng.integers(0, len(X), 128)
        loss = belief_bce(net, T[0][b], T[1][b], T[2][b])
        opt.zero_grad()
        loss.backward()
        opt.step()
    Xt, jt, st, yt, shown = cases(range(200, 220))
    p = HypothesisPredictor("teacher_hyp", net.eval()).belief(Xt)[np.arange(len(Xt)), jt]
    assert shown.sum() >= 20
    assert metrics.auc(p[shown], yt[shown]) > 0.9
    pairs = p[shown].reshape(-1, 2)  # (yields, stubborn) at one step of one world
    assert (pairs[:, 0] > pairs[:, 1]).mean() > 0.9 and (pairs[:, 0] - pairs[:, 1]).mean() > 0.2
    before = (st < 0).reshape(-1, 2).all(1)
    np.testing.assert_allclose(p.reshape(-1, 2)[before, 0], p.reshape(-1, 2)[before, 1], atol=1e-6)


@pytest.fixture(scope="module")
def hyp_models(tiny_dataset, tmp_path_factory):
    """A models folder with a one-epoch hypothesis teacher and student on a quarter of the tiny dataset, and both jobs'
    metrics."""
    from distill.train import run

    models_dir, runs = tmp_path_factory.mktemp("hyp_models"), tmp_path_factory.mktemp("hyp_runs")

    def job(name, *overrides):
        return run(compose_cfg("distill", [f"dataset_dir={tiny_dataset}", f"models_dir={models_dir}", f"run_dir={runs / name}",
                                           "trainer.enable_progress_bar=false", f"model={name}", "trainer.max_epochs=1",
                                           "model.data.fraction=0.25", *overrides]))

    teacher = job("teacher_hyp")
    student = job("student_hyp", "model.certificate.samples=480", "model.certificate.scenarios=[dense]")
    return models_dir, teacher, student


@pytest.mark.slow  # two tiny trainings (module fixture `hyp_models`)
def test_hypothesis_jobs_log_the_belief_and_per_hypothesis_figures_and_export_both_answers(hyp_models, tiny_dataset):
    import json

    import mlflow

    from distill import models

    models_dir, teacher, student = hyp_models
    for r in (teacher, student):
        assert 0.0 <= r["belief_brier"] <= 1.0 and 0.0 < r["belief_brier_prior"] <= 1.0  # the prior is the train split's
        assert r["belief_brier_ratio"] == pytest.approx(r["belief_brier"] / r["belief_brier_prior"])
        assert r["n_belief_cases_0.0s"] > 0 and all(f"belief_auc_{lag:.1f}s" in r for lag in metrics.BELIEF_LAGS_S)
        assert r["n_cars_yielders"] > 0 and r["n_cars_stubborn"] > 0
        assert np.isfinite(r["ade_rollout_m_yielders"]) and np.isfinite(r["ade_rollout_m_stubborn_cv"])
        assert r["onnx_max_err_m"] <= 1e-4 and r["onnx_belief_max_err"] <= 1e-4
    doc = json.loads((models_dir / "certificate_student_hyp.json").read_text())
    assert len(doc["hypotheses"]) == 16
    assert all(v <= 1.0 for h in doc["hypotheses"].values() for v in h["ratios"].values())
    assert student["cert_L"] == max(h["constants_m"]["L"] for h in doc["hypotheses"].values())
    run = mlflow.search_runs(experiment_names=["distill"], filter_string="params.model = 'student_hyp'").iloc[-1]
    assert "plots/belief_reliability.png" in [a.path for a in mlflow.MlflowClient().list_artifacts(run.run_id, "plots")]
    for name in ("teacher_hyp", "student_hyp"):
        p = models.load(name, models_dir)
        X = dataset_windows(tiny_dataset)
        hyp = np.tile([0.0, 1.0, 0.0, 1.0, 0.0], (len(X), 1))
        nxt, belief = load_onnx(name, models_dir).answers(X, hyp)
        np.testing.assert_allclose(nxt, p.given(hyp).phi(X), atol=1e-4)
        np.testing.assert_allclose(belief, p.belief(X), atol=1e-5)


def dataset_windows(root, n=16):
    """The first n test windows of a dataset (m)."""
    from data import dataset

    return dataset.load(root, "test")["X"][:n].astype(float)


@pytest.mark.slow  # two tiny trainings (module fixture `hyp_models`)
def test_a_student_of_the_other_kind_than_its_teacher_is_one_line(hyp_models, tiny_dataset, tmp_path):
    from core.jobs import UserError
    from distill.train import run

    models_dir = hyp_models[0]
    with pytest.raises(UserError, match="model.teacher=teacher_hyp: model=student distils from a teacher without hypotheses"):
        run(compose_cfg("distill", [f"dataset_dir={tiny_dataset}", f"models_dir={models_dir}", f"run_dir={tmp_path}",
                                    "model=student", "model.teacher=teacher_hyp"]))


def test_the_seen_oracle_knows_a_decision_only_once_the_driver_has_braked_for_the_ego():
    """knows=seen: a yielder that has not yet braked for the ego is taken as stubborn (the oracle predicts it keeps its
    pace under a nudge the true world answers by braking); once it has braked, its decision is known and the two oracles
    agree."""
    from planner.gradients import WorldModel

    sc = instantiate(compose_cfg("make_dataset").scenario, _convert_="all")

    def predicted(world, knows, j, steps=20):
        """Car j's predicted x (steps,) under the nudging ego's plan, by the oracle that knows `knows`."""
        drive, ego = world.copy(), Intervention(0.55 * sc.y_ref, float(world.states()[0, 3]))
        plan = []
        for _ in range(steps):
            drive.step(ego(drive))
            plan.append(drive.states()[0, :2])
        oracle = WorldModel(knows)
        oracle.world, oracle.ids = world, np.arange(len(world.states()))
        return oracle.react(world.past_xy(8), lambda window, tau: plan[tau][None], steps, 1)[0, :, j, 0]

    for seed in range(200, 220):
        world = sc.make_world(seed)
        z = world.states()
        behind = np.flatnonzero((world.road.lane_of(z[:, 1]) == 1) & (z[:, 0] < z[0, 0]))
        j = int(behind[np.argmax(z[behind, 0])])
        decisions = world.decisions()
        decisions[j] = True
        world = world.with_decisions(decisions)
        unshown = world.copy()
        ego = Intervention(0.55 * sc.y_ref, float(z[0, 3]))
        for _ in range(20):
            world.step(ego(world))
            if world.shown[j]:
                break
        if world.shown[j]:
            break
    assert world.shown[j], "no driver behind the ego braked for its nudge in 20 worlds"
    assert not unshown.seen_decisions()[j] and world.seen_decisions()[j]
    assert predicted(unshown, "all", j)[-1] < predicted(unshown, "seen", j)[-1] - 0.05  # only the truth brakes
    np.testing.assert_allclose(predicted(world, "all", j), predicted(world, "seen", j))


class Recorded:
    """A hypothesis predictor that has seen the runs: under each car's recorded decision its recorded next position,
    under any other hypothesis constant velocity (for the whole window); its belief is the recorded decision."""

    name = "recorded"

    def __init__(self, a):
        self.table = {self.key(x): (y, h) for x, y, h in zip(a["X"], a["Y"].astype(float), a["will_yield"])}

    @staticmethod
    def key(window):
        return np.round(np.asarray(window, dtype=float), 3).tobytes()

    def given(self, hyp):
        from distill.predictors import ConstantVelocity

        outer, cv = self, ConstantVelocity()

        class Given:
            def phi(self, X):
                out = cv.phi(X)
                for i, x in enumerate(X):
                    y, h = outer.table.get(outer.key(x), (None, None))
                    if y is not None and (np.asarray(hyp[i])[1:] == h[1:]).all():
                        out[i] = y
                return out

        return Given()

    def belief(self, X):
        return np.array([self.table[self.key(x)][1] for x in X], dtype=float) * (np.arange(X.shape[2]) > 0)


def test_the_hypothesis_figures_score_a_predictor_that_knows_the_runs_perfectly_and_its_opposite_as_cv(tiny_dataset):
    """metrics.hypothesis_quality on the tiny test split's own runs (whose windows are unique): a predictor that
    replays each recorded run under its recorded decisions has no rollout error, sorts every forcing braking and raises
    no false alarm under both hypotheses, and given the opposite hypotheses it is constant velocity; its belief, the
    decision itself, has Brier 0 and AUC 1, and the data's reveal is dataset.reveal's."""
    from data import dataset
    from distill.predictors import ConstantVelocity

    a = dataset.load(tiny_dataset, "test")
    a = {k: v[a["branch"] == 0] for k, v in a.items()}
    dt = dataset.read_meta(tiny_dataset)["dt"]
    r = metrics.hypothesis_quality(Recorded(a), a, 8, 0.5, dt)
    cv = metrics.engaged_rollouts(ConstantVelocity(), a, 8, dt)
    for label in ("yielders", "stubborn"):
        assert r[f"n_cars_{label}"] > 0
        assert r[f"ade_rollout_m_{label}"] < 1e-4
        assert r[f"ade_rollout_m_{label}_opposite"] == pytest.approx(r[f"ade_rollout_m_{label}_cv"])
        assert r[f"ade_rollout_m_{label}_cv"] > 0.01
        assert r[f"brake_fa_{label}"] == 0.0 and (r[f"brake_auc_{label}"] == 1.0 or np.isnan(r[f"brake_auc_{label}"]))
        assert r[f"brake_corr_{label}"] > 0.99
    assert r["belief_brier"] == 0.0 and r["belief_auc"] == 1.0 and r["belief_brier_prior"] == 0.25
    assert r["seen_auc_nearest_2.0s"] == pytest.approx(dataset.reveal(a, dt)["reveal_auc_nearest_2.0s"], nan_ok=True)
    err, yields, engaged, brake, true = cv
    assert (brake >= 0).all() and (true >= 0).all() and true[engaged].max() > 1.0  # braking is in the data
