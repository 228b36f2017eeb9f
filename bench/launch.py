"""The console scripts' entry points (pyproject.toml's [project.scripts]): a stop signal is one line and exit 128 + the
signal from the command's first instruction on, while its modules import and, after its job, while the interpreter
exits (loky's and llvmlite's clean-ups), where Python's own Ctrl-C would print a traceback or end the process by the
signal. Inside the job core.jobs.guarded takes the signals over and ends its MLflow run KILLED."""
import atexit
import os
import signal
import sys
import threading
from functools import partial
from importlib import import_module

_SAID = []  # the job ended on a stop signal and said so: a further one only ends the process


def _exit(signum, frame):
    """End the process now with 128 + signum: nothing of a job is open outside guarded, so no clean-up is due."""
    if not _SAID:
        os.write(2, f"error: stopped by {signal.Signals(signum).name}\n".encode())
    os._exit(128 + signum)


def run(module: str):
    """Stop signals handled by _exit, then `module`'s main() (a console script's whole work), then the interpreter's
    exit by hand: its threads' shut-down, its atexit functions and the end of the process, never the teardown after them, where Python hands
    Ctrl-C back to the system (death by the signal) and finalizers print tracebacks."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _exit)
    try:
        import_module(module).main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else int(e.code is not None)
        if e.code is not None and not isinstance(e.code, int):
            print(e.code, file=sys.stderr)
        if code in (128 + signal.SIGINT, 128 + signal.SIGTERM):
            _SAID.append(code)
    threading._shutdown()  # as the interpreter's exit does first: loky's executors shut down, so no worker is waited on
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


make_dataset = partial(run, "data.cli")
distill = partial(run, "distill.cli")
surrogate = partial(run, "surrogate.cli")
planner = partial(run, "planner.cli")
compare = partial(run, "planner.compare")
evaluate_interaction = partial(run, "bench.interaction")
results = partial(run, "bench.results")
ceiling = partial(run, "bench.ceiling")
cross_world = partial(run, "bench.cross_world")
safety = partial(run, "bench.safety")
