"""The tables of `results` (bench/results.py): the jobs' outputs read back, their statistics with 95% intervals, and the
Markdown cells and tables that show them.

Every bootstrap draws from its own random stream, spawned from `bootstrap.seed` by the names of its table and row
(`stream`), so adding, removing or reordering a section or a row moves no other interval."""
import csv
import warnings
import zlib
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from bench import breakdown
from core import stats
from planner.compare import fmt
from surrogate.evaluate import ENDS, metric

METHODS = ("admm", "nnmpc")
GRADIENT_ROWS = {"surrogate": "", "surrogate over the student's values (the planner's)": "_over_student",
                 "student": "_student", "constant velocity (baseline)": "_cv", "mean Jacobian (baseline)": "_mean"}  # the surrogate job's metrics per row: grad_rel_err, grad_rel_err_student, ...


def stream(seed: int, *names: str) -> np.random.Generator:
    """The random stream of one table row: a child of `seed` keyed by the names (table, row, ...), stable across runs
    and independent of which other streams exist or in which order they are drawn."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=tuple(zlib.crc32(n.encode()) for n in names)))


def methods(folder: Path) -> list[str]:
    """The methods (METHODS order) a batch's folder has episodes of: both, or ADMM alone for an mpc option's rows."""
    return [m for m in METHODS if any(folder.glob(f"episodes_{m}_*.csv"))]


def read_episodes(folder: Path, method: str) -> list[dict]:
    """The finished episodes of a batch's per-episode CSV (planner/batch.py) as {column: float}."""
    path = next(folder.glob(f"episodes_{method}_*.csv"))
    with open(path) as f:
        return [{k: float(v) for k, v in r.items() if k not in ("error", "notes")} for r in csv.DictReader(f)
                if r["crash"] == "0"]


def read_ceiling(work: Path, scenario: str, level: str | None = None) -> list[dict]:
    """The ceiling's per-world rows of `scenario` (bench/ceiling.py's CSV) as {column: float}, its policy names left out;
    with a cooperation `level`, those of the sweep's dense run at that level."""
    folder = work / "ceiling" if level is None else work / "ceiling" / f"dense_{level}"
    return breakdown.read(folder / f"ceiling_{scenario}.csv")


def rate(hits) -> dict:
    """A rate's {courteous, courteous_lo, courteous_hi} from 0/1 values (Wilson 95%); NaN for none."""
    hits = np.asarray(hits, float)
    lo, hi = stats.wilson(float(hits.sum()), len(hits))
    return {"courteous": float(hits.mean()) if len(hits) else float("nan"), "courteous_lo": lo, "courteous_hi": hi,
            "n": len(hits)}


def ceiling_row(r: dict, worlds: list[dict], search: str, resamples: int, rng) -> dict:
    """A dense-table row of the ceiling's `search` (SEARCHES): its courteous rate (Wilson) and t_merge over courteous
    worlds (steps, Student t) as the ceiling job gave them (r), and the mean braking it imposed over its worlds (m/s^2,
    percentile bootstrap over worlds, as the planners' means)."""
    row = {k + e: r[f"{search}_{k}{e}"] for k in ("courteous", "t_merge") for e in ("", "_lo", "_hi")}
    b = np.array([w[f"{search}_b_imposed"] for w in worlds])
    row["b_imposed_max"] = float(b.mean()) if len(b) else float("nan")
    row["b_imposed_max_lo"], row["b_imposed_max_hi"] = stats.bootstrap([b], np.mean, resamples, rng)
    return {"trainings": 1, "episodes": len(worlds), **row}


def beaten(worlds: list[dict], episodes: list[dict]) -> set[int]:
    """Seeds of the episodes that merged courteously where the ceiling on the same world did not, or did later (steps)."""
    best = {int(w["seed"]): w["ceiling_t_merge"] if w["ceiling_courteous"] else np.inf for w in worlds}
    return {int(e["seed"]) for e in episodes if e["courteous"] and e["t_merge"] < best[int(e["seed"])]}


