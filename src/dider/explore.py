"""Interactive explorer of a run's inferred interactions: one self-contained HTML file per run.

``python -m dider.explore RUN_DIR [--out FILE.html] [--max-clips K] [--clips 0,3,5]`` reads the run's
``clips.npz`` (``RUN_DIR/predictions/clips.npz`` of a prediction run, else ``RUN_DIR/clips.npz`` of a
training run's test split) and writes ``RUN_DIR/explorer.html``: the agents' paths over the scene image,
arrows sender -> receiver coloured by interaction type at a chosen frame, and per-edge timelines of every
source (truth, per-step posterior, segments, prior). The page needs no network: data, images (base64 PNG),
JavaScript and styles are inline.

Clips are addressed by their row in ``clips.npz`` everywhere (``--clips``, the page's selector, the URL hash
``#clip=ROW&frame=F&source=segments`` (also ``&zero=faint``) and ``window.explorer.setClip(ROW)``). Frame F
shows transition min(F, T-2), i.e. F -> F+1 (the last frame shows the last transition).

Embedded data are compact: only present agents and edges, coordinates as delta-coded integers at a
precision of a thousandth of the clip's extent, edge types and probabilities (percent) run-length coded.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import math
import sys
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from dider.graph import edge_index
from dider.io import atomic_write_text
from dider.type_meaning import profile_notes

REQUIRED_KEYS = ("positions", "mask", "segments", "probs", "per_step", "prior", "clip", "num_types", "model")
# Timeline strip order: the reference first, then the posterior before and after segmentation, then the prior.
EDGE_SOURCES = ("truth", "per_step", "segments", "prior")
EDGE_KEYS = (*EDGE_SOURCES, "probs", "step_probs")
PER_CLIP_KEYS = ("clip", "scene", "frame", "background_of")
MAX_BACKGROUND_SIDE = 1600  # pixels: beyond this an embedded scene image costs MBs for no visible detail
NONE_COLOR = "#9a9a9a"  # type 0 ("no interaction"): neutral, so real interactions stand out


class ExploreError(Exception):
    """A run folder or clips file the explorer cannot use; the message names the path or key."""


# ---------------------------------------------------------------------------------------------- loading


def find_clips(run_dir: Path) -> Path:
    """The run's clips.npz: a prediction run's first, else the test split's of a training run."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ExploreError(f"run directory not found: {run_dir}")
    candidates = (run_dir / "predictions" / "clips.npz", run_dir / "clips.npz")
    for path in candidates:
        if path.is_file():
            return path
    raise ExploreError(f"no clips.npz in {run_dir}: looked for {candidates[0]} and {candidates[1]}")


def load_clips(path: Path) -> dict[str, np.ndarray]:
    """Every array of ``path``, checked for the keys and shapes the page relies on."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise ExploreError(f"cannot read {path}: {err}") from err
    for key in REQUIRED_KEYS:
        if key not in data:
            raise ExploreError(f"{path} lacks key {key!r} (has: {', '.join(sorted(data))})")
    step_probs = data.get("step_probs")
    if step_probs is not None and step_probs.ndim == 4 and "per_step" in data:
        # Every type's per-step probability [S, E, T-1, K] (what prediction writes): the page shows the
        # probability of the per-step type.
        chosen = np.clip(data["per_step"].astype(np.int64), 0, step_probs.shape[-1] - 1)[..., None]
        data["step_probs"] = np.take_along_axis(step_probs, chosen, axis=-1)[..., 0]
    check_shapes(data, path)
    return data


def check_shapes(data: dict[str, np.ndarray], path: Path) -> None:
    """Shapes that agree with ``positions`` [S, T, N, 2]; raises naming the first key that does not."""
    pos = data["positions"]
    if pos.ndim != 4 or pos.shape[-1] != 2:
        raise ExploreError(f"{path}: key 'positions' has shape {pos.shape}, expected [S, T, N, 2]")
    s, t, n, _ = pos.shape
    expected = {"mask": (s, t, n), "agent": (s, n)}
    expected |= {key: (s, n * (n - 1), t - 1) for key in EDGE_KEYS}
    expected |= {key: (s,) for key in PER_CLIP_KEYS}
    for key, shape in expected.items():
        if key in data and data[key].shape != shape:
            raise ExploreError(f"{path}: key {key!r} has shape {data[key].shape}, expected {shape}")
    images = np.unique(data.get("background_of", np.array([], dtype=np.int64)))
    for key in (name for k in images[images >= 0] for name in (f"background_{k}", f"background_{k}_extent")):
        if key not in data:
            raise ExploreError(f"{path} lacks key {key!r} (named by 'background_of')")


def type_names(data: dict[str, np.ndarray]) -> list[str]:
    num_types = int(data["num_types"])
    given = [str(x) for x in data["type_names"]] if "type_names" in data else []
    return [given[k] if k < len(given) else f"type {k}" for k in range(num_types)]


def type_colors(num_types: int) -> list[str]:
    """The timeline PNGs' colours (:mod:`dider.viz`: tab10 resampled to the type count), type 0 grey."""
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    cmap = colormaps["tab10"].resampled(max(num_types, 2))
    return [NONE_COLOR] + [to_hex(cmap(k)) for k in range(1, num_types)]


