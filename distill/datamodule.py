"""Dataset windows as Lightning batches: (window, next) for the teacher; for the student (window, teacher next,
random cotangents v on the other cars' outputs, the teacher's v^T J), Jacobian matching by random projections."""
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, TensorDataset, WeightedRandomSampler

from core.jobs import UserError
from core.rollout import accelerations, rollout
from data import dataset
from distill.perturb import planner_like


class WindowData(L.LightningDataModule):
    """Train/val (window, next) pairs from data/<name>/ in metres, as recorded. A subclass that sets `group_batch` > 0
    and fills `groups` (a TensorDataset of branch groups) gets that many groups beside every training batch."""

    group_batch = 0  # branch groups per training batch
    hypotheses = False  # True: the runs under flipped decisions too, for a predictor given the hypotheses

    def __init__(self, dataset_dir, batch_size, fraction):
        """dataset_dir: a make-dataset folder; batch_size: training batch (validation uses 4x); fraction: the share of
        the training split's episodes trained on (the first ones, so a smaller share is a subset of a larger)."""
        super().__init__()
        self.dataset_dir, self.batch_size, self.fraction = dataset_dir, batch_size, float(fraction)
        self.splits = {}

    def setup(self, stage=None):
        """Load (and label) both splits once, the training split cut to `fraction` of its episodes."""
        for split in ("train", "val"):
            if split not in self.splits:
                arrays = dataset.load(self.dataset_dir, split)
                arrays = dataset.hidden_labels(arrays, f"{self.dataset_dir}/{split}.npz") if self.hypotheses else dataset.factual(arrays)
                self.splits[split] = self.tensors(first_episodes(arrays, self.fraction) if split == "train" else arrays)

    def tensors(self, arrays):
        """The split's training tensors: the recorded window and next positions."""
        return TensorDataset(torch.from_numpy(arrays["X"]), torch.from_numpy(arrays["Y"]))

    def sampler(self):
        """How training windows are drawn: None, uniformly shuffled (a subclass may weight them)."""
        return None

    def train_dataloader(self):
        """Shuffled training batches; with branch groups a dict {windows, groups} Lightning cycles together."""
        sampler = self.sampler()
        windows = DataLoader(self.splits["train"], batch_size=self.batch_size, shuffle=sampler is None, sampler=sampler)
        if not self.group_batch:
            return windows
        return {"windows": windows, "groups": DataLoader(self.groups, batch_size=self.group_batch, shuffle=True)}

    def val_dataloader(self):
        """Validation batches, in order."""
        return DataLoader(self.splits["val"], batch_size=4 * self.batch_size)


def first_episodes(arrays: dict, fraction: float) -> dict:
    """The windows of a split's first round(fraction x episodes) episodes (at least one), every array cut alike."""
    episodes = np.unique(arrays["episode"])
    keep = np.isin(arrays["episode"], episodes[:max(1, round(fraction * len(episodes)))])
    return {k: v[keep] for k, v in arrays.items()}


class SequenceData(WindowData):
    """Train/val windows with the recorded futures of their run for a multi-step rollout loss: (window, ego future
    (H, 2), others' future (H, N, 2), mask (H,)); where the run ends early the ego continues at constant velocity
    and the mask is False. With contrast_groups > 0 each training batch also carries that many branch groups (the
    same past under the episode's own and its counterfactual egos' futures, padded, with a member mask). Windows whose
    recorded future has another car braking harder than hard_braking are drawn hard_weight times as often, and those
    whose recorded future spans the whole horizon whole_weight times (the two factors multiply)."""

    def __init__(self, dataset_dir, batch_size, horizon, contrast_groups, hard_braking, hard_weight, whole_weight,
                 fraction):
        """horizon: H, steps of the recorded future per window (1 gives the one-step pairs only); contrast_groups:
        branch groups per training batch (0: none); hard_braking (m/s^2), hard_weight, whole_weight (-, 1: uniform);
        fraction: as WindowData's."""
        super().__init__(dataset_dir, batch_size, fraction)
        self.horizon, self.group_batch = horizon, contrast_groups
        self.hard_braking, self.hard_weight = float(hard_braking), float(hard_weight)  # > 0: core.validate
        self.whole_weight = float(whole_weight)

    def sampler(self):
        """Uniform shuffling, or a WeightedRandomSampler that favours the hard-braking windows (hard_weight != 1) and
        the windows with a whole recorded future (whole_weight != 1)."""
        if self.hard_weight == 1.0 and self.whole_weight == 1.0:
            return None
        X, ego, others, mask = (a.numpy() for a in self.splits["train"].tensors)
        hard = braking(X, ego, others, mask, dataset.read_meta(self.dataset_dir)["dt"]) > self.hard_braking
        w = np.where(hard, self.hard_weight, 1.0) * np.where(mask.all(axis=1), self.whole_weight, 1.0)
        return WeightedRandomSampler(torch.from_numpy(w), num_samples=len(w))

    def tensors(self, arrays):
        """The split's windows with their futures, float32; on the training split also its branch groups."""
        X, ego, others, mask = futures(arrays, self.horizon)
        arrays32 = (X, ego.astype(np.float32), others.astype(np.float32), mask)
        if self.group_batch and "train" not in self.splits:
            idx = groups(arrays, f"{self.dataset_dir}: contrast_groups={self.group_batch}")
            self.groups = TensorDataset(*(torch.from_numpy(a[np.maximum(idx, 0)]) for a in arrays32),
                                        torch.from_numpy(idx >= 0))
        return TensorDataset(*(torch.from_numpy(a) for a in arrays32))


