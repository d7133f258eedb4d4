"""Interactive explorer of a run's inferred interactions: one self-contained HTML file per run.

``python -m dider.analysis.explore RUN_DIR [--out FILE.html] [--max-clips K] [--clips 0,3,5]`` reads
the run's ``clips.npz`` (``RUN_DIR/predictions/clips.npz`` of a prediction run, else
``RUN_DIR/clips.npz`` of a training run's test split) and writes ``RUN_DIR/explorer.html``: the
agents' paths over the scene image with a scale bar in the data's units, the model's forecast after
the burn-in (dashed; ``forecast`` and ``forecast_start`` in clips.npz), arrows sender -> receiver
coloured by interaction type at a chosen frame, and per-edge timelines of every source (truth,
per-step posterior, segments, prior). String agent ids (``agent_names``) are shown in full; input
frame numbers are the source's (``frame`` of each clip plus its steps times ``frame_step``, the
frames per step under ``data.downsample``). The page needs no network: data, images (base64 PNG),
JavaScript and styles are inline.

Clips are addressed by their row in ``clips.npz`` everywhere (``--clips``, the page's selector, the
URL hash ``#clip=ROW&frame=F&source=segments`` (also ``&zero=faint``) and
``window.explorer.setClip(ROW)``). Frame F shows transition min(F, T-2), i.e. F -> F+1 (the last
frame shows the last transition).

Embedded data are compact: only present agents and edges, coordinates as delta-coded integers at a
precision of a thousandth of the clip's extent, edge types and probabilities (percent) run-length
coded.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import math
import sys
import zipfile
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from dider.evaluation.type_meaning import profile_notes
from dider.graph import edge_index
from dider.io import atomic_write_text

REQUIRED_KEYS = ("positions", "mask", "segments", "probs", "per_step", "prior", "clip", "num_types",
                 "model")
# Timeline strip order: the reference first, then the posterior before and after segmentation, then
# the prior.
EDGE_SOURCES = ("truth", "per_step", "segments", "prior")
EDGE_KEYS = (*EDGE_SOURCES, "probs", "step_probs")
PER_CLIP_KEYS = ("clip", "scene", "frame", "background_of")
# pixels: beyond this an embedded scene image costs MBs for no visible detail
MAX_BACKGROUND_SIDE = 1600
NONE_COLOR = "#9a9a9a"  # type 0 ("no interaction"): neutral, so real interactions stand out


class ExploreError(Exception):
    """A run folder or clips file the explorer cannot use; the message names the path or key."""


# ------------------------------------------------------------------------------------------ loading


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
        # Every type's per-step probability [S, E, T-1, K] (what prediction writes): the page shows
        # the probability of the per-step type.
        chosen = np.clip(data["per_step"].astype(np.int64), 0, step_probs.shape[-1] - 1)[..., None]
        data["step_probs"] = np.take_along_axis(step_probs, chosen, axis=-1)[..., 0]
    check_shapes(data, path)
    return data


def check_shapes(data: dict[str, np.ndarray], path: Path) -> None:
    """Shapes that agree with ``positions`` [S, T, N, 2]; raises naming the first key that does
    not."""
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
    for key in (name for k in images[images >= 0]
                for name in (f"background_{k}", f"background_{k}_extent")):
        if key not in data:
            raise ExploreError(f"{path} lacks key {key!r} (named by 'background_of')")


def type_names(data: dict[str, np.ndarray]) -> list[str]:
    num_types = int(data["num_types"])
    given = [str(x) for x in data["type_names"]] if "type_names" in data else []
    return [given[k] if k < len(given) else f"type {k}" for k in range(num_types)]


def type_colors(num_types: int) -> list[str]:
    """The timeline PNGs' colours (:mod:`dider.outputs.viz`: tab10 resampled to the type count),
    type 0 grey."""
    from matplotlib import colormaps
    from matplotlib.colors import to_hex

    cmap = colormaps["tab10"].resampled(max(num_types, 2))
    return [NONE_COLOR] + [to_hex(cmap(k)) for k in range(1, num_types)]


# ----------------------------------------------------------------------------------------- encoding


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


def agent_payload(xy: np.ndarray, present: np.ndarray, slot: int, ident: int,
                  decimals: int) -> dict[str, Any]:
    """One present agent: its path from its first to its last present frame ``f0``.., delta-coded
    (consecutive points differ by a few units: short numbers), with ``null, null`` for absent
    frames."""
    frames = np.flatnonzero(present)
    f0, f1 = int(frames[0]), int(frames[-1])
    seen = present[f0 : f1 + 1]
    points = np.round(xy[f0 : f1 + 1][seen].astype(np.float64) * 10**decimals).astype(np.int64)
    deltas = iter(np.diff(points, axis=0, prepend=0).tolist())
    coded = [v for here in seen for v in (next(deltas) if here else (None, None))]
    return {"k": slot, "id": ident, "f0": f0, "xy": coded}


def forecast_payload(data: dict[str, np.ndarray], s: int, decimals: int) -> dict[str, Any] | None:
    """The model's forecast of clip ``s`` (``forecast`` [S, P, N, 2] for frames
    ``forecast_start``..): the start frame and, per agent present at the frame before it, the
    predicted path delta-coded as in :func:`agent_payload`; with ``forecast_samples`` [S, K, P, N,
    2] also each sampled future's paths (``samples``: K lists); None without a forecast."""
    if "forecast" not in data or "forecast_start" not in data:
        return None
    start, pred = int(data["forecast_start"]), data["forecast"][s]
    alive = data["mask"][s][start - 1].astype(bool) & np.isfinite(pred).all(axis=(0, 2))

    def paths(future: np.ndarray) -> list[dict[str, Any]]:  # [P, N, 2]
        every = np.ones(len(future), bool)
        return [{"k": int(k),
                 "xy": agent_payload(future[:, k], every, int(k), int(k), decimals)["xy"]}
                for k in np.flatnonzero(alive & np.isfinite(future).all(axis=(0, 2)))]

    drawn = data["forecast_samples"][s] if "forecast_samples" in data else []
    return {"start": start, "agents": paths(pred), "samples": [paths(future) for future in drawn]}


