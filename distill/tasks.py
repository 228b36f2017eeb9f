"""Lightning tasks: fit the teacher to data, distil the student from the teacher on outputs and input-Jacobians.

Both hold their network as `self.net`, built by Hydra from its config dict, so a checkpoint alone rebuilds it.
Errors are measured on the other cars only (slots 1..N): the planner fills the ego slot from its own plan.
"""
import lightning as L
import torch
from hydra.utils import instantiate

from core.rollout import SLOTS, T_OBS, rollout
from distill.certificate import ego_columns, head_L, layer_recursion


class _Task(L.LightningModule):
    """Shared parts: the network from its config dict, AdamW with a cosine schedule over the run."""

    def __init__(self, net: dict, lr: float, weight_decay: float):
        """net: the network's Hydra config dict; lr, weight_decay for AdamW."""
        super().__init__()
        self.save_hyperparameters(logger=False)  # the job already logs the whole config to MLflow
        self.net = instantiate(net)

    def configure_optimizers(self):
        """AdamW, learning rate cosine-annealed to 0 over max_epochs."""
        opt = torch.optim.AdamW(self.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, self.trainer.max_epochs))
        return [opt], [sched]

    def training_step(self, batch, batch_idx):
        """Training loss of one batch."""
        return self._step(batch, "train")

    def validation_step(self, batch, batch_idx):
        """Validation loss of one batch."""
        self._step(batch, "val")

    def _log(self, stage, **values):
        """Log values as <stage>_<name>; validation values are averaged across DDP processes."""
        for k, v in values.items():
            self.log(f"{stage}_{k}", v, prog_bar=k in ("loss", "ade_m"), sync_dist=stage == "val")


class TeacherTask(_Task):
    """Huber loss of the other cars' one-step error in units of `scale_m` metres (collisions make heavy tails), plus
    `rollout_weight` x the Huber loss in units of `rollout_scale_m` of the Remark-2 rollout over the recorded horizon
    fed the recorded ego future: how the others answer the ego's moves is what the planner asks of the teacher. The
    rollout unit is wide so that the term is quadratic over the range of real responses and fits their mean, where
    a centimetre unit (an L1 loss in effect) would fit the median and miss the rare hard-braking answers.
    With `brake_weight`, plus that times the Huber loss in units of `brake_scale` (m/s^2) of each other car's hardest
    braking over the rollout, predicted against recorded: the figure the interactive step reads. A cut-in makes the
    car behind brake once, hard, at a step a window fixes only to within a step or two; positions alone are fit best by
    a braking spread over those steps, whose peak is a fraction of the world's."""

    def __init__(self, net: dict, lr: float, weight_decay: float, scale_m: float, rollout_weight: float,
                 rollout_scale_m: float, contrast_weight: float, brake_weight: float, brake_scale: float, dt: float):
        """scale_m, rollout_scale_m: loss units (m) of the one-step and rollout terms; rollout_weight, contrast_weight,
        brake_weight (-); brake_scale: the braking term's unit (m/s^2); dt: the data's step (s)."""
        super().__init__(net, lr, weight_decay)

    def _step(self, batch, stage):
        """Loss on (window, ego future, others' future, mask) and the logged one-step and rollout ADE (m); with branch
        groups (a dict batch) plus contrast_weight x their contrast loss."""
        if isinstance(batch, dict):
            contrast = self.contrast(*batch["groups"])
            loss = self._step(batch["windows"], stage) + self.hparams.contrast_weight * contrast
            self._log(stage, contrast=contrast)
            return loss
        X, ego, others, mask = batch[:4]
        horizon = ego.shape[1] if self.hparams.rollout_weight else 1
        mask = mask[:, :horizon, None, None]
        err = (rollout(self.phi(batch), X, ego[:, :horizon])[:, :, 1:] - others[:, :horizon]) * mask  # (B, H, N, 2) m
        loss = torch.nn.functional.huber_loss(err[:, 0] / self.hparams.scale_m, torch.zeros_like(err[:, 0]))
        dist = err.norm(dim=-1).mean(-1)  # (B, H) m
        values = {"ade_m": dist[:, 0].mean()}
        if horizon > 1:
            later = err[:, 1:] / self.hparams.rollout_scale_m
            huber = torch.nn.functional.huber_loss(later, torch.zeros_like(later), reduction="sum")
            loss = loss + self.hparams.rollout_weight * huber / mask[:, 1:].expand_as(later).sum().clamp(min=1)
            values["ade_rollout_m"] = dist.sum() / mask.sum()
            if self.hparams.brake_weight:
                pred, true = (hardest_braking(X, f, mask[:, :, 0, 0], self.hparams.dt) for f in (err + others[:, :horizon], others[:, :horizon]))
                values["brake_err"] = (pred - true).abs().mean()
                loss = loss + self.hparams.brake_weight * torch.nn.functional.huber_loss(
                    pred / self.hparams.brake_scale, true / self.hparams.brake_scale)
        loss = loss + self.extra_loss(batch, values)
        self._log(stage, loss=loss, **values)
        return loss

    def phi(self, batch):
        """The one-step predictor of the batch's rollouts: the network."""
        return self.net

    def extra_loss(self, batch, values):
        """A subclass's further loss terms on the batch, its logged parts added to `values`: none."""
        return 0.0

    def contrast(self, X, ego, others, mask, member):
        """branch_contrast of the rollouts of each branch group against the recorded futures, in rollout_scale_m units.
        X (G, S, T_obs, SLOTS, 2), ego (G, S, H, 2), others (G, S, H, N, 2), mask (G, S, H), member (G, S)."""
        pred = group_rollout(self.net, X, ego)
        return branch_contrast(pred, others, member[:, :, None] & mask, self.hparams.rollout_scale_m)


