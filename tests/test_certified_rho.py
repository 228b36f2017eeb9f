"""mpc.admm.rho=certified: the planner takes Theorem 1's bound for its scenario from models/certificate.json, and says in
one line when the certificate is missing or has no bound for the scenario; a bad rho names the key."""
import json

import pytest

from core import validate
from core.jobs import UserError, sha256
from planner.setup import build, planner_config, settings


def mpc_settings(scenario, *overrides):
    """mpc.Settings of the planner config for `scenario` (no gradient source is built: no model needed)."""
    cfg = planner_config(scenario, overrides)
    validate.check(cfg, "planner")
    return settings(cfg, build(cfg.scenario))


def test_certified_rho_is_the_certificates_bound_for_the_scenario(tmp_path):
    (tmp_path / "student.ckpt").write_bytes(b"the weights it certifies")
    doc = {"scenarios": {"two_lane": {"rho_bound": 1.25e8}, "three_lane": {"rho_bound": 3.5e9}},
           "certifies": {"student.ckpt": sha256(tmp_path / "student.ckpt")}}
    (tmp_path / "certificate.json").write_text(json.dumps(doc))
    over = ("mpc.admm.rho=certified", f"models_dir={tmp_path}")
    assert mpc_settings("two_lane", *over).admm.rho == 1.25e8
    assert mpc_settings("three_lane", *over).admm.rho == 3.5e9
    assert mpc_settings("two_lane", f"models_dir={tmp_path}").admm.rho == 100.0  # the paper's, unless asked
    with pytest.raises(UserError, match="has no bound for scenario random .it certifies two_lane, three_lane"):
        mpc_settings("random", *over)


def test_missing_certificate_and_bad_rho_fail_in_one_line(tmp_path):
    with pytest.raises(UserError, match=r"^mpc.admm.rho=certified: no certificate at .*certificate.json; run `distill model="):
        mpc_settings("two_lane", "mpc.admm.rho=certified", f"models_dir={tmp_path}")
    (tmp_path / "certificate.json").write_text(json.dumps({"scenarios": {"two_lane": {"rho_bound": float("inf")}}}))
    with pytest.raises(UserError, match="certified rho for two_lane .* is inf"):
        mpc_settings("two_lane", "mpc.admm.rho=certified", f"models_dir={tmp_path}")
    with pytest.raises(UserError, match=r"^mpc.admm.rho=certify: must be a number > 0 or one of certified$"):
        mpc_settings("two_lane", "mpc.admm.rho=certify")
    with pytest.raises(UserError, match=r"^mpc.admm.rho=-1.0: must be"):
        mpc_settings("two_lane", "mpc.admm.rho=-1.0")
    with pytest.raises(UserError, match=r"^paper.cost.lambda_v=-1.0: must be"):  # the keys beside it still checked
        mpc_settings("two_lane", "paper.cost.lambda_v=-1.0")
