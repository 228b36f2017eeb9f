"""`results`' job plan (bench/results_plan.py), built without running it: every ceiling after its scenario's planner
batches with their per-step CSVs as starts, and the cooperation sweep's jobs."""
import pytest

from bench.results_plan import build_plan
from conftest import compose_cfg
from core.jobs import UserError


def tiny_plan(tmp_path, *overrides):
    """(labels in order, {label: job config}, batches) of the tiny preset's plan."""
    cfg = compose_cfg("results", ["results_preset=tiny", f"out_dir={tmp_path}", f"work_dir={tmp_path}", *overrides])
    plan, batches = build_plan(cfg, tmp_path)
    return [label for label, _, _ in plan.steps], {label: args[0] for label, _, args in plan.steps}, batches


def test_every_ceiling_runs_after_its_batches_and_replays_each_of_their_runs(tmp_path):
    labels, jobs, batches = tiny_plan(tmp_path)
    keys = {key for key, _, _ in batches}
    assert keys == {"dense", "random", "two_lane", "dense cooperation=stubborn", "dense cooperation=willing"}
    for key in keys:
        folders = {str(f): row for (k, row, _), f in batches.items() if k == key}
        ran = [i for i, label in enumerate(labels) if label.startswith("planner ") and jobs[label].out_dir in folders]
        assert len(ran) == len(folders)
        assert labels.index(f"ceiling {key}") > max(ran)
        # the paper's step runs both methods, an mpc option's row ADMM alone: each writes steps/<method>_<seed>.csv
        expected = {f"{f}/steps/{m}_{{seed}}.csv" for f, row in folders.items()
                    for m in (["admm"] if " " in row else ["admm", "nnmpc"])}
        assert set(jobs[f"ceiling {key}"].starts) == expected and len(jobs[f"ceiling {key}"].starts) == len(expected)
    assert list(jobs["ceiling three_lane"].starts) == list(jobs["ceiling dense_deadline"].starts) == []  # no batches there


def test_the_cooperation_sweep_runs_each_fresh_level_on_the_first_training_and_reuses_the_headline_for_mixed(tmp_path):
    labels, jobs, batches = tiny_plan(tmp_path, "results_preset.training_seeds=[0,1]")
    for level in ("stubborn", "willing"):
        ceiling = jobs[f"ceiling dense cooperation={level}"]
        assert (ceiling.scenario.name, ceiling.scenario.cooperation, ceiling.episodes) == ("dense", level, 1)
        assert ceiling.out_dir.endswith(f"ceiling/dense_{level}")
        runs = {(row, k): jobs[label] for label in labels if label.startswith(f"planner dense cooperation={level} ")
                for (key, row, k), f in batches.items() if key == f"dense cooperation={level}" and str(f) == jobs[label].out_dir}
        assert set(runs) == {("cv", None), ("student", 0), ("cv courteous", None), ("student courteous", 0)}
        assert {(j.scenario.cooperation, j.episodes, j.seed) for j in runs.values()} == {(level, 1, 2000000)}
    assert not any("mixed" in label for label in labels)
    assert {k for (key, _, k) in batches if key == "dense"} == {None, 0, 1}  # the headline: every training
    with pytest.raises(UserError, match=r"results_preset.cooperation_episodes=3: the sweep's mixed level reads the "
                                        r"headline's first worlds, and it has 2"):
        tiny_plan(tmp_path, "results_preset.cooperation_episodes=3")
    with pytest.raises(UserError, match=r"results_preset.cooperation=\['polite'\]: must be"):
        tiny_plan(tmp_path, "results_preset.cooperation=[polite]")


def test_the_oracle_row_drives_the_interactive_step_with_the_world_as_predictor_on_the_headline_s_first_worlds(tmp_path):
    _, jobs, batches = tiny_plan(tmp_path)
    job = jobs["planner dense oracle interactive"]
    assert (job.gradients.name, job.predictor._target_, job.mpc.name, list(job.method)) == (
        "oracle", "planner.gradients.WorldModel", "interactive", ["admm"])
    assert (job.episodes, job.seed) == (1, 2000000)
    assert ("dense", "oracle interactive", None) in batches
    assert str(batches["dense", "oracle interactive", None] / "steps" / "admm_{seed}.csv") in jobs["ceiling dense"].starts
    with pytest.raises(UserError, match=r"results_preset.oracle_episodes=3: the oracle row drives the headline's first "
                                        r"worlds, and it has 2"):
        tiny_plan(tmp_path, "results_preset.oracle_episodes=3")


