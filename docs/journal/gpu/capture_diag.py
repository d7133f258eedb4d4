"""Where a training step's CUDA-graph capture fails, one stage per process (a failed capture can leave the context
unusable): python capture_diag.py MODEL STAGE [loop]. Stages: sync (one eager step under sync debug mode "error"),
full (grads' reset, forward, loss, backward), forward (forward and loss only), encoder, segment (the duration plugin's
cut and its backward), hold (hold_assignment and its backward). "loop": hold_assignment's step loop in place of the
cumulative product. Prints one line "RESULT {json}"; on a capture, the bare step's replay time against eager."""

from __future__ import annotations

import json
import os
import sys
import time
import traceback

import torch

import dider.models.hazard as hazard
from dider.bench.steps import build_model
from dider.models.plugins import Progress

DEV = os.environ.get("DEV", "cuda")  # DEV=cpu: a dry run of the stages, without the capture
model_name, stage = sys.argv[1], sys.argv[2]
if "loop" in sys.argv[3:]:
    original = hazard.hold_assignment
    hazard.hold_assignment = lambda gate, closed=None: original(gate, closed=False)
    import dider.models.segment_end as se
    se.hold_assignment = hazard.hold_assignment
r: dict = {"model": model_name, "stage": stage, "loop": "loop" in sys.argv[3:]}
torch.manual_seed(0)
net, _ = build_model([f"model={model_name}"])
net = net.to(DEV).train()
g = torch.Generator().manual_seed(0)
states = (torch.rand(16, 50, 3, 4, generator=g) * 2 - 1).to(DEV)
batch = {"states": states, "mask": torch.ones(16, 50, 3, dtype=torch.bool, device=DEV), "everyone": True}
values = {k: torch.full((), float(v), device=DEV) for k, v in net.schedule(Progress(10, 1000)).items()}
progress = Progress(values=values)
params = [p for p in net.parameters()]


def full() -> torch.Tensor:
    grads = [p.grad for p in params if p.grad is not None]
    if grads:
        torch._foreach_zero_(grads)
    loss = net.loss(net.infer(batch, hard=False, progress=progress), progress)["loss"]
    loss.backward()
    return loss.detach()


def forward() -> torch.Tensor:
    return net.loss(net.infer(batch, hard=False, progress=progress), progress)["loss"].detach()


with torch.no_grad():  # no autograd graph kept alive across the stages (its accumulators' stream would differ)
    enc = net.encoder(batch["states"], None)
h_fwd, h_rev = enc.h_fwd.detach().requires_grad_(), enc.h_rev.detach().requires_grad_()


def encoder() -> torch.Tensor:
    out = net.encoder(batch["states"], None)
    s = out.h_fwd.sum() + out.h_rev.sum() + out.posterior_logits.sum()
    s.backward()
    return s.detach()


def segment() -> torch.Tensor:
    kw = {"types": torch.softmax(enc.posterior_logits.detach().float(), -1)} if net.capabilities.held_type else {}
    seg = net.duration.segment(h_fwd, h_rev, batch["states"], progress, None, **kw)
    s = seg.kl.sum() + (seg.assign.sum() if seg.assign is not None else 0)
    s.backward()
    return s.detach()


gate_in = (torch.rand(16, 6, 49, device=DEV) < 0.3).float()
gate_in[..., 0] = 1
gate_in.requires_grad_()


def hold() -> torch.Tensor:
    s = (hazard.hold_assignment(gate_in) * 1.5).sum()
    s.backward()
    return s.detach()


def recover() -> None:
    """A capture that fails (a read-back inside it), then whether eager random draws work again once the generator's
    state is set back."""
    state = torch.cuda.get_rng_state()
    graph = torch.cuda.CUDAGraph()
    try:
        with torch.cuda.graph(graph):
            x = torch.rand(4, device=DEV)
            float(x.sum())
    except Exception as error:  # noqa: BLE001
        r["provoked"] = str(error).splitlines()[0][:200]
    for how in ("plain", "set_rng_state", "manual_seed"):
        try:
            if how == "set_rng_state":
                torch.cuda.set_rng_state(state)
            elif how == "manual_seed":
                torch.cuda.manual_seed(123)
            torch.rand(4, device=DEV).sum().item()
            r[how] = "draws"
            break
        except Exception as error:  # noqa: BLE001
            r[how] = str(error).splitlines()[0][:200]


fn = {"recover": recover, "full": full, "forward": forward, "encoder": encoder, "segment": segment, "hold": hold,
      "sync": full}[stage]
try:
    if DEV == "cpu":
        fn()
        fn()
        r["ok"] = "dry run"
    elif stage == "recover":
        recover()
        r["ok"] = True
    elif stage == "sync":
        fn()
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("error")
        fn()
        torch.cuda.set_sync_debug_mode(0)
        r["ok"] = True
    else:
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(3):
                fn()
        torch.cuda.current_stream().wait_stream(side)
        torch.cuda.synchronize()
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            fn()
        torch.cuda.synchronize()

        def timed(run, n=30):
            run()
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            for _ in range(n):
                run()
            torch.cuda.synchronize()
            return (time.perf_counter() - t0) / n * 1e3

        r |= {"ok": True, "replay_ms": timed(graph.replay), "eager_ms": timed(fn)}
except Exception as error:  # noqa: BLE001 - the diagnosis is the message
    frames = [f"{f.filename.split('/src/')[-1]}:{f.lineno} {f.line}" for f in traceback.extract_tb(error.__traceback__)
              if "/dider/" in f.filename or "capture_diag" in f.filename]
    r |= {"ok": False, "error": f"{type(error).__name__}: {error}"[:600], "frames": frames[-6:]}
print("RESULT " + json.dumps(r), flush=True)
