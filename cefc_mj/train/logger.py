"""Run logs: one CSV row and one TensorBoard point per iteration, and a tqdm progress bar.

What the columns mean (all per iteration):
- episode_return: the team reward R_L summed over a 100-step episode, averaged over the envs;
  reward_per_step = episode_return / steps (the paper's Table III "R_L").
- term/R_f, term/R_n, term/R_c: unweighted reward terms, per step, averaged over envs and steps.
- metric/F, metric/N: steps of the episode in formation / with the swarm centre within 1 m of the
  anchor; metric/C: % of agent-steps in collision (averaged over the iteration's episodes).
- policy_loss, value_loss, entropy, approx_kl, clipfrac, grad norms: means over all minibatches;
  explained_variance of the critic before the update; action_std of the Gaussian head.
- env_sps: agent-steps per second while collecting; update_sps: agent-samples x epochs per second
  in the update; sps: agent-steps per second overall.
"""

from __future__ import annotations

import csv
from pathlib import Path

from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm


class RunLogger:
    """CSV + TensorBoard + progress bar for one run folder. On resume, rows past the resumed
    iteration (written after the last checkpoint, before a kill) are dropped from the CSV and
    purged from TensorBoard, so the logs read as one uninterrupted run."""

    def __init__(self, run_dir: Path, resume_iteration: int, total: int | None, desc: str, show_progress: bool = True):
        self.csv_path = Path(run_dir) / "progress.csv"
        self.fields: list[str] | None = None
        if resume_iteration > 0 and self.csv_path.exists():
            with self.csv_path.open(newline="") as f:
                rows = [r for r in csv.DictReader(f) if int(float(r["iteration"])) <= resume_iteration]
            if rows:
                self.fields = list(rows[0])
                self._write_rows(rows)
        elif self.csv_path.exists():
            self.csv_path.unlink()
        # purge_step hides TensorBoard points past the resumed iteration (also when resuming from 0).
        self.writer = SummaryWriter(str(Path(run_dir) / "tb"), purge_step=resume_iteration + 1)
        self.bar = tqdm(
            total=total,
            initial=resume_iteration,
            desc=desc,
            unit="it",
            disable=not show_progress,
            dynamic_ncols=True,
            mininterval=2.0,
        )

    def _write_rows(self, rows: list[dict]) -> None:
        with self.csv_path.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=self.fields)
            w.writeheader()
            w.writerows(rows)

    def log(self, row: dict[str, float], postfix_keys: tuple[str, ...] = (), advance: int = 1) -> None:
        """Append `row` (keyed by row['iteration']) and move the progress bar by `advance`."""
        if self.fields is None:
            self.fields = list(row)
            self._write_rows([])
        with self.csv_path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore").writerow(row)
        step = int(row["iteration"])
        for k, v in row.items():
            if k != "iteration" and isinstance(v, (int, float)):
                self.writer.add_scalar(k, v, step)
        self.bar.update(advance)
        self.bar.set_postfix({k.split("/")[-1]: f"{row[k]:.3g}" for k in postfix_keys if k in row}, refresh=False)

    def close(self) -> None:
        self.writer.close()
        self.bar.close()
