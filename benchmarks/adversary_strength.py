"""How hard does each adversary press every Table V row, compared with the nearest-group rule?

Each adversary of `--adversaries` and the nearest-group rule are flown against every team of `--teams`
(default every shipped Table V row over its training seeds, each over the low level its file records,
and the rule teams), on the same `--episodes` validation games (batch seed `--seed`), under the game's
obstacle rule (a rule adversary steers round the obstacles; a trained one is penalised inside them).
Per Table V row: the team E summed over the row's training seeds against the adversary, over the same
sum against the nearest-group rule. An adversary is as strong as the rule for a row when that ratio is
>= 1. The game adversary's teacher was chosen among rules by the largest minimum over the rows.

An adversary is a rule's name (`nearest_group_member`, ...: `cefc_mj.task.config.ADVERSARY_RULES`),
`intercept[:FIELD=VALUE,...]`, a `cefc_mj.task.adversary.InterceptRule` (`intercept` alone is
`nearest_group_intercept`; fields: horizon (s ahead of the chased group, at most), strike_distance (m,
or none), strike_lead (s ahead of the struck UAV), strike_at (member, grouped or any)), or a trained
adversary's policy name (shipped folder) or file, flown by its mean action.

    python benchmarks/adversary_strength.py --adversaries nearest_group_member intercept intercept:strike_at=any
    python benchmarks/adversary_strength.py --adversaries adversary_ppo_nearest_group_intercept \\
        --teams benchmarl_masac,benchmarl_masac_seed1,rule-split --episodes 10

The figures depend on the policy files flown: the table in docs/research/high_level.md ("The next adversary")
was flown against the files the shipped `adversary_ppo_nearest_group_intercept` was trained against
(its model card lists them with their checksums).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import re
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from cefc_mj import paths
from cefc_mj.errors import CefcError, CheckpointError, ConfigError
from cefc_mj.eval.highlevel import TABLE5_ROWS
from cefc_mj.fileio import make_writable_folder, write_atomic
from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.provenance import display_path, git_commit, library_versions
from cefc_mj.seeds import GAME_VALIDATION_SEED, VALIDATION
from cefc_mj.task.adversary import InterceptRule
from cefc_mj.task.config import ADVERSARY_RULES
from cefc_mj.train.adversary import EVERY_ROW_POPULATION, AdversaryConfig, evaluate_adversary, load_population
from cefc_mj.train.config import Budget

PROG = "adversary_strength"
EXIT_USAGE = 2
BASELINE = "nearest_group"
SMOKE_TEAMS, SMOKE_EPISODES = ("cihrl_mappo", "rule-split"), 2
NAMED_RULES = tuple(rule for rule in ADVERSARY_RULES if rule != "none")
DEFAULT_OUT = paths.PROJECT_ROOT / "runs" / "adversary_strength" / "adversary_strength.json"


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (the usage is in --help)."""

    def error(self, message: str):
        print(f"{PROG}: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def parse_adversary(spec: str) -> tuple[object, object]:
    """(what `evaluate_adversary` flies, what the report records) of an adversary: a rule's name (both
    the name), `intercept[:FIELD=VALUE,...]` (an InterceptRule and its repr), or a trained adversary's
    policy name or file (its `act` and `resolve_adversary`'s record: file name and checksum); CefcError
    naming the problem."""
    if spec in NAMED_RULES:
        return spec, spec
    name, _, settings = spec.partition(":")
    if name != "intercept":
        try:
            _, act, record = resolve_adversary(spec)
        except CheckpointError as e:
            raise CheckpointError(f"--adversaries: {e}") from None
        return act, record
    fields = {f.name: f for f in dataclasses.fields(InterceptRule)}
    values: dict[str, object] = {}
    for part in filter(None, settings.split(",")):
        key, eq, text = part.partition("=")
        if key not in fields or not eq:
            raise ConfigError(
                f"--adversaries {spec!r}: {part!r} is not FIELD=VALUE with FIELD one of {', '.join(fields)}"
            )
        if key == "strike_at":
            values[key] = text
        elif key == "strike_distance" and text == "none":
            values[key] = None
        else:
            try:
                values[key] = float(text)
            except ValueError:
                raise ConfigError(f"--adversaries {spec!r}: {key}={text!r} is not a number") from None
    try:
        rule = InterceptRule(**values)
    except ValueError as e:
        raise ConfigError(f"--adversaries {spec!r}: {e}") from None
    return rule, str(rule)


def _team_figures(job: tuple[str, tuple[str, ...], int, int, Path | None]) -> tuple[str, dict[str, dict]]:
    """One team against the baseline and every adversary (a worker process): spec -> evaluate_adversary's figures."""
    name, specs, episodes, seed, policies_dir = job
    cfg = AdversaryConfig(budget=Budget(iterations=1), teams=(name,))
    population, _, low_level, interval, own = load_population(cfg, policies_dir)
    team = name if population[name] is None else population[name]
    return name, {
        spec: evaluate_adversary(
            parse_adversary(spec)[0], team, own.get(name, low_level), cfg.task(), episodes, seed, interval
        )
        for spec in (BASELINE, *specs)
    }


def row_of(team: str) -> str | None:
    """The Table V row a policy file's name belongs to (seed 0 is <stem><suffix>, seed k <stem>_seed<k><suffix>)."""
    for method, stem, suffix, _ in TABLE5_ROWS:
        if re.fullmatch(re.escape(stem) + r"(_seed\d+)?" + re.escape(suffix), team):
            return method
    return None


def per_row_ratios(per_team: dict[str, dict[str, dict]], spec: str) -> dict[str, float]:
    """Table V row -> summed E against `spec` over summed E against the baseline (rule teams: one each)."""
    sums: dict[str, list[float]] = {}
    for team, figures in per_team.items():
        row = row_of(team) or f"rule team {team}"
        pair = sums.setdefault(row, [0.0, 0.0])
        pair[0] += figures[spec]["E"]
        pair[1] += figures[BASELINE]["E"]
    return {row: ours / base if base else float("nan") for row, (ours, base) in sums.items()}


def table(per_team: dict[str, dict[str, dict]], specs: tuple[str, ...]) -> list[str]:
    lines = ["| adversary | min over the Table V rows (row) | mean over them | rule teams |", "|---|---|---|---|"]
    for spec in specs:
        ratios = per_row_ratios(per_team, spec)
        rows = {row: r for row, r in ratios.items() if not row.startswith("rule team")}
        rules = [f"{r:.2f}" for row, r in ratios.items() if row.startswith("rule team")]
        if rows:
            worst = min(rows, key=rows.get)
            low, mean = f"{rows[worst]:.2f} ({worst})", f"{sum(rows.values()) / len(rows):.2f}"
        else:
            low = mean = "-"
        lines.append(f"| `{spec}` | {low} | {mean} | {' / '.join(rules) or '-'} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--adversaries",
        nargs="+",
        required=True,
        help="rules, intercept:FIELD=VALUE,... settings or trained adversaries to compare with the nearest-group rule",
    )
    parser.add_argument(
        "--teams",
        default="every-row",
        help="every-row (default), or comma-separated policy names (in --policies-dir) and rule teams",
    )
    parser.add_argument("--episodes", type=int, default=30, help="validation games per team (default 30)")
    parser.add_argument(
        "--seed", type=int, default=GAME_VALIDATION_SEED, help=f"the games' batch seed (default {GAME_VALIDATION_SEED})"
    )
    parser.add_argument("--workers", type=int, default=2, help="processes, one team each at a time (default 2)")
    parser.add_argument(
        "--policies-dir",
        type=Path,
        default=None,
        help="folder of the teams' files and their low levels' (default: shipped)",
    )
    parser.add_argument(
        "--smoke",
        action="store_true",
        help=f"{SMOKE_EPISODES} games against {', '.join(SMOKE_TEAMS)}: the same code path",
    )
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help=f"JSON report (default {display_path(DEFAULT_OUT)})"
    )
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.workers < 1:
        parser.error("--episodes and --workers must be integers >= 1")
    if not VALIDATION.start <= args.seed < VALIDATION.stop:
        parser.error(f"--seed={args.seed}: not a validation game seed [{VALIDATION.start}, {VALIDATION.stop})")
    teams = tuple(t.strip() for t in args.teams.split(","))
    teams = EVERY_ROW_POPULATION if teams == ("every-row",) else teams
    if args.smoke:
        teams, args.episodes = SMOKE_TEAMS, SMOKE_EPISODES
    specs = tuple(dict.fromkeys(args.adversaries))
    try:
        records = {spec: parse_adversary(spec)[1] for spec in specs}  # every input checked before the long part
        if not all(teams):
            raise ConfigError(f"--teams {args.teams!r}: a comma-separated list of names, none empty")
        load_population(AdversaryConfig(budget=Budget(iterations=1), teams=teams), args.policies_dir)
        make_writable_folder(args.out.parent)
        start, per_team = time.perf_counter(), {}
        jobs = [(name, specs, args.episodes, args.seed, args.policies_dir) for name in teams]
        # spawn: a forked child of a parent that has loaded torch and numba can hang
        with ProcessPoolExecutor(args.workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            for done, (name, figures) in enumerate(pool.map(_team_figures, jobs), 1):
                per_team[name] = figures
                e = " ".join(f"{figures[s]['E']:.1f}" for s in (BASELINE, *specs))
                print(f"[{done}/{len(teams)}] {name}: E {e} steps ({time.perf_counter() - start:.0f} s)", flush=True)
        lines = table(per_team, specs)
        report = {
            "question": "E against each adversary over E against the nearest-group rule, per Table V row",
            "protocol": {
                "episodes": args.episodes,
                "seed": args.seed,
                "seed_block": "validation",
                "baseline": BASELINE,
                "obstacles": "a rule steers round them, a trained adversary is penalised inside them (the game's)",
                "trained_adversary": "its mean action",
                "row_ratio": "team E summed over the row's training seeds, over the same sum against the baseline",
            },
            "adversaries": records,
            "per_team": per_team,
            "per_row": {spec: per_row_ratios(per_team, spec) for spec in specs},
            "table": lines,
            "wall_s": round(time.perf_counter() - start, 1),
            "command": shlex.join(["python", "benchmarks/adversary_strength.py", *argv]),
            "provenance": {"commit": git_commit(), "library_versions": library_versions()},
        }
        write_atomic(args.out, json.dumps(report, indent=2) + "\n")
    except CefcError as e:
        print(f"{PROG}: error: {' '.join(str(e).split())}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; no report written", file=sys.stderr)
        return 130
    print("\n".join(lines))
    print(f"wrote {display_path(args.out)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
