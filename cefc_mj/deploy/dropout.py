"""Agent dropout (the paper's Fig. 4b): k UAVs leave the swarm mid-episode and the rest re-form.

The task core decides the formation target by group: in formation mode one group of all N agents,
whose template is Delta_N (`group_formation_error` picks the template by the group's member count).
`DropoutCEFCEnv` is `BatchedCEFCEnv` with an `active` mask [B, N]: a removed UAV is parked far
outside the arena (so no neighbour hears it and no LiDAR sees it: the paper's "no longer
observed"), labelled as its own singleton group (so the flying group, and its template, become
c - k), and left out of the metrics: F counts the flying agents in formation, N the flying group's
centre, C the flying agents' contacts over their agent-steps. With every agent active it is
exactly `BatchedCEFCEnv` (the same code paths, the same numbers).

`run_dropout_episode` is the lock-step dropout run (both backends); `run_sitl_episode` takes the
same `drop` for SITL-M, where the dropped agents' processes are killed (or stopped) as well.
"""

from __future__ import annotations

import numpy as np

from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.eval.requests import check_drop, parse_drop  # noqa: F401 (parse_drop: re-exported)
from cefc_mj.task.formation import connected_groups
from cefc_mj.task.guard import guarded

DROP_SEED_SALT = 0xD0
"""Mixed into the episode seed to choose which UAVs drop out (np.random.default_rng([seed, salt]))."""


