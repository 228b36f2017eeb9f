"""Every default has one home: a key a config sets for one of our `_target_`s must have no default in code.

Checked: every top-level config as composed by default, and every option of every group. A key the YAML sets whose
parameter also has a default in code (dataclass field, NamedTuple field or signature), equal or not, fails naming both
homes; so does a key the target does not take.
"""
import dataclasses
import functools
import importlib
import inspect
from pathlib import Path

import pytest
from hydra.utils import get_object
from omegaconf import DictConfig, ListConfig, OmegaConf

from conftest import compose_cfg
from core import validate
from core.jobs import CONF_DIR, options

PACKAGES = ("core", "data", "distill", "surrogate", "planner", "bench")  # third-party targets keep their own defaults
HOSTS = {"dataset": "make_dataset", "scenario": "make_dataset", "model": "distill", "trainer": "distill", "paper": "surrogate",
         "gradients": "planner", "predictor": "planner", "zstep": "planner", "solver": "planner", "method": "planner", "mpc": "planner",
         "results_preset": "results"}
CONFIGS = ["make_dataset", "distill", "surrogate", "planner", "compare", "bench", "evaluate_interaction", "results", "ceiling",
           "cross_world", "verdicts", "candidates", "safety"]
PENDING = {}  # second homes still in code, to remove there; may only shrink (test_pending_entries_are_still_second_homes)


def cases():
    """(config, overrides): every top-level config as it is, then every option of every group."""
    out = [pytest.param(c, (), id=c) for c in CONFIGS]
    for group, host in HOSTS.items():
        for option in options(group):
            out.append(pytest.param(host, (f"{group}={option}",), id=f"{host}-{group}={option}"))
    return out


@functools.cache
def composed(config, overrides: tuple):
    """compose_cfg, once per (config, overrides) in this session."""
    return compose_cfg(config, overrides)


def code_defaults(target):
    """{parameter: default} of a class or function: dataclass fields, NamedTuple _field_defaults or the signature."""
    if dataclasses.is_dataclass(target):
        return {f.name: f.default if f.default is not dataclasses.MISSING else f.default_factory()
                for f in dataclasses.fields(target)
                if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING}
    if isinstance(target, type) and issubclass(target, tuple) and hasattr(target, "_field_defaults"):
        return dict(target._field_defaults)
    params = inspect.signature(target).parameters.values()
    return {p.name: p.default for p in params if p.default is not inspect.Parameter.empty}


def parameters(target):
    """Names the target accepts, or None when it takes **kwargs."""
    params = inspect.signature(target).parameters.values()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return None
    return {p.name for p in params}


def targets(node, path=""):
    """(path, node) of every node with a `_target_` under `node`."""
    if isinstance(node, DictConfig):
        if "_target_" in node:
            yield path, node
        for key in node:
            if not OmegaConf.is_interpolation(node, key) and isinstance(node._get_node(key), (DictConfig, ListConfig)):
                yield from targets(node[key], f"{path}.{key}" if path else str(key))
    elif isinstance(node, ListConfig):
        for i in range(len(node)):
            if not OmegaConf.is_interpolation(node, i) and isinstance(node._get_node(i), (DictConfig, ListConfig)):
                yield from targets(node[i], f"{path}[{i}]")


def drift(cfg, where, packages=PACKAGES, pending=PENDING):
    """(problems, targets checked, (target, key) pairs let through by `pending`) of cfg's targets in `packages`, cfg composed
    as `where` says; problems: unknown keys and keys with a code default."""
    problems, checked, waived = [], 0, set()
    for path, node in targets(cfg):
        name = node._target_
        if name.split(".")[0] not in packages:
            continue
        target = get_object(name)
        defaults, accepted = code_defaults(target), parameters(target)
        checked += 1
        for key in node:
            if str(key).startswith("_"):
                continue
            if accepted is not None and key not in accepted:
                problems.append(f"{path}.{key}: {name} takes no such parameter")
            elif key in defaults and key in pending.get(name, ()):
                waived.add((name, key))
            elif key in defaults:
                problems.append(f"{path}.{key}: two homes, the YAML of `{where}` sets it and {name} defaults it to "
                                f"{defaults[key]!r}; remove the code default")
    return problems, checked, waived


@pytest.mark.parametrize("config,overrides", cases())
def test_no_key_a_config_sets_has_a_code_default(config, overrides):
    problems = drift(composed(config, overrides), " ".join([config, *overrides]))[0]
    assert not problems, "\n".join(problems)


def test_every_top_level_config_is_covered():
    assert sorted(p.stem for p in Path(CONF_DIR).glob("*.yaml")) == sorted(CONFIGS)
    groups = sorted(p.name for p in Path(CONF_DIR).iterdir() if p.is_dir() and p.name != "hydra")  # hydra/: Hydra's own (help)
    assert groups == sorted(HOSTS)


