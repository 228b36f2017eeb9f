"""bench.verdicts: each source's verdicts on the interactive step's candidates against the world's own."""
import numpy as np
import pytest

from bench import verdicts


def test_the_scores_count_refused_good_merges_accepted_bad_ones_and_the_first_choice():
    row = {"true_good": np.array([True, True, False, False]), "true_merge": np.array([True, True, True, False]),
           "good": np.array([True, False, True, False]), "merges": np.array([True, True, True, False]),
           "brake": np.array([0.0, 5.0, 0.0, 0.0]), "true_brake": np.array([0.0, 0.0, 5.0, 0.0]), "first": 2, "b_c": 3.0,
           "unsafe": np.array([False, True, False, True])}
    out = verdicts.scores([row], resamples=10, seed=0)
    assert out["false_alarm"] == 0.5  # of the two good merges it refuses the second
    assert out["miss"] == 1.0  # the one merge that is not good, it takes for good
    assert out["brake_fa"] == pytest.approx(1 / 3)  # three candidates brake nobody; it predicts 5 m/s^2 for one
    assert out["fa_unsafe"] == 0.5 and out["fa_braking"] == 0.5  # it refuses the second as unsafe and for its braking
    assert out["takes_good"] == 0.0 and out["takes_bad"] == 1.0 and out["states_with_good"] == 1


def test_the_world_agrees_with_itself_and_a_bad_value_is_one_line(tmp_path, capsys):
    table = verdicts.main(["worlds=1", "every=20", "sources=[cv]", "resamples=10", f"out_dir={tmp_path}",
                           "planner=['mpc.strategy.horizon=8','mpc.strategy.merge_steps=[0,4]']"])  # small, for speed
    assert set(table) == {"cv", "oracle"} and (tmp_path / "verdicts.csv").is_file()
    assert table["oracle"]["miss"] in (0.0,) or np.isnan(table["oracle"]["miss"])
    assert table["oracle"]["false_alarm"] in (0.0,) or np.isnan(table["oracle"]["false_alarm"])
    assert table["oracle"]["brake_fa"] == 0.0
    with pytest.raises(SystemExit):
        verdicts.main(["worlds=0"])
    assert capsys.readouterr().err.strip() == "error: worlds=0: must be an integer >= 1"
