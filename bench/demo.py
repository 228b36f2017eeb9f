"""`python -m bench.demo <folder> [planner overrides]` (the end of `make demo`): the dense headline on the demo's
held-out worlds, the clairvoyant ceiling beside the paper's step and the courteous step, as one short table read from
the runs' own files (<folder>/ceiling_dense.csv, <folder>/<step>/episodes_admm_*.csv), then one courteous merge drawn
as a GIF: the courteous step's first world that merged courteously, driven again into <folder>/merge_courteous.gif."""
import sys
from pathlib import Path

from bench import breakdown
from bench.results_tables import ci, markdown, pct, read_episodes, stream
from core import stats, validate
from core.jobs import UserError, guarded, job_config

STEPS = {"paper": "ADMM, the paper's step", "courteous": "ADMM, the courteous step"}  # <folder>/<step>: its row's name
RESAMPLES = 2000  # bootstrap resamples of the mean braking


def rows(folder: Path) -> tuple[dict, dict]:
    """{row name: outcomes row} of the ceiling and each step's batch, and {step: its episodes}; a UserError naming the
    file a run did not write."""
    path = folder / "ceiling_dense.csv"
    if not path.is_file():
        raise UserError(f"{path} not found: run `ceiling scenario=dense out_dir={folder}` first")
    # the ceiling's courteous merges as episodes: its t_merge over the worlds it merged courteously in, as its own report
    worlds = [{"courteous": w["ceiling_courteous"], "merged": w["ceiling_courteous"], "t_merge": w["ceiling_t_merge"],
               "b_imposed_max": w["ceiling_b_imposed"]} for w in breakdown.read(path)]
    ceiling = stats.outcomes([worlds], RESAMPLES, stream(0, "demo", "ceiling"))
    out = {"clairvoyant ceiling": {**ceiling, "episodes": len(worlds), "merged": float("nan")}}  # it reports no other merge
    episodes = {}
    for step, name in STEPS.items():
        if not any((folder / step).glob("episodes_admm_*.csv")):
            raise UserError(f"{folder / step}/episodes_admm_*.csv not found: run the `planner scenario=dense method=admm "
                            f"mpc={step} episodes=N out_dir={folder / step}` batch first")
        episodes[step] = read_episodes(folder / step, "admm")
        out[name] = {**stats.outcomes([episodes[step]], RESAMPLES, stream(0, "demo", step)), "episodes": len(episodes[step])}
    return out, episodes


def table(out: dict) -> list[str]:
    """The short headline table: worlds, courteous and merged rates, t_merge (steps), mean braking imposed (m/s^2)."""
    return markdown(["", "worlds", "courteous % [95% CI]", "merged % [95% CI]", "t_merge steps", "b_imposed_max m/s^2"],
                    [[name, f"{r['episodes']}", pct(r, "courteous"), pct(r, "merged"), ci(r, "t_merge"),
                      ci(r, "b_imposed_max", ".2f")] for name, r in out.items()])


@guarded
def run(folder: Path, overrides=()) -> Path | None:
    """Print the headline table and draw the first courteous merge of the courteous step (planner `overrides`, those
    of its batch but episodes and out_dir) as <folder>/merge_courteous.gif; returns its path, None when no world merged
    courteously."""
    from planner import report
    from planner.setup import drive, setup

    out, episodes = rows(folder)
    print("\n".join(["", f"Dense traffic, {out['clairvoyant ceiling']['episodes']} held-out worlds:", "", *table(out)]))
    won = [int(e["seed"]) for e in episodes["courteous"] if e["courteous"]]
    if not won:
        print("No courteous merge to draw.")
        return None
    cfg = job_config("planner", [*overrides, "mpc=courteous", "method=admm", f"seed={won[0]}"])
    validate.check(cfg, "planner")
    scenario, source, s = setup(cfg)
    ep = drive(cfg, scenario, source, s, "admm")  # the batch's episode of that world again: the batch keeps no states
    gif = folder / "merge_courteous.gif"
    report.animate(ep.states, scenario.road, gif, f"{scenario.name} world {won[0]}, courteous step, gradients={source.name}",
                   scenario.x_ref)
    m = report.metrics(ep, scenario)
    print(f"World {won[0]} driven again: courteous {m['courteous']:.0f}, t_merge {m['t_merge']:.0f} steps, hardest braking "
          f"imposed {m['b_imposed_max']:.2f} m/s^2; the GIF: {gif}")
    return gif


if __name__ == "__main__":
    run(Path(sys.argv[1]), sys.argv[2:])
