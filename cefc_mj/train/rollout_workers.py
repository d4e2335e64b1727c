"""Rollout worker processes: each steps its share of an iteration's envs with a copy of the actor.

A MuJoCo world steps its envs one after another in one thread, so an iteration's episodes are
collected faster by several processes, each holding `n_envs / workers` worlds. The learner sends the
actor's weights once per iteration; every worker collects its episodes (seeded by the run seed, the
iteration and its index, so a resumed run replays them) and sends back its `Shard`; the learner
concatenates the shards in worker order and runs the PPO update on them.

The workers are started with "spawn" (fresh interpreters, never a fork of a process whose threads may
hold a lock) and compute with one thread each. A worker that dies or raises ends the run with one line
(`RolloutWorkerFailed`), never a hang; `close()` leaves no process behind (the resource tracker that
spawning starts included).
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Callable

import numpy as np
import torch

from cefc_mj.errors import CefcError
from cefc_mj.executors import resource_tracker_running, stop_resource_tracker
from cefc_mj.nn.atm import ATMActor, ATMConfig
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.rollout import collect_shard, iteration_seed

START_TIMEOUT_S = 600.0
"""How long a worker may take to build its worlds (a cold numba cache compiles for about a minute)."""
POLL_S = 1.0


class RolloutWorkerFailed(CefcError, RuntimeError):
    """A rollout worker raised, or its process ended, while collecting."""


def shard_seeds(seed: int, iteration: int, worker: int) -> tuple[int, int]:
    """(env seed, action-sampling seed) of one worker's episodes in one iteration: independent streams
    per (run seed, iteration, worker), the env seed inside the training block of game seeds."""
    env_seed = iteration_seed(seed, iteration, stream=worker + 1)
    action_seed = int(np.random.SeedSequence([seed, iteration, worker + 1, 7]).generate_state(1)[0])
    return env_seed, action_seed


def _worker_main(conn, make_env, task_cfg: TaskConfig, n_envs: int, actor_cfg: ATMConfig, credit: str, index: int):
    """A worker's loop: build the env, then per request load the weights and collect one shard."""
    torch.set_num_threads(1)
    try:
        env = make_env(task_cfg, n_envs, index)
        actor = ATMActor(actor_cfg)
        conn.send(("ready", os.getpid()))
    except Exception as e:  # noqa: BLE001 - reported to the learner as one line
        conn.send(("error", f"{type(e).__name__}: {e}"))
        return
    while True:
        request = conn.recv()
        if request is None:
            return
        state, seed, iteration, steps = request
        try:
            actor.load_state_dict(state)
            env_seed, action_seed = shard_seeds(seed, iteration, index)
            generator = torch.Generator().manual_seed(action_seed)
            conn.send(("shard", collect_shard(env, actor, generator, steps, credit, env_seed)))
        except Exception as e:  # noqa: BLE001 - reported to the learner as one line
            conn.send(("error", f"{type(e).__name__}: {e}"))
            return


class RolloutWorkers:
    """`count` worker processes, each with `n_envs` envs built by `make_env(task_cfg, n_envs, index)`."""

    def __init__(
        self,
        count: int,
        make_env: Callable,
        task_cfg: TaskConfig,
        n_envs: int,
        actor_cfg: ATMConfig,
        credit: str,
    ):
        ctx = multiprocessing.get_context("spawn")
        self.connections, self.processes = [], []
        self._tracker_was_running = resource_tracker_running()  # spawning starts one; close() stops ours
        try:
            for index in range(count):
                parent, child = ctx.Pipe()
                process = ctx.Process(
                    target=_worker_main,
                    args=(child, make_env, task_cfg, n_envs, actor_cfg, credit, index),
                    name=f"cefc-rollout-{index}",
                    daemon=True,
                )
                process.start()
                child.close()
                self.connections.append(parent)
                self.processes.append(process)
            for index in range(count):
                self._receive(index, "ready", START_TIMEOUT_S)
        except BaseException:
            self.close()
            raise

    def _receive(self, index: int, kind: str, timeout_s: float | None = None):
        """The next message of worker `index`, which must be of `kind`; RolloutWorkerFailed otherwise."""
        conn, process = self.connections[index], self.processes[index]
        start = time.monotonic()
        while not conn.poll(POLL_S):
            if not process.is_alive():
                raise RolloutWorkerFailed(f"rollout worker {index} exited (code {process.exitcode}) without an answer")
            if timeout_s is not None and time.monotonic() - start > timeout_s:
                raise RolloutWorkerFailed(f"rollout worker {index} did not answer within {timeout_s:.0f} s")
        try:
            got, payload = conn.recv()
        except (EOFError, OSError):
            process.join(timeout=1.0)
            raise RolloutWorkerFailed(f"rollout worker {index} exited (code {process.exitcode}) mid-answer") from None
        if got == "error":
            raise RolloutWorkerFailed(f"rollout worker {index}: {payload}")
        if got != kind:
            raise RolloutWorkerFailed(f"rollout worker {index} sent {got!r}, expected {kind!r}")
        return payload

    def collect(self, actor_state: dict, seed: int, iteration: int, steps: int) -> list:
        """Every worker's Shard of this iteration, in worker order."""
        for index, conn in enumerate(self.connections):
            try:
                conn.send((actor_state, seed, iteration, steps))  # pickled here: the workers get a copy
            except OSError:
                self.processes[index].join(timeout=1.0)
                code = self.processes[index].exitcode
                raise RolloutWorkerFailed(f"rollout worker {index} exited (code {code})") from None
        return [self._receive(index, "shard") for index in range(len(self.connections))]

    def close(self) -> None:
        """Ask the workers to stop; terminate any that does not within a few seconds."""
        for conn in self.connections:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        for process in self.processes:
            process.join(timeout=5.0)
            if process.is_alive():
                process.terminate()
                process.join(timeout=5.0)
        for conn in self.connections:
            conn.close()
        if self.processes and not self._tracker_was_running:
            stop_resource_tracker()
        self.connections, self.processes = [], []
