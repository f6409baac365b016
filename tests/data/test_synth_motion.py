"""Tests of the synthetic motions under forces that are not constant (``synth/varying.py``) and of the
five scenes made with them: each closed form against its equation of motion, the timing of the
non-constant behaviour against the training span, json records that read back to the same motion,
and a tiny render of each scene that the project's parser reads.
"""

from __future__ import annotations

import json
from functools import cache

import numpy as np
import pytest

from tracegs.data.synth import SCENES, part_transforms
from tracegs.data.synth.motion import (
    RigidMotion,
    load_motions,
    motion_from_record,
    motion_record,
    part_angular_velocities,
)
from tracegs.data.synth.scenes import get_scene as _build
from tracegs.data.synth.varying import Bouncing, DampedRotation, FrictionStop

NEW_SCENES = ("pendulum", "spring", "brake", "bounce", "turntable")
OLD_SCENES = ("fan", "foldingchair", "satellite", "fallingball", "slider")
T_TRAIN_END = 45 / 59  # the last training time of the default 60 frames
H = 1e-4  # finite-difference step


get_scene = cache(_build)  # building a scene's textures takes a tenth of a second


def _records(scene: str) -> list[dict]:
    """The scene's ``gt/motion.json`` parts, through json and back."""
    spec = get_scene(scene)
    return json.loads(json.dumps([motion_record(p.name, i + 1, p.motion) for i, p in enumerate(spec.parts)]))


def _motion(scene: str, part: int):
    return get_scene(scene).parts[part].motion


def _signed_angle(R: np.ndarray, axis) -> np.ndarray:
    """[...] angle of the rotations R [..., 3, 3] about the unit ``axis`` (all turn about it)."""
    vee = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    return np.arctan2(0.5 * vee @ np.asarray(axis), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1))


def _derivatives(f, t: np.ndarray):
    """(f, f', f'') at ``t`` by central differences of step H."""
    lo, mid, hi = f(t - H), f(t), f(t + H)
    return mid, (hi - lo) / (2 * H), (hi - 2 * mid + lo) / H**2


