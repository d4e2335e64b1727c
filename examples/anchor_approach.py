"""Where Table VIII's N is lost: how fast the swarm reaches each new anchor, and how well it stays.

Flies Table VIII episodes (1000 steps, a new anchor every 250; calm air, exact sensing, the
separation guard on as in `cefc-eval`) and splits each anchor period at the first step the swarm
centre comes within 1 m of the anchor (the step N starts counting):

  reach      decision steps from the anchor's draw to that first step (the period's length if never)
  start      distance of the swarm centre from the anchor when it is drawn (m)
  approach   the centre's speed towards the 1 m circle until then: (start - 1 m) / reach time (m/s)
  stays      share of the period's steps after the first arrival with the centre within 1 m
  N          the episode metric, averaged over seeds (the env's own count: the periods' steps within 1 m)
  bound      the most N could be: each period's steps less those a centre flying straight at the speed
             limit from where the period's first step left it would need to come within 1 m
             (obstacles and formation ignored)
  never      anchor periods in which the centre never came within 1 m (left out of approach and stays)

With --png DIR, one picture per episode (c<C>_seed<S>.png): a panel per anchor period with every
UAV's path, where it started, the anchor and the obstacles; a UAV left behind shows at a glance.

Examples:

  python examples/anchor_approach.py                               # particle world, c = 5..8, seeds 0..4
  python examples/anchor_approach.py --backend mujoco --formations 5 --seeds 2 --policy student
  python examples/anchor_approach.py --backend mujoco --formations 5 --seeds 1 --policy nav --png paths/
  python examples/anchor_approach.py --formations 5 --seed 105 --seeds 20 --policy nav   # other layouts

Bad input ends in one line on stderr and exit code 2, before anything is flown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

PROG = "anchor_approach.py"


def anchor_periods(
    formation: int, seed: int, backend: str, policy, trace: dict | None = None
) -> tuple[list[dict], float]:
    """One Table VIII episode flown by `policy` (a loaded Policy): per anchor period its reach, start,
    approach, stays and bound; and the env's N. A `trace` dict receives the paths (positions [T, c, 2]
    after each step), each step's anchor (anchors [T, 2]) and the obstacles [M, 2]."""
    from cefc_mj.eval.runner import TABLE8_ANCHOR_REDRAW, EpisodeSpec, episode_env, fly
    from cefc_mj.task.rewards import anchor_navigation_reward

    env, act = episode_env(EpisodeSpec(formation=formation, seed=seed, backend=backend), policy)
    tolerance, step_length = env.config.navigation_tolerance, env.config.speed_max * env.config.dt
    distances, positions, anchors = [], [], []

    def after_step() -> None:
        distances.append(-float(anchor_navigation_reward(env.world.agent_pos, env.anchor)[0]))
        positions.append(np.array(env.world.agent_pos[0]))
        anchors.append(np.array(env.anchor[0]).reshape(-1)[:2])

    fly(env, env.config.episode_steps, act, after_step=after_step)
    if trace is not None:
        trace.update(
            positions=np.array(positions),
            anchors=np.array(anchors),
            obstacles=np.array(env.obstacles[0]),
            obstacle_radius=env.config.obstacle_radius,
        )
    periods = []
    for start in range(0, len(distances), TABLE8_ANCHOR_REDRAW):
        d = np.array(distances[start : start + TABLE8_ANCHOR_REDRAW])
        inside = d < tolerance
        reach = int(np.argmax(inside)) if inside.any() else len(d)
        periods.append(
            {
                "reach": reach,
                "start": float(d[0]),
                "approach": (d[0] - tolerance) / (max(reach, 1) * env.config.dt) if inside.any() else float("nan"),
                "stays": float(inside[reach:].mean()) if inside.any() else 0.0,
                "inside": int(inside.sum()),
                "bound": len(d) - int(np.ceil(max(d[0] - tolerance, 0.0) / step_length - 1e-9)),
            }
        )
    return periods, float(env.episode_metrics()["N"][0])


