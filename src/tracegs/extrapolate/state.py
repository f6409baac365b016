"""The post-training state of a run: everything the extrapolation policy chose on the training images
when training ended, saved in the run folder (``extrapolation.pt``) and read back as it is.

N: Gaussians, K: free bodies.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..physics.free_body import FREE_BODY_NUMBERS

STATE_VERSION = 3
"""Bumped when the saved layout changes; a run with a version not in ``READABLE_VERSIONS`` is
calibrated again (``tracegs calibrate --run RUN``)."""
READABLE_VERSIONS = (1, 3)
"""The saved layouts read as they are: version 1 has no joint laws (none chosen); version 2's joint
parts carried a law of a fixed catalog, not an identified model."""


@dataclass
class ExtrapolationState:
    """What ``gaussians_at`` needs besides the model to render any time past the training span."""

    t_max: float
    """Last training time of the run; the handover lies ``extrapolation.handover_frames`` before it."""
    freeze_threshold: float | None = None
    """Gaussians whose f_defo displacement up to the handover stays below this (scene units) hold still
    after it (``extrapolation.freeze_static``); 0 or None (not chosen): none."""
    unseen: torch.Tensor | None = None
    """[N] bool: the Gaussians no training image shows before the handover (``extrapolation.hold_unseen``);
    None: not looked for."""
    free_bodies: dict | None = None
    """``{"t0": handover, "labels": [N] long (0: the learned physics, k: body k - 1), "bodies": [K, 15]
    float64 (``FreeBody.as_tensor``)}``; None: not chosen."""
    joint_laws: dict | None = None
    """``{"t0": handover, "labels": [N] long (0: not a joint part, k: part k - 1), "parts": [one dict
    per part: "joint" ("hinge" or "slider"), "axis" [3] (the hinge's axis or the rail's direction),
    "pivot" [3] (zeros on a rail), "base_rotation" [3, 3], "base_translation" [3] (float64,
    ``physics/joint.py``), "model" (its coordinate's identified model, ``IdentifiedModel.to_dict``:
    terms, coefficients, contacts, its state at t0), "coordinate" (a chain's link: which of the
    model's coordinates is its own; absent: 0), "parent" (None, or the index of the part in whose
    frame it turns); a part on no joint (``"joint": "free"``, ``extrapolate/unjointed.py``) has
    instead "pivot" (its centre at t0), "basis" [k, 3] (the directions its model's coordinates move
    it along) and "spin" [3]; a thrown
    part (``"joint": "thrown"``, ``extrapolate/thrown.py``) "axis" (up), "pivot" (its centre at
    t0), "velocity" [3] (its drift along the floor) and "spin" [3]]}``
    (``extrapolate/joints.py``); None: none adopted, or not looked for (``extrapolation.joint_laws``)."""
    report: dict = field(default_factory=dict)
    """What the choices were made from, for ``summary.json``: ``freeze_psnr`` {threshold: training-view
    PSNR}, ``free_bodies`` [one entry per part backtested], ``joint_laws`` [one entry per part tried]."""
    cache: dict = field(default_factory=dict, repr=False, compare=False)
    """Derived data kept between renders (the surface painters of one handover state); never saved."""

    def to_dict(self) -> dict:
        """Plain tensors, numbers and strings: what ``torch.load(weights_only=True)`` reads back."""
        return {
            "version": STATE_VERSION,
            "t_max": float(self.t_max),
            "freeze_threshold": self.freeze_threshold,
            "unseen": self.unseen,
            "free_bodies": self.free_bodies,
            "joint_laws": self.joint_laws,
            "report": self.report,
        }

    @classmethod
    def from_dict(cls, data: dict, device: torch.device | str = "cpu") -> ExtrapolationState:
        """The state saved by :meth:`to_dict`; ValueError when its version or layout is another."""
        if data.get("version") not in READABLE_VERSIONS:
            raise ValueError(f"extrapolation state version {data.get('version')!r}, expected {STATE_VERSION}")
        bodies = data.get("free_bodies")
        if bodies is not None:
            if bodies["bodies"].shape[-1] != FREE_BODY_NUMBERS:
                raise ValueError(
                    f"free bodies of {bodies['bodies'].shape[-1]} numbers, expected {FREE_BODY_NUMBERS}"
                )
            bodies = {**bodies, "labels": bodies["labels"].to(device)}
        unseen, joints = data.get("unseen"), data.get("joint_laws")
        if joints is not None:
            joints = {**joints, "labels": joints["labels"].to(device)}
        return cls(
            t_max=float(data["t_max"]),
            freeze_threshold=data.get("freeze_threshold"),
            unseen=None if unseen is None else unseen.to(device),
            free_bodies=bodies,
            joint_laws=joints,
            report=data.get("report") or {},
        )
