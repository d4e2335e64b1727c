"""SITL-M: every UAV's policy in its own OS process, talking to the simulator over ZeroMQ.

- `run_sitl_episode(spec, SitlConfig(...))`: one episode, the world and task core here, the agents
  as processes (local, or on other machines with `cefc-agent --connect tcp://HOST:PORT --uav I`).
- `run_dropout_episode(spec, (k, step))`: the lock-step agent-dropout run (Fig. 4b), both backends.
- `run_sitl_game(GameSpec(...), SitlConfig(...))`: the CI-HRL game (Table V) with every UAV's whole
  hierarchy in its own process (`cefc-agent --game`) and the ConsMAC messages over the transport.
- `cefc_mj.deploy.agent`: the agent process; `cefc_mj.deploy.wire`: the message format.

docs/sitl_m.md describes SITL-M and its faults, docs/research/sitl_m.md the timing model and wire
format. The names below are imported on first use, so that an agent process
(`python -m cefc_mj.deploy.agent`) checks its command line before it pays for torch.
"""

import importlib

_EXPORTS = {
    "AgentError": "cefc_mj.deploy.sim_server",
    "AgentFault": "cefc_mj.deploy.episode",
    "DropoutCEFCEnv": "cefc_mj.deploy.dropout",
    "DropoutReport": "cefc_mj.deploy.results",
    "MavlinkLink": "cefc_mj.deploy.mavlink_link",
    "MavlinkLinkConfig": "cefc_mj.deploy.mavlink_link",
    "SitlConfig": "cefc_mj.deploy.episode",
    "SitlEpisodeResult": "cefc_mj.deploy.results",
    "SitlGameResult": "cefc_mj.deploy.game",
    "SitlStats": "cefc_mj.deploy.results",
    "choose_dropouts": "cefc_mj.deploy.dropout",
    "parse_drop": "cefc_mj.deploy.dropout",
    "run_dropout_episode": "cefc_mj.deploy.dropout",
    "run_latency_model_episode": "cefc_mj.deploy.episode",
    "run_sitl_episode": "cefc_mj.deploy.episode",
    "run_sitl_game": "cefc_mj.deploy.game",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'cefc_mj.deploy' has no attribute {name!r}")
