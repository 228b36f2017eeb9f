"""highway-env as a second world: the frame and action mapping, determinism, the env's success flag, the planner through
the World protocol and as a gymnasium policy, and the one-line errors."""
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("highway_env")
import gymnasium  # noqa: E402

from core.jobs import UserError, build, job_config  # noqa: E402
from data import bicycle, highway  # noqa: E402
from data.bicycle import BicycleParams  # noqa: E402
from planner import report  # noqa: E402
from planner.gym_policy import MergePolicy  # noqa: E402
from planner.setup import drive, planner_config, setup  # noqa: E402


def env(seed=2000000, **config):
    """A reset DenseMergeEnv (unwrapped) of world `seed`."""
    e = highway.DenseMergeEnv(config=config)
    e.reset(seed=seed)
    return e


def test_same_seed_same_episode_and_another_seed_another_world():
    runs = []
    for seed in (5, 5, 6):
        e = env(seed)
        for k in range(8):
            e.step(np.array([0.3, 0.1 * (-1) ** k], np.float32))
        runs.append(e.states())
    assert np.array_equal(runs[0], runs[1])
    assert runs[0].shape != runs[2].shape or not np.allclose(runs[0], runs[2])


def test_a_car_ahead_in_the_left_lane_lands_where_our_frame_says():
    e = env()
    ego, car = e.road.vehicles[0], e.road.vehicles[1]
    car.position = ego.position + np.array([10.0, -4.0])  # highway-env: 10 m ahead, one lane to the left (y grows right)
    car.heading = 0.1  # turning right in highway-env
    z = e.states()
    assert z[1, :2] - z[0, :2] == pytest.approx([10.0, 4.0])  # ours: y grows to the left
    assert z[1, 2] == pytest.approx(-0.1)  # ours: anticlockwise
    assert e.scenario().road.centre(1) == pytest.approx(z[0, 1] + 4.0)  # the ego starts on lane 0's centre


def test_action_order_scaling_axles_dt_and_substeps_match_our_bicycle():
    e = env()
    a_range, s_range = e.config["action"]["acceleration_range"], e.config["action"]["steering_range"]
    u = np.array([0.2, 1.5])  # steer left 0.2 rad, accelerate 1.5 m/s^2
    action = highway.to_action(u, a_range, s_range)
    assert action[0] == pytest.approx(2 * (1.5 - a_range[0]) / (a_range[1] - a_range[0]) - 1)  # acceleration first
    assert action[1] < 0  # steering left is negative in highway-env
    assert highway.from_action(action, a_range, s_range) == pytest.approx(u, abs=1e-6)
    sc = e.scenario()
    assert sc.road.car_length == highway.Vehicle.LENGTH and sc.params.l_f == sc.params.l_r == highway.Vehicle.LENGTH / 2
    substeps = e.config["simulation_frequency"] // e.config["policy_frequency"]
    assert sc.params.dt == pytest.approx(substeps / e.config["simulation_frequency"])
    z = e.states()[0]
    e.step(action)
    fine = BicycleParams(sc.params.l_f, sc.params.l_r, sc.params.dt / substeps)
    for _ in range(substeps):
        z = bicycle.step(z, u, fine)
    assert e.states()[0] == pytest.approx(z, abs=1e-6)
    assert z[1] > 0  # and it went left


def test_the_ego_stops_instead_of_reversing():
    e = env()
    for _ in range(10):
        e.step(np.array([-1.0, 0.0], np.float32))
    assert e.states()[0, 3] == 0.0


def test_success_flag_on_hand_built_episodes():
    e = env()
    sc = e.scenario()
    ego = e.vehicle
    for v in e.road.vehicles[1:]:  # clear the target lane around the ego
        v.position = v.position + np.array([100.0 if v.position[0] > ego.position[0] else -100.0, 0.0])
    ego.position = np.array([ego.position[0], -sc.y_ref])  # put the ego on the target lane's centre
    info = e.step(highway.to_action(np.zeros(2), e.config["action"]["acceleration_range"],
                                    e.config["action"]["steering_range"]))[-1]
    assert info["merged"] and not info["crashed"] and info["b_imposed_max"] <= sc.b_safe and info["courteous"]
    assert e._reward(None) == 0.0  # the courteous merge paid once, on its step
    # the same, with a follower put 1.5 m behind a stopped car: it brakes harder than b_safe (within b_max): not courteous
    follower, leader = e.road.vehicles[-1], e.road.vehicles[-2]
    leader.speed, follower.position = 0.0, leader.position - np.array([highway.Vehicle.LENGTH + 1.5, 0.0])
    info = e.step(np.zeros(2, np.float32))[-1]
    assert info["merged"] and sc.b_safe < info["b_imposed_max"] <= sc.b_max and not info["courteous"]


