"""The interaction explorer (dider.analysis.explore): what the page embeds, the CLI, the page in headless Chromium."""

from __future__ import annotations

import base64
import html
import io
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dider.analysis.explore import (
    clip_payload,
    decode_path,
    edge_fields,
    load_clips,
    main,
    page_payload,
    rle,
    select_rows,
    unrle,
    write_explorer,
)
from helpers.explore import (
    CLIP0_ARROWS,
    FORECAST_START,
    SWITCHES,
    T,
    chromium,
    edge_of,
    read_arrows,
    run_chromium,
    write_clips,
    write_realistic,
)


def embedded(page: Path) -> dict:
    """The DATA object a written page carries."""
    text = page.read_text()
    blob = text.split("const DATA = ", 1)[1].split(";</script>", 1)[0]
    return json.loads(blob)


def edges_by_pair(clip: dict, data: dict[str, np.ndarray]) -> dict[str, dict]:
    """A clip's embedded edges as "sender-receiver" -> {field: value}."""
    fields = edge_fields(data)
    return {f"{e[1]}-{e[2]}": dict(zip(fields, e, strict=True)) for e in clip["edges"]}


def expected_type(clip: int, pair: str, t: int) -> int:
    before, at, after = SWITCHES[clip].get(pair, (0, 99, 0))
    return before if t < at else after


@pytest.fixture
def run(tmp_path: Path) -> Path:
    write_clips(tmp_path / "run" / "clips.npz")
    return tmp_path / "run"


# ---------------------------------------------------------------------------------------- embedded data


def test_rle_round_trip() -> None:
    values = np.array([-1, -1, -1, 0, 0, 2, 1, 1, 1, 1])
    assert rle(values) == [[-1, 3], [0, 2], 2, [1, 4]]
    assert unrle(rle(values)) == values.tolist()
    assert rle(np.array([], dtype=np.int64)) == [] and unrle([]) == []


def test_clip_types_at_known_frames(run: Path) -> None:
    data = load_clips(run / "clips.npz")
    clip = clip_payload(data, 0)
    pairs = edges_by_pair(clip, data)
    assert set(pairs) == {"0-1", "0-2", "1-0", "1-2", "2-0", "2-1"}  # slot 3 is absent: its edges dropped
    for pair, edge in pairs.items():
        segments = unrle(edge["segments"])
        assert len(segments) == T - 1
        assert segments == [expected_type(0, pair, t) for t in range(T - 1)], pair
    assert {frame: {p: unrle(e["segments"])[frame] for p, e in pairs.items()} for frame in (2, 9)} == CLIP0_ARROWS
    one = pairs["0-1"]
    assert unrle(one["per_step"])[3] == 0 and unrle(one["segments"])[3] == 1  # the flicker segmentation removed
    assert unrle(one["truth"])[5] == 1 and unrle(one["prior"])[5] == 1  # truth and prior switch a step later
    assert unrle(one["p"])[:3] == [50, 54, 58]  # percent
    assert one["e"] == edge_of(0, 1)


def test_clip_agents_ids_and_paths(run: Path) -> None:
    data = load_clips(run / "clips.npz")
    clip = clip_payload(data, 0)
    assert [(a["k"], a["id"], a["f0"]) for a in clip["agents"]] == [(0, 17, 0), (1, 4, 0), (2, 23, 0)]
    assert (clip["row"], clip["clip"], clip["scene"], clip["frame"], clip["T"], clip["bg"]) == (0, 7, 2, 100, T, 0)
    for agent in clip["agents"]:
        path = np.array(decode_path(agent["xy"], clip["d"]))
        assert np.allclose(path, data["positions"][0, :, agent["k"]], atol=10 ** -clip["d"])


def test_agent_entering_late(run: Path) -> None:
    """Clip 1: slot 1 enters at frame 3, so its edges are absent (-1) over transitions 0-2."""
    data = load_clips(run / "clips.npz")
    clip = clip_payload(data, 1)
    agents = {a["k"]: a for a in clip["agents"]}
    assert agents[1]["f0"] == 3 and len(agents[1]["xy"]) == 2 * (T - 3)
    assert [a["id"] for a in clip["agents"]] == [5, 6, 7, 8]
    pairs = edges_by_pair(clip, data)
    assert len(pairs) == 12
    assert unrle(pairs["1-3"]["segments"]) == [-1] * 3 + [2] * (T - 4)
    assert unrle(pairs["1-3"]["p"])[:3] == [-1] * 3
    assert unrle(pairs["0-3"]["segments"])[3:5] == [0, 1]
    assert clip["bg"] is None


