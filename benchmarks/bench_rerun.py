"""Cost of recording an episode to Rerun (budget: at most +20 % wall time per episode).

Logs a synthetic episode (default 1000 steps, 8 UAVs, 24 LiDAR beams, the test airframe) to an
.rrd file with `log_episode` and prints the median time to log and to flush + close, against the
wall time of a 1000-step MuJoCo episode from docs/design.md §10 (100 s simulated at 30x-110x real time).

    .venv/bin/python benchmarks/bench_rerun.py [--steps 1000] [--agents 8] [--beams 24] [--repeats 5]
    .venv/bin/python benchmarks/bench_rerun.py --smoke   # 20 steps, one repeat (tests/test_benchmarks.py)
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from cefc_mj.eval.record import airframe_parts_from_mjcf, synthetic_record
from cefc_mj.paths import MJCF_DIR
from cefc_mj.viz.rerun_log import close_recording, log_episode, open_recording

TEST_AIRFRAME = Path(__file__).resolve().parent.parent / "tests" / "data" / "mini_quad.xml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--beams", type=int, default=24)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--smoke", action="store_true", help="20 steps, one repeat: the same code path in seconds")
    args = parser.parse_args()
    if args.smoke:
        args.steps, args.repeats = 20, 1

    airframe = MJCF_DIR / "iris.xml" if (MJCF_DIR / "iris.xml").is_file() else TEST_AIRFRAME
    record = synthetic_record(
        n_steps=args.steps, n_agents=args.agents, n_beams=args.beams, airframe_parts=airframe_parts_from_mjcf(airframe)
    )
    log_s, close_s, size = [], [], 0
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.repeats):
            path = Path(tmp) / f"episode{k}.rrd"
            recording = open_recording(rrd_path=path)
            t0 = time.perf_counter()
            log_episode(record, recording)
            t1 = time.perf_counter()
            close_recording(recording)
            t2 = time.perf_counter()
            log_s.append(t1 - t0)
            close_s.append(t2 - t1)
            size = path.stat().st_size
    total = statistics.median(a + b for a, b in zip(log_s, close_s))
    sim_s = args.steps * record.dt
    print(
        f"episode: {args.steps} steps x {args.agents} UAVs x {args.beams} beams, airframe {airframe.name} "
        f"({len(record.airframe_parts)} parts)"
    )
    print(
        f"log_episode      median {statistics.median(log_s) * 1e3:7.1f} ms  "
        f"({statistics.median(log_s) / args.steps * 1e3:.3f} ms a step)"
    )
    print(f"flush + close    median {statistics.median(close_s) * 1e3:7.1f} ms")
    print(f"total            median {total * 1e3:7.1f} ms   .rrd size {size / 1e6:.1f} MB")
    for speed in (30, 110):
        episode_s = sim_s / speed
        print(
            f"overhead vs a {sim_s:.0f} s episode at {speed:3d}x real time ({episode_s:.2f} s): "
            f"{100 * total / episode_s:5.1f} %"
        )


if __name__ == "__main__":
    main()
