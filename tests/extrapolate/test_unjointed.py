"""Parts on no joint: a disc that f_defo moves in a plane as two coupled damped springs while it
spins (on no hinge, no rail, no floor) gets the identified model of its centre, and after the handover
moves on as the closed form does; a part sliding at a steady velocity keeps the learned physics."""

import numpy as np
import torch
from scipy.linalg import expm
from tests.conftest import blob_model

from tracegs.extrapolate import calibrate
from tracegs.physics.so3 import rodrigues

T_MAX = 0.75
CENTRE = torch.tensor([0.1, 0.1, 0.0], dtype=torch.float64)
STIFFNESS = np.array([[30.0, 8.0], [8.0, 45.0]])  # coupled springs in x and y
DAMPING = 0.4
START = np.array([0.12, -0.08, 0.0, 0.5])  # x, y, x', y' at t = 0
SPIN = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)


def springs(t: float) -> np.ndarray:
    """[2] the centre's offset in the plane at ``t``: ``x'' = -K x - c x'`` in closed form."""
    system = np.block([[np.zeros((2, 2)), np.eye(2)], [-STIFFNESS, -DAMPING * np.eye(2)]])
    return (expm(system * t) @ START)[:2]


def disc(t: float) -> tuple[torch.Tensor, torch.Tensor]:
    offset = torch.tensor([*springs(t), 0.0], dtype=torch.float64)
    turn = rodrigues(SPIN * t)
    return turn, CENTRE + offset - turn @ CENTRE


def sliding(t: float) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.eye(3, dtype=torch.float64), torch.tensor([0.4 * t, 0.1 * t, 0.0], dtype=torch.float64)


def _calibrated(motion):
    model, settings, (part, still) = blob_model([tuple(CENTRE.tolist()), (0.0, -0.9, 0.0)], [motion, None])
    model.frame_interval.fill_(1 / 60)
    return model, calibrate(model, T_MAX, settings, extent=2.0), part, still


def test_a_disc_on_coupled_springs_moves_on_as_its_closed_form():
    model, predictor, part, still = _calibrated(disc)
    entry = next(e for e in predictor.state.report["joint_laws"] if e.get("joint") == "free")
    assert entry["adopted"], entry["why"]
    # its coordinates lie along the plane's principal directions: the identified stiffness matrix is
    # the truth's turned into them (the same eigenvalues), the damping the same on both
    c = entry["constants"]
    stiffness = -np.array([[c.get(f"q{i}'' <- q{j}", 0.0) for j in range(2)] for i in range(2)])
    np.testing.assert_allclose(np.linalg.eigvalsh(stiffness), np.linalg.eigvalsh(STIFFNESS), rtol=0.01)
    basis = predictor.state.joint_laws["parts"][0]["basis"].numpy()
    np.testing.assert_allclose(basis[:, :2].T @ stiffness @ basis[:, :2], STIFFNESS, atol=0.3)
    for i in range(2):
        assert abs(c.get(f"q{i}'' <- q{i}'", 0.0) + DAMPING) < 0.02, entry["model"]
    start = model.deform(predictor.handover_time())["means"]
    for t in (T_MAX, 1.0, 1.25):
        got, want = predictor.gaussians_at(t)["means"], model.deform(t)["means"]
        error = float((got[part] - want[part]).norm(dim=1).max())
        assert error < 5e-3, (t, error)
        torch.testing.assert_close(got[still], start[still])


def test_a_part_sliding_steadily_keeps_the_learned_physics():
    model, predictor, part, _ = _calibrated(sliding)
    assert predictor.state.joint_laws is None
    entry = next(e for e in predictor.state.report["joint_laws"] if e.get("gaussians") == int(part.sum()))
    assert not entry["adopted"]
