"""The extrapolation state of a trained model, chosen on the training images only (never on the
evaluation splits), once, when training ends (or by ``tracegs calibrate``).

``unseen_gaussians``: the Gaussians that no training camera sees over the last frames before the
handover. Training shapes f_trd only through rendered images, so there its velocities are whatever the
field's smoothness gives; ``extrapolation.hold_unseen`` keeps them where they are.

``choose_freeze_threshold``: Gaussians that never move during training may be frozen when
extrapolating (the paper's supplementary material); without it, f_trd's smoothness across an object's boundary lets a static part
creep along with its moving neighbour. Below which displacement a Gaussian counts as static depends on
the scene's scale and on how noisy f_defo is, so the threshold is chosen per run by a
pseudo-extrapolation on the training data: start the physics ``horizon`` frames before the last
training time, integrate to the last few training times, and score the training cameras there.

``choose_free_bodies`` (``free_bodies.py``): the rigid parts in flight that move as free bodies.
``choose_joint_laws`` (``joints.py``): the parts whose coordinates follow an identified model that
the learned physics does not (a hinge, a rail, a chain of them, a part on no joint).
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..data.cameras import scene_extent_from_cameras
from ..data.dataset import ViewDataset
from ..data.scene import load_image
from ..image_metrics import mae_psnr, mse
from ..render.sh import SH_C0
from .free_bodies import choose_free_bodies
from .joints import choose_joint_laws
from .predictor import Predictor
from .settings import ExtrapolationConfig
from .state import ExtrapolationState
from .views import training_frames_by_time


def unseen_gaussians(
    model, data: Path, downscale: int, t_max: float, frames: int = 9, min_weight: float = 0.5
) -> torch.Tensor:
    """[N] bool: the Gaussians that no training image at the last ``frames`` training times up to
    ``t_max`` shows (f_defo's state at each; the handover lies 4 frames before t_max).

    A Gaussian shows in an image by its blending weight ``sum_pixels alpha T``, read as the gradient
    of the image's sum with respect to its colour (the degree-0 SH coefficient, whose colour factor is
    ``SH_C0``): it must reach ``min_weight`` (half a pixel of full contribution) in some image, so
    that a Gaussian under a surface whose footprint peeks out by a faint fringe counts as unseen.
    """
    scene, by_time = training_frames_by_time(data, downscale, t_max)
    sh0 = model.gaussians["sh0"]
    background = torch.tensor(scene.background, device=sh0.device)
    seen = torch.zeros(sh0.shape[0], dtype=torch.bool, device=sh0.device)
    for t in list(by_time)[-frames:]:
        with torch.no_grad():
            state = model.deform(t)
        for f in by_time[t]:
            with torch.enable_grad():  # also when called under no_grad (evaluation)
                image = model.render(state, f.camera.to(sh0.device), model.sh_degree, background).image
                (grad,) = torch.autograd.grad(image.sum(), sh0)
            seen |= grad.reshape(sh0.shape[0], -1).sum(-1) / (3 * SH_C0) >= min_weight
    return ~seen


# Candidate thresholds as fractions of the scene extent (3DGS's camera radius); 0 = freeze nothing.
FREEZE_FRACTIONS = (0.0, 0.001, 0.002, 0.005, 0.01, 0.02)


@torch.no_grad()
def choose_freeze_threshold(
    predictor: Predictor,
    data: Path,
    downscale: int,
    t_max: float,
    extent: float,
    horizon_frames: int = 16,
    target_times: int = 3,
) -> tuple[float, dict[float, float]]:
    """The threshold (scene units) with the best PSNR of the training cameras at the last
    ``target_times`` training times, extrapolated from ``horizon_frames`` frames before t_max.

    Returns ``(threshold, {threshold: psnr})``; ties go to the smaller threshold. Models without both
    fields (DefGS, static, "no f_defo") return 0. ``predictor``: the trained model with the state
    chosen so far (the Gaussians no camera saw).
    """
    model = predictor.model
    if model.dynamics is None or model.deformation is None:
        return 0.0, {}
    scene, by_time = training_frames_by_time(data, downscale, t_max)
    times = list(by_time)
    if len(times) < 4:
        return 0.0, {}
    horizon = max(2, min(horizon_frames, len(times) // 3))
    start = times[-1 - horizon]
    targets = times[-target_times:]
    dev = model.aabb.device
    background = torch.tensor(scene.background, device=dev)
    images = {
        t: [(f.camera.to(dev), load_image(f, scene.background).to(dev)) for f in by_time[t]] for t in targets
    }
    sh_degree = model.sh_degree
    displacement = model.max_displacement(start)
    scores: dict[float, float] = {}
    for fraction in FREEZE_FRACTIONS:
        threshold = fraction * extent
        moving = (
            displacement > threshold if threshold > 0 else torch.ones_like(displacement, dtype=torch.bool)
        )
        errors = []
        for t in targets:
            gaussians = predictor.physics_from(start, t, moving=moving)
            for camera, gt in images[t]:
                pred = model.render(gaussians, camera, sh_degree, background).image.clamp(0, 1)
                errors.append(float(mse(pred, gt)))
        scores[threshold] = mae_psnr(errors)
    best = max(scores, key=lambda k: (round(scores[k], 2), -k))
    return best, scores


def has_policy(model) -> bool:
    """Whether the model has an extrapolation state to choose: TRACE with both fields (DefGS, static
    3DGS and the ablation "no f_defo" extrapolate without one)."""
    return model.dynamics is not None and model.deformation is not None


def calibrate(
    model,
    t_max: float,
    settings: ExtrapolationConfig,
    data: Path | None = None,
    downscale: int = 1,
    extent: float | None = None,
    background: torch.Tensor | None = None,
) -> Predictor:
    """The trained ``model`` whose training span ends at ``t_max``, with the extrapolation state chosen
    on its training images in ``data`` (at ``downscale``; None where no choice reads them) as ``settings``
    ask: the Gaussians no camera
    sees before the handover, the freeze threshold, the free bodies, then the joint parts.
    ``extent``: the scene extent of the training cameras, found from the scene when None;
    ``background``: the returned predictor's render background."""
    state = ExtrapolationState(t_max=t_max)
    predictor = Predictor(model, state, settings, background)
    if not has_policy(model):
        return predictor
    if settings.hold_unseen:
        state.unseen = unseen_gaussians(model, data, downscale, t_max)
    if extent is None and (settings.freeze_static or settings.free_bodies or settings.joint_laws):
        dev = model.aabb.device
        centers = ViewDataset(data, "train", downscale, t_max=t_max, device=dev).camera_centers()
        extent = scene_extent_from_cameras(centers)
    if settings.freeze_static:
        state.freeze_threshold, scores = choose_freeze_threshold(predictor, data, downscale, t_max, extent)
        state.report["freeze_psnr"] = {f"{k:.6g}": round(v, 3) for k, v in scores.items()}
    if settings.free_bodies:
        state.free_bodies, state.report["free_bodies"] = choose_free_bodies(
            predictor, data, downscale, extent
        )
    if settings.joint_laws:
        state.joint_laws, state.report["joint_laws"] = choose_joint_laws(predictor, extent)
    return predictor
