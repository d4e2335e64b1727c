"""One episode of the hierarchical CEFC game, recorded for Rerun and drawn as message-similarity
matrices (the paper's Fig. 12).

`play_highlevel_episode` flies one episode with the evaluation's own loop (`play_highlevel`, so
seed s gives the episode of a 1-episode evaluation with seed s) and keeps every low-level step's
state and every decision's anchors and messages in a `HighLevelEpisode`. `log_highlevel_episode`
sends it to a Rerun recording (entity paths in docs/rerun.md, "The hierarchical game"),
`record_highlevel_episode` writes it as a `.rrd` file, and `plot_similarity_matrices` draws a PNG of
the message similarity at a few decisions. `plot_game_moments` draws the paper's Fig. 11 (paths,
groups and chosen anchors at four moments) and `write_game_figures` Figs. 11 and 12 at the same four
evenly spaced decisions. A game played over SITL-M (`cefc_mj.deploy.game.SitlGameResult.episode`)
comes as the same `HighLevelEpisode`, its messages and anchors as the simulator received them: a
missing message is a NaN row (NaN similarity row and column), a missing anchor index -1.

Rows of the per-step arrays are states: row s is the state after s low-level steps (row 0 the reset
state, row T the end), so decision k is taken at row k * decision_interval, from the state shown
there. Reward arrays have one entry per low-level step: entry s - 1 is the reward of step s.

>>> from cefc_mj.game_protocol import game_task
>>> from cefc_mj.hierarchy import load_low_level
>>> from cefc_mj.nn.highlevel_policy import load_highlevel_policy
>>> policy, meta = load_highlevel_policy("policies/cihrl_consmac_a.pt")       # doctest: +SKIP
>>> episode = play_highlevel_episode(policy, game_task(), load_low_level("atm_student", game_task()))  # doctest: +SKIP
>>> record_highlevel_episode(episode, "game.rrd")                             # doctest: +SKIP
>>> plot_similarity_matrices(episode, "similarity.png")                       # doctest: +SKIP
"""

from __future__ import annotations

import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import torch

from cefc_mj.errors import ConfigError
from cefc_mj.eval.record import code_provenance
from cefc_mj.fileio import atomic_write
from cefc_mj.game_protocol import play_highlevel
from cefc_mj.hierarchy import DECISION_INTERVAL, HierarchicalCEFCEnv, LowLevel
from cefc_mj.nn.highlevel_policy import HighLevelPolicy
from cefc_mj.sim.particle import ParticleWorld
from cefc_mj.task.config import LEARNED_ADVERSARY, TaskConfig
from cefc_mj.viz.rerun_log import _segments_arrow, close_recording, group_colors, open_recording

REWARD_PARTS = ("R_t", "R_n", "R_e")
"""The weighted parts of R_H = R_t + R_n + R_e (10 R_t + 0.1 R_n + 100 R_e of the unweighted terms)."""
PLANE_Z = 0.0  # the particle game is planar: everything is drawn on z = 0
_ALERT_SEGMENTS = 48


