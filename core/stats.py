"""The 95% intervals every reported figure is given with: Wilson for rates (scipy.stats.binomtest), Student t or a
percentile bootstrap over groups then their items for means (hand-written: scipy.stats.bootstrap resamples one level
only), and outcome rows (episodes, or batches of them) pooled into {metric, metric_lo, metric_hi} (planner.batch,
planner.compare, bench.results)."""

import numpy as np
from scipy import stats

RATES = ("courteous", "merged", "collision")  # 0/1 per episode, a share per batch; courteous is the headline
MEANS = ("t_merge", "C_max", "fallbacks", "b_imposed_max")  # t_merge over merged episodes only: a run that never merged logs the steps it drove


def auc(p, y):
    """Area under the ROC curve of scores p for binary labels y (Mann-Whitney U / (n1 n0)); NaN without both classes."""
    p, y = np.asarray(p, dtype=float), np.asarray(y, dtype=bool)
    if y.all() or not y.any():
        return float("nan")
    return float(stats.mannwhitneyu(p[y], p[~y]).statistic / (y.sum() * (~y).sum()))


def wilson(k: float, n: float, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval (lo, hi) of a rate from k successes in n trials (scipy's binomtest; counts as floats are
    rounded: a batch's rate times its episodes); (nan, nan) for n = 0."""
    if n <= 0:
        return float("nan"), float("nan")
    ci = stats.binomtest(round(k), round(n)).proportion_ci(confidence, method="wilson")
    return float(ci.low), float(ci.high)


def mean_ci(values) -> tuple[float, float, float]:
    """(mean, lo, hi): the mean of the finite values with its Student-t 95% interval; lo = hi = mean for one value."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return (float("nan"),) * 3
    m = float(v.mean())
    if len(v) == 1:
        return m, m, m
    half = float(stats.t.ppf(0.975, len(v) - 1) * stats.sem(v))  # not t.interval: it is NaN for equal values
    return m, m - half, m + half


def bootstrap(groups, statistic, resamples: int, seed=None, within: bool = True) -> np.ndarray:
    """[lo, hi]: the 95% percentile-bootstrap interval of statistic(items), items the groups concatenated; a resample draws
    len(groups) groups with replacement and, when `within`, the items of each drawn group with replacement (groups: a
    training's episodes, a branch state's pairs). Empty groups are dropped; with fewer than two items there is nothing to
    resample and lo = hi = the statistic. NaN statistics are ignored. seed: an int, or a numpy Generator to draw on from
    where it stands (one stream across calls)."""
    groups = [np.asarray(g) for g in groups if len(g)]
    if not groups:
        return np.full(2, np.nan)
    items = np.concatenate(groups)
    if len(items) < 2:
        return np.array([statistic(items)] * 2)
    rng = np.random.default_rng(seed)
    draws = []
    for _ in range(resamples):
        pick = rng.integers(len(groups), size=len(groups))
        draws.append(statistic(np.concatenate([groups[i][rng.integers(len(groups[i]), size=len(groups[i]))] if within
                                               else groups[i] for i in pick])))
    return np.nanpercentile(np.array(draws), [2.5, 97.5], axis=0)



def paired_ratio(numerator, denominator, resamples: int, seed=None) -> tuple[float, float, float]:
    """(mean, lo, hi): the mean of the per-pair ratios numerator / denominator (a planner's t_merge over the ceiling's on
    each world both merged courteously: never a ratio of medians) with its 95% percentile-bootstrap interval over pairs
    (bootstrap, one group); nan for no pairs. seed as in bootstrap."""
    r = np.asarray(numerator, float) / np.asarray(denominator, float)
    if not len(r):
        return (float("nan"),) * 3
    lo, hi = bootstrap([r], np.mean, resamples, seed)
    return float(r.mean()), float(lo), float(hi)

def values_of(rows, key: str, weight: str | None):
    """(values, weights) of metric `key` over rows: the finite values, each weighted by the episodes its row stands for
    (row[weight], 1 when weight is None), for t_merge by its merged episodes only."""
    v = np.array([r.get(key, np.nan) for r in rows], float)
    w = np.array([r[weight] if weight else 1.0 for r in rows], float)
    if key == "t_merge":
        w = w * np.array([r.get("merged", np.nan) for r in rows], float)
    ok = np.isfinite(v) & (w > 0)
    return v[ok], w[ok]


def outcomes(groups, resamples: int = 0, seed=None, means=MEANS, weight: str | None = None) -> dict:
    """{k, k_lo, k_hi} of outcome rows pooled over groups (trainings): for RATES the share over all episodes with its
    Wilson interval, for `means` the episode-weighted mean of the finite values with a Student t interval, or with
    resamples > 0 a percentile bootstrap over groups then rows (seed: see bootstrap). A row is one episode, or with
    `weight` a batch of row[weight] episodes holding its rates and means: its spread within the batch is unknown, so
    means over such rows have no interval (NaN)."""
    nan = float("nan")
    rows = [r for g in groups for r in g]
    size = np.array([r[weight] if weight else 1.0 for r in rows], float)
    n = float(size.sum())
    out = {}
    for k in RATES:
        hits = float(np.multiply([r.get(k, np.nan) for r in rows], size).sum())
        ok = n > 0 and np.isfinite(hits)  # a batch that did not log the rate leaves the pooled rate unknown
        out[k] = hits / n if ok else nan
        # a batch's rate times its episodes is a count up to rounding
        out[f"{k}_lo"], out[f"{k}_hi"] = wilson(float(np.round(hits)), n) if ok else (nan, nan)
    for k in means:
        per_group = [values_of(g, k, weight) for g in groups]
        v = np.concatenate([x for x, _ in per_group]) if per_group else np.zeros(0)
        w = np.concatenate([x for _, x in per_group]) if per_group else np.zeros(0)
        if not (w == 1).all():
            out[k], out[f"{k}_lo"], out[f"{k}_hi"] = float(np.average(v, weights=w)), nan, nan
        elif resamples:
            lo, hi = bootstrap([x for x, _ in per_group], np.mean, resamples, seed)
            out[k], out[f"{k}_lo"], out[f"{k}_hi"] = float(v.mean()) if len(v) else nan, float(lo), float(hi)
        else:
            out[k], out[f"{k}_lo"], out[f"{k}_hi"] = mean_ci(v)
    return out
