"""The public DNRI code's training step timed against ours in the same process, in alternating
rounds."""

from __future__ import annotations

import contextlib
import logging
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from torch import nn

from dider.bench.cases import GEMM_SHAPE, Case, cases
from dider.bench.steps import build_model, gemm_seconds, random_batch, step_gflop, train_step

log = logging.getLogger(__name__)


REFERENCE_CASES = ("train/dnri/synth", "train/dnri/recurrent")
# --reference-size: "full" is the benchmark's cases as they are; "tiny" shrinks batch, clip and
# widths so the comparison runs in seconds (a test of the machinery; its timings mean nothing).
REFERENCE_SIZES: dict[str, dict[str, Any]] = {
    "full": {},
    "tiny": {"batch": 4, "steps": 8, "overrides": [
        "model.net.encoder.hidden=16", "model.net.encoder.rnn_hidden=8",
        "model.net.encoder.head_hidden=8",
        "model.net.prior.hidden=8", "model.net.decoder.hidden=16"]},
}  # fmt: skip
# What the reference's decoder_type is for each of our decoder classes.
REFERENCE_DECODERS = {"MarkovDecoder": "ref_mlp", "RecurrentDecoder": "recurrent"}


def reference_params(model_cfg: DictConfig, num_agents: int, device: str) -> dict[str, Any]:
    """The public DNRI code's ``params`` dict for the network of our model config ``model_cfg``
    (``model=dnri`` with either decoder): the same widths and depths, teacher-forced training with
    soft Gumbel-softmax edges, normalised Gaussian NLL and KL, and our objective's edge KL at weight
    1, or at 0.5 beside a ``mean_edges`` sparsity term at 0.5, as its ``add_uniform_prior`` (a fixed
    0.5/0.5 mix with KL(mean q || [no_edge_prob, ...]))."""
    net = model_cfg.net
    enc, dec, prior, objective = net.encoder, net.decoder, net.prior, net.objective
    decoder_class = str(dec._target_).rsplit(".", 1)[-1]
    sparsity = objective.get("sparsity")
    edge_weight = objective.kl_edge.weight
    halves = (sparsity is not None and sparsity.form == "mean_edges"
              and sparsity.weight == edge_weight == 0.5)
    if (decoder_class not in REFERENCE_DECODERS
        or not (halves or sparsity is None and edge_weight == 1)):
        raise ValueError(f"no reference counterpart of decoder {decoder_class} with objective "
                         f"{objective}")
    if objective.nll.variance == "fit":
        raise ValueError("no reference counterpart of model.net.objective.nll.variance=fit: the "
                         "reference's variance is a number")
    return {
        "num_vars": num_agents, "input_size": enc.input_dim, "num_edge_types": model_cfg.num_edges,
        "skip_first": dec.skip_first, "gpu": device == "cuda",
        "encoder_hidden": enc.hidden, "encoder_rnn_hidden": enc.rnn_hidden,
        "encoder_rnn_type": "lstm",
        "encoder_mlp_num_layers": enc.head_layers, "encoder_mlp_hidden": enc.head_hidden,
        "encoder_dropout": enc.dropout, "prior_num_layers": prior.num_layers,
        "prior_hidden_size": prior.hidden,
        "decoder_type": REFERENCE_DECODERS[decoder_class], "decoder_hidden": dec.hidden,
        "decoder_dropout": dec.dropout, "gumbel_temp": net.gumbel_tau, "train_hard_sample": False,
        "teacher_forcing_steps": -1, "val_teacher_forcing_steps": -1, "normalize_kl": True,
        "normalize_nll": True,
        "nll_loss_type": "gaussian", "prior_variance": objective.nll.variance, "kl_coef": 1.0,
        "add_uniform_prior": halves, "no_edge_prior": sparsity.no_edge_prob if halves else 0.9,
    }  # fmt: skip


def interleaved_timing(
    steps: Mapping[str, Callable[[], Any]],
    rounds: int,
    iters: int,
    warmup: int,
    device: str = "cpu",
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, list[float]]:
    """Seconds per call of each function, one value per round: ``warmup`` untimed calls of each,
    then ``rounds`` rounds of ``iters`` timed calls of each in turn. The order rotates by one every
    round, so no function always runs first (or right after the same neighbour) and a slow spell of
    the machine falls on all of them alike. -> {name: [s/call of round 0, round 1, ...]}."""
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    names = list(steps)
    for name in names:
        for _ in range(warmup):
            steps[name]()
    out: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        k = r % len(names)
        for name in names[k:] + names[:k]:
            sync()
            start = clock()
            for _ in range(iters):
                steps[name]()
            sync()
            out[name].append((clock() - start) / iters)
    return out


def speedups(per_round: Mapping[str, list[float]], baseline: str) -> dict[str, Any]:
    """From :func:`interleaved_timing`'s rounds: each function's median s/call, and every other
    function's speed-up over ``baseline`` (baseline time / its time) per round, paired within the
    round, and their median (the headline: a pairing within rounds cancels the machine's slow
    drifts)."""
    out: dict[str, Any] = {"step_s": {k: statistics.median(v) for k, v in per_round.items()},
                           "step_s_per_round": {k: list(v) for k, v in per_round.items()},
                           "speedup": {}, "speedup_per_round": {}}
    for name, times in per_round.items():
        if name != baseline:
            ratios = [b / t for b, t in zip(per_round[baseline], times, strict=True)]
            out["speedup_per_round"][name] = ratios
            out["speedup"][name] = statistics.median(ratios)
    return out


