"""Dataset windows as Lightning batches: (window, next) for the teacher; for the student (window, teacher next,
random cotangents v on the other cars' outputs, the teacher's v^T J), Jacobian matching by random projections."""
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, TensorDataset

from data import dataset
from distill.perturb import planner_like


class WindowData(L.LightningDataModule):
    """Train/val windows from data/<name>/ (metres); with a teacher, relabelled by it and widened with planner-like copies."""

    def __init__(self, dataset_dir, batch_size=256, teacher=None, perturbed_copies=1, perturb=None, projections=2, seed=0):
        """teacher: a predictor with phi_vjp, or None for the data's own next positions; perturb: planner_like's ranges."""
        super().__init__()
        self.dataset_dir, self.batch_size, self.teacher, self.projections = dataset_dir, batch_size, teacher, projections
        self.perturbed_copies, self.perturb, self.seed = perturbed_copies, dict(perturb or {}), seed
        self.splits = {}

    def setup(self, stage=None):
        """Load (and for the student, label) both splits once."""
        rng = np.random.default_rng(self.seed)
        for split in ("train", "val"):
            if split in self.splits:
                continue
            a = dataset.load(self.dataset_dir, split)
            if self.teacher is None:
                self.splits[split] = TensorDataset(torch.from_numpy(a["X"]), torch.from_numpy(a["Y"]))
                continue
            X = np.concatenate([a["X"]] + [planner_like(a["X"], rng, **self.perturb) for _ in range(self.perturbed_copies)])
            self.splits[split] = TensorDataset(*(torch.tensor(a, dtype=torch.float32)
                                                 for a in (X, *label(self.teacher, X, rng, self.projections))))

    def train_dataloader(self):
        """Shuffled training batches."""
        return DataLoader(self.splits["train"], batch_size=self.batch_size, shuffle=True)

    def val_dataloader(self):
        """Validation batches, in order."""
        return DataLoader(self.splits["val"], batch_size=4 * self.batch_size)


def label(teacher, X, rng, projections, chunk=1024):
    """Teacher next (n, SLOTS, 2), cotangents v (n, k, SLOTS, 2) (ego rows 0: the plan fills that slot), v^T J (n, k, T_obs*SLOTS*2)."""
    v = rng.standard_normal((len(X), projections) + X.shape[2:])
    v[:, :, 0] = 0.0
    parts = [teacher.phi_vjp(X[i : i + chunk], v[i : i + chunk]) for i in range(0, len(X), chunk)]
    return np.concatenate([p[0] for p in parts]), v, np.concatenate([p[1] for p in parts])
