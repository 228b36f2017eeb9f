"""Dataset windows as Lightning batches: (window, next) for the teacher, (window, teacher next, teacher Jacobian) for the student."""
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, TensorDataset

from data import dataset
from distill.perturb import planner_like


class WindowData(L.LightningDataModule):
    """Train/val windows from data/<name>/ (metres); with a teacher, relabelled by it and widened with planner-like copies."""

    def __init__(self, dataset_dir, batch_size=256, teacher=None, perturbed_copies=1, perturb=None, seed=0):
        super().__init__()
        self.dataset_dir, self.batch_size, self.teacher = dataset_dir, batch_size, teacher
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
            nxt, J = label(self.teacher, X)
            self.splits[split] = TensorDataset(*(torch.tensor(v, dtype=torch.float32) for v in (X, nxt, J)))

    def train_dataloader(self):
        return DataLoader(self.splits["train"], batch_size=self.batch_size, shuffle=True)

    def val_dataloader(self):
        return DataLoader(self.splits["val"], batch_size=4 * self.batch_size)


def label(teacher, X, chunk=1024):
    """Teacher outputs (n, M, 2) and exact input-Jacobians (n, M*2, T_obs*M*2) on windows X, in chunks."""
    parts = [teacher.phi_jac(X[i : i + chunk]) for i in range(0, len(X), chunk)]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
