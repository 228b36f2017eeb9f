"""`planner`: closed-loop merges with ADMM-NNMPC and/or NNMPC; metrics, per-step CSV and plots to MLflow (`planner`).

`planner --gradients=surrogate` (or `--gradients surrogate`) is the same as the Hydra override `gradients=surrogate`.
"""
import sys
from pathlib import Path

import hydra
import mlflow
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig

from core.jobs import CONF_DIR, UserError, guarded, mlflow_run, writable
from planner import batch, closed_loop, mpc, nnmpc, report
from planner.gradients import make_source
from planner.zstep import ZSTEPS

CHOICES = {"method": ("admm", "nnmpc", "both"), "world": ("reactive", "predictor"), "zstep": tuple(ZSTEPS),
           "linearize": ("last_observed", "along_plan")}


def translate(argv):
    """argv with `--gradients=X` / `--gradients X` turned into the Hydra override `gradients=X`."""
    out, args = [], iter(argv)
    for a in args:
        if a == "--gradients":
            out.append(f"gradients={next(args, '')}")
        elif a.startswith("--gradients="):
            out.append(a[2:])
        else:
            out.append(a)
    return out


def check_groups(argv):
    """One clear line, before Hydra, for a config-group override naming an option that does not exist."""
    for a in argv:
        key, _, value = a.lstrip("+~").partition("=")
        group = Path(CONF_DIR) / key
        if value and "," not in value and group.is_dir() and not (group / f"{value}.yaml").exists():
            options = sorted(p.stem for p in group.glob("*.yaml"))
            raise UserError(f"unknown {key} '{value}'; choose one of {', '.join(options)}")


def settings(cfg: DictConfig, scenario) -> mpc.Settings:
    """The MPC's settings from the config and the scenario's references (m, m/s) and road."""
    lim, saf = cfg.limits, cfg.safety
    R = saf.r + saf.r_i + saf.eps
    return mpc.Settings(
        weights=instantiate(cfg.cost), y_ref=scenario.y_ref, v_ref=scenario.v_ref, road=scenario.road,
        params=scenario.params, T_p=cfg.T_p, rho=cfg.rho, R=R, delta_box=tuple(lim.delta), a_box=tuple(lim.a),
        psi_box=tuple(lim.psi), v_box=tuple(lim.v), y_margin=lim.y_margin, linearize=cfg.linearize,
        admm=dict(cfg.admm), zstep=cfg.zstep, sqp=instantiate(cfg.sqp), pygranso=instantiate(cfg.pygranso),
        osqp=dict(cfg.osqp), check_tol=saf.check_tol, check_steps=saf.check_steps, brake=cfg.brake)


def drive(cfg: DictConfig, scenario, source, s: mpc.Settings, method: str, seed=None):
    """One closed-loop episode with `method`, seeded by `seed` (default cfg.seed)."""
    if method == "admm":
        step = lambda obs, warm: mpc.admm_step(s, obs, source, warm)
    else:
        step = lambda obs, warm: nnmpc.nnmpc_step(s, obs, source, warm, cfg.nnmpc.lengths, cfg.nnmpc.accels)
    world = scenario.make_world(cfg.seed if seed is None else seed)
    return closed_loop.drive(world, step, source, scenario.x_ref, scenario.target_lane, cfg.T_obs, cfg.max_steps, cfg.world)


@guarded
def run(cfg: DictConfig) -> dict:
    """Drive, log and summarise (cfg.episodes > 0: batch statistics, see planner.batch); returns {method: metrics}."""
    for key, options in CHOICES.items():
        if cfg[key] not in options:
            raise UserError(f"unknown {key} '{cfg[key]}'; choose one of {', '.join(options)}")
    scenario = instantiate(cfg.scenario, _convert_="all")
    source = make_source(cfg.gradients, cfg.predictor, cfg.models_dir, cfg.fd_step, dict(cfg.analytic))
    s = settings(cfg, scenario)
    out_dir = writable(Path(cfg.out_dir or HydraConfig.get().runtime.output_dir), "out_dir")
    methods = ["admm", "nnmpc"] if cfg.method == "both" else [cfg.method]
    if cfg.episodes:
        return batch.run(cfg, scenario.name, source, methods, out_dir)
    episodes = {m: drive(cfg, scenario, source, s, m) for m in methods}
    title = f"{scenario.name}, gradients={source.name}, predictor={source.predictor.name}, world={cfg.world}"
    shared = report.figures(episodes, scenario.road, scenario.x_ref, scenario.y_ref, out_dir, title) \
        if cfg.plots and len(episodes) > 1 else []
    results = {}
    for m, ep in episodes.items():
        results[m] = report.metrics(ep, scenario.y_ref, scenario.x_ref, cfg.merge_tol)
        csv_path = out_dir / f"steps_{m}.csv"
        report.write_csv(ep, csv_path)
        with mlflow_run("planner", cfg, run_name=f"{m}-{source.name}-{scenario.name}", gradients=source.name, method=m,
                        zstep=cfg.zstep, scenario=scenario.name, seed=cfg.seed, predictor=source.predictor.name):
            mlflow.log_metrics(results[m])
            mlflow.log_artifact(str(csv_path))
            own = report.figures({m: ep}, scenario.road, scenario.x_ref, scenario.y_ref, out_dir, title) if cfg.plots else []
            for p in own + shared:
                mlflow.log_artifact(str(p), "plots")
            if ep.notes:
                mlflow.set_tag("notes", "; ".join(ep.notes))
        reasons = sorted({r["fallback"] for r in ep.rows if r["fallback"]})
        for note in ep.notes + [f"fallback: {r}" for r in reasons]:
            print(f"[{m}] {note}")
    print(f"{title}, seed {cfg.seed}; outputs in {out_dir}")
    print(report.table({f"{scenario.name}/{m}": r for m, r in results.items()}))
    return results


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="planner")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


@guarded
def prepare(argv):
    """The argv Hydra will read: --gradients translated, config-group options checked."""
    argv = translate(argv)
    check_groups(argv[1:])
    return argv


def main() -> None:
    """Console entry point."""
    sys.argv = prepare(sys.argv)
    hydra_main()
