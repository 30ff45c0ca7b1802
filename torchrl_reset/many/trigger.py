"""The reset trigger on a batched env whose copies are in different phases: enabled, thresholded and
smoothed row by row (:class:`~torchrl_reset.many.BatchedDualCollector`)."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

from ..trigger import ResetTriggerTransform

__all__ = ["RowResetTriggerTransform"]


class RowResetTriggerTransform(ResetTriggerTransform):
    """:class:`~torchrl_reset.ResetTriggerTransform` for an env of N copies, each in its own phase.

    The same rule row by row: :meth:`set_enabled` takes a boolean mask of the batch (only its rows can
    trigger; a row turned on, or named in ``restart``, restarts its own smoothing), ``threshold`` may be
    one number per row (the runs of a ``p_thresh`` sweep in one batch), a partial ``env.reset`` restarts
    the smoothing of the rows it resets, and :meth:`score_rows`, :meth:`row_smoothing` and
    :meth:`restore_row` let :class:`~torchrl_reset.many.BatchedDualCollector` score and save single rows.
    A row that is off never triggers and its score reads NaN. With a plain bool, it is the unbatched
    trigger.

    Args:
        model, threshold, and the keyword arguments: as :class:`~torchrl_reset.ResetTriggerTransform`;
        ``threshold`` may also be a 1-D sequence, one per row.
    """

    def __init__(self, model, threshold, **kwargs) -> None:
        per_row = isinstance(threshold, (torch.Tensor, list, tuple))
        if per_row:
            values = torch.as_tensor(threshold, dtype=torch.float32).detach().clone()
            if values.dim() != 1 or not values.numel():
                raise ValueError(f"a threshold per row is a 1-D sequence, got shape {tuple(values.shape)}.")
            for v in values.tolist():  # each checked as the single threshold would be
                ResetTriggerTransform._check_threshold(v, kwargs.get("score", "success_probability"))
        super().__init__(model, float(values[0]) if per_row else threshold, **kwargs)
        if per_row:
            self.threshold = values
        self._rows: torch.Tensor | None = None  # the enabled rows, or None: all or nothing

    def set_enabled(self, enabled: bool | torch.Tensor, *, restart: torch.Tensor | None = None) -> None:
        """Turns the trigger on or off, or, with a boolean tensor of the env's batch shape, its rows: rows
        where it is False are not triggered (their score reads NaN, as a disabled trigger's), and a row
        turned on restarts its own smoothing, as do the rows of ``restart`` (a new episode in a row that
        stays on); the other rows keep theirs."""
        if isinstance(enabled, torch.Tensor) and enabled.dtype == torch.bool:
            rows = enabled.detach().clone()
            if self.smoothed is not None and self._rows is not None and self.smoothed.shape == rows.shape:
                keep = rows & self._rows if restart is None else rows & self._rows & ~restart.reshape(rows.shape)
                self.smoothed = torch.where(keep, self.smoothed, torch.full_like(self.smoothed, float("nan")))
            else:
                self.smoothed = None
            self._rows = rows
            self.enabled = bool(rows.any())
            return
        if isinstance(enabled, torch.Tensor):
            raise TypeError(f"set_enabled takes a bool or a boolean mask of the batch, got a {enabled.dtype} tensor.")
        super().set_enabled(enabled)
        self._rows = None

    @property
    def enabled_rows(self) -> torch.Tensor | None:
        """The mask last given to :meth:`set_enabled`, or None when the trigger is on or off as a whole."""
        return self._rows

    def score_step(self, tensordict: TensorDictBase) -> torch.Tensor:
        rows = self._rows
        if rows is None:
            return super().score_step(tensordict)
        score = self.evaluate(tensordict)
        rows = rows.to(score.device)  # a mask made on the CPU (the batched collector's numpy masks)
        if rows.shape != score.shape:
            raise ValueError(f"set_enabled was given a mask of shape {tuple(rows.shape)}; the env's batch is "
                             f"{tuple(score.shape)}.")
        if self.smoothing > 0:
            if self.smoothed is not None and self.smoothed.shape == score.shape:
                previous = self.smoothed
                smoothed = self.smoothing * previous + (1.0 - self.smoothing) * score
                score = torch.where(previous.isnan(), score, smoothed)
            self.smoothed = torch.where(rows, score, torch.full_like(score, float("nan")))
        trigger = self._below(score) & rows  # a row that is off never triggers and reads as off
        score = torch.where(rows, score, torch.full_like(score, float("nan")))
        tensordict.set(self.score_key, score.unsqueeze(-1))
        tensordict.set(self.trigger_key, trigger.unsqueeze(-1))
        return trigger

    def _below(self, score: torch.Tensor) -> torch.Tensor:
        threshold = self.threshold
        if isinstance(threshold, torch.Tensor):
            if threshold.numel() != score.numel():
                raise ValueError(f"{threshold.numel()} thresholds (one per row) for scores of shape {tuple(score.shape)}.")
            threshold = threshold.to(score.device).reshape(score.shape)
        return score < threshold

    def score_rows(self, tensordict: TensorDictBase, rows: torch.Tensor) -> torch.Tensor:
        """:meth:`score_step` for the rows of the boolean mask ``rows`` only (the flag is False elsewhere);
        the other rows' smoothing and the enabled rows are left as they were.

        :class:`~torchrl_reset.many.BatchedDualCollector` calls it on the actions drawn after some copies'
        H_f-th step while the other copies' episodes go on."""
        saved_rows, saved = self._rows, self.smoothed
        self._rows = rows.detach().clone()
        try:
            flag = self.score_step(tensordict)
        finally:
            new, self._rows = self.smoothed, saved_rows
            if saved is not None and new is not None and saved.shape == new.shape:
                self.smoothed = torch.where(rows.reshape(new.shape), new, saved)
            else:
                self.smoothed = saved
        return flag

    def row_smoothing(self, row: int) -> torch.Tensor | None:
        """Row ``row``'s smoothed score (a 0-dim tensor, what an unbatched env's trigger holds), or None
        when that row's smoothing restarts at its next score."""
        if self.smoothed is None or self._rows is None or not bool(self._rows.reshape(-1)[row]):
            return None
        value = self.smoothed.reshape(-1)[row]
        return None if bool(value.isnan()) else value.clone()

    def restore_row(self, row: int, smoothed: torch.Tensor | None, rows: int) -> None:
        """Sets row ``row`` (of a batch of ``rows``) to continue from ``smoothed`` (:meth:`row_smoothing`
        of a batch, or an unbatched trigger's state); None: its smoothing restarts."""
        if self._rows is None or self._rows.numel() != rows:
            self._rows = torch.zeros(rows, dtype=torch.bool)
        if self.smoothed is None or self.smoothed.numel() != rows:
            self.smoothed = torch.full((rows,), float("nan"))
        self._rows[row] = smoothed is not None
        self.smoothed[row] = float("nan") if smoothed is None else float(smoothed.reshape(-1)[0])
        self.enabled = bool(self._rows.any())

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        saved = self.smoothed
        out = super()._reset(tensordict, tensordict_reset)
        partial = None if tensordict is None else tensordict.get("_reset", None)
        if partial is not None and self._rows is not None and saved is not None and partial.numel() == saved.numel():
            # a partial reset of the batched env: only the rows reset restart their smoothing
            self.smoothed = torch.where(partial.reshape(saved.shape), torch.full_like(saved, float("nan")), saved)
        return out
