"""Gradient sources behind one interface: rollout values of the others and their derivative w.r.t. the ego plan.

Each source offers `values(history, ego_futures)` (B, T_p, SLOTS, 2) for a batch of ego plans and
`jacobian(history, ego_future)` -> values (T_p, SLOTS, 2), d values / d ego xy (T_p, SLOTS, 2, T_p, 2), metres throughout.
Built by the `gradients` config group (conf/gradients/), each option naming its class, predictor and settings; each
class declares what it can do as class attributes, readable from an option's `_target_` without building it.
"""
import copy
from pathlib import Path

import numpy as np
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from core.jobs import CONF_DIR, UserError, atomic_file, options
from core.rollout import react, rollout, rollout_jacobian
from core.validate import TRAINED_PREDICTORS
from data.world import World
from distill.models import probe_window
from planner.jit_interactive import open_loop
from planner.jit_rollout import KERNELS, values_params
from surrogate.kernels import compiled_phi

BATCHED = 4  # new windows: from this many in one call the teacher's onnxruntime graph beats its numba kernel (one core:
# 386 against 405 us at 4, 2.3 against 5.7 ms at 50; Surrogate.phi)


class Source:
    """Values from the predictor's own recursion; subclasses say where the derivative comes from."""

    joint = False  # values come with the Jacobian at little extra cost: a trial plan is linearised (Safety.trial)
    torch_rollout = False  # `module` and `dtype` give a torch rollout autograd can differentiate (zstep=pygranso)
    needs_world = False  # reads the running world (the oracle): only the planner's closed loop, world=reactive
    differentiates = False  # derives from the predictor's forward pass alone, so it works over any predictor
    compiled = False  # the compiled core runs its rollout and chain rule itself (planner.jit_rollout.KERNELS)
    hypotheses = False  # gives belief(history) and given(hyp): rollouts under hypotheses of yielding, with their probabilities

    def __init__(self, name, predictor):
        self.name, self.predictor = name, predictor

    def at(self, history):
        """This source as one step plans with it, from that step's observed history (T_obs, SLOTS, 2): itself, but for a
        source whose rollout depends on what it believes of the history (Hypotheses)."""
        return self

    def values(self, history, ego_futures):
        """Predicted xy (B, T_p, SLOTS, 2) of every slot for each ego plan (B, T_p, 2); history (T_obs, SLOTS, 2): react
        with the plans fixed in advance, in one compiled call where the predictor's rollout is compiled (cv, the
        student: planner.jit_interactive.open_loop)."""
        ego_futures = np.asarray(ego_futures, dtype=float)
        params = values_params(self.predictor)
        if params is not None:
            return open_loop(*params, np.ascontiguousarray(history, float), np.ascontiguousarray(ego_futures))
        return self.react(history, lambda window, tau: ego_futures[:, tau], ego_futures.shape[1], len(ego_futures))

    def drive(self, history, policy, T: int):
        """(Delta, alpha (K, T), Z (K, 4T), predicted xy (K, T, SLOTS, 2)) of K closed-loop candidates (planner.strategy.Chase)
        driven T steps against the predictor from the observed history (T_obs, SLOTS, 2): in one compiled call where
        its rollout is compiled, else the predictor's recursion calls the policy once a step (react)."""
        params = values_params(self.predictor)
        if params is not None:
            return policy.compiled(params, history, T)
        values = self.react(history, policy, T, len(policy.z))
        return policy.Delta, policy.alpha, policy.Z, values

    def react(self, history, ego_next, T, B):
        """Predicted xy (B, T, SLOTS, 2) of every slot over T steps while B feedback policies drive the ego:
        ego_next(window (B, T_obs, SLOTS, 2), tau) -> the ego's xy (B, 2) at step tau + 1; history (T_obs, SLOTS, 2)."""
        batch = np.broadcast_to(np.asarray(history, dtype=float), (B,) + np.shape(history))
        return np.asarray(react(self.phi, batch, ego_next, T), dtype=float)

    def phi(self, window):
        """Next xy (B, SLOTS, 2) of windows (B, T_obs, SLOTS, 2), metres: the predictor's."""
        return self.predictor.phi(window)

    def local_jacobians(self):
        """phi_jac(windows) -> (next xy, local J) from Python that the compiled chain rule composes; None: none, the
        source's own `jacobian` is called."""
        return None


