"""Free rigid bodies: the fits recover exact motion, the motion is rigid and follows its parabola, and
the parts are found by their velocities."""

import torch
from scipy.spatial.transform import Rotation

from tracegs.physics.free_body import (
    FreeBody,
    centre_of_mass,
    fit_parabola,
    fit_rigid_transform,
    fit_rigid_velocity,
    isolation,
    main_piece,
    move,
    pivot_path,
    rigid_components,
    split_rigid,
)
from tracegs.physics.so3 import quat_normalize, quat_to_rotmat, skew

torch.manual_seed(0)
DT = torch.float64


def test_parabola_fit_is_exact_on_a_parabola():
    c0, v, a = (
        torch.tensor([0.3, -1.0, 2.0], dtype=DT),
        torch.tensor([1.0, 0.5, 2.0], dtype=DT),
        torch.tensor([0.0, 0.0, -9.81], dtype=DT),
    )
    times = torch.linspace(0.2, 0.7, 9, dtype=DT)
    s = (times - 0.7)[:, None]
    points = c0 + v * s + 0.5 * a * s * s
    fit = fit_parabola(times, points, 0.7)
    for got, want in zip(fit, (c0, v, a), strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-9)


def test_rigid_velocity_fit_recovers_translation_and_spin():
    x = torch.randn(50, 3, dtype=DT)
    pivot = torch.tensor([1.0, 2.0, -0.5], dtype=DT)
    v, w = torch.tensor([0.2, -0.1, 0.4], dtype=DT), torch.tensor([0.5, -2.0, 1.0], dtype=DT)
    u = v + torch.cross(w.expand_as(x), x - pivot, dim=-1)
    fit_v, fit_w = fit_rigid_velocity(x, u, pivot)
    torch.testing.assert_close(fit_v, v, rtol=0, atol=1e-10)
    torch.testing.assert_close(fit_w, w, rtol=0, atol=1e-10)


def test_rigid_transform_fit_recovers_the_rotation_and_translation():
    a = torch.randn(40, 3, dtype=DT)
    rotation = torch.as_tensor(Rotation.from_rotvec([0.4, -1.2, 0.7]).as_matrix())
    translation = torch.tensor([0.3, -0.2, 1.5], dtype=DT)
    got_r, got_t = fit_rigid_transform(a, a @ rotation.T + translation)
    torch.testing.assert_close(got_r, rotation, rtol=0, atol=1e-10)
    torch.testing.assert_close(got_t, translation, rtol=0, atol=1e-10)
    # points on a plane, which a reflection maps as well as a rotation does: still a rotation
    flat = a * torch.tensor([1.0, 1.0, 0.0], dtype=DT)
    got_r, _ = fit_rigid_transform(flat, flat @ rotation.T + translation)
    torch.testing.assert_close(torch.linalg.det(got_r), torch.tensor(1.0, dtype=DT), rtol=0, atol=1e-10)
    torch.testing.assert_close(got_r, rotation, rtol=0, atol=1e-10)


def test_pivot_path_follows_the_body_point_not_its_strays():
    """A plate turning on a hinge as it drifts: the path of its centre is the arc the rigid motion
    carries it along, exactly, and a few points that stray from the plate move it little, while the
    hull of the points (their centre of mass) follows the strays."""
    gen = torch.Generator().manual_seed(1)
    plate = torch.rand(500, 3, generator=gen, dtype=DT) * torch.tensor([0.4, 0.01, 0.4], dtype=DT)
    hinge, axis = torch.tensor([0.0, 0.0, 0.4], dtype=DT), torch.tensor([1.0, 0.0, 0.0], dtype=DT)
    drift = torch.tensor([0.12, 0.08, 0.06], dtype=DT)
    times = torch.linspace(-0.2, 0.0, 9, dtype=DT)

    def at(t, points):
        turn = torch.as_tensor(Rotation.from_rotvec((axis * float(t)).numpy()).as_matrix())
        return (points - hinge) @ turn.T + hinge + drift * t

    past = [at(t, plate) for t in times]
    pivot = centre_of_mass(past[-1])
    truth = torch.stack([at(t - times[-1], pivot[None])[0] for t in times])
    torch.testing.assert_close(pivot_path(pivot, past[-1], past), truth, rtol=0, atol=1e-10)
    # 2% of the points, the plate's outermost, pushed off it by up to 0.05 over the window
    strays = torch.zeros(len(plate), dtype=torch.bool)
    strays[torch.argsort((plate - plate.mean(0)).norm(dim=1), descending=True)[:10]] = True
    push = torch.tensor([0.0, 0.05, 0.0], dtype=DT)
    moved = [p + push * strays[:, None] * (k / (len(past) - 1)) for k, p in enumerate(past)]
    off = (pivot_path(pivot, moved[-1], moved) - truth).norm(dim=1).max()
    hulls = torch.stack([centre_of_mass(p) for p in moved])
    hull_off = ((hulls - hulls[-1] + pivot) - truth).norm(dim=1).max()
    assert float(off) < 0.1 * float(hull_off)
    assert float(hull_off) > 0.005


