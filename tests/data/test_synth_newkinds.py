"""Tests of the five scenes of coupled motion kinds (``synth/mechanisms.py``, ``synth/impacts.py``,
``synth/scenes_coupled.py``): each motion against its equations (conserved energy and momenta where
undamped, the rolling and joint constraints, the impact's momentum and restitution), from the records
``gt/motion.json`` holds; a tiny render whose masks agree with the ground truth; and the CLI.
"""

from __future__ import annotations

import json
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from tracegs.data.synth import part_transforms
from tracegs.data.synth.integrate import matrix_to_quaternion, quaternion_to_matrix, trajectory_of
from tracegs.data.synth.kinematics import axis_angle_to_matrix
from tracegs.data.synth.mechanisms import HingedChain, PlanarSprings
from tracegs.data.synth.motion import load_motions, motion_record, part_angular_velocities
from tracegs.data.synth.scenes import get_scene as _build

KINDS = ("rolling", "gyroscope", "doublependulum", "planarsprings", "collision")
T_TRAIN_END = 45 / 59
H = 1e-5
TIMES = np.linspace(0.0, 1.5, 301)

get_scene = cache(_build)


@cache
def _motions(scene: str) -> list:
    """The scene's motions read back from its ``gt/motion.json`` records (through json)."""
    spec = get_scene(scene)
    records = [motion_record(p.name, i + 1, p.motion) for i, p in enumerate(spec.parts)]
    return load_motions({"parts": json.loads(json.dumps(records))})


def _moved(motion, point, t) -> np.ndarray:
    """[T, 3] where the rest-pose ``point`` is at times ``t``."""
    T = motion.transform(t)
    return T[..., :3, :3] @ np.asarray(point, dtype=np.float64) + T[..., :3, 3]


def _rate(f, t):
    return (f(t + H) - f(t - H)) / (2 * H)


# --- every kind ------------------------------------------------------------------------------------


@pytest.mark.parametrize("scene", KINDS)
def test_each_scene_is_timed_and_sized_like_the_others(scene):
    """A static part first, the identity at t = 0, every other part moving through the training span
    and the future; the fastest mesh vertex under about 3.5 px per frame at 60 frames and 128 px."""
    from tracegs.data.synth.writer import motion_bounds

    spec = get_scene(scene)
    motions = _motions(scene)
    assert motions[0].kind == "static" and np.allclose(motions[0].transform(TIMES), np.eye(4))
    bounds = motion_bounds(spec)
    assert bounds.radius < 1.35 and (np.abs(bounds.aabb) < 1.3).all()
    pixels_per_unit = 128 / (2 * bounds.radius * 1.05)
    frames = np.arange(61) / 59
    for p, motion in enumerate(motions[1:], start=1):
        np.testing.assert_allclose(motion.transform(0.0), np.eye(4), atol=1e-15)
        v = spec.part_mesh(p).vertices.astype(np.float64)
        T = motion.transform(frames)
        path = np.einsum("tij,vj->tvi", T[:, :3, :3], v) + T[:, None, :3, 3]
        step = np.linalg.norm(np.diff(path, axis=0), axis=-1).max(axis=1) * pixels_per_unit
        assert step.max() < 3.5, (scene, p, step.max())
        assert step[:45].mean() > 0.3 and step[46:59].mean() > 0.05, (scene, p)  # moves in both spans


@pytest.mark.parametrize("scene", KINDS)
def test_angular_velocity_is_the_rate_of_the_transforms(scene):
    t = np.array([0.1, 0.4, 0.7, 1.2])
    R = [part_transforms({"parts": _records(scene)}, t + d)[..., :3, :3] for d in (-H, 0.0, H)]
    W = (R[2] - R[0]) / (2 * H) @ np.swapaxes(R[1], -1, -2)
    vee = np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], -1)
    np.testing.assert_allclose(part_angular_velocities({"parts": _records(scene)}, t), vee, atol=1e-5)


def _records(scene: str) -> list[dict]:
    spec = get_scene(scene)
    return json.loads(json.dumps([motion_record(p.name, i + 1, p.motion) for i, p in enumerate(spec.parts)]))


def test_quaternions_turn_like_matrices():
    rng = np.random.default_rng(0)
    for _ in range(20):
        axis = rng.normal(size=3)
        R = axis_angle_to_matrix(axis / np.linalg.norm(axis), rng.uniform(-np.pi, np.pi))
        np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-12)


# --- rolling ---------------------------------------------------------------------------------------


