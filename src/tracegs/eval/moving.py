"""Metrics where things move: which pixels of a frame move, and PSNR / SSIM / LPIPS over them.

Most pixels of a dynamic scene never move, so the whole-image numbers are mostly those of the still
background. Each scored frame gets a mask of its moving pixels from the first of these sources that
has one for it:

1. ``parts``: a generated scene's ground-truth part ids (``gt/masks/SPLIT/NAME``, what ``tracegs
   synth`` writes) at the pixels of its moving parts, those whose ``type`` in ``gt/motion.json`` is
   not ``static``;
2. ``foreground``: the capture's own foreground mask of the frame (``data/masks.py``: Panoptic's
   ``seg/``, a Blender-layout scene's ``masks/``);
3. ``derived``: the motion mask derived from the capture itself (``tracegs.data.motion_masks``: what
   differs from a static camera's background plate, its per-pixel temporal median).

Every mask is dilated by ``MOVING_DILATION`` pixels. A frame that no source gives a mask is left out
of the moving-region numbers and counted (the result's notes say so); it is never scored as if all
of it moved. A frame whose mask is empty (nothing moving in its view) is counted apart.

Definitions over the mask M of a frame (``masked_scores``):

* PSNR: ``-10 log10`` of the mean squared error over M's pixels, all three channels;
* SSIM: the SSIM map (``ssim_map``, the window of ``image_metrics.ssim``) averaged over M's pixels where
  the map is defined (the whole window inside the image, as the whole-image SSIM);
* LPIPS: the spatial LPIPS map (``lpips.lpips_map``: each layer's distances upsampled to the image and
  summed, the official ``spatial=True``) averaged over M. It comes out of the same pass as the
  whole-image LPIPS, so it costs nothing more, and unlike a crop around M it is defined for a mask of
  any size (the VGG backbone refuses crops under 16 pixels, as small as a far ball's).

A split's numbers aggregate the frames as the whole-image ones do (``protocol._aggregate``): ``psnr`` is
the mean of per-frame masked PSNRs, ``mae_psnr`` the PSNR of the mean per-frame masked MSE (each frame
weighs the same, however many pixels move in it), ``ssim`` and LPIPS the means over frames.
"""

# H/W: image height/width

from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from ..data.frames import DatasetError, Frame
from ..data.masks import foreground_path, read_id_mask
from ..data.motion_masks import MotionMasks, MotionMaskSettings
from .metrics import SSIM_WINDOW, mae_psnr, ssim_map

MOVING_DILATION = 3
"""Pixels by which every moving mask grows (each pixel within this many pixels of a masked one, a
(2r+1)-square, at the frame's resolution). The edge pixels of a moving part blend it with what lies
behind it (antialiasing, motion blur: one or two pixels) and a part predicted a pixel or two off
shows its error on both sides of its true outline; both belong to the moving region. Three pixels
take them in and stay small beside what moves: a ball of 12 pixels across grows to 18, still
less than half of its mask."""

SOURCES = ("parts", "foreground", "derived")
"""The sources of a frame's moving mask, in the order they are tried."""


def mask_path(data: Path, f: Frame) -> Path:
    """Where ``tracegs synth`` keeps the part-id mask of a frame's image (``gt/masks/SPLIT/NAME``)."""
    return Path(data) / "gt" / "masks" / f.image_path.parent.name / f.image_path.name


def moving_part_ids(motion_json: Path) -> set[int]:
    """The ids of the parts of ``gt/motion.json`` that move: every part whose ``type`` is not
    ``static`` (``tracegs synth`` labels the parts that never move so). DatasetError naming the file
    when it holds no list of parts with ids."""
    return _part_ids(motion_json)[0]


def _part_ids(motion_json: Path) -> tuple[set[int], set[int]]:
    """(the moving parts' ids, every part's id) of ``gt/motion.json`` (``moving_part_ids``)."""
    try:
        parts = json.loads(Path(motion_json).read_text())["parts"]
        moving = {int(p["id"]) for p in parts if p.get("type", "static") != "static"}
        return moving, {int(p["id"]) for p in parts}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        raise DatasetError(f"{motion_json}: no list of parts with 'id' and 'type' ({err!r})") from None