class HypothesisSequenceData(SequenceData):
    """SequenceData's windows and futures of every run, flipped branches included, with each window's hypotheses (its
    run's latched decisions per slot, float (SLOTS,)) and each slot's weight in the belief's loss: 0 on a flipped run
    (its undecided cars hold the opposite of the world's population), encroached_weight on a car the ego has encroached
    on (where the decision can show; the rest teach the prior), 1 otherwise. Weighting by what a window shows keeps the
    belief calibrated within each kind."""

    hypotheses = True

    def __init__(self, dataset_dir, batch_size, horizon, contrast_groups, hard_braking, hard_weight, whole_weight,
                 fraction, encroached_weight):
        """As SequenceData's; encroached_weight (-): the belief loss's weight on cars the ego has encroached on."""
        super().__init__(dataset_dir, batch_size, horizon, contrast_groups, hard_braking, hard_weight, whole_weight, fraction)
        self.encroached_weight = float(encroached_weight)

    def tensors(self, arrays):
        """SequenceData's tensors, then the hypotheses and the belief weights."""
        base = super().tensors(arrays)
        w = np.where(arrays["since_encroach"] >= 0, self.encroached_weight, 1.0) * ~arrays["flipped"][:, None]
        return TensorDataset(*base.tensors, torch.from_numpy(arrays["will_yield"].astype(np.float32)),
                             torch.from_numpy(w.astype(np.float32)))


def groups(a, needed_by=None) -> np.ndarray:
    """Windows that share their past at a branch point, (G, S) indices padded with -1: the episode's own window at the
    step where a branch starts and each branch's first window (same history, different ego futures); needed_by: the
    option that needs them, named in the error when there are none (None: an empty result is fine)."""
    first = {}  # (episode, branch) -> index of the branch's first window
    for i, (e, b, s) in enumerate(zip(a["episode"].tolist(), a["branch"].tolist(), a["step"].tolist())):
        if b and ((e, b) not in first or s < a["step"][first[e, b]]):
            first[e, b] = i
    own = {(e, s): i for i, (e, b, s) in enumerate(zip(a["episode"].tolist(), a["branch"].tolist(), a["step"].tolist()))
           if b == 0}
    members = {}
    for (e, _), i in sorted(first.items()):
        j = own.get((e, int(a["step"][i])))
        if j is not None and np.array_equal(a["X"][i], a["X"][j]):  # a branch restarts from the episode's own state
            members.setdefault(j, [j]).append(i)
    if needed_by and not members:
        raise UserError(f"{needed_by} but the training split has no counterfactual branches (dataset.branches.points=0?)")
    width = max((len(m) for m in members.values()), default=0)
    return np.array([m + [-1] * (width - len(m)) for m in members.values()], dtype=np.int64).reshape(-1, width)


def braking(X, ego, others, mask, dt):
    """The hardest braking (m/s^2, >= 0) of another car over each window's recorded future (core.rollout.accelerations,
    the steps the run reached); X (n, T_obs, SLOTS, 2), ego (n, H, 2), others (n, H, N, 2), mask (n, H) as futures
    returns them."""
    a = accelerations(np.concatenate([ego[:, :, None], others], axis=2), X, dt)  # (n, N, H)
    return np.maximum(0.0, -np.where(mask[:, None, :], a, 0.0).min(axis=(1, 2)))


def futures(a, horizon):
    """Every window of split arrays `a` with the next `horizon` recorded steps of its run (episode and branch):
    X (n, T_obs, SLOTS, 2), ego (n, H, 2), others (n, H, N, 2), mask (n, H) of the steps the run reached with the
    same cars in its slots (the nearest cars change as the ego moves: a future never mixes cars)."""
    runs = list(zip(a["episode"], a["branch"], a["step"]))
    key = {r: i for i, r in enumerate(runs)}
    idx = np.array([[key.get((e, b, s + k), -1) for k in range(horizon)] for e, b, s in runs]).reshape(len(runs), horizon)
    same = (a["ids"][np.maximum(idx, 0)] == a["ids"][:, None]).all(-1)
    mask = np.cumprod((idx >= 0) & same, axis=1).astype(bool)  # stop at the first missing step or change of slots
    Y = a["Y"][np.where(mask, idx, 0)].astype(np.float64)  # (n, H, SLOTS, 2)
    ego = Y[:, :, 0]
    last, step = a["X"][:, -1, 0].astype(np.float64), (a["X"][:, -1, 0] - a["X"][:, -2, 0]).astype(np.float64)
    for k in range(horizon):  # beyond a run's end: the ego goes on at its last displacement, so windows stay plausible
        prev = ego[:, k - 1] if k else last
        prev2 = (ego[:, k - 2] if k > 1 else last) if k else last - step
        ego[:, k] = np.where(mask[:, k, None], ego[:, k], 2 * prev - prev2)
    return a["X"], ego, Y[:, :, 1:] * mask[:, :, None, None], mask


