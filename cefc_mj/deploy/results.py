"""What a SITL-M or dropout episode returns beyond the lock-step `EpisodeResult`."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from cefc_mj.eval.runner import HISTOGRAM_EDGES_MS, EpisodeResult

FAULT_EVENTS = {
    "agent_exited": "agent process exited",
    "offboard_loss_hold": "failsafe hold",
    "agent_error": "agent reported an error",
}
"""The events that make an episode not a measurement of the policy (what each says, for the one line)."""
REQUESTED_EVENTS = ("fault_kill", "fault_stop", "removed")
"""The events of a fault that was asked for (an injected fault, a dropout): its UAV's later faults are expected."""


def unrequested_faults(events: list[dict]) -> list[str]:
    """One line per cause of the FAULT_EVENTS that hit UAVs whose fault was not asked for: which UAVs,
    from which step, why ("UAVs 0-5: agent process exited at step 1 (t 0.10 s): process gone")."""
    requested = {e["uav"] for e in events if e["event"] in REQUESTED_EVENTS}
    causes: dict[tuple[str, str], list[dict]] = {}
    for e in events:
        if e["event"] in FAULT_EVENTS and e["uav"] not in requested:
            causes.setdefault((e["event"], e["detail"]), []).append(e)
    lines = []
    for (kind, detail), hits in causes.items():
        uavs = sorted({e["uav"] for e in hits if e["uav"] is not None})
        first = min(hits, key=lambda e: e["step"])
        who = f"UAV {uavs[0]}" if len(uavs) == 1 else f"UAVs {_ranges(uavs)}"
        lines.append(f"{who}: {FAULT_EVENTS[kind]} at step {first['step']} (t {first['t']:.2f} s): {detail}")
    return lines


def _ranges(values: list[int]) -> str:
    """ "0-3, 5" for [0, 1, 2, 3, 5]."""
    parts, start = [], None
    for i, v in enumerate(values):
        if start is None:
            start = v
        if i + 1 == len(values) or values[i + 1] != v + 1:
            parts.append(str(start) if start == v else f"{start}-{v}")
            start = None
    return ", ".join(parts)


def _histogram(values: np.ndarray) -> list[int]:
    counts, _ = np.histogram(np.clip(values, 0.0, HISTOGRAM_EDGES_MS[-1]), bins=HISTOGRAM_EDGES_MS)
    return counts.tolist()


def _percentiles(values: np.ndarray) -> dict[str, float | None]:
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return {"p50": None, "p99": None, "max": None, "count": 0}
    p50, p99 = np.percentile(values, [50, 99])
    return {"p50": float(p50), "p99": float(p99), "max": float(values.max()), "count": int(values.size)}


