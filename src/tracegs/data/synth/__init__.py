"""Synthetic multi-part dynamic scenes with ground-truth physics, rendered with Mitsuba 3.

``synthesize(scene, out)`` writes a Blender / D-NeRF style dataset following the Dynamic Multipart
protocol (cameras x frames, train / interpolation / extrapolation splits) plus ground truth: part
masks, closed-form motion, per-frame part transforms and a rest-pose point cloud.
``part_transforms(out, t)`` evaluates the closed-form motion at any time. See ``docs/SYNTH.md``.
"""

from .motion import part_transforms
from .scenes import SCENES
from .writer import synthesize

__all__ = ["SCENES", "part_transforms", "synthesize"]
