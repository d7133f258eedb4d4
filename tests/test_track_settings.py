"""The nested settings of the data sets of long tracks (``data.source``, ``data.windows``): their checks, what a
checkpoint records of them, and older flat configs read as today's."""

from dataclasses import replace

import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from dider.data.common import data_description
from dider.data.legacy import LEVELX_DEFAULTS, TRACKS, flat_view, upgrade_data_node
from dider.data.tracks import TracksDataModule
from dider.data.windowing import Windows
from dider.validation import ConfigError, settings_problems


def test_windows_override_the_data_sets_defaults_key_by_key_and_name_a_wrong_key():
    levelx = {"reader": "levelx"}
    assert TracksDataModule(source=levelx).windows == Windows(seq_len=50, downsample=10)
    inds = Windows(seq_len=50, downsample=10)
    assert TracksDataModule(source=levelx, windows={"stride": 5}).windows == replace(inds, stride=5)
    with pytest.raises(ConfigError, match=r"data.windows.seq_length: no such setting"):
        TracksDataModule(windows={"seq_length": 5})
    with pytest.raises(ConfigError, match=r"data.windows.max_agents=1: must be >= data.windows.min_agents=2"):
        Windows(max_agents=1)
    with pytest.raises(ConfigError, match=r"data.source.provider: no such setting \(expected one of \['reader', "
                                          r"'path', 'columns', 'frame_rate'\]\)"):
        TracksDataModule(source={"provider": "hawkeye"})
    with pytest.raises(ConfigError, match=r"data.source.files.trax: no such setting"):
        TracksDataModule(source={"reader": "levelx", "files": {"trax": "{id}.csv"}})


def test_a_checkpoint_records_the_settings_flat(tmp_path):
    dm = TracksDataModule(source={"path": str(tmp_path / "t.csv"), "frame_rate": 10.0},
                         windows={"downsample": 2, "max_speed": 12.0})
    args = data_description(dm)["args"]
    assert (args["frame_rate"], args["downsample"], args["max_speed"], args["seq_len"]) == (10.0, 2, 12.0, 20)
    assert args["path"] == str(tmp_path / "t.csv") and args["split"] == [0.8, 0.1, 0.1]
    assert flat_view({"source": {"root": "r"}, "windows": {"seq_len": 5}, "split": [1]}) == {
        "root": "r", "seq_len": 5, "split": [1]}


OLD = {
    "table": ({"_target_": "dider.data.table.TableDataModule", "path": "t.csv", "reader": "eth_ucy", "frame_rate": 2.5,
               "seq_len": 20, "stride": 4, "min_agent_steps": 8, "batch_size": 4},
              {"_target_": TRACKS, "source": {"path": "t.csv", "reader": "eth_ucy",
               "frame_rate": 2.5}, "windows": {"seq_len": 20, "stride": 4, "min_agent_steps": 8},
               "loader": {"batch_size": 4}}),
    "soccer": ({"_target_": "dider.data.soccer.SoccerDataModule", "provider": "tracab", "files": {"raw_data": "r"},
                "ball": True, "frame_rate": None, "downsample": 2, "max_speed": 40.0, "split": [0.5, 0.25, 0.25]},
               {"_target_": TRACKS, "source": {"reader": "kloppy", "provider": "tracab",
                "files": {"raw_data": "r"}, "ball": True, "frame_rate": None},
                "windows": {"downsample": 2, "max_speed": 40.0}, "split": [0.5, 0.25, 0.25]}),
    "ind": ({"_target_": "dider.data.ind.InDDataModule", "root": "d", "name": "round", "tracks_pattern": "{id}_t.csv",
             "class_column": "kind", "features": ["a", "b", "c", "d"], "seq_len": 30, "eval_stride": 10,
             "burn_in": 5, "horizons": [1, 5]},
            {"_target_": TRACKS, "source": {"reader": "levelx", "root": "d", "name": "round",
             "files": {"tracks": "{id}_t.csv"}, "columns": {"agent_class": "kind", "features": ["a", "b", "c", "d"]}},
             "windows": {"seq_len": 30, "eval_stride": 10}, **LEVELX_DEFAULTS}),
    # the previous version's two modules of long tracks, nested: the tracks module, reading as they read
    "table nested": ({"_target_": "dider.data.table.TableDataModule", "source": {"reader": "kloppy", "files": {}},
                      "windows": {"seq_len": 8}},
                     {"_target_": TRACKS, "source": {"reader": "kloppy", "files": {}}, "windows": {"seq_len": 8}}),
    "ind nested": ({"_target_": "dider.data.ind.InDDataModule", "source": {"root": "d"}, "windows": {"seq_len": 8},
                    "pairs": None, "loader": {"batch_size": 2}},
                   {"_target_": TRACKS, "source": {"reader": "levelx", "root": "d"}, "windows": {"seq_len": 8},
                    "pairs": {}, "loader": {"batch_size": 2, "eval_batch_size": 8}}),
}


