"""Continual learning (the paper's Section 4.4) on scenes, TRACE against DefGS: per round and on average.

Runs `tracegs train --continual` (``continual.py``) for each scene and method into
RUNS/<scene>_<method>, or reads the table a finished one left (RUN/continual.json); prints the rounds,
writes a plot per scene (docs/figures/continual/<scene>.png) and, with --json, the record.

Usage: .venv/bin/python benchmarks/continual.py SCENE_DIR [...] --runs RUNS [--window 0.15 --horizon 0.15]
       [--frames] [--step S] [--train-flags "--dynamic-iterations 6000"] [--methods trace defgs]
       [--json docs/results/continual.json]
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from pathlib import Path

METHODS = ("trace", "defgs")
LABEL = {"trace": "TRACE", "defgs": "DefGS"}
COLUMNS = ["scene", "method", "rounds", "observed until", "psnr per round", "psnr", "ssim", "lpips", "wall s"]
NOTES = (
    "Each round trains on the frames up to its window's end (`observed until`; the first from scratch, "
    "each next one from the round before with 25% of the steps) and is scored on the next window; psnr, "
    "ssim, lpips average over the rounds, wall s is the whole sequence."
)


def record_notes(note: str = "") -> str:
    """The record's notes: :data:`NOTES`, then ``note`` (``--note``: the one caveat of these runs, e.g.
    the steps of a round); ValueError if ``note`` is more than one sentence."""
    from tracegs.results import sentences

    if len(sentences(note)) > 1:
        raise ValueError(f"--note must be one sentence (the notes have at most two), got {note!r}")
    return f"{NOTES} {note}".strip()


def run_one(scene: Path, method: str, runs: Path, args) -> dict:
    run = runs / f"{scene.name}_{method}"
    table = run / "continual.json"
    plan = [f"--window={args.window}", f"--horizon={args.horizon}"]
    plan += [f"--step={args.step}"] if args.step is not None else []
    plan += ["--frames"] if args.frames else []
    if not (table.is_file() and _complete(table, scene, args)):
        command = [sys.executable, "-m", "tracegs", "train", "--continual", *plan, "--data", str(scene),
                   "--run", str(run), "--method", method, *shlex.split(args.train_flags)]  # fmt: skip
        print(" ".join(command), flush=True)
        subprocess.run(command, check=True)
    return json.loads(table.read_text())


def _complete(path: Path, scene: Path, args) -> bool:
    """Whether the table at ``path`` has every round of the plan (``continual.round_ends``)."""
    from tracegs.continual import Continual, round_ends
    from tracegs.data.scene import available_splits, load_scene

    times = [f.time for split in available_splits(scene) for f in load_scene(scene, split).frames]
    plan = Continual(args.window, args.horizon, args.step, args.frames)
    return len(json.loads(path.read_text())["rounds"]) == len(round_ends(times, plan))


def plot(scene: str, tables: dict[str, dict], out: Path) -> Path:
    from tracegs.export.plots import line_plot

    series = {
        LABEL[m]: ([r["observed_until"] for r in t["rounds"]], [r["psnr"] for r in t["rounds"]])
        for m, t in tables.items()
    }
    xlabel, ylabel = (
        "observed until t (each round predicts the next window)",
        "PSNR of the predicted window (dB)",
    )
    return line_plot(series, out, xlabel, ylabel, f"Continual learning: {scene}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--runs", type=Path, required=True)
    ap.add_argument("--window", type=float, default=0.15)
    ap.add_argument("--horizon", type=float, default=0.15)
    ap.add_argument("--step", type=float, default=None)
    ap.add_argument("--frames", action="store_true")
    ap.add_argument("--train-flags", default="", help="more `tracegs train` flags, e.g. the preset")
    ap.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS))
    ap.add_argument("--json", type=Path)
    ap.add_argument("--figures", type=Path, default=Path("docs/figures/continual"))
    ap.add_argument(
        "--note", default="", help="the notes' second sentence: the one caveat (e.g. the steps of a round)"
    )
    ap.add_argument("--title", default="Continual learning: TRACE and DefGS per round")
    ap.add_argument(
        "--benchmark", default="continual", help="the record's name (continual-panoptic for basketball)"
    )
    args = ap.parse_args()
    try:
        notes = record_notes(args.note)
    except ValueError as err:
        ap.error(str(err))
    rows = []
    for scene in args.scenes:
        tables = {m: run_one(scene, m, args.runs, args) for m in args.methods}
        name = scene.name.split("_")[0]
        plot(name, tables, args.figures / f"{name}.png")
        for method, table in tables.items():
            for r in table["rounds"]:
                print(f"{name} {LABEL[method]} round {r['round']}: observed until {r['observed_until']:.3f}, "
                      f"predicted until {r['extrapolated_until']:.3f}: PSNR {r['psnr']:.2f}, SSIM {r['ssim']:.3f}, "
                      f"{r['wall_s']:.0f} s")  # fmt: skip
            avg = table["average"]
            rows.append({"scene": name, "method": LABEL[method], "rounds": len(table["rounds"]),
                         "observed until": " / ".join(f"{r['observed_until']:.3f}" for r in table["rounds"]),
                         "psnr per round": " / ".join(f"{r['psnr']:.1f}" for r in table["rounds"]),
                         "psnr": round(avg["psnr"], 2), "ssim": round(avg["ssim"], 3),
                         "lpips": round(avg["lpips_vgg"], 3) if "lpips_vgg" in avg else None,
                         "wall s": round(table["wall_s"])})  # fmt: skip
    for method in args.methods:
        mine = [a for a in rows if a["method"] == LABEL[method] and a["scene"] != "all"]
        rows.append({"scene": "all", "method": LABEL[method], "rounds": sum(a["rounds"] for a in mine),
                     "psnr": round(sum(a["psnr"] for a in mine) / len(mine), 2),
                     "ssim": round(sum(a["ssim"] for a in mine) / len(mine), 3)})  # fmt: skip
    for row in rows:
        print("  ".join(str(row.get(c, "")) for c in COLUMNS))
    if args.json:
        from tracegs.results import make_record, write_record

        plan = f"--window {args.window} --horizon {args.horizon}" + (
            f" --step {args.step}" if args.step else ""
        )
        plan += " --frames" if args.frames else ""
        plan += "" if list(args.methods) == list(METHODS) else f" --methods {' '.join(args.methods)}"
        command = (
            f"python benchmarks/continual.py {' '.join('DATA/' + s.name for s in args.scenes)} --runs RUNS {plan}"
            + (f" --train-flags {shlex.quote(args.train_flags)}" if args.train_flags else "")
            + f" --json {args.json}"
        )
        record = make_record(args.benchmark, rows, command, title=args.title,
                             columns=COLUMNS, notes=notes)  # fmt: skip
        write_record(args.json, record)


if __name__ == "__main__":
    main()
