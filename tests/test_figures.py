"""End-of-run figures: they scale with the edges they show, and they come after the results."""

import json
import logging
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest
import torch

from dider.bench.outputs import fake_outputs, time_outputs
from dider.outputs.viz import TimelineFigures, shown_edges, timeline_figure, trajectory_figure
from dider.run import train

pytestmark = pytest.mark.usefixtures("one_thread")


def test_shown_edges_are_the_busiest_in_edge_order():
    rows = {"truth": torch.tensor([[0, 0, 0], [1, 1, 0], [0, 1, 0], [1, 1, 1], [-1, -1, -1], [0, 0, 2]]),
            "per_step": torch.tensor([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [-1, -1, -1], [1, 1, 1]])}
    # interaction steps per edge over both rows: 0, 2, 1, 3, 0, 4
    assert shown_edges(rows, 3).tolist() == [1, 3, 5]
    assert shown_edges(rows, 4).tolist() == [1, 2, 3, 5]
    assert shown_edges(rows, 6).tolist() == list(range(6))
    idle = {"truth": torch.zeros(6, 3, dtype=torch.long)}
    assert shown_edges(idle, 2).tolist() == [0, 1]  # ties keep the lower index


def test_a_timeline_of_forty_agents_is_one_image_of_the_busiest_edges():
    out = fake_outputs(1, 40, 30)
    rows = {k: out[k][0] for k in ("truth", "segments")}
    fig = timeline_figure(rows, 2, title="clip", max_edges=12)
    assert len(fig.axes) == 1 and len(fig.axes[0].images) == 1
    assert fig.axes[0].images[0].get_array().shape == (12 * 3 - 1, 29)  # 12 bands of 2 rows, blank rows between
    assert "12 of 1560 edges" in fig._suptitle.get_text()
    plt.close(fig)
    fig = trajectory_figure(out["states"][0, :, :, :2], out["mask"][0], out["segments"][0], 2)
    assert len(fig.axes[0].lines) == 0 and len(fig.axes[0].collections) <= 3  # paths and types as collections
    plt.close(fig)


def test_end_of_run_outputs_at_forty_agents_are_written():
    """The benchmark's case at a test-sized scale: every output is written (timings are `make bench`'s)."""
    record = time_outputs(40, clips=8, steps=20, figures=1)
    assert record["edges"] == 1560 and set(record["seconds"]) >= {"segments_json", "timelines", "trajectories"}


def crowd(path: Path, scenes: int = 6, agents: int = 40, frames: int = 30) -> Path:
    rng = np.random.default_rng(0)
    s, a, f = np.meshgrid(np.arange(scenes), np.arange(agents), np.arange(frames), indexing="ij")
    walk = rng.normal(0, 0.3, (scenes, agents, frames, 2)).cumsum(2) + rng.uniform(0, 50, (scenes, agents, 1, 2))
    pd.DataFrame({"scene": s.ravel(), "agent": a.ravel(), "frame": f.ravel(), "x": walk[..., 0].ravel(),
                  "y": walk[..., 1].ravel()}).to_csv(path, index=False)
    return path


def test_a_crowded_run_writes_results_before_figures(make_cfg, tmp_path, monkeypatch, caplog):
    """40 agents a window (1560 edges): the run ends with its results; the figures are drawn after
    metrics.json and segments.json exist, and a figure that fails costs them nothing."""
    out = tmp_path / "run"
    seen: dict[str, bool] = {}
    real = TimelineFigures._draw

    def draw(self, trainer, pl_module, written):
        seen.update({name: (out / name).exists() for name in ("metrics.json", "segments.json", "clips.npz")})
        real(self, trainer, pl_module, written)
        raise RuntimeError("a figure failed")

    monkeypatch.setattr(TimelineFigures, "_draw", draw)
    cfg = make_cfg(["data=table", f"data.source.path={crowd(tmp_path / 'crowd.csv')}", "data.windows.seq_len=12",
                    "data.windows.stride=12",
                    "protocol.burn_in=4", "protocol.horizons=[1,4]", "data.loader.batch_size=2",
                    "data.loader.eval_batch_size=2", "model=dnri", "model.num_edges=2", "logger=none"], out=out)
    with caplog.at_level(logging.WARNING, logger="dider.outputs.viz"):
        train(cfg)
    assert seen == {"metrics.json": True, "segments.json": True, "clips.npz": True}
    assert "test figures not drawn (RuntimeError: a figure failed)" in caplog.text
    assert sorted(p.name for p in (out / "figures").glob("*.png")) == [
        "forecast_00.png", "forecast_01.png", "timeline_00.png", "timeline_01.png", "trajectories_00.png",
        "trajectories_01.png"]
    assert json.loads((out / "metrics.json").read_text())["metrics"]["test/ade/h04"] > 0


def test_forecast_figure_draws_every_carried_agent():
    """One true path (observed and future), one model and one constant-velocity line per agent present at the
    burn-in's last frame; an agent gone by then is left out."""
    from dider.outputs.viz import forecast_figure

    t, n, burn_in = 10, 3, 4
    positions = torch.arange(t * n * 2, dtype=torch.float).reshape(t, n, 2)
    mask = torch.ones(t, n, dtype=torch.bool)
    mask[2:, 2] = False  # agent 2 leaves before the burn-in ends
    forecast = positions[burn_in:] + 1.0
    fig = forecast_figure(positions, mask, forecast, positions[burn_in:], burn_in)
    # one collection each: observed, future, model, constant velocity; agents 0 and 1 only
    observed, future, model, cv = (c.get_segments() for c in fig.axes[0].collections[:4])
    p = t - burn_in
    assert (len(observed), len(future), len(model), len(cv)) == (2 * (burn_in - 1), 2 * p, 2 * p, 2 * p)
    agent0 = np.stack(model)[0::2]  # segments come step by step, agents 0 and 1 in turn
    assert np.allclose(agent0[0, 0], positions[burn_in - 1, 0]) and np.allclose(agent0[:, 1], forecast[:, 0])
    plt.close(fig)
    samples = torch.stack([forecast - 1, forecast + 2])  # two sampled futures, drawn thin under the forecast
    fig = forecast_figure(positions, mask, forecast, positions[burn_in:], burn_in, samples=samples)
    drawn = fig.axes[0].collections[2].get_segments()
    assert len(drawn) == 2 * 2 * p and np.allclose(drawn[2 * p + 1][1], samples[1, 0, 1])  # the second, agent 1
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()][-1] == "sampled futures"
    plt.close(fig)
