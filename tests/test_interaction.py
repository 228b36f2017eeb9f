"""The counterfactual interaction benchmark (bench/interaction.py, bench/branches.py): known responses on constructed
branches, an ego-blind predictor scoring zero, branch pairs sharing the hidden decisions, held-out seeds, the job."""
import csv

import mlflow
import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from bench.branches import Pair, execute, heldout_seeds, make_pairs
from bench.interaction import (
    brake_scores,
    braking,
    first_order_response,
    follower_braking,
    intervals,
    load_source,
    rollout_response,
    run,
    scores,
)
from conftest import compose_cfg
from core.jobs import UserError
from core.rollout import SLOTS, T_OBS
from data.dataset import episode_seeds
from planner.gradients import ExactLocal

T_P = 8


def small_cfg(tmp_path, *overrides):
    """The job's config with a few branch states, writing to tmp_path."""
    return compose_cfg("evaluate_interaction", [f"out_dir={tmp_path}", f"models_dir={tmp_path / 'models'}", "states=3",
                                                *overrides])


@pytest.fixture(scope="module")
def pairs(tmp_path_factory):
    """Pairs of every kind from three held-out branch states."""
    cfg = small_cfg(tmp_path_factory.mktemp("pairs"))
    return make_pairs(instantiate(cfg.scenario, _convert_="all"), dict(cfg.dataset.policy), cfg)


def constructed_pair():
    """A branch by hand: four cars in lane 1 at 1 m per step, the ego in lane 0 beside them; plan A keeps the ego in its
    lane, plan B moves it 0.4 m per step towards lane 1. The cars' xy (the truth) is left to the caller."""
    t = np.arange(-T_OBS + 1, 1, dtype=float)
    history = np.zeros((T_OBS, SLOTS, 2))
    history[:, 0] = np.stack([10.0 + t, 0.0 * t], -1)
    for j, x0 in enumerate((20.0, 12.0, 6.0, -2.0), start=1):
        history[:, j] = np.stack([x0 + t, 4.0 + 0.0 * t], -1)
    k = np.arange(1, T_P + 1, dtype=float)
    ego_a = np.stack([10.0 + k, 0.0 * k], -1)
    ego_b = np.stack([10.0 + k, 0.4 * k], -1)
    return history, ego_a, ego_b


def analytic_by_hand(p, history, ego):
    """The analytic predictor's rollout of the others (T_p, N, 2), written out per car: x keeps its last displacement scaled
    by 1 - slowdown * w, w the product of three logistic switches of the ego's offset at the last observed step."""
    sig = lambda u: 1.0 / (1.0 + np.exp(-u))
    xy = [history[-2, 1:].copy(), history[-1, 1:].copy()]
    ego_last = [history[-1, 0]] + list(ego[:-1])
    out = []
    for tau in range(len(ego)):
        prev, last = xy[-2], xy[-1]
        dx, dy = ego_last[tau][0] - last[:, 0], ego_last[tau][1] - last[:, 1]
        w = sig((p.d_react - np.sqrt(dy**2 + p.c**2)) / p.s_lat) * sig(dx / p.s_ahead) * sig((p.view - dx) / p.s_view)
        nxt = np.stack([last[:, 0] + (last[:, 0] - prev[:, 0]) * (1 - p.slowdown * w), 2 * last[:, 1] - prev[:, 1]], -1)
        xy.append(nxt)
        out.append(nxt)
    return np.array(out)


def test_cv_gives_zero_and_analytic_its_known_response(tmp_path):
    history, ego_a, ego_b = constructed_pair()
    cv, analytic = load_source("cv", tmp_path), load_source("analytic", tmp_path)
    truth = np.stack([analytic_by_hand(analytic.predictor, history, e) for e in (ego_a, ego_b)])
    xy = np.concatenate([np.stack([ego_a, ego_b])[:, :, None], truth], axis=2)
    pair = Pair(0, 0, "push", history, np.arange(SLOTS), np.zeros((2, T_P, 2)), xy, None)
    assert np.abs(pair.response).max() > 0.2  # the constructed branch has a real response

    assert np.array_equal(rollout_response(cv, pair), np.zeros((T_P, 4, 2)))
    assert np.array_equal(first_order_response(cv, pair), np.zeros((T_P, 4, 2)))
    np.testing.assert_allclose(rollout_response(analytic, pair), pair.response, atol=1e-9)

    # first order: J(A) . (B - A) against the hand rollout's difference quotient along B - A
    eps = 1e-5
    quotient = (analytic_by_hand(analytic.predictor, history, ego_a + eps * (ego_b - ego_a)) - truth[0]) / eps
    np.testing.assert_allclose(first_order_response(analytic, pair), quotient, atol=1e-4)

    true = pair.response[None]
    assert scores(rollout_response(analytic, pair)[None], true, 0.2, 0.5) == pytest.approx(
        {"react_corr": 1.0, "react_gain": 1.0, "react_hit": 1.0})
    assert scores(rollout_response(cv, pair)[None], true, 0.2, 0.5) == {"react_corr": 0.0, "react_gain": 0.0, "react_hit": 0.0}