class ExactLocal(Source):
    """The predictor's own exact local Jacobians (phi_jac), composed by the rollout chain rule."""

    joint = True  # phi_jac gives the values too, at a small multiple of phi's cost

    @property
    def compiled(self) -> bool:
        """Whether the compiled core runs this source itself: its predictor's rollout is written as numba kernels."""
        return self.predictor.name in KERNELS

    def local_jacobians(self):
        """The predictor's phi_jac."""
        return self.predictor.phi_jac

    def jacobian(self, history, ego_future):
        """Values (T_p, SLOTS, 2) and d values / d ego_future (T_p, SLOTS, 2, T_p, 2)."""
        return rollout_jacobian(self.predictor.phi_jac, history, ego_future)


def same_network(phi, surrogate) -> bool:
    """Whether a fused surrogate export's forward pass predicts the others as phi does (within 1e-4 m) on the probe
    window: an export made from an earlier training of the teacher does not."""
    window = probe_window(*surrogate.session.get_inputs()[0].shape[1:3])
    return bool(np.abs(phi(window) - surrogate.phi(window))[:, 1:].max() <= 1e-4)


class Surrogate(Source):
    """A learned local Jacobian (the gradient network) paired with the predictor's values, through the chain rule."""

    def __init__(self, name, predictor, surrogate):
        super().__init__(name, predictor)
        self.surrogate = surrogate
        self.seen = (None, {})  # (history, {window bytes: next xy}) of the step being planned
        kernel = compiled_phi(predictor)
        exported = surrogate.fused and (predictor is None or same_network(kernel or predictor.phi, surrogate))  # the
        # export's forward pass is the predictor's own network (its teacher), not another's (predictor=student)
        self.joint = exported  # values and J from one file, J for a whole rollout in one call
        self.forward = kernel or (surrogate.phi if exported else predictor.phi)
        self.batched = surrogate.phi if exported else self.forward

    def phi(self, window):
        """Next xy (B, SLOTS, 2) of windows (B, T_obs, SLOTS, 2), m: the predictor's. Over the teacher, its network in
        float64, fewer than BATCHED new windows by a numba kernel (surrogate.kernels: ~2x faster than onnxruntime at
        batch 1), more in one call of the fused export's forward pass where it is the same network (same_network;
        onnxruntime: ~2x faster than the kernel from 10 windows on, equal to it within 1e-6 m). Each
        distinct window of the step being planned is computed once, the new ones of a batch in one call: a step's
        candidates share most of theirs (mpc=interactive: 1.2 thousand distinct of 2.9 thousand windows a step on the
        bench's dense states; the first window of every rollout, and a closed-loop candidate's until its policy
        departs from its siblings')."""
        memo = self.seen[1]
        keys = [w.tobytes() for w in window]
        new = {k: b for b, k in enumerate(keys) if k not in memo}  # a dict: a window repeated in the batch counts once
        if new:
            memo.update(zip(new, (self.batched if len(new) >= BATCHED else self.forward)(window[list(new.values())])))
        return np.array([memo[k] for k in keys]).reshape(len(keys), *window.shape[2:])  # np.stack: 3x the cost

    def react(self, history, ego_next, T, B):
        """Source.react with the memo of windows kept for one history (a step): a closed loop's does not grow."""
        history = np.asarray(history, dtype=float)
        if self.seen[0] is None or not np.array_equal(self.seen[0], history):
            self.seen = (history.copy(), {})
        return super().react(history, ego_next, T, B)

    def jacobian(self, history, ego_future):
        """Values (T_p, SLOTS, 2) and d values / d ego_future (T_p, SLOTS, 2, T_p, 2) with the surrogate's local Jacobians,
        all windows of the rollout in one call once its values are known."""
        from planner.jit_rollout import chain_rule

        history, ego_future = np.asarray(history, dtype=float), np.asarray(ego_future, dtype=float)
        values = self.values(history, ego_future[None])[0]
        t_obs, t_p = len(history), len(values)
        track = np.concatenate([history, values])
        J = np.zeros((t_p, values[0].size, history.size))  # the observed window's J meets a zero derivative: left out
        if t_p > 1:
            J[1:] = self.surrogate.jac(np.stack([track[tau:tau + t_obs] for tau in range(1, t_p)]))
        return values, chain_rule(J, t_obs)


