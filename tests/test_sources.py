"""Gradient sources declare what they can do: every conf/gradients/ option builds a source whose class attributes match
what it does (reads the world, a torch rollout, trained models), and the listed sources are the YAML files."""
import copy
import os
import shutil

import numpy as np
import pytest
import torch
from test_surrogate import smooth_student

from bench import interaction, results_plan
from core import validate
from core.jobs import CONF_DIR, UserError, check_groups, sha256
from core.rollout import SLOTS, T_OBS
from planner.gradients import available, predictor_of, reads_models, source_class
from planner.setup import make
from surrogate.export import export
from surrogate.network import Fused, JacobianNet

# what each source does, written out: joint, torch_rollout, needs_world, differentiates, reads trained models, predictor
DECLARED = ("joint", "torch_rollout", "needs_world", "differentiates")
EXPECTED = {
    "analytic": (True, False, False, False, False, "analytic"),
    "cv": (True, False, False, False, False, "cv"),
    "fd": (False, False, False, True, True, "teacher"),
    "oracle": (False, False, True, True, False, "oracle"),
    "student": (True, False, False, False, True, "student"),
    "surrogate": (False, False, False, False, True, "student"),  # the student's values: the fused export's forward
    # pass is the teacher's, so values and J do not come from one call
    "teacher": (False, True, False, True, True, "teacher"),
}


@pytest.fixture(scope="module")
def models_dir(tiny_models, tmp_path_factory):
    """The tiny teacher and student beside a fused random-weight surrogate: every source can be built."""
    out = tmp_path_factory.mktemp("all_models")
    shutil.copytree(tiny_models[0], out, dirs_exist_ok=True)
    torch.manual_seed(0)
    net = JacobianNet(T_OBS, SLOTS, 16, 1, "").eval()
    export(Fused(net, copy.deepcopy(smooth_student())), out / "surrogate.onnx", T_OBS, SLOTS, "teacher",
           sha256(out / "teacher.ckpt"))  # as the job records the teacher it learned
    return out


def test_the_listed_sources_are_the_yaml_files():
    files = sorted(f[:-5] for f in os.listdir(os.path.join(CONF_DIR, "gradients")) if f.endswith(".yaml"))
    hypotheses = ["student_hyp", "teacher_hyp"]  # built over hypothesis models (tests/test_contingency.py)
    assert available() == files == sorted([*EXPECTED, *hypotheses]) and available(hypotheses=True) == hypotheses
    with pytest.raises(UserError, match=f"unknown gradients 'nope'; choose one of {', '.join(files)}$"):
        check_groups(["gradients=nope"])
    assert available(needs_world=False, hypotheses=False) == [f for f in EXPECTED if f != "oracle"] == list(interaction.SOURCES)
    assert available(torch_rollout=True) == ["teacher"]
    assert results_plan.TRAINED == ("fd", "student", "surrogate", "teacher")
    assert validate.TRAINED_PREDICTORS == ("student", "student_hyp", "teacher", "teacher_hyp")
    assert validate.POINT_PREDICTORS == ("student", "teacher")


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_every_option_builds_a_source_that_does_what_it_declares(name, models_dir, tmp_path):
    *flags, trained, predictor = EXPECTED[name]
    src = make("two_lane", [f"gradients={name}", f"models_dir={models_dir}"])[1]
    assert [getattr(src, k) for k in DECLARED] == flags
    assert [getattr(source_class(name), k) for k in DECLARED[1:]] == flags[1:]  # readable without building it
    assert src.name == name and src.predictor.name == predictor == predictor_of(name) and reads_models(name) == trained
    assert src.torch_rollout == hasattr(src, "module")  # what zstep=pygranso's autodiff rollout reads
    history, ego = np.cumsum(np.full((T_OBS, SLOTS, 2), 0.5), 0), np.cumsum(np.full((1, 8, 2), 0.5), 1)
    if src.needs_world:  # outside the closed loop it has no world to read
        with pytest.raises(UserError, match="reads the running world"):
            src.values(history, ego)
    else:
        assert src.values(history, ego).shape == (1, 8, SLOTS, 2)
    empty = tmp_path / "none"
    empty.mkdir()
    if trained:  # without the models it is one clear error
        with pytest.raises(UserError, match="not found"):
            make("two_lane", [f"gradients={name}", f"models_dir={empty}"])
    else:
        make("two_lane", [f"gradients={name}", f"models_dir={empty}"])


def test_the_surrogate_without_a_student_names_the_missing_model_and_the_teacher_alternative(models_dir, tmp_path):
    for f in ("teacher.ckpt", "surrogate.onnx"):
        shutil.copy(models_dir / f, tmp_path / f)
    with pytest.raises(UserError, match=r"student\.ckpt not found: run `distill model=student` \(gradients=surrogate plans "
                                        r"on the student's values; predictor=teacher for the teacher's\)$"):
        make("two_lane", ["gradients=surrogate", f"models_dir={tmp_path}"])
    assert make("two_lane", ["gradients=surrogate", "predictor=teacher", f"models_dir={tmp_path}"])[1].predictor.name == "teacher"
