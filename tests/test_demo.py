"""bench.demo, the end of `make demo`: the dense headline table from the ceiling's and the batches' own CSVs, the
ceiling's t_merge over its courteous worlds only, and one line naming a run's missing file."""
import csv

import numpy as np
import pytest
from test_batch import wilson_by_roots

from bench import demo
from core.jobs import UserError, job_config


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
    for source, courteous in (("cv", [0, 0, 0, 0]), ("student", [0, 1, 0, 0]), ("surrogate", [1, 1, 0, 0])):
        write(tmp_path / source / f"episodes_admm_{source}_dense.csv", [
            {"seed": 2000000 + k, "crash": 0, "courteous": c, "merged": 1, "collision": 0, "t_merge": 30 + k,
             "b_imposed_max": 9.0 - 7 * c, "fallbacks": 0, "error": "", "notes": ""} for k, c in enumerate(courteous)])
    out, episodes = demo.rows(tmp_path)
    ceiling = out["clairvoyant ceiling"]
    assert ceiling["t_merge"] == pytest.approx(25.0) and np.isnan(ceiling["merged"])  # its courteous worlds only
    assert [ceiling["courteous_lo"], ceiling["courteous_hi"]] == pytest.approx(wilson_by_roots(3, 4))
    lines = demo.table(out)
    assert lines[2].startswith("| clairvoyant ceiling | 4 | 75.0 [") and "| - | 25.0 [" in lines[2]
    assert lines[3].startswith("| interactive step, cv (constant velocity) | 4 | 0.0 [")
    assert lines[4].startswith("| interactive step, the learned student | 4 | 25.0 [") and "| 100.0 [" in lines[4]
    assert lines[5].startswith("| interactive step, the student's gradient surrogate | 4 | 50.0 [")
    assert [int(e["seed"]) for e in episodes["student"] if e["courteous"]] == [2000001]
    (tmp_path / "surrogate" / "episodes_admm_surrogate_dense.csv").unlink()
    with pytest.raises(SystemExit) as e:
        demo.run(tmp_path)
    assert e.value.code == 2
    assert capsys.readouterr().err.strip() == (f"error: {tmp_path / 'surrogate'}/episodes_admm_*.csv not found: run the "
                                               f"`planner scenario=dense method=admm mpc=interactive gradients=surrogate "
                                               f"episodes=N out_dir={tmp_path / 'surrogate'}` batch first")


def test_the_shrink_line_sets_each_size_against_its_jobs_default():
    line = demo.shrunk(["make_dataset:dataset.episodes=80", "distill,model=teacher:model.epochs=3",
                        "distill,model=student,dataset=interactive:model.epochs=3", "surrogate:data.iterate_states=400"])
    assert "make-dataset: dataset.episodes 80 of 160 (50%)" in line and "distill model=teacher: model.epochs 3 of 12 (25%)" in line
    assert "distill model=student dataset=interactive: model.epochs 3 of 15 (20%)" in line
    assert "surrogate: data.iterate_states 400 of 8000 (5%)" in line
    with pytest.raises(UserError, match=r"^--shrunk distill:model.nosuch=3: expected job\[,override\]:key=value"):
        demo.shrunk(["distill:model.nosuch=3"])


def test_the_merge_picture_shows_the_ego_s_plan_at_each_moment(tmp_path):
    from PIL import Image

    cfg = job_config("planner", ["scenario=dense", "gradients=cv", "mpc=interactive", "max_steps=12"])
    scenario, ep, plans = demo.drive_with_plans(cfg, 2000000)
    assert len(plans) == len(ep.states) - 1 == 12
    assert all(p.shape == (cfg.paper.T_p + 1, 4) and np.allclose(p[0], z[0]) for p, z in zip(plans, ep.states) if p is not None)
    path = demo.picture(ep, plans, scenario, tmp_path / "merge.png", "a title", "the outcome")
    with Image.open(path) as png:
        assert png.size == (1100, 750)
