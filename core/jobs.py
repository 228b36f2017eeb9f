"""What every job shares: one-line user errors, stop signals, atomic writes, and MLflow runs that log their whole config."""
import contextlib
import difflib
import errno
import fcntl
import mmap
import os
import shutil
import signal
import sys
import tempfile
import threading
import uuid
from functools import partial
from pathlib import Path

import numpy as np
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
    """instantiate(node, **kwargs) with plain containers, each `_partial_: true` object a plain functools.partial (the
    installed Hydra's partial checks its target policy, a sha256 of it included, on every call: ~0.2 ms of a planner
    step; the target was checked once here, when built); a UserError raised while building (a missing model) is
    re-raised as itself, not wrapped in Hydra's InstantiationException."""
    try:
        return plain(instantiate(node, _convert_="all", **kwargs))
    except InstantiationException as e:
        cause = e.__cause__
        while cause is not None and not isinstance(cause, UserError):
            cause = cause.__cause__
        if cause is None:
            raise
        raise cause from None


def plain(obj):
    """obj; a partial as a plain functools.partial of the same function and arguments, those plain too."""
    if not isinstance(obj, partial):
        return obj
    return partial(obj.func, *map(plain, obj.args), **{k: plain(v) for k, v in obj.keywords.items()})


def options(group: str) -> list[str]:
    """The options of config group `group` (conf/<group>/*.yaml), sorted; none for a folder that does not exist."""
    return sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml"))


def job_groups(choices) -> str:
    """--help's list of a job's config groups: each group of its defaults list with its options and the chosen one."""
    lines = []
    for group, chosen in choices.items():
        if not group.startswith("hydra/"):
            lines.append(f"{group}: {' | '.join(options(group))}  (now {chosen or 'none'})")
    return "\n".join(lines) or "none: every setting is a key below"


def job_keys(config_name: str, keys, _root_) -> str:
    """--help's keys of job `config_name`: each of keys[config_name] ({key: meaning}) as `key=<value now>: meaning`, a
    group by its chosen option; a job without an entry: its top-level settings with their values."""
    chosen = _root_.hydra.runtime.choices
    value = lambda k: chosen[k] if k in chosen else OmegaConf.select(_root_, k, default="?")
    mine = keys.get(config_name) if keys is not None else None
    if mine is None:
        return "\n".join(f"{k}={v}" for k, v in _root_.items() if k != "hydra" and not OmegaConf.is_dict(v))
    short = lambda v: (str(v)[:37] + "...") if len(str(v)) > 40 else str(v)
    return "\n".join(f"{k}={short(value(k))}: {meaning}" for k, meaning in mine.items())


OmegaConf.register_new_resolver("job_groups", job_groups, replace=True)  # used by conf/hydra/help/job.yaml
OmegaConf.register_new_resolver("job_keys", job_keys, replace=True)


class UserError(Exception):
    """A problem the user can fix (missing or corrupt file, bad value); printed as one line, never a traceback."""


class MissingModel(UserError):
    """A model file that has not been made yet (a job that can do without it may skip it; a corrupt one is a UserError)."""


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
                near = difflib.get_close_matches(v, choices, n=1)
                raise UserError(f"unknown {key} '{v}'; " + (f"did you mean {key}={near[0]}? (choose one of {', '.join(choices)})"
                                                            if near else f"choose one of {', '.join(choices)}"))


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
        unknown = misspelt(config_name, argv)
        if unknown:
            raise UserError(unknown) from None
        cause = e.__cause__ if isinstance(e.__cause__, OmegaConfBaseException) else None
        raise UserError(" ".join(str(x).splitlines()[0].rstrip(".") + "." for x in (e, cause) if x is not None)) from None


def leaf_keys(node, prefix: str = "") -> list[str]:
    """The dotted keys of a nested dict's leaves."""
    if not isinstance(node, dict):
        return [prefix[:-1]]
    return [k for key, v in node.items() for k in leaf_keys(v, f"{prefix}{key}.")]


