"""The high level's training config (`HighLevelConfig`, Algorithm 2's settings), the two readings of
the paper's budget (`SCHEDULES`, and the paper's scaled to fewer updates) and the `cefc-train
highlevel` flags that fill it (`config_from_args`). The run is `cefc_mj.train.highlevel`."""

from __future__ import annotations

import copy
import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

from cefc_mj.errors import ConfigError
from cefc_mj.hierarchy import (
    CLM_PER_GROUP,
    DECISION_INTERVAL,
    NAVIGATION,
)
from cefc_mj.nn.consmac import ABLATIONS
from cefc_mj.nn.highlevel_policy import (
    CONSMAC_VARIANTS,
    SUPERVISED_VARIANTS,
    VARIANTS,
)
from cefc_mj.nn.registry import GAME_ADVERSARY, HIERARCHY_LOWLEVEL
from cefc_mj.task.config import ADVERSARY_RULES, LEARNED_ADVERSARY, TaskConfig
from cefc_mj.train.config import MAX_DENSITY, MAX_SEED, Budget, BudgetPPODict, PPOConfig, config_from_flags

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
    "paper-scaled": {
        "iterations": None,
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
every number here is fixed; "short" only names the defaults, which flags may change. "paper-scaled"
is "paper" shrunk to N < 1,500 iterations (`--budget Nit`, N a multiple of 3; the budget ladder's
shorter rungs) in its proportions: the first 2N/3 pre-training, ConsMAC 5,000 steps of 2,048 after
every 20 iterations (so 250 steps per iteration, as in "paper"); every number but N is fixed. It is
not the first N iterations of a "paper" run: the switch to fine-tuning comes at 2N/3, not at 1,000."""
PAPER_UPDATES = SCHEDULES["paper"]["iterations"]
"""The paper's 1,500 updates: "paper-scaled" takes fewer."""
PAPER_SCALED_STEP = 3
"""A "paper-scaled" N is a multiple of this, so its 2N/3 pre-training iterations are whole."""
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
    (Sec. V-A); the budget and the ConsMAC schedule default to the short reading of `SCHEDULES`
    (docs/research/high_level.md, docs/research/highlevel_speed.md)."""

    budget: Budget
    """Iterations (each: n_envs x episodes_per_iteration episodes, then the updates) and/or
    wall-clock time, counted across resumes. Read as 1,500 games, the paper's 1000 + 500 episodes
    are 75 iterations of 20 (schedule "short"; the shipped high levels ran those 75 and were continued
    with --resume to 150, docs/research/decisions.md); read as the MAPPO code base counts them, 1,500
    iterations of 20 (schedule "paper")."""
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
    V and VII, trained against a population of teams and at least as strong as the rules: docs/research/decisions.md):
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
    """ConsMAC trains after every this many iterations: 1 in the short schedule (20 envs make an
    iteration 20 games, the paper's "every 20 episodes" read as games), 20 in the paper schedule."""
    consmac_steps: int = 200
    """Adam steps per ConsMAC round (paper: 5000, schedule "paper"; the short schedule's 200 kept the
    shipped runs affordable when a step of batch 2048 cost 50-200 ms on a shared 2-core CPU)."""
    consmac_batch: int = 2048
    """Tuples per ConsMAC step (paper: 2048), drawn uniformly with replacement from the replay."""
    consmac_lr: float = 1e-4
    """ConsMAC's Adam learning rate (paper: 1e-4). The selector reads ConsMAC's messages, so every
    round moves its input; at 1e-3 (Adam's steps scale with the rate) the selector learned to evade
    worse (docs/research/decisions.md)."""
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
    those fields must then hold exactly the paper's values) or "paper-scaled" (the paper's shrunk to
    `paper_updates` iterations in its proportions). Runs saved before this field existed load as
    "short"."""
    paper_updates: int | None = None
    """Under schedule "paper-scaled" only: the N iterations the paper's schedule is shrunk to (a multiple
    of 3 from 3 to 1,497; the budget is exactly N iterations; the 1,500 themselves are schedule "paper").
    Part of the run's identity: --resume keeps it (a longer N moves the switch to fine-tuning from 2N/3,
    so a run is never extended to another N). None under the other schedules."""

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
        """Under schedule "paper" ("paper-scaled"), every number of SCHEDULES["paper"] must be the
        config's (but the iterations, `paper_updates`)."""
        if self.schedule not in SCHEDULES:
            _fail("schedule", self.schedule, f"must be one of {', '.join(SCHEDULES)}")
        if self.schedule != "paper-scaled":
            if self.paper_updates is not None:
                _fail("paper_updates", self.paper_updates, "is for schedule 'paper-scaled' only (None otherwise)")
            if self.schedule == "short":
                return
        else:
            _check_paper_updates(self.paper_updates)
        paper = SCHEDULES["paper"]
        iterations = self.paper_updates or paper["iterations"]
        held = {
            "budget": (self.budget, Budget(iterations=iterations)),
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
                    expected = f"{iterations} iterations"
                _fail(
                    name,
                    value,
                    f"schedule {self.schedule!r} fixes it to {expected} (paper Sec. V-A); leave it out or use "
                    "schedule 'short'",
                )


def _check_paper_updates(n: object) -> None:
    """N of schedule "paper-scaled": a multiple of PAPER_SCALED_STEP below the paper's 1,500."""
    if not isinstance(n, int) or isinstance(n, bool) or not 0 < n < PAPER_UPDATES or n % PAPER_SCALED_STEP:
        _fail(
            "paper_updates",
            n,
            f"schedule 'paper-scaled' needs N iterations (--budget Nit), N a multiple of {PAPER_SCALED_STEP} "
            f"from {PAPER_SCALED_STEP} to {PAPER_UPDATES - PAPER_SCALED_STEP} (the paper's {PAPER_UPDATES} "
            "are schedule 'paper')",
        )


def check_resume_schedule(saved: dict, cfg: HighLevelConfig, path: Path) -> None:
    """A resumed "paper-scaled" run keeps its N: ConfigError naming both where `cfg` asks for another
    (continuing to a longer N would fly the navigation-only low level again between the old 2N/3 and
    the new one). Other differences are `run_state.check_same_run`'s to report."""
    if saved.get("schedule") != "paper-scaled" or cfg.schedule != "paper-scaled":
        return
    if saved.get("paper_updates") != cfg.paper_updates:
        raise ConfigError(
            f"--resume: {path} is the paper's schedule scaled to {saved.get('paper_updates')} iterations, not "
            f"{cfg.paper_updates} (its switch to fine-tuning came at 2N/3, so it cannot be extended); train "
            f"{cfg.paper_updates} iterations in another --out"
        )


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
    "paper_updates": "--budget",
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
    defaults, and take the numbers of `--schedule paper` under that schedule and "paper-scaled";
    budget None: the schedule's iterations, which "paper-scaled" does not have: its --budget Nit is
    required); a bad value raises ConfigError naming the flag."""
    name = getattr(args, "schedule", None) or "short"
    schedule = SCHEDULES[name]
    make = HighLevelConfig
    if name == "paper-scaled":
        if budget is None or budget.seconds is not None or budget.iterations is None:
            given = (
                "left out"
                if budget is None
                else "".join(f"{v:g}{unit}" for v, unit in ((budget.iterations, "it"), (budget.seconds, "s")) if v)
            )
            raise ConfigError(
                f"--budget {given}: schedule 'paper-scaled' needs --budget Nit, N iterations (a multiple of "
                f"{PAPER_SCALED_STEP} from {PAPER_SCALED_STEP} to {PAPER_UPDATES - PAPER_SCALED_STEP})"
            )
        make = functools.partial(HighLevelConfig, paper_updates=budget.iterations)
    if budget is None:
        budget = Budget(iterations=schedule["iterations"])
    if name != "short":
        args = copy.copy(args)
        for field_name in ("consmac_every", "consmac_steps", "consmac_batch", "n_envs"):
            if getattr(args, field_name, None) is None:
                setattr(args, field_name, schedule[field_name])
    return config_from_flags(make, args, budget, CLI_FIELDS, CLI_PPO_FIELDS, _paper_ppo(), _FLAG_OF_FIELD)