def test_braking_is_the_hardest_deceleration_of_another_car_after_the_history():
    history, ego_a, _ = constructed_pair()
    dt, k = 0.2, np.arange(1, T_P + 1, dtype=float)
    xy = np.concatenate([ego_a[:, None], history[-1, 1:][None] + np.stack([k, 0 * k], -1)[:, None]], axis=1)  # cv
    assert braking(xy, history, dt) == 0.0
    xy[3:, 2, 0] -= 0.5 * 2.0 * (dt * np.arange(1, T_P - 2)) ** 2  # car 2 brakes at 2 m/s^2 from step 3
    xy[:, 0, 0] += 9.0 * np.arange(T_P) ** 2  # the ego's own motion never counts
    xy[5, 3, 0] -= 0.02  # car 3 jolts back 2 cm at step 5: 0.02 / 0.04 = 0.5 m/s^2 down, then up
    assert braking(xy, history, dt) == pytest.approx(2.0)
    assert np.array_equal(braking(np.stack([xy, xy]), history, dt), [2.0, 2.0])  # batched over leading axes
    xy[1, 1, 0] = xy[0, 1, 0]  # car 1 stops dead at step 2: (0 - 1 m) / dt^2 = 25 m/s^2
    assert braking(xy, history, dt) == pytest.approx(25.0)


def test_brake_scores_rank_the_forcing_plans_and_count_the_false_alarms():
    true = np.array([[0.0, 6.0], [1.0, 5.0], [2.0, 0.5]])  # m/s^2: two of six plans force (> 4), three are calm (< 2)
    judge = dict(forced=4.0, calm=2.0, alarm=3.0)
    assert brake_scores(true, true, **judge) == pytest.approx({"brake_corr": 1.0, "brake_auc": 1.0, "brake_fa": 0.0})
    cv = {"brake_corr": 0.0, "brake_auc": 0.5, "brake_fa": 0.0}  # all ties, and never an alarm
    assert brake_scores(np.zeros_like(true), true, **judge) == cv
    swapped = np.array([[5.0, 0.0], [6.0, 1.0], [2.0, 0.5]])  # the forcing plans predicted at 0 and 1 m/s^2
    assert brake_scores(swapped, true, **judge)["brake_auc"] == pytest.approx(1 / 8)  # of 8 (forcing, tolerated) pairs only
    # (1, 0.5) is ordered right; the calm plans (0, 1, 0.5 true) are predicted at 5, 6 and 0.5: two alarms of three
    assert brake_scores(swapped, true, **judge)["brake_fa"] == pytest.approx(2 / 3)
    assert np.isnan(brake_scores(true, true, 10.0, 2.0, 3.0)["brake_auc"])  # no plan forces: nothing to sort
    assert np.isnan(brake_scores(true + 9.0, true + 9.0, **judge)["brake_fa"])  # no calm plan: no alarm to count
    rng = np.random.default_rng(1)
    true = rng.exponential(2.0, (60, 2))  # 60 pairs of 20 branch states
    pred = true + rng.normal(0.0, 1.5, true.shape)
    ci = intervals(pred, true, np.repeat(np.arange(20), 3), 300, score=lambda p, t: brake_scores(p, t, **judge))
    point = brake_scores(pred, true, **judge)
    assert set(ci) == {f"brake_{k}_{end}" for k in ("corr", "auc", "fa") for end in ("lo", "hi")}
    assert all(ci[f"{k}_lo"] < point[k] < ci[f"{k}_hi"] for k in point) and ci["brake_auc_hi"] <= 1.0


