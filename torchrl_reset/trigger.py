"""The reset trigger: stop the forward agent before an action it may not come back from.

Paper: Kim et al. (RA-L 2022), "Reset trigger mechanism"; docs/method.md section 4.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs.transforms import Transform

from .ensemble import MEMBER_REDUCTIONS, reduce_members, success_probability

__all__ = ["ResetTriggerTransform"]

SCORES = ("success_probability", "value")


class ResetTriggerTransform(Transform):
    """Triggers a reset when a success model scores the action about to be executed too low.

    Before every step, the transform evaluates ``model`` on the current observation and the action
    in the input tensordict (the noisy action the forward policy is about to execute), turns its
    per-member output into one score and compares it with ``threshold``:

    - ``score="success_probability"`` (ours): the outputs are classifier logits, each member's
      ``p_i = C_i / (1 - C_i)`` with ``C_i`` clipped to [0, 0.5], reduced over members (the paper
      uses the mean); ``threshold`` is ``p_thresh`` and must lie in (0, 1);
    - ``score="value"`` (the LNT baselines): the outputs are reduced as they are, e.g. the minimum
      of a reset Q-ensemble against ``Q_thresh``.

    When ``score < threshold`` the step is **not executed**: the base env is skipped (torchrl's
    ``"_step"`` partial-step mechanism, as used by :class:`~torchrl.envs.transforms.ConditionalSkip`),
    the next observation equals the current one, the reward is zero and the step ends as
    *truncated* (``done`` set, ``terminated`` untouched). Every step writes the score under
    ``score_key`` and a boolean ``trigger_key`` in the next tensordict.

    The skip is exact for unbatched envs (the case of :class:`~torchrl_reset.DualCollector`) and
    for batched envs that honour partial steps (torchrl's ``SerialEnv`` / ``ParallelEnv``). The
    skip covers the whole transformed env this transform belongs to, so transforms placed beside
    it (in the same :class:`~torchrl.envs.TransformedEnv`) do not run on a triggered step either.

    Args:
        model (TensorDictModuleBase): reads the observation and action, writes per-member outputs
            ``[*batch, K]`` (``[*batch]`` is read as K = 1), e.g. :class:`~torchrl_reset.EnsembleValueOperator`.
        threshold (float): the trigger fires when the score is strictly below it.

    Keyword Args:
        score (str or callable): ``"success_probability"`` (default), ``"value"``, or a callable
            mapping the model output to per-member scores.
        reduction (str or callable): ``"mean"`` (default), ``"min"``, ``"max"``, or a callable reducing
            the trailing member dimension.
        model_out_key (NestedKey): the model output read. Defaults to ``model.out_keys[0]``.
        score_key (NestedKey): where the reduced score is written. Defaults to ``"success_probability"``.
        trigger_key (NestedKey): where the trigger flag is written. Defaults to ``"reset_trigger"``.
        smoothing (float): ``alpha`` in [0, 1) of an exponential moving average over consecutive
            scores, ``s_t = alpha * s_{t-1} + (1 - alpha) * score_t``, restarted at every env reset
            and whenever the transform is (re-)enabled. ``0`` (default) turns it off.
        done_key, truncated_key (NestedKey): Default to ``"done"`` and ``"truncated"``; a missing
            truncated entry is added to the done specs.

    Attributes:
        enabled (bool): when ``False`` the model is not evaluated and nothing triggers; the
            collector turns it off during reset episodes (one switch for the whole env).
        smoothed (Tensor or None): the smoothing's state, the last smoothed score (None: it restarts
            at the next score); a collector saves and restores it for an exact resume.

    Examples:
        >>> import torch
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_reset import EnsembleValueOperator, ResetTriggerTransform
        >>> from torchrl_reset_envs import ChainEnv
        >>> env = ChainEnv(num_states=8)
        >>> classifier = EnsembleValueOperator(8, 1, num_members=3, hidden_sizes=(16, 16))
        >>> env = TransformedEnv(env, ResetTriggerTransform(classifier, threshold=0.1))
        >>> check_env_specs(env)
        >>> td = env.rollout(3, break_when_any_done=False)
        >>> td["next", "reset_trigger"].shape
        torch.Size([3, 1])
    """

    def __init__(
        self,
        model: TensorDictModuleBase,
        threshold: float,
        *,
        score: str | Callable[[torch.Tensor], torch.Tensor] = "success_probability",
        reduction: str | Callable[[torch.Tensor], torch.Tensor] = "mean",
        model_out_key: NestedKey | None = None,
        score_key: NestedKey = "success_probability",
        trigger_key: NestedKey = "reset_trigger",
        smoothing: float = 0.0,
        done_key: NestedKey = "done",
        truncated_key: NestedKey = "truncated",
    ) -> None:
        super().__init__()
        if not isinstance(model, TensorDictModuleBase):
            raise TypeError(f"model must be a TensorDictModuleBase writing a score, got {type(model).__name__}.")
        if isinstance(score, str) and score not in SCORES:
            raise ValueError(f"score must be one of {SCORES} or a callable, got {score!r}.")
        if isinstance(reduction, str) and reduction not in MEMBER_REDUCTIONS:
            raise ValueError(f"reduction must be one of {MEMBER_REDUCTIONS} or a callable, got {reduction!r}.")
        threshold = self._check_threshold(threshold, score)
        smoothing = float(smoothing)
        if not (0.0 <= smoothing < 1.0):
            raise ValueError(f"smoothing must lie in [0, 1), got {smoothing!r}.")
        if model_out_key is None:
            if not model.out_keys:
                raise ValueError("model has no out_keys: pass model_out_key.")
            model_out_key = model.out_keys[0]
        self.model = model
        self.threshold = threshold
        self.score = score
        self.reduction = reduction
        self.model_out_key = model_out_key
        self.score_key = score_key
        self.trigger_key = trigger_key
        self.smoothing = smoothing
        self.done_key = done_key
        self.truncated_key = truncated_key
        self.enabled = True
        self.smoothed: torch.Tensor | None = None

    @staticmethod
    def _check_threshold(threshold, score) -> float:
        if isinstance(threshold, (torch.Tensor, list, tuple)):
            raise TypeError(f"threshold is one number, the same for every row of the env; got a "
                            f"{type(threshold).__name__}.")
        threshold = float(threshold)
        if score == "success_probability" and not 0.0 < threshold < 1.0:
            raise ValueError(
                f"threshold is a success probability (p_thresh) and must lie in (0, 1), got {threshold!r}."
            )
        if not math.isfinite(threshold):
            raise ValueError(f"threshold must be finite, got {threshold!r}.")
        return threshold

    def set_enabled(self, enabled: bool) -> None:
        """Turns the trigger on or off; (re-)enabling restarts the smoothing."""
        if isinstance(enabled, torch.Tensor):
            raise TypeError("set_enabled takes a bool: the trigger is on or off for the whole env, not row by "
                            "row; got a tensor.")
        self.enabled = bool(enabled)
        self.smoothed = None

    def evaluate(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The reduced score of the (observation, action) pairs in ``tensordict``, shape ``batch_size``."""
        missing = [key for key in self.model.in_keys if tensordict.get(key, None) is None]
        if missing:
            raise KeyError(
                f"ResetTriggerTransform's model needs {missing} in the tensordict passed to step(); got "
                f"{sorted(map(str, tensordict.keys(True, True)))}."
            )
        with torch.no_grad():
            out = self.model(tensordict.select(*self.model.in_keys).clone(False)).get(self.model_out_key)
            if out.shape == tensordict.batch_size:
                out = out.unsqueeze(-1)
            if out.shape[:-1] != tensordict.batch_size:
                raise ValueError(
                    f"the model output {self.model_out_key!r} has shape {tuple(out.shape)}; expected "
                    f"{tuple(tensordict.batch_size)} followed by one ensemble dimension."
                )
            if self.score == "success_probability":
                out = success_probability(out)
            elif callable(self.score):
                out = self.score(out)
            if callable(self.reduction):
                return self.reduction(out)
            return reduce_members(out, self.reduction)

    def score_step(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Scores the action in ``tensordict`` as a step would (smoothing included), writes the score
        and the flag into it and returns the flag (shape ``batch_size``); executes nothing.

        :class:`~torchrl_reset.DualCollector` calls it on the action drawn after the H_f-th step
        (Algorithm 1 scores that action before it checks the horizon)."""
        score = self.evaluate(tensordict)
        if self.smoothing > 0:
            if self.smoothed is not None and self.smoothed.shape == score.shape:
                score = self.smoothing * self.smoothed + (1.0 - self.smoothing) * score
            self.smoothed = score
        trigger = self._below(score)
        tensordict.set(self.score_key, score.unsqueeze(-1))
        tensordict.set(self.trigger_key, trigger.unsqueeze(-1))
        return trigger

    def _below(self, score: torch.Tensor) -> torch.Tensor:
        return score < self.threshold

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self.enabled:
            return tensordict
        trigger = self.score_step(tensordict)
        if trigger.any():
            step = tensordict.get("_step", None)
            tensordict.set("_step", ~trigger if step is None else step.reshape(trigger.shape) & ~trigger)
            # A skipped step copies these root entries into the next tensordict.
            for key in (self.done_key, self.truncated_key):
                flag = trigger.unsqueeze(-1)
                previous = tensordict.get(key, None)
                tensordict.set(key, flag if previous is None else previous | flag.reshape(previous.shape))
        return tensordict

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        shape = (*next_tensordict.batch_size, 1)
        self._ensure_truncated(next_tensordict)
        if not self.enabled:
            next_tensordict.set(self.score_key, torch.full(shape, float("nan"), device=next_tensordict.device))
            next_tensordict.set(self.trigger_key, torch.zeros(shape, dtype=torch.bool, device=next_tensordict.device))
            return next_tensordict
        score = tensordict.get(self.score_key)
        trigger = tensordict.get(self.trigger_key)
        next_tensordict.set(self.score_key, score)
        next_tensordict.set(self.trigger_key, trigger)
        if trigger.any():
            # Reached only when a batched env stepped triggered elements too (partial steps).
            for key in (self.done_key, self.truncated_key):
                previous = next_tensordict.get(key, None)
                next_tensordict.set(key, trigger if previous is None else previous | trigger.reshape(previous.shape))
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        self.smoothed = None
        shape = (*tensordict_reset.batch_size, 1)
        tensordict_reset.set(self.score_key, torch.full(shape, float("nan"), device=tensordict_reset.device))
        tensordict_reset.set(self.trigger_key, torch.zeros(shape, dtype=torch.bool, device=tensordict_reset.device))
        self._ensure_truncated(tensordict_reset)
        return tensordict_reset

    def _ensure_truncated(self, tensordict: TensorDictBase) -> None:
        """Writes a False truncated entry where the base env writes none (this transform adds it to the specs)."""
        if tensordict.get(self.truncated_key, None) is None:
            done = tensordict.get(self.done_key, None)
            flag = (
                torch.zeros((*tensordict.batch_size, 1), dtype=torch.bool, device=tensordict.device)
                if done is None
                else torch.zeros_like(done)
            )
            tensordict.set(self.truncated_key, flag)

    def transform_output_spec(self, output_spec: Composite) -> Composite:
        output_spec = super().transform_output_spec(output_spec)
        full_done_spec = output_spec["full_done_spec"]
        observation_spec = output_spec["full_observation_spec"]
        batch = observation_spec.shape
        device = output_spec.device
        shape = (*batch, 1)
        if self.truncated_key not in full_done_spec.keys(True, True):
            full_done_spec[self.truncated_key] = Categorical(2, shape=shape, dtype=torch.bool, device=device)
        observation_spec[self.score_key] = Unbounded(shape=shape, device=device)
        observation_spec[self.trigger_key] = Categorical(2, shape=shape, dtype=torch.bool, device=device)
        return output_spec

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # Outside an env (e.g. on replay data) the transform only writes the score and the flag.
        score = self.evaluate(tensordict)
        tensordict.set(self.score_key, score.unsqueeze(-1))
        tensordict.set(self.trigger_key, self._below(score).unsqueeze(-1))
        return tensordict

    def extra_repr(self) -> str:
        return f"threshold={self.threshold}, score={self.score!r}, reduction={self.reduction!r}, smoothing={self.smoothing}"