def misspelt(config_name: str, argv) -> str | None:
    """'unknown key K; did you mean N?' for the first override of argv whose key is neither a key of the job's default
    config nor a config group, N the nearest of those (difflib); None when every key exists."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(config_name)
    keys = [*leaf_keys(OmegaConf.to_container(cfg, resolve=False)), *(p.name for p in Path(CONF_DIR).iterdir() if p.is_dir())]
    for a in argv:
        key = a.lstrip("+~").partition("=")[0]
        if a.startswith("+") or key in keys or any(k.startswith(f"{key}.") for k in keys):
            continue
        near = difflib.get_close_matches(key, keys, n=1, cutoff=0.6)
        return f"unknown key '{key}'" + (f"; did you mean {near[0]}?" if near else f" (`{config_name} --help` lists them)")
    return None


class Stopped(BaseException):
    """The job was stopped by a signal; not an Exception, so no `except Exception` in a library swallows it."""

    def __init__(self, signum: int):
        super().__init__(f"stopped by {signal.Signals(signum).name}")
        self.signum = signum


_STOPPED = []  # the signal that stopped this process: a library that catches Stopped may raise its own error instead
RETRY_S = 0.005  # s: how soon a signal held back inside a compiled call is tried again
_DEFERRED = []  # non-empty inside uninterrupted(): a stop signal is recorded there and raised at its end


STOPS = (int(signal.SIGINT), int(signal.SIGTERM))  # the signals that stop a job
SIGNAL_BYTES = 4096  # signals a compiled call can see arrive (one byte each) between two stops consumed


def _signal_file() -> tuple[int, np.ndarray, tuple]:
    """A memory file (non-blocking, as signal.set_wakeup_fd needs), its bytes as an array and its (inode, device):
    guarded makes it the wakeup fd, to which Python's C-level handler writes each handled signal's number at once,
    one byte after another, also while a compiled call holds the interpreter; the long compiled loops
    (planner.zstep.stop_requested) read the array, passed as an argument (a numba global is frozen as a constant),
    and return early."""
    fd = os.memfd_create("signals", os.MFD_CLOEXEC)
    os.ftruncate(fd, SIGNAL_BYTES)
    os.set_blocking(fd, False)
    return fd, np.frombuffer(mmap.mmap(fd, SIGNAL_BYTES), np.uint8), os.fstat(fd)[1:3]


_SIGNAL_FD, SIGNALS, _SIGNAL_ID = _signal_file()  # _SIGNAL_ID (inode, device): whether the number still names this file


def _own_signal_file() -> None:
    """A signal file of this process's own where its number now names another file (a library that dup2s a log onto
    it): set_wakeup_fd refuses a blocking one, and a log is no place for signal bytes. Not the Ray launcher's case,
    a copy of this module's globals, which guarded's closure avoids by reaching them through _start_job."""
    global _SIGNAL_FD, SIGNALS, _SIGNAL_ID
    try:
        ours = os.fstat(_SIGNAL_FD)[1:3] == _SIGNAL_ID
    except OSError:
        ours = False
    if not ours:  # the number is another file's now: not ours to close
        _SIGNAL_FD, SIGNALS, _SIGNAL_ID = _signal_file()


def _clear_signals() -> None:
    """SIGNALS empty and the next signal's byte written at its start: what stopped a job stops nothing after it."""
    os.lseek(_SIGNAL_FD, 0, os.SEEK_SET)
    SIGNALS[:] = 0


def _unshare_signals() -> None:
    """In a forked child, a signal file of its own (a fork shares the parent's), its wakeup fd where the parent's was:
    neither stops the other's compiled calls."""
    global _SIGNAL_FD, SIGNALS, _SIGNAL_ID
    wakeup = signal.set_wakeup_fd(-1)
    parent, (_SIGNAL_FD, SIGNALS, _SIGNAL_ID) = _SIGNAL_FD, _signal_file()
    signal.set_wakeup_fd(_SIGNAL_FD if wakeup == parent else wakeup)
    os.close(parent)


os.register_at_fork(after_in_child=_unshare_signals)


def _in_numba_callback(frame) -> bool:
    """Whether `frame` runs inside numba's unpickler, which compiled code calls back into Python (to build an exception
    or a constant): an exception raised there is lost by the compiled caller (SystemError "returned a result with an
    exception set") or crashes it (a segmentation fault in planner.admm's one-call solve)."""
    serialize = sys.modules.get("numba.core.serialize")
    while serialize is not None and frame is not None:
        if frame.f_code.co_filename == serialize.__file__:
            return True
        frame = frame.f_back
    return False


