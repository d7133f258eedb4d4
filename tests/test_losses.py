"""The loss terms of dider.models.losses against closed forms evaluated by hand with math.log.

Inputs are float64 so that the comparisons can be tight; every expected value is derived in a comment.
"""

from __future__ import annotations

import math

import pytest
import torch

from dider.models.likelihood import GaussianNLL
from dider.models.losses import (
    capacity,
    categorical_kl,
    categorical_kl_probs,
    gaussian_kl,
    gaussian_nll,
    residual_variance,
)

F64 = torch.float64


def close(actual: torch.Tensor, expected: float | list) -> None:
    torch.testing.assert_close(actual, torch.tensor(expected, dtype=F64), rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------- gaussian_nll
# B=3 samples, T=1 step, N=2 agents, D=2 features; target 0; variance 0.5, so that
# per agent: |pred|^2 / (2 * 0.5) + 0.5 * D * log(2 pi * 0.5) = |pred|^2 + log(pi).
NLL_PRED = torch.tensor([[[[1.0, 0.0], [1.0, 1.0]]],         # |pred|^2 = 1, 2
                         [[[2.0, 0.0], [100.0, 100.0]]],     # 4, and a huge error on an absent agent
                         [[[3.0, 3.0], [5.0, 5.0]]]], dtype=F64)  # all absent
NLL_MASK = torch.tensor([[[True, True]], [[True, False]], [[False, False]]])


def test_gaussian_nll_hand_example() -> None:
    """Sum over features, mean over present (step, agent), one value per sample."""
    nll = gaussian_nll(NLL_PRED, torch.zeros_like(NLL_PRED), NLL_MASK, variance=0.5)
    # sample 0: mean(1 + log pi, 2 + log pi) = 1.5 + log pi
    # sample 1: only agent 0 is present -> 4 + log pi (the 100s of the absent agent do not count)
    # sample 2: nothing present -> 0 (the denominator is clamped to 1, the numerator is 0)
    close(nll, [1.5 + math.log(math.pi), 4 + math.log(math.pi), 0.0])


def test_gaussian_nll_normaliser_per_feature_and_variance() -> None:
    """A perfect prediction costs exactly the log-normaliser, once per feature: 0.5 * D * log(2 pi var)."""
    pred = torch.zeros(1, 2, 1, 3, dtype=F64)  # D=3
    mask = torch.ones(1, 2, 1, dtype=torch.bool)
    close(gaussian_nll(pred, pred, mask, variance=2.0), [1.5 * math.log(4 * math.pi)])
    # an error of 1 in one feature at variance 2: + 1 / (2 * 2) = 0.25 on that (step, agent), mean over 2 -> 0.125
    target = pred.clone()
    target[0, 0, 0, 1] = 1.0
    close(gaussian_nll(pred, target, mask, variance=2.0), [1.5 * math.log(4 * math.pi) + 0.125])


def test_gaussian_nll_masked_entries_get_no_gradient() -> None:
    """Masked-out predictions neither change the value nor receive gradient."""
    pred = NLL_PRED.clone().requires_grad_(True)
    gaussian_nll(pred, torch.zeros_like(pred), NLL_MASK, variance=0.5).sum().backward()
    assert (pred.grad[~NLL_MASK] == 0).all()
    # d/dpred of |pred|^2 / (2 var) / count = pred / (var * count): sample 0, agent 0, feature 0 -> 1 / (0.5 * 2)
    assert pred.grad[0, 0, 0, 0].item() == pytest.approx(1.0, rel=1e-12)


def test_gaussian_nll_empty_batch() -> None:
    pred = torch.zeros(0, 1, 2, 2, dtype=F64)
    assert gaussian_nll(pred, pred, torch.zeros(0, 1, 2, dtype=torch.bool), variance=1.0).shape == (0,)


# ----------------------------------------------------------------------------------------- categorical_kl
Q = [0.5, 0.25, 0.25]


def test_categorical_kl_hand_example() -> None:
    """KL(q || p) with q = (1/2, 1/4, 1/4) and p uniform over 3."""
    q_logits = torch.tensor(Q, dtype=F64).log() + 7.0  # logits are free up to a constant
    p_logits = torch.zeros(3, dtype=F64)
    # 1/2 log(1/2 / 1/3) + 2 * 1/4 log(1/4 / 1/3) = 1/2 log 1.5 + 1/2 log 0.75 = 1/2 log 1.125
    close(categorical_kl(q_logits, p_logits), 0.5 * math.log(1.125))
    # the argument order matters: KL(p || q) = 1/3 (log(1/3 / 1/2) + 2 log(1/3 / 1/4)) = 1/3 log(32/27)
    close(categorical_kl(p_logits, q_logits), math.log(32 / 27) / 3)


def test_categorical_kl_batched_and_zero_on_equal() -> None:
    """[..., K] -> [...]: one KL per row; identical rows give 0, a two-class case gives its closed form."""
    q = torch.tensor([[[0.0, 0.0]], [[math.log(3.0), 0.0]]], dtype=F64)  # (1/2, 1/2) and (3/4, 1/4)
    p = torch.tensor([[[0.0, 0.0]], [[0.0, 0.0]]], dtype=F64)
    # row 1: 3/4 log(3/4 / 1/2) + 1/4 log(1/4 / 1/2) = 3/4 log 1.5 - 1/4 log 2
    close(categorical_kl(q, p), [[0.0], [0.75 * math.log(1.5) - 0.25 * math.log(2)]])
    assert categorical_kl(torch.zeros(0, 4), torch.zeros(0, 4)).shape == (0,)


def test_categorical_kl_near_one_hot_stays_finite() -> None:
    """A nearly one-hot q (finite logits, as networks produce) gives KL = log K against uniform, not NaN."""
    q = torch.tensor([0.0, -1e4], dtype=F64)
    close(categorical_kl(q, torch.zeros(2, dtype=F64)), math.log(2))


def test_categorical_kl_probs_hand_example_and_exact_zeros() -> None:
    """q as probabilities: the hand example above, and a q with exact zeros (0 log 0 = 0): one-hot (1, 0)
    against (0.9, 0.1) is log(1/0.9)."""
    log_p = torch.full((3,), -math.log(3.0), dtype=F64)
    close(categorical_kl_probs(torch.tensor(Q, dtype=F64), log_p), 0.5 * math.log(1.125))
    close(categorical_kl_probs(torch.tensor([1.0, 0.0], dtype=F64), torch.tensor([0.9, 0.1], dtype=F64).log()),
          math.log(1 / 0.9))


# -------------------------------------------------------------------------------------------- gaussian_kl
def test_gaussian_kl_closed_form() -> None:
    """KL(N(mu, s^2) || N(mu0, s0^2)) = log(s0 / s) + (s^2 + (mu - mu0)^2) / (2 s0^2) - 1/2, elementwise."""
    mu = torch.tensor([1.0, 0.5, 3.0], dtype=F64)
    sigma = torch.tensor([2.0, 0.5, 1.0], dtype=F64)
    # against N(0, 1): (1, 2): log(1/2) + (4 + 1) / 2 - 1/2 = 2 - log 2
    #                  (0.5, 0.5): log 2 + (0.25 + 0.25) / 2 - 1/2 = log 2 - 0.25
    #                  (3, 1): 0 + (1 + 9) / 2 - 1/2 = 4.5
    close(gaussian_kl(mu, sigma, 0.0, 1.0), [2 - math.log(2), math.log(2) - 0.25, 4.5])
    # against N(1, 2^2): (0.5, 0.5): log 4 + (0.25 + 0.25) / 8 - 1/2 = log 4 - 0.4375
    close(gaussian_kl(mu[1:2], sigma[1:2], 1.0, 2.0), [math.log(4) - 0.4375])


def test_gaussian_kl_zero_at_the_prior() -> None:
    mu = torch.full((2, 3), 1.5, dtype=F64)
    close(gaussian_kl(mu, torch.full_like(mu, 0.7), 1.5, 0.7), torch.zeros(2, 3, dtype=F64).tolist())


# ----------------------------------------------------------------------------------------------- capacity
@pytest.mark.parametrize(("step", "expected"), [
    (0, 0.0),    # ramp start
    (5, 1.0),    # halfway: 2 * 5/10
    (10, 2.0),   # ramp end
    (25, 2.0),   # past the end: held at c_max
])
def test_capacity_linear_ramp(step: int, expected: float) -> None:
    assert capacity(step, c_max=2.0, ramp_steps=10) == pytest.approx(expected, abs=1e-15)


@pytest.mark.parametrize("ramp_steps", [0, -3])
def test_capacity_without_ramp_is_c_max_from_the_start(ramp_steps: int) -> None:
    """ramp_steps <= 0: no ramp (and no division by zero)."""
    assert capacity(0, c_max=2.5, ramp_steps=ramp_steps) == 2.5
    assert capacity(7, c_max=2.5, ramp_steps=ramp_steps) == 2.5


def test_gaussian_nll_per_feature_variance_hand_example() -> None:
    """Errors (1, 2) with variances (1, 4): 1/2 + 4/8 = 1, plus 0.5 (log 2 pi + log 8 pi)."""
    pred, target = torch.tensor([[[[1.0, 2.0]]]]), torch.zeros(1, 1, 1, 2)
    nll = gaussian_nll(pred, target, torch.ones(1, 1, 1, dtype=torch.bool), torch.tensor([1.0, 4.0]))
    assert nll.item() == pytest.approx(1.0 + 0.5 * (math.log(2 * math.pi) + math.log(8 * math.pi)))


def test_residual_variance_hand_example() -> None:
    """Three agents move by 0.1 x their velocity (1, 2, 3): the fitted step explains the positions (variance at
    the floor), the velocities change by 0.5, -1, 0.5 (sample variance 0.75); a fourth agent, absent at the
    second step, is left out whatever its values; y stays 0."""
    now = torch.tensor([[0.0, 0, 1, 0], [0, 0, 2, 0], [0, 0, 3, 0], [5, 5, 9, 9]])
    nxt = torch.tensor([[0.1, 0, 1.5, 0], [0.2, 0, 1.0, 0], [0.3, 0, 3.5, 0], [-7, 2, -9, 40]])
    x = torch.stack([now, nxt])[None]  # [1, 2, 4, 4]
    mask = torch.tensor([[[True, True, True, True], [True, True, True, False]]])
    var = residual_variance(x, mask, floor=1e-8)
    assert var.tolist() == pytest.approx([1e-8, 1e-8, 0.75, 1e-8], abs=1e-7)


def test_likelihood_fit_is_saved_and_old_weights_load() -> None:
    x = torch.randn(2, 6, 3, 4)
    fitted = GaussianNLL("fit")
    variance = fitted.fit(x, None)
    assert variance.shape == (4,) and bool((variance > 0).all())
    fresh = GaussianNLL("fit")  # before fitting: one variance of 1
    fresh.load_state_dict(fitted.state_dict())
    assert torch.equal(fresh.variance, variance)
    fixed = GaussianNLL(5e-5)
    fixed.load_state_dict({})  # weights saved before the variance was kept with them: the configured value
    assert fixed.variance.item() == pytest.approx(5e-5)
