"""A basketball's centre in an image, found by its colour and its shape: the ball detector of the
``ball`` benchmark (``benchmarks/ball.py``), which scores where a run's renders put the ball against
where the captured images show it, with the same detector on both.

The ball is a saturated orange-red against the grey dome, its white lights and the people. A pixel is
the ball's colour (``ball_colour``, the defaults of ``BallSettings``) where its hue lies within
``hue`` = (-20, 20) degrees of red (0 degrees; the grey dome's hue is about 40-70 degrees, skin's
about 15-35), its HSV saturation is at least ``saturation`` = 0.35 (the ball's is 0.4-0.7, the dome's
and the lights' below 0.25) and its value at least ``value`` = 0.2 (the dark camera holes of the dome
have no reliable hue). Hue and saturation do not change when a colour is scaled, so the ball's shaded
side passes as its lit side does. Then (``detect_ball``):

1. the ball's colour, within ``moving`` when a mask of moving pixels is given, is closed by a 3x3
   square (the ball's dark seams do not split it), its holes are filled (a highlight) and it is opened
   by a disc of radius ``opening`` = 2 pixels (thin bridges to a hand or a face are cut);
2. a connected region inside the image is a candidate when its radius (that of a disc of its area)
   lies within ``radius`` = (4, 20) pixels, it is round (its area over that of the circle about its
   centroid that encloses it, at least ``roundness`` = 0.6: a disc gives about 1, half a disc 0.43) and
   filled (its pixels of the ball's colour over its area, at least ``fill`` = 0.6); its centre is its
   centroid;
3. a region that touches the image's edge is a candidate when a circle fitted to its outline off the
   edge (``fit_circle``; its rms residual at most a tenth of its radius) has a radius within
   ``radius``, the image shows at least ``visible`` = 0.5 of its area, the region and the circle's
   disc overlap by at least ``roundness`` (intersection over union) and the region is filled; its
   centre is the circle's, which may lie outside the image;
4. the candidate of highest score (roundness x fill) is the ball; none, or a runner-up scoring within
   ``ambiguity`` = 0.1 of it (two balls?), gives None.

Pixel sizes are those of an image ``reference_height`` = 180 pixels high (CMU Panoptic's 640x360 at
``--downscale 2``, where the ball's radius is 5-15 pixels) and scale with the image's height.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# H, W: image size


@dataclass
class BallSettings:
    """The ball's colour and shape (the module docstring); pixel sizes at ``reference_height``."""

    hue: tuple[float, float] = (-20.0, 20.0)
    """The ball's hues, in degrees from red (negative: towards magenta)."""
    saturation: float = 0.35
    """The least HSV saturation of the ball's colour (max - min over max of the channels)."""
    value: float = 0.2
    """The least HSV value (the largest channel) of the ball's colour, in [0, 1]."""
    radius: tuple[float, float] = (4.0, 20.0)
    """The least and largest radius of the ball (of a disc of its area), in pixels at
    ``reference_height``."""
    roundness: float = 0.6
    """The least area of a candidate over that of the circle about its centroid that encloses it."""
    fill: float = 0.6
    """The least share of a candidate's area that has the ball's colour (the rest: seams, highlights)."""
    ambiguity: float = 0.1
    """No ball when a second candidate scores within this of the best one."""
    opening: float = 2.0
    """The regions are opened by a disc of this radius in pixels (thin bridges to skin are cut)."""
    visible: float = 0.5
    """A ball cut by the image's edge: the least share of its fitted circle's area that the image shows."""
    reference_height: int = 180
    """The image height at which the pixel sizes hold; they scale with an image's height."""


@dataclass
class BallDetection:
    """Where the ball is in an image: ``centre_xy`` (x right, y down, pixels; a pixel's centre at
    integers), ``radius_px`` (a disc of its area) and ``score`` (roundness x fill, in [0, 1])."""

    centre_xy: tuple[float, float]
    radius_px: float
    score: float


