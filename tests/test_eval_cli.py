"""cefc-eval: bad input ends in one clear line with exit code 2 before anything is flown or written;
a small particle run writes its JSON, PNGs and Rerun recording, creating their folders."""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

import cefc_mj.eval.table8 as table8
from cefc_mj.cli.eval import main
from cefc_mj.errors import ConfigError
from cefc_mj.eval import DEFAULT_POLICY
from cefc_mj.eval.runner import EpisodeSpec, episode_env
from cefc_mj.nn.atm import ATMActor, ATMConfig
from cefc_mj.nn.policy_io import load_policy, save_policy
from cefc_mj.task.config import TaskConfig


@pytest.fixture(scope="module")
def random_policy(tmp_path_factory):
    """An untrained AT-M actor for the low-level layout (the CLI's plumbing, not its skill, is tested)."""
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("pol") / "random_atm.pt"
    save_policy(ATMActor(ATMConfig.from_task(TaskConfig(n_agents=5, mode="formation"))), path)
    return path


@pytest.fixture(scope="module")
def wrong_shape_policy(tmp_path_factory):
    path = tmp_path_factory.mktemp("pol") / "wrong.pt"
    cfg = TaskConfig(n_agents=5, mode="formation", n_lidar_rays=12)
    save_policy(ATMActor(ATMConfig.from_task(cfg)), path)
    return path


