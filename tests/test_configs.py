"""Every default has one home: a key a config sets for one of our `_target_`s must not have another default in code.

Checked: every top-level config as composed by default, and every group option that does not extend a sibling. An
option that extends one (three_lane extends two_lane, large extends small, long extends default) exists to differ
from it, so there only the names of its keys are checked (a typo fails everywhere). Empty defaults (None, {}, []) mean "nothing"
rather than a second value and pass.
"""
import dataclasses
import inspect
from pathlib import Path

import pytest
from hydra.utils import get_object
from omegaconf import DictConfig, ListConfig, OmegaConf

from conftest import compose_cfg
from core.jobs import CONF_DIR

PACKAGES = ("core", "data", "distill", "surrogate", "planner", "bench")  # third-party targets keep their own defaults
HOSTS = {"dataset": "make_dataset", "scenario": "make_dataset", "model": "distill", "trainer": "distill", "paper": "surrogate",
         "gradients": "planner", "predictor": "planner", "zstep": "planner", "solver": "planner", "method": "planner",
         "results_preset": "results"}
CONFIGS = ["make_dataset", "distill", "surrogate", "planner", "compare", "bench", "evaluate_interaction", "results"]


def extends_sibling(group, option):
    """Whether conf/<group>/<option>.yaml builds on another option of its group (a plain name in its defaults list)."""
    doc = OmegaConf.load(Path(CONF_DIR) / group / f"{option}.yaml")
    return any(isinstance(d, str) and d != "_self_" for d in doc.get("defaults", []))


def cases():
    """(config, overrides, values checked): every top-level config as it is, then every option of every group."""
    out = [pytest.param(c, [], True, id=c) for c in CONFIGS]
    for group, host in HOSTS.items():
        for option in sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml")):
            out.append(pytest.param(host, [f"{group}={option}"], not extends_sibling(group, option), id=f"{host}-{group}={option}"))
    return out


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


def plain(value):
    """Tuples as lists, recursively, so a YAML list compares equal to a tuple default."""
    if isinstance(value, (tuple, list)):
        return [plain(v) for v in value]
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    return value


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


def drift(cfg, packages=PACKAGES, values=True):
    """Problems of cfg's targets in `packages`: unknown keys and (if values) keys whose code default differs from the YAML."""
    problems, checked = [], 0
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
                continue
            if not values or key not in defaults or OmegaConf.is_interpolation(node, key) or OmegaConf.is_missing(node, key):
                continue
            if defaults[key] is None or (isinstance(defaults[key], (dict, list, tuple)) and not defaults[key]):
                continue
            value = node[key]
            if isinstance(value, DictConfig) and "_target_" in value:
                continue  # built by its own target, checked on its own
            value = OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value
            if plain(value) != plain(defaults[key]):
                problems.append(f"{path}.{key}: YAML {value!r} but {name} defaults to {defaults[key]!r}")
    return problems, checked


@pytest.mark.parametrize("config,overrides,values", cases())
def test_yaml_values_and_code_defaults_agree(config, overrides, values):
    problems, _ = drift(compose_cfg(config, overrides), values=values)
    assert not problems, "\n".join(problems)


def test_every_top_level_config_is_covered():
    assert sorted(p.stem for p in Path(CONF_DIR).glob("*.yaml")) == sorted(CONFIGS)
    groups = sorted(p.name for p in Path(CONF_DIR).iterdir() if p.is_dir() and p.name != "hydra")  # hydra/: Hydra's own (help)
    assert groups == sorted(HOSTS)


def test_the_check_sees_targets_and_catches_drift():
    _, checked = drift(compose_cfg("surrogate"))
    assert checked >= 4  # predictor, states, network, module
    cfg = OmegaConf.create({"a": [{"_target_": "test_configs.tunable", "gain": 2.0, "offset": 1.0, "other": "${a}",
                                   "ranges": {"x": [0, 1]}}]})
    problems, checked = drift(cfg, packages=("test_configs",))
    assert checked == 1 and problems == ["a[0].gain: YAML 2.0 but test_configs.tunable defaults to 1.0"]
    cfg.a[0].typo = 1
    assert "a[0].typo: test_configs.tunable takes no such parameter" in drift(cfg, packages=("test_configs",))[0]


def tunable(gain=1.0, offset=1.0, other=None, ranges=None):
    """A target with defaults, for the self-test above."""
    return gain, offset, other


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
