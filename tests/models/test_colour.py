"""Per-camera colour recovers a known gain and offset, and leaves untrained cameras alone."""

from __future__ import annotations

import torch

from tracegs.models.colour import CameraColour


def test_camera_colour_recovers_a_known_gain_and_offset():
    g = torch.Generator().manual_seed(0)
    shared = torch.rand(16, 16, 3, generator=g)
    gain = {3: torch.tensor([1.3, 0.8, 1.1]), 7: torch.tensor([0.9, 1.0, 1.2])}
    offset = {3: torch.tensor([0.05, -0.02, 0.0]), 7: torch.tensor([-0.04, 0.03, 0.02])}
    seen = {c: shared * gain[c] + offset[c] for c in gain}
    colour = CameraColour([7, 3, 3])
    opt = torch.optim.Adam(colour.parameters(), lr=0.02)
    for _ in range(1500):
        opt.zero_grad()
        loss = sum((colour(shared, c) - seen[c]).square().mean() for c in gain)
        loss.backward()
        opt.step()
    for c in gain:
        row = colour.index(c)
        assert torch.allclose(colour.log_gain[row].exp().detach(), gain[c], atol=2e-3)
        assert torch.allclose(colour.offset[row].detach(), offset[c], atol=2e-3)
    # a camera never trained takes the mean map, the rig's average camera
    mean = shared * colour.log_gain.mean(0).exp() + colour.offset.mean(0)
    assert torch.allclose(colour(shared, 11), mean) and torch.allclose(colour(shared, None), mean)
    assert torch.equal(CameraColour([])(shared, 11), shared)


def test_camera_colour_starts_at_the_identity():
    image = torch.rand(4, 4, 3)
    assert torch.equal(CameraColour([0, 1])(image, 1), image)
