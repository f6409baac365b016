"""``extrapolation.hold_unseen``: after the handover, the Gaussians that no training camera shows and that f_trd
moves much faster than f_defo did are kept where they are (f_trd was never shown them)."""

import math

import pytest
import torch
from tests.conftest import randomised_model, write_tiny_scene

from tracegs.config import make_config
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.extrapolate.calibrate import unseen_gaussians
from tracegs.physics.integrate import DynamicsParams
from tracegs.run import EXTRAPOLATION, load_extrapolation, load_run, load_tensors
from tracegs.train.trainer import Trainer

T_MAX = 0.75
V = torch.tensor([0.4, -0.2, 0.1])


def _controlled_model(hold: float, n: int = 30):
    """Three groups of ten Gaussians: shown by the cameras and moved by f_defo with V; unseen and kept
    still by f_defo (under a surface); unseen and moved by f_defo with V (inside a moving object).
    f_trd gives every Gaussian V as its equivalent velocity, with no rotation or acceleration.
    ``hold``: ``extrapolation.unseen_speed_ratio``, 0 = ``hold_unseen`` off. Returns the model, its
    predictor (its state: the unseen Gaussians), their positions at the handover and their groups."""
    cfg = make_config("tiny", device="cpu", bf16=False)
    cfg.extrapolation.hold_unseen = hold > 0
    if hold > 0:
        cfg.extrapolation.unseen_speed_ratio = hold
    model = randomised_model(cfg, n=n)
    canonical = model.gaussians["means"].detach().clone()
    group = torch.arange(n) // (n // 3)
    velocity = torch.where((group == 1)[:, None], torch.zeros(3), V)
    state = ExtrapolationState(t_max=T_MAX, unseen=group > 0)

    def deform(t):
        g = model.gaussians
        return {"means": canonical + t * velocity, "quats": g["quats"], "scales": g["scales"]}

    def query_dynamics(means, t):
        zero = torch.zeros_like(means)
        return DynamicsParams(V.expand_as(means).clone(), zero, zero, zero)

    model.deform, model.query_dynamics = deform, query_dynamics
    predictor = Predictor(model, state, cfg.extrapolation)
    return model, predictor, canonical + predictor.handover_time() * velocity, group


@pytest.mark.parametrize("hold", [3.0, 0.0])
def test_only_unseen_gaussians_the_fields_disagree_on_are_held(hold):
    model, predictor, handover, group = _controlled_model(hold)
    t = 1.3
    with torch.no_grad():
        means = predictor.gaussians_at(t)["means"]
    carried = handover + (t - predictor.handover_time()) * V  # x(t0) + V (t - t0)
    held = (group == 1) if hold > 0 else torch.zeros_like(group, dtype=torch.bool)
    torch.testing.assert_close(means[~held], carried[~held], rtol=0, atol=1e-5)
    torch.testing.assert_close(means[held], handover[held], rtol=0, atol=0)


def test_a_slow_unseen_drift_within_the_floor_moves_on():
    """f_trd's speed below 3 x the floor (0.05 scene units per unit of time) is not held, even where
    f_defo kept the Gaussian still."""
    model, predictor, handover, group = _controlled_model(3.0)
    slow = torch.tensor([0.1, 0.0, 0.0])
    model.query_dynamics = lambda means, t: DynamicsParams(
        slow.expand_as(means).clone(), *(torch.zeros_like(means) for _ in range(3))
    )
    with torch.no_grad():
        means = predictor.gaussians_at(1.0)["means"]
    torch.testing.assert_close(means, handover + (1.0 - predictor.handover_time()) * slow, rtol=0, atol=1e-5)


def test_unseen_gaussians_are_those_no_training_image_shows(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", n_times=5, size=24)
    cfg = make_config("tiny", data=scene, run=tmp_path / "run", device="cpu")
    model = Trainer(cfg, progress=False).model
    g = model.gaussians
    n = g["means"].shape[0]
    kind = torch.arange(n) % 3  # 0: opaque and large at the centre, 1: transparent, 2: out of every view
    with torch.no_grad():
        g["means"][kind == 0] = 0.1 * torch.randn(int((kind == 0).sum()), 3)
        g["scales"][kind == 0] = math.log(0.2)
        g["opacities"][kind == 0] = 5.0
        g["opacities"][kind == 1] = -20.0
        g["means"][kind == 2] = torch.tensor([0.0, 0.0, -20.0])  # far below the cameras' view
    unseen = unseen_gaussians(model, scene, 1, T_MAX)
    assert unseen.shape == (n,) and unseen.dtype == torch.bool
    assert unseen[kind > 0].all()
    # the front ones of the opaque cluster are shown (those behind them may be hidden)
    assert (~unseen[kind == 0]).float().mean() > 0.2


def test_the_unseen_mask_is_found_after_training_and_kept_in_the_run_folder(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", n_times=5, size=24)
    cfg = make_config("tiny", data=scene, run=tmp_path / "run", device="cpu", init_points=200)
    trainer = Trainer(cfg, progress=False)
    trainer.train()
    mask = trainer.extrapolation.unseen
    assert mask is not None and mask.shape == (trainer.model.gaussians["means"].shape[0],)
    saved = load_tensors(tmp_path / "run" / EXTRAPOLATION)
    assert torch.equal(saved["unseen"], mask)
    assert torch.equal(load_extrapolation(tmp_path / "run").unseen, mask)
    assert torch.equal(load_run(tmp_path / "run", device="cpu").state.unseen, mask)


def test_still_codes_say_why_each_gaussian_holds_still_the_first_reason_winning():
    """Group 1 (unseen, still under f_defo) is held as UNSEEN; marking Gaussians static in training
    overrides that reason for those rows, and the Gaussians that move keep MOVES."""
    from tracegs.extrapolate.still import MOVES, STATIC, UNSEEN, still_codes

    model, predictor, handover, group = _controlled_model(3.0)
    t0 = predictor.handover_time()
    params = model.query_dynamics(handover, t0)
    codes = still_codes(predictor, t0, handover, params)
    assert codes.dtype == torch.uint8
    assert (codes[group == 1] == UNSEEN).all() and (codes[group != 1] == MOVES).all()
    static = torch.zeros(len(group), dtype=torch.bool)
    static[:5], static[10:12] = True, True  # shown ones and two of the unseen ones
    model.set_static_mask(static)
    codes = still_codes(predictor, t0, handover, params)
    assert (codes[static] == STATIC).all()
    assert (codes[(group == 1) & ~static] == UNSEEN).all()
    assert (codes[(group != 1) & ~static] == MOVES).all()
