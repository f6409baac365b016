"""The evaluation protocol of TRACE / NVFi: interpolation and extrapolation splits, and their metrics.

interpolation = held-out (val and test) frames at t <= t_train_end; extrapolation = every camera of
every split at t > t_train_end. Checkpoints and settings are never chosen on these frames.

For choosing settings there is a validation future instead: train on an earlier part of the training
span (``t_train_end`` set before the scene's), and score the training cameras' frames between that
cut and the scene's training end (``future_end``). Those frames belong to the training split, so
nothing of the test protocol is looked at.
"""

from __future__ import annotations

import json
from collections import Counter, defaultdict
from dataclasses import asdict, replace
from pathlib import Path

import torch
from tqdm import tqdm

from ..config import apply_overrides
from ..data.frames import camera_key
from ..data.scene import Frame, available_splits, load_image, load_scene
from ..extrapolate.predictor import MOTIONS
from ..run import load_run, run_data
from ..utils import atomic_write_image
from .metrics import mae_psnr, mse, psnr, ssim
from .moving import (
    MOVING_DILATION,
    MovingMasks,
    aggregate_moving,
    mask_path,
    masked_scores,
    missing_note,
    moving_per_time,
)


def split_frames(
    data: Path,
    t_train_end: float,
    downscale: int = 1,
    with_cameras: bool = False,
    future_end: float | None = None,
    horizon_end: float | None = None,
) -> dict[str, list[Frame]] | dict[str, list[tuple[str, Frame]]]:
    """Frames of the interpolation and extrapolation splits (deduplicated by image path).

    Interpolation: the held-out frames (``val`` and ``test`` splits) at t <= t_train_end, so a dataset
    without a ``val`` split (or with test frames inside the training span, as D-NeRF's) is scored on
    all of them; with ``future_end`` (the validation future) the ``val`` split alone, so that choosing
    settings never looks at a test frame. With ``future_end`` the extrapolation split is the
    validation future: frames of the train split with t_train_end < t <= future_end. With
    ``with_cameras``, ``(cameras, frame)`` pairs where ``cameras`` says whether a training camera
    took the frame ("train_cameras") or not ("new_cameras"). With ``horizon_end`` (a continual
    round's score), only the extrapolation split, up to that time."""
    chosen, seen, train_cameras = [], set(), set()  # (protocol split, cameras, split, frame)
    for split in available_splits(data):
        frames = load_scene(data, split, downscale).frames
        if split == "train":
            train_cameras = {camera_key(f) for f in frames}
        for f in frames:
            if f.image_path in seen:
                continue
            seen.add(f.image_path)
            cameras = "train_cameras" if camera_key(f) in train_cameras else "new_cameras"
            if horizon_end is not None and not t_train_end + 1e-9 < f.time <= horizon_end + 1e-9:
                continue
            if f.time > t_train_end + 1e-9:
                if future_end is None or (split == "train" and f.time <= future_end + 1e-9):
                    chosen.append(("extrapolation", cameras, split, f))
            elif split == "val" or (split == "test" and future_end is None):
                chosen.append(("interpolation", cameras, split, f))
    out = {"interpolation": [], "extrapolation": []}
    for protocol, cameras, f in _unique_names(chosen):
        out[protocol].append((cameras, f))
    return out if with_cameras else {k: [f for _, f in v] for k, v in out.items()}


def _unique_names(chosen: list[tuple[str, str, str, Frame]]) -> list[tuple[str, str, Frame]]:
    """``(protocol split, cameras, frame)``, the frames whose name another frame of their protocol split
    shares (``val/r_000`` and ``test/r_000``) renamed ``SPLIT_NAME``: one image file per frame."""
    counts = Counter((protocol, f.name) for protocol, _, _, f in chosen)
    return [
        (protocol, cameras, f if counts[protocol, f.name] == 1 else replace(f, label=f"{split}_{f.name}"))
        for protocol, cameras, split, f in chosen
    ]


def _aggregate(records: list[dict], with_lpips: bool) -> dict:
    if not records:
        return {"frames": 0}
    out = {
        "psnr": sum(r["psnr"] for r in records) / len(records),
        "mae_psnr": mae_psnr([r["mse"] for r in records]),
        "ssim": sum(r["ssim"] for r in records) / len(records),
        "frames": len(records),
    }
    if with_lpips:
        for key in ("lpips_vgg", "lpips_alex"):
            out[key] = sum(r[key] for r in records) / len(records)
    moving = aggregate_moving(records, with_lpips)
    if moving is not None:
        out["moving"] = moving
    return out


