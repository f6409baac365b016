"""The segmentation scores on constructed label images whose AP, PQ, F1, precision, recall and mIoU
are worked out by hand (docs/SEGMENTATION.md gives the definitions)."""

from __future__ import annotations

import numpy as np
import pytest

from tracegs.segment.metrics import average_precision, iou_matrix, match_image, pool


def image(sizes: dict[int, int]) -> np.ndarray:
    """A 10 x 10 label image with ``sizes[label]`` pixels of each label, in row-major runs."""
    flat = np.concatenate([np.full(n, label) for label, n in sizes.items()])
    assert flat.size == 100
    return flat.reshape(10, 10)


TRUTH = image({1: 60, 2: 20, 0: 20})  # part A 60 px, part B 20 px, background 20 px


def scores(pred, confidence=None, truth=TRUTH):
    return pool([match_image(truth, pred, confidence)]).as_dict()


def test_perfect_and_swapped_labels_score_one():
    for pred in (TRUTH, np.choose(TRUTH, [7, 3, 5])):  # the labels' names do not matter
        s = scores(pred)
        for name in ("ap", "pq", "f1", "precision", "recall", "miou"):
            assert s[name] == pytest.approx(1.0), name


def test_one_merged_segment():
    pred = np.where(TRUTH == 2, 1, TRUTH)  # B painted as A: one segment of 80 px
    s = scores(pred)
    # the merged segment matches A at IoU 60/80; B is missed: TP 2, FP 0, FN 1
    assert s["precision"] == pytest.approx(1.0)
    assert s["recall"] == pytest.approx(2 / 3)
    assert s["f1"] == pytest.approx(0.8)
    assert s["pq"] == pytest.approx((0.75 + 1.0) / (2 + 0.5))
    assert s["miou"] == pytest.approx((0.75 + 0.0 + 1.0) / 3)
    assert s["ap"] == pytest.approx(67 / 101)  # precision 1 up to recall 2/3: 67 of the 101 points


def test_one_missed_segment():
    truth = image({1: 50, 2: 20, 0: 30})
    pred = np.where(truth == 2, 0, truth)  # B rendered as background
    s = scores(pred, truth=truth)
    # background' (50 px) matches the background at 30/50; B is missed
    assert s["recall"] == pytest.approx(2 / 3)
    assert s["precision"] == pytest.approx(1.0)
    assert s["pq"] == pytest.approx((1.0 + 0.6) / 2.5)
    assert s["miou"] == pytest.approx((1.0 + 0.6) / 3)  # Hungarian: B and background both want it


def test_an_extra_segment_and_the_confidence_ranking():
    pred = TRUTH.copy()
    pred.ravel()[40:60] = 9  # A split into 40 px (IoU 2/3, a match) and an extra 20 px (IoU 1/3)
    s = scores(pred)
    assert s["precision"] == pytest.approx(0.75)
    assert s["recall"] == pytest.approx(1.0)
    assert s["f1"] == pytest.approx(2 * 0.75 / 1.75)
    assert s["pq"] == pytest.approx((2 / 3 + 1 + 1) / 3.5)
    assert s["miou"] == pytest.approx((2 / 3 + 1 + 1) / 3)
    # AP: ranked last, the false positive costs nothing; ranked first, it caps the precision at 3/4
    low = np.where(pred == 9, 0.2, 0.9)
    high = np.where(pred == 9, 0.99, 0.9)
    assert scores(pred, low)["ap"] == pytest.approx(1.0)
    assert scores(pred, high)["ap"] == pytest.approx(0.75)


def test_pooling_counts_every_image_and_averages_miou():
    a = match_image(TRUTH, TRUTH)
    b = match_image(TRUTH, np.where(TRUTH == 2, 1, TRUTH))
    s = pool([a, b]).as_dict()
    assert s["images"] == 2
    assert s["recall"] == pytest.approx(5 / 6)  # 5 of the 6 ground-truth segments found
    assert s["miou"] == pytest.approx((1.0 + 1.75 / 3) / 2)


def test_average_precision_edge_cases_and_iou_shapes():
    assert average_precision(np.array([1, 1]), np.array([0.5, 0.4]), 2) == pytest.approx(1.0)
    assert average_precision(np.array([0, 0]), np.array([0.5, 0.4]), 2) == 0.0
    assert np.isnan(average_precision(np.array([]), np.array([]), 0))
    iou, rows, cols = iou_matrix(TRUTH, TRUTH)
    assert iou.shape == (3, 3) and list(rows) == [0, 1, 2] and np.allclose(np.diag(iou), 1.0)
    with pytest.raises(ValueError, match="pixels"):
        iou_matrix(TRUTH, TRUTH[:5])


def test_ignoring_small_ground_truth_segments_as_ogc_does():
    truth = image({1: 60, 2: 37, 3: 3})  # part 3 a sliver of 3 px
    pred = np.where(truth == 3, 1, truth)  # painted as part 1: missed
    strict = pool([match_image(truth, pred)]).as_dict()
    assert strict["recall"] == pytest.approx(2 / 3)
    lenient = pool([match_image(truth, pred, ignore_pixels=5)]).as_dict()
    assert lenient["recall"] == pytest.approx(1.0) and lenient["precision"] == pytest.approx(1.0)
    assert lenient["miou"] == pytest.approx(1.0)  # the sliver's pixels leave part 1's prediction
    only_small = match_image(image({1: 98, 2: 2}), image({1: 98, 2: 2}), ignore_pixels=50)
    assert only_small.n_truth == 1
