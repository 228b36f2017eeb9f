"""`python -m bench.demo <folder> [planner overrides] [--shrunk job[,override]:key=value ...]` (the end of `make demo`):
the dense headline on the demo's held-out worlds, the clairvoyant ceiling beside the interactive step (mpc=interactive)
with each gradient source, as one short table read from the runs' own files (<folder>/ceiling_dense.csv,
<folder>/<source>/episodes_admm_*.csv); how far the demo's trainings were shrunk (each --shrunk value against its job's
default in conf/, the full recipe); then one merge drawn as a picture: the road, the cars, the ego's plan and the
outcome, at three moments of the first world a learned source merged courteously in (<folder>/merge.png)."""
import sys
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from bench import breakdown
from bench.results_tables import ci, markdown, pct, read_episodes, stream
from core import stats, validate
from core.jobs import UserError, build, guarded, job_config

SOURCES = {"cv": "interactive step, cv (constant velocity)", "student": "interactive step, the learned student",
           "surrogate": "interactive step, the student's gradient surrogate"}  # <folder>/<source>: its row's name
DRAWN = ("student", "surrogate", "cv")  # the source whose first courteous merge is drawn: the first that has one
RESAMPLES = 2000  # bootstrap resamples of the mean braking


def rows(folder: Path) -> tuple[dict, dict]:
    """{row name: outcomes row} of the ceiling and each source's batch, and {source: its episodes}; a UserError naming
    the file a run did not write."""
    path = folder / "ceiling_dense.csv"
    if not path.is_file():
        raise UserError(f"{path} not found: run `ceiling scenario=dense out_dir={folder}` first")
    # the ceiling's courteous merges as episodes: its t_merge over the worlds it merged courteously in, as its own report
    worlds = [{"courteous": w["ceiling_courteous"], "merged": w["ceiling_courteous"], "t_merge": w["ceiling_t_merge"],
               "b_imposed_max": w["ceiling_b_imposed"]} for w in breakdown.read(path)]
    ceiling = stats.outcomes([worlds], RESAMPLES, stream(0, "demo", "ceiling"))
    out = {"clairvoyant ceiling": {**ceiling, "episodes": len(worlds), "merged": float("nan")}}  # it reports no other merge
    episodes = {}
    for source, name in SOURCES.items():
        if not any((folder / source).glob("episodes_admm_*.csv")):
            raise UserError(f"{folder / source}/episodes_admm_*.csv not found: run the `planner scenario=dense method=admm "
                            f"mpc=interactive gradients={source} episodes=N out_dir={folder / source}` batch first")
        episodes[source] = read_episodes(folder / source, "admm")
        out[name] = {**stats.outcomes([episodes[source]], RESAMPLES, stream(0, "demo", source)),
                     "episodes": len(episodes[source])}
    return out, episodes


def table(out: dict) -> list[str]:
    """The short headline table: worlds, courteous and merged rates, t_merge (steps), mean braking imposed (m/s^2)."""
    return markdown(["", "worlds", "courteous % [95% CI]", "merged % [95% CI]", "t_merge steps", "b_imposed_max m/s^2"],
                    [[name, f"{r['episodes']}", pct(r, "courteous"), pct(r, "merged"), ci(r, "t_merge"),
                      ci(r, "b_imposed_max", ".2f")] for name, r in out.items()])


def shrunk(items) -> str:
    """One line: each 'job[,override...]:key=value' (a size make demo trained with) against that key's default in the
    job's config (the full recipe), with the factor."""
    parts = []
    for item in items:
        spec, _, assignment = item.partition(":")
        key, _, value = assignment.partition("=")
        job, *overrides = spec.split(",")
        full = OmegaConf.select(job_config(job, overrides), key)
        if full is None or not value:
            raise UserError(f"--shrunk {item}: expected job[,override]:key=value with a key of conf/{job}.yaml")
        parts.append(f"{' '.join([job.replace('_', '-'), *overrides])}: {key} {value} of {full} ({float(value) / full:.0%})")
    return "Trained smaller than the full recipe to fit 10 minutes (each job's default in conf/; `make models` trains " \
           "them all at it):\n  " + "\n  ".join(parts)


def drive_with_plans(cfg, seed: int):
    """(scenario, the episode, the ego's plan (T_p + 1, 4) after each step's solve or None) of world `seed` driven by
    cfg's ADMM step."""
    from planner import closed_loop
    from planner.setup import setup

    scenario, source, s = setup(cfg)
    step, plans = build(cfg.method["admm"]), []

    def planner(obs, warm):
        result = step(s, obs, source, warm)
        plans.append(None if result.plan is None else np.vstack([obs.z0, result.plan.Z.reshape(-1, 4)]))
        return result

    ep = closed_loop.drive(scenario.make_world(seed), planner, source, scenario.x_ref, scenario.target_lane, cfg.T_obs,
                           cfg.max_steps, cfg.world, cfg.n_slots)
    return scenario, ep, plans


