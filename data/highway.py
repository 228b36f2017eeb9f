"""highway-env (Farama) as a second world: the dense merge on its road, vehicles, IDM/MOBIL drivers and renderer.

Two faces of one simulation:
- `DenseMergeEnv`, a gymnasium environment (`admm-nnmpc/DenseMerge-v0`): the ego in a lane that ends at the scenario's
  x_ref beside a stream of highway-env IDM vehicles; ContinuousAction; an observation of absolute states with stable
  ids; the courteous merge in `info`.
- `HighwayWorld`, the same environment behind data.protocol.World, so the planner, batches, the ceiling and the oracle
  run on it unchanged (`scenario=highway`, `scenario=highway_three_lane`).

Every world is drawn by our scenario (data.scenarios.DenseScenario: speeds, gaps, driver parameters, seeded), so a seed
gives the same start in both simulators; from there highway-env's own vehicles drive. Its drivers never yield in
advance (no hidden decisions), brake at most ACC_MAX = b_max, and follow a car once its centre is near their lane.

Frames, done here once: highway-env's y grows to the right and its headings clockwise, ours to the left and
anticlockwise; lane k of ours (centre k * lane_width) is highway-env's y = -k * lane_width. Its action is [acceleration,
steering] in [-1, 1], mapped linearly onto `acceleration_range` (m/s^2) and `steering_range` (rad).
"""
import copy
from dataclasses import dataclass

import numpy as np
from omegaconf import OmegaConf
from PIL import Image

from core import validate
from core.jobs import UserError, build, check_overrides, job_config, options
from data import outcomes
from data.scenarios import DenseScenario
from data.world import MEMORY, Road, collided, remembered_xy

try:
    import gymnasium as gym
    from highway_env.envs.common.abstract import AbstractEnv
    from highway_env.envs.common.observation import ObservationType
    from highway_env.road.lane import LineType, StraightLane
    from highway_env.road.road import Road as HighwayRoad
    from highway_env.road.road import RoadNetwork
    from highway_env.vehicle.behavior import IDMVehicle
    from highway_env.vehicle.kinematics import Vehicle
except ImportError as e:  # an optional extra: one line naming it, where a highway scenario or the env is asked for
    raise UserError(f"highway-env is not installed ({e.name} missing): pip install -e '.[highway]'") from None

ENV_ID = "admm-nnmpc/DenseMerge-v0"
MAX_SIMULATION_HZ = 1000  # highway-env's sub-steps per second, each moving every car: 15 by default
ENV_CHECKS = {  # the env's own config (validate's rules; the scenario's are validate.SCENARIO), sizes bounded as the planner's
    "simulation_frequency": validate.Int(1, MAX_SIMULATION_HZ), "policy_frequency": validate.Int(1),
    "duration": validate.Int(1, validate.MAX_STEPS),  # decisions, as the planner's max_steps
    "observation.vehicles_count": validate.Int(1, validate.MAX_SLOTS + 1, optional=True),  # the ego and a window's cars
    "observation.view": validate.Real(0, lo_open=True, optional=True), "speed_limit": validate.POS,
}
ACTION_CHECKS = {"action.type": validate.OneOf(("ContinuousAction",)), "action.acceleration_range": validate.Range(strict=True),
                 "action.steering_range": validate.Range(strict=True)}  # m/s^2 and rad, onto [-1, 1]


def check_action(action) -> None:
    """One UserError unless `action` is a ContinuousAction config whose acceleration_range (m/s^2) and steering_range
    (rad) are each [low, high], low < high."""
    if not isinstance(action, dict):
        raise UserError(f"action={action!r}: {ENV_ID}'s action config is a dict of type ContinuousAction, acceleration_range "
                        "and steering_range")
    plain = {k: list(v) if isinstance(v, (list, tuple, np.ndarray)) else v for k, v in action.items()
             if f"action.{k}" in ACTION_CHECKS}  # highway-env's other keys (clip, speed_range) are its to check
    validate.check(OmegaConf.create({"action": plain}), ACTION_CHECKS)


def to_ours(states_hw) -> np.ndarray:
    """highway-env states (M, 4) [x, y, heading, speed] -> ours [x, y, psi, v] (m, m, rad, m/s)."""
    z = np.array(states_hw, dtype=float).reshape(-1, 4)
    z[:, 1:3] *= -1.0
    return z