class Autodiff(Source):
    """Reverse-mode autodiff (torch.func.jacrev) through the whole recursive rollout of the predictor's torch module."""

    torch_rollout = True
    differentiates = True

    def __init__(self, name, predictor):
        super().__init__(name, predictor)
        import torch

        self.torch, self.module = torch, predictor.module
        params = list(getattr(self.module, "parameters", lambda: [])())
        self.dtype = params[0].dtype if params else torch.float64

    def jacobian(self, history, ego_future):
        """Values (T_p, SLOTS, 2) and d values / d ego_future (T_p, SLOTS, 2, T_p, 2) by autodiff."""
        torch = self.torch
        hist = torch.as_tensor(np.asarray(history), dtype=self.dtype)[None]

        def values(ego):
            out = rollout(self.module, hist, ego[None])[0]
            return out, out

        with torch.no_grad():  # jacrev builds its own graph; no_grad keeps parameters out of it
            grads, vals = torch.func.jacrev(values, has_aux=True)(torch.as_tensor(np.asarray(ego_future), dtype=self.dtype))
        return vals.double().numpy(), grads.double().numpy()


class CentralDifferences(Source):
    """A check: central differences of the predictor's rollout, all 4 T_p perturbed plans in one batch; step h (m)."""

    differentiates = True

    def __init__(self, name, predictor, h):
        super().__init__(name, predictor)
        self.h = h

    def jacobian(self, history, ego_future):
        """Values (T_p, SLOTS, 2) and d values / d ego_future (T_p, SLOTS, 2, T_p, 2) by central differences."""
        ego_future = np.asarray(ego_future, dtype=float)
        n = ego_future.size
        steps = np.eye(n).reshape(n, *ego_future.shape) * self.h
        batch = np.concatenate([ego_future[None], ego_future + steps, ego_future - steps])
        out = self.values(history, batch)
        grads = (out[1:n + 1] - out[n + 1:]) / (2 * self.h)  # (n, T_p, SLOTS, 2)
        return out[0], np.moveaxis(grads, 0, -1).reshape(out.shape[1:] + ego_future.shape)