@dataclass
class HighLevelEpisode:
    """One hierarchical episode (no batch axis). T low-level steps, K = T / decision_interval
    decisions, N agents, J targets, M obstacles, D message numbers. Positions in metres (world frame)."""

    variant: str
    """The high-level policy's variant (consmac-a, consmac-o, mappo, tarmac)."""
    seed: int
    """The episode's seed (`HierarchicalCEFCEnv(seed=...)` and `reset(seed=...)`)."""
    backend: str
    """"particle" or "mujoco"."""
    adversary_rule: str
    """`TaskConfig.adversary`."""
    low_level: dict
    """`LowLevel.describe()` plus its name."""
    dt: float
    """Seconds per low-level step."""
    decision_interval: int
    """Low-level steps per decision."""
    arena_half_size: float
    """The arena is [-a, a]^2."""
    obstacle_radius: float
    """Radius of every obstacle (m)."""
    target_radius: float
    """A target counts as covered by a formation within this distance (m)."""
    alert_distance: float
    """E counts steps with some agent closer than this to the adversary (m)."""
    obstacles: np.ndarray
    """[M, 2] obstacle centres."""
    targets: np.ndarray
    """[J, 2] target positions (fixed for the episode)."""
    anchor_grid: np.ndarray
    """[A, 2] the candidate anchors; an anchor index points into it."""
    agent_pos: np.ndarray
    """[T + 1, N, 2] true UAV positions; row s after s low-level steps."""
    agent_vel: np.ndarray
    """[T + 1, N, 2] true UAV velocities (m/s)."""
    adversary_pos: np.ndarray | None
    """[T + 1, 2] the adversary's position (None without an adversary)."""
    adversary_goal: np.ndarray | None
    """[T + 1, 2] the point the adversary rule chases from the state of row s, i.e. during step
    s + 1: `adversary_goal(rule, ...)` on the same public state the env reads (for row T, the point
    it would chase next). None without an adversary."""
    urgency: np.ndarray
    """[T + 1, J] each target's urgency (1 at the start, decays while covered)."""
    group_label: np.ndarray
    """[T + 1, N] the env's group labels (connected components under the observation distance,
    each labelled by its smallest member index)."""
    group_size: np.ndarray
    """[T + 1, N] the size of each agent's group."""
    reward: np.ndarray
    """[T] R_H of each low-level step."""
    reward_parts: dict[str, np.ndarray]
    """R_t, R_n, R_e (weighted, they sum to R_H) of each low-level step, each [T]."""
    anchor_index: np.ndarray
    """[K, N] each agent's chosen anchor index at decision k (-1: unknown, in a SITL-M game an agent
    whose message did not reach the simulator)."""
    anchors: np.ndarray
    """[K, N, 2] the chosen anchors' coordinates (NaN where the index is -1)."""
    received: np.ndarray | None
    """[K, N] how many messages each agent heard at decision k (None without communication)."""
    messages: np.ndarray | None
    """[K, N, D] the message each agent sent at decision k (None without communication; a NaN row:
    the message did not arrive, in a SITL-M game)."""
    similarity: np.ndarray | None
    """[K, N, N] `message_similarity(messages)` (None without communication; NaN rows and columns
    for missing messages)."""
    metrics: dict[str, float]
    """The episode's F, N (steps), C (% of agent-steps), E (steps)."""
    returns: dict[str, float]
    """R_H and its weighted parts R_t, R_n, R_e summed over the episode (as the evaluation sums them)."""
    policy: str = ""
    """The policy file's name (stem), when the caller knows it."""
    policy_sha256: str = ""
    """The SHA-256 of the policy file, when the caller knows it."""
    provenance: dict[str, str] = field(default_factory=code_provenance)
    """The code that flew the episode (`cefc_mj.eval.record.code_provenance`)."""
    condition: str = ""
    """How the game was played, when not in one process: "SITL-M" (every UAV's hierarchy in its own
    process, `cefc_mj.deploy.game.SitlGameResult.episode`)."""

    @property
    def n_steps(self) -> int:
        return len(self.reward)

    @property
    def n_agents(self) -> int:
        return self.agent_pos.shape[1]

    @property
    def n_decisions(self) -> int:
        return len(self.anchor_index)

    @property
    def decision_rows(self) -> np.ndarray:
        """[K] the row (low-level step) at which each decision is taken."""
        return np.arange(self.n_decisions) * self.decision_interval

    def anchor_per_row(self) -> np.ndarray:
        """[T + 1, N, 2] the anchor each agent flies to from row s (the last decision's at row T)."""
        k = np.minimum(np.arange(self.n_steps + 1) // self.decision_interval, self.n_decisions - 1)
        return self.anchors[k]


def message_similarity(messages: np.ndarray) -> np.ndarray:
    """Cosine similarity of the agents' messages: [..., N, D] -> [..., N, N].

    S_ij = m_i . m_j / (|m_i| |m_j|), and 0 in every entry of a zero message's row and column
    (its diagonal entry included). Exactly symmetric, 1 on the diagonal of nonzero messages,
    clipped to [-1, 1]; computed in float64. A message with a NaN or infinite number (a missing one,
    in a SITL-M game) has NaN in its row and column."""
    m = np.asarray(messages, dtype=np.float64)
    missing = ~np.isfinite(m).all(axis=-1)
    m = np.where(missing[..., None], 0.0, m)
    norm = np.linalg.norm(m, axis=-1, keepdims=True)
    unit = np.divide(m, norm, out=np.zeros_like(m), where=norm > 0)
    s = unit @ np.swapaxes(unit, -1, -2)
    s = np.clip(0.5 * (s + np.swapaxes(s, -1, -2)), -1.0, 1.0)
    diagonal = np.arange(m.shape[-2])
    s[..., diagonal, diagonal] = (norm[..., 0] > 0).astype(np.float64)
    if missing.any():
        s[missing[..., :, None] | missing[..., None, :]] = np.nan
    return s


def similarity_floor(similarity: np.ndarray) -> float:
    """The low end of the colour scale: the smallest value rounded down to 0.05, at most 0.9. Messages
    are often alike to 0.85 and more (an untrained ConsMAC's are), so a [-1, 1] scale would show one
    colour; the paper's Fig. 12 also spans only the values it shows. NaN entries are left out."""
    values = np.asarray(similarity, dtype=np.float64)
    values = values[~np.isnan(values)]
    return min(0.9, float(np.floor(np.min(values) * 20) / 20)) if values.size else 0.0


# ---------------------------------------------------------------------------- playing
class _StepTap:
    """Stands in for the game's `BatchedCEFCEnv`, passes everything through, and keeps the state
    after the reset (`on_reset()`) and the state and reward terms after each low-level step."""

    def __init__(self, env, on_reset, on_step):
        self._env, self._on_reset, self._on_step = env, on_reset, on_step

    def __getattr__(self, name):
        return getattr(self._env, name)

    def reset(self, *args, **kwargs):
        obs = self._env.reset(*args, **kwargs)
        self._on_reset()
        return obs

    def step(self, actions):
        obs, reward, done, info = self._env.step(actions)
        self._on_step(reward, info["reward_terms"])
        return obs, reward, done, info


@torch.no_grad()
def play_highlevel_episode(
    policy: HighLevelPolicy,
    task: TaskConfig,
    low_level: LowLevel,
    seed: int = 0,
    world=None,
    decision_interval: int = DECISION_INTERVAL,
    adversary_policy=None,
) -> HighLevelEpisode:
    """Fly one episode of the hierarchical game (mode of each anchor distribution, as the evaluation)
    and record it. world: a physics world of 1 env (default the particle world); adversary_policy:
    the trained adversary of a task with adversary='learned' (its goal drawn is the nearest group of
    >= 3, the point it is trained to chase)."""
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        raise ConfigError(f"seed={seed!r}: must be an integer >= 0")
    game = HierarchicalCEFCEnv(
        task,
        low_level,
        n_envs=1,
        seed=seed,
        decision_interval=decision_interval,
        world=world,
        adversary_policy=adversary_policy,
    )
    env = game.env
    goal_rule = "nearest_group" if task.adversary == LEARNED_ADVERSARY else task.adversary
    weights = {
        "R_t": task.rewards.task_weight,
        "R_n": task.rewards.navigation_weight_high,
        "R_e": task.rewards.evasion_weight,
    }
    has_adversary = task.adversary != "none"
    rows: dict[str, list] = {
        k: []
        for k in ("agent_pos", "agent_vel", "adversary_pos", "adversary_goal", "urgency", "group_label", "group_size")
    }
    step_rewards: list[float] = []
    step_parts: dict[str, list[float]] = {name: [] for name in weights}

    def capture() -> None:
        w = env.world
        rows["agent_pos"].append(w.agent_pos[0].copy())
        rows["agent_vel"].append(w.agent_vel[0].copy())
        rows["urgency"].append(env.urgency[0].copy())
        rows["group_label"].append(env.labels[0].copy())
        rows["group_size"].append(game.agent_group_size()[0].copy())
        if has_adversary:  # the goal env.step computes first thing in the next step, from this state
            rows["adversary_pos"].append(w.adversary_pos[0].copy())
            rows["adversary_goal"].append(env.rule_adversary_goal(goal_rule)[0].copy())

    def on_step(reward, terms) -> None:
        step_rewards.append(float(reward[0]))
        for name, weight in weights.items():
            step_parts[name].append(float(weight * terms[name][0]))
        capture()

    game.env = _StepTap(env, capture, on_step)
    indices, messages, received = [], [], []

    def on_decision(inbox, index, message) -> None:
        if message is not None:
            messages.append(np.array(message[0], dtype=np.float32))
            received.append(inbox.received[0].copy())
        indices.append(np.array(index[0], dtype=np.int64))

    try:
        result = play_highlevel(policy, game, seed, on_decision)  # the evaluation's own loop
    finally:
        game.env = env

    arr = {k: np.asarray(v) for k, v in rows.items() if v}
    anchor_index = np.stack(indices)
    sent = np.stack(messages) if messages else None
    return HighLevelEpisode(
        variant=policy.variant,
        seed=seed,
        backend="particle" if isinstance(env.world, ParticleWorld) else "mujoco",
        adversary_rule=task.adversary,
        low_level={"name": low_level.name, **low_level.describe()},
        dt=task.dt,
        decision_interval=decision_interval,
        arena_half_size=task.arena_half_size,
        obstacle_radius=task.obstacle_radius,
        target_radius=task.target_radius,
        alert_distance=task.rewards.evasion_alert_distance,
        obstacles=env.obstacles[0].copy(),
        targets=env.targets[0].copy(),
        anchor_grid=game.grid.copy(),
        agent_pos=arr["agent_pos"],
        agent_vel=arr["agent_vel"],
        adversary_pos=arr.get("adversary_pos"),
        adversary_goal=arr.get("adversary_goal"),
        urgency=arr["urgency"],
        group_label=arr["group_label"],
        group_size=arr["group_size"],
        reward=np.asarray(step_rewards),
        reward_parts={k: np.asarray(v) for k, v in step_parts.items()},
        anchor_index=anchor_index,
        anchors=game.grid[anchor_index],
        received=np.stack(received) if received else None,
        messages=sent,
        similarity=None if sent is None else message_similarity(sent),
        metrics={m: float(game.episode_metrics()[m][0]) for m in ("F", "N", "C", "E")},
        returns={name: float(result[name][0]) for name in ("R_H", *weights)},
    )


# ---------------------------------------------------------------------------- Rerun
def highlevel_blueprint() -> rrb.Blueprint:
    """The arena seen from above on the left; on the right the message similarity matrix of the
    current decision, the reward parts per step, the mean similarity per decision, the episode card."""
    top_down = rrb.EyeControls3D(
        kind=rrb.Eye3DKind.Orbital, position=[0.0, -4.0, 30.0], look_target=[0.0, 0.0, 0.0], eye_up=[0.0, 0.0, 1.0]
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="Arena", origin="world", eye_controls=top_down),
            rrb.Vertical(
                rrb.TensorView(
                    name="Message similarity (row i, column j)",
                    origin="messages/similarity",
                    scalar_mapping=rrb.TensorScalarMapping(mag_filter="Nearest", colormap="Viridis"),
                    view_fit="Fill",
                ),
                rrb.TimeSeriesView(name="R_H = R_t + R_n + R_e per step (weighted)", origin="rewards"),
                rrb.TimeSeriesView(name="Mean message similarity", origin="messages/mean"),
                rrb.Tabs(
                    rrb.TextDocumentView(name="Episode", origin="episode"),
                    rrb.TextLogView(name="Decisions", origin="decisions"),
                ),
                row_shares=[3, 2, 2, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="step"),
    )


def record_highlevel_episode(
    episode: HighLevelEpisode, rrd_path: str | os.PathLike, recording_id: str | None = None
) -> Path:
    """Write the episode to a `.rrd` file with its blueprint; returns the path."""
    recording = open_recording(
        rrd_path=rrd_path, recording_id=recording_id or str(uuid.uuid4()), blueprint=highlevel_blueprint()
    )
    try:
        log_highlevel_episode(episode, recording)
    finally:
        close_recording(recording)
    return Path(rrd_path)


def log_highlevel_episode(episode: HighLevelEpisode, recording: rr.RecordingStream) -> None:
    """Send the episode to `recording`: static scene, one row per low-level step on the `step` and
    `sim_time` timelines, the messages at each decision. Send `highlevel_blueprint()` with it
    (`record_highlevel_episode` does)."""
    ep, rec = episode, recording
    n, j, rows = ep.n_agents, len(ep.targets), ep.n_steps + 1
    steps = np.arange(rows)
    index = [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=steps * ep.dt)]
    on_plane = lambda xy: np.concatenate([xy, np.full((*xy.shape[:-1], 1), PLANE_Z)], axis=-1)  # noqa: E731

    # static scene
    rec.send_recording_name(f"{ep.policy or ep.variant} seed={ep.seed} ({_played_text(ep)})")
    rec.send_property("provenance", rr.AnyValues(**provenance_fields(ep)))
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log("episode", rr.TextDocument(_episode_markdown(ep), media_type="text/markdown"), static=True)
    a = ep.arena_half_size
    rec.log(
        "world/arena",
        rr.LineStrips3D(
            [on_plane(np.array([[-a, -a], [a, -a], [a, a], [-a, a], [-a, -a]]))], colors=[160, 160, 160], radii=0.03
        ),
        static=True,
    )
    if len(ep.obstacles):
        m = len(ep.obstacles)
        rec.log(
            "world/obstacles",
            rr.Cylinders3D(
                lengths=np.full(m, 1.0),
                radii=np.full(m, ep.obstacle_radius),
                centers=on_plane(ep.obstacles) + [0.0, 0.0, 0.5],
                colors=[150, 150, 150, 160],
                fill_mode="solid",
            ),
            static=True,
        )
    rec.log(
        "world/anchor_grid",
        rr.Points3D(
            on_plane(ep.anchor_grid),
            radii=0.12,
            colors=[0, 200, 80, 120],
            labels=[str(i) for i in range(len(ep.anchor_grid))],
        ),
        static=True,
    )
    circle = 2 * np.pi * np.arange(_ALERT_SEGMENTS + 1) / _ALERT_SEGMENTS
    unit_circle = np.column_stack([np.cos(circle), np.sin(circle), np.zeros_like(circle)])

    # UAVs: positions and group colours per step, labels static
    colors = group_colors(ep.group_label)  # [rows, N, 3]
    rec.log("world/uavs", rr.Points3D.from_fields(radii=0.2, labels=[f"uav {i}" for i in range(n)]), static=True)
    rr.send_columns(
        "world/uavs",
        index,
        rr.Points3D.columns(positions=on_plane(ep.agent_pos).reshape(-1, 3), colors=colors.reshape(-1, 3)).partition(
            np.full(rows, n)
        ),
        recording=rec,
    )

    # anchors: each agent's anchor from this row on, and a line to it in the agent's group colour
    anchor = ep.anchor_per_row()  # [rows, N, 2]
    rec.log("world/anchors", rr.Points3D.from_fields(radii=0.3, colors=[0, 200, 80]), static=True)
    rr.send_columns(
        "world/anchors",
        index,
        rr.Points3D.columns(positions=on_plane(anchor).reshape(-1, 3), labels=_anchor_labels(ep, anchor)).partition(
            np.full(rows, n)
        ),
        recording=rec,
    )
    rec.log("world/anchors/lines", rr.LineStrips3D.from_fields(radii=0.02), static=True)
    lines = np.stack([on_plane(ep.agent_pos), on_plane(anchor)], axis=2).reshape(rows * n, 2, 3)
    rr.send_columns(
        "world/anchors/lines",
        index,
        rr.LineStrips3D.columns(strips=_segments_arrow(lines), colors=colors.reshape(-1, 3)).partition(
            np.full(rows, n)
        ),
        recording=rec,
    )

    # targets: the radius grows with the urgency, the label shows it
    if j:
        rec.log("world/targets", rr.Points3D.from_fields(colors=[230, 180, 0]), static=True)
        rr.send_columns(
            "world/targets",
            index,
            rr.Points3D.columns(
                positions=np.broadcast_to(on_plane(ep.targets), (rows, j, 3)).reshape(-1, 3),
                radii=(0.15 + 0.45 * ep.urgency).reshape(-1),
                labels=[f"target {t}: urgency {u:.2f}" for row in ep.urgency for t, u in enumerate(row)],
            ).partition(np.full(rows, j)),
            recording=rec,
        )
        rec.log(
            "world/targets/zone",
            rr.LineStrips3D(
                [on_plane(t) + ep.target_radius * unit_circle for t in ep.targets],
                colors=[230, 180, 0],
                radii=0.02,
            ),
            static=True,
        )

    # adversary: position, the goal its rule chases, the alert circle of the E metric
    if ep.adversary_pos is not None:
        adv, goal = on_plane(ep.adversary_pos), on_plane(ep.adversary_goal)
        rec.log(
            "world/adversary", rr.Points3D.from_fields(radii=0.3, colors=[200, 0, 0], labels="adversary"), static=True
        )
        rr.send_columns("world/adversary", index, rr.Points3D.columns(positions=adv), recording=rec)
        rec.log(
            "world/adversary/goal",
            rr.Points3D.from_fields(radii=0.12, colors=[255, 90, 90], labels="goal"),
            static=True,
        )
        rr.send_columns("world/adversary/goal", index, rr.Points3D.columns(positions=goal), recording=rec)
        rec.log("world/adversary/chase", rr.LineStrips3D.from_fields(radii=0.015, colors=[255, 90, 90]), static=True)
        rr.send_columns(
            "world/adversary/chase",
            index,
            rr.LineStrips3D.columns(strips=_segments_arrow(np.stack([adv, goal], axis=1))),
            recording=rec,
        )
        rec.log(
            "world/adversary/alert",
            rr.LineStrips3D([ep.alert_distance * unit_circle], colors=[200, 0, 0], radii=0.015),
            static=True,
        )
        rr.send_columns("world/adversary/alert", index, rr.Transform3D.columns(translation=adv), recording=rec)

    # reward parts of each low-level step, logged at the row the step ends in
    after = [rr.TimeColumn("step", sequence=steps[1:]), rr.TimeColumn("sim_time", duration=steps[1:] * ep.dt)]
    for name in ("R_H", *REWARD_PARTS):
        series = ep.reward if name == "R_H" else ep.reward_parts[name]
        rr.send_columns(f"rewards/{name}", after, rr.Scalars.columns(scalars=series), recording=rec)

    # decisions: the anchors (text) and, with communication, the message similarity
    at = ep.decision_rows
    when = [rr.TimeColumn("step", sequence=at), rr.TimeColumn("sim_time", duration=at * ep.dt)]
    rr.send_columns(
        "decisions",
        when,
        rr.TextLog.columns(
            text=[_decision_line(ep, k) for k in range(ep.n_decisions)], level=["INFO"] * ep.n_decisions
        ),
        recording=rec,
    )
    if ep.similarity is not None:
        low = similarity_floor(ep.similarity)
        for k, row in enumerate(at):
            rec.set_time("step", sequence=int(row))
            rec.set_time("sim_time", duration=float(row * ep.dt))
            rec.log(
                "messages/similarity",
                rr.Tensor(
                    ep.similarity[k].astype(np.float32), dim_names=["agent i", "agent j"], value_range=[low, 1.0]
                ),
            )
        rec.reset_time()
        same, other = _mean_similarity(ep)
        for name, series in (("same_anchor", same), ("other_anchor", other)):
            keep = ~np.isnan(series)  # no pair of that kind at this decision: no point
            if keep.any():
                rr.send_columns(
                    f"messages/mean/{name}",
                    [rr.TimeColumn("step", sequence=at[keep]), rr.TimeColumn("sim_time", duration=at[keep] * ep.dt)],
                    rr.Scalars.columns(scalars=series[keep]),
                    recording=rec,
                )


