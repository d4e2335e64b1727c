"""BenchMARL on the formation task (AT-M's Steps 1-3 scenarios): MADDPG, the paper's Table III baseline,
and IPPO, MAPPO and MASAC beside it, trained on our `BatchedCEFCEnv` and exported as AT-M policy files
that Table III's evaluator flies (docs/formation_benchmarl.md). Needs the optional `benchmarl` extra.

- `FormationEnv`: a torchrl `EnvBase` over `BatchedCEFCEnv` of the AT-M stage's TaskConfig (batch
  [B], one group "agents" of c): per agent the full low-level observation (63 numbers at c = 6), a
  continuous action (the acceleration setpoint [a_x, a_y], bounded by accel_max, which the env clips
  to as it always does), each agent's learning reward of our MAPPO trainer (15 R_f + 4 R_n - 100 CR_i,
  `rollout.agent_rewards` with the trainer's collision credit) times reward_scale, the global state
  for the centralised critics, the episode's F, N, C so far (`BatchedCEFCEnv.episode_metrics`) and
  `done` (= `terminated`) after the episode's 100 steps. Scenario, observation, reward and metric are
  the env's own code; the k-th full reset plays the episodes of `iteration_seed(seed, k)`, in the
  training block of game seeds.
- `ATMModel`: a BenchMARL model whose network is AT-M's actor (`nn.atm.ATMActor`, eq. 8, shared by the
  group): it outputs the acceleration setpoint before the clip, gain x (v* - v) for the velocity head
  (and, for the stochastic algorithms, a learned state-independent scale beside it). MADDPG's actor
  is `Delta` with BenchMARL's projection onto the action box (the clip), the others an
  `IndependentNormal` (no tanh squashing): the deterministic action is then exactly what the policy
  file flies, `clip(to_acceleration(actor(obs)))`.
- `train_formation`: a BenchMARL `Experiment` on the CPU under the frame budget, checkpointed every
  `checkpoint_every` iterations and resumable (`resume=True`), then `export_actor` writes the
  trained ATMActor as `<name>.pt` (checked to act as BenchMARL's deterministic policy does) with its
  model card, including Table III's protocol flown on the validation batch.
"""

from __future__ import annotations

import csv
import json
from dataclasses import MISSING, dataclass
from pathlib import Path

import numpy as np
import torch
from benchmarl.experiment.callback import Callback
from benchmarl.models.common import Model, ModelConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Unbounded
from torchrl.envs import EnvBase

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.nn.atm import ATMActor, ATMConfig
from cefc_mj.nn.policy_io import safe_torch_load, save_policy
from cefc_mj.seeds import FORMATION_VALIDATION_SEED
from cefc_mj.task.config import TaskConfig
from cefc_mj.train import run_state
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
    torch_threads,
    trained_weights,
)
from cefc_mj.train.benchmarl_config import FormationBenchMARLConfig
from cefc_mj.train.config import PPOConfig
from cefc_mj.train.model_card import table3_figures, write_model_card
from cefc_mj.train.rollout import agent_rewards

METRICS = ("F", "N", "C")
"""The episode metrics the env reports (so far in the episode) and progress.csv logs at episodes' ends."""
METHODS = {
    "maddpg": "BenchMARL MADDPG (the paper's Table III baseline), AT-M's actor network",
    "ippo": "BenchMARL IPPO, AT-M's actor network",
    "mappo": "BenchMARL MAPPO, AT-M's actor network",
    "masac": "BenchMARL MASAC, AT-M's actor network",
}
TABLE3_METHOD = {"maddpg": "MADDPG"}
"""The paper's Table III row each algorithm stands beside (the others have none)."""
COLLISION_CREDIT = PPOConfig().collision_credit
"""Whose collision penalty each agent's reward carries: our MAPPO trainer's default."""


