"""Batch statistics: `planner scenario=random episodes=N` drives N seeded episodes (seeds seed .. seed+N-1) in parallel
and logs one MLflow run per method: rates and means with 95% confidence intervals, step-time percentiles, a per-episode
CSV, histograms.

Episodes run on local joblib processes (`backend=loky`, the default) or on a Ray cluster (`backend=ray`, joblib's Ray
backend; `ray.address=auto` or `ray://host:10001` joins a running cluster, null starts a local instance). Either way an
episode depends only on its seed, so both give the same per-episode results.

An episode that raises, or whose local worker process is killed (SIGKILL, as the out-of-memory killer ends one), is
recorded as a crash with its message in the CSV; the batch goes on, and then fails with the count (exit 2, MLflow run
FAILED) unless `tolerate_crashes=true`; a batch in which every episode crashed always fails.
Rates and means are over the episodes that finished; `episodes` counts all N, so `compare` weights the run by its size.
Beside each method's per-episode CSV, steps/<method>_<seed>.csv holds each finished episode's per-step CSV
(planner/report.py write_csv; written here, not by the workers, so a Ray cluster needs no shared disk): the recorded
controls that `ceiling starts=[...]` replays. The headline is the courteous-merge rate (data.outcomes). Intervals
(core.stats): Wilson for `courteous`, `merged` and `collision`
(`courteous_lo`, `courteous_hi`, ...), a percentile bootstrap over the finished episodes for the means of t_merge, C_max,
fallbacks and b_imposed_max: these are non-negative and skewed (most episodes have no fallback), where a Student t interval
would reach below 0.
"""
import contextlib
import csv
import logging
import re
import signal
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from joblib import Parallel, delayed, effective_n_jobs, parallel_config  # noqa: E402
from joblib.externals.loky import FIRST_COMPLETED, BrokenProcessPool, ProcessPoolExecutor, wait  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

from core import stats  # noqa: E402
from core.jobs import Stopped, UserError, mlflow_run, quiet, stop_signal  # noqa: E402
from planner import report, setup  # noqa: E402
from planner.closed_loop import Episode  # noqa: E402

FIGURES = {"b_imposed_max": "largest braking imposed on another car (m/s^2)", "t_merge": "t_merge (s, merged episodes)", "C_max": "C_max", "d_min_m": "d_min (m)",
           "step_ms": "MPC step wall time (ms, every step)", "admm_iters_mean": "ADMM iterations (episode mean)",
           "fallbacks": "fallbacks per episode"}
RESAMPLES = 2000  # bootstrap resamples of the episode means; seeded (0): the same rows always give the same interval
_WORKER = {}  # per process: the config it was set up for, and its (scenario, source, settings)
log = logging.getLogger(__name__)


def worker_setup(cfg):
    """planner.setup.setup(cfg), once per worker process (models load once), torch on one thread: the workers fill the cores."""
    key = OmegaConf.to_yaml(cfg)
    if _WORKER.get("key") != key:
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(1)
        _WORKER.update(key=key, value=setup.setup(cfg))
    return _WORKER["value"]


def episode(cfg_dict: dict, method: str, seed: int):
    """(CSV row, per-step wall times ms, iterations of the non-fallback steps, per-step records) of one episode; never
    raises."""
    try:
        cfg = OmegaConf.create(cfg_dict)
        scenario, source, s = worker_setup(cfg)
        ep = setup.drive(cfg, scenario, source, s, method, seed=seed)
        m = report.metrics(ep, scenario)
        finite = np.isfinite(ep.states).all() and np.isfinite(ep.controls).all() and \
            np.isfinite([m[k] for k in ("t_merge", "C_max", "d_min_m")]).all()
        row = {"seed": seed, **m, "crash": 0, "nan": int(not finite), "error": "",
               "notes": "; ".join(ep.notes)}
        return row, [r["step_ms"] for r in ep.rows], [r["iterations"] for r in ep.rows if not r["fallback"]], ep.rows
    except Exception as e:  # one bad episode must not kill a thousand: count it and carry its message
        if stop_signal() is not None:  # the error came from a stop signal caught inside a library: stop, not a crash
            raise Stopped(stop_signal()) from e
        return crashed(seed, f"{type(e).__name__}: {e}")


def crashed(seed: int, error: str):
    """episode()'s answer for an episode that crashed with `error`: its CSV row and no steps."""
    return {"seed": seed, "crash": 1, "nan": 0, "error": error[:500]}, [], [], []


def aggregate(rows, step_ms, iters) -> dict:
    """The run's metrics from the per-episode rows and the pooled per-step wall times (ms) and iterations, with 95%
    intervals `<metric>_lo`, `<metric>_hi` (module doc)."""
    done = [r for r in rows if not r["crash"]]
    safe = lambda f, a: float(f(a)) if len(a) else float("nan")
    return {"episodes": float(len(rows)), "crashes": float(len(rows) - len(done)), "nans": float(sum(r["nan"] for r in rows)),
            "d_min_m": safe(np.min, [r["d_min_m"] for r in done]), "ttc_min": safe(np.min, [r["ttc_min"] for r in done]),
            "step_ms_median": safe(np.median, step_ms), "step_ms_p95": safe(lambda a: np.percentile(a, 95), step_ms),
            "admm_iters_mean": safe(np.mean, iters), **stats.outcomes([done], RESAMPLES, seed=0)}


