"""A training step captured as one CUDA graph and replayed for every batch of the captured shape.

The captured function runs all of a step's device work but the optimiser's update (a handful of
fused kernels, left to Lightning): the gradients' reset, the forward pass, the loss and the
backward. Its inputs (the batch's tensors, the schedules' values) are copied into static buffers
before each replay and its outputs read from static buffers after it; the parameters and their
gradients keep their addresses between steps, so the graph reads and writes them in place. On a CPU
there is no graph: the same function runs at every step on the step's inputs, the schedules as the
same 0-d tensors (a dry run, which the tests compare with the eager step), so what a GPU replays is
what the CPU runs.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Hashable, Mapping

import torch

log = logging.getLogger(__name__)

StepFn = Callable[[Mapping[str, torch.Tensor], Hashable], dict[str, torch.Tensor]]


class StepGraph:
    """``StepGraph(fn)(tensors, scalars, flags)`` -> ``fn(inputs, flags)``'s outputs, where inputs
    holds the tensors and each scalar as a 0-d float32 tensor on their device; from a CUDA graph
    after ``warmup`` eager calls.

    fn may not synchronise with the host nor make a tensor from host data (the conditions of a
    capture); flags (a hashable, such as whether every agent is present) are fixed in a graph. The
    first inputs whose shapes and flags repeat those of the call before, after the warm-up, are
    captured; a call of other shapes or flags (an epoch's last, shorter batch) runs eagerly on the
    same parameters, so a run captures once. A replay's outputs live in the graph's buffers until
    the next replay: read them before then.
    """

    def __init__(self, fn: StepFn, warmup: int = 3) -> None:
        if warmup < 1:
            raise ValueError(f"StepGraph: warmup={warmup}; a capture needs at least one eager step "
                             "before it")
        self.fn, self.warmup = fn, warmup
        self.graph: torch.cuda.CUDAGraph | None = None
        self.key: Hashable = None  # the captured call's shapes and flags
        self.last_key: Hashable = None
        self.static_in: dict[str, torch.Tensor] = {}
        self.static_out: dict[str, torch.Tensor] = {}
        self.eager_calls = 0  # eager steps (the warm-up, other shapes, a CPU's dry run)
        self.replays = 0
        self.stream: torch.cuda.Stream | None = None  # the warm-up's and the capture's

    def __call__(self, tensors: Mapping[str, torch.Tensor],
                 scalars: Mapping[str, float] | None = None,
                 flags: Hashable = None) -> dict[str, torch.Tensor]:
        scalars = scalars or {}
        device = next(iter(tensors.values())).device
        key = (tuple((k, tuple(v.shape), v.dtype) for k, v in sorted(tensors.items())),
               tuple(sorted(scalars)), flags)
        if (device.type == "cuda" and self.graph is None and self.eager_calls >= self.warmup
            and key == self.last_key):
            self._capture(tensors, scalars, flags, key)
        self.last_key = key
        if device.type != "cuda" or key != self.key:
            return self._eager(tensors, scalars, flags, device)
        self._fill(tensors, scalars)
        self.graph.replay()
        self.replays += 1
        return self.static_out

    def _fill(self, tensors: Mapping[str, torch.Tensor], scalars: Mapping[str, float]) -> None:
        for name, value in tensors.items():
            self.static_in[name].copy_(value, non_blocking=True)
        for name, value in scalars.items():
            # the value travels as a kernel argument: no copy from the host
            self.static_in[name].fill_(value)

    @staticmethod
    def _inputs(tensors: Mapping[str, torch.Tensor], scalars: Mapping[str, float],
                device: torch.device, own: bool = False) -> dict[str, torch.Tensor]:
        """The tensors (copies, ``own``: a capture's static buffers) and each scalar as a 0-d
        float32 tensor."""
        return {**{k: v.clone() if own else v for k, v in tensors.items()},
                **{k: torch.full((), v, dtype=torch.float32, device=device)
                   for k, v in scalars.items()}}

    def _eager(self, tensors: Mapping[str, torch.Tensor], scalars: Mapping[str, float],
               flags: Hashable, device: torch.device) -> dict[str, torch.Tensor]:
        self.eager_calls += 1
        inputs = self._inputs(tensors, scalars, device)
        if device.type != "cuda" or self.graph is not None:
            return self.fn(inputs, flags)
        # Before a capture, on the stream the capture will use, as capturing asks: the warm-up's
        # allocations, cuBLAS workspaces and autograd's gradient accumulators are then the ones the
        # capture finds.
        self.stream = self.stream or torch.cuda.Stream(device)
        self.stream.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(self.stream):
            out = self.fn(inputs, flags)
        torch.cuda.current_stream(device).wait_stream(self.stream)
        return out

    def _capture(self, tensors: Mapping[str, torch.Tensor], scalars: Mapping[str, float],
                 flags: Hashable, key: Hashable) -> None:
        device = next(iter(tensors.values())).device
        self.static_in = self._inputs(tensors, scalars, device, own=True)
        graph = torch.cuda.CUDAGraph()
        torch.cuda.synchronize(device)
        try:
            with torch.cuda.graph(graph, stream=self.stream):
                self.static_out = self.fn(self.static_in, flags)
        except RuntimeError as error:
            # An op the capture cannot hold (a read-back, a host copy). The failed capture leaves
            # the CUDA random generator unusable for this process, so the run cannot go on eagerly:
            # it stops, naming the way out.
            raise RuntimeError("the training step could not be captured as one CUDA graph; "
                               "cuda_graph=false trains without it "
                               f"({str(error).splitlines()[0][:300]})") from error
        self.graph, self.key = graph, key
        log.info("training step captured as one CUDA graph after %d eager steps (%s)",
                 self.eager_calls, ", ".join(f"{k} {list(v.shape)}" for k, v in tensors.items()))
