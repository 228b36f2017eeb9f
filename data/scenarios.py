"""Merge scenarios: the ego in lane 0 must reach lane 1 before x_ref beside a dense platoon of four reactive cars."""
from dataclasses import dataclass, field

import numpy as np

from data import bicycle
from data.drivers import IDMDriver, sample_driver
from data.world import Road, World


@dataclass
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
    gap_factor: float = 1.0  # initial bumper gaps = gap_factor x each follower's IDM equilibrium gap
    lane_change: bool = False  # others may change lanes (MOBIL); True in three-lane scenarios
    target_lane: int = 1
    params: bicycle.BicycleParams = field(default_factory=bicycle.BicycleParams)

    @property
    def y_ref(self):
        """Lateral reference (m): the target lane's centre."""
        return self.road.centre(self.target_lane)

    def sample(self, rng: np.random.Generator) -> dict:
        """What one episode starts from: road, lane changes, platoon speed, drivers, gap factor, ego start."""
        return dict(road=self.road, lane_change=self.lane_change, platoon_v=self.platoon_v,
                    drivers=[IDMDriver(**d) for d in self.drivers], gap_factor=self.gap_factor, ego=dict(self.ego))

    def make_world(self, seed: int) -> World:
        """A fresh world for one episode; the seed fixes sampled quantities and every hidden yield decision."""
        rng = np.random.default_rng(seed)
        e = self.sample(rng)
        road, v, drivers, ego = e["road"], e["platoon_v"], e["drivers"], e["ego"]
        xs = [self.platoon_x]
        for d in drivers[1:]:
            xs.append(xs[-1] - road.car_length - e["gap_factor"] * d.equilibrium_gap(v))
        y = road.centre(self.target_lane)
        z = [[ego["x"], ego["y"], ego.get("psi", 0.0), ego["v"]]] + [[x, y, 0.0, v] for x in xs]
        will_yield = np.concatenate([[False], rng.random(len(drivers)) < [d.eta_coop for d in drivers]])
        return World(road, np.array(z), drivers, will_yield, e["lane_change"], self.params)


@dataclass
class RandomScenario(Scenario):
    """Seeded random scenarios for batch statistics and data: lanes, speeds, gaps, ego start and drivers all sampled."""

    lanes_choices: tuple = (2, 3)
    speed_range: tuple = (3.5, 5.5)  # platoon speed (m/s)
    gap_factor_range: tuple = (0.85, 1.1)
    ego_offset_range: tuple = (-14.0, 6.0)  # ego x relative to the platoon's front car (m)
    ego_dv_range: tuple = (-1.0, 1.0)  # ego start speed relative to the platoon (m/s)
    v0_factor_range: tuple = (1.3, 1.6)  # followers' desired speed / platoon speed
    driver_ranges: dict = field(default_factory=dict)  # parameter name -> [low, high]

    def sample(self, rng):
        """Draw lanes, speed, drivers and ego start; the front car's desired speed sets the platoon's pace."""
        lanes = int(rng.choice(self.lanes_choices))
        v = float(rng.uniform(*self.speed_range))
        drivers = [sample_driver(rng, self.driver_ranges, v0=v)]
        drivers += [sample_driver(rng, self.driver_ranges, v0=v * rng.uniform(*self.v0_factor_range)) for _ in range(3)]
        ego = {"x": self.platoon_x + rng.uniform(*self.ego_offset_range), "y": 0.0, "psi": 0.0,
               "v": max(0.5, v + rng.uniform(*self.ego_dv_range))}
        road = Road(lanes, self.road.lane_width, self.road.car_length, self.road.car_width)
        return dict(road=road, lane_change=lanes > 2, platoon_v=v, drivers=drivers,
                    gap_factor=float(rng.uniform(*self.gap_factor_range)), ego=ego)
