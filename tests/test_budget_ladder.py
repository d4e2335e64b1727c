"""examples/budget_ladder.py: the plan --list prints (rungs, seeds kept apart from the confirmatory ones,
the schedules, the cost estimate), the report builder's means over seeds on hand-made progress.csv
files (read back from the CSV it writes beside the figure), bad input exiting 2 with one line, and
(slow) a --smoke ladder trained for real and reported."""

import csv
import importlib.util
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cefc_mj.eval.prereg import OTHER_SEEDS, PRIMARY_SEEDS

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "budget_ladder.py"


def load_script():
    spec = importlib.util.spec_from_file_location("budget_ladder", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up while the class is made
    spec.loader.exec_module(module)
    return module


def test_list_prints_every_planned_run_with_its_schedule_and_cost(tmp_path, capsys):
    module = load_script()
    assert module.main(["--list", "--out", str(tmp_path / "ladder")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    runs, total = lines[:-1], lines[-1]
    assert len(runs) == 2 * 3 * 3 and all(line.startswith("todo") for line in runs)
    for rung in (75, 300):
        scaled = [line for line in runs if f"--schedule paper-scaled --budget {rung}it" in line]
        assert len(scaled) == 6 and all(f"ladder/u{rung} " in line for line in scaled)
    assert sum("--schedule paper --budget 1500it" in line for line in runs) == 6
    for seed in (300, 301, 302):
        assert sum(f"--seed {seed} " in line for line in runs) == 6
    assert sum("--variant consmac-a" in line for line in runs) == sum("--variant mappo" in line for line in runs) == 9
    assert all(
        "--adversary adversary_ppo_nearest_group_intercept" in line and "--low-level" not in line for line in runs
    )
    expected = 3 * (3.26 + 0.70) * (75 + 300 + 1500) / 1500  # the benchmark's core-hours, scaled by updates
    assert f"estimated cost {expected:.1f} core-hours in all" in total and "0 of 18 runs done" in total


def test_ladder_seeds_are_not_the_shipped_or_confirmatory_ones():
    module = load_script()
    confirmatory = set(PRIMARY_SEEDS) | set(OTHER_SEEDS) | set(range(5))  # pre-registered; shipped 0..4
    assert len(module.SEEDS) >= 3 and not set(module.SEEDS) & confirmatory


def write_progress(folder: Path, e: list[float], r_h: list[float], switch: int) -> None:
    folder.mkdir(parents=True)
    with (folder / "progress.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["iteration", "episodes_total", "phase", "episode_return", "metric/E", "term/R_t"])
        for i, (ei, ri) in enumerate(zip(e, r_h), start=1):
            w.writerow([i, 20 * i, int(i > switch), ri, ei, 0.0])


def test_report_draws_the_mean_over_seeds_per_method_and_rung(tmp_path, capsys):
    module = load_script()
    out = tmp_path / "ladder"
    runs = module.planned_runs(out)
    rng = np.random.default_rng(0)
    values = {}
    for run in runs:
        if run.rung == 1500 or (run.rung == 300 and run.seed == 302 and run.method == "CI-HRL"):
            continue  # the 1,500 rung not started; one 300 run missing
        length = run.rung if run.seed != 301 or run.rung != 75 or run.method != "MAPPO+AT-M" else 40  # one partial
        e = list(rng.uniform(50, 200, length))
        r_h = list(rng.uniform(-3000, -1000, length))
        write_progress(out / f"u{run.rung}" / run.stem, e, r_h, 2 * run.rung // 3)
        if length == run.rung:
            run.policy.parent.mkdir(parents=True, exist_ok=True)
            run.policy.write_bytes(b"done")
        values[run.method, run.rung, run.seed] = (e, r_h)
    figure = tmp_path / "fig" / "ladder.png"
    assert module.main(["--report", "--out", str(out), "--figure", str(figure), "--smooth", "1"]) == 0
    printed = capsys.readouterr().out
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "missing: cihrl_consmac_a_seed302 at 300 updates" in printed
    assert "not done: cihrl_mappo_seed301 at 75 updates (40/75 it)" in printed
    assert "missing: cihrl_mappo_seed300 at 1500 updates" in printed
    with figure.with_suffix(".csv").open() as f:
        rows = list(csv.DictReader(f))
    groups = {row["group"] for row in rows}
    assert groups == {"CI-HRL@75", "CI-HRL@300", "MAPPO+AT-M@75", "MAPPO+AT-M@300"}
    for (method, rung), seeds, length in (
        (("CI-HRL", 75), (300, 301, 302), 75),
        (("CI-HRL", 300), (300, 301), 300),
        (("MAPPO+AT-M", 75), (300, 301, 302), 40),  # the group stops at its partial seed's last iteration
        (("MAPPO+AT-M", 300), (300, 301, 302), 300),
    ):
        mine = [row for row in rows if row["group"] == f"{method}@{rung}"]
        assert len(mine) == length and int(mine[0]["seeds"]) == len(seeds)
        for i in (0, length // 2, length - 1):
            e = [values[method, rung, s][0][i] for s in seeds]
            r_h = [values[method, rung, s][1][i] for s in seeds]
            assert math.isclose(float(mine[i]["metric/E_mean"]), np.mean(e), rel_tol=1e-5)
            assert math.isclose(float(mine[i]["episode_return_mean"]), np.mean(r_h), rel_tol=1e-5)
            assert float(mine[i]["metric/E_ci_low"]) < np.mean(e) < float(mine[i]["metric/E_ci_high"])
    assert not (out / "u1500").exists()  # the report writes nothing into the ladder's folders


def write_state(run_dir: Path, iteration: int, replay_rows: int | None) -> None:
    """A saved high-level state as the trainer writes it, as far as the tracked copy reads it."""
    import torch

    from cefc_mj.train.highlevel import STATE_FORMAT

    replay = (
        None if replay_rows is None else {"size": replay_rows, "next": 0, "data": {"obs": torch.zeros(replay_rows, 3)}}
    )
    trainer = {"counters": {"iteration": iteration}, "replay": replay}
    run_dir.mkdir(parents=True, exist_ok=True)
    torch.save({"format": STATE_FORMAT, "config": {}, "trainer": trainer}, run_dir / "state.pt")
    (run_dir / "progress.csv").write_text("iteration\n" + "".join(f"{i}\n" for i in range(1, iteration + 1)))
    (run_dir / "config.json").write_text("{}")


def test_keep_copies_done_runs_and_states_without_replay_rows_and_a_fresh_checkout_restores_them(tmp_path, capsys):
    module = load_script()
    out, kept = tmp_path / "ladder", tmp_path / "kept"
    runs = {(r.method, r.rung, r.seed): r for r in module.planned_runs(out)}
    done, compact, full, mappo = (
        runs["CI-HRL", 75, 300],
        runs["CI-HRL", 75, 301],
        runs["CI-HRL", 300, 300],
        runs["MAPPO+AT-M", 1500, 302],
    )
    write_state(done.run_dir, 75, 40)
    done.policy.parent.mkdir(parents=True, exist_ok=True)
    for name in (done.policy, done.policy.with_suffix(".json"), done.policy.with_name(f"{done.stem}_wo_ft.pt")):
        name.write_bytes(b"exported " + name.name.encode())
    write_state(compact.run_dir, 12, 0)
    write_state(full.run_dir, 15, 5)
    write_state(mappo.run_dir, 300, None)
    assert module.main(["--keep", "--out", str(out), "--kept", str(kept)]) == 0
    printed = capsys.readouterr().out
    assert f"kept {full.stem} (u300): its state at iteration 15 holds the replay's rows" in printed
    u75 = kept / "u75"
    assert {p.name for p in u75.iterdir() if p.is_file()} == {
        f"{done.stem}.pt",
        f"{done.stem}.json",
        f"{done.stem}_wo_ft.pt",
    }
    assert {p.name for p in done.kept_dir(kept).iterdir()} == {"config.json", "progress.csv"}  # no final state
    assert {p.name for p in compact.kept_dir(kept).iterdir()} == {"config.json", "progress.csv", "state.pt"}
    assert not full.kept_dir(kept).exists() and (mappo.kept_dir(kept) / "state.pt").is_file()

    # A fresh checkout (no <out>): training and --report start from the tracked copy.
    shutil.rmtree(out)
    printed = module.restore(list(runs.values()), kept)
    assert done.done() and done.policy.read_bytes() == b"exported " + done.policy.name.encode()
    assert (done.policy.parent / f"{done.stem}_wo_ft.pt").is_file()
    assert module.saved_iteration(compact.run_dir / "state.pt") == 12 and not full.run_dir.exists()
    assert module.saved_iteration(mappo.run_dir / "state.pt") == 300
    assert f"restored {compact.stem} (u75): iteration 12" in printed and len(printed) == 3
    # Later: the run goes on (a state with rows is not copied over the kept one; one without rows is).
    write_state(compact.run_dir, 17, 40)
    module.keep(list(runs.values()), kept)
    assert module.saved_iteration(compact.kept_dir(kept) / "state.pt") == 12
    write_state(compact.run_dir, 20, 0)
    module.keep(list(runs.values()), kept)
    assert module.saved_iteration(compact.kept_dir(kept) / "state.pt") == 20
    assert module.restore(list(runs.values()), kept) == []  # nothing newer there than here


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--jobs", "3"], "--jobs: invalid choice: 3"),
        (["--list", "--report"], "--list, --report and --keep: give one of them"),
        (["--keep", "--kept", "/proc/kept"], "--kept /proc/kept"),
        (["--keep"], "--keep: with another --out, give the tracked copy's folder with --kept"),
        (["--report", "--smooth", "0"], "--smooth 0: must be >= 1"),
        (["--report", "--figure", "/proc/ladder/fig.png"], "--figure /proc/ladder/fig.png"),
        (["--report"], "--report: no ladder run has a progress.csv under"),
    ],
)
def test_bad_input_exits_2_with_one_line(argv, needle, tmp_path, capsys):
    module = load_script()
    with pytest.raises(SystemExit) as exit_info:
        module.main([*argv, "--out", str(tmp_path / "ladder")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err
    assert not (tmp_path / "ladder").exists()


@pytest.mark.slow
def test_smoke_ladder_trains_resumably_and_reports(tmp_path):
    out = tmp_path / "ladder"
    run = [sys.executable, str(SCRIPT), "--out", str(out), "--kept", str(tmp_path / "kept"), "--smoke"]
    done = subprocess.run(run, capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, done.stdout + done.stderr
    for rung in (3, 6):
        for stem, variant in (("cihrl_consmac_a_seed300", "consmac-a"), ("cihrl_mappo_seed300", "mappo")):
            config = json.loads((out / f"u{rung}" / stem / "config.json").read_text())["highlevel"]
            assert (config["schedule"], config["paper_updates"], config["variant"]) == ("paper-scaled", rung, variant)
            card = json.loads((out / f"u{rung}" / "policies" / f"{stem}.json").read_text())
            assert card["schedule"]["iterations"] == rung and card["schedule"]["paper_updates"] == rung
            with (out / f"u{rung}" / stem / "progress.csv").open() as f:
                assert len(list(csv.DictReader(f))) == rung
            assert (out / "logs" / f"u{rung}_{stem}.log").is_file()
    again = subprocess.run(run + ["--list"], capture_output=True, text=True, timeout=120)
    assert "4 of 4 runs done" in again.stdout
    assert all(line.startswith("done") and "--resume" in line for line in again.stdout.splitlines()[:-1])
    nothing = subprocess.run(run, capture_output=True, text=True, timeout=120)  # every run done: none trained again
    assert nothing.returncode == 0 and "0 of 4 runs to train" in nothing.stdout
    longer = subprocess.run(  # a finished 3-update run is not continued to 6: its switch came at 2
        [
            str(Path(sys.executable).with_name("cefc-train")),
            *("highlevel --variant mappo --seed 300 --schedule paper-scaled --budget 6it --no-progress".split()),
            *("--out", str(out / "u3"), "--policies-dir", str(tmp_path / "other"), "--resume"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert longer.returncode == 2 and len(longer.stderr.strip().splitlines()) == 1, longer.stderr
    assert "scaled to 3 iterations, not 6" in longer.stderr and not (tmp_path / "other").exists()
    drawn = subprocess.run(run + ["--report", "--smooth", "1"], capture_output=True, text=True, timeout=300)
    assert drawn.returncode == 0, drawn.stderr
    assert (out / "ladder.png").is_file() and "CI-HRL at 6 updates, last iteration 6" in drawn.stdout


def test_the_tracked_copy_is_not_ignored_by_git():
    """The kept states and logs are committed: no .gitignore rule (such as runs/) may hide them."""
    module = load_script()
    run = module.planned_runs(module.ROOT / module.OUT)[0]
    for path in (run.kept_dir(module.ROOT / module.KEPT) / "state.pt", module.ROOT / module.KEPT / "u75" / "x.pt"):
        done = subprocess.run(["git", "check-ignore", "-q", str(path)], cwd=module.ROOT)
        assert done.returncode == 1, path  # 1: not ignored
