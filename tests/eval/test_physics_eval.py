"""Ground-truth physics errors against a stand-in model that moves exactly (or wrongly) by known rules
(read by ``physics_errors`` through ``Future``, a stand-in of ``extrapolate.Predictor``)."""

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from tracegs.eval.physics import physics_errors
from tracegs.extrapolate import ExtrapolationState
from tracegs.physics.free_body import FreeBody
from tracegs.physics.integrate import zero_params
from tracegs.physics.so3 import rodrigues


def _write_gt(root, w=2.0):
    gt = root / "gt"
    gt.mkdir(parents=True)
    rng = np.random.default_rng(0)
    body = rng.uniform(-0.2, 0.2, (200, 3)) + [0, 0, -0.5]
    blade = rng.uniform(-0.5, 0.5, (200, 3)) * [1, 1, 0.02] + [0, 0, 0.3]
    np.savez(gt / "points.npz", points=np.concatenate([body, blade]), part_ids=np.repeat([1, 2], 200))
    common = {"pivot": [0, 0, 0], "linear_velocity": [0, 0, 0], "linear_acceleration": [0, 0, 0]}
    parts = [
        {
            "name": "body",
            "id": 1,
            "type": "static",
            "axis": [0, 0, 1],
            "angular_velocity": 0.0,
            "angular_acceleration": 0.0,
            **common,
        },
        {
            "name": "blade",
            "id": 2,
            "type": "rotation",
            "axis": [0, 0, 1],
            "angular_velocity": w,
            "angular_acceleration": 0.0,
            **common,
        },
    ]
    (gt / "motion.json").write_text(json.dumps({"parts": parts}))
    return np.concatenate([body, blade]), np.repeat([1, 2], 200)


class StandIn:
    """Gaussians on the ground-truth points that rotate part 2 about z at ``w`` (plus an error offset)."""

    def __init__(self, points, ids, w, offset=0.0, w_learned=None, droop=0.0):
        self.x0 = torch.tensor(points, dtype=torch.float32)
        self.blade = torch.tensor(ids == 2)
        self.w, self.offset, self.droop = w, offset, droop
        self.w_learned = w if w_learned is None else w_learned

    def handover_time(self, t_max):
        return t_max - 0.05

    def gaussians_at(self, t, t_max):
        R = rodrigues(torch.tensor([0.0, 0.0, self.w * t]))
        x = torch.where(self.blade[:, None], self.x0 @ R.T, self.x0)
        if t > t_max:
            x = x + torch.tensor([self.offset, 0.0, 0.0])
        return {"means": x}

    dynamics = True

    def query_dynamics(self, means, t):
        p = zero_params(means)
        learned = self.w_learned * (1 - self.droop * t)  # the learned |w| falls off over time
        w = torch.where(self.blade[:, None], torch.tensor([0.0, 0.0, learned]), torch.zeros(3))
        return p._replace(angular_velocity=w)


class Future:
    """The trained run that ``physics_errors`` measures (``extrapolate.Predictor``'s interface): the
    stand-in's own rules."""

    def __init__(self, model: StandIn, state: ExtrapolationState, free_bodies: bool = False):
        self.model, self.state = model, state
        self.settings = SimpleNamespace(free_bodies=free_bodies)

    @property
    def t_max(self) -> float:
        return self.state.t_max

    def handover_time(self) -> float:
        return self.model.handover_time(self.state.t_max)

    def gaussians_at(self, t: float) -> dict:
        return self.model.gaussians_at(t, self.state.t_max)


def test_exact_motion_has_zero_error(tmp_path):
    points, ids = _write_gt(tmp_path)
    out = physics_errors(
        Future(StandIn(points, ids, 2.0), ExtrapolationState(t_max=0.75)), tmp_path, [0.8, 1.0]
    )
    blade, body = out["parts"]["2"], out["parts"]["1"]
    assert blade["gaussians"] == 200 and body["gaussians"] == 200
    assert blade["mean_trajectory_error"] < 1e-5 and body["mean_trajectory_error"] < 1e-5
    assert blade["axis_error_deg"] < 1e-3 and blade["omega_rel_error"] < 1e-6


