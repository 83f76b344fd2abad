"""DDPG update cost: :class:`gchgg.ddpg.agent.DDPGAgent` vs the same update written in plain torch.

Prints seconds per update (batch 256, push_new sizes: obs 25, goal 3, action 3) for the agent —
which reads a TensorDict batch and runs its loss module and target update — and for
:class:`BareDDPG`, the same networks and the same math with plain tensors and no TensorDict, plus
their ratio. The two are timed in alternating rounds of one run and the ratio is the median of the
per-round ratios, so it holds on a shared machine. :class:`BareDDPG` is also the "bare DDPG update"
of the training-iteration floor (``benchmarks/iteration.py`` may import it).

    python benchmarks/agent_update.py [--threads 2] [--rounds 15] [--updates 40] [--batch-size 256]
                                      [--min-features 16] [--compile] [--profile]

Both are timed, in rotating rounds, beside the same agent with ``gradients="fused"``
(:mod:`gchgg.fast.fused_update`: the same losses and gradients differentiated by hand), which also says
whether its networks still equal the autograd agent's bit for bit after every round's updates.
All three compare with the agent on torch's own BLAS (``matmul="default"``). The script then times that
update against the faster one, the same agent with its layers on oneDNN (``matmul="onednn"``,
:mod:`gchgg.fast.linear`), and that one against the same with bfloat16 products (``precision="bfloat16"``,
on CPUs with native bfloat16), in alternating rounds, and prints how far the two agree on one fixed batch
(losses and gradients, relative to their largest entry) and how far their weights and actions drift
apart over the run's updates, beside the drift of a torch-BLAS twin fed each batch in reverse row
order: the same math, other float32 rounding, which training amplifies in both. ``--compile`` also
times the same agent with ``torch.compile`` on its loss (a candidate that lost) against today's.
Last, the oneDNN update in float32 and in bfloat16, each by autograd and with ``gradients="fused"``,
in rotating rounds beside the bare float32 update (``fused / bare fp32``: below 1 is an update faster
than the fp32 floor's); then the training default's products in the update run eagerly
(``gradients=fused``) against a twin with ``gradients=compiled`` (:class:`gchgg.fast.fused_update.FusedDDPGUpdate`
compiled by ``torch.compile``, what ``gradients=auto`` runs there): the seconds of its first update, which
compiles, their agreement on one fixed batch and their drift; then the training default's update with its
optimisers stepped by :func:`gchgg.fast.adam_step.adam_step` against the same with ``Adam.step``, and whether
the two stay equal; ``--profile`` prints both updates' top operators.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # run from a checkout

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

import torch  # noqa: E402
from tensordict import TensorDict  # noqa: E402
from torch import nn  # noqa: E402

from gchgg.ddpg.agent import DDPGAgent  # noqa: E402
from gchgg.fast.fused_update import compiler_found  # noqa: E402
from gchgg.fast.linear import MIN_FEATURES, bf16_available, products_in, use_onednn  # noqa: E402


def _mlp(in_features: int, out_features: int, hidden: int = 256, depth: int = 3) -> nn.Sequential:
    layers, width = [], in_features
    for _ in range(depth):
        layers += [nn.Linear(width, hidden), nn.ReLU()]
        width = hidden
    return nn.Sequential(*layers, nn.Linear(width, out_features))


class BareDDPG:
    """The agent's update in plain torch: same networks, normalisation, targets, losses, Adam, polyak.

    Args:
        obs_dim, goal_dim, action_dim: sizes.
        gamma, polyak, target_update_every, action_l2: as in :class:`gchgg.ddpg.agent.DDPGAgent`.
    """

    def __init__(self, obs_dim: int, goal_dim: int, action_dim: int, gamma: float = 0.98, polyak: float = 0.95,
                 target_update_every: int = 20, action_l2: float = 1.0) -> None:  # fmt: skip
        in_features = obs_dim + goal_dim
        self.actor = _mlp(in_features, action_dim)
        self.critic = _mlp(in_features + action_dim, 1)
        self.target_actor = copy.deepcopy(self.actor)
        self.target_critic = copy.deepcopy(self.critic)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=1e-3, fused=True)  # as the agent
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=1e-3, fused=True)
        self.loc = torch.zeros(in_features)
        self.scale = torch.ones(in_features)
        self.gamma, self.polyak, self.every, self.action_l2 = gamma, polyak, target_update_every, action_l2
        self.num_updates = 0

    def _norm(self, observation: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        return ((torch.cat([observation, goal], -1) - self.loc) / self.scale).clamp(-5.0, 5.0)

    def update(self, observation, goal, action, next_observation, reward) -> tuple[float, float]:
        with torch.no_grad():
            x_next = self._norm(next_observation, goal)
            q_next = self.target_critic(torch.cat([x_next, self.target_actor(x_next).tanh()], -1))
            target = reward + self.gamma * q_next.clamp(-1.0 / (1.0 - self.gamma), 0.0)
        x = self._norm(observation, goal)
        loss_value = (self.critic(torch.cat([x, action], -1)) - target).square().mean()
        pi = self.actor(self._norm(observation, goal)).tanh()
        for p in self.critic.parameters():
            p.requires_grad_(False)
        loss_actor = -self.critic(torch.cat([self._norm(observation, goal), pi], -1)).mean()
        loss_actor = loss_actor + self.action_l2 * pi.square().mean()
        for p in self.critic.parameters():
            p.requires_grad_(True)
        values = torch.stack([loss_actor.detach(), loss_value.detach()]).tolist()
        self.actor_optimizer.zero_grad(set_to_none=True)
        self.critic_optimizer.zero_grad(set_to_none=True)
        (loss_actor + loss_value).backward()
        self.actor_optimizer.step()
        self.critic_optimizer.step()
        self.num_updates += 1
        if self.num_updates % self.every == 0:
            with torch.no_grad():
                for net, target_net in ((self.actor, self.target_actor), (self.critic, self.target_critic)):
                    for p, p_target in zip(net.parameters(), target_net.parameters(), strict=True):
                        p_target.lerp_(p, 1.0 - self.polyak)
        return values[0], values[1]


def _batches(count: int, size: int, obs_dim: int, goal_dim: int, action_dim: int, generator: torch.Generator):
    out = []
    for _ in range(count):
        out.append(
            TensorDict(
                {
                    "observation": torch.randn(size, obs_dim, generator=generator),
                    "desired_goal": torch.randn(size, goal_dim, generator=generator),
                    "action": torch.rand(size, action_dim, generator=generator) * 2 - 1,
                    "next": {
                        "observation": torch.randn(size, obs_dim, generator=generator),
                        "reward": -(torch.rand(size, 1, generator=generator) < 0.8).float(),
                    },
                },
                [size],
            )
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    parser.add_argument("--rounds", type=int, default=15, help="alternating timing rounds")
    parser.add_argument("--updates", type=int, default=40, help="updates per round and implementation")
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--compile", action="store_true",
                        help="also time the agent with torch.compile on its loss (the candidate faster update)")
    parser.add_argument("--min-features", type=int, default=MIN_FEATURES,
                        help="layers narrower than this stay on torch BLAS in the oneDNN agent "
                             "(gchgg.fast.linear.MIN_FEATURES)")
    parser.add_argument("--profile", action="store_true", help="also print the update's top operators (torch.profiler)")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    obs_dim, goal_dim, action_dim = 25, 3, 3
    generator = torch.Generator().manual_seed(0)
    batches = _batches(20, args.batch_size, obs_dim, goal_dim, action_dim, generator)
    plain = [tuple(b.get(k) for k in ("observation", "desired_goal", "action", ("next", "observation"),
                                      ("next", "reward"))) for b in batches]  # fmt: skip

    def make_agent(gradients: str) -> DDPGAgent:
        agent = DDPGAgent(obs_dim, goal_dim, action_dim, generator=torch.Generator().manual_seed(0), matmul="default",
                          gradients=gradients)  # fmt: skip
        agent.update_normalizer(
            torch.cat([b["observation"] for b in batches]), torch.cat([b["desired_goal"] for b in batches])
        )
        return agent

    torch.manual_seed(0)
    agent, fused = make_agent("autograd"), make_agent("fused")  # the same weights
    bare = BareDDPG(obs_dim, goal_dim, action_dim)
    runners = {
        "agent": lambda i: agent.update(batches[i % len(batches)]),
        "fused": lambda i: fused.update(batches[i % len(batches)]),
        "bare": lambda i: bare.update(*plain[i % len(plain)]),
    }
    times: dict[str, list[float]] = {name: [] for name in runners}
    for run in runners.values():  # warm-up
        for i in range(20):
            run(i)
    for r in range(args.rounds):  # rotate which goes first, so that none always follows another
        for name in list(runners)[r % 3:] + list(runners)[: r % 3]:
            start = time.perf_counter()
            for i in range(args.updates):
                runners[name](i)
            times[name].append((time.perf_counter() - start) / args.updates)

    def ratio(a: str, b: str) -> float:
        return statistics.median(x / y for x, y in zip(times[a], times[b], strict=True))

    same = all(torch.equal(x, y) for x, y in zip(agent.loss_module.state_dict().values(),
                                                 fused.loss_module.state_dict().values(), strict=True))  # fmt: skip
    print(f"threads={torch.get_num_threads()} batch={args.batch_size} rounds={args.rounds}x{args.updates} updates")
    print(f"agent (TorchRL, TensorDict batch): {statistics.median(times['agent']) * 1e3:.3f} ms/update")
    print(f"bare plain-torch DDPG update:      {statistics.median(times['bare']) * 1e3:.3f} ms/update")
    print(f"ratio agent / bare (median of rounds): {ratio('agent', 'bare'):.3f}")
    print(f"agent with gradients=fused (fast.fused_update): {statistics.median(times['fused']) * 1e3:.3f} ms/update; "
          f"fused / autograd agent {ratio('fused', 'agent'):.3f}, fused / bare {ratio('fused', 'bare'):.3f}; "
          f"networks equal to the autograd agent's after {20 + args.rounds * args.updates} updates: {same}")
    onednn = copy.deepcopy(agent)  # same weights, normalisers and optimiser state
    use_onednn(onednn.loss_module, "onednn", min_features=args.min_features)
    onednn_update(agent, onednn, batches, args.rounds, args.updates, args.min_features)
    bf16_update(onednn, batches, args.rounds, args.updates)
    fused_onednn(onednn, bare, batches, plain, args.rounds, args.updates)
    compiled_gradients(onednn, batches, args.rounds, args.updates)  # first: its first update compiles
    adam_steps(onednn, batches, args.rounds, args.updates)
    if args.compile:
        compiled_update(agent, batches, args.rounds, args.updates)
    act_one(onednn, args.rounds)
    if args.profile:
        profile_update(agent, batches, args.updates, "torch BLAS")
        profile_update(onednn, batches, args.updates, "oneDNN")


def _fixed_batch_agreement(a: DDPGAgent, b: DDPGAgent, batch) -> tuple[float, float]:
    """Largest difference of the two losses and of any parameter's gradient on ``batch``, each relative
    to the largest magnitude of that value under ``a``; no parameter changes."""
    gaps = []
    grads = []
    for agent in (a, b):
        loss = agent.loss_module
        with products_in(agent.precision):
            out = loss.losses(*loss.inputs(batch))
            for p in loss.parameters():
                p.grad = None
            (out[0] + out[1]).backward()
        grads.append([p.grad.clone() for p in loss.parameters() if p.grad is not None])
        gaps.append(out[:2])
        for p in loss.parameters():
            p.grad = None
    loss_gap = max(((x - y).abs() / x.abs()).item() for x, y in zip(*gaps, strict=True))
    grad_gap = max(((x - y).abs().max() / x.abs().max().clamp_min(1e-30)).item() for x, y in zip(*grads, strict=True))
    return loss_gap, grad_gap


def _drift(a: DDPGAgent, b: DDPGAgent, batch) -> tuple[float, float]:
    """Largest difference of the two actors' weights and of their actions on ``batch``."""
    weights = max((x - y).abs().max().item() for x, y in zip(a.actor.parameters(), b.actor.parameters(), strict=True))
    with torch.no_grad():
        actions = (a.actor(batch["observation"], batch["desired_goal"])
                   - b.actor(batch["observation"], batch["desired_goal"])).abs().max().item()  # fmt: skip
    return weights, actions


