"""The merge world: bicycles on straight parallel lanes, the ego (index 0) and reactive IDM/MOBIL drivers; the first
implementation of data.protocol.World."""
import bisect
import copy
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numba.extending import register_jitable

from data import bicycle
from data.drivers import IDMDriver

MEMORY = 20  # past states kept for perception, enough for reaction delays up to 4 s at dt = 0.2 s
YIELD_LABEL = 0.1  # a driver whose response exceeds this counts as yielding in the dataset's hidden label (-)
SHOWN_BRAKE = 0.3  # a driver has shown its decision once yielding takes this much off its acceleration (m/s^2)


@dataclass(frozen=True)
class Road:
    """Straight lanes along +x; lane k has its centre at y = k * lane_width (m). The ego starts in lane 0."""

    lanes: int
    lane_width: float
    car_length: float
    car_width: float

    def lane_of(self, y):
        """Index of the lane whose centre is nearest to lateral position y (m)."""
        lane = np.rint(np.asarray(y) / self.lane_width)
        return np.minimum(np.maximum(lane, 0), self.lanes - 1).astype(int)  # np.clip, without its microseconds of wrapping

    def centre(self, lane):
        """Lateral position (m) of lane `lane`'s centre."""
        return lane * self.lane_width


def unit(x):
    """x clipped to [0, 1]: builtins, as np.clip costs microseconds per scalar in the per-car loop."""
    return min(max(float(x), 0.0), 1.0)


def backfill(z, steps, dt):
    """xy (steps, M, 2) ending at the xy of states z (M, 4), earlier steps driven backwards at constant velocity (m)."""
    heading = np.stack([np.cos(z[:, 2]), np.sin(z[:, 2])], -1)
    return np.stack([z[:, :2] - k * dt * z[:, 3:4] * heading for k in range(steps - 1, -1, -1)])


class Steering(NamedTuple):
    """A steering law's gains and bounds (steer): lateral gain k_y and heading gain k_psi (1/s), the heading set-point
    within psi_lo..psi_hi and the steering within delta_lo..delta_hi (rad)."""

    k_y: float = 0.6
    k_psi: float = 2.0
    psi_lo: float = -math.inf
    psi_hi: float = math.inf
    delta_lo: float = -0.5
    delta_hi: float = 0.5


@register_jitable  # numpy arrays here, scalars where a numba kernel calls it (planner.jit_interactive, jit_bicycle)
def steer(y, psi, v, y_target, wheelbase, law):
    """Lane-keeping steering (rad) of cars at lateral position y (m), heading psi (rad) and speed v (m/s) with
    wheelbase l_f + l_r (m) towards lateral positions y_target (m) by the Steering `law`: a heading set-point from the
    lateral error, then a heading loop, both with the gains as at 1 m/s below it."""
    v = np.maximum(v, 1.0)
    psi_d = np.minimum(np.maximum(np.arctan(law.k_y * (y_target - y) / v), law.psi_lo), law.psi_hi)
    return np.minimum(np.maximum(wheelbase * law.k_psi * (psi_d - psi) / v, law.delta_lo), law.delta_hi)  # np.clip


def steer_to(z, y_target, p: bicycle.BicycleParams, k_y=0.6, k_psi=2.0, delta_max=0.5):
    """steer for states z (..., 4) with |delta| <= delta_max (rad); a world steers all its cars in one call."""
    z = np.asarray(z, dtype=float)
    return steer(z[..., 1], z[..., 2], z[..., 3], y_target, p.l_f + p.l_r, Steering(k_y, k_psi, delta_lo=-delta_max,
                                                                                      delta_hi=delta_max))


def corners(z, road: Road):
    """Corners (4, 2) of the car body of state z (m)."""
    x, y, psi, _ = z
    c, s = np.cos(psi), np.sin(psi)
    hl, hw = road.car_length / 2, road.car_width / 2
    local = np.array([[hl, hw], [hl, -hw], [-hl, -hw], [-hl, hw]])
    return local @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def overlap(z1, z2, road: Road) -> bool:
    """Whether two car bodies intersect (separating-axis test on oriented rectangles)."""
    if np.hypot(z1[0] - z2[0], z1[1] - z2[1]) > np.hypot(road.car_length, road.car_width):
        return False
    c1, c2 = corners(z1, road), corners(z2, road)
    for psi in (z1[2], z2[2]):
        for axis in (np.array([np.cos(psi), np.sin(psi)]), np.array([-np.sin(psi), np.cos(psi)])):
            p1, p2 = c1 @ axis, c2 @ axis
            if p1.max() < p2.min() or p2.max() < p1.min():
                return False
    return True


