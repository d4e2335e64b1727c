"""BenchMARL on the high-level game: MASAC (the stand-in for the paper's HASAC) and MAPPO (a cross-check of
`cefc-train highlevel --variant mappo`), trained on our `HierarchicalCEFCEnv` and exported as our own
high-level policy files, which Table V's evaluator flies unchanged (docs/research/baselines.md, "BenchMARL
baselines"). Needs the optional `benchmarl` extra (BenchMARL 1.5.2, torchrl 0.11).

- `HighLevelGameEnv`: a torchrl `EnvBase` over the batched game (batch [B], one group "agents" of N):
  per agent the observation o_i the anchor selector reads (the CEFC observation's targets, adversary
  and neighbour parts, 38 numbers, times the selector's obs_scale 0.125), a discrete action (one of
  the 9 anchors), the team reward R_H summed over the decision's 10 low-level steps (the reward our
  trainer optimises) given to every agent, the global state (`HierarchicalCEFCEnv.global_state`) for
  the centralised critics, and `done` (= `terminated`, as our trainer treats an episode's end) after
  the episode's 40 decisions. The k-th full reset plays the games of `iteration_seed(seed, k)`, the
  games our trainer plays at iteration k.
- `CEFCGameTask`: the BenchMARL `TaskClass` of that env, built from a `BenchMARLConfig`'s game: the
  TaskConfig of `HighLevelConfig.task()`, the trained adversary and the fine-tuning low level
  (`atm_student`). BenchMARL runs have no navigation-only pre-training phase: they fly the
  fine-tuning low level from the first episode (our trainer's `--pretrain-share 0`, CI-HRL-DT's
  schedule).
- `train_benchmarl`: a BenchMARL `Experiment` on the CPU under the episode budget (1500 episodes of 40
  decisions = 60000 frames), then `export_actor` copies BenchMARL's actor (4 linear layers with tanh,
  the shape of our `AnchorSelector`) into a `HighLevelPolicy` of the mappo variant (no
  communication), checks that both give the same logits, writes `<name>.pt` and its model card with a
  20-episode evaluation on the validation games (`GAME_VALIDATION_SEED`).
- `evaluate_benchmarl(path, episodes, seed)`: Table V's row of an exported file (`run_table5(policy=...)`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Unbounded
from torchrl.envs import EnvBase

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.eval.highlevel import run_table5
from cefc_mj.fileio import write_atomic
from cefc_mj.game_protocol import evaluate_highlevel
from cefc_mj.hierarchy import HierarchicalCEFCEnv, LowLevel, load_low_level
from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.nn.consmac import LOCAL_PARTS
from cefc_mj.nn.highlevel_policy import HighLevelPolicy, save_highlevel_policy
from cefc_mj.seeds import GAME_VALIDATION_SEED
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.benchmarl_common import (
    GROUP,
    CEFCTaskBase,
    Progress,
    SeededBatchEnv,
    benchmarl_versions,
    build,
    card_tail,
    done_spec,
    env_output,
    experiment_settings,
    group_spec,
    reward_spec,
    run_experiment,
    run_folders,
    tanh_mlp,
    torch_threads,
    trained_weights,
)
from cefc_mj.train.benchmarl_config import DECISION_INTERVAL, BenchMARLConfig
from cefc_mj.train.model_card import display_paths, write_model_card

METHODS = {
    "masac": "BenchMARL MASAC (maximum-entropy MARL; the stand-in for the paper's HASAC), no communication",
    "mappo": "BenchMARL MAPPO, no communication (cross-check of cefc-train highlevel --variant mappo)",
}


# ---------------------------------------------------------------------------- the game as a torchrl env
def selector_observation(obs: np.ndarray, task: TaskConfig, obs_scale: float) -> np.ndarray:
    """o_i as the anchor selector's encoder reads it: the LOCAL_PARTS of CEFC observations [..., D]
    (a prefix of the layout), times obs_scale, float32 [..., d]."""
    from cefc_mj.nn.selector import SelectorConfig

    size = SelectorConfig.from_task(task).obs_dim
    return np.asarray(obs, dtype=np.float32)[..., :size] * np.float32(obs_scale)


class HighLevelGameEnv(SeededBatchEnv):
    """The batched high-level game as a torchrl env (module docstring); batch_size [n_envs]."""

    def __init__(
        self,
        task: TaskConfig,
        low_level: LowLevel,
        n_envs: int,
        seed: int = 0,
        adversary_policy=None,
        obs_scale: float = 0.125,
        reward_scale: float = 1.0,
        device="cpu",
    ):
        super().__init__(device=device, batch_size=torch.Size([n_envs]))
        self.game = HierarchicalCEFCEnv(
            task,
            low_level,
            n_envs=n_envs,
            seed=seed,
            decision_interval=DECISION_INTERVAL,
            adversary_policy=adversary_policy,
        )
        self.task, self.obs_scale, self.reward_scale = task, float(obs_scale), float(reward_scale)
        self.run_seed, self.resets = int(seed), 0
        from cefc_mj.nn.selector import SelectorConfig

        s_cfg = SelectorConfig.from_task(task)
        if tuple(name for name, _ in s_cfg.layout[: len(LOCAL_PARTS)]) != LOCAL_PARTS:
            raise ConfigError("the CEFC layout does not start with the selector's parts; o_i is not a prefix")
        b, n = n_envs, task.n_agents
        self.obs_dim, self.n_anchors = s_cfg.obs_dim, self.game.n_anchors
        self.full_observation_spec = group_spec(
            b,
            n,
            "observation",
            Unbounded((b, n, self.obs_dim), dtype=torch.float32, device=device),
            state=Unbounded((b, self.game.state_size), dtype=torch.float32, device=device),
        )
        self.full_action_spec = group_spec(
            b, n, "action", Categorical(self.n_anchors, shape=(b, n), dtype=torch.int64, device=device)
        )
        self.full_reward_spec = reward_spec(b, n, device)
        self.full_done_spec = done_spec(b, device)

    def batched_env(self) -> HierarchicalCEFCEnv:
        return self.game

    def _observation(self, obs: np.ndarray, done: np.ndarray | None = None) -> TensorDict:
        b, n = self.batch_size[0], self.task.n_agents
        return env_output(
            torch.from_numpy(selector_observation(obs, self.task, self.obs_scale)),
            torch.as_tensor(self.game.global_state(), dtype=torch.float32),
            done,
            b,
            n,
            self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get((GROUP, "action")).cpu().numpy().astype(np.int64)
        obs, reward, done, _ = self.game.step(action.reshape(self.batch_size[0], self.task.n_agents))
        out = self._observation(obs, done)
        r = (
            torch.as_tensor(reward * self.reward_scale, dtype=torch.float32)
            .reshape(-1, 1, 1)
            .expand(-1, self.task.n_agents, 1)
        )
        out.set((GROUP, "reward"), r.clone())
        return out


def load_game(cfg: BenchMARLConfig) -> tuple[TaskConfig, LowLevel, object, dict]:
    """(TaskConfig, the fine-tuning low level, the adversary's policy or None, the adversary's record) of
    the config's game; CheckpointError (one line) for a missing or broken file."""
    game = cfg.game_config()
    task = game.task()
    try:
        low_level = load_low_level(cfg.low_level, task)
    except CheckpointError as e:
        raise CheckpointError(f"--low-level: {e}") from None
    try:
        _, adversary_policy, record = resolve_adversary(cfg.adversary)
    except CheckpointError as e:
        raise CheckpointError(f"--adversary: {e}") from None
    return task, low_level, adversary_policy, record