PROGRESS_S = 5.0  # s between progress lines without a terminal (a log file, nohup, SLURM); none for a shorter batch


class Lines:
    """A file for tqdm without a terminal: each refresh its own line, not a '\\r' redraw."""

    def __init__(self, f):
        self.f = f

    def write(self, s):
        s = s.replace("\r", "").strip()
        if s:
            self.f.write(s + "\n")

    def flush(self):
        self.f.flush()


def progress(iterable, total: int, desc: str):
    """`iterable` with tqdm's progress on stderr: a bar on a terminal, else a line (done/total, rate, ETA) at most every
    PROGRESS_S, the first once PROGRESS_S have passed."""
    if not quiet():
        return tqdm(iterable, total=total, desc=desc, unit="ep", dynamic_ncols=True)
    return tqdm(iterable, total=total, desc=desc, unit="ep", file=Lines(sys.stderr), mininterval=PROGRESS_S,
                delay=PROGRESS_S, ascii=True, ncols=90)


@contextlib.contextmanager
def backend(cfg):
    """joblib's backend for cfg.backend: local processes (loky), or Ray (joins cfg.ray.address, or starts a local
    instance once per process when it is null)."""
    if cfg.backend == "loky":
        yield
        return
    try:
        import ray
        from ray.util.joblib import register_ray
    except ImportError:
        raise UserError("backend=ray needs Ray: pip install -e '.[ray]'") from None
    if not ray.is_initialized():
        ray.init(address=cfg.ray.address, include_dashboard=False, log_to_driver=False)
    register_ray()
    with parallel_config(backend="ray"):
        yield


def write_csv(rows, path):
    """One row per episode: seed, outcome metrics, crash (0/1) with its error message, nan (0/1), notes."""
    fields = list(dict.fromkeys(k for r in sorted(rows, key=lambda r: r["crash"]) for k in r))
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)


def histograms(rows, step_ms, out_dir, tag, title, dt):
    """One PNG per figure in FIGURES: its distribution over the finished episodes (step_ms: over every step; t_merge in
    s, dt a step)."""
    done = [r for r in rows if not r["crash"]]
    paths = []
    for key, label in FIGURES.items():
        if key == "step_ms":
            values = np.asarray(step_ms, float)
        else:
            values = np.array([r[key] for r in done if key != "t_merge" or r["merged"]], float) * (dt if key == "t_merge" else 1)
        fig, ax = plt.subplots(figsize=(6, 3.5))
        ax.hist(values[np.isfinite(values)], bins=30, color="tab:blue", alpha=0.8)
        ax.set(xlabel=label, ylabel="count", title=f"{title}\n{label}, n = {np.isfinite(values).sum()}")
        fig.tight_layout()
        paths.append(out_dir / f"hist_{tag}_{key}.png")
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)
    return paths


@contextlib.contextmanager
def sigint_blocked():
    """SIGINT blocked in this thread, a mask the worker processes started inside inherit: Ctrl-C, which reaches every
    process of the terminal's group, stops the batch through this process alone (a worker hit while importing would
    print its own traceback); one that arrives meanwhile is delivered here as soon as the mask is lifted."""
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


ONE_THREAD = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}  # the workers fill the cores


def drive_local(cfg_dict, method: str, seeds, n_jobs, bar) -> list:
    """[episode(...)] of `seeds` in seed order on n_jobs local worker processes, each its own one-worker loky executor:
    a worker killed outright (SIGKILL, as the out-of-memory killer ends one) is the crash of the episode it was
    driving alone; the other workers drive on and a fresh one takes its place."""
    slots = min(effective_n_jobs(n_jobs), len(seeds))
    if slots <= 1:  # one worker: this process, as joblib runs one job
        out = []
        for seed in seeds:
            out.append(episode(cfg_dict, method, seed))
            bar.update()
        return out
    todo, done, busy, pools = list(seeds), {}, {}, [None] * slots  # busy: {future: (worker slot, seed)}
    try:
        while todo or busy:
            for i in sorted(set(range(len(pools))) - {i for i, _ in busy.values()})[:len(todo)]:
                seed = todo.pop(0)
                with sigint_blocked():  # a worker starts when its first episode is submitted
                    pools[i] = pools[i] or ProcessPoolExecutor(max_workers=1, env=ONE_THREAD)
                    busy[pools[i].submit(episode, cfg_dict, method, seed)] = (i, seed)
            finished, _ = wait(busy, return_when=FIRST_COMPLETED)
            if stop_signal() is not None:  # a library in this process caught the signal's Stopped and carried on
                raise Stopped(stop_signal())
            for f in finished:
                i, seed = busy.pop(f)
                try:
                    done[seed] = f.result()
                except BrokenProcessPool as e:  # its worker died without an answer: no other episode was on it
                    codes = re.search(r"exit codes of the workers are (.*)", str(e))
                    done[seed] = crashed(seed, f"{type(e).__name__}: its worker process was killed "
                                               f"({codes.group(1) if codes else 'no exit code'}; out of memory?)")
                    pools[i].shutdown()
                    pools[i] = None
                bar.update()
    finally:
        for pool in pools:
            if pool is not None:  # its workers ended and their queues' semaphores released (else loky warns at exit)
                pool.shutdown(kill_workers=True)
    return [done[seed] for seed in seeds]


