"""The high level's training (paper Sec. IV-C3, Algorithm 2): MAPPO anchor selection over ConsMAC.

One iteration, CleanRL-style:

1. **Collect** `n_envs x episodes_per_iteration` whole episodes of the hierarchical game
   (`cefc_mj.hierarchy`, 40 decisions of 10 low-level steps each). At every decision agent i
   receives its neighbours' messages of the previous decision (`MessageChannel`: one step late,
   true distance < 3 m), ConsMAC turns [o_i, own message, inbox] into m_i^(t+1) and g_hat_i, the
   message is sent, and the selector samples an anchor from (o_i, m_i^(t+1)) with the message
   detached (eq. 12). ConsMAC's inputs and the label g_i (ConsMAC-A: every agent's anchor of this
   decision; ConsMAC-O: every other agent's relative position and velocity) go to the replay B_C.
2. **RL update** of the selector Theta_H and the critic phi_H: PPO epochs over the iteration's
   decisions with the low level's PPO pieces (`cefc_mj.train.ppo`: GAE, clipped surrogate, value
   normalisation) and `PPOConfig`. Every agent learns from the team reward R_H summed over the 10
   low-level steps; the critic is V(s, o_i) (global state plus the agent's observation, MAPPO's
   agent-specific state), 3 layers of 128. The RL loss never reaches ConsMAC: the consensus input is
   stored detached and the selector detaches it again.
3. **ConsMAC update** (every `consmac_every` iterations): `consmac_steps` Adam steps on batches of
   `consmac_batch` tuples drawn from B_C, loss eq. (11).

Algorithm 2 pre-trains with a navigation-only low level and then fine-tunes with the trained one:
the first `pretrain_share` of the budget flies `NavigationOnly`, the rest `low_level` (default the
distilled student); networks, optimizers and the critic carry over. Variants: consmac-a, consmac-o
(the paper), mappo (no communication: the selector reads o_i only), tarmac (the TarMAC baseline:
the same communication module, its messages trained end to end by the RL loss instead of eq. (11):
in the update each receiver's inbox is recomputed, with gradients, from its senders' stored inputs
of the previous decision, so the PPO loss of decision t reaches the network that sent the messages
read at t; the senders' own inboxes are taken as stored, a one-step truncation of TarMAC's
backpropagation through time), masia and nvif (the paper's other communication baselines,
`cefc_mj.nn.obs_comm`: they send the raw local observation, MASIA alone and NVIF after a
variational latent, and their modules learn from their own supervised losses in the ConsMAC
update's place and schedule, MASIA's reconstructing the global state and NVIF's the local
observations; the RL loss never reaches them). `ablation` (consmac variants only) selects one of the paper's
Fig. 7 ablations of ConsMAC (`cefc_mj.nn.consmac.ABLATIONS`); "wt-rl" also lets the PPO loss into
ConsMAC, whose optimizer then steps on both losses.

    run folder   <out>/<name>/   config.json, progress.csv, tb/, state.pt (resumable)
    policy file  <policies_dir>/<name>.pt  + <name>.json model card      name = cihrl_<variant>[_<ablation>]

Every iteration's episodes are seeded from (seed, iteration) and `state.pt` holds networks,
optimizers, value normalisation, the torch RNG, counters and the replay, so `--resume` continues a
run as if it had not stopped.
"""

from __future__ import annotations

import copy
import csv
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.eval.highlevel import GAME_ADVERSARY, evaluate_highlevel, resolve_adversary
from cefc_mj.fileio import write_atomic
from cefc_mj.hierarchy import (
    CLM_PER_GROUP,
    DECISION_INTERVAL,
    NAVIGATION,
    HierarchicalCEFCEnv,
    LowLevel,
    load_low_level,
)
from cefc_mj.nn.atm import Critic
from cefc_mj.nn.consmac import ABLATIONS, ConsMACConfig, global_labels, seeded
from cefc_mj.nn.consmac_grad import fused_supported, supervised_grads
from cefc_mj.nn.highlevel_policy import (
    CONSMAC_VARIANTS,
    SUPERVISED_VARIANTS,
    VARIANTS,
    HighLevelPolicy,
    load_highlevel_policy,  # noqa: F401  (re-exported: tests/test_highlevel.py)
    save_highlevel_policy,
)
from cefc_mj.nn.policy_io import atomic_torch_save
from cefc_mj.nn.registry import HIERARCHY_LOWLEVEL
from cefc_mj.nn.selector import build_critic
from cefc_mj.task.config import ADVERSARY_RULES, LEARNED_ADVERSARY, TaskConfig
from cefc_mj.task.messages import MessageChannel
from cefc_mj.train import run_state
from cefc_mj.train.config import MAX_DENSITY, MAX_SEED, Budget, BudgetPPODict, PPOConfig, config_from_flags
from cefc_mj.train.logger import RunLogger
from cefc_mj.train.mappo import iteration_seed
from cefc_mj.train.model_card import display_path, display_paths, write_model_card
from cefc_mj.train.ppo import ValueNorm, advantages_and_targets, ppo_epochs
from cefc_mj.train.run_state import STATE_FILE

