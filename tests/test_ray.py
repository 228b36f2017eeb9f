"""Ray: a small batch on a local Ray instance (backend=ray) gives the same per-episode results as local joblib, and a
sweep on the Ray launcher (hydra/launcher=ray_cluster) the same per-run results as Hydra's basic launcher."""
import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import compose_cfg
from planner import cli

ray = pytest.importorskip("ray")
pytestmark = pytest.mark.slow  # a local Ray instance and four planner processes

COMPARED = ("seed", "merged", "t_merge", "C_max", "d_min_m", "collision", "fallbacks", "steps", "crash", "nan")


def episodes(tmp_path, *overrides) -> list[dict]:
    """The per-episode CSV of a 3-episode NNMPC batch on random merges, outcome columns only."""
    cfg = compose_cfg("planner", ["scenario=random", "gradients=analytic", "method=nnmpc", "max_steps=6", "episodes=3",
                                  "seed=2000000", "plots=false", f"out_dir={tmp_path}", *overrides])
    cli.run(cfg)
    with open(tmp_path / "episodes_nnmpc_analytic_random.csv") as f:
        return [{k: r[k] for k in COMPARED} for r in csv.DictReader(f)]


def test_ray_batch_matches_joblib(tmp_path):
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        on_ray = episodes(tmp_path / "ray", "backend=ray", "n_jobs=2")
    finally:
        ray.shutdown()
    assert on_ray == episodes(tmp_path / "loky", "n_jobs=1")
    assert [r["seed"] for r in on_ray] == ["2000000", "2000001", "2000002"] and all(r["crash"] == "0" for r in on_ray)


def sweep(tmp_path, name, *overrides) -> list[list[dict]]:
    """`planner -m` over two seeds of random merges (CV, 3 steps) in tmp_path: each job's steps CSV without its timings."""
    argv = [Path(sys.executable).parent / "planner", "-m", "scenario=random", "gradients=cv", "max_steps=3", "plots=false",
            "seed=2000000,2000001", f"hydra.sweep.dir={name}", *overrides]
    done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True,
                          env={**os.environ, "CI": "1", "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stderr[-3000:]
    jobs = []
    for k in range(2):
        assert f"seed={2000000 + k}" in (tmp_path / name / str(k) / ".hydra" / "overrides.yaml").read_text()
        with open(tmp_path / name / str(k) / "steps_admm.csv") as f:
            jobs.append([{c: v for c, v in r.items() if c != "step_ms"} for r in csv.DictReader(f)])
    return jobs


def test_ray_sweep_matches_the_basic_launcher(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    on_ray = sweep(tmp_path, "ray", "hydra/launcher=ray_cluster")  # ray.address null: a local instance
    assert on_ray == sweep(tmp_path, "basic")
    assert all(len(rows) == 3 for rows in on_ray) and on_ray[0] != on_ray[1]
