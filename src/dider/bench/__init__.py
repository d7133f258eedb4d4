"""Benchmarks: throughput and peak memory, written as JSON records (and a scaling plot).

`python -m dider.bench --out bench/results.json [--only NAME ...] [--plot bench/scaling.png]`. Every
case runs in a fresh subprocess so its peak memory (ru_maxrss on CPU, max allocated on CUDA) is its
own.

Cases: training steps of each model (Markovian and recurrent decoders, bf16, torch.compile),
roll-out (evaluation) throughput, generating the 40k synthetic clips, preprocessing an inD-size
recording, loading batches with DataLoader workers, and a training step as the agents (N) and the
clip length (T) grow.

The roofline: every training record carries the step's matmul arithmetic (``gflop_per_step``,
counted by ``torch.utils.flop_counter``) and the rate it achieved (``gflops``); the ``gemm/*`` cases
measure the device's matmul rate on the model's dominant shape. The summary divides the two into the
most samples/s a step could reach if it did nothing but its matmuls at that rate.

The reference in the same run: ``--reference PATH`` (a checkout of cgraber/cvpr_dNRI, imported from
PATH) also times the public DNRI code's training step against ours on the same random batch, in one
process, in alternating rounds (:func:`compare_with_reference`). The results JSON then has a
``reference`` section and the summary gives the speed-ups over the reference from it (only from it:
another machine's throughput is no yardstick). ``--reference-size tiny`` runs the same at toy sizes
(a check that it works, not a measurement).

The ``memory/*`` cases record the peak memory of one DNRI training step at the paper's widths as N
grows, with the activation checkpointing of the encoder and the decoder off and on, and
``memory/dnri/largest_N/*`` searches for the largest N whose step fits ``--memory-limit-gb``
(:mod:`dider.bench.memory`). The ``result/*`` cases time a whole documented job, ``make demo``'s or
the CPU-sized synthetic table, beside the edge accuracy it produced (:mod:`dider.bench.result`);
they run only when ``--only`` names them. ``--profile CASE`` times nothing: it prints and writes
where one step of a training case spends its time (torch.profiler's op table, :func:`profile_case`).
``--allocator heap thresholds`` runs every case under each allocator setting in turn, in alternating
rounds, and the summary pairs them by round (:func:`dider.bench.summary.allocator_ratios`). The
JSON's ``meta`` keeps the command and the commit.
"""


from dider.bench.cli import main

__all__ = ["main"]
