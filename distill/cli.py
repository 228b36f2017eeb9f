"""`distill`: train the teacher (model=teacher) or distil, certify and export the student (model=student)."""
import hydra
from omegaconf import DictConfig

from core.jobs import CONF_DIR, console, guarded
from distill.train import run


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="distill")
def hydra_main(cfg: DictConfig) -> None:
    guarded(run)(cfg)


def main() -> None:
    """Entry point of the `distill` console script."""
    console("distill", hydra_main)
