"""NStepStateTransform and InitialStateBuffer."""
from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer

from torchrl_reset import InitialStateBuffer, NStepStateTransform


def trajectory(cells, traj_ids, done_last=False):
    """Transitions cell[i] -> cell[i] + 1 with ids; observation = the cell number."""
    n = len(cells)
    obs = torch.tensor(cells, dtype=torch.float32).unsqueeze(-1)
    done = torch.zeros(n, 1, dtype=torch.bool)
    done[-1] = done_last
    return TensorDict(
        {
            "observation": obs,
            "next": {"observation": obs + 1, "done": done},
            "collector": {"traj_ids": torch.tensor(traj_ids)},
        },
        batch_size=[n],
    )


def test_nstep_state_is_n_steps_ahead_and_clipped_to_the_trajectory_end():
    rb = ReplayBuffer(storage=LazyTensorStorage(100), transform=NStepStateTransform(3))
    rb.extend(trajectory([0, 1, 2, 3, 4], [7] * 5, done_last=True))
    data = rb[:]
    # s_{t+n} = s_{t+3} = cell + 3, but never past the last state (5) of the trajectory
    assert data["nstep", "observation"].squeeze(-1).tolist() == [3, 4, 5, 5, 5]
    assert data["next", "observation"].squeeze(-1).tolist() == [1, 2, 3, 4, 5]


def test_transitions_wait_for_their_nstep_state_across_single_frame_extends():
    transform = NStepStateTransform(3)
    rb = ReplayBuffer(storage=LazyTensorStorage(100), transform=transform)
    for t in range(4):
        rb.extend(trajectory([t], [1]))
    assert len(rb) == 2 and transform.num_pending == 2
    # a new trajectory id closes the first one
    rb.extend(trajectory([10], [2]))
    assert len(rb) == 4
    assert rb[:]["nstep", "observation"].squeeze(-1).tolist() == [3, 4, 4, 4]
    tail = transform.flush()
    assert tail["nstep", "observation"].squeeze(-1).tolist() == [11]


@pytest.mark.parametrize("n", [1, 3])
@pytest.mark.parametrize("rows_per_extend", [1, 4])
def test_every_transition_gets_the_state_n_steps_ahead_within_its_trajectory(n, rows_per_extend):
    # three trajectories: one ended by done (cells 0..4), one cut by a new trajectory id without a
    # done (cells 10..11), one left open and flushed (cells 20..26)
    cells = [0, 1, 2, 3, 4, 10, 11, 20, 21, 22, 23, 24, 25, 26]
    ids = [0] * 5 + [1] * 2 + [2] * 7
    data = trajectory(cells, ids)
    data["next", "done"][4] = True
    # by hand: s_{t+n} is cell + n, but never past the last next state of the trajectory (5, 12, 27)
    last = {0: 5, 1: 12, 2: 27}
    expected = [min(c + n, last[i]) for c, i in zip(cells, ids)]
    transform = NStepStateTransform(n)
    rb = ReplayBuffer(storage=LazyTensorStorage(100), transform=transform)
    for start in range(0, len(cells), rows_per_extend):
        rb.extend(data[start:start + rows_per_extend])
    assert transform.num_pending == n - 1  # the open trajectory's last n - 1 transitions
    tail = transform.flush()
    assert (tail is None) == (n == 1)
    stored = rb[:] if tail is None else torch.cat([rb[:], tail.exclude("index")], 0)
    assert stored["observation"].squeeze(-1).tolist() == cells  # in order, none lost or repeated
    assert stored["nstep", "observation"].squeeze(-1).tolist() == expected


def test_n_equal_1_copies_the_next_state():
    rb = ReplayBuffer(storage=LazyTensorStorage(10), transform=NStepStateTransform(1))
    rb.extend(trajectory([0, 1, 2], [0, 0, 0]))
    torch.testing.assert_close(rb[:]["nstep", "observation"], rb[:]["next", "observation"])


