"""Merge scenarios: the ego in lane 0 must reach lane 1 before x_ref beside a dense platoon of four reactive cars."""
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from core.jobs import UserError
from data import bicycle
from data.drivers import COOPERATION, IDMDriver, cooperate, sample_driver
from data.world import Road, World


@dataclass(kw_only=True)  # keyword-only: a field whose value lives in conf/scenario/ has no default and may follow one that has
class Scenario:
    """A fixed scenario: road, the ego's start and the platoon (front to back) in lane 1, every number in SI units."""

    name: str
    road: Road
    x_ref: float  # the ego must be in the target lane before this x (m)
    v_ref: float  # the ego's reference speed (m/s)
    ego: dict  # start state {x, y, psi, v} (m, m, rad, m/s)
    platoon_x: float  # x of the platoon's front car (m)
    platoon_v: float  # initial speed of every platoon car (m/s)
    drivers: list  # per-car parameter dicts, front to back; missing keys take IDMDriver's defaults
    gap_factor: float  # initial bumper gaps = gap_factor x each follower's IDM equilibrium gap
    lane_change: bool  # others may change lanes (MOBIL); True in three-lane scenarios
    target_lane: int = 1
    params: bicycle.BicycleParams
    b_max: float  # the hardest any other car can brake (m/s^2)
    b_safe: float  # a merge is courteous when nobody brakes harder than this (m/s^2)
    merge_tol: float  # merged once the ego's centre is this close to the target lane's centre (m)
    cooperation: str  # the hidden willingness to yield: stubborn (nobody), mixed (each driver's own), willing (all)
    predictor_moves: ClassVar[bool] = True  # its worlds can put the others where a predictor says (world=predictor)

    def __post_init__(self):
        if self.b_safe > self.b_max:
            raise UserError(f"scenario.b_safe={self.b_safe} exceeds scenario.b_max={self.b_max}: no car can brake that hard")
        if self.cooperation not in COOPERATION:
            raise UserError(f"scenario.cooperation={self.cooperation}: must be one of {', '.join(COOPERATION)}")

    @property
    def y_ref(self):
        """Lateral reference (m): the target lane's centre."""
        return self.road.centre(self.target_lane)

    def sample(self, rng: np.random.Generator) -> dict:
        """What one episode starts from: road, lane changes, platoon speed, drivers, gap factor, ego start."""
        return dict(road=self.road, lane_change=self.lane_change, platoon_x=self.platoon_x, platoon_v=self.platoon_v,
                    drivers=[IDMDriver(**d) for d in self.drivers], gap_factor=self.gap_factor, ego=dict(self.ego))

    def render(self, seed: int, states, path):
        """A GIF of an episode by the world's own renderer, where it has one (highway-env); None here."""
        return None

    def make_world(self, seed: int) -> World:
        """A fresh world for one episode; the seed fixes sampled quantities and every hidden yield decision (drawn after
        everything else, Bernoulli(eta_coop) per driver: a cooperation level changes those alone)."""
        rng = np.random.default_rng(seed)
        e = self.sample(rng)
        road, v, drivers, ego = e["road"], e["platoon_v"], cooperate(e["drivers"], self.cooperation), e["ego"]
        xs = [e["platoon_x"]]
        for d in drivers[1:]:
            xs.append(xs[-1] - road.car_length - e["gap_factor"] * d.equilibrium_gap(v))
        y = road.centre(self.target_lane)
        z = [[ego["x"], ego["y"], ego.get("psi", 0.0), ego["v"]]] + [[x, y, 0.0, v] for x in xs]
        will_yield = np.concatenate([[False], rng.random(len(drivers)) < [d.eta_coop for d in drivers]])
        return World(road, np.array(z), drivers, will_yield, self.b_max, self.params, lane_change=e["lane_change"])