def run_cli(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def tree(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


BAD_INPUTS = [
    (["--wind", "-1"], "--wind -1"),
    (["--wind", "1e9"], "maximum speed"),
    (["--wind", "inf"], "--wind inf"),
    (["--deviation", "nan"], "--deviation nan"),
    (["--deviation", "11"], "--deviation 11"),
    (["--formation", "2"], "--formation 2"),
    (["--formation", "5", "5"], "listed twice"),
    (["--episodes", "0"], "--episodes 0"),
    (["--episodes", "1000000000"], "1..10000"),
    (["--steps", "0"], "--steps 0"),
    (["--steps", "100001"], "1..100000"),
    (["--seed", "-1"], "--seed -1"),
    (["--seed", "4294967295", "--episodes", "2"], "largest seed"),
    (["--seed", "abc"], "invalid int value"),
    (["--workers", "0"], "--workers 0"),
    (["--workers", "2", "--rrd", "run.rrd"], "--workers 2"),
    (["--policy", "no_such_policy"], "no_such_policy"),
    (["--policy", "elsewhere/atm_c5_nav.pt", "--formation", "5"], "no policy file 'elsewhere/atm_c5_nav.pt'"),
    (
        ["--protocol", "table5", "--backend", "particle", "--policy", "elsewhere/cihrl_mappo.pt"],
        "no policy file 'elsewhere/cihrl_mappo.pt'",
    ),
    (["--policy", "robust", "--formation", "3"], "AT-M-Robust is withdrawn"),
    (["--policy", "nav", "--formation", "3", "--wind", "0", "--wind-direction", "45"], "no wind to point"),
    (["--json", "{file}/out.json"], "is a file, not a folder"),
    (["--json", "{tmp}"], "is a folder"),
    (["--json", "/nonexistent/x.json"], "will not create /nonexistent"),
    (["--json", "/proc/forbidden/x.json"], "/proc"),
    (["--rrd", "{file}/x.rrd"], "--rrd"),
    (["--rrd", "/nonexistent/x.rrd"], "will not create /nonexistent"),
    (["--png", "{file}"], "is a file, not a folder"),
    (["--png", "/nonexistent/png"], "will not create /nonexistent"),
    (["--backend", "particle", "--wind", "3"], "no wind model"),
    (["--sitl-m", "--protocol", "table3", "--backend", "particle"], "--sitl-m: Table III"),
    (["--report-dir", "reports"], "only --protocol table8"),
    (["--fresh"], "only --protocol table8"),
    (["--protocol", "table8", "--wind", "3"], "its own 7 conditions"),
    (["--protocol", "table8", "--deviation", "0.5"], "its own 7 conditions"),
    (["--protocol", "table8", "--backend", "particle"], "needs --backend mujoco"),
    (["--protocol", "table8", "--png", "png"], "recording works with --protocol single, or table5 with --policy"),
    (["--protocol", "table8", "--report-dir", "{file}"], "is a file, not a folder"),
    (["--protocol", "table8", "--report-dir", "/nonexistent/reports"], "will not create /nonexistent"),
    (["--protocol", "table3"], "--backend particle"),
    (["--accel-max", "0"], "--accel-max 0: must be a number in (0, 9.81]"),
    (["--accel-max", "12"], "--accel-max 12"),
    (["--accel-max", "nan"], "--accel-max nan"),
    (["--accel-max", "3", "--sitl-m"], "--accel-max: not available with --sitl-m"),
    (
        ["--protocol", "table5", "--backend", "particle", "--seed", "80000"],
        "--seed 80000: the test batch of Table V at",
    ),
    (["--protocol", "table6", "--backend", "particle", "--seed", "80000"], "reserved for its pre-registered flight"),
    (["--push-observer", "-1"], "--push-observer -1: must be a number in [0, 10] s"),
    (["--push-observer", "nan"], "--push-observer nan"),
    (["--push-observer", "2", "--drop", "1"], "--push-observer: not available with --drop"),
    (["--protocol", "table5", "--backend", "particle", "--push-observer", "2"], "--push-observer: --protocol table5"),
    (["--protocol", "table5", "--backend", "particle", "--accel-max", "3"], "--accel-max: --protocol table5"),
    (["--protocol", "table3", "--backend", "particle", "--deviation", "0.3"], "exact sensing"),
    (["--protocol", "table3", "--backend", "particle", "--workers", "2"], "one batch"),
    (
        ["--protocol", "table3", "--backend", "particle", "--policy", "quad", "--formation", "3"],
        "AT-M-Quad is withdrawn",
    ),
]


@pytest.mark.parametrize("argv, needle", BAD_INPUTS, ids=[" ".join(a) for a, _ in BAD_INPUTS])
def test_bad_input_one_line_exit_2_nothing_flown_or_written(argv, needle, capsys, tmp_path, monkeypatch):
    work = tmp_path / "cwd"
    work.mkdir()
    (tmp_path / "a_file").write_text("not a folder")
    monkeypatch.chdir(work)
    flown = []
    monkeypatch.setattr(table8, "_fly", lambda *a, **k: flown.append(a) or pytest.fail("an episode was flown"))
    argv = [a.replace("{file}", str(tmp_path / "a_file")).replace("{tmp}", str(tmp_path)) for a in argv]
    before = tree(tmp_path)
    code, out, err = run_cli(argv, capsys)
    assert code == 2
    lines = [line for line in err.strip().splitlines() if line]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in err, err
    assert lines[0].startswith("cefc-eval: error: ")
    assert out == "" and not flown
    assert tree(tmp_path) == before


def test_a_policy_flies_at_its_own_bound_or_at_accel_max(random_policy):
    """The action bound is the policy's unless --accel-max says another: the env's clip and the
    policy's own (in torch and in the compiled kernel the evaluators fly) follow it."""
    policy = load_policy(random_policy)
    spec = EpisodeSpec(formation=5, seed=0, backend="particle", steps=5, policy=str(random_policy))
    env, _ = episode_env(spec, policy)
    assert policy.accel_max == 2.0 and env.config.accel_max == 2.0
    obs = np.random.default_rng(0).normal(0.0, 3.0, (64, 5, policy.obs_dim)).astype(np.float32)
    wide = policy.with_action_bound(3.5)
    env, _ = episode_env(dataclasses.replace(spec, accel_max=3.5), policy)
    assert env.config.accel_max == 3.5 and wide.accel_max == 3.5 and policy.accel_max == 2.0
    for p, bound in ((policy, 2.0), (wide, 3.5)):
        for actions in (p.act(obs), p.actor.inference_weights().actions(obs)):
            assert np.abs(actions).max() == pytest.approx(bound)
    inside = np.abs(policy.act(obs)) < 2.0 - 1e-6
    np.testing.assert_allclose(wide.act(obs)[inside], policy.act(obs)[inside], rtol=1e-6)  # the same network


def test_a_policy_flies_with_its_own_push_observer_or_the_one_asked_for(random_policy):
    """The push observer is the policy's (none for one trained without) unless --push-observer says
    another; {c} in a --policy path names one file per c."""
    from cefc_mj.nn.registry import policy_name_for

    policy = load_policy(random_policy)
    spec = EpisodeSpec(formation=5, seed=0, backend="particle", steps=5, policy=str(random_policy))
    env, _ = episode_env(spec, policy)
    assert policy.push_observer_s == 0.0 and env.push_observer is None
    env, _ = episode_env(dataclasses.replace(spec, push_observer=2.0), policy)
    assert env.config.push_observer_s == 2.0 and env.push_observer is not None and policy.push_observer_s == 0.0
    with_observer = policy.with_push_observer(2.0)
    env, _ = episode_env(spec, with_observer)  # a policy trained with one flies with it
    assert env.push_observer is not None and with_observer.task_for(env.config) == env.config
    env, _ = episode_env(dataclasses.replace(spec, push_observer=0.0), with_observer)
    assert env.push_observer is None
    assert policy_name_for("runs/x/atm_c{c}_mujoco.pt", 7) == "runs/x/atm_c7_mujoco.pt"


def test_checkpoint_for_another_observation_size(wrong_shape_policy, capsys):
    code, out, err = run_cli(
        ["--backend", "particle", "--formation", "5", "--steps", "5", "--policy", str(wrong_shape_policy)], capsys
    )
    assert code == 2 and "observations of size 51" in err and len(err.strip().splitlines()) == 1 and out == ""


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--backend", "bullet"], "invalid choice"),
        (["--json", "/nonexistent/x.json"], "will not create /nonexistent"),
        (["--wind", "1e9"], "maximum speed"),
        (["--protocol", "table8", "--deviation", "0.3"], "its own 7 conditions"),
    ],
)
def test_bad_input_via_subprocess(argv, needle, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "cefc_mj.cli.eval", *argv], capture_output=True, text=True, cwd=tmp_path, timeout=120
    )
    assert proc.returncode == 2 and needle in proc.stderr and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and proc.stdout == ""
    assert list(tmp_path.iterdir()) == []


