"""Deformation fields (MLP, HexPlane) and the dynamics field: no motion at init, shapes, training."""

import pytest
import torch

from tracegs.models.deformation import DeformationConfig, apply_deformation, make_deformation_field
from tracegs.models.dynamics import DynamicsConfig, DynamicsField
from tracegs.models.encoding import encoding_dim, positional_encoding, time_column
from tracegs.models.hexplane import HexPlaneConfig
from tracegs.physics.integrate import (
    DynamicsParams,
    acceleration_consistency,
    equivalent_from_center,
    integrate,
)
from tracegs.physics.so3 import quat_multiply, quat_normalize

N = 64
SMALL_HEXPLANE = HexPlaneConfig(spatial_resolution=8, time_resolution=5, feature_dim=4, decoder_width=16)


def deformation_config(kind: str) -> DeformationConfig:
    return DeformationConfig(kind=kind, depth=4, width=32, skip_layer=2, hexplane=SMALL_HEXPLANE)


def dynamics_config(**kw) -> DynamicsConfig:
    return DynamicsConfig(**{"depth": 3, "width": 32, "num_frequencies": 3, **kw})


def points(seed: int = 0) -> torch.Tensor:
    return torch.randn(N, 3, generator=torch.Generator().manual_seed(seed))


def first_layer(field: torch.nn.Module) -> torch.nn.Parameter:
    return next(p for name, p in field.named_parameters() if name.endswith("weight"))


def one_sgd_step(field: torch.nn.Module, lr: float = 0.1) -> None:
    with torch.no_grad():
        for p in field.parameters():
            if p.grad is not None:
                p -= lr * p.grad
                p.grad = None


def test_positional_encoding_layout():
    u = torch.tensor([[0.3, -1.2]])
    out = positional_encoding(u, 3)
    assert out.shape == (1, encoding_dim(2, 3)) == (1, 14)
    expected = [0.3, -1.2]
    for k in range(3):
        expected += [torch.sin(2**k * u[0, 0]), torch.sin(2**k * u[0, 1])]
        expected += [torch.cos(2**k * u[0, 0]), torch.cos(2**k * u[0, 1])]
    torch.testing.assert_close(out[0], torch.tensor(expected))
    assert positional_encoding(u, 0).shape == (1, 2)


def test_time_column():
    x = torch.zeros(5, 3, dtype=torch.float64)
    for t in (0.5, torch.tensor(0.5), torch.tensor([0.5]), torch.full((5,), 0.5), torch.full((5, 1), 0.5)):
        col = time_column(t, x)
        assert col.shape == (5, 1) and col.dtype == torch.float64
        torch.testing.assert_close(col, torch.full((5, 1), 0.5, dtype=torch.float64))


@pytest.mark.parametrize("kind", ["mlp", "hexplane"])
def test_new_deformation_field_is_no_motion(kind):
    field = make_deformation_field(deformation_config(kind))
    x0 = points()
    for t in (0.0, 0.37, torch.rand(N, 1)):
        dx, dq, dlog_s = field(x0, t)
        assert dx.shape == (N, 3) and dq.shape == (N, 4) and dlog_s.shape == (N, 3)
        assert (dx == 0).all() and (dlog_s == 0).all()
        assert (dq == torch.tensor([1.0, 0.0, 0.0, 0.0])).all()
    q0 = quat_normalize(torch.randn(N, 4))
    log_s0 = torch.randn(N, 3)
    x_t, q_t, log_s_t = apply_deformation(x0, q0, log_s0, dx, dq, dlog_s)
    assert torch.equal(x_t, x0) and torch.equal(log_s_t, log_s0)
    torch.testing.assert_close(q_t, q0)


def test_apply_deformation_composes_rotations_on_the_left():
    q0, dq = torch.randn(N, 4), 3.0 * quat_normalize(torch.randn(N, 4))
    q0 = quat_normalize(q0)
    _, q_t, _ = apply_deformation(
        torch.zeros(N, 3), q0, torch.zeros(N, 3), torch.zeros(N, 3), dq, torch.zeros(N, 3)
    )
    torch.testing.assert_close(q_t, quat_multiply(quat_normalize(dq), q0))
    torch.testing.assert_close(q_t.norm(dim=-1), torch.ones(N))


