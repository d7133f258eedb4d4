"""Interaction recall by the push's distance (``python -m dider.analysis.push_strength``)."""

import json
import math

import pytest
import torch

from dider.analysis.push_strength import main, push_distances, recall_by_distance
from dider.data.simulators.push import EDGE_0_TO_2, EDGE_1_TO_2, simulate_push
from dider.run import train


def test_distances_are_those_of_each_transitions_first_frame():
    states = torch.zeros(1, 3, 3, 4)
    states[0, 0, :, :2] = torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 0.5]])  # frame 0
    states[0, 1, :, :2] = torch.tensor([[0.0, 0.0], [3.0, 0.0], [2.4, 0.0]])  # frame 1
    dist = push_distances(states)  # [1, 6, 2]
    assert dist[0, EDGE_0_TO_2].tolist() == pytest.approx([0.5, 2.4])
    assert dist[0, EDGE_1_TO_2].tolist() == pytest.approx([math.hypot(3.0, 0.5), 0.6])
    others = [e for e in range(6) if e not in (EDGE_0_TO_2, EDGE_1_TO_2)]
    assert torch.isnan(dist[0, others]).all()


def test_every_labelled_push_lies_within_the_radius_and_no_other_step_does():
    """Pins the alignment: transition t -> t+1 is labelled edges[t+1], pushed from frame t's distance."""
    states, edges = simulate_push(50, 40, seed=3)
    truth = edges[:, 1:].transpose(1, 2)
    dist = push_distances(states.double())
    pushing = dist[:, [EDGE_0_TO_2, EDGE_1_TO_2]]
    labelled = truth[:, [EDGE_0_TO_2, EDGE_1_TO_2]] > 0
    assert labelled.any() and (~labelled).any()
    assert (pushing[labelled] < 1).all() and (pushing[~labelled] >= 1).all()


def test_recall_per_bin_by_hand():
    truth = torch.tensor([[[1, 1, 1, 1, 0, 0]]])
    dist = torch.tensor([[[0.2, 0.4, 0.85, 0.95, 1.5, 0.3]]])
    found = torch.tensor([[[1, 0, 1, 0, 1, 1]]])  # the last two are no pushes: not counted
    rows = recall_by_distance(found, truth, dist, [0.0, 0.5, 0.9, 1.0])
    assert [(r["steps"], r["recall"]) for r in rows] == [(2, 0.5), (1, 1.0), (1, 0.0)]
    perfect = recall_by_distance(truth, truth, dist, [0.0, 0.5, 0.9, 1.0])
    assert [r["recall"] for r in perfect] == [1.0, 1.0, 1.0]
    empty = recall_by_distance(found, truth, dist, [1.0, 2.0])
    assert empty[0]["steps"] == 0 and math.isnan(empty[0]["recall"])
    with pytest.raises(ValueError, match="one shape"):
        recall_by_distance(found[..., :3], truth, dist)


def test_command_line_scores_a_trained_run(make_cfg, tmp_path, capsys):
    run = tmp_path / "run"
    train(make_cfg(["model=dider", "logger=none"], out=run))
    out = tmp_path / "rows.json"
    args = [str(run), "--clips", "30", "--seed", "7", "--bins", "0,0.5,1", "--out", str(out)]
    main(args)
    record = json.loads(out.read_text())
    assert record["command"] == "python -m dider.analysis.push_strength " + " ".join(args)  # how to make it again
    (res,) = record["runs"]
    states, edges = simulate_push(30, 50, seed=7)
    pushes = int((edges[:, 1:] > 0).sum())
    for key in ("segments", "prior"):
        assert [(r["lo"], r["hi"]) for r in res[key]] == [(0.0, 0.5), (0.5, 1.0)]
        assert sum(r["steps"] for r in res[key]) == pushes  # the bins hold every push step
        assert all(0 <= r["recall"] <= 1 for r in res[key]) and 0 <= res[f"{key}_none_recall"] <= 1
    assert "segments [0,0.5)" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([str(run), "--bins", "0.5,0.2"])