def test_further_oracle_rows_see_more_cars_and_are_starts_of_the_ceiling(tmp_path):
    _, jobs, batches = tiny_plan(tmp_path)
    wide, plain = jobs["planner dense oracle interactive 8 cars"], jobs["planner dense oracle interactive"]
    assert (wide.n_slots, plain.n_slots, wide.gradients.name, wide.mpc.name) == (8, 4, "oracle", "interactive")
    assert (wide.episodes, wide.seed) == (plain.episodes, plain.seed)
    assert str(batches["dense", "oracle interactive 8 cars", None] / "steps" / "admm_{seed}.csv") in jobs["ceiling dense"].starts
    with pytest.raises(UserError, match=r"results_preset.oracle_n_slots"):
        tiny_plan(tmp_path, "results_preset.oracle_n_slots=[0]")


def test_a_teacher_trained_on_a_fraction_of_the_data_sees_the_first_episodes_windows_alone(tiny_dataset):
    import numpy as np

    from core import validate
    from data import dataset
    from distill.datamodule import SequenceData

    train = dataset.factual(dataset.load(tiny_dataset, "train"))  # a mean model reads the factual runs alone
    episodes = sorted(set(train["episode"].tolist()))
    first = set(episodes[: round(0.5 * len(episodes))])
    assert 0 < len(first) < len(episodes)
    data = SequenceData(tiny_dataset, 16, 8, 0, 3.0, 1.0, 1.0, 0.5)
    data.setup()
    X = data.splits["train"].tensors[0].numpy()
    np.testing.assert_array_equal(X, train["X"][[e in first for e in train["episode"].tolist()]])
    assert len(data.splits["val"]) == len(dataset.factual(dataset.load(tiny_dataset, "val"))["X"])  # validation: every episode
    with pytest.raises(UserError, match=r"^model.data.fraction=0: must be a number in \(0, 1\]$"):
        validate.check(compose_cfg("distill", ["model.data.fraction=0"]), "distill")


VARIANTS = ("results_preset.fidelity_variants=[{name: teacher_half, model: teacher, overrides: ['model.data.fraction=0.5']},"
            "{name: student_narrow, model: student, overrides: ['model=student']}]")


def test_fidelity_rows_reuse_the_headline_s_interactive_batches_and_graded_variants_train_and_plan_in_their_own_folders(tmp_path):
    labels, jobs, batches = tiny_plan(tmp_path, "results_preset.mpc_options=[courteous,interactive]", VARIANTS)
    planned = [label for label in labels if label.startswith("planner dense ")]
    assert len(planned) == len(set(planned))  # `cv interactive` and `student interactive`: the headline's batches alone
    assert {"planner dense cv interactive", "planner dense student interactive seed 0"} <= set(planned)
    teacher = jobs["distill teacher teacher_half seed 0"]
    assert (teacher.model.name, teacher.model.data.fraction, teacher.trainer.max_epochs) == ("teacher", 0.5, 2)  # tiny's too
    assert teacher.models_dir == str(tmp_path / "models" / "variants" / "teacher_half" / "seed0")
    student = jobs["distill student student_narrow seed 0"]
    assert list(student.model.net.hidden) == [64, 64] and student.models_dir.endswith("variants/student_narrow/seed0")
    assert labels.index("copy teacher student_narrow") < labels.index("distill student student_narrow seed 0")
    assert "distill teacher student_narrow seed 0" not in labels and "surrogate student_narrow seed 0" not in labels
    bench = jobs["evaluate-interaction student_narrow"]
    assert list(bench.sources) == ["student"] and bench.models_dir == student.models_dir
    for name, model in (("teacher_half", "teacher"), ("student_narrow", "student")):
        job = jobs[f"planner dense {name} interactive seed 0"]
        assert (job.gradients.name, job.mpc.name, list(job.method), job.episodes) == (model, "interactive", ["admm"], 2)
        assert job.models_dir == jobs[f"distill {model} {name} seed 0"].models_dir
        assert ("dense", f"{name} interactive", 0) in batches
        assert labels.index(f"planner dense {name} interactive seed 0") < labels.index("ceiling dense")


def test_one_verdicts_job_judges_every_training_and_variant_on_held_out_worlds_after_their_models(tmp_path):
    labels, jobs, _ = tiny_plan(tmp_path, "results_preset.training_seeds=[0,1]", VARIANTS)
    job = jobs["verdicts"]
    assert list(job.sources) == ["cv", "student"] and job.models_dir == str(tmp_path / "models" / "seed0")
    assert [dict(v) for v in job.variants] == [
        {"name": "student_seed1", "gradients": "student", "models_dir": str(tmp_path / "models" / "seed1")},
        {"name": "teacher_half", "gradients": "teacher", "models_dir": jobs["distill teacher teacher_half seed 0"].models_dir},
        {"name": "student_narrow", "gradients": "student", "models_dir": jobs["distill student student_narrow seed 0"].models_dir}]
    assert (job.worlds, job.every, job.seed_offset, job.dataset.name) == (1, 2, 2500000, "tiny")
    assert list(job.planner) == ["max_steps=6"]  # the step the fidelity rows plan with
    assert labels.index("verdicts") > max(labels.index(f"distill {m}") for m in (
        "student seed 1", "teacher teacher_half seed 0", "student student_narrow seed 0"))


