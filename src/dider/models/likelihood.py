"""The decoder's likelihood, the objective's ``nll`` term: a Gaussian with a fixed variance, one for
every feature or one per feature fitted to the data before training."""

from __future__ import annotations

from typing import Any, ClassVar

import torch

from dider.models.inference import Inference
from dider.models.losses import gaussian_nll, gaussian_nll_each, residual_variance
from dider.models.objective import Batch, Term
from dider.validation import Rule, above, check_settings, or_word


class GaussianNLL(Term):
    """``variance``: a number (DNRI's 5e-5 on its synthetic set), or ``"fit"``: per feature, the
    variance that one step of constant velocity leaves unexplained on a training batch (:meth:`fit`,
    called before the first optimiser step). A fitted variance makes the NLL a calibrated
    likelihood, so the edge KL prices what the edges tell the decoder at its true rate; a variance
    far below the data's lets edges that carry the clip's future buy likelihood at almost any KL.
    The variance is saved with the weights. Counted at weight 1, from the first step."""

    warms_up = False
    SETTINGS: ClassVar[dict[str, Rule]] = {"variance": or_word("fit", above(0))}

    def __init__(self, variance: float | str = 5e-5) -> None:
        super().__init__()
        check_settings(self, locals())
        self.to_fit = variance == "fit"
        # a single variance as a number: no device sync
        self.value = 1.0 if self.to_fit else float(variance)
        self.register_buffer("variance", torch.tensor(self.value))

    def forward(self, out: Inference, batch: Batch) -> torch.Tensor:
        """The NLL per clip [B] of the pass's one-step predictions of frames 1..T-1, over the agents
        present at both ends of each step."""
        mask = batch["mask"]
        return self.nll(out.pred, batch["states"][:, 1:], mask[:, :-1] & mask[:, 1:])

    def nll(self, pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """pred, target [B, T, N, D], mask [B, T, N] -> the NLL per sample [B]
        (:func:`gaussian_nll`)."""
        return gaussian_nll(pred, target, mask, self._variance())

    def each(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """pred, target [..., D] -> each agent-step's NLL [...]."""
        return gaussian_nll_each(pred, target, self._variance())

    def _variance(self) -> float | torch.Tensor:
        return self.variance if self.variance.dim() else self.value

    def fit(self, x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """Sets the variance per feature from the states x [B, T, N, D] (mask [B, T, N]). -> the
        variances [D]."""
        self.variance = residual_variance(x, mask).to(self.variance.device)
        return self.variance

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any,
                              **kwargs: Any) -> None:
        key = prefix + "variance"
        saved = state_dict.get(key)
        # a fitted variance, one per feature: take the saved shape
        if saved is not None and saved.dim() > 0:
            self.variance = saved.detach().clone().to(self.variance.device)
        else:
            # one variance is the configured number (the saved copy is rounded to the buffer's
            # dtype), also for checkpoints saved before the variance was kept with the weights
            state_dict[key] = self.variance
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