def test_forecast_names_and_units_embedded(tmp_path: Path) -> None:
    """The forecast of each agent present at the frame before it starts, decoded to the array's values; the
    agents' string names and the positions' units."""
    path = tmp_path / "clips.npz"
    data = write_clips(path, forecast=True)
    payload = page_payload(load_clips(path), path, [0, 1])
    assert payload["units"] == "m" and payload["agent_names"][17] == "provider-id-00017" and payload["frame_step"] == 10
    for s, clip in enumerate(payload["clips"]):
        fc = clip["fc"]
        assert fc["start"] == FORECAST_START
        assert [a["k"] for a in fc["agents"]] == ([0, 1, 2] if s == 0 else [0, 1, 2, 3])  # slot 3 absent in clip 0
        for agent in fc["agents"]:
            path_xy = np.array(decode_path(agent["xy"], clip["d"]))
            assert np.allclose(path_xy, data["forecast"][s, :, agent["k"]], atol=10 ** -clip["d"])
        assert len(fc["samples"]) == 2 and [[a["k"] for a in paths] for paths in fc["samples"]] == [
            [a["k"] for a in fc["agents"]]] * 2
        for k, paths in enumerate(fc["samples"]):
            for agent in paths:
                path_xy = np.array(decode_path(agent["xy"], clip["d"]))
                assert np.allclose(path_xy, data["forecast_samples"][s, k, :, agent["k"]], atol=10 ** -clip["d"])
    write_clips(tmp_path / "plain.npz")
    plain = page_payload(load_clips(tmp_path / "plain.npz"), tmp_path / "plain.npz", [0])
    assert plain["clips"][0]["fc"] is None and plain["units"] == "" and plain["agent_names"] == []
    assert plain["frame_step"] == 1


def test_optional_keys_absent(tmp_path: Path) -> None:
    path = tmp_path / "clips.npz"
    write_clips(path, truth=False, background=False, names=False)
    payload = page_payload(load_clips(path), path, [0, 1])
    assert payload["sources"] == ["per_step", "segments", "prior"]
    assert payload["edge_fields"] == ["e", "s", "r", "p", "sp", "per_step", "segments", "prior"]
    assert all(len(e) == 8 and e[4] is None for e in payload["clips"][0]["edges"])
    assert payload["type_names"] == ["type 0", "type 1", "type 2", "type 3"]
    assert payload["backgrounds"] == {} and all(c["bg"] is None for c in payload["clips"])
    assert len(payload["colors"]) == 4 and payload["colors"][0] == "#9a9a9a"


def test_background_embedded_once(run: Path) -> None:
    from PIL import Image

    payload = page_payload(load_clips(run / "clips.npz"), run / "clips.npz", [0, 1])
    assert list(payload["backgrounds"]) == ["0"]
    image = Image.open(io.BytesIO(base64.b64decode(payload["backgrounds"]["0"]["png"])))
    assert image.format == "PNG" and image.size == (30, 20)
    assert payload["backgrounds"]["0"]["extent"] == [-2.0, 14.0, -3.0, 9.0]
    only_second = page_payload(load_clips(run / "clips.npz"), run / "clips.npz", [1])
    assert only_second["backgrounds"] == {}  # images of clips left out are not embedded


def test_select_rows() -> None:
    assert select_rows(10, None, 50) == (list(range(10)), "")
    rows, note = select_rows(300, None, 50)
    assert rows == list(range(50)) and "50 of 300" in note
    assert select_rows(10, [5, 0, 5], 1) == ([5, 0], "showing the 2 chosen of 10 clips")


def test_page_is_compact(tmp_path: Path) -> None:
    """300 realistic clips (8 agent slots, 60 frames, 4 sources) stay within a few MB."""
    small = tmp_path / "small" / "clips.npz"
    write_realistic(small)
    with np.load(small) as npz:
        data = dict(npz)
    big = {k: np.concatenate([v] * 50) if v.ndim and v.shape[0] == 6 and k != "background_0" else v
           for k, v in data.items()}  # fmt: skip
    (tmp_path / "big").mkdir()
    np.savez_compressed(tmp_path / "big" / "clips.npz", **big)
    page = write_explorer(tmp_path / "big", max_clips=300)
    assert len(embedded(page)["clips"]) == 300
    assert page.stat().st_size < 3.6e6, page.stat().st_size  # 3.38 MB: ~11 KB a clip