@pytest.mark.parametrize("kind", ["mlp", "hexplane"])
def test_zero_heads_still_train(kind):
    torch.manual_seed(0)
    field = make_deformation_field(deformation_config(kind))
    x0 = points()
    target = torch.randn(N, 3)

    def loss():
        dx, dq, dlog_s = field(x0, 0.4)
        return (dx - target).square().mean() + dq[:, 1:].square().mean() + (dlog_s - 1).square().mean()

    loss().backward()
    head = field.heads.translation.weight
    assert head.grad.abs().sum() > 0  # the heads move on the first step...
    first = first_layer(field)
    assert first.grad is None or (first.grad == 0).all()  # ...nothing behind them yet (zero weights)
    one_sgd_step(field)
    loss().backward()
    assert first.grad.abs().sum() > 0  # after one step the gradient reaches the first layer
    if kind == "hexplane":
        assert all(plane.grad.abs().sum() > 0 for plane in field.grid.scales[0])


def test_deformation_mlp_architecture():
    cfg = DeformationConfig()
    field = make_deformation_field(cfg)
    in_dim = encoding_dim(3, 8) + encoding_dim(1, 6)
    widths = [layer.in_features for layer in field.layers]
    assert len(field.layers) == 8
    assert widths == [in_dim, 256, 256, 256, 256, 256 + in_dim, 256, 256]


def test_hexplane_grid_init_and_regularisers():
    field = make_deformation_field(deformation_config("hexplane"), aabb=torch.tensor([[-2.0] * 3, [2.0] * 3]))
    grid = field.grid
    assert grid.aabb[0, 0] == -2.0
    for planes in grid.scales:
        for index, plane in enumerate(planes):
            is_time = index in (2, 4, 5)  # xt, yt, zt
            if is_time:
                assert (plane == 1).all() and plane.shape[-2] == SMALL_HEXPLANE.time_resolution
            else:
                assert plane.min() >= 0.1 and plane.max() <= 0.5
    assert [p.shape[-1] for p in grid.scales[1]][:2] == [16, 16]  # scale 2 doubles the spatial size
    losses = field.regularization_losses()
    assert set(losses) == {"plane_tv", "time_smoothness", "time_l1"}
    assert losses["time_l1"] == 0 and losses["time_smoothness"] == 0 and losses["plane_tv"] > 0
    # points outside the box are clamped to its border: same features as on the border
    t = torch.full((2, 1), 0.5)
    inside, outside = torch.tensor([[2.0, 0.0, 0.0]] * 2), torch.tensor([[9.0, 0.0, 0.0]] * 2)
    torch.testing.assert_close(grid(inside, t), grid(outside, t))


def test_hexplane_feature_is_the_product_of_the_six_planes_at_grid_nodes():
    cfg = HexPlaneConfig(spatial_resolution=5, time_resolution=4, multires=(1,), feature_dim=3)
    field = make_deformation_field(
        DeformationConfig(kind="hexplane", hexplane=cfg), aabb=torch.tensor([[0.0] * 3, [4.0] * 3])
    )
    grid = field.grid
    with torch.no_grad():
        for plane in grid.scales[0]:
            plane.uniform_(0.5, 2.0)
    node = torch.tensor([1, 3, 2, 2])  # cell indices along x, y, z, t
    x = node[:3].float()[None]  # the box [0, 4] has 5 nodes per axis: index == coordinate
    t = torch.tensor([[2 / 3]])  # time range [0, 1] over 4 nodes
    expected = torch.ones(cfg.feature_dim)
    for (i, j), plane in zip(((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)), grid.scales[0], strict=True):
        expected = expected * plane[0, :, node[j], node[i]]  # plane (i, j) is [1, C, res_j, res_i]
    torch.testing.assert_close(grid(x, t)[0], expected)


def test_hexplane_features_depend_on_time_once_trained():
    field = make_deformation_field(deformation_config("hexplane"))
    with torch.no_grad():
        field.grid.scales[0][2].mul_(torch.linspace(0.5, 1.5, SMALL_HEXPLANE.time_resolution)[:, None])
    x = points()
    f0 = field.grid(x, time_column(0.0, x))
    f1 = field.grid(x, time_column(1.0, x))
    assert (f0 - f1).abs().max() > 1e-3


