"""Contact sheets of a synthesized folder: a grid of cameras x times, composited on white, with the
part masks beside the images, to check a scene by eye (``docs/synth/<scene>.png``)."""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np

# Distinct colours for part ids 1..; the background (id 0) stays white.
PART_COLORS = np.array(
    [
        [255, 255, 255],
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
    ],
    dtype=np.uint8,
)


def _index(root: Path) -> tuple[dict, float]:
    """(camera, frame) -> (relative image path, time, split) over all splits; and t_train_end."""
    index, t_end = {}, 0.0
    for split in ("train", "val", "test"):
        data = json.loads((root / f"transforms_{split}.json").read_text())
        t_end = data["t_train_end"]
        for fr in data["frames"]:
            index[(fr["camera_id"], fr["frame_id"])] = (fr["file_path"], fr["time"], split)
    return index, t_end


def composite_on_white(rgba: np.ndarray) -> np.ndarray:
    """[H, W, 4] uint8 straight alpha -> [H, W, 3] uint8 on a white background."""
    a = rgba[..., 3:4].astype(np.float64) / 255
    return np.rint(rgba[..., :3] * a + 255 * (1 - a)).astype(np.uint8)


def contact_sheet(
    root: str | Path, path: str | Path, cameras=(0, 4, 13), frames=None, masks: bool = True
) -> Path:
    """Save a grid: one row per camera (image and, with ``masks``, its part mask), one column per
    frame (default: 6 frames from t = 0 to 1, so both training and extrapolation times show)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    root, path = Path(root), Path(path)
    index, t_end = _index(root)
    n_frames = 1 + max(f for _, f in index)
    n_cams = 1 + max(c for c, _ in index)
    cameras = [c for c in cameras if c < n_cams] or [0]
    if frames is None:
        frames = sorted({round(x) for x in np.linspace(0, n_frames - 1, 6)})
    rows = [(c, kind) for c in cameras for kind in (("image", "mask") if masks else ("image",))]
    fig, axes = plt.subplots(
        len(rows), len(frames), figsize=(1.6 * len(frames), 1.6 * len(rows)), squeeze=False
    )
    for r, (c, kind) in enumerate(rows):
        for k, f in enumerate(frames):
            rel, t, split = index[(c, f)]
            if kind == "image":
                tile = composite_on_white(iio.imread(root / rel))
            else:
                tile = PART_COLORS[iio.imread(root / "gt" / "masks" / rel) % len(PART_COLORS)]
            ax = axes[r, k]
            ax.imshow(tile, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(f"t={t:.2f}" + (" (extrap.)" if t > t_end else ""), fontsize=7)
            if k == 0:
                ax.set_ylabel(f"cam {c} {kind}\n({split})", fontsize=7)
    scene = json.loads((root / "transforms_train.json").read_text()).get("scene", root.name)
    fig.suptitle(f"{scene}: rows = cameras (image / part mask), columns = time", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