def test_script_end_tag_in_names_is_escaped(tmp_path: Path) -> None:
    path = tmp_path / "run" / "clips.npz"
    write_clips(path)
    with np.load(path) as npz:
        data = dict(npz) | {"model": np.array("</script><b>x")}
    np.savez_compressed(path, **data)
    page = write_explorer(tmp_path / "run")
    assert page.read_text().count("</script>") == 2  # the two real ones
    assert embedded(page)["model"] == "</script><b>x"


HOSTILE = "<!--<script>a & b</script>"  # "<!--<script" puts the HTML parser into script-data double-escaped state


def test_browser_runs_the_page_whose_names_hold_markup(tmp_path: Path) -> None:
    """A model and agents named with comment and script markup: the data block holds no <, > or &, the page's own
    code runs in headless Chromium (it draws the arrows of the frame) and the names read back as given."""
    path = tmp_path / "run" / "clips.npz"
    write_clips(path, forecast=True)  # with agent names
    with np.load(path) as npz:
        data = dict(npz)
    names = np.array([f"{HOSTILE}{i}" for i in range(len(data["agent_names"]))])
    np.savez_compressed(path, **(data | {"model": np.array(HOSTILE), "agent_names": names}))
    page = write_explorer(tmp_path / "run")
    block = page.read_text().split("const DATA = ", 1)[1].split(";</script>", 1)[0]
    assert not set("<>&") & set(block)
    assert embedded(page)["model"] == HOSTILE and embedded(page)["agent_names"][0] == f"{HOSTILE}0"
    dom = run_chromium(browser(), page.resolve().as_uri() + "#clip=0&frame=9", "--dump-dom")
    assert read_arrows(dom).arrows == CLIP0_ARROWS[9]  # the explorer's script ran


# ------------------------------------------------------------------------------------------------- CLI


def test_cli_writes_default_page_prediction_first(run: Path, capsys: pytest.CaptureFixture) -> None:
    path = run / "predictions" / "clips.npz"
    write_clips(path, truth=False)
    assert main([str(run)]) == 0
    page = run / "explorer.html"
    assert str(page) in capsys.readouterr().out
    assert embedded(page)["path"] == str(path) and "truth" not in embedded(page)["sources"]
    assert [p.name for p in run.iterdir() if p.name.endswith(".tmp")] == []  # the temp file was renamed


def test_cli_out_and_clips(run: Path, tmp_path: Path) -> None:
    out = tmp_path / "elsewhere" / "page.html"
    assert main([str(run), "--out", str(out), "--clips", "1"]) == 0
    data = embedded(out)
    assert [c["row"] for c in data["clips"]] == [1] and data["note"] == "showing the 1 chosen of 2 clips"
    assert main([str(run), "--out", str(out), "--max-clips", "1"]) == 0
    assert [c["row"] for c in embedded(out)["clips"]] == [0] and "--max-clips" in embedded(out)["note"]


def test_cli_missing_run_dir(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(tmp_path / "nope")]) == 2
    assert f"run directory not found: {tmp_path / 'nope'}" in capsys.readouterr().err


def test_cli_missing_file_names_both_paths(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "predictions" / "clips.npz") in err and str(tmp_path / "clips.npz") in err


@pytest.mark.parametrize("key", ["prior", "num_types", "background_0_extent"])
def test_cli_missing_key(run: Path, key: str, capsys: pytest.CaptureFixture) -> None:
    with np.load(run / "clips.npz") as npz:
        data = {k: v for k, v in npz.items() if k != key}
    np.savez_compressed(run / "clips.npz", **data)
    assert main([str(run)]) == 2
    assert f"lacks key '{key}'" in capsys.readouterr().err
    assert not (run / "explorer.html").exists()


def test_cli_bad_shape_and_rows(run: Path, capsys: pytest.CaptureFixture) -> None:
    assert main([str(run), "--clips", "0,5"]) == 2
    assert "--clips [5] out of range" in capsys.readouterr().err
    with np.load(run / "clips.npz") as npz:
        data = dict(npz) | {"probs": np.zeros((2, 12, T), dtype=np.float16)}
    np.savez_compressed(run / "clips.npz", **data)
    assert main([str(run)]) == 2
    assert "key 'probs' has shape (2, 12, 12), expected (2, 12, 11)" in capsys.readouterr().err


