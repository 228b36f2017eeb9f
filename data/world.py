"""The merge world: bicycles on straight parallel lanes, the ego (index 0) and reactive IDM/MOBIL drivers."""
from dataclasses import dataclass, field

import numpy as np

from data import bicycle
from data.drivers import IDMDriver

MEMORY = 20  # past states kept for perception, enough for reaction delays up to 4 s at dt = 0.2 s
YIELD_LABEL = 0.1  # a driver whose response exceeds this counts as yielding in the dataset's hidden label (-)


@dataclass(frozen=True)
class Road:
    """Straight lanes along +x; lane k has its centre at y = k * lane_width (m). The ego starts in lane 0."""

    lanes: int = 2
    lane_width: float = 4.0
    car_length: float = 3.6
    car_width: float = 1.6

    def lane_of(self, y):
        """Index of the lane whose centre is nearest to lateral position y (m)."""
        return np.clip(np.rint(np.asarray(y) / self.lane_width), 0, self.lanes - 1).astype(int)

    def centre(self, lane):
        """Lateral position (m) of lane `lane`'s centre."""
        return lane * self.lane_width


def steer_to(z, y_target, p: bicycle.BicycleParams, k_y=0.6, k_psi=2.0, delta_max=0.5):
    """Lane-keeping steering (rad): heading set-point from the lateral error, then a heading loop."""
    _, y, psi, v = z
    psi_d = np.arctan(k_y * (y_target - y) / max(v, 1.0))
    return float(np.clip((p.l_f + p.l_r) * k_psi * (psi_d - psi) / max(v, 1.0), -delta_max, delta_max))


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


