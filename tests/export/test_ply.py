"""PLY: points read back as written; Gaussians written in the 3DGS layout; initial points used."""

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from tracegs.data.points import read_points
from tracegs.export.ply import write_gaussians
from tracegs.models.gaussians import create_gaussians


def test_read_points_and_errors(tmp_path):
    v = np.array(
        [(1.0, 2.0, 3.0, 255, 0, 0), (0.0, -1.0, 0.5, 0, 128, 255)],
        dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "p.ply"))
    xyz, rgb = read_points(tmp_path / "p.ply")
    assert torch.allclose(xyz, torch.tensor([[1.0, 2, 3], [0, -1, 0.5]]))
    assert torch.allclose(rgb[1], torch.tensor([0, 128 / 255, 1.0]))
    (tmp_path / "bad.ply").write_text("nonsense")
    with pytest.raises(ValueError, match="bad.ply"):
        read_points(tmp_path / "bad.ply")


def test_write_gaussians_layout(tmp_path):
    params = create_gaussians(
        torch.randn(5, 3), torch.rand(5, 3), sh_degree=2, init_scale=torch.full((5,), 0.1)
    )
    path = write_gaussians(dict(params), tmp_path / "g.ply")
    v = PlyData.read(str(path))["vertex"]
    assert len(v) == 5 and "f_rest_23" in v.data.dtype.names and "rot_3" in v.data.dtype.names
    assert np.allclose(v["x"], params["means"][:, 0].detach().numpy())