def test_pending_transitions_survive_a_state_dict_round_trip():
    a = NStepStateTransform(4)
    a._inv_call(trajectory([0, 1], [3, 3]))
    b = NStepStateTransform(4)
    b.load_state_dict(a.state_dict())
    out = b._inv_call(trajectory([2, 3], [3, 3]))
    assert out["nstep", "observation"].squeeze(-1).tolist() == [4]


def test_nstep_rejects_bad_input():
    with pytest.raises(ValueError, match="n_steps"):
        NStepStateTransform(0)
    with pytest.raises(KeyError, match="next"):
        NStepStateTransform(2)._inv_call(TensorDict(observation=torch.zeros(3, 1), batch_size=[3]))


def test_example_buffer_stores_states_samples_them_and_round_trips():
    buffer = InitialStateBuffer(max_size=10)
    with pytest.raises(RuntimeError, match="empty"):
        buffer.sample(2)
    buffer.add(TensorDict(observation=torch.zeros(2), other=torch.ones(1)))
    buffer.add(TensorDict(observation=torch.ones(3, 2), batch_size=[3]))
    assert len(buffer) == 4
    sample = buffer.sample(32)
    assert set(sample.keys()) == {"observation", "index"} and sample.shape == (32,)
    # slot 0 holds the zero state, slots 1-3 the ones: each sampled row matches its slot
    assert sample["index"].dtype == torch.int64
    assert ((sample["index"] >= 0) & (sample["index"] <= 3)).all()
    assert torch.equal(sample["observation"][:, 0], (sample["index"] > 0).float())
    copy = InitialStateBuffer(max_size=10)
    copy.load_state_dict(buffer.state_dict())
    assert len(copy) == 4
    with pytest.raises(KeyError, match="observation"):
        buffer.add(TensorDict(state=torch.zeros(2)))
    with pytest.raises(ValueError, match="max_size"):
        InitialStateBuffer(max_size=0)


# ---------------------------------------------------------------------------------------------- episode windows
def _episodes(lengths, first_id=0, t0=0):
    """Consecutive episodes of the given lengths: observation t (time), next observation t + 1."""
    traj = torch.cat([torch.full((n,), first_id + i) for i, n in enumerate(lengths)])
    t = torch.arange(t0, t0 + len(traj), dtype=torch.float32).unsqueeze(-1)
    done = torch.zeros(len(traj), 1, dtype=torch.bool)
    done[torch.tensor(lengths).cumsum(0) - 1] = True
    return TensorDict({"observation": t, ("next", "observation"): t + 1, ("next", "done"): done,
                       ("collector", "traj_ids"): traj}, batch_size=[len(traj)])


def test_episode_window_sampler_picks_episodes_uniformly_then_a_whole_window_inside():
    from torchrl_reset import EpisodeWindowSampler

    torch.manual_seed(0)
    n = 10
    # episodes of 12, 30 and 7 transitions: 3 and 21 admissible starts; the 7-step one is never drawn
    rb = ReplayBuffer(storage=LazyTensorStorage(100), sampler=EpisodeWindowSampler(n), batch_size=20000,
                      transform=NStepStateTransform(n))
    rb.extend(_episodes([12, 30, 7]))
    sample = rb.sample()
    t = sample["observation"].squeeze(-1).long()
    # the window is whole: s_{t+n} is exactly n steps later
    torch.testing.assert_close(sample["nstep", "observation"].squeeze(-1), (t + n).float())
    assert set(t.tolist()) == set(range(0, 3)) | set(range(12, 33))
    # episodes first: each of the two admissible episodes gets half the rows, whatever its length
    share_first = (t < 12).float().mean().item()
    assert share_first == pytest.approx(0.5, abs=0.015)
    # within an episode the start is uniform: 1/3 of the first episode's rows each
    counts = torch.bincount(t[t < 3], minlength=3).float() / (t < 3).sum()
    torch.testing.assert_close(counts, torch.full((3,), 1 / 3), atol=0.02, rtol=0)