def hardest_braking(X, others, mask, dt):
    """Each other car's hardest braking (B, N) in m/s^2 (0 if none) over its future xy `others` (B, H, N, 2) after the
    windows X (B, T_obs, SLOTS, 2): second differences of x, the last two observed steps first, over the steps `mask`
    (B, H) keeps."""
    x = torch.cat([X[:, -2:, 1:, 0], others[..., 0]], dim=1)  # (B, H + 2, N)
    acc = (x[:, 2:] - 2.0 * x[:, 1:-1] + x[:, :-2]) / dt**2
    return torch.relu(-torch.where(mask[:, :, None].bool(), acc, torch.zeros_like(acc)).amin(dim=1))


def group_rollout(net, X, ego):
    """The others' Remark-2 rollouts (G, S, H, N, 2) of branch groups: windows X (G, S, T_obs, SLOTS, 2) under ego
    futures (G, S, H, 2)."""
    G, S = X.shape[:2]
    return rollout(net, X.flatten(0, 1), ego.flatten(0, 1))[:, :, 1:].unflatten(0, (G, S))


def branch_contrast(pred, target, valid, scale_m):
    """Mean squared error, in units of scale_m, of each branch group's futures about the group's mean: the predicted
    difference the ego's choice makes against the target's, what react_corr and react_gain score. pred, target
    (G, S, H, N, 2); valid (G, S, H): the members and steps that count."""
    w = valid.to(pred.dtype)[..., None, None]

    def about_mean(v):
        return (v - (v * w).sum(1, keepdim=True) / w.sum(1, keepdim=True).clamp(min=1)) * w

    dev = (about_mean(pred) - about_mean(target)) / scale_m
    return dev.pow(2).sum() / (w.sum() * dev.shape[-2] * dev.shape[-1]).clamp(min=1)


