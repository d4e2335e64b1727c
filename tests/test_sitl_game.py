"""The CI-HRL game over SITL-M (docs/sitl_m.md, "The game over SITL-M"): every UAV's whole
hierarchy in its own process, ConsMAC messages over the transport. Real processes and sockets, short
games (4 UAVs, 40-60 low-level steps) on the particle world."""

from __future__ import annotations

import functools
import json
import os
import struct
import sys
import time

import numpy as np
import psutil
import pytest

from cefc_mj.deploy import wire
from cefc_mj.deploy.episode import AgentFault, SitlConfig
from cefc_mj.deploy.game import GameServer, game_sensor_packets, run_sitl_game
from cefc_mj.errors import ConfigError
from cefc_mj.eval.conditions import Conditions
from cefc_mj.eval.highlevel_sitl import GameSpec, play_game
from cefc_mj.game_protocol import game_task
from cefc_mj.hierarchy import agent_cefc_observation, agent_inbox
from cefc_mj.task.messages import MessageChannel

pytestmark = pytest.mark.skipif(
    not os.path.exists(os.path.join(os.path.dirname(os.path.dirname(__file__)), "policies", "cihrl_consmac_a.pt")),
    reason="needs the shipped cihrl_consmac_a policy",
)
D = 64


def _gone(pid: int) -> bool:
    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


@pytest.fixture(autouse=True)
def no_orphans():
    """No process started by a test may outlive it."""
    yield
    deadline = time.monotonic() + 5.0
    children = psutil.Process().children(recursive=True)
    while time.monotonic() < deadline and not all(_gone(c.pid) for c in children):
        time.sleep(0.05)
    assert [c.pid for c in children if not _gone(c.pid)] == []


def _message_frame(uav=2, seq=3, dim=D, anchor=4, latency=0.5, values=None) -> bytes:
    body = np.arange(dim, dtype=np.float32) / 10 if values is None else values
    return wire.encode(
        {"type": "message", "seq": seq, "uav": uav, "latency_ms": latency, "anchor": anchor, "message": body}
    )


def _inbox_frame(rows, seq=3, dim=D) -> bytes:
    return wire.encode({"type": "inbox", "seq": seq, "dim": dim, "rows": rows})


def _rejects(frame: bytes, schema, check=None) -> str:
    try:
        message = wire.decode(frame, schema)
        if check is not None:
            check(message)
    except wire.WireError as e:
        return str(e)
    raise AssertionError("accepted a bad frame")


