"""bench.candidates: the world's answers to the interactive step's candidate plans, as a make-dataset training set."""
import numpy as np
import pytest

from bench import candidates
from data import dataset
from data.perception import observe
from planner import mpc, setup

EVERY, HORIZON = 10, 12
SMALL = [f"every={EVERY}", "per_state=1000", "closed=false", "worlds=3", "dataset.split=[0.4,0.3,0.3]",
         f"planner=['mpc.strategy.horizon={HORIZON}','mpc.strategy.merge_steps=[0,6]']"]  # every open-loop plan, few of them


def world_answer(world, path, dt):
    """Every car's xy (H, M, 2) in a copy of `world` stepped with the ego put at each xy of `path` (H, 2), heading and
    speed from its displacement: the oracle's placement, written out step by step."""
    w, out = world.copy(), []
    for p in path:
        d = p - w.states()[0, :2]
        w.step_to([p[0], p[1], np.arctan2(d[1], d[0]), np.hypot(*d) / dt])
        out.append(w.states()[:, :2])
    return np.array(out)


def test_a_candidates_windows_are_the_worlds_answer_to_its_plan(tmp_path, capsys):
    meta = candidates.main([*SMALL, f"out_dir={tmp_path}", f"models_dir={tmp_path / 'none'}", "name=c"])
    assert meta["stats"]["worlds"] == 3 and all(meta["splits"][s]["windows"] for s in dataset.SPLITS)
    assert f"from {meta['stats']['candidates']} candidates" in capsys.readouterr().out
    split = next(s for s in dataset.SPLITS if 0 in meta["splits"][s]["episodes"])
    a = dataset.load(tmp_path / "c", split)  # the format distill reads: checksums, shapes, dtypes
    seed = meta["worlds"][0]["seed"]
    pc = setup.planner_config("dense", ["gradients=cv", "mpc=interactive", "method=admm", f"models_dir={tmp_path / 'none'}",
                                        f"mpc.strategy.horizon={HORIZON}", "mpc.strategy.merge_steps=[0,6]"])
    scenario, source, s = setup.setup(pc)
    controls = setup.drive(pc, scenario, source, s, "admm", seed).controls  # world 0's closed loop, by cv
    world, plans = scenario.make_world(seed), []
    for k, u in enumerate(controls[:EVERY + 1]):
        if k % EVERY == 0:  # the states whose candidates the job drew: all of them, in the strategy's order
            obs = mpc.Observation(world.states()[0], controls[k - 1] if k else np.zeros(2),
                                  observe(world, pc.n_slots, pc.T_obs).history)
            _, Delta, _, Z = s.strategy.open_loop.plans(s, obs, None)
            plans.append(Z.reshape(*Delta.shape, 4)[:, :, :2])
        if k < EVERY:
            world.step(u)
    pick = 2  # the third plan at the second state: a lean
    branch = len(plans[0]) + pick + 1
    truth = world_answer(world, plans[1][pick], scenario.params.dt)  # xy at steps EVERY + 1 .. EVERY + HORIZON
    rows = np.flatnonzero((a["episode"] == 0) & (a["branch"] == branch))
    assert len(rows) == HORIZON and a["step"][rows].tolist() == list(range(EVERY, EVERY + HORIZON))
    for r in rows:
        t = a["step"][r] - EVERY  # the window's target is the world's answer t + 1 steps on, its slots' cars
        assert a["Y"][r] == pytest.approx(truth[t][a["ids"][r]].astype(np.float32), abs=1e-5)
        assert a["Y"][r][0] == pytest.approx(plans[1][pick][t].astype(np.float32), abs=1e-5)  # the ego is on the plan
    assert (a["branch"][a["episode"] == 0] == 0).sum() > 0  # the closed loop's own windows are branch 0


@pytest.mark.parametrize("override, message", [
    ("every=0", "every=0: must be an integer >= 1"),
    ("seed_offset=23000000", "seed_offset=23000000, worlds=40: seeds 23000000-23000039 overlap reserved[0]=[1000000, "
                             "24999999] (seeds kept for evaluation); choose another seed_offset"),
    ("worlds=2", "worlds=2 leaves a split empty with dataset.split=[0.8, 0.1, 0.1]"),
    ("wolrds=3", None),
])
def test_a_bad_override_is_one_line_and_writes_nothing(tmp_path, capsys, override, message):
    with pytest.raises(SystemExit) as e:
        candidates.main([override, f"out_dir={tmp_path}"])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1 and not (tmp_path / "candidates").exists()
    assert err == f"error: {message}" if message else err.startswith("error: ") and "wolrds" in err
