"""distill init_from: a training that starts from a checkpoint's weights (a fine-tune), or one line why it cannot."""
import pytest
import torch
from hydra.utils import instantiate

from core.jobs import UserError
from data import dataset
from distill import metrics, models
from distill.train import run
from tests.conftest import compose_cfg


def distill(tiny_dataset, tmp_path, *overrides):
    """The distill job's config on the tiny dataset, writing under tmp_path."""
    return compose_cfg("distill", [f"dataset_dir={tiny_dataset}", f"models_dir={tmp_path / 'models'}",
                                   f"run_dir={tmp_path / 'run'}", "trainer.enable_progress_bar=false", *overrides])


def test_a_fine_tune_starts_from_the_checkpoints_weights(tiny_dataset, tiny_models, tmp_path):
    start = tiny_models[0] / "teacher.ckpt"
    run(distill(tiny_dataset, tmp_path, "model=teacher", f"init_from={start}", "trainer.max_epochs=1",
                "model.task.lr=1e-12"))  # no step moves the weights: the result is where the training started
    before, after = (models.read_checkpoint(p).state_dict() for p in (start, tmp_path / "models" / "teacher.ckpt"))
    torch.manual_seed(0)
    fresh = instantiate(compose_cfg("distill").model.net).state_dict()
    assert all(torch.allclose(before[k], after[k], atol=1e-9) for k in before)
    assert not all(torch.allclose(before[k], fresh[k]) for k in before)  # a fresh network would not pass


@pytest.mark.parametrize("overrides, message", [
    (["init_from={tmp}/none.ckpt"], r"init_from=.*none.ckpt: no such checkpoint file"),
    (["init_from={models}/student.ckpt"], r"student.ckpt holds a student network .*, not a teacher"),
    (["init_from={models}/teacher.ckpt", "model.net.hidden=32"],
     r"init_from=.*teacher.ckpt: its network does not fit model.net \(size mismatch for slot: .*\)$"),
    (["init_from={models}/teacher.ckpt", "ckpt_path={models}/teacher.ckpt"], r"init_from=.* and ckpt_path=.*: choose one"),
])
def test_a_checkpoint_that_cannot_start_the_training_is_one_line(tiny_dataset, tiny_models, tmp_path, overrides, message):
    over = [o.format(tmp=tmp_path, models=tiny_models[0]) for o in overrides]
    with pytest.raises(UserError, match=message):
        run(distill(tiny_dataset, tmp_path, "model=teacher", *over))
    assert not (tmp_path / "run").exists() and not (tmp_path / "models").exists()


def test_a_fine_tune_is_scored_on_the_eval_dir_s_test_split(tiny_dataset, tiny_models, tmp_path):
    val = dataset.load(tiny_dataset, "val")
    other = tmp_path / "other"  # a second set whose test split is tiny's val split
    dataset.save(other, {s: val for s in ("train", "val", "test")}, dataset.read_meta(tiny_dataset))
    out = run(distill(tiny_dataset, tmp_path, "model=teacher", f"init_from={tiny_models[0] / 'teacher.ckpt'}",
                      "trainer.max_epochs=1", "model.task.lr=1e-12", f"eval_dir={other}"))
    teacher, t_p = models.load("teacher", tmp_path / "models"), compose_cfg("distill").paper.T_p
    assert out["ade_1step_m"] == pytest.approx(metrics.ade(teacher, val, t_p)["ade_1step_m"], rel=1e-9)
    assert out["ade_1step_m"] != pytest.approx(metrics.ade(teacher, dataset.load(tiny_dataset, "test"), t_p)["ade_1step_m"])
    with pytest.raises(UserError, match=r"^dataset not found: .*none/meta.json is missing"):
        run(distill(tiny_dataset, tmp_path / "bad", "model=teacher", f"eval_dir={tmp_path / 'none'}"))
    assert not (tmp_path / "bad").exists()
