"""Does a UAV left behind an obstacle rejoin its group? A probe of the low level's escape behaviour.

Table VIII's N drops when one UAV of the group stops behind an obstacle: it sees no neighbour
within 3 m, the anchor is several metres away, and its LiDAR reads an obstacle ahead. The reported
layouts contain this situation only by chance, so this script builds it on purpose, case after case:

  - the straggler starts at rest at a random point of [-3, 3]^2, facing a random direction;
  - one obstacle stands 1-2 m ahead of it (0.3 m or less to the side), a second 1-2.5 m ahead and
    1.3-2 m to one side (so a gap or a wall), the arena's other obstacles are parked far outside it;
  - the anchor is 4.5-7 m straight ahead, and the other c - 1 UAVs wait on a 0.8 m ring around it.

Each case is flown for 200 decision steps (20 s; the straight flight needs at most 7 s) with the
evaluators' agent (the separation guard on, exact sensing, calm air). A case counts as escaped when
the straggler comes within 2 m of the anchor. Printed per c: escaped cases, and the mean and
median steps they took.

With --png DIR, DIR/c<C>_failures.png draws up to six cases that did not escape.

Examples:

  python examples/straggler_probe.py                                 # the default policy (nav), c = 5..8, 100 cases
  python examples/straggler_probe.py --formations 5 --policy runs/x/policies/atm_c5_nav.pt
  python examples/straggler_probe.py --backend mujoco --formations 5 --cases 20 --png probe/

Bad input ends in one line on stderr and exit code 2, before anything is flown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

PROG = "straggler_probe.py"
PROBE_STEPS = 200
JOINED_DISTANCE = 2.0
"""The straggler has rejoined when it is this close to the anchor (m)."""
PARKED = 50.0
"""Where (m, along x) the obstacles the case does not use are parked, beyond every LiDAR beam."""


def straggler_layout(formation: int, n_obstacles: int, case_seed: int):
    """The case's Scenario (one env): starts, the two obstacles, the anchor."""
    from cefc_mj.task.scenario import Scenario

    rng = np.random.default_rng(case_seed)
    heading = rng.uniform(0.0, 2 * np.pi)
    ahead = np.array([np.cos(heading), np.sin(heading)])
    side = np.array([-ahead[1], ahead[0]])
    start = rng.uniform(-3.0, 3.0, 2)
    anchor = start + rng.uniform(4.5, 7.0) * ahead
    obstacles = np.stack([np.full(n_obstacles, PARKED) + 2.0 * np.arange(n_obstacles), np.zeros(n_obstacles)], -1)
    obstacles[0] = start + rng.uniform(1.0, 2.0) * ahead + rng.uniform(-0.3, 0.3) * side
    obstacles[1] = start + rng.uniform(1.0, 2.5) * ahead + rng.choice([-1.0, 1.0]) * rng.uniform(1.3, 2.0) * side
    ring = np.linspace(0.0, 2 * np.pi, formation - 1, endpoint=False)
    waiting = anchor + 0.8 * (np.cos(ring)[:, None] * ahead + np.sin(ring)[:, None] * side)
    return Scenario(
        agent_pos=np.concatenate([start[None], waiting])[None],
        adversary_pos=np.zeros((1, 2)),
        obstacles=obstacles[None],
        targets=np.zeros((1, 0, 2)),
        anchor=anchor[None],
    )


def fly_case(formation: int, case_seed: int, backend: str, policy) -> tuple[int | None, dict]:
    """One case: (the step at which the straggler came within JOINED_DISTANCE of the anchor, or None)
    and its trace (positions [T, c, 2], the anchor, the two obstacles, their radius)."""
    from cefc_mj.eval.runner import EpisodeSpec, episode_env

    env, act = episode_env(EpisodeSpec(formation=formation, seed=case_seed, backend=backend), policy)
    layout = straggler_layout(formation, env.config.n_obstacles, case_seed)
    obs = env.reset(scenario=layout)
    anchor, positions, joined = layout.anchor[0], [], None
    for k in range(PROBE_STEPS):
        obs, _, _, _ = env.step(act(obs))
        positions.append(np.array(env.world.agent_pos[0]))
        if np.linalg.norm(positions[-1][0] - anchor) < JOINED_DISTANCE:
            joined = k + 1
            break
    return joined, {
        "positions": np.array(positions),
        "anchor": anchor,
        "obstacles": layout.obstacles[0, :2],
        "obstacle_radius": env.config.obstacle_radius,
    }