def _alternate(first: DDPGAgent, second: DDPGAgent, batches, rounds: int, updates: int, between=None):
    """Seconds per update of two agents over the same batches, in rounds that alternate which goes
    first; ``between()`` runs after each round, untimed."""
    times: tuple[list[float], list[float]] = ([], [])
    for r in range(rounds):
        for which, out in ((first, times[0]), (second, times[1]))[:: 1 if r % 2 else -1]:
            start = time.perf_counter()
            for i in range(updates):
                which.update(batches[i % len(batches)])
            out.append((time.perf_counter() - start) / updates)
        if between is not None:
            between()
    return times


def onednn_update(agent: DDPGAgent, onednn: DDPGAgent, batches, rounds: int, updates: int, min_features: int) -> None:
    """Today's update (torch BLAS) against the same agent with its layers on oneDNN, alternating
    rounds; their agreement on a fixed batch, and how far they drift apart beside a torch-BLAS twin fed
    every batch in reverse row order (the same math: only the order of the batch means' sums differs)."""
    loss_gap, grad_gap = _fixed_batch_agreement(agent, onednn, batches[0])
    twin = copy.deepcopy(agent)
    reversed_batches = [b[torch.arange(len(b) - 1, -1, -1)] for b in batches]
    today, fast = _alternate(agent, onednn, batches, rounds, updates,
                             between=lambda: [twin.update(reversed_batches[i % len(batches)]) for i in range(updates)])
    print(f"oneDNN layers (matmul=onednn, layers >= {min_features} wide): "
          f"{statistics.median(fast) * 1e3:.3f} ms/update against "
          f"{statistics.median(today) * 1e3:.3f} on torch BLAS: speed-up "
          f"{statistics.median(today) / statistics.median(fast):.2f}x (target >= 1.3)")
    print(f"  one fixed batch: losses agree to {loss_gap:.1e}, gradients to {grad_gap:.1e} of their largest entry")
    fresh = batches[-1]
    print(f"  after {rounds * updates} updates, actor weights / actions apart by: oneDNN vs torch BLAS "
          "{:.2g} / {:.2g}; torch BLAS vs the same on reversed batches {:.2g} / {:.2g}".format(
              *_drift(agent, onednn, fresh), *_drift(agent, twin, fresh)))


