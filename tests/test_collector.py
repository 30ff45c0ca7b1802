"""DualCollector: Algorithm 1 over tensordicts, its counters, its example buffer and its state."""
from __future__ import annotations

import io

import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import TransformedEnv
from torchrl.modules import OrnsteinUhlenbeckProcessModule

from torchrl_reset import DualCollector, ResetTriggerTransform
from torchrl_reset_envs import ChainEnv


class CountingChain(ChainEnv):
    """ChainEnv that counts env.reset() calls."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.resets = 0

    def _reset(self, tensordict=None, **kwargs):
        self.resets += 1
        return super()._reset(tensordict, **kwargs)


def constant_policy(value):
    return TensorDictModule(lambda obs: torch.full((*obs.shape[:-1], 1), value), in_keys=["observation"], out_keys=["action"])


RIGHT, LEFT = constant_policy(1.0), constant_policy(-1.0)


def collect(collector):
    return [batch for batch in collector]


def cell(observation):
    return int(observation.argmax())


def test_reset_episodes_start_where_forward_episodes_end_without_hidden_resets():
    env = CountingChain(num_states=10)
    collector = DualCollector(env, RIGHT, LEFT, max_forward_steps=3, min_reset_steps=1, total_frames=30)
    batches = collect(collector)
    assert env.resets == 1  # only the first one: every reset episode succeeded
    steps = torch.cat(batches)
    phases = steps["collector", "phase"].tolist()
    # F F F R R R F F F R R R ...: each reset episode walks back the 3 cells the forward one walked
    assert phases == ([0] * 3 + [1] * 3) * 5
    for t in range(1, len(steps)):
        # the state never jumps: each step starts where the previous one ended
        assert torch.equal(steps[t]["observation"], steps[t - 1]["next", "observation"])
    assert collector.counters["successful_resets"] == 5 and collector.counters["manual_resets"] == 0


def test_manual_reset_only_after_max_reset_steps_failed_steps():
    env = CountingChain(num_states=10, ditch=4)  # the forward policy walks into the ditch
    h_f, h_r = 6, 5
    collector = DualCollector(env, RIGHT, LEFT, max_forward_steps=h_f, max_reset_steps=h_r, total_frames=3 * (h_f + h_r))
    steps = torch.cat(collect(collector))
    assert collector.counters["manual_resets"] == 3
    assert env.resets == 1 + 3
    reset_ids = steps["collector", "traj_ids"][steps["collector", "phase"] == 1]
    for traj in reset_ids.unique():
        assert int((reset_ids == traj).sum()) == h_r  # every failed reset episode ran the full H_r steps
    # a manual reset puts the system back to the start: each forward episode starts in cell 0
    forward = steps[steps["collector", "phase"] == 0]
    starts = forward[forward["is_init"].squeeze(-1)]
    assert [cell(o) for o in starts["observation"]] == [0, 0, 0]


def test_success_needs_min_reset_steps():
    env = CountingChain(num_states=10)
    collector = DualCollector(env, RIGHT, LEFT, max_forward_steps=2, min_reset_steps=5, max_reset_steps=6, total_frames=14)
    steps = torch.cat(collect(collector))
    # back at cell 0 after 2 reset steps, but the episode only ends at the 5th (pushing against the wall)
    reset = steps[steps["collector", "phase"] == 1]
    assert len(reset) == 10 and collector.counters["successful_resets"] == 2
    assert collector.counters["manual_resets"] == 0 and env.resets == 1


def trigger_at(cell_index):
    """A success model that is sure below `cell_index` and hopeless from it on."""

    def logits(obs):
        cells = obs.argmax(-1, keepdim=True)
        return torch.where(cells >= cell_index, -10.0, 0.0)

    return TensorDictModule(logits, in_keys=["observation"], out_keys=["state_action_logit"])


def test_triggered_steps_are_not_executed_nor_yielded_and_are_counted():
    env = TransformedEnv(CountingChain(num_states=10), ResetTriggerTransform(trigger_at(3), 0.1))
    collector = DualCollector(env, RIGHT, LEFT, max_forward_steps=8, min_reset_steps=1, total_frames=24)
    steps = torch.cat(collect(collector))
    forward = steps[steps["collector", "phase"] == 0]
    # forward episodes stop at cell 3: the step from cell 3 fired and was dropped
    assert max(cell(o) for o in forward["observation"]) == 2
    assert max(cell(o) for o in forward["next", "observation"]) == 3
    assert not forward["next", "reset_trigger"].any()
    counters = collector.counters
    assert counters["triggered_resets"] == 4 and counters["requested_resets"] == 0
    events = [e for e in collector.pop_events() if e["outcome"] == "triggered"]
    assert len(events) == 4 and all(cell(e["state"]["observation"]) == 3 for e in events)
    # the trigger is off during reset episodes
    reset = steps[steps["collector", "phase"] == 1]
    assert torch.isnan(reset["next", "success_probability"]).all()


@pytest.mark.parametrize("trigger_cell, flag", [(4, True), (3, False)])
def test_event_keys_copy_the_envs_flag_of_the_state_each_episode_record_names(trigger_cell, flag):
    # An 8-cell chain with its ditch from cell 4; forward steps right, reset steps left, H_f = H_r = 6.
    # Trigger from cell 4: forward 0 -> 4 in 4 steps, the action from cell 4 (in the ditch) is stopped, so the
    # triggered state is already lost; the reset cannot leave the ditch and ends in a manual reset there after
    # 6 steps (10 steps a cycle). Trigger from cell 3: stopped at cell 3 (not lost), the reset walks back to 0
    # in 3 steps (6 steps a cycle).
    env = TransformedEnv(ChainEnv(num_states=8, ditch=4), ResetTriggerTransform(trigger_at(trigger_cell), 0.1))
    frames = 20 if flag else 12
    collector = DualCollector(env, RIGHT, LEFT, max_forward_steps=6, max_reset_steps=6, min_reset_steps=1,
                              total_frames=frames, event_keys=["irrecoverable"])
    collect(collector)
    events = collector.pop_events()
    reset_outcome = "manual" if flag else "success"
    assert [(e["phase"], e["outcome"]) for e in events] == [("forward", "triggered"), ("reset", reset_outcome)] * 2
    assert [cell(e["state"]["observation"]) for e in events] == ([4, 4] if flag else [3, 0]) * 2
    assert [bool(e["state"]["irrecoverable"]) for e in events] == [flag] * 4
    # without event_keys a record holds the example keys only; a key the env does not observe is refused
    plain = DualCollector(env, RIGHT, LEFT, max_forward_steps=6, min_reset_steps=1, total_frames=6)
    collect(plain)
    assert all(set(e["state"].keys()) == {"observation"} for e in plain.pop_events())
    with pytest.raises(ValueError, match="'ditch'.*observation spec"):
        DualCollector(env, RIGHT, LEFT, max_forward_steps=6, event_keys=["ditch"])


@pytest.mark.parametrize("trigger_cell, expected", [(3, "triggered"), (4, "requested")])
def test_at_the_horizon_the_trigger_is_scored_before_the_reset_is_requested(trigger_cell, expected):
    # H_f = 3 steps from cell 0 end in cell 3. Algorithm 1 then draws the next action and scores it
    # first: a trigger from cell 3 makes the episode a triggered one, else the reset is requested.
    env = TransformedEnv(CountingChain(num_states=10), ResetTriggerTransform(trigger_at(trigger_cell), 0.1))
    collector = DualCollector(env, RIGHT, LEFT, max_forward_steps=3, min_reset_steps=1, total_frames=12)
    steps = torch.cat(collect(collector))
    assert steps["collector", "phase"].tolist() == [0, 0, 0, 1, 1, 1] * 2  # the scored action is never executed
    c = collector.counters
    other = "requested" if expected == "triggered" else "triggered"
    assert c[f"{expected}_resets"] == 2 and c[f"{other}_resets"] == 0 and c["forward_episodes"] == 2
    events = [e for e in collector.pop_events() if e["phase"] == "forward"]
    assert [e["outcome"] for e in events] == [expected] * 2
    assert all(cell(e["state"]["observation"]) == 3 and e["steps"] == 3 for e in events)
    # the H_f-th step closes its episode either way
    forward = steps[steps["collector", "phase"] == 0]
    assert forward["next", "truncated"].squeeze(-1).tolist() == [False, False, True] * 2


def test_counters_and_example_buffer_match_the_yielded_transitions():
    env = TransformedEnv(CountingChain(num_states=12, ditch=9), ResetTriggerTransform(trigger_at(5), 0.1))
    policy = TensorDictModule(
        lambda obs: torch.rand(*obs.shape[:-1], 1) * 2 - 0.6, in_keys=["observation"], out_keys=["action"]
    )
    collector = DualCollector(env, policy, LEFT, max_forward_steps=7, max_reset_steps=6, min_reset_steps=2, total_frames=400)
    collector.set_seed(3)
    steps = torch.cat(collect(collector))
    c = collector.counters
    phase = steps["collector", "phase"]
    assert c["forward_steps"] == int((phase == 0).sum()) and c["reset_steps"] == int((phase == 1).sum())
    assert c["forward_steps"] + c["reset_steps"] == len(steps) == collector.frames == 400
    assert c["reset_episodes"] == c["successful_resets"] + c["manual_resets"]
    ended_forward = c["triggered_resets"] + c["requested_resets"]
    assert c["forward_episodes"] == ended_forward
    assert collector.forward_share == pytest.approx(c["forward_steps"] / 400)
    assert collector.reset_success_rate == pytest.approx(c["successful_resets"] / c["reset_episodes"])
    # one example per forward episode started: the first state, then one after every reset episode
    assert len(collector.example_buffer) == 1 + c["reset_episodes"]
    # distinct episode ids match the episodes that executed at least one step (a forward episode
    # triggered on its first action executes none), plus the episode still running at the end
    events = collector.pop_events()
    assert len(events) == c["forward_episodes"] + c["reset_episodes"]
    running = 1 if collector._phase_steps > 0 else 0
    ids = steps["collector", "traj_ids"]
    assert len(ids.unique()) == sum(1 for e in events if e["steps"] > 0) + running
    assert c["triggered_resets"] > 0 and c["requested_resets"] > 0 and c["successful_resets"] > 0


def test_is_init_marks_exactly_the_first_step_of_every_episode_and_restarts_ou_noise():
    env = ChainEnv(num_states=30)
    actor = TensorDictModule(nn.Linear(30, 1), in_keys=["observation"], out_keys=["action"])
    ou = OrnsteinUhlenbeckProcessModule(spec=env.action_spec, eps_init=1.0, eps_end=1.0, sigma=0.5)
    policy = TensorDictSequential(actor, ou)
    collector = DualCollector(env, policy, LEFT, max_forward_steps=4, min_reset_steps=1, max_reset_steps=8, total_frames=60)
    steps = torch.cat(collect(collector))
    is_init = steps["is_init"].squeeze(-1)
    ids = steps["collector", "traj_ids"]
    first_of_episode = torch.ones_like(is_init)
    first_of_episode[1:] = ids[1:] != ids[:-1]
    assert torch.equal(is_init, first_of_episode)


def test_batches_hold_one_phase_and_at_most_frames_per_batch_steps():
    collector = DualCollector(ChainEnv(num_states=10), RIGHT, LEFT, max_forward_steps=5, min_reset_steps=1,
                              frames_per_batch=3, total_frames=40)
    for batch in collector:
        assert len(batch) <= 3
        assert batch["collector", "phase"].unique().numel() == 1


def ou_policies(env):
    torch.manual_seed(123)
    f = TensorDictSequential(
        TensorDictModule(nn.Linear(env.num_states, 1), in_keys=["observation"], out_keys=["action"]),
        OrnsteinUhlenbeckProcessModule(spec=env.action_spec, eps_init=1.0, eps_end=1.0, sigma=0.6),
    )
    r = TensorDictSequential(
        TensorDictModule(nn.Linear(env.num_states, 1), in_keys=["observation"], out_keys=["action"]),
        OrnsteinUhlenbeckProcessModule(spec=env.action_spec, eps_init=1.0, eps_end=1.0, sigma=0.6),
    )
    return f, r


def make_noisy_collector(total_frames):
    env = TransformedEnv(ChainEnv(num_states=12, ditch=10), ResetTriggerTransform(trigger_at(7), 0.1, smoothing=0.3))
    f, r = ou_policies(env.base_env)
    return DualCollector(env, f, r, max_forward_steps=6, max_reset_steps=9, min_reset_steps=2, total_frames=total_frames)


def test_same_seed_gives_the_same_run():
    runs = []
    for _ in range(2):
        collector = make_noisy_collector(150)
        collector.set_seed(7)
        runs.append(torch.cat(collect(collector)))
    assert torch.equal(runs[0]["action"], runs[1]["action"])
    assert torch.equal(runs[0]["next", "observation"], runs[1]["next", "observation"])


def test_resuming_from_state_dict_continues_identically():
    reference = make_noisy_collector(200)
    reference.set_seed(11)
    batches = []
    for i, batch in enumerate(reference):
        batches.append(batch)
        if i == 99:
            buffer = io.BytesIO()
            torch.save(reference.state_dict(), buffer)
    tail = torch.cat(batches[100:])

    resumed = make_noisy_collector(200)
    buffer.seek(0)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    assert resumed.frames == 100
    continued = torch.cat(collect(resumed))
    assert torch.equal(continued["action"], tail["action"])
    assert torch.equal(continued["observation"], tail["observation"])
    assert torch.equal(continued["collector", "traj_ids"], tail["collector", "traj_ids"])
    assert resumed.counters == reference.counters
    assert len(resumed.example_buffer) == len(reference.example_buffer)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"max_forward_steps": 0}, "H_f"),
        ({"max_forward_steps": 5, "max_reset_steps": 0}, "H_r"),
        ({"max_forward_steps": 5, "max_reset_steps": 3, "min_reset_steps": 4}, "min_reset_steps"),
        ({"max_forward_steps": 5, "frames_per_batch": 0}, "frames_per_batch"),
        ({"max_forward_steps": 5, "total_frames": 0}, "total_frames"),
    ],
)
def test_bad_arguments_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        DualCollector(ChainEnv(), RIGHT, LEFT, **kwargs)


def test_batched_envs_and_missing_success_flags_are_rejected_clearly():
    from torchrl.envs import SerialEnv

    with pytest.raises(ValueError, match="unbatched"):
        DualCollector(SerialEnv(2, ChainEnv), RIGHT, LEFT, max_forward_steps=3)
    collector = DualCollector(ChainEnv(), RIGHT, LEFT, max_forward_steps=1, min_reset_steps=1, reset_success_key="at_home")
    with pytest.raises(KeyError, match="at_home"):
        collect(collector)


def counting_policy(sign: float):
    """Steps right (+1) or left (-1) and numbers its own steps in a private entry, as torchrl's
    Ornstein-Uhlenbeck module keeps its noise state (restarted where ``is_init`` holds); the step's
    number is copied to the public ``index`` entry so that the yielded batch shows it."""
    def policy(td):
        count = td.get("_count", None)
        if count is None or bool(td.get("is_init").any()):
            count = torch.zeros(1)
        td.set("_count", count + 1)
        td.set("index", count.clone())
        td.set("action", torch.full((1,), sign))
        return td
    return policy


@pytest.mark.parametrize("restart", [True, False])
def test_exploration_state_restarts_per_episode_or_goes_on_per_policy(restart):
    # two rounds of H_f = 3 steps right, then 3 steps left back to cell 0 (a successful reset each time)
    collector = DualCollector(ChainEnv(num_states=10), counting_policy(1.0), counting_policy(-1.0), max_forward_steps=3,
                              max_reset_steps=3, min_reset_steps=1, total_frames=12, restart_exploration=restart)
    steps = torch.cat([b for b in collector])
    forward = steps[steps["collector", "phase"] == 0]["index"].flatten().tolist()
    reset = steps[steps["collector", "phase"] == 1]["index"].flatten().tolist()
    assert collector.counters["successful_resets"] == 2
    if restart:  # every episode starts its policy's process anew
        assert forward == [0, 1, 2, 0, 1, 2] and reset == [0, 1, 2, 0, 1, 2]
    else:  # each policy's process goes on from its last episode, the other policy's steps in between
        assert forward == [0, 1, 2, 3, 4, 5] and reset == [0, 1, 2, 3, 4, 5]


def test_exploration_state_goes_on_across_manual_resets_and_a_saved_state():
    def make():
        return DualCollector(ChainEnv(num_states=10), counting_policy(1.0), counting_policy(-1.0), max_forward_steps=3,
                             max_reset_steps=2, min_reset_steps=1, total_frames=15, restart_exploration=False)

    whole = torch.cat(collect(make()))
    # every reset fails (2 steps from cell 3): a manual reset after each, and the forward process goes on
    assert whole["index"][whole["collector", "phase"] == 0].flatten().tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 8]
    assert whole["index"][whole["collector", "phase"] == 1].flatten().tolist() == [0, 1, 2, 3, 4, 5]
    first = make()
    first.total_frames = 7
    head = collect(first)
    buffer = io.BytesIO()
    torch.save(first.state_dict(), buffer)
    buffer.seek(0)
    second = make()
    second.load_state_dict(torch.load(buffer, weights_only=False))
    tail = collect(second)
    resumed = torch.cat(head + tail)
    assert resumed["index"].flatten().tolist() == whole["index"].flatten().tolist()
