"""BatchedDualCollector: N copies in their own phases, each exactly as DualCollector runs it alone.

The policies and the trigger's model are elementwise functions of the observation (no matrix
products), so a row computed in a batch of N and the same row computed alone are the same float
numbers: the batched copies must reproduce the single collectors bit for bit. Each copy gets its own
gains, so the copies fall out of step (different phases at the same iteration) and, between them,
end episodes in every way Algorithm 1 has: trigger, H_f (requested), success and manual reset.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.envs import TransformedEnv

from torchrl_reset import DualCollector, InitialStateBuffer
from torchrl_reset.many import BatchedDualCollector, RowResetTriggerTransform, split_phases
from torchrl_reset_envs import BatchedTaskEnv, make_env

TASK = "peg_insertion_insert"
SEEDS = [0, 1, 2]
HORIZONS = dict(max_forward_steps=20, max_reset_steps=15, min_reset_steps=3)
FORWARD_GAIN = torch.tensor([[0.3], [0.6], [1.0]])  # copy i's forward policy scale
RESET_GAIN = torch.tensor([[1.0], [2.5], [5.0]])  # copy i's reset controller gain (weak gains fail: manual resets)
KEYS = ["observation", "action", ("next", "observation"), ("next", "done"), ("next", "truncated"), ("collector", "phase"),
        ("collector", "traj_ids")]


@pytest.fixture(scope="module")
def start_joints():
    return make_env(TASK, seed=0).reset()["observation"][:7].clone()


def forward_policy(gain):
    return TensorDictModule(lambda obs: gain * torch.sin(3 * obs[..., :7] + 1.0), in_keys=["observation"], out_keys=["action"])


def reset_policy(gain, q0):
    # a PD controller back to the start joints: strong gains come back within H_r, weak ones do not
    return TensorDictModule(lambda obs: (-gain * (obs[..., :7] - q0) - 0.5 * obs[..., 7:14]).clamp(-1, 1),
                            in_keys=["observation"], out_keys=["action"])


def trigger(smoothing=0.0):
    def logits(obs, act):  # two members, elementwise: the same numbers in a batch and alone
        z = 3 * obs[..., 2:3] + 1.5 * act[..., 0:1] + 0.5
        return torch.cat([z - 0.5, z + 0.3], -1)

    model = TensorDictModule(logits, in_keys=["observation", "action"], out_keys=["logits"])
    return RowResetTriggerTransform(model, 0.3, smoothing=smoothing)


class Noisy:
    """A policy plus noise from each copy's own generator, drawn for the rows it acts for only (the
    ``"_acting"`` mask; alone, its one row): each copy's forward and reset policies share one generator,
    so a copy matches its single collector only if it draws in the single collector's order (the action
    after H_f included)."""

    def __init__(self, policy, generators):
        self.policy, self.generators = policy, generators

    def __call__(self, td):
        td = self.policy(td)
        action = td.get("action")
        acting = td.get("_acting", None)
        if acting is None:
            noise = torch.randn(action.shape, generator=self.generators[0])
        else:
            noise = torch.zeros_like(action)
            for i in acting.nonzero().flatten().tolist():
                noise[i] = torch.randn(action.shape[-1], generator=self.generators[i])
        td.set("action", (action + 0.2 * noise).clamp(-1, 1))
        return td


def generators(copies):
    return [torch.Generator().manual_seed(100 + i) for i in copies]


def single_collector(i, q0, steps, smoothing=0.0, noisy=False):
    env = make_env(TASK, seed=SEEDS[i])
    env.append_transform(trigger(smoothing))
    fwd, rst = forward_policy(FORWARD_GAIN[i]), reset_policy(RESET_GAIN[i], q0)
    if noisy:
        gens = generators([i])
        fwd, rst = Noisy(fwd, gens), Noisy(rst, gens)
    return DualCollector(env, fwd, rst, total_frames=steps, **HORIZONS)


def single_runs(q0, steps, smoothing=0.0, noisy=False):
    runs = []
    for i in range(len(SEEDS)):
        collector = single_collector(i, q0, steps, smoothing, noisy)
        trace = torch.cat([batch.select(*KEYS).clone() for batch in collector])
        runs.append((collector, trace))
    return runs


def batched(q0, steps, smoothing=0.0, noisy=False, **kwargs):
    env = TransformedEnv(BatchedTaskEnv(TASK, seeds=SEEDS), trigger(smoothing))
    fwd, rst = forward_policy(FORWARD_GAIN), reset_policy(RESET_GAIN, q0)
    if noisy:
        gens = generators(range(len(SEEDS)))
        fwd, rst = Noisy(fwd, gens), Noisy(rst, gens)
    return BatchedDualCollector(env, fwd, rst, max_frames_per_env=steps, **HORIZONS, **kwargs)


def events(collector):
    return [(e["outcome"], e["phase"], e["steps"], e["frame"], e.get("scores"), e["state"]["observation"].tolist())
            for e in collector.pop_events()]


def per_copy(batches):
    rows = {i: [] for i in range(len(SEEDS))}
    for batch in batches:
        for i in rows:
            mine = batch["collector", "env_ids"] == i
            if mine.any():
                rows[i].append(batch[mine].select(*KEYS))
    return {i: torch.cat(r) for i, r in rows.items()}


@pytest.mark.parametrize("smoothing,noisy", [(0.0, False), (0.5, False), (0.0, True)])
def test_each_copy_is_the_single_collector(start_joints, smoothing, noisy):
    steps = 600
    singles = single_runs(start_joints, steps, smoothing, noisy)
    collector = batched(start_joints, steps, smoothing, noisy)
    mixed = 0
    batches = []
    for batch in collector:
        mixed += len(set(collector.phases)) > 1
        batches.append(batch)
    traces = per_copy(batches)
    assert mixed > 100  # the copies are in different phases for much of the run
    for i, (alone, trace) in enumerate(singles):
        assert collector.env_metrics()[i] == pytest.approx(alone.metrics(), nan_ok=True)
        for key in KEYS:
            assert torch.equal(traces[i].get(key), trace.get(key)), (i, key)
        assert torch.equal(collector.example_buffers[i].states()["observation"], alone.example_buffer.states()["observation"])
        copy = collector.view(i)
        assert copy.counters == alone.counters and copy.frames == alone.frames
        assert events(copy) == events(alone)  # outcomes, steps, frames, the stopped actions' scores, states
    total = collector.metrics()
    outcomes = ("triggered_resets", "successful_resets") if smoothing else (
        "triggered_resets", "requested_resets", "successful_resets", "manual_resets")
    for outcome in outcomes:  # without smoothing, every way an episode ends was exercised
        assert total[outcome] > 0, outcome
    assert collector.frames == steps * len(SEEDS)
    assert all(m["forward_steps"] + m["reset_steps"] == steps for m in collector.env_metrics())


def test_a_triggered_copy_is_not_stepped_while_the_others_are(start_joints):
    collector = batched(start_joints, 200)
    seen = 0
    previous = None
    for batch in collector:
        if previous is not None:
            stepped = set(batch["collector", "env_ids"].tolist())
            skipped = [i for i in range(3) if i not in stepped]
            for i in skipped:  # a copy that executed nothing kept its simulator state
                assert torch.equal(collector._td["observation"][i], previous[i])
                seen += 1
        previous = collector._td["observation"].clone()
    assert seen > 0


def test_shared_mode_one_example_buffer_and_unique_episodes(start_joints):
    collector = batched(start_joints, 300, shared_examples=True, event_keys=["irrecoverable"])
    ids = {}
    for batch in collector:
        for env, traj in zip(batch["collector", "env_ids"].tolist(), batch["collector", "traj_ids"].tolist()):
            assert ids.setdefault(traj, env) == env  # an episode id belongs to one copy
        phases = split_phases(batch)
        assert sum(td.shape[0] for td in phases.values()) == batch.shape[0]
    assert len(collector.example_buffers) == 1
    total = collector.metrics()
    # one example per forward episode started: the N first states plus one per ended reset episode
    assert len(collector.example_buffers[0]) == len(SEEDS) + total["reset_episodes"] + total["terminations"]
    # each record copies the env's flag (peg-insertion has no irrecoverable state: always False)
    records = collector.pop_events()
    assert len(records) == total["forward_episodes"] + total["reset_episodes"]
    assert all(set(e["state"].keys()) == {"observation", "irrecoverable"} for e in records)
    assert not any(bool(e["state"]["irrecoverable"]) for e in records)


def test_resume_continues_exactly(start_joints):
    whole = per_copy(list(batched(start_joints, 400)))
    first = batched(start_joints, 400)
    iterator = iter(first)
    head = [next(iterator) for _ in range(150)]
    state = first.state_dict()
    resumed = batched(start_joints, 400)
    resumed.load_state_dict(state)
    tail = list(resumed)
    again = per_copy(head + tail)
    for i in whole:
        for key in KEYS:
            assert torch.equal(whole[i].get(key), again[i].get(key))
    assert resumed.env_metrics() == batched_metrics(start_joints, 400)


@pytest.mark.parametrize("smoothing", [0.0, 0.5])
def test_a_copy_continues_a_single_collector_and_the_other_way_round(start_joints, smoothing):
    """A copy's state is a single collector's state_dict (and back): a run saved alone continues in a
    batch, a run saved in a batch continues alone, each exactly as the uninterrupted single run."""
    steps, cut = 400, 170
    whole = single_runs(start_joints, steps, smoothing, noisy=True)
    heads, states = [], []
    for i in range(len(SEEDS)):
        alone = single_collector(i, start_joints, steps, smoothing, noisy=True)
        it = iter(alone)
        heads.append(torch.cat([next(it).select(*KEYS).clone() for _ in range(cut)]))
        states.append((alone.state_dict(), alone.forward_policy.generators[0].get_state()))
    collector = batched(start_joints, steps, smoothing, noisy=True)
    for i, (state, gen) in enumerate(states):
        collector.view(i).load_state_dict(state)
        collector.forward_policy.generators[i].set_state(gen)
    assert collector.view(1).frames == cut and collector.frames == cut * len(SEEDS)
    it = iter(collector)
    middle = per_copy([next(it) for _ in range(60)])
    back = []
    for i in range(len(SEEDS)):  # and back: each copy's state continues in a single collector
        alone = single_collector(i, start_joints, steps, smoothing, noisy=True)
        alone.load_state_dict(collector.view(i).state_dict())
        alone.forward_policy.generators[0].set_state(collector.forward_policy.generators[i].get_state())
        back.append(torch.cat([batch.select(*KEYS).clone() for batch in alone]))
        assert alone.counters == whole[i][0].counters
    for i, (_, trace) in enumerate(whole):
        again = torch.cat([heads[i], middle[i], back[i]])
        for key in KEYS:
            assert torch.equal(again.get(key), trace.get(key)), (i, key)
    with pytest.raises(RuntimeError, match="before the batch's first iteration"):
        collector.view(0).load_state_dict(states[0][0])
    with pytest.raises(ValueError, match="shared"):
        batched(start_joints, 10, shared_examples=True).view(0)


def batched_metrics(q0, steps):
    collector = batched(q0, steps)
    for _ in collector:
        pass
    return collector.env_metrics()


def test_bad_inputs(start_joints):
    with pytest.raises(ValueError, match=r"batch size \[N\]"):
        BatchedDualCollector(make_env(TASK), forward_policy(1.0), reset_policy(1.0, start_joints), max_forward_steps=5)
    env = BatchedTaskEnv(TASK, seeds=SEEDS)
    with pytest.raises(ValueError, match="one per copy"):
        BatchedDualCollector(env, forward_policy(1.0), reset_policy(1.0, start_joints), max_forward_steps=5,
                             example_buffers=[InitialStateBuffer(), InitialStateBuffer()])
    with pytest.raises(ValueError, match="'ditch'.*observation spec"):
        BatchedDualCollector(env, forward_policy(1.0), reset_policy(1.0, start_joints), max_forward_steps=5,
                             event_keys=["ditch"])
    with pytest.raises(ValueError, match="num_envs"):
        BatchedTaskEnv(TASK, num_envs=2, seeds=SEEDS)
    with pytest.raises(ValueError, match="robot"):
        BatchedTaskEnv("ur3_peg", num_envs=2)


def test_trigger_rows_off_never_fire_and_restart_their_smoothing():
    model = TensorDictModule(lambda obs, act: obs[..., :2] * 0 - 10.0, in_keys=["observation", "action"], out_keys=["logits"])
    t = RowResetTriggerTransform(model, 0.3, smoothing=0.5)
    td = __import__("tensordict").TensorDict({"observation": torch.zeros(3, 2), "action": torch.zeros(3, 1)}, batch_size=[3])
    t.set_enabled(torch.tensor([True, False, True]))
    fired = t.score_step(td.clone())
    assert fired.tolist() == [True, False, True]  # logit -10: C ~ 0, p ~ 0 < 0.3, but row 1 is off
    scored = td.clone()
    t.score_step(scored)
    assert np.isnan(scored["success_probability"][1].item())
    # row 0 restarts: its smoothing state is dropped, row 2 keeps its own
    t.set_enabled(torch.tensor([True, False, True]), restart=torch.tensor([True, False, False]))
    assert np.isnan(t.smoothed[0].item()) and not np.isnan(t.smoothed[2].item())
    with pytest.raises(TypeError, match="boolean mask"):
        t.set_enabled(torch.ones(3))


def test_the_pooled_view_is_one_run_over_the_copies_and_ends_with_the_iteration_that_reaches_the_budget(start_joints):
    collector = batched(start_joints, None, shared_examples=True, total_frames=301)
    view = collector.pooled()
    stepped = 0
    for batch in view:
        stepped += batch.shape[0]
        for event in view.pop_events():  # the run's step count when the episode ended, not the copy's
            assert event["frame"] == collector.frames
    # the iteration that reaches 301 is completed: at most 3 - 1 steps past it
    assert stepped == collector.frames == view.frames and 301 <= stepped <= 303
    copies = collector.env_metrics()
    assert view.counters == {k: sum(m[k] for m in copies) for k in view.counters}
    assert view.forward_share == view.counters["forward_steps"] / stepped
    assert view.example_buffer is collector.example_buffers[0]
    with pytest.raises(ValueError, match="independent runs"):
        batched(start_joints, 10).pooled()


class Drifting(Noisy):
    """A policy plus a noise process kept in the root tensordict, as torchrl's Ornstein-Uhlenbeck module
    keeps its own (``_drift`` and ``_drift_steps``; zeros when absent, and where ``is_init`` holds):
    ``x <- 0.7 x + 0.3 e`` with ``e`` from the copy's generator, the action moved by ``x / (1 + steps / 50)``.
    Each copy's forward and reset policies share one generator but have their own process, so a copy
    matches its single collector only if each phase's process continues where that phase left it."""

    def __call__(self, td):
        td = self.policy(td)
        action = td.get("action")
        acting = td.get("_acting", None)
        batch = action.unsqueeze(0) if acting is None else action
        prev = td.get("_drift", torch.zeros_like(action)).reshape(batch.shape).clone()
        steps = td.get("_drift_steps", torch.zeros(*action.shape[:-1], 1, dtype=torch.long)).reshape(-1, 1).clone()
        init = td.get("is_init", None)
        if init is not None:
            init = init.reshape(-1, 1)
            prev, steps = torch.where(init, 0.0, prev), torch.where(init, 0, steps)
        rows = [0] if acting is None else acting.nonzero().flatten().tolist()
        moved = batch.clone()
        for j, i in enumerate(rows):
            prev[i] = 0.7 * prev[i] + 0.3 * torch.randn(batch.shape[-1], generator=self.generators[j if acting is None else i])
            moved[i] = (batch[i] + prev[i] / (1 + steps[i] / 50)).clamp(-1, 1)
            steps[i] += 1
        td.set("action", moved.reshape(action.shape))
        td.set("_drift", prev.reshape(action.shape))
        td.set("_drift_steps", steps.reshape(*action.shape[:-1], 1))
        return td


