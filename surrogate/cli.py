"""`surrogate`: Jacobian data from the source predictor, train the gradient network, export ONNX, log to MLflow."""
import copy
import logging
from pathlib import Path

import hydra
import lightning as L
import mlflow
import mlflow.onnx
import numpy as np
import onnx
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from lightning.pytorch.loggers import MLFlowLogger
from omegaconf import DictConfig

from core import validate
from core.jobs import CONF_DIR, UserError, console, guarded, made_models, mlflow_run, sha256, staged, writable
from data import dataset
from distill.metrics import time_us
from distill.predictors import ConstantVelocity
from distill.train import quiet_lightning_tips
from surrogate import evaluate, jacobians, models
from surrogate.export import export
from surrogate.network import Fused
from surrogate.training import JacobianData, reaction, rel_err

log = logging.getLogger(__name__)


def instantiate_user(node, **kwargs):
    """hydra.utils.instantiate, letting a UserError from the target through as itself (one line, exit 2)."""
    try:
        return instantiate(node, **kwargs)
    except InstantiationException as e:
        if isinstance(e.__cause__, UserError):
            raise e.__cause__ from None
        raise


def windows_and_jacobians(cfg, source, sampler, X, n_dataset, n_states, rng, extra=None):
    """(windows, J) of one split's windows X: up to n_dataset of them plus every rollout window of n_states planning
    states and of the `extra` ones (history, ego_future), which come last, state-major."""
    own = X[rng.permutation(len(X))[:n_dataset]]
    history, ego_future = sampler.sample(X[rng.integers(0, len(X), n_states)], rng)
    if extra is not None:
        history, ego_future = np.concatenate([history, extra[0]]), np.concatenate([ego_future, extra[1]])
    W = np.concatenate([own, jacobians.planner_windows(source.phi, history, ego_future)])
    if cfg.jacobian == "autodiff":
        return W, jacobians.autodiff(source, W)
    return W, jacobians.central(source.phi, W, cfg.central_h)


def load_iterates(folder, T_obs, M, T_p) -> list:
    """[(history (n, T_obs, M, 2), ego_future (n, T_p, 2))] m, one per episode file of `folder` in name order: the
    states a planner linearised at (`planner record_dir=...`); a UserError naming the folder or file otherwise."""
    files = sorted(Path(folder).glob("*.npz"))
    if not files:
        raise UserError(f"data.iterates={folder}: no .npz episode files there (record them with `planner record_dir=...`)")
    out = []
    for f in files:
        try:
            with np.load(f) as d:
                history, ego_future = d["history"].astype(np.float64), d["ego_future"].astype(np.float64)
        except Exception as e:  # numpy raises several types for a damaged file (BadZipFile, OSError, EOFError, ...)
            raise UserError(f"{f}: not a recorded planner episode ({type(e).__name__}: {e})") from None
        if history.shape[1:] != (T_obs, M, 2) or ego_future.shape[1:] != (T_p, 2) or len(history) != len(ego_future):
            raise UserError(f"{f}: history {history.shape} and ego_future {ego_future.shape}, expected (n, {T_obs}, {M}, 2) "
                            f"and (n, {T_p}, 2): recorded with another T_obs, n_slots or T_p")
        if not (np.isfinite(history).all() and np.isfinite(ego_future).all()):
            raise UserError(f"{f}: non-finite positions")
        out.append((history, ego_future))
    return out


def pick(episodes, n, rng):
    """(history, ego_future) of n states drawn without replacement from the pooled episodes (all of them if fewer)."""
    history, ego_future = (np.concatenate(a) for a in zip(*episodes))
    chosen = rng.permutation(len(history))[:n]
    return history[chosen], ego_future[chosen]


def planning_states(split, n_states, T_p):
    """(windows (n, T_p, T_obs, SLOTS, 2), reaction (n, T_p, N, 2, T_p, 2)) of the n_states planning states at the end
    of a split from windows_and_jacobians, for the composed reaction loss."""
    W, J = (a[len(a) - n_states * T_p:].reshape((n_states, T_p) + a.shape[1:]) for a in split)
    return W, reaction(J)


def per_state(n, a):
    """(n * T_p, ...) state-major rows -> (n, T_p, ...)."""
    return a.reshape((n, -1) + a.shape[1:])


def time_autodiff(cfg, window):
    """Microseconds per exact local Jacobian at batch 1 for each trained predictor present (teacher, student)."""
    out = {}
    for name in cfg.timing.predictors:
        try:
            predictor = instantiate_user(cfg.predictor, name=name)
        except UserError:
            continue  # not trained here: nothing to time
        out[f"{name}_autodiff_us"] = time_us(predictor.phi_jac, window, cfg.timing.repeats, cfg.timing.budget_s)
    return out