def make_game_env(cfg: BenchMARLConfig, n_envs: int | None = None, seed: int | None = None) -> HighLevelGameEnv:
    """The config's game as a torchrl env of n_envs (default cfg.n_envs) envs."""
    task, low_level, adversary_policy, _ = load_game(cfg)
    return HighLevelGameEnv(
        task,
        low_level,
        n_envs=cfg.n_envs if n_envs is None else n_envs,
        seed=cfg.seed if seed is None else seed,
        adversary_policy=adversary_policy,
        reward_scale=cfg.reward_scale,
    )


class CEFCGameTask(CEFCTaskBase):
    """BenchMARL's task of the high-level game; `config` is a `BenchMARLConfig.to_dict()`."""

    def get_env_fun(self, num_envs: int, continuous_actions: bool, seed: int | None, device):
        cfg = BenchMARLConfig.from_dict(self.config)
        return lambda: make_game_env(cfg, n_envs=num_envs, seed=cfg.seed if seed is None else seed).to(device)

    def supports_continuous_actions(self) -> bool:
        return False

    def supports_discrete_actions(self) -> bool:
        return True

    def max_steps(self, env: EnvBase) -> int:
        return BenchMARLConfig.from_dict(self.config).decision_steps


def make_task(cfg: BenchMARLConfig) -> CEFCGameTask:
    return CEFCGameTask(name="highlevel", config=cfg.to_dict())


