"""cefc-eval's reports and the table8 cell cache: the cache never serves a cell flown with another
policy file, code or condition, an interrupted grid resumes, the default table8 run leaves the shipped
eval/reports/ alone, reports carry mean ± std and provenance and never print NaN, and atomic writes
honour the umask."""

import dataclasses
import hashlib
import json
import os
import re
import stat
import subprocess
import sys

import pytest
import torch

import cefc_mj.eval.table8 as table8
from cefc_mj import paths
from cefc_mj.cli.eval import main, single_table
from cefc_mj.eval import DEFAULT_POLICY
from cefc_mj.eval.runner import EpisodeSpec, policy_files, summarize
from cefc_mj.eval.table8 import aggregate, load_cells, plan_cells, report_csv, report_json, report_markdown, run_grid
from cefc_mj.fileio import write_atomic
from cefc_mj.nn.atm import ATMActor, ATMConfig
from cefc_mj.nn.policy_io import save_policy
from cefc_mj.provenance import code_version
from cefc_mj.task.config import TaskConfig

NAN = re.compile(r"\bnan\b", re.IGNORECASE)


def save_random_policy(path, seed):
    torch.manual_seed(seed)
    save_policy(ATMActor(ATMConfig.from_task(TaskConfig(n_agents=5, mode="formation"))), path)
    return path


@pytest.fixture
def flown(monkeypatch):
    """Records every episode actually flown (in this process)."""
    calls = []
    real = table8._fly

    def counting(spec, record=False, sitl=None, drop=None, runners=None):
        calls.append(spec)
        return real(spec, record=record)

    monkeypatch.setattr(table8, "_fly", counting)
    return calls


def particle_specs(policy, steps=10, deviations=(0.0, 0.3)):
    return [
        EpisodeSpec(formation=5, seed=0, backend="particle", deviation=d, steps=steps, policy=str(policy))
        for d in deviations
    ]


def plan(specs, policy):
    sha = policy_files(str(policy), [5])["5"]["sha256"]
    return plan_cells(specs, {5: sha}, code_version())


# ---------------------------------------------------------------------------- the cell cache
def test_cache_key_changes_with_policy_file_code_and_every_parameter(tmp_path, flown):
    policy = save_random_policy(tmp_path / "p.pt", seed=0)
    cell_file = tmp_path / "cells.jsonl"
    specs = particle_specs(policy)
    first = run_grid(plan(specs, policy), cell_file)
    assert len(flown) == 2 and len(load_cells(cell_file)) == 2

    again = run_grid(plan(specs, policy), cell_file)  # same key: reused, nothing flown
    assert len(flown) == 2 and [r["F"] for r in again] == [r["F"] for r in first]

    for field, value in (
        ("steps", 11),
        ("seed", 1),
        ("deviation", 0.31),
        ("formation", 6),
        ("wind", 3.0),
        ("backend", "mujoco"),
        ("policy", "other"),
        ("airframe", "crazyflie"),
    ):
        changed = dataclasses.replace(specs[0], **{field: value})
        sha = {5: "x", 6: "x"}
        assert plan_cells([changed], sha, "v")[0].key != plan_cells([specs[0]], sha, "v")[0].key, field
    assert plan_cells(specs, {5: "a"}, "v1")[0].key != plan_cells(specs, {5: "a"}, "v2")[0].key  # code digest

    save_random_policy(policy, seed=1)  # same name, other weights: every cell is flown again
    run_grid(plan(specs, policy), cell_file)
    assert len(flown) == 4 and len(load_cells(cell_file)) == 4
    row = next(iter(load_cells(cell_file).values()))
    assert set(row["key_fields"]) == {"schema", "spec", "policy_sha256", "code_version", "airframe"}


def test_interrupted_grid_resumes(tmp_path, flown):
    policy = save_random_policy(tmp_path / "p.pt", seed=0)
    cells = plan(particle_specs(policy, deviations=(0.0, 0.3, 0.5, 0.8)), policy)
    cell_file = tmp_path / "cells.jsonl"

    class StopAfterTwo:
        n = 0

        def update(self, k):
            self.n += k
            if self.n >= 2:
                raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_grid(cells, cell_file, progress=StopAfterTwo())
    assert len(load_cells(cell_file)) == 2 and len(flown) == 2
    with open(cell_file, "a") as fh:
        fh.write('{"key": "torn')  # a kill mid-line
    rows = run_grid(cells, cell_file)
    assert len(flown) == 4 and [r["deviation"] for r in rows] == [0.0, 0.3, 0.5, 0.8]
    run_grid(cells, cell_file, fresh=True)  # --fresh: flown anew, the old file moved aside
    assert len(flown) == 8 and (tmp_path / "cells.jsonl.replaced-1").is_file()


