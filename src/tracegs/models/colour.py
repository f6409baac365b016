"""Per-camera colour: a learned affine map of each training camera's rendered colours.

The cameras of a real rig differ in exposure, white balance and gain; one set of Gaussians cannot
match them all, and the fit spends Gaussians and fields on the difference (a wall lighter in one view
than in the next). As Dynamic 3D Gaussians does, each training camera c gets a gain and an offset per
channel, ``image_c = image * exp(log_gain_c) + offset_c``, learned with the rest; both start at the
identity. A camera never trained (a test camera, a viewer's) renders through the mean of the training
cameras' maps: the shared colours have no camera of their own (every camera's map may drift the same
way), and the mean map is the rig's average camera.

C: cameras.
"""

from __future__ import annotations

import torch
from torch import nn


class CameraColour(nn.Module):
    """Gains and offsets of the cameras ``camera_ids`` (the ids of ``Frame.camera_id``)."""

    def __init__(self, camera_ids: list[int]):
        super().__init__()
        ids = sorted({int(c) for c in camera_ids})
        self.register_buffer("camera_ids", torch.tensor(ids, dtype=torch.long))
        self.log_gain = nn.Parameter(torch.zeros(len(ids), 3))
        self.offset = nn.Parameter(torch.zeros(len(ids), 3))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # a run's cameras are known from its checkpoint: take their number from it before loading
        ids = state_dict.get(prefix + "camera_ids")
        if ids is not None and ids.shape != self.camera_ids.shape:
            self.camera_ids = torch.zeros_like(ids)
            self.log_gain = nn.Parameter(torch.zeros(len(ids), 3, device=self.log_gain.device))
            self.offset = nn.Parameter(torch.zeros(len(ids), 3, device=self.offset.device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def index(self, camera_id: int | None) -> int | None:
        """Row of ``camera_id``, or None for a camera that was not trained (or has no id)."""
        if camera_id is None:
            return None
        hit = torch.nonzero(self.camera_ids == int(camera_id))
        return int(hit[0, 0]) if len(hit) else None

    def forward(self, image: torch.Tensor, camera_id: int | None) -> torch.Tensor:
        """``image`` [H, W, 3] in the colours of camera ``camera_id``: its own map, or the mean map for a
        camera that was not trained (unchanged when none was)."""
        row = self.index(camera_id)
        if row is not None:
            return image * self.log_gain[row].exp() + self.offset[row]
        if len(self.camera_ids) == 0:
            return image
        return image * self.log_gain.mean(0).exp() + self.offset.mean(0)