def _stop(signum, frame):
    """SIGTERM/SIGINT: raise Stopped here, or, where raising is unsafe, at the first safe point; a later signal is
    ignored (the first one's clean-up runs)."""
    if _STOPPED and not _STOPPED[1:]:  # a second signal while the first one is being handled
        return
    if not _STOPPED:
        _STOPPED.append(signum)
    _STOPPED[1:] = []
    if _DEFERRED:
        return  # uninterrupted() raises it when its block ends
    if _in_numba_callback(frame):
        _STOPPED.append("retry")  # marks the next call of this handler as this signal's, not a second one
        # this handler again, from a thread: it runs once the compiled call has returned the GIL to Python code
        retry = threading.Timer(RETRY_S, _retry, (signum,))
        retry.daemon = True
        retry.start()
        return
    raise Stopped(signum)


def _retry(signum) -> None:
    """Run the stop handler again (in the main thread, at its next bytecode) if its signal is still waiting for it: not
    once something else raised it (check_stopped) or the job ended."""
    import _thread

    if _STOPPED[1:] == ["retry"]:
        _thread.interrupt_main(signum)


@contextlib.contextmanager
def uninterrupted():
    """A block a stop signal does not cut: one that arrives inside it is raised (Stopped) when the block ends."""
    before = stop_signal()
    _DEFERRED.append(True)
    try:
        yield
    finally:
        _DEFERRED.pop()
    if before is None and stop_signal() is not None and not _DEFERRED:
        raise Stopped(stop_signal())


def check_stopped() -> None:
    """Raise Stopped if a stop signal arrived (for a loop whose step may have caught the signal's exception)."""
    if stop_signal() is not None:
        _STOPPED[1:] = []  # raised here: a retry still to come has nothing left to do
        raise Stopped(stop_signal())


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


def _start_job() -> tuple[bool, dict]:
    """A job's start: unstopped, no model file read yet; on the main thread the stop handlers and this process's signal
    file as the wakeup fd. Whether on the main thread, and what to restore: {signal or "wakeup": the previous}."""
    main = threading.current_thread() is threading.main_thread()
    _STOPPED.clear()  # a job starts unstopped, whatever stopped an earlier one in this process
    MODEL_FILES.clear()  # the model files this job reads, not those of a job run before it in this process
    if not main:
        return False, {}
    previous = {s: signal.signal(s, _stop) for s in (signal.SIGTERM, signal.SIGINT)}
    _own_signal_file()
    _clear_signals()
    previous["wakeup"] = signal.set_wakeup_fd(_SIGNAL_FD)
    return True, previous


def _end_job(main: bool, previous: dict) -> None:
    """A job's end: the handlers and wakeup fd _start_job replaced, restored; what stopped it stops nothing after it."""
    if not main:
        return
    signal.set_wakeup_fd(previous.pop("wakeup"))
    for s, handler in previous.items():
        signal.signal(s, handler)
    _STOPPED.clear()  # what stopped this job stops nothing after it (the next job, a test)
    _clear_signals()


def guarded(fn):
    """Run a job body; a UserError or a full disk becomes one 'error: ...' line on stderr and exit status 2 (a UserError's
    empty Hydra folder removed), SIGTERM and SIGINT one line and exit 128 + the signal number.

    Both signals raise Stopped (Lightning, which otherwise turns SIGTERM into a clean exit 0 and Ctrl-C into exit 1, calls
    this handler after its own), so the MLflow run ends KILLED and `make` stops.
    """

    def run(*args, **kwargs):
        # the closure reaches this module's state only through its functions: a job sent to a Ray worker (Hydra's Ray
        # launcher) is pickled by value with a copy of the globals it names, the parent's signal file among them
        main, previous = _start_job()
        try:
            return fn(*args, **kwargs)
        except UserError as e:
            print(f"error: {e}", file=sys.stderr)
            drop_empty_run_dir()
            sys.exit(2)
        except Stopped as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(128 + e.signum)
        except Exception as e:
            if stop_signal() is not None:  # a library turned the signal's Stopped into an error of its own
                print(f"error: stopped by {signal.Signals(stop_signal()).name}", file=sys.stderr)
                sys.exit(128 + stop_signal())
            if not (isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT)):
                raise
            print(f"error: no space left on the device ({e.filename2 or e.filename or 'an output file'}); the old outputs "
                  "are kept", file=sys.stderr)
            sys.exit(2)
        finally:
            _end_job(main, previous)

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


