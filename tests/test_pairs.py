"""The inD consistency check: which pairs are parked / opposite-direction, their edges, and the metric."""


import pytest
import torch

from dider.data.pairs import OPPOSITE, PARKED, PairRules, find_pairs, pair_kind_matrix
from dider.data.tracks import TracksDataModule
from dider.evaluation.metrics import PairConsistency
from dider.graph import edge_index
from dider.training.preflight import validate_config
from helpers.fixtures import write_ind_root

LEVELX_SOURCE = "dider.data.levelx.source.LevelXSource"

T = 10


def agent(x0: float, y0: float, vx: float, vy: float, dt: float = 0.4) -> torch.Tensor:
    t = torch.arange(T, dtype=torch.float32)
    return torch.stack([x0 + vx * t * dt, y0 + vy * t * dt, torch.full((T,), vx), torch.full((T,), vy)], -1)


def test_find_pairs_by_rule():
    windows = [
        # parked car, parked car, a car driving east: one parked pair
        [agent(0, 0, 0, 0), agent(5, 0, 0.1, 0), agent(0, 5, 5, 0)],
        # opposite directions on parallel lanes (never cross); a third car follows the first: opposite to
        # the second too, but in the same direction as the first
        [agent(0, 0, 5, 0), agent(20, 3, -5, 0), agent(-5, 0, 5, 0)],
        # opposite directions whose paths cross, and a car creeping at 1 m/s (neither parked nor moving)
        [agent(0, 0, 5, 0.5), agent(20, 0, -5, 0.5), agent(0, 9, 1, 0)],
        # a parked car and a standing pedestrian: not a vehicle pair
        [agent(0, 0, 0, 0), agent(3, 3, 0, 0)],
    ]
    states = torch.cat([torch.stack(w) for w in windows])
    offsets = torch.tensor([0, 3, 6, 9, 11])
    vehicle = torch.ones(11, dtype=torch.bool)
    vehicle[10] = False
    out = find_pairs(states, torch.ones(11, T, dtype=torch.bool), offsets, vehicle, PairRules())
    assert out["pair_offsets"].tolist() == [0, 1, 3, 3, 3]
    assert out["pair_agents"].tolist() == [[0, 1], [0, 1], [1, 2]]
    assert out["pair_kind"].tolist() == [PARKED, OPPOSITE, OPPOSITE]


def test_pairs_need_to_be_present_together():
    states = torch.stack([agent(0, 0, 0, 0), agent(5, 0, 0, 0)])
    mask = torch.zeros(2, T, dtype=torch.bool)
    mask[0, :4], mask[1, 6:] = True, True  # never in the window at the same time: no edge-steps to check
    out = find_pairs(states, mask, torch.tensor([0, 2]), torch.ones(2, dtype=torch.bool), PairRules())
    assert out["pair_kind"].numel() == 0


def test_pair_kind_matrix_uses_the_models_edge_order():
    offsets, agents, kinds = torch.tensor([0, 1, 3]), torch.tensor([[0, 2], [1, 3], [0, 1]]), torch.tensor([1, 2, 1])
    m = pair_kind_matrix(offsets, agents, kinds, windows=torch.tensor([1, 0]), n=4)
    send, recv = edge_index(4)
    for b, pairs in enumerate([{(1, 3): 2, (0, 1): 1}, {(0, 2): 1}]):
        expect = [pairs.get((int(s), int(r)), pairs.get((int(r), int(s)), 0)) for s, r in zip(send, recv, strict=True)]
        assert m[b].tolist() == expect


def test_pair_consistency_metric():
    metric = PairConsistency(num_types=3)
    types = torch.tensor([[[2, 2, 2, 1], [0, 0, 1, 1], [1, 1, 1, 1]]])  # [B=1, E=3, T=4]
    kind = torch.tensor([[PARKED, OPPOSITE, 0]])
    present = torch.ones(1, 3, 4, dtype=torch.bool)
    present[0, 1, 3] = False  # the opposite pair's last step is absent: not counted
    metric.update(types, kind, present)
    share, dominant, total = metric.compute()
    assert share.tolist() == pytest.approx([0.75, 2 / 3]) and dominant.tolist() == [2, 0]
    assert total.tolist() == [4, 3]
    empty = PairConsistency(num_types=2)
    empty.update(types.clamp(max=1), torch.zeros(1, 3, dtype=torch.long), present)
    assert torch.isnan(empty.compute()[0]).all()


def test_ind_test_batches_carry_the_parked_pairs(tmp_path, make_cfg):
    # The fixture's tracks 0 and 1 are parked cars present in every window; the other tracks move.
    root = write_ind_root(tmp_path / "inD")
    dm = TracksDataModule(source={"_target_": LEVELX_SOURCE, "root": str(root)}, windows={"seq_len": 20}, pairs={},
                          cache_dir=str(tmp_path / "cache"), split=(2, 1, 1),
                          loader={"batch_size": 4, "eval_batch_size": 4})
    dm.prepare_data()
    dm.setup()
    batch = next(iter(dm.test_dataloader()))
    n = batch["states"].shape[2]
    send, recv = edge_index(n)
    assert (batch["pair_kind"][:, (send < 2) & (recv < 2)] == PARKED).all()
    assert not (batch["pair_kind"][:, (send >= 2) | (recv >= 2)] == PARKED).any()
    assert "pair_kind" not in next(iter(dm.train_dataloader()))
    with pytest.raises(ValueError, match="data.pairs"):
        TracksDataModule(source={"_target_": LEVELX_SOURCE, "root": str(root)}, pairs={"parked_speed": 0.0})
    with pytest.raises(ValueError, match=r"data.pairs.parked_sped: no such setting \(expected one of \['parked_speed'"):
        TracksDataModule(source={"_target_": LEVELX_SOURCE, "root": str(root)}, pairs={"parked_sped": 1.0})
    with pytest.raises(ValueError, match=r"data.pairs.parked_sped: no such setting"):  # and before a run starts
        validate_config(make_cfg(["data=ind", "+data.pairs.parked_sped=1.0"]))
