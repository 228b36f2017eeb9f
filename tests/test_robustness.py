"""A new user's defects: configs checked at start in one line, inputs checked before any output is written, a failed
job leaves the old outputs, two jobs may open a new MLflow store at once, SIGTERM stops a job non-zero and KILLED,
--help names its own command and groups."""
import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import mlflow
import pytest
import torch

from conftest import compose_cfg
from core import validate
from core.jobs import UserError, guarded, staged

VENV_BIN = Path(sys.executable).parent
REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("config,override,message", [
    ("planner", "paper.T_p=-3", "paper.T_p=-3: must be an integer >= 1"),
    ("planner", "paper.T_p=0", "paper.T_p=0: must be an integer >= 1"),
    ("planner", "mpc.T_p=0", "mpc.T_p=0: must be an integer >= 1"),
    ("planner", "paper.rho=abc", "paper.rho=abc: must be a number > 0"),
    ("planner", "paper.rho=-5", "paper.rho=-5: must be a number > 0"),
    ("planner", "mpc.rho=0", "mpc.rho=0: must be a number > 0"),
    ("planner", "T_obs=1", "T_obs=1: must be an integer in [2, 21]"),
    ("planner", "seed=-1", "seed=-1: must be an integer in [0, 4294967295]"),
    ("planner", "max_steps=0", "max_steps=0: must be an integer >= 1"),
    ("planner", "episodes=-2", "episodes=-2: must be an integer >= 0"),
    ("planner", "n_jobs=0", "n_jobs=0: must be an integer >= -1, not 0"),
    ("planner", "world=dream", "world=dream: must be one of reactive, predictor"),
    ("planner", "mpc.v_box=[10,0]", "mpc.v_box=[10, 0]: must be [low, high] with low < high"),
    ("planner", "zstep.settings.max_iters=0", "zstep.settings.max_iters=0: must be an integer >= 1"),
    ("planner", "paper.safety.eps=-1", "paper.safety.eps=-1: must be a number >= 0"),
    ("planner", "plots=maybe", "plots=maybe: must be true or false"),
    ("make_dataset", "dataset.episodes=abc", "dataset.episodes=abc: must be an integer >= 1"),
    ("make_dataset", "dataset.split=[0.5,0.5,0.1]", "dataset.split=[0.5, 0.5, 0.1]: must be 3 fractions in (0, 1) summing to 1"),
    ("make_dataset", "dataset.policy.p_reckless=1.5", "dataset.policy.p_reckless=1.5: must be a number in [0, 1]"),
    ("distill", "trainer.max_epochs=abc", "trainer.max_epochs=abc: must be an integer >= 1"),
    ("distill", "model.task.lr=nan", "model.task.lr=nan: must be a number > 0"),
    ("distill", "eval_split=dev", "eval_split=dev: must be one of train, val, test"),
    ("surrogate", "source=cv", "source=cv: must be one of student, teacher"),
    ("surrogate", "data.batch_size=0", "data.batch_size=0: must be an integer >= 1"),
    ("bench", "threads=0", "threads=0: must be an integer >= 1"),
    ("bench", "step_time.repeats=0", "step_time.repeats=0: must be an integer >= 1"),
    ("bench", "step_time.profile=[nonexistent]", "step_time.profile=['nonexistent']: must be a list, each one of"),
])
def test_bad_config_values_are_one_line_naming_key_value_and_range(config, override, message):
    with pytest.raises(UserError) as e:
        validate.check(compose_cfg(config, [override]), config)
    assert str(e.value).startswith(message)


@pytest.mark.parametrize("config,overrides", [
    ("make_dataset", []), ("make_dataset", ["dataset=large", "scenario=two_lane"]), ("distill", []),
    ("distill", ["model=student", "trainer=long"]), ("distill", ["trainer=ddp"]), ("surrogate", []),
    ("planner", []), ("planner", ["scenario=random", "zstep=pygranso", "method=both", "episodes=4"]),
])
def test_shipped_configs_pass_their_schema(config, overrides):
    validate.check(compose_cfg(config, overrides), config)


@pytest.mark.parametrize("job,override,message", [
    ("make_dataset", "dataset.episodes=abc", "error: dataset.episodes=abc: must be an integer >= 1"),
    ("distill", "trainer.max_epochs=abc", "error: trainer.max_epochs=abc: must be an integer >= 1"),
    ("surrogate", "seed=-1", "error: seed=-1: must be an integer in [0, 4294967295]"),
])
def test_every_job_checks_its_config_first(job, override, message, tmp_path, tiny_dataset, capsys):
    from data.cli import run as make_dataset
    from distill.train import run as distill
    from surrogate.cli import run as surrogate

    overrides = {"make_dataset": [f"out_dir={tmp_path}"], "surrogate": [f"dataset_dir={tiny_dataset}", f"models_dir={tmp_path}"],
                 "distill": [f"dataset_dir={tiny_dataset}", f"models_dir={tmp_path}", f"run_dir={tmp_path}/run"]}[job]
    run = {"make_dataset": make_dataset, "distill": guarded(distill), "surrogate": surrogate}[job]  # as the entry points call them
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        run(compose_cfg(job, [*overrides, override]))
    assert e.value.code == 2
    assert capsys.readouterr().err.strip().splitlines() == [message]
    assert list(tmp_path.iterdir()) == []


