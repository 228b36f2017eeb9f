"""`cross-world`: a tiny run trains in both worlds, plans in both, and writes tables whose numbers are the episodes'; bad
settings are one line."""
import csv

import numpy as np
import pytest
from test_results import cell, numbers, rate_cell

from bench import cross_world
from conftest import compose_cfg

pytest.importorskip("highway_env")

TINY = ["dataset=tiny", 'teacher=["trainer.max_epochs=1"]', 'student=["trainer.max_epochs=1","model.certificate.samples=500"]',
        "sources=[cv,student]", "nnmpc=[student]", "episodes.dense=2", "episodes.highway=2", "ceiling_episodes.dense=1",
        "ceiling_episodes.highway=1", 'planner=["max_steps=5"]', "n_jobs=1", "bootstrap.resamples=50",
        'ceiling=["max_steps=5","search.gaps=0","search.y_lean=[1.95]","search.clearance=[0.5]","search.enter=[4]","search.dv=[0.0]"]']


@pytest.mark.slow  # a tiny cross-world run: two datasets, four trainings, both worlds' batches
def test_tiny_run_plans_in_both_worlds_with_models_of_both_and_reports_the_episodes(tmp_path):
    path = cross_world.run(compose_cfg("cross_world", [*TINY, f"out_dir={tmp_path}", f"work_dir={tmp_path / 'work'}"]))
    md = path.read_text()
    for test in ("dense", "highway"):
        title = f"Planning in `{test}`"
        for row, method in (("ceiling", "-"), ("cv", "ADMM"), ("student, trained in dense", "ADMM"),
                            ("student, trained in highway", "ADMM"), ("student, trained in highway", "NNMPC")):
            assert cell(md, title, row, method, 2)  # trainings x worlds
        for m in ("admm", "nnmpc"):
            folder = tmp_path / "work" / "planner" / test / "student-highway"
            with open(next(folder.glob(f"episodes_{m}_*.csv"))) as f:
                eps = [r for r in csv.DictReader(f)]
            assert len(eps) == 2
            got = numbers(cell(md, title, "student, trained in highway", m.upper(), 3))
            assert np.allclose(got[0], rate_cell([float(e["courteous"]) for e in eps])[0], atol=0.05)
    assert md.count("Per-world check on the ceiling's 1 worlds") == 2
    accuracy = md.split("## Prediction accuracy across worlds\n")[1].split("\n## ")[0]
    for test in ("dense", "highway"):
        for row in ("cv", "teacher, trained in dense", "teacher, trained in highway", "student, trained in highway"):
            assert f"| {test} | {row} |" in accuracy


@pytest.mark.parametrize("override, message", [
    ("episodes.highway=0", "episodes.highway=0: every world of `worlds` needs a positive number of worlds"),
    ("models.highway=models", "models.highway=models: give data.highway too, the dataset those models were trained on"),
    ("worlds=[dense,nowhere]", "worlds=['dense', 'nowhere']: must be"),
])
def test_bad_settings_are_one_line(override, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cross_world.run(compose_cfg("cross_world", [override, f"out_dir={tmp_path}", f"work_dir={tmp_path / 'w'}"]))
    err = capsys.readouterr().err
    assert e.value.code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_verdicts_name_the_model_whose_rates_differ_between_its_trainings():
    cfg = compose_cfg("cross_world", ["sources=[cv,student]"])
    row = lambda c, lo, hi: {"courteous": c, "courteous_lo": lo, "courteous_hi": hi, "collision": 0.0, "collision_lo": 0.0,
                             "collision_hi": 0.1}
    rows = {("cv", "admm"): row(0.1, 0.0, 0.2), ("student, trained in highway", "admm"): row(0.6, 0.5, 0.7),
            ("student, trained in dense", "admm"): row(0.2, 0.1, 0.3)}
    lines = cross_world.verdicts(rows, "highway", cfg)
    assert lines == ["- In highway, student (ADMM) trained in dense: 20.0 [10.0, 30.0]% courteous merges, against "
                     "60.0 [50.0, 70.0]% trained in highway; the intervals do not overlap."]
    rows["student, trained in dense", "admm"] = row(0.45, 0.35, 0.55)
    assert "no model's" in cross_world.verdicts(rows, "highway", cfg)[0]
