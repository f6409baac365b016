"""A predicted frame rendered by tracegs beside the run's MuJoCo model (`tracegs export --mjcf`) at the
same time and from the same dataset camera: left the run's Gaussians under its own extrapolation,
middle the Gaussians moved by the MuJoCo model's bodies, right MuJoCo's own render of its bodies (their
convex hulls, in the segment palette). MuJoCo renders with EGL (``MUJOCO_GL=egl``, set here).

Usage: .venv/bin/python benchmarks/simulator_figure.py RUN [--time 0.9] [--camera test:0]
       [--out docs/figures/export/mujoco.png]
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import numpy as np

from tracegs.data.scene import load_scene
from tracegs.export.render import pick_camera
from tracegs.export.simulate import simulate
from tracegs.export.simulator import build_model
from tracegs.run import load_run
from tracegs.utils import atomic_write_image

GAP = 4


def with_camera(xml: str, camera) -> str:
    """``xml`` with a fixed camera ``view`` where the dataset's ``camera`` is (MuJoCo's cameras look
    along their -z with +y up: OpenGL's axes, OpenCV's y and z flipped)."""
    c2w = np.linalg.inv(camera.viewmat.double().cpu().numpy())
    x, y = c2w[:3, 0], -c2w[:3, 1]
    fovy = math.degrees(2 * math.atan(camera.height / (2 * float(camera.K[1, 1]))))
    element = (
        f'<camera name="view" pos="{" ".join(map(str, c2w[:3, 3]))}" '
        f'xyaxes="{" ".join(map(str, [*x, *y]))}" fovy="{fovy}"/>'
    )
    return xml.replace("<worldbody>", "<worldbody>" + element, 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--time", type=float, default=0.9)
    ap.add_argument("--camera", default="test:0")
    ap.add_argument("--out", type=Path, default=Path("docs/figures/export/mujoco.png"))
    args = ap.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    import mujoco

    loaded = load_run(args.run, "cpu")
    cfg = loaded.config
    predictor = loaded.predictor.with_background(load_scene(cfg.data, "train").background)
    camera = pick_camera(cfg.data, args.camera, cfg.downscale)
    rig, _, xml, _ = build_model(loaded)
    motion = simulate(xml, rig, args.time)
    own = predictor.render(camera, args.time).cpu().numpy()
    moved = predictor.gaussians_carried(args.time, motion.labels, motion.transforms)
    simulated = predictor.render(camera, gaussians=moved).cpu().numpy()
    model = mujoco.MjModel.from_xml_string(with_camera(xml, camera))
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("handover").id)
    while data.time < args.time:
        mujoco.mj_step(model, data)
    renderer = mujoco.Renderer(model, camera.height, camera.width)
    renderer.update_scene(data, camera="view")
    hulls = renderer.render().astype(np.float32) / 255
    gap = np.ones((camera.height, GAP, 3), dtype=np.float32)
    strip = np.concatenate([np.clip(own, 0, 1), gap, np.clip(simulated, 0, 1), gap, hulls], axis=1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_image(args.out, strip)
    error = float(np.abs(own - simulated).mean())
    print(f"wrote {args.out}: t = {args.time}, mean |run - MuJoCo-moved| {error:.4f} per pixel")


if __name__ == "__main__":
    main()
