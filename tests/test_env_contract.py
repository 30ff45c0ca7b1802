"""The environment contract (docs/environment-contract.md) as DualCollector enforces it: a warning
when the env truncates or terminates by itself, what a termination costs, seeding, exact resume."""
from __future__ import annotations

import io
import re
import warnings
from pathlib import Path

import gymnasium as gym
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.data import Categorical
from torchrl.envs import GymEnv, GymWrapper, StepCounter, Transform, TransformedEnv

from torchrl_reset import DualCollector
from torchrl_reset_envs import ChainEnv

ROOT = Path(__file__).resolve().parents[1]
OWN_END = "by itself"


def constant_policy(value):
    return TensorDictModule(lambda obs: torch.full((*obs.shape[:-1], 1), value), in_keys=["observation"], out_keys=["action"])


RIGHT, LEFT = constant_policy(1.0), constant_policy(-1.0)


class TimeLimitedChain(ChainEnv):
    """ChainEnv with a time limit of its own: every step from the ``limit``-th since the last reset is truncated."""

    def __init__(self, limit: int, **kwargs):
        super().__init__(**kwargs)
        self.limit, self.elapsed = limit, 0
        self.full_done_spec["truncated"] = Categorical(2, shape=(1,), dtype=torch.bool)

    def _reset(self, tensordict=None, **kwargs):
        self.elapsed = 0
        return super()._reset(tensordict, **kwargs).set("truncated", torch.zeros(1, dtype=torch.bool))

    def _step(self, tensordict):
        self.elapsed += 1
        out = super()._step(tensordict)
        truncated = torch.tensor([self.elapsed >= self.limit])
        return out.set("truncated", truncated).set("done", truncated | out["terminated"])


class TerminatingChain(ChainEnv):
    """ChainEnv that terminates on reaching cell ``fall`` (like a robot that falls over), and counts resets."""

    def __init__(self, fall: int, **kwargs):
        super().__init__(**kwargs)
        self.fall, self.resets = fall, 0

    def _reset(self, tensordict=None, **kwargs):
        self.resets += 1
        return super()._reset(tensordict, **kwargs)

    def _step(self, tensordict):
        out = super()._step(tensordict)
        fell = torch.tensor([self.position >= self.fall])
        return out.set("terminated", fell).set("done", fell)


class SlowPendulum(Transform):
    """reset_success for stock Pendulum-v1, which starts at any angle with |theta dot| <= 1: the speed check."""

    def __init__(self, max_speed: float = 1.0):
        super().__init__()
        self.max_speed = max_speed

    def _call(self, td):
        return td.set("reset_success", td["observation"][..., 2:].abs() <= self.max_speed)

    def _reset(self, td, td_reset):
        return self._call(td_reset)

    def transform_observation_spec(self, spec):
        spec["reset_success"] = Categorical(2, shape=(1,), dtype=torch.bool)
        return spec


def pendulum_policy():
    return TensorDictModule(lambda obs: torch.rand(*obs.shape[:-1], 1) * 4 - 2, in_keys=["observation"], out_keys=["action"])


def run(collector):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        steps = torch.cat(list(collector))
    return steps, [w for w in caught if OWN_END in str(w.message)]


def chain_collector(env, total_frames=36):
    return DualCollector(env, RIGHT, LEFT, max_forward_steps=3, min_reset_steps=1, total_frames=total_frames)


def test_an_env_that_truncates_by_itself_is_warned_about_once_and_the_loop_is_unchanged():
    # H_f = 3 right, then 3 left back to cell 0: only the first env.reset() ever happens, so from the
    # 4th step on every step comes back truncated, as gymnasium's TimeLimit does after its limit
    limited = chain_collector(TimeLimitedChain(4, num_states=10))
    steps, own = run(limited)
    assert len(own) == 1 and own[0].category is UserWarning
    assert own[0].filename == __file__  # it points at the loop over the collector, here in run()
    message = str(own[0].message)
    assert "('next', 'truncated') = True at frame 4" in message and "did not cause" in message
    assert "max_episode_steps=-1" in message and "docs/environment-contract.md" in message
    # the collector carries on exactly as without the limit; the flags stay on the yielded steps
    plain = chain_collector(ChainEnv(num_states=10))
    reference, none = run(plain)
    assert none == []
    assert torch.equal(steps["observation"], reference["observation"])
    assert torch.equal(steps["collector", "phase"], reference["collector", "phase"])
    assert limited.counters == plain.counters and limited.counters["successful_resets"] == 6
    assert steps["next", "truncated"].squeeze(-1)[3:].all()


def test_the_warning_is_once_per_collector():
    for _ in range(2):
        _, own = run(chain_collector(TimeLimitedChain(2, num_states=10), total_frames=20))
        assert len(own) == 1


@pytest.mark.parametrize("make_env, named", [
    (lambda: TransformedEnv(ChainEnv(num_states=10), StepCounter(max_steps=50)), "StepCounter(max_steps=50)"),
    (lambda: TransformedEnv(GymEnv("Pendulum-v1"), SlowPendulum()), "gymnasium's TimeLimit of 200 steps"),
], ids=["torchrl-StepCounter", "gymnasium-TimeLimit"])
def test_a_time_limit_inside_the_env_is_warned_about_at_construction(make_env, named):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        DualCollector(make_env(), RIGHT, LEFT, max_forward_steps=3)
    own = [w for w in caught if OWN_END in str(w.message)]
    assert len(own) == 1 and f"it has {named}" in str(own[0].message)
    assert own[0].filename == __file__  # it points at the line that built the collector


