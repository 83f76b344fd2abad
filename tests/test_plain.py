"""``plain=true``: the algorithm alone, no speed device of ``gchgg/fast`` called, and the same numbers as the devices.

(a) A tiny run with ``plain=true`` writes the ``metrics.csv`` (timing columns aside) that the same run writes with
    every speed device on at float32 products on torch's matmul and autograd's gradients, bit for bit: the
    one-row actor and eq. 22 (``fast/small_batch.py``), the fused Adam step, subnormals flushed, the field-by-field
    storage, EBP's per-row energy copy, Alg. 1's candidate pool, row caches and nearest-neighbour engine. None of
    them is equal only to float rounding. The candidate pool draws the candidates of ``draw_ahead`` = 8 samples at
    once, and a write to the buffer drops those not yet used (``on_write="redraw"``): their draws have moved the
    buffer's generator on, so the two paths draw the same batches only where no drawn candidate goes unused
    (``gchgg/fast/candidates.py``). The curriculum runs below therefore sample 8 batches per chunk (the normalisers'
    batch and 7 updates); with another count they train as well on other batches.
(b) With ``plain=true`` no function of ``gchgg/fast`` is called, from building the parts to the last checkpoint
    (a profiler hook, as ``docs/iteration_files.py --plain`` runs one iteration under).
(c) An explicit setting contrary to ``plain=true`` is refused, naming both; ``auto`` resolves to the plain choice.
"""

from __future__ import annotations

import csv
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from test_train import config, tiny
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from gchgg import train
from gchgg.ddpg import agent as ddpg_agent
from gchgg.ddpg.agent import DDPGAgent
from gchgg.fast.storage import FieldStorage
from gchgg.graph import EuclideanMetric
from gchgg.run import config as schema
from gchgg.run import fork
from gchgg.run.parts import make_parts
from gchgg.run.run_info import resolved_settings, startup_record
from gchgg.samplers import EnergySampler, GraphCurriculumSampler

ROOT = Path(__file__).resolve().parents[1]
FAST = ROOT / "gchgg" / "fast"
DEVICES_AT_FLOAT32 = ["precision=float32", "matmul=default", "gradients=autograd"]  # subnormals: auto -> flush
AGENT_AT_FLOAT32 = {"matmul": "default", "precision": "float32"}  # the agent's devices: gradients auto -> fused
ONE_POOL_PER_CHUNK = "train.updates=14"  # 2 chunks of 1 + 7 samples: one candidate pool (draw_ahead = 8) each

CASES = [
    ("push_new", "her", []),  # EBP, the storage, the agent's devices
    ("push_new", "cher", []),
    ("reach", "gchgg", [ONE_POOL_PER_CHUNK]),  # HGG's goals and value, Alg. 1 on the graph, EBP candidates
    ("reach", "gchgg_code", [ONE_POOL_PER_CHUNK]),  # F_div of the achieved goals, F_prox achieved to goal
]


def metrics(task: str, algo: str, folder: Path, *overrides: str) -> list[dict[str, str]]:
    """The rows of a 3-iteration tiny run's metrics.csv, timing columns dropped."""
    train.run(config([f"env={task}", f"algo={algo}", *tiny(folder, iterations=3), *overrides]), folder / "run")
    with open(folder / "run" / "metrics.csv", newline="") as f:
        return [{k: v for k, v in row.items() if not k.startswith("seconds_")} for row in csv.DictReader(f)]


@pytest.mark.parametrize("task, algo, extra", CASES, ids=[f"{t}-{a}" for t, a, _ in CASES])
def test_plain_true_writes_the_metrics_of_the_speed_devices_bit_for_bit(task, algo, extra, tmp_path):
    plain = metrics(task, algo, tmp_path / "plain", *extra, "plain=true")
    fast = metrics(task, algo, tmp_path / "fast", *extra, *DEVICES_AT_FLOAT32)
    assert len(plain) == 3 and plain == fast


