"""clips.npz files for the explorer's tests (dider.analysis.explore), and headless Chromium helpers.

- :func:`write_clips`: 2 clips of 4 agent slots with types that switch at known transitions (``SWITCHES``):
  clip 0 has agent slot 3 absent throughout, clip 1 has slot 1 absent for frames 0-2.
- :func:`write_realistic`: a crossroads scene with a few vehicles following, yielding and passing, for the
  screenshot in docs/figures/explorer.png (``PYTHONPATH=tests python -m helpers.explore`` remakes it).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from html.parser import HTMLParser
from pathlib import Path

import numpy as np

T, N = 12, 4
NAMES = np.array(["none", "follow", "yield", "avoid"])


def edge_of(sender: int, receiver: int, n: int = N) -> int:
    """Position of sender -> receiver in the sender-major edge order without self edges."""
    return sender * (n - 1) + receiver - (receiver > sender)


# clip -> "sender-receiver" -> (type before, first transition of the new type, type after); every other
# present edge is type 0 throughout. Read at frames 2 and 9 by the tests.
SWITCHES = {
    0: {"0-1": (1, 5, 2), "0-2": (2, 8, 0), "2-0": (0, 6, 3), "1-2": (1, 99, 1)},
    1: {"3-0": (3, 99, 3), "0-3": (0, 4, 1), "1-3": (2, 99, 2)},
}
# The arrows drawn (segments) at frames 2 and 9 of clip 0, written out by hand from SWITCHES.
CLIP0_ARROWS = {
    2: {"0-1": 1, "0-2": 2, "1-0": 0, "1-2": 1, "2-0": 0, "2-1": 0},
    9: {"0-1": 2, "0-2": 0, "1-0": 0, "1-2": 1, "2-0": 3, "2-1": 0},
}


def _mask() -> np.ndarray:
    mask = np.ones((2, T, N), dtype=bool)
    mask[0, :, 3] = False  # a padding slot: absent for the whole clip
    mask[1, :3, 1] = False  # enters at frame 3
    return mask


def _segments(mask: np.ndarray) -> np.ndarray:
    seg = np.zeros((2, N * (N - 1), T - 1), dtype=np.int8)
    steps = np.arange(T - 1)
    for s, edges in SWITCHES.items():
        for key, (before, at, after) in edges.items():
            a, b = map(int, key.split("-"))
            seg[s, edge_of(a, b)] = np.where(steps < at, before, after)
    present = mask[:, :-1] & mask[:, 1:]  # [S, T-1, N]: an agent present over a transition
    send, recv = np.nonzero(~np.eye(N, dtype=bool))
    edge_present = present[:, :, send] & present[:, :, recv]  # [S, T-1, E]
    return np.where(edge_present.transpose(0, 2, 1), seg, -1).astype(np.int8)


FORECAST_START = 6  # the fixture's forecast (``forecast=True``) starts at this frame
AGENT_NAMES = np.array([f"provider-id-{i:05d}" for i in range(24)])  # long string ids, coded in ``agent``


def write_clips(path: Path, truth: bool = True, background: bool = True, names: bool = True,
                forecast: bool = False) -> dict[str, np.ndarray]:
    """The small fixture; returns what it wrote. ``forecast``: also a forecast from FORECAST_START (the true
    positions shifted by 0.3 in x) and two sampled futures (that forecast 0.5 down and up), AGENT_NAMES for the agent
    codes, units "m" and ten input frames a step."""
    mask = _mask()
    frames = np.arange(T, dtype=np.float32)[None, :, None]
    slots = np.arange(N, dtype=np.float32)[None, None, :]
    pos = np.stack([np.broadcast_to(frames * 1.0 + slots * 0.5, (2, T, N)),
                    np.broadcast_to(slots * 2.0 + frames * 0.1, (2, T, N))], axis=-1)  # fmt: skip
    seg = _segments(mask)
    per_step = seg.copy()
    per_step[0, edge_of(0, 1), 3] = 0  # a one-step flicker that segmentation removed
    prior = np.concatenate([seg[..., :1], seg[..., :-1]], axis=-1)  # the prior lags one step
    prior = np.where(seg < 0, -1, prior)
    data = {
        "positions": (pos * mask[..., None]).astype(np.float32), "mask": mask, "segments": seg,
        "probs": np.where(seg >= 0, 0.5 + 0.04 * np.arange(T - 1), 0).astype(np.float16),
        "per_step": per_step, "prior": prior, "clip": np.array([7, 11]), "scene": np.array([2, 2]),
        "frame": np.array([100, 250]), "agent": np.array([[17, 4, 23, -1], [5, 6, 7, 8]]),
        "num_types": np.array(4), "model": np.array("dider"),
    }  # fmt: skip
    if truth:
        true = seg.copy()
        true[0, edge_of(0, 1), 5] = 1  # the true switch is one step later
        data["truth"] = true
    if names:
        data["type_names"] = NAMES
    if forecast:
        data["forecast"] = (pos[:, FORECAST_START:] + np.array([0.3, 0.0], np.float32)).astype(np.float32)
        data["forecast_start"] = np.array(FORECAST_START)
        data["agent_names"], data["units"] = AGENT_NAMES, np.array("m")
        data["frame_step"] = np.array(10)  # data.downsample=10: a step is ten input frames
        data["forecast_samples"] = np.stack([data["forecast"] + np.array([0.0, dy], np.float32) for dy in (-0.5, 0.5)],
                                            axis=1)  # [S, K, P, N, 2]
    if background:
        ramp = np.linspace(0, 255, 30, dtype=np.uint8)
        data["background_of"] = np.array([0, -1])
        data["background_0"] = np.stack([np.tile(ramp, (20, 1))] * 3, axis=-1)
        data["background_0_extent"] = np.array([-2.0, 14.0, -3.0, 9.0])
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **data)
    return data


# ------------------------------------------------------------------------------ a realistic scene

EXTENT = (0.0, 80.0, 0.0, 60.0)  # metres: left, right, bottom, top
CENTRE = np.array([40.0, 30.0])
DT = 0.4  # seconds per frame
# lane -> (axis it runs along, its offset on the other axis, direction)
LANES = {"east": (0, 28.0, 1), "west": (0, 32.0, -1), "north": (1, 42.0, 1), "south": (1, 38.0, -1)}


def crossroads_image() -> np.ndarray:
    """Two roads crossing on grass, flat colours (small PNG), 2 px per metre."""
    h, w = 120, 160
    img = np.empty((h, w, 3), dtype=np.uint8)
    img[:] = (206, 224, 190)
    rows = 60 - np.arange(h)[:, None] / 2 - 0.25  # metres, row 0 at the top
    cols = np.arange(w)[None, :] / 2 + 0.25
    road = (np.abs(rows - 30) < 4.5) | (np.abs(cols - 40) < 4.5)
    img[np.broadcast_to(road, (h, w))] = (188, 188, 184)
    dash = ((np.abs(rows - 30) < 0.3) & (cols % 6 < 3)) | ((np.abs(cols - 40) < 0.3) & (rows % 6 < 3))
    img[np.broadcast_to(dash, (h, w))] = (250, 250, 250)
    return img


def _motions(rng: np.random.Generator, steps: int) -> list[tuple[str, np.ndarray]]:
    """(lane, distance along the lane [T]) of each vehicle: an eastbound platoon of three, a northbound car
    waiting at its stop line until the platoon has crossed, oncoming cars west- and southbound, a late
    eastbound car."""
    t = np.arange(steps) * DT
    v = 5.0 * rng.uniform(0.9, 1.1)
    platoon = [start + rng.uniform(-1.5, 1.5) + v * t + 1.2 * np.sin(t / 2 + k)
               for k, start in enumerate((6.0, -9.0, -22.0))]  # fmt: skip
    t_go = (46 - platoon[-1][0]) / v  # the platoon's last car has crossed
    after = np.clip(t - t_go, 0, None)
    accel = np.where(after < 2.8, 1.25 * after**2, 1.25 * 2.8**2 + 7.0 * (after - 2.8))
    waiting = np.minimum(-5 + 6.0 * t, 20.0) + accel
    oncoming = 95 + rng.uniform(-3, 3) - 7.0 * t
    south = 130 + rng.uniform(-3, 3) - 6.0 * t
    late = -45 + rng.uniform(-3, 3) + 6.0 * t
    along = [*platoon, waiting, 80 - oncoming, 60 - south, late]
    return list(zip(["east", "east", "east", "north", "west", "south", "east"], along, strict=True))


def _vehicles(rng: np.random.Generator, steps: int, slots: int) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Positions [T, N, 2], mask [T, N] (inside the image) and lane of each slot; unused slots are padding."""
    pos, mask, lanes = np.zeros((steps, slots, 2)), np.zeros((steps, slots), dtype=bool), [""] * slots
    for k, (lane, along) in enumerate(_motions(rng, steps)[:slots]):
        axis, offset, sign = LANES[lane]
        length = EXTENT[1] if axis == 0 else EXTENT[3]
        pos[:, k, axis] = along if sign > 0 else length - along
        pos[:, k, 1 - axis] = offset + 0.15 * np.sin(np.arange(steps) / 7 + k)  # a little lane wander
        mask[:, k] = (along > 0) & (along < length)
        lanes[k] = lane
    return pos * mask[..., None], mask, lanes


