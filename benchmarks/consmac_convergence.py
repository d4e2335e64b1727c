"""Does ConsMAC's label loss converge at 200 supervised steps per round? (the paper trains 5000)

For each finished ConsMAC run (`cefc-train highlevel`, its `state.pt`): the run's final ConsMAC, its
Adam state (restored when it fits the module, else a fresh Adam at the run's rate) and its replay
B_C. The replay rows are split into a training part and a held-out part: when the ring buffer's
layout can be reconstructed from the run's counters (every iteration appends n_envs x episodes x
decisions x N rows, env-major within a decision), whole (iteration, env) groups are held out, i.e.
whole episodes with all their agents, chosen by a seeded permutation until `--heldout` of the rows
(default 10 %) are out; otherwise contiguous blocks of the ring (20 blocks in age order, the same
share). Then `--steps` supervised steps continue from that state on the training part: each one is
`HighLevelTrainer.train_consmac` itself (the run's batch, eq. (11) through `consmac_loss`, gradient
clip, the fast attention path, the run's learning rate), called on a stand-in that holds the run's
ConsMAC, its Adam and a replay of the training rows only. A second held-out set (`--fresh K`, default
1): the K iterations of 20 episodes the run would collect next, played by its restored trainer (the
final ConsMAC and selector, the same low level and adversary files, the next iterations' seeds), rows
that no supervised step has ever seen. Every `--every` steps (and at 200 and 1000) the loss is
evaluated with no gradient on the whole held-out part, the fresh rows and an equally large fixed sample
of the training part; the mean train-batch loss of the steps in between is recorded too. The
mean-guessing baseline is `consmac_loss` of always predicting the training part's label mean, on the
held-out part (and on the fresh rows): the same units (summed over the label's numbers, averaged over rows).

Caveat: this continues training from the final state on the final replay; it is not a retraining with
5000 steps per round (the replay's data, and the selector that produced it, would then differ). The
replay's held-out rows were sampled by the last rounds of training, so their step-0 loss is not a loss
on never-seen data (from step 0 on they are never trained on); the fresh rows are unseen throughout.

    .venv/bin/python benchmarks/consmac_convergence.py --runs runs/hl/cihrl_consmac_a runs/hl/cihrl_consmac_a_seed1
    .venv/bin/python benchmarks/consmac_convergence.py --runs RUN... --steps 5000 --every 100 --out DIR
    .venv/bin/python benchmarks/consmac_convergence.py --runs RUN --smoke --out DIR   # 20 steps, eval every 10
"""

from __future__ import annotations

import argparse
import io
import json
import math
import shlex
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import torch

from cefc_mj import paths
from cefc_mj.errors import CefcError, CheckpointError, ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.nn.consmac import consmac_loss
from cefc_mj.nn.highlevel_policy import HighLevelPolicy
from cefc_mj.provenance import display_path, display_run_path, file_sha256, git_commit, library_versions
from cefc_mj.train.consmac_replay import ConsMACReplay
from cefc_mj.train.highlevel import read_state
from cefc_mj.train.highlevel_config import HighLevelConfig
from cefc_mj.train.highlevel_export import PAPER_CONSMAC
from cefc_mj.train.highlevel_trainer import HighLevelTrainer
from cefc_mj.train.run_state import STATE_FILE