class StudentTask(_Task):
    """Sobolev distillation: squared output error / scale_m^2 + jac_weight * squared error of the random projections
    v^T J (an unbiased estimate of the Jacobian error's Frobenius norm) + the spectral penalty; with branch groups (a
    dict batch), the teacher's rollouts too: rollout_weight x their squared error and contrast_weight x their
    branch_contrast, in rollout_scale_m units. One-step outputs and Jacobians alone carried only about half the
    teacher's response to the ego into the student: it builds up over the rollout, where one-step errors compound."""

    def __init__(self, net: dict, lr: float, weight_decay: float, scale_m: float, jac_weight: float,
                 ego_jac_weight: float, spectral_weight: float, cert_weight: float, rollout_weight: float,
                 contrast_weight: float, rollout_scale_m: float):
        """scale_m: output loss unit (m); weights of the Jacobian term, of its ego columns, of the spectral penalty, of
        the log of the certified A3 constant L (Theorem 1's rho grows with it), of the teacher-rollout and branch-
        contrast terms; rollout_scale_m: their loss unit (m)."""
        super().__init__(net, lr, weight_decay)
        # d others / d ego is small beside the others' own dynamics, yet it is the interaction the planner uses
        columns = torch.ones(T_OBS, SLOTS, 2)
        columns[:, 0] = ego_jac_weight
        self.register_buffer("columns", columns.reshape(-1), persistent=False)

    def spectral_penalty(self):
        """Sum of log spectral norms of the layers (first with P folded): the log of the certificate's product."""
        norms = [torch.linalg.matrix_norm(self.first_weight() if k == 0 else layer.weight, ord=2)
                 for k, layer in enumerate(self.net.layers)]
        return torch.stack(norms).log().sum()

    def first_weight(self):
        """The first layer's weight on the window in metres (P folded in; a hypothesis student's further columns, its
        hypothesis inputs, only shift the bias)."""
        return self.net.layers[0].weight[:, :self.net.P.shape[0]] @ self.net.P

    def certified_L(self):
        """distill.certificate.constants' L (m^-1), differentiable: the same layer recursion on torch weights."""
        layers = self.net.layers
        hidden = [self.first_weight()[:, ego_columns()], *(layer.weight for layer in layers[1:-1])]
        lip, hess = layer_recursion(hidden, lambda W: torch.linalg.matrix_norm(W, ord=2), lambda W: W.norm(dim=1))
        return head_L(self.net.s, layers[-1].weight.norm(dim=1), lip, hess).max()

    def _step(self, batch, stage):
        """Loss on (window, teacher next, cotangents v, teacher v^T J) and its logged parts; a dict batch adds its branch
        groups' teacher-rollout terms."""
        if isinstance(batch, dict):
            X, ego, target, member = batch["groups"]
            pred = group_rollout(self.net, X, ego)
            w = member.to(pred.dtype)[:, :, None, None, None]
            rollout_loss = (((pred - target) * w / self.hparams.rollout_scale_m).pow(2).sum()
                            / (w.sum() * pred[0, 0].numel()).clamp(min=1))
            contrast = branch_contrast(pred, target, member[:, :, None].expand(pred.shape[:3]), self.hparams.rollout_scale_m)
            self._log(stage, rollout_loss=rollout_loss, contrast=contrast)
            return (self._step(batch["windows"], stage) + self.hparams.rollout_weight * rollout_loss
                    + self.hparams.contrast_weight * contrast)
        X, y_t, v, vJ_t = batch[:4]
        X = X.requires_grad_()
        y_s = self.phi(batch)(X)
        vJ_s = torch.stack([torch.autograd.grad(y_s, X, v[:, k], create_graph=True)[0].flatten(1)
                            for k in range(v.shape[1])], dim=1)
        err = (y_s - y_t)[:, 1:]
        out_loss = (err / self.hparams.scale_m).pow(2).mean()
        jac_loss = ((vJ_s - vJ_t).pow(2) * self.columns).mean()
        loss = out_loss + self.hparams.jac_weight * jac_loss
        if self.hparams.spectral_weight:
            loss = loss + self.hparams.spectral_weight * self.spectral_penalty()
        if self.hparams.cert_weight:
            loss = loss + self.hparams.cert_weight * self.certified_L().log()
        parts = {}
        loss = loss + self.extra_loss(batch, parts)
        self._log(stage, **parts)
        self._log(stage, loss=loss, out_loss=out_loss, jac_loss=jac_loss, ade_m=err.norm(dim=-1).mean())
        return loss

    def validation_step(self, batch, batch_idx):
        """Validation loss; the Jacobian term needs autograd even here."""
        with torch.enable_grad():
            self._step(batch, "val")

    def phi(self, batch):
        """The one-step predictor the batch's outputs and Jacobians are matched on: the network."""
        return self.net

    def extra_loss(self, batch, values):
        """A subclass's further loss terms on the batch, its logged parts added to `values`: none."""
        return 0.0


