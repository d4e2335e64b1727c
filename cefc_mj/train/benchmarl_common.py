"""What the BenchMARL tasks of this project share (the high-level game, `cefc_mj.train.benchmarl_game`,
and the formation task, `cefc_mj.train.benchmarl_formation`). Needs the optional `benchmarl` extra.

- `GROUP`, `group_spec`, `done_spec`, `reward_spec`, `env_output`, `reset_mask`, `SeededBatchEnv`: the
  pieces of a batched torchrl env over one of our batched envs (one group "agents", an episode's end
  as `done` = `terminated`, the k-th full reset playing the episodes of `iteration_seed(seed, k)`).
- `CEFCTaskBase`: the BenchMARL `TaskClass` methods both tasks answer alike (one group, the global
  state for centralised critics, no render, no info or action mask).
- `experiment_settings`: the `ExperimentConfig` values both tasks set (CPU, shared actor, no
  BenchMARL evaluation, csv logs), the rest left at BenchMARL 1.5.2's defaults.
- `Progress`: a callback writing progress.csv (frames, episodes, mean return, wall-clock, and any
  per-episode metrics the env reports at an episode's end).
- `build`, `run_folders`, `torch_threads`, `run_experiment`, `trained_weights`, `tanh_mlp`,
  `card_tail`: the steps of a training run both tasks take alike.
- `progress_bar`, `benchmarl_versions`.
"""

from __future__ import annotations

import contextlib
import csv
import math
import time
from pathlib import Path

import numpy as np
import torch
from benchmarl.environments import TaskClass
from benchmarl.experiment.callback import Callback
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from cefc_mj.provenance import display_path
from cefc_mj.train.rollout import iteration_seed

GROUP = "agents"
"""The one agent group of every task (BenchMARL's group name)."""
PROGRESS_FIELDS = (
    "iteration",
    "frames",
    "episodes",
    "episode_return",
    "wall_s",
    "collection_s",
    "training_s",
    "s_per_episode",
)
"""progress.csv's columns (a task's episode metrics follow them)."""


def benchmarl_versions() -> dict[str, str]:
    """Versions of BenchMARL and the libraries under it."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in ("benchmarl", "torchrl", "tensordict", "hydra-core", "omegaconf", "torch"):
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    return out


# ---------------------------------------------------------------------------- env pieces
def done_spec(n_envs: int, device) -> Composite:
    """done, terminated, truncated [n_envs, 1] bool: an episode's end is `done` = `terminated`, as our
    trainers treat it (no bootstrap past it); never `truncated`."""
    return Composite(
        {
            key: Categorical(2, shape=(n_envs, 1), dtype=torch.bool, device=device)
            for key in ("done", "terminated", "truncated")
        },
        shape=(n_envs,),
    )


def reset_mask(tensordict: TensorDictBase | None):
    """The envs a torchrl `_reset` asks to restart, as a numpy bool [B], or None for all of them."""
    if tensordict is None or "_reset" not in tensordict.keys():
        return None
    mask = tensordict.get("_reset").reshape(-1).cpu().numpy().astype(bool)
    return None if mask.all() else mask


def group_spec(n_envs: int, n_agents: int, key: str, leaf, **root) -> Composite:
    """A spec [n_envs] holding `leaf` [n_envs, n_agents, ...] as (GROUP, key), beside the `root` entries."""
    return Composite({GROUP: Composite({key: leaf}, shape=(n_envs, n_agents)), **root}, shape=(n_envs,))


def reward_spec(n_envs: int, n_agents: int, device) -> Composite:
    """reward [n_envs, n_agents, 1] float32: each agent's reward in the group."""
    return group_spec(n_envs, n_agents, "reward", Unbounded((n_envs, n_agents, 1), dtype=torch.float32, device=device))


def env_output(
    observation: torch.Tensor, state: torch.Tensor, done: np.ndarray | None, n_envs: int, n_agents: int, device, **root
) -> TensorDict:
    """What a reset or step returns: the agents' observations [n_envs, n_agents, ...], the global state,
    the `root` entries, done and terminated (the env's `done` [n_envs]; all False after a reset) and
    truncated (never)."""
    done_t = torch.zeros((n_envs, 1), dtype=torch.bool) if done is None else torch.as_tensor(done).reshape(n_envs, 1)
    return TensorDict(
        {
            GROUP: TensorDict({"observation": observation}, batch_size=(n_envs, n_agents)),
            "state": state,
            **root,
            "done": done_t.clone(),
            "terminated": done_t.clone(),
            "truncated": torch.zeros((n_envs, 1), dtype=torch.bool),
        },
        batch_size=(n_envs,),
        device=device,
    )


