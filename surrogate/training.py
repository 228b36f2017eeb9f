"""Lightning pieces: Jacobian data as a DataModule, the regression as a LightningModule (loss in standardised units)."""
import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, TensorDataset

from surrogate.network import JacobianNet


def rel_err(J_hat, J):
    """Mean over windows of ||J_hat - J||_F / ||J||_F (dimensionless); torch or numpy."""
    dims = tuple(range(1, J.ndim))
    if isinstance(J, torch.Tensor):
        return ((J_hat - J).square().sum(dims).sqrt() / J.square().sum(dims).sqrt().clamp_min(1e-12)).mean()
    return float(np.mean(np.sqrt(((J_hat - J) ** 2).sum(dims)) / np.maximum(np.sqrt((J**2).sum(dims)), 1e-12)))


class JacobianData(L.LightningDataModule):
    """Windows (n, T_obs, SLOTS, 2) m with their Jacobians (n, SLOTS*2, T_obs*SLOTS*2) for train and val, in float32 batches."""

    def __init__(self, train, val, batch_size):
        super().__init__()
        self.train_set = TensorDataset(*(torch.as_tensor(a, dtype=torch.float32) for a in train))
        self.val_set = TensorDataset(*(torch.as_tensor(a, dtype=torch.float32) for a in val))
        self.batch_size = batch_size

    def train_dataloader(self):
        """Shuffled training batches (window, J)."""
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True)

    def val_dataloader(self):
        """Validation in large batches (window, J)."""
        return DataLoader(self.val_set, batch_size=4096)


class SurrogateModule(L.LightningModule):
    """Fits JacobianNet by mean squared error of the standardised Jacobian; logs train/val loss and val_jac_rel_err."""

    def __init__(self, net: JacobianNet, lr, weight_decay):
        super().__init__()
        self.net, self.lr, self.weight_decay = net, lr, weight_decay

    def loss(self, window, J):
        """MSE in units of the per-entry training std, so the small interaction entries count as much as the big ones."""
        target = (J.flatten(1) - self.net.J_mean) / self.net.J_std
        return torch.nn.functional.mse_loss(self.net.standardised(window), target)

    def training_step(self, batch, _):
        """Standardised MSE of one batch."""
        loss = self.loss(*batch)
        self.log("train_loss", loss, prog_bar=True)
        return loss

    def validation_step(self, batch, _):
        """Standardised MSE and relative Frobenius error of the Jacobian."""
        window, J = batch
        self.log("val_loss", self.loss(window, J), prog_bar=True)
        self.log("val_jac_rel_err", rel_err(self.net(window), J))

    def configure_optimizers(self):
        """AdamW with a one-cycle learning rate over the whole run."""
        opt = torch.optim.AdamW(self.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        steps = self.trainer.estimated_stepping_batches
        return {"optimizer": opt, "lr_scheduler": {"scheduler": torch.optim.lr_scheduler.OneCycleLR(opt, self.lr, total_steps=steps), "interval": "step"}}