# ---------------------------------------------------------------------------- the experiment
def build_experiment(cfg: BenchMARLConfig, run_dir: Path, callbacks=()):
    """The BenchMARL Experiment of `cfg`, writing under run_dir (which must exist)."""
    from benchmarl.algorithms import MappoConfig, MasacConfig

    frames = cfg.frames_per_batch
    settings = {
        **experiment_settings(run_dir, cfg.gamma, cfg.lr, cfg.max_frames, frames, cfg.n_envs),
        "on_policy_n_minibatch_iters": cfg.mappo_epochs,
        "on_policy_minibatch_size": cfg.mappo_minibatch,
        "off_policy_n_optimizer_steps": cfg.masac_updates,
        "off_policy_train_batch_size": cfg.masac_batch,
        "off_policy_memory_size": max(cfg.max_frames, frames),
    }
    algorithm = (MasacConfig if cfg.algorithm == "masac" else MappoConfig).get_from_yaml()
    actor = tanh_mlp([cfg.hidden] * 3)
    return build(make_task(cfg), algorithm, actor, cfg.critic_cells, cfg.seed, settings, callbacks)


def _trained_actor(experiment):
    """(a context that loads the trained actor weights, the actor's Mlp model): the weights the optimizers
    update are the loss module's actor parameters, loaded into its actor network for the duration."""
    return trained_weights(experiment), experiment.losses[GROUP].actor_network.module[0]


def _actor_mlp(experiment) -> torch.nn.Module:
    """BenchMARL's trained actor network (the shared-parameter MLP of group "agents") as a plain module."""
    weights, model = _trained_actor(experiment)
    with weights:
        return model.mlp.get_stateful_net(copy=True)


def actor_logits(experiment, observation: torch.Tensor) -> torch.Tensor:
    """BenchMARL's actor logits [..., N, 9] for selector observations [..., N, d] (the trained actor's own
    forward pass, through its TensorDict modules)."""
    lead = observation.shape[:-2]
    td = TensorDict({GROUP: TensorDict({"observation": observation}, batch_size=observation.shape[:-1])}, lead)
    weights, model = _trained_actor(experiment)
    with weights, torch.no_grad():
        model(td)
    return td.get((GROUP, "logits"))


