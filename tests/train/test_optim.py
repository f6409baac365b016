"""``step_adams`` (train/optim.py) against ``Optimizer.step``: the same parameters and state to the bit."""

from __future__ import annotations

import torch

from tracegs.train.optim import step_adams, zero_grads


def optimisers(fused: bool | None) -> tuple[list[torch.nn.Parameter], list[torch.optim.Optimizer]]:
    g = torch.Generator().manual_seed(0)
    params = [torch.nn.Parameter(torch.randn(50, 3, generator=g)) for _ in range(4)]
    opts = [
        torch.optim.Adam([params[0]], lr=1e-2, eps=1e-15, fused=fused),
        torch.optim.Adam(
            [
                {"params": [params[1]], "lr": 3e-3},
                {"params": [params[2], params[3]], "lr": 1e-3, "weight_decay": 0.1},
            ],
            eps=1e-15,
            fused=fused,
        ),
    ]
    return params, opts


def test_step_adams_updates_as_optimizer_step_does():
    for fused in (True, None):  # (the default loop: step_adams hands it to step())
        ours, our_opts = optimisers(fused)
        theirs, their_opts = optimisers(fused)
        for it in range(6):
            g = torch.Generator().manual_seed(it)
            grads = [torch.randn(50, 3, generator=g) for _ in ours]
            skipped = it == 3  # a parameter without a gradient this step keeps its value and state
            for params in (ours, theirs):
                for k, (p, grad) in enumerate(zip(params, grads, strict=True)):
                    p.grad = None if skipped and k == 3 else grad.clone()
            for opt in their_opts:
                opt.step()
                opt.zero_grad(set_to_none=True)
            step_adams([our_opts[0], None, our_opts[1]])
            zero_grads([*our_opts, None])
            assert all(p.grad is None for p in ours)
        for a, b in zip(ours, theirs, strict=True):
            assert torch.equal(a, b)
        for ours_opt, theirs_opt in zip(our_opts, their_opts, strict=True):
            for p, q in zip(
                [p for g in ours_opt.param_groups for p in g["params"]],
                [q for g in theirs_opt.param_groups for q in g["params"]],
                strict=True,
            ):
                for key in ("step", "exp_avg", "exp_avg_sq"):
                    assert torch.equal(ours_opt.state[p][key], theirs_opt.state[q][key])
        assert float(our_opts[0].state[ours[0]]["step"]) == 6
