"""The derivative of :class:`gchgg.ddpg.loss.HindsightDDPGLoss` written out by hand, held equal to autograd's.

The loss (:mod:`gchgg.ddpg.loss`) states the update's math, and autograd differentiates it. Part of that
update is spent outside the products: building and walking the autograd graph, ``nn.Module`` calls,
normalising the same batch three times, and in bfloat16 converting every activation to and from float32.
:class:`FusedDDPGUpdate` computes the same losses and gradients with the products written out:

- the observation and goal are normalised once, by the loss's normalisers, for the actor and both critic
  terms; the losses are the loss's own formulas (:meth:`~gchgg.ddpg.loss.HindsightDDPGLoss.critic_target`,
  ``critic_objective``, ``actor_objective``), called on the products' outputs, not restated here;
- the critic loss's backward writes the critic's weight gradients; the actor loss's backward
  through the critic computes input gradients only and keeps the action's (the critic's weights
  get no gradient from it, as :meth:`~gchgg.ddpg.loss.HindsightDDPGLoss.actor_loss` says);
- each weight gradient is one ``torch.mm``, set as the parameter's ``.grad`` (replaced, not
  accumulated); the ReLU and tanh backwards are autograd's own kernels (``threshold_backward``,
  ``tanh_backward``).

What it reads of the loss is declared in :class:`DDPGLoss`, so this module imports nothing of the
algorithm: the loss is the one source of the math, this update its derivative, a speed device that
``tests/test_fused_update.py`` holds equal to autograd's derivative of it.
The arithmetic is one function of tensors (:func:`_losses_and_gradients`); ``compiled=True`` runs it
under ``torch.compile`` (the ``gradients=compiled`` setting), equal to the eager update to float32
rounding (:class:`FusedDDPGUpdate`).

Every product is one autograd computes, of the same shapes, so the losses and gradients equal
autograd's bit for bit (``tests/test_fused_update.py``, batch sizes 5 to 256; the recorded tiny runs of
``tests/test_same_numbers.py`` do not move). ``python benchmarks/agent_update.py`` times it against
the autograd update and the bare plain-torch one (``fused / autograd agent``, ``fused / bare``).

It applies to the networks :func:`gchgg.ddpg.networks.make_ddpg_networks` builds: ReLU MLPs of float32
``nn.Linear`` layers with biases (:func:`unsupported` says why other networks are not), on torch's
BLAS or converted to oneDNN (:mod:`gchgg.fast.linear`). A :class:`~gchgg.fast.linear.OneDNNLinear` layer's
products are computed as it computes them, by oneDNN in the products' precision (float32, or
bfloat16 with ``precision=bfloat16``: operands and results rounded, float32 accumulation), so the
fused update equals the autograd update bit for bit in every setting (``tests/test_fused_update.py``);
with bfloat16 it also keeps the hidden activations in bfloat16, rounds an online network's weight once
per update and a target network's only after it moved (every ``target_update_every``-th update) rather
than once per product, and lets oneDNN apply each hidden ReLU inside its product (``_Products``).
"""

from __future__ import annotations

import functools
import os
import shutil
import warnings
from collections.abc import Callable
from typing import Protocol

import torch
from torch import nn

from gchgg.fast.linear import MIN_BATCH, OneDNNLinear, onednn_linear, onednn_mm

__all__ = ["DDPGLoss", "FusedDDPGUpdate", "compiler_found", "unsupported"]


