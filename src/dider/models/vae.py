"""The relational VAE as a plain ``nn.Module``: inference, online edges and the forecast roll-out; its loss is
the ``objective``'s (:mod:`dider.models.objective`).

DNRI, DIDER, DIDER (with SKID) and NRI differ only in the plugins and objective the model is built with (see
:mod:`dider.models.plugins`): the duration plugin decides how each edge's time axis is cut into segments,
and the edge posterior and prior are read once per segment. With one-step segments this is exactly DNRI.
Nothing here needs Lightning: schedules come in as a :class:`Progress`, the forecast protocol as arguments.

Shapes: B batch, T frames, N agents, D = 4 features, E = N(N-1) edges, K edge types, S segment slots,
R LSTM width, P predicted steps.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any, ClassVar

import torch
import torch.nn.functional as F
from omegaconf import DictConfig
from torch import nn

from dider.graph import edge_index, edge_mask
from dider.models.checkpoint_format import network_config, read
from dider.models.decoders import evidence_problem
from dider.models.given_cut import cut_segmentation
from dider.models.inference import Inference, pick_types, plain_config  # noqa: F401 (re-exported)
from dider.models.likelihood import GaussianNLL
from dider.models.objective import Objective
from dider.models.plugins import (
    Decoder,
    Duration,
    DurationCapabilities,
    Encoder,
    KinematicDecoder,
    Prior,
    Progress,
    missing_members,
)
from dider.models.segments import Segmentation, entries
from dider.protocol import fill_absent, observed_inputs
from dider.targets import build, check, named_targets
from dider.validation import Rule, above, boolean, check_settings, integer, one_of, text


class RelationalVAE(nn.Module):
    """Encoder -> per-segment edge posterior q and learned prior p -> decoder, trained with the ``objective``'s
    terms (:mod:`dider.models.objective`: the NLL, the edge and duration KLs, and optional terms)."""

    SETTINGS: ClassVar[dict[str, Rule]] = {
        "num_edges": integer(2, " (type 0 is 'no interaction': a relation needs another type)"),
        "gumbel_tau": above(0), "posterior_readout": one_of("start", "mean"),
        "rollout_edges": one_of("sample", "argmax"), "forecast_edges": one_of("prior", "burn_in"),
        "decoder_edges": boolean, "name": text,
    }

    def __init__(
        self,
        encoder: Encoder,
        prior: Prior,
        duration: Duration,
        decoder: Decoder,
        objective: Objective,
        num_edges: int = 2,
        gumbel_tau: float = 0.5,
        rollout_edges: str = "sample",
        posterior_readout: str = "start",
        forecast_edges: str = "prior",
        decoder_edges: bool = True,
        name: str = "model",
    ) -> None:
        """num_edges: the number of edge types K (type 0 is "no interaction"). gumbel_tau: the Gumbel-softmax
        temperature of the decoder's edge draws in training. rollout_edges: ``sample`` (DNRI) or ``argmax`` prior
        edge types in roll-outs. posterior_readout: a segment's posterior type read at its first step (``start``,
        the paper) or pooled over its steps (``mean``). forecast_edges: where roll-outs take their edges from:
        ``prior`` (the online prior and duration, DNRI and DIDER) or ``burn_in`` (the posterior of the burn-in
        alone, one type per edge held for the whole roll-out: NRI). decoder_edges: False switches every edge off
        for the decoder (the ``static_decoder`` baseline: the learned per-agent dynamics alone)."""
        super().__init__()
        check_settings(self, locals())
        seams = {"encoder": (encoder, Encoder), "prior": (prior, Prior), "duration": (duration, Duration),
                 "decoder": (decoder, Decoder)}
        for key, (plugin, interface) in seams.items():
            if missing := missing_members(plugin, interface):  # a user's plugin: say what it lacks, up front
                raise TypeError(f"model.net.{key}: {type(plugin).__name__} is not a {interface.__name__} plugin "
                                f"(missing {missing}; see dider.models.plugins)")
        if not isinstance(objective, Objective):
            raise TypeError(f"model.net.objective: {type(objective).__name__} is not a "
                            f"dider.models.objective.Objective")
        if objective.needs_evidence and (why := evidence_problem(decoder)):
            raise ValueError(f"model.net.objective: a term reads each edge's evidence, which {why}; "
                             "DIDER's objective without the indifference prior reads none: model/net/objective=dider")
        self.encoder, self.prior, self.duration, self.decoder = encoder, prior, duration, decoder
        self.objective, self.num_types, self.name = objective, num_edges, name
        self.gumbel_tau, self.rollout_edges, self.posterior_readout = gumbel_tau, rollout_edges, posterior_readout
        self.forecast_edges, self.decoder_edges = forecast_edges, decoder_edges
        self.capabilities = DurationCapabilities.of(duration)  # the duration's optional members, read once
        # a decoder with a kinematic step to fit before training (not kept as a module here: one state-dict key)
        self.fits_kinematics = not missing_members(decoder, KinematicDecoder) and decoder.kinematic is not None

    @property
    def likelihood(self) -> GaussianNLL:
        """The decoder's Gaussian likelihood: the objective's ``nll`` term."""
        return self.objective.terms["nll"]

    @classmethod
    def from_config(cls, cfg: DictConfig | Mapping[str, Any]) -> RelationalVAE:
        """Build the network from the caller's own model config (``cfg.model`` of the Hydra app: its ``net`` node,
        or a network's config): every class it names is the caller's choice. A config read from a file is built by
        :meth:`from_file_config`."""
        node = network_config(plain_config(cfg))
        return build(node, "network", "model config", "model.net", trust=named_targets(node))

    @classmethod
    def from_file_config(cls, node: Mapping[str, Any], where: str | Path, path: str = "hyper_parameters.net",
                         trust: Collection[str] = ()) -> RelationalVAE:
        """The network a file's config describes (a checkpoint's ``hyper_parameters["net"]``), built only from
        dider's own classes and the ``trust``-ed ones (:mod:`dider.targets`); ``where`` and ``path`` name the
        file and the node in a refusal."""
        return build(node, "network", where, path, trust)

    @classmethod
    def from_checkpoint(cls, path: str | Path, trust: Collection[str] = ()) -> RelationalVAE:
        """The network a training checkpoint (``checkpoints/*.ckpt`` of a run, any format) holds, with its weights,
        read once; its config is checked whole (``trust``: classes of your own it may name) before anything is
        built."""
        ckpt = read(path)
        check(ckpt["hyper_parameters"], "module", path, "hyper_parameters", trust)
        return cls.from_file_config(ckpt["hyper_parameters"]["net"], path, trust=trust)._load_state(ckpt["state_dict"])

    def load_checkpoint(self, path: str | Path) -> RelationalVAE:
        """Load the weights of a training checkpoint (``checkpoints/*.ckpt`` of a run, any format) into this model."""
        return self._load_state(read(path)["state_dict"])

    def _load_state(self, state: Mapping[str, torch.Tensor]) -> RelationalVAE:
        self.load_state_dict({k.removeprefix("model."): v for k, v in state.items()})
        return self

    # ------------------------------------------------------------------ inference and loss
    def infer(self, batch: Mapping[str, torch.Tensor], hard: bool, progress: Progress = Progress(),
              cut: torch.Tensor | None = None) -> Inference:
        """Teacher-forced pass: posterior edges per segment drive one-step predictions of every frame.

        batch: ``states`` [B, T, N, D], ``mask`` [B, T, N] bool, optionally ``everyone`` (a bool: every agent
        present; without it the mask is read on the host). cut: [B, E, T-1] bool, a given segmentation
        (a segment starts at each true step; the fixed boundaries of ``forced_boundaries`` are added) in place of
        the duration plugin's, scored with :func:`~dider.models.given_cut.cut_segmentation` (``analysis.diagnose``)."""
        x, mask = batch["states"], batch["mask"]
        # With every agent present the plugins skip their masking passes; the batch says so (``everyone``): asking
        # the mask would make the device wait for the host.
        everyone = batch.get("everyone")
        plugin_mask = None if (bool(mask.all()) if everyone is None else everyone) else mask
        enc = self.encoder(x, plugin_mask)
        present = edge_mask(mask[:, :-1]).transpose(1, 2)  # [B, E, T-1]
        given = None if plugin_mask is None else present
        if cut is not None:
            seg: Segmentation = cut_segmentation(self.duration, self.capabilities, enc.h_fwd, enc.h_rev, cut, present,
                                                 enc.posterior_logits)
        elif self.capabilities.held_type:  # the end's prior reads each segment's type: the posterior's at each start
            seg = self.duration.segment(enc.h_fwd, enc.h_rev, x, progress, given,
                                        types=F.softmax(enc.posterior_logits.float(), -1))
        else:
            seg = self.duration.segment(enc.h_fwd, enc.h_rev, x, progress, given)
        q_seg = self.segment_posterior(enc.posterior_logits, seg)
        p_step = self.prior(enc.h_fwd)  # [B, E, T-1, K]; read at a segment's first step, so it stays online
        z = seg.spread(F.gumbel_softmax(q_seg, tau=self.gumbel_tau, hard=hard))  # [B, E, T-1, K]
        z = z if self.decoder_edges else torch.zeros_like(z)
        pred = self.decoder(x[:, :-1], z.transpose(1, 2), None if plugin_mask is None else mask[:, :-1])
        probs = seg.spread(F.softmax(q_seg, dim=-1))
        out = Inference(pred, q_seg, seg.gather(p_step), probs, enc.posterior_logits, p_step, seg, enc.h_fwd, present)
        if self.objective.reads_evidence(progress):
            _, recv = edge_index(x.shape[2], x.device)
            evidence = self.decoder.edge_evidence(x[:, :-1], z.transpose(1, 2), x[:, 1:], None if plugin_mask is None
                                                  else mask[:, :-1], self.likelihood.each)  # [B, T-1, E]
            out.evidence = evidence.masked_fill(~mask[:, 1:].index_select(2, recv), float("inf")).transpose(1, 2)
        if self.capabilities.held_type:  # the online boundary model, fitted at every step to the held type's changes
            out.boundary_fit = self.duration.boundary_fit(enc.h_fwd, out.posterior_types().detach(), present)
        out.terms = self.objective.values(out, batch)
        return out

    def segment_posterior(self, step_logits: torch.Tensor, seg: Segmentation) -> torch.Tensor:
        """A segment's posterior logits: read at its first step (the paper) or pooled over its steps.
        step_logits [B, E, T, K] -> [B, E, S, K]."""
        return seg.pool(step_logits) if self.posterior_readout == "mean" else seg.gather(step_logits)

    def schedule(self, progress: Progress = Progress()) -> dict[str, float]:
        """The annealed weights at ``progress``: the objective's (the KL weight, the capacities) and, for a
        duration plugin that has one, the soft-step temperature ``tau``."""
        out = self.objective.schedule(progress)
        if self.capabilities.tau:
            out["tau"] = self.duration.tau(progress)
        return out

    def loss(self, out: Inference, progress: Progress = Progress()) -> dict[str, torch.Tensor]:
        """The objective of a pass at ``progress``: ``loss``, each term's batch mean, and ``nelbo``, the objective
        free of schedules (for model selection)."""
        return self.objective(out.terms, progress)

    @torch.no_grad()
    def describe(self, out: Inference, mask: torch.Tensor) -> dict[str, torch.Tensor]:
        """What the model says about each edge of a clip, per transition t -> t+1 (what exports and prediction
        write). out: a hard :meth:`infer` pass, mask [B, T, N] ->
        ``segments`` (the segments' posterior types), ``per_step`` (per-step posterior types before
        segmentation), ``prior`` (the online prior's types, past only): each [B, E, T-1] long, -1 where the
        edge is absent; ``probs`` [B, E, T-1] the probability of the segment's type; ``step_probs``
        [B, E, T-1, K] per-step posterior probabilities."""
        absent = ~edge_mask(mask[:, :-1]).transpose(1, 2)  # [B, E, T-1]
        posterior = out.posterior_types()
        return {"segments": posterior.masked_fill(absent, -1),
                "probs": out.probs.gather(-1, posterior.unsqueeze(-1)).squeeze(-1),
                "per_step": out.step_logits.argmax(-1).masked_fill(absent, -1),
                "prior": self.online_types(out.h_fwd, ~absent).masked_fill(absent, -1),
                "step_probs": F.softmax(out.step_logits.float(), dim=-1)}

    # ------------------------------------------------------------------ online edges and roll-out
    def advance_edges(
        self, h_t: torch.Tensor, t: int, end: int, etype: torch.Tensor, left: torch.Tensor, sample: bool,
        entered: torch.Tensor | None = None, start: torch.Tensor | None = None, draw: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Online segment state machine, vectorised over [B, E]: when an edge's segment has no steps left (the
        burn-in's end, or a duration run out), a new type comes from the prior and a new duration from the duration
        plugin; where the plugin's optional ``boundary`` fires first, the segment ends there too. A plugin whose
        segments are runs of one type (``excludes_held``) reads its boundary with the held type and the segment's
        age, and a boundary of its brings the prior's most likely other type. entered: [B, E] bool, the edges
        present at t and not at t - 1 (None: none entered); there the type is read afresh and the segment's
        duration runs on, as training splits a slot at an entry (``Segmentation.split_at``). start: [B, E] long,
        the step each edge's segment started (None: 0). draw: a sampled future: the boundaries drawn with the
        hazard's probability and the type head's flip read from a drawn type, not the most likely one. -> the types
        held at t, the steps left, the starts."""
        caps = self.capabilities
        start = torch.zeros_like(etype) if start is None else start
        ran_out = left <= 0
        fired = torch.zeros_like(ran_out)
        extra = {"draw": True} if draw else {}
        if caps.boundary:
            fired = self.duration.boundary(h_t, t, end, etype, t - start, **extra) if caps.held_type else \
                self.duration.boundary(h_t, t, end, **extra)
        logits = self.prior(h_t)
        new = pick_types(logits, sample or draw)
        if caps.online_retype and t > caps.observed:  # the past shows another type than the one held
            fired = fired | ((new if draw else logits.argmax(-1)) != etype)
        need = ran_out | fired
        fresh = ran_out if entered is None else ran_out | entered  # read afresh: any type
        if caps.held_type and self.duration.excludes_held:  # a boundary of a run: another type than the held one
            other = pick_types(logits.masked_fill(etype.unsqueeze(-1) == torch.arange(
                logits.shape[-1], device=logits.device), float("-inf")), sample or draw)
            new = torch.where(fired & ~fresh, other, new)
        retype = need | fresh
        etype = torch.where(retype, new, etype)
        start = torch.where(retype, t, start)
        left = torch.where(need, self.duration.next_duration(h_t, t, end), left) - 1
        return etype, left, start

    @torch.no_grad()
    def online_types(self, h_fwd: torch.Tensor, present: torch.Tensor | None = None) -> torch.Tensor:
        """Prior-only (past-only) edge types over a clip: h_fwd [B, E, T, R], present [B, E, T] bool (the
        edges present at each step; None: all) -> [B, E, T] long."""
        b, e, t, _ = h_fwd.shape
        etype = torch.zeros(b, e, dtype=torch.long, device=h_fwd.device)
        left, start = torch.zeros_like(etype), torch.zeros_like(etype)
        entered = None if present is None else entries(present)
        types = []
        for s in range(t):
            step_entered = None if entered is None else entered[..., s]
            etype, left, start = self.advance_edges(h_fwd[:, :, s], s, t, etype, left, sample=False,
                                                    entered=step_entered, start=start)
            types.append(etype)
        return torch.stack(types, dim=2)

    @torch.no_grad()
    def burn_in_edges(self, x_obs: torch.Tensor, mask_obs: torch.Tensor, end: int, draw: bool = False) -> torch.Tensor:
        """NRI's forecast edges: the posterior of the observed frames alone, one type per edge (the readout
        of the segment that holds the last observed transition: NRI's one segment, or where agents come and
        go the edge's last stretch of presence; drawn from it with ``draw``), held for all ``end`` transitions.
        x_obs [B, T_obs, N, D], mask_obs [B, T_obs, N] -> [B, E, end]."""
        if x_obs.shape[1] < 2:
            raise ValueError("forecast_edges=burn_in: the burn-in needs at least 2 frames (one transition)")
        everyone = bool(mask_obs.all())
        enc = self.encoder(x_obs, None if everyone else mask_obs)
        present = None if everyone else edge_mask(mask_obs[:, :-1]).transpose(1, 2)
        seg = self.duration.segment(enc.h_fwd, enc.h_rev, x_obs, present=present)
        logits = seg.spread(self.segment_posterior(enc.posterior_logits, seg))[:, :, -1]  # [B, E, K]
        return pick_types(logits, self.rollout_edges == "sample" or draw).unsqueeze(-1).expand(-1, -1, end)

    @torch.no_grad()
    def sample_futures(self, x: torch.Tensor, mask: torch.Tensor, burn_in: int, num_pred: int,
                       mode: str = "global", samples: int = 6, draw: bool = True) -> torch.Tensor:
        """``samples`` forecasts of every clip, [B, K, P, N, D]: one roll-out of the batch repeated K times, whose
        edges are drawn from the prior (the types, and the segments' ends where the duration has them; NRI's from
        the burn-in posterior), under :meth:`rollout`'s protocol; ``draw=False``: the model's own roll-out, K times."""
        b = x.shape[0]
        pred, _ = self.rollout(x.repeat_interleave(samples, 0), mask.repeat_interleave(samples, 0), burn_in,
                               num_pred, mode, draw=draw)
        return pred.view(b, samples, *pred.shape[1:])

    @torch.no_grad()
    def rollout(
        self, x: torch.Tensor, mask: torch.Tensor, burn_in: int, num_pred: int, mode: str = "global",
        edges: torch.Tensor | None = None, decoder: nn.Module | None = None, draw: bool = False,
        edges_off: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Forecast: ground truth during the burn-in, then the model's own predictions.

        mode ``global``: every agent's input is ground truth for the window's first ``burn_in`` frames, its
        own prediction afterwards; x may hold only those frames, [B, >=burn_in, N, D].
        mode ``per_agent`` (agents entering mid-window, DNRI's inD protocol): agent i's input at frame t is
        ground truth while t is among its own first ``burn_in`` present frames (``burn_in_mask``), its own
        previous prediction afterwards; absent agents are zeros and masked. x: [B, >=burn_in+P-1, N, D].
        With every agent present from frame 0 both modes compute the same thing, bit for bit.

        Edges (``forecast_edges``) come from the prior, read from the forward LSTM that is advanced on the
        inputs above, so no state after an agent's burn-in is ever seen, or from the burn-in's posterior
        (NRI); or they are given: ``edges`` [B, E, >=burn_in+P-1] long (e.g. the ground truth or the
        posterior of the whole clip, to tell the decoder's error from the edge forecast's). mask:
        [B, >=burn_in+P, N] (agents present) -> predictions of x_burn_in..x_{burn_in+P-1} [B, P, N, D] (an
        agent's frame t is predicted from its input at t-1) and the edge types used at each transition
        [B, E, burn_in+P-1]. ``decoder``: another decoder to roll out under the same protocol and masks (the
        constant-velocity forecast that test scores beside the model's), else the model's own. ``draw``: the online
        edges drawn from the prior, types and segment ends, or NRI's from the burn-in posterior (a sampled future).
        ``edges_off``: the decoder gets no edge at all, whatever type 0 means to it (its own dynamics alone).
        """
        decoder = self.decoder if decoder is None else decoder
        if burn_in < 1 or num_pred < 1:
            raise ValueError(f"rollout: need burn_in >= 1 and num_pred >= 1, got {burn_in}, {num_pred}")
        b, n = x.shape[0], x.shape[2]
        end = burn_in + num_pred - 1  # transitions covered
        sample = self.rollout_edges == "sample"
        fed, t_obs, x_obs = observed_inputs(x, mask, burn_in, end, mode)
        if edges is None and self.forecast_edges == "burn_in":
            edges = self.burn_in_edges(x_obs, mask[:, :t_obs], end, draw)
        online = edges is None  # the prior picks the edges as the roll-out goes
        if online:
            h_past, enc_state = self.encoder.past(x_obs, mask[:, :t_obs])
        elif edges.shape[-1] < end:
            raise ValueError(f"rollout: edges cover {edges.shape[-1]} transitions, need {end}")
        etype = torch.zeros(b, n * (n - 1), dtype=torch.long, device=x.device)
        left, start = torch.zeros_like(etype), torch.zeros_like(etype)
        dec_state = decoder.init_state(b, n, x)
        preds, types = [], []
        cur = x[:, 0]
        present = edge_mask(mask[:, :end])  # [B, end, E]
        entered = entries(present.transpose(1, 2))  # [B, E, end]
        for t in range(end):
            m_t = mask[:, t]
            if t < t_obs:
                cur = x_obs[:, t]
                if online:
                    h_t = h_past[:, :, t]
            else:  # t >= t_obs >= burn_in: cur holds the previous step's prediction
                if fed is not None:
                    cur = fill_absent(torch.where(fed[:, t, :, None], x[:, t], cur), m_t)
                if online:
                    h_t, enc_state = self.encoder.step(cur, enc_state, m_t)
            if online:
                etype, left, start = self.advance_edges(h_t, t, end, etype, left, sample, entered[..., t], start,
                                                        draw)
            else:
                etype = edges[:, :, t]
            types.append(etype)
            # No input before burn_in - 1 is ever a prediction (an agent needs burn_in present frames
            # first), so a stateless decoder has nothing to do there.
            if t < burn_in - 1 and decoder.stateless:
                continue
            z_t = F.one_hot(etype, self.num_types).to(x.dtype) * (
                present[:, t, :, None] & self.decoder_edges & (not edges_off))
            out, dec_state = decoder.step(cur, z_t, dec_state, m_t)
            if t >= burn_in - 1:
                preds.append(out)
                cur = out
        return torch.stack(preds, dim=1), torch.stack(types, dim=2)

    @torch.no_grad()
    def forecast_after(self, x: torch.Tensor, mask: torch.Tensor, burn_in: int, steps: int,
                       decoder: nn.Module | None = None, samples: int = 0) -> torch.Tensor:
        """Forecast where nothing after the burn-in is known (new data, prediction): the agents present at the
        burn-in's last frame carry on. x [B, >=burn_in, N, D], mask [B, >=burn_in, N] -> [B, steps, N, D];
        with ``samples`` K > 0, K futures of each clip whose online edges are drawn (:meth:`sample_futures`)
        -> [B, K, steps, N, D]. ``decoder``: another decoder under the same protocol (as in :meth:`rollout`),
        which reads no edges: the model's encoder and prior are left alone (and draw nothing)."""
        mask = torch.cat([mask[:, :burn_in], mask[:, burn_in - 1 : burn_in].expand(-1, steps, -1)], dim=1)
        if samples:
            return self.sample_futures(x[:, :burn_in], mask, burn_in, steps, samples=samples)
        n = x.shape[2]
        edges = None if decoder is None else x.new_zeros(x.shape[0], n * (n - 1), burn_in + steps - 1, dtype=torch.long)
        return self.rollout(x[:, :burn_in], mask, burn_in, steps, edges=edges, decoder=decoder)[0]

    def forward(
        self, x: torch.Tensor, mask: torch.Tensor, burn_in: int, num_pred: int, mode: str = "global"
    ) -> torch.Tensor:
        """Inference entry point: the forecast of :meth:`rollout`, [B, P, N, D]."""
        return self.rollout(x, mask, burn_in, num_pred, mode)[0]
