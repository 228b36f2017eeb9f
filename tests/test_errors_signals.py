"""Stop signals: SIGTERM or SIGINT at any moment, inside a compiled solver call, a step that catches it, a batch, a
training or a set's swap, ends the job with one line, exit 128 + the signal and its MLflow run KILLED, leaving every set
of files old or new; a store or a set whose job was killed outright is whole again for the next job."""
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from types import SimpleNamespace

import mlflow
import numpy as np
import pytest
from errors_common import BIN, REPO, error_lines, job, python

from conftest import compose_cfg
from core import jobs
from core.jobs import UserError, guarded, mlflow_run, staged

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
    while not ready.exists() and p.poll() is None:
        time.sleep(0.05)
    p.terminate()  # SIGTERM
    out, err = p.communicate()
    assert p.returncode == 128 + 15, err[-2000:]
    assert err.strip().splitlines()[-1] == "error: stopped by SIGTERM"
    assert mlflow.get_run(out.split()[0]).info.status == "KILLED"


def test_sigint_inside_a_job_ends_its_run_killed():
    def body():
        with mlflow_run("reliability", compose_cfg("compare")) as run:
            body.run_id = run.info.run_id
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)

    with pytest.raises(SystemExit) as e:
        guarded(body)()
    assert e.value.code == 130 and mlflow.get_run(body.run_id).info.status == "KILLED"