def collided(z, road: Road) -> list:
    """Index pairs (i, j), i < j, whose bodies overlap in states z (M, 4); pairs further apart in x or in y than a body's
    diagonal are skipped before the exact test (overlap), which rejects every pair further apart than that."""
    reach = np.hypot(road.car_length, road.car_width)
    x, y = z[:, 0], z[:, 1]
    i, j = np.nonzero((np.abs(x[:, None] - x) <= reach) & (np.abs(y[:, None] - y) <= reach))
    return [(a, b) for a, b in zip(i.tolist(), j.tolist()) if a < b and overlap(z[a], z[b], road)]


def remembered_xy(seen, steps, dt) -> np.ndarray:
    """xy (steps, M, 2) of the last `steps` of the states `seen` (newest last), of which at most MEMORY + 1 are kept;
    before the first, every car is driven backwards at its initial heading and speed (constant velocity)."""
    if steps > MEMORY + 1:
        raise ValueError(f"a world remembers {MEMORY + 1} steps; {steps} asked")
    known = np.array([z[:, :2] for z in seen[-steps:]])
    if len(known) >= steps:
        return known
    return np.concatenate([backfill(seen[0], steps - len(known) + 1, dt)[:-1], known])


class Scene:
    """The states one step reads, fixed while its drivers decide: x and v (m, m/s) as Python floats and each car's
    nearest lane, computed once per step; per-car look-ups index these lists, as numpy scalars cost microseconds each.
    `order` caches each lane's occupants sorted by x (World.occupants) until a target lane changes."""

    def __init__(self, z, road: Road):
        self.x, self.y, self.v = z[:, 0].tolist(), z[:, 1].tolist(), z[:, 3].tolist()
        self.lanes = road.lane_of(z[:, 1])
        self.lane = self.lanes.tolist()
        self.order = {}


