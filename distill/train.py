"""The distill job: train (teacher) or distil (student) with Lightning, evaluate, certify, export, log to MLflow."""
import json
import logging
import os
import shutil
import time
from contextlib import nullcontext
from pathlib import Path

import lightning as L
import mlflow
import mlflow.onnx
import numpy as np
import onnx as onnx_model
import torch
from hydra.utils import instantiate
from lightning.pytorch.loggers import MLFlowLogger
from omegaconf import DictConfig, OmegaConf

from core import validate
from core.jobs import CONF_DIR, UserError, job_config, made_models, mlflow_run, quiet, sha256, staged, tracking_uri, writable
from data import dataset
from distill import certificate, metrics, models
from distill.export import export_onnx, load_onnx
from distill.perturb import box_windows, planner_like

ONNX_TOL_M = 1e-4
log = logging.getLogger(__name__)


class _NoTips(logging.Filter):
    """Drops Lightning's advertising tips (hosted loggers, model registry); its other messages pass."""

    def filter(self, record):
        return not str(record.msg).startswith("\N{ELECTRIC LIGHT BULB} Tip:")


def quiet_lightning_tips():
    """Silence Lightning's tips on the loggers its rank-zero messages go through (idempotent)."""
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, _NoTips) for f in logger.filters):
            logger.addFilter(_NoTips())


def make_trainer(cfg_trainer: DictConfig, **kwargs) -> L.Trainer:
    """The Trainer of cfg_trainer, its callbacks given by name in the config (a null one is left out), as a list; no
    progress bar when stderr is not a terminal (core.jobs.quiet: a redirected log would fill with redraws)."""
    quiet_lightning_tips()
    spec = OmegaConf.to_container(cfg_trainer, resolve=True)
    if quiet():
        spec["enable_progress_bar"] = False
    callbacks = [instantiate(c) for c in spec.pop("callbacks", {}).values() if c is not None]
    return instantiate(spec, callbacks=callbacks, **kwargs)


def fit(cfg: DictConfig, run_id, teacher, start=None):
    """Lightning fit of cfg.model's task, its network first set to `start`'s weights where given (init_from); returns the
    trainer (its best checkpoint holds the chosen weights)."""
    labels = {} if teacher is None else {"teacher": teacher}  # the student's data is relabelled by its teacher
    data = instantiate(cfg.model.data, dataset_dir=cfg.dataset_dir, **labels, _convert_="all")
    task = instantiate(cfg.model.task, _convert_="all")
    if start is not None:
        task.net.load_state_dict(start.state_dict())
    logger = MLFlowLogger(experiment_name="distill", tracking_uri=tracking_uri(), run_id=run_id) if run_id else False
    fitter = make_trainer(cfg.trainer, logger=logger)
    fitter.fit(task, datamodule=data, ckpt_path=cfg.ckpt_path)
    return fitter


def scenario_configs(names):
    """{name: conf/scenario/<name>.yaml composed, as plain containers} (inside a running Hydra job, by its search path)."""
    options = sorted(p.stem for p in (Path(CONF_DIR) / "scenario").glob("*.yaml"))
    unknown = [n for n in names if n not in options]
    if unknown:
        raise UserError(f"model.certificate.scenarios: unknown scenario {unknown[0]}; choose from {', '.join(options)}")
    return {n: OmegaConf.to_container(job_config(f"scenario/{n}").scenario, resolve=True) for n in names}