def test_a_short_cv_episode_reports_what_the_env_state_implies():
    cfg = planner_config("highway", ["gradients=cv", "max_steps=6"])
    scenario, source, s = setup(cfg)
    ep = drive(cfg, scenario, source, s, "admm", seed=2000003)
    m = report.metrics(ep, scenario)
    speeds = ep.states[:, 1:, 3]
    assert m["b_imposed_max"] == pytest.approx(max(0.0, np.max(speeds[:-1] - speeds[1:]) / scenario.params.dt))
    in_lane = np.abs(ep.states[1:, 0, 1] - scenario.y_ref) <= scenario.merge_tol
    assert m["merged"] == float(in_lane.any()) and len(ep.rows) == 6


def test_the_planner_drives_the_gymnasium_env_as_a_policy():
    e = gymnasium.make(highway.ENV_ID)
    policy = MergePolicy(["gradients=cv", "method=admm"])
    obs, _ = e.reset(seed=2000001)
    policy.reset()
    for _ in range(3):
        obs, _, terminated, truncated, info = e.step(policy(obs))
    assert e.action_space.contains(policy(obs)) and set(info) >= {"merged", "courteous", "b_imposed_max", "crashed"}


def test_bad_input_is_one_clear_line():
    with pytest.raises(UserError, match="call reset"):
        MergePolicy(["gradients=cv", "method=admm"])(np.zeros((24, 6)))
    with pytest.raises(UserError, match="observation.type=Kinematics"):
        env(observation={"type": "Kinematics"})
    with pytest.raises(UserError, match=r"action.steering_range=\[0.5, -0.5\]: must be \[low, high\] with low < high"):
        env(action={"type": "ContinuousAction", "acceleration_range": [-5, 5], "steering_range": [0.5, -0.5]})
    with pytest.raises(UserError, match="policy_frequency=4: must divide simulation_frequency=15"):
        env(policy_frequency=4)
    with pytest.raises(UserError, match="needs a dense scenario"):
        env(scenario="two_lane")
    world = build(job_config("planner", ["scenario=highway"]).scenario).make_world(0)
    with pytest.raises(UserError, match="never yield"):
        world.with_decisions(np.ones(len(world.states()), bool))
    with pytest.raises(UserError, match=r"^world=predictor moves the others by the predictor, but scenario=highway's cars"):
        setup(planner_config("highway", ["gradients=cv", "world=predictor"]))  # at set-up, before any step


@pytest.mark.parametrize("config,line", [
    ({"overrides": ["scenario.x_ref=abc"]}, "scenario.x_ref=abc: must be a number"),
    ({"scenario": "nosuch"}, "scenario=nosuch: unknown; choose one of dense, "),
    ({"overrides": "scenario.x_ref=300"}, "overrides='scenario.x_ref=300': a list of overrides of the scenario"),
    ({"overrides": ["scenario.nosuch=1"]}, "unknown key 'scenario.nosuch'"),
    ({"observation": {"type": "States", "vehicles_count": 0}}, "observation.vehicles_count=0: must be an integer in [1, 51]"),
    ({"simulation_frequency": 0}, "simulation_frequency=0: must be an integer in [1, 1000]"),
    ({"policy_frequency": 0}, "policy_frequency=0: must be an integer >= 1"),
    ({"overrides": ["gradients=cv"]}, "overrides=['gradients=cv']: admm-nnmpc/DenseMerge-v0 takes overrides of the scenario only"),
    # sizes where memory or time would explode: 45 GB of observation rows, 10^9 sub-steps of a decision
    ({"observation": {"type": "States", "vehicles_count": 10**9}}, "observation.vehicles_count=1000000000: must be an integer in [1, 51]"),
    ({"simulation_frequency": 10**9}, "simulation_frequency=1000000000: must be an integer in [1, 1000]"),
    ({"duration": 10**12}, "duration=1000000000000: must be an integer in [1, 10000]"),
    ({"observation": "States"}, "observation='States': admm-nnmpc/DenseMerge-v0's observation config is a dict"),
    ({"action": "abc"}, "action='abc': admm-nnmpc/DenseMerge-v0's action config is a dict"),
    ({"action": {"acceleration_range": [-5, 5], "steering_range": [-1, 1]}}, "action.type is missing from the config"),
    ({"action": {"type": "ContinuousAction", "acceleration_range": [1], "steering_range": [-1, 1]}},
     "action.acceleration_range=[1]: must be [low, high] with low < high"),
    ({"action": {"type": "ContinuousAction", "acceleration_range": ["a", "b"], "steering_range": [-1, 1]}},
     "action.acceleration_range=['a', 'b']: must be [low, high] with low < high, both numbers"),
])
def test_the_envs_config_errors_are_one_line_naming_the_key(config, line):
    with pytest.raises(UserError) as e:
        env(**config)
    assert str(e.value).startswith(line) and "\n" not in str(e.value)