def _sign_changes(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    return t[1:][np.diff(np.sign(x)) != 0]


# --- each closed form against its equation of motion ----------------------------------------------


def test_pendulum_angle_solves_the_damped_oscillator_equation():
    m = _motion("pendulum", 1)
    rec = _records("pendulum")[1]
    assert rec["type"] == "damped_rotation" and rec["id"] == 2
    zeta, w0 = rec["damping_ratio"], rec["natural_frequency"]
    t = np.linspace(0.0, 1.5, 301)

    def theta(times):  # from the transforms, measured from hanging straight down
        return (
            _signed_angle(part_transforms({"parts": _records("pendulum")}, times)[:, 1, :3, :3], m.axis)
            + (rec["rest_offset"])
        )

    th, dth, ddth = _derivatives(theta, t)
    np.testing.assert_allclose(ddth + 2 * zeta * w0 * dth + w0**2 * th, 0.0, atol=2e-3)
    np.testing.assert_allclose(th, m.value(t)[0], atol=1e-12)
    # A swing back in the training span and one in the future; the amplitude decays.
    turns = _sign_changes(dth, t)
    assert ((turns > 0) & (turns < T_TRAIN_END)).any() and ((turns > T_TRAIN_END) & (turns <= 1)).any()
    peaks = np.abs(m.value(turns)[0])
    assert (np.diff(peaks) < 0).all() and peaks[0] > 0.4 and peaks[-1] < 0.8 * peaks[0]
    # The hinge stays put and the rest pose is the identity.
    T = m.transform(t)
    np.testing.assert_allclose(
        T[:, :3, :3] @ np.array(m.pivot) + T[:, :3, 3], np.broadcast_to(m.pivot, (301, 3))
    )
    np.testing.assert_allclose(m.transform(0.0), np.eye(4), atol=1e-15)


def test_spring_block_oscillates_about_its_equilibrium_from_rest():
    m = _motion("spring", 1)
    zeta, w0 = m.damping_ratio, m.natural_frequency
    t = np.linspace(0.0, 1.5, 301)
    x0 = m.value(0.0)[0]

    def x(times):  # displacement from the equilibrium along the direction
        return part_transforms({"parts": _records("spring")}, times)[:, 1, :3, 3] @ np.array(m.direction) + x0

    s, ds, dds = _derivatives(x, t)
    np.testing.assert_allclose(dds + 2 * zeta * w0 * ds + w0**2 * s, 0.0, atol=2e-3)
    np.testing.assert_allclose(
        part_transforms({"parts": _records("spring")}, t)[:, 1, :3, :3], np.eye(3)[None].repeat(301, 0)
    )
    assert abs(m.value(0.0)[1]) < 1e-12 and x0 > 0.3  # released at rest, 0.35 from the equilibrium
    turns = _sign_changes(ds[1:], t[1:])
    assert ((turns > T_TRAIN_END) & (turns <= 1)).any() and ((turns > 0) & (turns < T_TRAIN_END)).any()


def test_brake_decelerates_at_a_constant_rate_and_stays_stopped():
    m = _motion("brake", 1)
    rec = _records("brake")[1]
    assert rec["type"] == "friction_stop"
    assert T_TRAIN_END < rec["stop_time"] <= 1.0
    w0, alpha, t_stop = rec["angular_velocity"], rec["angular_acceleration"], rec["stop_time"]
    assert w0 + alpha * t_stop == pytest.approx(0.0, abs=1e-12)

    def angle(times):
        return _signed_angle(part_transforms({"parts": _records("brake")}, times)[:, 1, :3, :3], m.axis)

    before = np.linspace(0.0, t_stop - 0.01, 50)
    after = np.linspace(t_stop + 0.01, 1.5, 50)
    _, w_before, a_before = _derivatives(angle, before)
    np.testing.assert_allclose(w_before, w0 + alpha * before, atol=1e-6)
    np.testing.assert_allclose(a_before, alpha, atol=1e-3)
    _, w_after, _ = _derivatives(angle, after)
    np.testing.assert_allclose(w_after, 0.0, atol=1e-9)
    total = w0**2 / (2 * abs(alpha))
    np.testing.assert_allclose(angle(np.array([t_stop, 1.0, 1.5])), total, atol=1e-12)
    w = m.angular_velocity_at(np.array([0.0, t_stop, 1.2]))
    np.testing.assert_allclose(w, [np.array(m.axis) * w0, np.zeros(3), np.zeros(3)], atol=1e-12)


def test_bouncing_ball_stays_above_the_floor_and_rebounds_with_restitution():
    m = _motion("bounce", 1)
    e, g, floor = m.restitution, m.gravity, m.floor_height
    c0 = np.array(m.pivot)

    def centre(times):
        T = part_transforms({"parts": _records("bounce")}, np.atleast_1d(times))[:, 1]
        return T[:, :3, :3] @ c0 + T[:, :3, 3]

    t = np.linspace(0.0, 2.5, 5001)
    c = centre(t)
    assert c[:, 2].min() >= floor - 1e-12
    np.testing.assert_allclose(c[:, 0], c0[0] + m.linear_velocity[0] * t, atol=1e-12)  # no friction
    contacts = m.contact_times()
    assert ((contacts > 0) & (contacts < T_TRAIN_END)).any()
    assert ((contacts > T_TRAIN_END) & (contacts <= 1.0)).any()
    h = 1e-5
    for tk in contacts[:5]:
        z_lo, z_k, z_hi = (centre(tk + d)[0, 2] for d in (-h, 0.0, h))
        assert z_k == pytest.approx(floor, abs=1e-12)
        # The mean speed over a step of a parabola is its speed at the step's middle.
        v_in, v_out = (z_k - z_lo) / h - g * h / 2, (z_hi - z_k) / h + g * h / 2
        assert v_in < 0 and v_out == pytest.approx(-e * v_in, rel=1e-5)
    # Between contacts: free flight under gravity; after the last one, at rest on the floor.
    flight = np.linspace(contacts[0] + 0.01, contacts[1] - 0.01, 20)
    _, _, a = _derivatives(lambda s: centre(s)[:, 2], flight)
    np.testing.assert_allclose(a, -g, atol=1e-3)
    rest = m.arcs()[0][-1]
    np.testing.assert_allclose(centre(np.array([rest + 0.1, rest + 1.0]))[:, 2], floor, atol=1e-12)
    # Spin at a constant rate about the moving centre.
    R = part_transforms({"parts": _records("bounce")}, t[:400])[:, 1, :3, :3]
    np.testing.assert_allclose(_signed_angle(R, m.axis), m.angular_velocity * t[:400], atol=1e-9)


def test_turntable_carries_the_box_round_a_circle_at_its_own_rate():
    disc, box = _motion("turntable", 1), _motion("turntable", 2)
    rec = _records("turntable")[2]
    assert (
        rec["type"] == "carried"
        and rec["parent_part"] == 2
        and rec["parent"] == {k: v for k, v in _records("turntable")[1].items() if k not in ("id", "name")}
    )
    c0 = np.array(box.child.pivot)
    t = np.linspace(0.0, 1.5, 151)
    T = part_transforms({"parts": _records("turntable")}, t)
    c = T[:, 2, :3, :3] @ c0 + T[:, 2, :3, 3]
    np.testing.assert_allclose(np.hypot(c[:, 0], c[:, 1]), np.hypot(*c0[:2]), atol=1e-12)
    np.testing.assert_allclose(c[:, 2], c0[2], atol=1e-12)
    polar = np.unwrap(np.arctan2(c[:, 1], c[:, 0]))
    np.testing.assert_allclose(polar, disc.angular_velocity * t, atol=1e-12)  # the turntable's rate
    w_box = disc.angular_velocity + box.child.angular_velocity
    np.testing.assert_allclose(np.unwrap(_signed_angle(T[:, 2, :3, :3], (0, 0, 1))), w_box * t, atol=1e-9)
    # On the turntable, the box only spins about its own centre.
    relative = np.linalg.inv(T[:, 1]) @ T[:, 2]
    np.testing.assert_allclose(relative, box.child.transform(t), atol=1e-12)
    np.testing.assert_allclose(box.angular_velocity_at(0.7), [0.0, 0.0, w_box], atol=1e-12)


@pytest.mark.parametrize("scene", NEW_SCENES)
def test_angular_velocity_is_the_rate_of_the_transforms(scene):
    """omega^ = R'(t) R(t)^T for every part, from the records (away from the brake's stop)."""
    t = np.array([0.1, 0.4, 0.7, 1.2])
    records = _records(scene)
    R = [part_transforms({"parts": records}, t + d)[..., :3, :3] for d in (-H, 0.0, H)]
    W = (R[2] - R[0]) / (2 * H) @ np.swapaxes(R[1], -1, -2)
    vee = np.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], -1)
    np.testing.assert_allclose(part_angular_velocities({"parts": records}, t), vee, atol=1e-6)


