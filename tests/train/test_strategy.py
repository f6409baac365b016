"""Densification: clone / split / prune keep parameters and their Adam moments aligned."""

import torch

from tracegs.config import OptimConfig
from tracegs.models.gaussians import create_gaussians
from tracegs.train.optim import gaussian_optimizers
from tracegs.train.strategy import DefaultStrategy, DensifyConfig, duplicate, remove, split_gaussians


def _setup(n=6):
    torch.manual_seed(0)
    params = create_gaussians(
        torch.randn(n, 3), torch.rand(n, 3), sh_degree=1, init_scale=torch.full((n,), 0.05)
    )
    opts = gaussian_optimizers(params, OptimConfig(), extent=1.0)
    loss = sum((p**2).sum() for p in params.values())
    loss.backward()
    for o in opts.values():
        o.step()
    return params, opts


def _check_aligned(params, opts):
    n = params["means"].shape[0]
    for name, p in params.items():
        assert p.shape[0] == n
        opt = opts[name]
        assert opt.param_groups[0]["params"][0] is p
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape


def test_duplicate_copies_rows_and_zeroes_new_moments():
    params, opts = _setup()
    before = params["means"].detach().clone()
    mask = torch.tensor([True, False, True, False, False, False])
    duplicate(params, opts, mask)
    _check_aligned(params, opts)
    assert torch.equal(params["means"][6:], before[mask])
    assert torch.count_nonzero(opts["means"].state[params["means"]]["exp_avg"][6:]) == 0


def test_split_replaces_with_smaller_children_near_parent():
    params, opts = _setup()
    parent_mean = params["means"][2].detach().clone()
    parent_scale = params["scales"][2].detach().clone()
    mask = torch.zeros(6, dtype=torch.bool)
    mask[2] = True
    split_gaussians(params, opts, mask)
    _check_aligned(params, opts)
    assert params["means"].shape[0] == 7
    children = params["scales"][-2:]
    assert torch.allclose(children, (parent_scale - torch.log(torch.tensor(1.6))).expand(2, 3), atol=1e-6)
    assert (params["means"][-2:] - parent_mean).norm(dim=-1).max() < 1.0  # within a few parent sigmas


def test_remove_and_refine_schedule():
    params, opts = _setup()
    params["opacities"].data[:2] = -10.0  # nearly transparent -> pruned
    remove(params, opts, torch.tensor([False] * 5 + [True]))
    _check_aligned(params, opts)
    assert params["means"].shape[0] == 5
    strategy = DefaultStrategy(
        DensifyConfig(refine_start=0, refine_every=1, grow_grad2d=1e-9), scene_extent=10.0
    )
    state = strategy.initialize_state()
    means2d = torch.zeros(5, 2, requires_grad=True)
    (means2d * torch.arange(10.0).reshape(5, 2)).sum().backward()
    info = {"means2d": means2d, "radii": torch.tensor([1, 1, 1, 1, 0]), "width": 10, "height": 10}
    report = strategy.step_post_backward(params, opts, state, step=1, render_infos=[info])
    _check_aligned(params, opts)
    # rows 0..3 are visible with a gradient and small (0.05 <= 0.01 * extent) -> cloned; row 4 is not seen
    assert report["cloned"] == 4 and report["split"] == 0
    # rows 0, 1 are transparent -> they and their clones are pruned
    assert report["pruned"] == 4
    assert params["means"].shape[0] == 5 + 4 - 4


def test_refinement_stops_by_a_fraction_of_short_runs():
    cfg = DensifyConfig(refine_stop=4500, refine_stop_fraction=0.5)
    assert DefaultStrategy(cfg, 1.0, total_steps=9500).refine_stop == 4500
    assert DefaultStrategy(cfg, 1.0, total_steps=3500).refine_stop == 1750
    assert DefaultStrategy(cfg, 1.0).refine_stop == 4500
    params, opts = _setup()
    strategy = DefaultStrategy(
        DensifyConfig(refine_start=0, refine_every=1, reset_every=1), 1.0, total_steps=4
    )
    before = params["opacities"].detach().clone()
    means2d = torch.zeros(6, 2, requires_grad=True)
    means2d.sum().backward()
    info = {"means2d": means2d, "radii": torch.ones(6), "width": 10, "height": 10}
    assert (
        strategy.step_post_backward(params, opts, strategy.initialize_state(), step=2, render_infos=[info])
        == {}
    )
    assert torch.equal(params["opacities"], before)  # no reset after the stop either


def test_growth_under_a_budget_takes_the_largest_gradients():
    params, opts = _setup()
    params["opacities"].data[:] = 5.0  # nothing is pruned
    params["scales"].data[3:] = 2.0  # rows 3..5 are large -> split; rows 0..2 small -> cloned
    strategy = DefaultStrategy(
        DensifyConfig(refine_start=0, refine_every=1, grow_grad2d=1e-9, max_gaussians=8), scene_extent=10.0
    )
    means2d = torch.zeros(6, 2, requires_grad=True)
    weights = torch.tensor([1.0, 5.0, 2.0, 6.0, 0.5, 3.0])  # gradient norm of each row, in pixels
    (means2d[:, 0] * weights).sum().backward()
    info = {"means2d": means2d, "radii": torch.ones(6), "width": 2, "height": 2}
    before = params["means"].detach().clone()
    report = strategy.step_post_backward(
        params, opts, strategy.initialize_state(), step=1, render_infos=[info]
    )
    _check_aligned(params, opts)
    # budget 8 - 6 = 2: rows 3 (6.0, large -> split) and 1 (5.0, small -> cloned), not the first rows
    assert report == {"cloned": 1, "split": 1, "pruned": 0}
    assert params["means"].shape[0] == 8
    assert torch.equal(params["means"][5], before[1])  # the clone follows the kept rows 0, 1, 2, 4, 5


def test_moving_refinement_leaves_the_held_gaussians_and_extends_the_mask():
    params, opts = _setup()
    params["opacities"].data[5] = -10.0  # transparent: pruned, unless held
    params["opacities"].data[4] = -10.0
    held = torch.tensor([True, True, False, False, False, True])
    strategy = DefaultStrategy(
        DensifyConfig(
            refine_every=1, grow_grad2d=1e-9, reset_every=0, moving_refine_stop=10, moving_max_gaussians=4
        ),
        scene_extent=10.0,
    )
    state = strategy.initialize_state()
    means2d = torch.zeros(6, 2, requires_grad=True)
    (means2d * torch.arange(1.0, 13.0).reshape(6, 2)).sum().backward()
    info = {"means2d": means2d, "radii": torch.ones(6, dtype=torch.int32), "width": 10, "height": 10}
    before = {k: p.detach().clone() for k, p in params.items()}
    report, grown = strategy.refine_moving(params, opts, state, step=1, render_infos=[info], held=held)
    _check_aligned(params, opts)
    # 3 moving (rows 2, 3, 4), budget 4: one clone, of the strongest gradient (row 4, transparent:
    # pruned with its clone); the held rows keep their values though row 5 is transparent
    assert report == {"cloned": 1, "split": 0, "pruned": 2}
    assert grown.shape == (params["means"].shape[0],) and grown.tolist() == [True, True, False, False, True]
    for k, p in params.items():
        assert torch.equal(p[grown], before[k][held])
    _, same = strategy.refine_moving(params, opts, state, step=10, render_infos=[info], held=grown)
    assert same is grown  # past moving_refine_stop nothing changes
