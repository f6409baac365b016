"""Tests of ``tracegs synth``: dataset files, masks, ground-truth geometry and motion, determinism.

Small renders (32 px, 3 cameras, 4 frames, few samples) keep the whole module at a few seconds.
"""

from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

pytest.importorskip("mitsuba")

from tracegs.data.synth import SCENES, part_transforms, synthesize  # noqa: E402
from tracegs.data.synth.cameras import fibonacci_band, make_split  # noqa: E402
from tracegs.data.synth.geometry import box, cylinder, sphere  # noqa: E402
from tracegs.data.synth.scenes import get_scene  # noqa: E402
from tracegs.data.synth.writer import motion_bounds  # noqa: E402

RES, VIEWS, FRAMES, SPP = 32, 3, 4, 4
SPLITS = ("train", "val", "test")


def _make(tmp_path_factory, scene: str, **kw) -> Path:
    out = tmp_path_factory.mktemp(scene) / "data"
    args = {"resolution": RES, "views": VIEWS, "frames": FRAMES, "progress": False, "spp": SPP}
    return synthesize(scene, out, **{**args, **kw})


@pytest.fixture(scope="module")
def fan_dir(tmp_path_factory) -> Path:
    return _make(tmp_path_factory, "fan")


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """scene name -> its folder at 40 px, rendered once per test module."""
    cache = {}

    def get(scene: str) -> Path:
        if scene not in cache:
            cache[scene] = _make(tmp_path_factory, scene, resolution=40)
        return cache[scene]

    return get


@pytest.fixture(params=sorted(SCENES))
def scene_dir(request, rendered) -> Path:
    return rendered(request.param)


def _frames(root: Path):
    """(split, frame entry, top-level json) for every image of the folder."""
    for split in SPLITS:
        top = json.loads((root / f"transforms_{split}.json").read_text())
        for fr in top["frames"]:
            yield split, fr, top


# --- files and protocol -------------------------------------------------------------------------


def test_json_files_follow_the_protocol(fan_dir):
    seen = {}
    for split, fr, top in _frames(fan_dir):
        assert top["scene"] == "fan"
        assert top["fps"] == FRAMES - 1
        assert top["background"] == [1.0, 1.0, 1.0]
        aabb = np.array(top["aabb"])
        assert aabb.shape == (2, 3) and (aabb[1] > aabb[0]).all()
        assert fr["file_path"] == f"{split}/c{fr['camera_id']:02d}_f{fr['frame_id']:03d}.png"
        assert fr["time"] == pytest.approx(fr["frame_id"] / (FRAMES - 1))
        c2w = np.array(fr["transform_matrix"])
        assert c2w.shape == (4, 4)
        np.testing.assert_allclose(c2w[:3, :3] @ c2w[:3, :3].T, np.eye(3), atol=1e-9)
        seen[(fr["camera_id"], fr["frame_id"])] = (split, top["t_train_end"])
    # Every camera x frame appears exactly once; 3 views -> 2 train cameras, 4 frames -> 3 train frames.
    assert len(seen) == VIEWS * FRAMES
    t_end = 2 / (FRAMES - 1)
    for (c, f), (split, t_train_end) in seen.items():
        assert t_train_end == pytest.approx(t_end)
        expected = "test" if f >= 3 else ("train" if c < 2 else "val")
        assert split == expected, (c, f)


def test_images_are_rgba_with_transparent_background(fan_dir):
    for _, fr, _ in _frames(fan_dir):
        img = iio.imread(fan_dir / fr["file_path"])
        assert img.shape == (RES, RES, 4) and img.dtype == np.uint8
        alpha = img[..., 3]
        assert alpha[0, :].max() == 0 and alpha[:, 0].max() == 0  # the object does not touch the border
        assert (alpha == 255).mean() > 0.05  # but covers a good part of the image
        mask = iio.imread(fan_dir / "gt" / "masks" / fr["file_path"])
        assert mask.shape == (RES, RES) and mask.dtype == np.uint8


def test_masks_agree_with_alpha(scene_dir):
    disagree, total = 0, 0
    for _, fr, _ in _frames(scene_dir):
        alpha = iio.imread(scene_dir / fr["file_path"])[..., 3]
        mask = iio.imread(scene_dir / "gt" / "masks" / fr["file_path"])
        solid, empty = alpha >= 250, alpha <= 5
        disagree += int(((mask == 0) & solid).sum() + ((mask > 0) & empty).sum())
        total += mask.size
        n_parts = len(json.loads((scene_dir / "gt" / "motion.json").read_text())["parts"])
        assert mask.max() <= n_parts
    assert disagree / total < 0.002