def bf16_update(onednn: DDPGAgent, batches, rounds: int, updates: int) -> None:
    """The oneDNN float32 update against a copy with ``precision="bfloat16"`` (bfloat16 products,
    float32 accumulation, parameters and optimiser state), alternating rounds; their agreement on a
    fixed batch and how far they drift apart."""
    if not bf16_available():
        print("bfloat16 products (precision=bfloat16): skipped, this CPU or torch has no native bfloat16 "
              "oneDNN products")
        return
    candidate = copy.deepcopy(onednn)
    candidate.precision = "bfloat16"
    loss_gap, grad_gap = _fixed_batch_agreement(onednn, candidate, batches[0])
    fp32, bf16 = _alternate(onednn, candidate, batches, rounds, updates)
    print(f"bfloat16 products (precision=bfloat16, oneDNN): {statistics.median(bf16) * 1e3:.3f} ms/update against "
          f"{statistics.median(fp32) * 1e3:.3f} in float32 on oneDNN: speed-up "
          f"{statistics.median(fp32) / statistics.median(bf16):.2f}x")
    print(f"  one fixed batch: losses agree to {loss_gap:.1e}, gradients to {grad_gap:.1e} of their largest entry; "
          "after {} updates actor weights / actions apart by {:.2g} / {:.2g}".format(
              rounds * updates, *_drift(onednn, candidate, batches[-1])))


