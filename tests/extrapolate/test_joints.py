"""Joint parts with identified models: a part that f_defo swings as a damped pendulum about a
hinge gets its hinge and a swinging law, and after the handover it swings on as the truth does; a
part that turns steadily (a fan) keeps the learned physics; the state round-trips; off, nothing
changes."""

import io

import numpy as np
import pytest
import torch
from tests.conftest import about, blob_model

from tracegs.config import make_config
from tracegs.extrapolate import ExtrapolationState, Predictor, calibrate
from tracegs.physics.force_law import LAWS, integrate
from tracegs.physics.so3 import rodrigues

AXIS = torch.nn.functional.normalize(torch.tensor([0.2, 0.1, 1.0], dtype=torch.float64), dim=0)
PIVOT = torch.tensor([0.0, 0.6, 0.0], dtype=torch.float64)
T_MAX = 0.75


def damped_pendulum(t: np.ndarray) -> np.ndarray:
    """[T] the angle of ``q'' = -40 sin q - 0.8 q'`` released at rest from 0.7 rad at t = 0."""
    p = np.array([[-40.0, 0.0, 0.8]])  # alpha = -k cos(q_rest), beta = k sin(q_rest), c
    return integrate(LAWS["pendulum"], p, [0.7], [0.0], t, 1e-4)[0][0]


def steady_turn(t: np.ndarray) -> np.ndarray:
    return 2.0 * t


def _model(angle, joint_laws: bool = True):
    """A blob 0.5 below the hinge turned about it by ``angle(t)``, and one far from it held still.
    Returns the model, its extrapolation settings and the turning part's rows."""
    turning = lambda t: about(float(angle(np.array([t]))[0]), PIVOT)  # noqa: E731
    model, settings, rows = blob_model([(0.0, 0.1, 0.0), (0.0, -0.8, 0.0)], [turning, None], joint_laws)
    model.frame_interval.fill_(1 / 60)  # frames as the synthetic scenes have them
    return model, settings, rows[0]


def test_a_damped_pendulum_is_put_on_its_hinge_and_swings_on():
    model, settings, part = _model(damped_pendulum)
    predictor = calibrate(model, T_MAX, settings, extent=2.0)
    state = predictor.state
    (entry,) = state.report["joint_laws"]
    assert entry["adopted"] and entry["joint"] == "hinge" and entry["gaussians"] == int(part.sum())
    # the truth q'' = -40 sin q - 0.8 q', identified from f_defo's path up to the handover; the hinge's
    # q is 0 at the handover's angle a, so -40 sin(q + a) = -40 cos a sin q - 40 sin a cos q
    c = entry["constants"]
    assert abs(np.hypot(c["q0'' <- sin q0"], c.get("q0'' <- cos q0", 0.0)) - 40.0) < 0.4, entry["model"]
    assert abs(entry["constants"]["q0'' <- q0'"] + 0.8) < 0.02, entry["model"]
    assert entry["residual"]["hinge"] < 1e-4 < entry["residual"]["slider"]
    assert entry["position_rms"]["law"] < 0.1 * entry["position_rms"]["learned"]
    assert torch.equal(state.joint_laws["labels"] > 0, part)
    hinge = state.joint_laws["parts"][0]
    assert abs(float(hinge["axis"] @ AXIS)) > 1 - 1e-8  # its sign: the last angle positive
    offset = hinge["pivot"] - PIVOT
    torch.testing.assert_close(
        offset - (offset @ AXIS) * AXIS, torch.zeros(3, dtype=torch.float64), atol=1e-5, rtol=0
    )

    t0 = predictor.handover_time()
    size = float(
        (model.deform(t0)["means"][part] - model.deform(t0)["means"][part].mean(0)).norm(dim=1).max()
    )
    for t in (t0 + 0.01, T_MAX, 1.0, 1.25):  # after the handover: the truth's swing
        got, want = predictor.gaussians_at(t), model.deform(t)
        error = float((got["means"][part] - want["means"][part]).norm(dim=1).max())
        assert error < 0.01 * size, (t, error, size)
        torch.testing.assert_close(got["quats"][part], want["quats"][part], atol=2e-3, rtol=0)
        torch.testing.assert_close(got["means"][~part], model.deform(t0)["means"][~part])  # still
    # without the law, the learned physics (zero here) leaves the part where the handover put it
    predictor.settings.joint_laws = False
    torch.testing.assert_close(predictor.gaussians_at(1.0)["means"], model.deform(t0)["means"])


