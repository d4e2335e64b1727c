"""The high level's policy file and model card (`export_policy`): the method's name, what its
messages carry and what trains them, the ConsMAC schedule it ran, and an evaluation of the final
policy."""

from __future__ import annotations

from pathlib import Path

from cefc_mj.game_protocol import evaluate_highlevel
from cefc_mj.hierarchy import (
    LowLevel,
)
from cefc_mj.nn.highlevel_policy import (
    HighLevelPolicy,
    save_highlevel_policy,
)
from cefc_mj.task.config import TaskConfig
from cefc_mj.train.consmac_replay import label_fit
from cefc_mj.train.highlevel_config import SCHEDULES, HighLevelConfig
from cefc_mj.train.highlevel_trainer import HighLevelTrainer
from cefc_mj.train.model_card import display_path, display_paths, write_model_card

METHODS = {
    "consmac-a": "CI-HRL (ConsMAC-A)",
    "consmac-o": "CI-HRL (ConsMAC-O)",
    "mappo": "MAPPO high level, no communication",
    "tarmac": "TarMAC: attention-based communication, messages trained end to end by RL (one-step truncation)",
    "masia": "MASIA+AT-M: raw local observations sent, aggregated by attention, decoded to the global state",
    "nvif": "NVIF+AT-M: a variational latent and the raw local observation sent, a VAE of local observations",
}
COMMUNICATION = {
    "consmac-a": ("m_i^(t+1)", "eq. (11): squared error of g_hat_i to every agent's anchor (ConsMAC-A)"),
    "consmac-o": ("m_i^(t+1)", "eq. (11): squared error of g_hat_i to the others' relative positions and velocities"),
    "tarmac": ("m_i^(t+1)", "the PPO loss, end to end through the received messages"),
    "masia": (
        "o_i, the sender's local observation (unscaled)",
        "supervised: z_i's decoder reconstructs the global state (ConsMAC-O's label); MASIA's latent "
        "future prediction is left out",
    ),
    "nvif": (
        "[mu_i || o_i]: the variational latent's mean (64) and the sender's local observation (38, unscaled)",
        "VAE: a sample of z_i reconstructs the own and the received local observations, plus kl_weight x KL to N(0, I)",
    ),
}
"""The model card's message content and what trains the communication module, per variant."""
ABLATION_METHODS = {
    "wo-com": "without communication (wo-Com: no message received)",
    "wo-mem": "without memory (wo-Mem: the GRU's hidden input is zero at every decision)",
    "wo-de": "without distance encoder (wo-DE: distance codes are zeros)",
    "wt-rl": "with the RL loss (wt-RL: ConsMAC trained by eq. (11) and the PPO loss)",
    "consmac-g": "ConsMAC-G (the estimate g_hat is sent as the message)",
}
"""The model card's method suffix of each of ConsMAC's ablations (paper Fig. 7)."""
TARMAC_MESSAGES = "end-to-end-1step"
"""How the tarmac variant trains its messages (saved in its resumable state, checked on --resume): the
PPO loss reaches the senders through the inbox recomputed from their previous decision's inputs.
States written before this had no gradient through received messages."""
PHASES = ("pretrain", "finetune")
PAPER_CONSMAC = {"every_episodes": 20, "steps": 5000, "batch": 2048}
"""Algorithm 2's ConsMAC schedule (paper Sec. V-A), recorded beside what a run did."""


