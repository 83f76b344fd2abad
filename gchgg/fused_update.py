"""The DDPG update of :class:`gchgg.agent.HindsightDDPGLoss` differentiated by hand: the speed device beside the loss.

:class:`HindsightDDPGLoss` states the losses (the paper's and the original code's critic and actor
losses) and autograd differentiates them. Part of that update is spent outside the products:
building and walking the autograd graph, ``nn.Module`` calls, normalising the same batch three
times, and in bfloat16 converting every activation to and from float32. :class:`FusedDDPGUpdate`
computes the same losses and gradients with the products written out:

- the observation and goal are normalised once for the actor and both critic terms;
- the critic loss's backward writes the critic's weight gradients; the actor loss's backward
  through the critic computes input gradients only and keeps the action's (the critic's weights
  get no gradient from it, as :meth:`HindsightDDPGLoss.actor_loss` says);
- each weight gradient is one ``torch.mm`` into the parameter's ``.grad`` (overwritten, not
  accumulated); the ReLU and tanh backwards are autograd's own kernels (``threshold_backward``,
  ``tanh_backward``).

Every product is one autograd computes, of the same shapes, so the losses and gradients equal
autograd's bit for bit (``tests/test_fused_update.py``, batch sizes 5 to 256; the recorded tiny runs of
``tests/test_same_numbers.py`` do not move). ``python benchmarks/agent_update.py`` times it against
the autograd update and the bare plain-torch one (``fused / autograd agent``, ``fused / bare``).

It applies to the networks :func:`gchgg.agent.make_ddpg_networks` builds: ReLU MLPs of float32
``nn.Linear`` layers with biases (:func:`unsupported` says why other networks are not), on torch's
BLAS or converted to oneDNN (:mod:`gchgg.linear`). A :class:`~gchgg.linear.OneDNNLinear` layer's
products are computed as it computes them, by oneDNN in the products' precision (float32, or
bfloat16 with ``precision=bfloat16``: operands and results rounded, float32 accumulation), so the
fused update equals the autograd update bit for bit in every setting (``tests/test_fused_update.py``);
with bfloat16 it also keeps the hidden activations in bfloat16, rounds an online network's weight once
per update and a target network's only after it moved (every ``target_update_every``-th update) rather
than once per product, and lets oneDNN apply each hidden ReLU inside its product (``_Products``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

from gchgg.linear import MIN_BATCH, OneDNNLinear, onednn_linear, onednn_mm

if TYPE_CHECKING:  # the loss module is only read: its networks, normalisers and constants
    from gchgg.agent import HindsightDDPGLoss

__all__ = ["FusedDDPGUpdate", "unsupported"]


def _relu_mlp_layers(mlp: nn.Module) -> list[nn.Linear] | str:
    """The linear layers of ``Linear, ReLU, …, Linear``, or why ``mlp`` is not such a network."""
    modules = list(mlp.children()) if isinstance(mlp, nn.Sequential) else []
    if not modules or len(modules) % 2 != 1:
        return f"{type(mlp).__name__} is not a Sequential of Linear, ReLU, ..., Linear"
    for i, module in enumerate(modules):
        wanted = (nn.Linear, OneDNNLinear) if i % 2 == 0 else (nn.ReLU,)
        if type(module) not in wanted:  # other subclasses may compute their products otherwise
            return f"layer {i} is {type(module).__name__}, not {wanted[0].__name__}"
        if i % 2 == 0 and (module.bias is None or module.weight.dtype != torch.float32
                           or module.weight.device.type != "cpu"):  # fmt: skip
            return f"layer {i} is not a float32 CPU nn.Linear with a bias"
    return modules[::2]


def unsupported(loss: HindsightDDPGLoss) -> str | None:
    """Why :class:`FusedDDPGUpdate` cannot compute ``loss``'s update, or ``None`` where it can."""
    for name in ("actor", "critic", "target_actor", "target_critic"):
        layers = _relu_mlp_layers(getattr(loss, name).mlp)
        if isinstance(layers, str):
            return f"the {name}'s mlp: {layers}"
    if not (loss.actor.observation_normalizer is loss.critic.observation_normalizer
            and loss.actor.goal_normalizer is loss.critic.goal_normalizer):  # fmt: skip
        return "the actor and the critic do not share their normalisers"
    return None