class DDPGLoss(Protocol):
    """What :class:`FusedDDPGUpdate` reads of the loss it differentiates (:class:`gchgg.ddpg.loss.HindsightDDPGLoss`),
    at every call, so it follows changed constants, moved target networks and a loaded state.

    - ``actor``, ``critic``, ``target_actor``, ``target_critic``: each with an ``mlp`` of ``Linear, ReLU, …,
      Linear`` layers; the actors compute ``tanh(mlp(x))`` and the critics ``mlp([x, a])`` of the normalised
      input ``x = [observation_normalizer(s), goal_normalizer(g)]``, the online actor's and critic's two
      normalisers shared (:func:`unsupported` checks the layers and the sharing, the test the rest);
    - the constants ``gamma``, ``clip_return`` and ``action_l2``;
    - the three formulas of the losses on tensors, pure functions of their arguments, which the update calls
      instead of restating them (the same functions for every loss: a compiled update is reused).
    """

    actor: nn.Module
    critic: nn.Module
    target_actor: nn.Module
    target_critic: nn.Module
    gamma: float
    clip_return: bool
    action_l2: float

    def critic_target(self, reward: torch.Tensor, next_value: torch.Tensor, gamma: float,
                      clip_return: bool) -> torch.Tensor:
        """``y = r + γ·clip(Q', −1/(1−γ), 0)`` (the clip with ``clip_return``)."""

    def critic_objective(self, pred_value: torch.Tensor, target_value: torch.Tensor) -> torch.Tensor:
        """``mean((Q − y)²)``."""

    def actor_objective(self, policy_value: torch.Tensor, policy_action: torch.Tensor,
                        action_l2: float) -> torch.Tensor:
        """``−mean Q(s‖g, π) + action_l2·mean(π²)``."""


Formulas = tuple[Callable[..., torch.Tensor], Callable[..., torch.Tensor], Callable[..., torch.Tensor]]
"""A loss's ``(critic_target, critic_objective, actor_objective)`` (:class:`DDPGLoss`)."""


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