def draw_failures(traces: list[dict], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cefc_mj.fileio import atomic_write

    fig, axes = plt.subplots(1, len(traces), figsize=(3.6 * len(traces), 3.9), squeeze=False)
    for ax, trace in zip(axes[0], traces):
        for x, y in trace["obstacles"]:
            ax.add_patch(plt.Circle((x, y), trace["obstacle_radius"], color="0.6"))
        positions = trace["positions"]
        for i in range(positions.shape[1]):
            ax.plot(positions[:, i, 0], positions[:, i, 1], lw=0.8, color="C3" if i == 0 else "0.3")
        ax.plot(*positions[0, 0], "ko", ms=4)
        ax.plot(*trace["anchor"], "r*", ms=12)
        ax.set(aspect="equal", title=trace["title"])
    fig.suptitle(title)
    fig.tight_layout()
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=80))  # a picture is complete or absent
    plt.close(fig)


def parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=("particle", "mujoco"), default="particle")
    parser.add_argument(
        "--formations", type=int, nargs="+", default=[5, 6, 7, 8], metavar="C", help="group sizes c (default 5 6 7 8)"
    )
    parser.add_argument("--cases", type=int, default=100, help="cases per c, seeds S..S+K-1 (default 100)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="first case seed (default 0)")
    parser.add_argument("--policy", default="nav", help="as cefc-eval's --policy (default nav, its default)")
    parser.add_argument(
        "--png",
        type=Path,
        default=None,
        metavar="DIR",
        help="draw up to six cases that did not escape into DIR/c<C>_failures.png",
    )
    args = parser.parse_args(argv)
    if any(c not in (3, 4, 5, 6, 7, 8) for c in args.formations):
        parser.exit(2, f"{PROG}: --formations {args.formations}: each c must be one of 3..8\n")
    if args.cases < 1:
        parser.exit(2, f"{PROG}: --cases {args.cases}: must be at least 1\n")
    if args.seed < 0:
        parser.exit(2, f"{PROG}: --seed {args.seed}: must be at least 0\n")
    if args.png is not None:
        from cefc_mj.errors import ConfigError
        from cefc_mj.fileio import make_writable_folder

        try:
            make_writable_folder(args.png)
        except ConfigError as e:
            parser.exit(2, f"{PROG}: --png {args.png}: {e}\n")
    from cefc_mj.errors import CefcError
    from cefc_mj.eval.runner import load_policy_for

    try:
        args.loaded = {c: load_policy_for(args.policy, c) for c in args.formations}
    except CefcError as e:
        parser.exit(2, f"{PROG}: --policy {args.policy}: {e}\n")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    seeds = range(args.seed, args.seed + args.cases)
    print(f"{args.backend}, policy {args.policy}, case seeds {seeds.start}..{seeds.stop - 1}, {PROBE_STEPS} steps each")
    print(f"{'c':>2} {'escaped':>9} {'mean steps':>11} {'median':>7}")
    for c in args.formations:
        steps, failures = [], []
        for seed in seeds:
            joined, trace = fly_case(c, seed, args.backend, args.loaded[c])
            if joined is None:
                failures.append(dict(trace, title=f"case seed {seed}"))
            else:
                steps.append(joined)
        mean, median = (np.mean(steps), np.median(steps)) if steps else (float("nan"), float("nan"))
        print(f"{c:>2} {len(steps):>4}/{args.cases:<4} {mean:11.1f} {median:7.0f}")
        if args.png is not None and failures:
            draw_failures(
                failures[:6],
                f"{args.backend}, policy {args.policy}, c = {c}: cases not escaped",
                args.png / f"c{c}_failures.png",
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