def derived_masks(data: Path, split: str, downscale: int = 1) -> MotionMasks:
    """The motion masks derived from the images of the scene's ``split`` (``MotionMasks``, whose
    ``mask(frame)`` is an [H, W] bool, or None for a camera with too few frames), not yet dilated
    (``MovingMasks`` dilates every source alike). Raises ``DatasetError`` when the split's cameras
    move (no background plate to compare with)."""
    return MotionMasks.of_split(data, split, downscale, MotionMaskSettings(dilate=0))


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """[H, W] bool ``mask`` grown by ``radius`` pixels (a (2 radius + 1)-square around each pixel)."""
    if radius <= 0:
        return np.asarray(mask, dtype=bool)
    m = torch.as_tensor(np.asarray(mask, dtype=np.float32))[None, None]
    grown = torch.nn.functional.max_pool2d(m, 2 * radius + 1, stride=1, padding=radius)
    return grown[0, 0].numpy() > 0


class MovingMasks:
    """The moving mask of each frame of the scene folder ``data`` (``mask``), from the first source
    (``SOURCES``) that has one, dilated by ``dilation`` pixels; ``notes`` gathers what was not used."""

    def __init__(self, data: Path, downscale: int = 1, dilation: int = MOVING_DILATION):
        if dilation < 0:
            raise ValueError(f"moving-mask dilation {dilation}: must be 0 or more pixels")
        self.data, self.downscale, self.dilation = Path(data), downscale, dilation
        self.notes: list[str] = []
        self._moving_parts, self._known_parts = self._read_parts()
        self._split_of: dict[Path, str] | None = None  # image -> the dataset split that holds it
        self._derived_of: dict[str, object] = {}  # dataset split -> its derived masks (or None)

    def _read_parts(self) -> tuple[set[int] | None, set[int]]:
        """(the moving parts' ids, every id a mask may hold) of ``gt/``; (None, ...) when the scene
        has no ground-truth masks that say which parts move."""
        gt = self.data / "gt"
        if not (gt / "masks").is_dir():
            return None, set()
        try:
            moving, parts = _part_ids(gt / "motion.json")
            known = {0} | parts
        except DatasetError as err:
            self.notes.append(f"moving masks: {gt / 'masks'} not used: {err}")
            return None, set()
        return moving, known

    def mask(self, frame: Frame) -> tuple[np.ndarray | None, str | None]:
        """([H, W] bool moving pixels of ``frame``, dilated, and the source's name), or (None, None)
        when no source has a mask for it. DatasetError naming the mask file when a mask does not fit
        its image (size, ids) or a split's ground-truth masks lack this frame's."""
        for source in SOURCES:
            mask = getattr(self, f"_{source}")(frame)
            if mask is not None:
                if mask.shape != (frame.height, frame.width):
                    raise DatasetError(
                        f"{source} mask of {frame.image_path}: {mask.shape[1]}x{mask.shape[0]} for an "
                        f"image of {frame.width}x{frame.height}"
                    )
                return dilate(mask, self.dilation), source
        return None, None

    def _parts(self, frame: Frame) -> np.ndarray | None:
        if self._moving_parts is None:
            return None
        path = mask_path(self.data, frame)
        if not path.parent.is_dir():
            return None
        if not path.is_file():
            count = sum(1 for _ in path.parent.glob("*.png"))
            raise DatasetError(f"{path}: missing ({count} masks in its folder, none for {frame.image_path})")
        ids = read_id_mask(path, frame.height, frame.width)
        unknown = set(np.unique(ids).tolist()) - self._known_parts
        if unknown:
            motion = self.data / "gt" / "motion.json"
            raise DatasetError(f"{path}: part ids {sorted(unknown)} are not parts of {motion}")
        return np.isin(ids, sorted(self._moving_parts))

    def _foreground(self, frame: Frame) -> np.ndarray | None:
        try:
            path = foreground_path(self.data, frame)
        except DatasetError:  # an image outside the scene folder has no mask there
            return None
        if not path.is_file():
            return None
        return read_id_mask(path, frame.height, frame.width) > 0

    def _derived(self, frame: Frame) -> np.ndarray | None:
        split = self._dataset_split(frame)
        if split is None:
            return None
        if split not in self._derived_of:
            try:
                self._derived_of[split] = derived_masks(self.data, split, self.downscale)
            except DatasetError as err:
                self._derived_of[split] = None
                self.notes.append(f"no derived motion masks for the {split} split: {err}")
        masks = self._derived_of[split]
        return None if masks is None else masks.mask(frame)

    def _dataset_split(self, frame: Frame) -> str | None:
        if self._split_of is None:
            from ..data.scene import available_splits, load_scene

            self._split_of = {}
            for split in available_splits(self.data):
                for f in load_scene(self.data, split, self.downscale).frames:
                    self._split_of.setdefault(Path(f.image_path), split)
        return self._split_of.get(Path(frame.image_path))