def test_the_follower_row_judges_a_cut_in_close_ahead_of_a_car_and_not_a_plan_that_stays_in_lane():
    from planner.setup import make

    s = make("dense", ["mpc=courteous", "gradients=cv"])[2]
    history, ego_a, _ = constructed_pair()  # cars in lane 1 at 20, 12, 6, -2 m moving 1 m per step; the ego at 10 m
    k = np.arange(1, T_P + 1, dtype=float)
    ego_b = np.stack([10.0 + k, np.minimum(0.8 * k, 4.0)], -1)  # into lane 1 (centre 4 m) by step 3, 4 m ahead of car 3
    pair = Pair(0, 0, "push", history, np.arange(SLOTS), np.zeros((2, T_P, 2)),
                np.stack([np.concatenate([e[:, None], np.zeros((T_P, SLOTS - 1, 2))], 1) for e in (ego_a, ego_b)]),
                type("W", (), {"params": s.params})())
    held, cut_in = follower_braking(s, pair)
    assert held == 0.0 and cut_in > 4.0  # 5 m/s closing to a 0.4 m bumper gap: far beyond b_safe


def test_scores_against_hand_computed_values():
    rng = np.random.default_rng(0)
    true = rng.normal(0.0, 0.3, (20, T_P, 4, 2))
    peak = np.linalg.norm(true, axis=-1).max(axis=1)
    s = scores(0.6 * true, true, 0.2, 0.5)  # peak error 0.4 of the peak: every real response hit
    assert s == pytest.approx({"react_corr": 1.0, "react_gain": 0.6, "react_hit": 1.0})
    assert scores(0.4 * true, true, 0.2, 0.5)["react_hit"] == 0.0  # peak error 0.6 of the peak
    noise = rng.normal(0.0, 0.3, true.shape)
    s = scores(true + noise, true, 0.2, 0.5)
    assert s["react_corr"] == pytest.approx(np.corrcoef((true + noise).ravel(), true.ravel())[0, 1])
    assert s["react_gain"] == pytest.approx(np.sum((true + noise) * true) / np.sum(true**2))
    err = np.linalg.norm(noise, axis=-1).max(axis=1)
    assert s["react_hit"] == pytest.approx(np.mean(err[peak > 0.2] <= 0.5 * peak[peak > 0.2]))


def test_bootstrap_intervals_resample_whole_branch_states():
    rng = np.random.default_rng(1)
    true = rng.normal(0.0, 0.3, (60, T_P, 4, 2))
    states = np.repeat(np.arange(20), 3)  # three pairs per branch state
    exact = intervals(2.0 * true, true, states, 200, "_jac")
    assert exact == pytest.approx({"react_corr_jac_lo": 1.0, "react_corr_jac_hi": 1.0, "react_gain_jac_lo": 2.0,
                                   "react_gain_jac_hi": 2.0})
    noisy = true + rng.normal(0.0, 0.3, true.shape)
    ci = intervals(noisy, true, states, 500)
    corr = scores(noisy, true, 0.2, 0.5)["react_corr"]
    assert ci["react_corr_lo"] < corr < ci["react_corr_hi"] and ci["react_corr_hi"] - ci["react_corr_lo"] > 0.02
    one_state = intervals(noisy, true, np.zeros(60), 50)  # nothing to resample: the interval is the point estimate
    assert one_state["react_corr_lo"] == pytest.approx(corr) and one_state["react_corr_hi"] == pytest.approx(corr)


class EgoBlind:
    """A one-step linear predictor of each car's next displacement from the others' past displacements only, fitted by
    least squares: trained on data with the ego columns zeroed, it has learned no interaction."""

    def __init__(self, windows, nexts):
        self.W = np.linalg.lstsq(self.features(windows), (nexts - windows[:, -1]).reshape(len(nexts), -1), rcond=None)[0]

    @staticmethod
    def features(window):
        """The others' displacements over the window (B, (T_obs - 1) * N * 2) and a constant; the ego's columns left out."""
        d = np.diff(np.asarray(window, dtype=float)[:, :, 1:], axis=1).reshape(len(window), -1)
        return np.concatenate([d, np.ones((len(d), 1))], axis=1)

    def phi(self, window):
        """Next xy (B, SLOTS, 2), m."""
        return np.asarray(window)[:, -1] + (self.features(window) @ self.W).reshape(len(window), SLOTS, 2)

    def phi_jac(self, window):
        """Next xy and its exact local Jacobian (B, SLOTS*2, T_obs*SLOTS*2), by central differences of the linear map."""
        window = np.asarray(window, dtype=float)
        n = window[0].size
        steps = np.eye(n).reshape(n, *window.shape[1:])
        J = np.stack([(self.phi(w + steps) - self.phi(w - steps)).reshape(n, -1).T / 2.0 for w in window])
        return self.phi(window), J


