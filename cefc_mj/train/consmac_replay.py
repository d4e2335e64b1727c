"""B_C of Algorithm 2, the replay of the communication module's inputs and global-state labels that
ConsMAC's supervised update draws from, and how well a module fits the newest labels (`label_fit`)."""

from __future__ import annotations

import torch

from cefc_mj.nn.consmac import ConsMACConfig


class ConsMACReplay:
    """B_C of Algorithm 2: a ring buffer of the communication module's inputs and labels, one row per
    agent-decision. Messages are stored at the module's sent size (64; ConsMAC-G's label size; 38 for
    MASIA, 102 for NVIF), labels at `label_dim` (0 for NVIF, whose targets are the observations in
    its inputs)."""

    FIELDS = ("obs", "own", "messages", "mask", "distance", "label")

    def __init__(self, capacity: int, cfg: ConsMACConfig):
        k, d = cfg.n_agents - 1, cfg.sent_dim
        shapes = {
            "obs": ((cfg.env_obs_dim,), torch.float32),
            "own": ((d,), torch.float32),
            "messages": ((k, d), torch.float32),
            "mask": ((k,), torch.bool),
            "distance": ((k,), torch.float32),
            "label": ((cfg.label_dim,), torch.float32),
        }
        self.capacity = capacity
        self.data = {name: torch.zeros((capacity, *shape), dtype=dtype) for name, (shape, dtype) in shapes.items()}
        self.size = 0
        self.next = 0
        self.rows_added = 0
        """Rows added since this buffer was built (not saved: a resumed buffer counts from 0)."""

    def add(self, rows: dict[str, torch.Tensor]) -> None:
        """Append rows (each [n, ...]); the oldest rows make room once the buffer is full."""
        n = len(rows["obs"])
        start = 0 if n <= self.capacity else n - self.capacity  # more rows than room: keep the newest
        index = (self.next + torch.arange(n - start)) % self.capacity
        for name in self.FIELDS:
            self.data[name][index] = rows[name][start:].to(self.data[name].dtype)
        self.next = int((self.next + n - start) % self.capacity)
        self.size = min(self.capacity, self.size + n - start)
        self.rows_added += n

    def sample(self, batch: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        index = torch.randint(0, self.size, (batch,), generator=generator)
        return {name: self.data[name].index_select(0, index) for name in self.FIELDS}

    def newest(self, rows: int) -> dict[str, torch.Tensor]:
        """The `rows` most recently added rows (fewer when the buffer holds fewer)."""
        n = min(rows, self.size)
        index = (self.next - n + torch.arange(n)) % self.capacity
        return {name: self.data[name][index] for name in self.FIELDS}

    def state_dict(self, keep_rows: bool = True) -> dict:
        """The buffer's rows and ring position. keep_rows=False saves the ring position only, as an
        empty buffer: right for a caller that knows every row will be overwritten before the next
        read (a ring refilled by `capacity` rows holds the same rows at the same places, and its size
        is then `capacity` either way), and it makes the state about 125 MB smaller."""
        size = self.size if keep_rows else 0
        return {"size": size, "next": self.next, "data": {k: v[:size].clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.size, self.next = int(state["size"]), int(state["next"])
        for name in self.FIELDS:
            self.data[name][: self.size] = state["data"][name]


@torch.no_grad()
def label_fit(comm, replay: ConsMACReplay, rows: int) -> dict | None:
    """How well the module estimates its global-state label on the replay's newest `rows` rows (the
    export passes the last iteration's agent-decisions, which at most the last supervised round has
    trained on): its loss (eq. (11),
    summed over the label's numbers, averaged over rows), the loss of always guessing those rows'
    mean label, and 1 - loss / guess (the share of the label's variance explained). None for a module
    without a global-state label (NVIF reconstructs observations)."""
    if comm is None or comm.cfg.label_dim == 0 or replay.size == 0:
        return None
    batch = replay.newest(rows)
    loss = float(comm.supervised_loss(batch))
    label = batch["label"]
    guess = float(((label - label.mean(dim=0)) ** 2).sum(dim=-1).mean())
    return {
        "rows": int(len(label)),
        "loss": loss,
        "mean_guess_loss": guess,
        "explained": 1.0 - loss / guess if guess > 0 else None,
    }
