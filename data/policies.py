"""Exploratory ego behaviours for the dataset: keep lane, or probe (nudge) the target lane, then commit or abort."""
from dataclasses import dataclass

import numpy as np

from data.drivers import IDMDriver
from data.protocol import World
from data.world import steer_to


def follow(world: World) -> float:
    """IDM acceleration (m/s^2, a default driver's) of the ego behind the nearest car ahead in its lane now: exploratory
    egos never drive into a car ahead on purpose."""
    z = world.states()
    lanes = world.road.lane_of(z[:, 1])
    ahead = np.flatnonzero((lanes[1:] == lanes[0]) & (z[1:, 0] > z[0, 0])) + 1
    if not len(ahead):
        return IDMDriver().acceleration(z[0, 3])
    j = ahead[np.argmin(z[ahead, 0])]
    return IDMDriver().acceleration(z[0, 3], z[j, 0] - z[0, 0] - world.road.car_length, z[j, 3])


REACHED = 0.15  # a probe has arrived once the ego is this close to y_nudge (m)
APPROACH_MAX = 4.0  # or this long after the probe began (s), whichever is first


@dataclass
class ProbePolicy:
    """Cruise, nudge to y_nudge and hold it, then merge if the gap is open (or if reckless), else back off and retry."""

    y_ref: float  # target lane centre (m)
    keep_lane: bool = False  # never leave the start lane
    t_start: float = 1.0  # first probe starts (s)
    y_nudge: float = 1.4  # lateral position held while probing (m)
    hold: float = 2.0  # time held within REACHED of y_nudge before deciding (s): long enough for a yielder to show
    # its braking (reaction delay and response lag), counted from arrival as the lean itself takes 1-3 s
    retry_after: float = 1.5  # wait after an abort (s)
    need_dx: float = 4.4  # longitudinal clearance to both target-lane neighbours that counts as an open gap (m)
    reckless: bool = False  # merge after the probe whatever the gap
    v_target: float = 5.0  # cruise speed (m/s)
    v_change_t: float = 1e9  # time the cruise speed changes (s)
    v_target2: float = 5.0  # cruise speed after v_change_t (m/s)
    align_gain: float = 0.0  # speed change per metre of offset from the gap's middle while probing (1/s)
    k_y: float = 0.8  # lateral gain of the steering law (1/s): how fast a probe leans in, and so how soon after the
    # first encroachment a yielder's braking can show
    a_bounds: tuple = (-3.0, 2.0)  # acceleration limits (m/s^2)
    phase: str = "cruise"
    phase_t: float = 0.0
    attempts: list = None  # (gap open at probe start, gap open at decision, committed) per probe

    def __post_init__(self):
        self.attempts = []
        self._open_at_start = False
        self._reached = None  # when this probe came within REACHED of y_nudge (s), None before

    def gap(self, world: World):
        """(clearance ahead, clearance behind, middle x) of the ego's slot among target-lane cars (m)."""
        lane, z = world.road.lane_of(self.y_ref), world.states()
        xs = z[1:, 0][world.road.lane_of(z[1:, 1]) == lane]
        x = z[0, 0]
        ahead, behind = xs[xs > x], xs[xs <= x]
        front = ahead.min() if len(ahead) else x + 50.0
        back = behind.max() if len(behind) else x - 50.0
        return front - x, x - back, 0.5 * (front + back)

    def is_open(self, world):
        """Whether the ego could merge now with `need_dx` clearance both ways."""
        ahead, behind, _ = self.gap(world)
        return ahead >= self.need_dx and behind >= self.need_dx

    def __call__(self, world: World):
        """Control [delta (rad), a (m/s^2)] for the ego now."""
        t = world.t
        z = world.states()[0]
        if self.phase == "cruise" and not self.keep_lane and t >= self.t_start:
            self.phase, self.phase_t, self._open_at_start = "probe", t, self.is_open(world)
        if self.phase == "probe" and self._reached is None and (abs(z[1] - self.y_nudge) <= REACHED
                                                                or t - self.phase_t >= APPROACH_MAX):
            self._reached = t
        if self.phase == "probe" and self._reached is not None and t - self._reached >= self.hold:
            opened = self.is_open(world)
            commit = opened or self.reckless
            self.attempts.append((self._open_at_start, opened, commit))
            self.phase, self.phase_t, self._reached = ("commit" if commit else "abort"), t, None
        elif self.phase == "abort" and t - self.phase_t >= self.retry_after:
            self.phase, self.phase_t, self._open_at_start = "probe", t, self.is_open(world)
        y_target = {"cruise": 0.0, "abort": 0.0, "probe": self.y_nudge, "commit": self.y_ref}[self.phase]
        v_des = self.v_target if t < self.v_change_t else self.v_target2
        if self.phase == "probe":
            v_des += self.align_gain * (self.gap(world)[2] - z[0])
        a = float(np.clip(min(1.0 * (v_des - z[3]), follow(world)), *self.a_bounds))
        return np.array([steer_to(z, y_target, world.params, k_y=self.k_y), a])


def sample_policy(rng: np.random.Generator, y_ref: float, v_platoon: float, ranges: dict) -> ProbePolicy:
    """A random exploratory policy; `ranges` holds [low, high] per numeric field and probabilities p_keep_lane, p_reckless."""
    r = {k: float(rng.uniform(*v)) for k, v in ranges.items() if not k.startswith("p_")}
    dv = r.pop("dv_cruise")
    dv2 = r.pop("dv_cruise2")
    return ProbePolicy(
        y_ref=y_ref,
        keep_lane=bool(rng.random() < ranges["p_keep_lane"]),
        reckless=bool(rng.random() < ranges["p_reckless"]),
        v_target=max(0.5, v_platoon + dv),
        v_target2=max(0.5, v_platoon + dv2),
        **r,
    )