def export_policy(
    policy: HighLevelPolicy,
    cfg: HighLevelConfig,
    task: TaskConfig,
    low_levels: tuple[LowLevel, LowLevel],
    trainer: HighLevelTrainer,
    policies_dir: Path,
    run_dir: Path,
    command: str | None,
    last_row: dict | None = None,
    wo_ft: bool = False,
) -> dict:
    """Write `policy` as <name>.pt with its model card (evaluated with the fine-tuning low level)
    into `policies_dir`; returns the card. wo_ft: the weights at the end of pre-training, written
    as <name>_wo_ft.pt (the paper's "wo-FT": pre-trained, then combined with the fine-tuning low
    level without joint fine-tuning)."""
    name = cfg.name + ("_wo_ft" if wo_ft else "")
    low_level_record = {
        "pretrain": display_paths(low_levels[0].describe()),
        "finetune": display_paths(low_levels[1].describe()),
    }
    iterations = trainer.progress["iterations"][0] if wo_ft else trainer.iteration
    episodes = iterations * cfg.ppo.n_envs * cfg.ppo.episodes_per_iteration if wo_ft else trainer.episodes
    policy_path = save_highlevel_policy(
        policy,
        policies_dir / f"{name}.pt",
        meta={
            "name": name,
            "variant": cfg.variant,
            "ablation": cfg.ablation,
            "seed": cfg.seed,
            "iterations": iterations,
            "decision_interval": cfg.decision_interval,
            "low_level": low_level_record["finetune"],
            "adversary": trainer.adversary_record,
        },
    )
    phases = [
        {"phase": phase, "low_level": low_levels[i].name, "iterations": trainer.progress["iterations"][i]}
        for i, phase in enumerate(PHASES)
    ]
    card = {
        "name": name,
        "method": METHODS[cfg.variant]
        + (f", {ABLATION_METHODS[cfg.ablation]}" if cfg.ablation != "none" else "")
        + (", without fine-tuning (wo-FT)" if wo_ft else ""),
        "variant": cfg.variant,
        "ablation": cfg.ablation,
        "seed": cfg.seed,
        "config": cfg.to_dict(),
        "task": task.to_dict(),
        "networks": {
            "comm": None if policy.comm is None else policy.comm.cfg.to_dict(),
            "selector": policy.selector.cfg.to_dict(),
            "critic_hidden": cfg.critic_hidden,
        },
        "low_level": low_level_record,
        "adversary": trainer.adversary_record,
        "phases": phases[:1] if wo_ft else phases,
        "schedule": {
            "name": cfg.schedule,
            **SCHEDULES[cfg.schedule],
            **({"iterations": cfg.paper_updates} if cfg.schedule == "paper-scaled" else {}),
            "paper_updates": cfg.paper_updates,
            "fixed": cfg.schedule != "short",
        },
        "consmac_training": None
        if not cfg.supervised
        else {
            "rounds": trainer.consmac_rounds,
            "steps": trainer.consmac_steps,
            "steps_per_round": cfg.consmac_steps,
            "every_iterations": cfg.consmac_every,
            "every_episodes": cfg.consmac_every * cfg.ppo.n_envs * cfg.ppo.episodes_per_iteration,
            "batch": cfg.consmac_batch,
            "lr": cfg.consmac_lr,
            "replay_capacity": cfg.replay_capacity,
            "paper": PAPER_CONSMAC,
            "label_fit": label_fit(
                policy.comm,
                trainer.replay,
                cfg.ppo.n_envs * cfg.ppo.episodes_per_iteration * cfg.decision_steps * cfg.n_agents,
            ),
        },
        "messages": None
        if policy.comm is None
        else {
            "numbers": policy.message_dim,
            "content": "g_hat (ConsMAC-G)" if cfg.ablation == "consmac-g" else COMMUNICATION[cfg.variant][0],
            "trained_by": COMMUNICATION[cfg.variant][1]
            + (" and the PPO loss (wt-RL)" if cfg.ablation == "wt-rl" else ""),
            "selector_reads": "the message"
            if policy.comm.cfg.message_content == "learned"
            else f"the aggregated feature ({policy.comm.cfg.feature_dim} numbers), detached",
            "received": "nothing (wo-Com)" if cfg.ablation == "wo-com" else "neighbours within 3 m, one decision late",
            "rl_gradient": {
                "tarmac": "end to end through the received messages, truncated one decision back",
                "wt-rl": "into ConsMAC through the agent's own message (besides eq. (11))",
            }.get(cfg.variant if cfg.variant == "tarmac" else cfg.ablation, "none (stop-gradient)"),
        },
        "iterations": iterations,
        "episodes": episodes,
        "decisions": episodes * cfg.decision_steps * cfg.n_agents,
        "train_wall_clock_s": round(trainer.elapsed, 1),
        "run_dir": display_path(run_dir),
        "command": command,
    }
    if wo_ft:
        card["wo_ft"] = (
            f"the weights at the end of pre-training (iteration {iterations}) of the run that made "
            f"{cfg.name}; the ConsMAC and wall-clock figures are the whole run's"
        )
    else:
        card["last_iteration"] = {k: v for k, v in (last_row or {}).items() if isinstance(v, (int, float))}
    if cfg.eval_episodes:
        card["evaluation"] = {
            "protocol": {
                "episodes": cfg.eval_episodes,
                "seed": 0,
                "anchors": "mode of the selector",
                "low_level": low_levels[1].name,
                "backend": "particle",
                "figures": "per-episode sums; R_t, R_n, R_e weighted, summing to R_H",
            },
            "ours": evaluate_highlevel(
                policy,
                task,
                low_levels[1],
                cfg.eval_episodes,
                seed=0,
                decision_interval=cfg.decision_interval,
                adversary_policy=trainer.adversary_policy,
            ),
        }
    write_model_card(policy_path, card)
    return card
