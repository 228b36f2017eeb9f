"""The distill job end to end on the tiny dataset: teacher beats constant velocity, resume, student certificate,
ONNX parity, and one-line errors for missing or corrupt files."""
import json

import mlflow
import numpy as np
import pytest
import torch

from conftest import TINY_TEACHER_EPOCHS, compose_cfg
from core.jobs import UserError, sha256
from data import dataset
from distill import models
from distill.export import load_onnx
from distill.perturb import box_windows, planner_like
from distill.train import run


def job(tiny_dataset, models_dir, run_dir, *overrides):
    """Run `distill` on the tiny dataset with small settings; returns its metrics."""
    return run(compose_cfg("distill", [f"dataset_dir={tiny_dataset}", f"models_dir={models_dir}", f"run_dir={run_dir}",
                                       "trainer.enable_progress_bar=false", *overrides]))


@pytest.fixture(scope="module")
def trained(tiny_models):
    """models_dir holding a tiny teacher and student, with both jobs' metrics (the session's tiny models)."""
    return tiny_models


def test_tiny_teacher_beats_constant_velocity(trained):
    _, r, _, _ = trained
    assert r["ade_1step_m"] < r["ade_1step_m_cv"]
    assert r["ade_rollout_m"] < r["ade_rollout_m_cv"]
    assert 1e5 <= r["params"] <= 1e6


def test_student_job_certifies_and_logs(trained):
    models_dir, _, r, _ = trained
    doc = json.loads((models_dir / "certificate.json").read_text())
    for k in ("s_x", "s_y", "theta_x", "theta_y", "L", "rho_bound", "rho_used"):
        assert np.isfinite(doc["constants_m"][k]) and doc["constants_m"][k] > 0
    assert doc["sampled"]["emp_samples"] >= 1500
    assert doc["certifies"] == {f: sha256(models_dir / f) for f in ("student.ckpt", "student.onnx")}  # the weights it holds for
    runs = mlflow.search_runs(experiment_names=["distill"], filter_string="params.model = 'student'")
    names = ("ade_1step_m", "ade_rollout_m", "fde_rollout_m", "jac_rel_err", "params", "forward_us", "cert_s_x",
             "cert_s_y", "cert_theta_x", "cert_theta_y", "cert_L", "cert_rho_bound", "emp_theta_max", "emp_L_max",
             "cert_L_J", "cert_M", "cert_sigma_min_C", "train_rollout_loss", "train_contrast", *(f"cert_{sc}_{k}" for sc in ("two_lane", "three_lane", "random")
                                                           for k in ("L_J", "M", "sigma_min_C", "rho_bound", "ratio_L")))
    assert all(0 < doc["scenarios"][sc]["rho_bound"] <= doc["constants_m"]["rho_bound"] for sc in ("two_lane", "three_lane"))
    assert all(f"metrics.{n}" in runs.columns and np.isfinite(runs[f"metrics.{n}"].iloc[0]) for n in names)
    assert r["jac_rel_err"] < 1.0


def test_certificate_bounds_fresh_autodiff_derivatives(trained, tiny_dataset):
    """The written theta_x, theta_y and L hold on windows the job never saw, by torch autodiff of the saved network."""
    models_dir = trained[0]
    doc = json.loads((models_dir / "certificate.json").read_text())
    c, box = doc["constants_m"], doc["box"]["box"]
    net = models.read_checkpoint(models_dir / "student.ckpt").double()
    rng = np.random.default_rng(12345)
    X = dataset.load(tiny_dataset, "val")["X"].astype(float)
    X = X - X[:, -1:, :1]
    W = torch.tensor(np.concatenate([X, planner_like(X, rng, **doc["box"]["perturb"]), box_windows(300, rng, box)]))

    def others(ego, window):
        """The other cars' next xy (N, 2) as a function of the ego's track (T_obs, 2) in `window`."""
        return net(torch.cat([ego[:, None], window[:, 1:]], 1)[None])[0, 1:]

    G = torch.func.vmap(torch.func.jacrev(others))(W[:, :, 0], W).abs()  # (n, N, 2, T_obs, 2)
    assert G.max() > 1e-3  # the others do react to the ego: the check has teeth
    assert G[:, :, 0].max() <= c["theta_x"] and G[:, :, 1].max() <= c["theta_y"]
    H = torch.func.vmap(torch.func.jacfwd(torch.func.jacrev(others)))(W[::20, :, 0], W[::20])  # (n, N, 2, T_obs, 2, T_obs, 2)
    H = H.reshape(len(H), -1, W.shape[1] * 2, W.shape[1] * 2)
    assert torch.linalg.matrix_norm(H, ord=2).max() <= c["L"]
    # A1: the others' next positions stay within s_x, s_y on box windows
    out = net(torch.tensor(box_windows(500, rng, box)))[:, 1:].detach().abs()
    assert out[..., 0].max() <= c["s_x"] and out[..., 1].max() <= c["s_y"]


