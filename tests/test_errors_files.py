"""Files: a missing, corrupt, truncated, empty or non-finite input is one line naming it; an output is replaced only by
a whole, sound new one (a failed job, a full disk, an empty dataset keep the old; a folder's other files are kept);
unwritable folders and stores are one line before the work; two jobs may open a new store at once."""
import errno
import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
from errors_common import error_lines, python
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import compose_cfg
from core import jobs
from core.jobs import UserError, guarded, staged
from data import dataset
from planner import cli, setup
from planner.setup import planner_config


def test_unwritable_output_folder_is_one_line_and_writes_nothing(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    before = len(mlflow.search_runs(experiment_names=["planner"]))
    capsys.readouterr()  # MLflow's own set-up lines, if the store is new
    cfg = compose_cfg("planner", ["scenario=two_lane", "gradients=cv", f"out_dir={blocker}/out", "max_steps=2"])
    with pytest.raises(SystemExit) as e:
        cli.run(cfg)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: cannot write to the output folder") and "a_file" in err[0]
    assert [p.name for p in tmp_path.iterdir()] == ["a_file"]
    assert len(mlflow.search_runs(experiment_names=["planner"])) == before  # no run was started


@pytest.mark.parametrize("job,overrides", [
    ("make_dataset", ["dataset=tiny", "out_dir={blocked}"]),
    ("distill", ["model=teacher", "dataset_dir={data}", "models_dir={blocked}", "run_dir={tmp}/run"]),
    ("surrogate", ["dataset_dir={data}", "models_dir={blocked}"]),
])
def test_every_job_refuses_an_unwritable_output_folder_in_one_line(job, overrides, tmp_path, tiny_dataset, capsys):
    from data.cli import run as make_dataset
    from distill.train import run as distill
    from surrogate.cli import run as surrogate

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    fill = dict(blocked=f"{blocker}/out", data=tiny_dataset, tmp=tmp_path)
    cfg = compose_cfg(job, [o.format(**fill) for o in overrides])
    run = {"make_dataset": make_dataset, "distill": guarded(distill), "surrogate": surrogate}[job]  # as the entry points call them
    with pytest.raises(SystemExit) as e:
        run(cfg)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: cannot write to the output folder") and "a_file" in err[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


@pytest.mark.parametrize("uri,why", [("sqlite:////proc/no/such/mlflow.db", "cannot use the MLflow store sqlite:////proc"),
                                     ("http://127.0.0.1:9", "cannot use the MLflow store http://127.0.0.1:9")])
def test_an_unusable_store_is_one_line_before_the_work(uri, why, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setattr(setup, "drive", lambda *a, **k: pytest.fail("drove an episode"))
    previous = mlflow.get_tracking_uri()
    t0 = time.perf_counter()
    with pytest.raises(SystemExit) as e:
        cli.run(compose_cfg("planner", ["gradients=cv", f"out_dir={tmp_path}"]))
    mlflow.set_tracking_uri(previous)  # the tests after this one keep their store
    # not MLflow's own retries (7, backed off to 2 minutes in all); a bound far above a loaded machine's seconds
    assert e.value.code == 2 and time.perf_counter() - t0 < 6 * jobs.STORE_TIMEOUT_S
    (err,) = error_lines(capsys.readouterr().err)
    assert err.startswith(f"error: {why}")
    assert os.environ.get("MLFLOW_HTTP_REQUEST_MAX_RETRIES") is None  # the quick check's settings are its own


def test_an_empty_tracking_uri_is_the_default_store(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "")  # as `export MLFLOW_TRACKING_URI=` leaves it
    monkeypatch.chdir(tmp_path)
    previous = mlflow.get_tracking_uri()
    try:
        assert jobs.open_experiment("empty-uri") == jobs.DEFAULT_TRACKING_URI
    finally:
        mlflow.set_tracking_uri(previous)  # the tests after this one keep their store
    assert (tmp_path / "mlflow.db").stat().st_size > 0


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
        _, err = p.communicate()
        assert p.returncode == 0, err[-2000:]
    client = mlflow.MlflowClient(uri)
    assert len(client.search_runs([client.get_experiment_by_name("race").experiment_id])) == 2


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


@pytest.mark.parametrize("text,why", [
    ("{not json", "is not a readable certificate .JSONDecodeError"),
    ("[1, 2]", "has no `scenarios` object"),
    (json.dumps({"scenarios": {"two_lane": {}}}), "certified rho for two_lane .* is None, not a usable penalty"),
    (json.dumps({"scenarios": {"two_lane": {"rho_bound": "big"}}}), "is big, not a usable penalty"),
    (json.dumps({"scenarios": {"two_lane": {"rho_bound": -5.0}}}), "is -5.0, not a usable penalty"),
    (json.dumps({"scenarios": {"two_lane": [3]}}), "is None, not a usable penalty"),
])
def test_a_corrupt_certificate_is_one_line(text, why, tmp_path):
    (tmp_path / "certificate.json").write_text(text)
    cfg = planner_config("two_lane", ["gradients=cv", "mpc.admm.rho=certified", f"models_dir={tmp_path}"])
    with pytest.raises(UserError, match=rf"^mpc.admm.rho=certified: .*{why}"):
        setup.setup(cfg)


def test_a_certificate_of_another_student_is_one_line_and_a_run_logs_the_rho_it_used(tmp_path, monkeypatch):
    (tmp_path / "student.ckpt").write_bytes(b"the student it certifies")
    doc = {"scenarios": {"two_lane": {"rho_bound": 5.72e7}}, "certifies": {"student.ckpt": jobs.sha256(tmp_path / "student.ckpt")}}
    (tmp_path / "certificate.json").write_text(json.dumps(doc))
    over = ["gradients=cv", "mpc.admm.rho=certified", f"models_dir={tmp_path}", "max_steps=1", "plots=false",
            f"out_dir={tmp_path / 'out'}"]
    monkeypatch.setattr(cli, "drive_each", lambda cfg, scenario, source, s, methods, out_dir, params, accuracy:
                        drive_each.append(params) or ({}, {}))
    drive_each = []
    cli.run(planner_config("two_lane", over))
    assert drive_each[0]["mpc.admm.rho"] == 5.72e7  # the number, not the word: MLflow's param
    (tmp_path / "student.ckpt").write_bytes(b"a student trained since")  # the certificate now belongs to no file here
    with pytest.raises(UserError, match=r"^mpc.admm.rho=certified: .*certificate.json certifies another student.ckpt "
                                        r"\(sha256 [0-9a-f]{8}\) than .*student.ckpt \([0-9a-f]{8}\): a student trained since"):
        setup.setup(planner_config("two_lane", over))
    (tmp_path / "student.ckpt").unlink()
    with pytest.raises(UserError, match=r"certifies .*student.ckpt, which is not there"):
        setup.setup(planner_config("two_lane", over))
    doc.pop("certifies")
    (tmp_path / "certificate.json").write_text(json.dumps(doc))
    with pytest.raises(UserError, match=r"does not record the student it certifies"):
        setup.setup(planner_config("two_lane", over))


def saved_net(folder, model) -> str:
    """<folder>/<model>.ckpt holding a random-weight network of conf/model/<model>.yaml as distill saves one; its sha256."""
    node = compose_cfg("distill", [f"model={model}"]).model.net
    net = instantiate(node)
    torch.save({"hyper_parameters": {"net": OmegaConf.to_container(node, resolve=True)},
                "state_dict": {f"net.{k}": v for k, v in net.state_dict().items()}}, folder / f"{model}.ckpt")
    return jobs.sha256(folder / f"{model}.ckpt")


def test_a_surrogate_for_another_predictor_is_one_line(tmp_path):
    from surrogate.export import export
    from surrogate.network import JacobianNet

    teacher, student = saved_net(tmp_path, "teacher"), saved_net(tmp_path, "student")
    net = JacobianNet(8, 5, 16, 1, "").eval()
    make = lambda *o: setup.setup(planner_config("two_lane", ["gradients=surrogate", f"models_dir={tmp_path}", *o]))
    export(net, tmp_path / "surrogate.onnx", 8, 5, "student", student)  # `surrogate source=student`
    with pytest.raises(UserError, match=r"^predictor=teacher: .*surrogate.onnx learned the student's Jacobians \(surrogate "
                                        r"source=student\), not the teacher's; use predictor=student"):
        make("predictor=teacher")
    make()  # the student's Jacobians with its own values
    export(net, tmp_path / "surrogate.onnx", 8, 5, "teacher", teacher)
    make(), make("predictor=teacher")  # over the student's values (the default pairing) and the teacher's own
    saved_net(tmp_path, "teacher")  # the teacher retrained in place
    with pytest.raises(UserError, match=r"surrogate.onnx learned the Jacobians of another teacher.ckpt \(sha256 [0-9a-f]{8}\) "
                                        r"than .*teacher.ckpt \([0-9a-f]{8}\): the teacher was retrained since"):
        make()
    (tmp_path / "teacher.ckpt").unlink()
    with pytest.raises(UserError, match=r"learned the Jacobians of .*teacher.ckpt, which is not there"):
        make()
    export(net, tmp_path / "surrogate.onnx", 8, 5, "teacher")  # made before surrogates recorded their predictor
    with pytest.raises(UserError, match=r"surrogate.onnx does not record the teacher it learned"):
        make()


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


def make_tiny(out, *overrides):
    """make-dataset of a 10-episode tiny dataset into out/tiny, as the console script runs it."""
    from data.cli import run

    return run(compose_cfg("make_dataset", ["dataset=tiny", "dataset.episodes=10", "dataset.steps=20", f"out_dir={out}",
                                            "plot_episodes=0", *overrides]))


def contents(folder: Path) -> dict:
    """{relative path: bytes} of every file under `folder`."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("override", ["dataset.T_obs=21", "dataset.steps=3"])
def test_a_dataset_without_windows_is_refused_and_the_old_one_kept(override, tiny_dataset, tmp_path, capsys):
    shutil.copytree(tiny_dataset, tmp_path / "tiny")
    before = contents(tmp_path / "tiny")
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        make_tiny(tmp_path, override)
    assert e.value.code == 2
    (err,) = error_lines(capsys.readouterr().err)
    assert err.startswith("error: dataset.T_obs=") and "0 windows" in err and "is left as it was" in err
    assert contents(tmp_path / "tiny") == before


def test_make_dataset_replaces_its_own_files_and_keeps_the_others(tmp_path):
    recorded = tmp_path / "tiny" / "iterates" / "dense_admm_5000000.npz"  # make demo's planner states for the surrogate
    recorded.parent.mkdir(parents=True)
    recorded.write_bytes(b"recorded episode")
    make_tiny(tmp_path)
    assert recorded.read_bytes() == b"recorded episode"
    assert sorted(p.name for p in (tmp_path / "tiny").iterdir()) == ["iterates", "meta.json", "test.npz", "train.npz", "val.npz"]
    assert all(len(dataset.load(tmp_path / "tiny", split)["X"]) for split in dataset.SPLITS)


def test_a_full_disk_is_one_line_and_keeps_the_old_dataset(tiny_dataset, tmp_path, monkeypatch, capsys):
    shutil.copytree(tiny_dataset, tmp_path / "tiny")
    before = contents(tmp_path / "tiny")

    def full(path, **arrays):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(np, "savez_compressed", full)
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        make_tiny(tmp_path)
    assert e.value.code == 2
    (err,) = error_lines(capsys.readouterr().err)
    assert err.startswith(f"error: no space left on the device ({tmp_path / 'tiny'}/.staging-") and "old outputs are kept" in err
    assert contents(tmp_path / "tiny") == before


def test_a_split_without_windows_is_one_line(tiny_dataset, tmp_path):
    from distill.train import check_inputs

    data = shutil.copytree(tiny_dataset, tmp_path / "data")  # as an older make-dataset wrote it
    with np.load(data / "val.npz") as f:
        empty = {k: f[k][:0] for k in f.files}
    np.savez_compressed(data / "val.npz", **empty)
    meta = json.loads((data / "meta.json").read_text())
    meta["splits"]["val"].update(windows=0, sha256=hashlib.sha256((data / "val.npz").read_bytes()).hexdigest())
    (data / "meta.json").write_text(json.dumps(meta))
    cfg = compose_cfg("distill", [f"dataset_dir={data}", f"models_dir={tmp_path / 'models'}", f"run_dir={tmp_path / 'run'}"])
    with pytest.raises(UserError, match=r"val.npz: the val split has 0 windows; rebuild it with make-dataset"):
        check_inputs(cfg)


def test_truncated_npz_files_are_one_line_naming_them(tmp_path):
    from bench import states
    from surrogate.cli import load_iterates

    full = tmp_path / "full.npz"
    np.savez(full, history=np.zeros((3, 8, 5, 2)), ego_future=np.zeros((3, 10, 2)))
    (tmp_path / "iterates").mkdir()
    truncated = tmp_path / "iterates" / "episode.npz"
    truncated.write_bytes(full.read_bytes()[:300])
    with pytest.raises(UserError, match=rf"^{truncated}: not a recorded planner episode \(BadZipFile"):
        load_iterates(tmp_path / "iterates", 8, 5, 10)
    with pytest.raises(UserError, match=rf"^damaged planning states {truncated} \(BadZipFile"):
        states.load(truncated)


def test_a_student_whose_output_is_not_finite_is_refused_at_load(tmp_path):
    from distill import models

    cfg = compose_cfg("distill", ["model=student"])
    net = instantiate(cfg.model.net)
    with torch.no_grad():
        net.layers[0].weight[0, 0] = float("nan")
    torch.save({"hyper_parameters": {"net": OmegaConf.to_container(cfg.model.net, resolve=True)},
                "state_dict": {f"net.{k}": v for k, v in net.state_dict().items()}}, tmp_path / "student.ckpt")
    with pytest.raises(UserError, match=r"student.ckpt is a corrupt model: its output on a probe window is not finite"):
        models.load("student", tmp_path)


def test_a_surrogate_whose_jacobians_are_not_finite_is_refused_at_load(tmp_path):
    from surrogate import models
    from surrogate.export import export

    class Linear(torch.nn.Module):
        """window (B, 8, 5, 2) -> J (B, 10, 80), one weight NaN."""

        def __init__(self):
            super().__init__()
            self.lin = torch.nn.Linear(80, 800)
            with torch.no_grad():
                self.lin.weight[3, 3] = float("nan")

        def forward(self, window):
            return self.lin(window.reshape(len(window), -1)).reshape(-1, 10, 80)

    export(Linear(), tmp_path / "surrogate.onnx", 8, 5, "teacher")
    with pytest.raises(UserError, match=r"surrogate.onnx is a corrupt model: its output on a probe window is not finite"):
        models.load(tmp_path, 8, 4)


def test_evaluate_interaction_stops_on_a_damaged_model_and_skips_a_missing_one(tmp_path):
    from bench import interaction

    (tmp_path / "student.ckpt").write_bytes(b"PK\x03\x04 cut short")
    cfg = compose_cfg("evaluate_interaction", [f"models_dir={tmp_path}"])
    with pytest.raises(UserError, match="corrupt checkpoint .*student.ckpt"):
        interaction.predict("student", [], cfg)
    assert interaction.predict("teacher", [], cfg) is None  # not trained yet: skipped with one log line


def test_a_rejected_distill_creates_no_models_folder(tiny_dataset, tmp_path):
    from distill.train import check_inputs

    (tmp_path / "bad.ckpt").write_bytes(b"not a checkpoint")
    cfg = compose_cfg("distill", [f"dataset_dir={tiny_dataset}", f"models_dir={tmp_path / 'models'}",
                                  f"ckpt_path={tmp_path / 'bad.ckpt'}", f"run_dir={tmp_path / 'run'}"])
    with pytest.raises(UserError, match="corrupt checkpoint"):
        check_inputs(cfg)
    assert [p.name for p in tmp_path.iterdir()] == ["bad.ckpt"]
