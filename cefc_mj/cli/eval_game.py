"""cefc-eval --protocol table5/table6/table7: the high level's game (Tables V, VI and VII) on particles
or quadrotors, beside the paper's rows; optional report folder, JSON, and (table5 with --policy) one
recorded game with its message-similarity matrices."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from tqdm import tqdm

from cefc_mj.cli.eval_common import (
    PROG,
    deploy_runners,
    report_faults,
    sitl_config,
    wind_direction_text,
    write_outputs,
)
from cefc_mj.errors import ConfigError
from cefc_mj.eval.highlevel import TABLE7_SIZES, run_table5, run_table6, run_table7
from cefc_mj.eval.highlevel_report import format_highlevel_table, plot_highlevel_table, report_markdown
from cefc_mj.eval.highlevel_sitl import format_sitl_game, run_table5_sitl
from cefc_mj.eval.ledger import check_before_flight, record_if_test
from cefc_mj.eval.requests import GameTablesRequest
from cefc_mj.eval.runner import provenance
from cefc_mj.game_protocol import GAME_AGENTS, GAME_STEPS, LOW_LEVEL, game_task
from cefc_mj.hierarchy import DECISION_INTERVAL, load_low_level
from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.nn.highlevel_policy import highlevel_policy_path, load_highlevel_policy
from cefc_mj.provenance import file_sha256


def check(request: GameTablesRequest) -> dict:
    """Before anything flies: the played policy's file (with messages to draw, for --png) and the
    adversary's (a rule, or a trained adversary's file, loaded). Returns the run's provenance."""
    if request.played_policy is not None:
        path = highlevel_policy_path(request.played_policy)  # a missing file fails before any episode
        if request.png is not None and load_highlevel_policy(path)[0].comm is None:
            raise ConfigError(
                f"--png: {request.policy} sends no messages (no communication), so there is no "
                "similarity to draw; drop --png"
            )
    if request.protocol in ("table5", "table7"):  # a missing or broken adversary file fails before any episode
        resolve_adversary(request.played_adversary, request.policies_dir)
    protocol = request.protocol if request.sitl is None else "table5-sitl-m"
    check_before_flight(protocol, request.seed, request.episodes)  # a damaged test ledger: refused here
    return provenance("atm", [])  # the tables record each row's file and sha256 themselves


def run(request: GameTablesRequest, prov: dict, command: str) -> int:
    """Play the table's games, print it, write the outputs and (table5 with --policy) record one game."""
    proto, where = request.protocol, request.conditions
    if request.policy:
        playing = f"policy {request.policy}"
    else:
        playing = "every method" if proto == "table5" else request.played_policy
    uavs = "N = " + ", ".join(map(str, TABLE7_SIZES)) if proto == "table7" else str(GAME_AGENTS)
    wind = {"wind": where.wind, "wind_direction": where.wind_direction}
    world = f"mujoco (iris airframe{wind_direction_text(wind)})" if where.backend == "mujoco" else where.backend
    print(
        f"{PROG} {proto}: {world}, wind {where.wind:g} m/s, deviation {where.deviation:g} m, {uavs} UAVs, "
        f"{request.episodes} episodes x {GAME_STEPS} steps, seed {request.seed}, {playing}"
    )
    prov = {k: v for k, v in prov.items() if k != "policies"}
    common = {"episodes": request.episodes, "seed": request.seed, "provenance": prov, "where": where}
    if request.sitl is not None:
        return _run_sitl_game(request, common, command)
    with _GameBar() as bar:
        if proto == "table5":
            result = run_table5(
                policy=request.policy,
                adversary=request.played_adversary,
                workers=request.workers,
                policies_dir=request.policies_dir,
                progress=bar,
                **common,
            )
        elif proto == "table6":
            result = run_table6(policy=request.played_policy, progress=bar, **common)
        else:
            result = run_table7(
                policy=request.played_policy, adversary=request.played_adversary, progress=bar, **common
            )
    result["protocol"]["command"] = command
    text = format_highlevel_table(result)
    print(text)
    report = None if request.report_dir is None else request.report_dir / f"{proto}.json"
    record_if_test(proto, request.seed, request.episodes, command, prov, (report, request.json))
    data = json.dumps(result, indent=2) + "\n"
    writes: list[tuple[Path, object]] = []
    if request.report_dir is not None:
        out = request.report_dir
        writes += [
            (out / f"{proto}.md", report_markdown(result, text)),
            (out / f"{proto}.json", data),
            (out / f"{proto}.png", lambda path: plot_highlevel_table(result, path)),
        ]
    if request.json is not None:
        writes.append((request.json, data))
    write_outputs(writes)
    if request.rrd is not None or request.png is not None:
        for path in _record_game(request):
            print(f"wrote {path}")
    return 0


