"""The plain summary a run prints at its end, read from its metrics and clips.npz."""

from __future__ import annotations

import numpy as np

from dider.outputs import summary


def _clips(folder):
    segments = np.zeros((2, 6, 5), dtype=np.int64)
    truth = np.zeros((2, 6, 5), dtype=np.int64)
    truth[0, 0, 2] = 1  # two changes
    truth[1, 2, 1:4] = 1  # two changes; edge 2 of 3 agents: agent 1 -> agent 0
    segments[1, 2, 1:3] = 1
    truth[0, 5] = -1  # absent
    np.savez(folder / "clips.npz", segments=segments, truth=truth)


def test_the_summary_reads_the_forecast_the_edges_and_example_timelines(tmp_path):
    _clips(tmp_path)
    metrics = {"test/ade/h01": 0.2, "test/cv/ade/h01": 0.1, "test/ade/h15": 0.5, "test/cv/ade/h15": 1.0,
               "test/ade_vs_cv/h15": 0.5, "test/ade_vs_no_edges/h15": 0.8}
    text = summary.plain_summary(metrics, [1, 15], tmp_path, "m", budget_note="train longer")
    assert "1 step(s) ahead: off by 0.2 m on average, constant velocity by 0.1 m (no better than it, 2.00x)" in text
    assert "15 step(s) ahead: off by 0.5 m on average, constant velocity by 1 m (better than it, 0.50x)" in text
    assert "Its edges help: with every edge off its error is 1.25x" in text
    metrics["test/ade_vs_no_edges/h15"] = 0.9997  # no interaction held: the two roll-outs differ by rounding
    assert "Its edges do not help: with every edge off its error is 1.00x" in summary.plain_summary(
        metrics, [1, 15], tmp_path, "m")
    assert "train longer" not in text  # it beats constant velocity at the longest horizon
    lines = text.splitlines()
    first = next(i for i, line in enumerate(lines) if "clip 0, agent 0 -> 1:" in line)
    assert lines[first].endswith("model .....") and lines[first + 1].endswith("truth ..1..")
    second = next(i for i, line in enumerate(lines) if "clip 1, agent 1 -> 0:" in line)
    assert lines[second].endswith("model .11..") and lines[second + 1].endswith("truth .111.")
    assert f"python -m dider.analysis.explore {tmp_path}" in text


def test_a_run_that_loses_to_constant_velocity_is_told_what_a_longer_one_scores(tmp_path, monkeypatch):
    record = {"what": "x", "trained_with": "python -m dider.run experiment=long", "evaluate": ["data.num_test=9"],
              "metrics": {"test/ade/h15": 0.3, "test/ade_vs_cv/h15": 0.3}}
    monkeypatch.setattr("dider.shipped.catalog", lambda: {"synth/dider": record})
    metrics = {"test/ade/h15": 1.2, "test/cv/ade/h15": 1.0, "test/ade_vs_cv/h15": 1.2}
    text = summary.run_summary(metrics, tmp_path, "dider", "synth", None)
    assert "(no better than it, 1.20x); the shipped synth/dider" in text and "0.3, 0.30x" in text
    assert "It does not beat constant velocity: this run is short; the shipped synth/dider was trained with " \
           "`python -m dider.run experiment=long`" in text
    assert "ckpt_path=synth/dider data.num_test=9" in text
    record |= {"trained_wall_s": 1265.7, "trained_device": "cpu"}  # how long a run that beats it takes
    assert "`python -m dider.run experiment=long`, 21 minute(s) on a CPU (" in summary.run_summary(
        metrics, tmp_path, "dider", "synth", None)
    record |= {"trained_wall_s": 20.0, "trained_device": None}  # a quick one, the device not recorded
    assert "`python -m dider.run experiment=long`, 1 minute(s) (" in summary.run_summary(
        metrics, tmp_path, "dider", "synth", None)
    assert summary.run_summary(metrics, tmp_path, "dider", "ind", None).count("shipped") == 0


def test_the_summary_says_what_each_type_means_and_whether_it_is_about_the_pair(tmp_path):
    features = ("distance", "closing_speed", "relative_heading_deg", "receiver_accel")
    metrics = {"test/ade/h15": 0.5, "test/cv/ade/h15": 1.0, "test/ade_vs_cv/h15": 0.5}
    for k, (share, dist, gap) in enumerate([(0.9, 3.0, 0.0), (0.1, 0.5, -1.0)]):
        metrics[f"test/type{k}/share"] = share
        for i, name in enumerate(features):
            metrics[f"test/type{k}/{name}"] = dist if i == 0 else 0.25
            metrics[f"test/type{k}/others/{name}"] = 1.0
        metrics[f"test/type{k}/beyond_shuffled/distance"] = gap
        metrics[f"test/type{k}/beyond_shuffled/closing_speed"] = 0.0
    lines = summary.plain_summary(metrics, [15], tmp_path).splitlines()
    cards = lines[lines.index("What each edge type means (while it holds; others: the other edge-steps):") + 1:][:2]
    assert cards[0].startswith("  type 0: 90.0% of edge-steps · distance 3 (others 1)")
    assert cards[0].endswith("than the same type on shuffled pairs (a state of the agents' own motion?)")
    assert cards[1].startswith("  type 1: 10.0% of edge-steps · distance 0.5 (others 1)")
    assert cards[1].endswith("about the pair: nearer than the same type on shuffled pairs")
