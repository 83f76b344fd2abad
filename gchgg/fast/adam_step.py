"""Adam's fused CPU step without ``torch.optim``'s per-call bookkeeping: the speed device beside the agent's optimisers.

:class:`DDPGAgent` steps two ``torch.optim.Adam(..., fused=True)`` optimisers per update. Their
``step()`` spends a sizeable part of each call in Python for these small networks (hooks, grad mode,
profiler records, grouping the tensors by device and dtype). :func:`adam_step` calls the same kernel
with the same arguments that ``Adam.step`` passes it for such an optimiser (``torch._fused_adam_``,
after adding one to each parameter's ``step``), so parameters and optimiser state come out the same bit
for bit (``tests/test_adam_step.py``); ``python benchmarks/agent_update.py`` prints the update with it
against the same update with ``Adam.step``. The state stays the optimiser's own: ``state_dict``,
``load_state_dict`` and a learning-rate change go on working.

Where the step is not that plain one, :func:`adam_step` calls ``optimizer.step()``: another optimiser,
one not fused, with AMSGrad, weight decay, ``maximize``, ``capturable`` or ``differentiable``, several
parameter groups, parameters off the CPU or not float32, a parameter without a gradient, the first
step (which creates the state), and any step or global optimiser hook registered.
"""

from __future__ import annotations

import torch
from torch.optim import optimizer as _optimizer

__all__ = ["adam_step", "plain_fused_adam"]

_PLAIN = {"amsgrad": False, "maximize": False, "weight_decay": 0.0, "capturable": False,
          "differentiable": False, "decoupled_weight_decay": False, "fused": True}  # fmt: skip


def plain_fused_adam(optimizer: torch.optim.Optimizer) -> bool:
    """Whether ``optimizer`` is a fused CPU float32 Adam of one parameter group whose step is the plain
    Adam update (the settings above), with no hooks: the optimisers :func:`adam_step` steps itself."""
    if type(optimizer) is not torch.optim.Adam or len(optimizer.param_groups) != 1:
        return False
    group = optimizer.param_groups[0]
    if any(group.get(key, value) != value for key, value in _PLAIN.items()) or isinstance(group["lr"], torch.Tensor):
        return False
    if (optimizer._optimizer_step_pre_hooks or optimizer._optimizer_step_post_hooks
            or _optimizer._global_optimizer_pre_hooks or _optimizer._global_optimizer_post_hooks):  # fmt: skip
        return False
    return all(p.device.type == "cpu" and p.dtype == torch.float32 for p in group["params"])


def adam_step(optimizer: torch.optim.Optimizer) -> None:
    """``optimizer.step()``, computed by the fused kernel directly where :func:`plain_fused_adam` holds
    and every parameter has a gradient and a state (the step after the first)."""
    if not plain_fused_adam(optimizer):
        optimizer.step()
        return
    group = optimizer.param_groups[0]
    params = group["params"]
    states = [optimizer.state.get(p) for p in params]
    if any(state is None or "step" not in state or p.grad is None for p, state in zip(params, states, strict=True)):
        optimizer.step()  # the first step creates the state; a parameter without a gradient is skipped there
        return
    steps = [state["step"] for state in states]
    beta1, beta2 = group["betas"]
    torch._foreach_add_(steps, 1)
    torch._fused_adam_(
        params,
        [p.grad for p in params],
        [state["exp_avg"] for state in states],
        [state["exp_avg_sq"] for state in states],
        [],
        steps,
        amsgrad=False,
        lr=group["lr"],
        beta1=float(beta1),
        beta2=float(beta2),
        weight_decay=0.0,
        eps=group["eps"],
        maximize=False,
        grad_scale=None,
        found_inf=None,
    )