def test_game_frames_round_trip_and_garbage_is_refused():
    good = _message_frame()
    assert len(good) == 12 + 16 + 4 * D  # 284 bytes: header, latency and anchor, 64 float32
    m = wire.decode(good, wire.AGENT_TO_SIM)
    assert (m["type"], m["uav"], m["seq"], m["anchor"]) == ("message", 2, 3, 4)
    assert (m["message"] == np.arange(D, dtype=np.float32) / 10).all()  # float32 bit for bit
    rows = [(1, 0.5, np.ones(D, dtype=np.float32)), (3, 2.9, np.full(D, -2.0, dtype=np.float32))]
    box = wire.decode(_inbox_frame(rows), wire.SIM_TO_AGENT)
    assert box["sender"].tolist() == [1, 3] and box["distance"].tolist() == [0.5, 2.9]
    assert (box["messages"][1] == -2.0).all()
    assert len(_inbox_frame(rows)) == 12 + 2 * (16 + 4 * D)

    # the agent's message, as the simulator checks it
    def sim_check(msg):
        wire.check_message(msg, D, 9)

    assert _rejects(good[:-3], wire.AGENT_TO_SIM) == "binary frame: wrong length"  # truncated
    assert _rejects(good + b"\0" * 4, wire.AGENT_TO_SIM) == "binary frame: wrong length"  # too long
    assert _rejects(good[:2] + bytes([9]) + good[3:], wire.AGENT_TO_SIM) == "wrong wire version"
    nan = good[:-4] + struct.pack("<f", float("nan"))
    assert _rejects(nan, wire.AGENT_TO_SIM) == "not a finite number"
    assert _rejects(_message_frame(dim=32), wire.AGENT_TO_SIM, sim_check) == "message: wrong size"
    assert _rejects(_message_frame(anchor=9), wire.AGENT_TO_SIM, sim_check) == "message: anchor out of range"
    assert _rejects(b'{"v": 2, "type": "message", "uav": 1}', wire.AGENT_TO_SIM) == "binary-only message type as JSON"
    assert _rejects(good, wire.SIM_TO_AGENT) == "unknown message type"  # the wrong direction

    # an inbox, as the agent of UAV 0 in a game of 4 checks it
    def agent_check(msg):
        wire.check_inbox(msg, D, 4, 0, 3.0)

    one = np.zeros(D, dtype=np.float32)
    assert _rejects(_inbox_frame([(0, 1.0, one)]), wire.SIM_TO_AGENT, agent_check) == "inbox: bad sender ids"
    assert _rejects(_inbox_frame([(4, 1.0, one)]), wire.SIM_TO_AGENT, agent_check) == "inbox: bad sender ids"
    dup = [(1, 1.0, one), (1, 2.0, one)]
    assert _rejects(_inbox_frame(dup), wire.SIM_TO_AGENT, agent_check) == "inbox: bad sender ids"
    assert _rejects(_inbox_frame([(1, 3.5, one)]), wire.SIM_TO_AGENT, agent_check) == "inbox: sender out of radio range"
    assert _rejects(_inbox_frame([(1, 1.0, one)] * 4), wire.SIM_TO_AGENT, agent_check) == "inbox: too many rows"
    assert _rejects(_inbox_frame([(1, 1.0, one[:32])], dim=32), wire.SIM_TO_AGENT, agent_check) == (
        "inbox: wrong message size"
    )
    frame = _inbox_frame([(1, 1.0, one)])
    assert _rejects(frame[:-1], wire.SIM_TO_AGENT) == "binary frame: wrong length"
    assert _rejects(frame[:-4] + struct.pack("<f", float("inf")), wire.SIM_TO_AGENT) == "not a finite number"
    with pytest.raises(ValueError):  # nobody sends NaN either
        _message_frame(values=np.full(D, np.nan, dtype=np.float32))


def test_simulator_drops_and_counts_garbage_and_spoofed_senders():
    import zmq

    server = GameServer(
        "tcp://127.0.0.1:*",
        4,
        {"formation": 4, "task": {}, "heartbeat_timeout_s": 5.0},
        0.1,
        message_dim=D,
        n_anchors=9,
        comm_range=3.0,
        decision_interval=10,
        dt=0.1,
    )
    context = zmq.Context()
    socks = []
    try:
        for uav in (1, 2):  # two registered connections
            sock = context.socket(zmq.DEALER)
            sock.setsockopt(zmq.LINGER, 0)
            sock.connect(server.local_endpoint)
            socks.append(sock)
            sock.send(wire.encode({"v": 2, "type": "hello", "uav": uav, "policy": "x", "pid": 1, "host": "h"}))
        deadline = time.monotonic() + 5
        while not all(server.vehicles[u].identity for u in (1, 2)) and time.monotonic() < deadline:
            server.receive(0.05)
        for u in (1, 2):
            server.vehicles[u].state = "flying"
        server.decision, server.decision_wall[0] = 0, time.perf_counter()
        garbage = [
            _message_frame(uav=2, seq=0),  # UAV 1's connection claims to be UAV 2
            _message_frame(uav=1, seq=0)[:-5],  # truncated
            _message_frame(uav=1, seq=0)[:2] + b"\x07" + _message_frame(uav=1, seq=0)[3:],  # version
            _message_frame(uav=1, seq=0)[:-4] + struct.pack("<f", float("nan")),  # NaN
            _message_frame(uav=1, seq=5),  # a decision never opened
            _message_frame(uav=1, seq=0, dim=8),  # wrong size
            os.urandom(300),
        ]
        for frame in garbage:
            socks[0].send(frame)
        socks[0].send(_message_frame(uav=1, seq=0))  # and one good message
        socks[1].send(_message_frame(uav=2, seq=0, anchor=7))
        deadline = time.monotonic() + 5
        while (server.malformed < len(garbage) or len(server.arrived) < 2) and time.monotonic() < deadline:
            server.receive(0.05)
        assert server.malformed == len(garbage), server.malformed_reasons
        assert server.malformed_reasons["uav does not match the sender"] == 1
        assert sorted(server.arrived) == [1, 2] and server.arrived[2]["anchor"] == 7
    finally:
        for sock in socks:
            sock.close(0)
        context.term()
        server.close()


