"""The gradient surrogate: central differences vs autodiff, ONNX parity and refusals, and a trained one beats baselines."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate

from conftest import compose_cfg
from core.jobs import UserError
from core.rollout import SLOTS, T_OBS
from distill.models import StudentPredictor, TorchPredictor
from surrogate import jacobians, models
from surrogate.export import export
from surrogate.network import Fused


def smooth_student(seed=0):
    """A student-shaped GELU network with random (not trained) weights whose others react to the ego."""
    torch.manual_seed(seed)
    net = instantiate(compose_cfg("distill", ["model=student"]).model.net, hidden=[16, 16])
    torch.nn.init.normal_(net.layers[-1].weight, 0.0, 0.5)
    return net.eval()


def stand_in(name, models_dir):
    """Drop-in for distill.models.load: the source predictor the job learns, without any trained model on disk."""
    return TorchPredictor(name, smooth_student())


class Blind(torch.nn.Module):
    """A predictor whose others never react to the ego: they see a phantom ego 40 m behind car 1 instead."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, window):
        phantom = window[:, :, 1:2] - torch.tensor([40.0, 4.0], dtype=window.dtype)
        return self.net(torch.cat([phantom, window[:, :, 1:]], dim=2))


def blind_stand_in(name, models_dir):
    """stand_in's network made blind to the ego (Blind): training data with no interaction in it."""
    return TorchPredictor(name, Blind(smooth_student()).eval())


def planning_states(n=6, seed=0):
    """(history (n, T_obs, SLOTS, 2), ego plan (n, T_p, 2)): a synthetic platoon history with sampled ego plans."""
    rng = np.random.default_rng(seed)
    start = np.array([[0.0, 0.0], [12.0, 4.0], [5.0, 4.0], [-2.0, 4.0], [-9.0, 4.0]])
    vel = np.array([1.0, 0.0]) + rng.normal(0, 0.05, (n, 1, SLOTS, 2))
    history = start[None, None] + rng.normal(0, 0.5, (n, 1, SLOTS, 2)) + np.arange(T_OBS)[None, :, None, None] * vel
    return instantiate(compose_cfg("surrogate").states).sample(history, rng)


def planning_windows(n=6, seed=0):
    """Windows the planner's recursion visits from planning_states."""
    return jacobians.planner_windows(StudentPredictor(smooth_student()).phi, *planning_states(n, seed))


def test_central_differences_agree_with_autodiff_on_a_smooth_student():
    W = planning_windows()
    J_auto = jacobians.autodiff(TorchPredictor("student", smooth_student()), W)
    J_central = jacobians.central(StudentPredictor(smooth_student()).phi, W, h=1e-4)  # float64 black box
    reaction = J_auto.reshape(len(W), SLOTS, 2, T_OBS, SLOTS, 2)[:, 1:, :, :, 0]  # others' next xy w.r.t. the ego's track
    assert np.abs(reaction).max() > 1e-2  # the others do react to the ego, so the check has teeth
    np.testing.assert_allclose(J_central, J_auto, atol=1e-4 * np.abs(J_auto).max())


def jacobian_net(slots=SLOTS, **overrides):
    """The surrogate network as the job configures it, with test-sized overrides."""
    return instantiate(compose_cfg("surrogate").network, T_obs=T_OBS, M=slots, **overrides)


def exported(tmp_path, module, slots=SLOTS):
    """Export `module` to tmp_path/surrogate.onnx and return the folder."""
    export(module, tmp_path / "surrogate.onnx", T_OBS, slots, source="student")
    return tmp_path


def test_onnx_matches_torch_and_records_its_source(tmp_path):
    torch.manual_seed(1)
    net = jacobian_net(hidden=32, depth=2).eval()
    W = planning_windows(2)
    net.fit_normalisation(W, jacobians.autodiff(TorchPredictor("student", smooth_student()), W))
    source = smooth_student()
    surrogate = models.load(exported(tmp_path, Fused(net, source)), T_OBS, SLOTS - 1)
    with torch.no_grad():
        J, nxt = net(torch.as_tensor(W, dtype=torch.float32)).numpy(), source(torch.as_tensor(W, dtype=torch.float32)).numpy()
    assert surrogate.source == "student" and surrogate.fused
    np.testing.assert_allclose(surrogate.jac(W), J, atol=1e-5 * np.abs(J).max())
    nxt_onnx, J_onnx = surrogate.phi_jac(W)
    np.testing.assert_allclose(nxt_onnx, nxt, atol=1e-4)
    np.testing.assert_allclose(J_onnx, J, atol=1e-5 * np.abs(J).max())