def test_every_part_is_visible(scene_dir):
    motion = json.loads((scene_dir / "gt" / "motion.json").read_text())
    ids = set()
    for _, fr, _ in _frames(scene_dir):
        ids |= set(np.unique(iio.imread(scene_dir / "gt" / "masks" / fr["file_path"])).tolist())
    assert ids == {0} | {p["id"] for p in motion["parts"]}


# --- ground-truth geometry -----------------------------------------------------------------------


def _project(points: np.ndarray, c2w_opengl: np.ndarray, camera_angle_x: float, res: int):
    """Pixel (col, row) and depth of world points, with the project's camera conventions: OpenGL
    c2w -> OpenCV by flipping camera y and z, fx = W / 2 / tan(fov / 2), pixel centres at +0.5."""
    c2w = c2w_opengl.copy()
    c2w[:3, 1:3] *= -1
    w2c = np.linalg.inv(c2w)
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    f = 0.5 * res / np.tan(0.5 * camera_angle_x)
    u = f * cam[:, 0] / cam[:, 2] + res / 2
    v = f * cam[:, 1] / cam[:, 2] + res / 2
    return u, v, cam[:, 2]


def test_gt_points_project_onto_their_part_masks(scene_dir):
    """World point = part_transforms(t)[part] @ rest point lands on that part's mask, or on a part in
    front of it; almost never on background. Checks cameras, intrinsics and transforms at once."""
    gt = np.load(scene_dir / "gt" / "points.npz")
    points, ids = gt["points"].astype(np.float64), gt["part_ids"]
    assert 5_000 <= len(points) <= 20_000
    assert set(np.unique(ids)) == set(range(1, ids.max() + 1))
    stored = np.load(scene_dir / "gt" / "part_transforms.npz")
    on_background, on_own, count = 0, 0, 0
    for _, fr, top in _frames(scene_dir):
        T = part_transforms(scene_dir, fr["time"])
        np.testing.assert_allclose(T, stored["transforms"][fr["frame_id"]], atol=1e-12)
        world = np.einsum("nij,nj->ni", T[ids - 1, :3, :3], points) + T[ids - 1, :3, 3]
        res = top["w"]
        u, v, z = _project(world, np.array(fr["transform_matrix"]), top["camera_angle_x"], res)
        assert (z > 0).all()
        col, row = np.floor(u).astype(int), np.floor(v).astype(int)
        assert ((col >= 0) & (col < res) & (row >= 0) & (row < res)).all()  # object stays in frame
        mask = iio.imread(scene_dir / "gt" / "masks" / fr["file_path"])
        hit = mask[row, col]
        # Points within half a pixel of the silhouette may fall on either side of it.
        inner = np.ones_like(hit, dtype=bool)
        for du in (-0.5, 0.5):
            for dv in (-0.5, 0.5):
                c2 = np.clip(np.floor(u + du).astype(int), 0, res - 1)
                r2 = np.clip(np.floor(v + dv).astype(int), 0, res - 1)
                inner &= mask[r2, c2] > 0
        on_background += int(((hit == 0) & inner).sum())
        on_own += int((hit == ids).sum())
        count += len(ids)
    assert on_background == 0
    assert on_own / count > 0.4  # about half the surface faces the camera; the rest is hidden


def test_silhouettes_match_projected_convex_parts(rendered):
    """For a convex part, the pixels whose centre falls inside the convex hull of its projected
    surface points are exactly its mask (where no other part is in front): a sub-pixel check of
    the camera model, which a half-pixel shift or a wrong focal length would fail."""
    from matplotlib.path import Path as Polygon
    from scipy.spatial import ConvexHull

    root = rendered("fallingball")  # a box slab and a sphere, both convex
    gt = np.load(root / "gt" / "points.npz")
    points, ids = gt["points"].astype(np.float64), gt["part_ids"]
    grid = np.arange(40) + 0.5
    centres = np.stack(np.meshgrid(grid, grid, indexing="xy"), -1).reshape(-1, 2)  # pixel centres (u, v)
    wrong, area = 0, 0
    for _, fr, top in _frames(root):
        mask = iio.imread(root / "gt" / "masks" / fr["file_path"]).ravel()
        T = part_transforms(root, fr["time"])
        for part in (1, 2):
            p = points[ids == part] @ T[part - 1, :3, :3].T + T[part - 1, :3, 3]
            u, v, _ = _project(p, np.array(fr["transform_matrix"]), top["camera_angle_x"], top["w"])
            uv = np.stack([u, v], -1)
            inside = Polygon(uv[ConvexHull(uv).vertices]).contains_points(centres)
            free = (mask == part) | (mask == 0)  # pixels where another part is in front say nothing
            wrong += int((inside != (mask == part))[free].sum())
            area += int((mask == part).sum())
    assert wrong / area < 0.02  # 0.3% here; a half-pixel shift gives 11%