PROG = "consmac_convergence"
EXIT_USAGE = 2
OURS = 200
"""Steps per round of the shipped runs (`HighLevelConfig.consmac_steps`)."""
MARKS = (0, OURS, 1000, PAPER_CONSMAC["steps"])
"""Steps at which the printed table reads the curves (those within --steps, and the last step)."""
BLOCKS = 20
"""Contiguous blocks of the ring buffer when the episode layout cannot be reconstructed."""
DEFAULT_OUT = paths.EVAL_DIR / "reports" / "consmac_convergence"


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (the usage is in --help)."""

    def error(self, message: str):
        print(f"{PROG}: error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


shown = display_run_path


# ---------------------------------------------------------------------------- loading
def load_run(run_dir: Path) -> dict:
    """The run's config, final ConsMAC, its Adam (restored or fresh), replay rows and counters."""
    run_dir = Path(run_dir)
    state_path = run_dir / STATE_FILE
    if not run_dir.is_dir():
        raise ConfigError(f"--runs: {run_dir} is not a folder")
    state = read_state(state_path)
    try:
        cfg = HighLevelConfig.from_dict(state["config"])
    except (TypeError, KeyError) as e:
        raise CheckpointError(f"{state_path}: config does not describe a high-level run ({e})") from None
    if not cfg.supervised:
        raise ConfigError(f"--runs: {run_dir} is a {cfg.variant} run; only consmac-a / consmac-o train ConsMAC")
    trainer = state["trainer"]
    policy = HighLevelPolicy.build(cfg.variant, cfg.task(), cfg.seed, cfg.hidden, cfg.ablation)
    try:
        policy.load_state_dict(trainer["policy"])
    except (RuntimeError, KeyError) as e:
        raise CheckpointError(f"{state_path}: weights do not fit ({str(e).splitlines()[0][:160]})") from None
    comm = policy.comm
    opt = torch.optim.Adam(comm.parameters(), lr=cfg.consmac_lr)
    adam = "fresh"
    try:
        opt.load_state_dict(trainer["consmac_opt"])
        steps = [int(s["step"]) for s in opt.state.values() if "step" in s]
        adam = f"restored (step {max(steps) if steps else 0})"
    except (ValueError, KeyError, TypeError, RuntimeError):
        opt = torch.optim.Adam(comm.parameters(), lr=cfg.consmac_lr)
    for group in opt.param_groups:  # the run's rate, whatever the saved groups say
        group["lr"] = cfg.consmac_lr
    replay_state = trainer.get("replay")
    if not replay_state or int(replay_state.get("size", 0)) < 2 * BLOCKS:
        raise CheckpointError(f"{state_path}: the replay holds fewer than {2 * BLOCKS} rows")
    replay = ConsMACReplay(int(replay_state["size"]), comm.cfg)
    try:
        replay.load_state_dict({"size": replay_state["size"], "next": 0, "data": replay_state["data"]})
    except (RuntimeError, KeyError) as e:
        raise CheckpointError(f"{state_path}: replay does not fit ConsMAC ({str(e).splitlines()[0][:160]})") from None
    counters = trainer["counters"]
    rows_per_iteration = cfg.ppo.n_envs * cfg.ppo.episodes_per_iteration * cfg.decision_steps * cfg.n_agents
    return {
        "dir": run_dir,
        "state_path": state_path,
        "state": state,
        "cfg": cfg,
        "comm": comm,
        "opt": opt,
        "adam": adam,
        "data": replay.data,
        "size": replay.size,
        "next": int(replay_state["next"]),
        "rows_written": int(counters["iteration"]) * rows_per_iteration,
        "rows_per_iteration": rows_per_iteration,
        "counters": {k: int(counters[k]) for k in ("iteration", "consmac_rounds", "consmac_steps")},
    }


def last_round_loss(run_dir: Path) -> float | None:
    """The mean train-batch loss of the run's last ConsMAC round (progress.csv), if it is there."""
    import csv

    try:
        with (Path(run_dir) / "progress.csv").open(newline="") as f:
            rows = [r for r in csv.DictReader(f) if r.get("consmac_loss") not in (None, "", "nan")]
        return float(rows[-1]["consmac_loss"]) if rows else None
    except (OSError, ValueError, KeyError):
        return None


