"""The high level's training (paper Sec. IV-C3, Algorithm 2): MAPPO anchor selection over ConsMAC.

One iteration, CleanRL-style:

1. **Collect** `n_envs x episodes_per_iteration` whole episodes of the hierarchical game
   (`cefc_mj.hierarchy`, 40 decisions of 10 low-level steps each). At every decision agent i
   receives its neighbours' messages of the previous decision (`MessageChannel`: one step late,
   true distance < 3 m), ConsMAC turns [o_i, own message, inbox] into m_i^(t+1) and g_hat_i, the
   message is sent, and the selector samples an anchor from (o_i, m_i^(t+1)) with the message
   detached (eq. 12). ConsMAC's inputs and the label g_i (ConsMAC-A: every agent's anchor of this
   decision; ConsMAC-O: every other agent's relative position and velocity) go to the replay B_C.
2. **RL update** of the selector Theta_H and the critic phi_H: PPO epochs over the iteration's
   decisions with the low level's PPO pieces (`cefc_mj.train.ppo`: GAE, clipped surrogate, value
   normalisation) and `PPOConfig`. Every agent learns from the team reward R_H summed over the 10
   low-level steps; the critic is V(s, o_i) (global state plus the agent's observation, MAPPO's
   agent-specific state), 3 layers of 128. The RL loss never reaches ConsMAC: the consensus input is
   stored detached and the selector detaches it again.
3. **ConsMAC update** (every `consmac_every` iterations): `consmac_steps` Adam steps on batches of
   `consmac_batch` tuples drawn from B_C, loss eq. (11).

Algorithm 2 pre-trains with a navigation-only low level and then fine-tunes with the trained one:
the first `pretrain_share` of the budget flies `NavigationOnly`, the rest `low_level` (default the
distilled student); networks, optimizers and the critic carry over. Variants: consmac-a, consmac-o
(the paper), mappo (no communication: the selector reads o_i only), tarmac (the TarMAC baseline:
the same communication module, its messages trained end to end by the RL loss instead of eq. (11):
in the update each receiver's inbox is recomputed, with gradients, from its senders' stored inputs
of the previous decision, so the PPO loss of decision t reaches the network that sent the messages
read at t; the senders' own inboxes are taken as stored, a one-step truncation of TarMAC's
backpropagation through time), masia and nvif (the paper's other communication baselines,
`cefc_mj.nn.obs_comm`: they send the raw local observation, MASIA alone and NVIF after a
variational latent, and their modules learn from their own supervised losses in the ConsMAC
update's place and schedule, MASIA's reconstructing the global state and NVIF's the local
observations; the RL loss never reaches them). `ablation` (consmac variants only) selects one of the paper's
Fig. 7 ablations of ConsMAC (`cefc_mj.nn.consmac.ABLATIONS`); "wt-rl" also lets the PPO loss into
ConsMAC, whose optimizer then steps on both losses.

    run folder   <out>/<name>/   config.json, progress.csv, tb/, state.pt (resumable)
    policy file  <policies_dir>/<name>.pt  + <name>.json model card      name = cihrl_<variant>[_<ablation>]

Every iteration's episodes are seeded from (seed, iteration) and `state.pt` holds networks,
optimizers, value normalisation, the torch RNG, counters and the replay, so `--resume` continues a
run as if it had not stopped.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from cefc_mj.errors import CheckpointError, ConfigError
from cefc_mj.fileio import write_atomic
from cefc_mj.hierarchy import (
    NAVIGATION,
    load_low_level,
)
from cefc_mj.nn.adversary_policy import resolve_adversary
from cefc_mj.nn.highlevel_policy import (
    HighLevelPolicy,
)
from cefc_mj.nn.policy_io import atomic_torch_save
from cefc_mj.train import run_state
from cefc_mj.train.highlevel_config import HighLevelConfig, check_resume_schedule
from cefc_mj.train.highlevel_export import export_policy
from cefc_mj.train.highlevel_trainer import HighLevelTrainer
from cefc_mj.train.logger import RunLogger
from cefc_mj.train.model_card import display_paths
from cefc_mj.train.run_state import STATE_FILE

TARMAC_MESSAGES = "end-to-end-1step"
"""How the tarmac variant trains its messages (saved in its resumable state, checked on --resume): the
PPO loss reaches the senders through the inbox recomputed from their previous decision's inputs.
States written before this had no gradient through received messages."""
STATE_FORMAT = "cefc-mj/highlevel-state"
PROGRESS_KEYS = ("episode_return", "metric/E", "consmac_loss", "approx_kl")


# ---------------------------------------------------------------------------- the run
def read_state(path: Path) -> dict:
    return run_state.read_state(path, STATE_FORMAT, "high-level training state")


def _last_csv_row(run_dir: Path) -> dict:
    with (run_dir / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    return rows[-1] if rows else {}


def train_highlevel(
    cfg: HighLevelConfig,
    out: Path,
    policies_dir: Path,
    resume: bool = False,
    show_progress: bool = True,
    command: str | None = None,
    low_level_dir: Path | None = None,
) -> dict:
    """Train under the budget, export pi_H and its model card to `policies_dir`; returns the card.

    resume: continue the run in <out>/<name>/ (ConfigError if there is none, or if it was made with
    other settings). low_level_dir: where `cfg.low_level` is looked up by name (default the shipped
    policies). Everything the run needs is loaded and checked before the run folder is made."""
    out, policies_dir = Path(out), Path(policies_dir)
    run_dir = out / cfg.name
    state_path = run_dir / STATE_FILE
    task = cfg.task()
    try:
        low_levels = (load_low_level(NAVIGATION, task), load_low_level(cfg.low_level, task, low_level_dir))
    except CheckpointError as e:
        raise CheckpointError(f"--low-level: {e}") from None
    try:
        _, adversary_policy, adversary_record = resolve_adversary(cfg.adversary)
    except CheckpointError as e:
        raise CheckpointError(f"--adversary: {e}") from None
    saved = None
    if run_state.run_state_path(run_dir, resume) is not None:
        saved = read_state(state_path)
        check_resume_schedule(saved["config"], cfg, state_path)
        run_state.check_same_run(saved["config"], cfg, state_path, free=("budget", "checkpoint_every", "eval_episodes"))
        if saved["low_level"]["finetune"] != display_paths(low_levels[1].describe()):
            raise ConfigError(
                f"--resume: {state_path} was trained with another fine-tuning low level "
                f"({saved['low_level']['finetune'].get('name')}); use another --out"
            )
        if cfg.variant == "tarmac" and saved.get("tarmac_messages") != TARMAC_MESSAGES:
            raise ConfigError(
                f"--resume: {state_path} was trained without gradient through received messages "
                "(the TarMAC-style row before end-to-end messages); use another --out"
            )
        if saved.get("adversary", {"rule": cfg.adversary}) != adversary_record:
            raise ConfigError(
                f"--resume: {state_path} was trained against another adversary file "
                f"({saved['adversary'].get('policy')}); use another --out"
            )
    trainer = HighLevelTrainer(cfg, low_levels, adversary_policy)
    trainer.adversary_record = adversary_record
    if saved is not None:
        run_state.restore_trainer(trainer, saved, state_path)
    low_level_record = {
        "pretrain": display_paths(low_levels[0].describe()),
        "finetune": display_paths(low_levels[1].describe()),
    }
    write_atomic(
        run_dir / "config.json",
        json.dumps(
            {
                "highlevel": cfg.to_dict(),
                "task": task.to_dict(),
                "low_level": low_level_record,
                "adversary": adversary_record,
                "command": command,
            },
            indent=2,
        )
        + "\n",
    )

    def checkpoint() -> None:
        atomic_torch_save(
            {
                "format": STATE_FORMAT,
                "config": cfg.to_dict(),
                "low_level": low_level_record,
                "adversary": adversary_record,
                "trainer": trainer.state_dict(),
                **({"tarmac_messages": TARMAC_MESSAGES} if cfg.variant == "tarmac" else {}),
            },
            state_path,
        )

    if saved is None:
        checkpoint()  # iteration 0: a run killed before its first periodic checkpoint can still --resume
    logger = RunLogger(run_dir, trainer.iteration, cfg.budget.iterations, desc=cfg.name, show_progress=show_progress)
    last_row = run_state.train_under_budget(
        trainer, cfg.budget, cfg.checkpoint_every, logger, PROGRESS_KEYS, checkpoint
    )
    if not last_row and trainer.iteration:  # a finished run re-exported: its last logged iteration
        last_row = _last_csv_row(run_dir)

    card = export_policy(
        trainer.policy, cfg, task, low_levels, trainer, policies_dir, run_dir, command, last_row=last_row
    )
    if trainer.pretrained is not None and trainer.progress["iterations"][1] > 0:
        pretrained = HighLevelPolicy.build(cfg.variant, task, cfg.seed, cfg.hidden, cfg.ablation)
        pretrained.load_state_dict(trainer.pretrained)
        card["wo_ft"] = export_policy(
            pretrained, cfg, task, low_levels, trainer, policies_dir, run_dir, command, wo_ft=True
        )["name"]
    return card


def summary_lines(card: dict, policies_dir: Path) -> list[str]:
    """What `cefc-train highlevel` prints when a run ends."""
    phases = ", ".join(f"{p['phase']} ({p['low_level']}): {p['iterations']} it" for p in card["phases"])
    lines = [
        f"{card['name']}: {card['iterations']} iterations ({phases}), {card['episodes']} episodes, "
        f"{card['train_wall_clock_s']} s -> {policies_dir / (card['name'] + '.pt')} (run {card['run_dir']})"
    ]
    if card.get("consmac_training"):
        c = card["consmac_training"]
        module = {"masia": "MASIA's module", "nvif": "NVIF's module"}.get(card["variant"], "ConsMAC")
        fit = c.get("label_fit")
        lines.append(
            f"{module}: {c['rounds']} rounds, {c['steps']} steps of batch {c['batch']} "
            f"(paper: {c['paper']['steps']} steps every {c['paper']['every_episodes']} episodes)"
            + (
                f"; label fit on the newest {fit['rows']} rows: loss {fit['loss']:.1f} against "
                f"{fit['mean_guess_loss']:.1f} for guessing the mean ({fit['explained']:.0%} explained)"
                if fit and fit["explained"] is not None
                else ""
            )
        )
    if card.get("wo_ft"):
        lines.append(f"pre-trained weights (wo-FT) -> {policies_dir / (card['wo_ft'] + '.pt')}")
    if "evaluation" in card:
        o = card["evaluation"]["ours"]
        lines.append(
            f"evaluation ({card['evaluation']['protocol']['episodes']} episodes): R_H {o['R_H']:.1f} = "
            f"R_t {o['R_t']:.1f} + R_n {o['R_n']:.1f} + R_e {o['R_e']:.1f}; E {o['E']:.1f}  F {o['F']:.1f}  "
            f"C {o['C']:.2f}%"
        )
    return lines