@pytest.mark.parametrize("order", [1, 2, 3])
@pytest.mark.parametrize("equivalent", [True, False])
def test_new_dynamics_field_has_zero_velocity(order, equivalent):
    field = DynamicsField(dynamics_config(order=order, equivalent=equivalent))
    x = points()
    params = field(x, 0.3)
    assert isinstance(params, DynamicsParams)
    assert params.order == (3 if order == 3 else 2)
    for p in params:
        assert p is None or p.shape == (N, 3)
    assert (params.velocity == 0).all() and (params.angular_velocity == 0).all()
    if order == 1:
        assert (params.acceleration == 0).all() and (params.angular_acceleration == 0).all()
        x1, q1, _ = integrate(x, quat_normalize(torch.randn(N, 4)), params, 0.1, 1 / 60)
        assert torch.equal(x1, x)  # exactly the identity
    else:
        # small random raw accelerations (so that they can learn), hence almost no motion
        assert 0 < params.acceleration.abs().max() < 1e-3
        x1, _, _ = integrate(x, quat_normalize(torch.randn(N, 4)), params, 2 / 60, 1 / 60)
        assert (x1 - x).abs().max() < 1e-6


def test_acceleration_scaling_and_order_one_outputs():
    field = DynamicsField(dynamics_config(order=2))
    assert field.head.out_features == 12
    assert DynamicsField(dynamics_config(order=1)).head.out_features == 6
    assert DynamicsField(dynamics_config(order=3)).head.out_features == 18
    assert DynamicsField(dynamics_config(equivalent=False)).head.out_features == 15
    with torch.no_grad():
        field.head.bias.copy_(torch.arange(12.0) - 6)
        field.head.weight.zero_()
    params = field(points(), 0.0)
    raw = torch.arange(12.0) - 6
    torch.testing.assert_close(params.velocity[0], raw[0:3])
    torch.testing.assert_close(params.acceleration[0], raw[6:9] * raw[6:9].abs() / 10)
    torch.testing.assert_close(params.angular_acceleration[0], raw[9:12] * raw[9:12].abs() / 10)


def test_non_equivalent_variant_equals_converted_parameters():
    torch.manual_seed(1)
    field = DynamicsField(dynamics_config(equivalent=False))
    with torch.no_grad():
        field.head.weight.normal_(std=0.5)
        field.head.bias.normal_()
    x = points()
    params = field(x, 0.2)
    raw = field.head(field.mlp(positional_encoding(torch.cat([x, time_column(0.2, x)], -1), 3)))
    center, center_velocity, w = raw[:, 0:3], raw[:, 3:6], raw[:, 6:9]
    a_c, eps = raw[:, 9:12] * raw[:, 9:12].abs() / 10, raw[:, 12:15] * raw[:, 12:15].abs() / 10
    expected = equivalent_from_center(center, center_velocity, a_c, w, eps)
    named = field.outputs(x, 0.2)  # the explicit centre and its motion, before the conversion
    assert list(named) == [
        "center",
        "center_velocity",
        "angular_velocity",
        "acceleration",
        "angular_acceleration",
    ]
    for got, want in zip(named.values(), (center, center_velocity, w, a_c, eps), strict=True):
        torch.testing.assert_close(got, want)
    for got, want in zip(params, expected, strict=True):
        torch.testing.assert_close(got, want)
    # and the particle velocity is the composite one, w x (x - P_c) + v_c (Eq. 3)
    composite = torch.linalg.cross(w, x - center) + center_velocity
    torch.testing.assert_close(params.velocity + torch.linalg.cross(params.angular_velocity, x), composite)