METHODS = {
    "consmac-a": "CI-HRL (ConsMAC-A)",
    "consmac-o": "CI-HRL (ConsMAC-O)",
    "mappo": "MAPPO high level, no communication",
    "tarmac": "TarMAC: attention-based communication, messages trained end to end by RL (one-step truncation)",
    "masia": "MASIA+AT-M: raw local observations sent, aggregated by attention, decoded to the global state",
    "nvif": "NVIF+AT-M: a variational latent and the raw local observation sent, a VAE of local observations",
}
COMMUNICATION = {
    "consmac-a": ("m_i^(t+1)", "eq. (11): squared error of g_hat_i to every agent's anchor (ConsMAC-A)"),
    "consmac-o": ("m_i^(t+1)", "eq. (11): squared error of g_hat_i to the others' relative positions and velocities"),
    "tarmac": ("m_i^(t+1)", "the PPO loss, end to end through the received messages"),
    "masia": (
        "o_i, the sender's local observation (unscaled)",
        "supervised: z_i's decoder reconstructs the global state (ConsMAC-O's label); MASIA's latent "
        "future prediction is left out",
    ),
    "nvif": (
        "[mu_i || o_i]: the variational latent's mean (64) and the sender's local observation (38, unscaled)",
        "VAE: a sample of z_i reconstructs the own and the received local observations, plus kl_weight x KL to N(0, I)",
    ),
}
"""The model card's message content and what trains the communication module, per variant."""
ABLATION_METHODS = {
    "wo-com": "without communication (wo-Com: no message received)",
    "wo-mem": "without memory (wo-Mem: the GRU's hidden input is zero at every decision)",
    "wo-de": "without distance encoder (wo-DE: distance codes are zeros)",
    "wt-rl": "with the RL loss (wt-RL: ConsMAC trained by eq. (11) and the PPO loss)",
    "consmac-g": "ConsMAC-G (the estimate g_hat is sent as the message)",
}
"""The model card's method suffix of each of ConsMAC's ablations (paper Fig. 7)."""
TARMAC_MESSAGES = "end-to-end-1step"
"""How the tarmac variant trains its messages (saved in its resumable state, checked on --resume): the
PPO loss reaches the senders through the inbox recomputed from their previous decision's inputs.
States written before this had no gradient through received messages."""
PHASES = ("pretrain", "finetune")
PAPER_CONSMAC = {"every_episodes": 20, "steps": 5000, "batch": 2048}
SCHEDULES = {
    "short": {
        "iterations": 75,
        "n_envs": 20,
        "pretrain_share": 2 / 3,
        "consmac_every": 1,
        "consmac_steps": 200,
        "consmac_batch": 2048,
    },
    "paper": {
        "iterations": 1500,
        "n_envs": 20,
        "pretrain_share": 2 / 3,
        "consmac_every": 20,
        "consmac_steps": 5000,
        "consmac_batch": 2048,
    },
}
"""Two readings of the paper's training budget (Sec. V-A: the high level "is updated for 1,000
episodes during pre-training and 500 episodes during fine-tuning", data "collected in 20 threads",
and "after every 20 episodes of interaction, the collected data are utilized to train ConsMAC for
5,000 times with a batch size of 2,048"). "paper": one episode of the training loop is one rollout
in each of the 20 envs followed by one update, as in the on-policy MAPPO code base the paper
follows, so 1,500 iterations of 20 envs (1,000 pre-training), ConsMAC 5,000 steps after every 20
iterations. "short": the project's first reading, 1,500 games in all (75 iterations of 20 envs)
with 200 ConsMAC steps after each iteration; the shipped high levels were trained so. Under "paper"
every number here is fixed; "short" only names the defaults, which flags may change."""
"""Algorithm 2's ConsMAC schedule (paper Sec. V-A), recorded beside what a run did."""
STATE_FORMAT = "cefc-mj/highlevel-state"
PROGRESS_KEYS = ("episode_return", "metric/E", "consmac_loss", "approx_kl")
CONSMAC_KEYS = ("consmac_loss", "consmac_loss_first", "consmac_loss_last", "consmac_steps", "replay_size")
MAX_REPLAY = 1_000_000
"""Most ConsMAC replay tuples (about 2.5 GB)."""


def _paper_ppo() -> PPOConfig:
    return PPOConfig(epochs=15, lr=1e-4, entropy_coef=0.01)


def _fail(name: str, value: object, why: str) -> None:
    raise ConfigError(f"{name}={value!r}: {why}")


def _check_int(name: str, value: object, least: int, most: int | None = None) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < least or (most is not None and value > most):
        _fail(name, value, f"must be an integer >= {least}" + (f" and <= {most}" if most is not None else ""))


