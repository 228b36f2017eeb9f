"""The perception boundary: what a predictor and a safety check see of a world at one moment.

Slot rule: the predictor's n_slots slots hold the n_slots other cars whose centres are nearest the ego's now (ties by
id), placed in id order (scenarios number cars front to back at the start), the ego in slot 0; each slot carries that
car's own observed past, so slots may change between steps but a history never mixes cars. Dataset windows are cut by
the same rule (`slot_ids` at the window's last observed step).
"""
from typing import NamedTuple

import numpy as np

from data.protocol import World


class Seen(NamedTuple):
    """One observation: the predictor's history (T_obs, n_slots+1, 2) m with the ego in slot 0, the world ids in each slot
    (n_slots+1,), and the states (K, 4) of every other car within `radius` of the ego, for the safety check."""

    history: np.ndarray
    ids: np.ndarray
    nearby: np.ndarray


def slot_ids(z, n_slots: int) -> np.ndarray:
    """World ids (n_slots+1,) of the ego (0) and the n_slots other cars nearest it in states z (M, 4), in id order."""
    if n_slots > len(z) - 1:
        raise ValueError(f"n_slots={n_slots} but the world holds {len(z) - 1} other cars")
    d = np.hypot(*(np.asarray(z)[1:, :2] - np.asarray(z)[0, :2]).T)
    nearest = np.sort(np.argsort(d, kind="stable")[:n_slots] + 1)
    return np.concatenate([[0], nearest])


def observe(world: World, n_slots: int, T_obs: int, radius: float = 50.0) -> Seen:
    """What the planner sees of `world` now: see Seen; n_slots from the config or the predictor's metadata."""
    z = world.states()
    ids = slot_ids(z, n_slots)
    near = np.hypot(*(z[1:, :2] - z[0, :2]).T) <= radius
    return Seen(world.past_xy(T_obs)[:, ids], ids, z[1:][near])
