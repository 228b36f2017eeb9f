"""backend=ray: a small batch on a local Ray instance gives the same per-episode results as local joblib."""
import csv

import pytest

from conftest import compose_cfg
from planner import cli

ray = pytest.importorskip("ray")

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
