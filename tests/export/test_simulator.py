"""``tracegs export --mjcf/--urdf``: a rig's bodies, joints and identified models as MuJoCo and URDF
models. A hinge with a spring and a damper simulates in MuJoCo to its closed form; a calibrated damped
pendulum (a blob that f_defo swings) is exported on its hinge and swings in MuJoCo as the run predicts
and as the truth does; a thrown ball bounces on its floor with its restitution; the URDF loads in
yourdfpy with its meshes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tests.conftest import about, blob_model

from tracegs.export.mjcf import contact_solref, mjcf_text
from tracegs.export.rig import Body, Rig, find_rig
from tracegs.export.simulate import load_urdf, simulate
from tracegs.export.urdf import write_urdf
from tracegs.extrapolate import calibrate
from tracegs.physics.force_law import LAWS, integrate
from tracegs.physics.identify import IdentifiedModel
from tracegs.physics.sindy import Contact

pytest.importorskip("mujoco")

AXIS = np.array([0.0, 1.0, 0.0])
PIVOT = np.array([0.1, 0.0, 0.4])


def box(centre, size=(0.3, 0.1, 0.1), n=300, seed=0) -> np.ndarray:
    """[n, 3] points filling a box about ``centre``."""
    rng = np.random.default_rng(seed)
    return np.asarray(centre) + (rng.random((n, 3)) - 0.5) * np.asarray(size)


def hinge_rig(model: IdentifiedModel, points: np.ndarray, t0: float) -> Rig:
    body = Body(
        name="arm", rows=torch.ones(len(points), dtype=torch.bool), joint="hinge", axis=AXIS, pivot=PIVOT,
        model=model, velocity=np.array([model.v_end[0]]), points=points,
    )  # fmt: skip
    return Rig(t0=t0, bodies=[body], up=np.array([0.0, 0.0, 1.0]))


def angles(motion, times) -> np.ndarray:
    """The hinge's turn about ``AXIS`` from the handover at each of ``times``."""
    out = []
    for t in times:
        r = motion.transforms(t)[0][:3, :3]
        out.append(math.atan2(r[0, 2] - r[2, 0], r[0, 0] + r[2, 2]))  # a turn about +y
    return np.array(out)


def test_a_hinge_with_a_spring_and_a_damper_simulates_to_its_closed_form():
    k, c, rest, t0, q0 = 60.0, 1.2, 0.3, 0.2, 0.5  # q'' = -k (q - rest) - c q', from rest at q0
    model = IdentifiedModel(
        [("1", -1), ("q", 0), ("v", 0)],
        np.array([[k * rest, -k, -c]]),
        (True,),
        t0,
        np.array([q0]),
        np.zeros(1),
    )
    xml, report = mjcf_text(hinge_rig(model, box(PIVOT + [0.3, 0.0, 0.0]), t0))
    (entry,) = report["bodies"]
    assert entry["joint"] == "hinge" and not entry["left_out"]
    assert float(report["gravity"][2]) == 0.0  # nothing falls or swings: no gravity
    motion = simulate(xml, hinge_rig(model, box(PIVOT + [0.3, 0.0, 0.0]), t0), t0 + 1.0)
    assert motion.finite
    s = np.linspace(0.05, 1.0, 20)
    wd, zeta = math.sqrt(k - c**2 / 4), c / 2
    a = q0 - rest  # q - rest = a e^{-zeta s} (cos wd s + zeta / wd sin wd s)
    truth = a * np.exp(-zeta * s) * (np.cos(wd * s) + zeta / wd * np.sin(wd * s)) + rest - q0
    got = angles(motion, t0 + s)
    assert np.abs(got - truth).max() < 2e-3 * abs(a), np.abs(got - truth).max()


def test_a_calibrated_pendulum_swings_in_mujoco_as_the_run_predicts_and_the_truth_does():
    pivot = torch.tensor([0.0, 0.6, 0.0], dtype=torch.float64)
    axis = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # horizontal: gravity turns it
    p = np.array([[-40.0, 0.0, 0.8]])  # q'' = -40 sin q - 0.8 q'

    def swing(t: float):
        return about(
            float(integrate(LAWS["pendulum"], p, [0.7], [0.0], np.array([t]), 1e-4)[0][0][0]), pivot, axis
        )

    model, settings, rows = blob_model([(0.0, 0.6, -0.5), (0.0, -0.8, 0.0)], [swing, None])
    model.frame_interval.fill_(1 / 60)
    predictor = calibrate(model, 0.75, settings, extent=2.0)
    rig = find_rig(predictor, 2.0)
    hinges = [b for b in rig.bodies if b.joint == "hinge"]
    assert len(hinges) == 1 and torch.equal(hinges[0].rows, rows[0])
    assert abs(abs(float(hinges[0].axis @ axis.numpy())) - 1) < 1e-6
    xml, report = mjcf_text(rig)
    entry = next(e for e in report["bodies"] if e["joint"] == "hinge")
    assert "sin" not in " ".join(entry["left_out"]) and "swing" in report["gravity_from"]
    motion = simulate(xml, rig, 1.25)
    part = rows[0]
    size = float(
        (model.deform(0.75)["means"][part] - model.deform(0.75)["means"][part].mean(0)).norm(dim=1).max()
    )
    for t in (0.8, 1.0, 1.25):
        got = predictor.gaussians_carried(t, motion.labels, motion.transforms)["means"][part]
        for want in (predictor.gaussians_at(t)["means"][part], model.deform(t)["means"][part]):
            error = float((got - want).norm(dim=1).max())
            assert error < 0.02 * size, (t, error, size)


