"""What the error tests (tests/test_errors_*.py) share: running the venv's console scripts and Python snippets, and
reading their error lines."""
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

BIN = Path(sys.executable).parent  # the venv's console scripts
REPO = Path(__file__).resolve().parents[1]


def job(args, cwd, env=None, **kwargs):
    """Run a console script of the venv in `cwd` (its MLflow store in `env`); returns the CompletedProcess."""
    return subprocess.run([str(BIN / args[0]), *args[1:]], cwd=cwd, env={**os.environ, **(env or {})}, capture_output=True,
                          text=True, **kwargs)


def error_lines(stderr: str) -> list[str]:
    """stderr without the log records of MLflow and Hydra (lines that start with their time stamps)."""
    return [s for s in stderr.splitlines() if s.strip() and not re.match(r"^(\d{4}/\d\d/\d\d |\[\d{4}-)", s)]


def python(code: str, *args, **env):
    """A Python process running `code` (with argv `args`) in the repository, with `env` added to the environment."""
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code), *map(str, args)], cwd=REPO,
                            env={**os.environ, **env}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