def sources_of(data: dict[str, np.ndarray]) -> list[str]:
    return [key for key in EDGE_SOURCES if key in data]


def edge_fields(data: dict[str, np.ndarray]) -> list[str]:
    """The layout of an embedded edge: a list, not a dict, as keys repeated on every edge of every
    clip would be a sixth of the page."""
    return ["e", "s", "r", "p", "sp", *sources_of(data)]


def edge_payload(data: dict[str, np.ndarray], s: int, e: int, sender: int,
                 receiver: int) -> list[Any] | None:
    """One directed edge of clip ``s`` as laid out by :func:`edge_fields`: its index, sender and
    receiver slots, the segments' (and per-step types', else null) probabilities in percent, then
    each source's types, all run-length coded with -1 where absent; None when the edge is absent
    throughout."""
    sources = sources_of(data)
    if all((data[key][s, e] < 0).all() for key in sources):
        return None
    probs = rle(percent(data["probs"][s, e], data["segments"][s, e]))
    step = (rle(percent(data["step_probs"][s, e], data["per_step"][s, e])) if "step_probs" in data
            else None)
    return [e, sender, receiver, probs, step,
            *(rle(data[key][s, e].astype(np.int64)) for key in sources)]


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
    edges = [edge_payload(data, s, e, int(a), int(b))
             for e, (a, b) in enumerate(zip(send, recv, strict=True))]
    background = optional_int(data, "background_of", s)
    return {"row": s, "clip": int(data["clip"][s]), "scene": optional_int(data, "scene", s),
            "frame": optional_int(data, "frame", s), "T": num_frames, "d": decimals,
            "bg": background if background is not None and background >= 0 else None,
            "agents": agents, "edges": [e for e in edges if e is not None],
            "fc": forecast_payload(data, s, decimals)}  # fmt: skip


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
    return {"png": base64.b64encode(buf.getvalue()).decode("ascii"),
            "extent": [float(x) for x in extent]}


# ----------------------------------------------------------------------------------------- the page