def fake_checkpoint(path, target):
    """A checkpoint file whose network is `target` (read_checkpoint checks the class before building anything)."""
    torch.save({"hyper_parameters": {"net": {"_target_": target}}, "state_dict": {}}, path)
    return path


def test_a_checkpoint_of_the_other_model_is_one_line(tiny_dataset, tmp_path):
    from distill import models
    from distill.train import run as distill

    fake_checkpoint(tmp_path / "student.ckpt", "distill.teacher.SocialTeacher")  # a teacher saved as student.ckpt
    with pytest.raises(UserError, match=r"student.ckpt holds a teacher network \(distill.teacher.SocialTeacher\), not a student"):
        models.load("student", tmp_path)
    fake_checkpoint(tmp_path / "s.ckpt", "distill.student.GeluStudent")
    cfg = compose_cfg("distill", ["model=teacher", f"ckpt_path={tmp_path / 's.ckpt'}", f"dataset_dir={tiny_dataset}",
                                  f"models_dir={tmp_path / 'models'}", f"run_dir={tmp_path / 'run'}"])
    with pytest.raises(UserError, match=r"s.ckpt holds a student network .*, not a teacher"):
        distill(cfg)
    assert not (tmp_path / "run").exists()


@pytest.fixture
def corrupt_test_split(tiny_dataset, tmp_path):
    """A copy of the tiny dataset whose test split no longer matches meta.json's checksum."""
    data = shutil.copytree(tiny_dataset, tmp_path / "data")
    meta = json.loads((data / "meta.json").read_text())
    meta["splits"]["test"]["sha256"] = "0" * 64
    (data / "meta.json").write_text(json.dumps(meta))
    return data


@pytest.mark.parametrize("job", ["distill", "surrogate"])
def test_a_corrupt_test_split_stops_the_job_before_it_writes_anything(job, corrupt_test_split, tmp_path, capsys):
    from distill.train import run as distill
    from surrogate.cli import run as surrogate

    models = tmp_path / "models"
    models.mkdir()
    for name in ("teacher.ckpt", "teacher.onnx", "surrogate.onnx"):
        (models / name).write_text("the good model")
    before = len(mlflow.search_runs(search_all_experiments=True))
    cfg = compose_cfg(job, [f"dataset_dir={corrupt_test_split}", f"models_dir={models}", "trainer.max_epochs=1"]
                      + ([f"run_dir={tmp_path / 'run'}"] if job == "distill" else []))
    with pytest.raises(SystemExit) as e:
        {"distill": guarded(distill), "surrogate": surrogate}[job](cfg)
    assert e.value.code == 2
    assert "test.npz does not match its meta.json checksum" in capsys.readouterr().err
    assert {p.name: p.read_text() for p in models.iterdir()} == dict.fromkeys(("teacher.ckpt", "teacher.onnx", "surrogate.onnx"),
                                                                              "the good model")
    assert len(mlflow.search_runs(search_all_experiments=True)) == before  # stopped before any run or training


def test_a_job_failing_after_training_leaves_the_old_models(tiny_dataset, tmp_path, monkeypatch):
    import distill.train

    models = tmp_path / "models"
    models.mkdir()
    for name in ("teacher.ckpt", "teacher.onnx"):
        (models / name).write_text("the good model")
    monkeypatch.setattr(distill.train, "ONNX_TOL_M", -1.0)  # the export check fails after training and exporting
    cfg = compose_cfg("distill", [f"dataset_dir={tiny_dataset}", f"models_dir={models}", f"run_dir={tmp_path / 'run'}",
                                  "trainer.max_epochs=1", "+trainer.limit_train_batches=2", "trainer.enable_progress_bar=false"])
    with pytest.raises(UserError, match="teacher.onnx disagrees with torch"):
        distill.train.run(cfg)
    assert {p.name: p.read_text() for p in models.iterdir()} == dict.fromkeys(("teacher.ckpt", "teacher.onnx"), "the good model")


def test_make_dataset_failing_after_the_build_leaves_the_old_dataset(tmp_path, monkeypatch):
    import data.cli

    def broken_plot(*args, **kwargs):
        raise OSError("disk full")

    old = tmp_path / "tiny"
    old.mkdir()
    (old / "meta.json").write_text("the good dataset")
    monkeypatch.setattr(data.cli, "plot_episode", broken_plot)
    with pytest.raises(OSError, match="disk full"):
        data.cli.run(compose_cfg("make_dataset", ["dataset=tiny", "dataset.episodes=10", f"out_dir={tmp_path}", "plot_episodes=1"]))
    assert [p.name for p in tmp_path.iterdir()] == ["tiny"] and [p.name for p in old.iterdir()] == ["meta.json"]
    assert (old / "meta.json").read_text() == "the good dataset"


