"""Trained predictors behind the shared interface: `load(name)` -> .name, .phi(window), .phi_jac(window), .module.

phi maps windows (B, T_obs, SLOTS, 2) of xy in metres to next xy (B, SLOTS, 2); phi_jac also returns the exact local
Jacobian (B, SLOTS*2, T_obs*SLOTS*2) of the flattened next w.r.t. the flattened window (C order).
A hypothesis predictor (teacher_hyp, student_hyp) gives that interface under fixed hypotheses, .given(hyp), and a
belief per car, .belief(window).
"""
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from torch.func import vjp

from core.jobs import MissingModel, UserError, model_file, recover
from distill import student
from distill.predictors import ConstantVelocity

NAMES = ("teacher", "student", "teacher_hyp", "student_hyp", "cv")
NETS = {"teacher": "distill.teacher.SocialTeacher", "student": "distill.student.GeluStudent",  # the network class of each
        "teacher_hyp": "distill.teacher.HypothesisTeacher", "student_hyp": "distill.student.HypothesisStudent"}


def window_of(module) -> tuple:
    """(T_obs, M) of the windows (B, T_obs, M, 2) a network takes, read from its weights: the student's feature map P
    fixes both, the teacher's slot embeddings fix M (its GRU reads any T_obs); None where nothing fixes one."""
    if hasattr(module, "P"):
        m = len(module.s) // 2 + 1  # the head bounds x and y of every car but the ego
        return module.P.shape[1] // (2 * m), m
    return None, module.slot.shape[0] if hasattr(module, "slot") else None


class TorchPredictor:
    """A torch network as a numpy predictor: forward in the network's dtype, Jacobians by reverse-mode autodiff."""

    fitted = True  # learned from data, its rollouts fitted over so many steps: mpc.strategy.trust cuts them short

    def __init__(self, name, module):
        """name for reports; module maps a torch window (B, T_obs, SLOTS, 2) to next (B, SLOTS, 2), metres."""
        self.name, self.module = name, module.eval()
        self.dtype = next(module.parameters()).dtype
        self.window = window_of(module)

    def phi(self, window):
        """Next xy (B, SLOTS, 2) in metres, float64."""
        with torch.no_grad():
            return self.module(torch.tensor(np.asarray(window), dtype=self.dtype)).double().numpy()

    def phi_vjp(self, window, cotangents):
        """Next xy (B, SLOTS, 2) and v^T J (B, k, T_obs*SLOTS*2) for cotangents v (B, k, SLOTS, 2), by torch.func.vjp."""
        w = torch.tensor(np.asarray(window), dtype=self.dtype)
        v = torch.tensor(np.asarray(cotangents), dtype=self.dtype)
        with torch.no_grad():
            nxt, pullback = vjp(self.module, w)
            vJ = torch.stack([pullback(v[:, k])[0].reshape(len(w), -1) for k in range(v.shape[1])], dim=1)
        return nxt.double().numpy(), vJ.double().numpy()

    def phi_jac(self, window):
        """Next xy (B, SLOTS, 2) and the exact J (B, SLOTS*2, T_obs*SLOTS*2): one vjp per output coordinate (faster than jacrev here)."""
        b, _, m, _ = np.shape(window)
        return self.phi_vjp(window, np.tile(np.eye(m * 2).reshape(1, m * 2, m, 2), (b, 1, 1, 1)))


class StudentPredictor(TorchPredictor):
    """The GELU student: phi and its exact Jacobian by its compiled float64 forward pass (distill.student.phi_jac: fast
    at batch 1, as a planner calls it)."""

    def __init__(self, module):
        """module: a GeluStudent; its weights are copied to float64 once."""
        super().__init__("student", module)
        self.weights = module.weights64()
        self.s = module.s.double().numpy()
        self.kernel = student.kernel_args(self.weights, self.s)  # (Ws, bs, s): the compiled kernels' arguments

    def phi(self, window):
        """Next xy (B, SLOTS, 2) in metres, float64."""
        return student.phis(*self.kernel, np.ascontiguousarray(window, float))

    def phi_jac(self, window):
        """Next xy (B, SLOTS, 2) and the exact J (B, SLOTS*2, T_obs*SLOTS*2), float64."""
        return student.phi_jacs(*self.kernel, np.ascontiguousarray(window, float))

    def jac_cols(self, window, cols):
        """The Jacobian's columns `cols` only (B, SLOTS*2, len(cols)), float64."""
        return self.phi_jac(window)[1][:, :, cols]


class Given(torch.nn.Module):
    """A hypothesis network as a plain one: window (B, T_obs, SLOTS, 2) -> next (B, SLOTS, 2) under fixed hypotheses."""

    def __init__(self, net, hyp):
        """net: a hypothesis network; hyp (SLOTS,) for every window, or (B, SLOTS) one per window, 1: the car yields."""
        super().__init__()
        self.net = net
        self.register_buffer("hyp", torch.as_tensor(np.asarray(hyp), dtype=next(net.parameters()).dtype))

    def forward(self, window):
        """Next xy (B, SLOTS, 2) in metres under the hypotheses."""
        return self.net(window, self.hyp.expand(window.shape[0], -1) if self.hyp.dim() == 1 else self.hyp)


