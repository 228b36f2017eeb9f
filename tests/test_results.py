"""`results`: the tiny preset runs every job from scratch and writes Markdown tables and figures whose numbers are the
MLflow runs' and the batches' episodes'; planner seeds that were the dataset's are refused."""
import csv
import re
from pathlib import Path

import mlflow
import numpy as np
import pytest
from test_batch import wilson_by_roots

from bench import results
from conftest import compose_cfg
from data.dataset import episode_seeds


def test_planner_seeds_that_were_dataset_episodes_are_refused(tmp_path, capsys):
    taken = episode_seeds(0, 40)[3]  # the tiny dataset's fourth episode
    cfg = compose_cfg("results", ["results_preset=tiny", f"planner_seed={taken - 1}", f"out_dir={tmp_path}"])
    with pytest.raises(SystemExit) as e:
        results.run(cfg)
    assert e.value.code == 2 and f"world seeds [{taken}] are episodes of the dataset tiny" in capsys.readouterr().err
    cfg = compose_cfg("results", ["results_preset=tiny", "planner_seed=999999", f"out_dir={tmp_path}"])
    with pytest.raises(SystemExit):  # 999999 + 3 reaches the interaction benchmark's worlds from 10**6
        results.run(cfg)


def cell(md: str, first: str, second: str, column: int) -> str:
    """The `column`-th cell of the Markdown row starting | first | second |."""
    row = next(line for line in md.splitlines() if line.startswith(f"| {first} | {second} |"))
    return row.split("|")[1:-1][column].strip()


def test_tiny_preset_writes_tables_and_figures_matching_mlflow(tmp_path):
    out = tmp_path / "results"
    path = results.run(compose_cfg("results", ["results_preset=tiny", f"out_dir={out}", f"work_dir={tmp_path / 'work'}",
                                               "n_jobs=1"]))
    md = path.read_text()
    for f in ("merge_rate.png", "t_merge.png", "fallbacks.png", "interaction_vs_step_time.png", "snapshots_admm.png"):
        assert (out / f).read_bytes()[:4] == b"\x89PNG" and f in md
    assert (out / "merge_admm.gif").read_bytes()[:3] == b"GIF"
    planner = mlflow.search_runs(experiment_names=["planner"])
    work = str(tmp_path / "work")
    mine = planner[planner["params.out_dir"].str.startswith(work)]
    for source in ("cv", "student"):  # one training: the pooled rates are the batch run's own
        for method in ("admm", "nnmpc"):
            r = mine[(mine["params.scenario"] == "random") & (mine["params.gradients"] == source)
                     & (mine["params.method"] == method)]
            assert len(r) == 1 and r["metrics.episodes"].iloc[0] == 4
            episodes = csv.DictReader(open(next(Path(r["params.out_dir"].iloc[0]).glob(f"episodes_{method}_*.csv"))))
            merged = [float(e["merged"]) for e in episodes if e["crash"] == "0"]
            k, n = sum(merged), len(merged)
            shown = [float(x) for x in re.findall(r"\d+\.\d", cell(md, source, method.upper(), 3))]  # rate [lo, hi], %
            assert shown == pytest.approx([100 * k / n, *(100 * np.array(wilson_by_roots(k, n)))], abs=0.051)
            assert cell(md, source, method.upper(), 2) == f"1 x {n}"
    distill = mlflow.search_runs(experiment_names=["distill"])
    teacher = distill[(distill["params.models_dir"].str.startswith(work)) & (distill["params.model"] == "teacher")]
    assert len(teacher) == 1
    ade = 1e3 * teacher["metrics.ade_rollout_m"].iloc[0]
    row = next(line for line in md.splitlines() if line.startswith("| teacher |"))
    assert float(row.split("|")[3]) == pytest.approx(ade, abs=0.051)
    inter = mlflow.search_runs(experiment_names=["interaction"])
    student = inter[(inter["params.models_dir"].str.startswith(work)) & (inter["params.source"] == "student")]
    section = md.split("## Interaction fidelity\n")[1]
    row = next(line for line in section.splitlines() if line.startswith("| student | "))
    assert float(row.split("|")[5]) == pytest.approx(student["metrics.react_corr_jac"].iloc[0], abs=5e-4)
    assert np.isfinite(float(row.split("|")[2]))
