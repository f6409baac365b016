"""Shared fixtures: tiny scenes in the Blender/D-NeRF format, generated on the fly."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

# Trainings in the tests keep torch's thread count (train/threads.py keeps a count set this way), so
# that runs compared bit for bit never differ by what else the machine runs meanwhile.
os.environ.setdefault("OMP_NUM_THREADS", str(torch.get_num_threads()))


def write_tiny_scene(
    root: Path, n_cams: int = 4, n_times: int = 4, size: int = 24, t_train_end: float = 0.75
) -> Path:
    """A disc moving across a textured square, seen by ``n_cams`` cameras on a circle; RGBA PNGs.

    Train = all but the last camera at t <= t_train_end; val = the last camera at those times;
    test = every camera after t_train_end. Images are synthetic patterns (not renders of a 3D
    scene): enough for the parser, the data pipeline and smoke training.
    """
    root.mkdir(parents=True, exist_ok=True)
    fov = 0.7
    times = [k / (n_times - 1) for k in range(n_times)]
    splits = {"train": [], "val": [], "test": []}
    yy, xx = np.mgrid[0:size, 0:size] / size
    for c in range(n_cams):
        az = 2 * math.pi * c / n_cams
        eye = np.array([3 * math.cos(az), 3 * math.sin(az), 1.5])
        fwd = -eye / np.linalg.norm(eye)
        right = np.cross(fwd, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -fwd, eye  # OpenGL axes
        for k, t in enumerate(times):
            split = "test" if t > t_train_end else ("val" if c == n_cams - 1 else "train")
            rgba = np.zeros((size, size, 4), np.uint8)
            disc = (xx - 0.3 - 0.4 * t) ** 2 + (yy - 0.5) ** 2 < 0.04
            board = (np.floor(xx * 6) + np.floor(yy * 6)) % 2
            rgba[..., 0] = 200 * disc + 40 * board
            rgba[..., 1] = 80 + 100 * board
            rgba[..., 2] = 60 + 30 * c
            rgba[..., 3] = np.where((xx > 0.15) & (xx < 0.85) & (yy > 0.15) & (yy < 0.85) | disc, 255, 0)
            rel = f"{split}/c{c}_f{k}.png"
            (root / split).mkdir(exist_ok=True)
            iio.imwrite(root / rel, rgba)
            splits[split].append(
                {"file_path": rel, "time": t, "camera_id": c, "transform_matrix": c2w.tolist()}
            )
    for split, frames in splits.items():
        meta = {"camera_angle_x": fov, "frames": frames, "fps": n_times - 1, "t_train_end": t_train_end}
        (root / f"transforms_{split}.json").write_text(json.dumps(meta))
    return root


def randomised_model(cfg, n: int = 400):
    """A TraceModel whose fields move the Gaussians: every field parameter drawn at random (the heads
    are zero-initialised, which would make comparisons of motion trivial). Gaussians in +/- 1."""
    import torch

    from tracegs.models.gaussians import random_gaussians
    from tracegs.models.trace import TraceModel

    torch.manual_seed(0)
    aabb = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    gaussians = random_gaussians(n, aabb, cfg.sh_degree)
    model = TraceModel(cfg.model_config(), gaussians, aabb, frame_interval=0.05)
    with torch.no_grad():
        for p in model.field_parameters():
            p.copy_(0.05 * torch.randn_like(p))
    return model.eval()


@pytest.fixture
def tiny_scene(tmp_path) -> Path:
    return write_tiny_scene(tmp_path / "scene")


def about(angle: float, pivot: torch.Tensor, axis=None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R, T)``: the turn by ``angle`` about the line through ``pivot`` along ``axis`` (default: the
    joint tests' ``AXIS``)."""
    from tracegs.physics.so3 import rodrigues

    if axis is None:
        axis = torch.nn.functional.normalize(torch.tensor([0.2, 0.1, 1.0], dtype=torch.float64), dim=0)
    turn = rodrigues(angle * axis)
    return turn, pivot - turn @ pivot


def blob_model(centres: list[tuple], motions: list, joint_laws: bool = True):
    """A model of blobs of Gaussians about ``centres`` (their means), one per entry, whose f_defo moves blob ``i`` by
    the rigid transform ``motions[i](t)`` ``(R, T)`` (None: still); f_trd is zero (its physics holds
    everything where the handover leaves it). Returns the model, its extrapolation settings and each
    blob's rows."""
    from tracegs.config import make_config
    from tracegs.physics.so3 import quat_multiply, rotmat_to_quat

    cfg = make_config("tiny", device="cpu")
    dyn = cfg.extrapolation
    dyn.hold_unseen = dyn.freeze_static = dyn.free_bodies = False
    dyn.joint_laws = joint_laws
    model = randomised_model(cfg)
    with torch.no_grad():
        for p in model.dynamics.parameters():
            p.zero_()
    g = model.gaussians
    n = g["means"].shape[0]
    blob = torch.arange(n) * len(centres) // n
    rows = [blob == i for i in range(len(centres))]
    noise = 0.08 * torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
    for part in rows:  # each blob's mean on its centre
        noise[part] -= noise[part].mean(0)
    with torch.no_grad():
        g["means"].copy_(noise + torch.tensor(centres)[blob])

    def deform(t: float) -> dict[str, torch.Tensor]:
        means, quats = g["means"].detach().double().clone(), g["quats"].detach().clone()
        for part, motion in zip(rows, motions, strict=True):
            if motion is not None:
                turn, shift = motion(t)
                means[part] = means[part] @ turn.T + shift
                q = rotmat_to_quat(turn).float()[None].expand(int(part.sum()), 4)
                quats[part] = quat_multiply(q, quats[part])
        return {"means": means.float(), "quats": quats, "scales": g["scales"].detach()}

    model.deform = deform  # f_defo, the truth: exact
    return model, dyn, rows
