"""Lightning pieces: Jacobian data as a DataModule, the regression as a LightningModule (loss in standardised units,
optionally plus the error of the others' reaction d p_i / d Z composed over whole planning states)."""
import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities import CombinedLoader
from torch.utils.data import DataLoader, TensorDataset

from core.rollout import chain_rule
from surrogate.evaluate import along_ramps
from surrogate.network import JacobianNet


def rel_err(J_hat, J):
    """Mean over windows of ||J_hat - J||_F / ||J||_F (dimensionless); torch or numpy."""
    dims = tuple(range(1, J.ndim))
    if isinstance(J, torch.Tensor):
        return ((J_hat - J).square().sum(dims).sqrt() / J.square().sum(dims).sqrt().clamp_min(1e-12)).mean()
    return float(np.mean(np.sqrt(((J_hat - J) ** 2).sum(dims)) / np.maximum(np.sqrt((J**2).sum(dims)), 1e-12)))


def reaction(J):
    """The others' d p_i / d Z (n, T_p, N, 2, T_p, 2) m/m composed from the local Jacobians (n, T_p, SLOTS*2,
    T_obs*SLOTS*2) of the windows each planning state's rollout visits: what the predictor adds to d b_i / d Z."""
    return chain_rule(J)[:, :, 1:]


def tensors(*arrays):
    """A float32 TensorDataset of numpy arrays."""
    return TensorDataset(*(torch.as_tensor(np.asarray(a), dtype=torch.float32) for a in arrays))


class JacobianData(L.LightningDataModule):
    """Windows (n, T_obs, SLOTS, 2) m with their Jacobians (n, SLOTS*2, T_obs*SLOTS*2) for train and val, in float32
    batches; with `states` (train, val), each a tuple (windows (n, T_p, T_obs, SLOTS, 2), reaction (n, T_p, N, 2, T_p, 2)),
    also whole planning states, `state_batch` to a batch, beside the windows."""

    def __init__(self, train, val, batch_size, states=None, state_batch=64):
        super().__init__()
        self.train_set, self.val_set = tensors(*train), tensors(*val)
        self.states = None if states is None else tuple(tensors(*s) for s in states)
        self.batch_size, self.state_batch = batch_size, state_batch

    def train_dataloader(self):
        """Shuffled training batches (window, J), or {"local": (window, J), "states": (windows, reaction)}."""
        local = DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True)
        if self.states is None:
            return local
        states = DataLoader(self.states[0], batch_size=self.state_batch, shuffle=True)
        return CombinedLoader({"local": local, "states": states}, mode="max_size_cycle")

    def val_dataloader(self):
        """Validation in large batches: (window, J), then (windows, reaction) of the planning states if any."""
        local = DataLoader(self.val_set, batch_size=4096)
        return local if self.states is None else [local, DataLoader(self.states[1], batch_size=4096)]


class SurrogateModule(L.LightningModule):
    """Fits JacobianNet by mean squared error of the standardised Jacobian, plus `composed` times the squared relative
    error of the reaction composed over whole planning states; logs train/val losses, val_jac_rel_err, val_react_rel_err."""

    def __init__(self, net: JacobianNet, lr, weight_decay, composed):
        super().__init__()
        self.net, self.lr, self.weight_decay, self.composed = net, lr, weight_decay, composed

    def loss(self, window, J):
        """MSE in units of the per-entry training std, so the small interaction entries count as much as the big ones."""
        target = (J.flatten(1) - self.net.J_mean) / self.net.J_std
        return torch.nn.functional.mse_loss(self.net.standardised(window), target)

    def reaction(self, windows):
        """The reaction (n, T_p, N, 2, T_p, 2) composed from the network's Jacobians on states' windows (n, T_p, T_obs, SLOTS, 2)."""
        J = self.net(windows.flatten(0, 1))
        return reaction(J.unflatten(0, windows.shape[:2]))

    def reaction_loss(self, windows, target):
        """Squared relative error of the composed reaction along ramps (surrogate.evaluate), pooled over the batch's
        states (dimensionless): the error the planner sees, where a local error early in the horizon is carried through
        every later step. Pooled, not per state: each state's own relative error diverges on the states where the plan
        barely moves anyone (docs/archive/2026-11-studies.md, "The reaction where there is one")."""
        e, t = along_ramps(self.reaction(windows) - target), along_ramps(target)
        return e.square().sum() / t.square().sum().clamp_min(1e-12)

    def training_step(self, batch, _):
        """Standardised MSE of one batch, plus the weighted reaction loss when planning states come along."""
        if not isinstance(batch, dict):
            loss = self.loss(*batch)
        else:
            local, states = self.loss(*batch["local"]), self.reaction_loss(*batch["states"])
            self.log("train_reaction_loss", states)
            loss = local + self.composed * states
        self.log("train_loss", loss, prog_bar=True)
        return loss

    def validation_step(self, batch, _, dataloader_idx=0):
        """Standardised MSE and relative Frobenius error of the Jacobian; for planning states, the reaction's pooled
        relative error."""
        if dataloader_idx == 1:
            self.log("val_react_rel_err", self.reaction_loss(*batch).sqrt(), add_dataloader_idx=False)
            return
        window, J = batch
        self.log("val_loss", self.loss(window, J), prog_bar=True, add_dataloader_idx=False)
        self.log("val_jac_rel_err", rel_err(self.net(window), J), add_dataloader_idx=False)

    def configure_optimizers(self):
        """AdamW with a one-cycle learning rate over the whole run."""
        opt = torch.optim.AdamW(self.parameters(), lr=self.lr, weight_decay=self.weight_decay)
        steps = self.trainer.estimated_stepping_batches
        return {"optimizer": opt, "lr_scheduler": {"scheduler": torch.optim.lr_scheduler.OneCycleLR(opt, self.lr, total_steps=steps), "interval": "step"}}
