"""EXPLORATORY: does the order of CI-HRL and MAPPO+AT-M on E and R_H flip against weaker adversaries?

The 40 runs of the pre-registered Table V (policies/prereg/: CI-HRL `cihrl_consmac_a_seed<k>.pt` and
MAPPO+AT-M `cihrl_mappo_seed<k>.pt`, training seeds 100..119, each trained against the game's PPO
adversary) are flown on the game's validation games against five adversaries: the game's PPO
adversary (the reference, what they were trained and tested against), the first-generation PPO
adversary `adversary_ppo`, the DDPG adversary `adversary_ddpg`, the rule R-Largest and the
nearest-group rule. Every flight is `cefc-eval --protocol table5`'s flight of one policy file
(`cefc_mj.eval.highlevel._fly_file`: the same game, low level, anchors and figures), on the particle
backend with the paper's conditions.

    python examples/adversary_order.py --list     # every (policy file, adversary) flight, done or todo
    python examples/adversary_order.py            # fly what is not done yet (2 workers), then the report
    python examples/adversary_order.py --smoke    # 2 seeds x 2 methods x 2 adversaries x 4 games, in a temp folder

Resumable: each finished flight is added to OUT/flights.json at once (written atomically), and a
rerun flies only the flights not in it. The report (OUT/report.json, report.md, adversary_order.png)
is rebuilt from flights.json after every run: per adversary, each method's mean over training seeds
with its 95 % CI, and the difference MAPPO+AT-M minus CI-HRL with its Welch CI and p.

Only validation games (`cefc_mj.seeds.VALIDATION`; default the game's validation batch seed 200),
never a test batch, so nothing is recorded in the test ledger. Nothing here was planned before it
was flown: the results are exploratory, not a test of the pre-registered hypothesis.
Bad input ends in one line on stderr and exit code 2, before anything is flown.
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROG = "adversary_order.py"
OUT = "eval/reports/exploratory/adversary_order"
POLICIES = "policies/prereg"
LABEL = (
    "EXPLORATORY (not pre-registered; validation games only): the pre-registered Table V runs flown "
    "against weaker adversaries"
)
METHODS = (("CI-HRL", "cihrl_consmac_a"), ("MAPPO+AT-M", "cihrl_mappo"))
"""(row, stem of its policy files in policies/prereg: <stem>_seed<k>.pt)."""
REFERENCE, OTHER = METHODS[0][0], METHODS[1][0]
TRAINING_SEEDS = tuple(range(100, 120))
"""The training seeds of both methods in the pre-registered Table V."""
ADVERSARIES = (
    ("PPO (game's; reference)", "adversary_ppo_nearest_group_intercept"),
    ("PPO (first generation)", "adversary_ppo"),
    ("DDPG", "adversary_ddpg"),
    ("R-Largest", "r_largest"),
    ("Nearest-group rule", "nearest_group"),
)
"""(label, adversary: a rule or a trained adversary's name in policies/). The first is the game's."""
METRICS = ("E", "R_H", "R_t", "R_n", "R_e", "E_agents")
"""The episode means kept per flight."""
REPORTED = ("E", "R_H")
"""The figures the report compares."""
KEPT_EPISODES = ("E", "R_H")
"""The per-episode values kept per flight."""
SMOKE = {"seeds": (100, 101), "adversaries": ("adversary_ddpg", "r_largest"), "episodes": 4}
"""The --smoke subset: real flights of real files, small enough for a minute."""
PAPER_E = {REFERENCE: 4.46, OTHER: 8.78}
"""The paper's Table V, E in s (its CI-HRL and MAPPO+AT-M rows)."""


# ---------------------------------------------------------------------------- the flights
def flight_plan(seeds=TRAINING_SEEDS, adversaries=None) -> list[tuple[str, str, int, str, str]]:
    """Every flight as (policy file name, method, training seed, adversary label, adversary), the
    training seeds outermost (a cut flight leaves whole seeds)."""
    wanted = adversaries or [a for _, a in ADVERSARIES]
    return [
        (f"{stem}_seed{seed}.pt", method, seed, label, adversary)
        for seed in seeds
        for method, stem in METHODS
        for label, adversary in ADVERSARIES
        if adversary in wanted
    ]


def protocol(episodes: int, seed: int) -> dict:
    from cefc_mj.eval.highlevel import PAPER_CONDITIONS
    from cefc_mj.game_protocol import GAME_AGENTS, GAME_DENSITY, GAME_STEPS
    from cefc_mj.seeds import block_of

    return {
        **PAPER_CONDITIONS.to_dict(),
        "n_agents": GAME_AGENTS,
        "density": GAME_DENSITY,
        "steps": GAME_STEPS,
        "episodes": episodes,
        "seed": seed,
        "seed_block": block_of(seed),
        "policies_dir": POLICIES,
        "anchors": "mode of the selector",
        "flight": "cefc_mj.eval.highlevel._fly_file (cefc-eval --protocol table5's flight of one policy file)",
    }


def check_seed(seed: int) -> None:
    """ConfigError unless `seed` is a validation game seed that no declared test batch holds."""
    from cefc_mj.errors import ConfigError
    from cefc_mj.seeds import GAME_FAMILY, TEST_BATCHES, VALIDATION, block_of

    if seed not in VALIDATION:
        raise ConfigError(
            f"--seed {seed}: in the {block_of(seed)} block; this exploratory flight takes validation "
            f"games only ({VALIDATION.start}..{VALIDATION.stop - 1})"
        )
    held = [b.name for b in TEST_BATCHES if b.family == GAME_FAMILY and seed in b.seeds]
    if held:  # cannot happen while the blocks are disjoint; kept as the rule this script keeps
        raise ConfigError(f"--seed {seed}: a declared test batch ({held[0]})")


def load_flights(path: Path, proto: dict) -> dict:
    """The flights document at `path` (a new one when absent); ConfigError when it was flown under
    another protocol (resuming it would mix games)."""
    from cefc_mj.errors import ConfigError

    if not path.is_file():
        return {
            "schema": "adversary-order/flights",
            "schema_version": 1,
            "label": LABEL,
            "protocol": proto,
            "flights": {},
        }
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path}: not a readable flights file ({e})") from None
    if doc.get("protocol") != proto:
        raise ConfigError(
            f"{path}: flown with another protocol ({_protocol_text(doc.get('protocol'))}, asked "
            f"{_protocol_text(proto)}); choose another --out"
        )
    return doc