def paired_t_merge(worlds: list[dict], episodes: list[dict], resamples: int, rng) -> dict:
    """The episodes' t_merge over the ceiling's on the same world, over the worlds both merged courteously on
    (stats.paired_ratio: the mean ratio, a bootstrap over those pairs): {ratio, ratio_lo, ratio_hi, pairs}."""
    best = {int(w["seed"]): w["ceiling_t_merge"] for w in worlds if w["ceiling_courteous"]}
    pairs = np.array([(e["t_merge"], best[int(e["seed"])]) for e in episodes if e["courteous"] and int(e["seed"]) in best])
    ratio = stats.paired_ratio(pairs[:, 0], pairs[:, 1], resamples, rng) if len(pairs) else (float("nan"),) * 3
    return {"ratio": ratio[0], "ratio_lo": ratio[1], "ratio_hi": ratio[2], "pairs": len(pairs)}

def world_hits(rows: dict, seeds) -> tuple[np.ndarray, np.ndarray]:
    """(hits, counts), each (rows, worlds): per row ({name: its episodes}) and world seed, the courteous merges and the
    episodes (one per training that finished it)."""
    col = {int(s): j for j, s in enumerate(seeds)}
    hits, counts = np.zeros((len(rows), len(col))), np.zeros((len(rows), len(col)))
    for i, eps in enumerate(rows.values()):
        for e in eps:
            hits[i, col[int(e["seed"])]] += e["courteous"]
            counts[i, col[int(e["seed"])]] += 1
    return hits, counts


