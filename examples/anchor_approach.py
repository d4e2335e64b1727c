"""Where Table VIII's N is lost: how fast the swarm reaches each new anchor, and how well it stays.

Flies Table VIII episodes (1000 steps, a new anchor every 250; calm air, exact sensing, the
separation guard on as in `cefc-eval`) and splits each anchor period at the first step the swarm
centre comes within 1 m of the anchor (the step N starts counting):

  reach      decision steps from the anchor's draw to that first step (the period's length if never)
  start      distance of the swarm centre from the anchor when it is drawn (m)
  approach   the centre's speed towards the 1 m circle until then: (start - 1 m) / reach time (m/s)
  stays      share of the period's steps after the first arrival with the centre within 1 m
  N          the episode metric, averaged over seeds (the env's own count: the periods' steps within 1 m)
  never      anchor periods in which the centre never came within 1 m (left out of approach and stays)

Examples:

  python examples/anchor_approach.py                               # particle world, c = 5..8, seeds 0..4
  python examples/anchor_approach.py --backend mujoco --formations 5 --seeds 2 --policy student

Bad input ends in one line on stderr and exit code 2, before anything is flown.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

PROG = "anchor_approach.py"


def anchor_periods(formation: int, seed: int, backend: str, policy) -> tuple[list[dict], float]:
    """One Table VIII episode flown by `policy` (a loaded Policy): per anchor period its reach, start,
    approach and stays; and the env's N."""
    from cefc_mj.eval.runner import TABLE8_ANCHOR_REDRAW, EpisodeSpec, episode_env, fly
    from cefc_mj.task.rewards import anchor_navigation_reward

    env, act = episode_env(EpisodeSpec(formation=formation, seed=seed, backend=backend), policy)
    tolerance = env.config.navigation_tolerance
    distances = []
    fly(env, env.config.episode_steps, act,
        after_step=lambda: distances.append(-float(anchor_navigation_reward(env.world.agent_pos, env.anchor)[0])))
    periods = []
    for start in range(0, len(distances), TABLE8_ANCHOR_REDRAW):
        d = np.array(distances[start:start + TABLE8_ANCHOR_REDRAW])
        inside = d < tolerance
        reach = int(np.argmax(inside)) if inside.any() else len(d)
        periods.append({
            "reach": reach, "start": float(d[0]),
            "approach": (d[0] - tolerance) / (max(reach, 1) * env.config.dt) if inside.any() else float("nan"),
            "stays": float(inside[reach:].mean()) if inside.any() else 0.0,
            "inside": int(inside.sum()),
        })
    return periods, float(env.episode_metrics()["N"][0])


def parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=("particle", "mujoco"), default="particle")
    parser.add_argument("--formations", type=int, nargs="+", default=[5, 6, 7, 8], metavar="C",
                        help="group sizes c (default 5 6 7 8)")
    parser.add_argument("--seeds", type=int, default=5, help="episodes per c, seeds 0..K-1 (default 5)")
    parser.add_argument("--policy", default="atm", help="as cefc-eval's --policy (default atm: AT-M Step 3)")
    args = parser.parse_args(argv)
    if any(c not in (3, 4, 5, 6, 7, 8) for c in args.formations):
        parser.exit(2, f"{PROG}: --formations {args.formations}: each c must be one of 3..8\n")
    if args.seeds < 1:
        parser.exit(2, f"{PROG}: --seeds {args.seeds}: must be at least 1\n")
    from cefc_mj.errors import CefcError
    from cefc_mj.eval.runner import load_policy_for
    try:
        args.loaded = {c: load_policy_for(args.policy, c) for c in args.formations}
    except CefcError as e:
        parser.exit(2, f"{PROG}: --policy {args.policy}: {e}\n")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    print(f"{args.backend}, policy {args.policy}, seeds 0..{args.seeds - 1}, means over the anchor periods")
    print(f"{'c':>2} {'N':>7} {'reach (steps)':>14} {'start (m)':>10} {'approach (m/s)':>15} {'stays':>6} {'never':>6}")
    for c in args.formations:
        periods, n_values = [], []
        for seed in range(args.seeds):
            p, n = anchor_periods(c, seed, args.backend, args.loaded[c])
            periods += p
            n_values.append(n)
        arrived = [p for p in periods if p["approach"] == p["approach"]]  # nan: never arrived
        print(f"{c:>2} {np.mean(n_values):7.1f} {np.mean([p['reach'] for p in periods]):14.1f} "
              f"{np.mean([p['start'] for p in periods]):10.2f} "
              f"{np.mean([p['approach'] for p in arrived]) if arrived else float('nan'):15.2f} "
              f"{np.mean([p['stays'] for p in arrived]) if arrived else 0.0:6.3f} {len(periods) - len(arrived):>6}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