class HypothesisPredictor:
    """A hypothesis network as a predictor: .given(hyp) is a predictor (phi, phi_vjp, phi_jac) under fixed hypotheses
    hyp (SLOTS,) or (B, SLOTS) (1: the car yields to an encroaching ego, 0: it does not; the ego's ignored), the fixed
    input of a rollout; .belief(window) is p(yields | window) (B, SLOTS), the ego's 0."""

    fitted = True

    def __init__(self, name, module):
        """name for reports; module: a HypothesisTeacher or HypothesisStudent."""
        self.name, self.module = name, module.eval()
        self.dtype = next(module.parameters()).dtype
        self.window = window_of(module)

    def given(self, hyp):
        """The predictor under hypotheses hyp: for one hypothesis (SLOTS,) the student is a GeluStudent
        (HypothesisStudent.fixed) behind its own float64 path; else torch autodiff through the network."""
        hyp = np.asarray(hyp, dtype=float)
        p = StudentPredictor(self.module.fixed(hyp)) if hasattr(self.module, "fixed") and hyp.ndim == 1 else \
            TorchPredictor(self.name, Given(self.module, hyp))
        p.name, p.window = self.name, self.window
        return p

    def belief(self, window):
        """p(yields | window) (B, SLOTS) per car, float64, the ego's 0."""
        with torch.no_grad():
            return self.module.belief(torch.tensor(np.asarray(window), dtype=self.dtype)).double().numpy()


def read_checkpoint(path: Path, name: str | None = None) -> torch.nn.Module:
    """The network stored in a Lightning checkpoint of a distill task, checked to be `name`'s network if given; a corrupt
    or mismatched file is a UserError naming it."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        target = ckpt["hyper_parameters"]["net"]["_target_"]
    except Exception as e:  # torch raises many types for a damaged zip or pickle
        raise UserError(f"corrupt checkpoint {path}: {type(e).__name__}: {str(e).splitlines()[0][:200]}") from None
    if name is not None and target != NETS[name]:
        owner = next((k for k, v in NETS.items() if v == target), target)
        raise UserError(f"{path} holds a {owner} network ({target}), not a {name} ({NETS[name]})")
    try:
        net = instantiate(ckpt["hyper_parameters"]["net"])
        net.load_state_dict({k[len("net."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("net.")})
    except Exception as e:  # torch raises many types for a damaged zip or pickle
        raise UserError(f"corrupt checkpoint {path}: {type(e).__name__}: {str(e).splitlines()[0][:200]}") from None
    return net.eval()


def probe_window(T_obs: int = 8, M: int = 5) -> np.ndarray:
    """A plausible window (1, T_obs, M, 2), m: the ego and M - 1 cars at 5 m/s, 8 m apart, alternating between two 4 m
    lanes (0.2 s steps), where every sound model's output and Jacobian are finite."""
    t = np.arange(1 - T_obs, 1)[:, None] * 0.2 * 5.0  # (T_obs, 1): x travelled since each step, the last one 0
    cars = np.arange(M)
    return np.stack([t + 8.0 * cars, np.broadcast_to(4.0 * (cars % 2), (T_obs, M))], axis=-1)[None]


def check_finite(outputs, path, advice: str) -> None:
    """One UserError naming `path` unless every array of `outputs` (a model's answer to probe_window) is finite."""
    if not all(np.isfinite(a).all() for a in outputs):
        raise UserError(f"{path} is a corrupt model: its output on a probe window is not finite (NaN or infinite "
                        f"weights); {advice}")


def load(name: str, models_dir):
    """The predictor `name` (teacher | student | teacher_hyp | student_hyp | cv) from models_dir/<name>.ckpt, checked
    finite on a probe window (a hypothesis predictor under every car yielding and its belief)."""
    if name == "cv":
        return ConstantVelocity()
    if name not in NAMES:
        raise UserError(f"unknown predictor '{name}': choose one of {', '.join(NAMES)}")
    recover(models_dir)  # a set a stopped distill committed but did not finish moving in
    path = Path(models_dir) / f"{name}.ckpt"
    if not path.exists():
        raise MissingModel(f"{path} not found: run `distill model={name}`")
    predictor = wrap(name, read_checkpoint(model_file(path), name))
    T_obs, M = predictor.window
    probe = probe_window(T_obs or 8, M or 5)
    if isinstance(predictor, HypothesisPredictor):
        check_finite((*predictor.given(np.ones(probe.shape[2])).phi_jac(probe), predictor.belief(probe)), path,
                     f"re-run `distill model={name}`")
    else:
        check_finite(predictor.phi_jac(probe), path, f"re-run `distill model={name}`")
    return predictor


def wrap(name: str, net):
    """The predictor of model `name` around its network: the student's numpy path, a hypothesis predictor, or torch."""
    if name.endswith("_hyp"):
        return HypothesisPredictor(name, net)
    return StudentPredictor(net) if name == "student" else TorchPredictor(name, net)