def select_rows(num_clips: int, clips: list[int] | None, max_clips: int) -> tuple[list[int], str]:
    """The rows to embed and a note for the page when some are left out. An explicit ``clips`` list
    is taken whole (the user chose it); otherwise the first ``max_clips``."""
    if clips is not None:
        bad = [c for c in clips if not 0 <= c < num_clips]
        if bad:
            raise ExploreError(f"--clips {bad} out of range: clips.npz has rows 0..{num_clips - 1}")
        rows = list(dict.fromkeys(clips))
        if not rows:
            raise ExploreError("--clips names no clip")
        return (rows, "" if len(rows) == num_clips
                else f"showing the {len(rows)} chosen of {num_clips} clips")
    if num_clips == 0 or max_clips < 1:
        raise ExploreError(f"nothing to show: clips.npz has {num_clips} clips, --max-clips is "
                           f"{max_clips}")
    rows = list(range(min(num_clips, max_clips)))
    note = ("" if len(rows) == num_clips
            else f"showing the first {len(rows)} of {num_clips} clips (--max-clips)")
    return rows, note


def page_payload(data: dict[str, np.ndarray], path: Path, rows: list[int],
                 note: str = "") -> dict[str, Any]:
    """Everything the page shows, as JSON-ready values."""
    clips = [clip_payload(data, s) for s in rows]
    used = sorted({c["bg"] for c in clips if c["bg"] is not None})
    num_types = int(data["num_types"])
    return {"model": str(data["model"]), "path": str(path),
            "total": int(data["positions"].shape[0]), "note": note, "num_types": num_types,
            "type_names": type_names(data), "colors": type_colors(num_types),
            "type_notes": profile_notes(data["type_profile"]) if "type_profile" in data else [],
            "units": str(data["units"]) if "units" in data else "",
            "frame_step": int(data["frame_step"]) if "frame_step" in data else 1,
            "agent_names": [str(n) for n in data["agent_names"]] if "agent_names" in data else [],
            "sources": sources_of(data), "edge_fields": edge_fields(data),
            "backgrounds": {str(k): background_payload(data[f"background_{k}"],
                                                       data[f"background_{k}_extent"])
                            for k in used},
            "clips": clips}  # fmt: skip


def render_html(payload: dict[str, Any], title: str) -> str:
    # Inside <script> the HTML parser reads "</script>", and "<!--" followed by "<script" (which
    # switches it into the double-escaped state, where the page's own "</script>" no longer ends the
    # block): with every <, > and & as a JSON \u escape (the same string to JSON.parse) a name or
    # path can hold neither.
    blob = (json.dumps(payload, separators=(",", ":"))
            .replace("<", "\\u003c").replace(">", "\\u003e").replace("&", "\\u0026"))
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
        raise argparse.ArgumentTypeError("expected comma-separated clip rows such as 0,3,5, got "
                                         f"{text!r}") from err


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dider.analysis.explore",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path,
                        help="a run folder holding clips.npz or predictions/clips.npz")
    parser.add_argument("--out", type=Path, help="the HTML file to write (default "
                        "RUN_DIR/explorer.html)")
    parser.add_argument("--max-clips", type=int, default=50,
                        help="embed at most this many clips (default 50)")
    parser.add_argument("--clips", type=parse_rows,
                        help="rows of clips.npz to embed, e.g. 0,3,5 (all of them: overrides "
                        "--max-clips)")
    args = parser.parse_args(argv)
    try:
        out = write_explorer(args.run_dir, args.out, args.max_clips, args.clips)
    except ExploreError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"explorer: {out} ({out.stat().st_size / 1e6:.2f} MB)")
    return 0


def _page() -> str:
    """The page's template: explorer.html with explorer.css and explorer.js (package data beside
    this module) inlined, so the written page is one file that opens offline; render_html() fills in
    the title and data."""
    files = resources.files("dider.analysis")
    html, css, js = ((files / f"explorer.{ext}").read_text(encoding="utf-8")
                     for ext in ("html", "css", "js"))
    return html.replace("/*__CSS__*/", css.rstrip("\n")).replace("/*__JS__*/", js.rstrip("\n"))


PAGE = _page()


if __name__ == "__main__":
    sys.exit(main())