def belief_bce(net, X, target, weight):
    """Weighted mean binary cross-entropy (-) of the network's belief about slots 1..N against target probabilities
    (B, SLOTS) (a latched label, or a teacher's belief), weights (B, SLOTS)."""
    bce = torch.nn.functional.binary_cross_entropy_with_logits(net.belief_logit(X)[:, 1:], target[:, 1:], reduction="none")
    w = weight[:, 1:].to(bce.dtype)
    return (bce * w).sum() / w.sum().clamp(min=1e-9)


class HypothesisTeacherTask(TeacherTask):
    """TeacherTask on batches (window, ego future, others' future, mask, hypotheses (B, SLOTS), belief weights (B, SLOTS)):
    every rollout under its run's latched decisions (on a flipped branch, its flipped ones), plus belief_weight x the
    belief's binary cross-entropy against those decisions (datamodule.HypothesisSequenceData's weights: the factual runs
    only, as a flipped branch would teach the belief its flipped rate)."""

    def __init__(self, net: dict, lr: float, weight_decay: float, scale_m: float, rollout_weight: float,
                 rollout_scale_m: float, contrast_weight: float, brake_weight: float, brake_scale: float, dt: float,
                 belief_weight: float):
        """As TeacherTask's; belief_weight (-): the belief term's weight."""
        super().__init__(net, lr, weight_decay, scale_m, rollout_weight, rollout_scale_m, contrast_weight, brake_weight,
                         brake_scale, dt)

    def phi(self, batch):
        """The network under the batch's hypotheses."""
        hyp = batch[4]
        return lambda window: self.net(window, hyp)

    def extra_loss(self, batch, values):
        """belief_weight x the belief's weighted cross-entropy."""
        values["belief_bce"] = belief_bce(self.net, batch[0], batch[4], batch[5])
        return self.hparams.belief_weight * values["belief_bce"]


class HypothesisStudentTask(StudentTask):
    """StudentTask on batches (window, teacher next, v, teacher v^T J, hypotheses (B, SLOTS), teacher belief (B, SLOTS)):
    outputs and Jacobians matched under each window's hypotheses, plus belief_weight x the cross-entropy of the
    student's belief against the teacher's."""

    def __init__(self, net: dict, lr: float, weight_decay: float, scale_m: float, jac_weight: float,
                 ego_jac_weight: float, spectral_weight: float, cert_weight: float, rollout_weight: float,
                 contrast_weight: float, rollout_scale_m: float, belief_weight: float):
        """As StudentTask's; belief_weight (-): the belief term's weight."""
        super().__init__(net, lr, weight_decay, scale_m, jac_weight, ego_jac_weight, spectral_weight, cert_weight,
                         rollout_weight, contrast_weight, rollout_scale_m)

    def phi(self, batch):
        """The network under the batch's hypotheses."""
        hyp = batch[4]
        return lambda window: self.net(window, hyp)

    def extra_loss(self, batch, values):
        """belief_weight x the belief's cross-entropy against the teacher's."""
        X = batch[0].detach()
        values["belief_bce"] = belief_bce(self.net, X, batch[5], torch.ones_like(batch[5]))
        return self.hparams.belief_weight * values["belief_bce"]
