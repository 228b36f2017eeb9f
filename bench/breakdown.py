"""Where a planner falls short of the clairvoyant ceiling, world by world: each held-out episode against the ceiling's
result on the same world (bench/ceiling.py's CSV), in one of the classes of OUTCOMES.

    python -m bench.breakdown <episodes_admm_*.csv> <ceiling_*.csv> [b_safe m/s^2, default 4]
"""
import csv
import sys
from collections import Counter

SLOW = 1.3  # a courteous merge later than this many times the ceiling's counts as too slow
LOOP = 10  # fallbacks in an episode that never merged from which it counts as a fallback loop
OUTCOMES = {
    "courteous": "merged courteously, within 1.3x the ceiling's t_merge (or where the ceiling found no courteous merge)",
    "too slow": "merged courteously, later than 1.3x the ceiling's t_merge",
    "forced": "merged, but made another car brake harder than b_safe: the predicted braking misjudged",
    "collision": "collided",
    "fallback loop": f"never merged, with at least {LOOP} fallbacks",
    "ran out of road": "never merged: no gap taken before the lane ended",
}


def classify(episode: dict, world: dict, b_safe: float) -> str:
    """The OUTCOMES class of one episode (planner/batch.py's per-episode row) against the ceiling's row of its world."""
    if episode["collision"]:
        return "collision"
    if episode["merged"] and episode["b_imposed_max"] > b_safe:
        return "forced"
    if episode["merged"]:
        slow = world["ceiling_courteous"] and episode["t_merge"] > SLOW * world["ceiling_t_merge"]
        return "too slow" if slow else "courteous"
    return "fallback loop" if episode["fallbacks"] >= LOOP else "ran out of road"


def breakdown(episodes: list[dict], worlds: list[dict], b_safe: float) -> dict:
    """{class: (worlds, of which the ceiling merged courteously)} over the episodes whose world the ceiling ran, in
    OUTCOMES order."""
    by_seed = {int(w["seed"]): w for w in worlds}
    pairs = [(classify(e, by_seed[int(e["seed"])], b_safe), by_seed[int(e["seed"])]["ceiling_courteous"])
             for e in episodes if int(e["seed"]) in by_seed]
    total, ceiling_ok = Counter(c for c, _ in pairs), Counter(c for c, ok in pairs if ok)
    return {c: (total[c], ceiling_ok[c]) for c in OUTCOMES}


def read(path) -> list[dict]:
    """A CSV's rows with every numeric cell as a float (policy names and notes left out)."""
    def number(v):
        try:
            return float(v)
        except ValueError:
            return None
    with open(path) as f:
        return [{k: x for k, v in r.items() if (x := number(v)) is not None} for r in csv.DictReader(f)]


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__.strip().splitlines()[-1].strip())
    counts = breakdown(read(sys.argv[1]), read(sys.argv[2]), float(sys.argv[3]) if len(sys.argv) == 4 else 4.0)
    for c, (n, ok) in counts.items():
        print(f"{c:>16}: {n:4d} worlds ({ok} where the ceiling merged courteously)")