@pytest.mark.parametrize("name", ["teacher", "student"])
def test_onnx_matches_torch(trained, tiny_dataset, name):
    models_dir = trained[0]
    X = dataset.load(tiny_dataset, "test")["X"]
    torch_pred, onnx_pred = models.load(name, models_dir), load_onnx(name, models_dir)
    for w in (X[:1], X[:37]):
        assert np.abs(onnx_pred.phi(w) - torch_pred.phi(w)).max() < 1e-4
    nxt, J = torch_pred.phi_jac(X[:3])
    assert nxt.shape == (3, 5, 2) and J.shape == (3, 10, 80)


def test_resume_continues_from_checkpoint(trained, tiny_dataset, tmp_path):
    ckpt = trained[0] / "teacher.ckpt"
    saved_epoch = torch.load(ckpt, map_location="cpu", weights_only=True)["epoch"]
    # one more epoch on a quarter of the data: what is checked is where the epochs resume, not the fit
    job(tiny_dataset, tmp_path, tmp_path / "run", "model=teacher", f"trainer.max_epochs={TINY_TEACHER_EPOCHS + 1}",
        "model.data.fraction=0.25", f"ckpt_path={ckpt}")
    last = mlflow.search_runs(experiment_names=["distill"], order_by=["attributes.start_time DESC"], max_results=1)
    epochs = [m.value for m in mlflow.MlflowClient().get_metric_history(last.run_id.iloc[0], "epoch")]
    assert min(epochs) == saved_epoch + 1  # picks up after the saved epoch, not at 0
    assert (tmp_path / "teacher.ckpt").exists()


def test_corrupt_files_name_themselves(trained, tmp_path):
    models_dir = trained[0]
    (tmp_path / "teacher.ckpt").write_bytes((models_dir / "teacher.ckpt").read_bytes()[:5000])
    with pytest.raises(UserError, match="teacher.ckpt"):
        models.load("teacher", tmp_path)
    (tmp_path / "student.onnx").write_bytes(b"not an onnx file")
    with pytest.raises(UserError, match="student.onnx"):
        load_onnx("student", tmp_path)


def test_missing_model_and_dataset_name_the_command(tiny_dataset, tmp_path):
    with pytest.raises(UserError, match="distill model=student"):
        models.load("student", tmp_path)
    with pytest.raises(UserError, match="distill model=teacher"):
        job(tiny_dataset, tmp_path, tmp_path / "run", "model=student")  # the student needs a teacher
    with pytest.raises(UserError, match="make-dataset"):
        job(tmp_path / "nope", tmp_path, tmp_path / "run", "model=teacher")


@pytest.mark.parametrize("model, weight, groups", [("teacher", "contrast_weight", "contrast_groups"),
                                                   ("student", "rollout_weight", "rollout_groups"),
                                                   ("student", "contrast_weight", "rollout_groups")])
def test_a_branch_term_without_branch_groups_is_one_clear_error(tiny_dataset, tmp_path, model, weight, groups):
    with pytest.raises(UserError, match=rf"model.task.{weight}=1.0 needs model.data.{groups} > 0"):
        job(tiny_dataset, tmp_path, tmp_path / "run", f"model={model}", f"model.task.{weight}=1.0")
    assert not list(tmp_path.glob("*.ckpt"))  # nothing trained or written


@pytest.mark.parametrize("override, shown", [("model.data.hard_weight=0", "0"), ("model.data.hard_braking=-1", "-1"),
                                             ("model.data.whole_weight=-2", "-2")])
def test_a_hard_window_setting_that_is_not_positive_is_one_line_before_any_training(tiny_dataset, tmp_path, override, shown):
    key = override.split("=")[0]
    with pytest.raises(UserError, match=rf"^{key}={shown}: must be a number > 0$"):
        job(tiny_dataset, tmp_path, tmp_path / "run", "model=teacher", override)
    assert not list(tmp_path.glob("*.ckpt"))
