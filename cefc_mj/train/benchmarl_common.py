"""What the BenchMARL tasks of this project share (the high-level game, `cefc_mj.train.benchmarl_game`,
and the formation task, `cefc_mj.train.benchmarl_formation`). Needs the optional `benchmarl` extra.

- `GROUP`, `done_spec`, `reset_mask`: the pieces of a batched torchrl env over one of our batched
  envs (one group "agents", an episode's end as `done` = `terminated`).
- `CEFCTaskBase`: the BenchMARL `TaskClass` methods both tasks answer alike (one group, the global
  state for centralised critics, no render, no info or action mask).
- `experiment_settings`: the `ExperimentConfig` values both tasks set (CPU, shared actor, no
  BenchMARL evaluation, csv logs), the rest left at BenchMARL 1.5.2's defaults.
- `Progress`: a callback writing progress.csv (frames, episodes, mean return, wall-clock, and any
  per-episode metrics the env reports at an episode's end).
- `progress_bar`, `benchmarl_versions`.
"""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path

import torch
from benchmarl.environments import TaskClass
from benchmarl.experiment.callback import Callback
from tensordict import TensorDictBase
from torchrl.data import Categorical, Composite
from torchrl.envs import EnvBase

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


def experiment_config(settings: dict):
    """BenchMARL's ExperimentConfig (its yaml defaults) with `settings` set."""
    from benchmarl.experiment import ExperimentConfig

    exp = ExperimentConfig.get_from_yaml()
    for key, value in settings.items():
        setattr(exp, key, value)
    return exp


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
