"""What every world implements (ours in data.world, others later): the planner, the dataset, the benchmarks and the
tests reach a world only through these members and data.perception.observe."""
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class World(Protocol):
    """A traffic world one dt at a time: car 0 is the ego, cars keep their index (id) for the whole episode.

    Made from a seed by its scenario (`scenario.make_world(seed)`); `road` (lanes, widths, car size in m), `params`
    (bicycle, dt in s), `t` (s), `collisions` [(t, i, j)], `yielding` (M,) bool (which drivers brake for the ego
    now), `shown` (M,) bool (whose yielding has visibly cut their acceleration so far; both dataset labels, never a
    planner's input) and `hidden_decisions` (whether its drivers decide in advance whether to yield, so that a run can
    be replayed with the decisions flipped) are read-only attributes.
    """

    def states(self) -> np.ndarray:
        """Every car's state (M, 4) = [x, y, psi, v] (m, m, rad, m/s), the ego first."""

    def past_xy(self, steps: int) -> np.ndarray:
        """xy (steps, M, 2) of the last `steps` steps, newest last (m), extrapolated at constant velocity before t = 0."""

    def step(self, ego_u) -> list:
        """Advance dt with the ego applying [delta (rad), a (m/s^2)]; the index pairs that collided."""

    def step_to(self, ego_z) -> list:
        """Advance dt with the ego put at the planned state ego_z (4,); the index pairs that collided."""

    def move(self, ego_u, others_xy) -> list:
        """Advance dt with the ego under ego_u and the others put at others_xy (M-1, 2) (world=predictor)."""

    def copy(self) -> "World":
        """An independent copy with the same hidden decisions."""

    def decisions(self) -> np.ndarray:
        """The hidden decisions to yield (M,): for benchmarks only."""

    def seen_decisions(self) -> np.ndarray:
        """The hidden decisions as far as the drivers have shown them (M,): for the knows=seen oracle only."""

    def encroachments(self) -> np.ndarray:
        """How far the ego encroaches on each driver's lane now (M,), 0..1: where a decision can start to show."""

    def with_decisions(self, will_yield) -> "World":
        """A copy with the hidden decisions to yield replaced by will_yield (M,)."""

    def redrawn(self, rng: np.random.Generator) -> "World":
        """A copy with the hidden decisions re-drawn from their prior."""