def export_actor(experiment, cfg: BenchMARLConfig, task: TaskConfig) -> HighLevelPolicy:
    """Our HighLevelPolicy (mappo variant: the anchor selector alone) with BenchMARL's actor weights:
    the actor's 4 linear layers become the selector's encoder (2) and head (2). The BenchMARL actor
    reads o_i x obs_scale, which the selector computes from the full CEFC observation, so both give
    the same logits; checked on random observations (CheckpointError if not)."""
    policy = HighLevelPolicy.build("mappo", task, cfg.seed, cfg.hidden)
    selector = policy.selector
    source = [m for m in _actor_mlp(experiment).modules() if isinstance(m, torch.nn.Linear)]
    target = [m for m in (*selector.encoder, *selector.selector) if isinstance(m, torch.nn.Linear)]
    if len(source) != len(target) or any(s.weight.shape != t.weight.shape for s, t in zip(source, target)):
        raise CheckpointError(
            f"BenchMARL's actor {[tuple(s.weight.shape) for s in source]} does not have the anchor selector's "
            f"shape {[tuple(t.weight.shape) for t in target]}"
        )
    with torch.no_grad():
        for s, t in zip(source, target):
            t.weight.copy_(s.weight)
            t.bias.copy_(s.bias)
    policy.eval()
    generator = torch.Generator().manual_seed(cfg.seed)
    probe = torch.randn(4, task.n_agents, selector.cfg.env_obs_dim, generator=generator) * 4.0
    with torch.no_grad():
        ours = selector(probe, torch.zeros(4, task.n_agents, 0))
        theirs = actor_logits(
            experiment, torch.from_numpy(selector_observation(probe.numpy(), task, selector.cfg.obs_scale))
        )
    if not torch.allclose(ours, theirs, atol=1e-5, rtol=1e-5):
        raise CheckpointError(
            f"the exported selector's logits differ from BenchMARL's actor's by {(ours - theirs).abs().max():.3g}"
        )
    return policy


def train_benchmarl(
    cfg: BenchMARLConfig,
    out_dir: Path,
    policies_dir: Path | None = None,
    show_progress: bool = True,
    command: str | None = None,
) -> dict:
    """Train `cfg.algorithm` with BenchMARL on the high-level game under cfg.budget_episodes, export the
    actor as <policies_dir>/<name>.pt (default <out_dir>/policies/) with its model card; returns the card.

    BenchMARL writes its own folder (csv logs, config.pkl) inside <out_dir>/<name>/, beside our
    config.json, progress.csv and the final BenchMARL actor/critic weights (benchmarl_losses.pt). Runs
    are not resumable. Runs on the CPU with cfg.threads torch threads."""
    out_dir, policies_dir, run_dir = run_folders(out_dir, policies_dir, cfg.name)
    task, low_level, adversary_policy, adversary_record = load_game(cfg)  # checked before anything is written
    run_dir.mkdir(parents=True, exist_ok=True)
    policies_dir.mkdir(parents=True, exist_ok=True)
    versions = benchmarl_versions()
    low_level_record = display_paths(low_level.describe())
    write_atomic(
        run_dir / "config.json",
        json.dumps(
            {
                "benchmarl": cfg.to_dict(),
                "task": task.to_dict(),
                "low_level": low_level_record,
                "adversary": adversary_record,
                "versions": versions,
                "command": command,
            },
            indent=2,
        )
        + "\n",
    )
    progress = Progress(run_dir / "progress.csv", cfg.reward_scale)
    with torch_threads(cfg.threads):
        experiment, settings = build_experiment(cfg, run_dir, callbacks=[progress])
        wall = run_experiment(experiment, show_progress)
    torch.save({group: loss.state_dict() for group, loss in experiment.losses.items()}, run_dir / "benchmarl_losses.pt")
    policy = export_actor(experiment, cfg, task)
    policy_path = save_highlevel_policy(
        policy,
        policies_dir / f"{cfg.name}.pt",
        meta={
            "name": cfg.name,
            "variant": "mappo",
            "trainer": f"benchmarl-{cfg.algorithm}",
            "algorithm": cfg.algorithm,
            "seed": cfg.seed,
            "iterations": experiment.n_iters_performed,
            "decision_interval": DECISION_INTERVAL,
            "low_level": low_level_record,
            "adversary": adversary_record,
        },
    )
    episodes = progress.rows[-1]["episodes"] if progress.rows else 0
    card = {
        "name": cfg.name,
        "method": METHODS[cfg.algorithm],
        "variant": "mappo",
        "algorithm": cfg.algorithm,
        "trainer": "BenchMARL",
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "benchmarl_settings": settings,
        "task": task.to_dict(),
        "networks": {
            "actor": f"MLP {policy.selector.cfg.obs_dim} -> {cfg.hidden} x 3 -> {policy.selector.cfg.n_anchors}, tanh "
            "(exported as the anchor selector: encoder 2 layers, head 2 layers)",
            "selector": policy.selector.cfg.to_dict(),
            "critic": f"centralised, reads the global state; MLP {list(cfg.critic_cells)}, tanh",
        },
        "low_level": low_level_record,
        "adversary": adversary_record,
        "phases": [{"phase": "finetune", "low_level": low_level.name, "iterations": experiment.n_iters_performed}],
        "pretraining": "none: the fine-tuning low level from the first episode",
        "iterations": experiment.n_iters_performed,
        "frames": int(experiment.total_frames),
        "episodes": episodes,
        "decisions": int(experiment.total_frames) * task.n_agents,
        "train_wall_clock_s": round(wall, 1),
        "s_per_episode": round(wall / episodes, 3) if episodes else None,
        **card_tail(experiment, run_dir, versions, command, progress),
    }
    if cfg.eval_episodes:
        card["evaluation"] = {
            "protocol": {
                "episodes": cfg.eval_episodes,
                "seed": GAME_VALIDATION_SEED,
                "anchors": "mode of the selector",
                "low_level": low_level.name,
                "backend": "particle",
                "game": "the training game (HighLevelConfig.task())",
                "figures": "per-episode sums; R_t, R_n, R_e weighted, summing to R_H",
            },
            "ours": evaluate_highlevel(
                policy,
                task,
                low_level,
                cfg.eval_episodes,
                seed=GAME_VALIDATION_SEED,
                decision_interval=DECISION_INTERVAL,
                adversary_policy=adversary_policy,
            ),
        }
    write_model_card(policy_path, card)
    return card


