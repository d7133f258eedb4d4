"""A training epoch's logged values kept where they are computed. Lightning's ``log`` costs about a
millisecond of host time a call (at batch 16 on a GPU, more than a graphed step's arithmetic) and
copies each Python float to the device: here a step adds all its tensors in one fused update on
their device and its floats on the host, reads nothing back, and the module logs the step's own
values only on the steps the trainer writes, the epoch's means once."""

from __future__ import annotations

from collections.abc import Collection, Mapping

import torch


class EpochMeans:
    """``add(values, weight)`` at each step (name -> 0-d tensor or float); ``last()``: the last
    step's tensors; ``means()``: each value's mean over the steps since the last ``reset()``,
    weighted (by batch size, as Lightning's epoch means are); ``weight``: the weights' sum (0:
    nothing added)."""

    def __init__(self) -> None:
        self.names: tuple[str, ...] = ()
        self.sums: torch.Tensor | None = None  # [len(names)] float32 on the values' device
        self.values: torch.Tensor | None = None  # the last step's, stacked
        self.host: dict[str, float] = {}
        self.weight = 0.0

    def add(self, values: Mapping[str, torch.Tensor | float], weight: float) -> None:
        tensors = {k: v for k, v in values.items() if isinstance(v, torch.Tensor)}
        if tensors:
            # 0-d each; one stack, not three ops each
            stacked = torch.stack(list(tensors.values())).detach().float()
            if self.sums is None or tuple(tensors) != self.names:
                if self.weight and self.sums is not None:
                    raise ValueError(f"EpochMeans: step values {sorted(tensors)} differ from the "
                                     f"epoch's {self.names}")
                self.names, self.sums = tuple(tensors), torch.zeros_like(stacked)
            if self.sums.device != stacked.device:  # restored from a checkpoint on the host
                self.sums = self.sums.to(stacked.device)
            self.sums.add_(stacked, alpha=weight)
            self.values = stacked
        for k, v in values.items():
            if not isinstance(v, torch.Tensor):
                self.host[k] = self.host.get(k, 0.0) + float(v) * weight
        self.weight += weight

    def last(self) -> dict[str, torch.Tensor]:
        return ({} if self.values is None
                else dict(zip(self.names, self.values.unbind(), strict=True)))

    def means(self) -> dict[str, torch.Tensor | float]:
        if not self.weight:
            return {}
        tensors = ({} if self.sums is None
                   else dict(zip(self.names, (self.sums / self.weight).unbind(), strict=True)))
        return tensors | {k: v / self.weight for k, v in self.host.items()}

    def pop(self, suffixed: Collection[str] = ()) -> dict[str, torch.Tensor | float]:
        """The :meth:`means`, each name in ``suffixed`` as ``<name>_epoch``; then :meth:`reset`."""
        means = {f"{k}_epoch" if k in suffixed else k: v for k, v in self.means().items()}
        self.reset()
        return means

    def reset(self) -> None:
        if self.sums is not None:
            self.sums.zero_()
        self.host, self.weight = {}, 0.0

    def state_dict(self) -> dict[str, object]:
        """The epoch's sums so far (host copies), for a checkpoint saved inside the epoch."""
        sums = None if self.sums is None else self.sums.detach().cpu()
        return {"names": list(self.names), "sums": sums, "host": dict(self.host),
                "weight": self.weight}

    def load_state_dict(self, state: Mapping[str, object]) -> None:
        """Go on from :meth:`state_dict`'s sums: the resumed epoch's means cover its batches before
        the stop too."""
        self.names, self.sums = tuple(state["names"]), state["sums"]
        self.host, self.weight = dict(state["host"]), float(state["weight"])
