"""A short plain-text summary of an evaluation result (the dict of ``evaluate_run``), for the console.

The full result, with every per-time, per-camera, per-part and physics number, stays in the JSON file;
this is what a user reads first: the two splits, the horizon, where the error is and the learned
motion against the ground truth.
"""

from __future__ import annotations

import math

SPLIT_COLUMNS = (
    ("frames", "frames", "{:d}"),
    ("psnr", "PSNR", "{:.2f}"),
    ("mae_psnr", "MAE-PSNR", "{:.2f}"),
    ("ssim", "SSIM", "{:.4f}"),
    ("lpips_vgg", "LPIPS-VGG", "{:.4f}"),
    ("lpips_alex", "LPIPS-Alex", "{:.4f}"),
)


def _split_table(result: dict) -> list[str]:
    splits = [s for s in ("interpolation", "extrapolation") if result.get(s, {}).get("frames")]
    cols = [c for c in SPLIT_COLUMNS if all(c[0] in result[s] for s in splits)]
    rows = [["split", *(c[1] for c in cols)]]
    rows += [[s, *(fmt.format(result[s][key]) for key, _, fmt in cols)] for s in splits]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return [
        "  ".join(
            cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(r, widths, strict=True))
        )
        for r in rows
    ]


def _horizon(extrap: dict, points: int = 5) -> str | None:
    per_time = extrap.get("per_time") or []
    if not per_time:
        return None
    step = max(1, (len(per_time) - 1) // (points - 1))
    picked = per_time[::step]
    if picked[-1] is not per_time[-1]:
        picked.append(per_time[-1])
    return "future PSNR by time: " + ", ".join(f"t={p['t']:.3f} {p['psnr']:.2f} dB" for p in picked)


def _parts(split: str, summary: dict) -> str | None:
    parts = summary.get("per_part")
    if not parts:
        return None
    cells = [
        f"{name} {p['psnr']:.2f} dB ({100 * p['pixel_share']:.0f}% of pixels, {100 * p['error_share']:.0f}% of error)"
        for name, p in parts.items()
    ]
    return f"{split} by part: " + "; ".join(cells)


def _moving(result: dict) -> str | None:
    cells = []
    for split in ("interpolation", "extrapolation"):
        m = result.get(split, {}).get("moving") or {}
        if not m.get("frames"):
            continue
        text = f"{split} {m['mae_psnr']:.2f} dB"
        text += "" if m.get("ssim") is None else f", SSIM {m['ssim']:.4f}"
        text += "" if m.get("lpips_vgg") is None else f", LPIPS-VGG {m['lpips_vgg']:.4f}"
        cells.append(text + f" ({m['frames']} frames, {100 * m['pixel_share']:.0f}% of their pixels)")
    return "where things move (MAE-PSNR): " + "; ".join(cells) if cells else None


def _physics(physics: dict) -> list[str]:
    lines = []
    for part, p in sorted((physics or {}).get("parts", {}).items()):
        if "mean_trajectory_error" not in p:  # no Gaussian lies on the part's ground-truth surface
            lines.append(f"part {part}: no Gaussians on it")
            continue
        text = f"part {part}: future trajectory error {p['mean_trajectory_error']:.4f}"
        if "omega_rel_error" in p:
            learned, truth = math.hypot(*p["omega_learned"]), math.hypot(*p["omega_gt"])
            text += f", |w| {learned:.3f} vs {truth:.3f} ({100 * p['omega_rel_error']:.1f}%)"
        if "axis_error_deg" in p:
            text += f", axis off by {p['axis_error_deg']:.2f} deg"
        lines.append(text)
    return lines


def format_summary(result: dict) -> str:
    """Plain-text summary of an ``evaluate_run`` result: header, split table, the moving pixels,
    horizon, parts, physics, and the notes on what was skipped."""
    head = f"{result.get('scene', '?')}: {result.get('method', '?')} ({result.get('preset', '?')})"
    if result.get("motion", "trace") != "trace":
        head += f", motion {result['motion']}"
    if result.get("gaussians") is not None:
        head += f", {result['gaussians']} Gaussians"
    if result.get("train_seconds") is not None:
        head += f", {result['train_seconds']:.0f} s of training"
    if result.get("t_train_end") is not None:
        head += f"; future: t > {result['t_train_end']:.3f}"
    lines = [head, *_split_table(result)]
    optional = [_moving(result), _horizon(result.get("extrapolation", {}))]
    optional += [_parts(s, result.get(s, {})) for s in ("interpolation", "extrapolation")]
    lines += [x for x in optional if x]
    lines += _physics(result.get("physics"))
    lines += [f"note: {note}" for note in result.get("notes", [])]
    return "\n".join(lines)