class DropoutCEFCEnv(BatchedCEFCEnv):
    """BatchedCEFCEnv whose UAVs can leave mid-episode (see the module docstring)."""

    def __init__(self, config, n_envs: int = 1, seed: int | None = 0, world=None):
        super().__init__(config, n_envs=n_envs, seed=seed, world=world)
        self.active = np.ones((n_envs, self.n_agents), dtype=bool)
        """[B, N] True for a UAV still in the swarm."""
        self.active_agent_steps = np.zeros(n_envs)
        self.trace: dict[str, list[np.ndarray]] = {k: [] for k in ("F", "N", "C", "active", "hd_error")}
        """Per step, each [B]: F and N contributions, contacts of flying agents, flying agents, the
        flying group's HD error."""

    def reset(self, mask: np.ndarray | None = None, seed: int | None = None) -> np.ndarray:
        m = np.ones(self.n_envs, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if m.shape == (self.n_envs,):
            self.active[m] = True
            self.active_agent_steps[m] = 0.0
            if m.all():
                self.trace = {k: [] for k in self.trace}
        return super().reset(mask, seed)

    def remove_agents(self, env: int, agents) -> None:
        """UAVs `agents` of env `env` leave: parked out of the arena, out of groups and metrics; the
        observations are recomputed so that the next decision already sees the smaller swarm."""
        agents = [int(i) for i in agents]
        if not agents:
            return
        from cefc_mj.deploy.tick_world import park_agents

        park_agents(self.world, env, agents)
        self.active[env, agents] = False
        self._groups(self.world.agent_pos)
        self._observe(np.ones(self.n_envs, dtype=bool))

    def _groups(self, pos):
        active = getattr(self, "active", None)
        if active is None or active.all():
            return super()._groups(pos)
        from cefc_mj.task.formation import agent_group_error, group_formation_error

        own = np.arange(self.n_agents)[None, :]
        if self.config.mode == "formation":
            labels = np.where(active, active.argmax(axis=1)[:, None], own)
        else:
            labels = np.where(active, connected_groups(pos, self.config.observation_distance), own)
        self.labels = labels
        error, size, centre = group_formation_error(pos, labels, self.config.formation_spacing)
        self.agent_error = agent_group_error(error, labels)
        self.group_size, self.group_centre = size, centre
        return error, size, centre

    def _accumulate_metrics(self, pos, centre_distance) -> None:
        cfg, active = self.config, self.active
        before = {k: v.copy() for k, v in self.metric_sums.items()}
        if active.all():
            super()._accumulate_metrics(pos, centre_distance)
        else:
            count = active.sum(axis=-1)
            in_formation = (self.agent_error < cfg.formation_tolerance) & active
            self.metric_sums["F"] += in_formation.sum(axis=-1) / count
            centre = (pos * active[..., None]).sum(axis=1) / count[:, None]
            self.metric_sums["N"] += np.linalg.norm(centre - self.anchor, axis=-1) < cfg.navigation_tolerance
            self.metric_sums["C"] += (self.world.collisions() & active).sum(axis=-1)
            if cfg.mode == "cefc" and cfg.adversary != "none":
                adv_dist = np.linalg.norm(pos - self.world.adversary_pos[:, None, :], axis=-1)
                near = (adv_dist < cfg.rewards.evasion_alert_distance) & active
                self.metric_sums["E"] += near.any(axis=-1)
                self.metric_sums["E_agents"] += near.sum(axis=-1)
        self.active_agent_steps += active.sum(axis=-1)
        for key in ("F", "N", "C"):
            self.trace[key].append(self.metric_sums[key] - before[key])
        self.trace["active"].append(active.sum(axis=-1))
        first = active.argmax(axis=1)
        self.trace["hd_error"].append(self.agent_error[np.arange(self.n_envs), first].copy())

    def episode_metrics(self) -> dict[str, np.ndarray]:
        metrics = super().episode_metrics()
        metrics["C"] = 100.0 * self.metric_sums["C"] / np.maximum(self.active_agent_steps, 1)
        return metrics

    def phase_metrics(self, env: int, start: int, stop: int | None = None) -> dict:
        """F, N (steps), C (% of the flying agents' agent-steps) over steps [start, stop) of env `env`,
        with the number of steps and the flying group's size at the phase's last step."""
        rows = {k: np.asarray([v[env] for v in self.trace[k][start:stop]], dtype=np.float64) for k in self.trace}
        steps = int(rows["F"].size)
        agent_steps = rows["active"].sum()
        return {
            "F": float(rows["F"].sum()),
            "N": float(rows["N"].sum()),
            "C": float(100.0 * rows["C"].sum() / agent_steps) if agent_steps else 0.0,
            "steps": steps,
            "group_size": int(rows["active"][-1]) if steps else int(self.active[env].sum()),
        }


def choose_dropouts(formation: int, k: int, seed: int) -> list[int]:
    """Which k of the c UAVs drop out: a seeded uniform choice (the paper's "randomly selected")."""
    rng = np.random.default_rng([int(seed), DROP_SEED_SALT])
    return sorted(int(i) for i in rng.choice(formation, size=k, replace=False))


def dropout_report(env: DropoutCEFCEnv, uavs: list[int], step: int):
    from cefc_mj.deploy.results import DropoutReport

    return DropoutReport(
        uavs=list(uavs),
        step=step,
        phases={"before": env.phase_metrics(0, 0, step), "after": env.phase_metrics(0, step)},
        hd_error=np.asarray([v[0] for v in env.trace["hd_error"]]),
    )


def run_dropout_episode(spec, drop: tuple[int, int], policy=None):
    """Lock-step dropout episode (one process, both backends): k UAVs chosen by `choose_dropouts`
    leave before decision step `step`; the others fly on. Returns a SitlEpisodeResult with
    mode "lock-step", no SITL stats, and the DropoutReport. Fly `spec.policy = "student"` for the
    paper's experiment (the teachers are trained for one c)."""
    import torch

    from cefc_mj.deploy.results import SitlEpisodeResult
    from cefc_mj.deploy.tick_world import TickedWorld
    from cefc_mj.eval.runner import episode_fields, fly, load_policy_for
    from cefc_mj.sim.backends import make_world

    torch.set_num_threads(1)
    k, step = check_drop(drop, spec.formation, spec.steps)
    policy = policy if policy is not None else load_policy_for(spec.policy, spec.formation)
    config = policy.task_for(spec.task_config())
    world = TickedWorld(
        make_world(
            spec.backend,
            config,
            n_envs=1,
            wind=spec.wind,
            seed=spec.seed,
            airframe=spec.mujoco_airframe,
            wind_direction=spec.wind_direction,
            rotor_actuation=spec.rotor_actuation if spec.backend == "mujoco" else None,
        ),
        1,
        config.dt,
    )
    env = DropoutCEFCEnv(config, n_envs=1, seed=spec.seed, world=world)
    dropped = choose_dropouts(spec.formation, k, spec.seed)

    def leave(t: int) -> None:
        if t == step:
            env.remove_agents(0, dropped)

    policy_act = guarded(policy.act, config)

    def act(obs):
        actions = policy_act(obs)
        gone = ~env.active
        if gone.any():  # parked UAVs brake to a stop (their policy no longer runs)
            actions[gone] = world.brake_accel(config.accel_max)[gone]
        return actions

    diverged, wall_s = fly(env, spec.steps, act, before_step=leave)
    return SitlEpisodeResult(
        **episode_fields(env, spec, diverged, wall_s),
        dropout=dropout_report(env, dropped, step),
        mode="lock-step",
    )
