"""The PPO pieces, as small pure functions checked against hand-computed values in tests/test_ppo.py.

- `compute_gae`: generalized advantage estimation with time-limit truncation handled by
  bootstrapping from the value of the episode's final state.
- `clipped_policy_loss`: the clipped surrogate of paper eq. (6) with PPO's health statistics.
- `ValueNorm`: running mean/variance of return targets; the critic predicts normalized returns.
- `explained_variance`.
"""

from __future__ import annotations

import torch


def compute_gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    next_values: torch.Tensor,
    episode_end: torch.Tensor,
    gamma: float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Advantages and return targets, both [T, B], for rewards [T, B] collected over T steps.

    values[t] = V(s_t); next_values[t] = V(s_{t+1}), where s_{t+1} is the state the step led to
    (for a step that ended an episode: the episode's final state, before any reset). episode_end[t]
    marks such steps; the advantage recursion does not cross them:

        delta_t = r_t + gamma V(s_{t+1}) - V(s_t)
        A_t     = delta_t + gamma lam (1 - end_t) A_{t+1}

    Episodes in this task end only by the time limit, so the final state is always bootstrapped
    (a truncation, not a termination). Returns = A + V.
    """
    steps = rewards.shape[0]
    deltas = rewards + gamma * next_values - values
    continues = 1.0 - episode_end.to(rewards.dtype)
    advantages = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[0])
    for t in reversed(range(steps)):
        running = deltas[t] + gamma * lam * continues[t] * running
        advantages[t] = running
    return advantages, advantages + values


def clipped_policy_loss(
    new_logp: torch.Tensor, old_logp: torch.Tensor, advantages: torch.Tensor, clip_eps: float
) -> tuple[torch.Tensor, dict[str, float]]:
    """-E[min(beta A, clip(beta, 1 - eps, 1 + eps) A)] with beta = exp(new - old).

    Returns (loss, stats) with stats approx_kl (the low-variance estimator E[(beta - 1) - log beta])
    and clipfrac (share of samples with |beta - 1| > eps).
    """
    log_ratio = new_logp - old_logp
    ratio = log_ratio.exp()
    unclipped = ratio * advantages
    clipped = ratio.clamp(1.0 - clip_eps, 1.0 + clip_eps) * advantages
    loss = -torch.min(unclipped, clipped).mean()
    with torch.no_grad():
        approx_kl = ((ratio - 1.0) - log_ratio).mean().item()
        clipfrac = ((ratio - 1.0).abs() > clip_eps).float().mean().item()
    return loss, {"approx_kl": approx_kl, "clipfrac": clipfrac}


PPO_STATS = ("policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac", "actor_grad_norm", "critic_grad_norm")


def ppo_epochs(
    n_samples: int,
    ppo,
    generator: torch.Generator,
    policy_terms,
    old_logp: torch.Tensor,
    advantages: torch.Tensor,
    policy_opt: torch.optim.Optimizer,
    policy_params: list,
    critic: torch.nn.Module,
    critic_in: torch.Tensor,
    targets: torch.Tensor,
    critic_opt: torch.optim.Optimizer,
    train_policy: bool = True,
) -> dict[str, float]:
    """PPO's epochs over one rollout of `n_samples` samples in shuffled minibatches: per minibatch,
    the clipped surrogate minus the entropy bonus for the policy and 0.5 MSE to the (normalized)
    targets for the critic, each with its own optimizer and gradient-norm clip.

    policy_terms(mb) -> (log-probabilities of the taken actions [mb, ...] under the current policy,
    mean entropy); old_logp, advantages, critic_in, targets are indexed by sample first. Returns the
    mean over minibatches of PPO_STATS. Shared by the low-level (Gaussian) and high-level
    (categorical) MAPPO updates. train_policy=False leaves the policy as it is (a critic warm-up: its
    loss is still reported)."""
    sums = dict.fromkeys(PPO_STATS, 0.0)
    count = 0
    for _ in range(ppo.epochs):
        perm = torch.randperm(n_samples, generator=generator)
        for mb in perm.chunk(ppo.minibatches):
            new_logp, entropy = policy_terms(mb)
            policy_loss, st = clipped_policy_loss(new_logp, old_logp[mb], advantages[mb], ppo.clip_eps)
            policy_opt.zero_grad()
            (policy_loss - ppo.entropy_coef * entropy).backward()
            actor_norm = torch.nn.utils.clip_grad_norm_(policy_params, ppo.max_grad_norm)
            if train_policy:
                policy_opt.step()

            value_loss = 0.5 * (critic(critic_in[mb]) - targets[mb]).pow(2).mean()
            critic_opt.zero_grad()
            value_loss.backward()
            critic_norm = torch.nn.utils.clip_grad_norm_(critic.parameters(), ppo.max_grad_norm)
            critic_opt.step()
            for k, v in (
                ("policy_loss", policy_loss.item()),
                ("value_loss", value_loss.item()),
                ("entropy", entropy.item()),
                ("approx_kl", st["approx_kl"]),
                ("clipfrac", st["clipfrac"]),
                ("actor_grad_norm", actor_norm.item()),
                ("critic_grad_norm", critic_norm.item()),
            ):
                sums[k] += v
            count += 1
    return {k: v / count for k, v in sums.items()}


LEARNER_PARTS = ("actor", "critic", "value_norm", "actor_opt", "critic_opt")
"""The attributes of an actor-critic PPO learner saved in its resumable state (with `generator`)."""


def learner_state(learner) -> dict:
    """The state dicts of a learner's LEARNER_PARTS and its torch generator's state."""
    return {
        **{name: getattr(learner, name).state_dict() for name in LEARNER_PARTS},
        "generator": learner.generator.get_state(),
    }


def load_learner_state(learner, state: dict) -> None:
    """Restore what `learner_state` saved."""
    for name in LEARNER_PARTS:
        getattr(learner, name).load_state_dict(state[name])
    learner.generator.set_state(state["generator"])


class ValueNorm(torch.nn.Module):
    """Running mean and variance of return targets (exact, over every target seen so far, merged
    batch by batch with the parallel-variance formula). The critic regresses normalize(returns);
    its outputs are denormalized before GAE. The statistics are buffers, so they travel with
    `state_dict()` into checkpoints."""

    def __init__(self, epsilon: float = 1e-5):
        super().__init__()
        self.epsilon = epsilon
        self.register_buffer("mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("var", torch.ones((), dtype=torch.float64))
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        x = x.detach().to(torch.float64).flatten()
        batch_mean, batch_var, n = x.mean(), x.var(unbiased=False), x.numel()
        total = self.count + n
        delta = batch_mean - self.mean
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        self.mean.copy_(self.mean + delta * n / total)
        self.var.copy_(m2 / total)
        self.count.copy_(total)

    def std(self) -> torch.Tensor:
        return (self.var + self.epsilon).sqrt()

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return ((x.to(torch.float64) - self.mean) / self.std()).to(x.dtype)

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x.to(torch.float64) * self.std() + self.mean).to(x.dtype)


def explained_variance(predicted: torch.Tensor, target: torch.Tensor) -> float:
    """1 - Var[target - predicted] / Var[target]; 1 is perfect, 0 no better than a constant."""
    var = target.var()
    if var.item() == 0:
        return float("nan")
    return (1.0 - (target - predicted).var() / var).item()


def advantages_and_targets(rewards, values, next_values, episode_end, ppo, value_norm: "ValueNorm"):
    """GAE advantages, the critic's targets and the explained variance for one rollout [T, B, N],
    as MAPPO uses them: values come normalized when ppo.value_normalization (and the norm is then
    updated with the new returns), advantages are standardized when ppo.normalize_advantages."""
    if ppo.value_normalization:
        values, next_values = value_norm.denormalize(values), value_norm.denormalize(next_values)
    advantages, returns = compute_gae(rewards, values, next_values, episode_end, ppo.gamma, ppo.gae_lambda)
    ev = explained_variance(values.flatten(), returns.flatten())
    if ppo.value_normalization:
        value_norm.update(returns)
        targets = value_norm.normalize(returns)
    else:
        targets = returns
    if ppo.normalize_advantages:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    return advantages, targets, ev
