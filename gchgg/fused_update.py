"""The DDPG update of :class:`gchgg.agent.HindsightDDPGLoss` differentiated by hand: the speed device beside the loss.

:class:`HindsightDDPGLoss` states the losses (the paper's and the original code's critic and actor
losses) and autograd differentiates them. Where the products run on torch's BLAS, part of that
update is spent outside them: building and walking the autograd graph, ``nn.Module`` calls,
normalising the same batch three times. :class:`FusedDDPGUpdate` computes the same losses and
gradients with the products written out:

- the observation and goal are normalised once for the actor and both critic terms;
- the critic loss's backward writes the critic's weight gradients; the actor loss's backward
  through the critic computes input gradients only and keeps the action's (the critic's weights
  get no gradient from it, as :meth:`HindsightDDPGLoss.actor_loss` says);
- each weight gradient is one ``torch.mm`` into the parameter's ``.grad`` (overwritten, not
  accumulated); the ReLU and tanh backwards are autograd's own kernels (``threshold_backward``,
  ``tanh_backward``).

Every product is one autograd computes, of the same shapes, so the losses and gradients equal
autograd's bit for bit (``tests/test_fused_update.py``, batch sizes 5 to 64; the recorded tiny runs of
``tests/test_same_numbers.py`` do not move). ``python benchmarks/agent_update.py`` times it against
the autograd update and the bare plain-torch one (``fused / autograd agent``, ``fused / bare``).

It applies to the networks :func:`gchgg.agent.make_ddpg_networks` builds: ReLU MLPs of plain
``nn.Linear`` layers with biases (:func:`unsupported` says why other networks are not), in
float32. Layers converted to oneDNN (:mod:`gchgg.linear`) keep the autograd update, whose oneDNN
products are the faster ones there.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import nn

if TYPE_CHECKING:  # the loss module is only read: its networks, normalisers and constants
    from gchgg.agent import HindsightDDPGLoss

__all__ = ["FusedDDPGUpdate", "unsupported"]


def _relu_mlp_layers(mlp: nn.Module) -> list[nn.Linear] | str:
    """The linear layers of ``Linear, ReLU, …, Linear``, or why ``mlp`` is not such a network."""
    modules = list(mlp.children()) if isinstance(mlp, nn.Sequential) else []
    if not modules or len(modules) % 2 != 1:
        return f"{type(mlp).__name__} is not a Sequential of Linear, ReLU, ..., Linear"
    for i, module in enumerate(modules):
        wanted = nn.Linear if i % 2 == 0 else nn.ReLU
        if type(module) is not wanted:  # subclasses (OneDNNLinear) compute their products otherwise
            return f"layer {i} is {type(module).__name__}, not {wanted.__name__}"
        if wanted is nn.Linear and (module.bias is None or module.weight.dtype != torch.float32
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


def _forward(layers: list[nn.Linear], x: torch.Tensor) -> list[torch.Tensor]:
    """``[x, h1, …, h_{L-1}, y]``: each layer's input (ReLU outputs) and the last layer's output."""
    outputs = [x]
    for layer in layers[:-1]:
        outputs.append(torch.addmm(layer.bias, outputs[-1], layer.weight.t()).relu_())
    outputs.append(torch.addmm(layers[-1].bias, outputs[-1], layers[-1].weight.t()))
    return outputs


def _grad(parameter: nn.Parameter) -> torch.Tensor:
    """``parameter.grad``, allocated where it is missing, to be overwritten."""
    if parameter.grad is None:
        parameter.grad = torch.empty_like(parameter)
    return parameter.grad


def _backward_input(layers: list[nn.Linear], outputs: list[torch.Tensor], grad_y: torch.Tensor) -> torch.Tensor:
    """The gradient of the first layer's input from the output gradient ``grad_y``; no weight gradients."""
    grad = grad_y
    for i in range(len(layers) - 1, 0, -1):  # ∂x = ∂y·W, through the ReLU whose output is this layer's input
        grad = torch.ops.aten.threshold_backward(torch.mm(grad, layers[i].weight), outputs[i], 0)
    return torch.mm(grad, layers[0].weight)