@dataclass
class SitlStats:
    """Transport and timing statistics of one SITL-M episode. The per-agent arrays are raw samples
    (one per reply or per applied command) for histograms; `summary()` gives p50/p99."""

    decision_latency_ms: list[np.ndarray]
    """Per UAV: the agent's own measure of each decision (packet received -> reply ready, wall clock)."""
    round_trip_ms: list[np.ndarray]
    """Per UAV: packet sent -> reply read by the simulator (wall clock; includes the simulator's
    own polling granularity, so it is an upper bound of the network + decision time)."""
    command_age_ms: list[np.ndarray]
    """Per UAV: age of each command when it took effect, in simulated time: the tick it was applied
    at minus the time of the sensor packet it answers (link delays + latency, rounded up to the
    control tick)."""
    late_commands: np.ndarray
    """[N] commands applied later than their simulated effective time (they arrived late in wall clock)."""
    skipped_packets: np.ndarray
    """[N] sensor packets never answered: the agent was busy and answered a newer one, or it died."""
    ignored_replies: np.ndarray
    """[N] replies that came after the vehicle had entered its failsafe or left the swarm."""
    malformed: int
    """Messages the simulator dropped in validation (never acted on)."""
    malformed_reasons: dict[str, int]
    """How many dropped messages per reason ("not JSON", "wrong wire version", ...)."""
    events: list[dict]
    """Faults and state changes in order: {"step", "t" (sim s), "uav", "event", "detail"}."""
    control_tick_s: float
    """The control tick at which setpoints take effect (s)."""
    startup_s: float
    """Wall time from binding the socket until every agent was ready (process start, imports, policy)."""
    loop_wall_s: float
    """Wall time of the episode loop (after startup)."""
    sim_s: float
    """Simulated time flown (s)."""
    agents: list[dict] = field(default_factory=list)
    """Per UAV: {"uav", "policy", "pid", "host", "local"} as announced in its hello."""

    @property
    def real_time_factor(self) -> float:
        """Simulated seconds per wall second of the episode loop."""
        return self.sim_s / self.loop_wall_s if self.loop_wall_s > 0 else float("nan")

    def summary(self) -> dict:
        """JSON-ready: p50/p99/max/count of each timing over all agents and per agent, counters, events."""
        timings = {}
        for name in ("decision_latency_ms", "round_trip_ms", "command_age_ms"):
            per_agent = getattr(self, name)
            pooled = np.concatenate(per_agent) if per_agent else np.zeros(0)
            timings[name] = {
                "all": _percentiles(pooled),
                "per_uav": [_percentiles(v) for v in per_agent],
                "histogram": _histogram(pooled),
            }
        return {
            **timings,
            "late_commands": self.late_commands.tolist(),
            "skipped_packets": self.skipped_packets.tolist(),
            "ignored_replies": self.ignored_replies.tolist(),
            "malformed": self.malformed,
            "malformed_reasons": dict(self.malformed_reasons),
            "events": list(self.events),
            "control_tick_s": self.control_tick_s,
            "startup_s": self.startup_s,
            "loop_wall_s": self.loop_wall_s,
            "sim_s": self.sim_s,
            "real_time_factor": self.real_time_factor,
            "agents": list(self.agents),
        }


@dataclass
class DropoutReport:
    """What happened around an agent dropout (the paper's Fig. 4b experiment)."""

    uavs: list[int]
    """The UAVs that left the swarm."""
    step: int
    """The decision step at which they left (before that step's decision)."""
    phases: dict[str, dict]
    """"before" (steps [0, step)) and "after" (steps [step, end)): {"F", "N" (steps), "C" (% of the
    remaining agents' agent-steps), "steps", "group_size"}."""
    hd_error: np.ndarray
    """[T] the flying group's Hausdorff formation error after each step (its template follows the
    group size, so it is c before the drop and c - k after)."""

    def to_dict(self) -> dict:
        return {"uavs": list(self.uavs), "step": self.step, "phases": self.phases}


@dataclass
class SitlEpisodeResult(EpisodeResult):
    """`EpisodeResult` (F, N, C over the whole episode) plus the SITL-M statistics and, with a
    dropout, the before/after report."""

    sitl: SitlStats | None = field(default=None, repr=False)
    dropout: DropoutReport | None = field(default=None, repr=False)
    mode: str = "SITL-M"
    """"SITL-M" (agents as processes) or "lock-step" (one process; dropout runs)."""

    def faults(self) -> list[str]:
        """`EpisodeResult.faults` plus every agent that exited, reported an error or failed safe
        without being asked to (`unrequested_faults`)."""
        return super().faults() + (unrequested_faults(self.sitl.events) if self.sitl is not None else [])

    def to_dict(self) -> dict:
        skip = ("record", "spec", "sitl", "dropout")
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in skip}
        out.update(dataclasses.asdict(self.spec))
        base = self.spec.condition
        if self.mode == "SITL-M":
            out["condition"] = "SITL-M" if base == "SITL-S" else f"SITL-M+{base}"
        else:
            out["condition"] = base
        if self.sitl is not None:
            out["sitl"] = self.sitl.summary()
        if self.dropout is not None:
            out["dropout"] = self.dropout.to_dict()
        out["faults"] = self.faults()
        return out
