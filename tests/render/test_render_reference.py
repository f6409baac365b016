"""The reference rasteriser against a direct per-pixel float64 loop, and its gradients against
finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tracegs.render import rasterize
from tracegs.render.reference import project_gaussians


def tiny_scene(dtype=torch.float64) -> dict:
    """8 Gaussians on a 20 x 18 image (2 x 2 tiles): overlapping, straddling tile borders, one
    behind the camera, one off screen, and an opaque stack in the middle so that some pixels stop
    early (T would drop below 1e-4)."""
    g = torch.Generator().manual_seed(0)
    W, H = 20, 18
    fx, fy = 18.0, 17.0
    K = torch.tensor([[fx, 0.0, 10.3], [0.0, fy, 8.7], [0.0, 0.0, 1.0]])
    c, s = math.cos(0.3), math.sin(0.3)
    viewmat = torch.tensor([[c, 0.0, s, 0.1], [0.0, 1.0, 0.0, -0.2], [-s, 0.0, c, 0.3], [0, 0, 0, 1.0]])
    p_cam = torch.tensor(
        [
            [0.0, 0.0, 2.0],
            [0.05, -0.02, 2.5],
            [-0.03, 0.04, 3.0],
            [0.02, 0.01, 3.5],
            [-0.6, -0.5, 3.2],
            [0.5, 0.4, 2.2],
            [0.1, 0.1, -1.0],  # behind the camera
            [4.0, 0.0, 2.0],  # far off screen
        ]
    )
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    scene = dict(
        means=(p_cam - t) @ R,
        quats=torch.randn(8, 4, generator=g),
        scales=torch.tensor(
            [[0.3, 0.2, 0.25]] * 4 + [[0.15, 0.25, 0.1], [0.2, 0.1, 0.3], [0.2] * 3, [0.1] * 3]
        ),
        opacities=torch.tensor([1.0, 0.97, 0.97, 0.97, 0.6, 0.8, 0.9, 0.9]),
        colors=torch.rand(8, 3, generator=g),
        viewmat=viewmat,
        K=K,
    )
    scene = {k: v.to(dtype) for k, v in scene.items()}
    scene.update(width=W, height=H)
    return scene


def naive_render(scene: dict, background, early_stop: bool = True, eps2d: float = 0.3):
    """Direct float64 transcription of gsplat's classic pipeline: no tiles, no vectorisation."""
    sc = {k: (v.detach().double().numpy() if torch.is_tensor(v) else v) for k, v in scene.items()}
    W, H = sc["width"], sc["height"]
    Rc, tc = sc["viewmat"][:3, :3], sc["viewmat"][:3, 3]
    fx, fy, cx, cy = sc["K"][0, 0], sc["K"][1, 1], sc["K"][0, 2], sc["K"][1, 2]
    splats = []
    for i in range(len(sc["means"])):
        x, y, z = Rc @ sc["means"][i] + tc
        if not 0.01 <= z <= 1e10:
            continue
        w_, qx, qy, qz = sc["quats"][i] / np.linalg.norm(sc["quats"][i])
        Rq = np.array(
            [
                [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - w_ * qz), 2 * (qx * qz + w_ * qy)],
                [2 * (qx * qy + w_ * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - w_ * qx)],
                [2 * (qx * qz - w_ * qy), 2 * (qy * qz + w_ * qx), 1 - 2 * (qx * qx + qy * qy)],
            ]
        )
        cov3 = Rc @ Rq @ np.diag(sc["scales"][i] ** 2) @ Rq.T @ Rc.T
        lim_x = (W - cx) / fx + 0.3 * 0.5 * W / fx, cx / fx + 0.3 * 0.5 * W / fx
        lim_y = (H - cy) / fy + 0.3 * 0.5 * H / fy, cy / fy + 0.3 * 0.5 * H / fy
        tx = z * min(lim_x[0], max(-lim_x[1], x / z))
        ty = z * min(lim_y[0], max(-lim_y[1], y / z))
        J = np.array([[fx / z, 0, -fx * tx / z**2], [0, fy / z, -fy * ty / z**2]])
        cov2 = J @ cov3 @ J.T + eps2d * np.eye(2)
        det = np.linalg.det(cov2)
        mean2 = np.array([fx * x / z + cx, fy * y / z + cy])
        half = 0.5 * (cov2[0, 0] + cov2[1, 1])
        radius = math.ceil(3 * math.sqrt(half + math.sqrt(max(0.01, half * half - det))))
        if det <= 0 or mean2[0] + radius <= 0 or mean2[0] - radius >= W:
            continue
        if mean2[1] + radius <= 0 or mean2[1] - radius >= H:
            continue
        splats.append((z, i, mean2, np.linalg.inv(cov2)))
    splats.sort(key=lambda s: (s[0], s[1]))

    image, alpha, depth = np.zeros((H, W, 3)), np.zeros((H, W, 1)), np.zeros((H, W, 1))
    stopped = 0
    for r in range(H):
        for c in range(W):
            pix = np.array([c + 0.5, r + 0.5])
            T, col, dep = 1.0, np.zeros(3), 0.0
            for z, i, mean2, conic in splats:
                d = mean2 - pix
                sigma = 0.5 * d @ conic @ d
                a = min(0.99, sc["opacities"][i] * math.exp(-sigma))
                if sigma < 0 or a < 1 / 255:
                    continue
                if early_stop and T * (1 - a) <= 1e-4:
                    stopped += 1
                    break
                col += a * T * sc["colors"][i]
                dep += a * T * z
                T *= 1 - a
            image[r, c] = col + T * background
            alpha[r, c] = 1 - T
            depth[r, c] = dep / max(1 - T, 1e-10)
    return image, alpha, depth, stopped


