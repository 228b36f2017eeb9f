"""bench.demo, the end of `make demo`: the dense headline table from the ceiling's and the batches' own CSVs, the
ceiling's t_merge over its courteous worlds only, and one line naming a run's missing file."""
import csv

import numpy as np
import pytest
from test_batch import wilson_by_roots

from bench import demo


def write(path, rows):
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def test_headline_table_reads_the_runs_files(tmp_path, capsys):
    write(tmp_path / "ceiling_dense.csv", [
        {"seed": 2000000 + k, "ceiling_courteous": c, "ceiling_t_merge": t, "ceiling_b_imposed": b, "ceiling_policy": "gap"}
        for k, (c, t, b) in enumerate([(1, 20, 2.0), (1, 30, 3.0), (0, 60, 5.0), (1, 25, 1.0)])])
    for step, courteous in (("paper", [0, 0, 0, 0]), ("courteous", [0, 1, 0, 0])):
        write(tmp_path / step / "episodes_admm_student_dense.csv", [
            {"seed": 2000000 + k, "crash": 0, "courteous": c, "merged": 1, "collision": 0, "t_merge": 30 + k,
             "b_imposed_max": 9.0 - 7 * c, "fallbacks": 0, "error": "", "notes": ""} for k, c in enumerate(courteous)])
    out, episodes = demo.rows(tmp_path)
    ceiling = out["clairvoyant ceiling"]
    assert ceiling["t_merge"] == pytest.approx(25.0) and np.isnan(ceiling["merged"])  # its courteous worlds only
    assert [ceiling["courteous_lo"], ceiling["courteous_hi"]] == pytest.approx(wilson_by_roots(3, 4))
    lines = demo.table(out)
    assert lines[2].startswith("| clairvoyant ceiling | 4 | 75.0 [") and "| - | 25.0 [" in lines[2]
    assert lines[4].startswith("| ADMM, the courteous step | 4 | 25.0 [") and "| 100.0 [" in lines[4]
    assert [int(e["seed"]) for e in episodes["courteous"] if e["courteous"]] == [2000001]
    (tmp_path / "courteous" / "episodes_admm_student_dense.csv").unlink()
    with pytest.raises(SystemExit) as e:
        demo.run(tmp_path)
    assert e.value.code == 2
    assert capsys.readouterr().err.strip() == (f"error: {tmp_path / 'courteous'}/episodes_admm_*.csv not found: run the "
                                               f"`planner scenario=dense method=admm mpc=courteous episodes=N "
                                               f"out_dir={tmp_path / 'courteous'}` batch first")