def _protocol_text(proto) -> str:
    if not isinstance(proto, dict):
        return "none"
    return f"{proto.get('episodes')} games of batch seed {proto.get('seed')}"


def flight_key(file: str, adversary: str) -> str:
    return f"{file} vs {adversary}"


def adversary_spec(adversary: str) -> str:
    """What `resolve_adversary` is given: a rule's name, or the shipped file of a trained adversary
    (the policies folder of the flights is policies/prereg, which holds no adversary)."""
    from cefc_mj import paths
    from cefc_mj.task.config import ADVERSARY_RULES

    return adversary if adversary in ADVERSARY_RULES else str(paths.POLICIES_DIR / f"{adversary}.pt")


def check_inputs(plan, policies_dir: Path) -> None:
    """ConfigError naming the first missing policy or adversary file of the plan."""
    from cefc_mj.errors import ConfigError
    from cefc_mj.task.config import ADVERSARY_RULES

    for file, *_ in plan:
        if not (policies_dir / file).is_file():
            raise ConfigError(f"{policies_dir / file}: missing (a pre-registered Table V run)")
    for adversary in {a for *_, a in plan} - set(ADVERSARY_RULES):
        if not Path(adversary_spec(adversary)).is_file():
            raise ConfigError(f"{adversary_spec(adversary)}: missing (a shipped adversary)")


def fly(plan, doc: dict, flights_path: Path, policies_dir: Path, workers: int) -> None:
    """Fly every flight of `plan` not in doc["flights"], adding each to it and rewriting
    `flights_path` atomically as it lands; one progress line per flight."""
    from cefc_mj.eval.highlevel import PAPER_CONDITIONS, _FileJob, _fly_file
    from cefc_mj.executors import ExecutorConfig, map_unordered
    from cefc_mj.fileio import write_atomic
    from cefc_mj.game_protocol import DT, LOW_LEVEL
    from cefc_mj.hierarchy import recorded_low_level
    from cefc_mj.nn.highlevel_policy import load_highlevel_policy

    proto = doc["protocol"]
    todo = [p for p in plan if flight_key(p[0], p[4]) not in doc["flights"]]
    print(f"{PROG}: {len(plan) - len(todo)} of {len(plan)} flights done; flying {len(todo)}", flush=True)
    if not todo:
        return
    jobs = {}
    for file, method, seed, label, adversary in todo:
        path = policies_dir / file
        low = recorded_low_level(load_highlevel_policy(path)[1], LOW_LEVEL)
        job = _FileJob(
            path, adversary_spec(adversary), low, proto["episodes"], proto["seed"], PAPER_CONDITIONS, policies_dir
        )
        jobs[id(job)] = (job, (file, method, seed, label, adversary))
    start = time.monotonic()
    for k, (job, row) in enumerate(
        map_unordered(_fly_file, [job for job, _ in jobs.values()], ExecutorConfig(workers=workers)), 1
    ):
        file, method, seed, label, adversary = jobs[id(job)][1]
        doc["flights"][flight_key(file, adversary)] = {
            "policy": file,
            "sha256": row["sha256"],
            "method": method,
            "training_seed": seed,
            "adversary": adversary,
            "adversary_label": label,
            **{m: row[m] for m in METRICS},
            **{f"{m}_std": row[f"{m}_std"] for m in METRICS},
            "per_episode": {m: row["per_episode"][m] for m in KEPT_EPISODES},
            **{note: row[note] for note in ("adversary_differs", "low_level_differs") if note in row},
        }
        write_atomic(flights_path, json.dumps(doc, indent=1) + "\n")
        elapsed = time.monotonic() - start
        left = elapsed / k * (len(todo) - k)
        print(
            f"[{k:3d}/{len(todo)}] {file} vs {adversary}: E {row['E'] * DT:5.2f} s, R_H x dt {row['R_H'] * DT:7.1f}"
            f"  ({elapsed / 60:4.1f} min, about {left / 60:4.1f} min left)",
            flush=True,
        )


