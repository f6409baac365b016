"""Mitsuba 3 rendering of a :class:`~tracegs.data.synth.scenes.SceneSpec`: RGBA images and part masks.

Uses the ``scalar_rgb`` variant, which every Mitsuba wheel ships and which renders the same bytes
on every run (image blocks are seeded by their index and, with a box filter, never overlap, so the
thread schedule cannot change a sum). Shading: textured Lambertian (``diffuse``, two-sided so thin
panels look the same from both sides) under a constant sky plus a sun, direct light only; emitters
are hidden so the background has alpha 0. Part masks come from a second pass with the ``aov``
integrator's ``shape_index`` at one ray through each pixel centre, mapped to part ids.

Mitsuba's camera looks along its local +z with +y up and +x to the left of the image; a Blender /
OpenGL camera-to-world (x right, y up, z backward) becomes a Mitsuba ``to_world`` by negating its
x and z axes.

# H, W: image size, P: parts
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scenes import SceneSpec

VARIANT = "scalar_rgb"
OPENGL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])


@dataclass(frozen=True)
class Lighting:
    """A constant sky and one sun; values in linear RGB."""

    sky_radiance: float = 0.42
    """Radiance of the constant environment (the shade side of every part still shows its texture)."""
    sun_irradiance: float = 1.9
    """Irradiance of the directional light on a surface facing it."""
    sun_direction: tuple[float, float, float] = (-0.35, -0.5, -1.0)
    """Direction the sunlight travels (from high up, slanted so faces of a box differ in shade)."""


def mitsuba():
    """The ``mitsuba`` module with the scalar RGB variant selected."""
    import mitsuba as mi

    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


@dataclass
class MitsubaScene:
    """A loaded Mitsuba scene plus what is needed to pose it at a time and decode its masks."""

    scene: object  # mi.Scene
    params: object  # mi.SceneParameters, to move the vertices
    rest_vertices: list[tuple[str, int, np.ndarray]]  # (shape id, part index, [V, 3] rest pose)
    shape_to_part_id: np.ndarray  # [S + 1] uint8: AOV shape index -> part id (0 = background)
    mask_integrator: object  # mi.Integrator writing the shape index of the first hit


def _shape_id(part: int, piece: int) -> str:
    return f"part{part + 1}_piece{piece}"


def _mesh(mi, name: str, mesh, texture: np.ndarray):
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(
        {
            "type": "twosided",
            "material": {
                "type": "diffuse",
                "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(texture))},
            },
        }
    )
    shape = mi.Mesh(
        name,
        len(mesh.vertices),
        len(mesh.faces),
        props=props,
        has_vertex_normals=True,
        has_vertex_texcoords=True,
    )
    p = mi.traverse(shape)
    p["vertex_positions"] = mesh.vertices.ravel()
    p["faces"] = mesh.faces.ravel()
    p["vertex_texcoords"] = mesh.uvs.ravel()
    p.update()  # also computes smooth vertex normals (hard edges have their own vertices)
    return shape


def build_scene(spec: SceneSpec, lighting: Lighting = Lighting()) -> MitsubaScene:
    """Load every piece of every part in its rest pose, with lights and a direct-light integrator."""
    mi = mitsuba()
    d = {
        "type": "scene",
        # max_depth 2 = camera ray + direct light; no interreflection noise to learn.
        "integrator": {"type": "path", "max_depth": 2, "hide_emitters": True},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": lighting.sky_radiance}},
        "sun": {
            "type": "directional",
            "direction": list(lighting.sun_direction),
            "irradiance": {"type": "rgb", "value": lighting.sun_irradiance},
        },
    }
    rest = []
    for p, part in enumerate(spec.parts):
        for k, piece in enumerate(part.pieces):
            sid = _shape_id(p, k)
            d[sid] = _mesh(mi, sid, piece.mesh, piece.texture)
            rest.append((sid, p, piece.mesh.vertices.astype(np.float64)))
    scene = mi.load_dict(d)
    part_of = {sid: p + 1 for sid, p, _ in rest}
    # shape_index is 1 + the position in scene.shapes(); read the order back rather than assume it.
    lut = np.zeros(len(scene.shapes()) + 1, dtype=np.uint8)
    for i, shape in enumerate(scene.shapes()):
        lut[i + 1] = part_of[shape.id()]
    mask_integrator = mi.load_dict({"type": "aov", "aovs": "sid:shape_index"})
    return MitsubaScene(scene, mi.traverse(scene), rest, lut, mask_integrator)


def pose(ms: MitsubaScene, transforms: np.ndarray) -> None:
    """Move every part by its rest -> world transform ``transforms`` [P, 4, 4] (in place)."""
    for sid, p, v in ms.rest_vertices:
        m = transforms[p]
        ms.params[f"{sid}.vertex_positions"] = (v @ m[:3, :3].T + m[:3, 3]).astype(np.float32).ravel()
    ms.params.update()


def make_sensors(c2w_opengl: np.ndarray, camera_angle_x: float, resolution: int, spp: int) -> tuple:
    """(colour sensor, mask sensor) for one camera. The colour sensor averages ``spp`` random
    samples per pixel with a box filter (anti-aliasing that stays inside the pixel); the mask sensor
    shoots one ray through the pixel centre, the convention of the project's cameras."""
    mi = mitsuba()
    to_world = mi.ScalarTransform4f(np.asarray(c2w_opengl, dtype=np.float64) @ OPENGL_TO_MITSUBA)
    common = {
        "type": "perspective",
        "fov": float(np.rad2deg(camera_angle_x)),
        "fov_axis": "x",
        "near_clip": 0.01,
        "to_world": to_world,
    }
    film = {
        "type": "hdrfilm",
        "width": resolution,
        "height": resolution,
        "pixel_format": "rgba",
        "rfilter": {"type": "box"},
    }
    color = mi.load_dict({**common, "film": film, "sampler": {"type": "independent", "sample_count": spp}})
    mask = mi.load_dict(
        {**common, "film": film, "sampler": {"type": "stratified", "sample_count": 1, "jitter": False}}
    )
    return color, mask


def render_rgba(ms: MitsubaScene, sensor, seed: int) -> np.ndarray:
    """[H, W, 4] float32 linear RGB premultiplied by alpha (coverage of the pixel by the object)."""
    img = np.array(mitsuba().render(ms.scene, sensor=sensor, seed=seed), dtype=np.float32)
    return img[..., :4]


def render_part_ids(ms: MitsubaScene, sensor) -> np.ndarray:
    """[H, W] uint8 part id of the surface seen through each pixel centre, 0 for background."""
    img = np.array(mitsuba().render(ms.scene, sensor=sensor, integrator=ms.mask_integrator, seed=0))
    shape_index = np.rint(img[..., -1]).astype(np.int64)
    return ms.shape_to_part_id[shape_index]


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def to_srgb8(rgba: np.ndarray) -> np.ndarray:
    """[H, W, 4] premultiplied linear float -> straight-alpha sRGB uint8, as Blender writes PNGs
    (readers composite ``rgb * a + background * (1 - a)``)."""
    alpha = np.clip(rgba[..., 3:4], 0.0, 1.0)
    straight = np.where(alpha > 1e-6, rgba[..., :3] / np.maximum(alpha, 1e-6), 0.0)
    out = np.concatenate([linear_to_srgb(straight), alpha], -1)
    return np.rint(out * 255).astype(np.uint8)