@dataclass
class World:
    """Mutable traffic state: z (SLOTS, 4) bicycle states, vehicle 0 the ego; drivers[j-1] drives vehicle j >= 1."""

    road: Road
    z: np.ndarray
    drivers: list
    will_yield: np.ndarray  # (SLOTS,) latched hidden decision per driver, drawn once per episode
    lane_change: bool = False  # MOBIL lane changes allowed (three-lane scenarios)
    params: bicycle.BicycleParams = field(default_factory=bicycle.BicycleParams)
    mobil_period: float = 1.0  # seconds between a driver's lane-change decisions
    t: float = 0.0
    target_lane: np.ndarray = None
    response: np.ndarray = None  # (SLOTS,) how far each yielding driver has blended into braking for the ego, 0..1
    yielding: np.ndarray = None  # (SLOTS,) whether each driver brakes for the ego at this step (response above YIELD_LABEL)
    seen: list = None  # past states z, newest last, from which drivers perceive the ego with their reaction delay
    collisions: list = field(default_factory=list)  # (time s, i, j) of every body overlap seen

    def __post_init__(self):
        m = len(self.z)
        self.z = np.asarray(self.z, dtype=float)
        if self.target_lane is None:
            self.target_lane = self.road.lane_of(self.z[:, 1])
        self.response = np.zeros(m)
        self.yielding = np.zeros(m, dtype=bool)
        self.seen = [self.z.copy()]

    @property
    def positions(self):
        """Current xy (M, 2) of every vehicle (m)."""
        return self.z[:, :2].copy()

    def driver(self, i) -> IDMDriver:
        """Driver of vehicle i; the ego gets a default IDM driver, used only to judge braking imposed on it."""
        return self.drivers[i - 1] if i > 0 else IDMDriver()

    def in_lane(self, lane):
        """Mask (SLOTS,) of vehicles occupying `lane`: nearest to its centre, or an other car changing into it."""
        mask = self.road.lane_of(self.z[:, 1]) == lane
        mask[1:] |= self.target_lane[1:] == lane
        return mask

    def leader(self, j, lane, exclude=()):
        """Index of the nearest vehicle ahead of vehicle j in `lane` (the ego included), or None."""
        occ = self.in_lane(lane)
        ahead = [i for i in range(len(self.z)) if i != j and i not in exclude and occ[i] and self.z[i, 0] > self.z[j, 0]]
        return min(ahead, key=lambda i: self.z[i, 0]) if ahead else None

    def follower(self, j, lane, exclude=()):
        """Index of the nearest vehicle behind vehicle j in `lane` (the ego included), or None."""
        occ = self.in_lane(lane)
        behind = [i for i in range(len(self.z)) if i != j and i not in exclude and occ[i] and self.z[i, 0] <= self.z[j, 0]]
        return max(behind, key=lambda i: self.z[i, 0]) if behind else None

    def idm_to(self, j, leader):
        """IDM acceleration (m/s^2) of vehicle j's driver behind vehicle `leader` (None: free road)."""
        d = self.driver(j)
        if leader is None:
            return d.acceleration(self.z[j, 3])
        gap = self.z[leader, 0] - self.z[j, 0] - self.road.car_length
        return d.acceleration(self.z[j, 3], gap, self.z[leader, 3])

    def perceived(self, j):
        """The state z (SLOTS, 4) driver j acts on: reaction_delay ago (the oldest recorded one early in an episode)."""
        back = int(round(self.drivers[j - 1].reaction_delay / self.params.dt))
        return self.seen[max(0, len(self.seen) - 1 - back)]

    def encroachment(self, j, z):
        """How far the ego encroaches on driver j's lane in state z, 0..1: depth past d_react (full after d_ramp)
        times how far it is ahead (full after x_ramp); 0 once it is in the lane (then it is a leader) or out of view."""
        d = self.drivers[j - 1]
        own = self.target_lane[j]
        dx = z[0, 0] - z[j, 0]
        if self.road.lane_of(z[0, 1]) == own or not dx < d.view:
            return 0.0
        depth = (d.d_react - abs(z[0, 1] - self.road.centre(own))) / d.d_ramp
        return float(np.clip(depth, 0.0, 1.0) * np.clip(dx / d.x_ramp, 0.0, 1.0))

    def respond(self):
        """Advance every yielding driver's response one step towards its perceived encroachment (first-order lag,
        time constant t_ramp); stubborn drivers keep 0."""
        for j in range(1, len(self.z)):
            d = self.drivers[j - 1]
            w = self.encroachment(j, self.perceived(j)) if self.will_yield[j] else 0.0
            self.response[j] += min(1.0, self.params.dt / d.t_ramp) * (w - self.response[j])
        self.yielding = self.response > YIELD_LABEL

    def acceleration(self, j):
        """Driver j's acceleration (m/s^2): IDM to its leader, blended by its response towards IDM behind the ego
        (projected into its lane, braking capped at b_yield) while the ego is ahead of it."""
        d = self.drivers[j - 1]
        lanes = {int(self.road.lane_of(self.z[j, 1])), int(self.target_lane[j])}  # both while changing lane
        a = min(self.idm_to(j, self.leader(j, lane)) for lane in lanes)
        if self.response[j] == 0.0:
            return a
        ahead = np.clip((self.z[0, 0] - self.z[j, 0]) / d.x_ramp, 0.0, 1.0)  # nothing to yield to once the ego is behind
        return a + self.response[j] * ahead * (min(a, max(self.idm_to(j, 0), -d.b_yield)) - a)

    def mobil(self, j, a_now):
        """The lane MOBIL picks for driver j: the lane to its left (away from the ego's lane) or its own.

        Cars only move left, as in the paper's three-lane scenario; the ego is a follower whose safety counts
        but whose acceleration change carries no politeness weight.
        """
        d = self.drivers[j - 1]
        lane, new = self.target_lane[j], self.target_lane[j] + 1
        if new >= self.road.lanes:
            return lane
        new_leader, new_f, old_f = self.leader(j, new), self.follower(j, new), self.follower(j, lane)
        if new_leader is not None and self.z[new_leader, 0] - self.z[j, 0] < 2 * self.road.car_length:
            return lane
        nf_gain = of_gain = 0.0
        if new_f is not None:
            nf_after = self.idm_to(new_f, j)
            if nf_after < -d.b_safe or self.z[j, 0] - self.z[new_f, 0] < 2 * self.road.car_length:
                return lane
            nf_gain = (nf_after - self.idm_to(new_f, self.leader(new_f, new))) if new_f > 0 else 0.0
        if old_f is not None and old_f > 0:
            of_gain = self.idm_to(old_f, self.leader(old_f, lane, exclude=(j,))) - self.idm_to(old_f, j)
        gain = self.idm_to(j, new_leader) - a_now + d.politeness * (nf_gain + of_gain)
        return new if gain > d.a_gain + d.a_bias else lane

    def step(self, ego_u, ego_z=None):
        """Advance dt: the ego applies ego_u = [delta, a], or with ego_z (4,) is put at that state instead (a planned
        path, for planner.gradients.WorldModel's copies); returns the indices pairs that collided this step."""
        p = self.params
        u = np.zeros((len(self.z), 2))
        u[0] = ego_u
        decide = self.lane_change and int(round(self.t / p.dt)) % max(1, int(round(self.mobil_period / p.dt))) == 0
        self.respond()
        for j in range(1, len(self.z)):
            a = self.acceleration(j)
            if decide and abs(self.z[j, 1] - self.road.centre(self.target_lane[j])) < 0.3:
                self.target_lane[j] = self.mobil(j, a)
            u[j] = [steer_to(self.z[j], self.road.centre(self.target_lane[j]), p), a]
        z_next = bicycle.step(self.z, u, p)
        z_next[1:, 3] = np.maximum(z_next[1:, 3], 0.0)  # human drivers stop, they do not reverse
        if ego_z is not None:
            z_next[0] = ego_z
        self.z = z_next
        self.t += p.dt
        self.seen = self.seen[-MEMORY:] + [z_next.copy()]
        hits = [(i, j) for i in range(len(self.z)) for j in range(i + 1, len(self.z)) if overlap(self.z[i], self.z[j], self.road)]
        self.collisions += [(self.t, i, j) for i, j in hits]
        return hits