def test_pending_entries_are_still_second_homes():
    waived = set().union(*(drift(composed(*c.values), "")[2] for c in cases()))
    stale = [(name, key) for name, keys in PENDING.items() for key in keys if (name, key) not in waived]
    assert not stale, f"one home already, drop them from PENDING: {stale}"


def test_the_check_sees_targets_and_catches_every_second_home():
    checked = drift(composed("surrogate", ()), "surrogate")[1]
    assert checked >= 4  # predictor, states, network, module
    cfg = OmegaConf.create({"a": [{"_target_": "test_configs.tunable", "gain": 2.0, "offset": 1.0, "other": "${a}"}]})
    problems, checked, _ = drift(cfg, "x", packages=("test_configs",))
    assert checked == 1 and problems == [  # an equal value and an interpolation are second homes too; gain has one
        "a[0].offset: two homes, the YAML of `x` sets it and test_configs.tunable defaults it to 1.0; remove the code default",
        "a[0].other: two homes, the YAML of `x` sets it and test_configs.tunable defaults it to None; remove the code default"]
    _, _, waived = drift(cfg, "x", packages=("test_configs",), pending={"test_configs.tunable": ("offset", "other", "gain")})
    assert drift(cfg, "x", packages=("test_configs",), pending={"test_configs.tunable": ("offset", "other")})[0] == []
    assert waived == {("test_configs.tunable", "offset"), ("test_configs.tunable", "other")}  # gain: no second home to waive
    cfg.a[0].typo = 1
    assert "a[0].typo: test_configs.tunable takes no such parameter" in drift(cfg, "x", packages=("test_configs",))[0]


def tunable(gain, offset=1.0, other=None):
    """A target with defaults, for the self-test above."""
    return gain, offset, other


@pytest.mark.parametrize("config,overrides", [
    ("make_dataset", []), ("make_dataset", ["dataset=large", "scenario=two_lane"]), ("distill", []),
    ("distill", ["model=student", "trainer=long"]), ("distill", ["trainer=ddp"]), ("surrogate", []),
    ("planner", []), ("planner", ["scenario=random", "zstep=pygranso", "method=both", "episodes=4"]),
    *(("results", [f"results_preset={o}"]) for o in options("results_preset")), ("compare", []), ("bench", [])])
def test_shipped_configs_pass_their_schema(config, overrides):
    validate.check(compose_cfg(config, overrides), config)


@pytest.mark.parametrize("job,override,message", [
    ("results", "bootstrap.resamples=0", "error: bootstrap.resamples=0: must be an integer >= 1"),
    ("results", "results_preset.sources=[cv,cvv]", "error: results_preset.sources=['cv', 'cvv']: must be a list, each one of "
                                                   + ", ".join(options("gradients"))),
    ("results", "results_preset.training_seeds=[]", "error: results_preset.training_seeds=[]: must be a list of at least 1, "
                                                    "each an integer in [0, 4294967295]"),
    ("compare", "columns=[]", "error: columns=[]: must be a list of at least 1, each a non-empty string"),
    ("bench", "step_time.repeats=0", "error: step_time.repeats=0: must be an integer >= 1"),
    ("bench", "states.gradients=oracel", "error: states.gradients=oracel: must be one of " + ", ".join(options("gradients"))),
])
def test_results_compare_and_bench_check_their_config_first(job, override, message, tmp_path, capsys):
    run = importlib.import_module({"results": "bench.results", "compare": "planner.compare", "bench": "bench.step_time"}[job]).run
    paths = {"results": [f"out_dir={tmp_path}/out", f"work_dir={tmp_path}/work"], "compare": [f"out_dir={tmp_path}/out"],
             "bench": [f"states.path={tmp_path}/states.npz", f"models_dir={tmp_path}/models"]}[job]
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        run(compose_cfg(job, [*paths, override]))
    assert e.value.code == 2 and capsys.readouterr().err.strip().splitlines() == [message]
    assert list(tmp_path.iterdir()) == []


def test_trainer_presets_name_their_callbacks(tmp_path):
    from lightning.pytorch.callbacks import EarlyStopping, ModelCheckpoint

    from distill.train import make_trainer

    def callbacks(*overrides):
        cfg = compose_cfg("distill", [f"run_dir={tmp_path}", *overrides])
        return {type(c): c for c in make_trainer(cfg.trainer, logger=False).callbacks}

    assert callbacks()[EarlyStopping].patience == 12  # the teacher's: its whole run
    assert callbacks("model=student")[EarlyStopping].patience == 4
    long = callbacks("trainer=long")
    assert long[EarlyStopping].patience == 15 and long[ModelCheckpoint].dirpath == str(tmp_path / "checkpoints")
    assert EarlyStopping not in callbacks("trainer.callbacks.early_stopping=null")
