"""What the dual collector finds in its env and asks of it: the reset triggers among its transforms, the time
limits and terminations it must not have of its own, the keys an event copies, and the loop's set-up."""
from __future__ import annotations

from collections.abc import Iterator

from tensordict import TensorDictBase
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.transforms import Compose, StepCounter

from ._validation import check_int, is_int_at_least
from .trigger import ResetTriggerTransform

__all__ = ["find_trigger_transforms", "own_time_limit", "truncation_warning", "termination_warning", "set_up_loop",
           "check_event_keys", "stopped_scores", "check_state_keys"]


def private_keys(td: TensorDictBase) -> list[str]:
    """The root entries whose names start with ``_``: state a module keeps in the tensordict (exploration noise)."""
    return [k for k in td.keys() if isinstance(k, str) and k.startswith("_")]


def find_trigger_transforms(env: EnvBase) -> list[ResetTriggerTransform]:
    """Every :class:`ResetTriggerTransform` inside ``env`` (nested transformed envs and Compose included)."""
    found: list[ResetTriggerTransform] = []

    def visit_transform(transform) -> None:
        if isinstance(transform, ResetTriggerTransform):
            found.append(transform)
        elif isinstance(transform, Compose):
            for t in transform.transforms:
                visit_transform(t)

    while isinstance(env, TransformedEnv):
        visit_transform(env.transform)
        env = env.base_env
    return found


def _transforms(env: EnvBase) -> Iterator:
    """Every transform inside ``env``, outermost env first (nested transformed envs and Compose included)."""

    def visit(transform):
        if isinstance(transform, Compose):
            for t in transform.transforms:
                yield from visit(t)
        else:
            yield transform

    while isinstance(env, TransformedEnv):
        yield from visit(env.transform)
        env = env.base_env


def own_time_limit(env: EnvBase) -> str | None:
    """The time limit inside ``env`` that would end episodes behind a reset-free loop's back, described
    (a torchrl ``StepCounter(max_steps=...)``, or gymnasium's ``TimeLimit`` under a torchrl ``GymWrapper``
    or ``GymEnv``), or None (docs/environment-contract.md)."""
    for transform in _transforms(env):
        if isinstance(transform, StepCounter) and transform.max_steps is not None:
            return f"StepCounter(max_steps={transform.max_steps})"
    while isinstance(env, TransformedEnv):
        env = env.base_env
    layer = getattr(env, "_env", None)  # the gymnasium env inside a torchrl GymWrapper
    for _ in range(100):  # a gymnasium wrapper stack, outermost first
        if layer is None:
            return None
        if type(layer).__name__ == "TimeLimit":
            return f"gymnasium's TimeLimit of {getattr(layer, '_max_episode_steps', '?')} steps"
        layer = getattr(layer, "env", None)
    return None


def truncation_warning(env_name: str, what: str) -> str:
    """The warning for an env that ends episodes by itself (a time limit): what it costs and the fix."""
    return (
        f"{env_name} ends episodes by itself: {what}. DualCollector owns the episode lengths (H_f, H_r) and never "
        "resets for free, so it carries on from that state, but the step keeps its ('next', 'truncated') / "
        "('next', 'done') flags and the replay buffers see an episode end there (NStepStateTransform cuts its "
        "n-step windows at it); a gymnasium TimeLimit then truncates every step after its limit since the last "
        "env.reset(). Remove the env's time limit: GymEnv(name, max_episode_steps=-1) or "
        "gymnasium.make(name, max_episode_steps=-1), a StepCounter without max_steps. "
        "See docs/environment-contract.md. (Warned once per collector.)"
    )


def termination_warning(env_name: str, what: str) -> str:
    """The warning for an env that terminates episodes by itself: what it costs and the fix."""
    return (
        f"{env_name} terminated an episode by itself: {what}. DualCollector ends such an episode with a manual "
        "reset (env.reset(), counted under counters['terminations']) instead of a reset episode: the reset agent "
        "does not act after it, and if every forward episode ends this way the reset agent never acts and "
        "never learns. Unless the termination is a safety stop that must end the episode, remove it and report "
        "such states in an observation entry instead (for instance 'irrecoverable'): the trigger and the reset "
        "agent are there to handle them. See docs/environment-contract.md. (Warned once per collector.)"
    )