# --- records, and the scenes that use them --------------------------------------------------------


def _assert_same_record(a: dict, b: dict) -> None:
    """Equal records but for the part's ``id`` and ``name`` and the last bits of floats."""
    b = {k: v for k, v in b.items() if k not in ("id", "name")}
    assert list(a) == list(b)
    for key, value in a.items():
        if isinstance(value, dict):
            _assert_same_record(value, b[key])
        elif isinstance(value, str | None):
            assert value == b[key], key
        else:
            np.testing.assert_allclose(value, b[key], rtol=1e-15, atol=1e-15, err_msg=key)


@pytest.mark.parametrize("scene", sorted(SCENES))
def test_records_read_back_to_the_same_motion(scene):
    t = np.linspace(-0.2, 2.0, 23)
    for part, record in zip(get_scene(scene).parts, _records(scene), strict=True):
        again = motion_from_record(record)
        # (a unit axis read back is normalised again: equal to the last bits)
        np.testing.assert_allclose(again.transform(t), part.motion.transform(t), rtol=0, atol=1e-14)
        np.testing.assert_allclose(
            again.angular_velocity_at(t), part.motion.angular_velocity_at(t), atol=1e-14
        )
        _assert_same_record(json.loads(json.dumps(again.record())), record)
    np.testing.assert_allclose(
        part_transforms({"parts": _records(scene)}, t),
        np.stack([p.motion.transform(t) for p in get_scene(scene).parts], axis=1),
        atol=1e-14,
    )