def logged_params(cfg: DictConfig) -> dict:
    """What an MLflow run logs of its config (the whole of it is the run's config.yaml): inside a Hydra job the chosen
    option of each config group, every top-level setting and each nested key the command line set; outside one (a test,
    a job composed in-process) every key. Hydra's own keys (_target_, _partial_, ...) never."""
    from hydra.core.hydra_config import HydraConfig

    flat = {k: v for k, v in flatten(cfg).items() if not k.rpartition(".")[2].startswith("_")}
    if not HydraConfig.initialized() or not is_job_config(cfg):
        return flat
    hc = HydraConfig.get()
    chosen = {g: str(c) for g, c in hc.runtime.choices.items() if not g.startswith("hydra/") and c is not None}
    set_keys = [k for k in (o.split("=", 1)[0].lstrip("+~") for o in hc.overrides.task) if k not in chosen]
    return {**chosen, **{k: v for k, v in flat.items()
                         if "." not in k or any(k == o or k.startswith(f"{o}.") for o in set_keys)}}


def is_job_config(cfg: DictConfig) -> bool:
    """Whether `cfg` is the running Hydra job's own config (its top-level keys those of conf/<job>.yaml and its groups),
    not one a job composed for another it runs in-process (`results` running `planner`)."""
    from hydra.core.hydra_config import HydraConfig

    primary = OmegaConf.load(Path(CONF_DIR) / f"{HydraConfig.get().job.config_name}.yaml")
    groups = {g for g in HydraConfig.get().runtime.choices if "/" not in g}
    own = set(primary) - {"defaults", "hydra"}
    return own <= set(cfg) <= own | groups


def command_overrides() -> list[str]:
    """The running Hydra job's command-line overrides (none outside a Hydra job)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


MODEL_FILES = {}  # {file name: sha256} of every model file the running job has read (model_file), logged on its runs


def sha256(path) -> str:
    """The hex SHA-256 of a file's bytes: what ties a file made from another (a certificate, a surrogate) to that one."""
    import hashlib

    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def model_file(path) -> Path:
    """`path`, recorded with its sha256 as a model file this process read: each MLflow run of the process logs it as
    the param sha256.<file name> (<file name>.2, .3 for further files of that name with other bytes: a judge's)."""
    path = Path(path)
    digest, key, n = sha256(path), path.name, 1
    while MODEL_FILES.get(key, digest) != digest:
        n += 1
        key = f"{path.name}.{n}"
    MODEL_FILES[key] = digest
    return path


def made_models(paths) -> None:
    """Tag the active MLflow run as the maker of model files `paths` (tag sha256.<file name>: how a run that reads one
    finds the run that made it) and log them as artifacts under models/ (a runs:/ models_dir downloads them)."""
    import mlflow

    for p in map(Path, paths):
        mlflow.set_tag(f"sha256.{p.name}", sha256(p))
        mlflow.log_artifact(str(p), "models")


def model_runs(files: dict, experiments=("distill", "surrogate")) -> dict:
    """{file name: the newest finished run of `experiments` that made a file of these bytes} for {file name: sha256}
    (a name with a .2 suffix is its base file's); a file no logged run made is left out."""
    import mlflow

    experiments = [e for e in experiments if mlflow.get_experiment_by_name(e) is not None]
    found = {}
    for key, digest in files.items() if experiments else ():
        name = key if key.count(".") < 2 or not key.rpartition(".")[2].isdigit() else key.rpartition(".")[0]
        runs = mlflow.search_runs(experiment_names=list(experiments), filter_string=f"tags.`sha256.{name}` = '{digest}' "
                                  "and attributes.status = 'FINISHED'", order_by=["attributes.start_time DESC"],
                                  max_results=1, output_format="list")
        if runs:
            found[key] = runs[0]
    return found


