"""The loss of given segmentations at a run's trained weights (``python -m dider.analysis.diagnose``)."""

import json

import pytest

from dider.analysis.diagnose import main
from dider.run import train


def test_command_line_scores_each_segmentation_of_a_trained_run(make_cfg, tmp_path, capsys):
    run = tmp_path / "run"
    train(make_cfg(["model=dider", "logger=none"], out=run))
    out = tmp_path / "diagnose.json"
    args = [str(run), "--clips", "16", "--draws", "2", "--lengths", "10", "--out", str(out)]
    main(args)
    result = json.loads(out.read_text())
    assert result["command"] == "python -m dider.analysis.diagnose " + " ".join(args)  # how to make it again
    rows, weights = result["rows"], result["weights"]
    assert weights == {"kl_edge": 0.5, "kl_duration": 1.0, "sparsity": 0.5, "indifference": 2.0}  # model=dider
    assert set(rows) == {"own (test)", "own (training)", "one-step", "posterior runs", "truth runs", "fixed 10"}
    for name, row in rows.items():  # the loss is the sum of its terms, the slots tile each edge's 49 steps
        assert row["loss"] == pytest.approx(row["nll"] + sum(w * row[k] for k, w in weights.items()), abs=1e-4), name
        assert row["segments_per_edge"] * row["steps_per_segment"] == pytest.approx(49, rel=1e-4), name
    # the burn-in (transitions 0-3) is one segment, every later step its own: 1 + 45 slots; fixed 10: at 0, the
    # burn-in's end (4), 10, 20, 30 and 40
    assert rows["one-step"]["segments_per_edge"] == pytest.approx(46)
    assert rows["fixed 10"]["segments_per_edge"] == pytest.approx(6)
    # a segment at every step pays the most duration KL of all: every step is a boundary under the prior
    assert rows["one-step"]["kl_duration"] > max(r["kl_duration"] for n, r in rows.items() if n != "one-step")
    printed = capsys.readouterr().out
    assert "posterior runs" in printed and "kl_duration" in printed
    with pytest.raises(SystemExit):
        main([str(run), "--lengths", "0"])
    with pytest.raises(FileNotFoundError, match="not a run folder"):
        main([str(tmp_path)])
