"""One agent pair over N copies of a task (``arms=N``): the per-arm replay of the reset agent, one arm
reproducing the run on one env, exact resume of N arms, and the configurations refused."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
sys.path.insert(0, str(RECIPES))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import train  # noqa: E402
from buffers import ArmReplay, fallback_counts  # noqa: E402
from config_checks import ConfigError  # noqa: E402
from test_recipes import config, rows  # noqa: E402

from torchrl_reset import EpisodeWindowSampler, NStepStateTransform  # noqa: E402


def episode(arm: int, start: float, length: int, traj: int) -> TensorDict:
    """One arm's episode of scalar states start, start + 1, ...; its last step is done."""
    obs = start + torch.arange(length, dtype=torch.float32).unsqueeze(-1)
    done = torch.zeros(length, 1, dtype=torch.bool)
    done[-1] = True
    return TensorDict({"observation": obs, "next": {"observation": obs + 1, "done": done},
                       ("collector", "traj_ids"): torch.full((length,), traj),
                       ("collector", "env_ids"): torch.full((length,), arm)}, batch_size=[length])


def arm_replay(n: int = 3, arms: int = 2, batch_size: int = 6000) -> ArmReplay:
    return ArmReplay([ReplayBuffer(storage=LazyTensorStorage(100), transform=NStepStateTransform(n),
                                   sampler=EpisodeWindowSampler(n)) for _ in range(arms)], batch_size=batch_size)


def interleaved(a: TensorDict, b: TensorDict) -> list[TensorDict]:
    """The collector's batches: one step of each arm still going per iteration."""
    return [torch.cat([x[t:t + 1] for x in (a, b) if t < x.shape[0]]) for t in range(max(a.shape[0], b.shape[0]))]


def test_each_arm_gets_its_own_n_step_states_from_interleaved_steps():
    rb = arm_replay(n=3)
    for batch in interleaved(episode(0, 0.0, 6, traj=1), episode(1, 100.0, 6, traj=2)):
        rb.extend(batch)
    first, second = rb.buffers[0][:], rb.buffers[1][:]
    # s_{t+3}, or the episode's last state when it ends earlier (0..5 -> next 1..6)
    assert first["nstep", "observation"].flatten().tolist() == [3, 4, 5, 6, 6, 6]
    assert second["nstep", "observation"].flatten().tolist() == [103, 104, 105, 106, 106, 106]
    assert len(rb) == 12


def test_a_sample_splits_over_the_arms_by_their_rows_and_keeps_whole_windows():
    torch.manual_seed(0)
    rb = arm_replay(n=3)
    for batch in interleaved(episode(0, 0.0, 6, traj=1), episode(1, 100.0, 12, traj=2)):
        rb.extend(batch)
    sample = rb.sample()
    obs = sample["observation"].flatten()
    # every row's window lies inside its episode: s_{t+n} is exactly n steps on (never the truncated end)
    assert torch.equal(sample["nstep", "observation"].flatten() - obs, torch.full_like(obs, 3.0))
    from_first = obs < 100
    # windows t = 0..3 of the 6-step episode, t = 0..9 of the 12-step one
    assert set(obs[from_first].tolist()) == {0.0, 1.0, 2.0, 3.0}
    assert set(obs[~from_first].tolist()) == {100.0 + t for t in range(10)}
    # the arms hold 6 and 12 rows: a third of the rows from the first, binomial sd sqrt(6000 * 2 / 9) = 36.5
    assert abs(int(from_first.sum()) - 2000) < 5 * 36.5


def test_the_forward_buffer_of_arms_samples_each_arms_episodes_first(tmp_path):
    """arms= with the release's episode-first forward sampling: the forward buffer is one buffer per arm
    (episodes are runs of consecutive steps, which interleaved arms would cut into single rows), each
    drawing an episode uniformly, then a step in it; the arms' shares follow the rows they hold."""
    from buffers import make_buffers

    forward_rb, _ = make_buffers(config(tmp_path, *COMMON, "arms=2", "forward.buffer_size=1001", "forward.batch_size=8000"))
    assert isinstance(forward_rb, ArmReplay) and len(forward_rb.buffers) == 2
    assert all(isinstance(b.sampler, EpisodeWindowSampler) and b.storage.max_size == 501 for b in forward_rb.buffers)
    # arm 0: episodes of 10 and 2 steps (states 0..9 and 50..51), arm 1: one of 4 (100..103), interleaved
    arm0 = torch.cat([episode(0, 0.0, 10, traj=1), episode(0, 50.0, 2, traj=3)])
    for batch in interleaved(arm0, episode(1, 100.0, 4, traj=2)):
        forward_rb.extend(batch)
    torch.manual_seed(0)
    obs = forward_rb.sample()["observation"].flatten()
    first = obs < 100
    # shares by rows held, 12 and 4: 6000 of 8000 from arm 0 (binomial sd sqrt(8000 * 3 / 16) = 38.7)
    assert abs(int(first.sum()) - 6000) < 5 * 38.7
    # within arm 0 each episode is drawn with probability 1/2 (uniform rows would give the short one 2/12):
    # sd of the short episode's count sqrt(6000 / 4) = 38.7
    assert abs(int((obs[first] >= 50).sum()) - 3000) < 5 * 38.7


def test_one_arm_samples_exactly_as_its_buffer_alone():
    single = ReplayBuffer(storage=LazyTensorStorage(100), transform=NStepStateTransform(3),
                          sampler=EpisodeWindowSampler(3), batch_size=64)
    arms = arm_replay(n=3, arms=1, batch_size=64)
    data = episode(0, 0.0, 12, traj=1)
    single.extend(data)
    arms.extend(data)
    torch.manual_seed(3)
    a = single.sample()
    torch.manual_seed(3)
    b = arms.sample()
    assert torch.equal(a["observation"], b["observation"])


