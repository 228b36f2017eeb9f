"""The figures of `results` (bench/results.py), drawn from the report's own tables."""
from pathlib import Path

import numpy as np
import pandas as pd

from bench.results_tables import GRADIENT_ROWS, METHODS
from planner import compare
from surrogate.evaluate import ENDS


def bar_plot(rows: dict, key: str, ylabel: str, title: str, path: Path, scale=1.0):
    """Grouped bars (a group per source, a bar per method) of rows[...][key] with its 95% interval as error bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sources = list(dict.fromkeys(s for s, _ in rows))
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(sources), 4))
    for j, m in enumerate(METHODS):
        x = np.arange(len(sources)) + (j - 0.5) * 0.38
        v = np.array([rows[s, m][key] for s in sources]) * scale
        lo = np.array([rows[s, m][f"{key}_lo"] for s in sources]) * scale
        hi = np.array([rows[s, m][f"{key}_hi"] for s in sources]) * scale
        err = np.nan_to_num(np.abs(np.vstack([v - lo, hi - v])))
        ax.bar(x, np.nan_to_num(v), width=0.36, yerr=err, capsize=4, label=m.upper(), color=("tab:red", "tab:purple")[j],
               alpha=0.8)
    ax.set_xticks(np.arange(len(sources)), sources)
    ax.set(ylabel=ylabel, title=title)
    ax.legend()
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def braking_plot(values: dict, b_safe: float, b_max: float, path: Path):
    """Box plots, one per row of the dense table ({name: per-world largest braking imposed on another car, m/s^2}), with
    every world as a dot, b_safe (courteous) and b_max (the physical cap) marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2.0 + 0.9 * len(values), 4.5))
    jitter = np.random.default_rng(0)
    for i, v in enumerate(values.values()):
        if len(v):
            ax.boxplot([v], positions=[i], widths=0.5, showfliers=False)
            ax.plot(i + jitter.uniform(-0.15, 0.15, len(v)), v, ".", color="tab:blue", alpha=0.4, ms=4)
    ax.axhline(b_safe, color="tab:red", ls="--", lw=1, label=f"b_safe = {b_safe:g} m/s^2 (courteous)")
    ax.axhline(b_max, color="k", ls=":", lw=1, label=f"b_max = {b_max:g} m/s^2 (physical cap)")
    ax.set_xticks(np.arange(len(values)), list(values), rotation=30, ha="right")
    ax.set(xlim=(-0.6, len(values) - 0.4), ylabel="largest braking imposed on another car (m/s^2)",
           title="dense traffic: braking imposed per world")
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def accuracy_plot(dense: dict, gradients: dict, inter: dict, path: Path):
    """compare's figure (planner.compare.plot) from the report's own figures: per dense ADMM row, the gradient error of its
    source along ramps (the baselines as lines), its courteous-merge rate and its source's react_corr_jac, against the
    row's median MPC step (ms) on the dense worlds."""
    names = {v: k for k, v in GRADIENT_ROWS.items()}  # a surrogate-job suffix -> its row of the Gradients table
    base = {f"ramp_grad_rel_err{suffix}": gradients[names[suffix]]["ramp_grad_rel_err"][0] for suffix in ("_cv", "_mean")}
    rows = []
    for (name, method), r in dense.items():
        if method != "admm":
            continue
        source = name.split(" ", 1)[0]  # the row name's gradient source (label)
        suffix = compare.scored_as(source)
        grad = (np.nan,) * 3 if suffix is None else gradients[names[suffix]]["ramp_grad_rel_err"]
        rows.append({"label": f"{name}/{method}", "gradients": name, "method": method, "step_median_ms": r["step_ms_median"],
                     "courteous_rate": r["courteous"], "courteous_lo": r["courteous_lo"], "courteous_hi": r["courteous_hi"],
                     **dict(zip((f"ramp_grad_rel_err{e}" for e in ENDS), grad)), **base,
                     "react_corr_jac": inter.get(source, {}).get("react_corr_jac", (np.nan,))[0],
                     "n_episodes": r["episodes"], "n_runs": r["trainings"]})
    compare.plot(pd.DataFrame(rows), path)


PER_PANEL = 4  # planner rows a panel draws beside the two ceilings: at most six series a panel