def evaluate_benchmarl(path: Path | str, episodes: int = 50, seed: int = GAME_VALIDATION_SEED, **table5) -> dict:
    """Table V's protocol (`run_table5`: the paper's game, the PPO adversary, atm_student) on one exported
    file: {"R_H", "R_t", "R_n", "R_e", "E", ... means, and the row as run_table5 gives it under "row"}.
    Extra keyword arguments go to run_table5 (where, adversary, policies_dir)."""
    path = Path(path)
    result = run_table5(episodes=episodes, seed=seed, policy=str(path), **table5)
    row = result["rows"][path.stem]
    return {
        **{m: row[m] for m in ("R_H", "R_t", "R_n", "R_e", "E", "F", "C")},
        "row": row,
        "protocol": result["protocol"],
    }


def summary_lines(card: dict, policies_dir: Path) -> list[str]:
    """What `cefc-train highlevel-benchmarl` prints when a run ends."""
    lines = [
        f"{card['name']}: BenchMARL {card['algorithm']}, {card['iterations']} iterations, {card['episodes']} episodes "
        f"({card['frames']} frames), {card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} "
        f"(run {card['run_dir']})"
    ]
    if "evaluation" in card:
        o = card["evaluation"]["ours"]
        lines.append(
            f"evaluation ({card['evaluation']['protocol']['episodes']} episodes, seed "
            f"{card['evaluation']['protocol']['seed']}): R_H {o['R_H']:.1f} = R_t {o['R_t']:.1f} + R_n {o['R_n']:.1f} "
            f"+ R_e {o['R_e']:.1f}; E {o['E']:.1f}  F {o['F']:.1f}  C {o['C']:.2f}%"
        )
    return lines
