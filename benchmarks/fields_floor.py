"""How far the fields of a training step are from their FLOP floor, on this CPU.

A trained run's model (its checkpoint, the demo's sizes: its Gaussians, its static mask) computes one
stage-2 step's fields, forward and backward (`TraceModel.training_state`: f_defo at t', f_trd there,
the RK2 integration, the acceleration consistency), without the rasteriser. Their floating-point
operations are counted by PyTorch's own counter (`torch.utils.flop_counter.FlopCounterMode`, matrix
products only: what dominates a 4 x 64 MLP). The floor is that count at the best rate this CPU
reaches in one large matrix product in the fields' dtype (bf16 where the run uses it, else float32),
with the same threads. Ratio = measured time / floor. The step's own matrix products (their shapes and
dtypes) are also timed replayed alone: what the fields would cost if every other op were free; and so
are its fused MLP calls (the native op's own forward and backward, as the step called them): the
fields without the glue between those calls.

The loop runs on a heap that keeps its freed memory (glibc ``mallopt``), as a training's grown heap
does (0-5 page faults a step); the faults per step are reported. The kernels (all the native ops as
the step's one autograd node; the fused MLP with the other native ops, the RK2, the positional
encoding, f_defo's output applied, each its own node; none) are measured in alternate blocks of one
process, each row taking its fastest block.

Run it alone on the machine. Usage:
.venv/bin/python benchmarks/fields_floor.py --run runs/demo/trace [--fields run|bf16|fp32] [--isa native|avx2]
    [--json F]
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import functools
import json
import resource
import sys
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from tracegs.machine import ISA_ENVIRONMENTS, json_of_process_held_to
from tracegs.models import deformation, encoding, fused_mlp
from tracegs.models import fields_step as one_node
from tracegs.physics import fused
from tracegs.results import make_record, write_record
from tracegs.run import load_run


def fastest_ms(call, blocks: int, calls: int, warmup: int = 0) -> float:
    """Milliseconds per ``call()`` in the fastest of ``blocks`` blocks of ``calls`` calls, after
    ``warmup`` calls (the other blocks ran beside whatever else the host did)."""
    for _ in range(warmup):
        call()
    best = float("inf")
    for _ in range(blocks):
        start = time.perf_counter()
        for _ in range(calls):
            call()
        best = min(best, 1000 * (time.perf_counter() - start) / calls)
    return best


def gemm_rate(dtype: torch.dtype, size: int = 2048, blocks: int = 6, repeats: int = 4) -> float:
    """FLOP/s of a [size, size] x [size, size] matrix product in ``dtype`` (the CPU's practical peak):
    the fastest of ``blocks`` blocks of ``repeats`` products."""
    a, b = torch.randn(size, size).to(dtype), torch.randn(size, size).to(dtype)
    return 2 * size**3 / (fastest_ms(lambda: a @ b, blocks, repeats, warmup=3) / 1000)


def keep_freed_memory() -> bool:
    """Ask glibc to keep freed memory in the heap (no mmap per large buffer, no trimming), as a
    training's grown heap does; False where the C library is not glibc."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        m_trim_threshold, m_mmap_threshold = -1, -3
        return bool(libc.mallopt(m_mmap_threshold, 1 << 30)) and bool(libc.mallopt(m_trim_threshold, 1 << 30))
    except (OSError, AttributeError, TypeError):
        return False


def loss_weights(model, t_prime: float, t: float) -> dict[str, torch.Tensor]:
    """Fixed random weights of the outputs (a stand-in for the rasteriser's gradient)."""
    with torch.no_grad():
        state, _ = model.training_state(t_prime, t)
    g = torch.Generator().manual_seed(0)
    return {name: torch.randn(state[name].shape, generator=g) for name in ("means", "quats", "scales")}


def fields_step(model, t_prime: float, t: float, weights: dict[str, torch.Tensor]) -> None:
    """One step's fields, forward and backward (a fixed random functional of every output); the
    gradients then dropped as the trainer's optimisers drop them (``train.optim.zero_grads``: by
    their parameters, not by walking the modules)."""
    state, losses = model.training_state(t_prime, t)
    total = sum(v.sum() for v in losses.values()) if losses else 0.0
    for name, w in weights.items():
        total = total + (state[name] * w).sum()
    total.backward()
    for p in _parameters(model):
        p.grad = None


@functools.cache
def _parameters(model) -> list[torch.Tensor]:
    return list(model.parameters())


GEMMS = {torch.ops.aten.mm.default, torch.ops.aten.addmm.default, torch.ops.aten.bmm.default}


class _RecordGemms(TorchDispatchMode):
    """Records the shapes and dtypes of the matrix products a step runs."""

    def __init__(self):
        super().__init__()
        self.calls: list[tuple] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func in GEMMS:
            tensors = [a for a in args if isinstance(a, torch.Tensor)]
            self.calls.append((func, [(tuple(a.shape), a.stride(), a.dtype) for a in tensors]))
        return func(*args, **(kwargs or {}))


def gemms_alone_ms(model, t_prime: float, t: float, weights, blocks: int = 6, steps: int = 20) -> float:
    """The step's own matrix products (its shapes, strides and dtypes), replayed alone on fresh operands:
    what the fields would cost with every other op free. The fastest block, per step."""
    with _RecordGemms() as recorder:
        fields_step(model, t_prime, t, weights)
    replay = []
    for func, operands in recorder.calls:
        tensors = [
            torch.empty_strided(shape, stride, dtype=dtype).normal_() for shape, stride, dtype in operands
        ]
        replay.append((func, tensors))

    def step():
        for func, tensors in replay:
            func(*tensors)

    return fastest_ms(step, blocks, steps)


class _RecordMLPs:
    """Stands in for the fields' native ops for one step: records the fused MLP calls' arguments."""

    def __init__(self, ops):
        self.ops, self.calls = ops, []

    def __getattr__(self, name):  # (the encoding's and the deformation's ops, as they are)
        return getattr(self.ops, name)

    def mlp_forward(self, *args):
        self.calls.append((self.ops.mlp_forward, args))
        return self.ops.mlp_forward(*args)

    def mlp_backward(self, *args):
        self.calls.append((self.ops.mlp_backward, args))
        return self.ops.mlp_backward(*args)


def mlps_alone_ms(model, t_prime: float, t: float, weights, blocks: int = 6, steps: int = 20) -> float:
    """The step's fused MLP calls (forward and backward, their inputs, settings and threads) replayed
    alone: the fields' time without the glue between them (Python, autograd, the other ops). The
    fastest block, per step."""
    recorder = _RecordMLPs(fused_mlp.EXTENSION.load())
    fused_mlp.EXTENSION.load = lambda: recorder  # (an instance attribute over the class' method)
    try:
        fields_step(model, t_prime, t, weights)
    finally:
        del fused_mlp.EXTENSION.load

    def step():
        for call, args in recorder.calls:
            call(*args)

    return fastest_ms(step, blocks, steps, warmup=2)


KERNELS = {
    "one node": (True, True, True),
    "fused MLP + native ops": (True, True, False),
    "pytorch": (False, False, False),
}
"""Rows: the field MLPs' fused op (``models/fused_mlp.py``; float32, and bf16 where it has
``bf16_products``) with the other native ops (the RK2, ``physics/fused.py``; the positional
encoding, ``models/encoding.py``; f_defo's output applied to the Gaussians, ``models/deformation.py``,
``deform_rows``), all of them as the step's one autograd node (``models/fields_step.py``) or each as
its own; or none of them (the PyTorch layers and ops)."""


def fixed_ms(model, t_prime: float, t: float, points: int = 16, blocks: int = 6, steps: int = 20) -> float:
    """The step's time with its moving Gaussians cut to the first ``points``: what a step costs
    whatever the points (Python, autograd, the ops' calls and threads' start), with the kernels in use."""
    full = model._moving
    rows = torch.arange(model.gaussians["means"].shape[0]) if full is None else full
    model._moving = rows[:points]
    try:
        weights = loss_weights(model, t_prime, t)
        return fastest_ms(lambda: fields_step(model, t_prime, t, weights), blocks, steps, warmup=5)
    finally:
        model._moving = full


def use_kernels(name: str) -> None:
    fused_mlp.ENABLED, native, one_node.ENABLED = KERNELS[name]
    fused.ENABLED = encoding.NATIVE = deformation.NATIVE_DEFORM = native
    fused_mlp.MIN_VECTOR_BYTES = 0  # (measured on any build: the fields take it with AVX-512 only)


def measure(model, threads: int, blocks: int = 6, steps: int = 20) -> list[dict]:
    """Rows for the kernels of ``KERNELS`` (without the fused MLP in bf16 where it has no bf16 products),
    measured in alternating blocks of ``steps`` steps: each row's time is its fastest block (the others
    ran beside whatever else the host did; an A/B in one process cancels the drift between runs)."""
    torch.set_num_threads(threads)
    t_prime, t = 0.55, 0.6
    weights = loss_weights(model, t_prime, t)
    use_kernels("pytorch")  # (the counter sees ATen's products, not the fused op's own)
    with FlopCounterMode(display=False) as counter:
        fields_step(model, t_prime, t, weights)
    flops = counter.get_total_flops()
    no_bf16 = model.bf16 and not fused_mlp.bf16_products()
    names = [name for name in KERNELS if not (no_bf16 and KERNELS[name][0])]
    for name in names:
        use_kernels(name)
        for _ in range(5):
            fields_step(model, t_prime, t, weights)
    best = dict.fromkeys(names, float("inf"))
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for block in range(len(names) * blocks):
        name = names[block % len(names)]
        use_kernels(name)
        start = time.perf_counter()
        for _ in range(steps):
            fields_step(model, t_prime, t, weights)
        best[name] = min(best[name], 1000 * (time.perf_counter() - start) / steps)
    faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults) / (len(names) * blocks * steps)
    fixed = {}
    for name in names:
        use_kernels(name)
        fixed[name] = fixed_ms(model, t_prime, t)
    use_kernels("one node")
    dtype = torch.bfloat16 if model.bf16 else torch.float32
    rate = gemm_rate(dtype)
    floor_ms = 1000 * flops / rate
    use_kernels("pytorch")
    gemms_ms = gemms_alone_ms(model, t_prime, t, weights)  # (the fused MLP runs its own products)
    use_kernels("one node")
    mlps_ms = mlps_alone_ms(model, t_prime, t, weights) if "one node" in names else None
    rows = model.moving_rows
    moving = model.gaussians["means"].shape[0] if rows is None else rows.numel()
    return [
        {
            "threads": threads,
            "kernels": name,
            "dtype": str(dtype).removeprefix("torch."),
            "moving_gaussians": moving,
            "mflop_per_step": round(flops / 1e6, 1),
            "gemm_gflops": round(rate / 1e9, 1),
            "floor_ms": round(floor_ms, 3),
            "gemms_alone_ms": round(gemms_ms, 2),
            "mlps_alone_ms": round(mlps_ms, 2) if mlps_ms is not None and KERNELS[name][0] else None,
            "measured_ms": round(best[name], 2),
            "ratio": round(best[name] / floor_ms, 1),
            "fixed_ms": round(fixed[name], 2),
            "page_faults_per_step": round(faults),
        }
        for name in names
    ]