def test_errors_measure_offsets_and_wrong_spin(tmp_path):
    points, ids = _write_gt(tmp_path)
    model = StandIn(points, ids, 2.0, offset=0.05, w_learned=-1.0)
    out = physics_errors(Future(model, ExtrapolationState(t_max=0.75)), tmp_path, [1.0])
    blade = out["parts"]["2"]
    assert blade["mean_trajectory_error"] == pytest.approx(0.05, rel=1e-4)
    assert blade["axis_error_deg"] == pytest.approx(180.0)
    assert blade["omega_rel_error"] == pytest.approx(0.5)
    assert math.isclose(out["parts"]["1"]["omega_abs_error"], 0.0)


def test_omega_over_span_follows_the_learned_drift(tmp_path):
    points, ids = _write_gt(tmp_path)
    out = physics_errors(
        Future(StandIn(points, ids, 2.0, droop=0.2), ExtrapolationState(t_max=0.8)), tmp_path, [1.0]
    )
    rows = out["omega_over_span"]
    assert [r["t"] for r in rows] == pytest.approx([0.2, 0.4, 0.6, 0.75, 0.8])  # incl. the handover
    for r in rows:
        blade = r["parts"]["2"]
        assert blade["omega_gt_norm"] == pytest.approx(2.0)
        assert blade["omega_rel_error"] == pytest.approx(0.2 * r["t"], rel=1e-5)
        assert "1" not in r["parts"]  # the static body has no rotation to compare


def test_a_free_body_s_spin_is_reported_where_it_moves_the_part(tmp_path):
    """Gaussians moved by a free body after the handover turn at its spin, not f_trd's."""
    points, ids = _write_gt(tmp_path)
    model = StandIn(points, ids, 2.0, w_learned=1.0)
    body = FreeBody(*(torch.zeros(3, dtype=torch.float64) for _ in range(3)), torch.tensor([0.0, 0.0, 2.0]))
    labels = torch.tensor(ids == 2, dtype=torch.long)
    bodies = {"t0": 0.7, "labels": labels, "bodies": body.as_tensor()[None]}
    state = ExtrapolationState(t_max=0.75, free_bodies=bodies)
    future = Future(model, state, free_bodies=True)
    assert physics_errors(future, tmp_path, [1.0])["parts"]["2"]["omega_rel_error"] < 1e-6
    future.settings.free_bodies = False  # switched off: f_trd's spin, half the truth
    assert physics_errors(future, tmp_path, [1.0])["parts"]["2"]["omega_rel_error"] == pytest.approx(0.5)


def test_a_part_touching_another_keeps_its_own_gaussians(tmp_path):
    """A turning disc lying on a still plate: at t_max the plate's surface points are as near the
    disc's Gaussians as the disc's own; the disc's motion over the span tells them apart."""
    rng = np.random.default_rng(1)

    def flat(n):  # points on the unit-half disc z = 0
        radius, angle = np.sqrt(rng.uniform(0.0, 0.25, n)), rng.uniform(0.0, 2 * np.pi, n)
        return np.c_[radius * np.cos(angle), radius * np.sin(angle), np.zeros(n)]

    _write_gt(tmp_path)
    truth = np.concatenate([flat(3000) + [0, 0, -0.005], flat(3000)])  # the plate just under the disc
    np.savez(tmp_path / "gt" / "points.npz", points=truth, part_ids=np.repeat([1, 2], 3000))
    points, ids = np.concatenate([flat(200) + [0, 0, -0.005], flat(200)]), np.repeat([1, 2], 200)
    out = physics_errors(
        Future(StandIn(points, ids, 2.0), ExtrapolationState(t_max=0.75)), tmp_path, [0.8, 1.0]
    )
    assert out["parts"]["2"]["gaussians"] == 200 and out["parts"]["1"]["gaussians"] == 200
    assert out["parts"]["1"]["mean_trajectory_error"] < 1e-5  # no disc Gaussian counted as the plate's
    assert out["parts"]["2"]["mean_trajectory_error"] < 1e-5
