"""`safety` (bench/safety.py): the table counts what each planner batch's per-episode CSV holds, the stubborn worlds are
their own seeds with nobody yielding, and a bad size, row or a missing model is one line before any batch runs."""
import csv

import mlflow
import numpy as np
import pandas as pd
import pytest
from scipy import stats

from bench import safety
from conftest import compose_cfg

TINY = ["rows=[rules,interactive_cv]", "worlds=2", "stubborn_worlds=1", "planner=['max_steps=4']", "n_jobs=1"]


def wilson_by_roots(k, n, z=stats.norm.ppf(0.975)):
    """The Wilson interval as the two rates p the score test does not reject: roots of (k/n - p)^2 = z^2 p (1 - p) / n."""
    return sorted(np.roots([1 + z * z / n, -(2 * k / n + z * z / n), (k / n) ** 2]).real)


def test_the_table_counts_what_each_batch_csv_holds(tmp_path):
    results = safety.run(compose_cfg("safety", [*TINY, f"out_dir={tmp_path}"]))
    assert list(results) == ["rules", "rules_stubborn", "interactive_cv", "interactive_cv_stubborn"]
    lines = (tmp_path / "safety.md").read_text().splitlines()
    for name, r in results.items():
        with open(next((tmp_path / name).glob("episodes_admm_*.csv"))) as f:
            rows = list(csv.DictReader(f))
        done = [e for e in rows if e["crash"] == "0"]
        hits = sum(float(e["collision"]) for e in done)
        first = 41_000_000 if name.endswith("_stubborn") else 40_000_000
        assert [int(e["seed"]) for e in rows] == list(range(first, first + (1 if name.endswith("_stubborn") else 2)))
        assert (r["worlds"], r["crashes"], r["collisions"]) == (len(rows), len(rows) - len(done), hits)
        assert r["courteous"] == pytest.approx(np.mean([float(e["courteous"]) for e in done]))
        cells = [c.strip() for c in next(line for line in lines if line.startswith(f"| {name} |")).split("|")[1:-1]]
        assert (cells[1], cells[2], cells[7]) == (str(len(rows)), str(int(hits)), str(len(rows) - len(done)))
    runs = mlflow.search_runs(experiment_names=["planner"], filter_string=f"params.out_dir LIKE '{tmp_path}/%'")
    assert sorted(zip(runs["params.out_dir"], runs["params.scenario.cooperation"])) == sorted(
        (f"{tmp_path}/{name}", "stubborn" if name.endswith("_stubborn") else "mixed") for name in results)
    assert pd.read_csv(tmp_path / "safety.csv")["row"].tolist() == list(results)


def test_a_collision_and_a_crash_are_counted_with_their_seeds():
    rows = pd.DataFrame([{"seed": str(s), "crash": "0", "collision": str(c), "courteous": str(1 - c), "merged": "1",
                          "fallbacks": str(f), "t_merge": "20", "C_max": "1", "b_imposed_max": "0"}
                         for s, c, f in ((7, 0, 0), (8, 1, 2), (9, 0, 1))]
                        + [{"seed": "10", "crash": "1"}]).fillna("")
    r = safety.figures(rows, wall_s=8.0)
    assert (r["worlds"], r["finished"], r["collisions"], r["crashes"]) == (4, 3, 1, 1)
    assert (r["collision_seeds"], r["crash_seeds"], r["s_per_world"]) == ("8", "10", 2.0)
    assert [r["collision_lo"], r["collision_hi"]] == pytest.approx(wilson_by_roots(1, 3))
    assert r["fallbacks"] == 1.0 and r["fallbacks_lo"] >= 0.0


@pytest.mark.parametrize("override,message", [
    ("worlds=0", "error: worlds=0: must be an integer in [1, 100000]"),
    ("worlds=-1", "error: worlds=-1: must be an integer in [1, 100000]"),
    ("stubborn_worlds=-1", "error: stubborn_worlds=-1: must be an integer in [0, 100000]"),
    ("rows=[rules,nosuch]", "error: rows=['rules', 'nosuch']: nosuch is not a row of `row` (rules, interactive_cv, "
                            "interactive_student, interactive_surrogate)"),
    ("stubborn_seed=40000001", "error: stubborn_seed=40000001: the stubborn worlds 40000001..40000100 overlap the fresh "
                               "batch's 40000000..40000499; choose another stubborn_seed"),
])
def test_a_bad_size_or_row_is_one_line_before_any_batch(override, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        safety.run(compose_cfg("safety", [f"out_dir={tmp_path}", override]))
    assert e.value.code == 2 and capsys.readouterr().err.strip().splitlines() == [message]
    assert list(tmp_path.iterdir()) == []


def test_a_row_whose_model_is_missing_names_the_file_and_make_demo(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        safety.run(compose_cfg("safety", [f"out_dir={tmp_path / 'out'}", f"models_dir={tmp_path}",
                                          "rows=[interactive_cv,interactive_student]"]))
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1
    assert err[0].startswith(f"error: row interactive_student: {tmp_path}/student.ckpt not found") and "`make demo`" in err[0]
    assert not (tmp_path / "out").exists()