class _Products:
    """The products of one network's layers in one update, as its layers compute them under autograd.

    A :class:`OneDNNLinear` layer given a batch of at least :data:`MIN_BATCH` rows multiplies on oneDNN
    in the products' dtype (operands rounded to it, results in it); every other layer multiplies in
    float32 on torch's BLAS (``addmm``/``mm``). A layer's weight is rounded once per update (a target
    network's once after it moved) and serves the forward passes and the backward; a hidden oneDNN
    layer's ReLU is applied by oneDNN before it rounds the product (the same values: rounding is
    monotone and keeps 0). Activations stay in the dtype they were computed in: ReLU and its backward
    commute with rounding to bfloat16, so keeping a bfloat16 result instead of its float32 copy (what
    autograd's layers return) changes no value and saves two conversions per layer.
    """

    def __init__(self, layers: list[nn.Linear], dtype: torch.dtype, rounded: dict | None = None) -> None:
        self.layers = layers
        self.dtype = dtype
        # layer index -> (weight, its data pointer and version, it in the products' dtype): kept across
        # updates when given (a target network's, moved every n-th update), so an unchanged weight is not
        # rounded again; the in-place changes such a weight sees (lerp_, load_state_dict's copy_) bump its
        # version. Not for weights a fused optimiser steps: its kernel leaves the version as it was.
        self._rounded = {} if rounded is None else rounded

    def onednn(self, i: int, x: torch.Tensor) -> bool:
        """Whether layer ``i`` computes its product with ``x`` on oneDNN (as :class:`OneDNNLinear` would)."""
        return type(self.layers[i]) is OneDNNLinear and x.shape[0] >= MIN_BATCH

    def weight(self, i: int) -> torch.Tensor:
        """Layer ``i``'s weight in the products' dtype, rounded again only after the weight changed."""
        weight = self.layers[i].weight
        stamp = (weight.data_ptr(), weight._version)
        kept = self._rounded.get(i)
        if kept is None or kept[0] is not weight or kept[1] != stamp:  # another tensor, or changed
            kept = self._rounded[i] = (weight, stamp, weight.detach().to(self.dtype))
        return kept[2]

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """``[x_0, h_1, …, h_{L-1}, y]``: each layer's input as its product used it (ReLU outputs after
        the first) and the last layer's float32 output."""
        outputs, last = [], len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            if self.onednn(i, x):
                x = x.to(self.dtype)
                y = onednn_linear(x, self.weight(i), layer.bias, relu=i < last)  # the ReLU fused into the product
            else:
                x = x.float()
                y = torch.addmm(layer.bias, x, layer.weight.t())
                if i < last:
                    y.relu_()
            outputs.append(x)
            x = y if i < last else y.float()
        outputs.append(x)
        return outputs

    def input_gradient(self, i: int, x: torch.Tensor, grad_y: torch.Tensor) -> torch.Tensor:
        """``∂y·W`` of layer ``i`` (whose product took ``x``), in its product's dtype."""
        if self.onednn(i, x):
            return onednn_mm(grad_y.to(self.dtype), self.weight(i))
        return torch.mm(grad_y.float(), self.layers[i].weight)

    def weight_gradients(self, i: int, x: torch.Tensor, grad_y: torch.Tensor) -> None:
        """Write layer ``i``'s ``.grad`` of weight (``∂yᵀ·x``) and bias (``Σ ∂y``)."""
        layer = self.layers[i]
        if self.onednn(i, x):
            grad_y = grad_y.to(self.dtype)
            _grad(layer.weight).copy_(onednn_mm(grad_y.t(), x))
            torch.sum(grad_y, 0, dtype=torch.float32, out=_grad(layer.bias))  # = grad_y.float().sum(0), one pass
        else:
            grad_y = grad_y.float()
            torch.mm(grad_y.t(), x, out=_grad(layer.weight))
            torch.sum(grad_y, 0, out=_grad(layer.bias))

    def backward_input(self, outputs: list[torch.Tensor], grad_y: torch.Tensor) -> torch.Tensor:
        """The float32 gradient of the first layer's input from the output gradient ``grad_y``; no weight
        gradients."""
        grad = grad_y
        for i in range(len(self.layers) - 1, 0, -1):  # ∂x = ∂y·W, through the ReLU whose output is this layer's input
            grad = torch.ops.aten.threshold_backward(self.input_gradient(i, outputs[i], grad), outputs[i], 0)
        return self.input_gradient(0, outputs[0], grad).float()

    def backward_weights(self, outputs: list[torch.Tensor], grad_y: torch.Tensor) -> None:
        """Write every layer's weight and bias gradients from the output gradient ``grad_y`` (the first
        layer's input gradient is not computed: nothing needs it)."""
        grad = grad_y
        for i in range(len(self.layers) - 1, -1, -1):
            self.weight_gradients(i, outputs[i], grad)
            if i > 0:
                grad = torch.ops.aten.threshold_backward(self.input_gradient(i, outputs[i], grad), outputs[i], 0)


def _grad(parameter: nn.Parameter) -> torch.Tensor:
    """``parameter.grad``, allocated where it is missing, to be overwritten."""
    if parameter.grad is None:
        parameter.grad = torch.empty_like(parameter)
    return parameter.grad


