"""What a run reports: Table II metrics, the per-step CSV, figures like the paper's Figs. 2-4, a merge animation and the
summary table."""
import csv

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402

from data import outcomes  # noqa: E402
from data.plot import draw_road, plot_episode  # noqa: E402
from data.world import corners  # noqa: E402

COLORS = {"admm": "tab:red", "nnmpc": "tab:purple"}


def metrics(ep, scenario):
    """Table II, courtesy and timing metrics of one episode in `scenario`: merged (0/1), t_merge (steps; steps driven if
    never; mlflow_metrics logs it in s, only when merged), C_max, d_min_m, collision, b_imposed_max (m/s^2), courteous (0/1), ttc_min (s), ..."""
    rows = ep.rows
    in_lane = [r["step"] for r in rows if abs(r["y"] - scenario.y_ref) <= scenario.merge_tol and r["x"] < scenario.x_ref]
    b_imposed = outcomes.b_imposed_max(ep.states, scenario.params.dt)
    ms = np.array([r["step_ms"] for r in rows]) if rows else np.array([np.nan])
    iters = [r["iterations"] for r in rows if not r["fallback"]]
    d0 = np.min(np.hypot(*(ep.states[0, 1:, :2] - ep.states[0, 0, :2]).T))
    return {"merged": float(bool(in_lane)), "t_merge": float(in_lane[0] if in_lane else len(rows)),
            "C_max": float(np.nanmax([r["cost"] for r in rows])) if rows else float("nan"),
            "d_min_m": float(min([d0] + [r["d_min_m"] for r in rows])), "collision": float(ep.collided),
            "b_imposed_max": b_imposed, "courteous": outcomes.courteous(in_lane, ep.collided, b_imposed, scenario.b_safe),
            "ttc_min": outcomes.ttc_min(ep.states, scenario.road),
            "step_ms_median": float(np.median(ms)), "step_ms_p95": float(np.percentile(ms, 95)),
            "admm_iters_mean": float(np.mean(iters)) if iters else 0.0,
            "fallbacks": float(sum(bool(r["fallback"]) for r in rows)), "steps": float(len(rows))}


# MLflow's names of the planner's metrics: <quantity>[_<statistic>]_<unit> (s, ms, m, mps2 = m/s^2; none for shares,
# counts and relative errors), then qualifiers (_lo, _hi: a 95% interval's ends); t_merge logged in s
MLFLOW_NAMES = {"t_merge": "t_merge_s", "b_imposed_max": "b_imposed_max_mps2", "ttc_min": "ttc_min_s",
                "step_ms_median": "step_median_ms", "step_ms_p95": "step_p95_ms"}


def mlflow_metrics(m: dict, dt: float) -> dict:
    """metrics() or a batch's aggregate as MLflow logs them: MLFLOW_NAMES (with _lo/_hi), t_merge times dt (s); a value
    that is not finite (no time to collision, no merge to time) is not logged, and t_merge only where a merge happened."""
    out = {}
    for k, v in m.items():
        base, _, end = k.rpartition("_") if k.endswith(("_lo", "_hi")) else (k, "", "")
        if base == "t_merge":
            v = v * dt if m.get("merged", 1) > 0 else float("nan")
        if np.isfinite(v):
            out[MLFLOW_NAMES.get(base, base) + (f"_{end}" if end else "")] = float(v)
    return out


def run_name(method: str, source, cfg, scenario) -> str:
    """A planner run's MLflow name: method, gradient source (+ its predictor where not the source's own), mpc, scenario,
    seed (a batch: its seed range), and `-record` for a run that records its iterates (record_dir: a data job)."""
    from planner.gradients import predictor_of

    src = source.name if source.predictor.name == predictor_of(source.name) else f"{source.name}+{source.predictor.name}"
    seeds = f"seed{cfg.seed}" if not cfg.episodes else f"seeds{cfg.seed}-{cfg.seed + cfg.episodes - 1}"
    return f"{method}-{src}-{cfg.mpc.name}-{scenario.name}-{seeds}{'-record' if cfg.record_dir else ''}"


