import torch

from dider.data.simulators.push import EDGE_0_TO_2, EDGE_1_TO_2, simulate_push


def test_shapes_and_determinism():
    states, edges = simulate_push(32, 50, seed=3)
    assert states.shape == (32, 50, 3, 4) and edges.shape == (32, 50, 6)
    again, _ = simulate_push(32, 50, seed=3)
    other, _ = simulate_push(32, 50, seed=4)
    assert torch.equal(states, again) and not torch.equal(states, other)


def test_initial_ranges():
    states, _ = simulate_push(2000, 2, seed=0)
    vel = states[:, 0, :, 2:]
    assert ((vel[:, 0] >= 0.05) & (vel[:, 0] <= 0.1)).all()
    assert ((vel[:, 1] >= -0.1) & (vel[:, 1] <= -0.05)).all()
    pos0 = states[:, 0, :, :2] - vel  # states hold the post-update positions
    assert ((pos0[:, 0] >= -2) & (pos0[:, 0] <= -1)).all() and ((pos0[:, 1] >= 1) & (pos0[:, 1] <= 2)).all()


def test_physics_and_edge_alignment():
    states, edges = simulate_push(500, 50, seed=1)
    pos, vel = states[..., :2].double(), states[..., 2:].double()
    # Euler step with dt = 1: x_t = x_{t-1} + v_t.
    torch.testing.assert_close(pos[:, 1:], pos[:, :-1] + vel[:, 1:], atol=1e-5, rtol=0)
    # Particles 0 and 1 never change velocity, and only the two pushes on particle 2 ever fire.
    assert torch.equal(vel[:, 1:, :2], vel[:, :-1, :2])
    assert edges.sum() > 0 and edges[..., [0, 2, 4, 5]].sum() == 0
    # edges[t] is the push that produced state t from t-1: measured on the positions at t-1.
    for t in (1, 10, 30, 49):
        d0 = (pos[:, t - 1, 2] - pos[:, t - 1, 0]).norm(dim=-1)
        d1 = (pos[:, t - 1, 2] - pos[:, t - 1, 1]).norm(dim=-1)
        assert torch.equal(edges[:, t, EDGE_0_TO_2].bool(), d0 < 1)
        assert torch.equal(edges[:, t, EDGE_1_TO_2].bool(), d1 < 1)
        dv = vel[:, t, 2] - vel[:, t - 1, 2]
        pushed = edges[:, t, [EDGE_0_TO_2, EDGE_1_TO_2]].sum(-1) > 0
        assert (dv[~pushed].abs() < 1e-6).all() and (dv[pushed].norm(dim=-1) > 0).all()
        # the push points away from the pusher: particle 2 moves away from particle 0
        only0 = edges[:, t, EDGE_0_TO_2].bool() & ~edges[:, t, EDGE_1_TO_2].bool()
        away = pos[:, t - 1, 2] - pos[:, t - 1, 0]
        assert ((dv[only0] * away[only0]).sum(-1) > 0).all()