# ---------------------------------------------------------------------------- the report
def build_report(doc: dict) -> dict:
    """Per adversary (in ADVERSARIES order, those flown): each method's per-seed episode means of E
    and R_H (x dt, the paper's scale), their mean with the 95 % CI over training seeds, and the
    difference OTHER - REFERENCE with its Welch CI and p (`cefc_mj.eval.stats`). Only training
    seeds flown against that adversary count; a method with fewer than 2 has no CI."""
    from cefc_mj.eval.stats import holm_adjusted, seed_interval, welch_difference, welch_p
    from cefc_mj.game_protocol import DT

    flights = doc["flights"].values()
    report = {
        "schema": "adversary-order/report",
        "schema_version": 1,
        "label": LABEL,
        "protocol": doc["protocol"],
        "units": "x dt (0.1 s): E in seconds within 2 m of the adversary, R_H on the paper's scale",
        "difference": f"{OTHER} - {REFERENCE}",
        "paper_E_s": PAPER_E,
        "adversaries": [],
    }
    for label, adversary in ADVERSARIES:
        here = [f for f in flights if f["adversary"] == adversary]
        if not here:
            continue
        entry = {"label": label, "adversary": adversary, "methods": {}, "difference": {}}
        for method, _ in METHODS:
            rows = sorted((f for f in here if f["method"] == method), key=lambda f: f["training_seed"])
            values = {m: [f[m] * DT for f in rows] for m in REPORTED}
            entry["methods"][method] = {
                "seeds": [f["training_seed"] for f in rows],
                **{m: {"per_seed": values[m], **seed_interval(values[m])} for m in REPORTED},
            }
        for m in REPORTED:
            a, b = entry["methods"][OTHER][m]["per_seed"], entry["methods"][REFERENCE][m]["per_seed"]
            d = welch_difference(a, b)
            entry["difference"][m] = {
                "n": [len(a), len(b)],
                "difference": None if d is None else d.difference,
                "ci_low": None if d is None else d.ci_low,
                "ci_high": None if d is None else d.ci_high,
                "df": None if d is None else d.df,
                "p": welch_p(a, b),
            }
        entry["E_vs_game_adversary"] = _strength(flights, adversary)
        entry["lower_E"] = _lower(entry, "E", higher_is_better=False)
        entry["higher_R_H"] = _lower(entry, "R_H", higher_is_better=True)
        report["adversaries"].append(entry)
    # Exploratory: many looks (adversaries x metrics), so each p also Holm-adjusted over all of them.
    family = [e["difference"][m] for e in report["adversaries"] for m in REPORTED]
    for d, adjusted in zip(family, holm_adjusted([d["p"] for d in family])):
        d["p_holm"] = adjusted
    report["p_holm_family"] = f"the {len(family)} differences of this report (adversaries x {', '.join(REPORTED)})"
    return report


def _strength(flights, adversary: str) -> dict:
    """Per method, how dangerous `adversary` is beside the game's: the ratio of the mean E against
    it to the mean E against the game's adversary, over the training seeds flown against both, and
    the one-sided paired t-test over those seeds that it is weaker (`eval.stats.weaker_p`)."""
    from cefc_mj.eval.stats import weaker_p

    game = ADVERSARIES[0][1]
    out = {}
    for method, _ in METHODS:
        against = {f["training_seed"]: f["E"] for f in flights if f["method"] == method and f["adversary"] == adversary}
        base = {f["training_seed"]: f["E"] for f in flights if f["method"] == method and f["adversary"] == game}
        seeds = sorted(set(against) & set(base))
        a, b = [against[k] for k in seeds], [base[k] for k in seeds]
        ratio = sum(a) / sum(b) if seeds and sum(b) > 0 else None
        out[method] = {"seeds": len(seeds), "ratio": ratio, "p_weaker": None if adversary == game else weaker_p(a, b)}
    return out