def provenance_fields(episode: HighLevelEpisode) -> dict[str, str | int | float]:
    """The `provenance` recording property: policy, its SHA-256, variant, low level, game, seed,
    the episode's metrics and returns, the code that flew it ("n/a" where unknown)."""
    ep = episode
    low_file = ep.low_level.get("file") or {}
    fields: dict[str, str | int | float] = {
        "policy": ep.policy,
        "policy_sha256": ep.policy_sha256,
        "variant": ep.variant,
        "low_level": ep.low_level.get("name", ""),
        "low_level_sha256": low_file.get("sha256", ""),
        "backend": ep.backend,
        "condition": ep.condition or "one process",
        "adversary": ep.adversary_rule,
        "seed": ep.seed,
        "agents": ep.n_agents,
        "steps": ep.n_steps,
        "decision_interval": ep.decision_interval,
        "dt": ep.dt,
        **ep.metrics,
        **ep.returns,
        **ep.provenance,
    }
    return {k: "n/a" if v == "" else v for k, v in fields.items()}


def _anchor_labels(ep: HighLevelEpisode, anchor: np.ndarray) -> list[str]:
    """One label per anchor point and row: the first agent at an anchor names all who chose it (an
    unknown anchor, NaN, has none)."""
    labels = []
    for row in anchor:
        seen: dict[tuple, list[int]] = {}
        for i, point in enumerate(map(tuple, row)):
            if np.isfinite(point).all():
                seen.setdefault(point, []).append(i)
        first = {members[0]: (point, members) for point, members in seen.items()}
        for i in range(len(row)):
            if i in first:
                (x, y), members = first[i]
                labels.append(f"({x:g}, {y:g}): uav {', '.join(map(str, members))}")
            else:
                labels.append("")
    return labels


