"""The console summary of ``tracegs segment``."""

from __future__ import annotations

from .metrics import METRICS


def format_report(report: dict) -> str:
    """A few lines: K and how it was chosen, the segments' sizes, the scores, where the files are."""
    sizes = ", ".join(
        f"{s['label']}{' (static)' if s['static'] else ''}: {s['gaussians']}" for s in report["segments"]
    )
    lines = [
        f"{report['features']} features at t = {report['time']:.3f}: K = {report['k']} ({sizes} Gaussians)"
    ]
    if report.get("note"):
        lines.append(report["note"])
    if report.get("auto_k"):
        tried = ", ".join(f"K={row['k']}: {row['rigid_residual']:.4f}" for row in report["auto_k"]["tried"])
        lines.append(f"auto-K by rigid residual (tolerance {report['auto_k']['tolerance']}): {tried}")
    for body in report.get("free_bodies") or []:
        lines.append(
            f"free body {body['body']}: {100 * body['purity']:.0f}% of it in segment {body['segment']}, "
            f"{100 * body['coverage']:.0f}% of that segment"
        )
    scores = report.get("scores")
    if scores:
        lines.append(f"ground truth: {report['ground_truth']['note']}")
        lines.append("            " + " ".join(f"{m:>9}" for m in ("images", *METRICS)))
        for name in ("training_times", "future_times"):
            row = scores[name]
            if row["images"]:
                values = " ".join(f"{100 * row[m]:9.2f}" for m in METRICS)
                lines.append(f"{name.replace('_', ' '):<12}{row['images']:>9} {values}")
    seconds = report["seconds"]
    lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items()))
    lines.append(f"files: {', '.join(report['outputs'].values())}")
    return "\n".join(lines)
