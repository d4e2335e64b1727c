"""Tables V and VI (cefc_mj/eval/highlevel.py, `cefc-eval --protocol table5|table6`).

Real particle games flown by the shipped student under freshly built (untrained) high-level
policies written as real policy files; 2-4 episodes, so the file takes well under a minute.
"""

import json

import numpy as np
import pytest
from scipy import stats

from cefc_mj import paths
from cefc_mj.cli.eval import main
from cefc_mj.errors import ConfigError
from cefc_mj.eval.conditions import Conditions
from cefc_mj.eval.highlevel import run_table5, run_table6, run_table7
from cefc_mj.eval.highlevel_report import format_highlevel_table, plot_highlevel_table
from cefc_mj.game_protocol import DT, evaluate_highlevel_episodes, game_task
from cefc_mj.hierarchy import CLM_PER_GROUP, load_low_level, recorded_low_level
from cefc_mj.nn.adversary_policy import AdversaryNetConfig, AdversaryPolicy, save_adversary_policy
from cefc_mj.nn.highlevel_policy import HighLevelPolicy, load_highlevel_policy, save_highlevel_policy
from cefc_mj.nn.registry import GAME_ADVERSARY

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture
def policies(tmp_path):
    """A policies folder with MAPPO seeds 0 and 1, a CI-HRL policy and both PPO adversaries (untrained weights)."""
    folder = tmp_path / "policies"
    folder.mkdir()
    task = game_task()
    for name, variant, seed in (
        ("cihrl_mappo", "mappo", 0),
        ("cihrl_mappo_seed1", "mappo", 1),
        ("cihrl_consmac_a", "consmac-a", 0),
    ):
        save_highlevel_policy(
            HighLevelPolicy.build(variant, task, seed=seed),
            folder / f"{name}.pt",
            meta={"name": name, "decision_interval": 10},
        )
    for seed, name in enumerate(("adversary_ppo", "adversary_ppo_nearest_group_member", GAME_ADVERSARY)):
        save_adversary_policy(AdversaryPolicy(AdversaryNetConfig(), seed=seed), folder / f"{name}.pt")
    return folder


def test_table5_on_two_processes_is_the_table_on_one(policies):
    """Each policy file's batch is seeded on its own: the pool changes where it flies, not a number."""
    one = run_table5(episodes=2, seed=3, policies_dir=policies)
    calls = []
    two = run_table5(episodes=2, seed=3, policies_dir=policies, workers=2, progress=lambda *c: calls.append(c))
    assert json.dumps(two, default=float) == json.dumps(one, default=float)
    # progress: 0 of all games first, then each batch of 2 games (2 rows x seeds x 2 adversaries = 6 batches)
    assert calls == [(0, 12), (2, 12), (4, 12), (6, 12), (8, 12), (10, 12), (12, 12)]
    assert list(two["rows"]["MAPPO+AT-M"]["against_rule"]["seeds"]) == [0, 1]