def test_staged_outputs_replace_only_on_success(tmp_path):
    (tmp_path / "a.onnx").write_text("old")
    with pytest.raises(RuntimeError):
        with staged(tmp_path) as stage:
            (stage / "a.onnx").write_text("half")
            raise RuntimeError
    assert [p.name for p in tmp_path.iterdir()] == ["a.onnx"] and (tmp_path / "a.onnx").read_text() == "old"
    with staged(tmp_path) as stage:
        (stage / "a.onnx").write_text("new")
        (stage / "b.json").write_text("{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.onnx", "b.json"] and (tmp_path / "a.onnx").read_text() == "new"


def python(code: str, **env):
    """A Python process running `code` in the repository, with `env` added to the environment."""
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, env={**os.environ, **env},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_two_jobs_opening_a_new_store_at_once(tmp_path):
    uri = f"sqlite:///{tmp_path / 'new.db'}"
    go = tmp_path / "go"
    code = f"""
        import sys, time
        from pathlib import Path
        import mlflow
        from omegaconf import OmegaConf
        from core.jobs import mlflow_run
        while not Path({str(go)!r}).exists():
            time.sleep(0.01)
        with mlflow_run("race", OmegaConf.create({{"job": sys.argv[-1]}})):
            pass
    """
    jobs = [python(code, MLFLOW_TRACKING_URI=uri) for _ in range(2)]
    time.sleep(4)  # both have imported mlflow and wait for the start
    go.touch()
    for p in jobs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err[-2000:]
    client = mlflow.MlflowClient(uri)
    assert len(client.search_runs([client.get_experiment_by_name("race").experiment_id])) == 2


SLOW_JOB = """
    import sys, time
    from pathlib import Path
    from omegaconf import OmegaConf
    from core.jobs import guarded, mlflow_run

    ready = Path(sys.argv[-1])

    def plain():
        with mlflow_run("stop", OmegaConf.create({"kind": "plain"})) as run:
            print(run.info.run_id, flush=True)
            ready.touch()
            time.sleep(120)

    def lightning():
        import lightning as L
        import torch
        from torch.utils.data import DataLoader, TensorDataset

        class Slow(L.LightningModule):
            def __init__(self):
                super().__init__()
                self.w = torch.nn.Linear(1, 1)

            def training_step(self, batch, i):
                ready.touch()
                time.sleep(0.5)
                return self.w(batch[0]).sum()

            def configure_optimizers(self):
                return torch.optim.SGD(self.parameters(), lr=0.1)

        with mlflow_run("stop", OmegaConf.create({"kind": "lightning"})) as run:
            print(run.info.run_id, flush=True)
            trainer = L.Trainer(max_epochs=100, logger=False, enable_checkpointing=False, enable_progress_bar=False)
            trainer.fit(Slow(), DataLoader(TensorDataset(torch.zeros(8, 1)), batch_size=1))

    guarded({kind})()
"""


@pytest.mark.parametrize("kind", ["plain", "lightning"])
def test_sigterm_stops_a_job_non_zero_and_marks_its_run_killed(kind, tmp_path, mlflow_store):
    ready = tmp_path / "ready"
    p = subprocess.Popen([sys.executable, "-c", textwrap.dedent(SLOW_JOB.replace("{kind}", kind)), str(ready)], cwd=REPO,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not ready.exists() and p.poll() is None and time.time() < deadline:
        time.sleep(0.05)
    p.terminate()  # SIGTERM
    out, err = p.communicate(timeout=60)
    assert p.returncode == 128 + 15, err[-2000:]
    assert err.strip().splitlines()[-1] == "error: stopped by SIGTERM"
    assert mlflow.get_run(out.split()[0]).info.status == "KILLED"


NO_GROUPS = ["none: every setting is a key below"]


@pytest.mark.parametrize("command,groups,foreign", [
    ("make-dataset", ["dataset: large | small | tiny  (now small)", "scenario: dense | dense_three_lane | highway | highway_three_lane | random | three_lane | two_lane  (now dense)"],
     ["model:", "trainer:"]),
    ("distill", ["model: student | student_certifiable | student_wide | teacher  (now teacher)", "trainer: ddp | default | long  (now default)"], ["scenario:"]),
    ("surrogate", ["paper: table1  (now table1)"], ["dataset:", "model:", "scenario:", "trainer:"]),
    ("compare", NO_GROUPS, ["dataset:", "gradients:", "model:", "paper:", "scenario:", "trainer:"]),
    ("python -m bench.step_time", NO_GROUPS, ["dataset:", "gradients:", "model:", "paper:", "scenario:", "trainer:"]),
])
def test_help_names_the_command_and_only_its_groups(command, groups, foreign):
    argv = [sys.executable, *command.split()[1:]] if command.startswith("python ") else [VENV_BIN / command]
    out = subprocess.run([*argv, "--help"], capture_output=True, text=True, timeout=120, cwd=REPO).stdout
    assert out.startswith(f"{command}: ") and "Hydra" not in out.splitlines()[0] and "powered by Hydra" not in out
    section = out.split("== Config groups (group=option) ==\n")[1].split("\n\n")[0].splitlines()
    assert all(g in section for g in groups)
    assert not any(line.startswith(f) for line in section for f in foreign)