def _pair_type(pos: np.ndarray, speed: np.ndarray, lanes: list[str], a: int, b: int, t: int) -> int:
    """1 following (same lane, a ahead of b by < 20 m), 2 yielding (b waits near the crossing while a
    crosses it), 3 passing (opposite lanes, < 12 m), else 0."""
    gap = float(np.linalg.norm(pos[t, a] - pos[t, b]))
    axis, _, sign = LANES[lanes[a]]
    near_a, near_b = (float(np.linalg.norm(pos[t, k] - CENTRE)) for k in (a, b))
    if lanes[a] == lanes[b]:
        return int((pos[t, a, axis] - pos[t, b, axis]) * sign > 0 and gap < 20)
    if LANES[lanes[b]][0] != axis:
        return 2 * int(speed[t, b] < 1.5 and near_b < 15 and near_a < 20)
    return 3 * int(gap < 12)


def _true_types(pos: np.ndarray, mask: np.ndarray, lanes: list[str]) -> np.ndarray:
    """[E, T-1] types of every directed edge, -1 where either vehicle is absent over the transition."""
    steps, slots = mask.shape
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=-1) / DT  # [T-1, N]
    present = mask[:-1] & mask[1:]
    send, recv = np.nonzero(~np.eye(slots, dtype=bool))
    out = np.full((len(send), steps - 1), -1, dtype=np.int8)
    for e, (a, b) in enumerate(zip(send, recv, strict=True)):
        for t in np.flatnonzero(present[:, a] & present[:, b]):
            out[e, t] = _pair_type(pos, speed, lanes, a, b, t)
    return out


