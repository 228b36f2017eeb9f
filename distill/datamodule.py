"""Dataset windows as Lightning batches: (window, next) for the teacher; for the student (window, teacher next,
random cotangents v on the other cars' outputs, the teacher's v^T J), Jacobian matching by random projections."""
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, TensorDataset

from data import dataset
from distill.perturb import planner_like


class WindowData(L.LightningDataModule):
    """Train/val (window, next) pairs from data/<name>/ in metres, as recorded."""

    def __init__(self, dataset_dir, batch_size):
        """dataset_dir: a make-dataset folder; batch_size: training batch (validation uses 4x)."""
        super().__init__()
        self.dataset_dir, self.batch_size = dataset_dir, batch_size
        self.splits = {}

    def setup(self, stage=None):
        """Load (and label) both splits once."""
        for split in ("train", "val"):
            if split not in self.splits:
                self.splits[split] = self.tensors(dataset.load(self.dataset_dir, split))

    def tensors(self, arrays):
        """The split's training tensors: the recorded window and next positions."""
        return TensorDataset(torch.from_numpy(arrays["X"]), torch.from_numpy(arrays["Y"]))

    def train_dataloader(self):
        """Shuffled training batches."""
        return DataLoader(self.splits["train"], batch_size=self.batch_size, shuffle=True)

    def val_dataloader(self):
        """Validation batches, in order."""
        return DataLoader(self.splits["val"], batch_size=4 * self.batch_size)


class SequenceData(WindowData):
    """Train/val windows with the recorded futures of their run for a multi-step rollout loss: (window, ego future
    (H, 2), others' future (H, N, 2), mask (H,)); where the run ends early the ego continues at constant velocity
    and the mask is False."""

    def __init__(self, dataset_dir, batch_size, horizon):
        """horizon: H, steps of the recorded future per window (1 gives the one-step pairs only)."""
        super().__init__(dataset_dir, batch_size)
        self.horizon = horizon

    def tensors(self, arrays):
        """The split's windows with their futures, float32."""
        X, ego, others, mask = futures(arrays, self.horizon)
        return TensorDataset(*(torch.from_numpy(a) for a in (X, ego.astype(np.float32), others.astype(np.float32), mask)))


def futures(a, horizon):
    """Every window of split arrays `a` with the next `horizon` recorded steps of its run (episode and branch):
    X (n, T_obs, SLOTS, 2), ego (n, H, 2), others (n, H, N, 2), mask (n, H) of the steps the run reached."""
    runs = list(zip(a["episode"], a["branch"], a["step"]))
    key = {r: i for i, r in enumerate(runs)}
    idx = np.array([[key.get((e, b, s + k), -1) for k in range(horizon)] for e, b, s in runs]).reshape(len(runs), horizon)
    mask = np.cumprod(idx >= 0, axis=1).astype(bool)  # a run has no holes, but stop at the first missing step anyway
    Y = a["Y"][np.where(mask, idx, 0)].astype(np.float64)  # (n, H, SLOTS, 2)
    ego = Y[:, :, 0]
    last, step = a["X"][:, -1, 0].astype(np.float64), (a["X"][:, -1, 0] - a["X"][:, -2, 0]).astype(np.float64)
    for k in range(horizon):  # beyond a run's end: the ego goes on at its last displacement, so windows stay plausible
        prev = ego[:, k - 1] if k else last
        prev2 = (ego[:, k - 2] if k > 1 else last) if k else last - step
        ego[:, k] = np.where(mask[:, k, None], ego[:, k], 2 * prev - prev2)
    return a["X"], ego, Y[:, :, 1:] * mask[:, :, None, None], mask


class DistillData(WindowData):
    """Windows relabelled by a teacher (next positions and v^T J), widened with planner-like copies of every window."""

    def __init__(self, dataset_dir, batch_size, teacher, perturbed_copies, perturb, projections, seed):
        """teacher: a predictor with phi_vjp; perturb: planner_like's ranges; projections: cotangents v per window."""
        super().__init__(dataset_dir, batch_size)
        self.teacher, self.perturbed_copies, self.perturb, self.projections = teacher, perturbed_copies, dict(perturb), projections
        self.rng = np.random.default_rng(seed)  # one stream for both splits, train first

    def tensors(self, arrays):
        """Dataset windows and their planner-like copies with the teacher's labels, float32."""
        X = np.concatenate([arrays["X"]] + [planner_like(arrays["X"], self.rng, **self.perturb)
                                            for _ in range(self.perturbed_copies)])
        return TensorDataset(*(torch.tensor(a, dtype=torch.float32)
                               for a in (X, *label(self.teacher, X, self.rng, self.projections))))


def label(teacher, X, rng, projections, chunk=1024):
    """Teacher next (n, SLOTS, 2), cotangents v (n, k, SLOTS, 2) (ego rows 0: the plan fills that slot), v^T J (n, k, T_obs*SLOTS*2)."""
    v = rng.standard_normal((len(X), projections) + X.shape[2:])
    v[:, :, 0] = 0.0
    parts = [teacher.phi_vjp(X[i : i + chunk], v[i : i + chunk]) for i in range(0, len(X), chunk)]
    return np.concatenate([p[0] for p in parts]), v, np.concatenate([p[1] for p in parts])
