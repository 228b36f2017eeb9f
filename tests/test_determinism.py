"""The same config and seed give bit-identical weights on one machine: teacher, student and surrogate trained twice."""
import onnx
import pytest
import torch
from onnx import numpy_helper

from conftest import compose_cfg

FAST = ["trainer.max_epochs=1", "+trainer.limit_train_batches=3", "+trainer.limit_val_batches=1"]


def distill_twice(tiny_dataset, tmp_path, name, *overrides, teacher_dir=None, runs=2):
    """State dicts of models/<name>.ckpt from `runs` runs of the same config into as many folders, and the first folder."""
    from distill.train import run

    out = []
    for k in range(runs):
        models = tmp_path / f"{name}{k}"
        models.mkdir()
        if teacher_dir is not None:
            (models / "teacher.ckpt").symlink_to(teacher_dir / "teacher.ckpt")
        run(compose_cfg("distill", [f"model={name}", f"dataset_dir={tiny_dataset}", f"models_dir={models}",
                                    f"run_dir={tmp_path / f'run_{name}{k}'}", "trainer.enable_progress_bar=false", *FAST,
                                    *overrides]))
        out.append(torch.load(models / f"{name}.ckpt", map_location="cpu", weights_only=True)["state_dict"])
    return out, tmp_path / f"{name}0"


def assert_identical(a: dict, b: dict):
    assert a.keys() == b.keys() and len(a) > 0
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.fixture(scope="module")
def teachers(tiny_dataset, tmp_path_factory):
    return distill_twice(tiny_dataset, tmp_path_factory.mktemp("det"), "teacher")


def test_teacher_training_is_deterministic(teachers):
    (a, b), _ = teachers
    assert_identical(a, b)


def test_the_comparison_sees_another_seed(teachers, tiny_dataset, tmp_path):
    (a, _), _ = teachers
    (c,), _ = distill_twice(tiny_dataset, tmp_path, "teacher", "seed=1", runs=1)
    assert a.keys() == c.keys() and not all(torch.equal(a[k], c[k]) for k in a)


def test_student_distillation_is_deterministic(teachers, tiny_dataset, tmp_path):
    _, teacher_dir = teachers
    (a, b), _ = distill_twice(tiny_dataset, tmp_path, "student", "model.certificate.samples=300", teacher_dir=teacher_dir)
    assert_identical(a, b)


def test_surrogate_training_is_deterministic(teachers, tiny_dataset, tmp_path):
    from surrogate.cli import run

    _, teacher_dir = teachers
    weights = []
    for k in range(2):
        models = tmp_path / f"s{k}"
        models.mkdir()
        (models / "teacher.ckpt").symlink_to(teacher_dir / "teacher.ckpt")
        run(compose_cfg("surrogate", [f"dataset_dir={tiny_dataset}", f"models_dir={models}", f"out_dir={tmp_path / f'out{k}'}",
                                      "data.dataset_windows=200", "data.plan_states=20", "data.val_dataset_windows=50",
                                      "data.val_plan_states=5", "data.test_plan_states=5", "data.batch_size=64",
                                      "trainer.max_epochs=2", "timing.repeats=1", "timing.budget_s=0.01",
                                      "timing.predictors=[]"]))
        weights.append({i.name: torch.from_numpy(numpy_helper.to_array(i).copy())
                        for i in onnx.load(str(models / "surrogate.onnx")).graph.initializer})
    assert_identical(*weights)
