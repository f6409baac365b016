"""Motion segmentation from the learned physics (paper Section 4.3): ``tracegs segment``.

``features.py`` (what is clustered), ``cluster.py`` (K-means, smoothing, the choice of K),
``masks.py`` (label masks through the rasteriser), ``truth.py`` (the ground-truth layout),
``metrics.py`` (AP, PQ, F1, precision, recall, mIoU), ``score.py`` (a run against the ground truth),
``command.py`` (the command and its outputs).

The names below are imported on first use, so that the CLI reads ``SegmentConfig`` without torch.
"""

from importlib import import_module

_WHERE = {
    "SegmentConfig": "config",
    "MotionFeatures": "features",
    "SegmentError": "features",
    "motion_features": "features",
    "Segmentation": "cluster",
    "choose_k": "cluster",
    "segment": "cluster",
    "match_image": "metrics",
    "pool": "metrics",
    "load_segments": "command",
    "segment_run": "command",
}
__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
