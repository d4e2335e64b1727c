"""Algorithm 2's learner (`HighLevelTrainer`): one `iterate()` collects a rollout of the hierarchical
game, runs the PPO update of the anchor selector and the critic, and every `consmac_every`
iterations trains the communication module by supervised learning on the replay B_C. The run
(budget, phases, checkpoints, export) is `cefc_mj.train.highlevel`."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch

from cefc_mj.hierarchy import (
    HierarchicalCEFCEnv,
    LowLevel,
)
from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.nn.atm import Critic
from cefc_mj.nn.consmac import global_labels, seeded
from cefc_mj.nn.consmac_grad import fused_supported, supervised_grads
from cefc_mj.nn.highlevel_policy import (
    HighLevelPolicy,
)
from cefc_mj.nn.selector import build_critic
from cefc_mj.task.config import LEARNED_ADVERSARY
from cefc_mj.task.messages import MessageChannel
from cefc_mj.train.consmac_replay import ConsMACReplay
from cefc_mj.train.highlevel_config import HighLevelConfig
from cefc_mj.train.mappo import iteration_seed
from cefc_mj.train.ppo import ValueNorm, advantages_and_targets, ppo_epochs

CONSMAC_KEYS = ("consmac_loss", "consmac_loss_first", "consmac_loss_last", "consmac_steps", "replay_size")


@dataclass
class HighRollout:
    """One iteration's decisions, time-major: T decisions x B envs (x N agents)."""

    obs: torch.Tensor  # [T, B, N, D] CEFC observation at each decision
    next_obs: torch.Tensor  # [T, B, N, D] at the next decision (an episode's final one before reset)
    consensus: torch.Tensor  # [T, B, N, C] the selector's consensus input as acted on (detached)
    comm_inputs: tuple[torch.Tensor, ...]  # tarmac: ConsMAC inputs (obs, own, messages, mask, distance), else ()
    actions: torch.Tensor  # [T, B, N] anchor indices
    logp: torch.Tensor  # [T, B, N]
    states: torch.Tensor  # [T, B, S]
    next_states: torch.Tensor  # [T, B, S]
    rewards: torch.Tensor  # [T, B] R_H summed over the decision's low-level steps
    episode_end: torch.Tensor  # [T, B] bool
    stats: dict[str, float]
    senders: torch.Tensor | None = None  # tarmac: [T, B, N, K] each inbox slot's sender (-1: empty), else None


# ---------------------------------------------------------------------------- trainer
class _Joint:
    """Optimizers stepped as one by `ppo_epochs` (wt-rl: the selector's and ConsMAC's own)."""

    def __init__(self, *optimizers: torch.optim.Optimizer):
        self.optimizers = optimizers

    def zero_grad(self, set_to_none: bool = True) -> None:
        for opt in self.optimizers:
            opt.zero_grad(set_to_none=set_to_none)

    def step(self) -> None:
        for opt in self.optimizers:
            opt.step()


