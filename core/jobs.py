"""What every job shares: one-line user errors, atomic writes, and MLflow runs that log their whole config."""
import contextlib
import os
import shutil
import sys
import tempfile
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

DEFAULT_TRACKING_URI = "sqlite:///mlflow.db"
CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")  # Hydra configs live beside the packages (editable install)


class UserError(Exception):
    """A problem the user can fix (missing or corrupt file, bad value); printed as one line, never a traceback."""


def guarded(fn):
    """Run a job body; a UserError becomes one 'error: ...' line on stderr and exit status 2."""

    def run(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except UserError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)

    run.__name__, run.__doc__ = fn.__name__, fn.__doc__
    return run


def flatten(cfg: DictConfig) -> dict:
    """Resolved config as {'a.b.c': value} strings, the form MLflow params take."""
    out = {}

    def walk(node, prefix):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}.")
        else:
            out[prefix[:-1]] = str(node)[:6000]

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return out


@contextlib.contextmanager
def mlflow_run(experiment: str, cfg: DictConfig, run_name: str | None = None, **params):
    """An MLflow run in `experiment` with the flattened config and `params` logged; FAILED with the error on exception."""
    import mlflow

    mlflow.set_tracking_uri(os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_TRACKING_URI))
    mlflow.set_experiment(experiment)
    with mlflow.start_run(run_name=run_name) as run:
        flat = {**flatten(cfg), **{k: str(v) for k, v in params.items()}}
        items = list(flat.items())
        for i in range(0, len(items), 100):
            mlflow.log_params(dict(items[i : i + 100]))
        mlflow.log_text(OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
        try:
            yield run
        except BaseException as e:
            mlflow.set_tag("error", f"{type(e).__name__}: {e}"[:5000])
            raise


def writable(folder: Path, key: str) -> Path:
    """`folder`, created and checked by writing a probe file; otherwise one UserError naming the config `key`."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as e:
        raise UserError(f"cannot write to the output folder {folder} ({e.strerror or e}); choose another with {key}=...") from None
    return folder


@contextlib.contextmanager
def atomic_dir(final: Path):
    """Yield a fresh temporary folder beside `final`; on success it replaces `final`, on failure `final` is untouched."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    if final.exists():
        final.rename(old)
    tmp.rename(final)
    shutil.rmtree(old, ignore_errors=True)


def atomic_file(final: Path, write):
    """Call write(tmp_path) then rename over `final`, so a crash never leaves a half-written file there."""
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}{final.suffix}")
    try:
        write(tmp)
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)