def test_a_predictor_without_interaction_scores_zero(pairs):
    windows = np.stack([np.concatenate([p.history, p.xy[b]])[k : k + T_OBS] for p in pairs for b in (0, 1) for k in range(T_P)])
    nexts = np.stack([np.concatenate([p.history, p.xy[b]])[k + T_OBS] for p in pairs for b in (0, 1) for k in range(T_P)])
    blind = ExactLocal("blind", EgoBlind(windows, nexts))
    moved = blind.values(pairs[0].history, pairs[0].ego[:1])[0, -1, 1:] - pairs[0].history[-1, 1:]
    assert np.abs(moved).max() > 1.0  # it does predict motion

    true = np.stack([p.response for p in pairs])
    assert np.abs(true).max() > 0.05  # the world did respond in some pair
    for response in (rollout_response, first_order_response):
        pred = np.stack([response(blind, p) for p in pairs])
        assert np.abs(pred).max() < 1e-6
        s = scores(pred, true, 0.2, 0.5)
        assert abs(s["react_corr"]) < 0.05 and abs(s["react_gain"]) < 0.05 and not s["react_hit"] > 0


def test_branch_pairs_share_the_hidden_decisions(pairs):
    for p in pairs:
        worlds = [execute(p.world, u)[1] for u in p.controls]
        for w in worlds:
            assert np.array_equal(w.will_yield, p.world.will_yield)
            assert w.drivers == p.world.drivers
        assert np.array_equal(execute(p.world, p.controls[0], p.ids)[0], p.xy[0])  # replaying a plan gives the same world
        assert np.array_equal(execute(p.world, p.controls[1], p.ids)[0], p.xy[1])
        assert np.array_equal(p.ego[0], execute(p.world, p.controls[0])[0][:, 0])
    world = pairs[0].world
    rng = np.random.default_rng(0)
    draws = [world.redrawn(rng) for _ in range(20)]
    assert all(d.drivers == world.drivers for d in draws)
    assert any(not np.array_equal(d.will_yield, world.will_yield) for d in draws)
    assert all(not d.will_yield[0] for d in draws)  # the ego never yields to itself


def test_heldout_seeds_are_disjoint_from_the_datasets(tmp_path):
    for dataset in ("small", "large"):
        cfg = small_cfg(tmp_path, f"dataset={dataset}")
        seeds = heldout_seeds("seed_offset", cfg.seed_offset, 10**4, cfg.dataset)
        assert not set(seeds) & set(episode_seeds(cfg.dataset.seed, cfg.dataset.episodes))
    used = episode_seeds(0, 160)[5]
    message = rf"seed_offset={used}: world seeds \[{used}\] are episodes of the dataset small \(seed 0, 160 episodes\)"
    with pytest.raises(UserError, match=message):
        heldout_seeds("seed_offset", used, 1, OmegaConf.create({"name": "small", "seed": 0, "episodes": 160}))


def test_job_logs_one_run_per_source_and_skips_missing_models(tmp_path, caplog):
    table = run(small_cfg(tmp_path, "sources=[cv,student,reference,follower]", "reference.draws=2"))
    assert list(table) == ["cv", "reference", "follower"]
    assert "student: skipped" in caplog.text
    assert table["cv"]["react_gain_jac"] == 0.0 and "react_gain_jac" not in table["reference"]
    assert table["cv"]["brake_corr"] == 0.0 and "react_corr" not in table["follower"] and "brake_corr" in table["follower"]
    with open(tmp_path / "interaction.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["source"] for r in rows] == ["cv", "reference", "follower"]
    assert float(rows[0]["brake_fa"]) == 0.0 and float(rows[2]["brake_fa"]) == pytest.approx(table["follower"]["brake_fa"], abs=1e-4)
    runs = mlflow.search_runs(experiment_names=["interaction"], filter_string="params.states = '3'")
    assert sorted(runs["params.source"])[-3:] == ["cv", "follower", "reference"]
    artifacts = mlflow.artifacts.list_artifacts(run_id=runs.loc[runs["params.source"] == "cv", "run_id"].iloc[0])
    assert "scatter_cv.png" in [a.path for a in artifacts]


def test_bad_value_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        run(small_cfg(tmp_path, "states=0"))
    assert e.value.code == 2
    assert "states=0: must be an integer >= 1" in capsys.readouterr().err