def cooperation_plot(rates: dict, levels, path: Path):
    """Courteous-merge rate (%) against cooperation level, a line per row ({name: {level: rate()}}), Wilson 95%
    intervals as error bars, PER_PANEL planner rows a panel with the ceilings (dashed) in each; each panel says how many
    worlds a level holds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ceilings = [n for n in rates if "ceiling" in n]
    rows = [n for n in rates if n not in ceilings]
    panels = [rows[i : i + PER_PANEL] for i in range(0, len(rows), PER_PANEL)] or [[]]
    cols = min(2, len(panels))
    fig, axes = plt.subplots(-(-len(panels) // cols), cols, figsize=(6.5 * cols, 4.2 * -(-len(panels) // cols)),
                             squeeze=False, sharey=True)
    x = np.arange(len(levels))
    for ax, names in zip(axes.flat, panels):
        for i, name in enumerate([*ceilings, *names]):
            v = rates[name]
            y = np.array([v[c]["courteous"] for c in levels]) * 100
            err = np.nan_to_num(np.abs(np.vstack([y - [100 * v[c]["courteous_lo"] for c in levels],
                                                  [100 * v[c]["courteous_hi"] for c in levels] - y])))
            shift = (i - len(names) / 2) * 0.03  # side by side: intervals at one level stay readable
            ax.errorbar(x + shift, y, yerr=err, capsize=3, marker="o", ms=4, label=name,
                        ls="--" if name in ceilings else "-", color=("k", "0.5")[i] if name in ceilings else f"C{i}")
        n = sorted({rates[name][c]["n"] for name in [*ceilings, *names] for c in levels})
        ax.set_xticks(x, levels)
        ax.set(xlabel="cooperation (scenario.cooperation)", ylabel="courteous merges (% of worlds)", ylim=(-3, 103),
               title=f"{n[0]}{'' if n[0] == n[-1] else f'-{n[-1]}'} dense worlds a level")
        ax.legend(fontsize=7, loc="best")
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    fig.suptitle("dense traffic: courteous merges against cooperation, 95% Wilson intervals", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fidelity_plot(points: dict, rhos: dict, where: dict, oracle: dict | None, path: Path, worlds: str = "dense worlds",
                  dt: float = 0.2):
    """Courteous-merge rate (%) and t_merge (s, dt a step) against fidelity, a column per score of rhos (brake_auc,
    react_corr, good_kept), each x axis saying where its score is measured ({score: its job and worlds}), the y axes the
    planner's `worlds`: a point per predictor ({name: {score: (mean, lo, hi), "row": outcomes row}}) with its 95%
    intervals both ways; Spearman's rho of each score ({score: (rho, lo, hi)}) in its title; the oracle's rate (a row,
    or None), which the scores cannot rank, as a dashed line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(rhos), figsize=(5.2 * len(rhos), 7.5), squeeze=False)
    colors = plt.cm.tab10(np.arange(len(points)) % 10)
    for j, (score, (rho, lo, hi)) in enumerate(rhos.items()):
        for i, (key, scale, ylabel) in enumerate((("courteous", 100.0, f"courteous merges (% of {worlds})"),
                                                  ("t_merge", dt, "t_merge (s), courteous merges"))):
            ax = axes[i, j]
            for c, (name, p) in zip(colors, points.items()):
                x, (y, ylo, yhi) = p[score], (scale * p["row"][key + e] for e in ("", "_lo", "_hi"))
                ax.errorbar(x[0], y, xerr=np.nan_to_num([[x[0] - x[1]], [x[2] - x[0]]]),
                            yerr=np.nan_to_num([[y - ylo], [yhi - y]]), fmt="o", capsize=3, color=c, label=name)
                ax.annotate(name.removesuffix(" interactive"), (x[0], y), textcoords="offset points", xytext=(4, 4),
                            fontsize=7)
            if oracle is not None and i == 0:
                ax.axhline(100 * oracle["courteous"], color="k", ls="--", lw=1,
                           label=f"oracle interactive ({oracle['episodes']} worlds; not scored)")
            ax.set(xlabel=f"{score} (measured on: {where[score]})", ylabel=ylabel)
            ax.grid(alpha=0.3)
        axes[0, j].set_title(f"Spearman's rho = {compare.fmt(rho, '.2f', lo, hi)} (95% CI over worlds)", fontsize=9)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"the interactive step: outcome on {worlds} against the predictor's fidelity, measured on other worlds "
                 "(each x axis), 95% CI", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