def test_move_is_a_rigid_turn_about_the_pivot_on_its_parabola():
    body = FreeBody(*(torch.randn(3, dtype=DT) for _ in range(5)))
    means, quats = torch.randn(20, 3, dtype=DT), quat_normalize(torch.randn(20, 4, dtype=DT))
    s = 0.37
    new_means, new_quats = move(means, quats, body, s)
    turn = torch.as_tensor(Rotation.from_rotvec((body.w * s).numpy()).as_matrix())
    centre = body.c0 + body.shift + body.v * s + 0.5 * body.a * s * s
    torch.testing.assert_close(new_means, (means - body.c0) @ turn.T + centre, rtol=0, atol=1e-10)
    torch.testing.assert_close(quat_to_rotmat(new_quats), turn @ quat_to_rotmat(quats), rtol=0, atol=1e-10)
    # the pivot's velocity is v + a s, and the other points' differ from it by w x r
    h = 1e-6
    ahead, _ = move(means, quats, body, s + h)
    behind, _ = move(means, quats, body, s - h)
    r = new_means - centre
    expected = body.v + body.a * s + r @ skew(body.w).T
    torch.testing.assert_close((ahead - behind) / (2 * h), expected, rtol=0, atol=1e-6)
    zero, same = move(means, quats, body, 0.0)  # at t0 the body only shifted
    torch.testing.assert_close(zero, means + body.shift, rtol=0, atol=1e-12)
    torch.testing.assert_close(same, quats, rtol=0, atol=1e-12)
    torch.testing.assert_close(FreeBody.from_tensor(body.as_tensor()).as_tensor(), body.as_tensor())


def test_centre_of_mass_is_the_solid_s_not_the_points_mean():
    """Points on a sphere, one side sampled ten times as densely: their mean leans to that side, the
    centre of the ball they bound does not. A box's centre; flat or too few points: their mean."""
    centre = torch.tensor([0.3, -0.2, 1.0], dtype=DT)
    d = torch.nn.functional.normalize(torch.randn(4000, 3, dtype=DT), dim=1)
    d = torch.cat([d, d[d[:, 0] > 0.3].repeat(9, 1)])
    points = centre + 0.5 * d
    assert (points.mean(0) - centre).norm() > 0.1
    torch.testing.assert_close(centre_of_mass(points), centre, rtol=0, atol=5e-3)
    corners = torch.tensor([[x, y, z] for x in (0, 2) for y in (0, 1) for z in (0, 3)], dtype=DT)
    lopsided = torch.cat([corners, corners[:1].repeat(50, 1) + 0.01 * torch.rand(50, 3, dtype=DT)])
    torch.testing.assert_close(centre_of_mass(lopsided), torch.tensor([1.0, 0.5, 1.5], dtype=DT))
    flat = torch.randn(30, 3, dtype=DT) * torch.tensor([1.0, 1.0, 0.0], dtype=DT)
    torch.testing.assert_close(centre_of_mass(flat), flat.mean(0))
    torch.testing.assert_close(centre_of_mass(points[:3]), points[:3].mean(0))


def test_a_few_points_apart_from_a_body_are_left_out_of_its_centre():
    """A ball's surface Gaussians and a few from near the ground a unit below it: the main piece is the
    ball, and its hull's centroid the ball's centre (the hull of all of them is pulled down)."""
    centre = torch.tensor([0.1, 0.0, 0.3], dtype=DT)
    ball = centre + 0.2 * torch.nn.functional.normalize(torch.randn(2000, 3, dtype=DT), dim=1)
    stray = torch.tensor([[0.0, 0.0, -0.8], [-0.3, 0.1, -0.7], [0.2, -0.1, -0.75]], dtype=DT)
    points = torch.cat([ball, stray])
    kept = main_piece(points)
    assert kept[:2000].all() and not kept[2000:].any()
    assert (centre_of_mass(points) - centre).norm() > 0.05
    torch.testing.assert_close(centre_of_mass(points[kept]), centre, rtol=0, atol=5e-3)