def test_a_part_turning_steadily_keeps_the_learned_physics():
    model, settings, part = _model(steady_turn)
    predictor = calibrate(model, T_MAX, settings, extent=2.0)
    state = predictor.state
    (entry,) = state.report["joint_laws"]
    assert entry["joint"] == "hinge" and not entry["adopted"]
    assert "constant" in entry["why"]
    assert state.joint_laws is None


def test_the_joint_parts_round_trip_through_the_saved_state():
    model, settings, part = _model(damped_pendulum)
    predictor = calibrate(model, T_MAX, settings, extent=2.0)
    state = predictor.state
    buffer = io.BytesIO()
    torch.save(state.to_dict(), buffer)
    buffer.seek(0)
    again = ExtrapolationState.from_dict(torch.load(buffer, weights_only=True))
    assert again.joint_laws["parts"][0]["model"] == state.joint_laws["parts"][0]["model"]
    for t in (T_MAX, 1.2):
        assert torch.equal(
            Predictor(model, again, settings).gaussians_at(t)["means"], predictor.gaussians_at(t)["means"]
        )
    old = {k: v for k, v in state.to_dict().items() if k != "joint_laws"} | {"version": 1}
    assert ExtrapolationState.from_dict(old).joint_laws is None  # written before joint laws: none
    with pytest.raises(ValueError, match="version"):
        ExtrapolationState.from_dict({**old, "version": 99})


def test_off_nothing_changes():
    """``joint_laws = False``: calibrate looks for none, and a state that holds some renders as the
    same state without them, bit for bit."""
    model, settings, part = _model(damped_pendulum, joint_laws=False)
    predictor = calibrate(model, T_MAX, settings, extent=2.0)
    state = predictor.state
    assert state.joint_laws is None and "joint_laws" not in state.report
    predictor.settings.joint_laws = True
    with_laws = calibrate(model, T_MAX, settings, extent=2.0)
    predictor.settings.joint_laws = False
    for t in (0.3, T_MAX, 1.2):
        a, b = with_laws.gaussians_at(t), predictor.gaussians_at(t)
        assert all(torch.equal(a[k], b[k]) for k in ("means", "quats", "scales"))


def test_a_piece_on_the_same_hinge_moves_with_the_adopted_part_and_a_still_one_does_not():
    """``carried_by``: a pendulum's rod, cut from its bob, joins the bob's joint; a piece that stays
    put, or turns about another axis, joins none."""
    from tracegs.extrapolate.joints import carried_by, fit_joint

    times = np.linspace(0.0, T_MAX, 40)
    q = torch.as_tensor(damped_pendulum(times))
    gen = torch.Generator().manual_seed(4)
    bob = (
        0.05 * torch.randn(150, 3, generator=gen, dtype=torch.float64)
        + PIVOT
        + torch.tensor([0.0, -0.6, 0.0])
    )
    rod = PIVOT + torch.linspace(-0.1, -0.5, 60, dtype=torch.float64)[:, None] * torch.tensor([0.0, 1.0, 0.0])

    def swung(x, angles, axis=AXIS, pivot=PIVOT):  # positions over the frames; x at the last one
        at_end = rodrigues(-float(angles[-1]) * axis)
        start = (x - pivot) @ at_end.T + pivot
        return [(start - pivot) @ rodrigues(float(a) * axis).T + pivot for a in angles]

    bob_path = swung(bob, q)
    joint, q_bob, residuals = fit_joint(bob, bob_path)
    assert joint["joint"] == "hinge" and residuals["hinge"] < 1e-4
    part = {**joint}
    settings = make_config("tiny").extrapolation
    assert carried_by(rod, swung(rod, q), [part], [q_bob], settings) == 0
    assert carried_by(rod, [rod] * len(times), [part], [q_bob], settings) is None  # still
    other = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    assert carried_by(rod, swung(rod, q, other, PIVOT + 0.3), [part], [q_bob], settings) is None


