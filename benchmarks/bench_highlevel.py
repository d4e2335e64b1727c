"""Cost of one agent's full decision in the hierarchical game, on one core, as an agent would run it.

One agent (batch 1) at a real decision of the game, on the deployed paths an agent process runs:
`HighLevelPolicy.agent_decider()` (ConsMAC's memory, distance code and attention over its
neighbours' messages, then the anchor selector, as a TorchScript trace) and the low level's action
toward the chosen anchor (the shipped student through `ATMActor.deterministic_actions`, the compiled kernel
the SITL-M agents run). `--eager` adds, in the same run, `HighLevelPolicy.decide` and `Policy.act`.
The state comes from a game played to decision `--decision` by the shipped CI-HRL, so the agent's
inbox holds the messages it would hear. Reference measured in the same run: the low level alone
(what the agent computes every 0.1 s anyway); the ratio full / low level is what moves least with
the machine's load. Best of `--rounds` rounds of `--repeat` calls each, one torch thread, no
autograd.

    .venv/bin/python benchmarks/bench_highlevel.py
    .venv/bin/python benchmarks/bench_highlevel.py --policy cihrl_mappo --rounds 9
    .venv/bin/python benchmarks/bench_highlevel.py --smoke   # decision 2, 1 round of 5 calls (tests/test_benchmarks.py)

The low level is the one the hierarchical evaluators fly (`cefc_mj.eval.highlevel.LOW_LEVEL`).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from cefc_mj.game_protocol import LOW_LEVEL, game_task
from cefc_mj.hierarchy import HierarchicalCEFCEnv, load_low_level
from cefc_mj.nn.highlevel_policy import highlevel_policy_path, load_highlevel_policy
from cefc_mj.nn.policy_io import load_policy, resolve_policy_path
from cefc_mj.task.messages import Inbox, MessageChannel

TARGET_US = 500.0
"""The budget of one agent's full decision (0.5 ms on one core)."""


def agent_inbox(inbox: Inbox, env: int, agent: int) -> Inbox:
    """The inbox of one agent as a batch of one ([1, 1, ...] arrays)."""
    pick = lambda a: a[env : env + 1, agent : agent + 1]  # noqa: E731
    return Inbox(
        pick(inbox.messages),
        pick(inbox.mask),
        pick(inbox.distance),
        pick(inbox.sender),
        pick(inbox.received),
        pick(inbox.own),
    )


def best_us(fn, repeat: int, rounds: int) -> float:
    """Best over rounds of the mean wall time of one call, in microseconds."""
    best = float("inf")
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(repeat):
            fn()
        best = min(best, (time.perf_counter() - start) / repeat * 1e6)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", default="cihrl_consmac_a", help="high-level policy name or .pt (default CI-HRL)")
    parser.add_argument("--decision", type=int, default=12, help="decision at which the state is taken (default 12)")
    parser.add_argument("--repeat", type=int, default=300, help="calls per round (default 300)")
    parser.add_argument("--rounds", type=int, default=5, help="rounds, best taken (default 5)")
    parser.add_argument("--eager", action="store_true", help="also time the eager paths (decide, Policy.act)")
    parser.add_argument(
        "--smoke", action="store_true", help="decision 2, one round of 5 calls: the same code path in seconds"
    )
    args = parser.parse_args()
    if args.smoke:
        args.decision, args.repeat, args.rounds = 2, 5, 1
    torch.set_num_threads(1)

    path = highlevel_policy_path(args.policy)
    policy, _ = load_highlevel_policy(path)
    task = game_task()
    low_level = load_low_level(LOW_LEVEL, task)
    env = HierarchicalCEFCEnv(task, low_level, n_envs=1, seed=0)
    channel = MessageChannel(1, task.n_agents, max(policy.message_dim, 1), task.observation_distance)
    obs = env.reset(seed=0)
    inbox = None
    for _ in range(args.decision):  # play the game to a decision with messages in flight
        inbox = channel.receive(env.world.agent_pos) if policy.comm is not None else None
        index, message = policy.decide(obs, inbox)
        if policy.comm is not None:
            channel.send(message)
        obs, _, _, _ = env.step(index)
    inbox = channel.receive(env.world.agent_pos) if policy.comm is not None else None
    received = inbox.received[0] if inbox is not None else np.zeros(task.n_agents, dtype=int)
    agent = int(np.argmax(received))  # the agent with the most neighbours: the costliest attention
    agent_obs = obs[:, agent : agent + 1]
    one_inbox = agent_inbox(inbox, 0, agent) if inbox is not None else None
    low_obs = env.low_level_observation()[:, agent : agent + 1]
    decider = policy.agent_decider()
    student = load_policy(resolve_policy_path(LOW_LEVEL))  # the game's low level, as the evaluators fly it
    low_act = student.actor.deterministic_actions
    index, message = decider(agent_obs, one_inbox)
    reference = policy.decide(agent_obs, one_inbox)
    assert (index == reference[0]).all() and (message is None or (message == reference[1]).all())

    high_us = best_us(lambda: decider(agent_obs, one_inbox), args.repeat, args.rounds)
    low_us = best_us(lambda: low_act(low_obs), args.repeat, args.rounds)
    full_us = high_us + low_us
    print(
        f"policy {path.name} ({policy.variant}), decision {args.decision}, agent {agent} with "
        f"{int(received[agent])} received messages, one torch thread, best of {args.rounds} x {args.repeat}"
    )
    print(f"  high level (ConsMAC + selector)  {high_us:8.1f} us")
    print(f"  low level (student, reference)   {low_us:8.1f} us")
    print(
        f"  full decision                    {full_us:8.1f} us = {full_us / low_us:.2f} x the low level alone; "
        f"target <= {TARGET_US:.0f} us: {'met' if full_us <= TARGET_US else 'NOT met'} "
        f"({full_us / TARGET_US:.2f} of it)"
    )
    if args.eager:
        with torch.inference_mode():
            eager_high = best_us(lambda: policy.decide(agent_obs, one_inbox), args.repeat, args.rounds)
            eager_low = best_us(lambda: student.act(low_obs), args.repeat, args.rounds)
        print(
            f"  eager paths: decide {eager_high:.1f} us ({eager_high / high_us:.2f} x the traced), "
            f"Policy.act {eager_low:.1f} us ({eager_low / low_us:.2f} x)"
        )


if __name__ == "__main__":
    main()