def rank_correlation(x, hits, counts, resamples: int, rng) -> tuple[float, float, float]:
    """(rho, lo, hi): Spearman's rank correlation between x (a value per row) and the rows' rates, hits over counts
    ((rows, worlds) as world_hits), with its 95% percentile-bootstrap interval over worlds (core.stats.bootstrap: the
    worlds drawn with replacement, every row's rate recomputed on them, rho recomputed); a resample where a side is
    constant has no rho and is left out; nan with fewer than two rows."""
    x, hits, counts = np.asarray(x, float), np.asarray(hits, float), np.asarray(counts, float)
    if len(x) < 2:
        return (float("nan"),) * 3

    def rho(worlds):
        with warnings.catch_warnings(), np.errstate(invalid="ignore", divide="ignore"):
            warnings.simplefilter("ignore")  # a constant side: scipy warns and returns nan, which is the answer
            return float(spearmanr(x, hits[:, worlds].sum(1) / counts[:, worlds].sum(1)).statistic)

    worlds = np.arange(hits.shape[1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # every resample without a rho: nanpercentile warns and gives nan
        lo, hi = stats.bootstrap([worlds], rho, resamples, rng)
    return rho(worlds), float(lo), float(hi)


def outcomes(per_training: list[list[dict]], resamples: int, rng) -> dict:
    """One table row from the episodes of each training: rates with Wilson intervals, means with bootstrap intervals."""
    eps = [e for t in per_training for e in t]
    row = {"trainings": len(per_training), "episodes": len(eps), **stats.outcomes(per_training, resamples, rng)}
    row["d_min_m"] = min((e["d_min_m"] for e in eps), default=float("nan"))
    row["step_ms_median"] = float(np.median([e["step_ms_median"] for e in eps])) if eps else float("nan")
    return row


def markdown(header, rows) -> list[str]:
    """A Markdown table."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header), *("| " + " | ".join(r) + " |" for r in rows), ""]


def over_trainings(values: list[dict], keys) -> dict:
    """{key: (mean, lo, hi)} over the trainings' dicts (t interval)."""
    return {k: stats.mean_ci([v.get(k, np.nan) for v in values]) for k in keys}


def gradient_row(runs: list[dict], suffix: str, keys) -> dict:
    """{key: (mean, lo, hi)} of one source's gradient scores (the surrogate job's metrics `key + suffix`): the t interval
    over trainings, or with one training the job's own interval over its planning states; NaN where not scored."""
    if len(runs) > 1:
        return over_trainings([{k: r.get(metric(k, suffix), np.nan) for k in keys} for r in runs], keys)
    out = {}
    for k in keys:
        if metric(k, suffix, "_lo") in runs[0]:
            out[k] = tuple(runs[0].get(metric(k, suffix, e), np.nan) for e in ENDS)
        else:  # a figure without an interval (jac_rel_err), or one not scored
            out[k] = (runs[0].get(metric(k, suffix), np.nan),) * 3
    return out


def pct(r: dict, k: str) -> str:
    """A rate's cell in %, with its interval; '-' for one the row does not have."""
    return fmt(100 * r.get(k, np.nan), ".1f", 100 * r.get(f"{k}_lo", np.nan), 100 * r.get(f"{k}_hi", np.nan))


def ci(r: dict, k: str, f=".1f") -> str:
    """A mean's cell, with its interval; '-' for one the row does not have."""
    return fmt(r.get(k, np.nan), f, r.get(f"{k}_lo", np.nan), r.get(f"{k}_hi", np.nan))


def size(r: dict) -> str:
    """The 'trainings x episodes' cell of a row."""
    return f"{r['trainings']} x {r['episodes'] // max(r['trainings'], 1)}"


def outcome_table(rows: dict, ceiling_run: dict | None = None) -> list[str]:
    """The Markdown table of batch outcomes, one line per (source, method); given the ceiling job's metrics on the same
    worlds (Table II), courteous merges lead and the ceiling's t_merge (steps) stands beside the planner's."""
    lead = [("courteous % [95% CI]", lambda r: pct(r, "courteous"))] if ceiling_run else []
    beside = [("ceiling t_merge steps [95% CI]", lambda r: ci(ceiling_run, "ceiling_t_merge"))] if ceiling_run else []
    columns = [*lead, ("merged % [95% CI]", lambda r: pct(r, "merged")), ("collision % [95% CI]", lambda r: pct(r, "collision")),
               ("t_merge steps [95% CI]", lambda r: ci(r, "t_merge")), *beside, ("C_max [95% CI]", lambda r: ci(r, "C_max")),
               ("d_min (m)", lambda r: fmt(r["d_min_m"])), ("fallbacks / episode [95% CI]", lambda r: ci(r, "fallbacks", ".2f")),
               ("step ms (median)", lambda r: fmt(r["step_ms_median"], ".1f"))]
    return markdown(["gradients", "method", "trainings x episodes", *(h for h, _ in columns)],
                    [[s, m.upper(), size(r), *(c(r) for _, c in columns)] for (s, m), r in rows.items()])


def dense_table(rows: dict) -> list[str]:
    """The Markdown table of the dense batch and the ceiling's rows (method ''), courteous merges first; '-' where a row
    has no such figure (the ceiling neither collides nor falls back)."""
    header = ["gradients", "method", "trainings x worlds", "courteous % [95% CI]", "merged % [95% CI]", "t_merge steps [95% CI]",
              "b_imposed_max m/s^2 [95% CI]", "collision % [95% CI]", "fallbacks / episode [95% CI]"]
    return markdown(header, [[s, m.upper() or "-", size(r), pct(r, "courteous"), pct(r, "merged"), ci(r, "t_merge"),
                              ci(r, "b_imposed_max", ".2f"), pct(r, "collision"), ci(r, "fallbacks", ".2f")]
                             for (s, m), r in rows.items()])


def sweep_table(rates: dict, levels) -> list[str]:
    """The Markdown table of the cooperation sweep: a line per row ({name: {level: rate()}}), its courteous rate per
    level."""
    return markdown(["row", *(f"{c}: courteous % [95% CI]" for c in levels)],
                    [[name, *(pct(v[c], "courteous") for c in levels)] for name, v in rates.items()])