def test_the_five_constant_force_scenes_keep_their_records():
    keys = ["name", "id", "type", "axis", "pivot", "angular_velocity", "angular_acceleration"]
    keys += ["linear_velocity", "linear_acceleration"]
    for scene in OLD_SCENES:
        for part, record in zip(get_scene(scene).parts, _records(scene), strict=True):
            assert isinstance(part.motion, RigidMotion) and list(record) == keys, scene
    blades = _records("fan")[1]
    assert (blades["type"], blades["angular_velocity"], blades["axis"]) == ("rotation", 2.0, [0.0, 0.0, 1.0])
    assert list(SCENES)[:5] == list(OLD_SCENES) and list(SCENES)[5:10] == list(NEW_SCENES)


def test_every_new_scene_has_a_static_part_and_identity_at_rest():
    for scene in NEW_SCENES:
        motions = load_motions({"parts": _records(scene)})
        T = np.stack([m.transform(np.linspace(0.0, 1.5, 31)) for m in motions], 1)
        assert motions[0].kind == "static" and np.allclose(T[:, 0], np.eye(4)), scene
        np.testing.assert_allclose(T[0], np.broadcast_to(np.eye(4), T[0].shape), atol=1e-15)
        assert all(not np.allclose(T[:, p], np.eye(4)) for p in range(1, len(motions))), scene


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="damping_ratio"):
        DampedRotation(amplitude=0.5, natural_frequency=3.0, damping_ratio=1.2)
    with pytest.raises(ValueError, match="opposite signs"):
        FrictionStop(angular_velocity=2.0, angular_acceleration=1.0)
    with pytest.raises(ValueError, match="below the floor"):
        Bouncing(pivot=(0, 0, -1.0), floor_height=0.0)
    with pytest.raises(ValueError, match="restitution"):
        Bouncing(restitution=1.0)


@pytest.mark.parametrize("scene", NEW_SCENES)
def test_tiny_render_is_a_scene_folder_the_parser_reads(scene, tmp_path):
    pytest.importorskip("mitsuba")
    from tracegs.data.scene import load_scene
    from tracegs.data.synth import synthesize

    root = synthesize(scene, tmp_path / scene, resolution=16, views=2, frames=3, progress=False, spp=1)
    motion = json.loads((root / "gt" / "motion.json").read_text())
    assert [p["id"] for p in motion["parts"]] == list(range(1, len(get_scene(scene).parts) + 1))
    assert all({"name", "type"} <= set(p) for p in motion["parts"])
    assert motion["parts"][-1]["type"] in motion["formulas"]
    stored = np.load(root / "gt" / "part_transforms.npz")
    np.testing.assert_allclose(stored["transforms"], part_transforms(root, stored["times"]), atol=1e-12)
    assert stored["transforms"].shape == (3, len(motion["parts"]), 4, 4)
    for split in ("train", "val", "test"):
        frames = load_scene(root, split).frames
        assert frames and all(f.image_path.is_file() for f in frames)
        for f in frames:
            assert (root / "gt" / "masks" / f.image_path.relative_to(root)).is_file()