class FusedDDPGUpdate:
    """The losses of ``loss`` and the gradients of its online actor and critic, without autograd.

    Call :meth:`forward` with a batch's tensors (what :meth:`HindsightDDPGLoss.losses` takes); it returns
    what that returns, as tensors without a graph. Then :meth:`backward` writes every parameter's
    ``.grad`` of the online actor and critic (overwriting it), as ``(loss_actor + loss_value).backward()``
    after zeroed gradients would; the optimisers step as usual. Target networks, normalisers and
    constants are read from ``loss`` at every call, so it follows their updates and a loaded state.

    Args:
        loss: the loss module; its networks must pass :func:`unsupported`.
        precision: the dtype of the :class:`~gchgg.linear.OneDNNLinear` layers' products, ``"float32"`` or
            ``"bfloat16"`` (resolved: what :func:`gchgg.linear.resolve_precision` returns and the autograd
            update would compute them in under :func:`gchgg.linear.products_in`); plain ``nn.Linear``
            layers multiply in float32.

    Raises:
        ValueError: ``loss`` has networks this update does not compute (the reason given), or
            ``precision`` is not a resolved precision.
    """

    def __init__(self, loss: HindsightDDPGLoss, precision: str = "float32") -> None:
        reason = unsupported(loss)
        if reason is not None:
            raise ValueError(f"FusedDDPGUpdate needs ReLU MLPs of plain float32 nn.Linear layers: {reason}")
        self.loss = loss
        if precision not in ("float32", "bfloat16"):
            raise ValueError(f"precision must be 'float32' or 'bfloat16' (resolved, as gchgg.linear.resolve_precision "
                             f"returns it), got {precision!r}")
        self.precision = precision
        self._dtype = getattr(torch, precision)
        self._layers = {name: _relu_mlp_layers(getattr(loss, name).mlp)
                        for name in ("actor", "critic", "target_actor", "target_critic")}  # fmt: skip
        # The target networks' rounded weights, kept across updates (see _Products). Only theirs: they move
        # in place by lerp_ and load_state_dict, which bump a tensor's version; a fused optimiser's step
        # (the online networks') does not.
        self._rounded: dict[str, dict] = {"target_actor": {}, "target_critic": {}}
        self._saved: tuple | None = None

    @torch.no_grad()
    def forward(
        self,
        observation: torch.Tensor,
        goal: torch.Tensor,
        action: torch.Tensor,
        next_observation: torch.Tensor,
        reward: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(loss_actor, loss_value, pred_value [B, 1], target_value [B, 1])``, the values of
        :meth:`HindsightDDPGLoss.losses`; keeps what :meth:`backward` needs."""
        loss, actor = self.loss, self.loss.actor
        normalize = lambda o, g: torch.cat([actor.observation_normalizer(o), actor.goal_normalizer(g)], -1)  # noqa: E731
        next_x = normalize(next_observation, goal)
        products = {name: _Products(layers, self._dtype, self._rounded.get(name))
                    for name, layers in self._layers.items()}  # fmt: skip
        next_action = products["target_actor"].forward(next_x)[-1].tanh_()
        next_value = products["target_critic"].forward(torch.cat([next_x, next_action], -1))[-1]
        if loss.clip_return:
            next_value = next_value.clamp_(*loss.return_range)
        target_value = reward + loss.gamma * next_value

        x = normalize(observation, goal)
        actor, critic = products["actor"], products["critic"]
        actor_outputs = actor.forward(x)
        policy_action = actor_outputs[-1].tanh()
        value_outputs = critic.forward(torch.cat([x, action], -1))  # Q(s‖g, a)
        policy_outputs = critic.forward(torch.cat([x, policy_action], -1))  # Q(s‖g, π(s‖g))
        pred_value, policy_value = value_outputs[-1], policy_outputs[-1]
        if pred_value.shape != target_value.shape:
            raise ValueError(
                f"the reward must be [B, 1] like the critic's output {tuple(pred_value.shape)}, "
                f"got {tuple(reward.shape)}"
            )
        error = pred_value - target_value
        loss_value = error.square().mean()
        loss_actor = -policy_value.mean()
        if loss.action_l2:
            loss_actor = loss_actor + loss.action_l2 * policy_action.square().mean()
        self._saved = (actor, critic, error, policy_action, actor_outputs, value_outputs, policy_outputs)
        return loss_actor, loss_value, pred_value, target_value

    @torch.no_grad()
    def backward(self) -> None:
        """Write the online actor's and critic's ``.grad`` from the last :meth:`forward`."""
        if self._saved is None:
            raise RuntimeError("FusedDDPGUpdate.backward() needs a forward() first (and runs once per forward)")
        actor, critic, error, policy_action, actor_outputs, value_outputs, policy_outputs = self._saved
        self._saved = None
        # the critic loss: ∂ mean((Q − y)²) / ∂Q into the critic's weights
        critic.backward_weights(value_outputs, error * (2.0 / error.numel()))
        # the actor loss: ∂(−mean Q(s‖g, π)) / ∂Q back to the action only (the critic's weights are constants)
        grad_q = torch.full_like(policy_outputs[-1], -1.0 / policy_outputs[-1].numel())
        grad_action = critic.backward_input(policy_outputs, grad_q)[:, -policy_action.shape[-1]:]
        if self.loss.action_l2:
            # ∂(l2·mean(a²))/∂a in autograd's order and rounding: (float32(l2) / n) · 2a
            scale = torch.tensor(self.loss.action_l2, dtype=grad_action.dtype) / policy_action.numel()
            grad_action = grad_action + (2 * policy_action) * scale
        grad_pre_tanh = torch.ops.aten.tanh_backward(grad_action, policy_action)  # ∂y·(1 − y²), as autograd
        actor.backward_weights(actor_outputs, grad_pre_tanh)