def fast_calls(run) -> dict[str, str]:
    """The functions of gchgg/fast that ``run()`` calls (file: first function), through a profiler hook."""
    called: dict[str, str] = {}

    def hook(frame, event, arg) -> None:
        if event == "call" and Path(frame.f_code.co_filename).resolve().is_relative_to(FAST):
            called.setdefault(Path(frame.f_code.co_filename).name, frame.f_code.co_qualname)

    sys.setprofile(hook)
    try:
        run()
    finally:
        sys.setprofile(None)
    return called


def test_plain_true_calls_no_speed_device_from_the_build_to_the_last_checkpoint(tmp_path):
    cfg = config(["env=reach", "algo=gchgg", *tiny(tmp_path, iterations=2), "plain=true"])
    assert fast_calls(lambda: train.run(cfg, tmp_path / "plain")) == {}
    # the hook sees the devices where they run: an iteration of the default run calls them
    (tmp_path / "fast").mkdir()
    trainer = train.Trainer(config(["env=reach", "algo=gchgg", *tiny(tmp_path)]), tmp_path / "fast")
    trainer.iteration_step()
    called = fast_calls(trainer.iteration_step)
    assert {"small_batch.py", "candidates.py", "nearest.py", "storage.py", "adam_step.py"} <= set(called), called


def test_plain_true_builds_each_part_on_its_plain_path(tmp_path):
    cfg = config(["env=reach", "algo=gchgg", *tiny(tmp_path), "plain=true"])
    parts = make_parts(cfg)
    assert type(parts.buffer.storage) is LazyTensorStorage
    assert parts.sampler._pool is None and parts.sampler._nearest is None and parts.sampler._energy._written is None
    agent = parts.agent
    assert not agent.fast and agent._small_batch_actor is None and agent._fused is None
    assert resolved_settings(agent) == schema.PLAIN == ddpg_agent.PLAIN
    record = startup_record(cfg, resolved_settings(agent))
    assert "plain: true (the algorithm alone" in record and "subnormals: auto -> keep" in record
    assert "matmul: auto -> default" in record and "gradients: auto -> autograd" in record
    # the devices' run, for contrast
    fast = make_parts(config(["env=reach", "algo=gchgg", *tiny(tmp_path)]))
    assert type(fast.buffer.storage) is FieldStorage and fast.sampler._pool is not None and fast.agent.fast
    assert fast.agent.subnormals == "flush"
    # the plain sampler keeps the engine's shortlist length for its state: "auto" resolved alike
    for metric in (parts.metric, EuclideanMetric()):
        for neighbours in ("auto", None, 2):
            plain = GraphCurriculumSampler(metric, neighbours=neighbours, fast=False)
            assert plain.neighbours == GraphCurriculumSampler(metric, neighbours=neighbours).neighbours
    with pytest.raises(ValueError, match="neighbours"):
        GraphCurriculumSampler(parts.metric, neighbours=0, fast=False)


@pytest.mark.parametrize("setting, value", [("precision", "bfloat16"), ("matmul", "onednn"), ("gradients", "fused"),
                                            ("gradients", "compiled"), ("subnormals", "flush")])
def test_a_setting_contrary_to_plain_true_is_refused_naming_both(setting, value):
    with pytest.raises(ValueError, match=rf"plain=true .* but {setting}={value} was set.*or set plain=false"):
        schema.check(config([f"{setting}={value}", "plain=true"]))
    schema.check(config([f"{setting}={value}"]))  # without plain: a setting like any other
    with pytest.raises(ValueError, match=rf"fast=False \(the plain path\) .* got {setting}='{value}'"):
        DDPGAgent(5, 3, 2, hidden=(8,), fast=False, **{setting: value})


def test_plain_true_takes_auto_and_the_plain_values():
    explicit = [f"{name}={value}" for name, value in schema.PLAIN.items()]
    for overrides in ([], explicit, ["precision=auto", "matmul=auto", "gradients=auto", "subnormals=auto"]):
        run = schema.check(config([*overrides, "plain=true"]))
        assert run.plain
    agent = DDPGAgent(5, 3, 2, hidden=(8,), fast=False, **schema.PLAIN)
    assert resolved_settings(agent) == schema.PLAIN
    with pytest.raises(ValueError, match="plain must be one of False, True, got 'yes'"):
        replace(schema.check(config([])), plain="yes").check()


