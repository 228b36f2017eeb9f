"""What an episode did to the others, from its states alone (any world): imposed braking, time to collision, courtesy.

b_safe = 4 m/s^2 is MOBIL's safe deceleration (Treiber & Kesting); a merge is courteous when it makes nobody brake
harder than that. Deceleration is read from the others' speed changes, so it is the same for every world and predictor.
"""
import numpy as np

from data.world import Road


def decelerations(states, dt):
    """Each other car's deceleration (T, M-1) in m/s^2 (positive when braking) from states (T+1, M, 4), step dt (s)."""
    states = np.asarray(states, dtype=float)
    return -np.diff(states[:, 1:, 3], axis=0) / dt


def b_imposed_max(states, dt):
    """The largest deceleration (m/s^2) of any other car over the episode; 0 when nobody braked."""
    b = decelerations(states, dt)
    return float(max(0.0, b.max(initial=0.0)))


def ttc(z, road: Road):
    """Smallest time to collision (s) between the ego and any car in its lane in states z (M, 4): bumper gap over closing
    speed where the two close in; 0 once the bodies touch along the lane; inf when nobody closes in."""
    z = np.asarray(z, dtype=float)
    same = np.flatnonzero(road.lane_of(z[1:, 1]) == road.lane_of(z[0, 1])) + 1
    out = np.inf
    for j in same:
        ahead = z[j, 0] >= z[0, 0]
        gap = abs(z[j, 0] - z[0, 0]) - road.car_length
        closing = (z[0, 3] - z[j, 3]) if ahead else (z[j, 3] - z[0, 3])
        if gap <= 0.0:
            return 0.0
        if closing > 0.0:
            out = min(out, gap / closing)
    return float(out)


def ttc_min(states, road: Road):
    """The smallest time to collision (s) over the episode's states (T+1, M, 4), see ttc."""
    return float(min(ttc(z, road) for z in states))


def courteous(merged, collision, b_imposed, b_safe):
    """1.0 for a courteous merge: merged, no collision, nobody made to brake harder than b_safe (m/s^2); else 0.0."""
    return float(bool(merged) and not bool(collision) and b_imposed <= b_safe)