def fused_onednn(onednn: DDPGAgent, bare: BareDDPG, batches, plain, rounds: int, updates: int) -> None:
    """The update on oneDNN layers, float32 and (where native) bfloat16, differentiated by autograd and by
    hand (``gradients="fused"``), in rotating rounds beside the bare float32 update on torch's BLAS (the
    fp32 floor's, ``benchmarks/iteration.py``); whether each fused agent's networks still equal its
    autograd twin's bit for bit after all of them."""
    precisions = ["float32"] + (["bfloat16"] if bf16_available() else [])
    agents = {}
    for precision in precisions:
        for gradients in ("autograd", "fused"):
            agent = DDPGAgent(onednn.obs_dim, onednn.goal_dim, onednn.action_dim, matmul="onednn",
                              precision=precision, gradients=gradients)  # fmt: skip
            agent.load_state_dict(copy.deepcopy(onednn.state_dict()))  # the same weights, normalisers, optimiser state
            agents[f"{precision} {gradients}"] = agent
    runners = {name: (lambda i, a=agent: a.update(batches[i % len(batches)])) for name, agent in agents.items()}
    runners["bare"] = lambda i: bare.update(*plain[i % len(plain)])
    times: dict[str, list[float]] = {name: [] for name in runners}
    names = list(runners)
    for r in range(rounds):
        for name in names[r % len(names):] + names[: r % len(names)]:
            start = time.perf_counter()
            for i in range(updates):
                runners[name](i)
            times[name].append((time.perf_counter() - start) / updates)

    def ratio(a: str, b: str) -> float:
        return statistics.median(x / y for x, y in zip(times[a], times[b], strict=True))

    for precision in precisions:
        fused, autograd = (agents[f"{precision} {g}"] for g in ("fused", "autograd"))
        pairs = zip(fused.loss_module.state_dict().values(), autograd.loss_module.state_dict().values(), strict=True)
        same = all(torch.equal(x, y) for x, y in pairs)
        print(f"oneDNN {precision} with gradients=fused: {statistics.median(times[f'{precision} fused']) * 1e3:.3f} "
              f"ms/update; fused / autograd {ratio(f'{precision} fused', f'{precision} autograd'):.3f}, "
              f"fused / bare fp32 (torch BLAS) {ratio(f'{precision} fused', 'bare'):.3f}; networks equal to "
              f"the autograd agent's after {rounds * updates} updates: {same}")