def test_sigint_in_a_batch_is_one_line_exit_130_and_its_run_killed(tmp_path):
    db = tmp_path / "m.db"
    proc = subprocess.Popen([str(BIN / "planner"), "scenario=random", "gradients=analytic", "method=nnmpc", "episodes=500",
                             "n_jobs=1", "max_steps=8", f"out_dir={tmp_path}"], cwd=tmp_path,
                            env={**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{db}"}, stderr=subprocess.PIPE, text=True)
    status = []
    while not status and proc.poll() is None:  # its run is open before the first episode
        time.sleep(0.2)
        if db.exists():
            with sqlite3.connect(db) as con:
                try:
                    status = con.execute("select status from runs").fetchall()
                except sqlite3.OperationalError:  # tables not there yet
                    pass
    assert status == [("RUNNING",)]
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate()
    assert proc.returncode == 130 and error_lines(err) == ["error: stopped by SIGINT"], err
    with sqlite3.connect(db) as con:
        assert con.execute("select status from runs").fetchall() == [("KILLED",)]


LAUNCHED = """
    import atexit, os, signal, sys, time
    from pathlib import Path
    from bench import launch

    def main():  # a command's main(), as bench.launch calls it
        if sys.argv[1] == "import":  # a stop while the command's modules import: before any job
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(30)
        atexit.register(lambda: os.kill(os.getpid(), signal.SIGINT) or time.sleep(30))  # one more while Python exits
        if sys.argv[1] == "stopped":  # the job was stopped and said so
            print("error: stopped by SIGINT", file=sys.stderr)
            sys.exit(130)

    sys.modules["a_command"] = type(sys)("a_command")
    sys.modules["a_command"].main = main
    launch.run("a_command")
"""


@pytest.mark.parametrize("moment", ["import", "stopped", "finished"])
def test_a_stop_outside_the_job_is_one_line_and_exit_130(moment):
    """While a command imports, after a stopped job (a second Ctrl-C: it was an llvmlite traceback and death by the
    signal) and while a finished one exits (loky's clean-up): one line, exit 130."""
    p = python(LAUNCHED, moment)
    _, err = p.communicate()
    assert p.returncode == 130 and error_lines(err) == ["error: stopped by SIGINT"], err


PARALLEL = """
    import sys
    from joblib import Parallel, delayed
    from bench import launch

    def main():  # a command whose job ran on loky's worker processes (the ceiling's search): they stay up after it
        print(sum(Parallel(n_jobs=2)(delayed(abs)(-k) for k in range(4))))

    sys.modules["a_command"] = type(sys)("a_command")
    sys.modules["a_command"].main = main
    launch.run("a_command")
"""


def test_a_command_whose_job_used_worker_processes_exits_after_it():
    p = python(PARALLEL)
    out, err = p.communicate()  # it hung, or a worker printed a traceback: the exit waited on workers nobody had stopped
    assert p.returncode == 0 and out.strip() == "6" and "Traceback" not in err, err


def test_every_console_script_goes_through_the_launcher():
    scripts = [line.split("=")[0].strip() for line in (REPO / "pyproject.toml").read_text().split("[project.scripts]")[1]
               .split("\n\n")[0].splitlines()[1:]]
    assert len(scripts) == 10 and all("bench.launch" in (BIN / s).read_text() for s in scripts)


def test_a_job_killed_while_creating_the_store_leaves_it_usable(tmp_path):
    db = tmp_path / "new.db"
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{db}"}
    first = subprocess.Popen([str(BIN / "compare"), f"out_dir={tmp_path}"], cwd=tmp_path, env={**os.environ, **env},
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not (db.exists() or any(tmp_path.glob(".new.db.creating-*"))) and first.poll() is None:
        time.sleep(0.02)
    time.sleep(0.5)  # MLflow's migrations take seconds: well inside them
    first.kill()  # SIGKILL: no clean-up of any kind runs
    first.wait()
    second = job(["compare", f"out_dir={tmp_path}"], tmp_path, env)
    assert second.returncode == 2, second.stderr
    assert error_lines(second.stderr) == ["error: no finished planner runs in the MLflow store: run `planner` first"]
    with sqlite3.connect(db) as con:
        assert con.execute("select count(*) from alembic_version").fetchone() == (1,)


@pytest.fixture
def stop_after_first_move(monkeypatch):
    """arm(folder, signum): from then on, the first rename of a file or folder to a path under `folder` sends signum to
    this process right after it: a stop at the worst moment of a swap (between its first and second rename)."""

    def arm(folder, signum):
        fired = []

        def hook(real):
            def rename(src, dst, *args, **kwargs):
                real(src, dst, *args, **kwargs)
                if not fired and str(dst).startswith(str(folder)):
                    fired.append(dst)
                    os.kill(os.getpid(), signum)
            return rename

        monkeypatch.setattr(os, "replace", hook(os.replace))
        monkeypatch.setattr(os, "rename", hook(os.rename))
        return fired

    return arm


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_inside_the_models_swap_leaves_the_whole_new_set(signum, tmp_path, stop_after_first_move):
    models = tmp_path / "models"
    models.mkdir()
    student = ("certificate.json", "student.ckpt", "student.onnx")  # a model, its ONNX and its certificate
    for name in student:
        (models / name).write_text("old")
    (models / "teacher.ckpt").write_text("the teacher")

    def distill():
        with staged(models) as stage:
            for name in student:
                (stage / name).write_text("new")
            fired = stop_after_first_move(models, signum)
        assert fired  # the signal was sent inside the swap

    with pytest.raises(SystemExit) as e:
        guarded(distill)()
    assert e.value.code == 128 + signum
    assert {p.name: p.read_text() for p in models.iterdir()} == {**dict.fromkeys(student, "new"), "teacher.ckpt": "the teacher"}


def test_a_stop_inside_the_dataset_swap_leaves_a_whole_dataset_and_its_other_files(tiny_dataset, tmp_path,
                                                                                   stop_after_first_move, capsys):
    from data import dataset
    from data.cli import run

    shutil.copytree(tiny_dataset, tmp_path / "tiny")
    (tmp_path / "tiny" / "iterates").mkdir()
    (tmp_path / "tiny" / "iterates" / "episode.npz").write_bytes(b"recorded")
    old_meta = (tmp_path / "tiny" / "meta.json").read_text()
    cfg = compose_cfg("make_dataset", ["dataset=tiny", "dataset.episodes=10", "dataset.steps=20", f"out_dir={tmp_path}",
                                       "plot_episodes=0"])
    fired = stop_after_first_move(tmp_path, signal.SIGTERM)
    with pytest.raises(SystemExit) as e:
        run(cfg)
    assert fired and e.value.code == 143 and error_lines(capsys.readouterr().err)[-1] == "error: stopped by SIGTERM"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny"]
    assert sorted(p.name for p in (tmp_path / "tiny").iterdir()) == ["iterates", "meta.json", "test.npz", "train.npz", "val.npz"]
    assert (tmp_path / "tiny" / "meta.json").read_text() != old_meta  # the new set, whole: every split matches it
    assert all(len(dataset.load(tmp_path / "tiny", split)["X"]) for split in dataset.SPLITS)
    assert (tmp_path / "tiny" / "iterates" / "episode.npz").read_bytes() == b"recorded"


KILLED_MID_SWAP = """
    import os, signal, sys
    from pathlib import Path
    from core.jobs import staged

    real = os.replace

    def replace(src, dst):
        real(src, dst)
        os.kill(os.getpid(), signal.SIGKILL)  # killed outright after the set's first file: no clean-up runs

    os.replace = replace
    with staged(Path(sys.argv[1])) as stage:
        for name in ("meta.json", "test.npz", "train.npz", "val.npz"):
            (stage / name).write_text("new")
"""


def test_a_set_whose_job_was_killed_mid_swap_is_completed_by_the_next_reader(tmp_path):
    from data import dataset

    folder = tmp_path / "tiny"
    folder.mkdir()
    names = ("meta.json", "test.npz", "train.npz", "val.npz")
    for name in names:
        (folder / name).write_text("old")
    p = python(KILLED_MID_SWAP, folder)
    p.communicate()
    assert p.returncode == -signal.SIGKILL
    assert {f.name: f.read_text() for f in folder.iterdir() if f.is_file()}["meta.json"] == "new"  # the mix it left
    with pytest.raises(UserError, match="corrupt dataset meta file"):  # the reader moves the rest in first: read as one set
        dataset.read_meta(folder)
    assert {f.name: f.read_text() for f in folder.iterdir()} == dict.fromkeys(names, "new")


def test_a_stop_inside_a_compiled_call_is_raised_once_it_returns(monkeypatch):
    from numba import njit
    from numba.core import serialize
    from numba.typed import List

    @njit
    def compiled():
        out = List()  # boxing it calls back into Python (numba's unpickler), where the signal is handled
        out.append(1.0)
        return out

    compiled()

    class Signalling(dict):
        """numba's memo of unpickled objects, sending SIGINT at its first look-up: a stop inside a compiled call."""

        def __getitem__(self, key):
            if not hasattr(self, "sent"):
                self.sent = True
                os.kill(os.getpid(), signal.SIGINT)
                sum(range(100))  # bytecode, where the handler runs
            return super().__getitem__(key)

    monkeypatch.setattr(serialize, "_unpickled_memo", Signalling(serialize._unpickled_memo))
    results = []

    def planner():
        results.append(type(compiled()).__name__)  # raising inside the call lost the stop (SystemError) or crashed (SIGSEGV)
        time.sleep(5)

    with pytest.raises(SystemExit) as e:
        guarded(planner)()
    assert e.value.code == 130 and results == ["List"]  # the call returned its result, then the job stopped


def test_the_compiled_loops_see_a_stop_signal_until_its_job_ends():
    from planner.zstep import stop_requested

    seen = []
    previous = signal.signal(signal.SIGUSR1, lambda *_: None)  # a signal Python handles that stops nothing

    def stopped():
        try:
            os.kill(os.getpid(), signal.SIGUSR1)
            seen.append(stop_requested(jobs.SIGNALS))
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        finally:
            seen.append(stop_requested(jobs.SIGNALS))

    try:
        with pytest.raises(SystemExit):
            guarded(stopped)()
    finally:
        signal.signal(signal.SIGUSR1, previous)
    assert seen == [False, True] and not guarded(lambda: stop_requested(jobs.SIGNALS))()  # the next job unstopped



def test_a_job_whose_signal_file_number_another_file_took_still_sees_its_stop(tmp_path):
    """Where a blocking log has been dup2'd onto the signal file's number, a job makes its own file instead of refusing
    to start (set_wakeup_fd: "the fd must be in non-blocking mode") or writing signals into the log."""
    from planner.zstep import stop_requested

    seen = []

    def stopped():
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        finally:
            seen.append(stop_requested(jobs.SIGNALS))

    with open(tmp_path / "raylet.out", "w") as log:
        os.dup2(log.fileno(), jobs._SIGNAL_FD)  # blocking, as a log is
        with pytest.raises(SystemExit) as e:
            guarded(stopped)()
    assert e.value.code == 130 and seen == [True] and (tmp_path / "raylet.out").read_bytes() == b""
    assert os.readlink(f"/proc/self/fd/{jobs._SIGNAL_FD}").startswith("/memfd:signals")

MARKED_PLANNER = """
    import sys
    from bench import launch
    from planner import admm

    solve = admm.typed_call

    def marked(kernel, *args):
        kernel.compile(tuple(map(kernel.typeof_pyval, args)))  # compiled or loaded first: the marker means the call is next
        print("solving", flush=True)
        return solve(kernel, *args)

    admm.typed_call = marked
    admm.TOL_F = admm.TOL_STEP = 1e-12  # tolerances no solve reaches: each runs its max_iters
    sys.argv = ["planner", *sys.argv[1:]]
    launch.run("planner.cli")
"""


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_inside_a_long_compiled_solve_ends_the_run_at_once(signum, tmp_path):
    """A stop while one ADMM solve runs as one compiled call (T_p 200 and 2000 iterations that never converge: over ten
    minutes) ends the run within the call: it was handled once the call returned."""
    db, log = tmp_path / "m.db", tmp_path / "stderr"
    args = ["gradients=cv", "scenario=two_lane", "plots=false", "mpc.T_p=200", "mpc.admm.max_iters=2000",
            f"out_dir={tmp_path / 'out'}", f"hydra.run.dir={tmp_path / 'hydra'}"]
    with log.open("w") as stderr:  # a file: numba's warnings while it compiles would fill a pipe nobody reads yet
        p = subprocess.Popen([sys.executable, "-c", textwrap.dedent(MARKED_PLANNER), *args], cwd=REPO, stdout=subprocess.PIPE,
                             stderr=stderr, text=True, env={**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{db}"})
    while (line := p.stdout.readline()) not in ("solving\n", ""):
        pass
    assert line, log.read_text()[-2000:]
    time.sleep(1)  # inside the call
    p.send_signal(signum)
    try:
        p.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        p.kill()
        p.communicate()
        pytest.fail("the stop waited for the compiled call to return")
    err = log.read_text()
    assert p.returncode == 128 + signum and error_lines(err)[-1] == f"error: stopped by {signal.Signals(signum).name}", err
    with sqlite3.connect(db) as con:
        assert con.execute("select status from runs").fetchall() == [("KILLED",)]
    assert not any((tmp_path / "out").iterdir())  # no steps CSV, whole or half


def test_a_step_that_swallows_a_stop_ends_the_episode_after_it():
    from planner import closed_loop, setup

    scenario, source, _ = setup.make("two_lane", ["gradients=cv"])
    steps = []

    def swallowing(obs, warm):
        """A step whose solver catches every exception (as numba's SystemError turned a stop into a fallback)."""
        steps.append(obs)
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        except BaseException:
            pass
        return SimpleNamespace(u=np.zeros(2), plan=None, iters=0, reason="fallback", J=0.0, F_norm=0.0, b_min=0.0, slack=0.0,
                               c_min=0.0, braking=0.0, follower_braking=0.0, fallback="step error", zstop="")

    def drive():
        closed_loop.drive(scenario.make_world(0), swallowing, source, scenario.x_ref, scenario.target_lane, 8, 5,
                          "reactive", 4)

    with pytest.raises(SystemExit) as e:
        guarded(drive)()
    assert e.value.code == 143 and len(steps) == 1


def test_a_stopped_planner_run_ends_killed(tmp_path, monkeypatch, capsys):
    from planner import cli

    def stopped(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)

    monkeypatch.setattr("planner.setup.drive", stopped)
    with pytest.raises(SystemExit) as e:
        cli.run(compose_cfg("planner", ["scenario=two_lane", "gradients=cv", "seed=4600", f"out_dir={tmp_path}"]))
    assert e.value.code == 130 and error_lines(capsys.readouterr().err) == ["error: stopped by SIGINT"]
    runs = mlflow.search_runs(experiment_names=["planner"], filter_string="params.seed = '4600'")
    assert list(runs["status"]) == ["KILLED"]
