"""The relational VAE: one LightningModule composing encoder, prior, duration and decoder plugins.

DNRI, DIDER, DIDER (with SKID) and NRI differ only in the plugins they are built with: the duration
plugin decides how each edge's time axis is cut into segments, and the edge prior and posterior are
read once per segment. With one-step segments this is exactly DNRI.

Shapes: B batch, T frames, N agents, D = 4 features, E = N(N-1) edges, K edge types, S segment slots,
R LSTM width, P predicted steps.
"""

from __future__ import annotations

import logging
import math
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from dider.data.batch import Batch
from dider.data.common import BURN_IN_MODES, agent_horizons, burn_in_mask, fill_absent
from dider.data.pairs import KIND_NAMES
from dider.graph import edge_mask
from dider.losses import capacity, categorical_kl, gaussian_nll
from dider.metrics import BoundaryF1, EdgeAccuracy, HorizonMSE, PairConsistency, SegmentStats
from dider.models.prior import fixed_log_probs
from dider.models.segments import Segmentation

log = logging.getLogger(__name__)

LOSS_TERMS = ("nll", "kl_edge", "kl_duration")


class NonFiniteError(FloatingPointError):
    """A NaN/inf loss term or gradient during training: the message names the step, batch and term."""


def rng_state(full: bool = True) -> dict[str, Any]:
    """The global random states a run draws from: torch CPU and CUDA and, with ``full``, numpy and Python.

    Plain tensors, ints and tuples only, so checkpoints holding it still load with ``weights_only=True``.
    """
    state: dict[str, Any] = {"torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    if full:
        kind, keys, pos, has_gauss, gauss = np.random.get_state()
        state["numpy"] = {"kind": str(kind), "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                          "has_gauss": int(has_gauss), "gauss": float(gauss)}
        state["python"] = random.getstate()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` captured (missing parts are left alone)."""
    if "torch" in state:
        torch.set_rng_state(torch.as_tensor(state["torch"], dtype=torch.uint8).cpu())
    if "cuda" in state and torch.cuda.is_available() and len(state["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(state["cuda"])
    if "numpy" in state:
        s = state["numpy"]
        keys = np.asarray(s["keys"].cpu().numpy(), dtype=np.uint32)
        np.random.set_state((s["kind"], keys, s["pos"], s["has_gauss"], s["gauss"]))
    if "python" in state:
        v, internal, gauss = state["python"]
        random.setstate((v, tuple(internal), gauss))


@dataclass
class Inference:
    """Result of the teacher-forced pass over a clip."""

    pred: torch.Tensor  # [B, T-1, N, D] predictions of x_1..x_{T-1}
    posterior_logits: torch.Tensor  # [B, E, S, K] per segment
    prior_logits: torch.Tensor  # [B, E, S, K] per segment
    probs: torch.Tensor  # [B, E, T-1, K] posterior probabilities held over each segment
    step_logits: torch.Tensor  # [B, E, T-1, K] per-step posterior logits (before segmentation)
    seg: Segmentation
    h_fwd: torch.Tensor  # [B, E, T-1, R]
    nll: torch.Tensor  # [B]
    kl_edge: torch.Tensor  # [B]
    kl_duration: torch.Tensor  # [B]

    def posterior_types(self) -> torch.Tensor:
        """[B, E, T-1] long: the argmax type of each step's segment."""
        one_hot = F.one_hot(self.posterior_logits.argmax(-1), self.posterior_logits.shape[-1]).float()
        return self.seg.spread(one_hot).argmax(-1)


class RelationalVAE(L.LightningModule):
    def __init__(
        self,
        encoder: nn.Module,
        prior: nn.Module,
        duration: nn.Module,
        decoder: nn.Module,
        optimizer: Callable[..., torch.optim.Optimizer],
        num_edges: int = 2,
        burn_in: int = 5,
        horizons: Sequence[int] = (1, 15, 25),
        scheduler: Callable[..., Any] | None = None,
        nll_variance: float = 5e-5,
        gumbel_tau: float = 0.5,
        beta_edge: float = 1.0,
        beta_duration: float = 1.0,
        capacity_edge: float = 0.0,
        capacity_duration: float = 0.0,
        capacity_ramp: float = 0.5,
        kl_warmup: float = 0.0,
        sparsity_mix: float = 0.0,
        no_edge_prob: float = 0.9,
        rollout_edges: str = "sample",
        posterior_readout: str = "start",
        num_figure_clips: int = 4,
        name: str = "model",
        burn_in_mode: str | None = None,
        eval_seed: int = 0,
        check_finite: bool = True,
    ) -> None:
        """burn_in_mode: ``global`` (every agent observed for the window's first ``burn_in`` frames),
        ``per_agent`` (each agent for its own first ``burn_in`` present frames, DNRI's inD protocol) or None:
        the attached datamodule's ``burn_in_mode`` (``global`` without one). eval_seed: validation and test
        draw from a generator seeded with it (restored afterwards), so their metrics depend on the weights
        only. check_finite: stop training on a NaN/inf loss term or gradient (:class:`NonFiniteError`)."""
        super().__init__()
        if num_edges < 2:
            raise ValueError(f"model.num_edges={num_edges}: need at least 2 edge types (type 0 is 'no interaction')")
        if posterior_readout not in ("start", "mean"):
            raise ValueError(f"model.posterior_readout={posterior_readout!r}: expected 'start' or 'mean'")
        if rollout_edges not in ("sample", "argmax"):
            raise ValueError(f"model.rollout_edges={rollout_edges!r}: expected 'sample' or 'argmax'")
        for key, value in {"model.nll_variance": nll_variance, "model.gumbel_tau": gumbel_tau}.items():
            if value <= 0:
                raise ValueError(f"{key}={value}: must be > 0")
        for key, value in {
            "model.capacity_edge": capacity_edge, "model.capacity_duration": capacity_duration,
            "model.beta_edge": beta_edge, "model.beta_duration": beta_duration,
        }.items():  # fmt: skip
            if value < 0:
                raise ValueError(f"{key}={value}: must be >= 0")
        if not 0.0 <= capacity_ramp <= 1.0:
            raise ValueError(f"model.capacity_ramp={capacity_ramp}: a fraction of training, in [0, 1]")
        if not 0.0 <= kl_warmup <= 1.0:
            raise ValueError(f"model.kl_warmup={kl_warmup}: a fraction of training, in [0, 1]")
        if not 0.0 <= sparsity_mix <= 1.0:
            raise ValueError(f"model.sparsity_mix={sparsity_mix}: must lie in [0, 1]")
        if burn_in_mode is not None and burn_in_mode not in BURN_IN_MODES:
            raise ValueError(f"model.burn_in_mode={burn_in_mode!r}: expected one of {list(BURN_IN_MODES)} or null")
        # Plugins and optimiser factories stay out of the checkpoint's hyper-parameters: checkpoints then
        # load with torch's safe weights_only unpickler; the Hydra config rebuilds them.
        plugins = ["encoder", "prior", "duration", "decoder", "optimizer", "scheduler"]
        self.save_hyperparameters(logger=False, ignore=plugins)
        self.optimizer_factory, self.scheduler_factory = optimizer, scheduler
        self.encoder, self.prior, self.duration, self.decoder = encoder, prior, duration, decoder
        self.num_types = num_edges
        self.register_buffer("sparsity_log_probs", fixed_log_probs(num_edges, no_edge_prob), persistent=False)
        self.val_mse = HorizonMSE(horizons)
        self.test_mse = HorizonMSE(horizons)
        self.test_mse_raw = HorizonMSE(horizons)
        self.test_acc_post = EdgeAccuracy()
        self.test_acc_prior = EdgeAccuracy()
        self.test_segments = SegmentStats()
        self.test_boundary = BoundaryF1(tolerance=2)
        self.test_pairs = PairConsistency(num_edges, num_kinds=len(KIND_NAMES))
        self.test_types: list[torch.Tensor] = []  # per-step posterior types and probabilities, for export
        self.test_probs: list[torch.Tensor] = []
        self.figure_data: dict[str, torch.Tensor] = {}
        self._rng_outside_eval: dict[str, Any] | None = None  # the training run's random state during evaluation
        self._last_step: tuple[Batch, int, dict[str, Any]] | None = None  # batch, index, rng: for diagnosis

    @property
    def burn_in_mode(self) -> str:
        """The forecast protocol in force: the model's own setting, else the attached datamodule's."""
        if self.hparams.burn_in_mode is not None:
            return self.hparams.burn_in_mode
        dm = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        return getattr(dm, "burn_in_mode", None) or "global"

    # ------------------------------------------------------------------ inference
    def infer(self, batch: Batch, hard: bool) -> Inference:
        """Teacher-forced pass: posterior edges per segment drive one-step predictions of every frame."""
        x, mask = batch["states"], batch["mask"]
        # With every agent present (the synthetic sets) the plugins skip their masking passes.
        plugin_mask = None if bool(mask.all()) else mask
        enc = self.encoder(x, plugin_mask)
        seg: Segmentation = self.duration.segment(enc.h_fwd, enc.h_rev, x)
        # The posterior reads a segment's type at its first step (the paper) or pools the per-step
        # logits over the segment; the prior always reads the first step, so it stays online.
        pooled = self.hparams.posterior_readout == "mean"
        q_seg = seg.pool(enc.posterior_logits) if pooled else seg.gather(enc.posterior_logits)
        p_seg = seg.gather(self.prior(enc.h_fwd))
        z = seg.spread(F.gumbel_softmax(q_seg, tau=self.hparams.gumbel_tau, hard=hard))  # [B, E, T-1, K]
        pred = self.decoder(x[:, :-1], z.transpose(1, 2), None if plugin_mask is None else mask[:, :-1])
        nll = gaussian_nll(pred, x[:, 1:], mask[:, :-1] & mask[:, 1:], self.hparams.nll_variance)

        # Edge KL per segment, summed over an edge's segments and divided by its steps, so that with
        # one-step segments it is DNRI's mean over (step, edge).
        present = edge_mask(mask[:, :-1]).transpose(1, 2)  # [B, E, T-1]
        at_start = present.gather(2, seg.start) & seg.valid
        kl_slots = categorical_kl(q_seg, p_seg) * at_start
        steps = present.flatten(1).sum(1).clamp_min(1)
        kl_edge = kl_slots.flatten(1).sum(1) / steps
        probs = seg.spread(F.softmax(q_seg, dim=-1))
        if self.hparams.sparsity_mix > 0:  # DNRI's synthetic runs: KL(mean_e q_t || [0.9, 0.1, ...])
            w = present.unsqueeze(-1).to(probs.dtype)
            mean_q = (probs * w).sum(1) / w.sum(1).clamp_min(1)  # [B, T-1, K]
            kl_sparse = (mean_q * (mean_q.clamp_min(1e-16).log() - self.sparsity_log_probs)).sum(-1).mean(-1)
            kl_edge = (1 - self.hparams.sparsity_mix) * kl_edge + self.hparams.sparsity_mix * kl_sparse
        return Inference(pred, q_seg, p_seg, probs, enc.posterior_logits, seg, enc.h_fwd, nll, kl_edge, seg.kl)

    def loss(self, out: Inference) -> dict[str, torch.Tensor]:
        """NLL + w (beta_e |KL_e - C_e| + beta_d |KL_d - C_d|): capacities ramped linearly (beta-VAE, Burgess
        et al.) and the KL weight w ramped from 0 to 1 over the first ``kl_warmup`` of training (Bowman et
        al.), so the posterior carries information before the prior may pull it in."""
        h = self.hparams
        total = self._trainer.estimated_stepping_batches if self._trainer is not None else 0
        known = bool(total) and total != float("inf")
        c_e = capacity(self.global_step, h.capacity_edge, int(h.capacity_ramp * total) if known else 0)
        c_d = capacity(self.global_step, h.capacity_duration, int(h.capacity_ramp * total) if known else 0)
        w = capacity(self.global_step, 1.0, int(h.kl_warmup * total) if known else 0)
        nll, kl_e, kl_d = out.nll.mean(), out.kl_edge.mean(), out.kl_duration.mean()
        loss = nll + w * (h.beta_edge * (kl_e - c_e).abs() + h.beta_duration * (kl_d - c_d).abs())
        return {"loss": loss, "nll": nll, "kl_edge": kl_e, "kl_duration": kl_d}

    def _advance_edges(
        self, h_t: torch.Tensor, t: int, end: int, etype: torch.Tensor, left: torch.Tensor, sample: bool
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Online segment state machine, vectorised over [B, E]: when an edge's segment has no steps
        left, a new type comes from the prior and a new duration from the duration plugin."""
        logits = self.prior(h_t)  # [B, E, K]
        if sample:
            logits = logits - torch.empty_like(logits).exponential_().log()  # + Gumbel noise
        need = left <= 0
        etype = torch.where(need, logits.argmax(-1), etype)
        left = torch.where(need, self.duration.next_duration(h_t, t, end), left) - 1
        return etype, left

    @torch.no_grad()
    def online_types(self, h_fwd: torch.Tensor) -> torch.Tensor:
        """Prior-only (past-only) edge types over a clip: h_fwd [B, E, T, R] -> [B, E, T] long."""
        b, e, t, _ = h_fwd.shape
        etype = torch.zeros(b, e, dtype=torch.long, device=h_fwd.device)
        left = torch.zeros_like(etype)
        types = []
        for s in range(t):
            etype, left = self._advance_edges(h_fwd[:, :, s], s, t, etype, left, sample=False)
            types.append(etype)
        return torch.stack(types, dim=2)

    @torch.no_grad()
    def rollout(
        self, x: torch.Tensor, mask: torch.Tensor, burn_in: int, num_pred: int, mode: str | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Forecast: ground truth during the burn-in, then the model's own predictions.

        mode ``global``: every agent's input is ground truth for the window's first ``burn_in`` frames, its
        own prediction afterwards; x may hold only those frames, [B, >=burn_in, N, D].
        mode ``per_agent`` (agents entering mid-window, DNRI's inD protocol): agent i's input at frame t is
        ground truth while t is among its own first ``burn_in`` present frames (``burn_in_mask``), its own
        previous prediction afterwards; absent agents are zeros and masked. x: [B, >=burn_in+P-1, N, D].
        With every agent present from frame 0 both modes compute the same thing, bit for bit.
        mode None: :attr:`burn_in_mode`.

        Edges come from the prior only, read from the forward LSTM that is advanced on the inputs above, so
        no state after an agent's burn-in is ever seen. mask: [B, >=burn_in+P, N] (agents present) ->
        predictions of x_burn_in..x_{burn_in+P-1} [B, P, N, D] (an agent's frame t is predicted from its
        input at t-1; score it with :func:`dider.data.common.agent_horizons` in ``per_agent`` mode) and the
        edge types used for every transition [B, E, burn_in+P-1].
        """
        mode = mode or self.burn_in_mode
        if mode not in BURN_IN_MODES:
            raise ValueError(f"burn_in_mode={mode!r}: expected one of {list(BURN_IN_MODES)}")
        if burn_in < 1 or num_pred < 1:
            raise ValueError(f"rollout: need burn_in >= 1 and num_pred >= 1, got {burn_in}, {num_pred}")
        b, n = x.shape[0], x.shape[2]
        end = burn_in + num_pred - 1  # transitions covered
        sample = self.hparams.rollout_edges == "sample"
        if mode == "per_agent":
            if x.shape[1] < end or mask.shape[1] < end:
                raise ValueError(f"rollout(per_agent): need >= {end} frames of states and mask (an agent may "
                                 f"enter late and be observed then), got {x.shape[1]} and {mask.shape[1]}")
            fed = burn_in_mask(mask[:, :end], burn_in)  # [B, end, N]: inputs that are ground truth
            # Frames before any present agent has left its burn-in are pure ground truth: one batched LSTM
            # pass over them, exactly as in the global mode (where this prefix is the burn-in itself).
            rolled = (mask[:, :end] & ~fed).any(dim=2).any(dim=0)  # [end]
            t_obs = int(rolled.to(torch.uint8).argmax()) if bool(rolled.any()) else end
            x_obs = fill_absent(x[:, :t_obs], mask[:, :t_obs])
        else:
            fed, t_obs, x_obs = None, burn_in, x[:, :burn_in]
        h_past, enc_state = self.encoder.past(x_obs, mask[:, :t_obs])
        etype = torch.zeros(b, h_past.shape[1], dtype=torch.long, device=x.device)
        left = torch.zeros_like(etype)
        dec_state = self.decoder.init_state(b, n, x)
        preds, types = [], []
        cur = x[:, 0]
        for t in range(end):
            m_t = mask[:, t]
            if t < t_obs:
                cur, h_t = x_obs[:, t], h_past[:, :, t]
            else:  # t >= t_obs >= burn_in: cur holds the previous step's prediction
                if fed is not None:
                    cur = fill_absent(torch.where(fed[:, t, :, None], x[:, t], cur), m_t)
                h_t, enc_state = self.encoder.step(cur, enc_state, m_t)
            etype, left = self._advance_edges(h_t, t, end, etype, left, sample)
            types.append(etype)
            # No input before burn_in - 1 is ever a prediction (an agent needs burn_in present frames
            # first), so a stateless decoder has nothing to do there.
            if t < burn_in - 1 and self.decoder.stateless:
                continue
            z_t = F.one_hot(etype, self.num_types).to(x.dtype) * edge_mask(m_t).unsqueeze(-1)
            out, dec_state = self.decoder.step(cur, z_t, dec_state, m_t)
            if t >= burn_in - 1:
                preds.append(out)
                cur = out
        return torch.stack(preds, dim=1), torch.stack(types, dim=2)

    def forward(
        self, x: torch.Tensor, mask: torch.Tensor, burn_in: int, num_pred: int, mode: str | None = None
    ) -> torch.Tensor:
        """Inference entry point: the forecast of :meth:`rollout`, [B, P, N, D]."""
        return self.rollout(x, mask, burn_in, num_pred, mode)[0]

    # ------------------------------------------------------------------ Lightning hooks
    def on_train_batch_start(self, batch: Batch, batch_idx: int) -> None:
        if hasattr(self.duration, "step"):  # annealed schedules inside the duration plugin
            self.duration.step = self.global_step

    def training_step(self, batch: Batch, batch_idx: int) -> torch.Tensor:
        if self.hparams.check_finite:  # what a gradient diagnosis needs to replay this step
            self._last_step = (batch, batch_idx, rng_state(full=False))
        terms = self.loss(self.infer(batch, hard=False))
        if self.hparams.check_finite:
            self._check_finite_terms(terms, batch_idx)
        self.log_dict({f"train/{k}": v for k, v in terms.items()}, prog_bar=False, on_step=True, on_epoch=True,
                      batch_size=batch["states"].shape[0])
        self.log("loss", terms["loss"], prog_bar=True, logger=False, batch_size=batch["states"].shape[0])
        return terms["loss"]

    def on_train_epoch_end(self) -> None:
        self.log("train/lr", self.trainer.optimizers[0].param_groups[0]["lr"])

    # ------------------------------------------------------------------ guards
    def _where(self, batch_idx: int) -> str:
        return f"step {self.global_step}, batch {batch_idx} of epoch {self.current_epoch}"

    def _check_finite_terms(self, terms: dict[str, torch.Tensor], batch_idx: int) -> None:
        """Raise :class:`NonFiniteError` naming the step, batch and term when a loss term is NaN/inf
        (one device sync per step)."""
        names = [*LOSS_TERMS, "loss"]
        values = torch.stack([terms[k].detach().float() for k in names])
        if bool(torch.isfinite(values).all()):
            return
        bad = {k: v for k, v in zip(names, values.tolist(), strict=True) if not math.isfinite(v)}
        culprits = [k for k in bad if k != "loss"] or ["loss"]
        msg = (f"non-finite loss at {self._where(batch_idx)}: term {', '.join(culprits)} "
               f"({', '.join(f'{k}={v}' for k, v in bad.items())}); stopping the run")
        log.error(msg)
        raise NonFiniteError(msg)

    def _uses_grad_scaler(self) -> bool:
        """fp16 mixed precision skips steps with inf gradients on purpose: not an error there."""
        plugin = getattr(self._trainer, "precision_plugin", None)
        return getattr(plugin, "scaler", None) is not None

    def on_after_backward(self) -> None:
        if not self.hparams.check_finite or self._trainer is None or self._uses_grad_scaler():
            return
        named = [(k, p.grad) for k, p in self.named_parameters() if p.grad is not None]
        if not named or bool(torch.stack([torch.isfinite(g).all() for _, g in named]).all()):
            return
        params = [k for k, g in named if not bool(torch.isfinite(g).all())]
        batch_idx = self._last_step[1] if self._last_step is not None else -1
        culprits = self._gradient_culprits()
        msg = (f"non-finite gradient at {self._where(batch_idx)}: from loss term {', '.join(culprits)}; "
               f"{len(params)} parameter(s) hit, e.g. {params[:3]}; stopping the run")
        log.error(msg)
        raise NonFiniteError(msg)

    def _gradient_culprits(self) -> list[str]:
        """Replay the last training step (same batch and random state) and differentiate each loss term
        on its own: the terms whose gradient is NaN/inf. Runs only when a bad gradient was found."""
        if self._last_step is None:
            return ["unknown (no step to replay)"]
        batch, _, state = self._last_step
        set_rng_state(state)
        params = [p for p in self.parameters() if p.requires_grad]
        context = self.trainer.precision_plugin.forward_context()
        with torch.enable_grad(), context:
            terms = self.loss(self.infer(batch, hard=False))
        culprits = []
        for name in LOSS_TERMS:
            if not terms[name].requires_grad:
                continue
            grads = torch.autograd.grad(terms[name], params, retain_graph=True, allow_unused=True)
            if any(g is not None and not bool(torch.isfinite(g).all()) for g in grads):
                culprits.append(name)
        return culprits or ["loss (no single term: their sum)"]

    # ------------------------------------------------------------------ reproducibility
    def _enter_eval_rng(self) -> None:
        """Evaluation draws (rollout edge samples, hard Gumbel samples) from ``eval_seed``, not from the
        training run's random state, which is put back afterwards: metrics are a function of the weights."""
        if self._rng_outside_eval is None:
            self._rng_outside_eval = rng_state()
        torch.manual_seed(self.hparams.eval_seed)

    def _exit_eval_rng(self) -> None:
        if self._rng_outside_eval is not None:
            set_rng_state(self._rng_outside_eval)
            self._rng_outside_eval = None

    def on_validation_epoch_start(self) -> None:
        self._enter_eval_rng()

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        # The random state of the training run (not of an evaluation in progress), so a resumed run draws
        # exactly what the uninterrupted one would have drawn after this point.
        checkpoint["dider_rng"] = self._rng_outside_eval or rng_state()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        if "dider_rng" in checkpoint and self._trainer is not None and self.trainer.state.fn == "fit":
            set_rng_state(checkpoint["dider_rng"])

    def _forecast(
        self, batch: Batch
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """Roll out over the whole clip after the burn-in: predictions, targets [B, P, N, D], target mask
        [B, P, N], edge types [B, E, T-1] and, in ``per_agent`` mode, each target's own horizon [B, P, N]
        (None in ``global`` mode: frame p is horizon p + 1)."""
        x, mask, b = batch["states"], batch["mask"], self.hparams.burn_in
        mode = self.burn_in_mode
        pred, types = self.rollout(x, mask, b, x.shape[1] - b, mode)
        horizon = agent_horizons(mask, b)[:, b:] if mode == "per_agent" else None
        return pred, x[:, b:], mask[:, b:], types, horizon

    def validation_step(self, batch: Batch, batch_idx: int) -> None:
        bs = batch["states"].shape[0]
        terms = self.loss(self.infer(batch, hard=True))
        self.log_dict({f"val/{k}": v for k, v in terms.items()}, batch_size=bs, sync_dist=True)
        pred, target, tmask, _, horizon = self._forecast(batch)
        self.val_mse.update(pred, target, tmask, horizon)

    def on_validation_epoch_end(self) -> None:
        self._log_horizons("val/mse", self.val_mse)
        self._exit_eval_rng()

    def test_step(self, batch: Batch, batch_idx: int) -> None:
        bs = batch["states"].shape[0]
        out = self.infer(batch, hard=True)
        terms = self.loss(out)
        self.log_dict({f"test/{k}": v for k, v in terms.items() if k != "loss"}, batch_size=bs, sync_dist=True)
        pred, target, tmask, roll_types, horizon = self._forecast(batch)
        self.test_mse.update(pred, target, tmask, horizon)
        norm = getattr(getattr(self.trainer, "datamodule", None), "normalizer", None)
        if norm is not None:
            self.test_mse_raw.update(norm.denormalize(pred), norm.denormalize(target), tmask, horizon)
        post_types = out.posterior_types()
        prior_types = self.online_types(out.h_fwd)
        present = edge_mask(batch["mask"][:, :-1])  # [B, T-1, E]
        self.test_segments.update(post_types, present.any(1))
        if "edges" in batch:
            self.test_acc_post.update(post_types.transpose(1, 2), batch["edges"], present)
            self.test_acc_prior.update(prior_types.transpose(1, 2), batch["edges"], present)
            self.test_boundary.update(post_types, batch["edges"].transpose(1, 2))
        if "pair_kind" in batch:
            self.test_pairs.update(post_types, batch["pair_kind"], present.transpose(1, 2))
        self.test_types.append(post_types.masked_fill(~present.transpose(1, 2), -1).cpu())  # -1: edge absent
        self.test_probs.append(out.probs.gather(-1, post_types.unsqueeze(-1)).squeeze(-1).cpu())
        if batch_idx == 0:
            k = self.hparams.num_figure_clips
            self.figure_data = {"segments": post_types[:k].cpu(), "prior": prior_types[:k].cpu(),
                                "per_step": out.step_logits[:k].argmax(-1).cpu(), "states": batch["states"][:k].cpu(),
                                "mask": batch["mask"][:k].cpu(),
                                # test-set index of each clip: rank r of W holds clips r, r + W, ... under DDP
                                "index": torch.arange(min(k, bs)) * self.trainer.world_size + self.global_rank}
            if "edges" in batch:
                self.figure_data["truth"] = batch["edges"][:k].transpose(1, 2).cpu()

    def on_test_epoch_start(self) -> None:
        self.test_types, self.test_probs = [], []
        self._enter_eval_rng()

    def _gather_test_clips(self) -> None:
        """Under DDP rank r of W tested clips r, r + W, ... (``ClipDataModule``'s unrepeated sampler): put
        the per-clip outputs of all ranks back in test-set order on rank 0."""
        world = self.trainer.world_size
        if world == 1:
            return
        clips = [(t, p) for tb, pb in zip(self.test_types, self.test_probs, strict=True)
                 for t, p in zip(tb, pb, strict=True)]
        per_rank: list[Any] = [None] * world if self.global_rank == 0 else None
        torch.distributed.gather_object(clips, per_rank, dst=0)  # the export runs on rank 0 only
        if self.global_rank != 0:
            self.test_types, self.test_probs = [], []
            return
        ordered = [per_rank[r][j] for j in range(max(map(len, per_rank))) for r in range(world)
                   if j < len(per_rank[r])]
        self.test_types = [t[None] for t, _ in ordered]
        self.test_probs = [p[None] for _, p in ordered]

    def on_test_epoch_end(self) -> None:
        self._gather_test_clips()
        self._log_horizons("test/mse", self.test_mse)
        if self.test_mse_raw.update_count:
            self._log_horizons("test/mse_raw", self.test_mse_raw)
        per_edge, per_100 = self.test_segments.compute()
        self.log("test/segments_per_edge", per_edge)
        self.log("test/switches_per_100", per_100)
        self.test_segments.reset()
        if self.test_boundary.update_count:
            self.log("test/boundary_f1", self.test_boundary.compute())
            self.test_boundary.reset()
        for name, metric in {"posterior": self.test_acc_post, "prior": self.test_acc_prior}.items():
            if metric.update_count:
                none, inter = metric.compute()
                self.log(f"test/edge_acc/{name}/none", none)
                self.log(f"test/edge_acc/{name}/interaction", inter)
                metric.reset()
        if self.test_pairs.update_count:
            self._log_consistency()
        self._exit_eval_rng()

    def _log_consistency(self) -> None:
        """test/consistency/{parked,opposite}/{share,type,edge_steps}; a kind with no edge-steps in the test
        split logs only its (zero) count, with a warning, rather than a made-up share."""
        share, dominant, total = self.test_pairs.compute()
        for k, name in KIND_NAMES.items():
            self.log(f"test/consistency/{name}/edge_steps", total[k - 1].float())
            if total[k - 1] > 0:
                self.log(f"test/consistency/{name}/share", share[k - 1])
                self.log(f"test/consistency/{name}/type", dominant[k - 1].float())
            elif self.trainer.is_global_zero:
                log.warning("consistency check: no %s pairs in the test split (data.pairs sets the rules)", name)
        self.test_pairs.reset()

    def _log_horizons(self, prefix: str, metric: HorizonMSE) -> None:
        for h, v in zip(metric.horizons, metric.compute(), strict=True):
            self.log(f"{prefix}/h{h:02d}", v)
        metric.reset()

    def configure_optimizers(self) -> Any:
        opt = self.optimizer_factory(params=self.parameters())
        if self.scheduler_factory is None:
            return opt
        scheduler = self.scheduler_factory(optimizer=opt)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}