# ------------------------------------------------------------------------------------------- encoding


def rle(values: np.ndarray) -> list[int | list[int]]:
    """Run-length code: a run of one value is the value, a longer run [value, length]."""
    v = np.asarray(values).ravel()
    if v.size == 0:
        return []
    starts = np.flatnonzero(np.r_[True, v[1:] != v[:-1]])
    lengths = np.diff(np.r_[starts, v.size])
    return [int(x) if n == 1 else [int(x), int(n)] for x, n in zip(v[starts], lengths, strict=True)]


def unrle(runs: list[int | list[int]]) -> list[int]:
    """The inverse of :func:`rle` (the page decodes the same way)."""
    out: list[int] = []
    for run in runs:
        out.extend([run[0]] * run[1] if isinstance(run, list) else [run])
    return out


def coord_decimals(points: np.ndarray) -> int:
    """Decimals that keep a thousandth of the points' extent: below a pixel at any sensible zoom."""
    if len(points) == 0:
        return 0
    span = float(np.ptp(points, axis=0).max()) or 1.0
    return int(np.clip(math.ceil(3 - math.log10(span)), 0, 6))


def decode_path(xy: list[int | None], decimals: int) -> list[tuple[float, float] | None]:
    """The inverse of the delta coding in :func:`agent_payload` (the page decodes the same way)."""
    out: list[tuple[float, float] | None] = []
    x = y = 0
    for i in range(0, len(xy), 2):
        if xy[i] is None:
            out.append(None)
            continue
        x, y = x + xy[i], y + xy[i + 1]
        out.append((x / 10**decimals, y / 10**decimals))
    return out


def agent_payload(xy: np.ndarray, present: np.ndarray, slot: int, ident: int, decimals: int) -> dict[str, Any]:
    """One present agent: its path from its first to its last present frame ``f0``.., delta-coded
    (consecutive points differ by a few units: short numbers), with ``null, null`` for absent frames."""
    frames = np.flatnonzero(present)
    f0, f1 = int(frames[0]), int(frames[-1])
    seen = present[f0 : f1 + 1]
    points = np.round(xy[f0 : f1 + 1][seen].astype(np.float64) * 10**decimals).astype(np.int64)
    deltas = iter(np.diff(points, axis=0, prepend=0).tolist())
    coded = [v for here in seen for v in (next(deltas) if here else (None, None))]
    return {"k": slot, "id": ident, "f0": f0, "xy": coded}


def sources_of(data: dict[str, np.ndarray]) -> list[str]:
    return [key for key in EDGE_SOURCES if key in data]


def edge_fields(data: dict[str, np.ndarray]) -> list[str]:
    """The layout of an embedded edge: a list, not a dict, as keys repeated on every edge of every clip
    would be a sixth of the page."""
    return ["e", "s", "r", "p", "sp", *sources_of(data)]


def edge_payload(data: dict[str, np.ndarray], s: int, e: int, sender: int, receiver: int) -> list[Any] | None:
    """One directed edge of clip ``s`` as laid out by :func:`edge_fields`: its index, sender and receiver
    slots, the segments' (and per-step types', else null) probabilities in percent, then each source's
    types, all run-length coded with -1 where absent; None when the edge is absent throughout."""
    sources = sources_of(data)
    if all((data[key][s, e] < 0).all() for key in sources):
        return None
    probs = rle(percent(data["probs"][s, e], data["segments"][s, e]))
    step = rle(percent(data["step_probs"][s, e], data["per_step"][s, e])) if "step_probs" in data else None
    return [e, sender, receiver, probs, step, *(rle(data[key][s, e].astype(np.int64)) for key in sources)]


def percent(probs: np.ndarray, types: np.ndarray) -> np.ndarray:
    p = np.nan_to_num(probs.astype(np.float32), nan=0.0)
    return np.where(types >= 0, np.round(np.clip(p, 0, 1) * 100), -1).astype(np.int64)


def optional_int(data: dict[str, np.ndarray], key: str, s: int) -> int | None:
    return int(data[key][s]) if key in data else None


def clip_payload(data: dict[str, np.ndarray], s: int) -> dict[str, Any]:
    """Row ``s`` of clips.npz as the page embeds it: present agents and present edges only."""
    pos, mask = data["positions"][s], data["mask"][s].astype(bool)
    num_frames, num_agents = mask.shape
    ids = data["agent"][s] if "agent" in data else np.arange(num_agents)
    decimals = coord_decimals(pos[mask])
    agents = [agent_payload(pos[:, k], mask[:, k], k, int(ids[k]) if ids[k] >= 0 else k, decimals)
              for k in range(num_agents) if mask[:, k].any()]  # fmt: skip
    send, recv = (v.numpy() for v in edge_index(num_agents))
    edges = [edge_payload(data, s, e, int(a), int(b)) for e, (a, b) in enumerate(zip(send, recv, strict=True))]
    background = optional_int(data, "background_of", s)
    return {"row": s, "clip": int(data["clip"][s]), "scene": optional_int(data, "scene", s),
            "frame": optional_int(data, "frame", s), "T": num_frames, "d": decimals,
            "bg": background if background is not None and background >= 0 else None,
            "agents": agents, "edges": [e for e in edges if e is not None]}  # fmt: skip


