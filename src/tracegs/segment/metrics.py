"""Segmentation scores as NVFi and TRACE report them (the OGC protocol): AP, PQ, F1, precision, recall
at IoU 0.5, and mIoU, from label images.

Per image every predicted segment (a label present in the image) is matched to the ground-truth
segment it overlaps most; it is a true positive when that IoU is at least 0.5 (at that threshold a
match is unique, so greedy and Hungarian matching agree). Over a set of images the predictions are
pooled: precision = TP / predictions, recall = TP / ground-truth segments, F1 their harmonic mean,
PQ = sum of the true positives' IoU / (TP + FP / 2 + FN / 2), and AP the COCO 101-point area under
the precision-recall curve with the predictions ranked by their confidence. mIoU is the mean over
images of the mean IoU of the ground-truth segments under a one-to-one Hungarian matching
(``scipy.optimize.linear_sum_assignment``); an unmatched ground-truth segment counts 0.

Labels are ints per pixel; every distinct value, the background's included, is one segment.
H, W: image size.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

IOU_THRESHOLD = 0.5
METRICS = ("ap", "pq", "f1", "precision", "recall", "miou")


@dataclass
class ImageMatch:
    """One image's predictions against its ground truth."""

    iou: np.ndarray
    """[P] each predicted segment's best IoU with a ground-truth segment."""
    confidence: np.ndarray
    """[P] each predicted segment's confidence (the ranking of AP)."""
    n_truth: int
    """Ground-truth segments in the image."""
    miou: float
    """Mean IoU of the ground-truth segments under a one-to-one Hungarian matching."""


def iou_matrix(truth: np.ndarray, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IoU [G, P] between the ground-truth segments (rows) and predicted segments (columns) of two
    label images [H, W], with the labels of the rows and of the columns."""
    truth, pred = np.asarray(truth).ravel(), np.asarray(pred).ravel()
    if truth.shape != pred.shape:
        raise ValueError(f"label images of {truth.size} and {pred.size} pixels")
    t_ids, t_index = np.unique(truth, return_inverse=True)
    p_ids, p_index = np.unique(pred, return_inverse=True)
    inter = np.zeros((len(t_ids), len(p_ids)))
    np.add.at(inter, (t_index, p_index), 1.0)
    union = inter.sum(1, keepdims=True) + inter.sum(0, keepdims=True) - inter
    return inter / np.maximum(union, 1.0), t_ids, p_ids


def match_image(
    truth: np.ndarray, pred: np.ndarray, confidence: np.ndarray | None = None, ignore_pixels: int = 0
) -> ImageMatch:
    """Score the label image ``pred`` [H, W] against ``truth`` [H, W]; ``confidence`` [H, W] (e.g. the
    rendered weight of the winning label) ranks each predicted segment by its mean over the segment's
    pixels (OGC's confidence); without it every segment has confidence 1.

    ``ignore_pixels``: ground-truth segments of fewer pixels are left out, as OGC's
    ``ignore_npoint_thresh`` does (a part seen edge-on as a sliver): a prediction lying mostly on them
    is not counted, and their pixels leave every prediction's size."""
    iou, _, p_ids = iou_matrix(truth, pred)
    if confidence is None:
        conf = np.ones(len(p_ids))
    else:
        flat, labels = np.asarray(confidence, dtype=np.float64).ravel(), np.asarray(pred).ravel()
        index = np.searchsorted(p_ids, labels)
        conf = np.bincount(index, flat, len(p_ids)) / np.bincount(index, minlength=len(p_ids))
    if ignore_pixels > 0:
        iou, kept = _ignoring(truth, pred, ignore_pixels)
        conf = conf[np.isin(p_ids, kept)]
    if iou.shape[0] == 0:
        return ImageMatch(np.zeros(iou.shape[1]), conf, 0, float("nan"))
    rows, cols = linear_sum_assignment(iou, maximize=True)
    miou = float(iou[rows, cols].sum() / iou.shape[0])
    return ImageMatch(iou.max(axis=0), conf, iou.shape[0], miou)


def _ignoring(truth: np.ndarray, pred: np.ndarray, ignore_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """The IoU matrix and predicted ids of ``match_image`` without the ground-truth segments smaller
    than ``ignore_pixels`` (OGC's rule)."""
    truth, pred = np.asarray(truth).ravel(), np.asarray(pred).ravel()
    t_ids, t_index = np.unique(truth, return_inverse=True)
    p_ids, p_index = np.unique(pred, return_inverse=True)
    inter = np.zeros((len(t_ids), len(p_ids)))
    np.add.at(inter, (t_index, p_index), 1.0)
    t_size, p_size = inter.sum(1), inter.sum(0)
    small = t_size < ignore_pixels
    on_small = inter[small].sum(0)
    valid = (p_size - on_small > 0) & ~(on_small > 0.5 * p_size)
    inter = inter[~small][:, valid]
    p_size = (p_size - on_small)[valid]
    union = t_size[~small][:, None] + p_size[None, :] - inter
    return inter / np.maximum(union, 1.0), p_ids[valid]


def average_precision(matched: np.ndarray, confidence: np.ndarray, n_truth: int) -> float:
    """COCO 101-point AP of predictions ``matched`` [P] (1 = true positive) ranked by ``confidence`` [P]
    against ``n_truth`` ground-truth segments."""
    if n_truth == 0:
        return float("nan")
    order = np.argsort(-np.asarray(confidence, dtype=np.float64), kind="mergesort")
    hits = np.asarray(matched, dtype=np.float64)[order]
    tp = np.cumsum(hits)
    precision = tp / np.arange(1, len(hits) + 1)
    recall = tp / n_truth
    precision = np.maximum.accumulate(precision[::-1])[::-1]  # the precision envelope
    queried = np.searchsorted(recall, np.linspace(0.0, 1.0, 101), side="left")
    return float(np.mean([precision[i] if i < len(precision) else 0.0 for i in queried]))


@dataclass
class Scores:
    """Pooled scores of a set of images (``pool``)."""

    ap: float
    pq: float
    f1: float
    precision: float
    recall: float
    miou: float
    images: int
    per_image_miou: list[float] = field(default_factory=list, repr=False)

    def as_dict(self) -> dict:
        return {name: getattr(self, name) for name in (*METRICS, "images")}


def pool(matches: list[ImageMatch]) -> Scores:
    """AP, PQ, F1, precision, recall at IoU 0.5 over the predictions of every image, and the mean mIoU."""
    if not matches:
        nan = float("nan")
        return Scores(nan, nan, nan, nan, nan, nan, 0)
    iou = np.concatenate([m.iou for m in matches])
    conf = np.concatenate([m.confidence for m in matches])
    n_truth = sum(m.n_truth for m in matches)
    hit = iou >= IOU_THRESHOLD
    tp = float(hit.sum())
    fp, fn = len(iou) - tp, n_truth - tp
    precision = tp / max(tp + fp, 1e-12)
    recall = tp / max(tp + fn, 1e-12)
    f1 = 2 * precision * recall / max(precision + recall, 1e-12)
    pq = float(iou[hit].sum()) / max(tp + 0.5 * fp + 0.5 * fn, 1e-12)
    per_image = [m.miou for m in matches]
    return Scores(
        average_precision(hit, conf, n_truth),
        pq,
        f1,
        precision,
        recall,
        float(np.nanmean(per_image)) if not np.isnan(per_image).all() else float("nan"),
        len(matches),
        per_image,
    )