def test_table5_rows_units_seeds_and_missing_methods(policies):
    result = run_table5(episodes=2, seed=3, policies_dir=policies)
    assert list(result["rows"]) == ["MAPPO+AT-M", "CI-HRL"]
    assert result["protocol"]["missing"] == [
        "MASAC+AT-M (BenchMARL; stands in for HASAC) (benchmarl_masac.pt)",
        "TarMAC+AT-M (cihrl_tarmac.pt)",
        "MASIA+AT-M (cihrl_masia.pt)",
        "NVIF+AT-M (cihrl_nvif.pt)",
        "CI-HRL-w-CL-M-wo-FT (cihrl_consmac_a_clm_wo_ft.pt)",
        "CI-HRL-w-CL-M (cihrl_consmac_a_clm.pt)",
        "CI-HRL-DT (cihrl_consmac_a_dt.pt)",
        "CI-HRL-wo-FT (cihrl_consmac_a_wo_ft.pt)",
        "CI-HRL (ConsMAC-O) (cihrl_consmac_o.pt)",
        "MAPPO+AT-M (BenchMARL) (benchmarl_mappo.pt)",
        "CI-HRL (ConsMAC-wo-Com) (cihrl_consmac_a_wo_com.pt)",
        "CI-HRL (ConsMAC-wo-Mem) (cihrl_consmac_a_wo_mem.pt)",
        "CI-HRL (ConsMAC-wo-DE) (cihrl_consmac_a_wo_de.pt)",
        "CI-HRL (ConsMAC-wt-RL) (cihrl_consmac_a_wt_rl.pt)",
        "CI-HRL (ConsMAC-G) (cihrl_consmac_a_consmac_g.pt)",
    ]
    for row in result["rows"].values():
        per = {k: np.array(v) for k, v in row["per_episode"].items()}
        np.testing.assert_allclose(per["R_H"], per["R_t"] + per["R_n"] + per["R_e"], rtol=1e-12, atol=1e-9)
        assert (per["E"] >= 0).all() and (per["E"] <= 400).all()
        for m in ("R_H", "R_t", "R_n", "R_e", "E"):
            assert row["seconds"][m] == pytest.approx(row[m] * DT)
        assert row["R_n"] < 0 and row["paper"] is not None
    seeds = result["rows"]["MAPPO+AT-M"]["training_seeds"]
    assert seeds["seeds"] == [0, 1] and seeds["files"] == ["cihrl_mappo.pt", "cihrl_mappo_seed1.pt"]
    assert seeds["mean"]["R_H"] == pytest.approx(np.mean(seeds["R_H"]))
    assert result["rows"]["CI-HRL"]["training_seeds"]["seeds"] == [0]
    assert seeds["ci95"]["E"]["ci_low"] <= seeds["mean"]["E"] <= seeds["ci95"]["E"]["ci_high"]
    assert set(result["rows"]["MAPPO+AT-M"]["against_rule"]["E"]) <= set(range(401))  # per seed, vs the rule
    strength, rule_e = (
        result["rows"]["MAPPO+AT-M"]["adversary_strength"],
        result["rows"]["MAPPO+AT-M"]["against_rule"]["E"],
    )
    assert strength["ratio"] == pytest.approx(np.mean(seeds["E"]) / np.mean(rule_e))
    differences = np.subtract(seeds["E"], rule_e)
    if np.all(differences == differences[0]):
        assert strength["p_weaker"] is None
    else:
        assert strength["p_weaker"] == pytest.approx(stats.ttest_rel(seeds["E"], rule_e, alternative="less").pvalue)
    assert result["rows"]["MAPPO+AT-M"]["vs_reference"]["E"]["p"] is None  # one CI-HRL seed: no test
    assert result["rows"]["MAPPO+AT-M"]["vs_reference"]["E"]["verdict"] == "no significant difference"
    assert result["rows"]["CI-HRL"]["paper"]["E"] == 4.46
    text = format_highlevel_table(result)
    assert "Over training seeds" in text and "E vs rule (s)" in text and "reference" in text and "R_e/N" in text
    assert "Adversary strength" in text and "  MAPPO+AT-M: " in text
    # R_e/N is the summed R_e over the game's 8 agents, both printed
    r_e = seeds["ci95"]["R_e"]["mean"]
    mappo_line = next(line for line in text.splitlines() if line.startswith("MAPPO+AT-M") and "[" in line)
    assert f"{r_e:.0f} [" in mappo_line and f"{r_e / 8:.0f} [" in mappo_line
    # the row's top-level figures are its first training seed's episodes, and say so
    assert result["rows"]["MAPPO+AT-M"]["episodes_of"]["training_seed"] == 0
    assert result["rows"]["MAPPO+AT-M"]["episodes_of"]["policy"] == result["rows"]["MAPPO+AT-M"]["policy"]
    seed_line, seeds_line = [line for line in text.splitlines() if line.startswith("MAPPO+AT-M ")][0], ""
    seeds_line = text.splitlines()[text.splitlines().index(seed_line) + 1]
    assert seed_line.split()[1:3] == ["seed", "0"] and seeds_line.split()[:2] == ["2", "seeds"]
    assert f"{seeds['mean']['E'] * DT:.1f} ± {seeds['std']['E'] * DT:.1f}" in seeds_line
    assert "'seed k' is that one training seed's policy" in text
    assert "missing policies: MASAC+AT-M (BenchMARL; stands in for HASAC)" in text
    assert "Table IV, message size per agent and decision: MAPPO+AT-M 0 (paper 0), CI-HRL 64 (paper 64)" in text
    # The same seed flies the same episodes: bit-identical figures.
    calls = []
    again = run_table5(
        episodes=2, seed=3, policies_dir=policies, policy="cihrl_mappo", progress=lambda *c: calls.append(c)
    )
    assert again["rows"]["cihrl_mappo"]["per_episode"] == result["rows"]["MAPPO+AT-M"]["per_episode"]
    assert calls == [(0, 2), (2, 2)]  # one policy: one batch of games