def _reference_step(ref: nn.Module, opt: torch.optim.Optimizer, x: torch.Tensor) -> None:
    """The reference's training step as its training script takes it (without gradient clipping,
    like ours). x: [B, T, N, D]."""
    loss = ref.calculate_loss(x, is_train=True, return_logits=True)[0]
    loss.backward()
    opt.step()
    opt.zero_grad()


@contextlib.contextmanager
def _reference_on_path(checkout: Path) -> Any:
    """The checkout's ``dnri`` package importable for the duration."""
    sys.path.insert(0, str(checkout))
    try:
        yield
    finally:
        sys.path.remove(str(checkout))


def _checkout_commit(checkout: Path) -> str | None:
    try:
        proc = subprocess.run(["git", "-C", str(checkout), "rev-parse", "--short", "HEAD"],
                              capture_output=True, text=True, timeout=10, check=False)
    except OSError:
        return None
    return proc.stdout.strip() or None


def compare_with_reference(
    checkout: Path,
    names: tuple[str, ...] = REFERENCE_CASES,
    size: str = "full",
    rounds: int = 4,
    iters: int = 2,
    warmup: int = 1,
    device: str = "cpu",
    threads: int | None = None,
    bf16: bool = True,
) -> dict[str, Any]:
    """Time the public DNRI code's training step and ours on the same random clips, in this one
    process.

    For each case of ``names`` (:func:`cases`' settings, shrunk by ``size``): the reference step is
    its training script's (``calculate_loss(inputs, is_train=True)``'s loss, backward, an Adam step,
    zero_grad); ours is :func:`train_step` in fp32 and in bf16 autocast; both with Adam at lr 5e-4.
    The three alternate in rounds (:func:`interleaved_timing`). -> the results JSON's ``reference``
    section: per case the batch, N, T, the median s/step of ``reference``, ``fp32`` and ``bf16``
    with every round's value, and the speed-ups (reference time / ours) with every round's value;
    the torch version and thread count (``threads``: set it first; None keeps torch's default).
    ``bf16=False`` leaves ours in bf16 out (a device that emulates it would take most of the
    run)."""
    if threads is not None:
        torch.set_num_threads(threads)
    checkout = Path(checkout).resolve()
    if not (checkout / "dnri" / "models" / "dnri.py").is_file():
        raise FileNotFoundError(f"{checkout}: not a checkout of cgraber/cvpr_dNRI (no "
                                "dnri/models/dnri.py)")
    scale = REFERENCE_SIZES[size]
    by_name = {c.name: c for c in cases()}
    out: dict[str, Any] = {}
    with _reference_on_path(checkout):
        from dnri.models.dnri import DNRI  # the reference, imported from the checkout

        for name in names:
            case = by_name[name]
            batch_size, steps = scale.get("batch", case.batch), scale.get("steps", case.steps)
            torch.manual_seed(0)
            ours, model_cfg = build_model([*case.overrides, *scale.get("overrides", [])])
            ours = ours.to(device).train()
            params = reference_params(model_cfg, case.agents, device)
            with contextlib.redirect_stdout(sys.stderr):  # it prints its prior on construction
                ref = DNRI(params).to(device).train()
            batch = random_batch(Case(name, [], batch_size, case.agents, steps), device)
            opt_ref = torch.optim.Adam([p for p in ref.parameters() if p.requires_grad], lr=5e-4)
            opt_ours = torch.optim.Adam(ours.parameters(), lr=5e-4)

            fns: dict[str, Callable[[], Any]] = {
                "reference": lambda m=ref, o=opt_ref, x=batch["states"]: _reference_step(m, o, x),
                "fp32": lambda m=ours, o=opt_ours, b=batch: train_step(m, o, b),
            }
            if bf16:
                fns["bf16"] = lambda m=ours, o=opt_ours, b=batch: train_step(m, o, b, "bf16")
            timing = speedups(interleaved_timing(fns, rounds, iters, warmup, device), "reference")
            timing["ceiling"] = matmul_ceiling(ours, batch, timing["step_s"]["reference"],
                                               list(fns)[1:], device)
            out[name] = {
                "batch": batch_size, "agents": case.agents, "steps": steps, "size": size,
                "overrides": [*case.overrides, *scale.get("overrides", [])],
                "reference_params": params, "rounds": rounds, "iters": iters, "warmup": warmup,
                "samples_per_s": {k: batch_size / v for k, v in timing["step_s"].items()}, **timing,
                "device": device, "threads": torch.get_num_threads(), "torch": torch.__version__,
            }  # fmt: skip
    return {"checkout": str(checkout), "commit": _checkout_commit(checkout), "cases": out}


def matmul_ceiling(model: Any, batch: dict[str, torch.Tensor], reference_s: float,
                   dtypes: list[str], device: str, iters: int = 10) -> dict[str, Any]:
    """The speed-up over the reference that a step of our arithmetic would reach if it did nothing
    but its matrix products at this device's matmul rate (:data:`GEMM_SHAPE`, timed here, in this
    process), per dtype of ``dtypes``: reference_s / (GFLOP per step / GFLOP/s). A target above it
    cannot be met on the device by any implementation of this arithmetic. -> ``gflop_per_step``,
    ``gemm_gflop_per_s`` and ``speedup`` by dtype."""
    m, k, n = GEMM_SHAPE
    gflop = step_gflop(model, batch)
    rate = {d: 2 * m * k * n / 1e9 / gemm_seconds(d, device, iters, 2) for d in dtypes}
    return {"gflop_per_step": gflop, "gemm_gflop_per_s": rate,
            "speedup": {d: reference_s / (gflop / r) for d, r in rate.items()}}