def test_delivery_is_the_message_channels_range_and_one_decision_delay():
    """The simulator's inboxes, through the wire and rebuilt by the agent, are the in-process
    channel's inbox rows for the same positions and messages: range 3 m by true distance, one
    decision late, a missing message an absent neighbour."""
    n = 4
    server = GameServer(
        "tcp://127.0.0.1:*",
        n,
        {},
        0.1,
        message_dim=D,
        n_anchors=9,
        comm_range=3.0,
        decision_interval=10,
        dt=0.1,
    )
    sent_frames: list[tuple[int, bytes]] = []
    server._send = lambda v, message: sent_frames.append((v.index, wire.encode({"v": 2, **message})))
    reference = MessageChannel(1, n, D, 3.0)
    rng = np.random.default_rng(0)
    try:
        for v in server.vehicles:
            v.state = "flying"
        own = np.zeros((n, D), dtype=np.float32)
        for d in range(4):
            pos = rng.uniform(-2.5, 2.5, size=(n, 2))
            pos[3] = [40.0, 40.0] if d == 2 else pos[3]  # out of everyone's range at decision 2
            server.decision_wall[max(d - 1, 0)] = time.perf_counter() - 10.0  # no waiting
            sent_frames.clear()
            server.open_decision(d, pos)
            ref = reference.receive(pos[None])
            for i, frame in sent_frames:
                box = wire.decode(frame, wire.SIM_TO_AGENT)
                wire.check_inbox(box, D, n, i, 3.0)
                assert box["seq"] == d
                mine = agent_inbox(own[i], box["sender"], box["distance"], box["messages"], n - 1)
                for name in ("messages", "mask", "distance", "sender", "received"):
                    assert (getattr(mine, name)[0, 0] == getattr(ref, name)[0, i]).all(), (d, i, name)
                assert (mine.own[0, 0] == ref.own[0, i]).all()
            assert sorted(i for i, _ in sent_frames) == list(range(n))
            # this decision's messages; UAV 1's never arrives at decision 1
            messages = rng.normal(size=(n, D)).astype(np.float32)
            sent = np.array([True, d != 1, True, True])
            for i in range(n):
                if sent[i]:
                    server.arrived[i] = {"message": messages[i], "anchor": 4}
                own[i] = messages[i] if sent[i] else 0.0
            reference.send(messages[None], sent[None])
        assert server.missing_messages.tolist() == [0, 1, 0, 0]
    finally:
        server.close()


def test_agent_builds_the_lockstep_cefc_observation_from_its_packet():
    from cefc_mj.env import BatchedCEFCEnv

    task = game_task("nearest_group", n_agents=6)
    env = BatchedCEFCEnv(task, n_envs=1, seed=3)
    obs = env.reset(seed=3)
    for _ in range(3):
        packets = game_sensor_packets(0, 0.0, env, task.observation_distance, np.ones(6, bool), list(range(6)))
        for i, p in enumerate(packets):
            p = wire.decode(wire.encode({"v": 2, **p}), wire.SIM_TO_AGENT)  # over the wire
            mine = agent_cefc_observation(
                task,
                [*p["pos"], *p["vel"]],
                sorted(p["neighbours"]),
                p["targets"],
                [*p["adversary_pos"], *p["adversary_vel"]],
                p["lidar"],
            )
            assert (mine == obs[0, i]).all()
        obs, *_ = env.step(np.random.default_rng(0).uniform(-2, 2, size=(1, 6, 2)))