def certify(cfg_cert, predictor, windows, rng):
    """Certificate (global and on the planner's region, the smaller kept) + rho bound, and the sampled check (metres).

    Every sample is checked against the global bound; those inside the region (its corners, uniform points, and the
    data and planner-like windows that fall in it) also against the region certificate.
    """
    box = dict(cfg_cert.box)
    glob = certificate.constants(predictor.weights, predictor.s, box)
    lo, hi = certificate.feature_box(cfg_cert.region)
    region = certificate.region_constants(predictor.weights, predictor.s, lo, hi)
    c = certificate.tightest(glob, region)
    scenarios = scenario_configs(list(cfg_cert.scenarios))
    params = certificate.scenario_setting(next(iter(scenarios.values())))[3]  # the global bound drives the first one's car
    c.update(certificate.rho_bound(c, box, dict(cfg_cert.cost), cfg_cert.T_p, lambda_s=cfg_cert.lambda_s, params=params,
                                   **dict(cfg_cert.typical)))
    c.update({f"{k}_global": glob[k] for k in ("theta_x", "theta_y", "L")})
    c.update({f"{k}_region": region[k] for k in ("theta_x", "theta_y", "L")})
    c["rho_used"] = float(cfg_cert.rho_used)
    data = windows - windows[:, -1:, :1]  # ego-centred frame; gradients do not depend on it
    n_pert = cfg_cert.samples // 3  # drawn with replacement, each with its own perturbation
    pert = planner_like(data[rng.integers(0, len(data), n_pert)], rng, **cfg_cert.perturb)
    pert = pert - pert[:, -1:, :1]
    n_region = cfg_cert.samples // 3
    boxed = box_windows(max(0, cfg_cert.samples - len(data) - n_pert - n_region), rng, box)
    sample = np.concatenate([data, pert, boxed])
    inside = np.concatenate([certificate.region_samples(lo, hi, n_region, rng),
                             sample[certificate.in_region(sample, lo, hi)]])
    cols = certificate.ego_columns()
    autodiff = models.TorchPredictor("student", predictor.module).phi_jac
    jac64 = lambda w: predictor.jac_cols(w, cols)  # noqa: E731
    emp = certificate.sampled(autodiff, jac64, inside, cfg_cert.fd_step_m)
    emp_all = certificate.sampled(autodiff, jac64, np.concatenate([sample, inside]), cfg_cert.fd_step_m)
    certificate.verify(glob, emp_all)
    emp["emp_samples"] = len(sample) + len(inside)
    emp["emp_samples_region"] = len(inside)
    emp["region_fraction_data"] = float(certificate.in_region(data, lo, hi).mean())
    emp["region_fraction_planner_like"] = float(certificate.in_region(pert, lo, hi).mean())
    plain = OmegaConf.to_container(cfg_cert, resolve=True)
    c["scenarios"] = certificate.per_scenario(predictor.weights, predictor.s, glob, plain["region"],
                                              scenarios, plain["planner"], plain["cost"],
                                              cfg_cert.T_p, cfg_cert.lambda_s)
    for name, sc in c["scenarios"].items():  # each scenario's bound checked at its own region's corners and inside
        sc_emp = certificate.sampled(autodiff, jac64, certificate.region_samples(
            *certificate.feature_box(sc["region"]), cfg_cert.samples // 6, rng), cfg_cert.fd_step_m)
        certificate.verify(sc, sc_emp)
        sc.update({k: v for k, v in sc_emp.items() if k != "emp_theta_max"}, **certificate.ratios(sc, sc_emp))
    return c, emp


SCENARIO_METRICS = ("theta_x", "theta_y", "L", "L_1", "L_g", "L_J", "M", "sigma_min_C", "rho_bound", "ratio_theta_x",
                    "ratio_theta_y", "ratio_L")


# each model's branch-group setting and the loss weights that need it
BRANCH_TERMS = {"teacher": ("contrast_groups", ("contrast_weight",)),
                "student": ("rollout_groups", ("rollout_weight", "contrast_weight")),
                "teacher_hyp": ("contrast_groups", ()), "student_hyp": ("rollout_groups", ())}


def hypotheses(n_others: int) -> np.ndarray:
    """Every hypothesis (2^N, N + 1) over N other cars, 1: the car yields (the ego's column 0)."""
    combos = (np.arange(2**n_others)[:, None] >> np.arange(n_others)) & 1
    return np.concatenate([np.zeros((len(combos), 1)), combos], 1).astype(float)


def certify_hypotheses(cfg_cert, predictor, windows, rng):
    """certify under every fixed hypothesis, the samples shared out among them: the largest constants and sampled values
    over all of them (each hypothesis checked against its own certificate), and per hypothesis (keyed 0/1 per car)."""
    hyps = hypotheses(windows.shape[2] - 1)
    share = OmegaConf.create({**OmegaConf.to_container(cfg_cert, resolve=True), "samples": max(6, cfg_cert.samples // len(hyps))})
    per = {}
    for h in hyps:
        pick = windows[rng.choice(len(windows), size=min(len(windows), share.samples // 3), replace=False)]
        per["".join(str(int(v)) for v in h[1:])] = certify(share, predictor.given(h), pick, rng)
    worst = lambda docs, k: max(d[k] for d in docs)  # noqa: E731
    certs, emps = [c for c, _ in per.values()], [e for _, e in per.values()]
    cert = {**certs[0], **{k: worst(certs, k) for k, v in certs[0].items() if isinstance(v, float)}}
    cert["scenarios"] = {n: {**sc, **{k: max(c["scenarios"][n][k] for c in certs) for k, v in sc.items()
                                     if isinstance(v, float)}} for n, sc in certs[0]["scenarios"].items()}
    emp = {k: (sum(e[k] for e in emps) if k.startswith("emp_samples") else worst(emps, k)) for k in emps[0]}
    cert["hypotheses"] = {k: {"constants_m": {n: v for n, v in c.items() if n != "scenarios"}, "sampled": e,
                              "ratios": certificate.ratios(c, e)} for k, (c, e) in per.items()}
    return cert, emp


def initial_net(cfg: DictConfig) -> torch.nn.Module:
    """The network of checkpoint cfg.init_from, checked to be cfg.model's and to fit model.net; one UserError naming
    init_from otherwise."""
    path = Path(cfg.init_from)
    if cfg.ckpt_path is not None:
        raise UserError(f"init_from={path} and ckpt_path={cfg.ckpt_path}: choose one (start a new run from the weights, or "
                        "resume the old run)")
    if not path.is_file():
        raise UserError(f"init_from={path}: no such checkpoint file")
    net = models.read_checkpoint(path, cfg.model.name)
    try:
        instantiate(cfg.model.net).load_state_dict(net.state_dict())
    except RuntimeError as e:
        raise UserError(f"init_from={path}: its network does not fit model.net ({str(e).splitlines()[1].strip()})") from None
    return net


def check_inputs(cfg: DictConfig):
    """Every input checked before any work: the config, the splits the job reads (checksums), the resumed checkpoint and
    the student's teacher, the checkpoint to start from; returns (the teacher (None for model=teacher), the network of
    init_from (None without))."""
    validate.check(cfg, "distill")
    groups, weights = BRANCH_TERMS[cfg.model.name]
    if cfg.model.name.endswith("_hyp") and cfg.model.data.get(groups, 0):
        raise UserError(f"model.data.{groups}={cfg.model.data[groups]}: model={cfg.model.name} takes no branch groups (set 0)")
    for weight in weights:
        if cfg.model.task.get(weight, 0) and not cfg.model.data.get(groups, 0):
            raise UserError(f"model.task.{weight}={cfg.model.task[weight]} needs model.data.{groups} > 0 (branch groups "
                            "per batch); without them the term is never computed")
    for folder, split in dict.fromkeys(((cfg.dataset_dir, "train"), (cfg.dataset_dir, "val"), (cfg.eval_dir, cfg.eval_split))):
        dataset.load(folder, split)  # a missing or corrupt split stops here, naming the file
    if cfg.ckpt_path is not None:
        if not Path(cfg.ckpt_path).is_file():
            raise UserError(f"ckpt_path={cfg.ckpt_path}: no such checkpoint file")
        models.read_checkpoint(Path(cfg.ckpt_path), cfg.model.name)
    start = None if cfg.init_from is None else initial_net(cfg)
    if cfg.model.name.endswith("_hyp"):
        for folder, split in dict.fromkeys(((cfg.dataset_dir, "train"), (cfg.eval_dir, cfg.eval_split))):
            dataset.hidden_labels(dataset.load(folder, split), Path(folder) / f"{split}.npz")
    teacher = None
    if cfg.model.name in ("student", "student_hyp"):
        scenario_configs(cfg.model.certificate.scenarios)  # an unknown name fails here, not after training
        teacher = models.load(cfg.model.teacher, cfg.models_dir)
        if cfg.model.name.endswith("_hyp") != hasattr(teacher, "given"):
            raise UserError(f"model.teacher={cfg.model.teacher}: model={cfg.model.name} distils from "
                            f"{'a hypothesis teacher (teacher_hyp)' if cfg.model.name.endswith('_hyp') else 'a teacher without hypotheses'}")
    writable(cfg.models_dir, "models_dir")  # last: a rejected command creates no folder
    return teacher, start


def run(cfg: DictConfig):
    """Train or distil cfg.model.name, write models/<name>.{ckpt,onnx} (+ certificate.json) once everything succeeded;
    returns the metrics."""
    name = cfg.model.name
    teacher, start = check_inputs(cfg)
    torch.set_num_threads(cfg.threads or max(1, (os.cpu_count() or 1) // cfg.trainer.devices))
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    rank0 = int(os.environ.get("LOCAL_RANK", 0)) == 0  # Lightning's DDP launcher re-runs this job in child processes
    run_name = f"{name}-{cfg.dataset.name}{'-from-' + Path(cfg.init_from).stem if cfg.init_from else ''}-seed{cfg.seed}"
    with (mlflow_run("distill", cfg, run_name=run_name, model=name) if rank0 else nullcontext()) as run_:
        t0 = time.perf_counter()
        trainer = fit(cfg, run_.info.run_id if rank0 else None, teacher, start)
        if trainer.global_rank != 0:
            return None
        results = {"train_s": time.perf_counter() - t0, "epochs": trainer.current_epoch}
        best = Path(trainer.checkpoint_callback.best_model_path or trainer.checkpoint_callback.last_model_path)
        predictor = models.wrap(name, models.read_checkpoint(best))
        test = dataset.load(cfg.eval_dir, cfg.eval_split)
        t_p = cfg.paper.T_p  # rollout horizon of the ade_rollout / fde_rollout figures
        table = {name: metrics.ade(predictor, test, t_p), "cv": metrics.ade(models.load("cv", cfg.models_dir), test, t_p)}
        results.update(table[name])
        results.update({f"{k}_cv": v for k, v in table["cv"].items()})  # a baseline's scores: its name last, as surrogate's
        results["params"] = sum(p.numel() for p in predictor.module.parameters())
        hyp = name.endswith("_hyp")
        cert_file = "certificate.json" if name == "student" else f"certificate_{name}.json"
        plain = predictor.given(np.zeros(test["X"].shape[2])) if hyp else predictor  # nobody yields: speed, Jacobians
        results["forward_us"] = metrics.forward_us(plain, test["X"])
        if hyp:
            results.update(hypothesis_figures(cfg, predictor, test, t_p))
        cert = None
        if name in ("student", "student_hyp"):
            table["teacher"] = metrics.ade(teacher, test, t_p)
            results.update({f"{k}_teacher": v for k, v in table["teacher"].items()})
            results.update(metrics.jac_rel_err(plain, teacher.given(np.zeros(test["X"].shape[2])) if hyp else teacher,
                                               test["X"][:512].astype(float)))
            t1 = time.perf_counter()
            cert, emp = (certify_hypotheses if hyp else certify)(cfg.model.certificate, predictor, test["X"].astype(float),
                                                                 np.random.default_rng(cfg.seed))
            results.update({f"cert_{k}": v for k, v in cert.items() if k not in ("rho_used", "scenarios", "hypotheses")})
            results.update({f"cert_{name}_{k}": sc[k] for name, sc in cert["scenarios"].items() for k in SCENARIO_METRICS})
            results.update(emp)
            results.update(certificate.ratios(cert, emp))
            results["cert_check_s"] = time.perf_counter() - t1
            certificate.verify(cert, emp)

        models_dir = Path(cfg.models_dir)
        models.check_finite(plain.phi_jac(models.probe_window(*test["X"].shape[1:3])), best,
                            f"the trained {name} is not kept; {models_dir} is left as it was")
        with staged(models_dir) as stage:  # models/ changes only if every check below passes, as one set
            meta = dataset.read_meta(cfg.dataset_dir)  # traced at the window it was trained on
            export_onnx(predictor.module, stage / f"{name}.onnx", meta["T_obs"], meta["N"] + 1)
            onnx = load_onnx(name, stage)
            if hyp:
                results.update(onnx_parity(onnx, predictor, test["X"][:256], np.random.default_rng(cfg.seed)))
            else:
                results["onnx_max_err_m"] = float(np.abs(onnx.phi(test["X"][:256]) - predictor.phi(test["X"][:256])).max())
            results["forward_us_onnx"] = metrics.forward_us(plain_onnx(onnx) if hyp else onnx, test["X"])
            if not results["onnx_max_err_m"] <= ONNX_TOL_M:
                raise UserError(f"{models_dir / name}.onnx disagrees with torch by {results['onnx_max_err_m']:.2e} m")
            shutil.copyfile(best, stage / f"{name}.ckpt")
            if cert is not None:
                doc = {"constants_m": {k: v for k, v in cert.items() if k != "scenarios"}, "scenarios": cert["scenarios"],
                       "sampled": emp, "ratios": certificate.ratios(cert, emp),
                       "box": {k: v for k, v in OmegaConf.to_container(cfg.model.certificate, resolve=True).items()
                               if k != "scenarios"},
                       "checkpoint": str(models_dir / f"{name}.ckpt"), "conventions": certificate.__doc__,
                       "certifies": {f: sha256(stage / f) for f in (f"{name}.ckpt", f"{name}.onnx")}}  # certified_rho checks them
                if hyp:
                    doc["hypotheses"] = cert.pop("hypotheses")
                    doc["constants_m"].pop("hypotheses")
                (stage / cert_file).write_text(json.dumps(doc, indent=1))
            made_models(stage / f for f in (f"{name}.ckpt", f"{name}.onnx", cert_file) if (stage / f).exists())
            mlflow.onnx.log_model(onnx_model.load(str(stage / f"{name}.onnx")), name=name, pip_requirements=["onnxruntime"])
            mlflow.log_metrics({k: float(v) for k, v in results.items()})
    log.info(summary(name, table, results, cert))
    return results


BELIEF_TOL = 1e-4  # onnxruntime against torch, the belief (-)


def hypothesis_figures(cfg, predictor, test, t_p) -> dict:
    """metrics.hypothesis_quality on the evaluation split, the prior from the training split, the mean model of the same
    kind (models_dir/teacher for teacher_hyp) beside it where it exists; the reliability figure logged to MLflow."""
    prior = metrics.yield_prior(dataset.load(cfg.dataset_dir, "train"))
    mean_name = cfg.model.name.removesuffix("_hyp")
    mean = models.load(mean_name, cfg.models_dir) if (Path(cfg.models_dir) / f"{mean_name}.ckpt").is_file() else None
    png = Path(cfg.run_dir) / "belief_reliability.png"
    png.parent.mkdir(parents=True, exist_ok=True)
    out = metrics.hypothesis_quality(predictor, test, t_p, prior, dataset.read_meta(cfg.eval_dir)["dt"], mean, png)
    if png.exists():
        mlflow.log_artifact(str(png), "plots")
    return out


def onnx_parity(onnx, predictor, X, rng) -> dict:
    """Largest onnxruntime-against-torch differences of a hypothesis model on windows X under random hypotheses: next
    (m) and belief (-); a UserError beyond ONNX_TOL_M or BELIEF_TOL."""
    hyp = (rng.random(X.shape[:1] + X.shape[2:3]) < 0.5).astype(float)
    nxt, belief = onnx.answers(X, hyp)
    out = {"onnx_max_err_m": float(np.abs(nxt - predictor.given(hyp).phi(X.astype(float))).max()),
           "onnx_belief_max_err": float(np.abs(belief - predictor.belief(X.astype(float))).max())}
    if not out["onnx_belief_max_err"] <= BELIEF_TOL:
        raise UserError(f"{onnx.name}.onnx's belief disagrees with torch by {out['onnx_belief_max_err']:.2e}")
    return out


def plain_onnx(onnx):
    """A hypothesis model's ONNX predictor under nobody yielding, as phi(window): what forward_us_onnx times."""
    class Plain:
        def phi(self, window):
            return onnx.answers(window, np.zeros(np.shape(window)[:1] + np.shape(window)[2:3]))[0]
    return Plain()


def summary(name, table, r, cert):
    """The end-of-job report: ADE table against constant velocity, and for the student the certificate."""
    cols = ["ade_1step_m", "ade_rollout_m", "fde_rollout_m", "ade_1step_m_yield", "ade_rollout_m_yield"]
    lines = [f"distill {name}: {r['epochs']} epochs in {r['train_s']:.1f} s, {r['params']} parameters, "
             f"phi {r['forward_us']:.0f} us (onnxruntime {r['forward_us_onnx']:.0f} us), onnx max err {r['onnx_max_err_m']:.1e} m",
             f"{'predictor':10s}" + "".join(f"{c:>21s}" for c in cols)]
    for k, m in table.items():
        lines.append(f"{k:10s}" + "".join(f"{m[c]:21.4f}" for c in cols))
    if "belief_brier" in r:
        lines.append(f"rollout error (m) on the cars the ego encroaches on, per recorded hypothesis: yield "
                     f"{r['ade_rollout_m_yielders']:.3f} (given the opposite {r['ade_rollout_m_yielders_opposite']:.3f}, "
                     f"cv {r['ade_rollout_m_yielders_cv']:.3f}), stubborn {r['ade_rollout_m_stubborn']:.3f} (given the "
                     f"opposite {r['ade_rollout_m_stubborn_opposite']:.3f}, cv {r['ade_rollout_m_stubborn_cv']:.3f})"
                     + (f"; mean model: yield {r['ade_rollout_m_yielders_mean']:.3f}, stubborn {r['ade_rollout_m_stubborn_mean']:.3f}"
                        if "ade_rollout_m_yielders_mean" in r else ""))
        lines.append(f"belief on {r['n_belief_cases']} encroached cars: Brier {r['belief_brier']:.4f} vs constant prior "
                     f"{r['belief_prior']:.2f}'s {r['belief_brier_prior']:.4f} (ratio {r['belief_brier_ratio']:.2f}; a belief told "
                     f"each decision once shown: {r['seen_brier_ratio']:.2f}); AUC "
                     f"{r['belief_auc']:.3f}; at " + ", ".join(f"{lag:.1f}" for lag in metrics.BELIEF_LAGS_S)
                     + " s after the first encroachment: AUC " + " ".join(f"{r[f'belief_auc_{lag:.1f}s']:.2f}" for lag in metrics.BELIEF_LAGS_S)
                     + " (the data's reveal " + " ".join(f"{r[f'seen_auc_{lag:.1f}s']:.2f}" for lag in metrics.BELIEF_LAGS_S)
                     + "); on the car nearest behind the ego " + " ".join(f"{r[f'belief_auc_nearest_{lag:.1f}s']:.2f}" for lag in metrics.BELIEF_LAGS_S)
                     + " (reveal " + " ".join(f"{r[f'seen_auc_nearest_{lag:.1f}s']:.2f}" for lag in metrics.BELIEF_LAGS_S) + ")")
        lines.append("braking under the own hypothesis (AUC for > 4 m/s^2, false alarms > 3 m/s^2 where truly < 2): "
                     + "; ".join(f"{label} AUC {r[f'brake_auc_{label}']:.3f}, alarms {r[f'brake_fa_{label}']:.3f} "
                                 f"({r[f'n_brake_cases_{label}']} cars braking > 1 m/s^2)" for label in ("yielders", "stubborn")))
    if cert is not None:
        lines.append(f"jac_rel_err {r['jac_rel_err']:.4f} (w.r.t. the ego's inputs {r['jac_rel_err_ego']:.4f}) vs teacher autodiff")
        lines.append(f"certificate (m): s_x {cert['s_x']:.2f}  s_y {cert['s_y']:.2f}  theta_x {cert['theta_x']:.4g}  "
                     f"theta_y {cert['theta_y']:.4g}  L {cert['L']:.4g}")
        lines.append(f"sampled over {r['emp_samples_region']} windows in the region: theta_x {r['emp_theta_x_max']:.4g} (ratio {r['ratio_theta_x']:.3f})  "
                     f"theta_y {r['emp_theta_y_max']:.4g} (ratio {r['ratio_theta_y']:.3f})  L {r['emp_L_max']:.4g} (ratio {r['ratio_L']:.3f})")
        lines.append("  global (weights' norms): " + "  ".join(f"{k} {cert[k + '_global']:.4g}" for k in ("theta_x", "theta_y", "L"))
                     + "; on the region: " + "  ".join(f"{k} {cert[k + '_region']:.4g}" for k in ("theta_x", "theta_y", "L"))
                     + f" (region holds {r['region_fraction_data']:.1%} of data, "
                     f"{r['region_fraction_planner_like']:.1%} of planner-like windows)")
        lines.append(f"Theorem 1: rho > {cert['rho_bound']:.4g} = (1 + 2 sigma_min(C)) L_J M with L_J {cert['L_J']:.4g} "
                     f"(L_1 {cert['L_1']:.4g}, L_2 {cert['L_2']:.3g}, L_3 {cert['L_3']:.3g}, L_g {cert['L_g']:.4g}), "
                     f"M {cert['M']:.3g}, sigma_min(C) {cert['sigma_min_C']:.3g}; the planner uses rho = {cert['rho_used']:g}")
        for name, sc in cert["scenarios"].items():
            lines.append(f"  {name} (rel_y {sc['region']['rel_y'][1]:g} m, x_max {sc['x_max']:g}, y_max {sc['y_max']:g}, "
                         f"v {sc['v']:g} m/s): theta_x {sc['theta_x']:.4g} ({sc['ratio_theta_x']:.3f})  theta_y "
                         f"{sc['theta_y']:.4g} ({sc['ratio_theta_y']:.3f})  L {sc['L']:.4g} ({sc['ratio_L']:.3f}); rho > "
                         f"{sc['rho_bound']:.4g} (L_1 {sc['L_1']:.4g}, L_g {sc['L_g']:.4g}, L_J {sc['L_J']:.4g}, "
                         f"M {sc['M']:.3g}, sigma_min(C) {sc['sigma_min_C']:.3g})")
    return "\n".join(lines)
