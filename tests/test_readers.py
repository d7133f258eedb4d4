"""A format as one reader: ETH/UCY pedestrians' text files (frame agent x y) read into the track table that
``data=table`` windows, with each problem named by file and line, and a short training on them (``data=eth_ucy``)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from dider.data.readers import read_tracks
from dider.run import train


def write_scenes(folder: Path, scenes: int = 5, frames: int = 36, people: int = 4, seed: int = 0) -> Path:
    """ETH/UCY-style files: people walking at about 1.3 m/s, a frame number every 10 (every 6 in the first file, as
    ETH's own), tab-separated, one file a scene."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    for s in range(scenes):
        step = 6 if s == 0 else 10
        start, heading = rng.uniform(-5, 5, (people, 2)), rng.uniform(0, 2 * np.pi, people)
        velocity = 1.3 * np.stack([np.cos(heading), np.sin(heading)], 1)
        lines = []
        for f in range(frames):
            for p in range(people):
                x, y = start[p] + velocity[p] * f * 0.4 + rng.normal(0, 0.02, 2)
                lines.append(f"{(f + 3) * step}\t{p + 1}\t{x:.3f}\t{y:.3f}")
        (folder / f"scene{s}.txt").write_text("\n".join(lines) + "\n")
    return folder


def test_the_reader_makes_steps_of_frames_and_scenes_of_files(tmp_path):
    table = read_tracks("eth_ucy", write_scenes(tmp_path / "eth", scenes=2, frames=3, people=2))
    assert list(table.columns) == ["scene", "agent", "frame", "x", "y"]
    assert sorted(set(table.scene)) == ["scene0", "scene1"]
    assert sorted(set(table.frame)) == [3, 4, 5]  # frames 18, 24, 30 (step 6) and 30, 40, 50 (step 10)
    one = read_tracks("eth_ucy", tmp_path / "eth" / "scene1.txt")
    assert len(one) == 6 and set(one.scene) == {"scene1"}


@pytest.mark.parametrize("line, why", [("10 1 2.0", "line 2 is not four numbers"),
                                       ("10 1 x 2.0", "line 2 is not four numbers"),
                                       ("10 1 nan 2.0", "line 2 is not four numbers"),
                                       ("1.43 1 1.0 2.0", "line 2: the frame number 1.43 is not a whole number"),
                                       ("10 2.5 1.0 2.0", "line 2: the agent number 2.5 is not a whole number")])
def test_a_bad_line_is_named_with_its_file(tmp_path, line, why):
    (tmp_path / "bad.txt").write_text(f"0 1 1.0 2.0\n{line}\n")
    with pytest.raises(ValueError, match=f"bad.txt: {why}"):
        read_tracks("eth_ucy", tmp_path)


def test_missing_input_and_unknown_readers_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no .txt files in the folder"):
        read_tracks("eth_ucy", tmp_path)
    with pytest.raises(FileNotFoundError, match="no such file or folder"):
        read_tracks("eth_ucy", tmp_path / "nowhere")
    with pytest.raises(ValueError, match="data.source.reader='sdd': unknown; known: table .* eth_ucy"):
        read_tracks("sdd", tmp_path)


def test_a_short_training_on_pedestrian_files(make_cfg, tmp_path):
    folder = write_scenes(tmp_path / "eth")
    cfg = make_cfg(["data=eth_ucy", f"data.source.path={folder}", "logger=none", "data.num_train=null",
                    "data.num_val=null", "data.num_test=null", "protocol.samples=0"], out=tmp_path / "run")
    assert cfg.protocol.burn_in == 8 and list(cfg.protocol.horizons) == [1, 6, 12]
    metrics = train(cfg)
    assert all(math.isfinite(metrics[f"test/ade/h{h:02d}"]) for h in (1, 6, 12))


def test_a_new_format_is_one_module_found_by_its_name(tmp_path, monkeypatch):
    """A module beside the readers that says TRACKS = True is a reader under its own name, with no list to edit:
    ``data.source.reader`` accepts it and ``read_tracks`` reads with it."""
    import dider.data.readers as readers

    package = tmp_path / "extra"
    package.mkdir()
    (package / "pairs_tsv.py").write_text(
        "import pandas as pd\nTRACKS = True\n\n\ndef read(path):\n"
        "    return pd.read_csv(path, sep='\\t', names=['agent', 'frame', 'x', 'y'])\n")
    (tmp_path / "walk.tsv").write_text("1\t0\t0.0\t0.0\n1\t1\t0.5\t0.0\n2\t0\t1.0\t1.0\n2\t1\t1.0\t1.5\n")
    monkeypatch.setattr(readers, "__path__", [*readers.__path__, str(package)])  # as if it sat beside eth_ucy
    readers._modules.cache_clear()
    try:
        assert "pairs_tsv" in readers.track_readers() and "eth_ucy" in readers.track_readers()
        assert "push" not in readers.track_readers()  # a clip source is not a track reader
        assert readers.reader_problem("pairs_tsv") is None
        assert "expected one of" in readers.reader_problem("no_such_format")
        table = readers.read_tracks("pairs_tsv", tmp_path / "walk.tsv")
        assert list(table.columns) == ["agent", "frame", "x", "y"] and len(table) == 4
    finally:
        readers._modules.cache_clear()
        sys.modules.pop(f"{readers.__name__}.pairs_tsv", None)


def test_a_new_clip_format_is_one_module_found_by_its_name(tmp_path, monkeypatch):
    """A module beside the readers that names its settings class CLIPS is a clip source under its own name: the clips
    module reads it, splits its one part by ``data.split``, caps and normalises it."""
    import dider.data.readers as readers
    from dider.data.clips import ClipsDataModule

    package = tmp_path / "extra"
    package.mkdir()
    (package / "ramps.py").write_text(
        "from dataclasses import dataclass\nimport torch\nfrom dider.data.clip_source import Clips\n\n\n"
        "@dataclass(frozen=True)\nclass Ramps:\n    reader: str = 'ramps'\n    count: int = 20\n"
        "    SPLIT_SETTINGS = ('split', 'seed')\n\n"
        "    def clips(self, sizes, cache_dir):\n"
        "        t = torch.arange(self.count * 6 * 2 * 4, dtype=torch.float32).reshape(self.count, 6, 2, 4)\n"
        "        return {'all': Clips(t)}\n\n    def where(self):\n        return 'the ramps'\n\n\n"
        "CLIPS = Ramps\n")
    monkeypatch.setattr(readers, "__path__", [*readers.__path__, str(package)])  # as if it sat beside push
    readers._modules.cache_clear()
    try:
        assert "ramps" in readers.clip_sources() and "ramps" not in readers.track_readers()
        dm = ClipsDataModule(source={"reader": "ramps", "count": 30}, split=(0.6, 0.2, 0.2), seed=2, num_test=4)
        dm.setup()
        assert {s: len(d) for s, d in dm.datasets.items()} == {"train": 18, "val": 6, "test": 4}
        states = dm.datasets["train"].states
        assert states[..., :2].min() == -1 and states[..., :2].max() == 1  # fitted on the training split
        with pytest.raises(ValueError, match=r"data.source.counts: no such setting"):
            ClipsDataModule(source={"reader": "ramps", "counts": 3})
    finally:
        readers._modules.cache_clear()
        sys.modules.pop(f"{readers.__name__}.ramps", None)