# ---------------------------------------------------------------------------- the task as a torchrl env
class FormationEnv(SeededBatchEnv):
    """The batched formation task as a torchrl env (module docstring); batch_size [n_envs]."""

    def __init__(
        self,
        task: TaskConfig,
        n_envs: int,
        seed: int = 0,
        reward_scale: float = 1.0,
        collision_credit: str = COLLISION_CREDIT,
        device="cpu",
    ):
        if task.mode != "formation":
            raise ConfigError(f"FormationEnv: a formation task, not mode={task.mode!r}")
        super().__init__(device=device, batch_size=torch.Size([n_envs]))
        self.env = BatchedCEFCEnv(task, n_envs=n_envs, seed=seed)
        self.task, self.reward_scale, self.collision_credit = task, float(reward_scale), collision_credit
        self.run_seed, self.resets = int(seed), 0
        b, n = n_envs, task.n_agents
        self.full_observation_spec = group_spec(
            b,
            n,
            "observation",
            Unbounded((b, n, self.env.layout.size), dtype=torch.float32, device=device),
            state=Unbounded((b, self.env.state_size), dtype=torch.float32, device=device),
            **{m: Unbounded((b, 1), dtype=torch.float32, device=device) for m in METRICS},
        )
        limit = float(task.accel_max)
        self.full_action_spec = group_spec(
            b, n, "action", Bounded(-limit, limit, shape=(b, n, 2), dtype=torch.float32, device=device)
        )
        self.full_reward_spec = reward_spec(b, n, device)
        self.full_done_spec = done_spec(b, device)

    def batched_env(self) -> BatchedCEFCEnv:
        return self.env

    def _observation(self, obs: np.ndarray, done: np.ndarray | None = None) -> TensorDict:
        b, n = self.batch_size[0], self.task.n_agents
        metrics = self.env.episode_metrics()
        return env_output(
            torch.from_numpy(obs.copy()),
            torch.from_numpy(self.env.global_state()),
            done,
            b,
            n,
            self.device,
            **{m: torch.as_tensor(metrics[m], dtype=torch.float32).reshape(b, 1) for m in METRICS},
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get((GROUP, "action")).detach().cpu().numpy().astype(np.float64)
        obs, reward, done, info = self.env.step(action.reshape(self.batch_size[0], self.task.n_agents, 2))
        own = agent_rewards(
            self.collision_credit,
            reward,
            info["reward_terms"]["R_c"],
            self.env.agent_collision_penalty,
            self.task.rewards,
        )
        out = self._observation(obs, done)
        out.set((GROUP, "reward"), torch.from_numpy((own * np.float32(self.reward_scale))[..., None]))
        return out


def make_formation_env(
    cfg: FormationBenchMARLConfig, n_envs: int | None = None, seed: int | None = None
) -> FormationEnv:
    """The config's formation task as a torchrl env of n_envs (default cfg.n_envs) envs."""
    return FormationEnv(
        cfg.task(),
        n_envs=cfg.n_envs if n_envs is None else n_envs,
        seed=cfg.seed if seed is None else seed,
        reward_scale=cfg.reward_scale,
    )


class CEFCFormationTask(CEFCTaskBase):
    """BenchMARL's task of the formation game; `config` is a `FormationBenchMARLConfig.to_dict()` with
    n_agents."""

    def get_env_fun(self, num_envs: int, continuous_actions: bool, seed: int | None, device):
        cfg = _config_of(self.config)
        return lambda: make_formation_env(cfg, n_envs=num_envs, seed=cfg.seed if seed is None else seed).to(device)

    def supports_continuous_actions(self) -> bool:
        return True

    def supports_discrete_actions(self) -> bool:
        return False

    def max_steps(self, env: EnvBase) -> int:
        return _config_of(self.config).episode_steps


def _config_of(task_config: dict) -> FormationBenchMARLConfig:
    return FormationBenchMARLConfig.from_dict({k: v for k, v in task_config.items() if k != "n_agents"})


def make_task(cfg: FormationBenchMARLConfig) -> CEFCFormationTask:
    return CEFCFormationTask(name="formation", config={**cfg.to_dict(), "n_agents": cfg.formation})


# ---------------------------------------------------------------------------- AT-M's actor as a BenchMARL model
class ATMModel(Model):
    """AT-M's actor (one ATMActor shared by the group) as a BenchMARL policy model (module docstring)."""

    def __init__(self, atm: dict, **kwargs):
        super().__init__(**kwargs)
        if self.is_critic or not self.input_has_agent_dim or self.centralised or not self.share_params:
            raise ConfigError("ATMModel is a decentralised actor with parameters shared by the group")
        self.actor = ATMActor(ATMConfig.from_dict(atm))
        act = self.actor.cfg.act_dim
        width = self.output_leaf_spec.shape[-1]
        if width not in (act, 2 * act):
            raise ConfigError(f"ATMModel: BenchMARL asks for {width} outputs, AT-M's actor gives {act} (or {2 * act})")
        # a state-independent scale parameter for the Normal of IPPO/MAPPO/MASAC (BenchMARL maps it to
        # a positive scale); MADDPG's Delta reads the actions alone
        self.scale = torch.nn.Parameter(torch.zeros(act)) if width == 2 * act else None

    def _perform_checks(self):
        super()._perform_checks()
        if len(self.in_keys) != 1:
            raise ConfigError(f"ATMModel reads the agents' observation alone, not {self.in_keys}")

    def _forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(self.in_key)
        command = self.actor(obs)
        cfg = self.actor.cfg
        if cfg.action == "velocity":  # ATMActor.to_acceleration before its clip
            command = cfg.velocity_gain * (command - obs[..., self.actor.velocity_slice])
        if self.scale is not None:
            command = torch.cat([command, self.scale.expand_as(command)], dim=-1)
        tensordict.set(self.out_key, command)
        return tensordict


@dataclass
class ATMModelConfig(ModelConfig):
    """BenchMARL's config of `ATMModel`: the ATMConfig (as a dict) of the actor."""

    atm: dict = MISSING

    @staticmethod
    def associated_class():
        return ATMModel


def actor_config(cfg: FormationBenchMARLConfig, task: TaskConfig) -> ATMConfig:
    """AT-M's actor shape for the task, with the stage's log-std init (AT-M's trainer's)."""
    return ATMConfig.from_task(task, hidden=cfg.hidden, log_std_init=cfg.stage().log_std_init)


# ---------------------------------------------------------------------------- the experiment
def algorithm_config(cfg: FormationBenchMARLConfig):
    """BenchMARL's config of cfg.algorithm (its yaml defaults), the actions unsquashed (see module docstring)."""
    from benchmarl.algorithms import IppoConfig, MaddpgConfig, MappoConfig, MasacConfig

    kind = {"maddpg": MaddpgConfig, "ippo": IppoConfig, "mappo": MappoConfig, "masac": MasacConfig}[cfg.algorithm]
    algorithm = kind.get_from_yaml()
    if cfg.algorithm == "maddpg":
        algorithm.use_tanh_mapping = False
    else:
        algorithm.use_tanh_normal = False
    return algorithm


class _EnvState(Callback):
    """Carries what a BenchMARL checkpoint lacks: the env's count of full resets (which batch of training
    episodes comes next) and torch's RNG state."""

    def _env(self) -> FormationEnv:
        env = self.experiment.collector.env
        while not isinstance(env, FormationEnv):
            env = env.base_env
        return env

    def on_state_dict(self, state_dict):
        state_dict["cefc_env"] = {"resets": self._env().resets, "torch_rng": torch.get_rng_state()}

    def on_load_state_dict(self, state_dict):
        saved = state_dict.get("cefc_env")
        if saved is not None:
            self._env().resets = int(saved["resets"])
            torch.set_rng_state(saved["torch_rng"])


def build_experiment(cfg: FormationBenchMARLConfig, run_dir: Path, callbacks=(), restore_file: Path | None = None):
    """The BenchMARL Experiment of `cfg`, writing under run_dir (which must exist); `restore_file`: a
    checkpoint it continues."""
    task = cfg.task()
    frames = cfg.frames_per_batch
    settings = {
        **experiment_settings(run_dir, cfg.gamma, cfg.lr, cfg.budget_frames, frames, cfg.n_envs),
        "on_policy_n_minibatch_iters": cfg.epochs,
        "on_policy_minibatch_size": cfg.minibatch_size,
        "off_policy_n_optimizer_steps": cfg.updates,
        "off_policy_train_batch_size": cfg.batch_size,
        "off_policy_memory_size": cfg.memory_frames,
        "exploration_anneal_frames": cfg.exploration_anneal_frames,
        "checkpoint_interval": cfg.checkpoint_every * frames,
        # the last iteration's checkpoint is the end's unless the budget stops between two of them
        "checkpoint_at_end": cfg.iterations % cfg.checkpoint_every != 0,
        "keep_checkpoints_num": 2,
        "restore_file": None if restore_file is None else str(restore_file),
    }
    algorithm = algorithm_config(cfg)
    actor = ATMModelConfig(atm=actor_config(cfg, task).to_dict())
    return build(make_task(cfg), algorithm, actor, cfg.critic_cells, cfg.seed, settings, [*callbacks, _EnvState()])


def trained_model(experiment) -> tuple[object, ATMModel]:
    """(a context that loads the trained actor weights, BenchMARL's ATMModel): the weights the optimizers
    update are the loss module's actor parameters, loaded into its actor network for the duration."""
    model = next(m for m in experiment.losses[GROUP].actor_network.modules() if isinstance(m, ATMModel))
    return trained_weights(experiment), model


def deterministic_actions(experiment, observation: torch.Tensor) -> torch.Tensor:
    """BenchMARL's deterministic actions [..., c, 2] (its policy's own forward, the trained weights) for
    observations [..., c, D]."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    loss = experiment.losses[GROUP]
    td = TensorDict(
        {GROUP: TensorDict({"observation": observation}, batch_size=observation.shape[:-1])},
        batch_size=observation.shape[:-2],
    )
    weights, _ = trained_model(experiment)
    with weights, torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        loss.actor_network(td)
    return td.get((GROUP, "action"))


def export_actor(experiment, cfg: FormationBenchMARLConfig, task: TaskConfig) -> ATMActor:
    """The trained actor as a plain ATMActor (its own copy of the weights), checked to fly BenchMARL's
    deterministic actions on random observations (CheckpointError if not): the exported file's
    `Policy.act` clips to_acceleration(actor(obs)) to accel_max, as MADDPG's projection onto the action
    box does and as the env does with the unclipped mean of the other algorithms."""
    weights, model = trained_model(experiment)
    actor = ATMActor(model.actor.cfg)
    with weights, torch.no_grad():
        actor.load_state_dict({k: v.detach().clone() for k, v in model.actor.state_dict().items()})
    actor.eval()
    generator = torch.Generator().manual_seed(cfg.seed)
    probe = torch.rand(4, task.n_agents, actor.cfg.obs_dim, generator=generator) * 4.0 - 1.0
    ours = torch.from_numpy(actor.deterministic_actions(probe.numpy()))
    limit = task.accel_max  # what the env does with any action: IndependentNormal's mean is not clipped
    theirs = deterministic_actions(experiment, probe).clamp(-limit, limit)
    if not torch.allclose(ours, theirs, atol=1e-4, rtol=1e-4):
        raise CheckpointError(
            f"the exported actor's actions differ from BenchMARL's policy's by {(ours - theirs).abs().max():.3g}"
        )
    return actor


# ---------------------------------------------------------------------------- training
def checkpoints(run_dir: Path) -> list[Path]:
    """BenchMARL's checkpoints of a run folder, newest (most frames) first."""
    found = Path(run_dir).glob("*/checkpoints/checkpoint_*.pt")
    return sorted(found, key=lambda p: int(p.stem.split("_")[-1]), reverse=True)


def readable_checkpoint(run_dir: Path) -> tuple[Path, dict]:
    """(the newest checkpoint that loads, its counters): BenchMARL writes checkpoints in place, so a run
    killed while writing one leaves it torn; the one before it (BenchMARL keeps two) is used then."""
    for path in checkpoints(run_dir):
        try:
            state = safe_torch_load(path)["state"]
        except (CheckpointError, KeyError):  # a torn file (BenchMARL writes in place) or not its checkpoint
            continue
        return path, dict(state)
    raise CheckpointError(f"--resume: no readable BenchMARL checkpoint in {run_dir}")


def _resumed_rows(path: Path, frames: int) -> list[dict]:
    """progress.csv's rows up to the checkpoint's `frames` (later ones were lost with the interrupted
    part), with their numbers; the file is rewritten to those rows."""
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        fields = reader.fieldnames or []
        rows = [
            {k: float(v) if k not in ("iteration", "frames", "episodes") else int(v) for k, v in r.items()}
            for r in reader
        ]
    rows = [r for r in rows if r["frames"] <= frames]
    lines = [",".join(fields)] + [",".join(str(r[k]) for k in fields) for r in rows]
    write_atomic(path, "\n".join(lines) + "\n")
    return rows


FREE_ON_RESUME = ("budget_frames", "checkpoint_every", "eval_episodes", "threads")
"""Settings a resumed run may change."""


def train_formation(
    cfg: FormationBenchMARLConfig,
    out_dir: Path,
    policies_dir: Path | None = None,
    resume: bool = False,
    show_progress: bool = True,
    command: str | None = None,
) -> dict:
    """Train cfg.algorithm with BenchMARL on the formation task under cfg.budget_frames, export the actor
    as <policies_dir>/<name>.pt (default <out_dir>/policies/) with its model card; returns the card.

    <out_dir>/<name>/ holds our config.json and progress.csv beside BenchMARL's folder (csv logs,
    config.pkl, checkpoints/). resume: continue the run there from its newest checkpoint (networks,
    optimizers, replay buffer, counters, exploration noise, the env's batch counter and torch's RNG);
    the episodes in flight at the checkpoint are not restored, so a resumed run is not bit-identical
    to an uninterrupted one. A larger budget on resume trains further."""
    out_dir, policies_dir, run_dir = run_folders(out_dir, policies_dir, cfg.name)
    task = cfg.task()
    found = checkpoints(run_dir) if run_dir.is_dir() else []
    if found and not resume:
        raise ConfigError(f"{run_dir} already holds a run; pass --resume to continue it, or choose another --out")
    checkpoint = None
    if resume:
        if not found:
            raise ConfigError(f"--resume: no run to continue in {run_dir} (no BenchMARL checkpoint); drop --resume")
        saved = json.loads((run_dir / "config.json").read_text())["benchmarl"]
        run_state.check_same_run(saved, cfg, run_dir / "config.json", free=FREE_ON_RESUME)
        checkpoint, restored = readable_checkpoint(run_dir)
        if restored["total_frames"] > cfg.budget_frames:
            raise ConfigError(
                f"--budget {cfg.budget_frames}: the run in {run_dir} has trained "
                f"{restored['total_frames']} frames already"
            )
    run_dir.mkdir(parents=True, exist_ok=True)
    policies_dir.mkdir(parents=True, exist_ok=True)
    versions = benchmarl_versions()
    write_atomic(
        run_dir / "config.json",
        json.dumps(
            {"benchmarl": cfg.to_dict(), "task": task.to_dict(), "versions": versions, "command": command}, indent=2
        )
        + "\n",
    )
    rows = _resumed_rows(run_dir / "progress.csv", restored["total_frames"]) if resume else []
    progress = Progress(run_dir / "progress.csv", cfg.reward_scale, metrics=METRICS, rows=rows)
    with torch_threads(cfg.threads):
        experiment, settings = build_experiment(cfg, run_dir, callbacks=[progress], restore_file=checkpoint)
        wall = run_experiment(experiment, show_progress)
        actor = export_actor(experiment, cfg, task)
    frames = int(experiment.total_frames)
    policy_path = save_policy(
        actor,
        policies_dir / f"{cfg.name}.pt",
        meta={
            "name": cfg.name,
            "method": METHODS[cfg.algorithm],
            "trainer": f"benchmarl-{cfg.algorithm}",
            "formation": cfg.formation,
            "seed": cfg.seed,
            "iterations": experiment.n_iters_performed,
            "agent_steps": frames * cfg.formation,
        },
    )
    train_s = float(experiment.total_time)  # BenchMARL's iteration time, summed across resumes
    card = {
        "name": cfg.name,
        "method": METHODS[cfg.algorithm],
        "algorithm": cfg.algorithm,
        "trainer": "BenchMARL",
        "formation": cfg.formation,
        "step": cfg.step,
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "benchmarl_settings": settings,
        "task": task.to_dict(),
        "network": actor.cfg.to_dict(),
        "critic": f"BenchMARL MLP {list(cfg.critic_cells)}, tanh, on the global state"
        + (" and every agent's action" if cfg.algorithm in ("maddpg", "masac") else ""),
        "init": {"actor": "random", "critic": "random"},
        "iterations": experiment.n_iters_performed,
        "frames": frames,
        "agent_steps": frames * cfg.formation,
        "train_wall_clock_s": round(train_s, 1),
        "this_process_wall_clock_s": round(wall, 1),
        "agent_steps_per_s": round(frames * cfg.formation / train_s, 1) if train_s else None,
        "threads": cfg.threads,
        "resumed": bool(resume),
        **card_tail(experiment, run_dir, versions, command, progress),
    }
    if cfg.eval_episodes:
        card["validation"] = validation_figures(policy_path, cfg)
    write_model_card(policy_path, card)
    return card


def validation_figures(policy_path: Path, cfg: FormationBenchMARLConfig) -> dict:
    """Table III's protocol (density 0.05, 100 steps) of the exported file on the validation batch
    FORMATION_VALIDATION_SEED (cfg.eval_episodes episodes), with the paper's row where it has one."""
    return table3_figures(
        policy_path,
        cfg.formation,
        TABLE3_METHOD.get(cfg.algorithm),
        seed=FORMATION_VALIDATION_SEED,
        episodes=cfg.eval_episodes,
    )


def summary_lines(card: dict, policies_dir: Path) -> list[str]:
    """What `cefc-train formation-benchmarl` prints when a run ends."""
    lines = [
        f"{card['name']}: BenchMARL {card['algorithm']}, c = {card['formation']}, {card['iterations']} iterations, "
        f"{card['frames']} frames ({card['agent_steps']} agent-steps), {card['train_wall_clock_s']} s, "
        f"{card['agent_steps_per_s']} agent-steps/s on {card['threads']} thread(s) -> "
        f"{policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})"
    ]
    if "validation" in card:
        o, p = card["validation"]["ours"], card["validation"]["protocol"]
        lines.append(
            f"validation (Table III protocol, {p['episodes']} episodes, seed {p['seed']}): R_L {o['R_L']:.2f}  "
            f"F {o['F']:.2f}  N {o['N']:.2f}  C {o['C']:.2f}%"
        )
    return lines