class SeededBatchEnv(EnvBase):
    """A torchrl env over one of our batched envs (`batched_env()`, with `reset(seed=)` and
    `reset(mask)`): the k-th full reset plays the episodes of `iteration_seed(run_seed, k)`, the
    episodes our trainers play at iteration k; a partial reset restarts the masked envs. Subclasses set
    `run_seed` and `resets` (0) and give `batched_env` and `_observation(obs)`."""

    batch_locked = True

    def batched_env(self):
        raise NotImplementedError

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = reset_mask(tensordict)
        if mask is None:  # a new batch of episodes: those of iteration_seed(seed, k)
            obs = self.batched_env().reset(seed=iteration_seed(self.run_seed, self.resets))
            self.resets += 1
        else:
            obs = self.batched_env().reset(mask)
        return self._observation(obs)

    def _set_seed(self, seed: int | None) -> None:
        """Restart the episodes from iteration_seed(seed, 0) at the next full reset."""
        self.run_seed, self.resets = (0 if seed is None else int(seed)), 0


class CEFCTaskBase(TaskClass):
    """A BenchMARL task over one of our torchrl envs; `config` is the run config's `to_dict()` with an
    `n_agents` entry. Subclasses give get_env_fun, the action kinds, max_steps and env_name."""

    def has_render(self, env: EnvBase) -> bool:
        return False

    def group_map(self, env: EnvBase) -> dict[str, list[str]]:
        return {GROUP: [f"uav_{i}" for i in range(self.config["n_agents"])]}

    def observation_spec(self, env: EnvBase) -> Composite:
        """The agents' observations (the env's observation spec without the global state and metrics)."""
        spec = env.full_observation_spec_unbatched.clone()
        for key in list(spec.keys()):
            if key != GROUP:
                del spec[key]
        return spec

    def info_spec(self, env: EnvBase):
        return None

    def state_spec(self, env: EnvBase) -> Composite:
        return Composite({"state": env.full_observation_spec_unbatched["state"].clone()})

    def action_spec(self, env: EnvBase) -> Composite:
        return env.full_action_spec_unbatched.clone()

    def action_mask_spec(self, env: EnvBase):
        return None

    @staticmethod
    def env_name() -> str:
        return "cefc"


# ---------------------------------------------------------------------------- the experiment
def experiment_settings(run_dir: Path, gamma: float, lr: float, max_frames: int, frames_per_batch: int, n_envs: int):
    """ExperimentConfig values every run sets: the CPU, one actor shared by the group, sequential
    collection, `frames_per_batch` frames from `n_envs` envs per iteration (on- and off-policy alike),
    no BenchMARL evaluation (the model card evaluates the exported policy with our own evaluator), csv
    logs under run_dir, no checkpoints (a resumable task sets its own)."""
    return {
        "sampling_device": "cpu",
        "train_device": "cpu",
        "buffer_device": "cpu",
        "share_policy_params": True,
        "parallel_collection": False,
        "gamma": gamma,
        "lr": lr,
        "max_n_iters": None,
        "max_n_frames": max_frames,
        "on_policy_collected_frames_per_batch": frames_per_batch,
        "on_policy_n_envs_per_worker": n_envs,
        "off_policy_collected_frames_per_batch": frames_per_batch,
        "off_policy_n_envs_per_worker": n_envs,
        "evaluation": False,
        "render": False,
        "evaluation_episodes": 1,  # BenchMARL builds its test env (used for specs only) with this many envs
        "loggers": ["csv"],
        "create_json": False,
        "save_folder": str(run_dir),
        "checkpoint_interval": 0,
        "checkpoint_at_end": False,
    }


def tanh_mlp(cells) -> object:
    """BenchMARL's MLP model config with hidden layers `cells`, linear layers and tanh."""
    from benchmarl.models.mlp import MlpConfig

    return MlpConfig(num_cells=list(cells), layer_class=torch.nn.Linear, activation_class=torch.nn.Tanh)


def experiment_config(settings: dict):
    """BenchMARL's ExperimentConfig (its yaml defaults) with `settings` set."""
    from benchmarl.experiment import ExperimentConfig

    exp = ExperimentConfig.get_from_yaml()
    for key, value in settings.items():
        setattr(exp, key, value)
    return exp


def build(task, algorithm, actor, critic_cells, seed: int, settings: dict, callbacks) -> tuple[object, dict]:
    """BenchMARL's Experiment of `task` with the `algorithm` and `actor` model configs, a tanh MLP
    critic of `critic_cells`, the ExperimentConfig `settings` and `callbacks`; returns (the experiment,
    the record of its settings for the model card: the ExperimentConfig values but restore_file, and
    the algorithm's)."""
    from benchmarl.experiment import Experiment

    experiment = Experiment(
        task=task,
        algorithm_config=algorithm,
        model_config=actor,
        critic_model_config=tanh_mlp(critic_cells),
        seed=seed,
        config=experiment_config(settings),
        callbacks=list(callbacks),
    )
    recorded = {k: v for k, v in settings.items() if k != "restore_file"}
    return experiment, {"experiment": recorded, "algorithm": dict(algorithm.__dict__)}