@dataclass(frozen=True)
class HighLevelConfig(BudgetPPODict):
    """One high-level training run (Algorithm 2). Defaults are the paper's where it gives a value
    (Sec. V-A); `consmac_steps` is scaled to a 2-core budget (docs/high_level.md)."""

    budget: Budget
    """Iterations (each: n_envs x episodes_per_iteration episodes, then the updates) and/or
    wall-clock time, counted across resumes. The paper's 1000 + 500 episodes are 75 iterations of 20;
    the shipped high levels ran those 75 and were continued with --resume to 150 (docs/decisions.md)."""
    variant: str = "consmac-a"
    """consmac-a / consmac-o: ConsMAC with the anchors / the observations of all agents as labels;
    mappo: no communication; tarmac: the communication module trained end to end by the RL loss;
    masia / nvif: the paper's baselines that send the raw local observation (38 / 102 numbers),
    trained by their own supervised losses (`cefc_mj.nn.obs_comm`)."""
    ablation: str = "none"
    """One of the paper's Fig. 7 ablations of ConsMAC (consmac variants only): none, wo-com (no message
    received), wo-mem (no GRU memory), wo-de (no distance encoder), wt-rl (the RL loss reaches ConsMAC
    too), consmac-g (the estimate g_hat is sent as the message); see `cefc_mj.nn.consmac`."""
    seed: int = 0
    """Seeds network init, anchor sampling, minibatches, replay sampling and every iteration's episodes."""
    n_agents: int = 8
    """N, UAVs in the game (paper: 8; the shipped low levels read at most 7 neighbours, so N <= 8)."""
    obstacle_density: float = 0.03
    """Obstacles per m^2 in the game (the density the low level was trained at; the paper's CEFC
    space is obstacle-cluttered but gives no density for it)."""
    adversary: str = GAME_ADVERSARY
    """The game's adversary during training (default the shipped PPO adversary, the opponent of Tables
    V and VII, trained against a population of teams and at least as strong as the rules: docs/decisions.md):
    a rule (TaskConfig.adversary: nearest_group, r_nearest, r_largest, none) or a trained adversary's
    policy name (in the shipped folder) or file (`cefc-train adversary`)."""
    episode_steps: int = 400
    """Low-level steps per episode (paper: 400); a multiple of decision_interval."""
    decision_interval: int = DECISION_INTERVAL
    """Low-level steps per high-level decision (paper: 10)."""
    low_level: str = HIERARCHY_LOWLEVEL
    """The fine-tuning low level: a policy name or file (default the distilled student),
    'per-group' (the AT-M teacher atm_c{c}_step3 of each agent's group size) or 'clm-per-group' (the
    CL-M policy clm_c{c} of each agent's group size: the paper's CI-HRL-w-CL-M)."""
    pretrain_share: float = 2 / 3
    """Share of the budget flown with the navigation-only low level before fine-tuning with
    `low_level` (paper: 1000 of 1500 episodes); 0 trains with `low_level` only (CI-HRL-DT)."""
    consmac_every: int = 1
    """ConsMAC trains after every this many iterations (1 with 20 envs: every 20 episodes, the paper's)."""
    consmac_steps: int = 200
    """Adam steps per ConsMAC round (paper: 5000; one step of batch 2048 costs 50-200 ms on a shared
    2-core CPU, so 5000 would be 98 % of a run)."""
    consmac_batch: int = 2048
    """Tuples per ConsMAC step (paper: 2048), drawn uniformly with replacement from the replay."""
    consmac_lr: float = 1e-4
    """ConsMAC's Adam learning rate (paper: 1e-4). The selector reads ConsMAC's messages, so every
    round moves its input; at 1e-3 (Adam's steps scale with the rate) the selector learned to evade
    worse (docs/decisions.md)."""
    replay_capacity: int = 50_000
    """Tuples (agent-decisions) the replay B_C keeps, newest first out last (about 8 iterations of
    20 envs; 2.5 KB each)."""
    hidden: int = 128
    """Hidden width of the selector's encoder and head (paper: 128)."""
    critic_hidden: int = 128
    """Hidden width of the 3-layer critic V_phiH (paper: 128)."""
    ppo: PPOConfig = field(default_factory=_paper_ppo)
    """MAPPO hyperparameters of the selector and critic: the paper's 15 epochs and Adam 1e-4, gamma
    0.8 per decision, and MAPPO's entropy bonus 0.01 (collision_credit is unused: R_H is a team reward)."""
    checkpoint_every: int = 5
    """Write the resumable state every this many iterations (and always at the end)."""
    eval_episodes: int = 20
    """Episodes of the final policy (the mode of each anchor distribution, the fine-tuning low level)
    whose mean rewards the model card reports; 0 skips the evaluation."""
    schedule: str = "short"
    """Which reading of the paper's budget the run follows (SCHEDULES): "short" (the default and the
    shipped runs': its numbers are the other fields' defaults, free to change) or "paper" (1,500
    iterations of 20 envs, 1,000 of them pre-training, ConsMAC 5,000 steps of 2,048 after every 20;
    those fields must then hold exactly the paper's values). Runs saved before this field existed
    load as "short"."""

    def __post_init__(self) -> None:
        if isinstance(self.pretrain_share, int) and not isinstance(self.pretrain_share, bool):
            object.__setattr__(self, "pretrain_share", float(self.pretrain_share))
        self.validate()

    # ------------------------------------------------------------------ derived
    @property
    def name(self) -> str:
        """Run folder and policy file stem: cihrl_<variant> (cihrl_consmac_a, cihrl_consmac_o, cihrl_mappo,
        cihrl_tarmac, cihrl_masia, cihrl_nvif), then _<ablation> for an ablation of ConsMAC
        (cihrl_consmac_a_wo_com, ..._wo_mem, ..._wo_de, ..._wt_rl, ..._consmac_g), _dt for direct training
        (no pre-training, the paper's CI-HRL-DT), _<low level> for a fine-tuning low level other than
        the student (_clm for clm-per-group, the paper's CI-HRL-w-CL-M; _per_group; a file's stem) and
        _seed<k> for seeds other than 0, so the runs of a comparison never overwrite each other."""
        low = {CLM_PER_GROUP: "clm"}.get(self.low_level, Path(self.low_level).stem.replace("-", "_"))
        return (
            "cihrl_"
            + self.variant.replace("-", "_")
            + ("" if self.ablation == "none" else "_" + self.ablation.replace("-", "_"))
            + ("" if self.low_level == HIERARCHY_LOWLEVEL else "_" + low)
            + ("_dt" if self.pretrain_share == 0 else "")
            + (f"_seed{self.seed}" if self.seed else "")
        )

    @property
    def supervised(self) -> bool:
        """ConsMAC, MASIA and NVIF: the communication module learns from its supervised loss on the
        replay (eq. (11) for ConsMAC), only, unless wt-rl."""
        return self.variant in SUPERVISED_VARIANTS

    @property
    def rl_into_comm(self) -> bool:
        """The PPO loss reaches the communication module: tarmac, and ConsMAC's wt-rl ablation."""
        return self.variant == "tarmac" or self.ablation == "wt-rl"

    @property
    def decision_steps(self) -> int:
        return self.episode_steps // self.decision_interval

    def task(self) -> TaskConfig:
        adversary = self.adversary if self.adversary in ADVERSARY_RULES else LEARNED_ADVERSARY
        return TaskConfig(
            n_agents=self.n_agents,
            mode="cefc",
            obstacle_density=self.obstacle_density,
            adversary=adversary,
            episode_steps=self.episode_steps,
        )

    def phase(self, iteration: int, seconds: float) -> int:
        """0 (pre-training, navigation-only low level) until `pretrain_share` of the budget is
        spent (iterations or seconds, whichever is further), then 1 (fine-tuning)."""
        share = self.pretrain_share
        if share <= 0:
            return 1
        done = self.budget.iterations is not None and iteration >= math.ceil(share * self.budget.iterations - 1e-9)
        done |= self.budget.seconds is not None and seconds >= share * self.budget.seconds
        return int(done and share < 1)

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        if self.variant not in VARIANTS:
            _fail("variant", self.variant, f"must be one of {', '.join(VARIANTS)}")
        if self.ablation not in ABLATIONS:
            _fail("ablation", self.ablation, f"must be one of {', '.join(ABLATIONS)}")
        if self.ablation != "none" and self.variant not in CONSMAC_VARIANTS:
            _fail(
                "ablation",
                self.ablation,
                f"ablates ConsMAC, so it needs variant consmac-a or consmac-o, not {self.variant!r}",
            )
        if not isinstance(self.budget, Budget):
            _fail("budget", self.budget, "must be a Budget")
        _check_int("seed", self.seed, 0, MAX_SEED)
        _check_int("n_agents", self.n_agents, 2, 8)
        if not isinstance(self.obstacle_density, (int, float)) or not 0 <= self.obstacle_density <= MAX_DENSITY:
            _fail("obstacle_density", self.obstacle_density, f"must be in [0, {MAX_DENSITY}] per m^2")
        if not isinstance(self.adversary, str) or not self.adversary or self.adversary == LEARNED_ADVERSARY:
            _fail(
                "adversary",
                self.adversary,
                f"must be a rule ({', '.join(ADVERSARY_RULES)}) or a trained adversary's policy name or file",
            )
        _check_int("decision_interval", self.decision_interval, 1, 1000)
        _check_int("episode_steps", self.episode_steps, self.decision_interval, 100_000)
        if self.episode_steps % self.decision_interval:
            _fail(
                "episode_steps", self.episode_steps, f"must be a multiple of decision_interval={self.decision_interval}"
            )
        if not isinstance(self.low_level, str) or not self.low_level or self.low_level == NAVIGATION:
            _fail(
                "low_level",
                self.low_level,
                "must name the fine-tuning low level: a policy name or file, 'per-group' or "
                "'clm-per-group' (the navigation-only one is the pre-training's)",
            )
        if not isinstance(self.pretrain_share, float) or not 0 <= self.pretrain_share <= 1:
            _fail("pretrain_share", self.pretrain_share, "must be a number in [0, 1]")
        for name in ("consmac_every", "consmac_steps", "consmac_batch", "hidden", "critic_hidden", "checkpoint_every"):
            _check_int(name, getattr(self, name), 1, 1_000_000)
        _check_int("replay_capacity", self.replay_capacity, 1, MAX_REPLAY)
        _check_int("eval_episodes", self.eval_episodes, 0, 1000)
        lr = self.consmac_lr
        if not isinstance(lr, (int, float)) or not math.isfinite(lr) or not 0 < lr <= 1:
            _fail("consmac_lr", self.consmac_lr, "must be a number in (0, 1]")
        if not isinstance(self.ppo, PPOConfig):
            _fail("ppo", self.ppo, "must be a PPOConfig")
        decisions = self.ppo.n_envs * self.ppo.episodes_per_iteration * self.decision_steps
        if isinstance(self.ppo.minibatches, int) and self.ppo.minibatches > decisions:
            _fail(
                "minibatches",
                self.ppo.minibatches,
                f"must be at most the {decisions} env-decisions of an iteration "
                f"(n_envs x episodes x {self.decision_steps} decisions)",
            )
        self.ppo.validate()
        self.task()  # the game itself (obstacle packing, ...)
        self.check_schedule()

    def check_schedule(self) -> None:
        """Under schedule "paper", every number of SCHEDULES["paper"] must be the config's."""
        if self.schedule not in SCHEDULES:
            _fail("schedule", self.schedule, f"must be one of {', '.join(SCHEDULES)}")
        if self.schedule != "paper":
            return
        paper = SCHEDULES["paper"]
        held = {
            "budget": (self.budget, Budget(iterations=paper["iterations"])),
            "n_envs": (self.ppo.n_envs, paper["n_envs"]),
            "episodes_per_iteration": (self.ppo.episodes_per_iteration, 1),
            **{
                name: (getattr(self, name), paper[name]) for name in ("consmac_every", "consmac_steps", "consmac_batch")
            },
            "pretrain_share": (self.pretrain_share, paper["pretrain_share"]),
        }
        for name, (value, expected) in held.items():
            if name == "pretrain_share" and math.isclose(value, expected):
                continue
            if value != expected:
                if name == "budget":  # as --budget takes it
                    value = "".join(f"{v:g}{unit}" for v, unit in ((value.iterations, "it"), (value.seconds, "s")) if v)
                    expected = f"{paper['iterations']} iterations"
                _fail(
                    name,
                    value,
                    f"schedule 'paper' fixes it to {expected} (paper Sec. V-A); leave it out or use schedule 'short'",
                )


