"""A format as one class: ETH/UCY pedestrians' text files (frame agent x y) read into the track table that
``data=table`` windows, with each problem named by file and line, and a short training on them (``data=eth_ucy``);
and a format of the user's own, outside the package (one class and one YAML in the user's config folder), trained
on and read back from its run folder only when trusted."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hydra.utils import instantiate

from dider.analysis.diagnose import diagnose
from dider.data.clips import ClipsDataModule
from dider.data.example import example_tracks
from dider.data.readers.eth_ucy import EthUcyFiles
from dider.data.tracks import TracksDataModule
from dider.models.checkpoint_format import read
from dider.run import train
from dider.targets import Untrusted
from dider.training.preflight import validate_config

USER_CONF = Path(__file__).resolve().parent / "helpers" / "conf"  # a config folder of the user's own
DELIMITED = "helpers.user_plugins.DelimitedTracks"


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
    table = EthUcyFiles().read(write_scenes(tmp_path / "eth", scenes=2, frames=3, people=2))
    assert list(table.columns) == ["scene", "agent", "frame", "x", "y"]
    assert sorted(set(table.scene)) == ["scene0", "scene1"]
    assert sorted(set(table.frame)) == [3, 4, 5]  # frames 18, 24, 30 (step 6) and 30, 40, 50 (step 10)
    one = EthUcyFiles().read(tmp_path / "eth" / "scene1.txt")
    assert len(one) == 6 and set(one.scene) == {"scene1"}


@pytest.mark.parametrize("line, why", [("10 1 2.0", "line 2 is not four numbers"),
                                       ("10 1 x 2.0", "line 2 is not four numbers"),
                                       ("10 1 nan 2.0", "line 2 is not four numbers"),
                                       ("1.43 1 1.0 2.0", "line 2: the frame number 1.43 is not a whole number"),
                                       ("10 2.5 1.0 2.0", "line 2: the agent number 2.5 is not a whole number")])
def test_a_bad_line_is_named_with_its_file(tmp_path, line, why):
    (tmp_path / "bad.txt").write_text(f"0 1 1.0 2.0\n{line}\n")
    with pytest.raises(ValueError, match=f"bad.txt: {why}"):
        EthUcyFiles(path=str(tmp_path)).rows()


def test_missing_input_and_unknown_formats_are_named(tmp_path, make_cfg):
    with pytest.raises(FileNotFoundError, match="no .txt files in the folder"):
        EthUcyFiles(path=str(tmp_path)).rows()
    with pytest.raises(FileNotFoundError, match="data.source.path=.*nowhere: no such file or folder"):
        EthUcyFiles(path=str(tmp_path / "nowhere")).rows()
    with pytest.raises(ValueError, match=r"data.source.path is not set: point it at what "
                                         r"dider.data.readers.eth_ucy.EthUcyFiles reads"):
        EthUcyFiles().rows()
    with pytest.raises(ValueError, match=r"data.source._target_='dider.data.readers.sdd.SDD': no such class"):
        TracksDataModule(source={"_target_": "dider.data.readers.sdd.SDD"})
    with pytest.raises(ValueError, match=r"data.source._target_='dider.data.readers.trajectories.NpzFile': not a "
                                         r"track source \(missing \['open'\]\)"):
        TracksDataModule(source={"_target_": "dider.data.readers.trajectories.NpzFile"})
    cfg = make_cfg([f"hydra.searchpath=[file://{USER_CONF}]", "data=delimited", "data.source._target_=mypkg.Nope"])
    with pytest.raises(ValueError, match=r"data.source._target_='mypkg.Nope': no such class \(module 'mypkg' has "
                                         rf"no 'Nope'\) \(data=delimited: {USER_CONF}/data/delimited.yaml, or the "
                                         r"command line\)"):
        validate_config(cfg)


def test_a_short_training_on_pedestrian_files(make_cfg, tmp_path):
    folder = write_scenes(tmp_path / "eth")
    cfg = make_cfg(["data=eth_ucy", f"data.source.path={folder}", "logger=none", "data.num_train=null",
                    "data.num_val=null", "data.num_test=null", "protocol.samples=0"], out=tmp_path / "run")
    assert cfg.protocol.burn_in == 8 and list(cfg.protocol.horizons) == [1, 6, 12]
    metrics = train(cfg)
    assert all(math.isfinite(metrics[f"test/ade/h{h:02d}"]) for h in (1, 6, 12))


def test_a_users_own_format_is_one_class_and_one_yaml(make_cfg, tmp_path):
    """A track format in the user's package (``helpers.user_plugins.DelimitedTracks``: its ``read`` and an option
    of its own) and one YAML in the user's config folder: a run trains on it and its checkpoint records the class;
    the run folder's config, read back (``dider.analysis.diagnose``), builds it only once the user trusts it."""
    example_tracks(scenes=6, frames=60, walkers=4).to_csv(tracks := tmp_path / "walks.txt", sep=";", header=False,
                                                          index=False)
    run = tmp_path / "run"
    cfg = make_cfg([f"hydra.searchpath=[file://{USER_CONF}]", "data=delimited", f"data.source.path={tracks}",
                    "logger=none"], out=run)
    assert cfg.data.source._target_ == DELIMITED and cfg.data.source.delimiter == ";"
    metrics = train(cfg)
    assert all(math.isfinite(metrics[f"test/ade/h{h:02d}"]) for h in (1, 5, 10))
    recorded = read(run / "checkpoints" / "last.ckpt")["dider"]["data"]["args"]["source"]
    assert recorded == {"_target_": DELIMITED, "path": str(tracks), "frame_rate": 10, "delimiter": ";"}
    with pytest.raises(Untrusted, match=rf"metrics\.json: data\.source\._target_='{DELIMITED}': not one of dider's "
                                        r"track source classes .*trust="):
        diagnose(run, clips=4, lengths=(3,))
    assert diagnose(run, clips=4, lengths=(3,), trust=[DELIMITED])["rows"]