def student_jacobians(cfg, W, surrogate, history, ego_future) -> dict:
    """When models_dir holds a distilled student (and it is not the surrogate's source): {"_student": its local Jacobians
    on windows W (n, T_p, ...), so that its d b_i / dZ is scored on the same planning states as the surrogate's;
    "_over_student": the planner's default pairing, the student's own rollout (n, T_p, ...) with the surrogate's
    Jacobians on its windows}. {} otherwise."""
    if cfg.source == "student":
        return {}
    try:
        student = instantiate_user(cfg.predictor, name="student")
    except UserError:
        return {}
    n, W_s = len(history), jacobians.planner_windows(student.phi, history, ego_future)
    return {"_student": per_state(n, student.phi_jac(W)[1]),
            "_over_student": tuple(per_state(n, a) for a in (W_s, student.phi(W_s), surrogate.jac(W_s)))}


@guarded
def run(cfg: DictConfig) -> dict:
    """Check every input, make the data, train, export, evaluate; models/surrogate.onnx is replaced only when all succeeded.
    Returns the logged metrics."""
    validate.check(cfg, "surrogate")
    writable(cfg.models_dir, "models_dir")
    X = {split: dataset.load(cfg.dataset_dir, split)["X"].astype(np.float64) for split in ("train", "val", "test")}
    L.seed_everything(cfg.seed, workers=True, verbose=False)  # the network's initialisation and batch order
    rng = np.random.default_rng(cfg.seed)
    source = instantiate_user(cfg.predictor)
    learned = Path(cfg.models_dir) / f"{cfg.source}.ckpt"  # the planner refuses the surrogate beside any other bytes
    learned = sha256(learned) if learned.is_file() else ""
    if cfg.fused and not hasattr(source, "module"):
        raise UserError(f"fused=true exports the source's torch network, and {cfg.source} has none: use fused=false")
    sampler = instantiate(cfg.states)
    with mlflow_run("surrogate", cfg, run_name=f"surrogate-of-{cfg.source}-seed{cfg.seed}", source=cfg.source) as run, \
            staged(cfg.models_dir) as stage:
        iterates = test_iterates = None
        if cfg.data.iterates:
            episodes = load_iterates(cfg.data.iterates, *X["train"].shape[1:3], cfg.paper.T_p)
            if len(episodes) <= cfg.data.test_iterate_episodes:
                raise UserError(f"data.iterates={cfg.data.iterates}: {len(episodes)} episode files, and "
                                f"data.test_iterate_episodes={cfg.data.test_iterate_episodes} of them are held out: "
                                "record more episodes")
            iterates = pick(episodes[:-cfg.data.test_iterate_episodes], cfg.data.iterate_states, rng)
            test_iterates = pick(episodes[-cfg.data.test_iterate_episodes:], cfg.data.test_plan_states, rng)
        train = windows_and_jacobians(cfg, source, sampler, X["train"], cfg.data.dataset_windows, cfg.data.plan_states, rng,
                                      iterates)
        val = windows_and_jacobians(cfg, source, sampler, X["val"], cfg.data.val_dataset_windows, cfg.data.val_plan_states, rng)
        T_obs, M = train[0].shape[1:3]
        net = instantiate(cfg.network, T_obs=T_obs, M=M)
        net.fit_normalisation(*train)
        logger = MLFlowLogger(experiment_name="surrogate", tracking_uri=mlflow.get_tracking_uri(), run_id=run.info.run_id)
        quiet_lightning_tips()
        trainer = instantiate(cfg.trainer, logger=logger, default_root_dir=cfg.out_dir)
        states = None
        if cfg.module.composed:
            states = (planning_states(train, cfg.data.plan_states + (0 if iterates is None else len(iterates[0])), cfg.paper.T_p),
                      planning_states(val, cfg.data.val_plan_states, cfg.paper.T_p))
        data = JacobianData(train, val, cfg.data.batch_size, states, cfg.data.state_batch)
        trainer.fit(instantiate(cfg.module, net=net), datamodule=data)

        net = net.eval()
        module = Fused(net, copy.deepcopy(source.module)) if cfg.fused else net
        export(copy.deepcopy(module), stage / "surrogate.onnx", T_obs, M, cfg.source, learned)
        surrogate = models.load(stage, T_obs, M - 1)

        test = X["test"]
        if test_iterates is not None:  # the planner's own states in held-out episodes, where its gradients are used
            history, ego_future = test_iterates
        else:
            history, ego_future = sampler.sample(test[rng.integers(0, len(test), cfg.data.test_plan_states)], rng)
        W = jacobians.planner_windows(source.phi, history, ego_future)  # (n * T_p, T_obs, SLOTS, 2), state-major
        J, J_hat = jacobians.autodiff(source, W), surrogate.jac(W)
        J_mean = np.broadcast_to(net.J_mean.double().numpy().reshape(J.shape[1:]), J.shape)
        J_cv = ConstantVelocity().phi_jac(W)[1]
        with torch.no_grad():
            with_torch = net(torch.as_tensor(W, dtype=torch.float32)).double().numpy()
            outside = float(net.outside(torch.as_tensor(W, dtype=torch.float32)).double().mean())
        metrics = {"jac_rel_err": rel_err(J_hat, J), "jac_rel_err_mean": rel_err(J_mean, J),
                   "jac_rel_err_cv": rel_err(J_cv, J), "onnx_max_abs_err": float(np.abs(J_hat - with_torch).max()),
                   "outside_box_share": outside}

        R = cfg.paper.safety.r + cfg.paper.safety.r_i + cfg.paper.safety.eps
        n = len(history)
        J_hats = {k: per_state(n, v) for k, v in {"": J_hat, "_mean": J_mean, "_cv": J_cv}.items()} | \
            student_jacobians(cfg, W, surrogate, history, ego_future)
        scores = evaluate.gradient_accuracy(per_state(n, W), per_state(n, source.phi(W)), per_state(n, J), J_hats,
                                            history, ego_future, R)
        metrics.update({evaluate.metric(k, suffix, e): x for suffix, s in scores.items() for k, v in s.items()
                        for e, x in zip(evaluate.ENDS, v)})

        window = test[:1]
        metrics["forward_us"] = time_us(surrogate.jac, window, cfg.timing.repeats, cfg.timing.budget_s)
        if surrogate.fused:
            metrics["fused_us"] = time_us(surrogate.phi_jac, window, cfg.timing.repeats, cfg.timing.budget_s)
        metrics["source_autodiff_us"] = time_us(source.phi_jac, window, cfg.timing.repeats, cfg.timing.budget_s)
        metrics.update(time_autodiff(cfg, window))
        metrics.update({"n_train": len(train[0]), "n_val": len(val[0]), "n_test": len(W)})
        mlflow.log_metrics(metrics)
        made_models([stage / "surrogate.onnx"])
        # the predictor it was trained for beside it: a runs:/<this run> models_dir is a set the planner can use whole
        for f in (f"{cfg.source}.ckpt", "certificate.json"):
            if (Path(cfg.models_dir) / f).exists():
                mlflow.log_artifact(str(Path(cfg.models_dir) / f), "models")
        mlflow.onnx.log_model(onnx.load(str(stage / "surrogate.onnx")), name="surrogate", pip_requirements=["onnxruntime"])
    path = Path(cfg.models_dir) / "surrogate.onnx"
    log.info(f"surrogate of {cfg.source} ({cfg.jacobian}) -> {path}: {len(train[0])} train windows; on {n} held-out planning "
             f"states ({'the planner iterates' if cfg.data.iterates else 'sampled'}), relative errors of the surrogate (cv, mean-J):"
             + "".join(f" {k} {metrics[k]:.3f} ({metrics[k + '_cv']:.3f}, {metrics[k + '_mean']:.3f});"
                       for k in evaluate.HEADLINE) +
             f" local J {metrics['jac_rel_err']:.4f} ({metrics['jac_rel_err_cv']:.4f}, {metrics['jac_rel_err_mean']:.4f}); "
             + (f"the student's ramp_grad_rel_err {metrics['ramp_grad_rel_err_student']:.3f}, ramp_react_rel_err "
                f"{metrics['ramp_react_rel_err_student']:.3f}; over the student's values (the planner's default) "
                f"ramp_grad_rel_err {metrics['ramp_grad_rel_err_over_student']:.3f}, ramp_react_rel_err "
                f"{metrics['ramp_react_rel_err_over_student']:.3f}; " if "grad_rel_err_student" in metrics else "") +
             f"{metrics['forward_us']:.0f} us per Jacobian vs {metrics['source_autodiff_us']:.0f} us {cfg.source} autodiff; "
             f"{100 * metrics['outside_box_share']:.1f}% of the test windows outside the training box")
    return metrics


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="surrogate")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Console entry point."""
    console("surrogate", hydra_main)