@pytest.mark.parametrize("equivalent", [True, False])
def test_dynamics_field_trains_through_the_integrator(equivalent):
    torch.manual_seed(0)
    field = DynamicsField(dynamics_config(equivalent=equivalent))
    x = points()
    q = quat_normalize(torch.randn(N, 4))
    target = x + 0.05 * torch.randn(N, 3)

    def loss():
        x1, q1, _ = integrate(x, q, field(x, 0.5), 2 / 60, 1 / 60)
        return (x1 - target).square().mean() + (q1 - q).square().mean()

    loss().backward()
    accel_rows = field.slices["acceleration"]
    assert field.head.weight.grad.abs().sum() > 0
    assert field.head.weight.grad[accel_rows].abs().sum() > 0  # accelerations learn from the start
    one_sgd_step(field)
    loss().backward()
    assert first_layer(field).grad.abs().sum() > 0


def _fit_velocities_with_consistency(accelerations: str, weight: float):
    """Velocities supervised to a constant-acceleration motion v(t) = v0 + a t (as the photometric loss
    would teach them) plus ``weight`` x the consistency loss; the acceleration and velocity error at
    t = 0.35 averaged over the last 200 of 600 Adam steps (single steps oscillate)."""
    torch.manual_seed(0)
    detach, depth = accelerations == "detached", 2 if accelerations == "separate" else 0
    field = DynamicsField(dynamics_config(detach_acceleration_features=detach, acceleration_depth=depth))
    x = 0.3 * points()
    v0, a = torch.tensor([0.2, 0.0, -0.1]), torch.tensor([0.9, 0.0, -2.0])
    opt = torch.optim.Adam(field.parameters(), lr=5e-3)
    accelerations, velocity_errors = [], []
    for it in range(600):
        t = (it % 17) / 16 * 0.7
        s = 2 / 60 if it % 2 else -2 / 60
        params = field(x, t)
        fit = (params.velocity - (v0 + a * t)).square().mean() + params.angular_velocity.square().mean()
        with torch.no_grad():
            later = field(x, t + s)  # the particles barely move in 2 frames; the field is smooth in x
        loss = fit + weight * acceleration_consistency(params, later, s)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it >= 400:
            with torch.no_grad():
                learned = field(x, 0.35)
            accelerations.append(learned.acceleration.mean(0))
            velocity_errors.append((learned.velocity - (v0 + a * 0.35)).abs().mean())
    return a, torch.stack(accelerations).mean(0), torch.stack(velocity_errors)


@pytest.mark.parametrize("accelerations", ["detached", "shared", "separate"])
def test_consistency_teaches_the_field_the_acceleration_of_its_own_velocities(accelerations):
    """The consistency loss alone must make the acceleration outputs learn a (without it they stay at
    their ~1e-4 init, as docs/PHYSICS.md measured in training). With the features' gradient stopped
    for the accelerations, or with the accelerations from their own MLP, the velocities train exactly
    as without the loss; from the shared features the loss pulls them and their fit is worse."""
    a, learned, velocity_error = _fit_velocities_with_consistency(accelerations, 0.05)
    _, untrained, no_loss_error = _fit_velocities_with_consistency(accelerations, 0.0)
    assert untrained.abs().max() < 1e-3
    torch.testing.assert_close(learned, a, atol=0.05, rtol=0.2)
    if accelerations == "shared":
        assert velocity_error.mean() > 2 * no_loss_error.mean()
    else:
        torch.testing.assert_close(velocity_error, no_loss_error, atol=1e-5, rtol=0)


@pytest.mark.parametrize("order", [2, 3])
def test_accelerations_from_their_own_mlp(order):
    """``acceleration_depth``: the shared head gives the velocities only, the accelerations (and jerks)
    come from their own MLP on the same encoding, scaled as before; a loss on them leaves every
    parameter the velocities are read from without gradient, and a new field is still "no motion"."""
    torch.manual_seed(0)
    field = DynamicsField(dynamics_config(order=order, acceleration_depth=2))
    assert field.head.out_features == 6
    assert field.acceleration_head.out_features == 6 * (order - 1)
    assert sum(isinstance(m, torch.nn.Linear) for m in field.acceleration_mlp) == 2
    x = points()
    params = field(x, 0.4)
    assert (params.velocity == 0).all() and (params.angular_velocity == 0).all()
    assert 0 < params.acceleration.abs().max() < 1e-3
    raw = field.acceleration_head(field.acceleration_mlp(field.encode(x, 0.4)))
    torch.testing.assert_close(params.acceleration, raw[:, :3] * raw[:, :3].abs() / 10)
    torch.testing.assert_close(params.angular_acceleration, raw[:, 3:6] * raw[:, 3:6].abs() / 10)
    if order == 3:
        torch.testing.assert_close(params.jerk, raw[:, 6:9] * raw[:, 6:9].abs() / 10)
    (params.acceleration.sum() + params.angular_acceleration.sum()).backward()
    velocity_side = [*field.mlp.parameters(), *field.head.parameters()]
    assert all(p.grad is None or (p.grad == 0).all() for p in velocity_side)
    assert first_layer(field.acceleration_mlp).grad.abs().sum() > 0