def test_missing_file_names_the_command(tmp_path):
    with pytest.raises(UserError, match=r"surrogate.onnx not found: run `surrogate`"):
        models.load(tmp_path, T_OBS, SLOTS - 1)


def test_corrupt_file_is_refused_with_the_expected_shapes(tmp_path):
    (tmp_path / "surrogate.onnx").write_bytes(b"not a protobuf" * 10)
    with pytest.raises(UserError, match=r"surrogate.onnx is not a valid ONNX model.*window \(B, 8, 5, 2\) -> J \(B, 10, 80\)"):
        models.load(tmp_path, T_OBS, SLOTS - 1)


def test_wrong_shape_model_is_refused(tmp_path):
    wrong = jacobian_net(SLOTS - 1, hidden=8, depth=1)  # a surrogate for four cars, not five
    with pytest.raises(UserError, match=r"surrogate.onnx has inputs .*\[8, 4, 2\].*expected window \(B, 8, 5, 2\)"):
        models.load(exported(tmp_path, wrong, SLOTS - 1), T_OBS, SLOTS - 1)


def job_cfg(tmp_path, tiny_dataset, *overrides):
    """The `surrogate` job at test size, learning the stand-in source on the tiny dataset."""
    return compose_cfg("surrogate", [
        f"dataset_dir={tiny_dataset}", f"models_dir={tmp_path}",
        f"out_dir={tmp_path}", "predictor._target_=test_surrogate.stand_in", "source=student",
        "data.dataset_windows=1500", "data.plan_states=300", "data.val_dataset_windows=200",
        "data.val_plan_states=30", "data.test_plan_states=30", "network.hidden=128",
        "trainer.max_epochs=15", "timing.repeats=20", "timing.predictors=[]", *overrides])


def test_trained_surrogate_beats_the_mean_and_constant_velocity_jacobians(tmp_path, tiny_dataset):
    import mlflow

    from surrogate.cli import run

    m = run(job_cfg(tmp_path, tiny_dataset))
    assert m["jac_rel_err"] < 0.8 * m["jac_rel_err_mean"] and m["jac_rel_err_mean"] < m["jac_rel_err_cv"]
    assert m["react_rel_err"] < 0.8 * m["react_rel_err_mean"]  # the part the predictor contributes
    assert m["grad_rel_err"] < m["grad_rel_err_mean"] and m["grad_cosine"] > m["grad_cosine_cv"]
    # along ramps, where the composed loss trains it: below both baselines with intervals apart
    assert m["ramp_grad_rel_err_hi"] < min(m["ramp_grad_rel_err_mean_lo"], m["ramp_grad_rel_err_cv_lo"])
    assert m["ramp_react_rel_err_hi"] < m["ramp_react_rel_err_mean_lo"] and m["ramp_react_rel_err"] < 0.5
    assert m["onnx_max_abs_err"] < 1e-4
    assert models.load(tmp_path, T_OBS, SLOTS - 1).source == "student"
    runs = mlflow.search_runs(experiment_names=["surrogate"], filter_string="params.source = 'student'")
    assert len(runs) >= 1 and "metrics.grad_cosine" in runs


def test_missing_dataset_and_missing_teacher_name_their_commands(tmp_path, tiny_dataset, capsys):
    from surrogate.cli import run

    with pytest.raises(SystemExit):
        run(job_cfg(tmp_path, tiny_dataset, f"dataset_dir={tmp_path}"))
    assert "make-dataset" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        run(job_cfg(tmp_path, tiny_dataset, "predictor._target_=distill.models.load", "source=teacher"))
    assert "run `distill model=teacher`" in capsys.readouterr().err