def test_sitl_game_over_the_wire_is_the_lockstep_game_and_async_stays_close(tmp_path):
    spec = GameSpec(seed=2, steps=40, n_agents=4, where=Conditions("particle"))
    reference = play_game(spec)
    wired = run_sitl_game(spec, SitlConfig(lockstep=True))
    assert wired.figures == reference  # the whole game, every message through the sockets, bit for bit
    assert wired.sitl["malformed"] == 0 and sum(wired.sitl["messages_delivered"]) > 0
    live = run_sitl_game(spec, SitlConfig())  # asynchronous: commands take effect one tick later
    assert live.steps == 40 and live.sitl["late_messages"] == [0] * 4
    for m in ("R_H", "R_n"):
        assert abs(live.figures[m] - reference[m]) <= 0.25 * abs(reference[m]) + 1.0, (m, live.figures, reference)
    assert abs(live.figures["E"] - reference["E"]) <= 20
    s = live.sitl
    assert s["high_latency_ms"]["count"] == 4 * 4 and s["low_latency_ms"]["count"] == 4 * 40
    assert s["bytes_per_s_by_kind_per_uav"]["up:message"] == pytest.approx(284 / 1.0)  # one per 1 s decision
    (tmp_path / "game.json").write_text(json.dumps(live.to_dict(), default=float))


def test_lockstep_with_a_fixed_delay_is_deterministic_and_delays_every_command_one_tick():
    """SitlConfig(lockstep=True, lockstep_delay_s=0.01): quadrotors at the 0.01 s control tick, every
    command in force from one tick after its packet, the same figures on every run."""
    spec = GameSpec(seed=4, steps=40, n_agents=4, where=Conditions("mujoco"))
    sitl = SitlConfig(lockstep=True, lockstep_delay_s=0.01)
    first, second = run_sitl_game(spec, sitl), run_sitl_game(spec, sitl)
    assert first.figures == second.figures
    age = first.sitl["command_age_ms"]
    assert age["p50"] == age["max"] == 10.0 and sum(first.sitl["late_commands"]) == 0
    assert first.figures != play_game(spec)  # the tick of delay changes the flight
    with pytest.raises(ConfigError, match="lockstep_delay_s"):
        run_sitl_game(spec, SitlConfig(lockstep_delay_s=0.01))
    with pytest.raises(ConfigError, match="lockstep_delay_s"):
        run_sitl_game(spec, SitlConfig(lockstep=True, lockstep_delay_s=-1.0))


def test_killed_agent_holds_its_messages_stop_and_the_game_goes_on(tmp_path):
    spec = GameSpec(seed=1, steps=60, n_agents=4, where=Conditions("particle"))
    result = run_sitl_game(spec, SitlConfig(faults=(AgentFault(1, 12, "kill"),)))
    s = result.sitl
    events = [(e["uav"], e["event"]) for e in s["events"]]
    assert (1, "fault_kill") in events and (1, "agent_exited") in events and (1, "offboard_loss_hold") in events
    assert result.steps == 60 and s["final_states"] == ["flying", "failsafe", "flying", "flying"]
    assert s["final_speed"][1] < 0.05  # its vehicle holds
    assert all(a[1] == -1 for a in result.anchors[2:])  # no message from UAV 1 after decision 1
    assert all(a[i] >= 0 for a in result.anchors for i in (0, 2, 3))  # the others keep deciding
    path = tmp_path / "killed.json"
    path.write_text(json.dumps(result.to_dict(), default=float))
    assert json.loads(path.read_text())["steps"] == 60
    pids = [a["pid"] for a in s["agents"]]
    assert all(_gone(p) for p in pids)


