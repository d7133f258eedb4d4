"""The nested settings of the data sets of long tracks (``data.source``, ``data.windows``): their checks and what a
checkpoint records of them."""

from dataclasses import replace

import pytest
from omegaconf import OmegaConf

from dider.data.description import data_description
from dider.data.tracks import TracksDataModule
from dider.data.windowing import Windows
from dider.validation import ConfigError, settings_problems

LEVELX_SOURCE = "dider.data.levelx.source.LevelXSource"
TABLE = "dider.data.track_sources.TableFile"


def test_windows_override_the_data_sets_defaults_key_by_key_and_name_a_wrong_key():
    levelx = {"_target_": LEVELX_SOURCE}
    assert TracksDataModule(source=levelx).windows == Windows(seq_len=50, downsample=10)
    inds = Windows(seq_len=50, downsample=10)
    assert TracksDataModule(source=levelx, windows={"stride": 5}).windows == replace(inds, stride=5)
    with pytest.raises(ConfigError, match=r"data.windows.seq_length: no such setting"):
        TracksDataModule(windows={"seq_length": 5})
    with pytest.raises(ConfigError, match=r"data.windows.max_agents=1: must be >= data.windows.min_agents=2"):
        Windows(max_agents=1)
    with pytest.raises(ConfigError, match=r"data.source.provider: no such setting \(expected one of \['path', "
                                          r"'frame_rate', 'columns'\]\)"):
        TracksDataModule(source={"_target_": TABLE, "provider": "hawkeye"})
    with pytest.raises(ConfigError, match=r"data.source.files.trax: no such setting"):
        TracksDataModule(source={"_target_": LEVELX_SOURCE, "files": {"trax": "{id}.csv"}})


def test_a_checkpoint_records_the_settings_nested(tmp_path):
    """As the config nests them: the source's under ``source`` (with the class that builds it again), the cut's under
    ``windows``, the module's beside."""
    dm = TracksDataModule(source={"_target_": TABLE, "path": str(tmp_path / "t.csv"), "frame_rate": 10.0},
                         windows={"downsample": 2, "max_speed": 12.0})
    args = data_description(dm)["args"]
    assert (args["source"]["frame_rate"], args["source"]["path"]) == (10.0, str(tmp_path / "t.csv"))
    assert args["source"]["_target_"] == TABLE and TracksDataModule(**args).source == dm.source
    assert (args["windows"]["downsample"], args["windows"]["max_speed"], args["windows"]["seq_len"]) == (2, 12.0, 20)
    assert args["split"] == [0.8, 0.1, 0.1] and "frame_rate" not in args and "seq_len" not in args


def test_the_source_says_how_its_data_set_is_split():
    """Left null, the split is the source's (a table's seeded fractions, DNRI's recordings in order); a seed is a
    table's, refused for recordings, and each source checks the split's form it reads."""
    assert TracksDataModule(source={"_target_": TABLE, "path": "t.csv"}).hparams.split == [0.8, 0.1, 0.1]
    assert TracksDataModule(source={"_target_": LEVELX_SOURCE}).hparams.split == [19, 7, 7]
    with pytest.raises(ConfigError, match=rf"data.seed=2: data.source._target_={LEVELX_SOURCE} splits its "
                                          r"recordings in order"):
        TracksDataModule(source={"_target_": LEVELX_SOURCE}, seed=2)
    with pytest.raises(ConfigError, match=r"data.split=\[19, 7, 7\]: three positive fractions"):
        TracksDataModule(source={"_target_": TABLE, "path": "t.csv"}, split=[19, 7, 7])
    with pytest.raises(ConfigError, match=r"data.split=\[2, 0.5, 1\]: give recording counts"):
        TracksDataModule(source={"_target_": LEVELX_SOURCE}, split=[2, 0.5, 1])
    with pytest.raises(ConfigError, match=r"data.split=5: "):
        TracksDataModule(source={"_target_": TABLE, "path": "t.csv"}, split=5)
    with pytest.raises(ConfigError, match=r"data.split=\[inf, 1, 1\]: give recording counts"):
        TracksDataModule(source={"_target_": LEVELX_SOURCE}, split=[float("inf"), 1, 1])
    with pytest.raises(ConfigError) as told:  # one message, the source's
        TracksDataModule(source={"_target_": TABLE, "path": "t.csv"}, split=[0.5, 0.5])
    assert str(told.value).count("data.split") == 1, told.value


def test_the_preflight_checks_the_source_and_split_of_the_data_sets_of_long_tracks(make_cfg):
    """Before a run folder is opened: the source's settings by its reader's class, the split's form."""
    problems = settings_problems(OmegaConf.to_container(make_cfg(
        ["data=ind", "data.source.background_scale=0", "data.split=[0.5,0.5]"]).data),
        "data")
    assert any(p.startswith("data.source.background_scale=0: ") for p in problems), problems
    assert any(p.startswith("data.split=[0.5, 0.5]: ") for p in problems), problems
    table = OmegaConf.to_container(make_cfg(["data=table", "+data.source.provider=x"]).data)
    assert settings_problems(table, "data") == [
        "data.source.provider: no such setting (expected one of ['path', 'frame_rate', 'columns'])"]
    springs = OmegaConf.to_container(make_cfg(["data=springs", "data.source.num_balls=1"]).data)  # a clip source too
    assert settings_problems(springs, "data") == ["data.source.num_balls=1: must be >= 2"]
