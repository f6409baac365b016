"""Procedural textures (numpy) for the synthetic scenes.

Every function returns a linear-RGB float32 image [H, W, 3] in [0, 1], ready for ``mi.Bitmap``.
Colours are given in sRGB (as one would pick them) and converted, because Mitsuba shades in linear
RGB. High-frequency patterns with some noise give the multi-view reconstruction something to lock
onto; each part of a scene gets a pattern and palette of its own so parts stay distinguishable.
"""

from __future__ import annotations

import numpy as np

Color = tuple[float, float, float]


def srgb_to_linear(c) -> np.ndarray:
    """The sRGB transfer function inverted (IEC 61966-2-1)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre coordinates u (columns) and v (rows) in [0, 1), each [size, size]."""
    x = (np.arange(size) + 0.5) / size
    return np.meshgrid(x, x, indexing="xy")


def _mix(mask: np.ndarray, c0: Color, c1: Color) -> np.ndarray:
    """[H, W, 3] linear colour: c0 where mask is 0, c1 where it is 1 (sRGB inputs)."""
    a, b = srgb_to_linear(c0), srgb_to_linear(c1)
    return (a + mask[..., None] * (b - a)).astype(np.float32)


def value_noise(size: int, cells: int, rng: np.random.Generator) -> np.ndarray:
    """[size, size] smooth noise in [0, 1]: random values on a periodic ``cells`` x ``cells`` lattice,
    interpolated with a smoothstep so the texture tiles without seams."""
    lattice = rng.random((cells, cells))
    x = np.arange(size) * cells / size
    i0 = np.floor(x).astype(int)
    f = x - i0
    f = f * f * (3 - 2 * f)
    i1 = (i0 + 1) % cells
    rows0 = lattice[i0][:, i0] * (1 - f)[None, :] + lattice[i0][:, i1] * f[None, :]
    rows1 = lattice[i1][:, i0] * (1 - f)[None, :] + lattice[i1][:, i1] * f[None, :]
    return rows0 * (1 - f)[:, None] + rows1 * f[:, None]


def fractal_noise(size: int, rng: np.random.Generator, octaves: int = 4, base_cells: int = 4) -> np.ndarray:
    """[size, size] sum of value-noise octaves, rescaled to [0, 1]."""
    total = sum(0.5**o * value_noise(size, base_cells * 2**o, rng) for o in range(octaves))
    return (total - total.min()) / max(total.max() - total.min(), 1e-9)


def with_noise(texture: np.ndarray, rng: np.random.Generator, amount: float = 0.25) -> np.ndarray:
    """``texture`` darkened by up to ``amount`` with fractal noise (a weathered look that also breaks
    the periodicity of checkers and stripes, so matches between views are unambiguous)."""
    n = fractal_noise(texture.shape[0], rng)
    return (texture * (1 - amount + amount * n[..., None])).astype(np.float32)


def checker(size: int, squares: int, c0: Color, c1: Color) -> np.ndarray:
    u, v = _grid(size)
    mask = (np.floor(u * squares) + np.floor(v * squares)) % 2
    return _mix(mask, c0, c1)


def stripes(
    size: int, count: int, c0: Color, c1: Color, along_u: bool = True, duty: float = 0.5
) -> np.ndarray:
    """``count`` stripes across u (``along_u``) or v; ``duty`` is the fraction of each period in c1."""
    u, v = _grid(size)
    x = u if along_u else v
    mask = ((x * count) % 1.0 < duty).astype(np.float64)
    return _mix(mask, c0, c1)


def palette_bands(size: int, colors: list[Color], along_u: bool = True) -> np.ndarray:
    """Equal bands of ``colors`` across u or v (beach-ball segments, multi-coloured blades)."""
    u, v = _grid(size)
    x = u if along_u else v
    idx = np.minimum((x * len(colors)).astype(int), len(colors) - 1)
    lin = srgb_to_linear(np.asarray(colors))
    return lin[idx].astype(np.float32)


def sectors(size: int, colors: list[Color], rim: Color | None = None, rim_width: float = 0.08) -> np.ndarray:
    """Pie sectors around the texture centre (spokes of a wheel seen on a cylinder cap), with an
    optional rim ring near the edge of the inscribed disk."""
    u, v = _grid(size)
    ang = np.arctan2(v - 0.5, u - 0.5) % (2 * np.pi)
    idx = np.minimum((ang / (2 * np.pi) * len(colors)).astype(int), len(colors) - 1)
    tex = srgb_to_linear(np.asarray(colors))[idx]
    if rim is not None:
        r = np.hypot(u - 0.5, v - 0.5) * 2
        tex[(r > 1 - rim_width) | (r < rim_width)] = srgb_to_linear(rim)
    return tex.astype(np.float32)


def cell_grid(size: int, cells: int, cell: Color, line: Color, line_width: float = 0.12) -> np.ndarray:
    """Square cells separated by lines (solar panels, grilles)."""
    u, v = _grid(size)
    fu, fv = (u * cells) % 1.0, (v * cells) % 1.0
    mask = ((fu < line_width) | (fv < line_width)).astype(np.float64)
    return _mix(mask, cell, line)


def wood(size: int, rng: np.random.Generator, light: Color, dark: Color, rings: float = 9.0) -> np.ndarray:
    """Wavy grain along u: stripes whose phase wanders with low-frequency noise."""
    u, v = _grid(size)
    wobble = fractal_noise(size, rng, octaves=3, base_cells=3)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (rings * v + 1.5 * wobble))
    return _mix(grain**2, light, dark)
