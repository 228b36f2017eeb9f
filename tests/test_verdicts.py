"""bench.verdicts: each source's verdicts on the interactive step's candidates against the world's own."""
import numpy as np
import pytest

from bench import verdicts


def test_the_scores_count_refused_good_merges_accepted_bad_ones_and_the_first_choice():
    row = {"true_good": np.array([True, True, False, False]), "true_merge": np.array([True, True, True, False]),
           "good": np.array([True, False, True, False]), "merges": np.array([True, True, True, False]),
           "brake": np.array([0.0, 5.0, 0.0, 3.5]), "true_brake": np.array([0.0, 0.0, 5.0, 4.5]), "first": 2, "b_c": 3.0,
           "b_safe": 4.0, "unsafe": np.array([False, True, False, True]), "unsafe_merged": np.array([False, True, False, False]),
           "unsafe_late": np.array([False, True, False, True])}
    out = verdicts.scores([row], resamples=10, seed=0)
    assert out["false_alarm"] == 0.5  # of the two good merges it refuses the second
    assert out["miss"] == 1.0  # the one merge that is not good, it takes for good
    assert out["brake_fa"] == 0.5  # two candidates brake nobody; it predicts 5 m/s^2 for one
    assert out["fa_unsafe"] == 0.5 and out["fa_braking"] == 0.5  # it refuses the second as unsafe and for its braking
    assert out["fa_unsafe_merged"] == 0.5  # ... unsafe only once it has merged
    assert out["fa_unsafe_late"] == 0.5  # ... with the first contact beyond T_p (the fourth is not a good merge)
    assert out["brake_detect"] == 0.5  # of the two that force, it sees braking above b_courtesy in the last
    assert out["takes_good"] == 0.0 and out["takes_bad"] == 1.0 and out["states_with_good"] == 1
    assert out["good_kept"] == 0.5  # it keeps the first good merge


def test_good_kept_is_one_minus_the_refusals_with_the_mirrored_interval():
    rng = np.random.default_rng(4)
    rows = []
    for _ in range(12):  # states with 1-5 candidates, the world's good merges and the source's verdicts drawn at random
        k = int(rng.integers(1, 6))
        rows.append({"true_good": rng.random(k) < 0.6, "true_merge": np.ones(k, bool), "good": rng.random(k) < 0.5,
                     "merges": np.ones(k, bool), "brake": np.zeros(k), "true_brake": np.zeros(k), "first": 0, "b_c": 3.0,
                     "b_safe": 4.0, "unsafe": np.zeros(k, bool), "unsafe_merged": np.zeros(k, bool),
                     "unsafe_late": np.zeros(k, bool)})
    out = verdicts.scores(rows, resamples=200, seed=1)
    kept = sum(int((r["good"] & r["true_good"]).sum()) for r in rows)  # counted directly
    assert 0 < out["good_kept"] < 1
    assert out["good_kept"] == pytest.approx(kept / sum(int(r["true_good"].sum()) for r in rows))
    assert out["good_kept"] == pytest.approx(1 - out["false_alarm"])
    assert (out["good_kept_lo"], out["good_kept_hi"]) == pytest.approx((1 - out["false_alarm_hi"], 1 - out["false_alarm_lo"]))
    assert out["good_kept_lo"] < out["good_kept"] < out["good_kept_hi"]


def test_the_world_agrees_with_itself_and_a_bad_value_is_one_line(tmp_path, capsys, store):
    import mlflow

    table = verdicts.main(["worlds=1", "every=20", "sources=[cv]", "resamples=10", f"out_dir={tmp_path}",
                           "planner=['mpc.strategy.horizon=8','mpc.strategy.merge_steps=[0,4]']",  # small, for speed
                           f"variants=[{{name: cv_again, gradients: cv, models_dir: {tmp_path / 'none'}}}]"])
    assert set(table) == {"cv", "cv_again", "oracle"} and (tmp_path / "verdicts.csv").is_file()
    np.testing.assert_equal(table["cv_again"], table["cv"])  # a variant is judged on the same states, against the same verdicts (NaN: no such candidate there)
    assert table["oracle"]["miss"] in (0.0,) or np.isnan(table["oracle"]["miss"])
    assert table["oracle"]["false_alarm"] in (0.0,) or np.isnan(table["oracle"]["false_alarm"])
    assert table["oracle"]["brake_fa"] == 0.0
    run = mlflow.search_runs(experiment_names=["verdicts"]).iloc[0]  # the scores in MLflow, the table's own
    assert run["metrics.cv.states"] == table["cv"]["states"] and run["metrics.oracle.brake_fa"] == 0.0
    capsys.readouterr()
    with pytest.raises(SystemExit):
        verdicts.main(["worlds=0"])
    assert capsys.readouterr().err.strip() == "error: worlds=0: must be an integer in [1, 100000]"


@pytest.mark.parametrize("variant, message", [
    ("{name: cv, gradients: student, models_dir: models}", "variants[0].name=cv: must be a name that no source, the oracle "
                                                          "or another variant has"),
    ("{name: s5, gradients: oracle, models_dir: models}", "variants[0].gradients=oracle: must be one of "),
    ("{name: s5, gradients: student}", "variants[0]={'name': 's5', 'gradients': 'student'}: must be {name: "),
    ("{name: s5, gradients: student, models_dir: MISSING}", "variants[0].models_dir=MISSING: "),
])
def test_a_bad_variant_is_one_line_naming_its_key(tmp_path, capsys, variant, message):
    with pytest.raises(SystemExit):
        verdicts.main(["worlds=1", "sources=[cv]", f"out_dir={tmp_path}",
                       f"variants=[{variant.replace('MISSING', str(tmp_path / 'none'))}]"])
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: " + message.replace("MISSING", str(tmp_path / "none"))) and "\n" not in err