def drifting_single(i, q0, steps, restart):
    env = make_env(TASK, seed=SEEDS[i])
    env.append_transform(trigger())
    gens = generators([i])
    return DualCollector(env, Drifting(forward_policy(FORWARD_GAIN[i]), gens),
                         Drifting(reset_policy(RESET_GAIN[i], q0), gens), total_frames=steps,
                         restart_exploration=restart, **HORIZONS)


def drifting_batched(q0, steps, restart):
    env = TransformedEnv(BatchedTaskEnv(TASK, seeds=SEEDS), trigger())
    gens = generators(range(len(SEEDS)))
    return BatchedDualCollector(env, Drifting(forward_policy(FORWARD_GAIN), gens),
                                Drifting(reset_policy(RESET_GAIN, q0), gens), max_frames_per_env=steps,
                                restart_exploration=restart, **HORIZONS)


def test_each_copy_continues_its_own_noise_per_phase_as_a_single_collector_does(start_joints):
    """restart_exploration=False: a copy's forward episode continues its forward noise, its reset episode its
    reset noise, as DualCollector(restart_exploration=False) does alone; and a copy's state (its noise
    included) continues in a single collector and the other way round."""
    steps, cut = 500, 170
    singles = []
    for i in range(len(SEEDS)):
        alone = drifting_single(i, start_joints, steps, restart=False)
        singles.append(torch.cat([batch.select(*KEYS).clone() for batch in alone]))
    restarted = torch.cat([b.select(*KEYS).clone() for b in drifting_single(0, start_joints, steps, restart=True)])
    assert not torch.equal(restarted["action"], singles[0]["action"])  # the two settings act differently
    collector = drifting_batched(start_joints, steps, restart=False)
    traces = per_copy(list(collector))
    for i, trace in enumerate(singles):
        for key in KEYS:
            assert torch.equal(traces[i].get(key), trace.get(key)), (i, key)
    assert collector.env_metrics()[0]["reset_episodes"] > 3  # the processes were carried over several switches

    # a single run saved at `cut` continues in the batch; the batch's copy then continues alone
    collector = drifting_batched(start_joints, steps, restart=False)
    heads = []
    for i in range(len(SEEDS)):
        alone = drifting_single(i, start_joints, steps, restart=False)
        it = iter(alone)
        heads.append(torch.cat([next(it).select(*KEYS).clone() for _ in range(cut)]))
        saved = alone.state_dict()["exploration"]
        assert saved["reset"] and saved["forward"]  # both phases have acted by then
        collector.view(i).load_state_dict(alone.state_dict())
        kept = collector.view(i).state_dict()["exploration"]  # read back before the batch moves
        assert {p: sorted(v) for p, v in kept.items()} == {p: sorted(v) for p, v in saved.items()}
        assert all(torch.equal(kept[p][k], saved[p][k]) for p in saved for k in saved[p])
        collector.forward_policy.generators[i].set_state(alone.forward_policy.generators[0].get_state())
    it = iter(collector)
    middle = per_copy([next(it) for _ in range(80)])
    for i in range(len(SEEDS)):
        alone = drifting_single(i, start_joints, steps, restart=False)
        alone.load_state_dict(collector.view(i).state_dict())
        alone.forward_policy.generators[0].set_state(collector.forward_policy.generators[i].get_state())
        tail = torch.cat([batch.select(*KEYS).clone() for batch in alone])
        again = torch.cat([heads[i], middle[i], tail])
        for key in KEYS:
            assert torch.equal(again.get(key), singles[i].get(key)), (i, key)

    # the batch's own state_dict resumes it exactly, the noise kept per copy and phase included
    first = drifting_batched(start_joints, steps, restart=False)
    it = iter(first)
    head = [next(it) for _ in range(150)]
    resumed = drifting_batched(start_joints, steps, restart=False)
    resumed.load_state_dict(first.state_dict())
    for i, gen in enumerate(first.forward_policy.generators):
        resumed.forward_policy.generators[i].set_state(gen.get_state())
    again = per_copy(head + list(resumed))
    for i, trace in enumerate(singles):
        assert torch.equal(again[i]["action"], trace["action"]), i
    with pytest.raises(TypeError, match="restart_exploration must be a bool"):
        BatchedDualCollector(BatchedTaskEnv(TASK, seeds=SEEDS), forward_policy(1.0), reset_policy(1.0, start_joints),
                             max_forward_steps=5, restart_exploration="never")