def test_reference_matches_naive_float64_loop():
    scene = tiny_scene()
    bg = np.array([0.1, 0.2, 0.3])
    out = rasterize(**scene, backend="reference", background=torch.tensor(bg))
    image, alpha, depth, stopped = naive_render(scene, bg)
    assert stopped > 0, "the scene must exercise early termination"
    np.testing.assert_allclose(out.image.numpy(), image, atol=1e-10)
    np.testing.assert_allclose(out.alpha.numpy(), alpha, atol=1e-10)
    np.testing.assert_allclose(out.depth.numpy(), depth, atol=1e-9)
    # early termination is visible in the output (so the check above can fail if it is skipped)
    image_no_stop, *_ = naive_render(scene, bg, early_stop=False)
    assert np.abs(image_no_stop - image).max() > 1e-6


def test_projection_culling_and_means2d():
    scene = tiny_scene()
    proj = project_gaussians(**{k: scene[k] for k in ("means", "quats", "scales", "opacities", "viewmat", "K")},
                             width=scene["width"], height=scene["height"])  # fmt: skip
    radii = proj.radii.tolist()
    assert radii[6] == 0 and radii[7] == 0  # behind the camera, off screen
    assert all(r > 0 for r in radii[:6])
    pc = scene["means"] @ scene["viewmat"][:3, :3].T + scene["viewmat"][:3, 3]
    K = scene["K"]
    expect = torch.stack(
        [K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]], -1
    )
    torch.testing.assert_close(proj.means2d[:6], expect[:6])


def test_reference_gradients_match_finite_differences():
    scene = tiny_scene()
    # Away from the alpha clamp and the early stop, so that finite differences see a smooth function.
    scene["opacities"] = scene["opacities"] * 0.6
    names = ("means", "quats", "scales", "opacities", "colors")
    rest = {k: v for k, v in scene.items() if k not in names}
    bg = torch.tensor([0.3, 0.1, 0.2], dtype=torch.float64)

    def fn(*params):
        out = rasterize(**dict(zip(names, params, strict=True)), **rest, backend="reference", background=bg)
        return out.image, out.alpha, out.depth

    inputs = tuple(scene[k].clone().requires_grad_(True) for k in names)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_reference_means2d_grad_is_screen_space_gradient(dtype):
    scene = tiny_scene(dtype)
    means = scene.pop("means").requires_grad_(True)
    out = rasterize(means, **scene, backend="reference")
    out.image[..., 0].sum().backward()
    g = out.means2d.grad
    assert g is not None and g.shape == (8, 2)
    assert g[:6].abs().sum() > 0 and torch.all(g[6:] == 0)
