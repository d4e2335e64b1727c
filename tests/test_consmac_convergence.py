"""benchmarks/consmac_convergence.py (docs/research/high_level.md, "Does ConsMAC's label loss converge at 200 steps
per round?"): its --smoke mode as a real subprocess on a tiny run state in the trainer's format (a real
ConsMAC for N = 3, a real Adam state, a replay ring buffer that has wrapped, learnable labels), the
episode-wise held-out split, the fresh held-out set (the run's next iteration, from a real tiny run), and
one-line errors with exit code 2 for bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from benchmark_scripts import load_benchmark

from cefc_mj.hierarchy import load_low_level
from cefc_mj.nn.consmac import consmac_loss
from cefc_mj.nn.highlevel_policy import HighLevelPolicy
from cefc_mj.train.config import Budget, PPOConfig
from cefc_mj.train.highlevel import STATE_FORMAT, train_highlevel
from cefc_mj.train.highlevel_config import HighLevelConfig
from cefc_mj.train.highlevel_trainer import HighLevelTrainer
from cefc_mj.train.run_state import STATE_FILE

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "benchmarks" / "consmac_convergence.py"
ITERATIONS, CAPACITY = 30, 600
"""30 iterations of 2 envs x 4 decisions x 3 agents = 720 rows written into a ring of 600 (next = 120)."""

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _script():
    return load_benchmark("consmac_convergence")


def tiny_run(folder: Path, iterations: int = ITERATIONS) -> Path:
    """A finished consmac-a run's state.pt: N = 3, 40-step episodes (4 decisions), 2 envs, a wrapped
    replay whose labels are an offset plus a linear map of the observation (learnable), lr 1e-2."""
    cfg = HighLevelConfig(
        budget=Budget(iterations=iterations),
        n_agents=3,
        episode_steps=40,
        consmac_batch=128,
        consmac_lr=1e-2,
        replay_capacity=CAPACITY,
        ppo=PPOConfig(n_envs=2, epochs=1, minibatches=2, lr=1e-4, update_threads=1),
    )
    policy = HighLevelPolicy.build(cfg.variant, cfg.task(), cfg.seed, cfg.hidden)
    comm = policy.comm
    g = torch.Generator().manual_seed(0)
    k, d, n = comm.cfg.n_agents - 1, comm.cfg.sent_dim, CAPACITY
    obs = torch.randn(n, comm.cfg.env_obs_dim, generator=g) * 2
    mask = torch.rand(n, k, generator=g) < 0.5
    local = comm.local_observation(obs)[:, : comm.cfg.global_dim]
    data = {
        "obs": obs,
        "own": torch.randn(n, d, generator=g),
        "messages": torch.randn(n, k, d, generator=g) * mask.unsqueeze(-1),
        "mask": mask,
        "distance": torch.rand(n, k, generator=g) * 3 * mask,
        "label": 3.0 + 0.5 * local,
    }
    opt = torch.optim.Adam(comm.parameters(), lr=cfg.consmac_lr)
    out = comm(data["obs"][:64], data["own"][:64], data["messages"][:64], data["mask"][:64], data["distance"][:64])
    consmac_loss(out.estimate, data["label"][:64]).backward()
    opt.step()
    written = iterations * 2 * 4 * 3
    state = {
        "format": STATE_FORMAT,
        "config": cfg.to_dict(),
        "trainer": {
            "policy": policy.state_dict(),
            "consmac_opt": opt.state_dict(),
            "replay": {"size": n, "next": written % CAPACITY, "data": data},
            "counters": {"iteration": iterations, "consmac_rounds": iterations, "consmac_steps": 1},
        },
    }
    folder.mkdir(parents=True)
    torch.save(state, folder / STATE_FILE)
    return folder


def test_smoke_learns_on_held_out_episodes(tmp_path):
    run = tiny_run(tmp_path / "runs" / "hl" / "cihrl_consmac_a")
    out = tmp_path / "report"
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--runs", str(run), "--smoke", "--fresh", "0", "--out", str(out)],
        cwd=ROOT,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "runs/hl/cihrl_consmac_a" in proc.stdout and "baseline" in proc.stdout
    report = json.loads((out / "consmac_convergence.json").read_text())
    assert (out / "consmac_convergence.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (result,) = report["runs"]
    assert result["run"] == "runs/hl/cihrl_consmac_a"  # never the machine's absolute path
    assert result["adam"] == "restored (step 1)"
    c = result["curve"]
    assert c["steps"] == [0, 10, 20]
    assert c["split"]["unit"] == "episodes" and c["split"]["groups"] == CAPACITY // 12  # (iteration, env) groups
    assert c["rows"]["heldout"] == 12 * c["split"]["groups_heldout"] >= CAPACITY // 10
    assert c["rows"]["train"] + c["rows"]["heldout"] == CAPACITY
    assert c["heldout"][-1] < c["heldout"][0]  # learnable labels: the continued steps help on unseen episodes
    assert c["train_batch"][0] is None and all(x > 0 for x in c["train_batch"][1:])
    assert 0 < c["baseline"] < c["heldout"][0]  # a fresh-ish net is worse than the label mean
    assert c["fresh"] == [] and c["fresh_set"] is None  # --fresh 0: the synthetic state has no game to play
    assert report["settings"]["steps"] == 20 and report["provenance"]["library_versions"]["torch"]


def test_split_holds_out_whole_groups_or_blocks():
    split_rows = _script().split_rows
    written, per_iteration, envs, agents = 720, 24, 2, 3
    train, held, how = split_rows(CAPACITY, written % CAPACITY, CAPACITY, written, per_iteration, envs, agents, 0.1, 0)
    assert how["unit"] == "episodes"
    assert sorted(torch.cat([train, held]).tolist()) == list(range(CAPACITY))
    index = written - CAPACITY + (torch.arange(CAPACITY) - written % CAPACITY) % CAPACITY  # global row index
    group = (index // per_iteration) * envs + (index // agents) % envs
    held_groups = set(group[held].tolist())
    assert not held_groups & set(group[train].tolist())  # no episode on both sides
    assert len(held) == 12 * len(held_groups) and len(held) >= CAPACITY // 10
    # counters that do not match the ring: contiguous blocks in age order instead
    train, held, how = split_rows(CAPACITY, 7, CAPACITY, written, per_iteration, envs, agents, 0.1, 0)
    assert how["unit"] == "blocks" and len(held) == CAPACITY // 10
    age = sorted(((held - 7) % CAPACITY).tolist())
    runs = sum(1 for a, b in zip(age, age[1:]) if b != a + 1) + 1
    assert runs <= 2  # two blocks of 30 rows, adjacent or not


def test_fresh_rows_are_the_rows_the_run_would_collect_next(tmp_path, monkeypatch):
    """--fresh plays the run's next iteration with its restored trainer: the same rows that the run,
    resumed for one more iteration, adds to its replay (a real 2-iteration run: particle world, the
    shipped student and PPO adversary, 2 envs, 5 decisions per episode)."""
    monkeypatch.chdir(tmp_path)
    cfg = HighLevelConfig(
        budget=Budget(iterations=2),
        episode_steps=50,
        consmac_steps=3,
        consmac_batch=64,
        ppo=PPOConfig(n_envs=2, epochs=1, minibatches=2, lr=1e-4, update_threads=1),
        eval_episodes=0,
    )
    train_highlevel(cfg, tmp_path / "runs" / "hl", tmp_path / "policies", show_progress=False)
    script = _script()
    run = script.load_run(tmp_path / "runs" / "hl" / cfg.name)
    rows, how = script.fresh_rows(run, 1)
    assert how["iterations"] == [2] and how["episodes"] == 2 and how["rows"] == len(rows["label"]) == 2 * 5 * 8

    task = cfg.task()
    trainer = HighLevelTrainer(cfg, (load_low_level("navigation", task), load_low_level(cfg.low_level, task)))
    trainer.load_state_dict(run["state"]["trainer"])
    trainer.iterate()
    newest = (trainer.replay.next - 80 + torch.arange(80)) % trainer.replay.capacity
    for name in ("obs", "own", "messages", "mask", "distance", "label"):
        assert torch.equal(rows[name], trainer.replay.data[name][newest]), name

    out = tmp_path / "report"
    assert script.main(["--runs", str(tmp_path / "runs" / "hl" / cfg.name), "--smoke", "--out", str(out)]) == 0
    curve = json.loads((out / "consmac_convergence.json").read_text())["runs"][0]["curve"]
    assert len(curve["fresh"]) == len(curve["steps"]) == 3 and curve["fresh_set"]["baseline"] > 0


@pytest.mark.parametrize(
    "args, says",
    [
        (["--runs", "{tmp}/missing"], "holds no state.pt"),
        (["--runs", "{run}", "--steps", "0"], "--steps=0: must be an integer >= 1"),
        (["--runs", "{run}", "--heldout", "0.7"], "--heldout=0.7"),
        (["--runs", "{bad}"], "not a readable checkpoint"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, args, says):
    run = tmp_path / "run"
    run.mkdir()
    (run / STATE_FILE).write_bytes(b"")  # never read: the argument checks come first
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / STATE_FILE).write_text("not a checkpoint")
    argv = [a.format(tmp=tmp_path, run=run, bad=bad) for a in args] + ["--out", str(tmp_path / "out")]
    try:
        rc = _script().main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith("consmac_convergence: error:") and says in err
    assert not (tmp_path / "out" / "consmac_convergence.json").exists()
