"""The forecast protocol: which frames a model observes before it forecasts, and which forecasts are
scored.

A clip of T frames is split into a burn-in, which the model observes, and the frames after it, which
it rolls out from its own predictions. There are two ways to place the burn-in (``burn_in_mode``):

- ``global``: every agent is observed for the clip's first ``burn_in`` frames and predicted from
  frame ``burn_in`` on. Used where every agent is present all along (synthetic push clips,
  basketball).
- ``per_agent``: each agent is observed for its own first ``burn_in`` *present* frames and predicted
  after those. Used for road users (inD and the other levelX data sets), who enter and leave
  mid-clip, so an agent that appears late still gets a full burn-in before its forecast is counted
  (DNRI's protocol).

A horizon h is the h-th predicted step after the burn-in: for ``global`` the frame
``burn_in + h - 1`` of every agent, for ``per_agent`` the agent's h-th present frame after its own
burn-in. A forecast frame is scored only while the agent has been present since its last observed
frame (:func:`scored_targets`). Test errors are reported at a few such horizons
(``protocol.horizons``, which the model config reads), each of which must therefore lie in 1..T -
burn_in.

Absent agents (mask False) get zero states, the centre of the normalised range, so no NaN ever
reaches a model. Shapes: B clips, T frames, N agents.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import torch

BURN_IN_MODES = ("global", "per_agent")
MIN_STEPS = 2  # steps a clip needs: one transition t -> t+1 to hold an edge type


def burn_in_mask(mask: torch.Tensor, burn_in: int) -> torch.Tensor:
    """The steps that are each agent's own burn-in: its first ``burn_in`` present steps.

    The per-agent protocol observes every agent for ``burn_in`` steps from its first appearance
    (agents enter and leave mid-clip), so forecasting errors are only counted after that. mask: [B,
    T, N] bool -> [B, T, N] bool.
    """
    return mask & (mask.long().cumsum(dim=1) <= burn_in)


def agent_horizons(mask: torch.Tensor, burn_in: int) -> torch.Tensor:
    """Per-agent forecast horizon of every frame: h >= 1 at an agent's h-th present frame after its
    own burn-in (its first ``burn_in`` present frames, :func:`burn_in_mask`); <= 0 in its burn-in, 0
    where absent.

    With every agent present from frame 0 this is the global horizon t - burn_in + 1. mask: [B, T,
    N] bool -> [B, T, N] long.
    """
    steps = mask.long().cumsum(dim=1) - burn_in
    return torch.where(mask, steps, torch.zeros((), dtype=steps.dtype, device=steps.device))


def scored_targets(mask: torch.Tensor, burn_in: int, mode: str) -> torch.Tensor:
    """The forecast frames that are scored, [B, T, N] bool -> [B, T - burn_in, N] bool (frames
    burn_in..T-1).

    One rule for an agent that leaves: a frame is scored only if the agent's forecast there starts
    from an observation of that agent and the agent has been present at every frame since. In
    ``global`` mode that observation is the burn-in's last frame (burn_in - 1), so an agent absent
    there is never scored; in ``per_agent`` mode it is the agent's own last burn-in frame (its
    burn_in-th present frame). Once an agent is missing for a frame it is not scored again in the
    clip, even when it comes back: the roll-out has lost it (its input is zeros while it is absent),
    and what comes back may be a track re-acquired elsewhere."""
    if mode == "per_agent":
        count = mask.long().cumsum(dim=1)  # present frames so far
        observed = count >= burn_in  # the agent's burn-in is complete at or before this frame
        gaps = (~mask & observed).long().cumsum(dim=1)  # frames missed since then
        scored = mask & (count > burn_in) & (gaps == 0)
    elif mode == "global":
        # present since frame burn_in - 1
        scored = mask[:, burn_in - 1 :].long().cumprod(dim=1).bool()[:, 1:]
    else:
        raise ValueError(f"scored_targets: mode={mode!r}, expected one of {list(BURN_IN_MODES)}")
    return scored[:, burn_in:] if mode == "per_agent" else scored


def fill_absent(states: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Zero the states of absent agents (normalised space: the centre of the range), never NaN.

    states: [..., N, 4], mask: [..., N] bool -> [..., N, 4].
    """
    return torch.where(mask[..., None], states, torch.zeros((), dtype=states.dtype))