class _GameBar:
    """The games flown of a table's run as a tqdm bar on stderr (games, rate, time left), drawn only
    when stderr is a terminal; a table's run calls it with (games flown, games in all)."""

    def __enter__(self) -> _GameBar:
        self.bar = tqdm(total=None, desc="games", unit="game", file=sys.stderr, disable=None)
        return self

    def __call__(self, flown: int, total: int) -> None:
        if self.bar.total != total:
            self.bar.total = total
            self.bar.refresh()
        self.bar.update(flown - self.bar.n)

    def __exit__(self, *exc) -> None:
        self.bar.close()


def _run_sitl_game(request: GameTablesRequest, common: dict, command: str) -> int:
    """--sitl-m: one game per seed with every UAV's hierarchy in its own process, beside the lock-step
    game of each seed; the table, timing and bytes on the wire."""
    runner = deploy_runners(False, False, game=True).game
    recorded = []  # the game of --seed (the first), when it is to be recorded

    def play(spec, sitl):
        game = runner(spec, sitl)
        if not recorded and (request.rrd is not None or request.png is not None):
            recorded.append(game)
        return game

    result = run_table5_sitl(
        play,
        sitl_config(request.sitl),
        policy=request.policy,
        adversary=request.played_adversary,
        **common,
    )
    result["protocol"]["command"] = command
    text = format_sitl_game(result)
    print(text)
    report = None if request.report_dir is None else request.report_dir / "table5_sitl_m.json"
    record_if_test(
        "table5-sitl-m", request.seed, request.episodes, command, common["provenance"], (report, request.json)
    )
    data = json.dumps(result, indent=2, default=float) + "\n"
    writes: list[tuple[Path, object]] = []
    if request.report_dir is not None:
        writes += [
            (
                request.report_dir / "table5_sitl_m.md",
                f"# table5, SITL-M game\n\n```\n{text}\n```\n\nCommand: `{command}`\n",
            ),
            (request.report_dir / "table5_sitl_m.json", data),
        ]
    if request.json is not None:
        writes.append((request.json, data))
    write_outputs(writes)
    if recorded:
        for path in _record_sitl_game(request, recorded[0], result["protocol"]["low_level"]):
            print(f"wrote {path}")
    rows = result["rows"].items()
    return report_faults([f"{label}, {line}" for label, row in rows for line in row.get("faults", [])])


def _record_sitl_game(request: GameTablesRequest, game, low_level: dict) -> list[Path]:
    """--rrd / --png with --sitl-m: the SITL-M game of --seed (the first of the batch), as the
    simulator kept it (every UAV's message and anchor as received, NaN / -1 where none arrived),
    recorded by the one-process game's recorder; the PNGs are the paper's Figs. 11 and 12 at four
    evenly spaced decisions. low_level: the table's record of the low level (the agents load it
    from their own policies/, the simulator's for local agents)."""
    from cefc_mj.viz.highlevel_log import record_highlevel_episode, write_game_figures  # imports rerun

    path = highlevel_policy_path(request.policy)
    episode = game.episode()
    episode.policy, episode.policy_sha256 = path.stem, file_sha256(path)
    episode.low_level = dict(low_level)
    adversary = request.played_adversary
    episode.adversary_rule = adversary if resolve_adversary(adversary)[1] is None else f"{adversary} (trained)"
    name = f"{path.stem}_s{game.spec.seed}_sitl_m"
    written: list[Path] = []
    if request.rrd is not None:
        request.rrd.parent.mkdir(parents=True, exist_ok=True)
        written.append(record_highlevel_episode(episode, request.rrd, recording_id=name))
    if request.png is not None:
        request.png.mkdir(parents=True, exist_ok=True)
        written += write_game_figures(episode, request.png, name)
    return written


def _record_game(request: GameTablesRequest) -> list[Path]:
    """--rrd / --png of table5: one game with --seed, flown by the evaluated policy, recorded (the
    same game as a one-episode evaluation with that seed)."""
    from cefc_mj.viz.highlevel_log import (  # imports rerun
        play_highlevel_episode,
        plot_similarity_matrices,
        record_highlevel_episode,
    )

    seed = request.seed
    path = highlevel_policy_path(request.policy)
    policy, meta = load_highlevel_policy(path)
    adversary = request.played_adversary
    kind, adversary_policy, _ = resolve_adversary(adversary)
    task = game_task(kind, deviation=request.conditions.deviation)
    episode = play_highlevel_episode(
        policy,
        task,
        load_low_level(LOW_LEVEL, task),
        seed=seed,
        world=request.conditions.world(task, 1, seed),
        decision_interval=int(meta.get("decision_interval", DECISION_INTERVAL)),
        adversary_policy=adversary_policy,
    )
    episode.policy, episode.policy_sha256 = path.stem, file_sha256(path)
    episode.adversary_rule = adversary if adversary_policy is None else f"{adversary} (trained)"
    written: list[Path] = []
    if request.rrd is not None:
        request.rrd.parent.mkdir(parents=True, exist_ok=True)
        written.append(record_highlevel_episode(episode, request.rrd, recording_id=f"{path.stem}_s{seed}"))
    if request.png is not None:
        request.png.mkdir(parents=True, exist_ok=True)
        written.append(plot_similarity_matrices(episode, request.png / f"similarity_{path.stem}_s{seed}.png"))
    return written