def picture(ep, plans, scenario, path: Path, title: str, outcome: str) -> Path:
    """A PNG of one merge at three moments (the start, the step before the ego enters the target lane, the end), each
    panel the road near the ego, every car, the ego's path so far and its plan (dashed); the outcome above them."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    from data.plot import draw_road
    from data.world import corners

    states, road = np.asarray(ep.states), scenario.road
    lanes = [int(road.lane_of(y)) for y in states[:, 0, 1]]
    entered = next((t for t, lane in enumerate(lanes) if lane == scenario.target_lane), len(states) - 1)
    moments = [0, max(entered - 1, 0), len(states) - 1]
    fig, axes = plt.subplots(3, 1, figsize=(11, 7.5))
    for ax, t in zip(axes, moments):
        x0 = states[t, 0, 0]
        draw_road(ax, road, x0 - 45, x0 + 65, scenario.x_ref)
        for i, z in enumerate(states[t]):
            ego = i == 0
            ax.add_patch(Polygon(corners(z, road), closed=True, fc="tab:green" if ego else "tab:blue", ec="k", lw=0.5,
                                 alpha=1.0 if ego else 0.7))
            if ego or abs(z[0] - x0) < 45:
                ax.text(z[0], z[1], "ego" if ego else f"{z[3]:.0f}", ha="center", va="center", fontsize=7, color="w")
        ax.plot(states[: t + 1, 0, 0], states[: t + 1, 0, 1], color="tab:green", lw=1.5, label="ego's path so far")
        plan = plans[t] if t < len(plans) else None
        if plan is not None:
            ax.plot(plan[:, 0], plan[:, 1], "--", color="tab:orange", lw=1.5, marker=".", ms=3, label="ego's plan")
        ax.set(xlim=(x0 - 45, x0 + 65), ylim=(-0.5 * road.lane_width - 0.5, (road.lanes - 0.5) * road.lane_width + 0.5),
               ylabel="y (m)", aspect=2.0)
        ax.set_title(f"t = {t * scenario.params.dt:.1f} s: ego {states[t, 0, 3]:.1f} m/s"
                     f"{'' if t else ' (numbers: the other cars speeds, m/s)'}", fontsize=9, loc="left")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("x along the road (m); y stretched 2x; red dotted: the end of the ego's lane")
    fig.suptitle(f"{title}\n{outcome}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


@guarded
def run(folder: Path, overrides=(), trained=()) -> Path | None:
    """Print the headline table and how the trainings were shrunk, then draw the first courteous merge of the first
    source in DRAWN that has one (planner `overrides`, those of its batch but episodes and out_dir) as
    <folder>/merge.png; returns its path, None when no world merged courteously."""
    from planner import report

    out, episodes = rows(folder)
    print("\n".join(["", f"Dense traffic, {out['clairvoyant ceiling']['episodes']} held-out worlds (seeds from the "
                         "batches' seed), ADMM's interactive step with each gradient source beside the ceiling:", "",
                     *table(out)]))
    if trained:
        print("\n" + shrunk(trained))
    drawn = next(((source, int(e["seed"])) for source in DRAWN for e in episodes[source] if e["courteous"]), None)
    if drawn is None:
        print("No courteous merge to draw.")
        return None
    source, seed = drawn
    cfg = job_config("planner", [*overrides, "mpc=interactive", "method=admm", f"gradients={source}", f"seed={seed}"])
    validate.check(cfg, "planner")
    scenario, ep, plans = drive_with_plans(cfg, seed)  # the batch's episode of that world again: the batch keeps no plans
    m = report.metrics(ep, scenario)
    outcome = (f"{'merged courteously' if m['courteous'] else 'merged' if m['merged'] else 'did not merge'} after "
               f"{m['t_merge'] * scenario.params.dt:.1f} s, {'a collision' if m['collision'] else 'no collision'}, "
               f"hardest braking it imposed on another car {m['b_imposed_max']:.2f} m/s^2 (courteous: at most "
               f"b_safe = {scenario.b_safe:g})")
    path = picture(ep, plans, scenario, folder / "merge.png",
                   f"{scenario.name} world {seed}, mpc=interactive, gradients={source}", outcome)
    print(f"\nWorld {seed} driven again with gradients={source}: {outcome}.\nThe picture: {path}")
    return path


if __name__ == "__main__":
    args = sys.argv[2:]
    cut = args.index("--shrunk") if "--shrunk" in args else len(args)
    run(Path(sys.argv[1]), args[:cut], args[cut + 1:])