def drive_all(cfg, method: str) -> list:
    """[episode(...)] for seeds cfg.seed .. cfg.seed + cfg.episodes - 1, over cfg.n_jobs workers of cfg.backend, in seed
    order, with a progress bar."""
    cfg_dict = OmegaConf.to_container(cfg, resolve=True)
    seeds = list(range(cfg.seed, cfg.seed + cfg.episodes))
    tasks = lambda part: (delayed(episode)(cfg_dict, method, seed) for seed in part)
    out = []
    with backend(cfg), progress(None, len(seeds), f"{method} episodes") as bar:
        if cfg.backend == "loky":  # results stream back one by one
            out = drive_local(cfg_dict, method, seeds, cfg.n_jobs, bar)
        else:  # Ray's joblib backend returns whole lists only: progress in chunks of a few episodes per worker
            chunk = 4 * effective_n_jobs(cfg.n_jobs)
            for i in range(0, len(seeds), chunk):
                out += Parallel(n_jobs=cfg.n_jobs)(tasks(seeds[i : i + chunk]))
                bar.update(len(seeds[i : i + chunk]))
    return out


def record(cfg, scenario, source, s, method: str, out_dir, params=None, accuracy=None) -> tuple[dict, str]:
    """One method's batch inside its MLflow run, opened first (a stopped batch ends KILLED), with `params` and the
    source's `accuracy` metrics (planner.compare.source_link): drive_all, aggregate, write the CSV, the per-step CSVs
    (steps/) and histograms to out_dir and log the first and last; returns (its metrics, its run id).
    Crashed episodes then fail the run with their count (UserError), unless cfg.tolerate_crashes; a batch whose every
    episode crashed always fails."""
    import mlflow

    tag = f"{method}_{source.name}_{scenario.name}"
    params = {**setup.run_params(scenario, source, cfg), **(params or {}), "method": method, "episodes": cfg.episodes}
    with mlflow_run("planner", cfg, run_name=report.run_name(method, source, cfg, scenario), **params) as run_:
        out = drive_all(cfg, method)
        rows = [o[0] for o in out]
        step_ms = [t for o in out for t in o[1]]
        r = aggregate(rows, step_ms, [k for o in out for k in o[2]])
        title = f"{scenario.name}, {method}, gradients={source.name}: {len(rows)} episodes"
        csv_path = out_dir / f"episodes_{tag}.csv"
        write_csv(rows, csv_path)
        (out_dir / "steps").mkdir(exist_ok=True)
        for row, *_, steps in out:
            if steps:
                report.write_csv(Episode(rows=steps), out_dir / "steps" / f"{method}_{row['seed']}.csv")
        plots = histograms(rows, step_ms, out_dir, tag, title, scenario.params.dt) if cfg.plots else []
        mlflow.log_metrics({**report.mlflow_metrics(r, scenario.params.dt), **(accuracy or {})})
        mlflow.log_artifact(str(csv_path))
        for p in plots:
            mlflow.log_artifact(str(p), "plots")
        errors = sorted({row["error"] for row in rows if row["crash"]})
        for e in errors:
            log.info(f"[{method}] crash: {e}")
        ci = lambda k, f: f"{r[k]:{f}} [{r[k + '_lo']:{f}}, {r[k + '_hi']:{f}}]"
        log.info(f"[{method}] {title} (95% intervals): courteous merges {ci('courteous', '.1%')}, merged {ci('merged', '.1%')}, collision {ci('collision', '.1%')}, "
                 f"t_merge {ci('t_merge', '.1f')} steps of {scenario.params.dt:g} s, d_min {r['d_min_m']:.2f} m, step {r['step_ms_median']:.1f} ms median / "
                 f"{r['step_ms_p95']:.1f} p95, fallbacks per episode {ci('fallbacks', '.2f')}, {r['crashes']:.0f} crashes, "
                 f"{r['nans']:.0f} NaN episodes; outputs in {out_dir}")
        crashes = int(r["crashes"])
        if crashes == len(rows) or (crashes and not cfg.tolerate_crashes):
            keep = "" if crashes == len(rows) else "; tolerate_crashes=true keeps such a batch"
            raise UserError(f"{crashes} of {len(rows)} {method} episodes crashed (first: {errors[0]}); see {csv_path}{keep}")
    return r, run_.info.run_id


def run(cfg, scenario, source, s, methods, out_dir, params=None, accuracy=None) -> tuple[dict, dict]:
    """Drive cfg.episodes episodes per method, write and log each method's batch (record); returns ({method: metrics},
    {method: run id})."""
    done = {m: record(cfg, scenario, source, s, m, out_dir, params, accuracy) for m in methods}
    return {m: r for m, (r, _) in done.items()}, {m: i for m, (_, i) in done.items()}