class WorldModel:
    """A ceiling for diagnosis, never a predictor the world follows: the running world itself, its drivers and their
    true hidden decisions (knows=all), or each decision only once the driver has shown it by braking for the ego, every
    other driver taken as stubborn (knows=seen: the bound of a predictor without clairvoyance), or each decision once
    an observer can tell it either way (World.decided) and every other driver given as both hypotheses with the
    population's prior (knows=prior: the contingency oracle, hypotheses with their probabilities as a hypothesis model
    gives them), driven on in copies with the ego put on each plan.
    planner.closed_loop hands it the world and the observed slots' ids before every step (`world`, `ids`)."""

    name = "oracle"
    world = None  # the closed loop's world at the current step
    ids = None  # the world ids of the observation's slots (data.perception), ego first

    def __init__(self, knows: str):
        """knows: all (the true hidden decisions), seen (World.seen_decisions) or prior (belief)."""
        self.knows = knows

    def prior(self) -> float:
        """The population's probability (-) that a driver yields: the mean of the world's drivers' eta_coop, each
        driver's latched decision being drawn Bernoulli(eta_coop) (data.scenarios; scenario.cooperation sets them);
        one UserError for a world without such drivers (highway-env's)."""
        if not isinstance(self.world, World):
            raise UserError("predictor.knows=prior reads the drivers' willingness to yield (eta_coop), which only "
                            "data.world.World has; use knows=all")
        return float(np.mean([d.eta_coop for d in self.world.drivers]))

    def belief(self) -> np.ndarray:
        """p(yields) (SLOTS,) of the observed slots, the ego's 0: its decision for a driver whose decision shows
        (World.decided: 1 seen yielding, 0 seen refusing), the population's prior for every other one (knows=prior)."""
        p = self.known(self.prior())[self.ids]
        p[0] = 0.0
        return p

    def known(self, otherwise) -> np.ndarray:
        """(M,) each driver's decision where it shows (World.decided), `otherwise` elsewhere."""
        return np.where(self.world.decided(), self.world.decisions(), otherwise)

    def start(self, hyp=None):
        """A copy of the running world to drive on: its own decisions (all), those shown (seen), or (prior) the
        observed slots' taken from the hypotheses hyp (SLOTS,) (None: the more probable of each, belief > 0.5) and
        every unobserved driver's as it shows (World.decided), else the more probable one."""
        if self.knows == "all":
            return self.world.copy()
        if self.knows == "seen":
            return self.world.with_decisions(self.world.seen_decisions())
        decided = self.known(self.prior() > 0.5)
        decided[self.ids] = self.belief() > 0.5 if hyp is None else np.asarray(hyp) > 0.5
        return self.world.with_decisions(decided)

    def split(self, group, hyp) -> list:
        """[(world, members)]: a group of rollouts (a world, its members' indices) split by their hypotheses hyp (B, SLOTS)
        once a driver they differ on responds to the ego this step (World.respond: its perceived encroachment or its
        response above 0), each part's world a copy with its own; until then a decision to yield changes nothing
        (World.acceleration), so all step one world alike."""
        w, members = group
        differ = self.ids[np.flatnonzero((hyp[members] != hyp[members[0]]).any(0))]
        seen = lambda j: w.seen[w.perceived(j)]
        if not any(w.response[j] > 0 or w.encroachment(j, seen(j), int(w.road.lane_of(seen(j)[0, 1]))) > 0 for j in differ):
            return [group]
        parts = {}
        for b in members:
            parts.setdefault(hyp[b].tobytes(), []).append(b)
        out = []
        for part in parts.values():
            v = w.copy()
            v.will_yield[self.ids[1:]] = hyp[part[0], 1:] > 0.5
            out.append((v, part))
        return out

    def react(self, history, ego_next, T, B, yielding=None, hyp=None):
        """Every car's xy (B, T, SLOTS, 2) (m) over T steps in B copies of the running world while B feedback policies
        drive the ego: ego_next(window (B, T_obs, SLOTS, 2), tau) -> its xy (B, 2) at step tau + 1, with the heading and
        speed of each step's displacement; history (T_obs, SLOTS, 2) the observed window; hyp (B, SLOTS): each
        rollout's hypotheses (knows=prior; None: the more probable); a bool array `yielding` (B, T, SLOTS) is filled
        with the drivers' hidden yielding flags (bench.candidates' dataset labels)."""
        if self.world is None:
            raise UserError("predictor=oracle reads the running world: only the planner's closed loop with "
                            "world=reactive can use it")
        dt = self.world.params.dt
        window = np.repeat(np.asarray(history, dtype=float)[None], B, 0)
        out = np.empty((B, T, len(self.ids), 2))
        hyp = None if hyp is None else np.asarray(hyp, dtype=float)
        groups = [(self.start(None if hyp is None else hyp[0]), list(range(B)))]  # one world per ego path driven so
        # far (plans that share a prefix share its steps) and, once they matter, per hypothesis (split)
        for k in range(T):
            if hyp is not None:
                groups = [part for group in groups for part in self.split(group, hyp)]
            xy = ego_next(window, k)
            split = []
            for w, members in groups:
                paths = {}
                for b in members:
                    paths.setdefault(xy[b].tobytes(), []).append(b)
                parts = list(paths.values())
                split += [(w.copy(), part) for part in parts[:-1]] + [(w, parts[-1])]  # copied before w steps on
            for w, members in split:
                z0, p = w.states()[0], xy[members[0]]
                d = p - z0[:2]
                psi = np.arctan2(d[1], d[0]) if np.hypot(*d) > 1e-9 else z0[2]
                w.step_to(np.array([p[0], p[1], psi, np.hypot(*d) / dt]))
                out[members, k] = w.states()[self.ids, :2]
                if yielding is not None:
                    yielding[members, k] = w.yielding[self.ids]
            groups = split
            window = np.concatenate([window[:, 1:], out[:, k, None]], axis=1)
        return out