def test_rolling_ball_rolls_without_slipping_and_keeps_its_energy():
    ball = _motions("rolling")[1]
    c, v, _ = ball.state(TIMES)
    n = (c - np.asarray(ball.bowl_center)) / (ball.bowl_radius - ball.ball_radius)
    np.testing.assert_allclose(
        np.linalg.norm(c - ball.bowl_center, axis=1), ball.bowl_radius - ball.ball_radius
    )
    # the centre's velocity, from the transforms, is w x (c - contact): the contact point is at rest
    velocity = _rate(lambda s: _moved(ball, ball.pivot, s), TIMES)
    omega = ball.angular_velocity_at(TIMES)
    np.testing.assert_allclose(velocity, np.cross(omega, -ball.ball_radius * n), atol=1e-6)
    np.testing.assert_allclose(velocity, v, atol=1e-6)
    # a solid ball: kinetic energy 1/2 v^2 + 1/2 (2/5 r^2) w^2 per unit mass, plus g z
    energy = 0.5 * (v**2).sum(1) + 0.2 * ball.ball_radius**2 * (omega**2).sum(1) + ball.gravity * c[:, 2]
    np.testing.assert_allclose(energy, energy[0], rtol=1e-9)
    # two degrees of freedom: the centre leaves every vertical plane (its horizontal path is no line)
    assert np.linalg.svd(c[:, :2] - c[:, :2].mean(0), compute_uv=False)[1] > 0.3
    # it turns back towards the bottom in the future span as it did in the training span
    height = c[:, 2]
    turns = TIMES[1:-1][(np.diff(np.sign(np.diff(height))) != 0)]
    assert (turns < T_TRAIN_END).any() and ((turns > T_TRAIN_END) & (turns <= 1.0)).any()


def test_rolling_ball_is_a_few_percent_of_the_scene():
    from tracegs.data.synth.writer import motion_bounds

    ball = _motions("rolling")[1]
    assert 0.02 < ball.ball_radius / (2 * motion_bounds(get_scene("rolling")).radius) < 0.1


# --- gyroscope -------------------------------------------------------------------------------------


def test_gyroscope_keeps_energy_momentum_and_spin_and_precesses():
    top = _motions("gyroscope")[1]
    R, L = top.state(TIMES)
    a = R @ np.asarray(top.axis)
    omega = top.angular_velocity_at(TIMES)
    energy = 0.5 * (omega * L).sum(1) + top.gravity * top.com_distance * a[:, 2]
    np.testing.assert_allclose(energy, energy[0], rtol=1e-9)
    np.testing.assert_allclose(L[:, 2], L[0, 2], atol=1e-10)  # no torque about the vertical
    np.testing.assert_allclose((omega * a).sum(1), top.spin, rtol=1e-9)  # symmetric body: spin kept
    # the torque about the pivot is the rate of the angular momentum
    torque = top.com_distance * np.cross(a, [0.0, 0.0, -top.gravity])
    np.testing.assert_allclose(_rate(lambda s: top.state(s)[1], TIMES[1:-1]), torque[1:-1], atol=1e-6)
    np.testing.assert_allclose(
        _moved(top, top.pivot, TIMES), np.broadcast_to(top.pivot, (len(TIMES), 3)), atol=1e-12
    )
    azimuth = np.unwrap(np.arctan2(a[:, 1], a[:, 0]))
    assert azimuth[TIMES <= 1.0][-1] > 1.0 and (np.diff(azimuth) > 0).all()  # precesses one way
    elevation = np.arcsin(a[:, 2])
    assert np.ptp(elevation) > np.radians(10)  # and nods


# --- double pendulum -------------------------------------------------------------------------------


def test_chain_joints_hold_and_energy_is_kept():
    links = _motions("doublependulum")[1:]
    chain = links[0]
    theta, rate = chain.angles_at(TIMES)
    down = np.array([0.0, 0.0, -1.0])
    joint0 = (
        np.asarray(chain.pivot) + chain.lengths[0] * axis_angle_to_matrix(chain.axis, chain.angles[0]) @ down
    )
    # the first bar turns about the fixed pivot; the point it shares with the second stays shared
    np.testing.assert_allclose(
        _moved(links[0], chain.pivot, TIMES), np.broadcast_to(chain.pivot, (len(TIMES), 3)), atol=1e-12
    )
    elbow = _moved(links[0], joint0, TIMES)
    np.testing.assert_allclose(_moved(links[1], joint0, TIMES), elbow, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(elbow - chain.pivot, axis=1), chain.lengths[0], atol=1e-12)
    # energy of two uniform bars from the angles: T = 1/2 q'^T M q', V = -g sum m_i z_i
    (m1, m2), (l1, l2), g = chain.masses, chain.lengths, chain.gravity
    kinetic = 0.5 * (m1 * l1**2 / 3 + m2 * l1**2) * rate[:, 0] ** 2 + 0.5 * m2 * l2**2 / 3 * rate[:, 1] ** 2
    kinetic += 0.5 * m2 * l1 * l2 * np.cos(theta[:, 0] - theta[:, 1]) * rate[:, 0] * rate[:, 1]
    potential = -g * ((m1 * l1 / 2 + m2 * l1) * np.cos(theta[:, 0]) + m2 * l2 / 2 * np.cos(theta[:, 1]))
    energy = kinetic + potential
    np.testing.assert_allclose(energy, energy[0], rtol=1e-9, atol=1e-9)
    assert np.ptp(theta[:, 1] - theta[:, 0]) > 0.5  # the elbow bends: two degrees of freedom