def test_mask_pixels_follow_the_moving_part(fan_dir):
    """The blades' mask changes between frames while the static body's mask pixels that are not
    covered by blades stay put."""
    first = iio.imread(fan_dir / "gt" / "masks" / "train" / "c00_f000.png")
    later = iio.imread(fan_dir / "gt" / "masks" / "test" / "c00_f003.png")
    assert ((first == 2) != (later == 2)).sum() > 10
    body_first = (first == 1) & (later != 2)
    assert (later[body_first] == 1).all()


def test_aabb_bounds_the_motion_up_to_extrapolation_horizon():
    for name in SCENES:
        spec = get_scene(name)
        b = motion_bounds(spec)
        assert b.radius < 1.35, name  # the object stays within about a unit of its centre
        assert (np.abs(b.aabb) < 1.3).all(), name


# --- closed-form motion ---------------------------------------------------------------------------


def _angle(R: np.ndarray) -> np.ndarray:
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1))


def test_part_transforms_shapes_and_identity_at_rest(fan_dir):
    T0 = part_transforms(fan_dir, 0.0)
    assert T0.shape == (2, 4, 4)
    np.testing.assert_allclose(T0, np.broadcast_to(np.eye(4), T0.shape), atol=1e-12)
    Ts = part_transforms(fan_dir / "gt" / "motion.json", np.array([0.0, 0.5, 1.5]))
    assert Ts.shape == (3, 2, 4, 4)
    R = Ts[..., :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)


def test_fan_angle_grows_linearly(fan_dir):
    t = np.linspace(0.0, 1.5, 7)
    T = part_transforms(fan_dir, t)
    np.testing.assert_allclose(T[:, 0], np.broadcast_to(np.eye(4), (7, 4, 4)), atol=1e-12)  # body static
    angle = _angle(T[:, 1, :3, :3])
    w = angle[1] / t[1]
    assert 1.0 < w * 1.0 < 3.0  # a learnable 1-3 rad over the unit time span
    np.testing.assert_allclose(angle, w * t, atol=1e-9)
    # Rotation about the fixed vertical axis through the origin: the axis is a fixed line.
    np.testing.assert_allclose(T[:, 1, :3, 2], np.broadcast_to([0, 0, 1], (7, 3)), atol=1e-12)
    np.testing.assert_allclose(T[:, 1, :3, 3], 0.0, atol=1e-12)


def test_foldingchair_angles_are_quadratic():
    root = {"parts": _motion_parts("foldingchair")}
    t = np.linspace(0.0, 1.5, 9)
    T = part_transforms(root, t)
    assert T.shape == (9, 4, 4, 4)
    for p in (1, 2, 3):
        angle = _angle(T[:, p, :3, :3])
        coeffs = np.polyfit(t, angle, 2)
        np.testing.assert_allclose(np.polyval(coeffs, t), angle, atol=1e-9)
        assert abs(coeffs[0]) > 0.1  # non-zero angular acceleration
    axes = [np.array(_motion_parts("foldingchair")[p]["axis"]) for p in (1, 2, 3)]
    pivots = [np.array(_motion_parts("foldingchair")[p]["pivot"]) for p in (1, 2, 3)]
    # Three different hinge lines.
    assert not np.allclose(pivots[0], pivots[1]) and abs(axes[2] @ axes[0]) < 0.5


def test_fallingball_centre_follows_a_projectile(rendered):
    scene_dir = rendered("fallingball")
    ball = json.loads((scene_dir / "gt" / "motion.json").read_text())["parts"][1]
    c0, v0, a = (np.array(ball[k]) for k in ("pivot", "linear_velocity", "linear_acceleration"))
    t = np.linspace(0.0, 1.5, 7)
    T = part_transforms(scene_dir, t)[:, 1]
    centre = T[:, :3, :3] @ c0 + T[:, :3, 3]
    np.testing.assert_allclose(centre, c0 + v0 * t[:, None] + 0.5 * a * t[:, None] ** 2, atol=1e-12)
    assert a[2] < 0 and np.allclose(a[:2], 0)  # gravity points down
    assert (_angle(T[1:, :3, :3]) > 0).all()  # and the ball spins
    # The ball's rest points stay on a sphere about the moving centre.
    gt = np.load(scene_dir / "gt" / "points.npz")
    p = gt["points"][gt["part_ids"] == 2].astype(np.float64)
    world = p @ T[-1, :3, :3].T + T[-1, :3, 3]
    r = np.linalg.norm(world - centre[-1], axis=1)
    np.testing.assert_allclose(r, r.mean(), atol=2e-3)