def test_a_render_mode_without_a_renderer_is_one_line():
    with pytest.raises(UserError, match=r"^render_mode='ansi': admm-nnmpc/DenseMerge-v0 renders 'human' or 'rgb_array'"):
        gymnasium.make(highway.ENV_ID, render_mode="ansi")


@pytest.mark.parametrize("overrides,line", [
    (["nosuch=1"], "unknown key 'nosuch'"),
    (["gradients=nosuch"], "unknown gradients 'nosuch'; choose one of "),
    ("gradients=cv", "MergePolicy: overrides='gradients=cv': a list of `planner` overrides"),
])
def test_the_policys_config_errors_are_one_line(overrides, line):
    with pytest.raises(UserError) as e:
        MergePolicy(overrides)
    assert str(e.value).startswith(line) and "\n" not in str(e.value)


@pytest.mark.parametrize("action,line", [
    ("abc", "action='abc': admm-nnmpc/DenseMerge-v0's action config is a dict"),
    ({"acceleration_range": [5, -5]}, "action.acceleration_range=[5, -5]: must be [low, high] with low < high"),
    ({"steering_range": [0.1]}, "action.steering_range=[0.1]: must be [low, high]"),
])
def test_the_policys_action_config_is_checked_as_the_envs(action, line):
    with pytest.raises(UserError) as e:
        MergePolicy(["gradients=cv"], action=action)
    assert str(e.value).startswith(line) and "\n" not in str(e.value)
    assert MergePolicy(["gradients=cv"], action={"steering_range": [-0.5, 0.5]}).ranges == ([-5.0, 5.0], [-0.5, 0.5])  # the rest default


def test_the_policy_refuses_ids_that_would_mix_cars_and_a_new_episode_without_reset():
    e = env(2000002)
    policy = MergePolicy(["gradients=cv", "method=admm"])
    policy.reset()
    obs = e.observation_type.observe()
    twice = obs.copy()
    twice[2, 1] = twice[1, 1]
    with pytest.raises(UserError, match=r"^MergePolicy: car ids \[1\] appear twice in one observation"):
        policy.observe(twice)
    second_ego = obs.copy()
    second_ego[1, 1] = 0.4  # would be read as id 0: a second ego
    with pytest.raises(UserError, match=r"^MergePolicy: car ids are whole numbers >= 0, not \[0.4\]"):
        policy.observe(second_ego)
    for _ in range(2):  # two steps of one episode pass
        obs = e.step(policy(obs))[0]
    policy(obs)
    obs, _ = e.reset(seed=2000003)  # the next world, the policy not reset: its histories are the last world's
    with pytest.raises(UserError, match="call reset\\(\\) at the start of every episode"):
        policy(obs)
    policy.reset()
    assert e.action_space.contains(policy(obs))


def test_the_return_never_pays_for_a_merge_that_ends_in_a_crash():
    e = env()
    sc, ego = e.scenario(), e.vehicle
    for v in e.road.vehicles[1:]:  # clear the target lane around the ego
        v.position = v.position + np.array([100.0 if v.position[0] > ego.position[0] else -100.0, 0.0])
    ego.position = np.array([ego.position[0], -sc.y_ref])  # the ego on the target lane's centre: a courteous merge
    keep = highway.to_action(np.zeros(2), e.config["action"]["acceleration_range"], e.config["action"]["steering_range"])
    rewards, infos = [], []
    for k in range(3):
        if k == 2:  # a car stopped just ahead of the ego in its lane: the ego runs into it
            e.road.vehicles[1].position, e.road.vehicles[1].speed = ego.position + np.array([3.0, 0.0]), 0.0
        _, r, terminated, _, info = e.step(keep)
        rewards.append(r)
        infos.append(info)
    assert infos[0]["courteous"] and rewards[:2] == [1.0, 0.0]
    assert terminated and infos[-1]["crashed"] and not infos[-1]["courteous"] and rewards[-1] == -1.0
    assert sum(rewards) == float(infos[-1]["courteous"]) == 0.0


