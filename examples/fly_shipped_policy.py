"""Fly a shipped AT-M policy through the PettingZoo env and record the flight.

The policy flies the low-level game (mode="formation": the group forms up and flies to the anchor)
on either backend; the flight is written to OUT:

  OUT ending in .gif   the env's rgb_array frames as an animated GIF (10 frames per second)
  OUT ending in .rrd   a Rerun recording of every step (open it with `rerun OUT`)

The default OUT is a file in the system's temporary folder. Examples:

  python examples/fly_shipped_policy.py                                  # particle world, GIF
  python examples/fly_shipped_policy.py --backend mujoco --out /tmp/quad.rrd
  python examples/fly_shipped_policy.py --policy atm_c8_step3 --agents 8 --steps 300

Bad input ends in one line on stderr and exit code 2, before anything is flown.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

PROG = "fly_shipped_policy.py"
MAX_STEPS = 10_000
SUFFIXES = (".gif", ".rrd")


def usage_error(message: str):
    print(f"{PROG}: {message}", file=sys.stderr)
    sys.exit(2)


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line, exit code 2."""

    def error(self, message: str):
        usage_error(f"{message} (see --help)")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--backend",
        choices=["particle", "mujoco"],
        default="particle",
        help="particle world (default) or MuJoCo quadrotors",
    )
    p.add_argument(
        "--policy",
        default="atm_c6_step3",
        metavar="NAME|PATH",
        help="a policy name in policies/ or a .pt path (default atm_c6_step3)",
    )
    p.add_argument("--agents", type=int, default=6, metavar="N", help="number of UAVs, 3..8 (default 6)")
    p.add_argument(
        "--steps", type=int, default=100, metavar="T", help=f"decision steps (0.1 s each), 1..{MAX_STEPS} (default 100)"
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="scenario seed, >= 0 (default 0)")
    p.add_argument("--density", type=float, default=0.03, metavar="D", help="obstacles per m^2, 0..0.1 (default 0.03)")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="PATH",
        help="where to write the recording, .gif or .rrd (default <temp folder>/cefc_fly_<policy>_<backend>.gif)",
    )
    return p


def validate(args) -> None:
    """Exit 2 with one line on the first bad argument; resolves args.out and args.policy_path."""
    from cefc_mj.errors import CefcError
    from cefc_mj.nn.policy_io import resolve_policy_path

    if not 3 <= args.agents <= 8:
        usage_error(f"--agents {args.agents}: must be in 3..8 (the shipped policies' formation sizes)")
    if not 1 <= args.steps <= MAX_STEPS:
        usage_error(f"--steps {args.steps}: must be in 1..{MAX_STEPS}")
    if args.seed < 0:
        usage_error(f"--seed {args.seed}: must be >= 0")
    if not 0.0 <= args.density <= 0.1:
        usage_error(f"--density {args.density}: must be in 0..0.1")
    try:
        args.policy_path = resolve_policy_path(args.policy)
    except CefcError as e:
        usage_error(f"--policy: {e}")
    if args.out is None:
        args.out = Path(tempfile.gettempdir()) / f"cefc_fly_{args.policy_path.stem}_{args.backend}.gif"
    if args.out.suffix not in SUFFIXES:
        usage_error(f"--out {args.out}: must end in {' or '.join(SUFFIXES)}")
    parent = args.out.parent
    if args.out.is_dir() or not parent.is_dir() or not os.access(parent, os.W_OK):
        usage_error(f"--out {args.out}: cannot write a file there")


def fly(args) -> int:
    import numpy as np
    import torch

    import cefc_mj
    from cefc_mj.nn.policy_io import load_policy
    from cefc_mj.viz.recorder import RerunRecorder

    torch.set_num_threads(1)  # a small network: intra-op threads only cost time
    as_gif = args.out.suffix == ".gif"
    env = cefc_mj.make_env(
        backend=args.backend,
        n_agents=args.agents,
        mode="formation",
        seed=args.seed,
        obstacle_density=args.density,
        episode_steps=args.steps,
        render_mode="rgb_array" if as_gif else None,
    )
    policy = load_policy(args.policy_path, obs_dim=env.layout.size)
    frames: list[np.ndarray] = []
    recorder = None if as_gif else RerunRecorder(env, rrd_path=args.out)
    try:
        observations, infos = env.reset(seed=args.seed)
        capture = env.render if as_gif else recorder.capture
        for _ in range(args.steps + 1):  # the start and every step
            frame = capture()
            if frame is not None:
                frames.append(frame)
            if not env.agents:
                break
            observations, rewards, terminations, truncations, infos = env.step(policy.act(observations))
    finally:
        env.close()
        if recorder is not None:
            recorder.close()
    if as_gif:
        write_gif(frames, args.out, fps=env.metadata["render_fps"])
    metrics = infos[env.possible_agents[0]].get("metrics", {})
    summary = ", ".join(f"{k} = {metrics[k]:.4g}" for k in ("F", "N", "C") if k in metrics)
    print(f"{policy.name} on {args.backend}, {args.agents} UAVs, {args.steps} steps: {summary}")
    print(f"wrote {args.out}")
    return 0


def write_gif(frames, path: Path, fps: int) -> None:
    """Animated GIF through Pillow (matplotlib's image library), written atomically."""
    from PIL import Image

    from cefc_mj.fileio import atomic_write

    images = [Image.fromarray(f) for f in frames]
    atomic_write(
        path,
        lambda fh: images[0].save(
            fh, format="GIF", save_all=True, append_images=images[1:], duration=round(1000 / fps), loop=0
        ),
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    validate(args)
    from cefc_mj.errors import CefcError

    try:
        return fly(args)
    except CefcError as e:
        print(f"{PROG}: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