def measure_run(run: Path, fields: list[str], blocks: int = 6) -> list[dict]:
    """The rows of every dtype of ``fields`` and 1 and 2 threads for the run's model."""
    model = load_run(run, "cpu").model
    as_loaded = model.bf16
    model.train()
    for p in model.parameters():
        p.requires_grad_(True)
    rows = []
    for dtype in fields:
        model.bf16 = as_loaded if dtype == "run" else dtype == "bf16"
        rows += [row for threads in (1, 2) for row in measure(model, threads, blocks)]
    return rows


def record_notes(blocks: int) -> str:
    """The record's notes: what the columns measure, and how (``blocks``: blocks of 20 steps a row)."""
    return (
        "One step's fields (f_defo, f_trd, RK2, the acceleration consistency) forward and backward on the "
        "run's Gaussians, without the rasteriser; floor = the step's matrix-product FLOPs at the rate of a "
        "2048^2 product in the same dtype and threads, `gemms_alone` and `mlps_alone` the step's matrix "
        f"products and fused MLP calls replayed alone. `measured` is the fastest of {blocks} blocks of 20 "
        "steps (the kernels in alternate blocks of one process), `fixed` the part that does not scale with "
        "the Gaussians."
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--run", type=Path, required=True, help="a trained run folder (e.g. the demo's)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--fields", choices=("run", "bf16", "fp32"), nargs="+", default=["run"],
        help="the fields' dtype (rows for each): the run's (as it loads on this CPU), bf16, fp32",
    )  # fmt: skip
    ap.add_argument(
        "--isa", choices=tuple(ISA_ENVIRONMENTS), nargs="+", default=["native"],
        help="instruction sets (rows for each): this CPU's, or AVX2 only (as an AVX2 laptop runs; float32)",
    )  # fmt: skip
    ap.add_argument(
        "--blocks", type=int, default=6,
        help="blocks of 20 steps per kernel (each row its fastest block): more on a host whose speed drifts",
    )  # fmt: skip
    ap.add_argument("--rows-only", action="store_true", help=argparse.SUPPRESS)  # (a child's JSON rows)
    args = ap.parse_args()
    kept = keep_freed_memory()
    if args.rows_only:
        print(json.dumps(measure_run(args.run, args.fields, args.blocks)))
        return
    rows = []
    for isa in args.isa:
        # an AVX2-only CPU runs the fields in float32 (bf16 without hardware dot products is ~100x slower)
        fields = ["fp32"] if isa == "avx2" else args.fields
        command = [sys.executable, __file__, "--run", str(args.run), "--fields", *fields, "--rows-only"]
        command += ["--blocks", str(args.blocks)]
        rows += [{"isa": isa, **row} for row in json_of_process_held_to(isa, command)]
    if not kept:  # (the caveat a reader needs, where glibc's mallopt was not there to keep the heap)
        rows = [{**row, "freed_memory_kept": False} for row in rows]
    for row in rows:
        print(row)
    if args.json:
        record = make_record(
            "fields-floor",
            rows,
            f"tracegs demo; python benchmarks/fields_floor.py --run {args.run} --fields {' '.join(args.fields)} "
            f"--isa {' '.join(args.isa)} --blocks {args.blocks} --json {args.json}",
            title="The fields of one stage-2 step against their FLOP floor",
            notes=record_notes(args.blocks),
        )
        write_record(args.json, record)


if __name__ == "__main__":
    main()