def test_version_and_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("cefc-eval 0.")
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "SITL-M: every UAV's policy in its own OS process" in " ".join(capsys.readouterr().out.split())


def test_particle_single_run_writes_json_and_png_into_new_folders(random_policy, tmp_path, capsys):
    out = tmp_path / "new" / "res.json"
    code = main(
        [
            "--backend",
            "particle",
            "--formation",
            "5",
            "--steps",
            "30",
            "--episodes",
            "1",
            "--deviation",
            "0.3",
            "--policy",
            str(random_policy),
            "--json",
            str(out),
            "--png",
            str(tmp_path / "png"),
        ]
    )
    assert code == 0
    data = json.loads(out.read_text())
    assert data["condition"] == "Deviation-0.3" and data["seeds"] == [0] and data["comparable_to_paper"] is False
    rows = data["rows"]["5"]
    assert set(rows) == {"Deviation-0.3", "SITL-S"}
    for cell in rows.values():
        assert 0 <= cell["F"] <= 30 and 0 <= cell["N"] <= 30 and 0 <= cell["C"] <= 100 and cell["episodes"] == 1
        assert cell["F_std"] is None and len(cell["episodes_detail"]) == 1
    assert data["provenance"]["policies"]["5"]["sha256"] and data["provenance"]["library_versions"]["mujoco"]
    assert list((tmp_path / "png").glob("*.png"))
    printed = capsys.readouterr().out
    assert "Table VIII metrics" in printed and "not comparable" in printed and "calm reference" in printed
    assert "our cells are ONE seed (0)" in printed and "NOT A MEASUREMENT of the policy" in printed
    assert "not saved" not in printed  # --json wrote it


MAIN_JOB = ["--wind", "8", "--deviation", "0.5"]
"""The README's main job."""


def test_main_job_flies_five_seeds_per_c_on_two_processes_outside_the_test_block():
    """`cefc-eval --wind 8 --deviation 0.5` flies seeds 0..4 of each c = 5..8 on a pool of 2 (fewer
    only where fewer CPUs are usable), none of them a test seed (no test-ledger line); SITL-M and
    recordings fly one at a time, and asking for a pool with them is still refused."""
    from cefc_mj.cli.eval import build_parser, to_request
    from cefc_mj.eval.ledger import touches_test_block
    from cefc_mj.executors import usable_cpus

    request = to_request(build_parser().parse_args(MAIN_JOB))
    assert (request.episodes, request.seed, request.formations) == (5, 0, (5, 6, 7, 8))
    assert request.workers == min(2, usable_cpus())
    assert not touches_test_block("single", request.seed, request.episodes)
    assert to_request(build_parser().parse_args([*MAIN_JOB, "--episodes", "1"])).workers == min(2, usable_cpus())
    for one_process in (["--sitl-m"], ["--rrd", "run.rrd"], ["--png", "plots"]):
        assert to_request(build_parser().parse_args([*MAIN_JOB, *one_process])).workers == 1
    with pytest.raises(ConfigError, match="--workers 2: SITL-M episodes fly one at a time"):
        to_request(build_parser().parse_args([*MAIN_JOB, "--sitl-m", "--workers", "2"]))


