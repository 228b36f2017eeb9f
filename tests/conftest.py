"""Shared fixtures: a temporary MLflow store for every test session and a tiny dataset built once."""
import os
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from core.jobs import CONF_DIR

# A certificate's feature region (m, m/s, m/s^2 per step) and its global position box (m) for small random students.
REGION = {"rel_x": [-8.0, 12.0], "rel_y": [-1.0, 5.0], "vel_x": [0.8, 1.2], "vel_y": [-0.05, 0.1],
          "acc_x": [-0.004, 0.004], "acc_y": [-0.002, 0.003]}
BOX = {"x": 60.0, "y": 12.0, "dx": 2.5, "dy": 0.6}


def compose_cfg(config_name: str, overrides=()):
    """A Hydra config composed the way the console scripts compose it."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name, overrides=list(overrides))


@pytest.fixture(scope="session", autouse=True)
def mlflow_store(tmp_path_factory):
    """Every job in the tests logs to a throw-away SQLite store, never the user's mlflow.db."""
    db = tmp_path_factory.mktemp("mlflow") / "mlflow.db"
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{db}"
    os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")
    return os.environ["MLFLOW_TRACKING_URI"]


@pytest.fixture(autouse=True)
def mlflow_current(mlflow_store):
    """Each test starts on the session's store: MLflow keeps the URI a job or an earlier test set beside the environment
    variable that monkeypatch restores, and a test's own search_runs would read that store."""
    import mlflow

    mlflow.set_tracking_uri(os.environ["MLFLOW_TRACKING_URI"])


@pytest.fixture()
def store(tmp_path, monkeypatch):
    """A fresh MLflow store of the test's own (compare reads every run in a store)."""
    import mlflow

    uri = f"sqlite:///{tmp_path / 'compare.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    mlflow.set_tracking_uri(uri)
    return tmp_path


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    """Root folder of a tiny interaction dataset (train/val/test.npz + meta.json), built once per session."""
    from data.cli import run

    out = tmp_path_factory.mktemp("data")
    run(compose_cfg("make_dataset", ["dataset=tiny", f"out_dir={out}", "plot_episodes=0"]))
    return out / "tiny"


@pytest.fixture(scope="session")
def tiny_models(tiny_dataset, tmp_path_factory):
    """A models folder with a tiny teacher and student trained on the tiny dataset, and both jobs' metrics."""
    from distill.train import run

    models_dir = tmp_path_factory.mktemp("models")
    runs = tmp_path_factory.mktemp("runs")

    def job(name, *overrides):
        return run(compose_cfg("distill", [f"dataset_dir={tiny_dataset}", f"models_dir={models_dir}", f"run_dir={runs / name}",
                                           "trainer.enable_progress_bar=false", f"model={name}", *overrides]))

    teacher = job("teacher", f"trainer.max_epochs={TINY_TEACHER_EPOCHS}")
    student = job("student", "trainer.max_epochs=2", "model.certificate.samples=1500", "model.task.rollout_weight=1",
                  "model.task.contrast_weight=1", "model.data.rollout_groups=8")  # the branch-rollout terms too
    return models_dir, teacher, student, runs


TINY_TEACHER_EPOCHS = 4