def to_action(u, acceleration_range, steering_range) -> np.ndarray:
    """Our control [delta (rad), a (m/s^2)] -> highway-env's ContinuousAction [acceleration, steering] in [-1, 1]."""
    unit = lambda v, lo_hi: 2.0 * (v - lo_hi[0]) / (lo_hi[1] - lo_hi[0]) - 1.0
    return np.clip([unit(u[1], acceleration_range), unit(-u[0], steering_range)], -1.0, 1.0).astype(np.float32)


def from_action(action, acceleration_range, steering_range) -> np.ndarray:
    """highway-env's [acceleration, steering] in [-1, 1] -> our [delta (rad), a (m/s^2)] (to_action's inverse)."""
    real = lambda v, lo_hi: lo_hi[0] + (v + 1.0) * (lo_hi[1] - lo_hi[0]) / 2.0
    return np.array([-real(action[1], steering_range), real(action[0], acceleration_range)])


class Ego(Vehicle):
    """The ego: highway-env's kinematic bicycle, stopping instead of reversing."""

    def step(self, dt):
        """Propagate dt (s); a braking command stops the car and holds it at 0 m/s."""
        super().step(dt)
        self.speed = max(self.speed, 0.0)


class StatesObservation(ObservationType):
    """Absolute states of the ego and every car within `view` metres, highway-env's frame: rows [present, id, x (m),
    y (m), heading (rad), speed (m/s)], the ego first, then by id; absent rows zero."""

    def __init__(self, env, vehicles_count=24, view=60.0, **_):
        super().__init__(env)
        self.vehicles_count, self.view = vehicles_count, view

    def space(self):
        """Box (vehicles_count, 6)."""
        return gym.spaces.Box(-np.inf, np.inf, (self.vehicles_count, 6), np.float64)

    def observe(self):
        """The rows of the ego and the cars in view."""
        out = np.zeros((self.vehicles_count, 6))
        ego = self.env.vehicle
        seen = [v for v in self.env.road.vehicles if v is ego or np.linalg.norm(v.position - ego.position) <= self.view]
        for row, v in zip(out, sorted(seen, key=lambda v: v.car_id)):
            row[:] = [1.0, v.car_id, *v.position, v.heading, v.speed]
        return out


