"""Long horizons (the paper's long-horizon figure): trained runs' futures rendered to twice their span.

For each RUN=LABEL (runs of one scene side by side; several scenes may be given, grouped by their
data folder), `tracegs eval --until` (``eval/horizon.py``) renders the new cameras from the end of
training to ``--factor`` x its end, scores each time while the scene has images, and follows the share
of the Gaussians still in sight. Per scene: a figure of PSNR and of that share against time, with the
ends of training and of the ground truth marked (docs/figures/horizon/<scene>.png), and a strip of one
camera's renders at four times (docs/figures/horizon/<scene>_strip.png); with --json, the record.

Usage: .venv/bin/python benchmarks/horizon.py RUN=LABEL [...] [--factor 2] [--json docs/results/horizon.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from tracegs.eval.horizon import long_horizon
from tracegs.results import make_record, write_record


def scene_name(run: Path) -> str:
    data = Path(json.loads((run / "config.json").read_text())["data"])
    return data.name.split("_")[0]


def figure(scene: str, results: dict[str, dict], out: Path) -> Path:
    """PSNR (left) and the share in sight (right) against time, one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.2), dpi=120, sharex=True)
    for label, r in results.items():
        rows = r["per_time"]
        scored = [x for x in rows if "psnr" in x]
        left.plot([x["t"] for x in scored], [x["psnr"] for x in scored], marker="o", ms=2, label=label)
        right.plot([x["t"] for x in rows], [x["in_sight"] for x in rows], label=label)
    first = next(iter(results.values()))
    for ax in (left, right):
        ax.axvline(first["trained_until"], color="grey", ls="--", lw=1, label="end of training")
        ax.axvline(first["checked_until"], color="black", ls=":", lw=1, label="last ground truth")
        ax.set_xlabel("time t")
        ax.grid(alpha=0.3)
    left.set_ylabel("PSNR of the new cameras (dB)")
    right.set_ylabel("share of Gaussians in sight")
    right.set_ylim(0, 1.05)
    left.legend(fontsize=7)
    fig.suptitle(f"Long horizon: {scene} (renders past the last ground truth are unchecked)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def strip(scene: str, results: dict[str, dict], out: Path, count: int = 4) -> Path:
    """Rows = runs, columns = ``count`` times from the first future frame to the last rendered one,
    of each run's first camera, each time marked scored or unchecked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(results.values()))
    times = [x["t"] for x in first["per_time"]]
    picks = [times[round(k * (len(times) - 1) / (count - 1))] for k in range(count)]
    camera = first["cameras"][0]
    h, w = iio.imread(Path(first["images"]) / f"c{camera}_t{picks[0]:.4f}.png").shape[:2]
    fig, axes = plt.subplots(len(results), count, figsize=(2.4 * count * w / max(h, w) + 0.6, 2.4 * len(results) * h / max(h, w) + 0.4),
                             dpi=150, squeeze=False)  # fmt: skip
    for i, (label, r) in enumerate(results.items()):
        for j, t in enumerate(picks):
            ax = axes[i, j]
            ax.imshow(iio.imread(Path(r["images"]) / f"c{camera}_t{t:.4f}.png")[..., :3])
            ax.set_xticks([]), ax.set_yticks([])
            if j == 0:
                ax.set_ylabel(label, fontsize=7)
            if i == 0:
                checked = "scored" if t <= r["checked_until"] + 1e-6 else "unchecked"
                ax.set_title(f"t = {t:.3f} ({checked})", fontsize=7)
    fig.suptitle(f"{scene}, camera {camera} (never trained on), from the end of training on", fontsize=8)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def summary(scene: str, label: str, r: dict) -> dict:
    rows = r["per_time"]
    scored = [x["psnr"] for x in rows if "psnr" in x]
    checked = [x for x in rows if x["t"] <= r["checked_until"] + 1e-6]
    return {
        "scene": scene,
        "method": label,
        "trained until": round(r["trained_until"], 4),
        "scored until": round(r["checked_until"], 4),
        "rendered until": round(r["rendered_until"], 4),
        "psnr, first future frame": scored[0] if scored else None,
        "psnr, last ground truth": scored[-1] if scored else None,
        "mean psnr, scored": round(float(np.mean(scored)), 2) if scored else None,
        "in sight at last ground truth": checked[-1]["in_sight"] if checked else None,
        "in sight at the end": rows[-1]["in_sight"] if rows else None,
        "spread at the end": rows[-1].get("spread") if rows else None,
    }


def record_notes(factor: float, cameras: int, figures: Path) -> str:
    """The record's notes: what each row renders and scores (to ``factor`` times the training end, on
    ``cameras`` new cameras), what 'in sight' counts, where the ``figures`` are."""
    return (
        f"Each run rendered from the end of its training to {factor:g}x that time on its first {cameras} "
        "new cameras, PSNR where the scene has images; 'in sight' is the share of Gaussians whose centres "
        "stay in the box of their positions at the end of training, padded by half its size. "
        f"Figures: {figures.as_posix()}/."
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="RUN=LABEL")
    ap.add_argument("--factor", type=float, default=2.0, help="render to this many times the training end")
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--figures", type=Path, default=Path("docs/figures/horizon"))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    scenes: dict[str, dict[str, dict]] = {}
    for spec in args.runs:
        path, _, label = spec.partition("=")
        run = Path(path)
        end = float(json.loads((run / "summary.json").read_text()).get("t_max", 0.75))
        result = long_horizon(run, args.factor * end, cameras=args.cameras)
        scenes.setdefault(scene_name(run), {})[label or run.name] = result
        print(f"{spec}: {result['note']}", flush=True)
    rows = []
    for scene, results in scenes.items():
        figure(scene, results, args.figures / f"{scene}.png")
        strip(scene, results, args.figures / f"{scene}_strip.png")
        rows += [summary(scene, label, r) for label, r in results.items()]
    columns = list(rows[0])
    for row in rows:
        print("  ".join(str(row[c]) for c in columns))
    if args.json:
        command = f"python benchmarks/horizon.py {' '.join('RUN=' + s.partition('=')[2] for s in args.runs)}"
        command += f" --factor {args.factor:g} --json {args.json}"
        notes = record_notes(args.factor, args.cameras, args.figures)
        record = make_record("horizon", rows, command, title="Long horizons: to twice the training span",
                             columns=columns, notes=notes)  # fmt: skip
        write_record(args.json, record)


if __name__ == "__main__":
    main()