def test_the_evaluation_follows_the_policy_a_better_anchor_choice_scores_more():
    """Not a constant: a selector that sends everyone to one target corner covers it (R_t > 0) and
    navigates better than one that sends everyone to the arena's far side of both targets."""
    task = game_task()
    low_level = load_low_level("atm_student", task)

    class Fixed:
        comm = None
        message_dim = 0

        def __init__(self, pick):
            self.pick = pick

        def decide(self, obs, inbox):
            return self.pick(obs), None

    def to_first_target(obs):
        # targets come first in the CEFC observation: the offset to target 0, in metres
        offset = obs[..., :2]
        anchor = np.sign(offset.mean(axis=1, keepdims=True)).repeat(obs.shape[1], axis=1) + 1  # 0, 1, 2 per axis
        return (3 * anchor[..., 0] + anchor[..., 1]).astype(np.int64)

    good = evaluate_highlevel_episodes(Fixed(to_first_target), task, low_level, episodes=3, seed=5)
    centre = evaluate_highlevel_episodes(Fixed(lambda obs: np.full(obs.shape[:2], 4)), task, low_level, 3, seed=5)
    assert good["R_t"].mean() > centre["R_t"].mean() and good["R_n"].mean() > centre["R_n"].mean()


def test_table6_plays_one_policy_against_each_adversary(policies):
    result = run_table6(episodes=2, policies_dir=policies, policy="cihrl_mappo")
    assert list(result["rows"]) == [
        "PPO",
        "PPO (previous generation)",
        "PPO (first generation)",
        "R-Largest",
        "R-Nearest",
        "Nearest-group rule",
    ]
    assert [r["adversary"] for r in result["rows"].values()] == [
        GAME_ADVERSARY,
        "adversary_ppo_nearest_group_member",
        "adversary_ppo",
        "r_largest",
        "r_nearest",
        "nearest_group",
    ]
    assert result["rows"]["PPO"]["adversary_record"]["policy"] == f"{GAME_ADVERSARY}.pt"
    assert result["rows"]["PPO (first generation)"]["paper"] is None
    assert "not in the paper" in result["rows"]["Nearest-group rule"]["differs"]
    assert result["rows"]["Nearest-group rule"]["paper"] is None
    assert result["rows"]["R-Nearest"]["paper"] == {"R_t": 187.87, "R_e": -79.54, "E": 5.8}
    # The adversary changes the episodes (same layouts and targets, another pursuer).
    assert result["rows"]["R-Nearest"]["per_episode"]["R_e"] != result["rows"]["R-Largest"]["per_episode"]["R_e"]
    # Table V against a rule: the same games as Table VI's row of that rule.
    rule = run_table5(episodes=2, policies_dir=policies, policy="cihrl_mappo", adversary="r_nearest")
    assert rule["rows"]["cihrl_mappo"]["per_episode"] == result["rows"]["R-Nearest"]["per_episode"]
    assert rule["protocol"]["adversary"] == {"rule": "r_nearest"} and "adversary r_nearest" in format_highlevel_table(
        rule
    )


