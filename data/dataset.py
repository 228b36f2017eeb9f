"""The interaction dataset: episodes of the merge world cut into (T_obs past xy of ego + N cars) -> next xy windows.

Slots: 0 is the ego; 1..N hold the N other cars nearest the ego at each window's last observed step, in id order
(front to back at the episode's start), each with its own past: data.perception's rule, the planner's. Coordinates are world metres: x along the road, y to the left.
Besides each episode's own run (branch 0), counterfactual branches (1, 2, ...) restart a copy of the world at a few
random steps where the ego can interact (same drivers, same hidden decisions) and drive the ego on differently for
branches.steps steps: interventional data showing how the others react to what the ego does. With branches.flip each
such ego drives once more in a copy whose undecided drivers (those that have not yet perceived an encroachment, so
that their past is the same under either decision: `undecided`) hold the opposite hidden decision
(World.with_decisions): the same history under the other hypothesis, by the world's own drivers.
Every window records each slot's latched decision (`will_yield`) beside the per-step `yielding` flag, whether its
yielding has visibly cut its acceleration so far (`shown`, data.world.SHOWN_BRAKE), and how many steps ago the ego
first encroached on that car (`since_encroach`, -1: not yet), where a decision can start to show.
"""
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from joblib import Parallel, delayed

from core.jobs import UserError, recover, sha256, staged
from core.stats import auc
from data.perception import slot_ids
from data.policies import follow, sample_policy
from data.scenarios import Scenario
from data.world import steer_to

FORMAT = 5  # 4: will_yield, since_encroach, flipped and the flipped branches; 5: shown
SPLITS = ("train", "val", "test")
REVEAL_LAGS_S = (0.0, 0.4, 0.8, 1.2, 1.6, 2.0)  # how long after the ego first encroaches on a car its reveal is scored (s)
ARRAYS = {  # name -> (dtype kind, trailing shape given T_obs and SLOTS = N + 1)
    "X": ("f", lambda t, m: (t, m, 2)),
    "Y": ("f", lambda t, m: (m, 2)),
    "episode": ("i", lambda t, m: ()),
    "step": ("i", lambda t, m: ()),
    "branch": ("i", lambda t, m: ()),
    "yielding": ("b", lambda t, m: (m,)),
    "ids": ("i", lambda t, m: (m,)),
}
LABELS = {  # the hidden-decision labels make-dataset writes; a dataset written by another job (bench/candidates) may lack them
    "will_yield": ("b", lambda t, m: (m,)),
    "since_encroach": ("i", lambda t, m: (m,)),
    "flipped": ("b", lambda t, m: ()),
    "shown": ("b", lambda t, m: (m,)),
}


def flags_of(world) -> dict:
    """The per-car hidden flags (M,) of a world now: yielding (braking for the ego) and shown (its yielding has cut its
    acceleration by SHOWN_BRAKE at some step so far: the decision is visible)."""
    return {"yielding": world.yielding.copy(), "shown": world.shown.copy()}


def stack_flags(flags: list) -> dict:
    """Per-step flags {name: (T, M)} from a list of flags_of dicts."""
    return {k: np.array([f[k] for f in flags]) for k in flags[0]}


def rollout(scenario: Scenario, policy, seed: int, steps: int, snapshots=()):
    """Run one episode; returns states (steps+1, M, 4), the flags {yielding, shown} (steps+1, SLOTS) (flags_of), the
    world (ends early on a collision), and copies of the world after each step in `snapshots` that the episode reached."""
    world = scenario.make_world(seed)
    states, flags, copies = [world.states()], [flags_of(world)], {}
    for k in range(steps):
        if k in snapshots:
            copies[k] = world.copy()
        hits = world.step(policy(world))
        states.append(world.states())
        flags.append(flags_of(world))
        if hits:
            break
    return np.array(states), stack_flags(flags), world, copies


@dataclass(frozen=True)
class Intervention:
    """A counterfactual ego from a branch point on: steer to y_target (m) with lateral gain k_y (1/s) and track v_target
    (m/s), lane-keeping law."""

    y_target: float
    v_target: float
    k_y: float = 0.8

    def __call__(self, world):
        """Control [delta (rad), a (m/s^2)] for the ego now."""
        z = world.states()[0]
        return np.array([steer_to(z, self.y_target, world.params, k_y=self.k_y), float(np.clip(min(self.v_target - z[3], follow(world)), -3.0, 2.0))])