class DenseMergeEnv(AbstractEnv):
    """The dense merge in highway-env: the scenario's start (config `scenario`: a data.scenarios.DenseScenario or a
    conf/scenario name with `overrides`), highway-env's vehicles from there; `reset(seed=k)` draws world k."""

    def __init__(self, config=None, render_mode=None):
        """highway-env's env; a render mode it has no renderer for is one UserError (its own check is a bare assert)."""
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise UserError(f"render_mode={render_mode!r}: {ENV_ID} renders {' or '.join(map(repr, self.metadata['render_modes']))}"
                            " (or None: no rendering)")
        super().__init__(config, render_mode)

    @classmethod
    def default_config(cls) -> dict:
        """highway-env's defaults with this merge's: the scenario, 5 Hz decisions over 15 Hz simulation, continuous
        actions, absolute observations."""
        cfg = super().default_config()
        cfg.update({
            "scenario": "highway", "overrides": [],
            "observation": {"type": "States", "vehicles_count": 24, "view": 60.0},
            "action": {"type": "ContinuousAction", "acceleration_range": [-5.0, 5.0], "steering_range": [-np.pi / 4, np.pi / 4],
                       "clip": True},
            "simulation_frequency": 15, "policy_frequency": 5, "duration": 60,  # steps of 1 / policy_frequency
            "speed_limit": 40.0,  # m/s: far above any desired speed, so only the drivers' own v0 sets their pace
            "screen_width": 900, "screen_height": 180, "scaling": 6.0, "centering_position": [0.35, 0.5],
        })
        return cfg

    def check(self):
        """One UserError for a config value this merge cannot honour."""
        c = self.config
        plain = {k: c[k] for k in ("simulation_frequency", "policy_frequency", "duration", "speed_limit")}
        if not isinstance(c["observation"], dict):
            raise UserError(f"observation={c['observation']!r}: {ENV_ID}'s observation config is a dict of type States, "
                            "vehicles_count and view")
        validate.check(OmegaConf.create({**plain, "observation": dict(c["observation"])}), ENV_CHECKS)
        check_action(c["action"])
        if c["simulation_frequency"] % c["policy_frequency"]:
            raise UserError(f"policy_frequency={c['policy_frequency']}: must divide simulation_frequency={c['simulation_frequency']}")

    def define_spaces(self):
        """highway-env's action space; our observation (its factory knows only its own types)."""
        self.check()
        obs_cfg = self.config["observation"]
        self.config["observation"] = {"type": "Kinematics"}
        super().define_spaces()
        self.config["observation"] = obs_cfg
        if obs_cfg.get("type") != "States":
            raise UserError(f"observation.type={obs_cfg.get('type')}: {ENV_ID} observes absolute states (type States)")
        self.observation_type = StatesObservation(self, **obs_cfg)
        self.observation_space = self.observation_type.space()

    def step(self, action):
        """highway-env's step of an action [acceleration, steering]: two finite numbers (in [-1, 1]; beyond, clipped
        when action.clip); anything else is one UserError."""
        try:
            a = np.asarray(action, dtype=float)
        except (TypeError, ValueError):
            a = np.zeros(0)
        if a.shape != (2,) or not np.isfinite(a).all():
            raise UserError(f"action {repr(action)[:80]}: {ENV_ID} takes [acceleration, "
                            "steering], two finite numbers in [-1, 1]")
        return super().step(a)

    def reset(self, *, seed=None, options=None):
        """Draw world `seed` of the scenario (None: one from the env's generator); (observation, info)."""
        self.world_seed = seed
        return super().reset(seed=seed, options=options)

    def scenario(self) -> DenseScenario:
        """The scenario object of config `scenario` (built from conf/scenario/ when a name is given, with `overrides`, a
        list of Hydra overrides of it such as ["scenario.x_ref=300"]; checked as the planner command checks them)."""
        sc = self.config["scenario"]
        if isinstance(sc, str):
            if sc not in options("scenario"):
                raise UserError(f"scenario={sc}: unknown; choose one of {', '.join(options('scenario'))}")
            overrides = self.config["overrides"]
            if not isinstance(overrides, (list, tuple)) or not all(isinstance(o, str) for o in overrides):
                raise UserError(f"overrides={overrides!r}: a list of overrides of the scenario, such as ['scenario.x_ref=300']")
            outside = [o for o in overrides if not o.lstrip("+~").startswith("scenario.")]
            if outside:  # Hydra's own line names no scope ("No match in the defaults list")
                raise UserError(f"overrides={outside}: {ENV_ID} takes overrides of the scenario only (scenario.<key>=...); "
                                "the planner's go to planner.gym_policy.MergePolicy")
            check_overrides(f"scenario/{sc}", overrides)
            cfg = job_config(f"scenario/{sc}", overrides)
            validate.check(cfg, validate.SCENARIO)
            sc = self.config["scenario"] = build(cfg.scenario)
        if not isinstance(sc, DenseScenario):
            raise UserError(f"scenario={getattr(sc, 'name', sc)}: {ENV_ID} needs a dense scenario (a stream beside the ego)")
        return sc

    def _reset(self):
        sc = self.scenario()
        seed = self.world_seed if self.world_seed is not None else int(self.np_random.integers(2**31))
        start = DenseScenario.make_world(sc, seed)  # our draw of the start: states and drivers, not its dynamics
        self.ours = start.road
        self.b_imposed, self.merged, self.paid = 0.0, False, False
        self._make_road(start.road, sc.x_ref)
        self._make_vehicles(start.states(), start.drivers, start.lane_change, sc.b_max)

    def _make_road(self, road: Road, x_ref):
        """Straight lanes of `road`, ours lane k at highway-env y = -k * lane_width; the ego's (lane 0) ends at x_ref."""
        net, length = RoadNetwork(), x_ref + 2000.0
        c, s, n = LineType.CONTINUOUS_LINE, LineType.STRIPED, LineType.NONE
        for k in range(road.lanes):
            y = -road.centre(k)
            lines = [s if k < road.lanes - 1 else c, c if k == 0 else n]
            end = x_ref if k == 0 else length
            net.add_lane("a", "b", StraightLane([-1000.0, y], [end, y], line_types=lines, width=road.lane_width,
                                                speed_limit=self.config["speed_limit"]))
        self.road = HighwayRoad(network=net, np_random=self.np_random, record_history=False)

    def _make_vehicles(self, z, drivers, lane_change, b_max):
        """The ego and one IDM vehicle per driver at our states z (M, 4), each with that driver's parameters."""
        z = to_ours(z)  # ours -> highway-env is the same sign flip
        self.vehicle = Ego(self.road, z[0, :2], z[0, 2], z[0, 3])
        self.vehicle.car_id = 0
        self.road.vehicles.append(self.vehicle)
        for i, (state, d) in enumerate(zip(z[1:], drivers), start=1):
            v = IDMVehicle(self.road, state[:2], state[2], state[3], target_speed=d.v0, enable_lane_change=lane_change)
            v.car_id = i
            v.TIME_WANTED, v.DISTANCE_WANTED, v.DELTA = d.T, d.s0 + Vehicle.LENGTH, d.delta
            v.COMFORT_ACC_MAX, v.COMFORT_ACC_MIN, v.ACC_MAX = d.a_max, -d.b, b_max
            v.LENGTH, v.WIDTH = Vehicle.LENGTH, Vehicle.WIDTH
            self.road.vehicles.append(v)
        self.ego_lane = self.road.network.get_closest_lane_index(self.vehicle.position)

    def states(self) -> np.ndarray:
        """Every car's state (M, 4) in our frame, by id."""
        return to_ours([[*v.position, v.heading, v.speed] for v in sorted(self.road.vehicles, key=lambda v: v.car_id)])

    def _simulate(self, action=None):
        """highway-env's sub-steps of one decision, then the braking they imposed on the others (m/s^2), for `info`."""
        before = self.states()
        super()._simulate(action)
        z, sc = self.states(), self.scenario()
        self.b_imposed = max(self.b_imposed, outcomes.b_imposed_max([before, z], 1.0 / self.config["policy_frequency"]))
        self.merged = self.merged or bool(abs(z[0, 1] - sc.y_ref) <= sc.merge_tol and z[0, 0] < sc.x_ref)

    def _info(self, obs, action=None) -> dict:
        """highway-env's info with ours: merged, crashed, b_imposed_max (m/s^2, so far), courteous."""
        return {"speed": self.vehicle.speed, "crashed": self.vehicle.crashed, "merged": self.merged,
                "b_imposed_max": self.b_imposed, "courteous": self.courteous()}

    def courteous(self) -> bool:
        """Merged before the lane's end, no crash, nobody made to brake harder than b_safe so far."""
        return self.merged and not self.vehicle.crashed and self.b_imposed <= self.scenario().b_safe

    def _reward(self, action) -> float:
        """1 on the step the merge completes courteously, -1 on a later step that makes it not courteous (a crash, braking
        imposed beyond b_safe), else 0: the return is the benchmark's success at the episode's end, not a shaping term."""
        now = self.courteous()
        pay, self.paid = float(now) - float(self.paid), now
        return pay

    def _is_terminated(self) -> bool:
        """A crash, or the ego past the end of its lane (merged or not: the episode's question is answered)."""
        return bool(self.vehicle.crashed or self.vehicle.position[0] >= self.scenario().x_ref)

    def _is_truncated(self) -> bool:
        return self.steps >= self.config["duration"] * self.config["simulation_frequency"] // self.config["policy_frequency"]