def _decision_line(ep: HighLevelEpisode, k: int) -> str:
    row = ep.decision_rows[k]
    picks = ", ".join(f"{i}->{_anchor_text(xy)}" for i, xy in enumerate(ep.anchors[k]))
    groups = _group_text(ep.group_label[row])
    heard = "" if ep.received is None else f"; heard {ep.received[k].tolist()}"
    missing = [] if ep.messages is None else np.flatnonzero(~np.isfinite(ep.messages[k]).all(axis=-1)).tolist()
    lost = f"; no message from {missing}" if missing else ""
    return f"decision {k} at step {row}: anchors {picks}; groups {groups}{heard}{lost}"


def _anchor_text(xy) -> str:
    """ "(x,y)" of an anchor, "none" for an unknown one (NaN)."""
    x, y = xy
    return f"({x:g},{y:g})" if np.isfinite(xy).all() else "none"


def _played_text(ep: HighLevelEpisode) -> str:
    return f"{ep.backend}, {ep.condition}" if ep.condition else ep.backend


def _group_text(labels: np.ndarray) -> str:
    return " ".join("{" + ",".join(str(i) for i in np.flatnonzero(labels == g)) + "}" for g in np.unique(labels))


def _mean_similarity(ep: HighLevelEpisode) -> tuple[np.ndarray, np.ndarray]:
    """Mean off-diagonal similarity per decision among agents with the same anchor and with different
    anchors ([K] each, NaN where there is no such pair)."""
    same_anchor = ep.anchor_index[:, :, None] == ep.anchor_index[:, None, :]  # [K, N, N]
    off_diagonal = ~np.eye(ep.n_agents, dtype=bool)
    known = ~np.isnan(ep.similarity) & (ep.anchor_index >= 0)[:, :, None] & (ep.anchor_index >= 0)[:, None, :]
    out = []
    for mask in (same_anchor & off_diagonal & known, ~same_anchor & known):
        count = mask.sum(axis=(1, 2))
        total = np.where(mask, ep.similarity, 0.0).sum(axis=(1, 2))
        out.append(np.where(count > 0, total / np.maximum(count, 1), np.nan))
    return out[0], out[1]