LEAN_K_Y = 2.0  # lateral gain of the lean (1/s): deep within about a second, so a yielder shows within the branch


def interventions(rng, world, y_ref, ranges):
    """The counterfactual egos of one branch point: push on towards y_ref, back off to the start lane, change speed,
    with ranges["y_lean"] lean quickly to a depth short of the target lane and hold it (where a yielder shows its
    decision: the ego in the lane is a leader every driver follows alike), and with ranges["cut_in"] steer right into
    the target lane (what mpc=interactive's merging candidates ask about)."""
    y, v = (float(q) for q in world.states()[0, [1, 3]])
    push = Intervention(float(rng.uniform(*ranges["y_push"])) * y_ref, v)
    back = Intervention(0.0, v)
    speed = Intervention(y, max(0.0, v + float(rng.choice([-1.0, 1.0]) * rng.uniform(*ranges["dv"]))))
    lean = [Intervention(float(rng.uniform(*ranges["y_lean"])) * y_ref, v, LEAN_K_Y)] if ranges.get("y_lean") else []
    return [push, back, speed, *lean, *([Intervention(y_ref, v)] if ranges.get("cut_in") else [])]


def can_interact(world, scenario, reach):
    """Whether what the ego does next can matter to the others: it is before x_ref, not yet in the target lane, and a
    target-lane car is within `reach` metres along the road (where random branch points would mostly be idle)."""
    z, lane = world.states(), world.road.lane_of(scenario.y_ref)
    ego = z[0]
    near = (np.abs(z[1:, 0] - ego[0]) <= reach) & (world.road.lane_of(z[1:, 1]) == lane)
    return bool(ego[0] < scenario.x_ref and world.road.lane_of(ego[1]) != lane and near.any())


def branch(world, ego, steps):
    """Drive a copy of `world` on for `steps` steps with the ego controller `ego`: states (steps+1, M, 4), the flags
    {yielding, shown} (steps+1, M)."""
    world = world.copy()
    states, flags = [world.states()], [flags_of(world)]
    for _ in range(steps):
        hits = world.step(ego(world))
        states.append(world.states())
        flags.append(flags_of(world))
        if hits:
            break
    return np.array(states), stack_flags(flags)


def windows(xy, flags, t_obs: int, n_slots: int):
    """All (X (n, t_obs, n_slots+1, 2), Y (n, n_slots+1, 2), last observed step (n,), flags at it, the world ids in the
    slots (n, n_slots+1)) of one episode's xy (T, M, 2), slots chosen at each last observed step
    (data.perception.slot_ids). flags: the yielding flags (T, M), or a dict of per-step labels, (T, M) per car (gathered
    to (n, n_slots+1)) or (T,) per run (to (n,))."""
    last = np.arange(t_obs - 1, len(xy) - 1)
    m = n_slots + 1
    labels = flags if isinstance(flags, dict) else {"yielding": flags}
    ids = np.stack([slot_ids(xy[t], n_slots) for t in last]) if len(last) else np.zeros((0, m), int)
    rows = np.arange(len(last))[:, None]
    picked = {k: (a[last][rows, ids] if np.ndim(a) == 2 else np.asarray(a)[last]) for k, a in labels.items()}
    picked = picked if isinstance(flags, dict) else picked["yielding"]
    if not len(last):
        return np.zeros((0, t_obs, m, 2)), np.zeros((0, m, 2)), last, picked, ids
    X = np.stack([xy[t - t_obs + 1 : t + 1][:, i] for t, i in zip(last, ids)])
    return X, xy[last + 1][rows, ids], last, picked, ids


def first_encroached(world, states, first=None, t0=0) -> np.ndarray:
    """The step (M,) at which the ego first encroached on each car (World.encroachments; each car's lane its nearest) in
    a run's states (T, M, 4) of `world`'s drivers numbered from step t0, carried on from `first` (-1: not yet)."""
    first = np.full(states.shape[1], -1) if first is None else first.copy()
    if not world.hidden_decisions:  # nothing to label: no driver decides in advance
        return first
    w = world.copy()
    for t, z in enumerate(states, start=t0):
        w.z, w.target_lane = z, w.road.lane_of(z[:, 1])
        first[(first < 0) & (w.encroachments() > 0)] = t
    return first


