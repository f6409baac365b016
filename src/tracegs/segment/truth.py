"""Ground-truth segments of a scene folder, in the layout docs/SEGMENTATION.md describes.

* ``gt/masks/<file_path>.png`` beside the scene's json: a uint8 part id per pixel, 0 = background
  (``file_path`` as the json gives it, e.g. ``train/c00_f000``; what ``tracegs synth`` writes).
* ``gt/motion.json``: ``{"parts": [{"id", "name", "type", ...motion parameters}]}``. Every part of
  ``type`` ``static`` joins one segment, and parts whose motion records are equal but for ``id`` and
  ``name`` (parts fixed to each other) join one segment: what moves alike cannot be told apart by its
  motion. Without the file every part id is its own segment.
* The Dynamic 3D Gaussians layout (CMU Panoptic): ``seg/<camera>/<frame>.png``, a binary foreground
  mask per image of the training cameras; scored as foreground / background.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data.frames import DatasetError, Frame, load_json
from ..data.masks import read_id_mask


@dataclass
class GroundTruth:
    """Where a scene's ground-truth masks are and how its parts merge into segments."""

    root: Path
    layout: str
    """``"parts"`` (gt/masks + gt/motion.json) or ``"foreground"`` (Panoptic seg/)."""
    segment_of: dict[int, int]
    """Part id -> segment id (0 stays the background); ids not listed are their own segment."""
    merged: list[list[str]]
    """The names of the parts that were merged, one list per merged segment, for the output."""

    def mask_path(self, frame: Frame) -> Path:
        return mask_path(self.root, frame, self.layout)

    def read(self, frame: Frame) -> np.ndarray | None:
        """The segment id per pixel [H, W] (int64) of ``frame`` at its camera's size, or None when the
        frame has no mask. A mask of another size than the image is reduced by nearest sampling when
        the image was downscaled by an integer factor, and refused otherwise."""
        path = self.mask_path(frame)
        if not path.is_file():
            return None
        ids = read_id_mask(path, frame.height, frame.width)
        if self.layout == "foreground":
            ids = (ids > 0).astype(np.int64)
        if self.segment_of:
            lut = np.arange(max(int(ids.max()), max(self.segment_of)) + 1)
            for part, segment in self.segment_of.items():
                lut[part] = segment
            ids = lut[ids]
        return ids


def mask_path(root: Path, frame: Frame, layout: str) -> Path:
    """The ground-truth mask of ``frame`` (see the module docstring)."""
    root = Path(root).resolve()
    image = Path(frame.image_path).resolve()
    base = root / ("ims" if layout == "foreground" else "")
    try:
        rel = image.relative_to(base)
    except ValueError:
        raise DatasetError(f"{image}: the image lies outside {base}, so its mask cannot be found") from None
    folder = root / ("seg" if layout == "foreground" else "gt/masks")
    return (folder / rel).with_suffix(".png")


def find_ground_truth(root: str | Path, layout: str | None = None) -> GroundTruth | None:
    """The ground truth of the scene folder ``root``, or None when it has none."""
    root = Path(root)
    if (root / "gt" / "masks").is_dir():
        segment_of, merged = merged_parts(root / "gt" / "motion.json")
        return GroundTruth(root, "parts", segment_of, merged)
    if (root / "seg").is_dir() and (root / "train_meta.json").is_file():
        return GroundTruth(root, "foreground", {}, [])
    return None


def merged_parts(motion_json: Path) -> tuple[dict[int, int], list[list[str]]]:
    """Part id -> segment id from ``gt/motion.json`` (static parts together, parts with equal motions
    together; segment ids are the smallest part id of each group), and the merged groups' names."""
    if not motion_json.is_file():
        return {}, []
    data = load_json(motion_json)
    parts = data.get("parts") if isinstance(data, dict) else None
    if not isinstance(parts, list) or not all(isinstance(p, dict) and "id" in p for p in parts):
        raise DatasetError(f"{motion_json}: expected {{'parts': [{{'id', 'name', 'type', ...}}]}}")
    groups: dict[str, list[dict]] = {}
    for part in sorted(parts, key=lambda p: int(p["id"])):
        if part.get("type") == "static":
            key = "static"
        else:
            key = json.dumps({k: v for k, v in part.items() if k not in ("id", "name")}, sort_keys=True)
        groups.setdefault(key, []).append(part)
    segment_of, merged = {}, []
    for members in groups.values():
        first = int(members[0]["id"])
        for part in members:
            segment_of[int(part["id"])] = first
        if len(members) > 1:
            merged.append([str(p.get("name", p["id"])) for p in members])
    return segment_of, merged