class ConsMACReplay:
    """B_C of Algorithm 2: a ring buffer of the communication module's inputs and labels, one row per
    agent-decision. Messages are stored at the module's sent size (64; ConsMAC-G's label size; 38 for
    MASIA, 102 for NVIF), labels at `label_dim` (0 for NVIF, whose targets are the observations in
    its inputs)."""

    FIELDS = ("obs", "own", "messages", "mask", "distance", "label")

    def __init__(self, capacity: int, cfg: ConsMACConfig):
        k, d = cfg.n_agents - 1, cfg.sent_dim
        shapes = {
            "obs": ((cfg.env_obs_dim,), torch.float32),
            "own": ((d,), torch.float32),
            "messages": ((k, d), torch.float32),
            "mask": ((k,), torch.bool),
            "distance": ((k,), torch.float32),
            "label": ((cfg.label_dim,), torch.float32),
        }
        self.capacity = capacity
        self.data = {name: torch.zeros((capacity, *shape), dtype=dtype) for name, (shape, dtype) in shapes.items()}
        self.size = 0
        self.next = 0

    def add(self, rows: dict[str, torch.Tensor]) -> None:
        """Append rows (each [n, ...]); the oldest rows make room once the buffer is full."""
        n = len(rows["obs"])
        start = 0 if n <= self.capacity else n - self.capacity  # more rows than room: keep the newest
        index = (self.next + torch.arange(n - start)) % self.capacity
        for name in self.FIELDS:
            self.data[name][index] = rows[name][start:].to(self.data[name].dtype)
        self.next = int((self.next + n - start) % self.capacity)
        self.size = min(self.capacity, self.size + n - start)

    def sample(self, batch: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        index = torch.randint(0, self.size, (batch,), generator=generator)
        return {name: self.data[name].index_select(0, index) for name in self.FIELDS}

    def newest(self, rows: int) -> dict[str, torch.Tensor]:
        """The `rows` most recently added rows (fewer when the buffer holds fewer)."""
        n = min(rows, self.size)
        index = (self.next - n + torch.arange(n)) % self.capacity
        return {name: self.data[name][index] for name in self.FIELDS}

    def state_dict(self) -> dict:
        return {"size": self.size, "next": self.next, "data": {k: v[: self.size].clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.size, self.next = int(state["size"]), int(state["next"])
        for name in self.FIELDS:
            self.data[name][: self.size] = state["data"][name]


@torch.no_grad()
def label_fit(comm, replay: ConsMACReplay, rows: int) -> dict | None:
    """How well the module estimates its global-state label on the replay's newest `rows` rows (the
    export passes the last iteration's agent-decisions, which at most the last supervised round has
    trained on): its loss (eq. (11),
    summed over the label's numbers, averaged over rows), the loss of always guessing those rows'
    mean label, and 1 - loss / guess (the share of the label's variance explained). None for a module
    without a global-state label (NVIF reconstructs observations)."""
    if comm is None or comm.cfg.label_dim == 0 or replay.size == 0:
        return None
    batch = replay.newest(rows)
    loss = float(comm.supervised_loss(batch))
    label = batch["label"]
    guess = float(((label - label.mean(dim=0)) ** 2).sum(dim=-1).mean())
    return {
        "rows": int(len(label)),
        "loss": loss,
        "mean_guess_loss": guess,
        "explained": 1.0 - loss / guess if guess > 0 else None,
    }


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
        rollout = self.collect(env)
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
            "replay": None if self.replay is None else self.replay.state_dict(),
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


# ---------------------------------------------------------------------------- the run
def read_state(path: Path) -> dict:
    return run_state.read_state(path, STATE_FORMAT, "high-level training state")


def _last_csv_row(run_dir: Path) -> dict:
    with (run_dir / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return rows[-1] if rows else {}


def train_highlevel(
    cfg: HighLevelConfig,
    out: Path,
    policies_dir: Path,
    resume: bool = False,
    show_progress: bool = True,
    command: str | None = None,
    low_level_dir: Path | None = None,
) -> dict:
    """Train under the budget, export pi_H and its model card to `policies_dir`; returns the card.

    resume: continue the run in <out>/<name>/ (ConfigError if there is none, or if it was made with
    other settings). low_level_dir: where `cfg.low_level` is looked up by name (default the shipped
    policies). Everything the run needs is loaded and checked before the run folder is made."""
    out, policies_dir = Path(out), Path(policies_dir)
    run_dir = out / cfg.name
    state_path = run_dir / STATE_FILE
    task = cfg.task()
    try:
        low_levels = (load_low_level(NAVIGATION, task), load_low_level(cfg.low_level, task, low_level_dir))
    except CheckpointError as e:
        raise CheckpointError(f"--low-level: {e}") from None
    try:
        _, adversary_policy, adversary_record = resolve_adversary(cfg.adversary)
    except CheckpointError as e:
        raise CheckpointError(f"--adversary: {e}") from None
    saved = None
    if run_state.run_state_path(run_dir, resume) is not None:
        saved = read_state(state_path)
        run_state.check_same_run(saved["config"], cfg, state_path, free=("budget", "checkpoint_every", "eval_episodes"))
        if saved["low_level"]["finetune"] != display_paths(low_levels[1].describe()):
            raise ConfigError(
                f"--resume: {state_path} was trained with another fine-tuning low level "
                f"({saved['low_level']['finetune'].get('name')}); use another --out"
            )
        if cfg.variant == "tarmac" and saved.get("tarmac_messages") != TARMAC_MESSAGES:
            raise ConfigError(
                f"--resume: {state_path} was trained without gradient through received messages "
                "(the TarMAC-style row before end-to-end messages); use another --out"
            )
        if saved.get("adversary", {"rule": cfg.adversary}) != adversary_record:
            raise ConfigError(
                f"--resume: {state_path} was trained against another adversary file "
                f"({saved['adversary'].get('policy')}); use another --out"
            )
    trainer = HighLevelTrainer(cfg, low_levels, adversary_policy)
    trainer.adversary_record = adversary_record
    if saved is not None:
        trainer.load_state_dict(saved["trainer"])
    low_level_record = {
        "pretrain": display_paths(low_levels[0].describe()),
        "finetune": display_paths(low_levels[1].describe()),
    }
    write_atomic(
        run_dir / "config.json",
        json.dumps(
            {
                "highlevel": cfg.to_dict(),
                "task": task.to_dict(),
                "low_level": low_level_record,
                "adversary": adversary_record,
                "command": command,
            },
            indent=2,
        )
        + "\n",
    )

    def checkpoint() -> None:
        atomic_torch_save(
            {
                "format": STATE_FORMAT,
                "config": cfg.to_dict(),
                "low_level": low_level_record,
                "adversary": adversary_record,
                "trainer": trainer.state_dict(),
                **({"tarmac_messages": TARMAC_MESSAGES} if cfg.variant == "tarmac" else {}),
            },
            state_path,
        )

    if saved is None:
        checkpoint()  # iteration 0: a run killed before its first periodic checkpoint can still --resume
    logger = RunLogger(run_dir, trainer.iteration, cfg.budget.iterations, desc=cfg.name, show_progress=show_progress)
    last_row = run_state.train_under_budget(
        trainer, cfg.budget, cfg.checkpoint_every, logger, PROGRESS_KEYS, checkpoint
    )
    if not last_row and trainer.iteration:  # a finished run re-exported: its last logged iteration
        last_row = _last_csv_row(run_dir)

    card = export_policy(
        trainer.policy, cfg, task, low_levels, trainer, policies_dir, run_dir, command, last_row=last_row
    )
    if trainer.pretrained is not None and trainer.progress["iterations"][1] > 0:
        pretrained = HighLevelPolicy.build(cfg.variant, task, cfg.seed, cfg.hidden, cfg.ablation)
        pretrained.load_state_dict(trainer.pretrained)
        card["wo_ft"] = export_policy(
            pretrained, cfg, task, low_levels, trainer, policies_dir, run_dir, command, wo_ft=True
        )["name"]
    return card


def export_policy(
    policy: HighLevelPolicy,
    cfg: HighLevelConfig,
    task: TaskConfig,
    low_levels: tuple[LowLevel, LowLevel],
    trainer: HighLevelTrainer,
    policies_dir: Path,
    run_dir: Path,
    command: str | None,
    last_row: dict | None = None,
    wo_ft: bool = False,
) -> dict:
    """Write `policy` as <name>.pt with its model card (evaluated with the fine-tuning low level)
    into `policies_dir`; returns the card. wo_ft: the weights at the end of pre-training, written
    as <name>_wo_ft.pt (the paper's "wo-FT": pre-trained, then combined with the fine-tuning low
    level without joint fine-tuning)."""
    name = cfg.name + ("_wo_ft" if wo_ft else "")
    low_level_record = {
        "pretrain": display_paths(low_levels[0].describe()),
        "finetune": display_paths(low_levels[1].describe()),
    }
    iterations = trainer.progress["iterations"][0] if wo_ft else trainer.iteration
    episodes = iterations * cfg.ppo.n_envs * cfg.ppo.episodes_per_iteration if wo_ft else trainer.episodes
    policy_path = save_highlevel_policy(
        policy,
        policies_dir / f"{name}.pt",
        meta={
            "name": name,
            "variant": cfg.variant,
            "ablation": cfg.ablation,
            "seed": cfg.seed,
            "iterations": iterations,
            "decision_interval": cfg.decision_interval,
            "low_level": low_level_record["finetune"],
            "adversary": trainer.adversary_record,
        },
    )
    phases = [
        {"phase": phase, "low_level": low_levels[i].name, "iterations": trainer.progress["iterations"][i]}
        for i, phase in enumerate(PHASES)
    ]
    card = {
        "name": name,
        "method": METHODS[cfg.variant]
        + (f", {ABLATION_METHODS[cfg.ablation]}" if cfg.ablation != "none" else "")
        + (", without fine-tuning (wo-FT)" if wo_ft else ""),
        "variant": cfg.variant,
        "ablation": cfg.ablation,
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "task": task.to_dict(),
        "networks": {
            "comm": None if policy.comm is None else policy.comm.cfg.to_dict(),
            "selector": policy.selector.cfg.to_dict(),
            "critic_hidden": cfg.critic_hidden,
        },
        "low_level": low_level_record,
        "adversary": trainer.adversary_record,
        "phases": phases[:1] if wo_ft else phases,
        "schedule": {"name": cfg.schedule, **SCHEDULES[cfg.schedule], "fixed": cfg.schedule == "paper"},
        "consmac_training": None
        if not cfg.supervised
        else {
            "rounds": trainer.consmac_rounds,
            "steps": trainer.consmac_steps,
            "steps_per_round": cfg.consmac_steps,
            "every_iterations": cfg.consmac_every,
            "every_episodes": cfg.consmac_every * cfg.ppo.n_envs * cfg.ppo.episodes_per_iteration,
            "batch": cfg.consmac_batch,
            "lr": cfg.consmac_lr,
            "replay_capacity": cfg.replay_capacity,
            "paper": PAPER_CONSMAC,
            "label_fit": label_fit(
                policy.comm,
                trainer.replay,
                cfg.ppo.n_envs * cfg.ppo.episodes_per_iteration * cfg.decision_steps * cfg.n_agents,
            ),
        },
        "messages": None
        if policy.comm is None
        else {
            "numbers": policy.message_dim,
            "content": "g_hat (ConsMAC-G)" if cfg.ablation == "consmac-g" else COMMUNICATION[cfg.variant][0],
            "trained_by": COMMUNICATION[cfg.variant][1]
            + (" and the PPO loss (wt-RL)" if cfg.ablation == "wt-rl" else ""),
            "selector_reads": "the message"
            if policy.comm.cfg.message_content == "learned"
            else f"the aggregated feature ({policy.comm.cfg.feature_dim} numbers), detached",
            "received": "nothing (wo-Com)" if cfg.ablation == "wo-com" else "neighbours within 3 m, one decision late",
            "rl_gradient": {
                "tarmac": "end to end through the received messages, truncated one decision back",
                "wt-rl": "into ConsMAC through the agent's own message (besides eq. (11))",
            }.get(cfg.variant if cfg.variant == "tarmac" else cfg.ablation, "none (stop-gradient)"),
        },
        "iterations": iterations,
        "episodes": episodes,
        "decisions": episodes * cfg.decision_steps * cfg.n_agents,
        "train_wall_clock_s": round(trainer.elapsed, 1),
        "run_dir": display_path(run_dir),
        "command": command,
    }
    if wo_ft:
        card["wo_ft"] = (
            f"the weights at the end of pre-training (iteration {iterations}) of the run that made "
            f"{cfg.name}; the ConsMAC and wall-clock figures are the whole run's"
        )
    else:
        card["last_iteration"] = {k: v for k, v in (last_row or {}).items() if isinstance(v, (int, float))}
    if cfg.eval_episodes:
        card["evaluation"] = {
            "protocol": {
                "episodes": cfg.eval_episodes,
                "seed": 0,
                "anchors": "mode of the selector",
                "low_level": low_levels[1].name,
                "backend": "particle",
                "figures": "per-episode sums; R_t, R_n, R_e weighted, summing to R_H",
            },
            "ours": evaluate_highlevel(
                policy,
                task,
                low_levels[1],
                cfg.eval_episodes,
                seed=0,
                decision_interval=cfg.decision_interval,
                adversary_policy=trainer.adversary_policy,
            ),
        }
    write_model_card(policy_path, card)
    return card


# ---------------------------------------------------------------------------- command line
_FLAG_OF_FIELD = {
    "variant": "--variant",
    "ablation": "--ablation",
    "seed": "--seed",
    "obstacle_density": "--density",
    "adversary": "--adversary",
    "episode_steps": "--episode-steps",
    "low_level": "--low-level",
    "pretrain_share": "--pretrain-share",
    "consmac_every": "--consmac-every",
    "consmac_steps": "--consmac-steps",
    "consmac_batch": "--consmac-batch",
    "consmac_lr": "--consmac-lr",
    "replay_capacity": "--replay",
    "eval_episodes": "--eval-episodes",
    "n_envs": "--envs",
    "epochs": "--epochs",
    "minibatches": "--minibatches",
    "lr": "--lr",
    "update_threads": "--threads",
    "entropy_coef": "--entropy",
    "schedule": "--schedule",
    "budget": "--budget",
}
"""Config fields set by `cefc-train highlevel` flags: their errors name the flag the user typed."""
CLI_FIELDS = (
    "variant",
    "ablation",
    "seed",
    "obstacle_density",
    "adversary",
    "episode_steps",
    "low_level",
    "pretrain_share",
    "consmac_every",
    "consmac_steps",
    "consmac_batch",
    "consmac_lr",
    "replay_capacity",
    "eval_episodes",
    "schedule",
)
CLI_PPO_FIELDS = ("n_envs", "epochs", "minibatches", "lr", "update_threads", "entropy_coef")


def config_from_args(args, budget: Budget | None) -> HighLevelConfig:
    """The HighLevelConfig of `cefc-train highlevel` arguments (flags left out keep the config's
    defaults, and take the numbers of `--schedule paper` under that schedule; budget None: the
    schedule's iterations); a bad value raises ConfigError naming the flag."""
    schedule = SCHEDULES[getattr(args, "schedule", None) or "short"]
    if budget is None:
        budget = Budget(iterations=schedule["iterations"])
    if getattr(args, "schedule", None) == "paper":
        args = copy.copy(args)
        for name in ("consmac_every", "consmac_steps", "consmac_batch", "n_envs"):
            if getattr(args, name, None) is None:
                setattr(args, name, schedule[name])
    return config_from_flags(HighLevelConfig, args, budget, CLI_FIELDS, CLI_PPO_FIELDS, _paper_ppo(), _FLAG_OF_FIELD)


def summary_lines(card: dict, policies_dir: Path) -> list[str]:
    """What `cefc-train highlevel` prints when a run ends."""
    phases = ", ".join(f"{p['phase']} ({p['low_level']}): {p['iterations']} it" for p in card["phases"])
    lines = [
        f"{card['name']}: {card['iterations']} iterations ({phases}), {card['episodes']} episodes, "
        f"{card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})"
    ]
    if card.get("consmac_training"):
        c = card["consmac_training"]
        module = {"masia": "MASIA's module", "nvif": "NVIF's module"}.get(card["variant"], "ConsMAC")
        fit = c.get("label_fit")
        lines.append(
            f"{module}: {c['rounds']} rounds, {c['steps']} steps of batch {c['batch']} "
            f"(paper: {c['paper']['steps']} steps every {c['paper']['every_episodes']} episodes)"
            + (
                f"; label fit on the newest {fit['rows']} rows: loss {fit['loss']:.1f} against "
                f"{fit['mean_guess_loss']:.1f} for guessing the mean ({fit['explained']:.0%} explained)"
                if fit and fit["explained"] is not None
                else ""
            )
        )
    if card.get("wo_ft"):
        lines.append(f"pre-trained weights (wo-FT) -> {policies_dir / (card['wo_ft'] + '.pt')}")
    if "evaluation" in card:
        o = card["evaluation"]["ours"]
        lines.append(
            f"evaluation ({card['evaluation']['protocol']['episodes']} episodes): R_H {o['R_H']:.1f} = "
            f"R_t {o['R_t']:.1f} + R_n {o['R_n']:.1f} + R_e {o['R_e']:.1f}; E {o['E']:.1f}  F {o['F']:.1f}  "
            f"C {o['C']:.2f}%"
        )
    return lines