def run_labels(flags, will_yield, first, flipped: bool) -> dict:
    """The per-step labels (windows' flags) of a run of T steps: its flags {yielding, shown} (T, M), the latched
    will_yield (M,) and the steps since the first encroachment (T, M) (-1 before it) from `first` (M,), and whether the
    run is flipped."""
    n = len(flags["yielding"])
    t = np.arange(n)[:, None]
    since = np.where((first >= 0) & (first <= t), t - first, -1)
    return {**flags, "will_yield": np.broadcast_to(will_yield, flags["yielding"].shape),
            "since_encroach": since, "flipped": np.full(n, flipped)}


def episode_seeds(seed: int, episodes: int):
    """The world seed of each of a dataset's episodes."""
    return [int(s) for s in np.random.SeedSequence(seed).generate_state(episodes)]


def explore(scenario, policy_ranges, seed, steps, snapshots=()):
    """One seeded episode with a sampled exploratory ego: states, flags {yielding, shown}, final world, world copies,
    the policy."""
    world0 = scenario.make_world(seed)
    policy = sample_policy(np.random.default_rng([seed, 1]), scenario.y_ref, float(world0.states()[1:, 3].mean()), policy_ranges)
    return (*rollout(scenario, policy, seed, steps, snapshots), policy)


def undecided(world, first, b) -> np.ndarray:
    """(M,) the drivers whose past up to step b of a run (`world` then) is the same under either decision: none of the
    states they have acted on (each its reaction delay back, World.perceived) was encroached on, `first` (M,) the
    first encroachment (-1: never). A driver the ego encroached on within its reaction delay is still undecided: the
    lean in progress, whose answer the flipped branch shows."""
    lag = np.array([0] + [len(world.seen) - 1 - world.perceived(j) for j in range(1, len(first))])
    return (first < 0) | (first >= b - lag)


def episode(scenario, policy_ranges, branch_cfg, seed, steps, t_obs, n_slots):
    """One seeded episode's windows (its own run and its counterfactual branches) and what happened in it."""
    rng = np.random.default_rng([seed, 2])
    t_pred, n = branch_cfg["steps"], branch_cfg["points"]
    candidates = set(range(t_obs - 1, steps - t_pred + 1)) if n else set()
    states, own, world, copies, policy = explore(scenario, policy_ranges, seed, steps, candidates)
    eligible = [k for k, w in sorted(copies.items()) if can_interact(w, scenario, branch_cfg["reach"])]
    points = sorted(rng.choice(eligible, size=min(n, len(eligible)), replace=False).tolist()) if eligible else []
    first = first_encroached(world, states)
    parts = [(*windows(states[..., :2], run_labels(own, world.decisions(), first, False), t_obs, n_slots), 0)]
    for b, w in ((k, copies[k]) for k in points):
        before = np.where(first < b + 1, first, -1)  # encroached on up to the branch point
        decided = w.decisions()
        flipped = np.where(undecided(w, first, b), ~decided, decided) if w.hidden_decisions else decided
        flipped[0] = False
        flip = w.hidden_decisions and branch_cfg.get("flip") and (flipped != decided).any()
        worlds = [(w, False)] + ([(w.with_decisions(flipped), True)] if flip else [])
        for ego in interventions(rng, w, scenario.y_ref, branch_cfg):
            for w_b, flip in worlds:
                s_b, y_b = branch(w_b, ego, t_pred)
                run = run_labels({k: np.concatenate([own[k][:b], y_b[k]]) for k in own}, w_b.decisions(),
                                 first_encroached(w_b, s_b[1:], before, b + 1), flip)
                X, Y, last, flags, ids = windows(np.concatenate([states[:b, :, :2], s_b[..., :2]]), run, t_obs, n_slots)
                keep = last >= b  # earlier windows are the episode's own
                parts.append((X[keep], Y[keep], last[keep], {k: v[keep] for k, v in flags.items()}, ids[keep], len(parts)))
    X, Y, last, ids = (np.concatenate([p[k] for p in parts]) for k in (0, 1, 2, 4))
    flags = {k: np.concatenate([p[3][k] for p in parts]) for k in parts[0][3]}
    branch_id = np.concatenate([np.full(len(p[0]), p[5]) for p in parts])
    stats = {"collided": bool(world.collisions), "attempts": policy.attempts, "any_yield": bool(own["yielding"].any()),
             "any_shown": bool(own["shown"].any()),
             "merged": bool(world.road.lane_of(world.states()[0, 1]) == world.road.lane_of(scenario.y_ref)),
             "branches": len(parts) - 1}
    return X, Y, last, flags, ids, branch_id, stats