def unsupported(loss: DDPGLoss) -> str | None:
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

    The layers come as tensors: ``weights[i]`` in the products' dtype where ``onednn[i]`` (the layer is a
    :class:`OneDNNLinear` and the batch has at least :data:`MIN_BATCH` rows: it multiplies on oneDNN,
    operands rounded to that dtype, results in it), else float32 (``addmm``/``mm`` on torch's BLAS); the
    caller rounds each weight, once per update (:meth:`FusedDDPGUpdate._weights`) or inside the compiled
    update. A hidden oneDNN layer's ReLU is applied by oneDNN before it rounds the product (the same
    values: rounding is monotone and keeps 0). Activations stay in the dtype they were computed in: ReLU
    and its backward commute with rounding to bfloat16, so keeping a bfloat16 result instead of its
    float32 copy (what autograd's layers return) changes no value and saves two conversions per layer.
    """

    def __init__(self, weights: list[torch.Tensor], biases: list[torch.Tensor], onednn: tuple[bool, ...]) -> None:
        self.weights, self.biases, self.onednn = weights, biases, onednn

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """``[x_0, h_1, …, h_{L-1}, y]``: each layer's input as its product used it (ReLU outputs after
        the first) and the last layer's float32 output."""
        outputs, last = [], len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases, strict=True)):
            if self.onednn[i]:
                x = x.to(weight.dtype)
                y = onednn_linear(x, weight, bias, relu=i < last)  # the ReLU fused into the product
            else:
                x = x.float()
                y = torch.addmm(bias, x, weight.t())
                if i < last:
                    y.relu_()
            outputs.append(x)
            x = y if i < last else y.float()
        outputs.append(x)
        return outputs

    def input_gradient(self, i: int, grad_y: torch.Tensor) -> torch.Tensor:
        """``∂y·W`` of layer ``i``, in its product's dtype."""
        weight = self.weights[i]
        if self.onednn[i]:
            return onednn_mm(grad_y.to(weight.dtype), weight)
        return torch.mm(grad_y.float(), weight)

    def weight_gradients(self, i: int, x: torch.Tensor, grad_y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Layer ``i``'s float32 gradients of weight (``∂yᵀ·x``) and bias (``Σ ∂y``); its product took ``x``."""
        if self.onednn[i]:
            grad_y = grad_y.to(self.weights[i].dtype)
            return onednn_mm(grad_y.t(), x).float(), torch.sum(grad_y, 0, dtype=torch.float32)
        grad_y = grad_y.float()
        return torch.mm(grad_y.t(), x), torch.sum(grad_y, 0)

    def backward_input(self, outputs: list[torch.Tensor], grad_y: torch.Tensor) -> torch.Tensor:
        """The float32 gradient of the first layer's input from the output gradient ``grad_y``; no weight
        gradients."""
        grad = grad_y
        for i in range(len(self.weights) - 1, 0, -1):  # ∂x = ∂y·W, through the ReLU whose output is this layer's input
            grad = torch.ops.aten.threshold_backward(self.input_gradient(i, grad), outputs[i], 0)
        return self.input_gradient(0, grad).float()

    def backward_weights(self, outputs: list[torch.Tensor], grad_y: torch.Tensor) -> list[torch.Tensor]:
        """Every layer's weight and bias gradients from the output gradient ``grad_y``, in the order of the
        network's parameters (weight, bias, layer by layer); the first layer's input gradient is not computed."""
        grads, grad = [], grad_y
        for i in range(len(self.weights) - 1, -1, -1):
            grads[:0] = self.weight_gradients(i, outputs[i], grad)
            if i > 0:
                grad = torch.ops.aten.threshold_backward(self.input_gradient(i, grad), outputs[i], 0)
        return grads


def _losses_and_gradients(
    products: dict[str, _Products],
    formulas: Formulas,
    x: torch.Tensor,
    next_x: torch.Tensor,
    action: torch.Tensor,
    reward: torch.Tensor,
    gamma: float,
    clip_return: bool,
    action_l2: float,
) -> tuple[torch.Tensor, ...]:
    """The update's arithmetic: the loss's values (:meth:`~gchgg.ddpg.loss.HindsightDDPGLoss.losses`, by its
    ``formulas``) and the online networks' gradients from the normalised inputs ``x = s‖g`` and
    ``next_x = s'‖g``: ``(loss_actor, loss_value, pred_value [B, 1], target_value [B, 1], the critic's
    gradients, the actor's gradients)``, the gradients in each network's parameter order. The same function
    runs eagerly and under ``torch.compile`` (:class:`FusedDDPGUpdate`)."""
    critic_target, critic_objective, actor_objective = formulas
    next_action = products["target_actor"].forward(next_x)[-1].tanh_()
    next_value = products["target_critic"].forward(torch.cat([next_x, next_action], -1))[-1]
    target_value = critic_target(reward, next_value, gamma, clip_return)

    actor, critic = products["actor"], products["critic"]
    actor_outputs = actor.forward(x)
    policy_action = actor_outputs[-1].tanh()
    value_outputs = critic.forward(torch.cat([x, action], -1))  # Q(s‖g, a)
    policy_outputs = critic.forward(torch.cat([x, policy_action], -1))  # Q(s‖g, π(s‖g))
    pred_value, policy_value = value_outputs[-1], policy_outputs[-1]
    loss_value = critic_objective(pred_value, target_value)
    loss_actor = actor_objective(policy_value, policy_action, action_l2)

    # the critic loss: ∂ mean((Q − y)²) / ∂Q into the critic's weights
    error = pred_value - target_value
    critic_grads = critic.backward_weights(value_outputs, error * (2.0 / error.numel()))
    # the actor loss: ∂(−mean Q(s‖g, π)) / ∂Q back to the action only (the critic's weights are constants)
    grad_q = torch.full_like(policy_value, -1.0 / policy_value.numel())
    grad_action = critic.backward_input(policy_outputs, grad_q)[:, -policy_action.shape[-1]:]
    if action_l2:
        # ∂(l2·mean(a²))/∂a in autograd's order and rounding: (float32(l2) / n) · 2a
        scale = torch.tensor(action_l2, dtype=grad_action.dtype) / policy_action.numel()
        grad_action = grad_action + (2 * policy_action) * scale
    grad_pre_tanh = torch.ops.aten.tanh_backward(grad_action, policy_action)  # ∂y·(1 − y²), as autograd
    actor_grads = actor.backward_weights(actor_outputs, grad_pre_tanh)
    return loss_actor, loss_value, pred_value, target_value, critic_grads, actor_grads


def _compiled_arithmetic(
    weights: dict[str, list[torch.Tensor]],
    biases: dict[str, list[torch.Tensor]],
    onednn: dict[str, tuple[bool, ...]],
    dtype: torch.dtype,
    *inputs,
) -> tuple[torch.Tensor, ...]:
    """:func:`_losses_and_gradients` from the float32 weights, each oneDNN layer's rounded to ``dtype`` first:
    what :class:`FusedDDPGUpdate` hands to ``torch.compile`` (tensors, constants and the loss class's formulas
    only, so a new agent of the same sizes reuses the compiled code)."""
    products = {name: _Products([w.to(dtype) if on else w for w, on in zip(weights[name], onednn[name], strict=True)],
                                biases[name], onednn[name])
                for name in weights}  # fmt: skip
    return _losses_and_gradients(products, *inputs)


def compiler_found() -> bool:
    """Whether a C++ compiler is on this machine (``$CXX``, ``c++``, ``g++`` or ``clang++``), which TorchInductor
    needs to build :class:`FusedDDPGUpdate`'s compiled update."""
    return bool(os.environ.get("CXX") or any(shutil.which(name) for name in ("c++", "g++", "clang++")))


@functools.cache
def _compiled() -> Callable:
    """:func:`_compiled_arithmetic` compiled by TorchInductor (built once per process, per input shapes)."""
    return torch.compile(_compiled_arithmetic, dynamic=False)


class FusedDDPGUpdate:
    """The losses of ``loss`` and the gradients of its online actor and critic, without autograd.

    Call :meth:`forward` with a batch's tensors (what :meth:`gchgg.ddpg.loss.HindsightDDPGLoss.losses` takes);
    it returns what that returns, as tensors without a graph. Then :meth:`backward` sets every parameter's
    ``.grad`` of the online actor and critic (replacing it), as ``(loss_actor + loss_value).backward()``
    after zeroed gradients would; the optimisers step as usual. Target networks, normalisers and
    constants are read from ``loss`` at every call, so it follows their updates and a loaded state.

    With ``compiled=True`` the arithmetic (:func:`_losses_and_gradients`, every layer's weight rounded
    inside it) of each batch whose products run on oneDNN (:class:`OneDNNLinear` layers, batches of at least
    :data:`MIN_BATCH` rows; smaller batches run eagerly, on torch's BLAS, where compiling was not measured)
    runs compiled by ``torch.compile`` (TorchInductor, which needs a C++ compiler): the
    element-wise work fused into a few loops and the Python between the kernels gone. Its products are
    the same oneDNN and BLAS calls, but Inductor sums the bias gradients and the losses' means in its own
    order and computes some thin products its own way, so losses and gradients agree with the eager
    update's to float32 rounding, not bit for bit (``tests/test_fused_update.py``). The first update
    of each batch size compiles (seconds; cached on disk across runs).

    Args:
        loss: the loss module; its networks must pass :func:`unsupported`.
        precision: the dtype of the :class:`~gchgg.fast.linear.OneDNNLinear` layers' products, ``"float32"`` or
            ``"bfloat16"`` (resolved: what :func:`gchgg.fast.linear.resolve_precision` returns and the autograd
            update would compute them in under :func:`gchgg.fast.linear.products_in`); plain ``nn.Linear``
            layers multiply in float32.
        compiled: run the arithmetic compiled (above).
        fall_back: where the compiled update cannot be built (Inductor fails: no usable C++ compiler or
            headers, an unsupported platform), warn and run eagerly from then on (``compiled`` turns False)
            instead of raising; ``gradients=auto`` sets it, ``gradients=compiled`` does not.

    Raises:
        ValueError: ``loss`` has networks this update does not compute (the reason given), ``precision``
            is not a resolved precision, or ``compiled=True`` with no layer on oneDNN.
    """

    def __init__(
        self, loss: DDPGLoss, precision: str = "float32", compiled: bool = False, fall_back: bool = False
    ) -> None:
        reason = unsupported(loss)
        if reason is not None:
            raise ValueError(f"FusedDDPGUpdate needs ReLU MLPs of plain float32 nn.Linear layers: {reason}")
        self.loss = loss
        if precision not in ("float32", "bfloat16"):
            raise ValueError(f"precision must be 'float32' or 'bfloat16' (resolved, as fast.linear.resolve_precision "
                             f"returns it), got {precision!r}")
        self.precision = precision
        self.compiled = bool(compiled)
        self.fall_back = bool(fall_back)
        self._dtype = getattr(torch, precision)
        self._layers = {name: _relu_mlp_layers(getattr(loss, name).mlp)
                        for name in ("actor", "critic", "target_actor", "target_critic")}  # fmt: skip
        on_onednn = [type(layer) is OneDNNLinear for layers in self._layers.values() for layer in layers]
        if self.compiled and not any(on_onednn):
            raise ValueError("compiled=True compiles the updates whose products run on oneDNN, but no layer of these "
                             "networks is a OneDNNLinear (matmul=default?); use the eager update (gradients=fused)")
        # The target networks' rounded weights, kept across updates by the eager update (layer index ->
        # (weight, its data pointer and version, it rounded)). Only theirs: they move in place by lerp_ and
        # load_state_dict, which bump a tensor's version; a fused optimiser's step (the online networks') does not.
        self._rounded: dict[str, dict] = {"target_actor": {}, "target_critic": {}}
        self._saved: tuple | None = None

    def _onednn(self, name: str, rows: int) -> tuple[bool, ...]:
        """Which layers of network ``name`` multiply a batch of ``rows`` rows on oneDNN (as :class:`OneDNNLinear`
        would)."""
        return tuple(type(layer) is OneDNNLinear and rows >= MIN_BATCH for layer in self._layers[name])

    def _weights(self, name: str, onednn: tuple[bool, ...]) -> list[torch.Tensor]:
        """Network ``name``'s weights, each oneDNN layer's in the products' dtype: rounded once per update,
        a target network's again only after it moved."""
        kept = self._rounded.get(name, {})
        weights = []
        for i, (layer, on) in enumerate(zip(self._layers[name], onednn, strict=True)):
            weight = layer.weight
            if not on:
                weights.append(weight)
                continue
            stamp = (weight.data_ptr(), weight._version)
            rounded = kept.get(i)
            if rounded is None or rounded[0] is not weight or rounded[1] != stamp:  # another tensor, or changed
                rounded = kept[i] = (weight, stamp, weight.detach().to(self._dtype))
            weights.append(rounded[2])
        return weights

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
        :meth:`gchgg.ddpg.loss.HindsightDDPGLoss.losses`; keeps the gradients for :meth:`backward`."""
        loss, actor = self.loss, self.loss.actor
        if reward.shape != (observation.shape[0], 1):
            raise ValueError(f"the reward must be [B, 1] like the critic's output ({observation.shape[0]}, 1), "
                             f"got {tuple(reward.shape)}")
        normalize = lambda o, g: torch.cat([actor.observation_normalizer(o), actor.goal_normalizer(g)], -1)  # noqa: E731
        x, next_x = normalize(observation, goal), normalize(next_observation, goal)
        onednn = {name: self._onednn(name, observation.shape[0]) for name in self._layers}
        formulas = (loss.critic_target, loss.critic_objective, loss.actor_objective)
        inputs = (formulas, x, next_x, action, reward, loss.gamma, loss.clip_return, loss.action_l2)
        out = None
        if self.compiled and any(any(on) for on in onednn.values()):
            weights = {name: [layer.weight for layer in layers] for name, layers in self._layers.items()}
            biases = {name: [layer.bias for layer in layers] for name, layers in self._layers.items()}
            try:
                out = _compiled()(weights, biases, onednn, self._dtype, *inputs)
            except Exception as error:  # Inductor's failures (no C++ compiler, an unsupported op) have many types
                cause = f"torch.compile (TorchInductor, with a C++ compiler) failed: {type(error).__name__}: {error}"
                if not self.fall_back:
                    raise RuntimeError(f"gradients='compiled' needs torch.compile to build the update on this "
                                       f"machine, and {cause}; use gradients=fused") from error
                warnings.warn(f"the compiled DDPG update cannot be built here ({cause}); the updates run eagerly "
                              "from now on, as gradients=fused runs them", RuntimeWarning, stacklevel=2)
                self.compiled = False
        if out is None:
            products = {name: _Products(self._weights(name, on), [layer.bias for layer in self._layers[name]], on)
                        for name, on in onednn.items()}  # fmt: skip
            out = _losses_and_gradients(products, *inputs)
        self._saved = out[4:]
        return out[:4]

    @torch.no_grad()
    def backward(self) -> None:
        """Set the online actor's and critic's ``.grad`` from the last :meth:`forward`."""
        if self._saved is None:
            raise RuntimeError("FusedDDPGUpdate.backward() needs a forward() first (and runs once per forward)")
        for name, grads in zip(("critic", "actor"), self._saved, strict=True):
            parameters = [p for layer in self._layers[name] for p in (layer.weight, layer.bias)]
            for parameter, grad in zip(parameters, grads, strict=True):
                parameter.grad = grad
        self._saved = None