@dataclass
class World:
    """Mutable traffic state: z (SLOTS, 4) bicycle states, vehicle 0 the ego; drivers[j-1] drives vehicle j >= 1."""

    road: Road
    z: np.ndarray
    drivers: list
    will_yield: np.ndarray  # (M,) latched hidden decision per driver, drawn once per episode
    b_max: float  # the hardest any other car can brake (m/s^2): a cut-in with no room left ends in a collision
    params: bicycle.BicycleParams
    lane_change: bool = False  # MOBIL lane changes allowed (three-lane scenarios)
    mobil_period: float = 1.0  # seconds between a driver's lane-change decisions
    t: float = 0.0
    target_lane: np.ndarray = None
    response: np.ndarray = None  # (SLOTS,) how far each yielding driver has blended into braking for the ego, 0..1
    yielding: np.ndarray = None  # (SLOTS,) whether each driver brakes for the ego at this step (response above YIELD_LABEL)
    shown: np.ndarray = None  # (SLOTS,) whether each driver's yielding has cut its acceleration by SHOWN_BRAKE so far
    refused: np.ndarray = None  # (SLOTS,) whether each stubborn driver has kept an acceleration its yielding would have cut so
    seen: list = None  # past states z, newest last, from which drivers perceive the ego with their reaction delay
    hidden_decisions = True  # each driver's decision to yield is drawn before the episode and latched
    collisions: list = field(default_factory=list)  # (time s, i, j) of every body overlap seen
    _scene: Scene = None  # the current z as a step's drivers read it, built once per step rather than per car

    def __post_init__(self):
        m = len(self.z)
        self.z = np.asarray(self.z, dtype=float)
        if self.target_lane is None:
            self.target_lane = self.road.lane_of(self.z[:, 1])
        self.response = np.zeros(m)
        self.yielding = np.zeros(m, dtype=bool)
        self.shown = np.zeros(m, dtype=bool)
        self.refused = np.zeros(m, dtype=bool)
        self.seen = [self.z.copy()]

    @property
    def positions(self):
        """Current xy (M, 2) of every vehicle (m)."""
        return self.z[:, :2].copy()

    def driver(self, i) -> IDMDriver:
        """Driver of vehicle i; the ego gets a default IDM driver, used only to judge braking imposed on it."""
        return self.drivers[i - 1] if i > 0 else IDMDriver()

    def scene(self) -> Scene:
        """The current z as drivers read it: the step's own while it runs, else a fresh one (z may have been set)."""
        return self._scene if self._scene is not None else Scene(self.z, self.road)

    def in_lane(self, lane):
        """Mask (SLOTS,) of vehicles occupying `lane`: nearest to its centre, or an other car changing into it."""
        mask = self.scene().lanes == lane
        mask[1:] |= self.target_lane[1:] == lane
        return mask

    def occupants(self, lane) -> list:
        """(x (m), index) of every vehicle in `lane` (in_lane), sorted by x then index, which leader and follower bisect;
        a car at x NaN is left out, as no comparison of x counts it ahead or behind. Kept while the step's z and
        target lanes stand."""
        s = self.scene()
        if lane not in s.order:
            s.order[lane] = sorted((s.x[i], i) for i in np.flatnonzero(self.in_lane(lane)).tolist() if not math.isnan(s.x[i]))
        return s.order[lane]

    def leader(self, j, lane, exclude=()):
        """Index of the nearest vehicle ahead of vehicle j in `lane` (the ego included; of cars level in x the lowest
        index), or None."""
        cars, x = self.occupants(lane), self.scene().x[j]
        k = bisect.bisect_right(cars, (x, math.inf))  # the first car with x above vehicle j's: the nearest ahead
        while k < len(cars) and cars[k][1] in exclude:
            k += 1
        return cars[k][1] if k < len(cars) else None

    def follower(self, j, lane, exclude=()):
        """Index of the nearest vehicle behind vehicle j in `lane` (the ego included; level in x counts as behind, and
        of cars level in x the lowest index), or None."""
        cars, x = self.occupants(lane), self.scene().x[j]
        best = x_best = None
        for x_i, i in reversed(cars[:bisect.bisect_right(cars, (x, math.inf))]):  # x up to vehicle j's, nearest first
            if best is not None and x_i < x_best:  # past the nearest x: only lower indices level with it could follow
                break
            if i != j and i not in exclude:
                best, x_best = i, x_i
        return best

    def idm_to(self, j, leader):
        """IDM acceleration (m/s^2) of vehicle j's driver behind vehicle `leader` (None: free road)."""
        d, s = self.driver(j), self.scene()
        if leader is None:
            return d.acceleration(s.v[j])
        return d.acceleration(s.v[j], s.x[leader] - s.x[j] - self.road.car_length, s.v[leader])

    def perceived(self, j) -> int:
        """Index in `seen` of the state driver j acts on: reaction_delay ago (the oldest recorded one early on)."""
        back = int(round(self.drivers[j - 1].reaction_delay / self.params.dt))
        return max(0, len(self.seen) - 1 - back)

    def encroachment(self, j, z, ego_lane):
        """How far the ego, in lane `ego_lane` in state z, encroaches on driver j's lane, 0..1: depth past d_react (full
        after d_ramp) times how far it is ahead (full after x_ramp); 0 once it is in the lane (then it is a leader) or
        out of view."""
        d = self.drivers[j - 1]
        own = self.target_lane[j]
        dx = z[0, 0] - z[j, 0]
        if ego_lane == own or not dx < d.view:
            return 0.0
        depth = (d.d_react - abs(z[0, 1] - self.road.centre(own))) / d.d_ramp
        return float(unit(depth) * unit(dx / d.x_ramp))

    def encroachments(self) -> np.ndarray:
        """How far the ego encroaches on every driver's lane now (M,), 0..1 (`encroachment`; the ego's 0), whatever their
        decisions: where a decision to yield can start to show, for the dataset's labels, never for a driver."""
        ego_lane = int(self.road.lane_of(self.z[0, 1]))
        return np.array([0.0] + [self.encroachment(j, self.z, ego_lane) for j in range(1, len(self.z))])

    def respond(self):
        """Advance every driver's response one step towards its perceived encroachment (first-order lag, time constant
        t_ramp): the yielding a stubborn driver withholds too, which is what an observer sees it refuse."""
        w = np.zeros(len(self.z) - 1)
        ks = [self.perceived(j) for j in range(1, len(self.z))]
        ego_lanes = self.road.lane_of([self.seen[k][0, 1] for k in ks]).tolist()  # in one call, not one per driver
        for i, (k, ego_lane) in enumerate(zip(ks, ego_lanes)):
            w[i] = self.encroachment(i + 1, self.seen[k], ego_lane)
        rate = np.array([min(1.0, self.params.dt / d.t_ramp) for d in self.drivers])
        self.response[1:] += rate * (w - self.response[1:])
        self.yielding = (self.response > YIELD_LABEL) & self.will_yield

    def acceleration(self, j):
        """Driver j's acceleration (m/s^2): IDM to its leader, blended by its response towards IDM behind the ego
        (projected into its lane, braking capped at b_yield) while the ego is ahead of it."""
        d, s = self.drivers[j - 1], self.scene()
        low, high = sorted((s.lane[j], int(self.target_lane[j])))  # its lane and its target lane
        a = self.idm_to(j, self.leader(j, low))
        if high != low:  # changing lane: the harder of both (lower lane first: of equal values, 0.0 and -0.0, min keeps the first)
            a = min(a, self.idm_to(j, self.leader(j, high)))
        if self.response[j] == 0.0:
            return a
        ahead = unit((s.x[0] - s.x[j]) / d.x_ramp)  # nothing to yield to once the ego is behind
        yielded = a + self.response[j] * ahead * (min(a, max(self.idm_to(j, 0), -d.b_yield)) - a)
        if yielded < a - SHOWN_BRAKE:  # an observer can tell the decision, either way (latched; the oracles read it)
            (self.shown if self.will_yield[j] else self.refused)[j] = True
        return yielded if self.will_yield[j] else a

    def mobil(self, j, a_now):
        """The lane MOBIL picks for driver j: the lane to its left (away from the ego's lane) or its own.

        Cars only move left, as in the paper's three-lane scenario; the ego is a follower whose safety counts
        but whose acceleration change carries no politeness weight.
        """
        d = self.drivers[j - 1]
        lane, new = self.target_lane[j], self.target_lane[j] + 1
        if new >= self.road.lanes:
            return lane
        x = self.scene().x
        new_leader, new_f, old_f = self.leader(j, new), self.follower(j, new), self.follower(j, lane)
        if new_leader is not None and x[new_leader] - x[j] < 2 * self.road.car_length:
            return lane
        nf_gain = of_gain = 0.0
        if new_f is not None:
            nf_after = self.idm_to(new_f, j)
            if nf_after < -d.b_safe or x[j] - x[new_f] < 2 * self.road.car_length:
                return lane
            nf_gain = (nf_after - self.idm_to(new_f, self.leader(new_f, new))) if new_f > 0 else 0.0
        if old_f is not None and old_f > 0:
            of_gain = self.idm_to(old_f, self.leader(old_f, lane, exclude=(j,))) - self.idm_to(old_f, j)
        gain = self.idm_to(j, new_leader) - a_now + d.politeness * (nf_gain + of_gain)
        return new if gain > d.a_gain + d.a_bias else lane

    def states(self):
        """Every car's state z (M, 4) = [x, y, psi, v] (m, m, rad, m/s) now, the ego first; row i is car id i."""
        return self.z.copy()

    def copy(self) -> "World":
        """An independent copy: same drivers, same hidden decisions, same past (branches, the oracle, the ceiling).
        Only what a step or a caller writes is copied: road, params and drivers are frozen, and a remembered state is
        never written (a step appends a new one); a deepcopy took a millisecond, the oracle makes one per plan."""
        w = copy.copy(self)
        w.z, w.target_lane, w.response, w.yielding, w.shown, w.refused, w.will_yield = (
            a.copy() for a in (self.z, self.target_lane, self.response, self.yielding, self.shown, self.refused,
                               self.will_yield))
        w.drivers, w.seen, w.collisions = list(self.drivers), list(self.seen), list(self.collisions)
        return w

    def decisions(self):
        """The hidden, latched decisions to yield (M,) (the ego's always False): for benchmarks, never for a planner."""
        return self.will_yield.copy()

    def seen_decisions(self):
        """The hidden decisions as far as shown (M,): True for a driver whose yielding has cut its acceleration by
        SHOWN_BRAKE at some step, False for every other (undecided or stubborn): the knows=seen oracle's, never a
        planner's."""
        return self.will_yield & self.shown

    def decided(self):
        """Whose decision an observer can tell now (M,): a yielder once its yielding has cut its acceleration by
        SHOWN_BRAKE (shown), a stubborn driver once it has kept an acceleration its yielding would have cut as much
        (refused): the knows=prior oracle's, never a planner's."""
        return self.shown | self.refused

    def with_decisions(self, will_yield) -> "World":
        """A copy whose hidden decisions to yield are `will_yield` (M,); the ego's stays False."""
        w = self.copy()
        w.will_yield = np.asarray(will_yield, dtype=bool).copy()
        w.will_yield[0] = False
        return w

    def redrawn(self, rng: np.random.Generator) -> "World":
        """A copy whose decisions to yield are re-drawn from their prior, Bernoulli(eta_coop) per driver."""
        return self.with_decisions(np.concatenate([[False], rng.random(len(self.drivers)) < [d.eta_coop for d in self.drivers]]))

    def step(self, ego_u, ego_z=None):
        """Advance dt: the ego applies ego_u = [delta, a], or with ego_z (4,) is put at that state instead (a planned
        path: `step_to`); returns the index pairs that collided this step."""
        p = self.params
        u = np.zeros((len(self.z), 2))
        u[0] = ego_u
        decide = self.lane_change and int(round(self.t / p.dt)) % max(1, int(round(self.mobil_period / p.dt))) == 0
        self.respond()
        s = self._scene = Scene(self.z, self.road)
        try:
            for j in range(1, len(self.z)):  # in index order: a lane change counts for the cars after it
                u[j, 1] = max(self.acceleration(j), -self.b_max)
                if decide and abs(s.y[j] - self.road.centre(self.target_lane[j])) < 0.3:
                    self.change_lane(j, self.mobil(j, u[j, 1]))
        finally:
            self._scene = None
        u[1:, 0] = steer_to(self.z[1:], self.road.centre(self.target_lane[1:]), p)
        z_next = bicycle.step(self.z, u, p)
        z_next[1:, 3] = np.maximum(z_next[1:, 3], 0.0)  # human drivers stop, they do not reverse
        if ego_z is not None:
            z_next[0] = ego_z
        return self._advance(z_next)

    def change_lane(self, j, lane):
        """Set driver j's target lane; a change moves it into `lane`'s occupants for the rest of the step."""
        if lane != self.target_lane[j]:
            self.target_lane[j] = lane
            self.scene().order.clear()

    def step_to(self, ego_z):
        """Advance dt with the others driving and the ego put at the planned state ego_z (4,); returns collided pairs."""
        return self.step(np.zeros(2), ego_z=np.asarray(ego_z, dtype=float))

    def move(self, ego_u, others_xy):
        """Advance dt with the ego on its bicycle under ego_u and every other car put at others_xy (M-1, 2), heading and
        speed from its displacement (world=predictor: the others follow a predictor, as in the paper)."""
        z = self.z.copy()
        moved = np.asarray(others_xy, dtype=float) - z[1:, :2]
        z[1:, 2] = np.where(np.hypot(*moved.T) > 1e-6, np.arctan2(moved[:, 1], moved[:, 0]), z[1:, 2])
        z[1:, 3] = np.hypot(*moved.T) / self.params.dt
        z[1:, :2] = others_xy
        z[0] = bicycle.step(self.z[0], ego_u, self.params)
        return self._advance(z)

    def _advance(self, z_next):
        """Take z_next as the state one dt on, remember it, record and return the pairs whose bodies overlap."""
        self.z = z_next
        self.t += self.params.dt
        self.seen = self.seen[-MEMORY:] + [z_next.copy()]
        hits = collided(self.z, self.road)
        self.collisions += [(self.t, i, j) for i, j in hits]
        return hits

    def past_xy(self, steps):
        """xy (steps, M, 2) of the last `steps` steps, newest last (m); before t = 0 every car is driven backwards at its
        initial heading and speed (constant velocity), as nothing was observed then."""
        return remembered_xy(self.seen, steps, self.params.dt)