@torch.no_grad()
def evaluate_run(
    run: Path,
    data: Path | None = None,
    half_res: bool = False,
    with_lpips: bool = True,
    save_images: bool = True,
    device: str = "auto",
    future_end: float | None = None,
    render_settings: dict | None = None,
    out: Path | None = None,
    horizon_end: float | None = None,
    motion: str = "trace",
    moving_dilation: int | None = None,
) -> dict:
    """Render both splits of a trained run and score them (schema in docs/EVALUATION.md), the whole
    images and the pixels that move (``moving.py``: each frame's moving mask, dilated by
    ``moving_dilation`` pixels, default ``MOVING_DILATION``); with ``future_end``, the extrapolation
    split is the validation future (``split_frames``). ``motion``: how the run moves its Gaussians
    (``Predictor.gaussians_at``: ``trace``, ``f_defo`` or ``hold``), recorded in the result.
    ``render_settings``: ``extrapolation`` settings that change rendering without a new calibration,
    by dotted name as in ``config.apply_overrides`` (e.g. ``{"extrapolation.free_bodies": False}``).
    ``out``: the folder of the rendered images (``OUT/<split>/<frame>.png``; default ``RUN/eval``).
    ``horizon_end``: score only the future up to this time (``split_frames``).
    Ground truth the scene's ``gt/`` lacks, or holds in another layout, is skipped and said so in the
    result's ``notes``."""
    if motion not in MOTIONS:
        raise ValueError(f"motion {motion!r}: expected one of {list(MOTIONS)}")
    run = Path(run)
    out = run / "eval" if out is None else Path(out)
    loaded = load_run(run, device, data)
    predictor, cfg, meta = loaded.predictor, loaded.config, loaded.meta
    data = run_data(cfg, data)  # (a clear error when the scene is not there)
    if render_settings:
        cfg = apply_overrides(cfg, render_settings)
        predictor = predictor.with_settings(**asdict(cfg.extrapolation))
    scene = load_scene(data, "train", cfg.downscale)
    t_end = cfg.t_train_end if cfg.t_train_end is not None else scene.t_train_end
    t_end = meta["t_max"] if t_end is None else t_end
    dev = predictor.device
    result: dict = {}
    notes: list[str] = []
    names = part_names(data, notes)
    moving_dilation = MOVING_DILATION if moving_dilation is None else moving_dilation
    masks = MovingMasks(data, cfg.downscale, moving_dilation)
    splits = split_frames(data, t_end, cfg.downscale, True, future_end, horizon_end)
    progress = tqdm(
        total=sum(map(len, splits.values())), desc="eval", unit="image", disable=None, leave=False
    )
    for split, frames in splits.items():
        parts = PartErrors(names) if names and not half_res and cfg.downscale == 1 else None
        by_time: dict[float, list[tuple[str, Frame]]] = defaultdict(list)
        for cameras, f in frames:
            by_time[f.time].append((cameras, f))
        records = []
        for t in sorted(by_time):
            gaussians = predictor.gaussians_at(t, motion)
            for cameras, f in by_time[t]:
                # (a training camera in its own colours)
                pred = predictor.render(f.camera.to(dev), gaussians=gaussians, camera_id=f.camera_id)
                gt = load_image(f, scene.background).to(dev)
                moving, source = masks.mask(f)
                moving = None if moving is None else torch.as_tensor(moving, device=dev)
                if half_res:
                    pred, gt = (
                        torch.nn.functional.avg_pool2d(x.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)
                        for x in (pred, gt)
                    )
                    if moving is not None:  # a pixel of the half image moves if one of its four does
                        moving = torch.nn.functional.max_pool2d(moving[None, None].float(), 2)[0, 0] > 0
                rec = {"t": t, "cameras": cameras, **_scores(pred, gt, moving, source, with_lpips)}
                records.append(rec)
                if parts is not None:
                    parts = _add_part_errors(parts, pred, gt, mask_path(data, f), split, notes)
                if save_images:
                    atomic_write_image(out / split / f"{f.name}.png", pred)
                progress.update(1)
        summary = _aggregate(records, with_lpips)
        if "moving" in summary:
            summary["moving"]["dilation"] = moving_dilation
        if note := missing_note(split, records):
            notes.append(note)
        if split == "extrapolation":
            summary["per_time"] = _per_time(records, with_lpips)
            # training cameras (future time only) vs the others (future time and a new view)
            summary["per_cameras"] = {
                c: _aggregate([r for r in records if r["cameras"] == c], False)
                for c in dict.fromkeys(r["cameras"] for r in records)
            }
        if parts is not None and parts.pixels.sum() > 0:
            summary["per_part"] = parts.summary()
        result[split] = summary
    progress.close()
    notes += [n for n in masks.notes if n not in notes]
    if (data / "gt").is_dir() and result["extrapolation"].get("frames"):
        from .physics import ground_truth_problem, physics_errors

        problem = ground_truth_problem(data)
        if motion != "trace":
            problem = f"they measure the learned physics, and the motion scored is {motion!r}"
        if problem is None:
            future = [r["t"] for r in result["extrapolation"]["per_time"]]
            result["physics"] = physics_errors(predictor, data, future)
        else:
            notes.append(f"physics errors skipped: {problem}")
    result.update(
        method=cfg.method,
        motion=motion,
        preset=cfg.preset,
        scene=str(data),
        t_train_end=t_end,
        **({} if future_end is None else {"future_end": future_end}),
        train_seconds=meta["train_seconds"],
        iterations=meta["step"],
        freeze_threshold=predictor.state.freeze_threshold,
        gaussians=int(predictor.model.gaussians["means"].shape[0]),
        **({"images": str(out)} if save_images else {}),
        **({"notes": notes} if notes else {}),
    )
    return result


