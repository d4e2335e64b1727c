"""The test ledger (cefc_mj/eval/ledger.py, eval/test_ledger.jsonl): its records, the rule that a report
flown on games an earlier flight informed a change with is tainted, the shipped reports held to that
rule, and cefc-eval recording its own flights of test seeds.

The rule on the shipped reports fails for any tainted report not in KNOWN_TAINTED, and for any entry of
KNOWN_TAINTED that is no longer tainted or no longer shipped. The pre-registered Table V
(eval/reports/prereg/table5.json, docs/research/preregistration.md) flew batch 50000 once and must stay clean; the
generation-4 table5.json beside it is kept as the earlier, tainted result it is listed as.
"""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from cefc_mj import paths, seeds
from cefc_mj.errors import ConfigError
from cefc_mj.eval import ledger
from cefc_mj.eval.ledger import Flight, read_ledger, record_flight, tainting_flights

ROOT = Path(__file__).resolve().parent.parent
REPORTS = paths.EVAL_DIR / "reports"
SHIPPED_LEDGER = paths.EVAL_DIR / ledger.LEDGER_NAME
BATCH_10000 = "batch seed 10000, whose flights of generations 2 and 3 decided two adversary replacements"
KNOWN_TAINTED = {
    "table5.json": f"Table V of generation 4 on {BATCH_10000}",
    "table6.json": f"Table VI on {BATCH_10000}",
    "table7.json": f"Table VII on {BATCH_10000}",
    "table5_mujoco/table5.json": f"CI-HRL seed 0 on quadrotors on {BATCH_10000}",
    "table5_sitl_m/table5_sitl_m.json": "seeds 20000..20099, whose first 20 games decided the study's size",
}
"""Shipped reports (under eval/reports/) known to be flown on games that informed a change, each with
why. Remove an entry when its report is re-flown on a clean batch; never add one to silence the test."""


# ---------------------------------------------------------------------------- records
def _flight(protocol="table5", seed=10000, episodes=50, informed=False, name="x") -> Flight:
    return Flight(
        id=name,
        protocol=protocol,
        seed=seed,
        episodes=episodes,
        command="cefc-eval ...",
        commit=None,
        code_version=None,
        date="2026-12-01",
        informed_change=informed,
        change="a change" if informed else None,
    )


def test_records_round_trip_marks_and_queries(tmp_path):
    path = tmp_path / "ledger.jsonl"
    prov = {"git_commit": "abc123", "code_version": "d" * 16}
    first = record_flight(
        "table5", 10000, 50, "cefc-eval --protocol table5 --seed 10000", prov, ["r/table5.json"], path=path
    )
    sitl = record_flight("table5-sitl-m", 20000, 100, "cefc-eval --sitl-m ...", None, path=path)
    assert first.commit == "abc123" and first.outputs == ("r/table5.json",) and not first.informed_change
    assert [f.id for f in read_ledger(path).flights] == [first.id, sitl.id]
    marked = ledger.mark_informed_change(first.id, "the adversary replaced", path=path)
    assert marked.informed_change and marked.change == "the adversary replaced"
    assert ledger.flights("table5", 10000, path=path) == [marked]
    assert ledger.flights(seed=20099, path=path) == [sitl] and ledger.flights(seed=20100, path=path) == []
    lines = path.read_text().splitlines()
    assert [json.loads(line)["kind"] for line in lines] == ["flight", "flight", "mark"]  # appended, never rewritten
    with pytest.raises(ConfigError, match="no flight 'nope'"):
        ledger.mark_informed_change("nope", "x", path=path)