def test_every_student_is_distilled_further_on_the_interactive_step_s_own_states_before_anything_reads_it(tmp_path):
    labels, jobs, _ = tiny_plan(tmp_path, "results_preset.training_seeds=[0,1]", VARIANTS)
    windows = jobs["candidates"]
    assert labels.index("make-dataset") < labels.index("candidates") < labels.index("distill student on the dataset seed 0")
    assert (windows.worlds, windows.per_state, windows.dataset.name, list(windows.drive)) == (3, 2, "tiny", ["cv"])
    folder, dataset_dir = str(tmp_path / "data" / "candidates"), str(tmp_path / "data" / "tiny")
    for tag, models in (("seed 0", tmp_path / "models" / "seed0"), ("seed 1", tmp_path / "models" / "seed1"),
                        ("student_narrow seed 0", tmp_path / "models" / "variants" / "student_narrow" / "seed0")):
        first, tuned = jobs[f"distill student on the dataset {tag}"], jobs[f"distill student {tag}"]
        assert (first.dataset_dir, first.eval_dir, first.init_from) == (dataset_dir, dataset_dir, None)
        # from the first's weights, on the candidates' windows, scored on the dataset's test split as the first
        assert (tuned.dataset_dir, tuned.eval_dir, tuned.init_from) == (folder, dataset_dir, str(models / "student.ckpt"))
        assert first.models_dir == tuned.models_dir == str(models) and tuned.model.net == first.model.net
        assert labels.index(f"distill student on the dataset {tag}") < labels.index(f"distill student {tag}")
    assert list(jobs["distill student student_narrow seed 0"].model.net.hidden) == [64, 64]  # the variant's own width
    for k in (0, 1):  # the surrogate's recorded states and everything after read the fine-tuned student
        assert labels.index(f"distill student seed {k}") < labels.index(f"iterates seed {k}")
    labels, jobs, _ = tiny_plan(tmp_path, "results_preset.candidates=null")
    assert "candidates" not in labels and not any("on the dataset" in label for label in labels)
    assert (jobs["distill student seed 0"].dataset_dir, jobs["distill student seed 0"].init_from) == (dataset_dir, None)


@pytest.mark.parametrize("override, message", [
    ("results_preset.verdicts_seed=2000000", r"^results_preset.verdicts_seed=2000000: the verdicts' worlds "
                                             r"2000000..2000000 overlap the planner's 2000000..2000003; choose another"),
    ("results_preset.verdicts_seed=1000000", r"^results_preset.verdicts_seed=1000000: the verdicts' worlds "
                                             r"1000000..1000000 overlap the interaction benchmark's 1000000\.\."),
    ("results_preset.candidates=['seed_offset=2000000','reserved=[]']", r"^results_preset.candidates: seed_offset=2000000: "
     r"the candidates' worlds 2000000..2000039 overlap the planner's 2000000..2000003; choose another seed_offset$"),
    ("results_preset.candidates=['seed_offset=2500000','reserved=[]']", r"^results_preset.candidates: seed_offset=2500000: "
     r"the candidates' worlds 2500000..2500039 overlap the verdicts job's"),
    ("results_preset.candidates=['drive=[cv,student]']", r"^results_preset.candidates: drive=\['cv', 'student'\]: student "
     r"needs trained models, and this job runs before any training; drive with sources that need none"),
    ("results_preset.candidates=['per_state=0']", r"^results_preset.candidates: per_state=0: must be an integer >= 1$"),
    ("results_preset.verdicts=['worlds=0']", r"^results_preset.verdicts: worlds=0: must be an integer in \[1, 100000\]$"),
    ("results_preset.fidelity_sources=[oracle]", r"^results_preset.fidelity_sources=\['oracle'\]: must be"),
    ("results_preset.fidelity_sources=[teacher]", r"^results_preset.fidelity_sources: teacher not in "
                                                  r"results_preset.interaction_sources"),
    ("results_preset.fidelity_variants=[{name: cv, model: teacher, overrides: []}]",
     r"^results_preset.fidelity_variants\[0\].name=cv: must be a folder name without spaces that no gradient source"),
    ("results_preset.fidelity_variants=[{name: t5, model: surrogate, overrides: []}]",
     r"^results_preset.fidelity_variants\[0\].model=surrogate: must be one of teacher, student$"),
    ("results_preset.fidelity_variants=[{name: t5, model: teacher}]", r"^results_preset.fidelity_variants\[0\]=.*: must be "),
])
def test_a_bad_fidelity_preset_key_is_one_line_naming_it(tmp_path, override, message):
    with pytest.raises(UserError, match=message) as e:
        tiny_plan(tmp_path, override)
    assert "\n" not in str(e.value)