class HighLevelTrainer:
    """Algorithm 2's learner: the policy (ConsMAC + selector), the critic, their optimizers, the
    value normalizer, the replay B_C and a torch RNG; one `iterate()` = collect, RL update, ConsMAC."""

    def __init__(self, cfg: HighLevelConfig, low_levels: tuple[LowLevel, LowLevel], adversary_policy=None):
        """adversary_policy: the trained adversary's action function when cfg.adversary names one
        (default: loaded from that name)."""
        self.cfg = cfg
        self.task = cfg.task()
        self.low_levels = low_levels  # (pre-training, fine-tuning)
        self.adversary_record: dict = {"rule": cfg.adversary}
        if adversary_policy is None and self.task.adversary == LEARNED_ADVERSARY:  # the one cfg names
            _, adversary_policy, self.adversary_record = resolve_adversary(cfg.adversary)
        self.adversary_policy = adversary_policy  # the trained adversary of a 'learned' game, else None
        self.policy = HighLevelPolicy.build(cfg.variant, self.task, cfg.seed, cfg.hidden, cfg.ablation)
        probe = HierarchicalCEFCEnv(
            self.task,
            low_levels[1],
            n_envs=1,
            seed=0,
            decision_interval=cfg.decision_interval,
            adversary_policy=adversary_policy,
        )
        with seeded(cfg.seed + 2):
            self.critic: Critic = build_critic(probe.state_size + probe.layout.size, cfg.critic_hidden)
        self.value_norm = ValueNorm()
        rl_params = list(self.policy.selector.parameters())
        if cfg.variant == "tarmac":
            rl_params += list(self.policy.comm.parameters())
        self.policy_opt = torch.optim.Adam(rl_params, lr=cfg.ppo.lr, eps=1e-5)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=cfg.ppo.lr, eps=1e-5)
        self.consmac_opt = (
            torch.optim.Adam(self.policy.comm.parameters(), lr=cfg.consmac_lr, foreach=True) if cfg.supervised else None
        )
        # wt-rl: the PPO step also steps ConsMAC, with ConsMAC's own optimizer (one Adam state for both losses)
        self.rl_step = _Joint(self.policy_opt, self.consmac_opt) if cfg.ablation == "wt-rl" else self.policy_opt
        self.replay = ConsMACReplay(cfg.replay_capacity, self.policy.comm.cfg) if cfg.supervised else None
        self.replay_rows_per_iteration: int | None = None
        """Rows one iteration's rollout adds to the replay (measured by the last iteration; None before one)."""
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.iteration = 0
        self.episodes = 0
        self.elapsed = 0.0
        self.progress = {"phase": 0, "iterations": [0, 0]}
        self.consmac_rounds = 0
        self.consmac_steps = 0
        self.envs: dict[int, HierarchicalCEFCEnv] = {}
        self.pretrained: dict | None = None
        """The policy's weights when pre-training ended (the paper's "wo-FT" ablation); None before
        that, or when the run has no pre-training."""

    # ------------------------------------------------------------------ phases
    def enter_phase(self) -> int:
        """The phase the budget has reached (never going back); builds its env on first entry."""
        phase = max(self.progress["phase"], self.cfg.phase(self.iteration, self.elapsed))
        if phase == 1 and self.progress["phase"] == 0 and self.progress["iterations"][0] > 0:
            self.pretrained = {k: v.detach().clone() for k, v in self.policy.state_dict().items()}
        self.progress["phase"] = phase
        if phase not in self.envs:
            self.envs[phase] = HierarchicalCEFCEnv(
                self.task,
                self.low_levels[phase],
                n_envs=self.cfg.ppo.n_envs,
                seed=self.cfg.seed,
                decision_interval=self.cfg.decision_interval,
                adversary_policy=self.adversary_policy,
            )
        return phase

    # ------------------------------------------------------------------ rollout
    @torch.no_grad()
    def collect(self, env: HierarchicalCEFCEnv) -> HighRollout:
        cfg, policy = self.cfg, self.policy
        weights = self.task.rewards
        channel = (
            MessageChannel(env.n_envs, env.n_agents, policy.message_dim, self.task.observation_distance)
            if policy.comm is not None
            else None
        )
        obs = env.reset(seed=iteration_seed(cfg.seed, self.iteration))
        state = env.global_state()
        keys = ("obs", "next_obs", "consensus", "actions", "logp", "states", "next_states", "rewards", "episode_end")
        buf: dict[str, list] = {k: [] for k in keys}
        comm_buf: list[tuple[torch.Tensor, ...]] = []
        sender_buf: list[torch.Tensor] = []
        keep_inputs = cfg.rl_into_comm  # the update recomputes the consensus with gradients
        episode_return = np.zeros(env.n_envs)
        weighted = {"R_t": weights.task_weight, "R_n": weights.navigation_weight_high, "R_e": weights.evasion_weight}
        term_sums = {name: np.zeros(env.n_envs) for name in weighted}
        finished: dict[str, list[float]] = {"return": [], **{name: [] for name in weighted}}
        metrics: dict[str, list[float]] = {}
        anchor_counts = np.zeros(env.n_anchors)
        for _ in range(cfg.ppo.episodes_per_iteration * env.decision_steps):
            obs_t = torch.from_numpy(obs)
            inbox = channel.receive(env.world.agent_pos) if channel is not None else None
            comm_inputs = policy.comm_inputs(obs_t, inbox)
            consensus, out = policy.consensus(comm_inputs, tuple(obs_t.shape[:-1]))
            if out is not None:
                channel.send(out.message.numpy())
            index, logp = policy.selector.act(obs_t, consensus, generator=self.generator)
            if self.replay is not None:
                comm_cfg = policy.comm.cfg
                if comm_cfg.label_dim:
                    label = global_labels(
                        comm_cfg, env.world.agent_pos, env.world.agent_vel, anchors=env.decode(index.numpy())
                    )
                else:  # NVIF: nothing beyond its inputs
                    label = np.zeros((*index.shape, 0), dtype=np.float32)
                rows = dict(zip(ConsMACReplay.FIELDS[:-1], comm_inputs))
                rows["label"] = torch.from_numpy(label)
                rows_per_step = index.numel()  # one per agent-decision (a zero-width label cannot reshape by -1)
                self.replay.add({k: v.reshape(rows_per_step, *v.shape[2:]) for k, v in rows.items()})
            next_obs, reward, done, info = env.step(index.numpy())
            next_state = env.global_state()
            for k, v in (
                ("obs", obs_t),
                ("next_obs", torch.from_numpy(next_obs)),
                ("consensus", consensus.detach()),
                ("actions", index),
                ("logp", logp),
                ("states", torch.from_numpy(state)),
                ("next_states", torch.from_numpy(next_state)),
                ("rewards", torch.from_numpy(reward.astype(np.float32))),
                ("episode_end", torch.from_numpy(done)),
            ):
                buf[k].append(v)
            if keep_inputs:
                comm_buf.append(comm_inputs)
            if cfg.variant == "tarmac":
                sender_buf.append(torch.from_numpy(inbox.sender))
            anchor_counts += np.bincount(index.numpy().ravel(), minlength=env.n_anchors)
            episode_return += reward
            for name, w in weighted.items():
                term_sums[name] += w * info["reward_terms"][name]
            obs, state = next_obs, next_state
            if done.any():
                finished["return"].extend(episode_return[done].tolist())
                episode_return[done] = 0.0
                for name in weighted:
                    finished[name].extend(term_sums[name][done].tolist())
                    term_sums[name][done] = 0.0
                for name, value in info["metrics"].items():
                    metrics.setdefault(name, []).extend(value[done].tolist())
                obs = env.reset(mask=done)
                if channel is not None:
                    channel.reset(done)
                state = env.global_state()
        usage = anchor_counts / anchor_counts.sum()
        stats = {
            "episode_return": float(np.mean(finished["return"])),
            **{f"term/{name}": float(np.mean(finished[name])) for name in weighted},
            **{f"metric/{name}": float(np.mean(v)) for name, v in metrics.items() if name != "N"},
            "anchor_usage_entropy": float(-(usage[usage > 0] * np.log(usage[usage > 0])).sum()),
            "episodes": len(finished["return"]),
        }
        comm_inputs = tuple(torch.stack(parts) for parts in zip(*comm_buf)) if comm_buf else ()
        senders = torch.stack(sender_buf) if sender_buf else None
        return HighRollout(
            **{k: torch.stack(v) for k, v in buf.items()}, comm_inputs=comm_inputs, stats=stats, senders=senders
        )

    def critic_input(self, states: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """[..., S] global states and [..., N, D] observations -> [..., N, S + D] (V(s, o_i))."""
        return torch.cat([states.unsqueeze(-2).expand(*obs.shape[:-1], states.shape[-1]), obs], dim=-1)

    # ------------------------------------------------------------------ RL update
    def policy_terms(
        self,
        obs: torch.Tensor,
        consensus: torch.Tensor,
        comm_inputs: tuple[torch.Tensor, ...],
        actions: torch.Tensor,
        senders: tuple[torch.Tensor, ...] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(log-probabilities, entropies) of taken anchors under the current policy. The ConsMAC
        variants act on the stored (detached) consensus; tarmac and wt-rl recompute it with gradients.

        senders (tarmac): (the previous decision's comm inputs (obs, own, messages, mask, distance)
        [M, N, ...], each inbox slot's sender [M, N, K], fresh [M] (True where the episode began at
        this decision: nothing was sent before)). With them the inbox of this decision is recomputed
        live (`live_inbox`), so the loss reaches the senders' message network; without them the
        stored inbox is used (the received messages are constants)."""
        if self.cfg.rl_into_comm:
            if senders is not None:
                comm_inputs = self.live_inbox(comm_inputs, *senders)
            consensus, _ = self.policy.consensus(comm_inputs, tuple(obs.shape[:-1]))
        return self.policy.selector.evaluate(obs, consensus, actions)

    def live_inbox(
        self,
        comm_inputs: tuple[torch.Tensor, ...],
        previous: tuple[torch.Tensor, ...],
        sender: torch.Tensor,
        fresh: torch.Tensor,
    ) -> tuple[torch.Tensor, ...]:
        """TarMAC's end-to-end messages: the comm inputs of one decision with the own message and every
        received message replaced by the senders' messages recomputed, with gradients, from their
        inputs of the previous decision (which are constants: the gradient is truncated one step back).
        Where `fresh` (an episode's first decision) the stored inbox (silence) is kept."""
        obs, own, messages, mask, distance = comm_inputs
        sent = self.policy.comm(*previous, with_estimate=False).message  # [M, N, D]: what each agent sent
        m, n, k = sender.shape
        slot_sender = sender.clamp_min(0).reshape(m, n * k, 1).expand(m, n * k, sent.shape[-1])
        received = torch.gather(sent, 1, slot_sender).reshape(m, n, k, -1)
        received = torch.where(mask.unsqueeze(-1), received, messages)  # empty slots stay as stored (zeros)
        live = ~fresh.reshape(m, 1, 1)
        own = torch.where(live, sent, own)
        messages = torch.where(live.unsqueeze(-1), received, messages)
        return obs, own, messages, mask, distance

    def update(self, ro: HighRollout) -> dict[str, float]:
        """PPO epochs over one rollout (the low level's MAPPO, for a categorical policy)."""
        ppo = self.cfg.ppo
        t, b, n = ro.logp.shape
        with torch.no_grad():
            critic_in = self.critic_input(ro.states, ro.obs)
            values = self.critic(critic_in)
            next_values = self.critic(self.critic_input(ro.next_states, ro.next_obs))
            rewards = ro.rewards.unsqueeze(-1).expand(t, b, n)  # the team reward, for every agent
            end = ro.episode_end.unsqueeze(-1).expand(t, b, n)
            advantages, targets, ev = advantages_and_targets(rewards, values, next_values, end, ppo, self.value_norm)

        flat = lambda x: x.reshape(t * b, *x.shape[2:])  # noqa: E731 - a sample is one env-decision, all agents
        obs, consensus, actions, old_logp = flat(ro.obs), flat(ro.consensus), flat(ro.actions), flat(ro.logp)
        comm_inputs = tuple(flat(x) for x in ro.comm_inputs)
        senders = None
        if ro.senders is not None:  # tarmac: each decision's senders' inputs at the previous decision
            previous = tuple(flat(torch.cat([x[:1], x[:-1]])) for x in ro.comm_inputs)
            fresh = torch.cat([torch.ones_like(ro.episode_end[:1]), ro.episode_end[:-1]])
            senders = (previous, flat(ro.senders), flat(fresh))
        adv, critic_in, targets = flat(advantages), flat(critic_in), flat(targets)
        rl_params = list(self.policy.selector.parameters())
        if self.cfg.rl_into_comm:
            rl_params += list(self.policy.comm.parameters())

        def policy_terms(mb):
            new_logp, entropy = self.policy_terms(
                obs[mb],
                consensus[mb],
                tuple(x[mb] for x in comm_inputs),
                actions[mb],
                None if senders is None else (tuple(x[mb] for x in senders[0]), senders[1][mb], senders[2][mb]),
            )
            return new_logp, entropy.mean()

        stats = ppo_epochs(
            t * b,
            ppo,
            self.generator,
            policy_terms,
            old_logp,
            adv,
            self.rl_step,
            rl_params,
            self.critic,
            critic_in,
            targets,
            self.critic_opt,
        )
        stats["explained_variance"] = ev
        return stats

    # ------------------------------------------------------------------ ConsMAC update
    def train_consmac(self, steps: int) -> dict[str, float]:
        """`steps` Adam steps of the module's supervised loss (eq. (11) for ConsMAC; MASIA's and
        NVIF's own: `supervised_loss`) on batches from the replay; returns the round's losses."""
        comm, opt = self.policy.comm, self.consmac_opt
        fused = fused_supported(comm)  # ConsMAC: the hand-written backward pass, else autograd
        params = list(comm.parameters())
        losses = []
        for _ in range(steps):
            batch = self.replay.sample(self.cfg.consmac_batch, self.generator)
            if fused:
                loss = supervised_grads(comm, batch)
            else:
                loss = comm.supervised_loss(batch, generator=self.generator)
                opt.zero_grad()
                loss.backward()
            torch.nn.utils.clip_grad_norm_(params, self.cfg.ppo.max_grad_norm)
            opt.step()
            losses.append(loss.item())
        self.consmac_rounds += 1
        self.consmac_steps += steps
        return {
            "consmac_loss": float(np.mean(losses)),
            "consmac_loss_first": losses[0],
            "consmac_loss_last": losses[-1],
            "consmac_steps": steps,
            "replay_size": self.replay.size,
        }

    # ------------------------------------------------------------------ one iteration
    def iterate(self) -> dict[str, float]:
        cfg = self.cfg
        t0 = time.perf_counter()
        phase = self.enter_phase()
        env = self.envs[phase]
        torch.set_num_threads(cfg.ppo.rollout_threads)
        rows_before = None if self.replay is None else self.replay.rows_added
        rollout = self.collect(env)
        if self.replay is not None:
            self.replay_rows_per_iteration = self.replay.rows_added - rows_before
        t1 = time.perf_counter()
        torch.set_num_threads(cfg.ppo.update_threads)
        stats = self.update(rollout)
        t2 = time.perf_counter()
        self.iteration += 1
        self.episodes += rollout.stats["episodes"]
        self.progress["iterations"][phase] += 1
        consmac: dict[str, float] = {}
        if self.replay is not None:  # the same CSV columns in every row, NaN between rounds
            consmac = dict.fromkeys(CONSMAC_KEYS, math.nan)
            if self.iteration % cfg.consmac_every == 0:
                consmac.update(self.train_consmac(cfg.consmac_steps))
        t3 = time.perf_counter()
        self.elapsed += t3 - t0
        decisions = rollout.logp.numel()
        return {
            "iteration": self.iteration,
            "episodes_total": self.episodes,
            "wall_s": self.elapsed,
            "phase": phase,
            "low_level": self.low_levels[phase].name,
            **rollout.stats,
            **stats,
            **consmac,
            "rollout_s": t1 - t0,
            "update_s": t2 - t1,
            "consmac_s": t3 - t2,
            "decisions_per_s": decisions / (t1 - t0),
        }

    # ------------------------------------------------------------------ checkpoint state
    def state_dict(self) -> dict:
        return {
            "policy": self.policy.state_dict(),
            "critic": self.critic.state_dict(),
            "value_norm": self.value_norm.state_dict(),
            "policy_opt": self.policy_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "consmac_opt": None if self.consmac_opt is None else self.consmac_opt.state_dict(),
            "replay": None
            if self.replay is None
            else self.replay.state_dict(keep_rows=not self.replay_refilled_before_read()),
            "generator": self.generator.get_state(),
            "progress": {"phase": self.progress["phase"], "iterations": list(self.progress["iterations"])},
            "pretrained": self.pretrained,
            "counters": {
                "iteration": self.iteration,
                "episodes": self.episodes,
                "elapsed": self.elapsed,
                "consmac_rounds": self.consmac_rounds,
                "consmac_steps": self.consmac_steps,
            },
        }

    def replay_refilled_before_read(self) -> bool:
        """Whether every row the replay holds now is overwritten before anything reads it again: the
        iterations up to the next ConsMAC round (or the budget's last iteration, after which the
        export reads the newest rows) add at least `replay_capacity` rows. At the paper's schedule
        (a round every 20 iterations, the replay about 8 iterations deep) that holds for the
        checkpoints of the first 12 iterations after each round, so their states leave the rows out
        and a resumed run continues bit for bit (tests/test_highlevel.py)."""
        if self.replay is None or not self.replay_rows_per_iteration:
            return False
        if self.cfg.budget.exhausted(self.iteration, self.elapsed):  # the final state: a re-export reads the rows
            return False
        every = self.cfg.consmac_every
        next_read = (self.iteration // every + 1) * every
        if self.cfg.budget.iterations is not None:
            next_read = min(next_read, self.cfg.budget.iterations)
        return (next_read - self.iteration) * self.replay_rows_per_iteration >= self.replay.capacity

    def load_state_dict(self, state: dict) -> None:
        self.policy.load_state_dict(state["policy"])
        self.critic.load_state_dict(state["critic"])
        self.value_norm.load_state_dict(state["value_norm"])
        self.policy_opt.load_state_dict(state["policy_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        if self.consmac_opt is not None:
            self.consmac_opt.load_state_dict(state["consmac_opt"])
            self.replay.load_state_dict(state["replay"])
        self.generator.set_state(state["generator"])
        self.progress = {"phase": int(state["progress"]["phase"]), "iterations": list(state["progress"]["iterations"])}
        self.pretrained = state.get("pretrained")  # absent in states written before wo-FT snapshots
        c = state["counters"]
        self.iteration, self.episodes, self.elapsed = int(c["iteration"]), int(c["episodes"]), float(c["elapsed"])
        self.consmac_rounds, self.consmac_steps = int(c["consmac_rounds"]), int(c["consmac_steps"])