def test_a_part_spinning_on_a_turning_part_turns_on_its_joint_in_that_parts_frame():
    """A box spinning (2.5 rad per unit t) about its own centre on a table that turns steadily (2.0)
    about the hinge: on no hinge of its own in the world, it is put on one in the table's frame and
    moves after the handover as the truth does; the table, turning steadily, keeps the learned
    physics (zero here: it stays where the handover left it), its law moving only the box."""
    centre = PIVOT + torch.tensor([0.8, 0.0, 0.0], dtype=torch.float64)

    def box(t: float):
        table, (own, own_shift) = about(2.0 * t, PIVOT), about(2.5 * t, centre)
        return table[0] @ own, table[0] @ own_shift + table[1]

    motions = [lambda t: about(2.0 * t, PIVOT), box, None]
    model, settings, (table, spinning, still) = blob_model(
        [(0.0, 0.1, 0.0), tuple(centre.tolist()), (0.0, -0.8, 0.0)], motions
    )
    predictor = calibrate(model, T_MAX, settings, extent=2.0)
    state = predictor.state
    by_rows = {e["gaussians"]: e for e in state.report["joint_laws"] if "chain" not in e}
    (chain,) = (e for e in state.report["joint_laws"] if "chain" in e)  # two steady turns: no system
    assert not chain["adopted"] and "constant" in chain["why"]
    assert len(by_rows) == 2
    disc, part = by_rows[int(table.sum())], by_rows[int(spinning.sum())]
    assert "constant" in disc["why"] and not disc["adopted"] and disc["frame_of"] == [2]
    assert part["adopted"] and part["on"] == 1 and part["joint"] == "hinge"
    assert all(term.endswith("<- 1") for term in part["constants"]), part["model"]  # a steady turn
    assert part["position_rms"]["law"] < 0.01 * part["position_rms"]["learned"]
    assert torch.equal(state.joint_laws["labels"], spinning.long() * 2)
    t0 = predictor.handover_time()
    start = model.deform(t0)["means"]
    for t in (T_MAX, 1.0, 1.25):
        got, want = predictor.gaussians_at(t), model.deform(t)
        error = float((got["means"][spinning] - want["means"][spinning]).norm(dim=1).max())
        assert error < 2e-3, (t, error)
        alike = (got["quats"][spinning] * torch.nn.functional.normalize(want["quats"][spinning], dim=1)).sum(
            1
        )
        assert float(alike.abs().min()) > 1 - 1e-5  # the same turn (q and -q are one)
        torch.testing.assert_close(got["means"][table | still], start[table | still])


CHAIN_K = np.array([[40.0, -12.0], [-30.0, 50.0]])  # two hinges whose angles drive each other
CHAIN_START = np.array([0.5, -0.2, 0.0, 0.0])


def chain_angles(t: float) -> np.ndarray:
    """[2] the carrier's angle and the link's angle relative to it: ``q'' = -K q`` in closed form."""
    from scipy.linalg import expm

    system = np.block([[np.zeros((2, 2)), np.eye(2)], [-CHAIN_K, np.zeros((2, 2))]])
    return (expm(system * t) @ CHAIN_START)[:2]


def test_a_chain_of_two_hinges_is_identified_as_one_system():
    """A link on a hinge at the end of a part on a hinge, their angles coupled (each drives the
    other): the link is put on its joint in the carrier's frame, and the two angles identified
    together; after the handover both move as the closed form does, which neither angle's model with
    the other's path unknown foresees."""
    elbow = PIVOT + torch.tensor([0.0, -0.8, 0.0], dtype=torch.float64)

    def carrier(t: float):
        return about(float(chain_angles(t)[0]), PIVOT)

    def link(t: float):
        q1, q2 = chain_angles(t)
        (r1, s1), (r2, s2) = about(float(q1), PIVOT), about(float(q2), elbow)
        return r1 @ r2, r1 @ s2 + s1

    centres = [tuple((PIVOT + torch.tensor([0.0, -0.3, 0.0], dtype=torch.float64)).tolist())]
    centres += [
        tuple((elbow + torch.tensor([0.0, -0.3, 0.0], dtype=torch.float64)).tolist()),
        (0.9, 0.9, 0.0),
    ]
    model, settings, (first, second, still) = blob_model(centres, [carrier, link, None])
    model.frame_interval.fill_(1 / 60)
    predictor = calibrate(model, T_MAX, settings, extent=2.0)
    chain = next(e for e in predictor.state.report["joint_laws"] if "chain" in e)
    assert chain["adopted"], chain["why"]
    assert chain["position_rms"]["chain"] < 0.1 * chain["position_rms"]["own"]
    parts = predictor.state.joint_laws["parts"]
    assert [p.get("coordinate") for p in parts] == [0, 1] and parts[1]["parent"] == 0
    for t in (T_MAX, 1.0, 1.25):
        got, want = predictor.gaussians_at(t)["means"], model.deform(t)["means"]
        for rows in (first, second):
            error = float((got[rows] - want[rows]).norm(dim=1).max())
            assert error < 5e-3, (t, error)
