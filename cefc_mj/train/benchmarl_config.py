"""The configuration of a BenchMARL run on the high-level game (`cefc_mj.train.benchmarl_game`), kept
apart from that module so that `cefc-train highlevel-benchmarl --help` and its flag checks need
neither BenchMARL nor torchrl (the `benchmarl` extra is optional, and CI does not install it).

>>> cfg = BenchMARLConfig(algorithm="masac", seed=3)
>>> cfg.name, cfg.decision_steps, cfg.frames_per_batch, cfg.iterations, cfg.max_frames
('benchmarl_masac_seed3', 40, 800, 75, 60000)
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass

from cefc_mj.errors import ConfigError
from cefc_mj.nn.registry import GAME_ADVERSARY, HIERARCHY_LOWLEVEL
from cefc_mj.train.config import MAX_DENSITY, MAX_ENVS, MAX_LR, MAX_SEED, MAX_THREADS

ALGORITHMS = ("masac", "mappo")
"""BenchMARL's algorithms this integration runs: MASAC (the stand-in for the paper's HASAC) and MAPPO
(the cross-check of `cefc-train highlevel --variant mappo`)."""
DECISION_INTERVAL = 10
"""Low-level steps per high-level decision (`cefc_mj.hierarchy.DECISION_INTERVAL`, the paper's 10)."""
BENCHMARL_EXTRA = "cefc-train highlevel-benchmarl: needs the benchmarl extra (pip install -e '.[benchmarl]')"
"""The one line the subcommand prints (exit 2) when BenchMARL is not installed."""
MAX_EPISODES = 10_000_000


def _fail(name: str, value: object, why: str) -> None:
    raise ConfigError(f"{name}={value!r}: {why}")


def _check_int(name: str, value: object, least: int, most: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not least <= value <= most:
        _fail(name, value, f"must be an integer in [{least}, {most}]")


def _check_real(name: str, value: object, low: float, high: float, low_open: bool = False) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (low < value if low_open else low <= value) and value <= high
    if not ok:
        _fail(name, value, f"must be a number in {'(' if low_open else '['}{low:g}, {high:g}]")


def parse_episode_budget(text: str) -> int:
    """'1500ep' or '1500' -> 1500 episodes (the budget of `cefc-train highlevel-benchmarl`)."""
    text = str(text)
    shown = text if len(text) <= 40 else text[:37] + "..."
    m = re.fullmatch(r"\s*(\d+)\s*(ep)?\s*", text)
    if not m:
        raise ConfigError(f"--budget {shown!r}: expected a number of episodes ('1500ep' or '1500')")
    episodes = int(m.group(1))
    if not 1 <= episodes <= MAX_EPISODES:
        raise ConfigError(f"--budget {shown!r}: must be 1 to {MAX_EPISODES} episodes")
    return episodes


class _BenchMARLRunConfig:
    """What both BenchMARL run configs (the game's and the formation task's) do alike: their list
    fields read back as tuples, integer reals as floats, the dict form, and the checks of the
    settings they share (reward scale, optimiser, networks, evaluation, threads)."""

    def _normalise(self, real_fields: tuple[str, ...]) -> None:
        """critic_cells as a tuple and the `real_fields` given as integers as floats (a frozen dataclass's
        __post_init__)."""
        if isinstance(self.critic_cells, list):
            object.__setattr__(self, "critic_cells", tuple(self.critic_cells))
        for name in real_fields:
            value = getattr(self, name)
            if isinstance(value, int) and not isinstance(value, bool):
                object.__setattr__(self, name, float(value))

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["critic_cells"] = list(self.critic_cells)
        return d

    @classmethod
    def from_dict(cls, d: dict):
        return cls(**d)

    def _check_optimisation(self) -> None:
        _check_real("reward_scale", self.reward_scale, 0.0, 1e6, low_open=True)
        _check_real("gamma", self.gamma, 0.0, 1.0)
        _check_real("lr", self.lr, 0.0, MAX_LR, low_open=True)

    def _check_networks(self) -> None:
        _check_int("hidden", self.hidden, 1, 4096)
        if (
            not isinstance(self.critic_cells, tuple)
            or not self.critic_cells
            or not all(isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= 4096 for c in self.critic_cells)
        ):
            _fail("critic_cells", self.critic_cells, "must be a non-empty tuple of widths in [1, 4096]")

    def _check_run(self) -> None:
        _check_int("eval_episodes", self.eval_episodes, 0, 1000)
        _check_int("threads", self.threads, 1, MAX_THREADS)


@dataclass(frozen=True)
class BenchMARLConfig(_BenchMARLRunConfig):
    """One BenchMARL run (MASAC or MAPPO) on the high-level game of `cefc-train highlevel`.

    The game fields (n_agents, obstacle_density, adversary, episode_steps, low_level) are
    HighLevelConfig's, with its defaults and checks, and build the same TaskConfig. The budget is
    counted in episodes: one iteration collects one episode in each of the `n_envs` envs (the
    `n_envs` x 40 decisions BenchMARL calls frames), as our trainer's iteration does. The other
    hyperparameters are BenchMARL 1.5.2's defaults (conf/experiment/base_experiment.yaml,
    conf/algorithm/*.yaml) except gamma (the game's discount per decision), the reward's scale (for the
    critics' sake) and the actor's widths (our anchor selector's, so that the trained actor exports into
    our policy format).
    """

    algorithm: str = "masac"
    """masac (BenchMARL's MASAC, the stand-in for the paper's HASAC) or mappo (BenchMARL's MAPPO)."""
    seed: int = 0
    """BenchMARL's seed (networks, sampling) and the seed of every iteration's episodes."""
    budget_episodes: int = 1500
    """Training episodes (paper: 1000 + 500 = 1500); a multiple of n_envs. 1500 at 20 envs is 75
    iterations of 800 frames, 60000 frames (env-decisions) in all."""
    n_agents: int = 8
    """N, UAVs in the game (paper: 8)."""
    obstacle_density: float = 0.03
    """Obstacles per m^2 (HighLevelConfig's default)."""
    adversary: str = GAME_ADVERSARY
    """The game's adversary: a rule or a trained adversary's policy name or file (default the shipped PPO
    adversary, as in `cefc-train highlevel` and Table V)."""
    episode_steps: int = 400
    """Low-level steps per episode (paper: 400, 40 decisions); a multiple of 10."""
    low_level: str = HIERARCHY_LOWLEVEL
    """The low level that flies to the anchors: our trainer's fine-tuning low level (default the distilled
    student). There is no navigation-only pre-training phase."""
    n_envs: int = 20
    """Envs stepped as one batch; each iteration collects one episode per env (our trainer's 20)."""
    reward_scale: float = 1e-3
    """Factor on R_H before BenchMARL sees it (1: unscaled). A positive factor leaves the optimal policy
    alone; it stands in for what BenchMARL lacks and our trainer has (value normalisation, advantage
    standardisation): R_H is -500 to -2000 per decision, and Adam at lr 5e-5 moves a critic's output
    bias by about lr per step, so unscaled values are out of the critics' reach in 75 iterations
    (measured: MASAC's Q loss 1e7 unscaled, about 1 at 1e-3; docs/research/baselines.md)."""
    gamma: float = 0.8
    """Discount per decision (our trainer's and the paper's 0.8; BenchMARL's default is 0.99)."""
    lr: float = 5e-5
    """Adam learning rate of every network (BenchMARL's default)."""
    masac_updates: int = 1000
    """MASAC: gradient steps after each iteration (BenchMARL's off_policy_n_optimizer_steps)."""
    masac_batch: int = 128
    """MASAC: frames per gradient step, drawn uniformly from the replay (BenchMARL's default)."""
    mappo_epochs: int = 45
    """MAPPO: passes over each iteration's frames (BenchMARL's on_policy_n_minibatch_iters)."""
    mappo_minibatch: int = 400
    """MAPPO: frames per minibatch (BenchMARL's default; 800 frames make 2 minibatches)."""
    hidden: int = 128
    """Actor width: 4 linear layers 38 -> hidden -> hidden -> hidden -> 9 with tanh, our anchor selector's
    shape (BenchMARL's default actor is 2 layers of 256)."""
    critic_cells: tuple[int, ...] = (256, 256)
    """Hidden layers of the centralised critic, which reads the global state (BenchMARL's default MLP)."""
    eval_episodes: int = 20
    """Episodes (batch seed cefc_mj.seeds.GAME_VALIDATION_SEED) of the exported policy evaluated for the
    model card; 0 skips."""
    threads: int = 1
    """torch threads of the whole run (collection and updates)."""

    def __post_init__(self) -> None:
        self._normalise(("obstacle_density", "reward_scale", "gamma", "lr"))
        self.validate()

    # ------------------------------------------------------------------ derived
    @property
    def name(self) -> str:
        """Run folder and policy file stem: benchmarl_<algorithm>, then _seed<k> for seeds other than 0
        (the `_seed<k>` convention Table V reads)."""
        return f"benchmarl_{self.algorithm}" + (f"_seed{self.seed}" if self.seed else "")

    @property
    def on_policy(self) -> bool:
        return self.algorithm == "mappo"

    @property
    def decision_steps(self) -> int:
        """Decisions per episode (40)."""
        return self.episode_steps // DECISION_INTERVAL

    @property
    def frames_per_batch(self) -> int:
        """BenchMARL frames (env-decisions) per iteration: one episode in every env."""
        return self.n_envs * self.decision_steps

    @property
    def iterations(self) -> int:
        return self.budget_episodes // self.n_envs

    @property
    def max_frames(self) -> int:
        return self.budget_episodes * self.decision_steps

    def game_config(self):
        """The HighLevelConfig of the same game (its `task()` is the TaskConfig trained on)."""
        from cefc_mj.train.config import Budget
        from cefc_mj.train.highlevel_config import HighLevelConfig

        return HighLevelConfig(
            budget=Budget(iterations=self.iterations),
            variant="mappo",
            seed=self.seed,
            n_agents=self.n_agents,
            obstacle_density=self.obstacle_density,
            adversary=self.adversary,
            episode_steps=self.episode_steps,
            low_level=self.low_level,
            pretrain_share=0.0,
            hidden=self.hidden,
            eval_episodes=0,
        )

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        if self.algorithm not in ALGORITHMS:
            _fail("algorithm", self.algorithm, f"must be one of {', '.join(ALGORITHMS)}")
        _check_int("seed", self.seed, 0, MAX_SEED)
        _check_int("n_envs", self.n_envs, 1, MAX_ENVS)
        _check_int("budget_episodes", self.budget_episodes, 1, MAX_EPISODES)
        if self.budget_episodes % self.n_envs:
            _fail(
                "budget_episodes",
                self.budget_episodes,
                f"must be a multiple of the {self.n_envs} envs (n_envs, --envs): one episode per env per iteration",
            )
        _check_int("n_agents", self.n_agents, 2, 8)
        _check_real("obstacle_density", self.obstacle_density, 0.0, MAX_DENSITY)
        if not isinstance(self.adversary, str) or not self.adversary:
            _fail("adversary", self.adversary, "must be a rule or a trained adversary's policy name or file")
        _check_int("episode_steps", self.episode_steps, DECISION_INTERVAL, 100_000)
        if self.episode_steps % DECISION_INTERVAL:
            _fail("episode_steps", self.episode_steps, f"must be a multiple of {DECISION_INTERVAL}")
        if not isinstance(self.low_level, str) or not self.low_level:
            _fail("low_level", self.low_level, "must be a policy name or file, or 'per-group'")
        self._check_optimisation()
        _check_int("masac_updates", self.masac_updates, 1, 1_000_000)
        _check_int("masac_batch", self.masac_batch, 1, 1_000_000)
        _check_int("mappo_epochs", self.mappo_epochs, 1, 10_000)
        _check_int("mappo_minibatch", self.mappo_minibatch, 1, 1_000_000)
        if self.on_policy and self.mappo_minibatch > self.frames_per_batch:
            _fail(
                "mappo_minibatch",
                self.mappo_minibatch,
                f"must be at most the {self.frames_per_batch} frames of an iteration (n_envs x decisions)",
            )
        self._check_networks()
        self._check_run()


# ---------------------------------------------------------------------------- command line
FLAG_OF_FIELD = {
    "algorithm": "--algorithm",
    "seed": "--seed",
    "budget_episodes": "--budget",
    "n_envs": "--envs",
    "episode_steps": "--episode-steps",
    "obstacle_density": "--density",
    "adversary": "--adversary",
    "low_level": "--low-level",
    "reward_scale": "--reward-scale",
    "gamma": "--gamma",
    "lr": "--lr",
    "masac_updates": "--updates",
    "masac_batch": "--batch-size",
    "mappo_epochs": "--epochs",
    "mappo_minibatch": "--minibatch-size",
    "eval_episodes": "--eval-episodes",
    "threads": "--threads",
}
"""Config fields set by `cefc-train highlevel-benchmarl` flags (argparse dest = field): their errors name
the flag the user typed."""


def _given_flags(args, flag_of_field: dict[str, str], budget_field: str) -> dict:
    """The config fields of the flags given (argparse dest = field; None: left out), but the budget,
    which the caller parses."""
    return {
        name: getattr(args, name)
        for name in flag_of_field
        if name != budget_field and getattr(args, name, None) is not None
    }


def config_from_args(args, budget_episodes: int) -> BenchMARLConfig:
    """The BenchMARLConfig of `cefc-train highlevel-benchmarl` arguments (flags left out keep the config's
    defaults), its game checked as HighLevelConfig checks it; a bad value raises ConfigError naming the flag."""
    from cefc_mj.train.config import flag_error

    given = _given_flags(args, FLAG_OF_FIELD, "budget_episodes")
    try:
        algorithm = given.get("algorithm", BenchMARLConfig.algorithm)
        for name in given:
            if name.split("_")[0] in ALGORITHMS and name.split("_")[0] != algorithm:
                raise ConfigError(f"{FLAG_OF_FIELD[name]}: a {name.split('_')[0]} setting, not {algorithm}'s")
        cfg = BenchMARLConfig(budget_episodes=budget_episodes, **given)
        cfg.game_config()  # the game: adversary, low level, obstacle packing
    except ConfigError as e:
        raise flag_error(e, FLAG_OF_FIELD) from None
    return cfg


# ---------------------------------------------------------------------------- the formation task
FORMATION_ALGORITHMS = ("maddpg", "ippo", "mappo", "masac")
"""BenchMARL's algorithms run on the formation task: MADDPG (the paper's Table III baseline), IPPO,
MAPPO and MASAC (exploratory rows beside it)."""
OFF_POLICY = ("maddpg", "masac")
ON_POLICY = ("ippo", "mappo")
FORMATION_COMMAND = "formation-benchmarl"
FORMATION_EXTRA = f"cefc-train {FORMATION_COMMAND}: needs the benchmarl extra (pip install -e '.[benchmarl]')"
"""The one line `cefc-train formation-benchmarl` prints (exit 2) when BenchMARL is not installed."""
MAX_FRAMES = 10**10


def parse_frame_budget(text: str) -> int:
    """'600000', '600000f', '600kf' or '6mf' -> frames (env-steps) of `cefc-train formation-benchmarl`."""
    text = str(text)
    shown = text if len(text) <= 40 else text[:37] + "..."
    m = re.fullmatch(r"\s*(\d+)\s*([km]?)f?\s*", text.lower())
    if not m:
        raise ConfigError(f"--budget {shown!r}: expected a number of frames (env-steps): '600000', '600kf' or '6mf'")
    frames = int(m.group(1)) * {"": 1, "k": 1000, "m": 1_000_000}[m.group(2)]
    if not 1 <= frames <= MAX_FRAMES:
        raise ConfigError(f"--budget {shown!r}: must be 1 to {MAX_FRAMES} frames")
    return frames


@dataclass(frozen=True)
class FormationBenchMARLConfig(_BenchMARLRunConfig):
    """One BenchMARL run (MADDPG, IPPO, MAPPO or MASAC) on the formation task of AT-M's stages.

    The task is `cefc_mj.train.lowlevel.task_config_for` of the AT-M stage with the same formation and
    step: one group of c agents flying to an anchor for 100 steps, Step 1's scenario (no obstacles) or
    Steps 2 and 3's (density 0.03). The actor is AT-M's network (eq. 8, `nn.atm.ATMActor`, velocity
    head) so that the trained actor is an AT-M policy file that every low-level evaluator flies; the
    critics are BenchMARL's MLPs on the global state. The budget is counted in frames (env-steps; one
    frame is c agent-steps). The other hyperparameters are BenchMARL 1.5.2's defaults
    (conf/experiment/base_experiment.yaml, conf/algorithm/*.yaml) except gamma (our trainer's), the
    reward's scale, no tanh squashing of the actions (the file's actions are clipped, as the env clips),
    the replay's capacity, a fixed exploration schedule and the widths.

    >>> cfg = FormationBenchMARLConfig(formation=7, seed=2)
    >>> cfg.name, cfg.frames_per_batch, cfg.iterations, cfg.agent_steps
    ('benchmarl_maddpg_c7_seed2', 6000, 200, 8400000)
    """

    algorithm: str = "maddpg"
    """maddpg, ippo, mappo or masac (BenchMARL's)."""
    formation: int = 6
    """c: agents in the group (3..8; Table III: 6, 7, 8)."""
    step: int = 2
    """The AT-M stage whose scenario is trained: 1 (no obstacles) or 2 (density 0.03, the scenario of
    Steps 2 and 3). Training always starts from random weights: there is no Step 3 merge."""
    seed: int = 0
    """BenchMARL's seed (networks, sampling) and the seed of every batch of training episodes."""
    budget_frames: int = 1_200_000
    """Training frames (env-steps, each c agent-steps), a multiple of frames_per_batch. 1.2M is the
    budget of Table III's MADDPG runs: 200 iterations, 200,000 gradient steps, 1.5-1.9 core-hours
    (docs/formation_benchmarl.md, "Budget")."""
    n_envs: int = 10
    """Envs stepped as one batch (BenchMARL's default)."""
    episodes_per_iteration: int = 6
    """Episodes each env plays per iteration: an iteration collects n_envs x this x 100 frames (6000 at
    the defaults, BenchMARL's frames per batch) and always ends at the episodes' end."""
    reward_scale: float = 0.01
    """Factor on each agent's reward before BenchMARL sees it (1: unscaled). R_L is about -100 per step
    (std 170) under random actions; BenchMARL's critics have no value normalisation, which our MAPPO
    trainer has. A positive factor leaves the optimal policy alone."""
    gamma: float = 0.8
    """Discount per step (our low-level trainer's and the paper's; BenchMARL's default is 0.99)."""
    lr: float = 5e-5
    """Adam learning rate of every network (BenchMARL's default)."""
    updates: int = 1000
    """maddpg, masac: gradient steps after each iteration (BenchMARL's off_policy_n_optimizer_steps)."""
    batch_size: int = 128
    """maddpg, masac: frames per gradient step, drawn uniformly from the replay (BenchMARL's default)."""
    memory_frames: int = 100_000
    """maddpg, masac: replay capacity in frames. BenchMARL's default is 1e6, but its replay storage is
    allocated whole and saved whole in every checkpoint: a frame at c = 6 holds about 1150 numbers
    (both observations of 6 agents and both global states), 4.6 GB at 1e6 frames, 0.46 GB at 1e5."""
    exploration_anneal_frames: int = 400_000
    """maddpg: frames over which its Gaussian exploration noise falls from sigma 0.8 to 0.01 m/s^2
    (BenchMARL's defaults). BenchMARL's own rule is a third of the budget; this is that third of the
    first proposed budget, 1.2M frames, fixed so that a run trained in legs (--resume with a larger budget) follows
    the schedule of one trained at once."""
    epochs: int = 45
    """ippo, mappo: passes over each iteration's frames (BenchMARL's on_policy_n_minibatch_iters)."""
    minibatch_size: int = 400
    """ippo, mappo: frames per minibatch (BenchMARL's default)."""
    hidden: int = 128
    """Width of AT-M's actor modules (AT-M's 128)."""
    critic_cells: tuple[int, ...] = (256, 256)
    """Hidden layers of BenchMARL's critic MLP (tanh; BenchMARL's default)."""
    checkpoint_every: int = 5
    """Write BenchMARL's resumable checkpoint every this many iterations (and at the end)."""
    eval_episodes: int = 50
    """Episodes of Table III's protocol (density 0.05, 100 steps) flown by the exported policy for the
    model card, on the validation batch cefc_mj.seeds.FORMATION_VALIDATION_SEED; 0 skips."""
    threads: int = 1
    """torch threads of the whole run (collection and updates)."""

    def __post_init__(self) -> None:
        self._normalise(("reward_scale", "gamma", "lr"))
        self.validate()

    # ------------------------------------------------------------------ derived
    @property
    def name(self) -> str:
        """Run folder and policy file stem: benchmarl_<algorithm>_c<c>, then _step1 for Step 1's
        scenario and _seed<k> for seeds other than 0."""
        return (
            f"benchmarl_{self.algorithm}_c{self.formation}"
            + ("_step1" if self.step == 1 else "")
            + (f"_seed{self.seed}" if self.seed else "")
        )

    @property
    def on_policy(self) -> bool:
        return self.algorithm in ON_POLICY

    @property
    def episode_steps(self) -> int:
        from cefc_mj.task.config import FORMATION_EPISODE_STEPS

        return FORMATION_EPISODE_STEPS

    @property
    def frames_per_batch(self) -> int:
        """Frames (env-steps) per iteration: whole episodes in every env."""
        return self.n_envs * self.episodes_per_iteration * self.episode_steps

    @property
    def iterations(self) -> int:
        return self.budget_frames // self.frames_per_batch

    @property
    def agent_steps(self) -> int:
        return self.budget_frames * self.formation

    def stage(self):
        """The AT-M stage (`LowLevelConfig`) whose task is trained."""
        from cefc_mj.train.config import Budget, LowLevelConfig

        return LowLevelConfig(formation=self.formation, step=self.step, budget=Budget(iterations=1), seed=self.seed)

    def task(self):
        """The TaskConfig trained on: the AT-M stage's (`lowlevel.task_config_for`)."""
        from cefc_mj.train.lowlevel import task_config_for

        return task_config_for(self.stage())

    # ------------------------------------------------------------------ validation
    def validate(self) -> None:
        if self.algorithm not in FORMATION_ALGORITHMS:
            _fail("algorithm", self.algorithm, f"must be one of {', '.join(FORMATION_ALGORITHMS)}")
        _check_int("formation", self.formation, 3, 8)
        if self.step not in (1, 2) or isinstance(self.step, bool):
            _fail("step", self.step, "must be 1 (no obstacles) or 2 (density 0.03, the scenario of Steps 2 and 3)")
        _check_int("seed", self.seed, 0, MAX_SEED)
        _check_int("n_envs", self.n_envs, 1, MAX_ENVS)
        _check_int("episodes_per_iteration", self.episodes_per_iteration, 1, 10_000)
        _check_int("budget_frames", self.budget_frames, 1, MAX_FRAMES)
        if self.budget_frames % self.frames_per_batch:
            _fail(
                "budget_frames",
                self.budget_frames,
                f"must be a multiple of the {self.frames_per_batch} frames of an iteration "
                f"({self.n_envs} envs x {self.episodes_per_iteration} episodes x {self.episode_steps} steps)",
            )
        self._check_optimisation()
        _check_int("updates", self.updates, 1, 1_000_000)
        _check_int("batch_size", self.batch_size, 1, 1_000_000)
        _check_int("memory_frames", self.memory_frames, 1, MAX_FRAMES)
        _check_int("exploration_anneal_frames", self.exploration_anneal_frames, 1, MAX_FRAMES)
        _check_int("epochs", self.epochs, 1, 10_000)
        _check_int("minibatch_size", self.minibatch_size, 1, 1_000_000)
        if self.on_policy and self.minibatch_size > self.frames_per_batch:
            _fail(
                "minibatch_size",
                self.minibatch_size,
                f"must be at most the {self.frames_per_batch} frames of an iteration",
            )
        self._check_networks()
        _check_int("checkpoint_every", self.checkpoint_every, 1, 1_000_000)
        self._check_run()


FORMATION_FLAG_OF_FIELD = {
    "algorithm": "--algorithm",
    "formation": "--formation",
    "step": "--step",
    "seed": "--seed",
    "budget_frames": "--budget",
    "n_envs": "--envs",
    "episodes_per_iteration": "--episodes-per-iteration",
    "reward_scale": "--reward-scale",
    "gamma": "--gamma",
    "lr": "--lr",
    "updates": "--updates",
    "batch_size": "--batch-size",
    "memory_frames": "--memory",
    "exploration_anneal_frames": "--anneal-frames",
    "epochs": "--epochs",
    "minibatch_size": "--minibatch-size",
    "checkpoint_every": "--checkpoint-every",
    "eval_episodes": "--eval-episodes",
    "threads": "--threads",
}
"""Config fields set by `cefc-train formation-benchmarl` flags (argparse dest = field)."""
ALGORITHM_FIELDS = {
    "updates": OFF_POLICY,
    "batch_size": OFF_POLICY,
    "memory_frames": OFF_POLICY,
    "exploration_anneal_frames": ("maddpg",),
    "epochs": ON_POLICY,
    "minibatch_size": ON_POLICY,
}
"""The fields only some algorithms read: a flag given for another algorithm is an error, not ignored."""


def formation_config_from_args(args, budget_frames: int) -> FormationBenchMARLConfig:
    """The FormationBenchMARLConfig of `cefc-train formation-benchmarl` arguments (flags left out keep
    the config's defaults); a bad value raises ConfigError naming the flag."""
    from cefc_mj.train.config import flag_error

    given = _given_flags(args, FORMATION_FLAG_OF_FIELD, "budget_frames")
    try:
        algorithm = given.get("algorithm", FormationBenchMARLConfig.algorithm)
        for name, algorithms in ALGORITHM_FIELDS.items():
            if name in given and algorithm not in algorithms:
                raise ConfigError(
                    f"{FORMATION_FLAG_OF_FIELD[name]}: a setting of {', '.join(algorithms)}, not {algorithm}'s"
                )
        cfg = FormationBenchMARLConfig(budget_frames=budget_frames, **given)
    except ConfigError as e:
        raise flag_error(e, FORMATION_FLAG_OF_FIELD) from None
    return cfg
