"""segments.json: the per-edge segment lists of every test clip."""

import json

import torch

from dider.graph import edge_index
from dider.outputs.clips import split_clips, stack_clips
from dider.outputs.export import segments_json
from dider.run import train


def test_segments_json_lists_runs_of_present_edges():
    types = torch.tensor([[[0, 0, 1, 1, 1], [2, 2, 2, 0, 0]]])  # one clip, 2 agents (2 edges), 5 steps
    types[0, 1, 4] = -1  # edge 1 -> 0 is absent at the last step
    probs = torch.full(types.shape, 0.5)
    probs[0, 0, 2:] = 0.9
    three = torch.full((2, 6, 5), -1)
    three[1, 3] = torch.tensor([1, 1, 1, 1, 1])  # 3 agents, only edge 1 -> 2 of the second clip present
    clips = split_clips({"segments": types, "probs": probs}) + split_clips({"segments": three,
                                                                            "probs": torch.ones(2, 6, 5)})
    blob = segments_json(stack_clips(clips))  # the 2-agent clip is padded to 3 agents: its edges keep their pairs
    assert [c["clip"] for c in blob["clips"]] == [0, 1, 2]
    first = blob["clips"][0]["edges"]
    assert [(e["sender"], e["receiver"]) for e in first] == [(0, 1), (1, 0)]
    assert first[0]["segments"] == [{"start": 0, "end": 2, "type": 0, "prob": 0.5},
                                    {"start": 2, "end": 5, "type": 1, "prob": 0.9}]
    assert first[1]["segments"] == [{"start": 0, "end": 3, "type": 2, "prob": 0.5},
                                    {"start": 3, "end": 4, "type": 0, "prob": 0.5}]
    assert blob["clips"][1]["edges"] == []
    send, recv = edge_index(3)
    assert blob["clips"][2]["edges"] == [{"sender": int(send[3]), "receiver": int(recv[3]),
                                          "segments": [{"start": 0, "end": 5, "type": 1, "prob": 1.0}]}]


def test_run_exports_every_test_clip(make_cfg, tmp_path):
    out = tmp_path / "run"
    train(make_cfg(["model=dider", "trainer.max_epochs=1"], out=out))
    blob = json.loads((out / "segments.json").read_text())
    record = json.loads((out / "metrics.json").read_text())
    from dider.analysis import explore  # the explorer reads the test clips of a synthetic run (no source ids)

    assert explore.main([str(out)]) == 0 and (out / "explorer.html").stat().st_size > 0
    assert len(blob["clips"]) == record["config"]["data"]["num_test"]
    steps = record["config"]["data"]["source"]["num_steps"] - 1
    for clip in blob["clips"]:
        assert len(clip["edges"]) == 6  # 3 particles, all present
        for edge in clip["edges"]:  # the segments tile the clip's transitions
            segs = edge["segments"]
            assert segs[0]["start"] == 0 and segs[-1]["end"] == steps
            assert all(a["end"] == b["start"] and a["type"] != b["type"] for a, b in zip(segs, segs[1:], strict=False))


def test_segments_json_carries_the_source_identifiers():
    types = torch.tensor([[[1, 1, 0], [0, 0, 0]]])  # one clip, 2 agents, 3 steps
    clips = split_clips({"segments": types, "probs": torch.ones(1, 2, 3),
                         "source": {"clip": torch.tensor([7]), "scene": torch.tensor([1]),
                                    "frame": torch.tensor([100]), "agent": torch.tensor([[42, 5]])}})
    blob = segments_json(stack_clips(clips), frame_step=10, names={"scene": ["a", "b"]})
    clip = blob["clips"][0]
    assert clip["source"] == {"clip": 7, "scene": "b", "frame": 100, "agent": [42, 5]}
    first = clip["edges"][0]
    assert (first["sender_id"], first["receiver_id"]) == (42, 5)
    # the 0 -> 1 edge: type 1 over transitions 0..1 (frames 100..120 of the input), then type 0
    assert first["segments"][0] == {"start": 0, "end": 2, "type": 1, "prob": 1.0, "start_frame": 100,
                                    "end_frame": 120}
