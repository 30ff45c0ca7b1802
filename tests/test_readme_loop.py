"""The README's loop runs as written, and the pages name what the code exports.

The loop's code block is read from README.md and run with its sizes line shrunk (a few hundred
steps, tiny networks), so the README cannot drift from working code."""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import check_env_specs

from torchrl_reset import DualCollector, EpisodeWindowSampler, NStepStateTransform, accel
from torchrl_reset.collector_env import own_time_limit

ROOT = Path(__file__).resolve().parents[1]
SIZES = re.compile(r"^total_steps, hidden, buffer_size, heat_up = .*$", re.M)
# a few hundred steps; heat_up stays >= n = 10, the reset buffer's wait that the README's guard relies on
SMALL = "total_steps, hidden, buffer_size, heat_up = 500, (16, 16), 1000, 10"


def readme_loop() -> str:
    """The python code block of README.md's "The loop" section."""
    text = (ROOT / "README.md").read_text()
    section = text.split("\n## The loop\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(blocks) == 1, f"README's loop section should hold one python block, found {len(blocks)}"
    return blocks[0]


@pytest.fixture(scope="module")
def ran():
    """The README's loop, run once with the sizes shrunk; its variables and the warnings it raised."""
    code = readme_loop()
    assert len(SIZES.findall(code)) == 1, "the loop's sizes line moved: update SIZES here"
    namespace = {"__name__": "readme_loop"}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny networks: one thread is several times faster on a busy machine
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            exec(compile(SIZES.sub(SMALL, code), "README.md (The loop)", "exec"), namespace)
    finally:
        torch.set_num_threads(threads)
    namespace["warnings"] = [w for w in caught if issubclass(w.category, UserWarning)]
    return namespace


def test_the_readme_loop_runs_both_agents_and_updates_both(ran):
    collector = ran["collector"]
    c = collector.counters
    assert collector.frames == 500 == c["forward_steps"] + c["reset_steps"]
    assert len(ran["forward_rb"]) == c["forward_steps"]
    # at most n - 1 = 9 reset steps of the open episode are still held back by NStepStateTransform
    assert c["reset_steps"] - 9 <= len(ran["reset_rb"]) <= c["reset_steps"]
    assert c["forward_steps"] >= 10 and c["reset_steps"] >= 10, c
    # both optimizers stepped (Adam keeps state only for parameters it updated) and the losses are finite
    assert ran["forward_opt"].state and ran["reset_opt"].state
    losses = ran["rce"](_reset_sample(ran))
    assert torch.isfinite(losses["loss_classifier"]) and torch.isfinite(losses["loss_actor"])
    # the project's reset actor: stochastic, its temperature learned (moved from its first value, 0.01)
    assert ran["rce"].stochastic and torch.isfinite(losses["loss_alpha"])
    assert float(ran["rce"].alpha) != pytest.approx(0.01)
    assert c["manual_resets"] + c["successful_resets"] + c["terminations"] == c["reset_episodes"]


def _reset_sample(ran):
    sample = ran["reset_rb"].sample()
    sample["example"] = ran["collector"].example_buffer.sample(len(sample))
    return sample


def test_the_readme_env_meets_the_contract_and_the_loop_is_silent(ran):
    env = ran["env"]
    check_env_specs(env)
    spec = env.observation_spec["reset_success"]
    assert spec.shape == (1,) and spec.dtype == torch.bool
    assert own_time_limit(env) is None  # max_episode_steps=-1 leaves gymnasium's TimeLimit out
    assert ran["collector"].counters["terminations"] == 0
    own_end = [str(w.message) for w in ran["warnings"] if "by itself" in str(w.message)]
    assert not own_end, own_end
    # every start state passes the example's check: the examples and reset_success agree
    starts = ran["collector"].example_buffer.states()["observation"]
    assert bool((starts[:, 0] < -0.95).all()) and bool((starts[:, 2].abs() < 0.5).all())


def test_the_readme_optimizers_cover_the_actors_and_trained_members_only(ran):
    def ids(tensors):
        return {id(t) for t in tensors}

    def optimized(opt):
        return ids(p for group in opt.param_groups for p in group["params"])

    reset_actor, classifiers, rce = ran["reset_actor"], ran["classifiers"], ran["rce"]
    assert optimized(ran["reset_opt"]) == (ids(reset_actor.parameters()) | ids(classifiers.parameters())
                                           | {id(rce.temperature.log_alpha)})
    assert any(p is rce.temperature.log_alpha for p in rce.parameters())  # the temperature is the loss's own
    trained = {p.data_ptr() for group in ran["reset_opt"].param_groups for p in group["params"]}
    priors = {b.data_ptr() for name, b in classifiers.named_buffers() if name.startswith("prior")}
    targets = {t.data_ptr() for t in rce.target_classifier_network_params.values(True, True)}
    assert priors and targets and not (trained & priors) and not (trained & targets)
    # the tensors the loss trains with are these very tensors
    assert {p.data_ptr() for p in rce.classifier_network_params.values(True, True) if p.requires_grad} == (
        {p.data_ptr() for p in classifiers.parameters()})
    assert optimized(ran["forward_opt"]) == ids(ran["ddpg"].parameters())


def test_the_readme_loop_is_the_documented_one():
    code = readme_loop()
    for piece in ("max_episode_steps=-1", '"reset_success"', "NStepStateTransform(10)", "EpisodeWindowSampler(10)",
                  "collector.set_seed(", "example_buffer.sample(len(sample))", "targets.step()", ">= heat_up",
                  "TanhNormalHead()", 'loss["loss_alpha"]'):
        assert piece in code, piece


def test_sampling_the_reset_buffer_before_its_first_nstep_row_says_what_it_waits_for():
    transform = NStepStateTransform(10)
    rb = ReplayBuffer(storage=LazyTensorStorage(100), sampler=EpisodeWindowSampler(10), transform=transform,
                      batch_size=4)

    def step(t):  # one reset step of one open episode, as the collector yields it
        return TensorDict({"observation": torch.full((1, 1), float(t)),
                           "next": {"observation": torch.full((1, 1), t + 1.0), "done": torch.zeros(1, 1, dtype=torch.bool)},
                           "collector": {"traj_ids": torch.ones(1, dtype=torch.long)}}, batch_size=[1])

    for t in range(9):
        rb.extend(step(t))
    assert len(rb) == 0
    with pytest.raises(RuntimeError, match=r"NStepStateTransform\(n_steps=10\) holds back 9 transition") as err:
        rb.sample()
    assert "after 10 steps of the first episode" in str(err.value) and "len(buffer) > 0" in str(err.value)
    rb.extend(step(9))  # the 10th step brings s_{0+10}: the first row is written
    assert len(rb) == 1
    assert rb.sample()["nstep", "observation"].flatten().tolist() == [10.0] * 4


def test_an_empty_episode_window_buffer_without_nstep_transform_says_so():
    rb = ReplayBuffer(storage=LazyTensorStorage(10), sampler=EpisodeWindowSampler(3), batch_size=2)
    with pytest.raises(RuntimeError, match="empty storage. Extend the buffer"):
        rb.sample()


def test_the_components_page_names_every_accelerator_component():
    page = (ROOT / "docs" / "components.md").read_text()
    missing = [name for name in accel.__all__ if f"`{name}`" not in page]
    assert not missing, f"docs/components.md does not name {missing}"


def test_the_readme_and_components_page_link_the_environment_contract():
    assert (ROOT / "docs" / "environment-contract.md").exists()
    assert "(docs/environment-contract.md)" in (ROOT / "README.md").read_text()
    assert "(environment-contract.md)" in (ROOT / "docs" / "components.md").read_text()
    assert DualCollector.set_seed.__doc__ and "docs/environment-contract.md" in DualCollector.set_seed.__doc__
