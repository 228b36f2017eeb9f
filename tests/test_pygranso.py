"""zstep=pygranso, the paper's Z-update by PyGranso: same local solution as our SQP Z-step on a small instance, its
termination reason in the step info and the per-step log, and one clear error when the `pygranso` extra is missing."""
import sys

import numpy as np
import pytest

from conftest import compose_cfg
from core.jobs import SIGNALS, UserError
from data.world import backfill
from planner import admm, cli, closed_loop, daqp_qp, mpc
from planner import zstep as zsteps
from planner.pygranso_zstep import import_pygranso, linear_term
from planner.setup import build, make, planner_config, setup

SMALL = ["paper.T_p=2"]  # a small instance: two steps


@pytest.fixture(scope="module")
def small():
    """T_p = 2 on two_lane, the ego nudged towards the platoon: analytic gradients' settings, observation, scenario."""
    scenario, _, s = make("two_lane", ["gradients=analytic", *SMALL])
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15
    return s, mpc.Observation(z[0].copy(), np.zeros(2), backfill(z, 8, 0.2)), scenario


def zstep(*overrides):
    """The Z-step class with its settings (a partial) as conf/zstep/ builds it, with overrides."""
    return build(planner_config("two_lane", [*SMALL, *overrides]).zstep)


def z_problem(s, obs, source, z_step):
    """A Z-update after three ADMM sweeps with Z-step z_step (a partial): the Problem, its Solvers and (Z_k, mu, c_Z)."""
    prob, solvers, st = mpc.build(s, obs, source, None, z_step)
    st, _ = admm.admm_solve(prob, solvers, st, 3, 1e-12, 1e-12)
    dyn = tuple(np.ascontiguousarray(M) for M in prob.dyn)
    box = lambda b, update: admm.box_update(daqp_qp.handle(len(b.lo)), True, b, update)[0]
    Delta = box(solvers.delta_qp, admm.delta_update(dyn, solvers.delta_qp, prob.rho, st.Delta, st.alpha, st.Z, st.mu))
    alpha = box(solvers.alpha_qp, admm.alpha_update(dyn, solvers.alpha_qp, prob.rho, Delta, st.alpha, st.Z, st.mu))
    return prob, solvers, (st.Z, st.mu, admm.z_residual(dyn, Delta, alpha, st.Z))


@pytest.mark.parametrize("gradients,predictor", [("analytic", "auto"), ("teacher", "analytic")])
def test_both_zsteps_reach_the_same_local_solution(small, gradients, predictor):
    pytest.importorskip("pygranso")
    s, obs, _ = small
    source = make("two_lane", [f"gradients={gradients}", *([f"predictor={predictor}"] if predictor != "auto" else [])])[1]
    prob, solvers, (Z, mu, c_Z) = z_problem(s, obs, source, zstep())
    safety = solvers.zstep.safety
    sqp = zstep("zstep=sqp", "zstep.settings.max_iters=100", "zstep.settings.tol=1e-9")(prob, safety)
    pg = zstep("zstep=pygranso", "zstep.settings.maxit=100", "zstep.settings.opt_tol=1e-7")(prob, safety)
    Z_sqp = zsteps.z_update(sqp.kernel(), True, safety.linearize(Z)[2], Z, mu, c_Z, 0.0, True, SIGNALS)[0]
    Z_pg, _, info = pg(Z, mu, c_Z)
    lin_q = linear_term(prob.Phi_3, prob.dyn.C, s.admm.rho, mu, c_Z)
    f = lambda x: 0.5 * x @ (sqp.data.H @ x) + lin_q @ x
    b = safety(Z_pg)
    assert b.min() > -1e-6 and np.sum(np.abs(b) < 1e-4) >= 1  # feasible, a safety constraint active: not a trivial QP
    assert f(Z_pg) < f(Z) - 1e-2  # both moved well away from the start
    assert abs(f(Z_pg) - f(Z_sqp)) <= 1e-6 * abs(f(Z_sqp)) and np.abs(Z_pg - Z_sqp).max() < 1e-4
    assert info.termination in (0, 6) and not info.infeasible


def test_termination_reason_in_step_info_and_per_step_log(small):
    pytest.importorskip("pygranso")
    _, obs, scenario = small
    cfg = planner_config("two_lane", ["gradients=analytic", "zstep=pygranso", "zstep.settings.maxit=3",
                                      "mpc.admm.max_iters=2", *SMALL])
    (_, source, s), admm_step = setup(cfg), build(cfg.solver.step)
    _, solvers, (Z, mu, c_Z) = z_problem(s, obs, source, admm_step.keywords["zstep"])
    _, _, info = solvers.zstep(Z, mu, c_Z, None)
    assert info.termination == 4 and info.termination_reason == "pygranso 4: max iterations (maxit)"
    step = lambda o, warm: admm_step(s, o, source, warm)
    ep = closed_loop.drive(scenario.make_world(0), step, source, scenario.x_ref, scenario.target_lane, T_obs=8, max_steps=1,
                           others="reactive", n_slots=4)
    assert ep.rows[0]["zstep_stop"].startswith("pygranso ") and not ep.rows[0]["fallback"]


def test_missing_pygranso_is_one_clear_error(small, monkeypatch, tmp_path, capsys):
    for name in [m for m in sys.modules if m == "pygranso" or m.startswith("pygranso.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "pygranso", None)  # what an environment without the extra looks like to import
    with pytest.raises(UserError, match=r"pip install -e '\.\[pygranso\]'"):
        import_pygranso()
    cfg = compose_cfg("planner", ["scenario=two_lane", "zstep=pygranso", "gradients=cv", "max_steps=1", "plots=false",
                                  f"out_dir={tmp_path}"])
    with pytest.raises(SystemExit):
        cli.run(cfg)
    err = capsys.readouterr().err.strip().splitlines()  # after MLflow's own lines if the job created the store
    assert err[-1] == "error: zstep=pygranso needs PyGranso, which is not installed; run pip install -e '.[pygranso]'"
    assert not any("Traceback" in line for line in err)