def test_rigid_components_split_bodies_by_their_velocities():
    """A spinning disc beside a block that moves away from it: two bodies; the still points get no
    body. (Bodies that slide past each other keep the distance of the pairs across their contact, and
    may be joined: the backtest of ``choose_free_bodies`` is what guards against such a group.)"""
    g = torch.linspace(-0.5, 0.5, 8, dtype=DT)
    grid = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2) * 0.1
    disc = torch.cat([grid, torch.zeros(len(grid), 1, dtype=DT)], 1)
    block = disc + torch.tensor([0.105, 0.0, 0.0], dtype=DT)
    still = disc + torch.tensor([0.0, 0.3, 0.0], dtype=DT)
    x = torch.cat([disc, block, still])
    w = torch.tensor([0.0, 0.0, 0.5], dtype=DT)
    u = torch.cat(
        [
            torch.cross(w.expand_as(disc), disc, dim=-1),
            torch.tensor([0.8, 0.0, 0.3], dtype=DT).expand_as(block),
            torch.zeros_like(still),
        ]
    )
    moved = torch.cat([torch.ones(2 * len(grid), dtype=torch.bool), torch.zeros(len(grid), dtype=torch.bool)])
    labels = rigid_components(x, moved, u, speed_floor=0.01)
    n = len(grid)
    assert set(labels[:n].tolist()) == {labels[0].item()} and labels[0] > 0
    assert set(labels[n : 2 * n].tolist()) == {labels[n].item()} and labels[n] > 0
    assert labels[0] != labels[n]
    assert (labels[2 * n :] == 0).all()
    # one velocity field for both (they move as one body): one component
    joined = rigid_components(x, moved, torch.zeros_like(u), speed_floor=0.01)
    assert set(joined[: 2 * n].tolist()) == {1}


def test_isolation_counts_spacings_to_the_nearest_still_point():
    g = torch.linspace(0, 0.9, 10, dtype=DT)
    line = torch.stack([g, torch.zeros_like(g), torch.zeros_like(g)], 1)  # spacing 0.1
    for offset, want in ((3.0, 21.0), (1.0, 1.0)):  # the group's nearest points lie offset - 0.9 away
        x = torch.cat([line, line + torch.tensor([offset, 0.0, 0.0], dtype=DT)])
        group = torch.arange(20) >= 10
        assert abs(isolation(x, group, ~group, quantile=0.0) - want) < 1e-9
    assert isolation(x, group, torch.zeros(20, dtype=torch.bool)) == float("inf")  # nothing still


def test_split_rigid_finds_the_parts_of_a_hinged_body():
    """A box that drifts, with a plate on a hinge along one edge turning as it drifts: one connected
    group, two rigid motions; the split gives the box and the plate (the points next to the hinge,
    which barely move apart, may go either way). A body that spins as one is one part."""
    gen = torch.Generator().manual_seed(0)
    box = torch.rand(1500, 3, generator=gen, dtype=DT) * 0.4
    plate = torch.rand(600, 3, generator=gen, dtype=DT) * torch.tensor([0.4, 0.4, 0.01], dtype=DT)
    plate = plate + torch.tensor([0.4, 0.0, 0.4], dtype=DT)  # from the box's top edge at x = 0.4
    x = torch.cat([box, plate])
    drift = torch.tensor([0.12, 0.08, 0.06], dtype=DT)
    hinge, w = torch.tensor([0.4, 0.0, 0.4], dtype=DT), torch.tensor([0.0, 1.0, 0.0], dtype=DT)
    u = torch.cat([drift.expand_as(box), drift + torch.cross(w.expand_as(plate), plate - hinge, dim=-1)])
    u = u + 0.003 * torch.randn(u.shape, generator=gen, dtype=DT)  # a learned field's noise
    labels = split_rigid(x, u, floor=0.005)
    assert int(labels.max()) == 2
    far = (x - hinge)[:, [0, 2]].norm(dim=1) > 0.05  # away from the hinge line
    on_plate = torch.arange(len(x)) >= len(box)
    box_label = labels[~on_plate & far].mode().values
    assert bool((labels[~on_plate & far] == box_label).all())
    assert bool((labels[on_plate & far] != box_label).all())
    # a noisier field: the box's claim (six times its median residual) takes a strip of the plate
    # along the hinge, and one pass of reassignment gives back only its edge; the passes give it all
    noisy = u + 0.007 * torch.randn(u.shape, generator=gen, dtype=DT)
    far = (x - hinge)[:, [0, 2]].norm(dim=1) > 0.03
    for rounds, plate_in_box in ((1, True), (30, False)):
        labels = split_rigid(x, noisy, floor=0.005, rounds=rounds)
        box_label = labels[~on_plate & far].mode().values
        assert bool((labels[on_plate & far] == box_label).any()) == plate_in_box
        assert bool((labels[~on_plate & far] == box_label).all())
    # one body turning about its centre: one part
    spin = torch.tensor([0.3, 4.0, 1.1], dtype=DT)
    ball = torch.nn.functional.normalize(torch.randn(2000, 3, generator=gen, dtype=DT), dim=1) * 0.2
    u = torch.tensor([0.65, 0.0, 0.1], dtype=DT) + torch.cross(spin.expand_as(ball), ball, dim=-1)
    u = u + 0.02 * torch.randn(u.shape, generator=gen, dtype=DT)
    assert bool((split_rigid(ball, u, floor=0.005) == 1).all())
