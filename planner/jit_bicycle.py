"""The planner's own bicycle rollouts compiled (numba): a plan's states from its controls (`simulate`, behind
planner.mpc.simulate) and the plans that hold a lane at an acceleration (`lane_plans`, behind planner.mpc.lane_plans).
Every step checks, falls back and judges its plans by these; in numpy they were ~100 us a plan, a tenth of a compiled
paper step (18 calls of data.bicycle.step on one car each).

data.bicycle.step stays the world's and the reference: the arithmetic is the same, in the same order, but numba's libm
atan, tan, sin and cos may differ from numpy's SIMD loops in the last bit, so the numbers agree to rounding
(tests/test_multistart.py)."""
import math
from typing import NamedTuple

import numpy as np
from numba import njit

from data.world import Steering, steer


@njit(cache=True)
def advance(z, d, a, l_f, l_r, dt):
    """data.bicycle.step for one car: its state z (4,) one step of dt (s) on under steering d (rad) and acceleration a
    (m/s^2), written into z; l_f, l_r (m) its axles' distances from the centre of mass."""
    x, y, psi, v = z[0], z[1], z[2], z[3]
    beta = math.atan(l_r / (l_f + l_r) * math.tan(d))
    z[0] = x + dt * v * math.cos(psi + beta)
    z[1] = y + dt * v * math.sin(psi + beta)
    z[2] = psi + dt * v / l_r * math.sin(beta)
    z[3] = v + dt * a


@njit(cache=True)
def simulate(z0, Delta, alpha, l_f, l_r, dt):
    """The states Z (n, 4H) that n plans' controls Delta, alpha (n, H) (rad, m/s^2) drive from z0 (4,), each plan
    alone."""
    n, H = Delta.shape
    Z = np.empty((n, 4 * H))
    for k in range(n):
        z = z0.copy()
        for t in range(H):
            advance(z, Delta[k, t], alpha[k, t], l_f, l_r, dt)
            Z[k, 4 * t:4 * t + 4] = z
    return Z


class Car(NamedTuple):
    """A planned ego as drive moves it: axles l_f, l_r (m) from the centre of mass, step dt (s), the acceleration box
    a_box (lo, hi) in m/s^2 and its steering law (data.world.Steering)."""

    l_f: float
    l_r: float
    dt: float
    a_box: tuple
    law: Steering


@njit(cache=True)
def drive(z, y_target, a, car):
    """One ego in state z (4,) (x, y m, psi rad, v m/s) one step on, written into z, steering to y_target (m) by its
    car's law and accelerating at a (m/s^2) within the box, never into reverse: its controls delta (rad), a (m/s^2)."""
    d = steer(z[1], z[2], z[3], y_target, car.l_f + car.l_r, car.law)
    a = max(min(max(a, car.a_box[0]), car.a_box[1]), -z[3] / car.dt)
    advance(z, d, a, car.l_f, car.l_r, car.dt)
    return d, a


@njit(cache=True)
def lane_plans(z0, lane_y, accels, H, car):
    """planner.mpc.lane_plans' plans from z0 (4,): Delta, alpha (n, H) and Z (n, 4H) of n plans steering to lane_y (m)
    by the car's law at the accelerations accels (n,) (m/s^2, already in the box), never below the stop -v/dt."""
    n = len(accels)
    Delta, alpha, Z = np.empty((n, H)), np.empty((n, H)), np.empty((n, 4 * H))
    for k in range(n):
        z = z0.copy()
        for t in range(H):
            Delta[k, t] = d = steer(z[1], z[2], z[3], lane_y, car.l_f + car.l_r, car.law)
            stop = -z[3] / car.dt
            alpha[k, t] = a = stop if stop > accels[k] else accels[k]
            advance(z, d, a, car.l_f, car.l_r, car.dt)
            Z[k, 4 * t:4 * t + 4] = z
    return Delta, alpha, Z
