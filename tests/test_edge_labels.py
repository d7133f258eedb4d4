"""The label alignment, pinned through the metrics: the batch labels transition t -> t+1 with the push that
produced x_{t+1}; the ground truth scores 1.0 against itself, and labels one step late (the public DNRI
code's alignment, which scores transition t against the push that produced x_t) score what that implies."""

import torch

from dider.data.simulate import EDGE_0_TO_2, EDGE_1_TO_2
from dider.evaluation.metrics import BoundaryF1, EdgeAccuracy
from helpers.flat import flat


def first_test_batch(tmp_path) -> dict[str, torch.Tensor]:
    dm = flat("synth", num_train=8, num_val=4, num_test=200, loader={"eval_batch_size": 200},
                         cache_dir=str(tmp_path), seed=5)
    dm.prepare_data()
    dm.setup()
    return next(iter(dm.test_dataloader()))


def test_labels_mark_the_transition_they_drive(tmp_path):
    batch = first_test_batch(tmp_path)
    vel = batch["states"][..., 2:]  # normalised: an affine map per feature, so a change stays a change
    dv = (vel[:, 1:, 2] - vel[:, :-1, 2]).norm(dim=-1)  # [S, T-1]: particle 2's velocity change over t -> t+1
    pushed = (batch["edges"][..., [EDGE_0_TO_2, EDGE_1_TO_2]] > 0).any(-1)  # [S, T-1]
    assert pushed.any() and (~pushed).any()
    assert (dv[pushed] > 1e-5).all() and (dv[~pushed] < 1e-5).all()


def test_truth_scores_one_and_a_late_copy_scores_what_the_shift_implies(tmp_path):
    edges = first_test_batch(tmp_path)["edges"]  # [S, T-1, E]
    perfect = EdgeAccuracy()
    perfect.update(edges, edges)
    assert perfect.compute().tolist() == [1.0, 1.0]

    late = torch.cat([torch.zeros_like(edges[:, :1]), edges[:, :-1]], dim=1)  # transition t gets label t-1
    acc = EdgeAccuracy()
    acc.update(late, edges)
    truth, guess = (edges > 0), (late > 0)
    # recall by class, counted by hand: every step of a push but its first is still covered
    none = (~truth & ~guess).sum().item() / (~truth).sum().item()
    interaction = (truth & guess).sum().item() / truth.sum().item()
    assert acc.compute().tolist() == [float(torch.tensor(none, dtype=torch.float32)),
                                      float(torch.tensor(interaction, dtype=torch.float32))]
    pushes = (truth[:, 1:] & ~truth[:, :-1]).sum().item() + truth[:, 0].sum().item()  # one first step each
    assert interaction == 1 - pushes / truth.sum().item()
    assert 0.5 < interaction < 1.0  # pushes last several steps: one step late still finds most of each

    # Clips whose pushes keep off both ends: there a one-step-late copy moves every switch by exactly one.
    inner = ~(truth[:, :1] | truth[:, -2:]).flatten(1).any(1)
    truth_t, late_t = edges[inner].transpose(1, 2), late[inner].transpose(1, 2)
    assert (truth_t > 0).any()
    f1 = BoundaryF1(tolerance=2)
    f1.update(truth_t, truth_t)
    assert f1.compute().item() == 1.0
    f1 = BoundaryF1(tolerance=1)
    f1.update(late_t, truth_t)
    assert f1.compute().item() == 1.0  # every switch found within one step
    f1 = BoundaryF1(tolerance=0)
    f1.update(late_t, truth_t)
    assert f1.compute().item() < 0.05  # exact only where a one-step push's late start meets its true end