def test_only_declared_test_batches_are_recorded_and_a_damaged_ledger_is_refused(tmp_path, capsys):
    path = tmp_path / "ledger.jsonl"
    with pytest.raises(ConfigError, match="flies no seed of the test block"):
        record_flight("table5", 200, 50, "cmd", path=path)
    with pytest.raises(ConfigError, match="flies no declared test batch"):
        record_flight("single", 91731, 1, "cmd", path=path)
    assert ledger.touches_test_block("table8", 9995, 10) and not ledger.touches_test_block("table8", 9990, 10)
    assert not ledger.touches_test_block("table5", 9999, 50)  # a batch seed is one seed, not 50
    assert [b.name for b in ledger.declared_batches("table8", 10015, 10)] == ["Table VIII"]
    assert [b.name for b in ledger.declared_batches("table5-sitl-m", 20099, 5)] == ["SITL-M game fidelity"]
    assert ledger.declared_batches("table5", 10001, 50) == []  # another batch seed: other games
    assert ledger.declared_batches("single", 50000, 1) == []  # the formation family's games
    assert ledger.record_if_test("single", 91731, 3, "cmd", None) is None and not path.exists()
    assert capsys.readouterr().out == (
        "test ledger: not recorded: seeds 91731..91733 are in the test block but in no declared test batch "
        "(cefc_mj.seeds.TEST_BATCHES)\n"
    )
    # every reader and writer checks the ledger the same way: a damaged line, torn or not, is refused
    good = record_flight("table8", 10000, 20, "cmd", path=path)
    for damage in ('{"kind": "fli', '{"kind": "flight"}\n', "[1, 2]\n", b"\xff\xfe\n"):
        path.write_text(json.dumps(good.to_json()) + "\n")
        with open(path, "ab") as fh:
            fh.write(damage if isinstance(damage, bytes) else damage.encode())
        before = path.read_bytes()
        with pytest.raises(ConfigError, match=r"ledger.jsonl:2: ") as refused:
            read_ledger(path)
        assert "\n" not in str(refused.value)
        with pytest.raises(ConfigError, match=r"ledger.jsonl:2: "):
            record_flight("table7", 10000, 50, "cmd", path=path)
        with pytest.raises(ConfigError, match=r"ledger.jsonl:2: "):
            ledger.mark_informed_change(good.id, "x", path=path)
        assert path.read_bytes() == before  # nothing appended