def fresh_rows(run: dict, iterations: int) -> tuple[dict[str, torch.Tensor], dict]:
    """ConsMAC's replay rows of the `iterations` iterations the run would collect next (its trainer
    restored from state.pt, the same low levels and adversary, the next iterations' seeds, anchors
    sampled by the final selector): data no supervised step of the run has seen. ConfigError when the
    run flew another low level or adversary than the files found now."""
    from cefc_mj.hierarchy import NAVIGATION, load_low_level
    from cefc_mj.nn.adversary_policy import resolve_adversary
    from cefc_mj.train.model_card import display_paths

    cfg, state = run["cfg"], run["state"]
    task = cfg.task()
    low_levels = (load_low_level(NAVIGATION, task), load_low_level(cfg.low_level, task))
    _, adversary_policy, adversary_record = resolve_adversary(cfg.adversary)
    if state.get("low_level", {}).get("finetune") != display_paths(low_levels[1].describe()):
        raise ConfigError(
            f"--fresh: {run['dir']} flew another fine-tuning low level than {cfg.low_level}; use --fresh 0"
        )
    if state.get("adversary", {"rule": cfg.adversary}) != adversary_record:
        raise ConfigError(f"--fresh: {run['dir']} flew against another adversary than {cfg.adversary}; use --fresh 0")
    trainer = HighLevelTrainer(cfg, low_levels, adversary_policy)
    trainer.load_state_dict(state["trainer"])
    replay, per_iteration = trainer.replay, run["rows_per_iteration"]
    parts, first, start = [], trainer.iteration, time.perf_counter()
    for _ in range(iterations):
        begin = replay.next
        trainer.collect(trainer.envs[trainer.enter_phase()])
        index = (begin + torch.arange(per_iteration)) % replay.capacity
        parts.append({k: replay.data[k][index].clone() for k in ConsMACReplay.FIELDS})
        trainer.iteration += 1  # the next iteration's episode seeds
    rows = {k: torch.cat([p[k] for p in parts]) for k in ConsMACReplay.FIELDS}
    how = {
        "iterations": list(range(first, first + iterations)),
        "episodes": iterations * cfg.ppo.n_envs * cfg.ppo.episodes_per_iteration,
        "rows": len(rows["label"]),
        "low_level": cfg.low_level,
        "adversary": cfg.adversary,
        "collect_s": time.perf_counter() - start,
    }
    return rows, how


