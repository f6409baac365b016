"""The exported MuJoCo model run from the handover: each body's rigid motion from its pose there, the
Gaussians it carries moved by it (``Predictor.gaussians_carried``), for the comparison with the run's
own future and, on a ``tracegs synth`` scene, with the ground truth (``check_export``), and as the
viewer's third motion.

B: bodies, K: simulated times, N: Gaussians.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from .rig import Rig


class SimulatedMotion:
    """The bodies' rigid motions from the handover ``t0``, sampled every ``step`` of the dataset's time
    up to ``t_end`` by MuJoCo from the keyframe ``handover`` of the MJCF ``xml``."""

    def __init__(self, xml: str, rig: Rig, t_end: float, step: float = 1 / 240):
        import mujoco

        model = mujoco.MjModel.from_xml_string(xml)
        data = mujoco.MjData(model)
        mujoco.mj_resetDataKeyframe(model, data, model.key("handover").id)
        mujoco.mj_forward(model, data)
        ids = [model.body(b.name).id for b in rig.bodies]
        start = self._poses(data, ids)
        self.t0, self.step = rig.t0, step
        self.labels = torch.zeros(rig.bodies[0].rows.shape[0] if rig.bodies else 0, dtype=torch.long)
        for k, body in enumerate(rig.bodies):
            self.labels[body.rows.cpu()] = k + 1
        samples = max(1, int(np.ceil((t_end - rig.t0) / step - 1e-9)))
        motions = [np.broadcast_to(np.eye(4), (len(ids), 4, 4)).copy()]
        for s in range(1, samples + 1):
            target = rig.t0 + s * step
            while data.time < target - 0.5 * model.opt.timestep:
                mujoco.mj_step(model, data)
            motions.append(self._poses(data, ids) @ np.linalg.inv(start))
        self.motions = np.stack(motions)  # [K, B, 4, 4] world x at t0 -> world x at t
        self.finite = bool(np.isfinite(self.motions).all())

    @staticmethod
    def _poses(data, ids: list[int]) -> np.ndarray:
        out = np.tile(np.eye(4), (len(ids), 1, 1))
        for i, b in enumerate(ids):
            out[i, :3, :3] = data.xmat[b].reshape(3, 3)
            out[i, :3, 3] = data.xpos[b]
        return out

    def transforms(self, t: float) -> np.ndarray:
        """[B, 4, 4] each body's motion from the handover to ``t`` (the nearest sample; the identity
        before the handover)."""
        k = int(round((t - self.t0) / self.step))
        return self.motions[min(max(k, 0), len(self.motions) - 1)]


def simulate(xml: str, rig: Rig, t_end: float = 1.0) -> SimulatedMotion:
    """``SimulatedMotion`` of the MJCF text ``xml`` written from ``rig``, to ``t_end``."""
    return SimulatedMotion(xml, rig, t_end)


def load_urdf(path: Path):
    """The URDF at ``path`` loaded by yourdfpy (meshes included): the check that it reads."""
    import yourdfpy

    return yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=True)