def adam_steps(onednn: DDPGAgent, batches, rounds: int, updates: int) -> None:
    """The training default's update (``matmul``, ``precision`` and ``gradients`` auto) with its optimisers
    stepped by :func:`gchgg.fast.adam_step.adam_step` against a twin whose optimisers take ``Adam.step`` (a no-op
    step hook on each makes ``adam_step`` leave the step to it), in alternating rounds; and whether the
    twins' networks and optimiser states are still equal after them."""
    twins = []
    for _ in range(2):
        agent = DDPGAgent(onednn.obs_dim, onednn.goal_dim, onednn.action_dim, precision="auto")
        agent.load_state_dict(copy.deepcopy(onednn.state_dict()))
        twins.append(agent)
    direct, stepped = twins
    for optimizer in (stepped.actor_optimizer, stepped.critic_optimizer):
        optimizer.register_step_post_hook(lambda *args: None)
    times = _alternate(direct, stepped, batches, rounds, updates)
    same = all(torch.equal(x, y) for x, y in zip(_flat(direct.state_dict()), _flat(stepped.state_dict()), strict=True))
    ratio = statistics.median(a / b for a, b in zip(*times, strict=True))
    print(f"Adam stepped by gchgg.fast.adam_step ({direct.precision}, gradients={direct.gradients}): "
          f"{statistics.median(times[0]) * 1e3:.3f} ms/update against {statistics.median(times[1]) * 1e3:.3f} with "
          f"Adam.step: {ratio:.3f}; networks and optimiser states equal after {rounds * updates} updates: {same}")