def test_table7_plays_the_n8_policy_in_larger_swarms_per_agent(policies, tmp_path):
    """Table VII: the same policy file, trained for N = 8, plays 8 and 12 UAVs (the observations read
    the 7 nearest neighbours); the per-agent columns are the seconds-scale means divided by N."""
    calls = []
    result = run_table7(
        episodes=2, policies_dir=policies, policy="cihrl_consmac_a", sizes=(8, 12), progress=lambda *c: calls.append(c)
    )
    assert calls == [(0, 4), (2, 4), (4, 4)]
    assert list(result["rows"]) == ["N = 8", "N = 12"] and result["protocol"]["n_agents"] == [8, 12]
    for n, row in zip((8, 12), result["rows"].values()):
        assert len(row["per_episode"]["R_H"]) == 2 and row["n_agents"] == n
        for m in ("R_H", "R_t", "R_n", "R_e", "E"):
            assert row["per_agent"][m] == pytest.approx(row[m] * DT / n)
    assert result["rows"]["N = 12"]["paper"] == {"R_H": -42.26, "R_t": 8.91, "R_n": -44.97, "R_e": -6.2, "E": 0.49}
    text = format_highlevel_table(result)
    assert "Table VII protocol (particle, N = 8, 12" in text and "R_t/N" in text
    assert plot_highlevel_table(result, tmp_path / "t7.png").read_bytes()[:4] == b"\x89PNG"
    # more UAVs share the targets: the same episodes' total R_n (all agents' distances) grows with N
    assert result["rows"]["N = 12"]["R_n"] < result["rows"]["N = 8"]["R_n"]


def test_the_game_flies_on_quadrotors_with_wind_and_deviation(policies):
    """The same policy file on MuJoCo quadrotors: the same episodes (layouts, targets), other physics."""
    calm = run_table5(episodes=1, seed=2, policies_dir=policies, policy="cihrl_mappo")["rows"]["cihrl_mappo"]
    quad = run_table5(
        episodes=1,
        seed=2,
        policies_dir=policies,
        policy="cihrl_mappo",
        where=Conditions("mujoco", wind=5.0, deviation=0.3),
    )
    assert quad["protocol"]["backend"] == "mujoco" and not quad["protocol"]["comparable_to_paper"]
    row = quad["rows"]["cihrl_mappo"]
    assert row["per_episode"] != calm["per_episode"] and row["R_n"] < 0
    assert "not like-for-like" in format_highlevel_table(quad)


def test_cli_writes_the_report_folder(policies, tmp_path, monkeypatch, capsys):
    (policies / "atm_student.pt").write_bytes((paths.POLICIES_DIR / "atm_student.pt").read_bytes())
    monkeypatch.setattr(paths, "POLICIES_DIR", policies)
    out = tmp_path / "reports"
    assert (
        main(
            [
                "--backend",
                "particle",
                "--protocol",
                "table5",
                "--episodes",
                "2",
                "--report-dir",
                str(out),
                "--json",
                str(tmp_path / "t5.json"),
            ]
        )
        == 0
    )
    captured = capsys.readouterr()
    assert "MAPPO+AT-M" in captured.out and "games" not in captured.err  # stderr no terminal: no progress bar
    assert {p.name for p in out.iterdir()} == {"table5.md", "table5.json", "table5.png"}
    data = json.loads((out / "table5.json").read_text())
    assert data == json.loads((tmp_path / "t5.json").read_text())
    assert data["protocol"]["command"].startswith("cefc-eval --backend particle --protocol table5")
    assert data["protocol"]["adversary"]["policy"] == f"{GAME_ADVERSARY}.pt"  # the PPO adversary by default
    assert (out / "table5.png").read_bytes()[:4] == b"\x89PNG"