@pytest.mark.parametrize("name", OLD)
def test_an_older_flat_config_reads_as_todays(name):
    old, new = OLD[name]
    assert upgrade_data_node(old) == new
    built = instantiate(OmegaConf.create(new), _convert_="all")  # and it builds
    assert built.windows == Windows.of(type(built.source).WINDOWS, new["windows"], {})


CLIPS = "dider.data.clips.ClipsDataModule"
SIZES = {"num_train": 4, "num_val": 2, "num_test": 2}
# An older data module of clips (flat, or nested under its own class) and the node it reads as today.
OLD_CLIPS = {
    "synth": ({"_target_": "dider.data.synth.SynthDataModule", "num_steps": 12, "seed": 3, "burn_in": 5, **SIZES},
              {"_target_": CLIPS, **SIZES, "source": {"reader": "push", "num_steps": 12, "seed": 3}}),
    "synth nested": ({"_target_": "dider.data.synth.SynthDataModule", "source": {"push": "step"}, **SIZES},
                     {"_target_": CLIPS, "source": {"reader": "push", "push": "step"}, **SIZES}),
    "springs": ({"_target_": "dider.data.nri.NRIDataModule", "simulate": {"system": "charged"}, "root": None,
                 "suffix": "_springs5", **SIZES},
                {"_target_": CLIPS, **SIZES, "source": {"reader": "particles", "system": "charged"}}),
    "springs nested": ({"_target_": "dider.data.nri.NRIDataModule", "source": {"system": "charged"}, **SIZES},
                       {"_target_": CLIPS, "source": {"reader": "particles", "system": "charged"}, **SIZES}),
    "nri_files": ({"_target_": "dider.data.nri.NRIDataModule", "simulate": None, "root": "d", "suffix": "_s"},
                  {"_target_": CLIPS, "source": {"reader": "nri_files", "root": "d", "suffix": "_s"}}),
    "dnri_files": ({"_target_": "dider.data.dnri_files.DNRIFilesDataModule", "root": "d", "normalization": "same"},
                   {"_target_": CLIPS, "normalization": "same", "source": {"reader": "dnri_files", "root": "d"}}),
    "basketball": ({"_target_": "dider.data.basketball.BasketballDataModule", "root": "d", "val_fraction": 0.2,
                    "train_len": 40},
                   {"_target_": CLIPS, "val_fraction": 0.2, "train_len": 40,
                    "source": {"reader": "basketball", "root": "d"}}),
    "trajectories": ({"_target_": "dider.data.trajectories.TrajectoryDataModule", "path": "x.npz", "frame_rate": 5,
                      "split": [0.6, 0.2, 0.2]},
                     {"_target_": CLIPS, "split": [0.6, 0.2, 0.2],
                      "source": {"reader": "trajectories", "path": "x.npz", "frame_rate": 5}}),
}


