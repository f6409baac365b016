"""What keeps a long training safe from its own numbers and from Ctrl-C: the NaN guard's checks, and
an interrupt that waits for the step under way to end (a checkpoint then holds a whole step)."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import torch


class NonFinite(ArithmeticError):
    """A step's loss or gradients, or the parameters, are not finite (NaN or Inf)."""

    def __init__(self, step: int, what: str):
        super().__init__(f"non-finite {what} at step {step}")
        self.step, self.what = step, what


def first_non_finite(tensors: Iterable[torch.Tensor]) -> int | None:
    """Index of the first of ``tensors`` holding a NaN or Inf, or None (empty tensors are finite)."""
    # the least and largest value of each (a NaN makes both NaN, an Inf shows in one): no copy of the
    # tensors, one host sync for all of them
    ends = [
        torch.stack(torch.aminmax(t.detach())).float() if t.numel() else t.new_zeros(2, dtype=torch.float)
        for t in tensors
    ]
    if not ends:
        return None
    finite = torch.isfinite(torch.stack(ends)).all(dim=1)
    return None if bool(finite.all()) else int((~finite).nonzero()[0])


def any_non_finite(tensors: list[torch.Tensor]) -> bool:
    """Whether one of ``tensors`` (floating point, on one device) holds a NaN or Inf: one fused pass
    over all of them where torch has it (GradScaler's check, here with a scale of exactly 1, which
    leaves every value as it is), else ``first_non_finite``."""
    if not tensors:
        return False
    check = getattr(torch, "_amp_foreach_non_finite_check_and_unscale_", None)
    if check is not None and len({t.device for t in tensors}) == 1:
        found = torch.zeros(1, device=tensors[0].device)
        try:
            check(tensors, found, torch.ones(1, device=found.device))
            return bool(found.item())
        except (RuntimeError, NotImplementedError):  # a dtype or device the fused check does not take
            pass
    return first_non_finite(tensors) is not None


def check_step(loss: torch.Tensor, parameters: Iterable[torch.Tensor], step: int) -> None:
    """NonFinite when the ``loss`` or a gradient of ``parameters`` holds a NaN or Inf (called between
    the backward pass and the optimiser step, so that nothing is updated from them)."""
    if not bool(torch.isfinite(loss.detach()).all()):
        raise NonFinite(step, "loss")
    if any_non_finite([p.grad for p in parameters if p.grad is not None]):
        raise NonFinite(step, "gradient")


def check_parameters(parameters: Iterable[torch.Tensor], step: int) -> None:
    """NonFinite when one of ``parameters`` holds a NaN or Inf (before a checkpoint keeps them)."""
    if first_non_finite(list(parameters)) is not None:
        raise NonFinite(step, "parameters")


@dataclass
class Interrupt:
    requested: bool = False
    """Whether Ctrl-C came; the loop ends its step, saves and raises KeyboardInterrupt."""


@contextlib.contextmanager
def interrupt_at_step_end() -> Iterator[Interrupt]:
    """Within the block, Ctrl-C (SIGINT) sets ``Interrupt.requested`` rather than raising where the step
    happens to be; a second Ctrl-C raises KeyboardInterrupt at once. Outside the main thread (which
    alone receives signals) Ctrl-C is left as it is."""
    interrupt = Interrupt()
    if threading.current_thread() is not threading.main_thread():
        yield interrupt
        return
    previous = signal.getsignal(signal.SIGINT)
    previous = signal.default_int_handler if previous is None else previous

    def handler(signum, frame):
        interrupt.requested = True
        signal.signal(signal.SIGINT, previous)

    signal.signal(signal.SIGINT, handler)
    try:
        yield interrupt
    finally:
        signal.signal(signal.SIGINT, previous)


def diverged(checkpoint, err: NonFinite, first: dict, factor: float, step: int) -> str:
    """The message of a training stopped by the NaN guard's second restoration (``err``): the first
    restoration ``first`` ({"step", "to_step", "what"}), the learning-rate ``factor`` it applied, and
    the ``step`` the ``checkpoint`` keeps."""
    return (
        f"{checkpoint.parent}: training diverged: {err} after the {first['what']} at step {first['step']} "
        f"had restored step {first['to_step']} with the learning rates x{factor}; "
        f"{checkpoint} keeps step {step}, the last good state"
    )