def background_payload(image: np.ndarray, extent: np.ndarray) -> dict[str, Any]:
    """A scene image as base64 PNG (downscaled past MAX_BACKGROUND_SIDE) with its imshow extent."""
    from PIL import Image  # a matplotlib dependency

    pixels = np.asarray(image)
    if pixels.dtype.kind == "f":
        pixels = (np.clip(pixels, 0, 1) * 255).astype(np.uint8)
    img = Image.fromarray(np.ascontiguousarray(pixels))
    img.thumbnail((MAX_BACKGROUND_SIDE, MAX_BACKGROUND_SIDE))
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True)
    return {"png": base64.b64encode(buf.getvalue()).decode("ascii"), "extent": [float(x) for x in extent]}


# ------------------------------------------------------------------------------------------ the page


def select_rows(num_clips: int, clips: list[int] | None, max_clips: int) -> tuple[list[int], str]:
    """The rows to embed and a note for the page when some are left out. An explicit ``clips`` list is
    taken whole (the user chose it); otherwise the first ``max_clips``."""
    if clips is not None:
        bad = [c for c in clips if not 0 <= c < num_clips]
        if bad:
            raise ExploreError(f"--clips {bad} out of range: clips.npz has rows 0..{num_clips - 1}")
        rows = list(dict.fromkeys(clips))
        if not rows:
            raise ExploreError("--clips names no clip")
        return rows, "" if len(rows) == num_clips else f"showing the {len(rows)} chosen of {num_clips} clips"
    if num_clips == 0 or max_clips < 1:
        raise ExploreError(f"nothing to show: clips.npz has {num_clips} clips, --max-clips is {max_clips}")
    rows = list(range(min(num_clips, max_clips)))
    note = "" if len(rows) == num_clips else f"showing the first {len(rows)} of {num_clips} clips (--max-clips)"
    return rows, note


def page_payload(data: dict[str, np.ndarray], path: Path, rows: list[int], note: str = "") -> dict[str, Any]:
    """Everything the page shows, as JSON-ready values."""
    clips = [clip_payload(data, s) for s in rows]
    used = sorted({c["bg"] for c in clips if c["bg"] is not None})
    num_types = int(data["num_types"])
    return {"model": str(data["model"]), "path": str(path), "total": int(data["positions"].shape[0]),
            "note": note, "num_types": num_types, "type_names": type_names(data), "colors": type_colors(num_types),
            "type_notes": profile_notes(data["type_profile"]) if "type_profile" in data else [],
            "sources": sources_of(data), "edge_fields": edge_fields(data),
            "backgrounds": {str(k): background_payload(data[f"background_{k}"], data[f"background_{k}_extent"])
                            for k in used},
            "clips": clips}  # fmt: skip


def render_html(payload: dict[str, Any], title: str) -> str:
    # "</" would end the <script> early if a name or path held "</script>"; "<\/" is the same JSON string.
    blob = json.dumps(payload, separators=(",", ":")).replace("</", "<\\/")
    escaped = title.replace("&", "&amp;").replace("<", "&lt;")
    return PAGE.replace("__TITLE__", escaped).replace("/*__DATA__*/null", blob)


def write_explorer(run_dir: Path, out: Path | None = None, max_clips: int = 50,
                   clips: list[int] | None = None) -> Path:
    """Build the explorer page of ``run_dir``; returns its path."""
    run_dir = Path(run_dir)
    path = find_clips(run_dir)
    data = load_clips(path)
    rows, note = select_rows(data["positions"].shape[0], clips, max_clips)
    out = Path(out) if out is not None else run_dir / "explorer.html"
    title = f"{data['model']} interactions: {run_dir.resolve().name}"
    atomic_write_text(out, render_html(page_payload(data, path, rows, note), title))
    return out


def parse_rows(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected comma-separated clip rows such as 0,3,5, got {text!r}") from err


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dider.explore", description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, help="a run folder holding clips.npz or predictions/clips.npz")
    parser.add_argument("--out", type=Path, help="the HTML file to write (default RUN_DIR/explorer.html)")
    parser.add_argument("--max-clips", type=int, default=50, help="embed at most this many clips (default 50)")
    parser.add_argument("--clips", type=parse_rows,
                        help="rows of clips.npz to embed, e.g. 0,3,5 (all of them: overrides --max-clips)")
    args = parser.parse_args(argv)
    try:
        out = write_explorer(args.run_dir, args.out, args.max_clips, args.clips)
    except ExploreError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"explorer: {out} ({out.stat().st_size / 1e6:.2f} MB)")
    return 0


