"""What every job shares: one-line user errors, stop signals, atomic writes, and MLflow runs that log their whole config."""
import contextlib
import fcntl
import os
import shutil
import signal
import sys
import tempfile
import threading
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

DEFAULT_TRACKING_URI = "sqlite:///mlflow.db"
CONF_DIR = str(Path(__file__).resolve().parents[1] / "conf")  # Hydra configs live beside the packages (editable install)


def job_config(name: str, overrides=()) -> DictConfig:
    """The config of job `name` (conf/<name>.yaml) with Hydra overrides, composed as its console script would (inside a
    running Hydra job, by its own search path)."""
    if GlobalHydra.instance().is_initialized():
        return compose(name, overrides=list(overrides))
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(name, overrides=list(overrides))


def build(node, **kwargs):
    """instantiate(node, **kwargs) with plain containers; a UserError raised while building (a missing model) is
    re-raised as itself, not wrapped in Hydra's InstantiationException."""
    try:
        return instantiate(node, _convert_="all", **kwargs)
    except InstantiationException as e:
        cause = e.__cause__
        while cause is not None and not isinstance(cause, UserError):
            cause = cause.__cause__
        if cause is None:
            raise
        raise cause from None


def options(group: str) -> list[str]:
    """The options of config group `group` (conf/<group>/*.yaml), sorted; none for a folder that does not exist."""
    return sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml"))


def job_groups(choices) -> str:
    """--help's list of a job's config groups: each group of its defaults list with its options and the chosen one."""
    lines = []
    for group, chosen in choices.items():
        if not group.startswith("hydra/") and chosen is not None:
            lines.append(f"{group}: {' | '.join(options(group))}  (now {chosen})")
    return "\n".join(lines) or "none: every setting is a key below"


OmegaConf.register_new_resolver("job_groups", job_groups, replace=True)  # used by conf/hydra/help/job.yaml


class UserError(Exception):
    """A problem the user can fix (missing or corrupt file, bad value); printed as one line, never a traceback."""


def check_groups(argv):
    """One clear line, before Hydra, for a config-group override naming an option that does not exist (each value of a
    comma-separated sweep checked)."""
    for a in argv:
        key, _, value = a.lstrip("+~").partition("=")
        choices = options(key)  # none: not a config group
        if not value or not choices:
            continue
        for v in value.split(","):
            if v not in choices:
                raise UserError(f"unknown {key} '{v}'; choose one of {', '.join(choices)}")


def check_overrides(config_name: str, argv) -> None:
    """check_groups, then one UserError line for an override Hydra would reject with several (a misspelt key); argv with
    Hydra's own flags (--help, --multirun, ...) is left to Hydra."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    check_groups(argv)
    if any(a.startswith("-") for a in argv):
        return
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            compose(config_name, overrides=list(argv))
    except (HydraException, OmegaConfBaseException) as e:
        cause = e.__cause__ if isinstance(e.__cause__, OmegaConfBaseException) else None
        raise UserError(" ".join(str(x).splitlines()[0].rstrip(".") + "." for x in (e, cause) if x is not None)) from None


class Stopped(BaseException):
    """The job was stopped by a signal; not an Exception, so no `except Exception` in a library swallows it."""

    def __init__(self, signum: int):
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum


_STOPPED = []  # the signal that stopped this process: a library that catches Stopped may raise its own error instead


def _stop(signum, frame):
    signal.signal(signum, signal.SIG_IGN)  # a second signal must not interrupt the clean-up this one starts
    _STOPPED.append(signum)
    raise Stopped(signum)


def stop_signal() -> int | None:
    """The signal that stopped this process, or None while none has."""
    return _STOPPED[0] if _STOPPED else None


def quiet() -> bool:
    """No progress bars under CI (the CI variable set, as every CI service does) or when stderr is not a terminal."""
    return bool(os.environ.get("CI")) or not sys.stderr.isatty()


def drop_empty_run_dir():
    """Remove the running Hydra job's output folder (and its parents, while empty) when it holds nothing but Hydra's own
    records (.hydra/, empty logs): a rejected command writes nothing."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    if not run_dir.is_dir() or any(p.name != ".hydra" and not (p.suffix == ".log" and p.stat().st_size == 0)
                                   for p in run_dir.iterdir()):
        return
    shutil.rmtree(run_dir, ignore_errors=True)
    for parent in run_dir.parents:
        if parent == Path.cwd() or not parent.is_dir() or any(parent.iterdir()):
            break
        parent.rmdir()


def guarded(fn):
    """Run a job body; a UserError becomes one 'error: ...' line on stderr and exit status 2 (its empty Hydra folder
    removed), SIGTERM and SIGINT one line and exit 128 + the signal number.

    Both signals raise Stopped (Lightning, which otherwise turns SIGTERM into a clean exit 0 and Ctrl-C into exit 1, calls
    this handler after its own), so the MLflow run ends KILLED and `make` stops.
    """

    def run(*args, **kwargs):
        main = threading.current_thread() is threading.main_thread()
        _STOPPED.clear()  # a job starts unstopped, whatever stopped an earlier one in this process
        previous = {s: signal.signal(s, _stop) for s in (signal.SIGTERM, signal.SIGINT)} if main else {}
        try:
            return fn(*args, **kwargs)
        except UserError as e:
            print(f"error: {e}", file=sys.stderr)
            drop_empty_run_dir()
            sys.exit(2)
        except Stopped as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(128 + e.signum)
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)

    run.__name__, run.__doc__ = fn.__name__, fn.__doc__
    return run