def test_slider_translates_with_constant_acceleration():
    parts = _motion_parts("slider")
    t = np.linspace(0.0, 1.5, 7)
    T = part_transforms({"parts": parts}, t)
    x = T[:, 1, 0, 3]
    coeffs = np.polyfit(t, x, 2)
    assert coeffs[0] > 0.1 and np.allclose(T[:, 1, :3, :3], np.eye(3))
    assert (_angle(T[1:, 2, :3, :3]) > 0).all()


def _motion_parts(scene: str) -> list[dict]:
    from tracegs.data.synth.motion import motion_record

    spec = get_scene(scene)
    return [motion_record(p.name, i + 1, p.motion) for i, p in enumerate(spec.parts)]


# --- determinism, errors, helpers -------------------------------------------------------------------


def test_same_seed_gives_byte_identical_images(fan_dir, tmp_path_factory):
    again = _make(tmp_path_factory, "fan")
    for _, fr, _ in _frames(fan_dir):
        for rel in (fr["file_path"], f"gt/masks/{fr['file_path']}"):
            assert (fan_dir / rel).read_bytes() == (again / rel).read_bytes(), rel
    a = json.loads((fan_dir / "transforms_train.json").read_text())
    b = json.loads((again / "transforms_train.json").read_text())
    assert a == b


def test_other_seed_moves_the_cameras(fan_dir, tmp_path_factory):
    other = _make(tmp_path_factory, "fan", seed=1, frames=2)
    a = json.loads((fan_dir / "transforms_train.json").read_text())["frames"][0]["transform_matrix"]
    b = json.loads((other / "transforms_train.json").read_text())["frames"][0]["transform_matrix"]
    assert not np.allclose(a, b)


def test_rerun_replaces_previous_output_and_refuses_foreign_folder(fan_dir, tmp_path):
    out = synthesize("slider", tmp_path / "d", resolution=16, views=2, frames=2, progress=False, spp=1)
    synthesize("slider", out, resolution=16, views=2, frames=2, progress=False, spp=1)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]  # no temporary folders left behind
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError):
        synthesize("slider", foreign, resolution=16, views=2, frames=2, progress=False, spp=1)
    assert (foreign / "keep.txt").read_text() == "mine"


def test_bad_input_gives_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="available: fan, foldingchair"):
        synthesize("teapot", tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="train_views"):
        synthesize("fan", tmp_path / "x", views=3, train_views=3, progress=False)
    with pytest.raises(ValueError, match="frames"):
        synthesize("fan", tmp_path / "x", frames=1, progress=False)
    with pytest.raises(ValueError, match="sun and ambient"):
        synthesize("fan", tmp_path / "x", sun=0.0, ambient=0.0, progress=False)
    with pytest.raises(ValueError, match="sun and ambient"):
        synthesize("fan", tmp_path / "x", sun=-1.0, progress=False)
    assert not (tmp_path / "x").exists()


def test_paper_protocol_split_sizes():
    split = make_split(15, 60, 12, 46)
    assert (len(split.train), len(split.val), len(split.test)) == (552, 138, 210)
    dirs = fibonacci_band(15, seed=0)
    elevation = np.rad2deg(np.arcsin(dirs[:, 2]))
    assert elevation.min() >= 15 and elevation.max() <= 60


@pytest.mark.parametrize("mesh", [box((0.3, 0.5, 0.7)), cylinder(0.4, 0.2), sphere(0.5)])
def test_primitive_meshes_are_closed_and_outward(mesh):
    """Signed volume > 0 (faces wound counter-clockwise from outside) and each edge used twice
    (no holes), counting coincident vertices as one."""
    v = mesh.vertices.astype(np.float64)
    a, b, c = (v[mesh.faces[:, i]] for i in range(3))
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6 > 0
    key = np.unique(np.round(v, 6), axis=0, return_inverse=True)[1].ravel()
    f = key[mesh.faces]
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()


