"""An override of a key the config does not have, with or without ``+``: dider's message, naming where 0.2 moved the
key or the nearest keys, before any work (not Hydra's "Could not override")."""

from __future__ import annotations

import subprocess
import sys

import pytest

from dider.run import ConfigError, validate_config
from dider.training.overrides import job_overrides, override_problem


@pytest.mark.parametrize("override, says", [
    ("data.path=x.csv", "data.path=x.csv: no such key; 0.2 moved it to data.source.path (data.source.path=x.csv)"),
    ("data.seq_len=5", "0.2 moved it to data.windows.seq_len"),
    ("data.burn_in=5", "0.2 moved it to protocol.burn_in"),
    ("model.samples=3", "0.2 moved it to protocol.samples (protocol.samples=3)"),
    ("model.num_edgs=3", "model.num_edgs=3: no such key; did you mean model.num_edges"),
    ("trainer.max_epoch=3", "did you mean trainer.max_epochs?"),
])
def test_a_key_the_config_lacks_is_named_with_where_to_look(override, says):
    assert says in override_problem([override])


def test_the_command_line_refuses_it_before_any_work(tmp_path):
    done = subprocess.run([sys.executable, "-m", "dider.run", "data.path=x.csv", f"hydra.run.dir={tmp_path / 'r'}"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 2 and "0.2 moved it to data.source.path" in done.stderr
    assert "Could not override" not in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "r").exists()


def test_with_a_plus_the_preflight_names_it(make_cfg):
    with pytest.raises(ConfigError, match=r"data.path: no such setting of ClipsDataModule \(expected some of "
                                          r"\['source', .*\]\); 0.2 moved it to data.source.path"):
        validate_config(make_cfg(["+data.path=x.csv"]))


def test_what_is_checked_of_a_command_line():
    assert job_overrides(["-m", "model.num_edges=4", "seed=1"]) == ("config", ["model.num_edges=4", "seed=1"])
    assert job_overrides(["--config-name", "eval", "ckpt_path=x"]) == ("eval", ["ckpt_path=x"])
    assert job_overrides(["-m", "seed=1,2,3"]) is None  # a sweep: each job's own preflight
    assert job_overrides(["--help"]) is None
    assert override_problem(["model.num_edges=4", "data=ind"]) is None  # composes