def masked_scores(
    pred: torch.Tensor,
    gt: torch.Tensor,
    mask: torch.Tensor,
    lpips_maps: dict[str, torch.Tensor] | None = None,
) -> dict | None:
    """Scores of ``pred`` against ``gt`` ([H, W, 3] in [0, 1]) over ``mask`` [H, W] bool (definitions
    in the module docstring): ``mse``, ``psnr``, ``ssim`` (None when no masked pixel has a whole SSIM
    window inside the image), one value per LPIPS map of ``lpips_maps`` (name -> [H, W]) and
    ``pixel_share`` (of the image); None when the mask is empty."""
    mask = mask.to(pred.device).bool()
    if not bool(mask.any()):
        return None
    err = ((pred - gt) ** 2).mean(dim=-1)
    mse = float(err[mask].double().mean())
    r = SSIM_WINDOW // 2
    inner = mask[r : mask.shape[0] - r, r : mask.shape[1] - r]
    out = {
        "mse": mse,
        "psnr": -10.0 * math.log10(mse) if mse > 0 else math.inf,
        "ssim": float(ssim_map(pred, gt)[inner].double().mean()) if bool(inner.any()) else None,
        "pixel_share": float(mask.double().mean()),
    }
    for name, lmap in (lpips_maps or {}).items():
        out[name] = float(lmap.to(mask.device)[mask].double().mean())
    return out


def aggregate_moving(records: list[dict], with_lpips: bool, dilation: int | None = None) -> dict | None:
    """A split's (or a group of frames') moving-region numbers from the frames' ``moving`` entries
    (``masked_scores`` with its ``source``; ``"none"``: no mask, ``"empty"``: nothing moves in view),
    aggregated as the whole-image ones are; None when no frame had a mask."""
    entries = [r.get("moving") for r in records if "moving" in r]
    scored = [m for m in entries if m.get("mse") is not None]
    without = sum(1 for m in entries if m["source"] == "none")
    if len(entries) == without:
        return None
    out: dict = {"frames": len(scored)}
    if scored:
        with_ssim = [m["ssim"] for m in scored if m["ssim"] is not None]
        out |= {
            "psnr": sum(m["psnr"] for m in scored) / len(scored),
            "mae_psnr": _mae_psnr([m["mse"] for m in scored]),
            "ssim": sum(with_ssim) / len(with_ssim) if with_ssim else None,
            "pixel_share": sum(m["pixel_share"] for m in scored) / len(scored),
        }
        if with_lpips:
            for key in ("lpips_vgg", "lpips_alex"):
                out[key] = sum(m[key] for m in scored) / len(scored)
    out |= {
        "sources": dict(Counter(m["source"] for m in scored)),
        "frames_without_motion": sum(1 for m in entries if m["source"] == "empty"),
        "frames_without_mask": without,
    }
    if dilation is not None:
        out["dilation"] = dilation
    return out


def moving_per_time(records: list[dict], with_lpips: bool) -> dict | None:
    """The ``moving`` entry of one ``per_time`` row (the frames at that time), as the row's whole-image
    numbers: ``psnr`` the MAE-PSNR over the masked MSEs, ``ssim`` and ``lpips_vgg`` the means."""
    scored = [r["moving"] for r in records if r.get("moving", {}).get("mse") is not None]
    if not scored:
        return None
    ssims = [m["ssim"] for m in scored if m["ssim"] is not None]
    row = {
        "psnr": _mae_psnr([m["mse"] for m in scored]),
        "ssim": sum(ssims) / len(ssims) if ssims else None,
        "frames": len(scored),
    }
    if with_lpips:
        row["lpips_vgg"] = sum(m["lpips_vgg"] for m in scored) / len(scored)
    return row


def _mae_psnr(mses: list[float]) -> float:
    """``mae_psnr``, infinite where every masked pixel is exact."""
    return math.inf if not any(mses) else mae_psnr(mses)


def missing_note(split: str, records: list[dict]) -> str | None:
    """The note for a split's frames that no source gave a moving mask, or None when every one had one."""
    missing = sum(1 for r in records if r.get("moving", {}).get("source") == "none")
    if not missing:
        return None
    return (
        f"{split}: {missing} of {len(records)} frames have no moving mask (no gt/masks of moving parts, "
        "no foreground mask, no derived motion mask) and are left out of the moving-region numbers"
    )