def test_fallbacks_are_counted_over_the_arms_and_saved_with_the_buffers(tmp_path):
    rb = arm_replay(n=3, batch_size=8)
    rb.extend(episode(0, 0.0, 2, traj=1))  # no arm holds a whole 3-step window yet: uniform rows
    rb.extend(episode(1, 100.0, 2, traj=2))
    rb.sample()
    assert fallback_counts(rb) == [1, 1]
    rb.dumps(tmp_path)
    again = arm_replay(n=3, batch_size=8)
    again.loads(tmp_path)
    assert len(again) == 4 and fallback_counts(again) == [1, 1]
    assert torch.equal(again.buffers[1][:]["observation"], rb.buffers[1][:]["observation"])


def test_a_sample_says_whether_an_arm_fell_back_to_uniform_rows():
    """The recipe reads the one-step fallback from the sample's info (the reset kind marks the batch)."""
    rb = arm_replay(n=3, batch_size=8)
    rb.extend(episode(0, 0.0, 2, traj=1))  # two steps: no whole 3-step window in either arm
    rb.extend(episode(1, 100.0, 2, traj=2))
    _, info = rb.sample(return_info=True)
    assert info == {"fallback": True}
    rb.extend(episode(0, 10.0, 5, traj=3))  # now each arm holds a 5-step episode: windows exist
    rb.extend(episode(1, 110.0, 5, traj=4))
    before = fallback_counts(rb)
    assert [rb.sample(return_info=True)[1]["fallback"] for _ in range(20)] == [False] * 20
    assert fallback_counts(rb) == before
    assert isinstance(rb.sample(), torch.Tensor) is False and len(rb.sample()) == 8  # without info: the rows alone


def test_rows_without_their_arm_or_of_an_unknown_arm_are_refused():
    rb = arm_replay()
    with pytest.raises(KeyError, match="env_ids"):
        rb.extend(episode(0, 0.0, 3, traj=1).exclude(("collector", "env_ids")))
    with pytest.raises(IndexError, match="arm 2"):
        rb.extend(episode(2, 0.0, 3, traj=1))


COMMON = ["task=peg_insertion_insert", "algo=ours", "threads=1"]  # the paper preset's settings, the release's included


def without_speed(table):
    return [{k: v for k, v in r.items() if k != "steps_per_second"} for r in table]


def test_one_arm_is_the_run_on_one_env(tmp_path):
    """arms=1: the batched collector's one copy, seeded as the run's env, with one reset buffer: every
    counter, evaluation and loss of the run on one env, row by row."""
    alone = train.train(config(tmp_path / "alone", *COMMON, "total_steps=300"))
    one = train.train(config(tmp_path / "one", *COMMON, "total_steps=300", "arms=1"))
    assert without_speed(rows(tmp_path / "one" / "progress.csv")) == without_speed(rows(tmp_path / "alone" / "progress.csv"))
    assert rows(tmp_path / "one" / "eval.csv") == rows(tmp_path / "alone" / "eval.csv")
    assert one["manual_resets"] == alone["manual_resets"] and one["arms"] == 1


@pytest.mark.parametrize("algo", ["ours", "lnt"])
def test_arms_train_one_run_and_resume_exactly(tmp_path, algo):
    common = ["task=peg_insertion_insert", f"algo={algo}", "threads=1", "arms=3"]
    whole = train.train(config(tmp_path / "whole", *common, "total_steps=400"))
    train.train(config(tmp_path / "split", *common, "total_steps=200"))
    resumed = train.train(config(tmp_path / "split", *common, "total_steps=400", "resume=true"))
    # the iteration that reaches the budget is completed: at most N - 1 = 2 steps past it, the same
    # iterations as a run that goes on, so the run resumed at 200 continues as the uninterrupted one
    assert 400 <= whole["steps"] <= 402 and whole["finished"]
    a, b = without_speed(rows(tmp_path / "whole" / "progress.csv")), without_speed(rows(tmp_path / "split" / "progress.csv"))
    assert a == b and len(a) >= 8
    assert rows(tmp_path / "whole" / "eval.csv") == rows(tmp_path / "split" / "eval.csv")
    assert {k: resumed[k] for k in ("manual_resets", "reset_episodes", "forward_share")} == \
        {k: whole[k] for k in ("manual_resets", "reset_episodes", "forward_share")}
    last = a[-1]
    assert int(last["forward_steps"]) + int(last["reset_steps"]) == int(last["frames"]) == whole["steps"]
    for agent in ("forward", "reset"):  # past its 40-step heat-up, each agent updated
        if int(last[f"{agent}_steps"]) > 41:
            assert last[f"loss_{agent}_critic"] not in ("", "nan")


@pytest.mark.parametrize("overrides, message", [
    (["arms=0"], "arms must be a positive integer"),
    (["arms=true"], "arms must be a positive integer"),
    (["arms=2", "seeds=2"], "cannot be combined"),
    (["arms=2", "task=ur3_peg"], "a UR3 arm is one env"),
])
def test_bad_arm_configurations_fail_before_training(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=message):
        train.train(config(tmp_path, *COMMON, *overrides))


def test_a_checkpoint_resumes_only_with_its_number_of_arms(tmp_path):
    train.train(config(tmp_path, *COMMON, "total_steps=100", "arms=2"))
    with pytest.raises(ConfigError, match="arms"):
        train.train(config(tmp_path, *COMMON, "total_steps=200", "arms=3", "resume=true"))
    with pytest.raises(ConfigError, match="arms"):
        train.train(config(tmp_path, *COMMON, "total_steps=200", "resume=true"))