def register() -> None:
    """Register ENV_ID with gymnasium (once), its time limit the default config's duration (decisions). gymnasium 1.x has
    no plugin entry points: `gymnasium.make("data.highway:admm-nnmpc/DenseMerge-v0")` imports this module first."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="data.highway:DenseMergeEnv", max_episode_steps=DenseMergeEnv.default_config()["duration"])


register()


class HighwayWorld:
    """A DenseMergeEnv behind data.protocol.World: our frame and units, collisions by the same body-overlap test as
    ours, the ego driven through the env's own action mapping."""

    hidden_decisions = False  # highway-env's drivers decide nothing in advance

    def __init__(self, env: DenseMergeEnv, params):
        self.env, self.params = env, params
        self.road = env.ours
        self.collisions = []
        self.seen = [env.states()]

    @property
    def yielding(self) -> np.ndarray:
        """Nobody yields in advance in highway-env (M,)."""
        return np.zeros(len(self.seen[-1]), bool)

    @property
    def shown(self) -> np.ndarray:
        """Nobody shows a decision to yield in highway-env (M,)."""
        return self.yielding

    @property
    def t(self) -> float:
        """Time since the start (s)."""
        return float(self.env.time)

    def states(self) -> np.ndarray:
        """Every car's [x, y, psi, v] (M, 4), the ego first."""
        return self.env.states()

    def past_xy(self, steps) -> np.ndarray:
        """xy (steps, M, 2), newest last; before t = 0 at constant velocity."""
        return remembered_xy(self.seen, steps, self.params.dt)

    def _act(self, ego_u):
        """One env step with the ego applying [delta (rad), a (m/s^2)] through the env's action mapping."""
        a = self.env.config["action"]
        self.env.step(to_action(ego_u, a["acceleration_range"], a["steering_range"]))

    def step(self, ego_u) -> list:
        """Advance dt with the ego applying [delta (rad), a (m/s^2)]; the pairs that collided."""
        self._act(ego_u)
        return self._advance()

    def step_to(self, ego_z) -> list:
        """Advance dt with the others driving and the ego then put at ego_z (4,)."""
        self._act(np.zeros(2))
        x, y, psi, v = ego_z
        ego = self.env.vehicle
        ego.position, ego.heading, ego.speed = np.array([x, -y]), -psi, max(v, 0.0)
        return self._advance()

    def move(self, ego_u, others_xy) -> list:
        """Not available: highway-env's cars move only by their own drivers."""
        raise UserError("world=predictor moves the others by the predictor; highway-env's cars drive themselves: use world=reactive")

    def copy(self) -> "HighwayWorld":
        """An independent copy (a deep copy of the env: its vehicles, road and generator)."""
        return copy.deepcopy(self)

    def decisions(self) -> np.ndarray:
        """No hidden decisions: highway-env's drivers never yield in advance."""
        return self.yielding

    def seen_decisions(self) -> np.ndarray:
        """Nobody has shown a decision to yield (M,)."""
        return self.yielding

    def encroachments(self) -> np.ndarray:
        """No driver responds to encroachment in advance (M,): zeros."""
        return np.zeros(len(self.seen[-1]))

    def with_decisions(self, will_yield) -> "HighwayWorld":
        """A copy; only `nobody yields` is possible here."""
        if np.any(will_yield):
            raise UserError("highway-env's drivers never yield in advance: only will_yield all False exists there")
        return self.copy()

    def redrawn(self, rng) -> "HighwayWorld":
        """A copy: there is nothing hidden to re-draw."""
        return self.copy()

    def _advance(self) -> list:
        z = self.env.states()
        self.seen = self.seen[-MEMORY:] + [z]
        hits = collided(z, self.road)
        self.collisions += [(self.t, i, j) for i, j in hits]
        return hits