def console(config_name: str, hydra_main) -> None:
    """A console script: sys.argv's overrides checked first (check_overrides: one line, exit 2), then `hydra_main` (a
    hydra.main function of config `config_name`)."""
    guarded(check_overrides)(config_name, sys.argv[1:])
    hydra_main()


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


def tracking_uri() -> str:
    """The MLflow store: $MLFLOW_TRACKING_URI, else sqlite:///mlflow.db in the working directory."""
    return os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_TRACKING_URI)


@contextlib.contextmanager
def store_lock(uri: str):
    """An exclusive lock on a SQLite store (a `.lock` file beside it), held while MLflow creates or migrates its schema.

    Two jobs opening a new store at once would both run the migrations and leave it unreadable
    (`table _alembic_tmp_tags already exists`); other stores need no lock.
    """
    if not uri.startswith("sqlite:///"):
        yield
        return
    db = Path(uri[len("sqlite:///"):])
    db.parent.mkdir(parents=True, exist_ok=True)
    with open(db.with_name(db.name + ".lock"), "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def create_store(uri: str) -> None:
    """A new SQLite store built whole in a temporary file beside it and renamed into place (call under store_lock): a job
    killed while MLflow creates its tables leaves no half-made store behind."""
    from mlflow.tracking import MlflowClient

    db = Path(uri[len("sqlite:///"):])
    if db.exists() and db.stat().st_size:
        return
    tmp = db.with_name(f".{db.name}.creating")
    leftovers = [tmp, *(tmp.with_name(tmp.name + s) for s in ("-journal", "-wal", "-shm"))]  # SQLite's own beside it
    for f in leftovers:  # a creator killed outright (SIGKILL) left them; the lock says nobody else is writing them
        f.unlink(missing_ok=True)
    try:
        MlflowClient(f"sqlite:///{tmp}").search_experiments(max_results=1)
        os.replace(tmp, db)
    finally:
        for f in leftovers:
            f.unlink(missing_ok=True)


STORE_TIMEOUT_S = 10  # how long open_experiment waits for a tracking server before the job gives up


def open_experiment(experiment: str) -> str:
    """Create the store (once, under store_lock) and the experiment if needed, make it current; returns the tracking URI.

    Called before a job's work: a store that cannot be written or reached is one UserError at once, a server that does
    not answer within STORE_TIMEOUT_S without MLflow's minutes of retries.
    """
    import mlflow

    uri = tracking_uri()
    quick = {"MLFLOW_HTTP_REQUEST_TIMEOUT": str(STORE_TIMEOUT_S), "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0"}
    saved = {k: os.environ.get(k) for k in quick}
    os.environ.update(quick)
    try:
        with store_lock(uri):
            if uri.startswith("sqlite:///"):
                db = Path(uri[len("sqlite:///"):])
                if not os.access(db.parent, os.W_OK) or (db.exists() and not os.access(db, os.W_OK)):
                    raise OSError(f"{db} is not writable")
                create_store(uri)
            mlflow.set_tracking_uri(uri)
            mlflow.set_experiment(experiment)
    except Exception as e:  # OSError, sqlalchemy's and MLflow's own types: the store is unusable either way
        why = (str(e).splitlines() or [""])[0][:200]
        raise UserError(f"cannot use the MLflow store {uri} ({type(e).__name__}: {why}); set MLFLOW_TRACKING_URI to a "
                        "writable sqlite:///path or a running server") from None
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k)
            else:
                os.environ[k] = v
    return uri


@contextlib.contextmanager
def mlflow_run(experiment: str, cfg: DictConfig, run_name: str | None = None, **params):
    """An MLflow run in `experiment` with the flattened config and `params` logged; on exception it ends FAILED with the
    error as a tag, or KILLED when the job was stopped (Stopped, Ctrl-C)."""
    import mlflow

    open_experiment(experiment)
    run = mlflow.start_run(run_name=run_name)
    try:
        flat = {**flatten(cfg), **{k: str(v) for k, v in params.items()}}
        items = list(flat.items())
        for i in range(0, len(items), 100):
            mlflow.log_params(dict(items[i : i + 100]))
        mlflow.log_text(OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
        yield run
    except BaseException as e:
        mlflow.set_tag("error", f"{type(e).__name__}: {e}"[:5000])
        mlflow.end_run("KILLED" if isinstance(e, (Stopped, KeyboardInterrupt)) else "FAILED")
        raise
    mlflow.end_run("FINISHED")


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


@contextlib.contextmanager
def staged(folder: Path):
    """Yield a private staging folder inside `folder`; only when the block succeeds does every file written there replace
    its namesake in `folder` (each by an atomic rename), so a job that fails anywhere leaves its old outputs intact."""
    folder = Path(folder)
    stage = folder / f".staging-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    try:
        yield stage
        for f in sorted(stage.iterdir()):
            os.replace(f, folder / f.name)
    finally:
        shutil.rmtree(stage, ignore_errors=True)


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