def test_parser_reads_the_folder(fan_dir):
    blender = pytest.importorskip("tracegs.data.scene")
    for split in SPLITS:
        scene = blender.load_scene(fan_dir, split)
        data = json.loads((fan_dir / f"transforms_{split}.json").read_text())
        assert len(scene.frames) == len(data["frames"])
        for frame, entry in zip(scene.frames, data["frames"], strict=True):
            assert frame.image_path.is_file()
            assert (frame.width, frame.height) == (RES, RES)
            assert frame.time == pytest.approx(entry["time"])
            # The parser's OpenCV camera projects GT points like our own numpy projection.
            gt = np.load(fan_dir / "gt" / "points.npz")
            T = part_transforms(fan_dir, entry["time"])
            ids = gt["part_ids"]
            world = np.einsum("nij,nj->ni", T[ids - 1, :3, :3], gt["points"]) + T[ids - 1, :3, 3]
            viewmat, K = frame.camera.viewmat.numpy(), frame.camera.K.numpy()
            cam = world @ viewmat[:3, :3].T + viewmat[:3, 3]
            uv = cam @ K.T
            u, v, _ = _project(world, np.array(entry["transform_matrix"]), data["camera_angle_x"], RES)
            np.testing.assert_allclose(uv[:, 0] / uv[:, 2], u, atol=1e-3)
            np.testing.assert_allclose(uv[:, 1] / uv[:, 2], v, atol=1e-3)


def test_turn_is_the_rotation_made_between_two_times():
    from tracegs.data.synth.ceiling import turn
    from tracegs.data.synth.motion import axis_angle_to_matrix

    blades = get_scene("fan").parts[1].motion  # 2 rad per unit of t about z
    np.testing.assert_allclose(turn(blades, 0.7, 0.2), axis_angle_to_matrix((0, 0, 1), 1.0), atol=1e-12)
    np.testing.assert_allclose(turn(blades, 0.2, 0.7), axis_angle_to_matrix((0, 0, 1), -1.0), atol=1e-12)
    chair = get_scene("foldingchair").parts[1].motion  # angular acceleration: the angle is quadratic in t
    theta = lambda t: chair.angular_velocity * t + 0.5 * chair.angular_acceleration * t**2  # noqa: E731
    np.testing.assert_allclose(
        turn(chair, 0.9, 0.4), axis_angle_to_matrix(chair.axis, theta(0.9) - theta(0.4)), atol=1e-12
    )


def test_frozen_appearance_is_exact_at_its_own_frame_and_costs_where_shading_changes(fan_dir, tmp_path):
    from tracegs.data.synth.ceiling import SceneFolder, frozen_appearance

    scene = SceneFolder(fan_dir)
    assert scene.check_reproduction([FRAMES - 1]) == 2  # the renderer reproduces the stored bytes
    same = frozen_appearance(scene, [FRAMES - 1], [FRAMES - 1])
    assert same["mse"] < 1e-9 and same["frames_scored"] == VIEWS
    earlier = frozen_appearance(scene, [0], [FRAMES - 1])  # blades lit as at t = 0, turned 2 rad since
    parts = earlier["per_part"]
    assert parts["background"]["error_share"] == 0.0
    assert 10 < parts["blades"]["psnr"] < 45 and earlier["mse"] > 1e-5
    averaged = frozen_appearance(scene, [0, FRAMES - 1], [FRAMES - 1])  # the mean of both appearances
    assert 0 < averaged["mse"] < earlier["mse"]
    with pytest.raises(FileNotFoundError, match="synth.json"):
        SceneFolder(tmp_path)


def test_without_the_sun_a_turning_part_keeps_its_appearance(tmp_path_factory, fan_dir):
    from tracegs.data.synth.ceiling import SceneFolder, frozen_appearance

    flat = _make(tmp_path_factory, "fan", sun=0.0, ambient=1.0)
    settings = json.loads((flat / "gt" / "synth.json").read_text())
    assert (settings["sun"], settings["ambient"]) == (0.0, 1.0)
    lit, unlit = (iio.imread(d / "train" / "c00_f000.png").astype(float) for d in (fan_dir, flat))
    assert np.array_equal(lit[..., 3], unlit[..., 3]) and not np.array_equal(lit, unlit)  # same geometry
    scene = SceneFolder(flat)
    assert scene.check_reproduction([FRAMES - 1]) == 2  # the folder's own light is re-rendered
    blades = frozen_appearance(scene, [0], [FRAMES - 1])["per_part"]["blades"]
    assert blades["psnr"] is None  # turned 2 rad, looks exactly as it did at t = 0
    shaded = frozen_appearance(SceneFolder(fan_dir), [0], [FRAMES - 1])["per_part"]["blades"]
    assert shaded["psnr"] is not None and shaded["psnr"] < 45


def test_the_cli_lights_scenes_as_the_library_does():
    from tracegs.cli import Synth
    from tracegs.data.synth.render import Lighting

    cli = Synth(out=Path("x"))
    assert (cli.sun, cli.ambient) == (Lighting().sun_irradiance, Lighting().ambient)
