"""What every job shares: one-line user errors, stop signals, atomic writes, and MLflow runs that log their whole config."""
import contextlib
import errno
import fcntl
import os
import shutil
import signal
import sys
import tempfile
import threading
from functools import partial
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
        if not group.startswith("hydra/") and chosen is not None:
            lines.append(f"{group}: {' | '.join(options(group))}  (now {chosen})")
    return "\n".join(lines) or "none: every setting is a key below"


OmegaConf.register_new_resolver("job_groups", job_groups, replace=True)  # used by conf/hydra/help/job.yaml


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
RETRY_S = 0.005  # s: how soon a signal held back inside a compiled call is tried again
_DEFERRED = []  # non-empty inside uninterrupted(): a stop signal is recorded there and raised at its end


def _in_numba_callback(frame) -> bool:
    """Whether `frame` runs inside numba's unpickler, which compiled code calls back into Python (to build an exception
    or a constant): an exception raised there is lost by the compiled caller (SystemError "returned a result with an
    exception set") or crashes it (a segmentation fault in planner.jit_admm's one-call solve)."""
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


def guarded(fn):
    """Run a job body; a UserError or a full disk becomes one 'error: ...' line on stderr and exit status 2 (a UserError's
    empty Hydra folder removed), SIGTERM and SIGINT one line and exit 128 + the signal number.

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
            for s, handler in previous.items():
                signal.signal(s, handler)
            if main:
                _STOPPED.clear()  # what stopped this job stops nothing after it (the next job, a test)

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