def test_gymnasium_time_limit_truncates_every_step_after_it_and_is_warned_once():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        collector = DualCollector(TransformedEnv(GymEnv("Pendulum-v1"), SlowPendulum()), pendulum_policy(),
                                  pendulum_policy(), max_forward_steps=100, min_reset_steps=200, total_frames=230)
        steps = torch.cat(list(collector))
    assert len([w for w in caught if OWN_END in str(w.message)]) == 1  # at construction, not again at step 200
    truncated = steps["next", "truncated"].squeeze(-1)
    # the collector ends the forward episode at H_f = 100; the TimeLimit truncates every step from the 200th
    assert truncated[199:].all() and int(truncated[:199].sum()) == 1 and bool(truncated[99])
    assert collector.counters["manual_resets"] == 0  # the collector did not reset: it does not own those flags


def test_no_time_limit_no_warning():
    env = TransformedEnv(GymEnv("Pendulum-v1", max_episode_steps=-1), SlowPendulum())
    collector = DualCollector(env, pendulum_policy(), pendulum_policy(), max_forward_steps=100, min_reset_steps=200,
                              total_frames=230)
    steps, own = run(collector)
    assert own == []
    assert not steps["next", "truncated"].squeeze(-1)[199:].any()


def test_an_env_that_terminates_starves_the_reset_agent_and_is_warned_about_once():
    # every forward episode ends by a termination at cell 3, before H_f = 20: no reset episode ever runs
    env = TerminatingChain(3, num_states=10)
    collector = DualCollector(env, RIGHT, LEFT, max_forward_steps=20, total_frames=60)
    steps, own = run(collector)
    assert len(own) == 1 and own[0].category is UserWarning and own[0].filename == __file__
    message = str(own[0].message)
    assert "terminated an episode by itself" in message and "at frame 3, step 3 of a forward episode" in message
    assert "manual reset" in message and "reset agent never acts" in message
    c = collector.counters
    assert c["reset_steps"] == 0 and c["reset_episodes"] == 0 and c["manual_resets"] == 0
    assert c["terminations"] == 20 == c["forward_episodes"] and env.resets == 21  # one env.reset() per 3 steps
    assert not (steps["collector", "phase"] == DualCollector.RESET).any()


def test_a_termination_in_a_reset_episode_is_warned_about_too():
    env = TerminatingChain(8, num_states=12)
    # forward walks right 3 cells and asks for a reset; the "reset" policy walks right too, and falls
    collector = DualCollector(env, RIGHT, RIGHT, max_forward_steps=3, total_frames=10)
    _, own = run(collector)
    assert len(own) == 1 and "step 5 of a reset episode" in str(own[0].message)
    assert collector.counters["terminations"] >= 1 and collector.counters["reset_episodes"] >= 1


def pendulum_collector(env, seed):
    # reset_success never holds: every reset episode fails at H_r = 20 and ends with env.reset(),
    # whose start state the env's generator draws
    collector = DualCollector(TransformedEnv(env, SlowPendulum(max_speed=-1.0)), pendulum_policy(), pendulum_policy(),
                              max_forward_steps=10, max_reset_steps=20, total_frames=120)
    collector.set_seed(seed)
    return collector


def test_set_seed_seeds_the_policies_noise_and_the_envs_start_states():
    runs = {}
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        collector = pendulum_collector(GymEnv("Pendulum-v1", max_episode_steps=-1), seed)
        steps, _ = run(collector)
        runs[name] = (steps, collector.example_buffer.states()["observation"])
    (a, starts_a), (b, starts_b), (c, starts_c) = runs["a"], runs["b"], runs["c"]
    assert len(starts_a) == 5  # the first env.reset() and four manual resets
    assert torch.equal(a["action"], b["action"]) and torch.equal(a["next", "observation"], b["next", "observation"])
    assert torch.equal(starts_a, starts_b)
    assert not torch.equal(starts_a, starts_c) and not torch.equal(a["action"], c["action"])


def contract_page_snippet() -> str:
    """The simulator-state wrapper of docs/environment-contract.md, as printed there."""
    text = (ROOT / "docs" / "environment-contract.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", text, re.S) if "def get_simulator_state" in b]
    assert len(blocks) == 1
    return blocks[0]


def test_the_contract_pages_simulator_state_resumes_pendulum_exactly():
    namespace = {"__name__": "contract_page"}
    exec(compile(contract_page_snippet(), "docs/environment-contract.md", "exec"), namespace)
    PendulumState = namespace["PendulumState"]

    def make(seed):
        return pendulum_collector(GymWrapper(PendulumState(gym.make("Pendulum-v1", max_episode_steps=-1))), seed)

    reference = make(5)
    batches = []
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*get_simulator_state.*")  # the env's state is saved
        for i, batch in enumerate(reference):
            batches.append(batch)
            if i == 44:  # inside a reset episode, after a manual reset drew a start state
                buffer = io.BytesIO()
                torch.save(reference.state_dict(), buffer)
    resumed = make(99)
    buffer.seek(0)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    continued = torch.cat(list(resumed))
    tail = torch.cat(batches[45:])
    assert torch.equal(continued["observation"], tail["observation"])
    assert torch.equal(continued["action"], tail["action"])
    assert resumed.counters == reference.counters and reference.counters["manual_resets"] >= 3