@dataclass(kw_only=True)
class HighwayScenario(DenseScenario):
    """The dense scenario's draw, driven in highway-env (its car size and axle distances in road and params)."""

    safety_stretch: float  # the planner's safety ellipse for these bodies: along-road semi-axis over R (conf/mpc reads
    # it as `stretch`, core.rollout.b_i; scenarios without it keep the paper's circle)
    lean_shape: dict  # the leaning steps' safety shape for these bodies and how deep it lets the ego lean: r, r_i, eps
    # (m), stretch, shape, psi_box (rad), lean (m); conf/mpc/courteous.yaml and its strategies read it
    predictor_moves = False  # highway-env's cars drive themselves (HighwayWorld.move)

    def make_world(self, seed: int) -> HighwayWorld:
        """World `seed`: our draw of the start, highway-env's vehicles from there."""
        env = DenseMergeEnv(config={"scenario": self})
        env.reset(seed=seed)
        return HighwayWorld(env, self.params)

    def render(self, seed: int, states, path):
        """A GIF at `path` of the episode `states` (T+1, M, 4) of world `seed`, drawn by highway-env's renderer."""
        env = DenseMergeEnv(config={"scenario": self}, render_mode="rgb_array")
        env.reset(seed=seed)
        frames = []
        for z in np.asarray(states):
            for v, zi in zip(sorted(env.road.vehicles, key=lambda v: v.car_id), to_ours(z)):  # the flip is its own inverse
                v.position, v.heading, v.speed = zi[:2].copy(), zi[2], zi[3]
            frames.append(Image.fromarray(env.render()))
        env.close()
        frames[0].save(path, save_all=True, append_images=frames[1:], duration=round(1000 * self.params.dt), loop=0)
        return path
