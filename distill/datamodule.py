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