def _inferred(rng: np.random.Generator, truth: np.ndarray) -> tuple[np.ndarray, ...]:
    """Segments (truth with switches a step late on half the edges), per-step types (segments with
    flickers), the prior (segments two steps late) and the segments' probabilities."""
    seg = np.where(rng.random(truth.shape[0])[:, None] < 0.5, np.roll(truth, 1, axis=1), truth)
    seg = np.where(truth < 0, -1, np.where(seg < 0, truth, seg))
    flicker = (rng.random(seg.shape) < 0.03) & (seg >= 0)
    per_step = np.where(flicker, rng.integers(0, 4, seg.shape), seg)
    prior = np.where(seg < 0, -1, np.concatenate([np.zeros_like(seg[:, :2]), seg[:, :-2]], axis=1))
    wobble = np.abs(np.sin(np.arange(seg.shape[1]) / 5.0)) * rng.random((seg.shape[0], 1))
    return seg, per_step.astype(np.int8), prior.astype(np.int8), np.clip(0.97 - 0.35 * wobble, 0.4, 0.99)


def write_realistic(path: Path, clips: int = 6, steps: int = 60, slots: int = 8, seed: int = 0) -> Path:
    """A crossroads data set with 4 interaction types, truth, agent ids, frame numbers and a scene image."""
    rng = np.random.default_rng(seed)
    keys = ("positions", "mask", "truth", "segments", "per_step", "prior", "probs")
    out: dict[str, list[np.ndarray]] = {k: [] for k in keys}
    for _ in range(clips):
        pos, mask, lanes = _vehicles(rng, steps, slots)
        truth = _true_types(pos, mask, lanes)
        values = (pos, mask, truth, *_inferred(rng, truth))
        for key, value in zip(keys, values, strict=True):
            out[key].append(value)
    data = {k: np.stack(v) for k, v in out.items()}
    agent = 100 + np.arange(clips * slots).reshape(clips, slots)
    agent[:, -1] = -1
    data |= {"positions": data["positions"].astype(np.float32), "probs": data["probs"].astype(np.float16),
             "clip": np.arange(clips) * 3, "scene": np.zeros(clips, dtype=np.int64),
             "frame": 1000 + 75 * np.arange(clips), "agent": agent, "num_types": np.array(4),
             "model": np.array("dider"), "type_names": np.array(["none", "following", "yielding", "passing"]),
             "background_of": np.zeros(clips, dtype=np.int64), "background_0": crossroads_image(),
             "background_0_extent": np.array(EXTENT)}  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **data)
    return path