def _missing_text(ep: HighLevelEpisode) -> str:
    """How many (decision, UAV) messages did not arrive (NaN rows; only a SITL-M game has any)."""
    if ep.messages is None:
        return "n/a (no communication)"
    missing = ~np.isfinite(ep.messages).all(axis=-1)
    return f"{int(missing.sum())} of {missing.size} (recorded as NaN, never invented)"


def _episode_markdown(ep: HighLevelEpisode) -> str:
    code = ep.provenance
    libraries = ", ".join(f"{name} {code[name]}" for name in ("python", "numpy", "torch") if name in code)
    low_file = ep.low_level.get("file") or {}
    comm = (
        "no communication" if ep.messages is None else f"{ep.messages.shape[-1]} numbers per message, once per decision"
    )
    return "\n".join(
        [
            f"# Hierarchical game, {ep.policy or ep.variant}, seed {ep.seed}"
            + (f" ({ep.condition})" if ep.condition else ""),
            "",
            "| | |",
            "|---|---|",
            f"| high level | {ep.variant} ({comm}) |",
            f"| low level | {ep.low_level.get('name', 'n/a')} |",
            f"| backend, adversary | {ep.backend}, {ep.adversary_rule} |",
            f"| played | {ep.condition or 'one process'} |",
            f"| messages missing | {_missing_text(ep)} |",
            f"| UAVs, targets, obstacles | {ep.n_agents}, {len(ep.targets)}, {len(ep.obstacles)} |",
            f"| steps | {ep.n_steps} (dt = {ep.dt} s), a decision every {ep.decision_interval} |",
            f"| R_H = R_t + R_n + R_e | {ep.returns['R_H']:.1f} = {ep.returns['R_t']:.1f} + {ep.returns['R_n']:.1f} "
            f"+ {ep.returns['R_e']:.1f} (per-episode sums) |",
            f"| F, N, C, E | {ep.metrics['F']:.1f}, {ep.metrics['N']:.0f}, {ep.metrics['C']:.2f} %, "
            f"{ep.metrics['E']:.0f} |",
            "",
            "## Provenance",
            "",
            "| | |",
            "|---|---|",
            f"| policy | {ep.policy or 'n/a'} |",
            f"| policy SHA-256 | `{ep.policy_sha256 or 'n/a'}` |",
            f"| low-level SHA-256 | `{low_file.get('sha256') or 'n/a'}` |",
            f"| git commit | `{code.get('git_commit') or 'n/a'}` |",
            f"| cefc-mj | {code.get('cefc_mj', 'n/a')} (code `{code.get('code_version', 'n/a')}`) |",
            f"| libraries | {libraries or 'n/a'} |",
        ]
    )