def test_module_entry_point(run: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "dider.analysis.explore", str(run), "--max-clips", "1"],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert (run / "explorer.html").is_file()
    proc = subprocess.run([sys.executable, "-m", "dider.analysis.explore", str(run / "x")], capture_output=True,
                          text=True)
    assert proc.returncode == 2 and "run directory not found" in proc.stderr


# --------------------------------------------------------------------------------------------- browser

# Appended to a copy of the page: drives window.explorer after the page has read its URL hash, and leaves
# what it saw in <pre id="result"> for --dump-dom.
DRIVER = """<script>
(function () {
  const ex = window.explorer, out = {};
  const seen = () => ({state: ex.state(), arrows: Object.fromEntries(ex.arrows().map((a) => [a.edge, a.type]))});
  out.hash = seen();
  const tip = () => document.getElementById("tip").textContent;
  const mouse = (kind, node, x, y) => node.dispatchEvent(new MouseEvent(kind, {bubbles: true, clientX: x, clientY: y}));
  const hover = (node, x, y) => mouse("mousemove", node, x, y);
  const hit = document.querySelector('.arrow[data-edge="0-1"] .hit'), box = hit.getBoundingClientRect();
  hover(hit, box.left + box.width / 2, box.top + box.height / 2);
  out.arrow_tip = tip();
  const cell = ex.cellCentre(0, "truth", 5);  // row 0 is edge 0-1
  hover(document.getElementById("tl"), cell.x, cell.y);
  out.cell_tip = tip();
  mouse("click", document.getElementById("tl"), cell.x, cell.y);
  out.clicked = ex.state().frame;
  ex.setFrame(9); out.frame9 = seen();
  ex.setSource("truth"); ex.setFrame(5); out.truth5 = seen();
  ex.setSource("segments"); out.segments5 = seen();
  ex.setClip(1); ex.setFrame(1); out.clip1 = seen();
  out.bad_clip = ex.setClip(42);
  ex.play(); out.playing = ex.state().playing; ex.pause(); out.paused = !ex.state().playing;
  out.text = document.getElementById("frameLabel").textContent;
  const pre = document.createElement("pre");
  pre.id = "result"; pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
})();
</script></body>"""


def browser() -> str:
    binary = chromium()
    if binary is None:
        pytest.skip("no chromium binary on PATH (Debian: apt-get install chromium)")
    return binary


def test_browser_draws_types_of_each_frame(run: Path) -> None:
    """The real page in headless Chromium: arrows' data-type at frames 2 and 9 as the fixture says, from
    the URL hash and through window.explorer."""
    binary = browser()
    page = write_explorer(run)
    driven = run / "driven.html"
    driven.write_text(page.read_text().replace("</body>", DRIVER))
    start = time.perf_counter()
    dom = run_chromium(binary, driven.resolve().as_uri() + "#clip=0&frame=2", "--dump-dom")
    plain = read_arrows(run_chromium(binary, page.resolve().as_uri() + "#clip=0&frame=9", "--dump-dom"))
    print(f"two headless page loads: {time.perf_counter() - start:.1f} s")
    seen = json.loads(html.unescape(re.search(r'<pre id="result">(.*?)</pre>', dom, re.S).group(1)))

    assert seen["hash"]["state"] == {"clip": 0, "frame": 2, "transition": 2, "source": "segments", "zero": "hidden",
                                     "forecast": True, "playing": False}  # fmt: skip
    assert seen["hash"]["arrows"] == CLIP0_ARROWS[2]
    arrow_tip = seen["arrow_tip"].splitlines()  # every source at step 2 of edge 0 -> 1 (agent ids 17, 4)
    assert arrow_tip[0].startswith("agent 17 \u2192 agent 4") and "input frames 102\u2192103" in arrow_tip[1]
    assert arrow_tip[2:] == ["truth: 1 follow", "per step: 1 follow", "segments: 1 follow   p = 0.58",
                             "prior: 1 follow"]  # fmt: skip
    cell_tip = seen["cell_tip"].splitlines()  # the truth strip only, at step 5
    assert cell_tip[1:] == ["step 5 (frames 5\u21926), input frames 105\u2192106", "truth: 1 follow"]
    assert seen["clicked"] == 5
    assert seen["frame9"]["arrows"] == CLIP0_ARROWS[9]
    changed = {k for k in CLIP0_ARROWS[2] if CLIP0_ARROWS[2][k] != CLIP0_ARROWS[9][k]}
    assert changed == {"0-1", "0-2", "2-0"}
    assert plain.arrows == CLIP0_ARROWS[9]  # the URL hash alone, on the page as written
    assert plain.body["clip"] == "0" and plain.body["frame"] == "9" and plain.body["transition"] == "9"

    assert seen["truth5"]["arrows"]["0-1"] == 1 and seen["segments5"]["arrows"]["0-1"] == 2
    clip1 = seen["clip1"]
    assert clip1["state"]["clip"] == 1 and clip1["state"]["frame"] == 1
    assert clip1["arrows"] == {"0-2": 0, "0-3": 0, "2-0": 0, "2-3": 0, "3-0": 3, "3-2": 0}  # slot 1 not yet there
    assert seen["bad_clip"] is False and seen["playing"] and seen["paused"]
    assert "input frame 251" in seen["text"]  # frame[1] = 250, plus frame 1
    final = read_arrows(dom)  # the DOM itself, after the driver's last step
    assert final.arrows == clip1["arrows"]