def _backward_weights(layers: list[nn.Linear], outputs: list[torch.Tensor], grad_y: torch.Tensor) -> None:
    """Write the weight and bias gradients of ``layers`` from the output gradient ``grad_y`` (the first
    layer's input gradient is not computed: nothing needs it)."""
    grad = grad_y
    for i in range(len(layers) - 1, -1, -1):
        layer = layers[i]
        torch.mm(grad.t(), outputs[i], out=_grad(layer.weight))
        torch.sum(grad, 0, out=_grad(layer.bias))
        if i > 0:
            grad = torch.ops.aten.threshold_backward(torch.mm(grad, layer.weight), outputs[i], 0)  # ∂y·W


class FusedDDPGUpdate:
    """The losses of ``loss`` and the gradients of its online actor and critic, without autograd.

    Call :meth:`forward` with a batch's tensors (what :meth:`HindsightDDPGLoss.losses` takes); it returns
    what that returns, as tensors without a graph. Then :meth:`backward` writes every parameter's
    ``.grad`` of the online actor and critic (overwriting it), as ``(loss_actor + loss_value).backward()``
    after zeroed gradients would; the optimisers step as usual. Target networks, normalisers and
    constants are read from ``loss`` at every call, so it follows their updates and a loaded state.

    Args:
        loss: the loss module; its networks must pass :func:`unsupported`.

    Raises:
        ValueError: ``loss`` has networks this update does not compute (the reason given).
    """

    def __init__(self, loss: HindsightDDPGLoss) -> None:
        reason = unsupported(loss)
        if reason is not None:
            raise ValueError(f"FusedDDPGUpdate needs ReLU MLPs of plain float32 nn.Linear layers: {reason}")
        self.loss = loss
        self.actor = _relu_mlp_layers(loss.actor.mlp)
        self.critic = _relu_mlp_layers(loss.critic.mlp)
        self.target_actor = _relu_mlp_layers(loss.target_actor.mlp)
        self.target_critic = _relu_mlp_layers(loss.target_critic.mlp)
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
        next_action = _forward(self.target_actor, next_x)[-1].tanh_()
        next_value = _forward(self.target_critic, torch.cat([next_x, next_action], -1))[-1]
        if loss.clip_return:
            next_value = next_value.clamp_(*loss.return_range)
        target_value = reward + loss.gamma * next_value

        x = normalize(observation, goal)
        actor_outputs = _forward(self.actor, x)
        policy_action = actor_outputs[-1].tanh()
        value_outputs = _forward(self.critic, torch.cat([x, action], -1))  # Q(s‖g, a)
        policy_outputs = _forward(self.critic, torch.cat([x, policy_action], -1))  # Q(s‖g, π(s‖g))
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
        self._saved = (error, policy_action, actor_outputs, value_outputs, policy_outputs)
        return loss_actor, loss_value, pred_value, target_value

    @torch.no_grad()
    def backward(self) -> None:
        """Write the online actor's and critic's ``.grad`` from the last :meth:`forward`."""
        if self._saved is None:
            raise RuntimeError("FusedDDPGUpdate.backward() needs a forward() first (and runs once per forward)")
        error, policy_action, actor_outputs, value_outputs, policy_outputs = self._saved
        self._saved = None
        # the critic loss: ∂ mean((Q − y)²) / ∂Q into the critic's weights
        _backward_weights(self.critic, value_outputs, error * (2.0 / error.numel()))
        # the actor loss: ∂(−mean Q(s‖g, π)) / ∂Q back to the action only (the critic's weights are constants)
        grad_q = torch.full_like(policy_outputs[-1], -1.0 / policy_outputs[-1].numel())
        grad_action = _backward_input(self.critic, policy_outputs, grad_q)[:, -policy_action.shape[-1]:]
        if self.loss.action_l2:
            grad_action = grad_action + policy_action * (2.0 * self.loss.action_l2 / policy_action.numel())
        grad_pre_tanh = torch.ops.aten.tanh_backward(grad_action, policy_action)  # ∂y·(1 − y²), as autograd
        _backward_weights(self.actor, actor_outputs, grad_pre_tanh)
