"""Driver behaviours of the other cars: IDM car following, yielding to an intruding ego, MOBIL lane changes."""
import math
from dataclasses import dataclass, replace

import numpy as np
from numba.extending import register_jitable


@register_jitable  # plain Python here, and compiled where a numba kernel calls it (planner.jit_interactive.chase)
def desired_gap(v, dv, T, s0, a_max, b):
    """IDM desired bumper gap s* (m) at speed v and approach rate dv = v - v_leader (m/s), scalars, with IDMDriver's
    parameters: builtins, as numpy costs microseconds per scalar and a world step asks this of every car."""
    return s0 + max(v * T + v * dv / (2.0 * math.sqrt(a_max * b)), 0.0)


@register_jitable
def idm(v, gap, v_lead, v0, T, s0, a_max, b, delta):
    """IDM acceleration (m/s^2) at speed v behind a leader `gap` metres ahead driving at v_lead (m/s); free road where
    gap is NaN; IDMDriver's parameters."""
    free = a_max * (1.0 - (max(v, 0.0) / v0) ** delta)
    if math.isnan(gap):
        return free
    return free - a_max * (desired_gap(v, v - v_lead, T, s0, a_max, b) / max(gap, 0.1)) ** 2


@dataclass(frozen=True)
class IDMDriver:
    """One driver's named parameters (SI units); `eta_coop` is hidden from observers and shows only in behaviour."""

    v0: float = 7.0  # desired speed (m/s)
    T: float = 0.4  # desired time headway (s)
    s0: float = 1.2  # minimum bumper-to-bumper gap (m)
    a_max: float = 2.0  # maximum acceleration (m/s^2)
    b: float = 2.0  # comfortable deceleration (m/s^2)
    delta: float = 4.0  # free-road acceleration exponent (-)
    eta_coop: float = 0.5  # probability of yielding to an ego that intrudes (-), latched once per episode
    d_react: float = 2.8  # ego-centre distance from this driver's lane centre where encroachment starts (m)
    d_ramp: float = 0.8  # encroachment depth beyond d_react at which the response is full (m)
    x_ramp: float = 1.0  # how far ahead of this car the ego must be for a full response (m)
    view: float = 20.0  # how far ahead an intruder is noticed (m)
    reaction_delay: float = 0.6  # perception-reaction time: the driver responds to where the ego was this long ago (s)
    t_ramp: float = 0.5  # time constant of the response following the perceived encroachment (s)
    b_yield: float = 2.5  # cap on braking while yielding (m/s^2)
    politeness: float = 0.3  # MOBIL weight on the other drivers' acceleration change (-)
    a_gain: float = 0.2  # MOBIL minimum own acceleration gain to change lane (m/s^2)
    a_bias: float = 1.5  # MOBIL keep-right bias: extra gain a move to the left must bring (m/s^2)
    b_safe: float = 2.0  # MOBIL largest braking a lane change may impose on the new follower (m/s^2)

    @property
    def following(self) -> tuple:
        """(v0, T, s0, a_max, b, delta): the parameters `idm` takes after v, gap and v_lead."""
        return self.v0, self.T, self.s0, self.a_max, self.b, self.delta

    def desired_gap(self, v, dv):
        """IDM desired bumper gap s* (m) at speed v and approach rate dv = v - v_leader (m/s), scalars."""
        return desired_gap(v, dv, self.T, self.s0, self.a_max, self.b)

    def acceleration(self, v, gap=None, v_lead=None):
        """IDM acceleration (m/s^2) behind a leader `gap` metres ahead driving at v_lead; free road if gap is None."""
        return idm(v, math.nan if gap is None else gap, v_lead, self.v0, self.T, self.s0, self.a_max, self.b, self.delta)

    def equilibrium_gap(self, v):
        """Bumper gap (m) at which this driver follows a leader steadily at speed v (< v0)."""
        return self.desired_gap(v, 0.0) / np.sqrt(1.0 - (v / self.v0) ** self.delta)


def sample_driver(rng: np.random.Generator, ranges: dict, **fixed) -> IDMDriver:
    """A driver with each parameter drawn uniformly from `ranges[name] = [low, high]`, then `fixed` values on top."""
    params = {k: float(rng.uniform(lo, hi)) for k, (lo, hi) in sorted(ranges.items())}
    params.update(fixed)
    return IDMDriver(**params)


COOPERATION = {"stubborn": 0.0, "mixed": None, "willing": 1.0}  # scenario.cooperation: every driver's eta_coop, or None: each its own


def cooperate(drivers, level: str) -> list:
    """`drivers` with the hidden willingness of cooperation `level` (COOPERATION): stubborn sets every eta_coop to 0 (nobody
    yields), willing to 1 (everybody yields to an intruding ego), mixed keeps each driver's own (in random and dense
    scenarios drawn uniformly in driver_ranges.eta_coop, [0, 1])."""
    eta = COOPERATION[level]
    return list(drivers) if eta is None else [replace(d, eta_coop=eta) for d in drivers]