def test_cli_plays_the_sitl_game_and_writes_its_report(tmp_path, monkeypatch, capsys):
    from cefc_mj.cli.eval import main

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "game.json"
    argv = ["--backend", "particle", "--protocol", "table5", "--sitl-m", "--policy", "cihrl_consmac_a"]
    assert main([*argv, "--episodes", "1", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "SITL-M - lock-step" in text and "B/s per UAV" in text
    assert (
        "of which ConsMAC messages" in text and "message 64 floats per decision (paper's Table IV, ConsMAC: 64)" in text
    )
    result = json.loads(out.read_text())
    assert result["rows"]["cihrl_consmac_a (SITL-M)"]["variant"] == "consmac-a"
    assert set(result["rows"]) == {"cihrl_consmac_a (SITL-M)", "cihrl_consmac_a (lock-step)"}


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--protocol", "table5", "--sitl-m"], "--sitl-m: the SITL-M game plays one policy of table5"),
        (["--protocol", "table6", "--sitl-m"], "--sitl-m: --protocol table6 plays the paper's game"),
        (
            ["--protocol", "table5", "--sitl-m", "--policy", "cihrl_mappo", "--png", "figs"],
            "--png: cihrl_mappo sends no messages",
        ),
    ],
)
def test_cli_refuses_what_the_sitl_game_cannot_do(argv, needle, tmp_path, monkeypatch, capsys):
    from cefc_mj.cli.eval import main

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["--backend", "particle", *argv])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and needle in err, err


# ------------------------------------------------------------------ the recorded game (Figs. 11, 12)
_CAPTURING_AGENT = """
import sys
import numpy as np
from cefc_mj.deploy import agent

send = agent.GameAgent.send

def capture(self, message):
    if message["type"] == "message":  # the agent's own message, before it is framed
        path = f"{folder}/uav{{self.uav}}_d{{message['seq']}}.npz"
        np.savez(path, message=message["message"], anchor=message["anchor"])
    send(self, message)

agent.GameAgent.send = capture
sys.exit(agent.main())
"""