def build(scenario: Scenario, policy_ranges: dict, branch_cfg: dict, episodes: int, steps: int, t_obs: int, n_slots: int,
          seed: int, split_fractions=(0.8, 0.1, 0.1), n_jobs: int = 1):
    """Roll `episodes` seeded episodes (and their branches) out and split their windows train/val/test by episode."""
    which = assign(episodes, split_fractions, seed)
    if min(len(e) for e in which.values()) == 0:
        raise UserError(f"dataset.episodes={episodes} leaves a split empty with dataset.split={list(split_fractions)}")
    results = Parallel(n_jobs=n_jobs)(
        delayed(episode)(scenario, policy_ranges, branch_cfg, s, steps, t_obs, n_slots) for s in episode_seeds(seed, episodes))
    return stack(results, which), [r[6] for r in results]


def assign(episodes: int, split_fractions, seed: int) -> dict:
    """{split: the episode indices it holds}: a seeded permutation of range(episodes) cut by split_fractions."""
    order = np.random.default_rng(seed).permutation(episodes)
    n_train = int(round(split_fractions[0] * episodes))
    n_val = int(round(split_fractions[1] * episodes))
    return {"train": order[:n_train], "val": order[n_train:n_train + n_val], "test": order[n_train + n_val:]}


def stack(results: list, which: dict) -> dict:
    """{split: arrays} of per-episode windows (X, Y, last observed step, flags, ids, branch, ...: `episode`'s
    results; flags the yielding flags or a dict of labels, as `windows` gives them), each split holding the episodes
    `which` gives it (numbered by their place in `results`)."""
    splits = {}
    dtypes = {"b": bool, "i": np.int32}
    for name, eps in which.items():
        eps = np.sort(eps)
        parts = [results[e] for e in eps]
        flags = [p[3] if isinstance(p[3], dict) else {"yielding": p[3]} for p in parts]
        splits[name] = {
            "X": np.concatenate([p[0] for p in parts]).astype(np.float32),
            "Y": np.concatenate([p[1] for p in parts]).astype(np.float32),
            "episode": np.concatenate([np.full(len(p[0]), e) for e, p in zip(eps, parts)]).astype(np.int32),
            "step": np.concatenate([p[2] for p in parts]).astype(np.int32),
            "ids": np.concatenate([p[4] for p in parts]).astype(np.int32),
            "branch": np.concatenate([p[5] for p in parts]).astype(np.int32),
            **{k: np.concatenate([f[k] for f in flags]).astype(dtypes[kind]) for k, (kind, _) in
               {"yielding": ARRAYS["yielding"], **LABELS}.items() if k in flags[0]},
        }
    return splits


def summarize(stats: list) -> dict:
    """Episode counts and, over every probe that started with a closed gap, the fraction that opened it."""
    attempts = [a for s in stats for a in s["attempts"]]
    closed = [a for a in attempts if not a[0]]
    return {
        "episodes": len(stats),
        "collisions": int(sum(s["collided"] for s in stats)),
        "merged": int(sum(s["merged"] for s in stats)),
        "episodes_with_yield": int(sum(s["any_yield"] for s in stats)),
        "episodes_with_shown": int(sum(s["any_shown"] for s in stats)),
        "branches": int(sum(s["branches"] for s in stats)),
        "nudges": len(closed),
        "nudges_opened_gap": int(sum(a[1] for a in closed)),
        "nudge_open_frac": float(np.mean([a[1] for a in closed])) if closed else 0.0,
    }


def restore_renamed(root: Path) -> None:
    """Put back a dataset folder that an older make-dataset, stopped between its two folder renames, left as
    .<name>.old-<pid> (with .<name>.tmp-<pid> beside it); nothing when `root` exists."""
    if root.exists():
        return
    for kind in ("old", "tmp"):  # the old folder first; the new one only if the old one is gone too
        for p in sorted(root.parent.glob(f".{root.name}.{kind}-*")):
            if (p / "meta.json").is_file() and not root.exists():
                p.rename(root)