def test_episode_window_sampler_falls_back_to_uniform_rows_and_follows_overwrites():
    from torchrl_reset import EpisodeWindowSampler

    torch.manual_seed(1)
    sampler = EpisodeWindowSampler(5)
    rb = ReplayBuffer(storage=LazyTensorStorage(10), sampler=sampler, batch_size=500)
    rb.extend(_episodes([3, 4]))  # no episode has 5 transitions yet
    assert set(rb.sample()["observation"].squeeze(-1).long().tolist()) == set(range(7))
    assert sampler.fallbacks == 1
    # 6 more rows overwrite 3 of the 10 slots: the first episode is gone, the second keeps t = 3..6,
    # and the new 6-row episode (t = 7..12) wraps around the storage's end
    rb.extend(_episodes([6], first_id=2, t0=7))
    starts = set(rb.sample()["observation"].squeeze(-1).long().tolist())
    assert starts == {7, 8} and sampler.fallbacks == 1
    # one at a time, as the recipe writes: the same episodes
    again = EpisodeWindowSampler(5)
    rb2 = ReplayBuffer(storage=LazyTensorStorage(10), sampler=again, batch_size=500)
    for row in torch.cat([_episodes([3, 4]), _episodes([6], first_id=2, t0=7)]).split(1):
        rb2.extend(row)
    assert set(rb2.sample()["observation"].squeeze(-1).long().tolist()) == {7, 8}
    for key in ("traj", "start", "length", "rows"):
        assert again.state_dict()[key] == sampler.state_dict()[key]
    # slots 3-6 (t = 3..6) and 7, 8, 9, 0, 1, 2 (t = 7..12)
    assert sampler.state_dict()["start"] == [3, 7] and sampler.state_dict()["length"] == [4, 6]


def test_episode_window_sampler_survives_dumps_and_loads(tmp_path):
    from torchrl_reset import EpisodeWindowSampler

    rb = ReplayBuffer(storage=LazyTensorStorage(50), sampler=EpisodeWindowSampler(4), batch_size=8)
    rb.extend(_episodes([5, 9, 2]))
    rb.sample()
    rb.extend(_episodes([6], first_id=3, t0=16))
    rb.dumps(tmp_path / "rb")
    fresh = ReplayBuffer(storage=LazyTensorStorage(50), sampler=EpisodeWindowSampler(4), batch_size=8)
    fresh.loads(tmp_path / "rb")
    torch.manual_seed(3)
    a = rb.sample()["observation"]
    torch.manual_seed(3)
    b = fresh.sample()["observation"]
    torch.testing.assert_close(a, b)
    assert set(a.squeeze(-1).long().tolist()) <= {0, 1, 5, 6, 7, 8, 9, 10, 16, 17, 18}


def test_a_buffer_saved_with_another_sampler_loads_into_episode_windows(tmp_path):
    from torchrl.data import RandomSampler

    from torchrl_reset import EpisodeWindowSampler

    old = ReplayBuffer(storage=LazyTensorStorage(50), sampler=RandomSampler(), batch_size=500)
    old.extend(_episodes([5, 9, 2]))
    old.dumps(tmp_path / "rb")
    sampler = EpisodeWindowSampler(4)
    fresh = ReplayBuffer(storage=LazyTensorStorage(50), sampler=sampler, batch_size=500)
    with pytest.warns(UserWarning, match="rebuilding"):
        fresh.loads(tmp_path / "rb")
    # the episodes of 5 and 9 rows give starts 0-1 and 5-10; the 2-row one none
    assert set(fresh.sample()["observation"].squeeze(-1).long().tolist()) == {0, 1, 5, 6, 7, 8, 9, 10}
    assert sampler.state_dict()["length"] == [5, 9, 2]