@pytest.mark.parametrize("name", OLD_CLIPS)
def test_an_older_data_module_of_clips_reads_as_the_clips_module(name):
    old, new = OLD_CLIPS[name]
    assert upgrade_data_node(old) == new
    built = instantiate(OmegaConf.create(new), _convert_="all")  # and it builds, reading with the old reader
    assert built.source.reader == new["source"]["reader"]


def test_a_config_in_todays_layout_passes_through_unchanged():
    for node in ({"_target_": CLIPS, "source": {"reader": "particles", "system": "charged"}, "num_train": 4},
                 {"_target_": TRACKS, "source": {"reader": "kloppy", "files": {}},
                  "windows": {"seq_len": 8}}):
        assert upgrade_data_node(node) == node


def test_a_checkpoints_flat_view_keeps_the_data_seed_and_an_older_nri_files_config_reads_the_files():
    """A simulator's seed is the data seed in the flat view a checkpoint records (as older checkpoints hold it), and
    NRI's older ``simulate: null`` means its files even before ``root`` is set."""
    from dider.data.legacy import flat_view, nest_args

    assert flat_view({"seed": 1, "source": {"reader": "push", "seed": 7}})["seed"] == 7
    assert flat_view({"seed": 3, "source": {"reader": "trajectories"}})["seed"] == 3  # the split seed there
    _, nested = nest_args("dider.data.nri.NRIDataModule", {"simulate": None, "root": None})
    assert nested["source"] == {"reader": "nri_files", "root": None}


def test_the_source_says_how_its_data_set_is_split():
    """Left null, the split is the source's (a table's seeded fractions, DNRI's recordings in order); a seed is a
    table's, refused for recordings, and each source checks the split's form it reads."""
    assert TracksDataModule(source={"path": "t.csv"}).hparams.split == [0.8, 0.1, 0.1]
    assert TracksDataModule(source={"reader": "levelx"}).hparams.split == [19, 7, 7]
    with pytest.raises(ConfigError, match=r"data.seed=2: data.source.reader=levelx splits its recordings in order"):
        TracksDataModule(source={"reader": "levelx"}, seed=2)
    with pytest.raises(ConfigError, match=r"data.split=\[19, 7, 7\]: three positive fractions"):
        TracksDataModule(source={"path": "t.csv"}, split=[19, 7, 7])
    with pytest.raises(ConfigError, match=r"data.split=\[2, 0.5, 1\]: give recording counts"):
        TracksDataModule(source={"reader": "levelx"}, split=[2, 0.5, 1])
    with pytest.raises(ConfigError, match=r"data.split=5: "):
        TracksDataModule(source={"path": "t.csv"}, split=5)
    with pytest.raises(ConfigError, match=r"data.split=\[inf, 1, 1\]: give recording counts"):
        TracksDataModule(source={"reader": "levelx"}, split=[float("inf"), 1, 1])
    with pytest.raises(ConfigError) as told:  # one message, the source's
        TracksDataModule(source={"path": "t.csv"}, split=[0.5, 0.5])
    assert str(told.value).count("data.split") == 1, told.value


def test_the_preflight_checks_the_source_and_split_of_the_data_sets_of_long_tracks(make_cfg):
    """Before a run folder is opened: the source's settings by its reader's class, the split's form."""
    problems = settings_problems(OmegaConf.to_container(make_cfg(
        ["data=ind", "data.source.background_scale=0", "data.source.reader=levelx", "data.split=[0.5,0.5]"]).data),
        "data")
    assert any(p.startswith("data.source.background_scale=0: ") for p in problems), problems
    assert any(p.startswith("data.split=[0.5, 0.5]: ") for p in problems), problems
    table = OmegaConf.to_container(make_cfg(["data=table", "+data.source.provider=x"]).data)
    assert settings_problems(table, "data") == [
        "data.source.provider: no such setting (expected one of ['reader', 'path', 'columns', 'frame_rate'])"]
    springs = OmegaConf.to_container(make_cfg(["data=springs", "data.source.num_balls=1"]).data)  # a clip source too
    assert settings_problems(springs, "data") == ["data.source.num_balls=1: must be >= 2"]
