"""The ball's flight, predicted from a real capture: CMU Panoptic `basketball` at 320x180 px.

Two windows in which the ball flies freely: trained on frames 0-58, predict frames 59-65 (a pass,
caught at about 66); trained on frames 0-139, predict frames 140-149 (a throw, released at about 133).
For each window a run of the `capture` preset (trained here, `--t-train-end` = last frame / 149, or
given with `--runs`) predicts the 4 test cameras' images at the window's frames by three motions:
TRACE (the run's own), DefGS (the same run's f_defo, or a DefGS run given with `--defgs-runs`) and
Hold (the Gaussians of the last training time, held). The ball detector of `tracegs.eval.ball` finds
the ball in each render and in each ground-truth image; the centre error in pixels is scored where
the ground truth shows the ball (mean over the window's frames and at its last frame; a render without
a ball there counts as missed). The run's report says whether the ball became a free body (a free
body whose Gaussians lie on the ground truth's ball at the handover) and its fitted acceleration.

Usage:
  .venv/bin/python benchmarks/ball.py --ground-truth-only            (the detector on the images alone)
  .venv/bin/python benchmarks/ball.py --figure docs/figures/panoptic/ball_detections.png --ground-truth-only
  .venv/bin/python benchmarks/ball.py --out runs/ball [--runs 58=RUN 139=RUN] [--defgs-runs 58=RUN ...]
      [--json docs/results/ball.json]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from tracegs.data.frames import load_image
from tracegs.data.scene import load_scene
from tracegs.eval.ball import BallDetection, detect_ball
from tracegs.results import make_record, write_record

DATA = Path("../shared/data/panoptic/basketball")
LAST_FRAME = 149  # frame i is at time i / 149
WINDOWS = {58: range(59, 66), 139: range(140, 150)}  # last training frame: the predicted frames
FIGURE_FRAMES = (55, 60, 65, 135, 140, 145)
COLUMNS = ["window", "method", "visible", "missed", "mean_px", "last_px", "free_body", "gravity"]
NOTES = (
    "Centre errors in pixels at 320x180 over the (test camera, frame) pairs whose ground truth shows the "
    "ball, the same detector (tracegs.eval.ball) on the renders and the images; a render without a ball "
    "there is missed, not scored. Gravity: the ball's free body's acceleration in scene units per s^2 "
    "at 30 frames per second."
)
FPS = 30.0  # the capture's frame rate: frame i at i / 30 s


def frame_of(t: float) -> int:
    return round(t * LAST_FRAME)


def ground_truth(scene, frames) -> dict[tuple[int, int], tuple[object, np.ndarray, BallDetection | None]]:
    """(camera id, frame) -> (the frame, its image, the ball in it) for the test cameras at ``frames``."""
    out = {}
    for f in scene.frames:
        i = frame_of(f.time)
        if i in frames:
            image = load_image(f, scene.background).numpy().astype(np.float32)
            out[(f.camera_id, i)] = (f, image, detect_ball(image))
    return out


def print_ground_truth(truth: dict, frames) -> None:
    """Per camera, the frames of ``frames`` whose image shows the ball."""
    for camera in sorted({c for c, _ in truth}):
        seen = [i for i in frames if truth[(camera, i)][2] is not None]
        line = "".join("B" if i in seen else "." for i in frames)
        print(
            f"camera {camera:>2}: {line}  frames {frames[0]}-{frames[-1]}: {len(seen)} with the ball {seen}"
        )


def _circle(image: np.ndarray, found: BallDetection | None, colour) -> np.ndarray:
    if found is None:
        return image
    yy, xx = np.mgrid[: image.shape[0], : image.shape[1]]
    ring = np.abs(np.hypot(xx - found.centre_xy[0], yy - found.centre_xy[1]) - found.radius_px - 2) < 0.8
    image = image.copy()
    image[ring] = colour
    return image


def detections_figure(truth: dict, path: Path, crop: tuple[int, int] = (96, 128)) -> Path:
    """A PNG at ``path``: a row per test camera, a crop per frame of ``FIGURE_FRAMES`` about the ball
    (the detection circled in green; where none, about the camera's last detection, in a red frame)."""
    import imageio.v3 as iio

    rows = []
    for camera in sorted({c for c, _ in truth}):
        tiles, last = [], None
        for i in FIGURE_FRAMES:
            _, image, found = truth[(camera, i)]
            H, W = image.shape[:2]
            centre = found.centre_xy if found is not None else last or (W / 2, H / 2)
            last = centre
            y0 = int(np.clip(round(centre[1]) - crop[0] // 2, 0, H - crop[0]))
            x0 = int(np.clip(round(centre[0]) - crop[1] // 2, 0, W - crop[1]))
            tile = _circle(image, found, (0.1, 1.0, 0.1))[y0 : y0 + crop[0], x0 : x0 + crop[1]]
            edge = (1.0, 1.0, 1.0) if found is not None else (1.0, 0.1, 0.1)
            tile = np.stack([np.pad(tile[..., k], 2, constant_values=edge[k]) for k in range(3)], -1)
            tiles.append(tile)
        rows.append(np.concatenate(tiles, 1))
    grid = np.concatenate(rows, 0)
    grid = grid.repeat(2, 0).repeat(2, 1)  # the ball's few pixels, large enough to see
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, (grid.clip(0, 1) * 255).round().astype(np.uint8))
    return path


def train(data: Path, run: Path, last: int, downscale: int, method: str = "trace") -> Path:
    """``tracegs train --preset capture`` on frames 0..``last`` into ``run`` (kept when it has a
    checkpoint)."""
    if (run / "checkpoint.pt").is_file():
        return run
    command = [sys.executable, "-m", "tracegs", "train", "--data", str(data), "--run", str(run)]
    command += [
        "--preset",
        "capture",
        "--downscale",
        str(downscale),
        "--t-train-end",
        f"{last / LAST_FRAME:.9f}",
    ]
    command += ["--method", method] if method != "trace" else []
    print(" ".join(command), flush=True)
    subprocess.run(command, check=True)
    return run


def motions(predictor, defgs=None) -> dict:
    """Method name -> a function of t to Gaussians: TRACE, DefGS (``defgs``' f_defo, else the run's
    own) and Hold (the motion "hold" when the Predictor has it, else f_defo at the last training time)."""
    from tracegs.extrapolate.predictor import MOTIONS

    other = defgs if defgs is not None else predictor
    if "hold" in MOTIONS:
        hold = lambda t: predictor.gaussians_at(t, "hold")  # noqa: E731
    else:
        held = predictor.gaussians_at(predictor.t_max, "f_defo")
        hold = lambda t: held  # noqa: E731
    return {
        "TRACE": (predictor, lambda t: predictor.gaussians_at(t, "trace")),
        "DefGS": (other, lambda t: other.gaussians_at(t, "f_defo")),
        "Hold": (predictor, hold),
    }


def project(camera, points) -> np.ndarray:
    """[P, 2] pixel positions of world ``points`` [P, 3] seen by ``camera``."""
    import torch

    p = torch.cat([points.double(), torch.ones_like(points[:, :1]).double()], 1) @ camera.viewmat.double().T
    uv = p[:, :3] @ camera.K.double().T
    return (uv[:, :2] / uv[:, 2:3]).cpu().numpy()


def ball_free_body(predictor, scene) -> tuple[bool, float | None]:
    """(whether a free body's Gaussians lie on the ground truth's ball at the handover in a test
    camera, the magnitude of that body's acceleration in scene units per s^2 at ``FPS``)."""
    from tracegs.physics.free_body import FreeBody

    bodies = predictor.state.free_bodies
    if not predictor.settings.free_bodies or bodies is None or not len(bodies["bodies"]):
        return False, None
    start = predictor.model.deform(bodies["t0"])["means"]
    truth = ground_truth(scene, {frame_of(bodies["t0"])})
    for k, row in enumerate(bodies["bodies"]):
        centre = start[bodies["labels"].to(start.device) == k + 1].mean(0, keepdim=True)
        for f, _, found in truth.values():
            if found is None:
                continue
            xy = project(f.camera, centre)[0]
            if np.hypot(*(xy - np.array(found.centre_xy))) <= 2 * found.radius_px:
                a = FreeBody.from_tensor(row).a
                return True, float(a.norm()) / (LAST_FRAME / FPS) ** 2
    return False, None


def score_window(last: int, run: Path, scene, truth: dict, defgs_run: Path | None = None) -> list[dict]:
    """The rows of one window (the test ``scene``, its ``truth``): per method, the centre errors over
    the predicted frames."""
    from tracegs.run import load_run

    predictor = load_run(run, "cpu").predictor.with_background(scene.background)
    defgs = load_run(defgs_run, "cpu").predictor.with_background(scene.background) if defgs_run else None
    frames = list(WINDOWS[last])
    free, gravity = ball_free_body(predictor, scene)
    rows = []
    for method, (owner, at) in motions(predictor, defgs).items():
        errors, last_errors, missed = [], [], 0
        for t_frame in frames:
            gaussians = at(t_frame / LAST_FRAME)
            for (_, i), (f, _image, found) in truth.items():
                if i != t_frame or found is None:
                    continue
                image = owner.render(f.camera, gaussians=gaussians).cpu().numpy()
                mine = detect_ball(image)
                if mine is None:
                    missed += 1
                    continue
                error = float(np.hypot(*(np.array(mine.centre_xy) - np.array(found.centre_xy))))
                errors.append(error)
                if t_frame == frames[-1]:
                    last_errors.append(error)
        rows.append(
            {
                "window": f"frames 0-{last} -> {frames[0]}-{frames[-1]}",
                "method": method,
                "visible": len(errors) + missed,
                "missed": missed,
                "mean_px": round(float(np.mean(errors)), 2) if errors else None,
                "last_px": round(float(np.mean(last_errors)), 2) if last_errors else None,
                "free_body": free if method == "TRACE" else None,
                "gravity": round(gravity, 2) if method == "TRACE" and gravity is not None else None,
            }
        )
    return rows


def pairs(specs: list[str], flag: str) -> dict[int, Path]:
    """``LAST=RUN`` arguments -> {last training frame: run folder}."""
    out = {}
    for spec in specs:
        last, _, run = spec.partition("=")
        if not last.isdigit() or int(last) not in WINDOWS or not run:
            raise SystemExit(f"{flag} {spec!r}: expected LAST=RUN with LAST one of {sorted(WINDOWS)}")
        out[int(last)] = Path(run)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--data", type=Path, default=DATA, help="the basketball capture (Dynamic 3D Gaussians layout)"
    )
    ap.add_argument("--downscale", type=int, default=2, help="image size divisor (2: 320x180)")
    ap.add_argument("--out", type=Path, default=Path("runs/ball"), help="where the runs trained here go")
    ap.add_argument(
        "--runs", nargs="*", default=[], help="LAST=RUN: a trained capture run per window (58, 139)"
    )
    ap.add_argument("--defgs-runs", nargs="*", default=[], help="LAST=RUN: a DefGS run per window")
    ap.add_argument(
        "--windows", type=int, nargs="*", default=sorted(WINDOWS), help="the windows' last frames"
    )
    ap.add_argument("--ground-truth-only", action="store_true", help="only the detector on the images")
    ap.add_argument("--figure", type=Path, help="a PNG of the detections at frames 55-65 and 135-145")
    ap.add_argument("--json", type=Path, help="write the results record here (docs/results/ball.json)")
    args = ap.parse_args()
    runs, defgs_runs = pairs(args.runs, "--runs"), pairs(args.defgs_runs, "--defgs-runs")
    scene = load_scene(args.data, "test", args.downscale)
    wanted = {i for last in args.windows for i in WINDOWS[last]}
    truth = ground_truth(scene, wanted | (set(FIGURE_FRAMES) if args.figure else set()))
    for last in args.windows:
        frames = list(WINDOWS[last])
        print(
            f"trained on frames 0-{last}, predicting {frames[0]}-{frames[-1]}: the ball in the ground truth"
        )
        print_ground_truth(truth, frames)
    if args.figure:
        print(f"figure: {detections_figure(truth, args.figure)}")
    if args.ground_truth_only:
        return
    rows = []
    for last in args.windows:
        run = runs.get(last) or train(args.data, args.out / f"capture_{last}", last, args.downscale)
        rows += score_window(last, run, scene, truth, defgs_runs.get(last))
    for row in rows:
        print("  ".join(f"{c}={row[c]}" for c in COLUMNS))
    if args.json:
        command = "python benchmarks/ball.py --out runs/ball" + f" --json {args.json}"
        title = "The ball's flight predicted from CMU Panoptic `basketball` (320x180, `capture` preset)"
        write_record(args.json, make_record("ball", rows, command, title=title, columns=COLUMNS, notes=NOTES))


if __name__ == "__main__":
    main()