def set_up_loop(collector, create_env_fn, forward_policy, reset_policy, *, max_forward_steps, max_reset_steps,
                min_reset_steps, total_frames, max_events, trigger_key, reset_success_key, init_key,
                exploration_type, event_keys=()) -> EnvBase:
    """Checks and sets what every Algorithm 1 collector holds: H_f, H_r, the minimum reset length, the
    frame budget, the env, both policies, the triggers and the keys. Returns the env."""
    collector.max_forward_steps = check_int("max_forward_steps (H_f)", max_forward_steps)
    if max_reset_steps is None:
        max_reset_steps = 2 * max_forward_steps
    collector.max_reset_steps = check_int("max_reset_steps (H_r)", max_reset_steps)
    collector.min_reset_steps = check_int("min_reset_steps", min_reset_steps, minimum=0)
    if collector.min_reset_steps > collector.max_reset_steps:
        raise ValueError(
            f"min_reset_steps ({min_reset_steps}) exceeds max_reset_steps (H_r = {max_reset_steps}): "
            "no reset episode could ever succeed."
        )
    if total_frames != -1 and not is_int_at_least(total_frames, 1):
        raise ValueError(f"total_frames must be a positive integer or -1, got {total_frames!r}.")
    collector.total_frames = total_frames
    collector.max_events = check_int("max_events", max_events)
    env = create_env_fn if isinstance(create_env_fn, EnvBase) else create_env_fn()
    if not isinstance(env, EnvBase):
        raise TypeError(f"create_env_fn must be an EnvBase or return one, got {type(env).__name__}.")
    for name, policy in (("forward_policy", forward_policy), ("reset_policy", reset_policy)):
        if not callable(policy):
            raise TypeError(f"{name} must be callable on a tensordict, got {type(policy).__name__}.")
    collector.env, collector.forward_policy, collector.reset_policy = env, forward_policy, reset_policy
    collector.triggers = find_trigger_transforms(env)
    if trigger_key is None:
        keys = {t.trigger_key for t in collector.triggers} or {"reset_trigger"}
        if len(keys) > 1:
            raise ValueError(f"the env's trigger transforms write different keys {keys}; pass trigger_key.")
        trigger_key = keys.pop()
    if reset_success_key is None:
        raise ValueError("reset_success_key is required: the env's at-initial-state flag ends reset episodes.")
    collector.trigger_key, collector.reset_success_key, collector.init_key = trigger_key, reset_success_key, init_key
    collector.exploration_type = exploration_type
    collector.event_keys = check_event_keys(env, event_keys)
    return env


def check_event_keys(env: EnvBase, event_keys) -> list:
    """``event_keys`` as a list, each an entry of the env's observation spec (else a ValueError naming them)."""
    event_keys = [event_keys] if isinstance(event_keys, str) else list(event_keys)
    observed = set(env.full_observation_spec.keys(True, True))
    missing = [key for key in event_keys if key not in observed]
    if missing:
        raise ValueError(f"event_keys {missing} are not entries of the env's observation spec "
                         f"(it has {sorted(map(str, observed))}); an episode record can only copy what the env observes.")
    return event_keys


def stopped_scores(triggers, scored: TensorDictBase) -> list[float]:
    """The triggers' scores of the action they stopped (or scored after H_f), from the tensordict they scored."""
    return [float(scored.get(t.score_key).reshape(-1)[0]) for t in triggers if scored.get(t.score_key, None) is not None]


def check_state_keys(state_dict) -> None:
    """Raises unless ``state_dict`` has the entries of :meth:`DualCollector.state_dict` a load needs."""
    missing = {"counters", "phase", "phase_steps", "traj_id", "frames", "td", "example_buffer"} - set(state_dict)
    if missing:
        raise KeyError(f"not a DualCollector state_dict: missing {sorted(missing)}.")


def state_owner(env: EnvBase):
    """The innermost env (or wrapper) offering ``get_simulator_state`` / ``set_simulator_state``, if any."""
    while True:
        if callable(getattr(env, "get_simulator_state", None)) and callable(getattr(env, "set_simulator_state", None)):
            return env
        if not isinstance(env, TransformedEnv):
            return None
        env = env.base_env