class DistillData(WindowData):
    """Windows relabelled by a teacher (next positions and v^T J), widened with planner-like copies of every window;
    with rollout_groups > 0 each training batch also carries that many branch groups (one past under the episode's own
    and its counterfactual egos' futures) with the teacher's rollouts under each."""

    def __init__(self, dataset_dir, batch_size, teacher, perturbed_copies, perturb, projections, seed, horizon,
                 rollout_groups, fraction):
        """teacher: a predictor with phi_vjp; perturb: planner_like's ranges; projections: cotangents v per window;
        horizon: steps of the teacher's branch rollouts; rollout_groups: branch groups per training batch (0: none);
        fraction: as WindowData's."""
        super().__init__(dataset_dir, batch_size, fraction)
        self.teacher, self.perturbed_copies, self.perturb, self.projections = teacher, perturbed_copies, dict(perturb), projections
        self.horizon, self.group_batch = horizon, rollout_groups
        self.rng = np.random.default_rng(seed)  # one stream for both splits, train first

    def tensors(self, arrays):
        """Dataset windows and their planner-like copies with the teacher's labels, float32; on the training split also
        its branch groups with the teacher's rollouts."""
        X = np.concatenate([arrays["X"]] + [planner_like(arrays["X"], self.rng, **self.perturb)
                                            for _ in range(self.perturbed_copies)])
        if self.group_batch and "train" not in self.splits:
            self.groups = TensorDataset(*(torch.from_numpy(a) for a in teacher_rollouts(self.teacher, arrays, self.horizon,
                                                                                     self.dataset_dir)))
        return TensorDataset(*(torch.tensor(a, dtype=torch.float32)
                               for a in (X, *label(self.teacher, X, self.rng, self.projections))))


def teacher_rollouts(teacher, arrays, horizon, where, chunk=1024):
    """The split's branch groups as float32 X (G, S, T_obs, SLOTS, 2) and ego futures (G, S, H, 2), the teacher's
    rollouts of the other cars under each (G, S, H, N, 2) and the member mask (G, S)."""
    idx = groups(arrays, f"{where}: rollout_groups > 0")
    X, ego, _, _ = futures(arrays, horizon)
    Xg, egog = X[np.maximum(idx, 0)].astype(float), ego[np.maximum(idx, 0)]
    flat_X, flat_ego = Xg.reshape(-1, *Xg.shape[2:]), egog.reshape(-1, *egog.shape[2:])
    target = np.concatenate([rollout(teacher.phi, flat_X[i:i + chunk], flat_ego[i:i + chunk])[:, :, 1:]
                             for i in range(0, len(flat_X), chunk)])
    return (Xg.astype(np.float32), egog.astype(np.float32), target.reshape(idx.shape + target.shape[1:]).astype(np.float32),
            idx >= 0)


class HypothesisDistillData(DistillData):
    """DistillData for a hypothesis student from a hypothesis teacher: every window under hypotheses drawn uniformly
    (each other slot yields with probability 1/2), the teacher's next and v^T J under them, and the teacher's belief."""

    hypotheses = True

    def tensors(self, arrays):
        """Windows and planner-like copies, their hypotheses, the teacher's labels under them and its belief, float32."""
        X = np.concatenate([arrays["X"]] + [planner_like(arrays["X"], self.rng, **self.perturb)
                                            for _ in range(self.perturbed_copies)])
        hyp = (self.rng.random(X.shape[:1] + X.shape[2:3]) < 0.5).astype(float)
        hyp[:, 0] = 0.0
        belief = np.concatenate([self.teacher.belief(X[i:i + 1024]) for i in range(0, len(X), 1024)])
        return TensorDataset(*(torch.tensor(a, dtype=torch.float32)
                               for a in (X, *label(self.teacher, X, self.rng, self.projections, hyp), hyp, belief)))


def label(teacher, X, rng, projections, hyp=None, chunk=1024):
    """Teacher next (n, SLOTS, 2), cotangents v (n, k, SLOTS, 2) (ego rows 0: the plan fills that slot), v^T J (n, k,
    T_obs*SLOTS*2); a hypothesis teacher under the hypotheses hyp (n, SLOTS)."""
    v = rng.standard_normal((len(X), projections) + X.shape[2:])
    v[:, :, 0] = 0.0
    given = (lambda i: teacher) if hyp is None else (lambda i: teacher.given(hyp[i : i + chunk]))
    parts = [given(i).phi_vjp(X[i : i + chunk], v[i : i + chunk]) for i in range(0, len(X), chunk)]
    return np.concatenate([p[0] for p in parts]), v, np.concatenate([p[1] for p in parts])
