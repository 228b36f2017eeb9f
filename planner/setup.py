"""The one place a `planner` config becomes objects: the scenario, the gradient source and the MPC settings, and one
closed-loop episode of a method; used by the `planner` command, its batch workers, the benchmarks and the tests."""
from pathlib import Path

from hydra.utils import get_class, get_object
from omegaconf import DictConfig, OmegaConf

from core.jobs import MissingModel, UserError, build, job_config, sha256
from core.validate import TRAINED_PREDICTORS
from distill import certificate
from planner import admm, closed_loop, cost, mpc
from planner.gradients import Recording, Surrogate, WorldModel


def planner_config(scenario: str = "two_lane", overrides=()) -> DictConfig:
    """The `planner` config composed for `scenario` with Hydra overrides, as the console script would compose it."""
    return job_config("planner", [f"scenario={scenario}", *overrides])


def rho(cfg: DictConfig, scenario) -> float:
    """ADMM's rho: cfg.mpc.admm.rho, or for mpc.admm.rho=certified Theorem 1's bound that models/certificate.json gives
    the scenario (the student's certificate, whatever the gradient source)."""
    if cfg.mpc.admm.rho != "certified":
        return cfg.mpc.admm.rho
    return certificate.certified_rho(Path(cfg.models_dir) / "certificate.json", scenario.name)


def settings(cfg: DictConfig, scenario) -> mpc.Settings:
    """The MPC settings of cfg.mpc with the paper's cost weights (paper.cost), cfg.linearize and the scenario's references
    (m, m/s), lane end (x_ref, m), merge tolerance (m), road and bicycle parameters; each value checked where it is defined (planner.mpc.Settings, planner.strategy),
    one UserError naming the key."""
    node = OmegaConf.to_container(cfg.mpc, resolve=True)
    problem = {k: v for k, v in node.items() if k not in ("admm", "strategy")}
    return mpc.Settings(**problem, admm=admm.Settings(**{**node["admm"], "rho": rho(cfg, scenario)}),
                        strategy=build(cfg.mpc.strategy), weights=cost.Weights(**cfg.paper.cost), linearize=cfg.linearize,
                        y_ref=scenario.y_ref, v_ref=scenario.v_ref, lane_y=scenario.y_ref, lane_end=scenario.x_ref,
                        merge_tol=scenario.merge_tol, road=scenario.road, params=scenario.params)


def setup(cfg: DictConfig):
    """(scenario, gradient source, mpc.Settings) of a composed `planner` config."""
    needs_world = get_class(cfg.gradients._target_).needs_world  # the source reads the running world: the oracle
    if needs_world != (get_object(cfg.gradients.predictor._target_) is WorldModel):  # and so does only its predictor
        raise UserError("gradients=oracle and predictor=oracle go only together: the oracle is the running world, "
                        "not a map of the observed window")
    if needs_world and cfg.world != "reactive":
        raise UserError("gradients=oracle predicts with the world's own drivers; it needs world=reactive")
    if cfg.mpc.b_courtesy is not None and (cfg.solver.name != "admm" or get_object(cfg.zstep._target_).name != "sqp"):
        raise UserError(f"mpc={cfg.mpc.name} has courtesy rows, which only solver=admm with zstep=sqp solves; use "
                        f"mpc=paper for solver={cfg.solver.name}, zstep={get_object(cfg.zstep._target_).name}")
    scenario = build(cfg.scenario)
    if cfg.world == "predictor" and not scenario.predictor_moves:
        raise UserError(f"world=predictor moves the others by the predictor, but scenario={scenario.name}'s cars drive "
                        "themselves: use world=reactive")
    try:
        source = build(cfg.gradients)
    except MissingModel as e:
        if cfg.gradients.name == "surrogate" and cfg.gradients.predictor.get("name") == "student":
            raise MissingModel(f"{e} (gradients=surrogate plans on the student's values; predictor=teacher for the "
                               "teacher's)") from None
        raise
    check_window(cfg, source.predictor)
    if isinstance(source, Surrogate):
        check_surrogate(source)
    return scenario, source, settings(cfg, scenario)