PAGE = r"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title>
<style>
body{font:13px/1.35 system-ui,sans-serif;margin:0;color:#222;background:#f6f6f4}
header{display:flex;flex-wrap:wrap;gap:6px 12px;align-items:center;padding:7px 12px;background:#fff;
 border-bottom:1px solid #ddd}
header h1{font-size:14px;margin:0 6px 0 0}
button,select{font:inherit}
#note{color:#9a5800;padding:4px 12px 0}
#main{display:flex;gap:14px;padding:8px 12px;align-items:flex-start}
#scene{background:#fff;border:1px solid #ccc;flex:none}
#side{flex:1;min-width:200px;font-size:12px}
#side h2{font-size:13px;margin:2px 0 4px}
#side table td{padding:0 8px 0 0;vertical-align:top}
.sw{display:inline-block;width:12px;height:12px;border-radius:2px;vertical-align:-2px;margin-right:5px}
#legend div{margin:2px 0}
#legend .note{color:#555;font-size:11px;margin-left:17px}
#tlwrap{padding:0 12px 16px}
#tl{background:#fff;border:1px solid #ccc;display:block}
#tl text,#scene text{font-size:11px}
#tip{position:fixed;pointer-events:none;background:rgba(255,255,255,.97);border:1px solid #888;border-radius:3px;
 padding:4px 7px;font-size:12px;white-space:pre;display:none;box-shadow:0 1px 4px rgba(0,0,0,.25);z-index:9}
.path{fill:none;stroke:#555;stroke-opacity:.28;stroke-width:1.2}
.past{fill:none;stroke:#333;stroke-opacity:.6;stroke-width:1.6}
.agent circle{fill:#fff;stroke:#222;stroke-width:1.6}
.agent text{paint-order:stroke;stroke:#fff;stroke-width:3px;font-weight:600}
.arrow{cursor:pointer}
.arrow .hit{stroke:transparent;stroke-width:12}
.arrow .body{stroke-width:2.6;stroke-linecap:round}
.arrow[data-type="0"] .body{stroke-width:1.2;stroke-dasharray:3 3;opacity:.5}
.arrow[data-type="0"] .head{opacity:.5}
#scene.hide0 .arrow[data-type="0"]{display:none}
.arrow.hl .body{stroke-width:5}
.edgelabel{font-weight:600}
.srclabel{fill:#666;font-size:10px!important}
#cursor{fill:#000;opacity:.18;pointer-events:none}
#rowhl{fill:#ffd54a;opacity:.35;pointer-events:none}
.help{color:#666}
</style></head>
<body>
<header>
 <h1 id="title"></h1>
 <label>clip <select id="clipSel"></select></label>
 <button id="prevClip" title="previous clip">&#9664;</button><button id="nextClip" title="next clip">&#9654;</button>
 <button id="play" title="play / pause (space)">&#9654; play</button>
 <input id="slider" type="range" min="0" value="0" step="1" style="width:260px" aria-label="frame">
 <span id="frameLabel"></span>
 <label>arrows <select id="sourceSel"></select></label>
 <label>type 0 <select id="zeroSel"><option value="hidden">hidden</option><option value="faint">faint</option>
 </select></label>
 <label><input type="checkbox" id="activeOnly"> only edges with interactions</label>
</header>
<div id="note"></div>
<div id="main">
 <svg id="scene" class="hide0" width="720" height="520" xmlns="http://www.w3.org/2000/svg">
  <g id="bg"></g><g id="paths"></g><g id="arrows"></g><g id="agents"></g>
 </svg>
 <div id="side"><h2>clip</h2><table id="info"></table><h2>interaction types</h2><div id="legend"></div>
  <p class="help">Frame F shows the transition F&rarr;F+1. Hover arrows and timeline cells for details;
  click a timeline cell to jump there, an arrow to find its timeline. Keys: &larr;/&rarr; frame,
  space play, PgUp/PgDn clip.</p></div>
</div>
<div id="tlwrap"><svg id="tl" xmlns="http://www.w3.org/2000/svg"></svg></div>
<div id="tip"></div>
<script>const DATA = /*__DATA__*/null;</script>
<script>
(function () {
"use strict";
const NS = "http://www.w3.org/2000/svg";
const SHORT = {truth: "truth", per_step: "per step", segments: "segments", prior: "prior"};
const EMPTY = "#e4e4e4";  // type 0 in timelines: visible as "nothing", lighter than any type colour
const TL = {left: 128, head: 22, row: 10, gap: 8};
const R = 6;  // agent dot radius, px
const $ = (id) => document.getElementById(id);
const state = {pos: 0, frame: 0, source: "segments", zero: "hidden", activeOnly: false, timer: null};
let cur = null;  // the decoded current clip

function el(tag, attrs, parent) {
  const node = document.createElementNS(NS, tag);
  for (const k in attrs) node.setAttribute(k, attrs[k]);
  if (parent) parent.appendChild(node);
  return node;
}
function unrle(runs) {
  const out = [];
  for (const r of runs) {
    if (Array.isArray(r)) { for (let i = 0; i < r[1]; i++) out.push(r[0]); } else out.push(r);
  }
  return out;
}
function decodeAgent(a, d) {
  const q = Math.pow(10, -d), pts = [];
  let x = 0, y = 0;
  for (let i = 0; i < a.xy.length; i += 2) {
    if (a.xy[i] === null) { pts.push(null); continue; }
    x += a.xy[i]; y += a.xy[i + 1];
    pts.push([x * q, y * q]);
  }
  return {slot: a.k, id: a.id, f0: a.f0, pts: pts};
}
function posAt(agent, f) {
  const i = f - agent.f0;
  return agent && i >= 0 && i < agent.pts.length ? agent.pts[i] : null;
}
function decodeEdge(raw) {
  const e = {};
  DATA.edge_fields.forEach((k, i) => { e[k] = raw[i]; });
  const out = {e: e.e, s: e.s, r: e.r, p: unrle(e.p), sp: e.sp ? unrle(e.sp) : null, types: {}};
  for (const src of DATA.sources) if (e[src]) out.types[src] = unrle(e[src]);
  // per-step flickers alone do not make an edge "interacting": the segments or the truth must say so
  out.active = ["segments", "truth"].some((src) => out.types[src] && out.types[src].some((v) => v > 0));
  return out;
}
function decodeClip(c) {
  const agents = new Map();
  for (const a of c.agents) agents.set(a.k, decodeAgent(a, c.d));
  const bg = c.bg === null ? null : DATA.backgrounds[c.bg];
  return {raw: c, T: c.T, agents: agents, edges: c.edges.map(decodeEdge), bg: bg};
}

// Fit the clip's paths into the scene, equal aspect. y points up unless the scene image's extent says
// top < bottom (image coordinates), as matplotlib's imshow would show it.
function projection(clip, W, H) {
  let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
  for (const a of clip.agents.values()) for (const p of a.pts) if (p) {
    x0 = Math.min(x0, p[0]); x1 = Math.max(x1, p[0]); y0 = Math.min(y0, p[1]); y1 = Math.max(y1, p[1]);
  }
  if (!isFinite(x0)) { x0 = 0; x1 = 1; y0 = 0; y1 = 1; }
  const span = Math.max(x1 - x0, y1 - y0, 1e-9), m = 28;
  const k = Math.min((W - 2 * m) / Math.max(x1 - x0, span * 0.05), (H - 2 * m) / Math.max(y1 - y0, span * 0.05));
  const up = !clip.bg || clip.bg.extent[3] >= clip.bg.extent[2];
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  return {px: (x) => W / 2 + (x - cx) * k, py: (y) => H / 2 + (up ? cy - y : y - cy) * k};
}

function typeName(v) { return v < 0 ? "absent" : v + " " + (DATA.type_names[v] || ""); }
function agentId(slot) { const a = cur.agents.get(slot); return a ? a.id : slot; }
function transitionAt(f) { return Math.max(0, Math.min(f, cur.T - 2)); }
function stepText(t) {
  let s = "step " + t + " (frames " + t + "\u2192" + (t + 1) + ")";
  if (cur.raw.frame !== null) s += ", input frames " + (cur.raw.frame + t) + "\u2192" + (cur.raw.frame + t + 1);
  return s;
}
function pairText(e) {
  return "agent " + agentId(e.s) + " \u2192 agent " + agentId(e.r) + "   (slots " + e.s + "\u2192" + e.r + ")";
}
function valueText(e, src, t) {
  const v = e.types[src][t];
  let s = SHORT[src] + ": " + typeName(v);
  if (src === "segments" && v >= 0) s += "   p = " + (e.p[t] / 100).toFixed(2);
  if (src === "per_step" && v >= 0 && e.sp) s += "   p = " + (e.sp[t] / 100).toFixed(2);
  return s;
}
function edgeDetails(e, t, only) {
  const lines = [pairText(e), stepText(t)];
  for (const src of only ? [only] : DATA.sources) if (e.types[src]) lines.push(valueText(e, src, t));
  return lines.join("\n");
}

// ---------------------------------------------------------------- scene
function drawScene() {
  const svg = $("scene"), W = +svg.getAttribute("width"), H = +svg.getAttribute("height");
  cur.proj = projection(cur, W, H);
  const P = cur.proj, bg = $("bg"), paths = $("paths");
  bg.textContent = ""; paths.textContent = "";
  if (cur.bg) {
    const [l, r, b, t] = cur.bg.extent;
    el("image", {href: "data:image/png;base64," + cur.bg.png, preserveAspectRatio: "none",
      x: Math.min(P.px(l), P.px(r)), y: Math.min(P.py(b), P.py(t)),
      width: Math.abs(P.px(r) - P.px(l)), height: Math.abs(P.py(t) - P.py(b))}, bg);
  }
  for (const a of cur.agents.values()) {
    el("path", {class: "path", d: pathD(a, a.f0 + a.pts.length - 1)}, paths);
    a.past = el("path", {class: "past", d: ""}, paths);
  }
}
function pathD(a, last) {
  const P = cur.proj;
  let d = "", pen = false;
  for (let i = 0; i < a.pts.length && a.f0 + i <= last; i++) {
    const p = a.pts[i];
    if (!p) { pen = false; continue; }
    d += (pen ? "L" : "M") + P.px(p[0]).toFixed(1) + " " + P.py(p[1]).toFixed(1);
    pen = true;
  }
  return d;
}
function arrow(e, type, a, b, t, parent) {
  const P = cur.proj;
  const g = el("g", {class: "arrow", "data-edge": e.s + "-" + e.r, "data-e": e.e, "data-type": type,
    "data-sender": agentId(e.s), "data-receiver": agentId(e.r), "data-t": t}, parent);
  const x1 = P.px(a[0]), y1 = P.py(a[1]), x2 = P.px(b[0]), y2 = P.py(b[1]);
  const len = Math.hypot(x2 - x1, y2 - y1);
  if (len < 2 * R + 2) return g;  // agents on top of each other: nothing to draw, the cell says it
  const ux = (x2 - x1) / len, uy = (y2 - y1) / len, ox = -uy * 3, oy = ux * 3;  // a->b and b->a side by side
  const sx = x1 + ux * R + ox, sy = y1 + uy * R + oy, ex = x2 - ux * (R + 1) + ox, ey = y2 - uy * (R + 1) + oy;
  const color = DATA.colors[type] || "#000", head = Math.min(9, len / 3);
  el("line", {class: "hit", x1: sx, y1: sy, x2: ex, y2: ey}, g);
  el("line", {class: "body", x1: sx, y1: sy, x2: ex - ux * head * 0.8, y2: ey - uy * head * 0.8, stroke: color}, g);
  const bx = ex - ux * head, by = ey - uy * head, w = head * 0.5;
  el("polygon", {class: "head", fill: color,
    points: ex + "," + ey + " " + (bx - uy * w) + "," + (by + ux * w) + " " + (bx + uy * w) + "," + (by - ux * w)}, g);
  return g;
}
function drawFrame() {
  const f = state.frame, t = transitionAt(f), P = cur.proj;
  for (const a of cur.agents.values()) a.past.setAttribute("d", pathD(a, f));
  const arrows = $("arrows"), agents = $("agents");
  arrows.textContent = ""; agents.textContent = "";
  let active = 0;
  for (const e of cur.edges) {
    const types = e.types[state.source];
    const type = types ? types[t] : -1;
    const a = posAt(cur.agents.get(e.s), f), b = posAt(cur.agents.get(e.r), f);
    if (type === undefined || type < 0 || !a || !b) continue;
    arrow(e, type, a, b, t, arrows);
    if (type > 0) active++;
  }
  for (const a of cur.agents.values()) {
    const p = posAt(a, f);
    if (!p) continue;
    const g = el("g", {class: "agent", "data-agent": a.id}, agents);
    el("circle", {cx: P.px(p[0]), cy: P.py(p[1]), r: R}, g);
    el("text", {x: P.px(p[0]) + R + 2, y: P.py(p[1]) - R - 1}, g).textContent = a.id;
  }
  const cursor = $("cursor");
  if (cursor) cursor.setAttribute("x", TL.left + t * cur.cw);
  $("slider").value = f;
  let label = "frame " + f + " / " + (cur.T - 1) + " \u00b7 step " + t + "\u2192" + (t + 1);
  if (cur.raw.frame !== null) label += " \u00b7 input frame " + (cur.raw.frame + f);
  $("frameLabel").textContent = label + " \u00b7 " + active + " interacting";
  const ds = document.body.dataset;
  ds.clip = cur.raw.row; ds.frame = f; ds.transition = t; ds.source = state.source;
  if (state.timer === null) saveHash();
}

// ------------------------------------------------------------- timelines
function drawTimelines() {
  const svg = $("tl");
  svg.textContent = "";
  const edges = cur.edges.filter((e) => !state.activeOnly || e.active);
  const srcs = DATA.sources, n = Math.max(cur.T - 1, 1);
  const wrap = getComputedStyle($("tlwrap"));  // clientWidth includes the padding
  const inner = $("tlwrap").clientWidth - parseFloat(wrap.paddingLeft) - parseFloat(wrap.paddingRight);
  const W = Math.max(500, inner - 2), block = srcs.length * TL.row + TL.gap;
  cur.cw = (W - TL.left - 16) / n;  // room for the last tick's label
  cur.shown = edges;
  svg.setAttribute("width", W);
  svg.setAttribute("height", TL.head + Math.max(edges.length, 1) * block + 4);
  const every = [1, 2, 5, 10, 20, 50, 100, 200, 500].find((k) => n / k <= 24) || 1000;
  for (let t = 0; t <= n; t += every) {
    const x = TL.left + t * cur.cw;
    el("line", {x1: x, x2: x, y1: TL.head - 5, y2: TL.head - 1, stroke: "#888"}, svg);
    el("text", {x: x, y: TL.head - 8, "text-anchor": "middle", fill: "#666"}, svg).textContent = t;
  }
  el("text", {x: 6, y: TL.head - 8, fill: "#666"}, svg).textContent = edges.length ? "step" : "no edges";
  el("rect", {id: "rowhl", x: 0, y: -100, width: W, height: block - 2}, svg);
  edges.forEach((e, i) => {
    const y0 = TL.head + i * block;
    el("text", {class: "edgelabel", x: 6, y: y0 + srcs.length * TL.row / 2 + 4}, svg).textContent =
      agentId(e.s) + "\u2192" + agentId(e.r);
    srcs.forEach((src, j) => {
      const y = y0 + j * TL.row;
      const label = el("text", {class: "srclabel", x: TL.left - 4, y: y + TL.row - 1.5, "text-anchor": "end"}, svg);
      label.textContent = SHORT[src];
      if (e.types[src]) runs(e.types[src], (v, a, b) => el("rect", {x: TL.left + a * cur.cw, y: y + 0.5,
        width: (b - a) * cur.cw, height: TL.row - 1, fill: v === 0 ? EMPTY : DATA.colors[v] || "#000"}, svg));
    });
  });
  el("rect", {id: "cursor", x: TL.left + transitionAt(state.frame) * cur.cw, y: TL.head - 2, width: cur.cw,
    height: Math.max(edges.length, 1) * block}, svg);
}
function runs(values, draw) {
  let a = 0;
  for (let t = 1; t <= values.length; t++) {
    if (t === values.length || values[t] !== values[a]) {
      if (values[a] >= 0) draw(values[a], a, t);
      a = t;
    }
  }
}
// Client coordinates of the middle of a timeline cell: row i of the shown edges, a source, step t.
function cellCentre(i, src, t) {
  const box = $("tl").getBoundingClientRect(), block = DATA.sources.length * TL.row + TL.gap;
  return {x: box.left + TL.left + (t + 0.5) * cur.cw,
    y: box.top + TL.head + i * block + (DATA.sources.indexOf(src) + 0.5) * TL.row};
}
function cellAt(evt) {
  const box = $("tl").getBoundingClientRect(), x = evt.clientX - box.left, y = evt.clientY - box.top;
  const block = DATA.sources.length * TL.row + TL.gap, i = Math.floor((y - TL.head) / block);
  const j = Math.floor((y - TL.head - i * block) / TL.row), t = Math.floor((x - TL.left) / cur.cw);
  if (i < 0 || i >= cur.shown.length || t < 0 || t >= cur.T - 1) return null;
  return {e: cur.shown[i], i: i, src: j < DATA.sources.length ? DATA.sources[j] : null, t: t};
}

// ------------------------------------------------------------- hover
function showTip(evt, text) {
  const tip = $("tip");
  tip.textContent = text;
  tip.style.display = "block";
  tip.style.left = Math.min(evt.clientX + 14, window.innerWidth - tip.offsetWidth - 4) + "px";
  tip.style.top = Math.min(evt.clientY + 14, window.innerHeight - tip.offsetHeight - 4) + "px";
}
function hideTip() { $("tip").style.display = "none"; highlight(null); }
function highlight(e) {
  for (const g of $("arrows").querySelectorAll(".arrow.hl")) g.classList.remove("hl");
  const hl = $("rowhl");
  if (!e) { if (hl) hl.setAttribute("y", -100); return; }
  const g = $("arrows").querySelector('.arrow[data-e="' + e.e + '"]');
  if (g) g.classList.add("hl");
  const i = cur.shown.indexOf(e), block = DATA.sources.length * TL.row + TL.gap;
  if (hl && i >= 0) hl.setAttribute("y", TL.head + i * block - 1);
}
function edgeOf(g) { const k = +g.getAttribute("data-e"); return cur.edges.find((e) => e.e === k); }

// ------------------------------------------------------------- state
function setClip(row) {
  const pos = DATA.clips.findIndex((c) => c.row === +row);
  if (pos < 0) return false;
  state.pos = pos;
  cur = decodeClip(DATA.clips[pos]);
  $("clipSel").value = pos;
  $("slider").max = cur.T - 1;
  state.frame = Math.min(state.frame, cur.T - 1);
  drawInfo(); drawScene(); drawTimelines(); drawFrame();
  return true;
}
function setFrame(f) {
  state.frame = Math.max(0, Math.min(Math.round(+f) || 0, cur.T - 1));
  drawFrame();
  return state.frame;
}
function setSource(src) {
  if (DATA.sources.indexOf(src) < 0) return false;
  state.source = src; $("sourceSel").value = src;
  drawFrame();
  return true;
}
function setZero(mode) {
  state.zero = mode === "faint" ? "faint" : "hidden"; $("zeroSel").value = state.zero;
  $("scene").classList.toggle("hide0", state.zero === "hidden");
}
function setActiveOnly(on) { state.activeOnly = !!on; $("activeOnly").checked = state.activeOnly; drawTimelines(); }
function play() {
  if (state.timer !== null) return;
  if (state.frame >= cur.T - 1) setFrame(0);
  state.timer = setInterval(() => {
    if (state.frame >= cur.T - 1) pause(); else setFrame(state.frame + 1);
  }, 125);
  $("play").textContent = "\u275a\u275a pause";
}
function pause() {
  if (state.timer !== null) clearInterval(state.timer);
  state.timer = null;
  $("play").innerHTML = "&#9654; play";
  saveHash();
}
function saveHash() {
  const h = "#clip=" + cur.raw.row + "&frame=" + state.frame + "&source=" + state.source;
  if (location.hash !== h) try { history.replaceState(null, "", h); } catch (err) { /* some file: setups refuse */ }
}
function readHash() {
  const q = new URLSearchParams(location.hash.replace(/^#/, ""));
  if (DATA.sources.indexOf(q.get("source")) >= 0) state.source = $("sourceSel").value = q.get("source");
  if (q.has("zero")) setZero(q.get("zero"));
  if (q.has("frame")) state.frame = Math.max(0, Math.round(+q.get("frame")) || 0);
  if (!(q.has("clip") && setClip(q.get("clip"))) && !cur) setClip(DATA.clips[0].row);
  setFrame(state.frame);
}
function arrowsNow() {
  return Array.from($("arrows").querySelectorAll(".arrow")).map((g) => ({
    edge: g.getAttribute("data-edge"), type: +g.getAttribute("data-type"),
    sender: +g.getAttribute("data-sender"), receiver: +g.getAttribute("data-receiver")}));
}

// ------------------------------------------------------------- static parts
function drawInfo() {
  const c = cur.raw, rows = [["row", c.row + " of " + DATA.total], ["clip", c.clip]];
  if (c.scene !== null) rows.push(["scene", c.scene]);
  if (c.frame !== null) rows.push(["input frames", c.frame + "\u2013" + (c.frame + c.T - 1)]);
  rows.push(["agents", Array.from(cur.agents.values()).map((a) => a.id).join(", ")]);
  rows.push(["edges", cur.edges.length + " present, " + cur.edges.filter((e) => e.active).length + " interacting"]);
  rows.push(["image", cur.bg ? "yes" : "none"]);
  $("info").innerHTML = "";
  for (const [k, v] of rows) {
    const tr = $("info").insertRow();
    tr.insertCell().textContent = k; tr.insertCell().textContent = v;
  }
}
function setup() {
  $("title").textContent = DATA.model;
  $("title").title = DATA.path;
  $("note").textContent = DATA.note;
  DATA.clips.forEach((c, i) => {
    const o = document.createElement("option");
    o.value = i;
    o.textContent = "#" + c.row + " \u00b7 clip " + c.clip + (c.scene !== null ? " \u00b7 scene " + c.scene : "")
      + (c.frame !== null ? " \u00b7 frame " + c.frame : "");
    $("clipSel").appendChild(o);
  });
  for (const src of DATA.sources) {
    const o = document.createElement("option");
    o.value = src; o.textContent = SHORT[src];
    $("sourceSel").appendChild(o);
  }
  $("sourceSel").value = state.source;
  DATA.type_names.forEach((name, k) => {
    const d = document.createElement("div");
    d.innerHTML = '<span class="sw"></span>';
    d.firstChild.style.background = k === 0 ? EMPTY : DATA.colors[k];
    d.appendChild(document.createTextNode(k + ": " + name + (k === 0 ? " (arrows hidden or faint)" : "")));
    if (DATA.type_notes[k]) {  // what the type means: its pairs while it holds, beside the others
      const n = document.createElement("div");
      n.className = "note"; n.textContent = DATA.type_notes[k];
      d.appendChild(n);
    }
    $("legend").appendChild(d);
  });
  wire();
}
function wire() {
  $("clipSel").onchange = (ev) => setClip(DATA.clips[+ev.target.value].row);
  $("prevClip").onclick = () => stepClip(-1);
  $("nextClip").onclick = () => stepClip(1);
  $("slider").oninput = (ev) => setFrame(ev.target.value);
  $("play").onclick = () => (state.timer === null ? play() : pause());
  $("sourceSel").onchange = (ev) => setSource(ev.target.value);
  $("zeroSel").onchange = (ev) => setZero(ev.target.value);
  $("activeOnly").onchange = (ev) => setActiveOnly(ev.target.checked);
  const arrows = $("arrows");
  arrows.onmousemove = (ev) => {
    const g = ev.target.closest(".arrow");
    if (!g) return hideTip();
    const e = edgeOf(g);
    highlight(e);
    showTip(ev, edgeDetails(e, +g.getAttribute("data-t")));
  };
  arrows.onmouseleave = hideTip;
  arrows.onclick = (ev) => {
    const g = ev.target.closest(".arrow"), i = g ? cur.shown.indexOf(edgeOf(g)) : -1;
    if (i >= 0) window.scrollTo(0, $("tl").getBoundingClientRect().top + window.scrollY
      + TL.head + i * (DATA.sources.length * TL.row + TL.gap) - 80);
  };
  const tl = $("tl");
  tl.onmousemove = (ev) => {
    const c = cellAt(ev);
    if (!c) return hideTip();
    highlight(c.e);
    showTip(ev, edgeDetails(c.e, c.t, c.src));
  };
  tl.onmouseleave = hideTip;
  tl.onclick = (ev) => { const c = cellAt(ev); if (c) setFrame(c.t); };
  window.addEventListener("hashchange", readHash);
  window.addEventListener("keydown", onKey);
  let pending = null;
  window.addEventListener("resize", () => { clearTimeout(pending); pending = setTimeout(drawTimelines, 150); });
}
function stepClip(d) {
  const pos = Math.max(0, Math.min(state.pos + d, DATA.clips.length - 1));
  setClip(DATA.clips[pos].row);
}
function onKey(ev) {
  if (["INPUT", "SELECT", "BUTTON"].indexOf(ev.target.tagName) >= 0) return;  // they handle their own keys
  const keys = {ArrowLeft: () => setFrame(state.frame - 1), ArrowRight: () => setFrame(state.frame + 1),
    " ": () => (state.timer === null ? play() : pause()), PageUp: () => stepClip(-1), PageDown: () => stepClip(1)};
  if (keys[ev.key]) { ev.preventDefault(); keys[ev.key](); }
}

setup();
readHash();
window.explorer = {setFrame: setFrame, setClip: setClip, setSource: setSource, setZero: setZero,
  setActiveOnly: setActiveOnly, play: play, pause: pause, arrows: arrowsNow, cellCentre: cellCentre, data: DATA,
  clips: () => DATA.clips.map((c) => c.row),
  state: () => ({clip: cur.raw.row, frame: state.frame, transition: transitionAt(state.frame),
    source: state.source, zero: state.zero, playing: state.timer !== null})};
document.body.dataset.ready = "1";
})();
</script>
</body></html>
"""


if __name__ == "__main__":
    sys.exit(main())