@dataclass(kw_only=True)
class RandomScenario(Scenario):
    """Seeded random scenarios for batch statistics and data: lanes, speeds, gaps, ego start and drivers all sampled."""

    lanes_choices: tuple
    speed_range: tuple  # platoon speed (m/s)
    gap_factor_range: tuple
    ego_offset_range: tuple  # ego x relative to the platoon's front car (m)
    ego_dv_range: tuple  # ego start speed relative to the platoon (m/s)
    v0_factor_range: tuple  # followers' desired speed / platoon speed
    driver_ranges: dict  # parameter name -> [low, high]
    followers: int  # cars behind the platoon's front car

    def stream(self, rng):
        """(lanes, platoon speed (m/s), drivers front to back): the front car's desired speed sets the platoon's pace."""
        lanes = int(rng.choice(self.lanes_choices))
        v = float(rng.uniform(*self.speed_range))
        drivers = [sample_driver(rng, self.driver_ranges, v0=v)]
        drivers += [sample_driver(rng, self.driver_ranges, v0=v * rng.uniform(*self.v0_factor_range))
                    for _ in range(self.followers)]
        return lanes, v, drivers

    def sample(self, rng):
        """Draw lanes, speed, drivers and ego start."""
        lanes, v, drivers = self.stream(rng)
        ego = {"x": self.platoon_x + rng.uniform(*self.ego_offset_range), "y": 0.0, "psi": 0.0,
               "v": max(0.5, v + rng.uniform(*self.ego_dv_range))}
        road = Road(lanes, self.road.lane_width, self.road.car_length, self.road.car_width)
        return dict(road=road, lane_change=lanes > 2, platoon_x=self.platoon_x, platoon_v=v, drivers=drivers,
                    gap_factor=float(rng.uniform(*self.gap_factor_range)), ego=ego)


@dataclass(kw_only=True)
class DenseScenario(RandomScenario):
    """Dense traffic: a target-lane stream too long to pass in front of or drop behind before the ego's lane ends at
    x_ref, the ego starting beside one of its middle cars; drivers, speed, gaps and lanes sampled as in `random`."""

    beside_range: tuple  # the stream car (1 = the front one) the ego starts beside, drawn uniformly
    min_behind_s: float  # the stream must reach further behind the ego than it drives in this time (s)

    def __post_init__(self):
        super().__post_init__()
        for v in self.speed_range:  # the shortest stream any seed can draw: tightest gaps, the ego beside its last car
            spacing = self.road.car_length + self.gap_factor_range[0] * (self.driver_ranges["s0"][0] + v * self.driver_ranges["T"][0])
            behind = (self.followers + 0.5 - self.beside_range[1]) * spacing
            if behind < self.min_behind_s * v:
                raise UserError(f"scenario.followers={self.followers}: the stream may reach only {behind:.0f} m behind the ego, "
                                f"less than the {self.min_behind_s * v:.0f} m it drives in min_behind_s={self.min_behind_s} s "
                                f"at {v} m/s; raise scenario.followers")

    def sample(self, rng):
        """Draw lanes, speed, drivers and gaps, then put the stream so that the ego is beside car k, within half a gap."""
        lanes, v, drivers = self.stream(rng)
        gap_factor = float(rng.uniform(*self.gap_factor_range))
        k = int(rng.integers(self.beside_range[0], self.beside_range[1] + 1))
        spacing = [self.road.car_length + gap_factor * d.equilibrium_gap(v) for d in drivers[1:]]
        x0 = self.ego["x"] + sum(spacing[: k - 1]) + rng.uniform(-0.5, 0.5) * spacing[k - 1]
        ego = {"x": self.ego["x"], "y": 0.0, "psi": 0.0, "v": max(0.5, v + rng.uniform(*self.ego_dv_range))}
        road = Road(lanes, self.road.lane_width, self.road.car_length, self.road.car_width)
        return dict(road=road, lane_change=lanes > 2, platoon_x=x0, platoon_v=v, drivers=drivers,
                    gap_factor=gap_factor, ego=ego)
