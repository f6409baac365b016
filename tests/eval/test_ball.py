"""The ball detector on synthetic images: a shaded, anti-aliased ball of known centre and radius on a
grey textured wall with a skin-coloured arm and a white light bar."""

import numpy as np
import pytest

from tracegs.eval.ball import BallSettings, ball_colour, detect_ball, fit_circle, hsv

BALL = np.array([0.78, 0.27, 0.16])  # the basketball's orange-red (hue about 10 degrees)
SKIN = np.array([0.80, 0.60, 0.45])  # hue about 26 degrees
SUPER = 4  # samples per pixel side for the anti-aliased edges


def scene(H: int, W: int, seed: int = 0) -> np.ndarray:
    """[H, W, 3] a grey wall with a texture of dark dots, a skin-coloured arm and a white light bar."""
    rng = np.random.default_rng(seed)
    wall = 0.55 + 0.04 * rng.standard_normal((H, W, 1)) * np.ones(3)
    wall *= np.array([0.97, 1.0, 0.95])  # the dome's faint green-grey
    yy, xx = np.mgrid[:H, :W] / H
    for cy, cx in rng.uniform(0, 1, (30, 2)) * (1, W / H):
        wall[(yy - cy) ** 2 + (xx - cx) ** 2 < 0.012**2] = 0.08
    arm = ((yy - 0.7) / 0.06) ** 2 + ((xx - 0.25) / 0.18) ** 2 < 1  # an ellipse of skin
    wall[arm] = SKIN * (0.7 + 0.3 * xx[arm, None] / xx.max())
    wall[(yy > 0.88) & (yy < 0.92) & (xx > 0.9) & (xx < 1.3)] = 1.0  # a light bar
    return wall.clip(0, 1)


def draw_ball(image: np.ndarray, cx: float, cy: float, r: float, occluder=None) -> np.ndarray:
    """``image`` with a ball of centre (cx, cy) (pixel centres at integers) and radius r drawn over it:
    shaded from its upper left (x 0.5 to 1), its edge anti-aliased by supersampling; ``occluder`` (a
    function of x, y -> bool) hides the ball where true."""
    H, W = image.shape[:2]
    off = (np.arange(SUPER) + 0.5) / SUPER - 0.5
    ys = (np.arange(H)[:, None] + off[None, :]).reshape(-1)
    xs = (np.arange(W)[:, None] + off[None, :]).reshape(-1)
    Y, X = np.meshgrid(ys, xs, indexing="ij")
    inside = (X - cx) ** 2 + (Y - cy) ** 2 <= r**2
    if occluder is not None:
        inside &= ~occluder(X, Y)
    cover = inside.reshape(H, SUPER, W, SUPER).mean(axis=(1, 3))
    shade = 0.75 - 0.25 * ((X - cx) + (Y - cy)) / (np.sqrt(2) * r)
    shade = np.where(inside, shade, 0).reshape(H, SUPER, W, SUPER).sum(axis=(1, 3))
    shade = shade / np.maximum(cover * SUPER * SUPER, 1)
    ball = BALL * shade[..., None]
    return image * (1 - cover[..., None]) + ball * cover[..., None]


@pytest.mark.parametrize("scale", [1, 2])
@pytest.mark.parametrize("centre", [(201.3, 62.7), (90.6, 120.2)])
def test_the_centre_within_a_pixel_at_two_scales(scale, centre):
    H, W, r = 180 * scale, 320 * scale, 8.0 * scale
    cx, cy = centre[0] * scale, centre[1] * scale
    found = detect_ball(draw_ball(scene(H, W), cx, cy, r))
    assert found is not None
    assert np.hypot(found.centre_xy[0] - cx, found.centre_xy[1] - cy) < 1.0
    assert abs(found.radius_px - r) < 1.0 * scale
    assert 0.6 <= found.score <= 1.0


def test_no_ball_is_none_though_skin_and_lights_are_there():
    image = scene(180, 320)
    assert not ball_colour(image).any()
    assert detect_ball(image) is None


def test_a_ball_too_small_for_the_scale_is_none():
    # a ball of radius 4 px is one at 180 px high, but a speck at 720 px high
    assert detect_ball(draw_ball(scene(180, 320), 150.2, 80.4, 4.5)) is not None
    assert detect_ball(draw_ball(scene(720, 1280), 600.2, 320.4, 4.5)) is None


@pytest.mark.parametrize("cy", [2.0, -3.0, 4.5])
def test_a_ball_cut_by_the_edge_is_near_or_none(cy):
    cx, r = 160.4, 9.0
    found = detect_ball(draw_ball(scene(180, 320), cx, cy, r))
    if found is not None:
        assert np.hypot(found.centre_xy[0] - cx, found.centre_xy[1] - cy) < 3.0


def test_a_ball_mostly_in_view_at_the_edge_is_found():
    cx, cy, r = 314.6, 90.3, 9.0  # a third of it past the right edge
    found = detect_ball(draw_ball(scene(180, 320), cx, cy, r))
    assert found is not None
    assert np.hypot(found.centre_xy[0] - cx, found.centre_xy[1] - cy) < 1.5


@pytest.mark.parametrize("side", ["left", "top", "quarter"])
def test_a_half_hidden_ball_is_near_or_none(side):
    cx, cy, r = 160.4, 70.6, 9.0
    hide = {
        "left": lambda X, Y: X < cx,
        "top": lambda X, Y: Y < cy,
        "quarter": lambda X, Y: (X < cx) & (Y < cy),
    }[side]
    found = detect_ball(draw_ball(scene(180, 320), cx, cy, r, occluder=hide))
    if found is not None:
        assert np.hypot(found.centre_xy[0] - cx, found.centre_xy[1] - cy) < 4.0


def test_the_mask_of_moving_pixels_limits_the_search():
    image = draw_ball(scene(180, 320), 100.5, 60.5, 8.0)
    moving = np.zeros((180, 320), bool)
    assert detect_ball(image, moving) is None
    moving[40:80, 80:120] = True
    assert detect_ball(image, moving) is not None
    with pytest.raises(ValueError, match="mask"):
        detect_ball(image, np.ones((90, 160), bool))


def test_two_balls_are_ambiguous():
    image = draw_ball(draw_ball(scene(180, 320), 100.5, 60.5, 8.0), 220.5, 60.5, 8.0)
    assert detect_ball(image) is None
    assert detect_ball(image, settings=BallSettings(ambiguity=0.0)) is not None


def test_hsv_and_the_circle_fit():
    hue, sat, val = hsv(np.array([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.5, 0.5], [1.0, 0.0, 0.5]]]))
    assert np.allclose(hue[0], [0, 120, 0, -30])
    assert np.allclose(sat[0], [1, 1, 0, 1]) and np.allclose(val[0], [1, 1, 0.5, 1])
    a = np.linspace(0, np.pi, 40)
    cx, cy, r, rms = fit_circle(3.0 + 5 * np.cos(a), -2.0 + 5 * np.sin(a))
    assert np.allclose([cx, cy, r], [3, -2, 5]) and rms < 1e-9