def test_the_baselines_and_the_reaction_split_on_a_constructed_state():
    """A linear predictor whose others react to the ego: constant velocity's Jacobian (the others blind to the ego)
    scores reaction error 1 and a d b_i / d Z error equal to the reaction part's share, and that part plus the direct
    term (the ego's own xy, exact for every source) is the whole d b_i / d Z."""
    from core.rollout import b_i_jacobian, rollout_jacobian
    from surrogate.evaluate import gradient_accuracy

    rng = np.random.default_rng(0)
    T_p, R = 8, 3.95
    A = rng.normal(0.0, 0.05, (SLOTS * 2, T_OBS * SLOTS * 2))
    A[:, -SLOTS * 2:] += np.eye(SLOTS * 2)  # each car stays near its last position
    blind = A.copy()
    blind[2:, [k for k in range(A.shape[1]) if (k // 2) % SLOTS == 0]] = 0.0  # others ignore every ego column
    histories = rng.normal(0.0, 3.0, (2, T_OBS, SLOTS, 2))
    egos = rng.normal(0.0, 3.0, (2, T_p, 2))
    windows, nexts, J = [], [], []
    for h, e in zip(histories, egos):
        seen = []
        rollout_jacobian(lambda w: seen.append(w[0].copy()) or ((A @ w.reshape(-1)).reshape(1, SLOTS, 2), A[None]), h, e)
        windows.append(np.stack(seen))
        nexts.append(np.stack([(A @ w.reshape(-1)).reshape(SLOTS, 2) for w in seen]))
        J.append(np.broadcast_to(A, (T_p, *A.shape)))
    windows, nexts, J = map(np.stack, (windows, nexts, J))
    scores = gradient_accuracy(windows, nexts, J, {"cv": np.broadcast_to(blind, J.shape), "exact": J}, histories, egos, R)
    assert scores["cv"]["react_rel_err"][0] == pytest.approx(1.0) and scores["exact"]["react_rel_err"][0] == pytest.approx(0.0)
    assert scores["cv"]["react_wrel_err"] == pytest.approx((1.0, 1.0, 1.0)) and scores["exact"]["react_wrel_err"][0] == 0.0
    shares = []
    for h, e in zip(histories, egos):
        values, grads = rollout_jacobian(lambda w: ((A @ w.reshape(-1)).reshape(1, SLOTS, 2), A[None]), h, e)
        whole = b_i_jacobian(values, grads, R)[1]
        direct = grads.copy()
        direct[:, 1:] = 0.0  # the others held where the predictor put them
        gap = values[:, :1] - values[:, 1:]  # (T_p, N, 2)
        react = -2.0 * np.einsum("tnk,tnkse->ntse", gap, grads[:, 1:])  # by hand: d b_i through the others' reaction
        react_Z = np.zeros((*react.shape[:3], 4))
        react_Z[..., :2] = react
        assert np.allclose(b_i_jacobian(values, direct, R)[1] + react_Z.reshape(whole.shape), whole)
        shares.append(np.linalg.norm(react_Z) / np.linalg.norm(whole))
    assert scores["cv"]["grad_rel_err"][0] == pytest.approx(np.mean(shares)) and 0.05 < np.mean(shares) < 1.0
    from scipy.stats import t as student_t

    half = student_t.ppf(0.975, len(shares) - 1) * np.std(shares, ddof=1) / np.sqrt(len(shares))  # its 95% interval over states
    assert np.allclose(scores["cv"]["grad_rel_err"][1:], [np.mean(shares) - half, np.mean(shares) + half])


def test_a_pairing_is_scored_on_its_own_rollout_against_the_sources():
    """Another predictor's values (the source's linear map plus a bias on the others' next positions) with the source's
    own local Jacobian at that rollout's windows: its score is the relative error of the d b_i / d Z it composes from
    its own values, computed here by hand; with no bias it scores 0."""
    from core.rollout import b_i_jacobian, rollout_jacobian
    from surrogate.evaluate import gradient_accuracy

    rng = np.random.default_rng(1)
    T_p, R = 8, 3.95
    A = rng.normal(0.0, 0.05, (SLOTS * 2, T_OBS * SLOTS * 2))
    A[:, -SLOTS * 2:] += np.eye(SLOTS * 2)
    bias = np.r_[0.0, 0.0, rng.normal(0.0, 0.3, (SLOTS - 1) * 2)]  # the ego slot follows the plan whatever phi says
    histories, egos = rng.normal(0.0, 3.0, (3, T_OBS, SLOTS, 2)), rng.normal(0.0, 3.0, (3, T_p, 2))

    def recorded(c):
        """(windows, nexts, J) (n, T_p, ...) of the rollouts of next = A @ window + c, and each state's d b_i / d Z."""
        phi_jac = lambda w: ((A @ w.reshape(-1) + c).reshape(1, SLOTS, 2), A[None])
        out, truths = [], []
        for h, e in zip(histories, egos):
            seen = []
            values, grads = rollout_jacobian(lambda w: seen.append(w[0].copy()) or phi_jac(w), h, e)
            out.append((np.stack(seen), np.stack([phi_jac(w[None])[0][0] for w in seen]), np.broadcast_to(A, (T_p, *A.shape))))
            truths.append(b_i_jacobian(values, grads, R)[1])
        return tuple(map(np.stack, zip(*out))), truths

    (W, nexts, J), truth = recorded(0.0)
    pair, biased = recorded(bias)
    scores = gradient_accuracy(W, nexts, J, {"pair": pair, "same": recorded(0.0)[0]}, histories, egos, R)
    by_hand = [np.linalg.norm(b - t) / np.linalg.norm(t) for b, t in zip(biased, truth)]
    assert scores["pair"]["grad_rel_err"][0] == pytest.approx(np.mean(by_hand)) and np.mean(by_hand) > 0.01
    assert scores["same"]["grad_rel_err"][0] == pytest.approx(0.0, abs=1e-12)


def test_the_weighted_error_pools_states_by_the_size_of_their_truth():
    """Two states, a tiny reaction missed by 5x and a large one by 10%: the mean of ratios says 2.55, the weighted error
    (1.5 / 10.1) says what the error is where the reaction is; its interval, resampling the states, spans both states'
    ratios."""
    from surrogate.evaluate import weighted

    value, lo, hi = weighted([0.5, 1.0], [0.1, 10.0])
    assert value == pytest.approx(1.5 / 10.1)
    assert lo == pytest.approx(0.1) and hi == pytest.approx(5.0)  # all-large and all-tiny resamples


def test_a_surrogate_trained_without_interaction_scores_at_the_no_reaction_baseline(tmp_path, tiny_dataset):
    """Trained on a source whose others never react (so its mean Jacobian has no reaction either), then scored against
    the reacting source on its planning states: its reaction error is the baseline's 1, not better."""
    from surrogate.cli import per_state, run
    from surrogate.evaluate import gradient_accuracy

    run(job_cfg(tmp_path, tiny_dataset, "predictor._target_=test_surrogate.blind_stand_in"))
    history, ego_future = planning_states(30, seed=3)
    source = TorchPredictor("student", smooth_student())
    W = jacobians.planner_windows(source.phi, history, ego_future)
    J, n = jacobians.autodiff(source, W), len(history)
    J_hat = models.load(tmp_path, T_OBS, SLOTS - 1).jac(W)
    scores = gradient_accuracy(per_state(n, W), per_state(n, source.phi(W)), per_state(n, J), {"blind": per_state(n, J_hat)},
                               history, ego_future, 3.95)
    assert scores["blind"]["react_rel_err"][1] > 0.9  # its interval's lower end: no better than predicting no reaction
    assert scores["blind"]["react_wrel_err"][1] > 0.9


def linear_rollout(A, h, e):
    """Values and d values / d ego plan of the rollout of the linear predictor next = A @ window, one planning state."""
    from core.rollout import rollout_jacobian

    return rollout_jacobian(lambda w: ((A @ w.reshape(-1)).reshape(1, SLOTS, 2), A[None]), h, e)


def test_a_derivative_along_ramps_is_the_rollouts_response_to_a_change_of_speed():
    """For a linear predictor the rollout is affine in the plan, so its response to a ramp (the ego's speed changed by
    1 m per step from step k on, along x or y) is exactly the derivative along that ramp."""
    from surrogate.evaluate import along_ramps

    rng = np.random.default_rng(1)
    T_p = 8
    A = rng.normal(0.0, 0.05, (SLOTS * 2, T_OBS * SLOTS * 2))
    A[:, -SLOTS * 2:] += np.eye(SLOTS * 2)
    h, e = rng.normal(0.0, 3.0, (T_OBS, SLOTS, 2)), rng.normal(0.0, 3.0, (T_p, 2))
    values, grads = linear_rollout(A, h, e)
    steps = np.arange(1, T_p + 1)
    for k in (0, 3, T_p - 1):
        for axis in (0, 1):
            changed = e.copy()
            changed[:, axis] += np.maximum(0, steps - k)  # 1 m per step faster from step k + 1 on
            assert np.allclose(linear_rollout(A, h, changed)[0] - values, along_ramps(grads)[..., k, axis], atol=1e-9)


def test_the_composed_reaction_loss_is_zero_at_the_source_and_positive_off_it():
    """The training loss on whole planning states: the network's Jacobians composed over the rollout and compared along
    ramps with the source's; exactly the source's Jacobians score 0, a perturbed copy more."""
    from surrogate.network import JacobianNet
    from surrogate.training import SurrogateModule, reaction

    source = StudentPredictor(smooth_student())
    history, ego_future = planning_states(4, seed=5)
    W = jacobians.planner_windows(source.phi, history, ego_future)
    J = jacobians.autodiff(source, W).reshape(4, 8, SLOTS * 2, -1)

    class Exact(JacobianNet):
        def forward(self, window):
            return torch.as_tensor(self.J_now, dtype=torch.float32)

    net = Exact(T_OBS, SLOTS, hidden=4, depth=1, absolute="")
    module = SurrogateModule(net, lr=1e-3, weight_decay=0.0, composed=1.0)
    windows = torch.as_tensor(W.reshape(4, 8, T_OBS, SLOTS, 2), dtype=torch.float32)
    target = torch.as_tensor(reaction(J), dtype=torch.float32)
    net.J_now = J.reshape(32, SLOTS * 2, -1)
    assert float(module.reaction_loss(windows, target)) < 1e-8
    net.J_now = net.J_now * 1.1
    assert float(module.reaction_loss(windows, target)) > 1e-3


def recorded(folder, n_files, seed=0, **changes):
    """n_files recorded planner episodes (as `planner record_dir=...` writes them) of synthetic planning states."""
    folder.mkdir(exist_ok=True)
    for k in range(n_files):
        history, ego_future = planning_states(40, seed=seed + k)
        arrays = {"history": history, "ego_future": ego_future, **changes}
        np.savez(folder / f"dense_admm_{k}.npz", **arrays)
    return folder


def test_planner_iterates_train_the_surrogate_and_hold_out_its_test(tmp_path, tiny_dataset):
    """With data.iterates the composed loss trains on recorded planner states and the last episode is the test: the
    ramp scores are logged for the surrogate and both baselines."""
    from surrogate.cli import run

    iterates = recorded(tmp_path / "iterates", 3)
    m = run(job_cfg(tmp_path, tiny_dataset, f"data.iterates={iterates}", "data.iterate_states=60",
                    "data.test_iterate_episodes=1", "module.composed=1.0", "trainer.max_epochs=3"))
    for key in ("ramp_grad_rel_err", "ramp_react_rel_err"):
        assert all(np.isfinite(m[f"{key}{s}"]) for s in ("", "_cv", "_mean"))
    assert m["ramp_react_rel_err_cv"] == pytest.approx(1.0) and 0.0 <= m["outside_box_share"] <= 1.0
    assert m["n_test"] == 30 * 8  # test_plan_states drawn from the held-out episode


@pytest.mark.parametrize("change, message", [
    ({"ego_future": np.zeros((40, 5, 2))}, r"dense_admm_0.npz: history \(40, 8, 5, 2\) and ego_future \(40, 5, 2\)"),
    ({"history": np.full((40, T_OBS, SLOTS, 2), np.nan)}, r"dense_admm_0.npz: non-finite positions"),
])
def test_bad_iterates_are_refused_naming_the_file(tmp_path, tiny_dataset, change, message):
    from surrogate.cli import run

    iterates = recorded(tmp_path / "iterates", 2, **change)
    with pytest.raises(SystemExit):
        run(job_cfg(tmp_path, tiny_dataset, f"data.iterates={iterates}", "data.test_iterate_episodes=1"))
    with pytest.raises(UserError, match=message):
        from surrogate.cli import load_iterates

        load_iterates(iterates, T_OBS, SLOTS, 8)
    assert not (tmp_path / "surrogate.onnx").exists()


def test_outside_its_training_box_the_surrogate_reads_the_nearest_state_it_knows():
    """Fitted on windows where every car keeps its lane, the network gives a window where car 3 changes lanes at 1 m
    per step the same Jacobian as one where it does so at 10 (its features clipped to the training box), while an
    unclipped copy extrapolates; inside the box both agree."""
    from surrogate.network import JacobianNet

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    t = np.arange(T_OBS)[None, :, None]
    x = rng.uniform(0.0, 50.0, (256, 1, SLOTS)) + rng.uniform(0.8, 1.2, (256, 1, SLOTS)) * t  # m, about 1 m per step
    y = np.broadcast_to(rng.choice([0.0, 4.0], (256, 1, SLOTS)), x.shape) + rng.normal(0.0, 0.01, x.shape)
    windows = np.stack([x, y], axis=-1)
    net = JacobianNet(T_OBS, SLOTS, 16, 2, "")
    net.fit_normalisation(windows, rng.normal(0.0, 1.0, (256, SLOTS * 2, T_OBS * SLOTS * 2)))
    free = JacobianNet(T_OBS, SLOTS, 16, 2, "")
    free.load_state_dict(net.state_dict())
    free.x_lo.fill_(-torch.inf), free.x_hi.fill_(torch.inf)
    lane_change = [windows[:1].copy() for _ in range(2)]
    for w, speed in zip(lane_change, (1.0, 10.0)):
        w[0, :, 3, 1] += speed * np.arange(T_OBS)
    inside, slow, fast = (torch.as_tensor(w, dtype=torch.float32) for w in (windows[:8], *lane_change))
    with torch.no_grad():
        assert torch.allclose(net(inside), free(inside))
        assert (net(slow) - net(fast)).abs().max() < 1e-3  # float32 rounding of the lane change's accelerations
        assert (free(slow) - free(fast)).abs().max() > 1.0
    assert not net.outside(inside).any() and net.outside(slow).all() and net.outside(fast).all()


def test_beside_a_student_the_job_scores_the_planners_pairing_on_the_students_own_rollout(tiny_models, tiny_dataset,
                                                                                         tmp_path, caplog):
    """With a teacher and a student in models_dir, the job also scores the student's exact Jacobians on the teacher's
    rollout and the planner's default pairing (gradients=surrogate: the student's values, the surrogate's J on the
    student's own windows) against teacher autodiff, and prints the pairing."""
    import logging

    from surrogate.cli import run

    caplog.set_level(logging.INFO)
    models_dir = tiny_models[0]
    for f in ("teacher.ckpt", "student.ckpt"):
        (tmp_path / f).symlink_to(models_dir / f)
    m = run(compose_cfg("surrogate", [f"dataset_dir={tiny_dataset}", f"models_dir={tmp_path}", f"out_dir={tmp_path / 'out'}",
                                      "data.dataset_windows=200", "data.plan_states=20", "data.val_dataset_windows=50",
                                      "data.val_plan_states=5", "data.test_plan_states=8", "trainer.max_epochs=1",
                                      "timing.repeats=1", "timing.budget_s=0.01", "timing.predictors=[]"]))
    for suffix in ("_student", "_over_student"):
        lo, mean, hi = (m[f"grad_rel_err{suffix}{e}"] for e in ("_lo", "", "_hi"))
        assert np.isfinite([lo, mean, hi]).all() and lo <= mean <= hi and mean > 0
    assert m["grad_rel_err_over_student"] != m["grad_rel_err"]  # its own rollout, not the teacher's
    assert "over the student's values" in caplog.text