def compiled_gradients(onednn: DDPGAgent, batches, rounds: int, updates: int) -> None:
    """The training default's products (``precision=auto``) in the fused update run eagerly (``gradients=fused``)
    against a twin with ``gradients=compiled`` (the same update compiled by ``torch.compile``; what
    ``gradients=auto`` picks where the products are bfloat16 on oneDNN): their losses and gradients on one
    fixed batch from the same weights, relative to each value's largest entry (the compiled twin's first
    update, which compiles, timed); then their updates in alternating rounds, and how far the twins' actors
    drift apart over them."""
    if not compiler_found():
        print("gradients=compiled: skipped (torch.compile's Inductor needs a C++ compiler, and none is found)")
        return
    twins = {}
    for gradients in ("fused", "compiled"):
        agent = DDPGAgent(onednn.obs_dim, onednn.goal_dim, onednn.action_dim, precision="auto", gradients=gradients)
        agent.load_state_dict(copy.deepcopy(onednn.state_dict()))
        twins[gradients] = agent
    eager, compiled = twins.values()
    values, seconds = {}, {}
    for name, agent in twins.items():  # one fixed batch, from the same weights; nothing steps
        inputs = agent.loss_module.inputs(batches[0])
        start = time.perf_counter()
        with products_in(agent.precision):
            out = agent._fused.forward(*inputs)  # the compiled twin's first: compiles
            agent._fused.backward()
        seconds[name] = time.perf_counter() - start
        values[name] = (out[:2], [p.grad.clone() for p in (*agent.actor.parameters(), *agent.critic.parameters())])
    (eager_losses, eager_grads), (compiled_losses, compiled_grads) = values.values()
    loss_gap = max(((x - y).abs() / x.abs()).item() for x, y in zip(eager_losses, compiled_losses, strict=True))
    grad_gap = max(((x - y).abs().max() / x.abs().max().clamp_min(1e-30)).item()
                   for x, y in zip(eager_grads, compiled_grads, strict=True))  # fmt: skip
    times = _alternate(eager, compiled, batches, rounds, updates)
    weights, actions = _drift(eager, compiled, batches[1])
    ratio = statistics.median(b / a for a, b in zip(*times, strict=True))
    print(f"gradients=compiled ({compiled.precision}): {seconds['compiled']:.1f} s for the first update (it compiles); "
          f"then {statistics.median(times[1]) * 1e3:.3f} ms/update against {statistics.median(times[0]) * 1e3:.3f} "
          f"with gradients={eager.gradients}: compiled / {eager.gradients} {ratio:.3f}")
    print(f"  one fixed batch: losses agree to {loss_gap:.1e}, gradients to {grad_gap:.1e} of their largest entry; "
          f"after {rounds * updates + 1} updates actor weights / actions apart by {weights:.2g} / {actions:.2g}")


def _flat(state) -> list[torch.Tensor]:
    """The tensors of a nested state dict, in order."""
    if isinstance(state, torch.Tensor):
        return [state]
    if isinstance(state, dict):
        return [t for value in state.values() for t in _flat(value)]
    if isinstance(state, (list, tuple)):
        return [t for value in state for t in _flat(value)]
    return []


def compiled_update(agent: DDPGAgent, batches, rounds: int, updates: int) -> None:
    """Today's update against the same agent's update with ``torch.compile`` on its loss's tensor path
    (a copy of the agent: same weights), alternating rounds; compile seconds, ratio, and how far the
    two agents' weights drift apart."""
    candidate = copy.deepcopy(agent)
    loss = candidate.loss_module
    start = time.perf_counter()
    loss.losses = torch.compile(loss.losses, dynamic=False)
    candidate.update(batches[0])
    agent.update(batches[0])
    compile_seconds = time.perf_counter() - start
    today, compiled = _alternate(agent, candidate, batches, rounds, updates)
    drift = max((a - b).abs().max().item()
                for a, b in zip(agent.actor.parameters(), candidate.actor.parameters(), strict=True))
    print(f"torch.compile of the loss: {compile_seconds:.0f} s to compile; {statistics.median(compiled) * 1e3:.3f} "
          f"ms/update against {statistics.median(today) * 1e3:.3f}: speed-up "
          f"{statistics.median(today) / statistics.median(compiled):.2f}x (target >= 1.3); actor weights apart by "
          f"up to {drift:.2g} after {rounds * updates + 1} updates")


