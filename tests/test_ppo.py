"""The PPO pieces against hand-computed values."""

import math

import numpy as np
import pytest
import torch

from cefc_mj.train.ppo import ValueNorm, clipped_policy_loss, compute_gae, explained_variance


def test_gae_matches_hand_computation():
    # One env, three steps, gamma = lambda = 0.5 (so gamma * lambda = 0.25), the last step ends the episode.
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    next_values = torch.tensor([[1.0], [1.5], [2.0]])  # V of the final state is bootstrapped (time limit)
    end = torch.tensor([[False], [False], [True]])
    adv, ret = compute_gae(rewards, values, next_values, end, gamma=0.5, lam=0.5)
    # delta_2 = 3 + 0.5*2.0 - 1.5 = 2.5;  A_2 = 2.5
    # delta_1 = 2 + 0.5*1.5 - 1.0 = 1.75; A_1 = 1.75 + 0.25*2.5 = 2.375
    # delta_0 = 1 + 0.5*1.0 - 0.5 = 1.0;  A_0 = 1.0 + 0.25*2.375 = 1.59375
    assert adv[:, 0].tolist() == pytest.approx([1.59375, 2.375, 2.5])
    assert ret[:, 0].tolist() == pytest.approx([2.09375, 3.375, 4.0])


def test_gae_does_not_cross_an_episode_end():
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [1.5]])
    next_values = torch.tensor([[1.0], [1.5], [2.0]])
    end = torch.tensor([[False], [True], [False]])
    adv, _ = compute_gae(rewards, values, next_values, end, gamma=0.5, lam=0.5)
    # A_1 = delta_1 = 1.75 (episode ends at t = 1); A_0 = 1.0 + 0.25*1.75 = 1.4375; A_2 = 2.5
    assert adv[:, 0].tolist() == pytest.approx([1.4375, 1.75, 2.5])


def test_gae_batched_columns_are_independent():
    torch.manual_seed(0)
    r, v, nv = torch.randn(5, 3), torch.randn(5, 3), torch.randn(5, 3)
    end = torch.zeros(5, 3, dtype=torch.bool)
    adv, _ = compute_gae(r, v, nv, end, 0.8, 0.95)
    for b in range(3):
        col, _ = compute_gae(r[:, b : b + 1], v[:, b : b + 1], nv[:, b : b + 1], end[:, b : b + 1], 0.8, 0.95)
        assert torch.allclose(adv[:, b], col[:, 0])


def test_clipped_policy_loss_hand_values():
    old = torch.zeros(3)
    new = torch.log(torch.tensor([1.5, 0.5, 1.1])).requires_grad_()
    adv = torch.tensor([1.0, 1.0, -1.0])
    loss, stats = clipped_policy_loss(new, old, adv, clip_eps=0.2)
    # min(1.5*1, 1.2*1) = 1.2; min(0.5*1, 0.8*1) = 0.5; min(1.1*-1, 1.1*-1) = -1.1
    assert loss.item() == pytest.approx(-(1.2 + 0.5 - 1.1) / 3)
    assert stats["clipfrac"] == pytest.approx(2 / 3)
    kl = np.mean([(r - 1) - math.log(r) for r in (1.5, 0.5, 1.1)])
    assert stats["approx_kl"] == pytest.approx(kl, rel=1e-5)
    loss.backward()
    # The clipped sample (ratio 1.5 > 1.2 with A > 0) passes no gradient; the others do.
    assert new.grad[0].item() == 0.0
    assert new.grad[1].item() == pytest.approx(-0.5 / 3)
    assert new.grad[2].item() == pytest.approx(1.1 / 3)


def test_value_norm_tracks_mean_and_variance_of_everything_seen():
    rng = np.random.default_rng(0)
    a, b = rng.normal(5.0, 3.0, 400), rng.normal(-2.0, 0.5, 100)
    vn = ValueNorm()
    vn.update(torch.from_numpy(a))
    vn.update(torch.from_numpy(b))
    both = np.concatenate([a, b])
    assert vn.mean.item() == pytest.approx(both.mean())
    assert vn.var.item() == pytest.approx(both.var())
    x = torch.tensor([0.0, 1.0, 10.0])
    assert torch.allclose(vn.denormalize(vn.normalize(x)), x, atol=1e-5)
    assert vn.normalize(torch.tensor([both.mean()])).item() == pytest.approx(0.0, abs=1e-6)
    # The statistics are state: a reloaded normalizer normalizes the same way.
    other = ValueNorm()
    other.load_state_dict(vn.state_dict())
    assert torch.equal(other.normalize(x), vn.normalize(x))


def test_explained_variance():
    y = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert explained_variance(y, y) == pytest.approx(1.0)
    assert explained_variance(torch.full_like(y, 2.5), y) == pytest.approx(0.0)
