"""Decoder plugins: predict x_{t+1} from x_t and the sampled edge types z_t.

Edge type 0 is "no interaction" when ``skip_first``: it sends no message and its MLP is never built.
With ``checkpoint``, teacher-forced training recomputes each step's message passing in the backward
pass instead of storing its edge-sized activations ([B, E, H] per step): only the per-agent
aggregate is kept. With ``kinematic``, the positions also move by the predicted velocity
(:class:`KinematicStep`), so the MLP learns the acceleration and not the integration. Shapes: x [B,
T, N, D], z [B, T, E, K] (one-hot or soft), mask [B, T, N] bool or None.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from dider.graph import aggregate_to_receivers, edge_index, edge_mask
from dider.models.layers import PairLinear, TypedLinear, checkpointed
from dider.models.losses import line_fit
from dider.validation import NUM_TYPES, Rule, boolean, check_settings, integer, within


class _MessagePassing(nn.Module):
    """Typed messages over directed edges, weighted by z and summed over types.

    nodes [..., N, F], z [..., E, K] -> edge messages [..., E, H].
    """

    def __init__(self, num_types: int, node_dim: int, hidden: int, skip_first: bool, act: nn.Module,
                 dropout: float):
        super().__init__()
        self.first = 1 if skip_first else 0
        self.num_msg = num_types - self.first
        if self.num_msg < 1:
            raise ValueError(f"model.num_edges={num_types}: need at least 2 edge types when type 0 "
                             "sends nothing")
        self.fc1 = PairLinear(node_dim, self.num_msg * hidden)
        self.fc2 = TypedLinear(self.num_msg, hidden, hidden)
        self.act, self.drop, self.hidden = act, nn.Dropout(dropout), hidden

    def typed(self, nodes: torch.Tensor) -> torch.Tensor:
        """Every message type's message on every edge: nodes [..., N, F] -> [..., E, K', H] (K' =
        the types that send one)."""
        pre = self.act(self.fc1(nodes))  # [..., E, K'*H]: every type's first layer in one matmul
        return self.act(self.fc2(self.drop(pre.unflatten(-1, (self.num_msg, self.hidden)))))

    def forward(self, nodes: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        msg = self.typed(nodes)  # [..., E, K', H]
        z = z[..., self.first :].to(msg.dtype)  # under autocast, keep the edge tensors in bf16
        if self.num_msg == 1:  # one pass instead of a product and a sum over a size-1 axis
            return msg.squeeze(-2) * z
        return (msg * z[..., None]).sum(-2)


class KinematicStep(nn.Module):
    """x_{t+1} = x_t + delta, then the positions (features 0, 1) move by the new velocity (features
    2, 3).

    In data units p_{t+1} = p_t + v_{t+1} dt. Positions and velocities are min/max-normalised with
    their own ranges, so in normalised units that step is affine in the velocity, p += slope * v +
    offset, with slope and offset set by dt and the two ranges. Both start at zero (the plain
    residual update); :meth:`fit` sets them by least squares on training clips before the first
    step, and training goes on from there. Learned from zero they take hundreds of steps (Adam moves
    them by about the learning rate a step), and an MLP alone learns the integration through its
    ReLU layers to about half a step's motion on small real data.
    """

    def __init__(self) -> None:
        super().__init__()
        self.slope = nn.Parameter(torch.zeros(()))
        self.offset = nn.Parameter(torch.zeros(()))

    @torch.no_grad()
    def fit(self, x: torch.Tensor, mask: torch.Tensor | None = None) -> bool:
        """Least squares of each step's position change on the new velocity over the agents present
        at both ends: x [B, T, N, D], mask [B, T, N] or None. False (and nothing set) without two
        distinct velocities."""
        dp = (x[:, 1:, :, :2] - x[:, :-1, :, :2]).float()
        v = x[:, 1:, :, 2:4].float()
        both = (torch.ones_like(dp[..., 0], dtype=torch.bool) if mask is None
                else mask[:, 1:] & mask[:, :-1])
        v, dp = v[both].flatten(), dp[both].flatten()
        if v.numel() < 2 or not v.var() > 0:
            return False
        slope, offset = line_fit(v, dp)
        self.slope.fill_(slope)
        self.offset.fill_(offset)
        return True

    def forward(self, x: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        """x, delta [..., D] with D >= 4 -> [..., D]."""
        nxt = x + delta
        pos = nxt[..., :2] + self.slope * nxt[..., 2:4] + self.offset
        return torch.cat([pos, nxt[..., 2:]], dim=-1)


# What the two decoders take alike (checked by each, and by the preflight under model.net.decoder).
DECODER_SETTINGS: dict[str, Rule] = {"num_types": NUM_TYPES, "input_dim": integer(1),
                                     "hidden": integer(1),
                                     "skip_first": boolean, "dropout": within(0.0, 1.0),
                                     "checkpoint": boolean, "kinematic": boolean}
MARKOV_SETTINGS: dict[str, Rule] = DECODER_SETTINGS | {"prediction_steps": integer(1)}


def _state_update(kinematic: bool, input_dim: int) -> KinematicStep | None:
    if kinematic and input_dim < 4:
        raise ValueError("model.net.decoder.kinematic=true needs positions and velocities: "
                         f"input_dim={input_dim} < 4")
    return KinematicStep() if kinematic else None


class MarkovDecoder(nn.Module):
    """NRI/DNRI's Markovian MLP decoder: messages from the current states, summed over senders.

    Under teacher forcing it has no recurrence, so all steps run in one batched call.
    """

    stateless = True
    SETTINGS = MARKOV_SETTINGS

    def __init__(
        self,
        num_types: int,
        input_dim: int = 4,
        hidden: int = 256,
        skip_first: bool = True,
        dropout: float = 0.0,
        checkpoint: bool = False,
        kinematic: bool = False,
        prediction_steps: int = 1,
    ) -> None:
        """prediction_steps: in training, each prediction starts from the true state at most this
        many steps back and feeds the decoder its own predictions since (NRI's multi-step training:
        with 1, teacher forcing at every step, a decoder can fit short-range dynamics without the
        edges, whose effect shows over several steps)."""
        super().__init__()
        check_settings(self, locals())
        self.checkpoint = checkpoint
        self.prediction_steps = prediction_steps
        self.kinematic = _state_update(kinematic, input_dim)
        self.messages = _MessagePassing(num_types, input_dim, hidden, skip_first, nn.ReLU(),
                                        dropout)
        self.out = nn.Sequential(
            nn.Linear(input_dim + hidden, hidden), nn.ReLU(), nn.Dropout(dropout),
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Dropout(dropout),
            nn.Linear(hidden, input_dim),
        )  # fmt: skip

    def _aggregate(self, x: torch.Tensor, z: torch.Tensor,
                   mask: torch.Tensor | None) -> torch.Tensor:
        """Messages summed over senders: x [..., N, D], z [..., E, K], mask [..., N] or None ->
        [..., N, H]."""
        msg = self.messages(x, z)
        if mask is not None:
            msg = msg * edge_mask(mask).unsqueeze(-1).to(msg.dtype)
        return aggregate_to_receivers(msg, x.shape[-2])

    def forward(self, x: torch.Tensor, z: torch.Tensor,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        """Prediction of every next state, x [B, T, N, D], z [B, T, E, K] -> [B, T, N, D]:
        teacher-forced, or with ``prediction_steps`` > 1 from the true state at the start of each
        block of that many steps."""
        if self.prediction_steps > 1:
            return self._blocks(x, z, mask)
        if self.checkpoint and torch.is_grad_enabled():
            # One checkpoint per step, so that the backward pass re-creates one step's edge
            # activations at a time, not the whole clip's at once. unbind, not [:, s]: see
            # RecurrentDecoder.forward. With dropout the per-step calls draw other (equally
            # distributed) masks than the one batched call would.
            masks = [None] * x.shape[1] if mask is None else mask.unbind(1)
            steps = zip(x.unbind(1), z.unbind(1), masks, strict=True)
            agg = torch.stack([checkpointed(self._aggregate, *step) for step in steps], dim=1)
        else:
            agg = self._aggregate(x, z, mask)
        return self._next(x, self.out(torch.cat([x, agg], dim=-1)))

    def _next(self, x: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
        return x + delta if self.kinematic is None else self.kinematic(x, delta)

    @torch.no_grad()
    def edge_evidence(self, x: torch.Tensor, z: torch.Tensor, target: torch.Tensor,
                      mask: torch.Tensor | None,
                      nll: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor:
        """What each edge's interaction tells its receiver's next state: the one-step NLL of the
        receiver with the edge at "none" minus the least NLL over the interaction types, every other
        edge as ``z`` holds it.

        x [B, T, N, D] (the states predicted from), z [B, T, E, K], target [B, T, N, D] (the next
        states), mask [B, T, N] or None; nll(pred, target) [..., D] twice -> [...]: one agent-step's
        NLL. -> [B, T, E] (0 where the edge is absent). About zero where the decoder predicts the
        receiver alike with and without the edge."""
        if why := evidence_problem(self):
            raise ValueError(f"the edge evidence {why}")
        # at least float32: NLLs of thousands of nats differ by one
        dtype = torch.promote_types(self.out[0].weight.dtype, torch.float32)
        with torch.autocast(x.device.type, enabled=False):
            return self._evidence(x.to(dtype), z.to(dtype), target.to(dtype), mask, nll)

    def _evidence(self, x: torch.Tensor, z: torch.Tensor, target: torch.Tensor,
                  mask: torch.Tensor | None,
                  nll: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor:
        n = x.shape[-2]
        recv = edge_index(n, x.device)[1]
        msg = self.messages.typed(x)  # [B, T, E, K', H]
        # [B, T, E, 1]
        present = None if mask is None else edge_mask(mask).unsqueeze(-1).to(msg.dtype)
        # [B, T, E, H]: each edge's message as z holds it
        held = (msg * z[..., 1:, None].to(msg.dtype)).sum(-2)
        if present is not None:
            held, msg = held * present, msg * present.unsqueeze(-1)
        agg = aggregate_to_receivers(held, n)  # [B, T, N, H]
        base = agg.index_select(-2, recv) - held  # the receiver's messages without the edge
        # [B, T, E, K, H]: none, types
        options = torch.cat([base.unsqueeze(-2), base.unsqueeze(-2) + msg], -2)
        x_r = x.index_select(-2, recv).unsqueeze(-2).expand(*options.shape[:-1], x.shape[-1])
        pred = self._next(x_r, self.out(torch.cat([x_r, options], -1)))
        # [B, T, E, K]
        cost = nll(pred, target.index_select(-2, recv).unsqueeze(-2).expand_as(pred))
        evidence = cost[..., 0] - cost[..., 1:].amin(-1)
        return evidence if present is None else evidence * present.squeeze(-1)

    def _blocks(self, x: torch.Tensor, z: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
        """Every block of P = prediction_steps steps rolled out from its first true state, all
        blocks at once (P batched steps): x [B, T, N, D], z [B, T, E, K], mask [B, T, N] or None ->
        [B, T, N, D]."""
        p, t = self.prediction_steps, x.shape[1]
        # the last block is cut short: pad it with its last step and drop those predictions
        pad = -t % p

        def blocks(a: torch.Tensor) -> torch.Tensor:  # [B, T, ...] -> [B, T / P, P, ...]
            a = torch.cat([a, a[:, -1:].expand(-1, pad, *a.shape[2:])], 1) if pad else a
            return a.unflatten(1, (-1, p))

        zb, mb = blocks(z), None if mask is None else blocks(mask)
        cur, preds = blocks(x)[:, :, 0], []
        for k in range(p):
            cur, _ = self.step(cur, zb[:, :, k], None, None if mb is None else mb[:, :, k])
            preds.append(cur)
        return torch.stack(preds, 2).flatten(1, 2)[:, :t]

    def init_state(self, batch: int, num_agents: int, ref: torch.Tensor) -> None:
        return None

    def step(
        self, x_t: torch.Tensor, z_t: torch.Tensor, state: None, mask_t: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, None]:
        """One step: x_t [B, N, D], z_t [B, E, K] -> prediction of x_{t+1} [B, N, D]."""
        return self._next(x_t, self.out(torch.cat([x_t, self._aggregate(x_t, z_t, mask_t)],
                                                  dim=-1))), None


class RecurrentDecoder(nn.Module):
    """DNRI's recurrent GNN decoder: messages from the agents' hidden states, a GRU-style update
    driven by x_t and the aggregated message, and a residual output MLP."""

    stateless = False
    SETTINGS = DECODER_SETTINGS

    def __init__(
        self,
        num_types: int,
        input_dim: int = 4,
        hidden: int = 256,
        skip_first: bool = True,
        dropout: float = 0.0,
        checkpoint: bool = False,
        kinematic: bool = False,
    ) -> None:
        super().__init__()
        check_settings(self, locals())
        self.checkpoint = checkpoint
        self.kinematic = _state_update(kinematic, input_dim)
        self.messages = _MessagePassing(num_types, hidden, hidden, skip_first, nn.Tanh(), dropout)
        self.type_norm = float(num_types - 1 if skip_first else num_types)
        self.input_gates = nn.Linear(input_dim, 3 * hidden)  # W_r, W_i, W_n with bias
        self.message_gates = nn.Linear(hidden, 3 * hidden, bias=False)  # U_r, U_i, U_n
        self.out = nn.Sequential(
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Dropout(dropout),
            nn.Linear(hidden, hidden), nn.ReLU(), nn.Dropout(dropout),
            nn.Linear(hidden, input_dim),
        )  # fmt: skip
        self.hidden = hidden

    def init_state(self, batch: int, num_agents: int, ref: torch.Tensor) -> torch.Tensor:
        return ref.new_zeros(batch, num_agents, self.hidden)

    def _aggregate(self, h: torch.Tensor, z_t: torch.Tensor,
                   mask_t: torch.Tensor | None) -> torch.Tensor:
        """Mean message over present senders: h [B, N, H], z_t [B, E, K], mask_t [B, N] or None ->
        [B, N, H]."""
        n = h.shape[-2]
        msg = self.messages(h, z_t) / self.type_norm
        if mask_t is None:
            return aggregate_to_receivers(msg, n) / max(n - 1, 1)
        em = edge_mask(mask_t).unsqueeze(-1).to(msg.dtype)
        count = aggregate_to_receivers(em, n).clamp_min(1.0)
        return aggregate_to_receivers(msg * em, n) / count

    def _update(
        self,
        gates_x: torch.Tensor,
        z_t: torch.Tensor,
        h: torch.Tensor,
        mask_t: torch.Tensor | None,
        checkpoint: bool = False,
    ) -> torch.Tensor:
        """gates_x [B, N, 3H] (input projections), z_t [B, E, K], h [B, N, H] -> new h [B, N, H]."""
        agg = (checkpointed(self._aggregate, h, z_t, mask_t) if checkpoint
               else self._aggregate(h, z_t, mask_t))
        new = self._gru(gates_x, agg, h)
        if mask_t is not None:  # absent agents keep their state
            new = torch.where(mask_t.unsqueeze(-1), new, h)
        return new

    def _gru(self, gates_x: torch.Tensor, agg: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """The gated update: gates_x [..., 3H], agg [..., H] (the mean message), h [..., H] -> new h
        [..., H]."""
        xr, xi, xn = gates_x.chunk(3, dim=-1)
        mr, mi, mn = self.message_gates(agg).chunk(3, dim=-1)
        r, i = torch.sigmoid(xr + mr), torch.sigmoid(xi + mi)
        return (1 - i) * torch.tanh(xn + r * mn) + i * h

    def forward(self, x: torch.Tensor, z: torch.Tensor,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        """Teacher-forced: x [B, T, N, D], z [B, T, E, K] -> predictions of x_{t+1}, [B, T, N,
        D]."""
        b, t, n, _ = x.shape
        h = self.init_state(b, n, x)
        # All steps' input projections at once (only the message path is recurrent), split by
        # unbind: the backward of indexing [:, s] would allocate a zero gradient of the whole tensor
        # at every step.
        gates_x, z_steps = self.input_gates(x).unbind(1), z.unbind(1)
        mask_steps = [None] * t if mask is None else mask.unbind(1)
        hs = []
        checkpoint = self.checkpoint and torch.is_grad_enabled()
        for s in range(t):
            h = self._update(gates_x[s], z_steps[s], h, mask_steps[s], checkpoint)
            hs.append(h)
        return self._next(x, self.out(torch.stack(hs, dim=1)))

    def step(
        self, x_t: torch.Tensor, z_t: torch.Tensor, h: torch.Tensor,
        mask_t: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One step: x_t [B, N, D], z_t [B, E, K], h [B, N, H] -> (prediction of x_{t+1}, new h)."""
        h = self._update(self.input_gates(x_t), z_t, h, mask_t)
        return self._next(x_t, self.out(h)), h

    _next = MarkovDecoder._next
    # the same contract; the options are scored by _evidence below
    edge_evidence = MarkovDecoder.edge_evidence

    def _evidence(self, x: torch.Tensor, z: torch.Tensor, target: torch.Tensor,
                  mask: torch.Tensor | None,
                  nll: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor:
        """Each step's update of the receiver from its state before it (the teacher-forced
        recurrence with z as drawn, replayed once), the edge's share of the mean message swapped:
        one step of evidence, not what the edge leaves in later states."""
        (b, t, n, _), recv = x.shape, edge_index(x.shape[-2], x.device)[1]
        gates_x, h, before = self.input_gates(x), self.init_state(b, n, x), []
        for s in range(t):  # the recurrence: sequential in time only
            before.append(h)
            h = self._update(gates_x[:, s], z[:, s], h, None if mask is None else mask[:, s])
        h_prev = torch.stack(before, 1)  # [B, T, N, H]
        msg = self.messages.typed(h_prev) / self.type_norm  # [B, T, E, K', H]
        if mask is None:
            present, count = None, torch.full((), float(max(n - 1, 1)), dtype=msg.dtype,
                                              device=msg.device)
        else:
            present = edge_mask(mask).unsqueeze(-1).to(msg.dtype)  # [B, T, E, 1]
            msg = msg * present.unsqueeze(-1)
            count = (aggregate_to_receivers(present, n).clamp_min(1.0).index_select(-2, recv)
                     .unsqueeze(-2))
        held = (msg * z[..., self.messages.first:, None].to(msg.dtype)).sum(-2)  # [B, T, E, H]
        base = aggregate_to_receivers(held, n).index_select(-2, recv) - held  # the receiver's sum without the edge
        options = torch.cat([base.unsqueeze(-2), base.unsqueeze(-2) + msg], -2) / count  # [B, T, E, K, H]: means

        # each edge's receiver: [B, T, N, F] -> [B, T, E, 1, F]
        def pick(a: torch.Tensor) -> torch.Tensor:
            return a.index_select(-2, recv).unsqueeze(-2)

        new = self._gru(pick(gates_x), options, pick(h_prev))
        x_r = pick(x).expand(*options.shape[:-1], x.shape[-1])
        cost = nll(self._next(x_r, self.out(new)), pick(target).expand_as(x_r))  # [B, T, E, K]
        evidence = cost[..., 0] - cost[..., 1:].amin(-1)
        return evidence if present is None else evidence * present.squeeze(-1)


def evidence_problem(decoder: nn.Module) -> str | None:
    """Why ``decoder`` cannot score each edge's evidence (:meth:`MarkovDecoder.edge_evidence`), said
    as the end of a sentence about the evidence; None when it can."""
    if not hasattr(decoder, "edge_evidence"):
        return f"{type(decoder).__name__} does not give (model.net.decoder=markov and recurrent do)"
    if decoder.messages.first != 1:
        return "needs type 0 to send no message (model.net.decoder.skip_first=true)"
    # each option would draw its own dropout masks: the difference would be noise
    if decoder.messages.drop.p > 0:
        return "is scored without dropout (model.net.decoder.dropout=0)"
    return None