def save(root: Path, splits: dict, meta: dict) -> dict:
    """Write {train,val,test}.npz and meta.json into `root` as one set (core.jobs.staged: a failed or stopped job leaves
    the old set whole, and every other file or folder in `root`, such as iterates/, is kept); a split with no windows is
    a UserError that keeps the old dataset."""
    empty = [name for name, arrays in splits.items() if not len(arrays["X"])]
    if empty:
        raise UserError(f"dataset.T_obs={meta['T_obs']}: the {' and '.join(empty)} split(s) have 0 windows (an episode "
                        f"needs more than T_obs steps; raise dataset.steps or lower dataset.T_obs); {root} is left as it was")
    restore_renamed(root)
    with staged(root) as tmp:
        files = {}
        for name, arrays in splits.items():
            np.savez_compressed(tmp / f"{name}.npz", **arrays)
            files[name] = {"windows": int(len(arrays["X"])), "sha256": sha256(tmp / f"{name}.npz"),
                           "episodes": sorted(int(e) for e in np.unique(arrays["episode"]))}
        meta = {**meta, "format": FORMAT, "splits": files}
        (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    return meta


def read_meta(root: Path) -> dict:
    """The dataset's meta.json, validated; a missing or corrupt one is a UserError naming the file."""
    recover(root)  # a set a stopped make-dataset committed but did not finish moving in
    path = Path(root) / "meta.json"
    if not path.exists():
        raise UserError(f"dataset not found: {path} is missing (build it with `make-dataset dataset={Path(root).name}`)")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise UserError(f"corrupt dataset meta file {path}: {e}") from None
    for key in ("format", "T_obs", "N", "splits"):
        if key not in meta:
            raise UserError(f"corrupt dataset meta file {path}: key '{key}' missing")
    if meta["format"] != FORMAT:
        raise UserError(f"{path}: dataset format {meta['format']} is not {FORMAT}; rebuild it with make-dataset")
    return meta


def load(root, split: str) -> dict:
    """Arrays of one split, checked against meta.json (checksum, shapes, dtypes, finiteness); errors name the file."""
    root = Path(root)
    meta = read_meta(root)
    if split not in meta["splits"]:
        raise UserError(f"{root / 'meta.json'}: no split '{split}' (have {sorted(meta['splits'])})")
    path = root / f"{split}.npz"
    if not path.exists():
        raise UserError(f"dataset file missing: {path} (rebuild with make-dataset)")
    if sha256(path) != meta["splits"][split]["sha256"]:
        raise UserError(f"{path} does not match its meta.json checksum (corrupt or from another build); rebuild with make-dataset")
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as e:  # numpy raises several types for a damaged zip
        raise UserError(f"cannot read dataset file {path}: {e}") from None
    t_obs, m = meta["T_obs"], meta["N"] + 1
    n = meta["splits"][split]["windows"]
    if not n:
        raise UserError(f"{path}: the {split} split has 0 windows; rebuild it with make-dataset (more dataset.steps or a "
                        "smaller dataset.T_obs)")
    for key, (kind, shape) in {**ARRAYS, **{k: v for k, v in LABELS.items() if k in arrays}}.items():
        if key not in arrays:
            raise UserError(f"{path}: array '{key}' missing")
        a = arrays[key]
        want = (n,) + shape(t_obs, m)
        if a.shape != want or a.dtype.kind != kind:
            raise UserError(f"{path}: array '{key}' has shape {a.shape} dtype {a.dtype}, expected {want} kind '{kind}'")
        if kind == "f" and not np.isfinite(a).all():
            raise UserError(f"{path}: array '{key}' holds NaN or infinite values")
    return arrays


def factual(arrays: dict) -> dict:
    """The windows of runs under the world's own hidden decisions (all, where the split has no flipped branches): what a
    predictor that takes no hypothesis is fitted and scored on."""
    if "flipped" not in arrays:
        return arrays
    keep = ~arrays["flipped"]
    return {k: v[keep] for k, v in arrays.items()}


def encroached(a: dict):
    """The factual windows' other cars the ego has encroached on (the only ones whose decision can show): window
    index (k,), slot (k,), steps since the first encroachment (k,), latched decision (k,)."""
    w, j = np.nonzero((a["since_encroach"][:, 1:] >= 0) & ~a["flipped"][:, None])
    return w, j + 1, a["since_encroach"][w, j + 1], a["will_yield"][w, j + 1]


def nearest_behind(a: dict, w, j) -> np.ndarray:
    """Whether slot j of window w (k,) holds the encroached car nearest behind the ego at the window's last observed
    step (k,): the one the ego leans in front of, whose decision can show (a car further back follows that one, and
    its own decision shows only once it is the nearest)."""
    x = a["X"][:, -1, :, 0]
    behind = (a["since_encroach"] >= 0) & (x < x[:, :1])
    behind[:, 0] = False
    nearest = np.where(behind.any(1), np.argmax(np.where(behind, x, -np.inf), axis=1), -1)
    return nearest[w] == j


def reveal(a: dict, dt: float) -> dict:
    """How far the data shows the hidden decisions (encroached cars): at each of REVEAL_LAGS_S after the first
    encroachment (steps of dt s), the AUC of `shown` (the yielding has visibly cut the car's acceleration) for the
    latched will_yield (reveal_auc_<lag>s: what a predictor told each decision once shown would score; 0.5 where
    nothing shows), the share of the yielders shown (reveal_yielders_<lag>s) and the cars counted (reveal_cases_<lag>s);
    the same AUC and count for the car nearest behind the ego alone (nearest_behind; reveal_auc_nearest_<lag>s,
    reveal_cases_nearest_<lag>s); and over every case the Brier score of the belief that knows each decision once shown
    and otherwise the yield rate of the cars not shown, over the constant prior's (reveal_brier_ratio: a bound on what a
    belief read from the windows reaches, fitted on the cases it scores)."""
    w, j, since, y = encroached(a)
    shown, nearest = a["shown"][w, j], nearest_behind(a, w, j)
    y_f = y.astype(float)
    hidden = y_f[~shown].mean() if (~shown).any() else 0.0
    prior = np.mean((y_f - y_f.mean()) ** 2) if len(y) else float("nan")
    out = {"reveal_brier_ratio": float(np.mean((np.where(shown, 1.0, hidden) - y_f) ** 2) / prior) if prior else float("nan")}
    for lag in REVEAL_LAGS_S:
        at = since == int(round(lag / dt))
        out[f"reveal_auc_{lag:.1f}s"] = auc(shown[at], y[at])
        out[f"reveal_yielders_{lag:.1f}s"] = float(shown[at & y].mean()) if (at & y).any() else float("nan")
        out[f"reveal_cases_{lag:.1f}s"] = int(at.sum())
        out[f"reveal_auc_nearest_{lag:.1f}s"] = auc(shown[at & nearest], y[at & nearest])
        out[f"reveal_cases_nearest_{lag:.1f}s"] = int((at & nearest).sum())
    return out


def hidden_labels(arrays: dict, where) -> dict:
    """`arrays` when they carry the hidden-decision labels (LABELS), else one UserError naming `where`."""
    missing = [k for k in LABELS if k not in arrays]
    if missing:
        raise UserError(f"{where}: no hidden-decision labels ({', '.join(missing)}); a hypothesis model needs a dataset "
                        "written by make-dataset (format 4)")
    return arrays


def make(cfg_dataset, scenario, root: Path, config_yaml: str) -> dict:
    """Build and save the dataset described by `cfg_dataset`; returns meta (with build time and statistics)."""
    t0 = time.perf_counter()
    splits, stats = build(scenario, dict(cfg_dataset.policy), dict(cfg_dataset.branches), cfg_dataset.episodes, cfg_dataset.steps,
                          cfg_dataset.T_obs, cfg_dataset.n_slots, cfg_dataset.seed, tuple(cfg_dataset.split), cfg_dataset.n_jobs)
    meta = {
        "name": cfg_dataset.name, "seed": cfg_dataset.seed, "T_obs": cfg_dataset.T_obs, "T_pred": 1,
        "N": int(splits["train"]["X"].shape[2] - 1), "dt": scenario.params.dt, "units": "m",
        "slots": "0 = ego; 1..N = the N other cars nearest the ego at the last observed step, in id order",
        "shapes": {"X": "(n, T_obs, N+1, 2) past xy", "Y": "(n, N+1, 2) next xy", "episode": "(n,)",
                   "step": "(n,) last observed step", "yielding": "(n, N+1) hidden: car brakes for the ego",
                   "will_yield": "(n, N+1) hidden: the car's latched decision to yield to an encroaching ego, in this run",
                   "since_encroach": "(n, N+1) steps since the ego first encroached on the car (-1: not yet)",
                   "flipped": "(n,) the run's undecided drivers hold the opposite of the world's decisions",
                   "shown": "(n, N+1) hidden: the car's yielding has cut its acceleration by SHOWN_BRAKE so far",
                   "ids": "(n, N+1) the world ids in the slots (0: the ego)",
                   "branch": "(n,) 0 = the episode's own run, k >= 1 its k-th counterfactual branch"},
        "stats": {**summarize(stats), **reveal({k: np.concatenate([splits[s][k] for s in SPLITS]) for k in (*LABELS, "X")},
                                               scenario.params.dt)},
        "build_s": round(time.perf_counter() - t0, 2), "config": config_yaml,
    }
    return save(root, splits, meta)