def test_gymnasium_makes_the_env_in_a_fresh_interpreter_with_its_time_limit_and_its_checks_pass(tmp_path):
    from gymnasium.utils.env_checker import check_env

    code = ("import gymnasium; e = gymnasium.make('data.highway:admm-nnmpc/DenseMerge-v0'); "
            "print(e.spec.max_episode_steps, type(e.unwrapped).__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)  # not the repository
    assert out.returncode == 0 and out.stdout.split() == ["60", "DenseMergeEnv"], out.stderr[-2000:]
    e = gymnasium.make(highway.ENV_ID)
    assert e.spec.max_episode_steps == highway.DenseMergeEnv.default_config()["duration"]
    check_env(e.unwrapped)  # gymnasium's own checks: spaces, reset and step signatures, determinism under a seed


def test_highway_env_missing_names_the_extra():
    code = "import sys; sys.modules['highway_env'] = None\nimport data.highway"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode != 0 and "pip install -e '.[highway]'" in out.stderr.strip().splitlines()[-1]


def test_an_episode_renders_as_a_gif_by_highway_envs_renderer(tmp_path):
    from PIL import Image

    scenario = build(job_config("planner", ["scenario=highway"]).scenario)
    world = scenario.make_world(3)
    states = [world.states()]
    for _ in range(2):
        world.step(np.array([0.1, 0.0]))
        states.append(world.states())
    path = scenario.render(3, states, tmp_path / "run.gif")
    with Image.open(path) as gif:
        assert gif.n_frames == 3 and gif.size == (900, 180)


@pytest.mark.parametrize("mpc", ["paper", "interactive"])
def test_the_planners_safety_shape_keeps_highway_bodies_apart_and_the_circle_would_not(mpc):
    """Sampled pairs of 5 m x 2 m bodies (the ego's heading anywhere in mpc.psi_box, the other's along the road): every
    overlapping pair has b_i < 0 with the highway scenario's shape (the paper's ellipse, or the leaning steps' superellipse
    from its lean_shape); with the paper's circle some do not."""
    from core.rollout import b_i
    from data.world import overlap

    sc, _, s = setup(planner_config("highway", ["gradients=cv", f"mpc={mpc}"]))
    if mpc == "paper":
        assert s.stretch == pytest.approx(1.77) and setup(planner_config("two_lane", ["gradients=cv"]))[2].stretch == 1.0
    else:
        assert (s.R, s.stretch, s.shape, *s.psi_box, s.strategy.lean) == pytest.approx((2.6, 2.35, 8, -0.2, 0.2, 1.4))
    rng = np.random.default_rng(0)
    n = 20000
    ego = np.column_stack([rng.uniform(-9, 9, n), rng.uniform(-4.5, 4.5, n), rng.uniform(*s.psi_box, n), np.ones(n)])
    hits = np.array([overlap(z, np.array([0.0, 0.0, 0.0, 1.0]), sc.road) for z in ego])
    values = np.zeros((n, 2, 2))
    values[:, 0] = ego[:, :2]  # (T_p = n, SLOTS = 2, 2): one pair per "step"
    assert hits.sum() > 1000
    assert (b_i(values, s.R, s.stretch, s.shape)[0][hits] < 0).all()
    assert (b_i(values, s.R)[0][hits] >= 0).any()


def test_the_leaning_steps_take_the_scenarios_shape_and_lean_and_it_lets_the_ego_lean_beside_a_car():
    """mpc=courteous and mpc=interactive read the highway scenario's lean_shape (it used to refuse the step: our 3.6 m x
    1.6 m shape does not cover its bodies); the lean it declares leaves b_i >= 0 beside a car on the next lane's centre,
    one 0.1 m deeper does not; the dense scenario keeps its own shape and 1.9 m lean."""
    from core.rollout import b_i

    for mpc in ("courteous", "interactive"):
        sc, _, s = setup(planner_config("highway", ["gradients=cv", f"mpc={mpc}"]))
        lean = s.strategy.lean if mpc == "interactive" else s.strategy.starts[0][0]
        assert lean == 1.4
        beside = lambda d: b_i(np.array([[[0.0, d], [0.0, sc.road.lane_width]]]), s.R, s.stretch, s.shape)[0, 0]
        assert beside(lean) == pytest.approx(0.0, abs=1e-9) and beside(lean + 0.1) < 0
    s = setup(planner_config("dense", ["gradients=cv", "mpc=interactive"]))[2]
    assert (s.R, s.stretch, s.shape, *s.psi_box, s.strategy.lean) == pytest.approx((2.1, 2.4, 6, -0.25, 0.25, 1.9))
