"""Kill (or hang) one UAV's agent process in the middle of a SITL-M game and show what follows.

Plays one Table V game on MuJoCo quadrotors with every UAV's whole hierarchy in its own process
(`cefc_mj.deploy.run_sitl_game`), sends SIGKILL (or SIGSTOP) to one agent before decision step
--step, and prints:

- the game's figures (R_H, R_t, E, F, C): the other agents play on to the end;
- the hit UAV's speed and drift after PX4's offboard-loss timeout (1 s): its vehicle holds;
- the simulator's events (the agent's exit, the failsafe);
- the agent processes still alive afterwards, from `ps`: there must be none.

  python examples/sitl_game_fault.py                          # UAV 3 killed at step 200
  python examples/sitl_game_fault.py --uav 0 --step 120 --action stop --seed 20001

Exit code 0 when the vehicle held and no agent process is left, 1 otherwise; bad input ends in one
line on stderr and exit code 2, before anything is flown.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

import numpy as np

PROG = "sitl_game_fault.py"
AGENT_MODULE = "cefc_mj.deploy.agent"
HOLD_SPEED = 0.1
"""m/s: a held vehicle's speed stays below this once the failsafe has braked it."""


def usage_error(message: str):
    print(f"{PROG}: {message}", file=sys.stderr)
    sys.exit(2)


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line, exit code 2."""

    def error(self, message: str):
        usage_error(f"{message} (see --help)")


def agent_processes() -> list[str]:
    """`ps` lines of the SITL-M agent processes this simulator started (their command line names it
    with --parent-pid; an orphan keeps that line after its parent has gone)."""
    out = subprocess.run(["ps", "-eo", "pid,ppid,args"], capture_output=True, text=True, check=True).stdout
    mine = f"--parent-pid {os.getpid()}"
    return [line.strip() for line in out.splitlines() if AGENT_MODULE in line and mine in line]


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--policy", default="cihrl_consmac_a", help="high-level policy (default cihrl_consmac_a)")
    parser.add_argument("--uav", type=int, default=3, help="the UAV whose agent is hit (default 3)")
    parser.add_argument("--step", type=int, default=200, help="before which decision step (default 200)")
    parser.add_argument("--action", choices=("kill", "stop"), default="kill", help="SIGKILL or SIGSTOP (default kill)")
    parser.add_argument("--seed", type=int, default=20000, help="game seed (default 20000, a test-block seed)")
    parser.add_argument("--backend", choices=("mujoco", "particle"), default="mujoco", help="default mujoco")
    args = parser.parse_args(argv)

    from cefc_mj.deploy import SitlConfig, run_sitl_game
    from cefc_mj.deploy.episode import AgentFault
    from cefc_mj.errors import CefcError
    from cefc_mj.eval.conditions import Conditions
    from cefc_mj.eval.highlevel_sitl import GameSpec
    from cefc_mj.game_protocol import GAME_AGENTS, GAME_STEPS

    if not 0 <= args.uav < GAME_AGENTS:
        usage_error(f"--uav {args.uav}: must be in 0..{GAME_AGENTS - 1}")
    if not 1 <= args.step < GAME_STEPS:
        usage_error(f"--step {args.step}: must be in 1..{GAME_STEPS - 1}")
    spec = GameSpec(policy=args.policy, seed=args.seed, where=Conditions(args.backend))
    sitl = SitlConfig(faults=(AgentFault(uav=args.uav, step=args.step, action=args.action),))
    try:
        result = run_sitl_game(spec, sitl)
    except CefcError as e:
        usage_error(str(e))

    pos = result.trace.arrays()["agent_pos"][:, args.uav]  # [steps + 1, 2]; index k: after k steps
    settle = args.step + 10 + int(round(sitl.offboard_loss_timeout_s / 0.1))  # the timeout, then 1 s to brake
    settle = min(settle, len(pos) - 1)
    speed = np.linalg.norm(np.diff(pos[settle:], axis=0), axis=-1) / 0.1
    drift = float(np.linalg.norm(pos[-1] - pos[settle]))
    fig = result.figures
    print(
        f"game seed {args.seed} ({args.backend}), {result.steps} steps: R_H {fig['R_H']:.1f}, R_t {fig['R_t']:.1f}, "
        f"E {fig['E']:.0f} steps, F {fig['F']:.1f}, C {fig['C']:.2f} %"
    )
    print(
        f"UAV {args.uav}: agent {args.action} before step {args.step}; from step {settle} to the end its speed "
        f"is at most {speed.max() if speed.size else 0.0:.3f} m/s and it drifts {drift:.3f} m "
        f"(final state {result.sitl['final_states'][args.uav]!r})"
    )
    for event in result.sitl["events"]:
        print(f"event: {event}")
    left = agent_processes()
    print(f"agent processes left after the game (ps): {len(left)}")
    for line in left:
        print(f"  {line}")
    held = speed.size == 0 or float(speed.max()) < HOLD_SPEED
    return 0 if held and not left else 1


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    sys.exit(main())