def hsv(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(hue in degrees in (-180, 180], red at 0; saturation; value) [H, W] each of ``image`` [H, W, 3]
    RGB in [0, 1]."""
    rgb = np.asarray(image, dtype=np.float32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    top, low = rgb.max(-1), rgb.min(-1)
    span = top - low
    safe = np.where(span > 0, span, 1.0)
    hue = np.where(top == r, (g - b) / safe, np.where(top == g, 2.0 + (b - r) / safe, 4.0 + (r - g) / safe))
    hue = np.where(span > 0, hue * 60.0, 0.0)
    hue = np.where(hue > 180.0, hue - 360.0, hue)
    saturation = np.where(top > 0, span / np.where(top > 0, top, 1.0), 0.0)
    return hue, saturation, top


def ball_colour(image: np.ndarray, settings: BallSettings | None = None) -> np.ndarray:
    """[H, W] bool: the pixels of ``image`` [H, W, 3] in the ball's colour window (the module docstring)."""
    s = settings or BallSettings()
    hue, saturation, value = hsv(image)
    return (hue >= s.hue[0]) & (hue <= s.hue[1]) & (saturation >= s.saturation) & (value >= s.value)


def _disc(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return r[:, None] ** 2 + r[None, :] ** 2 <= radius**2


def fit_circle(xs: np.ndarray, ys: np.ndarray) -> tuple[float, float, float, float]:
    """(centre x, centre y, radius, rms distance of the points from it) of the circle that fits the
    points ``xs``, ``ys`` [P] best in the algebraic least-squares sense (Kasa's fit)."""
    A = np.stack([xs, ys, np.ones_like(xs)], axis=1).astype(np.float64)
    b = xs.astype(np.float64) ** 2 + ys.astype(np.float64) ** 2
    (a, c, d), *_ = np.linalg.lstsq(A, b, rcond=None)
    cx, cy = a / 2, c / 2
    radius = float(np.sqrt(max(d + cx**2 + cy**2, 0.0)))
    rms = float(np.sqrt(np.mean((np.hypot(xs - cx, ys - cy) - radius) ** 2)))
    return float(cx), float(cy), radius, rms


def _candidate(region: np.ndarray, colour: np.ndarray, settings: BallSettings, scale: float):
    """(score, centre_xy, radius) of a connected ``region`` [H, W] bool that does not touch the image's
    edge, with the ball's colour ``colour`` [H, W], or None when it is not ball-like (rule 2 of the
    module docstring)."""
    area = float(region.sum())
    radius = float(np.sqrt(area / np.pi))
    if not settings.radius[0] * scale <= radius <= settings.radius[1] * scale:
        return None
    ys, xs = np.nonzero(region)
    cy, cx = ys.mean(), xs.mean()
    enclosing = float(np.sqrt(((ys - cy) ** 2 + (xs - cx) ** 2).max())) + 0.5  # to the pixels' edges
    roundness = min(area / (np.pi * enclosing**2), 1.0)
    fill = float(colour[region].mean())
    if roundness < settings.roundness or fill < settings.fill:
        return None
    return roundness * fill, (float(cx), float(cy)), radius


def _cut_candidate(region: np.ndarray, colour: np.ndarray, settings: BallSettings, scale: float):
    """(score, centre_xy, radius) of a connected ``region`` [H, W] bool that touches the image's edge: a
    circle fitted to its outline off the edge (rule 3 of the module docstring), or None."""
    from scipy import ndimage

    H, W = region.shape
    outline = region & ~ndimage.binary_erosion(region, border_value=1)
    outline[[0, -1], :] = False
    outline[:, [0, -1]] = False
    ys, xs = np.nonzero(outline)
    if len(xs) < 8:
        return None
    cx, cy, radius, rms = fit_circle(xs, ys)
    radius += 0.5  # the outline's pixel centres lie half a pixel inside the ball's edge
    if not settings.radius[0] * scale <= radius <= settings.radius[1] * scale or rms > 0.1 * radius:
        return None
    area = float(region.sum())
    gy, gx = np.mgrid[:H, :W]
    disc = (gx - cx) ** 2 + (gy - cy) ** 2 <= radius**2  # the fitted ball, as far as the image shows it
    visible = area / (np.pi * radius**2)
    roundness = float((disc & region).sum()) / float((disc | region).sum())
    fill = float(colour[region].mean())
    if visible < settings.visible or roundness < settings.roundness or fill < settings.fill:
        return None
    return roundness * fill, (cx, cy), radius


def detect_ball(
    image: np.ndarray, moving: np.ndarray | None = None, settings: BallSettings | None = None
) -> BallDetection | None:
    """The ball in ``image`` [H, W, 3] RGB in [0, 1], searched within ``moving`` [H, W] bool (the pixels
    that move, e.g. ``data.motion_masks``; None: everywhere); None when no region is ball-like or two
    are (the rules of the module docstring)."""
    from scipy import ndimage

    s = settings or BallSettings()
    image = np.asarray(image, dtype=np.float32)
    H, W = image.shape[:2]
    scale = H / s.reference_height
    colour = ball_colour(image, s)
    if moving is not None:
        if moving.shape != (H, W):
            raise ValueError(f"the mask of moving pixels is {moving.shape}, the image {(H, W)}")
        colour &= moving
    if not colour.any():
        return None
    regions = ndimage.binary_closing(colour, structure=np.ones((3, 3), bool), border_value=0) | colour
    regions = ndimage.binary_fill_holes(regions)
    opening = max(1, round(s.opening * scale))
    regions = ndimage.binary_opening(regions, structure=_disc(opening))
    labels, _ = ndimage.label(regions)
    edge = set(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]).tolist())
    found = []
    for i in range(1, labels.max() + 1):
        region = labels == i
        judge = _cut_candidate if i in edge else _candidate
        candidate = judge(region, colour, s, scale)
        if candidate is not None:
            found.append(candidate)
    if not found:
        return None
    found.sort(key=lambda c: -c[0])
    if len(found) > 1 and found[1][0] > found[0][0] - s.ambiguity:
        return None
    score, centre, radius = found[0]
    return BallDetection(centre, radius, score)