def test_cli_records_one_game_of_a_policy(policies, tmp_path, monkeypatch, capsys):
    """--rrd and --png with table5 --policy: one recorded game (the .rrd is read back in
    tests/test_highlevel_log.py) and the similarity matrices; a policy without messages has none."""
    (policies / "atm_student.pt").write_bytes((paths.POLICIES_DIR / "atm_student.pt").read_bytes())
    monkeypatch.setattr(paths, "POLICIES_DIR", policies)
    rrd, png = tmp_path / "game.rrd", tmp_path / "png"
    assert (
        main(
            [
                "--backend",
                "particle",
                "--protocol",
                "table5",
                "--policy",
                "cihrl_consmac_a",
                "--episodes",
                "1",
                "--rrd",
                str(rrd),
                "--png",
                str(png),
            ]
        )
        == 0
    )
    assert rrd.stat().st_size > 0 and [p.name for p in png.iterdir()] == ["similarity_cihrl_consmac_a_s0.png"]
    with pytest.raises(SystemExit) as exc:
        main(["--backend", "particle", "--protocol", "table5", "--policy", "cihrl_mappo", "--png", str(tmp_path / "x")])
    assert exc.value.code == 2 and "sends no messages" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--protocol", "table5", "--backend", "particle", "--wind", "3"], "--wind: the particle backend has no wind"),
        (["--protocol", "table5", "--backend", "particle", "--estimator", "raw"], "--estimator: --protocol table5"),
        (["--protocol", "table6", "--backend", "particle", "--steps", "100"], "--steps: --protocol table6"),
        (["--protocol", "table6", "--backend", "particle", "--workers", "2"], "--workers 2: only table5"),
        (
            ["--protocol", "table5", "--backend", "particle", "--policy", "cihrl_mappo", "--workers", "2"],
            "table5 with --policy flies one batch",
        ),
        (["--protocol", "table5", "--backend", "particle", "--workers", "0"], "--workers 0"),
        (["--protocol", "table5", "--backend", "particle", "--policy", "no_such"], "--policy no_such: no high-level"),
        (["--protocol", "table6", "--backend", "particle", "--episodes", "0"], "--episodes 0"),
        (["--protocol", "table5", "--backend", "particle", "--rrd", "x.rrd"], "--rrd: recording works with"),
        (
            ["--protocol", "table6", "--backend", "particle", "--adversary", "r_nearest"],
            "--adversary r_nearest: chooses",
        ),
        (["--formation", "6", "--adversary", "r_nearest"], "--adversary r_nearest: chooses"),
        (["--protocol", "table7", "--backend", "particle", "--formation", "6"], "--formation: --protocol table7"),
        (["--protocol", "table5", "--backend", "particle", "--adversary", "no_such"], "adversary no_such: "),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(argv, needle, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and needle in err, err
    assert not any(tmp_path.iterdir())


def test_agent_decider_is_decide_bit_for_bit_for_one_agent(policies):
    """The deployed, traced path of one agent: the same anchor and message as decide(), for any
    number of received messages (none, some), for every variant, and a new trace per slot count."""
    from cefc_mj.hierarchy import HierarchicalCEFCEnv
    from cefc_mj.nn.highlevel_policy import load_highlevel_policy
    from cefc_mj.task.messages import Inbox, MessageChannel

    task = game_task()
    env = HierarchicalCEFCEnv(task, load_low_level("atm_student", task), n_envs=1, seed=4)
    for name in ("cihrl_consmac_a", "cihrl_mappo"):
        policy, _ = load_highlevel_policy(policies / f"{name}.pt")
        decider = policy.agent_decider()
        channel = MessageChannel(1, 8, 64, task.observation_distance)
        obs = env.reset(seed=4)
        for _ in range(4):
            inbox = channel.receive(env.world.agent_pos)
            for agent in range(8):
                one = Inbox(
                    *(
                        a[:, agent : agent + 1]
                        for a in (inbox.messages, inbox.mask, inbox.distance, inbox.sender, inbox.received, inbox.own)
                    )
                )
                one = one if policy.comm is not None else None
                index, message = decider(obs[:, agent : agent + 1], one)
                ref_index, ref_message = policy.decide(obs[:, agent : agent + 1], one)
                assert (index == ref_index).all()
                assert (message is None and ref_message is None) or (message == ref_message).all()
            index, message = policy.decide(obs, inbox if policy.comm is not None else None)
            if message is not None:
                channel.send(message)
            obs, _, _, _ = env.step(index)
        if policy.comm is not None:  # 3 slots instead of 7: traced anew, still equal
            short = Inbox(
                *(a[:, :1, :3] for a in (inbox.messages, inbox.mask, inbox.distance, inbox.sender)),
                np.minimum(inbox.received[:, :1], 3),
                inbox.own[:, :1],
            )
            assert (decider(obs[:, :1], short)[1] == policy.decide(obs[:, :1], short)[1]).all()
    with pytest.raises(ConfigError, match=r"\[1, 1, D\]"):
        decider(obs, None)


def test_a_high_level_flies_over_the_per_group_low_level_its_file_records():
    """Table V and the adversary's population read a file's low level from its meta: the CL-M rows
    over the CL-M policy of each group size, every other file over the caller's (the student)."""
    for stem, expected in (("cihrl_consmac_a_clm", CLM_PER_GROUP), ("cihrl_consmac_a", "student")):
        meta = load_highlevel_policy(paths.POLICIES_DIR / f"{stem}.pt")[1]
        assert recorded_low_level(meta, "student") == expected
    assert recorded_low_level({"low_level": {"name": "some_file"}}, None) is None
    assert recorded_low_level({}, "student") == "student"


def test_a_table5_report_is_reanalysed_from_its_json_without_flying(tmp_path, capsys):
    """`python -m cefc_mj.eval.highlevel_reanalyse`: the pre-registered report's statistics recomputed
    from the per-seed figures it holds and written again beside it (JSON, Markdown, figure), every
    flown number unchanged, the flight's command and provenance kept, the test ledger untouched; bad
    input is one line and exit code 2 before anything is written."""
    from cefc_mj.eval import ledger
    from cefc_mj.eval.highlevel_reanalyse import main as reanalyse

    shipped = paths.EVAL_DIR / "reports" / "prereg" / "table5.json"
    report = tmp_path / "table5.json"
    report.write_text(shipped.read_text())
    flights = len(ledger.read_ledger(paths.EVAL_DIR / ledger.LEDGER_NAME).flights)
    assert reanalyse([str(report)]) == 0
    assert {p.name for p in tmp_path.iterdir()} == {"table5.json", "table5.md", "table5.png"}
    before, after = json.loads(shipped.read_text()), json.loads(report.read_text())
    for key in ("protocol", "provenance"):
        assert after[key] == before[key]
    for method, row in before["rows"].items():
        for key in ("per_episode", "training_seeds", "against_rule", "E", "R_H"):
            assert after["rows"][method][key] == row[key], (method, key)
    assert after["reanalysis"]["command"] == f"python -m cefc_mj.eval.highlevel_reanalyse {report}"
    assert len(ledger.read_ledger(paths.EVAL_DIR / ledger.LEDGER_NAME).flights) == flights
    assert "Re-analysed from its JSON, no game flown again" in (tmp_path / "table5.md").read_text()
    assert (tmp_path / "table5.png").read_bytes()[:4] == b"\x89PNG"
    capsys.readouterr()
    for argv, needle in (
        ([str(tmp_path / "nope.json")], "No such file"),
        ([str(paths.EVAL_DIR / "reports" / "table6.json")], "not a Table V report"),
        ([str(report), "--report-dir", str(tmp_path / "absent")], "not a folder"),
    ):
        assert reanalyse(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and needle in err, err


def test_cli_draws_the_games_flown_on_a_terminal(policies, monkeypatch, capsys):
    """On a terminal, cefc-eval's table runs draw a bar of the games flown (count, rate, time left) on
    stderr; the table itself stays on stdout."""
    import io
    import sys

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    (policies / "atm_student.pt").write_bytes((paths.POLICIES_DIR / "atm_student.pt").read_bytes())
    monkeypatch.setattr(paths, "POLICIES_DIR", policies)
    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main(["--backend", "particle", "--protocol", "table7", "--episodes", "1"]) == 0
    bar = terminal.getvalue()
    assert "games" in bar and "5/5" in bar and "<00:00" in bar, bar
    assert "5/5" not in capsys.readouterr().out