class Given:
    """A source with hypotheses of yielding: given(hyp) is the same source with each rollout under its own."""

    hyp = None  # (B, SLOTS): each of B rollouts' hypotheses, 1: the car yields (given); None: the more probable of each

    def given(self, hyp):
        """This source with each of B rollouts under its hypotheses hyp (B, SLOTS) (1: the car yields)."""
        out = copy.copy(self)
        out.hyp = np.asarray(hyp, dtype=float)
        return out


class WorldOracle(Given, CentralDifferences):
    """gradients=oracle: the WorldModel's futures, derivatives by central differences of them (step h, m)."""

    needs_world = True

    @property
    def hypotheses(self) -> bool:
        """Whether it gives hypotheses with their probabilities (knows=prior)."""
        return self.predictor.knows == "prior"

    def belief(self, history):
        """p(yields) (SLOTS,) of each observed car, the ego's 0 (WorldModel.belief; the history is the world's own)."""
        return self.predictor.belief()

    def react(self, history, ego_next, T, B):
        """Every car's xy (B, T, SLOTS, 2) while B feedback policies drive the ego, in copies of the running world."""
        return self.predictor.react(history, ego_next, T, B, hyp=self.hyp)


class Hypotheses(Given, ExactLocal):
    """gradients=student_hyp | teacher_hyp: a hypothesis predictor (distill.models.HypothesisPredictor): its belief
    per car, every rollout under its own hypotheses of yielding (given: the contingency step's branches) and the step's
    plan (ADMM, the safeguard) under the history's most probable ones (at), with the exact local Jacobians under them.
    The student's rollouts run compiled, one call per distinct hypothesis: a fixed hypothesis is a GeluStudent whose
    first bias it shifts (HypothesisStudent.fixed)."""

    hypotheses = True

    def __init__(self, name, predictor):
        super().__init__(name, predictor)
        self.network, self.under = predictor, {}  # under: {hypotheses' bytes: the predictor under them}, made once

    def fixed(self, hyp):
        """The predictor under hypotheses hyp (SLOTS,) (> 0.5: the car yields)."""
        h = (np.asarray(hyp) > 0.5).astype(float)
        key = h.tobytes()
        if key not in self.under:
            self.under[key] = self.network.given(h)
        return self.under[key]

    def belief(self, history):
        """p(yields) (SLOTS,) of each observed car given the history (T_obs, SLOTS, 2), the ego's 0: the network's."""
        return self.network.belief(np.asarray(history, float)[None])[0]

    def at(self, history):
        """This source for one step: its plain rollout under the history's most probable hypotheses (belief > 0.5)."""
        return self.plain(self.fixed(self.belief(history) > 0.5))

    def plain(self, predictor):
        """This source with one predictor for every rollout."""
        out = copy.copy(self)
        out.predictor, out.hyp = predictor, None
        return out

    def parts(self):
        """[(this source under one hypothesis, the rollouts (indices) given it)] of each distinct row of hyp."""
        kinds, which = np.unique(self.hyp > 0.5, axis=0, return_inverse=True)
        return [(self.plain(self.fixed(h)), np.flatnonzero(which == k)) for k, h in enumerate(kinds)]

    def values(self, history, ego_futures):
        """Source.values, each rollout under its own hypotheses (given) where they are given."""
        if self.hyp is None:
            return super().values(history, ego_futures)
        ego_futures = np.asarray(ego_futures, dtype=float)
        out = np.empty((len(ego_futures), ego_futures.shape[1], *np.shape(history)[1:]))
        for part, b in self.parts():
            out[b] = part.values(history, ego_futures[b])
        return out

    def drive(self, history, policy, T: int):
        """Source.drive, each policy under its own hypotheses (given) where they are given."""
        if self.hyp is None:
            return super().drive(history, policy, T)
        K = len(policy.z)
        out = [np.empty((K, T)), np.empty((K, T)), np.empty((K, 4 * T)), np.empty((K, T, *np.shape(history)[1:]))]
        for part, b in self.parts():
            for whole, piece in zip(out, part.drive(history, policy.rows(b), T)):
                whole[b] = piece
        return tuple(out)