class Progress(Callback):
    """Writes <run_dir>/progress.csv: per iteration the frames, episodes, mean episode return (summed
    over the episode, averaged over the agents and the episodes that ended, divided by the reward
    scale back to the task's units), the wall-clock of collection and training, and the mean of each
    of `metrics` (root keys of the env's output, read at the steps that end an episode).

    `rows`: the rows of an earlier part of the same run (a resumed run appends to its file)."""

    def __init__(self, path: Path, reward_scale: float = 1.0, metrics: tuple[str, ...] = (), rows=None):
        super().__init__()
        self.path, self.reward_scale, self.metrics = Path(path), reward_scale, tuple(metrics)
        self.fields = PROGRESS_FIELDS + self.metrics
        self.rows: list[dict] = list(rows or [])
        self.start = self.collected = self.trained = None

    def on_setup(self):
        self.start = self.collected = time.perf_counter()
        if not self.rows:
            with self.path.open("w", newline="") as f:
                csv.DictWriter(f, self.fields).writeheader()

    def on_batch_collected(self, batch: TensorDictBase):
        now = time.perf_counter()
        done = batch.get(("next", "done")).reshape(-1)
        returns = batch.get(("next", GROUP, "episode_reward")).mean(dim=(-2, -1)).reshape(-1)[done]
        self.pending = {
            "episodes": int(done.sum()),
            "episode_return": float(returns.mean()) / self.reward_scale if len(returns) else math.nan,
            "collection_s": now - (self.trained or self.start),
            "frames": int(batch.numel()),
        }
        for name in self.metrics:
            ended = batch.get(("next", name)).reshape(-1)[done]
            self.pending[name] = float(ended.mean()) if len(ended) else math.nan
        self.collected = now

    def on_train_end(self, training_td: TensorDictBase, group: str):
        now = time.perf_counter()
        self.trained = now
        previous = self.rows[-1] if self.rows else {"frames": 0, "episodes": 0, "wall_s": 0.0}
        row = {
            "iteration": len(self.rows) + 1,
            "frames": previous["frames"] + self.pending["frames"],
            "episodes": previous["episodes"] + self.pending["episodes"],
            "episode_return": self.pending["episode_return"],
            "collection_s": self.pending["collection_s"],
            "training_s": now - self.collected,
            **{name: self.pending[name] for name in self.metrics},
        }
        row["wall_s"] = float(previous["wall_s"]) + row["collection_s"] + row["training_s"]
        row["s_per_episode"] = (row["collection_s"] + row["training_s"]) / max(1, self.pending["episodes"])
        self.rows.append(row)
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, self.fields).writerow(row)


def progress_bar(show: bool):
    """A context in which BenchMARL's iteration bar is shown, or not (it reads no flag of its own)."""
    import contextlib
    import functools
    from unittest import mock

    from benchmarl.experiment import experiment as module

    if show:
        return contextlib.nullcontext()
    return mock.patch.object(module, "tqdm", functools.partial(module.tqdm, disable=True))


# ---------------------------------------------------------------------------- a training run
def run_folders(out_dir: Path, policies_dir: Path | None, name: str) -> tuple[Path, Path, Path]:
    """(out_dir, policies_dir (default <out_dir>/policies), the run folder <out_dir>/<name>) as Paths."""
    out_dir = Path(out_dir)
    policies_dir = Path(policies_dir) if policies_dir is not None else out_dir / "policies"
    return out_dir, policies_dir, out_dir / name


@contextlib.contextmanager
def torch_threads(threads: int):
    """A context in which torch uses `threads` threads (the number before is restored after)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def run_experiment(experiment, show_progress: bool) -> float:
    """Run a BenchMARL Experiment to its budget (its bar shown or not); returns the wall-clock in s."""
    start = time.perf_counter()
    with progress_bar(show_progress):
        experiment.run()
    return time.perf_counter() - start


def trained_weights(experiment):
    """A context that loads the trained actor weights into the group's actor network: the weights the
    optimizers update are the loss module's actor parameters."""
    loss = experiment.losses[GROUP]
    return loss.actor_network_params.to_module(loss.actor_network)


def card_tail(experiment, run_dir: Path, versions: dict, command: str | None, progress: Progress) -> dict:
    """The model card's last entries, alike for both tasks: versions, folders, command, last iteration."""
    return {
        "benchmarl_versions": versions,
        "benchmarl_folder": display_path(Path(experiment.folder_name)),
        "run_dir": display_path(run_dir),
        "command": command,
        "last_iteration": progress.rows[-1] if progress.rows else {},
    }