def test_where_it_writes(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv(ledger.ENV_VAR, raising=False)
    if paths.CHECKOUT_ROOT is not None:
        assert ledger.ledger_path() == (paths.CHECKOUT_ROOT / "eval" / "test_ledger.jsonl", "checkout")
    monkeypatch.setattr(paths, "CHECKOUT_ROOT", None)  # an installed wheel: no repository to write into
    assert record_flight("table5", 10000, 50, "cmd") is None
    assert capsys.readouterr().err == (
        "test ledger: this flight of test seeds is not recorded (no checkout (an installed package); "
        "set CEFC_TEST_LEDGER=PATH to record)\n"
    )
    monkeypatch.setenv(ledger.ENV_VAR, "/proc/no/ledger.jsonl")  # unwritable: one line, the flight goes on
    assert record_flight("table5", 10000, 50, "cmd") is None
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("test ledger: this flight of test seeds is not recorded (/proc")
    monkeypatch.setenv(ledger.ENV_VAR, str(tmp_path / "mine.jsonl"))
    assert record_flight("table5", 10000, 50, "cmd") is not None and (tmp_path / "mine.jsonl").is_file()


def test_the_module_lists_and_marks(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(ledger.ENV_VAR, str(tmp_path / "l.jsonl"))
    flight = record_flight("table6", 10000, 50, "cmd")
    assert ledger.main(["mark", flight.id, "Table VI's rows changed"]) == 0
    assert ledger.main([]) == 0
    out = capsys.readouterr().out
    assert "1 flights" in out and f"{flight.id}  table6 seeds 10000 (game)" in out and "informed: Table VI's" in out
    assert ledger.main(["mark", "nope", "x"]) == 2 and "no flight 'nope'" in capsys.readouterr().err


# ---------------------------------------------------------------------------- the rule
def test_the_rule_on_synthetic_ledgers():
    """Tainted: an earlier flight on some of the same games that informed a change; not tainted: a later
    one, one on other games (another seed or the other family), or one that informed nothing."""
    informed = _flight(informed=True, name="informed")
    report = _flight(name="report")
    assert tainting_flights(report, [informed, report]) == [informed]
    assert tainting_flights(report, [report, informed]) == []  # a change after the report's flight
    assert tainting_flights(report, [_flight(name="plain"), report]) == []
    other_seed = _flight(seed=30000, informed=True, name="other seed")
    other_family = _flight(protocol="table8", seed=10000, episodes=20, informed=True, name="table8")
    assert tainting_flights(report, [other_seed, other_family, report]) == []
    # Table VI on the batch that a Table V flight informed a change with: the same games
    assert tainting_flights(_flight("table6", name="t6"), [informed, _flight("table6", name="t6")]) == [informed]
    # one game per seed: any seed in common counts, and a batch seed shares its first draws with it
    sitl = _flight("table5-sitl-m", 20000, 100, name="sitl")
    early = _flight("table5-sitl-m", 20010, 5, informed=True, name="early")
    assert tainting_flights(sitl, [early, sitl]) == [early]
    assert tainting_flights(sitl, [_flight("table5", 20099, informed=True, name="batch"), sitl])
    assert tainting_flights(sitl, [_flight("table5", 20100, informed=True, name="batch"), sitl]) == []
    with pytest.raises(ConfigError, match="not in the ledger"):
        tainting_flights(report, [informed])


def _shipped_test_flights() -> dict[str, dict]:
    """{path under eval/reports: what flew it (protocol, seed, episodes, command, commit)} of every
    shipped game-table or Table VIII report that flew a test-block seed."""
    found = {}
    for path in sorted(REPORTS.rglob("*.json")):
        data = json.loads(path.read_text())
        if not isinstance(data, dict) or not isinstance(data.get("schema"), str):
            continue
        proto = data["protocol"] if isinstance(data["protocol"], dict) else data  # table8/single: top level
        protocol = "table5-sitl-m" if proto.get("sitl_m") else data["schema"].removeprefix("cefc-eval/")
        if protocol not in seeds.PROTOCOL_FAMILY:
            continue
        if isinstance(data.get("seeds"), list):  # single: the seeds flown
            seed, episodes = min(data["seeds"]), len(data["seeds"])
        else:
            seed, episodes = proto["seed"], proto["episodes"]
        if ledger.touches_test_block(protocol, seed, episodes):
            found[str(path.relative_to(REPORTS))] = {
                "protocol": protocol,
                "seed": seed,
                "episodes": episodes,
                "command": proto["command"],
                "commit": data.get("provenance", {}).get("git_commit"),
            }
    return found


def test_every_shipped_test_report_is_in_the_ledger_and_untainted_unless_known():
    flights = read_ledger(SHIPPED_LEDGER).flights
    reports = _shipped_test_flights()
    assert {"table5.json", "prereg/table5.json", "table8_test/wind8.json", "table8_test/dev08.json"} <= set(reports)
    tainted = {}
    for name, flew in reports.items():
        matches = [f for f in flights if all(getattr(f, k) == v for k, v in flew.items())]
        assert len(matches) == 1, f"{name}: {len(matches)} ledger flights match {flew}"
        assert f"eval/reports/{name}" in matches[0].outputs, name
        earlier = tainting_flights(matches[0], flights)
        if earlier:
            tainted[name] = [f.id for f in earlier]
    new = sorted(set(tainted) - set(KNOWN_TAINTED))
    assert not new, f"reports flown on games that informed a change: {new} ({tainted})"
    clean = sorted(set(KNOWN_TAINTED) - set(tainted))
    assert not clean, f"no longer tainted or no longer shipped: remove {clean} from KNOWN_TAINTED"


def test_the_shipped_ledger_backfills_the_known_history():
    flights = read_ledger(SHIPPED_LEDGER).flights
    batch = [f for f in flights if f.family == seeds.GAME_FAMILY and seeds.GAME_TEST_SEED in f.seeds]
    assert [f.protocol for f in batch if f.informed_change] == ["table5"] * 5  # generations 2 (x4) and 3
    assert all("adversary" in f.change for f in batch if f.informed_change)
    table8 = [f for f in flights if f.family == seeds.FORMATION_FAMILY]
    declared = [set(b.seeds) for b in seeds.TEST_BATCHES if b.family == seeds.FORMATION_FAMILY]
    assert all(f.seeds in declared and not f.informed_change for f in table8) and table8
    assert set(seeds.TABLE8_TEST_SEEDS) in [f.seeds for f in table8]
    dates = [f.date for f in flights]
    assert dates == sorted(dates)  # recorded in the order flown


# ---------------------------------------------------------------------------- the next batch
def test_the_preregistered_batch_is_a_never_informing_test_batch_of_other_games():
    seed = seeds.GAME_PREREGISTERED_TEST_SEED
    assert seed in seeds.TEST and seed != seeds.GAME_TEST_SEED
    declared = {b.first: b for b in seeds.TEST_BATCHES}
    assert declared[seed].family == seeds.GAME_FAMILY and declared[seed].count == 1
    for a in seeds.TEST_BATCHES:  # declared batches of one family never share a seed
        for b in seeds.TEST_BATCHES:
            if a is not b and a.family == b.family:
                assert not set(a.seeds) & set(b.seeds)
    touching = [f for f in read_ledger(SHIPPED_LEDGER).flights if f.family == seeds.GAME_FAMILY and seed in f.seeds]
    assert all(f.protocol in seeds.BATCH_SEEDED and not f.informed_change for f in touching)
    # A batch seed seeds one generator for the whole batch: other batch seeds draw other games. The games
    # are built as the evaluation builds them (the env of a batch, reset with the batch seed) and
    # compared by content: each game's spawns, adversary start, obstacles, targets and anchor.
    from cefc_mj.game_protocol import EPISODES

    shared = {s: _game_contents(s) for s in (seed, seeds.GAME_TEST_SEED, seeds.GAME_VALIDATION_SEED)}
    assert len(set(shared[seed])) == EPISODES  # fifty different games in the batch
    assert _game_contents(seed) == shared[seed]  # the same seed is the same games: the comparison sees sameness
    for other in (seeds.GAME_TEST_SEED, seeds.GAME_VALIDATION_SEED):
        assert not set(shared[seed]) & set(shared[other]), f"batch {seed} shares games with batch {other}"
        # nor any drawn part of a game: the spawns, the adversary's start, the obstacles, the anchor
        # (not the targets: 2 of the 4 corners, a dozen layouts, which batches share by design)
        for part in (0, 1, 2, 4):
            assert not {g[part] for g in shared[seed]} & {g[part] for g in shared[other]}, (other, part)


def _game_contents(batch_seed: int) -> list[tuple]:
    """Each game of a batch as the evaluation flies it (`game_protocol.game_task`, EPISODES envs, reset with
    the batch seed): (agent spawns, adversary start, obstacles, targets, anchor), rounded to 1e-9 m."""
    from cefc_mj.env import BatchedCEFCEnv
    from cefc_mj.game_protocol import EPISODES, game_task

    env = BatchedCEFCEnv(game_task(), n_envs=EPISODES, seed=batch_seed)
    env.reset(seed=batch_seed)
    parts = (env.world.agent_pos, env.world.adversary_pos, env.obstacles, env.targets, env.anchor)

    def key(a) -> tuple:
        return tuple(np.round(np.asarray(a, dtype=float), 9).ravel())

    return [tuple(key(part[e]) for part in parts) for e in range(EPISODES)]


# ---------------------------------------------------------------------------- cefc-eval records itself
@pytest.fixture
def seed_only_policies(tmp_path):
    """A folder with MAPPO and CI-HRL at training seeds 100 and 101 only (untrained weights) and the
    game's adversary, as a pre-registered run's folder would be."""
    from cefc_mj.game_protocol import game_task
    from cefc_mj.nn.adversary_policy import AdversaryNetConfig, AdversaryPolicy, save_adversary_policy
    from cefc_mj.nn.highlevel_policy import HighLevelPolicy, save_highlevel_policy
    from cefc_mj.nn.registry import GAME_ADVERSARY

    folder = tmp_path / "prereg"
    folder.mkdir()
    for stem, variant in (("cihrl_mappo", "mappo"), ("cihrl_consmac_a", "consmac-a")):
        for k in (100, 101):
            name = f"{stem}_seed{k}"
            policy = HighLevelPolicy.build(variant, game_task(), seed=k)
            save_highlevel_policy(policy, folder / f"{name}.pt", meta={"name": name, "decision_interval": 10})
    save_adversary_policy(AdversaryPolicy(AdversaryNetConfig(), seed=0), folder / f"{GAME_ADVERSARY}.pt")
    return folder


@pytest.mark.usefixtures("one_torch_thread")
def test_cefc_eval_records_its_test_flights_and_reads_another_folder(seed_only_policies, tmp_path, capsys):
    from cefc_mj.cli.eval import main

    path = Path(os.environ[ledger.ENV_VAR])
    before = len(read_ledger(path).flights)
    out = tmp_path / "reports"
    argv = [
        "--backend",
        "particle",
        "--protocol",
        "table5",
        "--episodes",
        "1",
        "--policies-dir",
        str(seed_only_policies),
    ]
    assert main([*argv, "--seed", "10000", "--report-dir", str(out)]) == 0
    printed = capsys.readouterr().out
    flights = read_ledger(path).flights
    assert (
        len(flights) == before + 1
        and f"test ledger: flight {flights[-1].id} of test batch 'Tables V-VII (shipped)' recorded" in printed
    )
    flight = flights[-1]
    assert (flight.protocol, flight.seed, flight.episodes, flight.source) == ("table5", 10000, 1, "cefc-eval")
    assert flight.command.endswith("--report-dir " + str(out)) and flight.outputs == (str(out / "table5.json"),)
    assert flight.commit == json.loads((out / "table5.json").read_text())["provenance"].get("git_commit")
    report = json.loads((out / "table5.json").read_text())
    assert list(report["rows"]) == ["MAPPO+AT-M", "CI-HRL"]  # no seed-0 file: each row from seed 100
    assert report["rows"]["CI-HRL"]["training_seeds"]["seeds"] == [100, 101]
    assert report["rows"]["MAPPO+AT-M"]["policy"] == "cihrl_mappo_seed100.pt"
    assert report["comparison"]["primary"]["method"] == "MAPPO+AT-M"
    assert main([*argv, "--seed", "7"]) == 0  # the protocol block: nothing recorded
    assert len(read_ledger(path).flights) == before + 1 and "test ledger" not in capsys.readouterr().out


def _eval_refusal(argv, capsys) -> str:
    from cefc_mj.cli.eval import main

    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert exit_info.value.code == 2 and len(err.splitlines()) == 1, err
    return err


def test_the_preregistered_batch_flies_only_as_planned(tmp_path, monkeypatch, capsys):
    """Every way to fly the pre-registered batch other than the planned flight is refused before
    anything flies (nothing here flies it: each call ends in the flag checks)."""
    seed = str(seeds.GAME_PREREGISTERED_TEST_SEED)
    table5 = ["--backend", "particle", "--protocol", "table5", "--seed", seed]
    assert "add --preregistered-flight" in _eval_refusal(table5, capsys)
    assert "add --preregistered-flight" in _eval_refusal([*table5[:3], "table6", *table5[4:]], capsys)
    flight = [*table5, "--preregistered-flight"]
    assert "(no --policy)" in _eval_refusal([*flight, "--policy", "cihrl_consmac_a"], capsys)
    assert "give --policies-dir" in _eval_refusal(flight, capsys)
    assert "(no --policy)" in _eval_refusal([*table5[:5], "40000", "--preregistered-flight"], capsys)
    partial = tmp_path / "prereg"
    partial.mkdir()
    (partial / "cihrl_consmac_a_seed100.pt").write_bytes(b"")
    err = _eval_refusal([*flight, "--policies-dir", str(partial)], capsys)
    assert "104 of 105 planned runs are not in" in err and "cihrl_mappo_seed100.pt" in err, err
    # a batch the ledger shows flown is never flown again, whatever the folder holds
    ledger_file = tmp_path / "ledger.jsonl"
    monkeypatch.setenv("CEFC_TEST_LEDGER", str(ledger_file))
    ledger.record_flight("table5", seeds.GAME_PREREGISTERED_TEST_SEED, 50, "cefc-eval ...", None, [])
    assert "was already flown" in _eval_refusal([*flight, "--policies-dir", str(partial)], capsys)


# ---------------------------------------------------------------------------- the pre-registered runs
def test_the_prereg_driver_lists_the_plan_and_every_shipped_run_is_complete():
    """`examples/prereg_table5.py --list` names every planned run once; a run marked done has its model
    card (written by the training command, with the seed of its plan) and its kept progress log."""
    import subprocess
    import sys

    from cefc_mj.eval.prereg import planned_runs

    script = ROOT / "examples" / "prereg_table5.py"
    listed = subprocess.run([sys.executable, script, "--list"], capture_output=True, text=True, check=True).stdout
    lines = listed.splitlines()
    runs = planned_runs()
    assert len(lines) == len(runs) + 1
    n_done = 0
    for (stem, _), line in zip(runs, lines[:-1], strict=True):
        policy = ROOT / "policies" / "prereg" / f"{stem}.pt"
        assert line.startswith("done" if policy.is_file() else "todo"), line
        if policy.is_file():
            n_done += 1
            card = json.loads(policy.with_suffix(".json").read_text())
            assert card["seed"] == int(stem.rsplit("seed", 1)[1]) and card["git_commit"]
            assert (ROOT / "eval" / "training_logs" / "prereg" / stem / "progress.csv").is_file()
            assert " min " in line  # its training time, read from the kept log
    assert lines[-1].startswith(f"{n_done} of {len(runs)} runs done")
    bad = subprocess.run([sys.executable, script, "--start-before", "25:00"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--start-before" in bad.stderr


def test_the_shipped_preregistered_table_is_the_plan_flown_once():
    """eval/reports/prereg/table5.json: the pre-registered batch, flown once (one ledger flight, which
    informed nothing), every row with its planned training seeds; its Markdown and docs/results.md's Table V
    are the report's own table, and its primary comparison is labelled confirmatory."""
    from cefc_mj.eval.highlevel import TABLE5_ROWS
    from cefc_mj.eval.highlevel_comparison import add_comparisons
    from cefc_mj.eval.highlevel_report import table5_markdown
    from cefc_mj.eval.prereg import OTHER_SEEDS, PRIMARY_SEEDS
    from cefc_mj.game_protocol import EPISODES

    result = json.loads((REPORTS / "prereg" / "table5.json").read_text())
    seed = seeds.GAME_PREREGISTERED_TEST_SEED
    assert (result["protocol"]["seed"], result["protocol"]["episodes"]) == (seed, EPISODES)
    flown = [f for f in read_ledger(SHIPPED_LEDGER).flights if f.family == seeds.GAME_FAMILY and seed in f.seeds]
    assert len(flown) == 1 and flown[0].protocol == "table5" and not flown[0].informed_change
    assert flown[0].outputs == ("eval/reports/prereg/table5.json",)
    primary_rows = {"CI-HRL", "CI-HRL-wo-FT", "MAPPO+AT-M"}
    assert list(result["rows"]) == [row[0] for row in TABLE5_ROWS]  # every row, in the table's order
    for method, row in result["rows"].items():
        expected = PRIMARY_SEEDS if method in primary_rows else OTHER_SEEDS
        assert row["training_seeds"]["seeds"] == list(expected), method
    markdown = table5_markdown(add_comparisons(result))
    shipped = (REPORTS / "prereg" / "table5.md").read_text()
    assert markdown in shipped and "confirmatory: the pre-registered batch" in markdown
    results = (ROOT / "docs" / "results.md").read_text()
    missing = [line for line in markdown.splitlines() if line.startswith("|") and line not in results]
    assert not missing, f"docs/results.md's Table V is not the pre-registered report's: {missing[:1]}"