def test_a_thrown_ball_bounces_on_its_floor_with_its_restitution():
    e, g, h = 0.7, 9.81, 0.5
    rng = np.random.default_rng(1)
    sphere = rng.normal(size=(400, 3))
    sphere = 0.05 * sphere / np.linalg.norm(sphere, axis=1, keepdims=True) + [0.0, 0.0, h]
    up = np.array([0.0, 0.0, 1.0])
    model = IdentifiedModel(
        [("1", -1)], np.array([[-g]]), (False,), 0.0, np.array([h]), np.zeros(1), (Contact(0, 0.05, -1, e),)
    )
    body = Body(
        name="ball", rows=torch.ones(400, dtype=torch.bool), joint="free", axis=up, pivot=np.array([0, 0, h]),
        model=model, velocity=np.zeros(6), acceleration=-g * up, points=sphere,
        floor={"normal": up, "offset": 0.0, "restitution": e, "radius": 0.05},
    )  # fmt: skip
    rig = Rig(t0=0.0, bodies=[body], up=up)
    xml, _ = mjcf_text(rig)
    motion = simulate(xml, rig, 1.0)
    centre = np.array([0.0, 0.0, h, 1.0])
    heights = np.array([(motion.transforms(t)[0] @ centre)[2] for t in np.arange(0, 1.0, motion.step)])
    fall = math.sqrt(2 * (h - 0.05) / g)
    early = np.arange(0, 0.9 * fall, motion.step)
    np.testing.assert_allclose(
        heights[: len(early)], h - 0.5 * g * early**2, atol=1e-3
    )  # (samples within a step)
    after = heights[int(1.1 * fall / motion.step) :]
    apex = after.max() - 0.05  # the centre's rise above where it touches
    assert abs(apex / (h - 0.05) - e**2) < 0.03 * e**2, (apex / (h - 0.05), e**2)
    assert contact_solref(1.0)[1] < 1e-3 * contact_solref(0.2)[1]  # no damping keeps the speed


def test_the_urdf_loads_with_its_meshes_and_names_what_it_cannot_hold(tmp_path):
    k, c = 60.0, 1.2
    model = IdentifiedModel(
        [("q", 0), ("v", 0)], np.array([[-k, -c]]), (True,), 0.0, np.zeros(1), np.zeros(1)
    )
    rig = hinge_rig(model, box(PIVOT + [0.3, 0.0, 0.0]), 0.0)
    from tracegs.export.mjcf import rig_hulls

    hulls = rig_hulls(rig)
    path, report = write_urdf(rig, hulls, tmp_path / "urdf")
    robot = load_urdf(path)
    assert set(robot.link_map) == {"world", "arm"} and robot.joint_map["arm"].type == "continuous"
    np.testing.assert_allclose(robot.joint_map["arm"].origin[:3, 3], PIVOT)
    inertia = hulls[0].inertia @ AXIS @ AXIS + hulls[0].mass * 0.3**2
    assert abs(float(robot.joint_map["arm"].dynamics.damping) - c * inertia) < 0.05 * c * inertia
    assert report["bodies"][0]["not_in_urdf"] == ["q term of q0"]  # a stiffness URDF cannot hold
    assert len(robot.scene.geometry) == 1


def test_a_run_without_physics_is_told_to_train_trace():
    from types import SimpleNamespace

    from tracegs.export.simulator import build_model
    from tracegs.run import RunError

    model = SimpleNamespace(dynamics=None, method="defgs")
    loaded = SimpleNamespace(predictor=SimpleNamespace(model=model), config=None, path="runs/fan_defgs")
    with pytest.raises(RunError, match="runs/fan_defgs: a defgs run has no physics"):
        build_model(loaded)


def test_a_part_carried_by_a_free_body_turns_about_its_own_hinge():
    """A small arm on a hinge through ``PIVOT`` carried by a large free body centred away from it: in
    MuJoCo the arm turns about that hinge (its pivot stays put while the heavy body barely moves)."""
    up = np.array([0.0, 0.0, 1.0])
    carrier = Body(
        name="body", rows=torch.tensor([True] * 400 + [False] * 300), joint="free", axis=np.zeros(3),
        pivot=np.array([-1.0, 0.0, 0.4]), velocity=np.zeros(6), points=box([-1.0, 0.0, 0.4], (1.2, 1.2, 1.2), 400),
        source="free body",
    )  # fmt: skip
    model = IdentifiedModel([("1", -1)], np.zeros((1, 1)), (True,), 0.0, np.zeros(1), np.array([2.0]))
    arm = Body(
        name="arm", rows=torch.tensor([False] * 400 + [True] * 300), joint="hinge", axis=AXIS, pivot=PIVOT,
        parent=0, model=model, velocity=np.array([2.0]), points=box(PIVOT + [0.3, 0.0, 0.0], n=300),
    )  # fmt: skip
    rig = Rig(t0=0.0, bodies=[carrier, arm], up=up)
    xml, report = mjcf_text(rig)
    motion = simulate(xml, rig, 0.5)
    for t in (0.1, 0.3, 0.5):
        turn = motion.transforms(t)[1]
        np.testing.assert_allclose(turn[:3, :3] @ PIVOT + turn[:3, 3], PIVOT, atol=5e-3)  # the hinge stays
        r = turn[:3, :3]  # a turn about +y (AXIS)
        assert abs(math.atan2(r[0, 2] - r[2, 0], r[0, 0] + r[2, 2]) - 2.0 * t) < 0.05 * 2.0 * t
    assert report["bodies"][1]["parent"] == "body"
