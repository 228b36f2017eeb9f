"""The multi-step data and losses: recorded futures per window, the teacher's masked rollout term, branch groups and
their contrast term against a direct computation, the teacher's rollouts on them and the student's terms fitting them."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import compose_cfg
from core.jobs import UserError
from core.rollout import rollout
from data import dataset
from distill.datamodule import futures, groups, teacher_rollouts
from distill.metrics import rollout_cases
from distill.models import TorchPredictor
from distill.tasks import StudentTask, TeacherTask, group_rollout, hardest_braking

NET = {"_target_": "distill.teacher.SocialTeacher", "hidden": 8, "pool": 8, "decoder": [16], "pos_scale": 10.0,
       "vel_scale": 0.5, "acc_scale": 0.05}
NO_BRAKE = {"brake_weight": 0.0, "brake_scale": 1.0, "dt": 0.2}  # the hardest-braking term off


def test_futures_follow_each_run_and_agree_with_the_rollout_cases(tiny_dataset):
    a = dataset.load(tiny_dataset, "val")
    X, ego, others, mask = futures(a, 8)
    assert mask[:, 0].all()  # every window has its own next step
    np.testing.assert_array_equal(others[:, 0], a["Y"][:, 1:])
    full = mask.all(axis=1)
    hist, ego_c, others_c, _ = rollout_cases(a, 8)  # chains of complete runs, computed independently
    assert full.sum() == len(hist) > 0
    np.testing.assert_allclose(ego[full], ego_c)
    np.testing.assert_allclose(others[full], others_c)
    assert (a["branch"][full] > 0).any()  # counterfactual branches are runs of their own
    cut = ~mask[:, -1]
    k = mask[cut].sum(axis=1)  # first missing step: the ego goes on at its last displacement
    rows = np.flatnonzero(cut)
    prev = ego[rows, k - 1]
    prev2 = np.where((k > 1)[:, None], ego[rows, np.maximum(k - 2, 0)], X[rows, -1, 0])
    np.testing.assert_allclose(ego[rows, k], 2 * prev - prev2, atol=1e-5)


def batch(tiny_dataset, n=16):
    a = dataset.load(tiny_dataset, "val")
    return [torch.tensor(t[:n], dtype=torch.float32 if t.dtype != bool else torch.bool) for t in futures(a, 8)]


def test_rollout_term_sees_only_the_steps_the_run_reached(tiny_dataset):
    torch.manual_seed(0)
    task = TeacherTask(NET, 1e-3, 0.0, scale_m=0.01, rollout_weight=10.0, rollout_scale_m=1.0, contrast_weight=0.0, **NO_BRAKE)
    task.log = lambda *args, **kwargs: None
    X, ego, others, mask = batch(tiny_dataset)
    mask[:, 5:] = False
    base = task._step((X, ego, others, mask), "val").item()
    junk = others.clone()
    junk[:, 5:] += 100.0
    assert task._step((X, ego, junk, mask), "val").item() == pytest.approx(base)
    junk[:, 3] += 0.5  # 0.5 m more error at a reached step: counted (its size depends on the untrained net's errors)
    assert task._step((X, ego, junk, mask), "val").item() > base + 0.01


def test_hardest_braking_is_each_car_s_largest_deceleration_over_the_steps_reached():
    dt, H = 0.2, 6
    X = torch.zeros(1, 8, 3, 2)
    X[0, :, 1:, 0] = torch.arange(8.0)[:, None] * 5.0 * dt  # two cars at 5 m/s
    v = torch.full((H, 2), 5.0)
    v[2:, 0] -= 3.0 * dt  # car 1 brakes at 3 m/s^2 for one step
    v[4:, 1] -= 6.0 * dt  # car 2 at 6 m/s^2, but the run ends before that step
    others = torch.zeros(1, H, 2, 2)
    others[0, :, :, 0] = X[0, -1, 1:, 0] + torch.cumsum(v * dt, 0)
    mask = torch.tensor([[True] * 4 + [False] * 2])
    assert hardest_braking(X, others, mask, dt)[0].tolist() == pytest.approx([3.0, 0.0])
    assert hardest_braking(X, others, torch.ones(1, H, dtype=torch.bool), dt)[0].tolist() == pytest.approx([3.0, 6.0])


def test_the_braking_term_adds_the_huber_error_of_the_predicted_hardest_braking(tiny_dataset):
    torch.manual_seed(0)
    args = dict(scale_m=0.01, rollout_weight=10.0, rollout_scale_m=1.0, contrast_weight=0.0)
    plain, braking = TeacherTask(NET, 1e-3, 0.0, **args, **NO_BRAKE), TeacherTask(NET, 1e-3, 0.0, **{**args, **NO_BRAKE, "brake_weight": 2.0})
    braking.net.load_state_dict(plain.net.state_dict())
    for task in (plain, braking):
        task.log = lambda *a, **k: None
    X, ego, others, mask = batch(tiny_dataset)
    pred = rollout(plain.net, X, ego)[:, :, 1:]
    want = torch.nn.functional.huber_loss(*(hardest_braking(X, f, mask, 0.2) for f in (pred, others)))
    step = lambda task: task._step((X, ego, others, mask), "val").item()
    assert step(braking) - step(plain) == pytest.approx(2.0 * want.item(), rel=1e-4)


def test_without_the_rollout_term_the_loss_is_the_one_step_huber(tiny_dataset):
    torch.manual_seed(0)
    task = TeacherTask(NET, 1e-3, 0.0, scale_m=0.01, rollout_weight=0.0, rollout_scale_m=1.0, contrast_weight=0.0, **NO_BRAKE)
    task.log = lambda *args, **kwargs: None
    X, ego, others, mask = batch(tiny_dataset)
    err = (task.net(X) - torch.cat([ego[:, :1], others[:, 0]], 1))[:, 1:] / 0.01
    want = torch.nn.functional.huber_loss(err, torch.zeros_like(err))
    assert task._step((X, ego, others, mask), "val").item() == pytest.approx(want.item(), rel=1e-5)


def test_branch_groups_share_their_past_and_differ_in_the_ego_future(tiny_dataset):
    a = dataset.factual(dataset.load(tiny_dataset, "train"))  # what the mean models train on: no flipped branches
    g = groups(a)
    assert g.shape[0] > 0 and g.shape[1] == 5  # the episode's own window and its push-on, back-off, speed and quick-lean egos
    for row in g:
        m = row[row >= 0]
        assert a["branch"][m[0]] == 0 and (a["branch"][m[1:]] > 0).all()
        assert len(set(a["episode"][m])) == 1 and len(set(a["step"][m])) == 1
        assert all(np.array_equal(a["X"][i], a["X"][m[0]]) for i in m)
    _, ego, _, _ = futures(a, 8)
    assert np.abs(ego[g[:, 1]] - ego[g[:, 2]]).max() > 0.1  # different egos from one past


def test_contrast_term_scores_the_predicted_difference_between_branches(tiny_dataset):
    torch.manual_seed(0)
    task = TeacherTask(NET, 1e-3, 0.0, scale_m=0.01, rollout_weight=0.0, rollout_scale_m=0.5, contrast_weight=1.0, **NO_BRAKE)
    a = dataset.factual(dataset.load(tiny_dataset, "train"))  # the mean models' data
    g = groups(a)[:6]
    X, ego, others, mask = (torch.from_numpy(np.asarray(t[np.maximum(g, 0)], dtype=np.float32 if t.dtype != bool else bool))
                            for t in futures(a, 8))
    member = torch.from_numpy(g >= 0)
    got = task.contrast(X, ego, others, mask, member).item()
    shifted = task.contrast(X, ego, others + torch.randn(6, 1, 8, 1, 2), mask, member).item()
    assert shifted == pytest.approx(got, rel=1e-4)  # a shift common to a group's futures is no response to the ego
    with torch.no_grad():  # direct: per group, step and car, both deviations from the mean of the valid members
        from core.rollout import rollout
        total, count = 0.0, 0
        for k in range(6):
            pred = rollout(task.net, X[k], ego[k])[:, :, 1:].numpy()
            for t in range(8):
                ok = (member[k] & mask[k, :, t]).numpy()
                p, o = pred[ok, t], others[k, ok, t].numpy()
                total += (((p - p.mean(0)) - (o - o.mean(0))) ** 2).sum() / 0.5**2
                count += ok.sum() * p.shape[1] * 2
    assert got == pytest.approx(total / count, rel=1e-4) and got > 0


def test_teacher_rollouts_label_each_branch_member_with_the_teachers_own_rollout(tiny_dataset):
    a = dataset.factual(dataset.load(tiny_dataset, "train"))  # the mean models' data
    teacher = TorchPredictor("teacher", instantiate(NET).eval())
    X, ego, target, member = teacher_rollouts(teacher, a, 8, tiny_dataset)
    g = groups(a)
    assert X.shape[:2] == member.shape == g.shape and target.shape == (*g.shape, 8, 4, 2)
    np.testing.assert_array_equal(member, g >= 0)
    _, ego_all, _, _ = futures(a, 8)
    for k in (0, len(g) - 1):  # one member at a time, straight from the teacher's phi
        for s in np.flatnonzero(g[k] >= 0):
            window, want = a["X"][g[k, s]].astype(float), []
            for t in range(8):
                nxt = teacher.phi(window[None])[0]
                nxt[0] = ego_all[g[k, s], t]
                want.append(nxt[1:])
                window = np.concatenate([window[1:], nxt[None]])
            np.testing.assert_allclose(target[k, s], np.stack(want), atol=1e-4)
    with pytest.raises(UserError, match="rollout_groups > 0 but the training split has no counterfactual branches"):
        teacher_rollouts(teacher, {k: v[a["branch"] == 0] for k, v in a.items()}, 8, tiny_dataset)


def test_student_branch_terms_fit_the_teachers_rollouts_and_their_response(tiny_dataset):
    torch.manual_seed(0)
    net = compose_cfg("distill", ["model=student"]).model.net
    task = StudentTask(OmegaConf.to_container(net), 1e-3, 0.0, scale_m=0.01, jac_weight=1.0, ego_jac_weight=1.0,
                       spectral_weight=0.0, cert_weight=0.0, rollout_weight=2.0, contrast_weight=3.0, rollout_scale_m=0.5)
    task.log = lambda *args, **kwargs: None
    a = dataset.factual(dataset.load(tiny_dataset, "train"))  # the mean models' data
    X, ego, _, member = (torch.from_numpy(t) for t in teacher_rollouts(TorchPredictor("teacher", instantiate(NET).eval()),
                                                                       a, 8, tiny_dataset))
    X, ego, member = X[:5], ego[:5], member[:5]
    with torch.no_grad():
        own = group_rollout(task.net, X, ego)
    windows = [torch.randn(4, 8, 5, 2), torch.randn(4, 5, 2), torch.randn(4, 2, 5, 2), torch.randn(4, 2, 80)]
    base = task._step(windows, "val").item()
    step = lambda target: task._step({"windows": windows, "groups": (X, ego, target, member)}, "val").item()  # noqa: E731
    assert step(own) == pytest.approx(base, rel=1e-5)  # its own rollouts: no rollout error, no contrast
    shift = torch.zeros_like(own)
    shift[..., 0] = 0.25  # 0.25 m on every x, common to each group: 0.25 m error (half a unit, squared 1/8 per coordinate)
    assert step(own + shift) == pytest.approx(base + 2.0 * 0.125, rel=1e-4)
    pushed = own.clone()
    pushed[:, 1] += 0.5  # member 1 of every group moved 0.5 m: a response to its ego
    S = member.sum(1).float()
    contrast = sum(((1 - 1 / S[k]) ** 2 + (S[k] - 1) / S[k] ** 2) * 8 * 4 * 2 for k in range(5)) / (member.sum() * 8 * 8)
    rollout_err = 5 * 8 * 4 * 2 / (member.sum() * 8 * 8)
    assert step(pushed) == pytest.approx(base + 2.0 * rollout_err.item() + 3.0 * contrast.item(), rel=1e-4)


def test_hard_braking_windows_are_found_from_the_recorded_future_and_drawn_more_often(tiny_dataset):
    from distill.datamodule import SequenceData, braking

    dt, k = 0.2, np.arange(-7, 1)
    X = np.zeros((2, 8, 3, 2))
    X[:, :, 1, 0], X[:, :, 2, 0] = 5.0 * k * dt, 20.0 + 5.0 * k * dt  # two cars at 5 m/s
    t = np.arange(1, 4) * dt
    others = np.stack([5.0 * t - 0.5 * 6.0 * t**2, 20.0 + 5.0 * t], -1)[..., None] * [1.0, 0.0]  # car 1 brakes at 6 m/s^2
    others = np.stack([others, others]).astype(float)
    mask = np.array([[True, True, True], [False, False, False]])  # the second window's future was never recorded
    ego = np.zeros((2, 3, 2))
    np.testing.assert_allclose(braking(X, ego, others * mask[:, :, None, None], mask, dt), [6.0, 0.0], atol=1e-9)
    data = SequenceData(tiny_dataset, 16, 8, 0, 3.0, 10.0, 1.0, 1.0)
    data.setup()
    X, ego, others, mask = (a.numpy() for a in data.splits["train"].tensors)
    hard = braking(X, ego, others, mask, dataset.read_meta(tiny_dataset)["dt"]) > 3.0
    assert 0 < hard.sum() < len(hard)
    weights = data.sampler().weights.numpy()
    np.testing.assert_array_equal(weights, np.where(hard, 10.0, 1.0))
    assert SequenceData(tiny_dataset, 16, 8, 0, 3.0, 1.0, 1.0, 1.0).sampler() is None  # uniform: shuffled as before


def test_windows_whose_recorded_future_spans_the_horizon_are_drawn_more_often(tiny_dataset):
    from distill.datamodule import SequenceData

    arrays = dataset.factual(dataset.load(tiny_dataset, "train"))  # the mean models' data
    whole = futures(arrays, 8)[3].all(axis=1)  # the run goes on 8 steps with the same cars in its slots
    assert 0 < whole.sum() < len(whole)
    data = SequenceData(tiny_dataset, 16, 8, 0, 3.0, 1.0, 4.0, 1.0)
    data.setup()
    np.testing.assert_array_equal(data.sampler().weights.numpy(), np.where(whole, 4.0, 1.0))