@pytest.mark.parametrize("order", [2, 3])
def test_angular_accelerations_from_the_shared_head(order):
    """``angular_accelerations_from_head``: the own MLP gives the linear acceleration (and jerk), the
    shared head the velocities and, from its features with their gradient stopped, the angular rates;
    a loss on the rates trains the own MLP and the head's angular rows, nothing the velocities are
    read from."""
    torch.manual_seed(0)
    cfg = dynamics_config(
        order=order,
        acceleration_depth=2,
        angular_accelerations_from_head=True,
        detach_acceleration_features=True,
    )
    field = DynamicsField(cfg)
    assert (
        field.head_names
        == ["velocity", "angular_velocity", "angular_acceleration", "angular_jerk"][: order + 1]
    )
    assert field.own_names == ["acceleration", "jerk"][: order - 1]
    assert field.head.out_features == 3 * (order + 1)
    assert field.acceleration_head.out_features == 3 * (order - 1)
    x = points()
    params = field(x, 0.4)
    assert (params.velocity == 0).all() and (params.angular_velocity == 0).all()
    assert 0 < params.angular_acceleration.abs().max() < 1e-3
    own = field.acceleration_head(field.acceleration_mlp(field.encode(x, 0.4)))
    head = field.head(field.mlp(field.encode(x, 0.4)))
    torch.testing.assert_close(params.acceleration, own[:, :3] * own[:, :3].abs() / 10)
    torch.testing.assert_close(params.angular_acceleration, head[:, 6:9] * head[:, 6:9].abs() / 10)
    if order == 3:
        torch.testing.assert_close(params.jerk, own[:, 3:6] * own[:, 3:6].abs() / 10)
        torch.testing.assert_close(params.angular_jerk, head[:, 9:12] * head[:, 9:12].abs() / 10)
    (params.acceleration.sum() + params.angular_acceleration.sum()).backward()
    assert all(p.grad is None or (p.grad == 0).all() for p in field.mlp.parameters())
    assert (field.head.weight.grad[:6] == 0).all() and field.head.weight.grad[6:9].abs().sum() > 0
    assert first_layer(field.acceleration_mlp).grad.abs().sum() > 0


def test_light_preset():
    cfg = DynamicsConfig.light()
    assert (cfg.depth, cfg.width, cfg.num_frequencies) == (6, 128, 3)
    field = DynamicsField(cfg)
    assert first_layer(field).shape == (128, encoding_dim(4, 3))
    assert sum(isinstance(m, torch.nn.Linear) for m in field.mlp) == 6
    assert DynamicsConfig.light(order=3).order == 3


def test_dynamics_encoding_with_its_own_time_frequencies():
    x, t = points(), 0.3
    joint = DynamicsField(dynamics_config())
    torch.testing.assert_close(
        joint.encode(x, t), positional_encoding(torch.cat([x, torch.full((N, 1), t)], -1), 3)
    )
    split = DynamicsField(dynamics_config(time_frequencies=5))
    assert first_layer(split).shape == (32, encoding_dim(3, 3) + encoding_dim(1, 5))
    encoded = split.encode(x, t)
    torch.testing.assert_close(encoded[:, : encoding_dim(3, 3)], positional_encoding(x, 3))
    torch.testing.assert_close(
        encoded[:, encoding_dim(3, 3) :], positional_encoding(torch.full((N, 1), t), 5)
    )
    assert split(x, t).velocity.abs().max() == 0  # still "no motion" at init