def _cosine(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a.astype(np.float64), b.astype(np.float64)
    return float(a @ b / np.linalg.norm(a) / np.linalg.norm(b))


def _png_is_a_figure(path) -> None:
    from matplotlib.image import imread

    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000
    pixels = imread(path)[..., :3]
    assert pixels.shape[0] > 300 and pixels.shape[1] > 300
    assert len(np.unique(pixels.reshape(-1, 3), axis=0)) > 50 and pixels.std() > 0.05  # drawn, not blank


def test_recorded_sitl_game_holds_the_messages_the_agents_sent(tmp_path):
    """The SITL-M game's recording: per decision every UAV's message and anchor as the simulator
    received them, equal bit for bit to what each agent process sent (captured inside the agents),
    a killed agent's missing messages NaN (never invented); the .rrd read back holds one similarity
    matrix per decision equal to the cosine similarities of the sent messages; Figs. 11 and 12 drawn."""
    from rrd_reader import read_rrd

    from cefc_mj.viz.highlevel_log import record_highlevel_episode, write_game_figures

    sent = tmp_path / "sent"
    sent.mkdir()
    command = (sys.executable, "-c", _CAPTURING_AGENT.format(folder=sent), "--game")
    spec = GameSpec(seed=1, steps=40, n_agents=4, where=Conditions("particle"))
    result = run_sitl_game(spec, SitlConfig(agent_command=command, faults=(AgentFault(1, 12, "kill"),)))
    n, k_count = 4, 4
    assert result.steps == 40 and result.sitl["late_messages"] == [0] * n
    captured = {}
    for path in sent.iterdir():
        uav, d = (int(part[1:] if part[0] == "d" else part[3:]) for part in path.stem.split("_"))
        with np.load(path) as f:
            captured[d, uav] = (f["message"], int(f["anchor"]))
    assert {(d, 1) for d in range(k_count)} & set(captured) == {(0, 1), (1, 1)}  # UAV 1 killed at step 12
    assert len(captured) == k_count * (n - 1) + 2
    messages = result.messages
    assert messages.shape == (k_count, n, D) and messages.dtype == np.float32
    assert len(result.anchors) == k_count
    for d in range(k_count):
        for i in range(n):
            if (d, i) in captured:
                message, anchor = captured[d, i]
                assert messages[d, i].tobytes() == message.astype(np.float32).tobytes(), (d, i)  # bit for bit
                assert result.anchors[d][i] == anchor
            else:
                assert np.isnan(messages[d, i]).all() and result.anchors[d][i] == -1, (d, i)

    episode = result.episode()
    assert episode.condition == "SITL-M" and episode.n_decisions == k_count and episode.agent_pos.shape == (41, n, 2)
    assert np.isnan(episode.anchors[2:, 1]).all() and np.isfinite(episode.anchors[:, [0, 2, 3]]).all()
    rrd = record_highlevel_episode(episode, tmp_path / "game.rrd")
    data = read_rrd(rrd)
    tensors = data["/messages/similarity"]["Tensor:data"]
    assert sorted(tensors) == [10 * d for d in range(k_count)]  # one matrix per decision, at its step
    for d in range(k_count):
        tensor = tensors[10 * d][0]
        assert tensor["shape"] == [n, n]
        recorded = np.array(tensor["buffer"], dtype=np.float64).reshape(n, n)
        expected = np.full((n, n), np.nan)
        for i in range(n):
            for j in range(n):
                if (d, i) in captured and (d, j) in captured:
                    expected[i, j] = _cosine(captured[d, i][0], captured[d, j][0])
        np.testing.assert_allclose(recorded, expected, atol=1e-6)  # NaN where a message is missing
    anchors = data["/world/anchors"]["Points3D:positions"]
    for d in range(k_count):
        shown = np.array(anchors[10 * d])[:, :2]
        for i in range(n):
            if (d, i) in captured:
                np.testing.assert_allclose(shown[i], episode.anchor_grid[captured[d, i][1]], atol=1e-6)
            else:
                assert np.isnan(shown[i]).all()
    np.testing.assert_allclose(np.array(data["/world/uavs"]["Points3D:positions"][25])[:, :2], episode.agent_pos[25])
    assert "no message from [1]" in data["/decisions"]["TextLog:text"][20][0]
    prov = {name: values[None][0] for name, values in data["/__properties/provenance"].items()}
    assert (prov["condition"], prov["seed"], prov["agents"], prov["R_H"]) == ("SITL-M", 1, n, result.figures["R_H"])

    figures = write_game_figures(episode, tmp_path, "game")
    assert [p.name for p in figures] == ["game_fig11.png", "game_fig12.png"]
    for path in figures:
        _png_is_a_figure(path)


def test_cli_records_the_sitl_game_of_the_seed(tmp_path, monkeypatch, capsys):
    """`cefc-eval --protocol table5 --sitl-m --policy P --rrd --png` records the SITL-M game of --seed
    (the first of the batch, as the one-process game records the game of --seed); short games here
    (8 UAVs, 40 steps instead of 400)."""
    from rrd_reader import read_rrd

    import cefc_mj.cli.eval_game as eval_game
    from cefc_mj.cli.eval import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(eval_game, "run_table5_sitl", functools.partial(eval_game.run_table5_sitl, steps=40))
    argv = ["--backend", "particle", "--protocol", "table5", "--sitl-m", "--policy", "cihrl_consmac_a"]
    out = tmp_path / "game.json"
    assert (
        main([*argv, "--episodes", "2", "--seed", "3", "--rrd", "game.rrd", "--png", "figs", "--json", str(out)]) == 0
    )
    text = capsys.readouterr().out
    assert "wrote game.rrd" in text and "cihrl_consmac_a_s3_sitl_m_fig12.png" in text
    assert "paired t-test p" in text and "fidelity: mean R_t" in text
    report = json.loads(out.read_text())
    assert report["protocol"]["seeds"] == [3, 4] and set(report["fidelity"]) >= {"R_t_met", "E_met"}
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == [
        "cihrl_consmac_a_s3_sitl_m_fig11.png",
        "cihrl_consmac_a_s3_sitl_m_fig12.png",
    ]
    data = read_rrd(tmp_path / "game.rrd")
    tensors = data["/messages/similarity"]["Tensor:data"]
    assert sorted(tensors) == [0, 10, 20, 30] and all(t[0]["shape"] == [8, 8] for t in tensors.values())
    prov = {name: values[None][0] for name, values in data["/__properties/provenance"].items()}
    assert (prov["policy"], prov["seed"], prov["condition"], prov["steps"]) == ("cihrl_consmac_a", 3, "SITL-M", 40)
    for path in (tmp_path / "figs").iterdir():
        _png_is_a_figure(path)