def act_one(agent: DDPGAgent, rounds: int, calls: int = 500) -> None:
    """``act`` on one observation (the per-episode loop's rollout step): the actor's modules against
    :class:`~gchgg.ddpg.agent.SmallBatchActor`, the path ``act`` takes below ``MIN_BATCH`` rows (same actions)."""
    g = torch.Generator().manual_seed(1)
    observation, goal = torch.randn(1, agent.obs_dim, generator=g), torch.randn(1, agent.goal_dim, generator=g)
    paths = {"modules": agent.actor, "SmallBatchActor": agent._small_batch_actor}
    times: dict[str, list[float]] = {name: [] for name in paths}
    with torch.no_grad():
        for _ in range(rounds):
            for name, forward in paths.items():
                start = time.perf_counter()
                for _ in range(calls):
                    forward(observation, goal)
                times[name].append((time.perf_counter() - start) / calls)
        same = torch.equal(paths["modules"](observation, goal), paths["SmallBatchActor"](observation, goal))
    modules, small = (statistics.median(times[name]) for name in paths)
    print(f"actor on one observation: modules {modules * 1e6:.1f} us, SmallBatchActor {small * 1e6:.1f} us "
          f"({modules / small:.2f}x; same actions: {same}; x5,000 rollout steps an iteration: "
          f"{modules * 5000:.2f} s against {small * 5000:.2f} s)")

    # eq. 22 on that one row: over both outcomes with torch.where, and act()'s one-row branch
    with torch.no_grad():
        action = agent._small_batch_actor(observation, goal)
    explorations = {"where": agent.explore_actions, "one-row branch": agent._explore_one_row}
    draws = {name: torch.Generator().manual_seed(2) for name in explorations}
    times = {name: [] for name in explorations}
    for _ in range(rounds):
        for name, explore in explorations.items():
            start = time.perf_counter()
            for _ in range(calls):
                explore(action.clone(), draws[name])
            times[name].append((time.perf_counter() - start) / calls)
    same = all(torch.equal(agent.explore_actions(action.clone(), draws["where"]),
                           agent._explore_one_row(action.clone(), draws["one-row branch"])) for _ in range(200))
    same = same and torch.equal(draws["where"].get_state(), draws["one-row branch"].get_state())
    where, branch = (statistics.median(times[name]) for name in explorations)
    print(f"exploring one row (eq. 22): where {where * 1e6:.1f} us, one-row branch {branch * 1e6:.1f} us "
          f"({branch / where:.2f}x; same actions and draws: {same}; x5,000 rollout steps an iteration: "
          f"{where * 5000:.2f} s against {branch * 5000:.2f} s)")


def profile_update(agent: DDPGAgent, batches, updates: int, name: str) -> None:
    """The update's top operators by self CPU time (torch.profiler)."""
    from torch.profiler import profile

    with profile() as prof:
        for i in range(updates):
            agent.update(batches[i % len(batches)])
    events = sorted(prof.key_averages(), key=lambda e: -e.self_cpu_time_total)
    total = sum(e.self_cpu_time_total for e in events)
    print(f"{name}: profile of {updates} updates ({total / updates / 1e3:.2f} ms each), "
          "top operators by self CPU time:")
    for e in events[:8]:
        print(f"  {e.key:28s} {e.self_cpu_time_total / total:6.1%}")


if __name__ == "__main__":
    from report import run  # prints, and with --docs writes docs/benchmarks.md

    run(main, __file__)