# ---------------------------------------------------------------------------- table8 end to end
def shipped_reports_digest():
    root = paths.EVAL_DIR / "reports"
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


TINY_TABLE8 = ["--protocol", "table8", "--formation", "5", "--episodes", "1", "--steps", "10"]


def test_table8_default_run_leaves_shipped_reports_alone(tmp_path):
    """`cefc-eval --protocol table8` (a real process, default flags) writes into a new folder under
    the current directory and leaves every file of the shipped eval/reports/ as it was."""
    before = shipped_reports_digest()
    proc = subprocess.run(
        [sys.executable, "-m", "cefc_mj.cli.eval", *TINY_TABLE8],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert shipped_reports_digest() == before
    (out,) = (tmp_path / "cefc-eval-reports").iterdir()
    assert out.name.startswith(f"table8-{DEFAULT_POLICY}-mujoco-") and f"reports go to {out}" in proc.stdout
    assert {p.name for p in out.iterdir()} == {
        "table8.md",
        "table8.csv",
        "table8.json",
        "table8.png",
        "table8_cells_mujoco.jsonl",
    }
    assert f"0 of 7 cells reused from {out / 'table8_cells_mujoco.jsonl'}" in proc.stdout
    data = json.loads((out / "table8.json").read_text())
    assert data["provenance"]["policies"]["5"]["name"] == "atm_c5_nav" and data["comparable_to_paper"] is False
    assert len(data["rows"]["5"]) == 7 and not NAN.search((out / "table8.md").read_text())


def test_table8_reuses_cells_of_the_same_key_and_says_so(tmp_path, capsys, flown):
    out = tmp_path / "reports"
    cells = out / "table8_cells_mujoco.jsonl"
    assert main(TINY_TABLE8 + ["--report-dir", str(out)]) == 0
    assert f"0 of 7 cells reused from {cells}" in capsys.readouterr().out and len(flown) == 7
    assert main(TINY_TABLE8 + ["--report-dir", str(out)]) == 0  # the same command: every cell reused
    assert f"7 of 7 cells reused from {cells}" in capsys.readouterr().out and len(flown) == 7
    assert json.loads((out / "table8.json").read_text())["cells_reused"] == 7
    assert "7 of 7 episodes were reused" in (out / "table8.md").read_text()
    assert main(TINY_TABLE8[:-1] + ["11", "--report-dir", str(out)]) == 0  # another --steps: none reused
    printed = capsys.readouterr().out
    assert "0 of 7 cells reused" in printed and "7 rows there are for other code" in printed and len(flown) == 14
    assert main(TINY_TABLE8 + ["--report-dir", str(out), "--fresh"]) == 0
    assert "--fresh" in capsys.readouterr().out and len(flown) == 21 and (out / f"{cells.name}.replaced-1").is_file()


# ---------------------------------------------------------------------------- report content
def fake_rows(seeds=3, calm_zero=False):
    rows = []
    for cond, (wind, dev) in table8.CONDITIONS.items():
        for s in range(seeds):
            f = 0.0 if calm_zero and cond == "SITL-S" else 800.0 + 10 * s - 50 * dev
            rows.append(
                {
                    "formation": 5,
                    "seed": s,
                    "condition": cond,
                    "wind": wind,
                    "deviation": dev,
                    "F": f,
                    "N": 0.0 if calm_zero and cond == "SITL-S" else 600.0 - s,
                    "C": 0.1 * s,
                    "steps": 1000,
                    "diverged": None,
                }
            )
    return rows


META = {
    "command": "cefc-eval --protocol table8",
    "backend": "mujoco",
    "policy": "atm",
    "episodes": 3,
    "seed": 0,
    "steps": 1000,
    "report_dir": "r",
    "cell_file": "r/cells.jsonl",
    "cells_reused": 0,
    "cells_total": 21,
    "provenance": {
        "git_commit": "abc",
        "code_version": "0123456789abcdef",
        "library_versions": {"mujoco": "3.17.0", "code_version": "0123456789abcdef"},
        "policies": {"5": {"name": "atm_c5_step3", "file": "p.pt", "sha256": "f" * 64}},
    },
}


def test_table8_reports_carry_mean_std_and_provenance_never_nan():
    table = aggregate(fake_rows())
    md, csv_text, js = report_markdown(table, META), report_csv(table), report_json(table, META)
    assert "810.0 ± 10.0" in md and "sample std" in md and "f" * 64 in md and "3.17.0" in md
    assert csv_text.splitlines()[0].startswith("c,condition,episodes,diverged,F_mean,F_std,N_mean,N_std,C_mean,C_std")
    data = json.loads(js)
    cell = data["rows"]["5"]["SITL-S"]
    assert cell["F"] == 810.0 and cell["F_std"] == pytest.approx(10.0) and len(cell["episodes_detail"]) == 3
    assert cell["paper"]["F"] == 693 and data["provenance"]["git_commit"] == "abc"
    for text in (md, csv_text, js):
        assert not NAN.search(text)

    degenerate = aggregate(fake_rows(seeds=1, calm_zero=True))  # one seed, calm F+N = 0
    md = report_markdown(degenerate, {**META, "episodes": 1})
    assert "retention -: calm F+N is 0" in md and "±" not in md.split("## Provenance")[0].split("|---|")[1]
    assert not NAN.search(md + report_csv(degenerate) + report_json(degenerate, META))


def test_single_table_labels_columns_and_explains_dashes():
    calm = {
        **summarize([{"F": 0.0, "N": 0.0, "C": 0.0, "steps": 200}] * 2),
        "retention": None,
        "retention_note": "calm F+N is 0",
    }
    windy = {
        **summarize([{"F": 10.0, "N": 5.0, "C": 1.0, "steps": 200}, {"F": 20.0, "N": 7.0, "C": 0.0, "steps": 200}]),
        "retention": None,
        "retention_note": "calm F+N is 0",
    }
    text = single_table(
        {
            "condition": "Wind-8+Deviation-0.5",
            "steps": 200,
            "seeds": [0, 1],
            "backend": "mujoco",
            "policy": "atm",
            "rows": {"5": {"Wind-8+Deviation-0.5": {**windy, "diverged": 0}, "SITL-S": {**calm, "diverged": 0}}},
        }
    )
    assert not NAN.search(text)
    assert "F, N over 200 steps; the paper's are over 1000: not comparable" in text
    assert "15.0 ± 7.1" in text and "SITL-S (calm reference)" in text and "retention - (calm F+N is 0)" in text
    header = next(line for line in text.splitlines() if line.startswith("c "))
    assert header.split() == ["c", "source", "condition", "F", "N", "F+N", "C", "(%)", "retention"]
    assert "paper   Wind-8" in text and "paper   Deviation-0.5" in text and "no combined" in text
    assert "  seeds: each of our cells is the mean ± sample std over 2 seeds (0..1), the same" in text


def test_single_json_has_mean_std_and_per_episode_rows(tmp_path, capsys):
    policy = save_random_policy(tmp_path / "p.pt", seed=0)
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "--backend",
                "particle",
                "--formation",
                "5",
                "--steps",
                "10",
                "--episodes",
                "3",
                "--workers",
                "1",
                "--policy",
                str(policy),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "mean ± sample std over 3 seeds" in printed and not NAN.search(printed)
    text = out.read_text()
    cell = json.loads(text)["rows"]["5"]["SITL-S"]
    assert cell["episodes"] == 3 and cell["F_std"] is not None and len(cell["episodes_detail"]) == 3
    assert "NaN" not in text


# ---------------------------------------------------------------------------- file modes
def test_write_atomic_honours_the_umask_and_keeps_an_existing_mode(tmp_path):
    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / "a.txt", "x")
        assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
        os.umask(0o077)
        write_atomic(tmp_path / "b.txt", "x")
        assert stat.S_IMODE((tmp_path / "b.txt").stat().st_mode) == 0o600
        (tmp_path / "a.txt").chmod(0o640)
        write_atomic(tmp_path / "a.txt", "y")
        assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o640 and (tmp_path / "a.txt").read_text() == "y"
    finally:
        os.umask(old)


def test_shipped_reports_folder_is_recognised(tmp_path):
    from cefc_mj.cli.eval import default_report_dir, is_shipped_reports

    shipped = paths.EVAL_DIR / "reports"
    assert is_shipped_reports(shipped) and is_shipped_reports(shipped / "quad")
    assert not is_shipped_reports(tmp_path) and not is_shipped_reports(paths.EVAL_DIR)
    assert not is_shipped_reports(default_report_dir("atm", "mujoco"))
    assert default_report_dir("/x/my policy.pt", "mujoco").name.startswith("table8-my_policy-mujoco-")