# ------------------------------------------------------------------------------ headless Chromium


def chromium() -> str | None:
    """A Chromium or Chrome binary on PATH, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        found = shutil.which(name)
        if found:
            return found
    return None


def run_chromium(binary: str, url: str, *args: str, timeout: float = 120) -> str:
    """One headless page load; returns stdout (the DOM with --dump-dom). A fresh profile each time: two
    runs sharing one would lock each other out."""
    with tempfile.TemporaryDirectory() as profile:
        cmd = [binary, "--headless=new", "--disable-gpu", "--no-sandbox", "--no-first-run", "--disable-extensions",
               "--disable-dev-shm-usage", "--hide-scrollbars", f"--user-data-dir={profile}", *args, url]  # fmt: skip
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"{binary} failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return proc.stdout


class ArrowParser(HTMLParser):
    """The arrows (``g.arrow``) of a dumped DOM as data-edge -> data-type, and the body's data-* state."""

    def __init__(self) -> None:
        super().__init__()
        self.arrows: dict[str, int] = {}
        self.body: dict[str, str] = {}

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if tag == "g" and "arrow" in a.get("class", "").split():
            self.arrows[a["data-edge"]] = int(a["data-type"])
        elif tag == "body":
            self.body = {k[5:]: v for k, v in a.items() if k.startswith("data-")}


def read_arrows(dom: str) -> ArrowParser:
    parser = ArrowParser()
    parser.feed(dom)
    return parser


def screenshot(html: Path, png: Path, fragment: str = "", size: str = "1200,900") -> Path:
    """A headless screenshot of ``html`` (at URL fragment ``fragment``), palette-reduced to stay small."""
    from PIL import Image

    binary = chromium()
    if binary is None:
        raise RuntimeError("no chromium binary on PATH (apt-get install chromium)")
    raw = png.with_suffix(".raw.png")
    run_chromium(binary, html.resolve().as_uri() + fragment, f"--screenshot={raw}", f"--window-size={size}")
    Image.open(raw).convert("RGB").quantize(colors=128, method=Image.Quantize.MEDIANCUT).save(png, optimize=True)
    raw.unlink()
    return png


def make_figure(png: Path) -> Path:
    """docs/figures/explorer.png: the realistic fixture's explorer at a frame with interactions."""
    from dider.analysis.explore import write_explorer

    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "synth_run"
        write_realistic(run / "clips.npz")
        with np.load(run / "clips.npz") as data:
            busiest = int((data["segments"][0] > 0).sum(axis=0).argmax())  # the frame with most arrows
        html = write_explorer(run)
        return screenshot(html, png, f"#clip=0&frame={busiest}")


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).parents[1] / "docs/figures/explorer.png"
    print(make_figure(target), f"{target.stat().st_size / 1e3:.0f} KB")
