"""Bad values and commands are one clear line naming the key, before any work, and write nothing: config values and
ranges (every job, nonsense scenarios), misspelt keys and options, dataset names, model windows, --help."""
import subprocess
import sys

import pytest
from errors_common import BIN, REPO, error_lines, job
from hydra.utils import instantiate

from bench import interaction
from conftest import compose_cfg
from core import jobs, validate
from core.jobs import UserError, guarded, options
from distill.models import StudentPredictor, TorchPredictor
from distill.train import make_trainer
from planner import setup
from planner.setup import check_window, planner_config


@pytest.mark.parametrize("config,override,message", [
    ("planner", "paper.T_p=-3", "paper.T_p=-3: must be an integer in [1, 200]"),
    ("planner", "paper.T_p=0", "paper.T_p=0: must be an integer in [1, 200]"),
    ("planner", "mpc.T_p=0", "mpc.T_p=0: must be an integer in [1, 200]"),
    ("planner", "paper.rho=abc", "paper.rho=abc: must be a number > 0"),
    ("planner", "paper.rho=-5", "paper.rho=-5: must be a number > 0"),
    ("planner", "mpc.admm.rho=0", "mpc.admm.rho=0: must be a number > 0"),
    ("planner", "T_obs=1", "T_obs=1: must be an integer in [2, 21]"),
    ("planner", "seed=-1", "seed=-1: must be an integer in [0, 4294967295]"),
    ("planner", "max_steps=0", "max_steps=0: must be an integer in [1, 10000]"),
    ("planner", "episodes=-2", "episodes=-2: must be an integer in [0, 100000]"),
    ("planner", "n_jobs=0", f"n_jobs=0: must be an integer in [-1, {validate.CORES}], not 0"),
    ("planner", "world=dream", "world=dream: must be one of reactive, predictor"),
    ("planner", "mpc.v_box=[10,0]", "mpc.v_box=[10, 0]: must be [low, high] with low < high"),
    ("planner", "zstep.settings.max_iters=0", "zstep.settings.max_iters=0: must be an integer in [1, 10000]"),
    ("planner", "paper.safety.eps=-1", "paper.safety.eps=-1: must be a number >= 0"),
    ("planner", "plots=maybe", "plots=maybe: must be true or false"),
    # sizes where memory or time would explode: a T_p of 1000 never returned from its first ADMM call
    ("planner", "mpc.T_p=201", "mpc.T_p=201: must be an integer in [1, 200]"),
    ("planner", "paper.T_p=1000", "paper.T_p=1000: must be an integer in [1, 200]"),
    ("planner", "mpc.admm.max_iters=100000", "mpc.admm.max_iters=100000: must be an integer in [1, 10000]"),
    ("planner", "zstep.settings.max_iters=100000", "zstep.settings.max_iters=100000: must be an integer in [1, 10000]"),
    ("planner", "episodes=1000000", "episodes=1000000: must be an integer in [0, 100000]"),
    ("planner", "max_steps=100000", "max_steps=100000: must be an integer in [1, 10000]"),
    ("planner", f"n_jobs={validate.CORES + 1}", f"n_jobs={validate.CORES + 1}: must be an integer in [-1, {validate.CORES}], not 0"),
    ("planner", "n_slots=1000", "n_slots=1000: must be an integer in [1, 50]"),
    ("make_dataset", "dataset.episodes=1000000", "dataset.episodes=1000000: must be an integer in [1, 100000]"),
    ("make_dataset", "dataset.steps=100000", "dataset.steps=100000: must be an integer in [2, 10000]"),
    ("make_dataset", "dataset.T_obs=1000", "dataset.T_obs=1000: must be an integer in [2, 21]"),
    ("make_dataset", "dataset.n_slots=1000", "dataset.n_slots=1000: must be an integer in [1, 50]"),
    ("surrogate", "data.plan_states=10000000", "data.plan_states=10000000: must be an integer in [1, 1000000]"),
    ("surrogate", "states.T_p=1000", "states.T_p=1000: must be an integer in [1, 200]"),
    ("make_dataset", "scenario.followers=10000000", "scenario.followers=10000000: must be an integer in [1, 1000]"),
    ("surrogate", "network.hidden=1000000", "network.hidden=1000000: must be an integer in [1, 4096]"),
    ("surrogate", "network.depth=1000", "network.depth=1000: must be an integer in [1, 16]"),
    ("distill", "model.net.hidden=1000000", "model.net.hidden=1000000: must be an integer in [1, 4096] or a list of at least 1 "
                                            "and at most 16, each an integer in [1, 4096]"),
    ("distill", f"model.net.decoder={[64] * 17}", "model.net.decoder=[64, 64,"),
    ("make_dataset", "dataset.episodes=abc", "dataset.episodes=abc: must be an integer in [1, 100000]"),
    ("make_dataset", "dataset.split=[0.5,0.5,0.1]", "dataset.split=[0.5, 0.5, 0.1]: must be 3 fractions in (0, 1) summing to 1"),
    ("make_dataset", "dataset.policy.p_reckless=1.5", "dataset.policy.p_reckless=1.5: must be a number in [0, 1]"),
    ("distill", "trainer.max_epochs=abc", "trainer.max_epochs=abc: must be an integer >= 1"),
    ("distill", "model.task.lr=nan", "model.task.lr=nan: must be a number > 0"),
    ("distill", "eval_split=dev", "eval_split=dev: must be one of train, val, test"),
    ("surrogate", "source=cv", "source=cv: must be one of student, teacher"),
    ("surrogate", "data.batch_size=0", "data.batch_size=0: must be an integer in [1, 1000000]"),
    ("bench", "threads=0", "threads=0: must be an integer >= 1"),
    ("bench", "step_time.repeats=0", "step_time.repeats=0: must be an integer >= 1"),
    ("bench", "step_time.profile=[nonexistent]", "step_time.profile=['nonexistent']: must be a list, each one of"),
])
def test_bad_config_values_are_one_line_naming_key_value_and_range(config, override, message):
    cfg = compose_cfg(config, [override, *(["gradients=cv"] if config == "planner" else [])])
    with pytest.raises(UserError) as e:
        validate.check(cfg, config)
        if config == "planner":
            setup.setup(cfg)  # the mpc values its settings dataclasses check on their fields
    assert str(e.value).startswith(message)