def test_a_format_with_the_bases_options_is_picked_on_the_command_line(make_cfg, tmp_path):
    """``data.source._target_=`` over a data config whose source has the same settings (path, frame_rate)."""
    example_tracks(scenes=3, frames=30, walkers=3).to_csv(tracks := tmp_path / "walks.tsv", sep="\t", header=False,
                                                          index=False)
    cfg = make_cfg(["data=eth_ucy", f"data.source._target_={DELIMITED}", f"data.source.path={tracks}"])
    dm = instantiate(cfg.data, _convert_="all")
    assert type(dm.source).__name__ == "DelimitedTracks" and dm.source.delimiter == "\t"
    assert dm.tracks().scenes == ["0", "1", "2"]
    with pytest.raises(ValueError, match=r"data.source.delimiter=';;': expected one character"):
        TracksDataModule(source={"_target_": DELIMITED, "delimiter": ";;"})


def test_a_users_own_clip_format_is_one_class(tmp_path):
    """A clip source in the user's package: the clips module reads it, splits its one part by ``data.split``, caps
    and normalises it."""
    dm = ClipsDataModule(source={"_target_": "helpers.user_plugins.Ramps", "count": 30}, split=(0.6, 0.2, 0.2),
                         seed=2, num_test=4)
    dm.setup()
    assert {s: len(d) for s, d in dm.datasets.items()} == {"train": 18, "val": 6, "test": 4}
    states = dm.datasets["train"].states
    assert states[..., :2].min() == -1 and states[..., :2].max() == 1  # fitted on the training split
    assert dm.hparams["source"] == {"_target_": "helpers.user_plugins.Ramps", "count": 30}
    with pytest.raises(ValueError, match=r"data.source.counts: no such setting"):
        ClipsDataModule(source={"_target_": "helpers.user_plugins.Ramps", "counts": 3})