def _lower(entry: dict, metric: str, higher_is_better: bool) -> str | None:
    """The method ahead on `metric` by its point estimate (None when they tie or a side is empty)."""
    means = {m: entry["methods"][m][metric]["mean"] for m, _ in METHODS}
    if any(v is None or (isinstance(v, float) and math.isnan(v)) for v in means.values()):
        return None
    a, b = means[REFERENCE], means[OTHER]
    if a == b:
        return None
    return REFERENCE if (a > b) == higher_is_better else OTHER


def _num(x, digits: int) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _cell(block: dict, digits: int) -> str:
    if block["ci_low"] is None:
        return f"{_num(block['mean'], digits)} (n {block['n']})"
    return f"{block['mean']:.{digits}f} [{block['ci_low']:.{digits}f}, {block['ci_high']:.{digits}f}]"


def _diff_cell(d: dict, digits: int) -> str:
    if d["difference"] is None:
        return "-"
    return (
        f"{d['difference']:+.{digits}f} [{d['ci_low']:+.{digits}f}, {d['ci_high']:+.{digits}f}], "
        f"p {_p(d['p'])} (Holm {_p(d.get('p_holm'))})"
    )


def _p(p) -> str:
    return "-" if p is None else (f"{p:.2g}" if p >= 0.001 else "<0.001")


def format_report(report: dict) -> str:
    """The report as Markdown: the protocol, then one table for E and one for R_H."""
    proto = report["protocol"]
    lines = [
        "# CI-HRL and MAPPO+AT-M against weaker adversaries",
        "",
        f"**{report['label']}.**",
        "",
        f"Games: {proto['episodes']} games of batch seed {proto['seed']} ({proto['seed_block']} block), "
        f"{proto['backend']} backend, N = {proto['n_agents']}, {proto['steps']} steps; policies: "
        f"{proto['policies_dir']}. Each cell: the mean over training seeds of the per-seed episode means, "
        "[95 % CI over seeds]; the difference is "
        f"{report['difference']} with its Welch 95 % CI and two-sided Welch p, unadjusted and Holm-adjusted "
        f"over {report['p_holm_family']}. "
        f"Units: {report['units']}. The paper's E: {REFERENCE} {PAPER_E[REFERENCE]} s, {OTHER} {PAPER_E[OTHER]} s.",
        "",
    ]
    for metric, digits, ahead, title in (
        ("E", 2, "lower_E", "E (s within 2 m of the adversary; lower is better)"),
        ("R_H", 1, "higher_R_H", "R_H (x dt; higher is better)"),
    ):
        lines += [
            f"## {title}",
            "",
            f"| adversary | seeds | {REFERENCE} | {OTHER} | {report['difference']} | ahead |",
            "|---|---|---|---|---|---|",
        ]
        for entry in report["adversaries"]:
            seeds = "/".join(str(len(entry["methods"][m]["seeds"])) for m, _ in METHODS)
            cells = [_cell(entry["methods"][m][metric], digits) for m, _ in METHODS]
            diff = _diff_cell(entry["difference"][metric], digits)
            lines.append(f"| {entry['label']} | {seeds} | {cells[0]} | {cells[1]} | {diff} | {entry[ahead] or '-'} |")
        lines.append("")
    lines += [
        "## How dangerous each adversary is beside the game's",
        "",
        "E against the adversary / E against the game's PPO adversary (the same training seeds and games), "
        "with the one-sided paired t-test over seeds that it is weaker.",
        "",
        f"| adversary | {REFERENCE} | {OTHER} |",
        "|---|---|---|",
    ]
    for entry in report["adversaries"]:
        cells = []
        for method, _ in METHODS:
            s = entry["E_vs_game_adversary"][method]
            cells.append(f"{_num(s['ratio'], 2)}, p {_p(s['p_weaker'])}")
        lines.append(f"| {entry['label']} | {cells[0]} | {cells[1]} |")
    lines.append("")
    return "\n".join(lines)