def models_cache() -> Path:
    """Where a runs:/ or models:/ models_dir is downloaded: beside a SQLite store (models_cache/), else the user's cache."""
    uri = tracking_uri()
    if uri.startswith("sqlite:///"):
        return Path(uri[len("sqlite:///"):]).parent / "models_cache"
    return Path.home() / ".cache" / "admm-nnmpc" / "models"


def local_models_dir(models_dir: str) -> str:
    """A folder of model files for `models_dir`: itself, or for runs:/<run id>[/<path>] or models:/<name>/<version> (a
    registered model, or models:/<model id> of a logged one) the model run's models/ artifacts, downloaded once to
    models_cache()/<run id> (whole or not at all); one UserError when the run or model does not exist or has none."""
    models_dir = str(models_dir)
    if not models_dir.startswith(("runs:/", "models:/")):
        return models_dir
    import mlflow

    uri = tracking_uri()
    if uri.startswith("sqlite:///"):
        with store_lock(uri):  # a new store built whole, as every job's (open_experiment)
            create_store(uri)
    mlflow.set_tracking_uri(uri)
    client = mlflow.MlflowClient()
    try:
        if models_dir.startswith("runs:/"):
            run_id, _, sub = models_dir[len("runs:/"):].strip("/").partition("/")
        else:
            name, _, version = models_dir[len("models:/"):].strip("/").partition("/")
            if version:
                mv = client.get_model_version(name, version) if version.isdigit() else \
                    client.get_model_version_by_alias(name, version.lstrip("@"))
                run_id = mv.run_id
            else:
                run_id = client.get_logged_model(name).source_run_id
            sub = ""
        sub = sub or "models"
        dest = models_cache() / run_id / sub
        if not dest.is_dir():
            tmp = dest.parent / f".download-{os.getpid()}"
            tmp.mkdir(parents=True, exist_ok=True)
            os.environ["MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR"] = "false"  # one line per job, not a bar per file
            try:
                mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=sub, dst_path=str(tmp))
                os.replace(tmp / sub, dest)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
    except Exception as e:  # MLflow's own error types for a missing run, model or artifact
        why = (str(e).splitlines() or [""])[0][:200]
        raise UserError(f"models_dir={models_dir}: no model files there in the MLflow store {tracking_uri()} "
                        f"({type(e).__name__}: {why}); pass a folder or a run that logged models/") from None
    if not dest.is_dir() or not any(dest.iterdir()):
        raise UserError(f"models_dir={models_dir}: run {run_id} logged no model files under {sub}/")
    return str(dest)


def tracking_uri() -> str:
    """The MLflow store: $MLFLOW_TRACKING_URI, else (unset or empty) sqlite:///mlflow.db in the working directory."""
    return os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_TRACKING_URI


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
    db = db.resolve()
    for f in db.parent.glob(f".{db.name}.creating-*"):  # a creator killed outright (SIGKILL) left them (with SQLite's
        f.unlink(missing_ok=True)  # -journal beside them); the lock says nobody else is writing them
    # A name of its own each time: MLflow keeps the store of a URI it has opened, so a second store created at a name
    # already used in this process (another folder, or the same one after a removal) would never be written.
    tmp = db.with_name(f".{db.name}.creating-{os.getpid()}-{uuid.uuid4().hex}")
    try:
        MlflowClient(f"sqlite:///{tmp}").search_experiments(max_results=1)
        os.replace(tmp, db)
    finally:
        for f in db.parent.glob(f"{tmp.name}*"):
            f.unlink(missing_ok=True)