class Recording:
    """A gradient source that keeps every (history, ego plan) it is linearised at: the planner's own iterates, as
    training and test states for the surrogate (`planner record_dir=...`). Everything else is the wrapped source's, but
    it runs neither compiled nor by its local Jacobians: the step takes the Python path that calls `jacobian`."""

    compiled = False

    def __init__(self, source):
        self.source, self.histories, self.plans = source, [], []

    def __getattr__(self, name):
        return getattr(self.source, name)

    def at(self, history):
        """The wrapped source as the step plans with it, its linearisations kept here."""
        out = Recording(self.source.at(history))  # not copy.copy: __getattr__ would recurse on the bare copy
        out.histories, out.plans = self.histories, self.plans
        return out

    def local_jacobians(self):
        """None: every linearisation goes through `jacobian`, which keeps it."""
        return None

    def jacobian(self, history, ego_future):
        """The wrapped source's values and Jacobian (m, m/m), with the state they are taken at kept."""
        self.histories.append(np.array(history, dtype=float))
        self.plans.append(np.array(ego_future, dtype=float))
        return self.source.jacobian(history, ego_future)

    def save(self, path: Path):
        """Write the kept states to `path` (.npz: history (n, T_obs, SLOTS, 2), ego_future (n, T_p, 2), m), atomically."""
        def write(tmp):
            np.savez(tmp, history=np.array(self.histories), ego_future=np.array(self.plans))
        atomic_file(path, write)


def option(group: str, name: str) -> DictConfig:
    """conf/<group>/<name>.yaml as written (interpolations unresolved)."""
    return OmegaConf.load(Path(CONF_DIR) / group / f"{name}.yaml")


def source_class(name: str) -> type:
    """The class gradients=<name> builds (its `_target_`), whose attributes declare what it can do."""
    return get_class(option("gradients", name)._target_)


def available(**capabilities) -> list[str]:
    """The gradient sources: the options of conf/gradients/, sorted, whose class declares `capabilities`, e.g.
    available(needs_world=False)."""
    return [n for n in options("gradients") if all(getattr(source_class(n), k) == v for k, v in capabilities.items())]


def predictor_of(name: str) -> str:
    """The predictor whose values gradients=<name> uses by default (conf/planner.yaml: predictor=${gradients}): its own
    conf/predictor/ option, or the one that option only extends (fd, surrogate: the teacher)."""
    return next(iter(option("predictor", name).get("defaults", [])), name)


def reads_models(name: str) -> bool:
    """Whether gradients=<name>, over its default predictor, loads trained models from models_dir (so it runs once per
    training)."""
    return "${models_dir}" in OmegaConf.to_yaml(option("gradients", name)) or predictor_of(name) in TRAINED_PREDICTORS