# ---------------------------------------------------------------------------- the split
def split_rows(
    size: int,
    nxt: int,
    capacity: int,
    rows_written: int,
    rows_per_iteration: int,
    n_envs: int,
    n_agents: int,
    share: float,
    seed: int,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """(training rows, held-out rows, how) of a ring buffer of `size` rows whose next write goes to `nxt`.

    With the layout consistent with `rows_written` (size = min(written, capacity), next = written mod
    capacity), each row's global index is known, hence its iteration and env: whole (iteration, env)
    groups (whole episodes, all agents) are held out in a seeded order until `share` of the rows are.
    Otherwise the rows in age order are cut into BLOCKS contiguous blocks and round(share x BLOCKS) of
    them, chosen by the same seeded permutation, are held out."""
    g = torch.Generator().manual_seed(seed)
    position = torch.arange(size)
    want = max(1, math.ceil(share * size))
    if size == min(rows_written, capacity) and nxt == rows_written % capacity and rows_written > 0:
        index = rows_written - capacity + (position - nxt) % capacity if size == capacity else position
        group = (index // rows_per_iteration) * n_envs + (index // n_agents) % n_envs
        groups, inverse, counts = torch.unique(group, return_inverse=True, return_counts=True)
        order = torch.randperm(len(groups), generator=g)
        taken = order[: int(torch.searchsorted(counts[order].cumsum(0), want)) + 1]
        held = torch.zeros(len(groups), dtype=torch.bool)
        held[taken] = True
        out = held[inverse]
        how = {
            "unit": "episodes",
            "text": f"whole (iteration, env) groups, i.e. whole episodes with all {n_agents} agents: "
            f"{len(taken)} of the replay's {len(groups)} groups, by a permutation seeded {seed}",
            "groups_heldout": len(taken),
            "groups": len(groups),
        }
    else:
        age = (position - nxt) % size
        block = age * BLOCKS // size
        taken = torch.randperm(BLOCKS, generator=g)[: max(1, round(share * BLOCKS))]
        out = torch.isin(block, taken)
        how = {
            "unit": "blocks",
            "text": f"contiguous blocks of the ring buffer in age order: {len(taken)} of {BLOCKS}, "
            f"by a permutation seeded {seed} (the episode layout did not match the run's counters)",
            "groups_heldout": len(taken),
            "groups": BLOCKS,
        }
    return position[~out], position[out], how


# ---------------------------------------------------------------------------- the curve
@torch.no_grad()
def eval_loss(comm, rows: dict[str, torch.Tensor], chunk: int) -> float:
    """`consmac_loss` over all `rows` (eval mode, no gradient, in chunks): the row-weighted mean."""
    comm.eval()
    total, n = 0.0, len(rows["label"])
    for s in range(0, n, chunk):
        part = {k: v[s : s + chunk] for k, v in rows.items()}
        out = comm(part["obs"], part["own"], part["messages"], part["mask"], part["distance"], fast=True)
        total += consmac_loss(out.estimate, part["label"]).item() * len(part["label"])
    comm.train()
    return total / n


def eval_points(steps: int, every: int) -> list[int]:
    return sorted({0, steps, *range(every, steps + 1, every), *(m for m in MARKS if m <= steps)})


def curve(
    run: dict, steps: int, every: int, share: float, seed: int, chunk: int, batch: int | None, fresh: int
) -> dict:
    cfg, comm, data = run["cfg"], run["comm"], run["data"]
    fresh_set, fresh_how = fresh_rows(run, fresh) if fresh else (None, None)
    train_idx, held_idx, how = split_rows(
        run["size"],
        run["next"],
        cfg.replay_capacity,
        run["rows_written"],
        run["rows_per_iteration"],
        cfg.ppo.n_envs,
        cfg.n_agents,
        share,
        seed,
    )
    pick = lambda idx: {k: data[k][idx] for k in ConsMACReplay.FIELDS}  # noqa: E731
    heldout = pick(held_idx)
    g = torch.Generator().manual_seed(seed + 1)
    train_eval = pick(train_idx[torch.randperm(len(train_idx), generator=g)[: len(held_idx)]])
    train_replay = ConsMACReplay(len(train_idx), comm.cfg)
    train_replay.load_state_dict({"size": len(train_idx), "next": 0, "data": pick(train_idx)})
    mean = train_replay.data["label"].mean(dim=0)
    baseline = consmac_loss(mean.expand_as(heldout["label"]), heldout["label"]).item()
    if fresh_set is not None:
        fresh_how["baseline"] = consmac_loss(mean.expand_as(fresh_set["label"]), fresh_set["label"]).item()
    batch = batch or cfg.consmac_batch
    stand_in = SimpleNamespace(  # what HighLevelTrainer.train_consmac reads and counts
        policy=SimpleNamespace(comm=comm),
        consmac_opt=run["opt"],
        replay=train_replay,
        cfg=SimpleNamespace(consmac_batch=batch, ppo=cfg.ppo),
        generator=torch.Generator().manual_seed(seed + 2),
        consmac_rounds=0,
        consmac_steps=0,
    )
    points = eval_points(steps, every)
    result = {"steps": [], "heldout": [], "fresh": [], "train_eval": [], "train_batch": [], "train_s": 0.0}
    done = 0
    for point in points:
        if point > done:
            start = time.perf_counter()
            stats = HighLevelTrainer.train_consmac(stand_in, point - done)
            result["train_s"] += time.perf_counter() - start
            result["train_batch"].append(stats["consmac_loss"])
            done = point
        else:
            result["train_batch"].append(None)  # step 0: no batch yet
        result["steps"].append(point)
        result["heldout"].append(eval_loss(comm, heldout, chunk))
        result["train_eval"].append(eval_loss(comm, train_eval, chunk))
        if fresh_set is not None:
            result["fresh"].append(eval_loss(comm, fresh_set, chunk))
        print(
            f"  {shown(run['dir'])}: step {point:5d}  held-out {result['heldout'][-1]:8.2f}  "
            + (f"fresh {result['fresh'][-1]:8.2f}  " if fresh_set is not None else "")
            + f"training rows {result['train_eval'][-1]:8.2f}  baseline {baseline:8.2f}",
            flush=True,
        )
    assert stand_in.consmac_steps == steps
    return {
        **result,
        "baseline": baseline,
        "split": how,
        "fresh_set": fresh_how,
        "rows": {"replay": run["size"], "train": len(train_idx), "heldout": len(held_idx)},
        "batch": batch,
        "s_per_step": result["train_s"] / steps,
    }


# ---------------------------------------------------------------------------- report
SETS = {"heldout": "held-out episodes", "fresh": "fresh episodes", "train_eval": "training rows"}
"""The evaluated sets of a curve, as the table and the plot name them."""


def at(curve: dict, key: str, step: int) -> float | None:
    """The loss of set `key` after `step` continued steps (None when not evaluated there)."""
    values = curve.get(key) or []
    return values[curve["steps"].index(step)] if step in curve["steps"] and values else None


def table(results: list[dict], steps: int) -> list[str]:
    """Per run and evaluated set: the loss after 0, 200, 1000, 5000 (and the last) continued steps, the
    mean-guessing baseline, the share of it explained (1 - loss / baseline) and the time per step."""
    marks = [m for m in MARKS if m <= steps] + ([steps] if steps not in MARKS else [])
    shares = [m for m in (0, OURS, steps) if m in marks]
    head = f"{'run':30s}{'set':19s}" + "".join(f"{'@' + str(m):>8s}" for m in marks) + f"{'baseline':>9s}"
    head += "".join(f"{'expl@' + str(m):>10s}" for m in shares) + f"{'s/step':>8s}"
    lines = [
        "ConsMAC loss (eq. 11, summed over the label's numbers) after @N continued steps; "
        "expl = 1 - loss / mean-guessing baseline",
        head,
    ]
    for r in results:
        c = r["curve"]
        for key in ("heldout", "fresh"):
            if at(c, key, 0) is None:
                continue
            base = c["baseline"] if key == "heldout" else c["fresh_set"]["baseline"]
            row = f"{r['run']:30s}{SETS[key]:19s}" + "".join(f"{at(c, key, m):8.1f}" for m in marks)
            row += f"{base:9.1f}" + "".join(f"{1 - at(c, key, m) / base:10.1%}" for m in shares)
            lines.append(row + f"{c['s_per_step']:8.3f}")
    return lines


def plot(results: list[dict], steps: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    styles = {"heldout": ("-", 1.8), "fresh": ("-.", 1.8), "train_eval": (":", 1.0), "baseline": ("--", 1.0)}
    fig, ax = plt.subplots(figsize=(8.5, 5.5))
    for i, r in enumerate(results):
        c, color = r["curve"], f"C{i}"
        for key in ("heldout", "fresh", "train_eval"):
            if c.get(key):
                ax.plot(c["steps"], c[key], color=color, ls=styles[key][0], lw=styles[key][1])
        ax.axhline(c["baseline"], color=color, ls=styles["baseline"][0], lw=styles["baseline"][1])
    for x, text in ((OURS, f"ours: {OURS} per round"), (PAPER_CONSMAC["steps"], f"paper: {PAPER_CONSMAC['steps']}")):
        if x <= steps:
            ax.axvline(x, color="0.4", lw=0.8)
            ax.annotate(text, (x, 0.02), xycoords=("data", "axes fraction"), rotation=90, va="bottom", ha="right")
    handles = [Line2D([], [], color=f"C{i}", lw=2, label=r["run"]) for i, r in enumerate(results)]
    shown_sets = [k for k in ("heldout", "fresh", "train_eval") if any(r["curve"].get(k) for r in results)]
    handles += [Line2D([], [], color="0.2", ls=styles[k][0], lw=styles[k][1], label=SETS[k]) for k in shown_sets]
    handles.append(Line2D([], [], color="0.2", ls="--", lw=1.0, label="mean-guessing (held-out episodes)"))
    ax.set_xscale("symlog", linthresh=100)
    ax.set_xlim(0, steps * 1.2)
    ax.set_xlabel("supervised Adam steps continued from the run's final state (symlog: linear below 100)")
    ax.set_ylabel("ConsMAC loss, eq. (11) (summed over the label's numbers)")
    ax.set_title("ConsMAC-A label loss vs further supervised steps on the run's replay")
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, fontsize=7, loc="center left", handlelength=4)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    write_atomic(path, buf.getvalue())


def replot(out: Path) -> int:
    """Redraw the PNG and reprint the table of the report in `out` (no training)."""
    path = Path(out) / "consmac_convergence.json"
    try:
        report = json.loads(path.read_text())
        steps = report["settings"]["steps"]
        report["table"] = table(report["runs"], steps)
        plot(report["runs"], steps, Path(out) / "consmac_convergence.png")
    except (OSError, ValueError, KeyError, TypeError) as e:
        print(f"{PROG}: error: --replot: {display_path(path)}: {' '.join(str(e).split())[:200]}", file=sys.stderr)
        return EXIT_USAGE
    print("\n".join(report["table"]))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="+", type=Path, help="run folders holding state.pt")
    parser.add_argument("--steps", type=int, default=PAPER_CONSMAC["steps"], help="steps to continue (default 5000)")
    parser.add_argument("--every", type=int, default=100, help="evaluate every this many steps (default 100)")
    parser.add_argument("--heldout", type=float, default=0.1, help="share of the replay held out (default 0.1)")
    parser.add_argument("--seed", type=int, default=0, help="seeds the split and the batches (default 0)")
    parser.add_argument("--batch", type=int, default=None, help="batch per step (default: the run's, 2048)")
    parser.add_argument("--chunk", type=int, default=4096, help="rows per evaluation forward (default 4096)")
    parser.add_argument(
        "--out", type=Path, default=DEFAULT_OUT, help=f"report folder (default {display_path(DEFAULT_OUT)})"
    )
    parser.add_argument(
        "--fresh",
        type=int,
        default=1,
        help="iterations of new episodes to collect as a second held-out set, 0 for none (default 1)",
    )
    parser.add_argument("--smoke", action="store_true", help="20 steps, evaluated every 10: the same code path")
    parser.add_argument(
        "--replot", action="store_true", help="redraw the PNG and reprint the table from --out's JSON (no training)"
    )
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    if args.smoke:
        args.steps, args.every = 20, 10
    for name, least in (("steps", 1), ("every", 1), ("chunk", 1), ("seed", 0), ("fresh", 0)):
        if getattr(args, name) < least:
            parser.error(f"--{name}={getattr(args, name)}: must be an integer >= {least}")
    if args.batch is not None and args.batch < 1:
        parser.error(f"--batch={args.batch}: must be an integer >= 1")
    if not 0 < args.heldout < 0.5:
        parser.error(f"--heldout={args.heldout}: must be in (0, 0.5)")
    if args.replot:
        return replot(args.out)
    if not args.runs:
        parser.error("--runs: give at least one run folder (or --replot)")
    torch.set_num_threads(1)
    try:
        for run_dir in args.runs:  # every input checked before the long part
            if not (run_dir / STATE_FILE).is_file():
                raise ConfigError(f"--runs: {run_dir} holds no {STATE_FILE}")
        args.out.mkdir(parents=True, exist_ok=True)
        results = []
        for run_dir in args.runs:
            start = time.perf_counter()
            run = load_run(run_dir)
            print(f"{shown(run_dir)}: {run['size']} replay rows, Adam {run['adam']}", flush=True)
            res = curve(run, args.steps, args.every, args.heldout, args.seed, args.chunk, args.batch, args.fresh)
            cfg = run["cfg"]
            results.append(
                {
                    "run": shown(run_dir),
                    "state_sha256": file_sha256(run["state_path"]),
                    "variant": cfg.variant,
                    "ablation": cfg.ablation,
                    "seed": cfg.seed,
                    "trained": {
                        **run["counters"],
                        "steps_per_round": cfg.consmac_steps,
                        "batch": cfg.consmac_batch,
                        "lr": cfg.consmac_lr,
                        "max_grad_norm": cfg.ppo.max_grad_norm,
                        "last_round_train_loss": last_round_loss(run_dir),
                    },
                    "adam": run["adam"],
                    "curve": res,
                    "wall_s": time.perf_counter() - start,
                }
            )
            del run
        shown_argv = [shown(Path(a)) if Path(a).is_dir() else a for a in argv]
        report = {
            "question": "Does ConsMAC's label loss converge at 200 supervised steps per round (paper: 5000)?",
            "method": (__doc__.split("\n\n")[1].replace("\n", " ")),
            "caveat": (__doc__.split("\n\n")[2].replace("\n", " ")),
            "loss_units": "consmac_loss (eq. 11): squared error summed over the label's numbers, mean over rows",
            "baseline": "consmac_loss of predicting the training part's label mean, on the held-out part",
            "settings": {
                "steps": args.steps,
                "every": args.every,
                "heldout_share": args.heldout,
                "seed": args.seed,
                "eval_chunk": args.chunk,
                "fast_attention": True,
                "fresh_iterations": args.fresh,
                "torch_threads": 1,
            },
            "paper": PAPER_CONSMAC,
            "runs": results,
            "table": table(results, args.steps),
            "command": shlex.join(["python", "benchmarks/consmac_convergence.py", *shown_argv]),
            "provenance": {"commit": git_commit(), "library_versions": library_versions()},
        }
        write_atomic(args.out / "consmac_convergence.json", json.dumps(report, indent=2) + "\n")
        plot(results, args.steps, args.out / "consmac_convergence.png")
    except CefcError as e:
        print(f"{PROG}: error: {' '.join(str(e).split())}", file=sys.stderr)
        return EXIT_USAGE
    print("\n".join(report["table"]))
    print(f"wrote {display_path(args.out / 'consmac_convergence.json')} and consmac_convergence.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
