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
