"""benchmarks/adversary_strength.py (docs/research/high_level.md, "The next adversary"): a real run as a subprocess on
a learned team and a rule team (its figures are evaluate_adversary's for the same adversary and games,
the kept rule's spec flies exactly the named rule, a trained adversary by its file), rule specs parsed
into InterceptRule, and one-line
errors with exit code 2 before any game is flown (`main` in-process; the real run as a subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from benchmark_scripts import load_benchmark

from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.task.adversary import InterceptRule
from cefc_mj.train.adversary import AdversaryConfig, evaluate_adversary, load_population
from cefc_mj.train.config import Budget

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "adversary_strength.py"
LEARNED = "cihrl_mappo"
TRAINED = "adversary_ppo_nearest_group_intercept"

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _script():
    return load_benchmark("adversary_strength")


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300, cwd=ROOT, check=False
    )


def test_rule_specs():
    script = _script()  # executed once: every call below reads the same module

    def parse(spec):
        return script.parse_adversary(spec)[0]

    assert script.parse_adversary("nearest_group_member") == ("nearest_group_member", "nearest_group_member")
    assert script.parse_adversary("intercept")[1] == str(InterceptRule())
    assert parse("intercept") == InterceptRule()
    assert parse("intercept:strike_at=any,strike_distance=2.5") == InterceptRule(strike_at="any", strike_distance=2.5)
    assert parse("intercept:strike_distance=none,horizon=1") == InterceptRule(strike_distance=None, horizon=1.0)
    assert script.row_of("cihrl_consmac_a_clm_seed2_wo_ft") == "CI-HRL-w-CL-M-wo-FT"
    assert script.row_of("cihrl_consmac_a_seed3") == "CI-HRL"
    assert script.row_of("rule-split") is None


@pytest.mark.parametrize(
    "args, message",
    [
        (["--adversaries", "chase_everything"], "--adversaries: adversary chase_everything:"),
        (["--adversaries", "intercept:lead=1"], "'lead=1' is not FIELD=VALUE with"),
        (["--adversaries", "intercept:horizon=-1"], "horizon=-1.0: must be a finite number >= 0"),
        (["--adversaries", "intercept:strike_at=lone"], "strike_at='lone'"),
        (["--adversaries", "intercept", "--teams", "no_such_policy"], "--teams:"),
        (["--adversaries", "intercept", "--seed", "10000"], "--seed=10000: not a validation game seed"),
        (["--adversaries", "intercept", "--episodes", "0"], "--episodes and --workers"),
        (["--adversaries", "intercept", "--out", "/proc/adversary_strength/x.json"], "cannot write there"),
    ],
)
def test_bad_input_is_one_line_with_exit_code_2(args, message, capsys):
    try:
        code = _script().main(args)
    except SystemExit as e:  # argparse's errors
        code = e.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert message in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_a_run_writes_the_per_team_and_per_row_figures(tmp_path):
    out = tmp_path / "sweep" / "rules.json"
    result = _run(
        "--adversaries", "intercept", "nearest_group_intercept", "intercept:strike_at=any", TRAINED,
        "--smoke", "--workers", "2", "--out", str(out),
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    report = json.loads(out.read_text())
    assert set(report["per_team"]) == {LEARNED, "rule-split"}
    assert report["protocol"]["seed_block"] == "validation" and report["protocol"]["episodes"] == 2
    # the figures are evaluate_adversary's on the same games, each team over its own low level
    cfg = AdversaryConfig(budget=Budget(iterations=1), teams=(LEARNED,))
    population, _, low_level, interval, _ = load_population(cfg)
    direct = evaluate_adversary("nearest_group_intercept", population[LEARNED], low_level, cfg.task(), 2, 200, interval)
    figures = report["per_team"][LEARNED]
    assert figures["intercept"]["E"] == figures["nearest_group_intercept"]["E"] == direct["E"]
    trained = evaluate_adversary(
        resolve_adversary(TRAINED)[1], population[LEARNED], low_level, cfg.task(), 2, 200, interval
    )
    assert figures[TRAINED]["E"] == trained["E"]
    assert report["adversaries"][TRAINED]["policy"] == f"{TRAINED}.pt"
    row = report["per_row"]["intercept:strike_at=any"]
    assert row["MAPPO+AT-M"] == pytest.approx(figures["intercept:strike_at=any"]["E"] / figures["nearest_group"]["E"])
    assert set(row) == {"MAPPO+AT-M", "rule team rule-split"}
    assert "| `intercept` | " in result.stdout and "(MAPPO+AT-M)" in result.stdout
