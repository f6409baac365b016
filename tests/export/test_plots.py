import numpy as np

from tracegs.export.plots import error_image


def test_error_image_is_gain_times_mean_abs_error_clipped():
    rng = np.random.default_rng(0)
    gt = rng.random((4, 5, 3))
    pred = gt.copy()
    pred[0, 0] += (0.03, -0.06, 0.0)  # mean |error| 0.03 -> 0.15 at gain 5
    pred[1, 2] = gt[1, 2] + 0.5  # 0.5 x 5 = 2.5 -> clipped to 1
    out = error_image(pred, gt, gain=5.0)
    assert out.shape == (4, 5, 3)
    np.testing.assert_allclose(out[0, 0], 0.15, atol=1e-12)
    np.testing.assert_allclose(out[1, 2], 1.0)
    out[0, 0] = out[1, 2] = 0.0
    assert np.abs(out).max() < 1e-12  # identical pixels have no error