def test_the_plain_agent_acts_and_learns_as_the_agent_with_its_devices():
    """One agent per path from the same seed: the same actions on one row and on a few (eq. 22's draws too),
    the same updates, through ``rollout_policy`` as the trainer acts."""
    agents = [DDPGAgent(5, 3, 2, hidden=(16, 16), generator=torch.Generator().manual_seed(0), fast=fast,
                        **AGENT_AT_FLOAT32) for fast in (False, True)]
    data = torch.Generator().manual_seed(1)
    obs, goal = torch.randn(64, 5, generator=data), torch.randn(64, 3, generator=data)
    for agent in agents:
        agent.update_normalizer(obs, goal)
    batch = TensorDict({"observation": obs, "desired_goal": goal, "action": torch.rand(64, 2, generator=data) * 2 - 1,
                        "next": {"observation": obs + 0.1, "reward": -torch.ones(64, 1)}}, [64])
    outputs = []
    for agent in agents:
        explore = torch.Generator().manual_seed(2)
        with torch.inference_mode():
            policy = agent.rollout_policy(explore)
            acted = [policy(obs[i : i + 1], goal[i : i + 1]) for i in range(8)]
            acted.append(agent.act(obs[:5], goal[:5], explore=True, generator=explore))
        losses = [agent.update(batch) for _ in range(3)]
        outputs.append((acted, losses, [p.detach().clone() for p in agent.loss_module.parameters()]))
    (acted, losses, weights), (acted_fast, losses_fast, weights_fast) = outputs
    assert all(torch.equal(a, b) for a, b in zip(acted, acted_fast, strict=True))
    assert losses == losses_fast and all(torch.equal(a, b) for a, b in zip(weights, weights_fast, strict=True))


def test_the_plain_ebp_draws_what_its_energy_copy_draws_as_the_fifo_wraps():
    """EBP's plain path reads every energy again after a write; its per-row copy reads the written rows only."""
    buffers = [TensorDictReplayBuffer(storage=LazyTensorStorage(50), sampler=EnergySampler(fast=fast), batch_size=32,
                                      generator=torch.Generator().manual_seed(0)) for fast in (False, True)]
    data = torch.Generator().manual_seed(1)
    for _ in range(12):  # episodes of 10 rows, one energy each (some 0); the FIFO wraps after 5
        energy = torch.rand((), generator=data).item() * float(torch.rand((), generator=data) > 0.2)
        episode = TensorDict({"energy": torch.full((10, 1), energy)}, [10])
        draws = []
        for buffer in buffers:
            buffer.extend(episode.clone())
            draws.append(torch.stack([buffer.sample()["index"] for _ in range(3)]))
        assert torch.equal(*draws)
    assert buffers[0].sampler.cache_bytes == 0 and buffers[1].sampler.cache_bytes > 0


def test_the_subnormals_default_is_the_agents():
    assert schema.RunConfig().subnormals == "auto" == DDPGAgent.__init__.__kwdefaults__["subnormals"]
    assert schema.RunConfig().plain is False and DDPGAgent.__init__.__kwdefaults__["fast"] is True


def test_plain_is_a_setting_a_fork_may_change(tmp_path):
    """As ``precision`` may: it changes how the numbers are computed, not the state a fork takes over."""
    assert "plain" in fork.MAY_DIFFER and "precision" in fork.MAY_DIFFER
    assert not any(fork._matches("plain", (pattern,)) for pattern in fork.SAMPLER)  # the sampler's state carries over
    source = tmp_path / "source"
    train.run(config(["env=reach", "algo=gchgg", *tiny(tmp_path, iterations=2)]), source)
    forked = tmp_path / "fork"
    rows = train.run(config(["env=reach", "algo=gchgg", *tiny(tmp_path, iterations=3), "plain=true",
                             f"init_from={source}"]), forked)
    assert [row["iteration"] for row in rows] == [0, 1, 2]
    record = (forked / fork.RECORD).read_text()
    assert "plain:" in record and "sampler: carried over" in record