def horizons_problem(horizons: object, longest: int | None, key: str = "protocol.horizons",
                     context: str = "", integers: bool = False) -> str | None:
    """The one rule for forecast horizons: a non-empty list, each h in 1..longest (h is the h-th
    predicted step after the burn-in, so ``longest`` = clip length - burn_in; None while the clip
    length is unknown: each h >= 1). Returns ``"key=value: what is wrong (context)"`` or None.
    integers: also reject horizons that are not integers (bools included) rather than truncating
    them."""
    try:
        hs = [h if integers else int(h) for h in horizons]  # type: ignore[union-attr]
    except (TypeError, ValueError):
        return f"{key}={horizons!r}: expected a list of ints"
    if (integers and not all(isinstance(h, numbers.Integral) and not isinstance(h, bool)
                             for h in hs)):
        return f"{key}={list(horizons)}: each must be a whole number of steps"  # type: ignore[arg-type]
    if longest is None:
        return None if hs and min(hs) >= 1 else f"{key}={list(horizons)}: need at least one horizon >= 1"  # type: ignore[arg-type]
    if hs and min(hs) >= 1 and max(hs) <= longest:
        return None
    return f"{key}={list(horizons)}: each must lie in 1..{longest}" + (f" ({context})" if context else "")  # type: ignore[arg-type]



def check_horizons(horizons: Sequence[int], seq_len: int | None, burn_in: int, where: str = "", *,
                   length_key: str | None = None, integers: bool = False) -> None:
    """Raise a ValueError naming ``protocol.burn_in`` or ``protocol.horizons`` unless the burn-in is
    shorter than the clips and every horizon fits after it (:func:`horizons_problem`).

    seq_len: the clip length in steps, or None while it is unknown: then only that there is a
    horizon and none is below 1. where: appended to the clip length in messages (e.g. ", the test
    split's"); length_key: the config key that sets the clip length, named in messages instead of
    "<seq_len>-step clips"; integers: see :func:`horizons_problem`.
    """
    if seq_len is not None:
        if burn_in < 1:
            raise ValueError(f"protocol.burn_in={burn_in}: must be >= 1")
        if length_key is None:
            clip, clips = f"the clips ({seq_len} steps{where})", f"{seq_len}-step clips{where}"
        else:
            clip, clips = f"the clip ({length_key}={seq_len})", f"{length_key}={seq_len}"
        if burn_in >= seq_len:
            raise ValueError(f"protocol.burn_in={burn_in} must be shorter than {clip}")
    longest = None if seq_len is None else seq_len - burn_in
    context = ("" if seq_len is None
               else f"the predicted steps after protocol.burn_in={burn_in} of {clips}")
    if (found := horizons_problem(horizons, longest, "protocol.horizons", context,
                                  integers)) is not None:
        raise ValueError(found)


def observed_inputs(x: torch.Tensor, mask: torch.Tensor, burn_in: int, end: int, mode: str
                    ) -> tuple[torch.Tensor | None, int, torch.Tensor]:
    """What a roll-out of ``end`` transitions observes (:meth:`RelationalVAE.rollout`): ``fed`` [B,
    end, N] bool, the inputs that are ground truth (None in ``global`` mode: the first ``burn_in``
    frames), ``t_obs``, the frames before any present agent is rolled out, and ``x_obs`` [B, t_obs,
    N, D], those frames."""
    if mode == "per_agent":
        if x.shape[1] < end or mask.shape[1] < end:
            raise ValueError(f"rollout(per_agent): need >= {end} frames of states and mask (an "
                             f"agent may enter late and be observed then), got {x.shape[1]} and "
                             f"{mask.shape[1]}")
        fed = burn_in_mask(mask[:, :end], burn_in)  # [B, end, N]: inputs that are ground truth
        # Frames before any present agent has left its burn-in are pure ground truth: one batched
        # LSTM pass over them, exactly as in the global mode (where this prefix is the burn-in
        # itself).
        rolled = (mask[:, :end] & ~fed).any(dim=2).any(dim=0)  # [end]
        t_obs = int(rolled.to(torch.uint8).argmax()) if bool(rolled.any()) else end
        x_obs = fill_absent(x[:, :t_obs], mask[:, :t_obs])
    elif mode == "global":
        fed, t_obs, x_obs = None, burn_in, x[:, :burn_in]
    else:
        raise ValueError(f"rollout: mode={mode!r}, expected 'global' or 'per_agent'")
    return fed, t_obs, x_obs