def write_csv(ep, path):
    """One row per MPC step: time, state, control, iterations, stop reason, cost, residuals, fallback, wall time."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(ep.rows[0]) if ep.rows else ["step"])
        w.writeheader()
        w.writerows(ep.rows)


def animate(states, road, path, title="", x_ref=None, dt=0.2):
    """A GIF of a closed-loop run (pillow writer, real time): the cars as rectangles, the ego green, trails behind them;
    states (T+1, M, 4), dt the step (s)."""
    states = np.asarray(states)
    fig, ax = plt.subplots(figsize=(10, 1.4 + 1.1 * road.lanes))
    draw_road(ax, road, states[:, :, 0].min() - 5, states[:, :, 0].max() + 5, x_ref)
    colors = ["tab:green"] + ["tab:blue"] * (states.shape[1] - 1)
    cars = [ax.add_patch(Polygon(corners(z, road), closed=True, fc=c, ec="k", lw=0.5)) for z, c in zip(states[0], colors)]
    trails = [ax.plot([], [], color=c, lw=1.5 if i == 0 else 0.8, alpha=0.6)[0] for i, c in enumerate(colors)]
    ax.set(aspect="equal", xlabel="x (m)", ylabel="y (m)")
    ax.set_ylim(-0.5 * road.lane_width - 1, (road.lanes - 0.5) * road.lane_width + 1)
    fig.tight_layout()

    def frame(t):
        for i, (car, trail) in enumerate(zip(cars, trails)):
            car.set_xy(corners(states[t, i], road))
            trail.set_data(states[: t + 1, i, 0], states[: t + 1, i, 1])
        ax.set_title(f"{title}   t = {t * dt:.1f} s", fontsize=9)
        return cars + trails

    FuncAnimation(fig, frame, frames=len(states), blit=False).save(path, writer=PillowWriter(fps=round(1 / dt)))
    plt.close(fig)


def figures(episodes: dict, road, x_ref, y_ref, out_dir, title, animation=True):
    """Paths: merge snapshots per method (Figs. 2-3) with the run as a GIF beside them, trajectory + cost and steering +
    acceleration (Fig. 4)."""
    paths = []
    for method, ep in episodes.items():
        p = out_dir / f"snapshots_{method}.png"
        plot_episode(ep.states, road, p, f"{title} - {method}", x_ref, snapshots=6)
        paths.append(p)
        if animation:
            paths.append(out_dir / f"merge_{method}.gif")
            animate(ep.states, road, paths[-1], f"{title} - {method}", x_ref)
    tag = "_".join(episodes)
    fig, (ax_xy, ax_J) = plt.subplots(2, 1, figsize=(9, 6))
    for method, ep in episodes.items():
        c = COLORS.get(method, "k")
        ax_xy.plot(ep.states[:, 0, 0], ep.states[:, 0, 1], color=c, lw=2, label=f"ego ({method})")
        ax_J.plot([r["time_s"] for r in ep.rows], [r["cost"] for r in ep.rows], color=c, label=method)
    first = next(iter(episodes.values()))
    for j in range(1, first.states.shape[1]):
        ax_xy.plot(first.states[:, j, 0], first.states[:, j, 1], color="tab:blue", alpha=0.4, lw=1)
    ax_xy.axhline(y_ref, color="k", ls=":", lw=0.8)
    ax_xy.axvline(x_ref, color="tab:red", ls=":", lw=0.8)
    ax_xy.set(xlabel="x (m)", ylabel="y (m)", title=f"{title}: trajectories (others in blue)")
    ax_J.set(xlabel="time (s)", ylabel="cost J")
    ax_xy.legend(fontsize=8)
    ax_J.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / f"trajectory_cost_{tag}.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    fig, (ax_d, ax_a) = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    for method, ep in episodes.items():
        t = [r["time_s"] for r in ep.rows]
        ax_d.step(t, ep.controls[:, 0], where="post", color=COLORS.get(method, "k"), label=method)
        ax_a.step(t, ep.controls[:, 1], where="post", color=COLORS.get(method, "k"), label=method)
    ax_d.set(ylabel="steering delta (rad)", title=f"{title}: controls")
    ax_a.set(xlabel="time (s)", ylabel="acceleration a (m/s^2)")
    ax_d.legend(fontsize=8)
    fig.tight_layout()
    paths.append(out_dir / f"controls_{tag}.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def table(results: dict) -> str:
    """A Table II-style summary: one column per (scenario, method) run."""
    names = list(results)
    lines = [f"{'':>16}" + "".join(f"{n:>24}" for n in names)]
    cell = {
        "courteous": lambda m: f"{m['courteous']:.0f}",
        "b_imposed (m/s2)": lambda m: f"{m['b_imposed_max']:.1f}",
        "ttc_min (s)": lambda m: f"{m['ttc_min']:.1f}",
        "t_merge": lambda m: f"{m['t_merge']:.0f}" if m["merged"] else f"fails after {m['t_merge']:.0f}",
        "C_max": lambda m: f"{m['C_max']:.1f}",
        "d_min (m)": lambda m: f"{m['d_min_m']:.2f}",
        "collision": lambda m: f"{m['collision']:.0f}",
        "fallbacks": lambda m: f"{m['fallbacks']:.0f}",
        "ADMM iters": lambda m: f"{m['admm_iters_mean']:.1f}",
        "step ms (med)": lambda m: f"{m['step_ms_median']:.1f}",
        "step ms (p95)": lambda m: f"{m['step_ms_p95']:.1f}",
    }
    for label, fmt in cell.items():
        lines.append(f"{label:>16}" + "".join(f"{fmt(results[n]):>24}" for n in names))
    return "\n".join(lines)
