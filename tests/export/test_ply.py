"""PLY: points read back as written; Gaussians written in the layout of the original 3DGS code (header,
property order, channel-major f_rest) and read back bit for bit; clear errors for other PLYs."""

import numpy as np
import numpy.lib.recfunctions as rfn
import pytest
import torch
from plyfile import PlyData, PlyElement

from tracegs.data.points import read_points
from tracegs.export.ply import read_gaussians, write_gaussians


def random_params(n: int, degree: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Gaussians with every parameter random (unnormalised quaternions, non-zero higher SH)."""
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return {
        "means": torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 3,
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, k - 1, 3, generator=g),
    }


def write_subset(vertices: np.ndarray, keep: list[str], path):
    """A PLY of ``vertices`` with only the properties ``keep``."""
    PlyData([PlyElement.describe(rfn.repack_fields(vertices[keep]), "vertex")]).write(str(path))


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


def test_the_header_is_the_3dgs_one(tmp_path):
    path = write_gaussians(random_params(5, degree=3), tmp_path / "g.ply")
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n")].decode().splitlines()
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 5"]
    expected = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(45)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    assert header[3:] == [f"property float {name}" for name in expected]
    body = raw[raw.index(b"end_header\n") + len(b"end_header\n") :]
    assert len(body) == 5 * len(expected) * 4  # float32, nothing else
    v = PlyData.read(str(path))["vertex"]
    assert all(np.all(v[n] == 0) for n in ("nx", "ny", "nz"))


def test_f_rest_is_channel_major_as_inria_writes_it(tmp_path):
    n, rest = 4, 8  # degree 2: 8 higher coefficients per channel
    shn = torch.zeros(n, rest, 3)
    for i in range(n):
        for k in range(rest):
            for c in range(3):
                shn[i, k, c] = 1000 * i + 10 * k + c
    params = random_params(n, degree=2) | {"shN": shn}
    v = PlyData.read(str(write_gaussians(params, tmp_path / "g.ply")))["vertex"]
    for c in range(3):
        for k in range(rest):
            assert np.array_equal(v[f"f_rest_{c * rest + k}"], 1000 * np.arange(n) + 10 * k + c)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_gaussians_read_back_bit_for_bit(tmp_path, degree):
    params = random_params(7, degree)
    back = read_gaussians(write_gaussians(params, tmp_path / "g.ply"))
    assert set(back) == set(params)
    for name, value in params.items():
        assert back[name].dtype == torch.float32 and back[name].shape == value.shape, name
        assert torch.equal(back[name], value), name
    v = PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    assert np.array_equal(v["rot_0"], params["quats"][:, 0].numpy())  # w first
    assert np.array_equal(v["opacity"], params["opacities"].numpy())  # the logit as stored
    assert np.array_equal(v["scale_2"], params["scales"][:, 2].numpy())  # the log as stored


def test_a_ply_without_normals_is_read(tmp_path):
    params = random_params(3, degree=0)
    v = PlyData.read(str(write_gaussians(params, tmp_path / "g.ply")))["vertex"].data
    keep = [n for n in v.dtype.names if n not in ("nx", "ny", "nz")]
    write_subset(v, keep, tmp_path / "bare.ply")
    assert torch.equal(read_gaussians(tmp_path / "bare.ply")["means"], params["means"])


def test_other_plys_are_refused_naming_the_file(tmp_path):
    v = PlyData.read(str(write_gaussians(random_params(3, degree=1), tmp_path / "g.ply")))["vertex"].data
    cases = {
        "no_opacity.ply": [n for n in v.dtype.names if n != "opacity"],
        "no_rot.ply": [n for n in v.dtype.names if not n.startswith("rot_")],
        "odd_rest.ply": [n for n in v.dtype.names if n != "f_rest_8"],
    }
    messages = {"no_opacity.ply": "no opacity", "no_rot.ply": "no rot_0, rot_1", "odd_rest.ply": "f_rest"}
    for name, keep in cases.items():
        write_subset(v, keep, tmp_path / name)
        with pytest.raises(ValueError, match=messages[name]) as err:
            read_gaussians(tmp_path / name)
        assert name in str(err.value) and "\n" not in str(err.value)
    (tmp_path / "text.ply").write_text("not a ply")
    with pytest.raises(ValueError, match="text.ply: cannot read"):
        read_gaussians(tmp_path / "text.ply")
    faces = np.zeros(2, dtype=[("x", "f4")])
    PlyData([PlyElement.describe(faces, "face")]).write(str(tmp_path / "faces.ply"))
    with pytest.raises(ValueError, match="faces.ply: not a 3DGS PLY"):
        read_gaussians(tmp_path / "faces.ply")
