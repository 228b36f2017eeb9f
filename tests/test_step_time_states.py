"""The step-time bench's planning states and report: every scenario family has its states (dense from several held-out
worlds), a states file collected otherwise is collected again, medians per family are each family's own, the profile's
three-way split adds up to its parts, each multi-start row is set against its own source's paper step, and a repeat meets
every other state before the same one again."""
from types import SimpleNamespace

import numpy as np
from omegaconf import OmegaConf

from bench import states as bench_states
from bench import step_time
from bench.states import collect, planning_states

SHORT = ("max_steps=6",)  # a few steps per world are enough to have states


def test_each_family_has_its_states_and_dense_comes_from_several_worlds():
    got = collect(per_scenario=4, dense_worlds=2, overrides=SHORT)
    families = [st.scenario for st in got]
    assert families == ["two_lane"] * 4 + ["three_lane"] * 4 + ["dense"] * 4
    dense = [st.obs.z0 for st in got if st.scenario == "dense"]
    assert not np.allclose(dense[0][:2], dense[-1][:2])  # spread over the runs, not one step repeated
    first_worlds = {st.obs.z0[3] for st in collect(scenarios=("dense",), per_scenario=2, dense_worlds=1, overrides=SHORT)}
    second = {st.obs.z0[3] for st in collect(scenarios=("dense",), per_scenario=2, dense_seed=2_000_001, dense_worlds=1,
                                             overrides=SHORT)}
    assert first_worlds != second  # another held-out world: another sampled start


def test_a_states_file_collected_otherwise_is_collected_again(tmp_path, monkeypatch):
    path, made = tmp_path / "states.npz", []
    real = bench_states.collect
    monkeypatch.setattr(bench_states, "collect", lambda **kw: made.append(kw) or real(**kw))
    kwargs = {"scenarios": ("two_lane",), "per_scenario": 2, "overrides": SHORT}
    a = planning_states(path, **kwargs)
    b = planning_states(path, **kwargs)
    assert len(made) == 1 and len(a) == len(b) == 2  # loaded, not collected again
    c = planning_states(path, **{**kwargs, "per_scenario": 3})
    assert len(made) == 2 and len(c) == 3


def test_medians_per_family_are_each_familys_own():
    ms = np.array([1.0, 2.0, 3.0, 10.0, 30.0])
    families = np.array(["two_lane"] * 3 + ["dense"] * 2)
    st = OmegaConf.create({"ratios": [], "ipopt": []})
    out = step_time.summary({"cv": (ms, 5.0, 0, np.zeros(5), families)}, st)
    assert out["cv_ms_median"] == 3.0 and out["cv_ms_median_two_lane"] == 2.0 and out["cv_ms_median_dense"] == 20.0
    assert out["cv_ms_p95_dense"] == np.percentile([10.0, 30.0], 95) and out["cv_ms_p99"] == np.percentile(ms, 99)


def test_each_multi_start_row_is_set_against_its_sources_paper_step():
    row = lambda ms: (np.full(4, ms), 5.0, 0, np.zeros(4), np.array(["dense"] * 4))
    timings = {"cv": row(2.0), "student": row(3.0), "cv-courteous": row(5.0), "student-interactive": row(12.0),
               "cv-interactive": row(7.0), "surrogate-courteous": row(9.0), "student-ref": row(4.0)}
    assert step_time.multi_start(timings) == [("cv-courteous", "cv"), ("student-interactive", "student"),
                                              ("cv-interactive", "cv")]  # surrogate's paper step was not timed
    st = OmegaConf.create({"ratios": [], "ipopt": [], "repeats": 1})
    out = step_time.summary(timings, st)
    assert out["ratio_student-interactive_student"] == 4.0 and out["ratio_cv-interactive_cv"] == 3.5
    srcs = {"cv": SimpleNamespace(predictor=SimpleNamespace(name="cv")),
            "student": SimpleNamespace(predictor=SimpleNamespace(name="student"))}
    shown = step_time.table(timings, srcs, out, [SimpleNamespace(scenario="dense")], st).splitlines()
    assert next(line for line in shown if "student-interactive " in line).split()[1] == "student"
    assert "student-interactive/student: 4.0x" in shown


def test_a_listed_ratio_is_also_taken_between_the_two_sources_multi_start_rows_where_both_have_one():
    row = lambda ms: (np.full(4, ms), 5.0, 0, np.zeros(4), np.array(["dense"] * 4))
    timings = {"surrogate": row(6.0), "student": row(3.0), "surrogate-interactive": row(15.0),
               "student-interactive": row(10.0), "surrogate-courteous": row(9.0), "teacher": row(300.0)}
    st = OmegaConf.create({"ratios": [["surrogate", "student"], ["teacher", "surrogate"]], "ipopt": []})
    assert step_time.pairs(timings, st) == [("surrogate", "student"), ("teacher", "surrogate"),
                                            ("surrogate-interactive", "student-interactive"),  # not courteous: one row
                                            ("surrogate-interactive", "surrogate"), ("student-interactive", "student"),
                                            ("surrogate-courteous", "surrogate")]
    assert step_time.summary(timings, st)["ratio_surrogate-interactive_student-interactive"] == 1.5


def test_the_split_sorts_every_part_into_one_of_three():
    ms = {"ADMM solve, one compiled call (numba + DAQP)": 3.0, "onnxruntime": 2.0, "surrogate/models.py": 0.5,
          "planner/step.py": 1.0, "numpy / builtins": 0.25, "daqp": 0.125}
    out = step_time.split(ms)
    assert out == {"compiled solve": 3.125, "predictor calls": 2.5, "Python": 1.25}
    assert "split: compiled solve 3.1 ms" in step_time.profile_table("cv-courteous", dict(sorted(ms.items())), {})


def test_repeats_pass_over_every_state_before_meeting_one_again(monkeypatch):
    """A source that remembers the step it just planned (the surrogate's memo of windows) gains nothing from a repeat."""
    seen, clock = [], iter(np.cumsum([0.0, 0.005, 0.0, 0.005] * 3 + [0.0, 0.002, 0.0, 0.002] * 3))
    monkeypatch.setattr(step_time.time, "perf_counter", lambda: next(clock))
    run = lambda name: lambda i, state: seen.append((name, i)) or SimpleNamespace(iters=i, fallback="", J=float(i))
    out = step_time.fastest({"a": run("a"), "b": run("b")}, [SimpleNamespace(scenario="two_lane")] * 3, repeats=2)
    assert seen == [(n, i) for i in range(3) for n in "ab"] * 2
    np.testing.assert_allclose(out["a"][0], [2.0] * 3)  # ms, the faster pass
    assert out["b"][1] == 1.0 and list(out["b"][3]) == [0.0, 1.0, 2.0]