def test_chain_equations_reduce_to_the_textbook_ones():
    """One bar: theta'' = -3 g / (2 L) sin(theta). Two bars: the equations of a double physical pendulum."""
    bar = HingedChain(lengths=(0.6,), masses=(2.0,), angles=(0.4,), rates=(0.0,), gravity=9.0)
    assert bar.derivative(0.0, np.array([0.4, 0.3]))[1] == pytest.approx(-3 * 9.0 / 1.2 * np.sin(0.4))
    chain = HingedChain(lengths=(0.5, 0.4), masses=(1.0, 0.8), gravity=12.0)
    (m1, m2), (l1, l2), g = chain.masses, chain.lengths, chain.gravity
    rng = np.random.default_rng(1)
    for q1, q2, w1, w2 in rng.uniform(-1.5, 1.5, size=(5, 4)):
        d = q1 - q2
        M = np.array(
            [
                [m1 * l1**2 / 3 + m2 * l1**2, m2 * l1 * l2 / 2 * np.cos(d)],
                [m2 * l1 * l2 / 2 * np.cos(d), m2 * l2**2 / 3],
            ]
        )
        rhs = [
            -m2 * l1 * l2 / 2 * np.sin(d) * w2**2 - (m1 / 2 + m2) * g * l1 * np.sin(q1),
            m2 * l1 * l2 / 2 * np.sin(d) * w1**2 - m2 * g * l2 / 2 * np.sin(q2),
        ]
        np.testing.assert_allclose(
            chain.derivative(0.0, np.array([q1, q2, w1, w2]))[2:], np.linalg.solve(M, rhs), rtol=1e-12
        )


# --- planar springs --------------------------------------------------------------------------------


def test_planar_springs_rest_at_the_origin_keep_energy_undamped_and_move_in_three_coordinates():
    disc = _motions("planarsprings")[1]
    # at the origin, unturned and at rest, every spring pulls radially with the same tension: equilibrium
    np.testing.assert_allclose(disc.derivative(0.0, np.zeros(6)), 0.0, atol=1e-12)
    undamped = replace(disc, damping=0.0)
    y = trajectory_of(undamped)(TIMES)
    energy = undamped.energy(y)
    np.testing.assert_allclose(energy, energy[0], rtol=1e-9)
    damped = disc.energy(trajectory_of(disc)(TIMES))
    assert (np.diff(damped) <= 1e-12).all() and damped[-1] < 0.9 * damped[0]
    y = trajectory_of(disc)(TIMES)
    for coordinate in range(3):  # x, y and the angle all swing back and forth
        assert (np.diff(np.sign(y[:, 3 + coordinate])) != 0).sum() >= 2
    # the transform moves the disc's centre to (x, y) and turns it by phi about z
    np.testing.assert_allclose(_moved(disc, disc.pivot, TIMES)[:, :2], y[:, :2], atol=1e-12)
    np.testing.assert_allclose(
        disc.transform(TIMES)[:, :3, :3], axis_angle_to_matrix((0, 0, 1), y[:, 2]), atol=1e-12
    )
    with pytest.raises(ValueError, match="one value per spring"):
        PlanarSprings(anchors=((0, 0, 0),), attachments=((0, 0, 0),), stiffnesses=(1.0,), rest_lengths=(1.0,))


# --- collision -------------------------------------------------------------------------------------