@pytest.mark.parametrize("kind", ["mlp", "hexplane", "dynamics"])
def test_bf16_autocast_gives_float32(kind):
    field = (
        DynamicsField(dynamics_config())
        if kind == "dynamics"
        else make_deformation_field(deformation_config(kind))
    )
    x = points()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = field(x, 0.25)
    assert all(o is None or o.dtype == torch.float32 for o in out)
    assert all(o is None or torch.isfinite(o).all() for o in out)


@pytest.mark.parametrize("kind", ["mlp", "hexplane", "dynamics"])
def test_fields_follow_input_dtype(kind):
    field = (
        DynamicsField(dynamics_config())
        if kind == "dynamics"
        else make_deformation_field(deformation_config(kind))
    )
    field = field.double()
    out = field(points().double(), torch.full((N, 1), 0.1, dtype=torch.float64))
    assert all(o is None or o.dtype == torch.float64 for o in out)


def test_bad_config_is_rejected():
    with pytest.raises(ValueError):
        make_deformation_field(DeformationConfig(kind="grid"))
    with pytest.raises(ValueError):
        DynamicsField(dynamics_config(order=4))
    with pytest.raises(ValueError):
        DynamicsField(dynamics_config(activation="tanh"))
    with pytest.raises(ValueError, match="acceleration_depth"):
        DynamicsField(dynamics_config(acceleration_depth=-1))


def test_hexplane_fit_bounds_covers_the_bulk_and_ignores_far_floaters():
    from tracegs.models.hexplane import HexPlane, HexPlaneConfig

    grid = HexPlane(
        HexPlaneConfig(spatial_resolution=4, time_resolution=3, multires=(1,)),
        torch.tensor([[-0.1] * 3, [0.1] * 3]),
    )
    points = torch.rand(5000, 3) * 4 - 2  # the scene: [-2, 2]^3
    points[:3] = 100.0  # three far floaters
    grid.fit_bounds(points)
    lo, hi = grid.aabb
    assert torch.all(lo < -1.9) and torch.all(hi > 1.9)  # the bulk is inside
    assert torch.all(hi < 3.0)  # the floaters did not stretch the box


def _randomised(module: torch.nn.Module) -> torch.nn.Module:
    """Non-zero weights everywhere (the heads start at zero, which would hide any difference)."""
    generator = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=generator))
    return module


def _mlp_on_concatenation(field, x, t):
    """The Deformable 3DGS MLP written out with its concatenated input and skip."""
    inputs = field.encode(x, t)
    h = inputs
    for i, layer in enumerate(field.layers):
        h = torch.relu(layer(h))
        if i == field.cfg.skip_layer:
            h = torch.cat([inputs, h], dim=-1)
    return field.heads(h, x.dtype)


@pytest.mark.parametrize("time_frequencies", [None, 5])
def test_fields_fold_a_shared_time_into_the_bias_exactly(time_frequencies):
    """``linear_of_parts``: one time for all points (a bias) or one per point gives the same
    outputs as the layers on the concatenated encoding, for f_defo (with its skip) and f_trd
    (one joint (x, t) encoding, whose time columns interleave, or the time's own)."""
    x, t = points(), 0.3
    deformation = _randomised(make_deformation_field(deformation_config("mlp")))
    dynamics = _randomised(DynamicsField(dynamics_config(time_frequencies=time_frequencies)))
    reference_trd = dynamics.head(dynamics.mlp(dynamics.encode(x, t)))
    for time in (t, torch.full((N, 1), t)):
        for ours, ref in zip(deformation(x, time), _mlp_on_concatenation(deformation, x, t), strict=True):
            torch.testing.assert_close(ours, ref, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(dynamics(x, time).velocity, reference_trd[:, :3], atol=1e-5, rtol=1e-5)
    # a single point: every part is one row
    one = _mlp_on_concatenation(deformation, x[:1], t)
    for ours, ref in zip(deformation(x[:1], t), one, strict=True):
        torch.testing.assert_close(ours, ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(dynamics(x[:1], t).velocity, reference_trd[:1, :3], atol=1e-5, rtol=1e-5)
    # per-point times differ from a shared one where they differ
    varied = torch.linspace(0, 1, N)[:, None]
    assert not torch.allclose(deformation(x, varied)[0], deformation(x, t)[0])