def test_main_job_says_its_seeds_and_writes_nothing(tmp_path):
    """The main job, shortened (c = 5, 5 steps), as a real process: its header and table say 5 seeds
    per cell and on how many processes, the last line says the table is not saved, and it leaves no
    file behind."""
    from cefc_mj.executors import usable_cpus

    done = subprocess.run(
        [sys.executable, "-m", "cefc_mj.cli.eval", *MAIN_JOB, "--formation", "5", "--steps", "5"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    workers = min(2, usable_cpus())
    header = done.stdout.splitlines()[0]
    assert "seeds 0..4 (5 per cell)" in header and "10 episodes" in header
    assert header.endswith(f"on {workers} workers") if workers > 1 else "workers" not in header
    assert "  seeds: each of our cells is the mean ± sample std over 5 seeds (0..4)" in done.stdout
    assert done.stdout.strip().splitlines()[-1].startswith("the table above is not saved: --json PATH writes it")
    assert "episodes: 100%" in done.stderr  # the progress bar
    assert list(tmp_path.iterdir()) == []


def test_the_seeds_behind_each_cell_are_said_in_one_line():
    """One seed is called one seed and not a measurement; several, the mean ± std over them; cells an
    interruption left short are named."""
    from cefc_mj.cli.eval_single import single_table
    from cefc_mj.eval.runner import summarize

    def summary(seeds, episodes_per_cell):
        rows = {
            "5": {
                cond: {**summarize([{"F": 9.0, "N": 4.0, "C": 0.0, "steps": 10}] * n), "retention": 1.0}
                for cond, n in zip(("Wind-8", "SITL-S"), episodes_per_cell)
            }
        }
        for cells in rows.values():
            for cell in cells.values():
                cell["retention_note"] = None
        return {
            "condition": "Wind-8",
            "steps": 10,
            "seeds": seeds,
            "backend": "particle",
            "policy": "nav",
            "rows": rows,
        }

    lines = lambda text: [line for line in text.splitlines() if line.startswith("  seeds: ")]  # noqa: E731
    one = lines(single_table(summary([7], (1, 1))))
    assert one == [
        "  seeds: our cells are ONE seed (7), one layout of obstacles and anchors: NOT A MEASUREMENT of the "
        "policy (layouts differ widely); --episodes 5 or more gives mean ± std."
    ]
    assert lines(single_table(summary([0, 1, 2], (3, 3)))) == [
        "  seeds: each of our cells is the mean ± sample std over 3 seeds (0..2), the same layouts in every one "
        "of our rows."
    ]
    short = lines(single_table(summary([0, 1, 2], (3, 2))))
    assert len(short) == 1 and "over 3 seeds (0..2; interrupted: c = 5 SITL-S has 2), the same" in short[0]


def test_single_with_workers_uses_a_pool(random_policy, tmp_path, capsys):
    """--workers 2 flies the episodes in two processes and gives the same numbers as one process."""
    argv = [
        "--backend",
        "particle",
        "--formation",
        "5",
        "--steps",
        "15",
        "--episodes",
        "2",
        "--deviation",
        "0.5",
        "--policy",
        str(random_policy),
    ]
    assert main(argv + ["--workers", "1", "--json", str(tmp_path / "one.json")]) == 0
    assert main(argv + ["--workers", "2", "--json", str(tmp_path / "two.json")]) == 0
    one, two = (json.loads((tmp_path / f"{n}.json").read_text())["rows"] for n in ("one", "two"))
    for cond in ("SITL-S", "Deviation-0.5"):
        f_one, f_two = ([e["F"] for e in rows["5"][cond]["episodes_detail"]] for rows in (one, two))
        assert f_one == f_two
        assert one["5"][cond]["F_std"] is not None


def test_rrd_recording_into_a_missing_folder_read_back(random_policy, tmp_path):
    """--rrd writes a Rerun file (its missing folder created, like --png's) whose entities say what they are."""
    import rerun as rr

    rrd = tmp_path / "missing" / "run.rrd"
    assert (
        main(
            [
                "--backend",
                "particle",
                "--formation",
                "5",
                "--steps",
                "20",
                "--episodes",
                "1",
                "--policy",
                str(random_policy),
                "--rrd",
                str(rrd),
            ]
        )
        == 0
    )
    paths = set()
    for chunk in rr.chunk.RrdReader(rrd).stream().to_chunks():
        paths.add(str(chunk.entity_path))
    expected = {"/world/uav_0", "/world/uav_4/lidar", "/world/obstacles", "/world/anchor", "/metrics/hd_error"}
    assert expected <= paths and "/world/uav_5" not in paths  # five UAVs flew


def test_output_that_fails_at_the_end_is_one_line_after_the_table(random_policy, tmp_path, capsys, monkeypatch):
    """A write that fails after the run (disk full) prints the table first, then one line, exit 1."""
    import cefc_mj.fileio

    def disk_full(path, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cefc_mj.fileio, "write_atomic", disk_full)
    with pytest.raises(SystemExit) as exc:
        main(
            [
                "--backend",
                "particle",
                "--formation",
                "5",
                "--steps",
                "5",
                "--episodes",
                "1",
                "--workers",
                "1",
                "--policy",
                str(random_policy),
                "--json",
                str(tmp_path / "r.json"),
            ]
        )
    out = capsys.readouterr()
    assert exc.value.code == 1 and "Table VIII metrics" in out.out
    last = out.err.strip().splitlines()[-1]
    assert last == f"cefc-eval: error: could not write {tmp_path / 'r.json'}: No space left on device"


def test_interrupted_table8_says_how_to_resume(tmp_path, capsys, monkeypatch):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(table8, "run_grid", interrupted)
    assert main(["--protocol", "table8", "--formation", "5", "--episodes", "1", "--steps", "10"]) == 130
    err = capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # the report folder is made by run_grid, right before its first write
    assert "resume with:" in err and "--report-dir" in err and f"table8-{DEFAULT_POLICY}-mujoco-" in err


def test_default_policy_is_shipped_for_every_formation_and_says_how_it_differs():
    """The evaluators' default low level (AT-M-Nav) exists for every c the CLI accepts, reads that
    game's observations, and each model card states its changes from the paper (the navigation weight,
    and for some c training episodes of several anchor periods, some with stragglers)."""
    from cefc_mj.eval.runner import EpisodeSpec, load_policy_for, policy_name_for
    from cefc_mj.nn.policy_io import resolve_policy_path

    assert EpisodeSpec(formation=5, seed=0).policy == DEFAULT_POLICY == "nav"
    for c in range(3, 9):
        assert load_policy_for(DEFAULT_POLICY, c).name == f"atm_c{c}_nav"
        card = json.loads(resolve_policy_path(policy_name_for(DEFAULT_POLICY, c)).with_suffix(".json").read_text())
        assert card["method"] == "AT-M-Nav" and card["config"]["navigation_weight"] in (7.0, 10.0)
        periods = card["config"].get("anchor_periods", 1)
        stragglers = card["config"].get("straggler_fraction", 0.0)
        assert (
            card["differs_from_paper"][0]
            == f"navigation weight omega_n = {card['config']['navigation_weight']:g} (paper 4)"
        )
        assert len(card["differs_from_paper"]) == 1 + (periods > 1) + (stragglers > 0)
        assert card["task"].get("straggler_fraction", 0.0) == stragglers
        assert card["task"]["rewards"]["navigation_weight_low"] == card["config"]["navigation_weight"]
        assert card["task"]["anchor_redraw_steps"] == (None if periods == 1 else 100)


def test_table3_shows_its_progress_in_episodes(capsys):
    """Table III's batches count on a progress bar on stderr (episodes done of those planned), the
    method flying named beside it; the table goes to stdout."""
    argv = ["--backend", "particle", "--protocol", "table3", "--formation", "6", "--episodes", "2", "--steps", "5"]
    assert main([*argv, "--policy", "atm"]) == 0
    out, err = capsys.readouterr()
    assert "| 2/2 [" in err and "c = 6 AT-M-Step3" in err and "episodes: 100%" in err
    assert "episodes:" not in out and "AT-M-Step3" in out
