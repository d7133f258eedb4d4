"""Every `experiment=` config runs end to end, briefly (`debug=fdr`: one batch of each split), on small fake
data of its data set's format, as lightning-hydra-template's experiment tests do: a config that composes but
fails to train is caught here, not after an hour of a sweep."""

import json
from pathlib import Path

import dider.conf
import pytest
from omegaconf import OmegaConf, open_dict

from dider.run import train
from helpers.fixtures import write_ind_root, write_zhan

ROOT = Path(__file__).resolve().parents[1]
# In the slow suite, experiments whose code path another one runs in the default suite: ind200_table (inD as
# ind50_table, larger windows), bball_table (basketball as tests/test_real_data_runs.py), synth_cpu_table and
# synth_claims (the synthetic CPU tables as synth_protocol)
SLOW = {"ind200_table", "bball_table", "synth_cpu_table", "synth_claims"}
EXPERIMENTS = [pytest.param(name, marks=pytest.mark.slow) if name in SLOW else name
               for name in sorted(p.stem for p in (Path(dider.conf.__file__).parent / "experiment").glob("*.yaml"))]
SMALL_SYNTH = ["data.num_train=32", "data.num_val=8", "data.num_test=8", "data.loader.batch_size=8"]


def fake_data(data: str, tmp: Path) -> list[str]:
    """Overrides that point the experiment's data set at a small fake of its format."""
    if data == "ind":
        return [f"data.source.root={write_ind_root(tmp / 'inD', num_recordings=3, num_frames=600)}",
                "data.split=[1,1,1]"]
    if data == "ind200":  # 200-step windows at 2.5 Hz: 80 s recordings
        return [f"data.source.root={write_ind_root(tmp / 'inD', num_recordings=3, num_frames=2100)}",
                "data.split=[1,1,1]"]
    if data == "basketball":
        write_zhan(tmp / "bball")
        return [f"data.source.root={tmp / 'bball'}"]
    if data == "soccer":  # kloppy's own sample files, which the experiment names: the first 3000 frames
        pytest.importorskip("kloppy")
        return ["data.source.options={limit:3000}", "data.loader.batch_size=4", "data.loader.eval_batch_size=4"]
    return SMALL_SYNTH


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_experiment_runs(experiment, make_cfg, tmp_path):
    cfg = make_cfg([f"experiment={experiment}"], tiny=False)
    data = cfg.data.source._target_.rpartition(".")[2]  # the source's class: Push, Simulation, ..., LevelXSource
    data = {"KloppySource": "soccer", "BasketballFiles": "basketball"}.get(data, data)
    if data == "LevelXSource":
        data = "ind200" if cfg.data.windows.seq_len == 200 else "ind"
    cfg = make_cfg([f"experiment={experiment}", "debug=fdr", *fake_data(data, tmp_path), "protocol.samples=0",
                    "trainer.enable_progress_bar=false"], tiny=False, out=tmp_path / "run")
    metrics = train(cfg)
    assert metrics and (tmp_path / "run" / "metrics.json").exists()


@pytest.mark.parametrize("model", ["dider", "dnri"])
def test_synth_claims_is_the_recorded_table(make_cfg, model):
    """`experiment=synth_claims` composes, job by job, to what its record (claims_30epochs_fp32.json) ran (the CPU
    table with its settings spelled out as overrides), so the short command reproduces the committed figures."""
    record = json.loads((ROOT / "docs" / "records" / "claims_30epochs_fp32.json").read_text())
    job = next(j for j in record["jobs"] if j["model"] == model)
    recorded = make_cfg([*job["overrides"], f"seed={job['seed']}"], tiny=False)
    short = make_cfg(["experiment=synth_claims", f"model={model}", f"seed={job['seed']}"], tiny=False)
    assert short.hydra.sweeper.params == {"model": "dider,dnri", "seed": "range(1,5)"}
    for cfg in (recorded, short):
        cfg.logger = None  # the record's jobs logged to CSV; the logger does not touch the figures
        with open_dict(cfg):
            del cfg["hydra"]
    assert OmegaConf.to_yaml(short) == OmegaConf.to_yaml(recorded)