def _scores(
    pred: torch.Tensor, gt: torch.Tensor, moving: torch.Tensor | None, source: str | None, with_lpips: bool
) -> dict:
    """One frame's numbers: the whole image's, and ``moving`` (``masked_scores`` and its mask's
    ``source``; ``"none"``: no source had a mask, ``"empty"``: nothing moves in view)."""
    rec = {"mse": float(mse(pred, gt)), "psnr": float(psnr(pred, gt)), "ssim": float(ssim(pred, gt))}
    maps = None
    if with_lpips:
        from .lpips import lpips, lpips_map

        maps = {} if moving is not None and bool(moving.any()) else None
        for net in ("vgg", "alex"):
            if maps is None:
                rec[f"lpips_{net}"] = float(lpips(pred, gt, net=net))
            else:  # one pass of the backbone gives the distance and its map
                value, maps[f"lpips_{net}"] = lpips_map(pred, gt, net=net)
                rec[f"lpips_{net}"] = float(value)
    if moving is None:
        rec["moving"] = {"source": "none"}
    else:
        scores = masked_scores(pred, gt, moving, maps)
        rec["moving"] = {"source": "empty"} if scores is None else {**scores, "source": source}
    return rec


def _add_part_errors(parts, pred, gt, mask: Path, split: str, notes: list[str]):
    """``parts`` with one more frame, or None (and a note) when the scene's mask does not fit it."""
    try:
        parts.add(pred, gt, mask)
    except ValueError as err:
        notes.append(f"{split} per-part errors skipped: {err}")
        return None
    return parts


def part_names(data: Path, notes: list[str] | None = None) -> dict[int, str]:
    """Part id -> name of a generated scene (``gt/motion.json``; 0 = background), else empty. A ``gt/``
    folder that lacks the masks or the parts, or holds them in another layout, adds to ``notes``."""
    gt = Path(data) / "gt"
    path = gt / "motion.json"
    notes = [] if notes is None else notes
    missing = [name for name in ("motion.json", "masks") if not (gt / name).exists()]
    if missing:
        if gt.is_dir():
            notes.append(f"per-part errors skipped: no {' and no '.join(missing)} in {gt}")
        return {}
    try:
        parts = json.loads(path.read_text())["parts"]
        names = {int(p["id"]): str(p["name"]) for p in parts}
    except (ValueError, KeyError, TypeError) as err:
        notes.append(f"per-part errors skipped: {path}: no list of parts with 'id' and 'name' ({err!r})")
        return {}
    if any(i < 1 for i in names):
        notes.append(f"per-part errors skipped: {path}: part ids must be 1 or more (0 is the background)")
        return {}
    return {0: "background"} | names


class PartErrors:
    """Squared error summed per ground-truth part (``gt/masks``: part id per pixel), over frames.

    Says where a split's error lies: in the moving parts, the static ones or the background.
    """

    def __init__(self, names: dict[int, str]):
        self.names = names
        size = max(names) + 1
        self.error = torch.zeros(size, dtype=torch.float64)
        self.pixels = torch.zeros(size, dtype=torch.float64)

    def add(self, pred: torch.Tensor, gt: torch.Tensor, mask_path: Path) -> None:
        """Add one frame: ``pred``, ``gt`` [H, W, 3]; frames without a mask file are skipped."""
        if not mask_path.is_file():
            return
        import imageio.v3 as iio

        ids = torch.as_tensor(iio.imread(mask_path).astype("int64")).reshape(-1)
        err = ((pred - gt) ** 2).mean(dim=-1).reshape(-1).double().cpu()
        if ids.numel() != err.numel() or int(ids.max()) >= self.error.numel():
            raise ValueError(f"{mask_path}: mask does not match the image size or the parts of motion.json")
        self.error += torch.bincount(ids, weights=err, minlength=self.error.numel())
        self.pixels += torch.bincount(ids, minlength=self.error.numel()).double()

    def summary(self) -> dict[str, dict[str, float]]:
        """Per part: its share of the pixels and of the squared error, and the PSNR over its pixels."""
        out = {}
        for i, name in self.names.items():
            if self.pixels[i] == 0:
                continue
            mean = float(self.error[i] / self.pixels[i])
            out[name] = {
                "pixel_share": float(self.pixels[i] / self.pixels.sum()),
                "error_share": float(self.error[i] / self.error.sum()) if self.error.sum() > 0 else 0.0,
                "psnr": mae_psnr([mean]),
            }
        return out


def _per_time(records: list[dict], with_lpips: bool) -> list[dict]:
    groups: dict[float, list[dict]] = defaultdict(list)
    for r in records:
        groups[r["t"]].append(r)
    rows = []
    for t in sorted(groups):
        g = groups[t]
        row = {"t": t, "psnr": mae_psnr([r["mse"] for r in g]), "ssim": sum(r["ssim"] for r in g) / len(g)}
        if with_lpips:
            row["lpips_vgg"] = sum(r["lpips_vgg"] for r in g) / len(g)
        if (moving := moving_per_time(g, with_lpips)) is not None:
            row["moving"] = moving
        rows.append(row)
    return rows