def artifacts_beside(db: Path, experiment_id: str) -> None:
    """Point a SQLite store's experiment that holds no runs yet at <the store's folder>/mlruns/<id>, written as the
    store's own path is (relative for the default sqlite:///mlflow.db): MLflow would write the absolute path of the
    folder the first job ran in, so a moved or copied store would lose its artifacts. Call under store_lock."""
    import sqlite3

    want = str(db.parent / "mlruns" / experiment_id)
    with contextlib.closing(sqlite3.connect(db)) as con, con:
        (location,), (runs,) = (con.execute("SELECT artifact_location FROM experiments WHERE experiment_id = ?",
                                            (experiment_id,)).fetchone(),
                                con.execute("SELECT count(*) FROM runs WHERE experiment_id = ?", (experiment_id,)).fetchone())
        if location != want and not runs:
            con.execute("UPDATE experiments SET artifact_location = ? WHERE experiment_id = ?", (want, experiment_id))


STORE_TIMEOUT_S = 10  # how long open_experiment waits for a tracking server before the job gives up


def open_experiment(experiment: str) -> str:
    """Create the store (once, under store_lock) and the experiment if needed, make it current; returns the tracking URI.

    Called before a job's work: a store that cannot be written or reached is one UserError at once, a server that does
    not answer within STORE_TIMEOUT_S without MLflow's minutes of retries.
    """
    import mlflow

    uri = tracking_uri()
    quick = {"MLFLOW_HTTP_REQUEST_TIMEOUT": str(STORE_TIMEOUT_S), "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0"}
    # set_tracking_uri also writes its URI to MLFLOW_TRACKING_URI: left absolute, the next tracking_uri() would make
    # artifacts_beside write an absolute artifact path
    saved = {k: os.environ.get(k) for k in (*quick, "MLFLOW_TRACKING_URI")}
    os.environ.update(quick)
    try:
        with store_lock(uri):
            if uri.startswith("sqlite:///"):
                db = Path(uri[len("sqlite:///"):])
                if not os.access(db.parent, os.W_OK) or (db.exists() and not os.access(db, os.W_OK)):
                    raise OSError(f"{db} is not writable")
                create_store(uri)
                # MLflow keeps the store of every URI it opened: a relative one, once opened in another folder in this
                # process, would be that folder's file
                mlflow.set_tracking_uri(f"sqlite:///{db.resolve()}")
            else:
                mlflow.set_tracking_uri(uri)
            exp = mlflow.set_experiment(experiment)
            if "mlflow.experimentKind" not in exp.tags:  # MLflow's UI opens it on its training runs, not GenAI traces
                mlflow.MlflowClient().set_experiment_tag(exp.experiment_id, "mlflow.experimentKind", "custom_model_development")
            if uri.startswith("sqlite:///"):
                artifacts_beside(Path(uri[len("sqlite:///"):]), exp.experiment_id)
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


def git_tags() -> dict:
    """mlflow.source.git.commit (what MLflow's UI shows as the run's source version) and git_dirty ("true" when tracked
    files differ from it) of this checkout; none outside a git checkout (an installed copy)."""
    import subprocess

    git = ["git", "-C", str(Path(CONF_DIR).parent)]
    try:
        commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True,
                               check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return {}
    return {"mlflow.source.git.commit": commit, "git_dirty": str(bool(dirty)).lower()}


def group_run(experiment: str) -> str | None:
    """The id of the parent run of a group of jobs in `experiment`, made on first use: of $MLFLOW_RUN_GROUP (a name any
    set of commands shares: `make demo`'s) or of the running Hydra sweep (its folder); None outside a group."""
    import mlflow
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    group = os.environ.get("MLFLOW_RUN_GROUP")
    if not group and HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        group = f"sweep {HydraConfig.get().sweep.dir}"
    if not group:
        return None
    client = mlflow.MlflowClient()
    exp = client.get_experiment_by_name(experiment).experiment_id
    with store_lock(tracking_uri()):  # parallel jobs of one sweep make one parent
        found = client.search_runs([exp], filter_string=f"tags.run_group = '{group}'", max_results=1)
        if found:
            return found[0].info.run_id
        parent = client.create_run(exp, run_name=group, tags={"run_group": group, **git_tags()})
        client.set_terminated(parent.info.run_id, "FINISHED")  # a folder of runs, not a job that could fail
        return parent.info.run_id


def log_model_files() -> None:
    """Log the active run's param sha256.<file> for each model file read so far (MODEL_FILES) not yet logged."""
    import mlflow

    logged = mlflow.get_run(mlflow.active_run().info.run_id).data.params
    new = {f"sha256.{k}": v for k, v in MODEL_FILES.items() if f"sha256.{k}" not in logged}
    if new:
        mlflow.log_params(new)