def check_surrogate(source: Surrogate) -> None:
    """One UserError unless gradients=surrogate's learned Jacobians are those of the predictor they stand for: the
    checkpoint of their source beside surrogate.onnx holds the bytes it was trained on (sha256 in its metadata), and the
    values are that source's own, or the student's over the teacher's Jacobians (the student distilled from it)."""
    learned, path = source.surrogate.source, Path(source.surrogate.path)
    file, digest = path.parent / f"{learned}.ckpt", source.surrogate.source_sha256
    if not digest:
        raise UserError(f"{path} does not record the {learned} it learned (ONNX metadata source_sha256); re-run `surrogate`")
    if not file.is_file():
        raise UserError(f"{path} learned the Jacobians of {file}, which is not there; re-run `surrogate` beside the {learned}")
    if sha256(file) != digest:
        raise UserError(f"{path} learned the Jacobians of another {file.name} (sha256 {digest[:8]}) than {file} "
                        f"({sha256(file)[:8]}): the {learned} was retrained since; re-run `surrogate`")
    values = source.predictor.name if source.predictor is not None else learned
    if values in TRAINED_PREDICTORS and values != learned and (values, learned) != ("student", "teacher"):
        raise UserError(f"predictor={values}: {path} learned the {learned}'s Jacobians (surrogate source={learned}), not the "
                        f"{values}'s; use predictor={learned}, or re-run `surrogate source={values}`")


def check_window(cfg: DictConfig, predictor) -> None:
    """One UserError unless `predictor` takes the planner's windows (T_obs, n_slots + 1): a trained model's `window`
    (distill.models.window_of; None where any size goes) must match, or its first call inside an MPC step would fail."""
    T_obs, M = getattr(predictor, "window", (None, None))
    if (T_obs is not None and cfg.T_obs != T_obs) or (M is not None and cfg.n_slots + 1 != M):
        raise UserError(f"T_obs={cfg.T_obs}, n_slots={cfg.n_slots}: the {predictor.name} model takes windows of "
                        f"{'any T_obs' if T_obs is None else f'T_obs={T_obs}'} and {'any n_slots' if M is None else f'n_slots={M - 1}'}; "
                        "set those, or retrain")


def make(scenario: str = "two_lane", overrides=()):
    """setup() of the `planner` config for `scenario` with Hydra overrides: (scenario, gradient source, mpc.Settings)."""
    return setup(planner_config(scenario, overrides))


def run_params(scenario, source, cfg: DictConfig) -> dict:
    """The MLflow params that name a planner run's set-up (compare groups rows by them) from its `planner` config."""
    return {"gradients": source.name, "zstep": get_object(cfg.zstep._target_).name, "solver": cfg.solver.name,
            "scenario": scenario.name, "seed": cfg.seed, "predictor": source.predictor.name, "mpc": cfg.mpc.name}


def drive(cfg: DictConfig, scenario, source, s: mpc.Settings, method: str, seed=None) -> closed_loop.Episode:
    """One closed-loop episode with `method` (a key of cfg.method), seeded by `seed` (default cfg.seed); with
    cfg.record_dir, every state the planner linearises at goes to <record_dir>/<scenario>_<method>_<seed>.npz."""
    step = build(cfg.method[method])
    seed = cfg.seed if seed is None else seed
    if cfg.record_dir:
        source = Recording(source)
    ep = closed_loop.drive(scenario.make_world(seed), lambda obs, warm: step(s, obs, source.at(obs.history), warm), source,
                           scenario.x_ref, scenario.target_lane, cfg.T_obs, cfg.max_steps, cfg.world, cfg.n_slots)
    if cfg.record_dir:
        source.save(Path(cfg.record_dir) / f"{scenario.name}_{method}_{seed}.npz")
    return ep
