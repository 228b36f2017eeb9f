"""Dataset: determinism by seed, splits by episode, validation of damaged files, atomic rebuilds, CLI errors, MLflow."""
import json
import os
import subprocess
import sys

import mlflow
import numpy as np
import pytest
from hydra.utils import instantiate

from conftest import compose_cfg
from core.jobs import UserError
from data import dataset
from data.plot import plot_episode
from data.policies import ProbePolicy

POLICY = dict(compose_cfg("make_dataset").dataset.policy)
BRANCHES = dict(compose_cfg("make_dataset").dataset.branches)


def build(seed, episodes=10):
    sc = instantiate(compose_cfg("make_dataset").scenario, _convert_="all")
    return dataset.build(sc, POLICY, BRANCHES, episodes=episodes, steps=20, t_obs=8, n_slots=4, seed=seed)[0]


def test_same_seed_same_data_other_seed_other_data():
    a, b, c = build(3), build(3), build(4)
    for split in dataset.SPLITS:
        for k in a[split]:
            np.testing.assert_array_equal(a[split][k], b[split][k])
    assert not np.array_equal(a["train"]["X"][:50], c["train"]["X"][:50])


def test_branches_restart_the_episode_and_drive_the_ego_differently():
    a = build(5)["train"]
    n_branch = BRANCHES["points"] * 3  # push on, back off, change speed
    for e in np.unique(a["episode"]):
        own = (a["episode"] == e) & (a["branch"] == 0)
        branches = np.unique(a["branch"][a["episode"] == e])[1:]
        assert list(branches) == list(range(1, n_branch + 1))
        by_step = dict(zip(a["step"][own], np.flatnonzero(own)))
        ego_moved = []
        for b in branches:
            rows = np.flatnonzero((a["episode"] == e) & (a["branch"] == b))
            first = rows[np.argmin(a["step"][rows])]
            assert len(rows) <= BRANCHES["steps"]
            np.testing.assert_array_equal(a["X"][first], a["X"][by_step[a["step"][first]]])  # same past as the episode
            ego_moved.append(np.abs(a["Y"][rows[-1], 0] - a["Y"][by_step[a["step"][rows[-1]]], 0]).max())
        assert max(ego_moved) > 0.3  # the interventions take the ego elsewhere than the episode's own run


def test_too_few_episodes_for_the_splits_is_a_user_error():
    with pytest.raises(UserError, match="dataset.episodes=4"):
        build(0, episodes=4)


def test_windows_are_consistent_with_the_episode_and_splits_disjoint(tiny_dataset):
    meta = dataset.read_meta(tiny_dataset)
    splits = {s: dataset.load(tiny_dataset, s) for s in dataset.SPLITS}
    episodes = [set(np.unique(splits[s]["episode"])) for s in dataset.SPLITS]
    assert not (episodes[0] & episodes[1]) and not (episodes[0] & episodes[2]) and not (episodes[1] & episodes[2])
    assert sum(len(e) for e in episodes) == meta["stats"]["episodes"]
    tr = splits["train"]
    # consecutive windows of one episode overlap: the target of step t is the last observation of step t+1
    same = (tr["episode"][1:] == tr["episode"][:-1]) & (tr["branch"][1:] == tr["branch"][:-1]) & \
        (tr["step"][1:] == tr["step"][:-1] + 1) & (tr["ids"][1:] == tr["ids"][:-1]).all(1)  # slots: the nearest cars
    assert same.sum() > 100
    np.testing.assert_allclose(tr["Y"][:-1][same], tr["X"][1:][same][:, -1])
    # others move forward about dt * speed (m), never backwards
    dx = tr["Y"][:, 1:, 0] - tr["X"][:, -1, 1:, 0]
    assert dx.min() >= -1e-6 and dx.max() < 0.2 * 12


def test_damaged_files_give_one_clear_error_naming_the_file(tiny_dataset, tmp_path):
    root = tmp_path / "copy"
    root.mkdir()
    for f in tiny_dataset.iterdir():
        (root / f.name).write_bytes(f.read_bytes())
    dataset.load(root, "val")
    (root / "val.npz").write_bytes(b"not a zip file")
    with pytest.raises(UserError, match="val.npz"):
        dataset.load(root, "val")
    meta = json.loads((root / "meta.json").read_text())
    (root / "meta.json").write_text("{broken")
    with pytest.raises(UserError, match="meta.json"):
        dataset.load(root, "test")
    meta["T_obs"] = 6  # mismatched meta: shapes no longer agree
    (root / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(UserError, match="test.npz.*shape"):
        dataset.load(root, "test")
    with pytest.raises(UserError, match="make-dataset"):
        dataset.load(tmp_path / "nowhere", "train")


def test_nan_windows_are_refused(tiny_dataset, tmp_path):
    arrays = dataset.load(tiny_dataset, "test")
    arrays["X"][0, 0, 0, 0] = np.nan
    meta = dataset.read_meta(tiny_dataset)
    dataset.save(tmp_path / "nan", {"train": arrays, "val": arrays, "test": arrays}, {k: meta[k] for k in ("T_obs", "N")})
    with pytest.raises(UserError, match="NaN"):
        dataset.load(tmp_path / "nan", "train")


def test_failed_rebuild_leaves_the_good_dataset(tiny_dataset, tmp_path):
    root = tmp_path / "good"
    arrays = dataset.load(tiny_dataset, "val")
    dataset.save(root, {s: arrays for s in dataset.SPLITS}, {"T_obs": 8, "N": 4})
    before = {f.name: f.read_bytes() for f in root.iterdir()}
    bad = dict(arrays, X=None)  # np.savez fails half way through
    with pytest.raises(Exception):
        dataset.save(root, {"train": arrays, "val": bad, "test": arrays}, {"T_obs": 8, "N": 4})
    assert {f.name: f.read_bytes() for f in root.iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["good"]


def test_build_is_logged_to_mlflow(tiny_dataset, mlflow_store):
    runs = mlflow.search_runs(experiment_names=["dataset"], filter_string="params.`dataset.name` = 'tiny'")
    assert len(runs) >= 1
    meta = dataset.read_meta(tiny_dataset)
    assert runs.iloc[0]["metrics.n_train"] == meta["splits"]["train"]["windows"]
    assert runs.iloc[0]["status"] == "FINISHED"


def run_cli(*args, cwd):
    env = dict(os.environ)
    return subprocess.run([sys.executable, "-c", "from data.cli import main; main()", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_bad_overrides_fail_clearly(tmp_path):
    r = run_cli("dataset.episodez=3", cwd=tmp_path)
    assert r.returncode != 0 and "episodez" in r.stderr
    r = run_cli("scenario=four_lane", cwd=tmp_path)
    assert r.returncode != 0 and "four_lane" in r.stderr
    assert not (tmp_path / "data").exists()


def test_episode_plot_is_a_png(tmp_path):
    sc = instantiate(compose_cfg("make_dataset", ["scenario=two_lane"]).scenario, _convert_="all")
    states, _, world, _ = dataset.rollout(sc, ProbePolicy(y_ref=4.0, t_start=0.2), 0, 20)
    plot_episode(states, world.road, tmp_path / "e.png", "two_lane", sc.x_ref)
    assert (tmp_path / "e.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