def test_browser_draws_forecast_scale_bar_full_names_and_source_frames(tmp_path: Path) -> None:
    """The page in headless Chromium draws one dashed forecast per agent that carries on, from its position
    at the frame before the forecast, a scale bar of a round length in metres, the long names in full (on the
    scene and the timelines), and the source's frame numbers (ten input frames a step)."""
    binary = browser()
    data = write_clips(tmp_path / "run" / "clips.npz", forecast=True)
    page = write_explorer(tmp_path / "run")
    dom = run_chromium(binary, page.resolve().as_uri() + "#clip=0&frame=2", "--dump-dom")
    forecast = re.search(r'<g id="forecast">(.*?)</g>', dom, re.S).group(1)
    paths = re.findall(r'<path class="fc" data-agent="(\d+)" d="([^"]+)"', forecast)
    assert [int(a) for a, _ in paths] == [17, 4, 23]  # clip 0's present agents, by slot
    assert all(len(re.findall("[ML]", d)) == 1 + T - FORECAST_START for _, d in paths)  # start point + forecast
    drawn = re.findall(r'<path class="fcs" data-agent="(\d+)"', forecast)
    assert [int(a) for a in drawn] == [17, 4, 23] * 2  # each sampled future, thin, under the forecast
    bar = re.search(r'<g id="scalebar" data-length="([\d.]+)">.*?<text[^>]*>([^<]+)</text>', dom, re.S)
    assert float(bar.group(1)) in {1, 2, 5, 10, 20, 50} and bar.group(2) == f"{float(bar.group(1)):g} m"
    labels = re.findall(r'<g class="agent" data-agent="(\d+)"><title>agent ([^<]+)</title>.*?<text[^>]*>([^<]+)</text>',
                        dom, re.S)
    assert labels[0] == ("17", "provider-id-00017", "provider-id-00017")
    assert {full for _, full, _ in labels} == {str(data["agent_names"][k]) for k in (17, 4, 23)}
    pairs = re.findall(r'<text class="edgelabel"[^>]*>([^<]+)</text>', dom)
    assert "provider-id-00017\u2192provider-id-00004" in pairs
    frame = re.search(r'<[^>]*id="frameLabel"[^>]*>([^<]+)<', dom).group(1)
    assert "input frame 120" in frame  # clip 0 starts at input frame 100; frame 2 is two steps of ten later


@pytest.mark.slow
def test_browser_screenshot(tmp_path: Path) -> None:
    """A realistic run renders: the scene image, and arrows in the types' colours (the docs figure is made
    the same way: ``PYTHONPATH=tests python -m helpers.explore``)."""
    from PIL import Image

    binary = browser()
    write_realistic(tmp_path / "run" / "predictions" / "clips.npz")
    page = write_explorer(tmp_path / "run")
    shot = tmp_path / "shot.png"
    run_chromium(binary, page.resolve().as_uri() + "#clip=0&frame=23", f"--screenshot={shot}",
                 "--window-size=1200,900", "--hide-scrollbars")  # fmt: skip
    pixels = np.asarray(Image.open(shot).convert("RGB")).reshape(-1, 3).astype(int)
    assert len(pixels) == 1200 * 900
    colours = {tuple(int(c[i : i + 2], 16) for i in (1, 3, 5)) for c in embedded(page)["colors"][1:]}
    colours.add((206, 224, 190))  # the scene image's grass
    for colour in colours:
        assert (np.abs(pixels - colour).sum(axis=1) < 12).sum() > 50, colour