# ---------------------------------------------------------------------------- PNG
def plot_similarity_matrices(
    episode: HighLevelEpisode,
    png_path: str | os.PathLike,
    decisions: list[int] | None = None,
    dpi: int = 110,
    agents: list[int] | None = None,
    cols: int | None = None,
    title: str | None = None,
) -> Path:
    """A PNG grid of the message similarity matrices at a few decisions (default 6 evenly spaced),
    each titled with its decision and step, the axes labelled with every agent's anchor and group,
    and the mean same- and other-anchor similarity over the episode (all agents) beneath. agents:
    only these agents' rows and columns (default all; the paper's Fig. 12 shows UAVs 1-4, agents
    0-3 here); cols: matrices per row (default up to 3). A missing message (NaN, a SITL-M game) is
    a blank row and column marked "-". Written atomically. ConfigError for an episode without
    messages or a decision or agent out of range."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    ep = episode
    if ep.similarity is None:
        raise ConfigError(f"plot_similarity_matrices: the {ep.variant} policy sends no messages")
    if decisions is None:
        decisions = sorted(set(np.linspace(0, ep.n_decisions - 1, min(6, ep.n_decisions)).round().astype(int)))
    decisions = [int(k) for k in decisions]
    if not decisions or any(not 0 <= k < ep.n_decisions for k in decisions):
        raise ConfigError(f"decisions={decisions}: give decisions in 0..{ep.n_decisions - 1}")
    agents = list(range(ep.n_agents)) if agents is None else [int(i) for i in agents]
    if not agents or any(not 0 <= i < ep.n_agents for i in agents):
        raise ConfigError(f"agents={agents}: give agents in 0..{ep.n_agents - 1}")
    shown = ep.similarity[np.ix_(decisions, agents, agents)]  # [len(decisions), n, n]
    n = len(agents)
    low = similarity_floor(shown)
    cols = min(cols or 3, len(decisions))
    grid_rows = -(-len(decisions) // cols)
    fig = Figure(figsize=(4.6 * cols + 1.0, 4.0 * grid_rows + 2.4), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    spec = fig.add_gridspec(grid_rows + 1, cols, height_ratios=[*([4.0] * grid_rows), 1.8])
    matrices = []
    for slot, k in enumerate(decisions):
        ax = fig.add_subplot(spec[slot // cols, slot % cols])
        image = ax.imshow(shown[slot], vmin=low, vmax=1.0, cmap="viridis")
        row = ep.decision_rows[k]
        ticks = [f"{i} {_anchor_text(ep.anchors[k, i])} g{ep.group_label[row, i]}" for i in agents]
        ax.set_xticks(range(n), [str(i) for i in agents], fontsize=7)
        ax.set_yticks(range(n), ticks, fontsize=7)
        ax.set_title(f"decision {k} (step {row})", fontsize=9)
        for i in range(n):
            for jj in range(n):
                value = shown[slot, i, jj]
                ax.text(
                    jj,
                    i,
                    "-" if np.isnan(value) else f"{value:.2f}",
                    ha="center",
                    va="center",
                    fontsize=5.5,
                    color="black" if np.isnan(value) or value > low + 0.6 * (1.0 - low) else "white",
                )
        matrices.append(ax)
    fig.colorbar(image, ax=matrices, shrink=0.8, label="cos(m_i, m_j)")
    ax = fig.add_subplot(spec[grid_rows, :])
    same, other = _mean_similarity(ep)
    ax.plot(ep.decision_rows, same, marker="o", markersize=3, label="same anchor")
    ax.plot(ep.decision_rows, other, marker="o", markersize=3, label="different anchors")
    ax.set_xlabel("low-level step of the decision")
    ax.set_ylabel("mean similarity")
    ax.legend(fontsize=8, loc="best")
    ax.grid(True, linewidth=0.3, alpha=0.5)
    fig.suptitle(
        title
        or f"Message similarity, {ep.policy or ep.variant}, seed {ep.seed} (rows: agent (its anchor) g<group label>)",
        fontsize=10,
    )
    path = Path(png_path)
    atomic_write(path, lambda fh: fig.savefig(fh, format="png"))
    return path


def game_moments(episode: HighLevelEpisode, count: int = 4) -> list[int]:
    """The decisions the paper's Figs. 11 and 12 show: `count` evenly spaced over the game, the
    first and the last included (fewer in a game of fewer decisions)."""
    k = episode.n_decisions
    return sorted(set(np.linspace(0, k - 1, min(count, k)).round().astype(int).tolist()))


def plot_game_moments(
    episode: HighLevelEpisode, png_path: str | os.PathLike, decisions: list[int] | None = None, dpi: int = 110
) -> Path:
    """The paper's Fig. 11: the arena from above at a few decisions (default `game_moments`, four
    evenly spaced), one panel each: every UAV's path so far and its position in its group's colour
    (groups as the env labels them: connected under the observation distance), a dashed line to the
    anchor it chose at that decision (a cross; none where its choice is unknown), the targets with
    their urgency, the obstacles, and the adversary's path and alert circle. Written atomically.
    ConfigError for a decision out of range."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    ep = episode
    decisions = game_moments(ep) if decisions is None else [int(k) for k in decisions]
    if not decisions or any(not 0 <= k < ep.n_decisions for k in decisions):
        raise ConfigError(f"decisions={decisions}: give decisions in 0..{ep.n_decisions - 1}")
    cols = min(2, len(decisions))
    grid_rows = -(-len(decisions) // cols)
    fig = Figure(figsize=(5.2 * cols, 5.2 * grid_rows + 0.6), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    a = ep.arena_half_size
    for slot, k in enumerate(decisions):
        ax = fig.add_subplot(grid_rows, cols, slot + 1)
        row = int(ep.decision_rows[k])
        colors = group_colors(ep.group_label[row]) / 255.0  # [N, 3]
        ax.plot([-a, a, a, -a, -a], [-a, -a, a, a, -a], color="0.6", linewidth=0.8)
        for centre in ep.obstacles:
            ax.add_patch(Circle(centre, ep.obstacle_radius, color="0.6", alpha=0.6, linewidth=0))
        ax.scatter(*ep.anchor_grid.T, s=12, color=(0.0, 0.78, 0.31), alpha=0.35, marker="s", linewidths=0)
        for t, (x, y) in enumerate(ep.targets):
            ax.add_patch(Circle((x, y), ep.target_radius, fill=False, color=(0.9, 0.7, 0.0), linewidth=0.8))
            ax.scatter([x], [y], s=90, marker="*", color=(0.9, 0.7, 0.0), zorder=3)
            ax.annotate(f"u={ep.urgency[row, t]:.2f}", (x, y), textcoords="offset points", xytext=(6, 6), fontsize=7)
        if ep.adversary_pos is not None:
            adv = ep.adversary_pos[: row + 1]
            ax.plot(*adv.T, color=(0.78, 0.0, 0.0), linewidth=1.0, alpha=0.7)
            ax.scatter(*adv[-1], s=60, color=(0.78, 0.0, 0.0), zorder=4)
            ax.add_patch(Circle(adv[-1], ep.alert_distance, fill=False, color=(0.78, 0.0, 0.0), linestyle=":"))
        for i in range(ep.n_agents):
            path = ep.agent_pos[: row + 1, i]
            ax.plot(*path.T, color=colors[i], linewidth=0.9, alpha=0.8)
            ax.scatter(*path[-1], s=30, color=colors[i], edgecolors="black", linewidths=0.4, zorder=5)
            ax.annotate(str(i), path[-1], textcoords="offset points", xytext=(3, -9), fontsize=7)
            anchor = ep.anchors[k, i]
            if np.isfinite(anchor).all():
                ax.plot(*np.stack([path[-1], anchor]).T, color=colors[i], linestyle="--", linewidth=0.7)
                ax.scatter(*anchor, s=70, marker="x", color=colors[i], linewidths=1.6, zorder=4)
        missing = [i for i in range(ep.n_agents) if not np.isfinite(ep.anchors[k, i]).all()]
        note = f"; anchor unknown: {missing}" if missing else ""
        ax.set_title(
            f"decision {k}, step {row} (t = {row * ep.dt:.1f} s)\ngroups {_group_text(ep.group_label[row])}{note}",
            fontsize=8,
        )
        ax.set_xlim(-a - 0.5, a + 0.5)
        ax.set_ylim(-a - 0.5, a + 0.5)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
    fig.suptitle(
        f"Paths, groups (colours) and chosen anchors (x), {ep.policy or ep.variant}, seed {ep.seed} "
        f"({_played_text(ep)}), at {len(decisions)} evenly spaced decisions",
        fontsize=10,
    )
    path = Path(png_path)
    atomic_write(path, lambda fh: fig.savefig(fh, format="png"))
    return path


def write_game_figures(episode: HighLevelEpisode, folder: str | os.PathLike, stem: str) -> list[Path]:
    """The paper's Figs. 11 and 12 of one game at the same moments (`game_moments`: four evenly
    spaced decisions): `<stem>_fig11.png` (`plot_game_moments`) and, for a policy with messages,
    `<stem>_fig12.png` (`plot_similarity_matrices` of UAVs 1-4, agents 0-3 here, one row)."""
    folder = Path(folder)
    moments = game_moments(episode)
    written = [plot_game_moments(episode, folder / f"{stem}_fig11.png", moments)]
    if episode.similarity is not None:
        written.append(
            plot_similarity_matrices(
                episode,
                folder / f"{stem}_fig12.png",
                moments,
                agents=list(range(min(4, episode.n_agents))),
                cols=len(moments),
                title=f"Cosine similarity of UAVs 1-4's messages (agents 0-3), {episode.policy or episode.variant}, "
                f"seed {episode.seed} ({_played_text(episode)}), at the decisions of Fig. 11 "
                "(rows: agent (its anchor) g<group label>)",
            )
        )
    return written
