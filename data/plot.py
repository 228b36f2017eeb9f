"""Episode pictures: lanes, cars as rectangles at a few instants, trajectories, the ego highlighted."""
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402

from data.world import Road, corners  # noqa: E402


def draw_road(ax, road: Road, x_lo, x_hi, x_ref=None):
    """Lane boundaries (solid outer, dashed inner) and the merge deadline x_ref."""
    w = road.lane_width
    for k in range(road.lanes + 1):
        y = (k - 0.5) * w
        ax.plot([x_lo, x_hi], [y, y], "k-" if k in (0, road.lanes) else "k--", lw=1 if k in (0, road.lanes) else 0.6)
    if x_ref is not None:
        ax.axvline(x_ref, color="tab:red", ls=":", lw=1)


def plot_episode(states, road: Road, path, title="", x_ref=None, snapshots=4):
    """Save a PNG of an episode; states (T, M, 4) bicycle states with the ego in slot 0."""
    states = np.asarray(states)
    T, M, _ = states.shape
    fig, ax = plt.subplots(figsize=(12, 1.2 + 1.1 * road.lanes))
    draw_road(ax, road, states[:, :, 0].min() - 5, states[:, :, 0].max() + 5, x_ref)
    colors = ["tab:green"] + ["tab:blue"] * (M - 1)
    for i in range(M):
        ax.plot(states[:, i, 0], states[:, i, 1], color=colors[i], lw=2 if i == 0 else 1, alpha=0.8)
    for k, t in enumerate(np.linspace(0, T - 1, snapshots).astype(int)):
        alpha = 0.25 + 0.75 * (k + 1) / snapshots
        for i in range(M):
            ax.add_patch(Polygon(corners(states[t, i], road), closed=True, fc=colors[i], ec="k", alpha=alpha, lw=0.5))
            if k == snapshots - 1:
                ax.text(states[t, i, 0], states[t, i, 1], "ego" if i == 0 else str(i), ha="center", va="center", fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