def plot_report(report: dict, path: Path) -> None:
    """Two panels (E, R_H): per adversary, each method's seed means (dots) and their mean with the
    95 % CI over seeds, the two methods side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    entries = report["adversaries"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    colours = {REFERENCE: "tab:blue", OTHER: "tab:orange"}
    for ax, (metric, ylabel) in zip(axes, (("E", "E (s within 2 m)"), ("R_H", "R_H (x dt)"))):
        for j, (method, _) in enumerate(METHODS):
            offset = (j - 0.5) * 0.3
            for i, entry in enumerate(entries):
                block = entry["methods"][method][metric]
                x = i + offset
                ax.scatter(
                    np.full(len(block["per_seed"]), x), block["per_seed"], s=9, alpha=0.35, color=colours[method]
                )
                if block["ci_low"] is not None:
                    err = [[block["mean"] - block["ci_low"]], [block["ci_high"] - block["mean"]]]
                    ax.errorbar(x, block["mean"], yerr=err, fmt="o", capsize=4, color=colours[method])
                else:
                    ax.plot(x, block["mean"], "o", color=colours[method])
            ax.plot([], [], "o", color=colours[method], label=f"{method} (mean, 95 % CI over seeds)")
        if metric == "E":  # the paper's Table V, against its own PPO adversary
            for method, _ in METHODS:
                ax.axhline(PAPER_E[method], color=colours[method], ls="--", lw=1, label=f"{method}: the paper's E")
        ax.set_xticks(range(len(entries)), [e["label"] for e in entries], rotation=20, ha="right", fontsize=8)
        ax.set_ylabel(ylabel)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    proto = report["protocol"]
    fig.suptitle(
        f"EXPLORATORY: pre-registered runs against other adversaries ({proto['episodes']} validation games, "
        f"batch seed {proto['seed']})",
        fontsize=10,
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(doc: dict, out: Path) -> dict:
    from cefc_mj.fileio import write_atomic

    report = build_report(doc)
    write_atomic(out / "report.json", json.dumps(report, indent=1) + "\n")
    write_atomic(out / "report.md", format_report(report) + "\n")
    plot_report(report, out / "adversary_order.png")
    return report


# ---------------------------------------------------------------------------- the command
def main(argv: list[str] | None = None) -> int:
    from cefc_mj.errors import CefcError, OneLineParser
    from cefc_mj.seeds import GAME_VALIDATION_SEED

    p = OneLineParser(prog=PROG, description=__doc__.splitlines()[0])
    p.add_argument("--list", action="store_true", help="print every flight and whether it is done, then exit")
    p.add_argument("--smoke", action="store_true", help=f"fly {SMOKE} into a temporary folder (or --out) and report")
    p.add_argument("--episodes", type=int, default=50, help="games per flight (default 50, the game's batch)")
    p.add_argument(
        "--seed", type=int, default=GAME_VALIDATION_SEED, help=f"validation batch seed (default {GAME_VALIDATION_SEED})"
    )
    p.add_argument("--workers", type=int, default=2, help="processes flying (default 2)")
    p.add_argument("--out", type=Path, help=f"folder of flights.json and the report (default {OUT})")
    args = p.parse_args(argv)
    try:
        from cefc_mj.fileio import make_writable_folder

        episodes = SMOKE["episodes"] if args.smoke else args.episodes
        if episodes < 1:
            raise p.error(f"--episodes {episodes}: must be at least 1")
        if args.workers < 1:
            raise p.error(f"--workers {args.workers}: must be at least 1")
        check_seed(args.seed)
        if args.smoke:
            plan = flight_plan(SMOKE["seeds"], SMOKE["adversaries"])
            out = args.out or Path(tempfile.mkdtemp(prefix="adversary_order_smoke_"))
        else:
            plan = flight_plan()
            out = args.out or ROOT / OUT
        policies_dir = ROOT / POLICIES
        check_inputs(plan, policies_dir)
        proto = protocol(episodes, args.seed)
        flights_path = out / "flights.json"
        doc = load_flights(flights_path, proto)
        if args.list:
            for file, _, _, _, adversary in plan:
                state = "done" if flight_key(file, adversary) in doc["flights"] else "todo"
                print(f"{state}  {file} vs {adversary}")
            done = sum(flight_key(f, a) in doc["flights"] for f, *_, a in plan)
            print(f"{done} of {len(plan)} flights done ({_protocol_text(proto)}; {flights_path})")
            return 0
        try:
            make_writable_folder(out)
        except CefcError as e:
            raise CefcError(f"--out {out}: {e}") from None
        fly(plan, doc, flights_path, policies_dir, args.workers)
        report = write_report(doc, out)
    except CefcError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    print(format_report(report))
    print(f"{PROG}: wrote {out / 'flights.json'}, report.json, report.md and adversary_order.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