def draw_episode(trace: dict, title: str, path: Path) -> None:
    """One panel per anchor period: each UAV's path (its start dotted black), the anchor, the obstacles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cefc_mj.eval.runner import TABLE8_ANCHOR_REDRAW
    from cefc_mj.fileio import atomic_write

    positions, anchors = trace["positions"], trace["anchors"]
    n_periods = len(positions) // TABLE8_ANCHOR_REDRAW
    fig, axes = plt.subplots(1, n_periods, figsize=(4 * n_periods, 4.3), squeeze=False)
    for k, ax in enumerate(axes[0]):
        period = slice(k * TABLE8_ANCHOR_REDRAW, (k + 1) * TABLE8_ANCHOR_REDRAW)
        for x, y in trace["obstacles"]:
            ax.add_patch(plt.Circle((x, y), trace["obstacle_radius"], color="0.6"))
        for i in range(positions.shape[1]):
            ax.plot(positions[period, i, 0], positions[period, i, 1], lw=0.8)
        ax.plot(positions[period.start, :, 0], positions[period.start, :, 1], "k.", ms=4)
        ax.plot(*anchors[period.start], "r*", ms=13)
        ax.set(xlim=(-10, 10), ylim=(-10, 10), aspect="equal", title=f"anchor period {k + 1}")
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
    parser.add_argument("--seeds", type=int, default=5, help="episodes per c, seeds S..S+K-1 (default 5)")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="first seed (default 0, as cefc-eval)")
    parser.add_argument("--policy", default="atm", help="as cefc-eval's --policy (default atm: AT-M Step 3)")
    parser.add_argument(
        "--png",
        type=Path,
        default=None,
        metavar="DIR",
        help="also draw each episode's paths per anchor period into DIR/c<C>_seed<S>.png",
    )
    args = parser.parse_args(argv)
    if any(c not in (3, 4, 5, 6, 7, 8) for c in args.formations):
        parser.exit(2, f"{PROG}: --formations {args.formations}: each c must be one of 3..8\n")
    if args.seeds < 1:
        parser.exit(2, f"{PROG}: --seeds {args.seeds}: must be at least 1\n")
    if args.seed < 0:
        parser.exit(2, f"{PROG}: --seed {args.seed}: must be at least 0\n")
    from cefc_mj.errors import CefcError
    from cefc_mj.eval.runner import load_policy_for

    try:
        args.loaded = {c: load_policy_for(args.policy, c) for c in args.formations}
    except CefcError as e:
        parser.exit(2, f"{PROG}: --policy {args.policy}: {e}\n")
    if args.png is not None:
        from cefc_mj.errors import ConfigError
        from cefc_mj.fileio import make_writable_folder

        try:
            make_writable_folder(args.png)
        except ConfigError as e:
            parser.exit(2, f"{PROG}: --png {args.png}: {e}\n")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    print(
        f"{args.backend}, policy {args.policy}, seeds {args.seed}..{args.seed + args.seeds - 1}, "
        "means over the anchor periods"
    )
    print(
        f"{'c':>2} {'N':>7} {'bound':>6} {'reach (steps)':>14} {'start (m)':>10} {'approach (m/s)':>15} {'stays':>6} "
        f"{'never':>6}"
    )
    for c in args.formations:
        periods, n_values, bounds = [], [], []
        for seed in range(args.seed, args.seed + args.seeds):
            trace = {} if args.png is not None else None
            p, n = anchor_periods(c, seed, args.backend, args.loaded[c], trace)
            periods += p
            n_values.append(n)
            bounds.append(sum(q["bound"] for q in p))
            if trace is not None:
                draw_episode(
                    trace,
                    f"{args.backend}, policy {args.policy}, c = {c}, seed {seed}: N {n:.0f} (bound {bounds[-1]})",
                    args.png / f"c{c}_seed{seed}.png",
                )
        arrived = [p for p in periods if p["approach"] == p["approach"]]  # nan: never arrived
        print(
            f"{c:>2} {np.mean(n_values):7.1f} {np.mean(bounds):6.1f} {np.mean([p['reach'] for p in periods]):14.1f} "
            f"{np.mean([p['start'] for p in periods]):10.2f} "
            f"{np.mean([p['approach'] for p in arrived]) if arrived else float('nan'):15.2f} "
            f"{np.mean([p['stays'] for p in arrived]) if arrived else 0.0:6.3f} {len(periods) - len(arrived):>6}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