@contextlib.contextmanager
def mlflow_run(experiment: str, cfg: DictConfig, run_name: str | None = None, **params):
    """An MLflow run in `experiment`, nested in the active run if any (else in its group_run), tagged with the git commit
    and the command's overrides, with logged_params(cfg), `params` and the sha256 of every model file the process read
    (before the run or during it); on exception it ends FAILED with the error as a tag, or KILLED when the job was
    stopped (Stopped, Ctrl-C)."""
    import mlflow

    open_experiment(experiment)
    nested = mlflow.active_run() is not None
    from hydra.core.hydra_config import HydraConfig

    told = command_overrides() if HydraConfig.initialized() and is_job_config(cfg) else []
    tags = {**git_tags(), **({"overrides": " ".join(told)} if told else {})}
    run = mlflow.start_run(run_name=run_name, nested=nested, parent_run_id=None if nested else group_run(experiment),
                           tags=tags)
    try:
        flat = {**logged_params(cfg), **{k: str(v) for k, v in params.items()}}
        items = list(flat.items())
        for i in range(0, len(items), 100):
            mlflow.log_params(dict(items[i : i + 100]))
        log_model_files()
        mlflow.log_text(OmegaConf.to_yaml(cfg, resolve=True), "config.yaml")
        yield run
        log_model_files()
    except BaseException as e:
        mlflow.set_tag("error", f"{type(e).__name__}: {e}"[:5000])
        mlflow.end_run("KILLED" if isinstance(e, (Stopped, KeyboardInterrupt)) or stop_signal() is not None else "FAILED")
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


def _alive(pid: int) -> bool:
    """Whether process `pid` exists."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        return True
    return True


def _fsync(path: Path) -> None:
    """Flush a file's or a folder's entries to the disk (a rename is durable only once its folder is)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def _locked(folder: Path):
    """An exclusive lock on `folder` itself (flock on its descriptor): one commit or recovery at a time."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _roll_forward(folder: Path, pending: Path) -> None:
    """Move every file of a committed set `pending` over its namesake in `folder`, then remove `pending`."""
    for f in sorted(pending.iterdir()):
        os.replace(f, folder / f.name)
    pending.rmdir()
    _fsync(folder)


def recover(folder: Path) -> None:
    """Finish what a job stopped mid-commit left in `folder` (a committed set is moved in whole) and remove the staging
    folders of jobs that no longer run; a folder this process cannot write is left as it is."""
    folder = Path(folder)
    try:
        leftovers = [p for p in folder.iterdir() if p.name.startswith((".commit-", ".staging-"))]
    except OSError:  # no folder, or not readable: nothing of ours to finish
        return
    if not leftovers:
        return
    try:
        with _locked(folder):  # a running commit holds it: its set is then moved by itself
            for p in folder.glob(".commit-*"):
                _roll_forward(folder, p)
            for p in folder.glob(".staging-*"):
                pid = p.name.rpartition("-")[2]
                if pid.isdigit() and not _alive(int(pid)):
                    shutil.rmtree(p, ignore_errors=True)
    except OSError:
        return


@contextlib.contextmanager
def staged(folder: Path):
    """Yield a private staging folder inside `folder`; only when the block succeeds do the files written there replace
    their namesakes in `folder`, as one set: a job that fails or is stopped at any moment leaves the old set or the new,
    never a mix, and every other file in `folder` is kept.

    The commit is one rename (the staging folder to `.commit-<pid>`), then each file's rename, under a lock on `folder`
    and with stop signals held back (uninterrupted); a process killed outright in between leaves the committed set,
    which `recover` (called here and by the loaders) moves in whole."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    recover(folder)
    stage = folder / f".staging-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir()
    try:
        yield stage
        for f in stage.iterdir():
            _fsync(f)
        with uninterrupted(), _locked(folder):
            pending = folder / f".commit-{os.getpid()}"
            os.rename(stage, pending)  # the commit: from here on the new set is the folder's
            _fsync(folder)
            _roll_forward(folder, pending)
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
