"""`make-dataset`: build the interaction dataset, log it to MLflow (experiment `dataset`) with episode plots."""
import logging
import tempfile
from pathlib import Path

import hydra
import mlflow
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from core import validate
from core.jobs import CONF_DIR, console, guarded, mlflow_run, writable
from data import dataset
from data.plot import plot_episode

log = logging.getLogger(__name__)


@guarded
def run(cfg: DictConfig) -> dict:
    """Build, save, log; returns the dataset's meta. The plots come first, so the dataset is replaced only by a run
    whose every other step succeeded (the save itself is atomic)."""
    validate.check(cfg, "make_dataset")
    scenario = instantiate(cfg.scenario, _convert_="all")
    root = writable(cfg.out_dir, "out_dir") / cfg.dataset.name
    d = cfg.dataset  # the name alone is shared by every build of a preset (a demo's smaller one too)
    with mlflow_run("dataset", cfg, run_name=f"{d.name}-{scenario.name}-episodes{d.episodes}-seed{d.seed}"):
        with tempfile.TemporaryDirectory() as tmp:
            for e, seed in enumerate(dataset.episode_seeds(cfg.dataset.seed, cfg.plot_episodes)):  # the dataset's first
                states, _, world, _, _ = dataset.explore(scenario, dict(cfg.dataset.policy), seed, cfg.dataset.steps)
                png = Path(tmp) / f"episode_{e}.png"
                plot_episode(states, world.road, png, f"{scenario.name} episode {e} (seed {seed})", scenario.x_ref)
                mlflow.log_artifact(str(png), "plots")
        meta = dataset.make(cfg.dataset, scenario, root, OmegaConf.to_yaml(cfg, resolve=True))
        mlflow.log_metrics({f"n_{k}": v["windows"] for k, v in meta["splits"].items()})
        mlflow.log_metrics({"build_s": meta["build_s"], **{k: float(v) for k, v in meta["stats"].items()}})
        mlflow.log_artifact(str(root / "meta.json"))
    s = meta["stats"]
    log.info(f"dataset {root}: " + ", ".join(f"{k} {v['windows']}" for k, v in meta["splits"].items())
             + f" windows; built in {meta['build_s']} s; {s['collisions']}/{s['episodes']} episodes collided; "
             f"{s['nudges_opened_gap']}/{s['nudges']} nudges into a closed gap opened it")
    return meta


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="make_dataset")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Entry point of the `make-dataset` console script: overrides checked first (one line for a misspelt key)."""
    console("make_dataset", hydra_main)