@pytest.mark.parametrize("job,override,message", [
    ("make_dataset", "dataset.episodes=abc", "error: dataset.episodes=abc: must be an integer in [1, 100000]"),
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


@pytest.mark.parametrize("config,override,message", [
    ("distill", "modle.epochs=3", "unknown key 'modle.epochs'; did you mean model.epochs?"),
    ("make_dataset", "dataset.nme=x", "unknown key 'dataset.nme'; did you mean dataset.name?"),
    ("results", "bootstrap.resample=3", "unknown key 'bootstrap.resample'; did you mean bootstrap.resamples?"),
    ("planner", "gradient=cv", "unknown key 'gradient'; did you mean gradients?"),
    ("planner", "zzz.qqq=1", "unknown key 'zzz.qqq' (`planner --help` lists them)"),
    ("distill", "model=studnet", "unknown model 'studnet'; did you mean model=student? (choose one of student, "
                                 "student_certifiable, student_hyp, student_wide, teacher, teacher_hyp)"),
])
def test_a_misspelt_key_or_option_is_one_line(config, override, message):
    with pytest.raises(UserError) as e:
        jobs.check_overrides(config, [override])
    assert str(e.value) == message
    jobs.check_overrides("distill", ["--help", "modle.epochs=3"])  # with Hydra's own flags the keys are left to Hydra


def test_a_rejected_command_writes_nothing(tmp_path):
    for args in (["distill", "modle.epochs=3"], ["evaluate-interaction", "sources=[]"]):  # before Hydra, inside its job
        r = job(args, tmp_path)
        assert r.returncode == 2 and len(error_lines(r.stderr)) == 1, r.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", [".", "..", "../../etc", "a/b", ""])
def test_a_dataset_name_that_is_not_one_folder_is_refused_and_nothing_is_removed(name, tmp_path, capsys):
    from data.cli import run

    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(SystemExit) as e:
        run(compose_cfg("make_dataset", [f"out_dir={tmp_path}", f"dataset.name='{name}'", "dataset=tiny", "plot_episodes=0"]))
    assert e.value.code == 2
    assert capsys.readouterr().err.startswith(f"error: dataset.name={name}: must be")
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
    with pytest.raises(UserError, match="^dataset.name=.*single folder name"):
        validate.check(compose_cfg("distill", [f"dataset.name='{name}'"]), "distill")


def test_a_window_the_model_cannot_take_is_refused_before_planning():
    net = instantiate(compose_cfg("distill", ["model=student"]).model.net)
    student = StudentPredictor(net)
    assert student.window == (8, 5)  # from its feature map P (78 x 80) and its head
    for over in ("T_obs=3", "T_obs=9", "n_slots=3"):
        with pytest.raises(UserError, match=r"^T_obs=\d+, n_slots=\d: the student model takes windows of T_obs=8 and n_slots=4"):
            check_window(planner_config("two_lane", [over]), student)
    check_window(planner_config("two_lane"), student)  # the default fits
    teacher = instantiate(compose_cfg("distill", ["model=teacher"]).model.net)
    check_window(planner_config("two_lane", ["T_obs=5"]), TorchPredictor("teacher", teacher))  # a GRU reads any T_obs
    with pytest.raises(UserError, match="teacher model takes windows of any T_obs and n_slots=4"):
        check_window(planner_config("two_lane", ["n_slots=5"]), TorchPredictor("teacher", teacher))


@pytest.mark.slow
def test_a_teacher_trains_and_exports_at_its_datasets_window(tmp_path):
    from data.cli import run as make_dataset
    from distill.export import load_onnx
    from distill.train import run as distill

    make_dataset(compose_cfg("make_dataset", ["dataset=tiny", "dataset.n_slots=3", "dataset.T_obs=6", f"out_dir={tmp_path}",
                                              "plot_episodes=0"]))
    distill(compose_cfg("distill", ["model=teacher", f"dataset_dir={tmp_path / 'tiny'}", f"models_dir={tmp_path / 'models'}",
                                    f"run_dir={tmp_path / 'run'}", "trainer.max_epochs=1", "trainer.enable_progress_bar=false"]))
    assert load_onnx("teacher", tmp_path / "models").session.get_inputs()[0].shape[1:] == [6, 4, 2]  # not 8 steps of 5 cars


def test_interaction_values_are_checked():  # the bench's values: as the table of bad config values above
    with pytest.raises(UserError) as e:
        validate.check(compose_cfg("evaluate_interaction", ["sources=[]"]), interaction.SCHEMA)
    assert str(e.value).startswith("sources=[]: must be a list of at least 1")


def test_a_redirected_trainer_draws_no_progress_bar(monkeypatch):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    assert make_trainer(compose_cfg("distill").trainer, logger=False).progress_bar_callback is None
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    monkeypatch.delenv("CI", raising=False)
    assert make_trainer(compose_cfg("distill").trainer, logger=False).progress_bar_callback is not None


NO_GROUPS = ["none: every setting is a key below"]


@pytest.mark.parametrize("command,groups,foreign", [
    ("make-dataset", ["dataset: interactive | large | small | tiny  (now small)", f"scenario: {' | '.join(options('scenario'))}  (now dense)"],
     ["model:", "trainer:"]),
    ("distill", ["model: student | student_certifiable | student_hyp | student_wide | teacher | teacher_hyp  (now teacher)", "trainer: ddp | default | long  (now default)"], ["scenario:"]),
    ("surrogate", ["paper: table1  (now table1)"], ["dataset:", "model:", "scenario:", "trainer:"]),
    ("compare", [f"scenario: {' | '.join(options('scenario'))}  (now none)"], ["dataset:", "gradients:", "model:", "paper:",
                                                                              "trainer:"]),
    ("python -m bench.step_time", NO_GROUPS, ["dataset:", "gradients:", "model:", "paper:", "scenario:", "trainer:"]),
])
def test_help_names_the_command_and_only_its_groups(command, groups, foreign):
    argv = [sys.executable, *command.split()[1:]] if command.startswith("python ") else [BIN / command]
    out = subprocess.run([*argv, "--help"], capture_output=True, text=True, cwd=REPO).stdout
    assert out.startswith(f"{command}: ") and "Hydra" not in out.splitlines()[0] and "powered by Hydra" not in out
    section = out.split("== Config groups (group=option) ==\n")[1].split("\n\n")[0].splitlines()
    assert all(g in section for g in groups)
    assert not any(line.startswith(f) for line in section for f in foreign)


@pytest.mark.parametrize("overrides,message", [
    (["scenario.road.lanes=1"], "scenario.road.lanes=1: must be an integer >= 2"),
    (["scenario.road.lanes=0"], "scenario.road.lanes=0: must be an integer >= 2"),
    (["scenario.road.lane_width=0"], "scenario.road.lane_width=0: must be a number > 0"),
    (["scenario=dense", "scenario.lanes_choices=[1]"], "scenario.lanes_choices=[1]: must be a list of at least 1, each an integer >= 2"),
    (["scenario.v_ref=nan"], "scenario.v_ref=nan: must be a number >= 0"),
    (["scenario.ego.v=nan"], "scenario.ego.v=nan: must be a number >= 0"),
    (["scenario.ego.y=-50"], "scenario.ego.y=-50: the ego must start on the road, y in [-2, 6] m (2 lanes of 4 m)"),
    (["scenario.params.dt=0"], "scenario.params.dt=0: must be a number > 0"),
    (["scenario.params.dt=nan"], "scenario.params.dt=nan: must be a number > 0"),
    (["scenario=dense", "scenario.speed_range=[5,1]"], "scenario.speed_range=[5, 1]: must be [low, high] with low <= high"),
    (["scenario.drivers=[]"], "scenario.drivers=[]: scenario=two_lane needs at least one driver to merge among"),
    # an episode that would end before its first step (it was logged FINISHED with NaN metrics)
    (["scenario.x_ref=-5"], "scenario.x_ref=-5: the ego's lane must end ahead of its start (scenario.ego.x = 9.2 m)"),
    (["scenario.ego.x=100"], "scenario.x_ref=45: the ego's lane must end ahead of its start (scenario.ego.x = 100 m)"),
    (["scenario=dense", "scenario.x_ref=9"], "scenario.x_ref=9: the ego's lane must end ahead of its start (scenario.ego.x = 9.2 m)"),
    (["scenario=random", "scenario.x_ref=25"], "scenario.x_ref=25: the ego's lane must end ahead of its start "
                                               "(scenario.platoon_x + scenario.ego_offset_range[1] = 26 m)"),
])
@pytest.mark.parametrize("config", ["planner", "make_dataset"])
def test_nonsense_scenarios_are_one_line(config, overrides, message):
    with pytest.raises(UserError) as e:
        validate.check(compose_cfg(config, ["scenario=two_lane", *overrides]), config)
    assert str(e.value).startswith(message)