def test_collision_conserves_momentum_and_scales_the_normal_speed_by_restitution():
    striker, struck = _motions("collision")[1:]
    t_c = striker.contact_time
    assert 0.1 < t_c < T_TRAIN_END
    (ma, mb), e = striker.masses, striker.restitution
    before = [m.path(t_c - 1e-9)[1] for m in (striker, struck)]
    after = [m.path(t_c + 1e-9)[1] for m in (striker, struck)]
    np.testing.assert_allclose(ma * after[0] + mb * after[1], ma * before[0] + mb * before[1], atol=1e-6)
    centres = [m.path(t_c)[0] for m in (striker, struck)]
    gap = centres[1] - centres[0]
    assert np.linalg.norm(gap) == pytest.approx(2 * striker.radius, abs=1e-12)  # touching at the contact
    n = gap / np.linalg.norm(gap)
    assert (after[0] - after[1]) @ n == pytest.approx(-e * (before[0] - before[1]) @ n, abs=1e-6)
    tangent = np.array([-n[1], n[0], 0.0])
    for b, a in zip(before, after, strict=True):  # smooth discs: no tangential impulse
        assert a @ tangent == pytest.approx(b @ tangent, abs=1e-6)
    assert np.linalg.norm(before[1]) == 0 and min(np.linalg.norm(a) for a in after) > 0.3  # both move after
    # never overlapping; sliding with the friction's deceleration until each stops in the future span
    paths = [m.path(TIMES) for m in (striker, struck)]
    assert (np.linalg.norm(paths[0][0] - paths[1][0], axis=1) >= 2 * striker.radius - 1e-9).all()
    for m, (_, v) in zip((striker, struck), paths, strict=True):
        speed = np.linalg.norm(v, axis=1)
        moving = (TIMES > t_c + 0.01) & (speed > 0.05)
        np.testing.assert_allclose(
            _rate(lambda s, m=m: np.linalg.norm(m.path(s)[1], axis=-1), TIMES[moving]),
            -m.deceleration,
            rtol=1e-5,
        )
    stops = striker.record()["stop_times"]
    assert all(T_TRAIN_END < s < 2.0 for s in stops)


# --- the files -------------------------------------------------------------------------------------


@pytest.mark.parametrize("scene", KINDS)
def test_tiny_render_masks_follow_the_ground_truth(scene, tmp_path):
    """Each moving part's mask centroid is where its ground-truth points project (within 1.5 px at
    32 px), the stored transforms are the records', and motion.json states the equations."""
    pytest.importorskip("mitsuba")
    import imageio.v3 as iio

    from tracegs.data.synth import synthesize

    root = synthesize(scene, tmp_path / scene, resolution=32, views=2, frames=4, progress=False, spp=1)
    motion = json.loads((root / "gt" / "motion.json").read_text())
    assert all(p["type"] in motion["formulas"] for p in motion["parts"][1:])
    stored = np.load(root / "gt" / "part_transforms.npz")
    np.testing.assert_allclose(stored["transforms"], part_transforms(root, stored["times"]), atol=1e-12)
    gt = np.load(root / "gt" / "points.npz")
    checked = 0
    for split in ("train", "val", "test"):
        top = json.loads((root / f"transforms_{split}.json").read_text())
        for fr in top["frames"]:
            mask = iio.imread(root / "gt" / "masks" / fr["file_path"])
            T = part_transforms(root, fr["time"])
            c2w = np.array(fr["transform_matrix"])
            c2w[:3, 1:3] *= -1  # OpenGL -> OpenCV
            w2c = np.linalg.inv(c2w)
            f = 0.5 * top["w"] / np.tan(0.5 * top["camera_angle_x"])
            for part in range(2, len(motion["parts"]) + 1):
                p = gt["points"][gt["part_ids"] == part].astype(np.float64)
                cam = (p @ T[part - 1, :3, :3].T + T[part - 1, :3, 3]) @ w2c[:3, :3].T + w2c[:3, 3]
                uv = f * cam[:, :2] / cam[:, 2:] + top["w"] / 2
                rows, cols = np.nonzero(mask == part)
                if len(rows) < 8:  # mostly hidden in this view
                    continue
                centroid = np.array([cols.mean(), rows.mean()]) + 0.5
                assert np.linalg.norm(centroid - uv.mean(0)) < 1.5, (scene, fr["file_path"], part)
                checked += 1
    assert checked >= 4


def test_cli_renders_every_new_scene(tmp_path):
    pytest.importorskip("mitsuba")
    from tracegs.cli import main

    for scene in KINDS:
        out = tmp_path / scene
        main(
            [
                "synth",
                "--out",
                str(out),
                "--scene",
                scene,
                "--resolution",
                "12",
                "--views",
                "2",
                "--frames",
                "2",
            ]
        )
        assert json.loads((out / "gt" / "motion.json").read_text())["scene"] == scene
        assert len(json.loads((out / "transforms_train.json").read_text())["frames"]) == 1
