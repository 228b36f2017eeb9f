"""`distill`: train the teacher (model=teacher) or distil, certify and export the student (model=student)."""
import hydra
from omegaconf import DictConfig

from core.jobs import CONF_DIR, guarded
from distill.train import run


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="distill")
def main(cfg: DictConfig) -> None:
    """Entry point of the `distill` console script."""
    guarded(run)(cfg)
