"""The high level: the hierarchical game (cefc_mj/hierarchy.py) and its trainer (cefc_mj/train/highlevel.py).

Real particle worlds, the shipped low-level policies, real torch updates and real run folders; the
runs are tiny (2 envs, 5 decisions per episode) so the file stays well under a minute on one core.
"""

import csv
import hashlib
import json
import shutil

import numpy as np
import pytest
import torch

from cefc_mj import paths
from cefc_mj.cli.train import main
from cefc_mj.env import BatchedCEFCEnv
from cefc_mj.errors import CefcError, CheckpointError, ConfigError
from cefc_mj.hierarchy import HierarchicalCEFCEnv, NavigationOnly, PerGroupPolicies, load_low_level
from cefc_mj.nn.highlevel_policy import load_highlevel_policy
from cefc_mj.nn.registry import GAME_ADVERSARY
from cefc_mj.task.config import TaskConfig
from cefc_mj.task.observation import build_low_level_observation
from cefc_mj.train.config import Budget, PPOConfig
from cefc_mj.train.highlevel_config import HighLevelConfig
from cefc_mj.train.highlevel_trainer import HighLevelTrainer

TASK = TaskConfig(n_agents=8, mode="cefc", obstacle_density=0.03)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def tiny_config(variant="consmac-a", **overrides) -> HighLevelConfig:
    """2 envs, 50-step episodes (5 decisions), 2 PPO epochs, a few ConsMAC steps."""
    ppo = PPOConfig(n_envs=2, epochs=2, minibatches=2, lr=1e-4, entropy_coef=0.01, update_threads=1)
    settings = dict(
        budget=Budget(iterations=2),
        variant=variant,
        episode_steps=50,
        consmac_steps=4,
        consmac_batch=64,
        ppo=ppo,
        eval_episodes=0,
    )
    settings.update(overrides)
    return HighLevelConfig(**settings)


def make_trainer(cfg: HighLevelConfig) -> HighLevelTrainer:
    task = cfg.task()
    return HighLevelTrainer(cfg, (load_low_level("navigation", task), load_low_level(cfg.low_level, task)))


# ---------------------------------------------------------------------------- the hierarchical game
def test_shapes_anchor_decoding_and_a_400_step_episode_of_40_decisions():
    env = HierarchicalCEFCEnv(TASK, NavigationOnly.for_task(TASK), n_envs=2, seed=0)
    obs = env.reset()
    assert obs.shape == (2, 8, 69) and env.decision_steps == 40 and env.n_anchors == 9
    assert env.global_state().shape == (2, env.state_size)
    # index = 3 ix + iy over the absolute arena points {-8, 0, 8}^2
    index = np.array([[0, 1, 2, 3, 4, 5, 6, 8], [8, 7, 6, 5, 4, 3, 2, 0]])
    expected = np.array([[-8, -8], [-8, 0], [-8, 8], [0, -8], [0, 0], [0, 8], [8, -8], [8, 8]], dtype=float)
    np.testing.assert_array_equal(env.decode(index)[0], expected)
    for bad in (np.zeros((2, 7), int), np.full((2, 8), 9), np.full((2, 8), -1), np.zeros((2, 8))):
        with pytest.raises(ConfigError, match="anchor_index"):
            env.decode(bad)
    for k in range(1, 41):
        obs, reward, done, info = env.step(index)
        assert (env.env.t == 10 * k).all() and info["low_level_steps"] == 10
        assert info["low_level_rewards"].shape == (10, 2) and reward.shape == (2,)
        assert done.all() == (k == 40) and ("metrics" in info) == (k == 40)
        np.testing.assert_array_equal(info["anchors"], env.decode(index))
    assert set(info["metrics"]) == {"F", "N", "C", "E", "E_agents"}
    with pytest.raises(ConfigError, match="finished episode"):
        env.step(index)
    # Each agent's low-level observation points at its own anchor, from its perceived position.
    low = env.low_level_observation()
    assert low.shape == (2, 8, 63)
    np.testing.assert_allclose(low[..., :2], env.decode(index) - env.env.perceived_pos, atol=1e-5)
    # The navigation-only low level flew there: every agent within 1.5 m of its anchor.
    assert (np.linalg.norm(env.world.agent_pos - env.decode(index), axis=-1) < 1.5).all()
    env.reset()
    assert (env.env.t == 0).all()
    with pytest.raises(ConfigError, match="multiple"):
        HierarchicalCEFCEnv(TaskConfig(n_agents=8, mode="cefc", episode_steps=45), NavigationOnly.for_task(TASK))
    # The observations do not grow with N (the 7 nearest neighbours within 3 m): the student flies
    # a 12-UAV game and the CEFC observation keeps its 69 numbers; a low level for other K is refused.
    task12 = TaskConfig(n_agents=12, mode="cefc")
    big = HierarchicalCEFCEnv(task12, load_low_level("atm_student", task12), n_envs=1, seed=0)
    assert big.reset().shape == (1, 12, 69) and big.low_level_observation().shape == (1, 12, 63)
    big.step(np.full((1, 12), 4))
    with pytest.raises(ConfigError, match="max_neighbours=9: the low level 'atm_student' reads 63"):
        HierarchicalCEFCEnv(TaskConfig(n_agents=8, mode="cefc", max_neighbours=9), load_low_level("atm_student", TASK))


def test_reward_is_the_envs_r_h_summed_over_ten_low_level_steps_of_the_student():
    """A twin BatchedCEFCEnv with the same seed, driven by hand with the student on the same
    per-agent observations, gives the same states; the high-level reward is its R_H summed."""
    student = load_low_level("atm_student", TASK)
    env = HierarchicalCEFCEnv(TASK, student, n_envs=2, seed=3)
    twin = BatchedCEFCEnv(TASK, n_envs=2, seed=3)
    env.reset()
    twin.reset()
    rng = np.random.default_rng(0)
    for _ in range(3):
        index = rng.integers(0, 9, (2, 8))  # groups split over several anchors
        obs, reward, done, info = env.step(index)
        anchors = env.decode(index)
        expected, terms = np.zeros(2), []
        for _ in range(10):
            low = build_low_level_observation(TASK, twin.perceived_pos, twin.world.agent_vel, anchors, twin.lidar)
            twin_obs, r, _, twin_info = twin.step(student.policy.act(low))
            expected += r
            terms.append(twin_info["reward_terms"])
        np.testing.assert_array_equal(env.world.agent_pos, twin.world.agent_pos)
        np.testing.assert_array_equal(obs, twin_obs)
        np.testing.assert_allclose(reward, expected, rtol=1e-12)
        np.testing.assert_allclose(info["low_level_rewards"].sum(0), reward, rtol=1e-12)
        w = TASK.rewards
        weighted = sum(
            w.task_weight * t["R_t"] + w.navigation_weight_high * t["R_n"] + w.evasion_weight * t["R_e"] for t in terms
        )
        np.testing.assert_allclose(reward, weighted, rtol=1e-9)
        assert not done.any()


def test_a_low_level_trained_with_another_lidar_is_refused():
    # AT-M Step 1 trained with a LiDAR blind to the other UAVs; the game's LiDAR sees them.
    with pytest.raises(ConfigError, match="LiDAR that sees obstacles only"):
        load_low_level("atm_c6_step1_obstacle_lidar", TASK)
    assert load_low_level("atm_c6_step3", TASK).name == "atm_c6_step3"


def test_per_group_low_level_flies_the_teacher_of_each_group_size():
    per_group = load_low_level("per-group", TASK)
    assert isinstance(per_group, PerGroupPolicies)
    env = HierarchicalCEFCEnv(TASK, per_group, n_envs=3, seed=1)
    env.reset()
    low = env.low_level_observation()
    size = np.array([[1, 2, 3, 3, 5, 5, 5, 8], [4, 4, 4, 4, 6, 6, 6, 6], [7] * 7 + [2]])
    actions = per_group.act(low, size)
    for c in (3, 4, 5, 6, 7, 8):
        rows = np.clip(size, 3, 8) == c
        teacher = per_group.policies[c][0]
        np.testing.assert_allclose(actions[rows], teacher.act(low[rows]), rtol=1e-6)


def test_clm_per_group_low_level_flies_the_clm_policy_of_each_group_size(tmp_path):
    # the shipped CL-M policies cover c = 6..8; stand-ins for c = 3..5 (copies of c = 6) test the wiring
    for c in range(3, 9):
        for ext in (".pt", ".json"):
            shutil.copy(paths.POLICIES_DIR / f"clm_c{max(c, 6)}{ext}", tmp_path / f"clm_c{c}{ext}")
    clm = load_low_level("clm-per-group", TASK, tmp_path)
    assert clm.name == "clm-per-group" and "CL-M" in clm.describe()["kind"]
    assert set(clm.describe()["files"]) == {"3", "4", "5", "6", "7", "8"}
    obs = np.random.default_rng(0).normal(size=(1, 8, clm.obs_dim))
    size = np.array([[3, 3, 3, 7, 7, 7, 7, 7]])
    np.testing.assert_allclose(clm.act(obs, size)[0, 3:], clm.policies[7][0].act(obs[0, 3:]), rtol=1e-6)
    (tmp_path / "clm_c4.pt").unlink()
    with pytest.raises(CefcError, match="clm_c4"):
        load_low_level("clm-per-group", TASK, tmp_path)
    assert tiny_config(low_level="clm-per-group", seed=1).name == "cihrl_consmac_a_clm_seed1"
    assert tiny_config(low_level="clm-per-group", pretrain_share=0.0).name == "cihrl_consmac_a_clm_dt"


# ---------------------------------------------------------------------------- the trainer
def test_messages_arrive_one_decision_late_within_3_m_and_restart_with_each_episode():
    cfg = tiny_config(
        "tarmac", ppo=PPOConfig(n_envs=2, episodes_per_iteration=2, epochs=1, minibatches=2, update_threads=1)
    )
    trainer = make_trainer(cfg)
    ro = trainer.collect(
        HierarchicalCEFCEnv(
            trainer.task, trainer.low_levels[0], n_envs=2, seed=0, adversary_policy=trainer.adversary_policy
        )
    )
    obs, own, messages, mask, distance = ro.comm_inputs
    assert obs.shape[:3] == (10, 2, 8) and messages.shape == (10, 2, 8, 7, 64)
    for start in (0, 5):  # each episode starts silent
        assert not mask[start].any() and not own[start].any()
    assert mask[1:5].any()  # agents start within 2 m of each other: they hear each other
    assert (distance[mask] < 3.0).all() and (distance[mask] > 0).all() and not distance[~mask].any()
    with torch.no_grad():  # what an agent gets back as its own message is what it computed one decision earlier
        sent = trainer.policy.comm(*(x[2] for x in ro.comm_inputs)).message
    torch.testing.assert_close(own[3], sent)
    assert not ro.consensus.requires_grad


def test_the_rl_update_never_changes_consmac_but_reaches_tarmacs_communication():
    for variant in ("consmac-a", "tarmac"):
        trainer = make_trainer(tiny_config(variant))
        env = HierarchicalCEFCEnv(
            trainer.task, trainer.low_levels[1], n_envs=2, seed=0, adversary_policy=trainer.adversary_policy
        )
        ro = trainer.collect(env)
        comm_before = {k: v.clone() for k, v in trainer.policy.comm.state_dict().items()}
        selector_before = {k: v.clone() for k, v in trainer.policy.selector.state_dict().items()}
        # The RL loss of one minibatch: ConsMAC gets no gradient at all (stop-gradient, paper Sec. IV-C3).
        rows = slice(0, 4)
        flat = lambda x: x.reshape(-1, *x.shape[2:])[rows]  # noqa: E731
        logp, entropy = trainer.policy_terms(
            flat(ro.obs), flat(ro.consensus), tuple(flat(x) for x in ro.comm_inputs), flat(ro.actions)
        )
        (-(logp * torch.randn(logp.shape)).mean() - entropy.mean()).backward()
        comm_grads = [p.grad for p in trainer.policy.comm.parameters()]
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in trainer.policy.selector.parameters())
        if variant == "consmac-a":
            assert all(g is None for g in comm_grads)
        else:
            assert any(g is not None and g.abs().sum() > 0 for g in comm_grads)
        trainer.policy.zero_grad(set_to_none=True)
        # A whole PPO update leaves ConsMAC bit for bit as it was and moves the selector.
        trainer.update(ro)
        comm_same = all(torch.equal(v, comm_before[k]) for k, v in trainer.policy.comm.state_dict().items())
        assert comm_same == (variant == "consmac-a")
        assert not all(torch.equal(v, selector_before[k]) for k, v in trainer.policy.selector.state_dict().items())


def test_consmac_supervised_loss_falls_on_a_small_fixed_replay():
    cfg = tiny_config("consmac-o", replay_capacity=64, consmac_batch=32, consmac_lr=3e-3)
    trainer = make_trainer(cfg)
    env = HierarchicalCEFCEnv(
        trainer.task, trainer.low_levels[0], n_envs=2, seed=0, adversary_policy=trainer.adversary_policy
    )
    trainer.collect(env)  # 80 agent-decisions; the replay keeps the newest 64
    assert trainer.replay.size == 64
    data = {k: v.clone() for k, v in trainer.replay.data.items()}

    def loss_on_replay() -> float:
        with torch.no_grad():
            out = trainer.policy.comm(data["obs"], data["own"], data["messages"], data["mask"], data["distance"])
            return float(((out.estimate - data["label"]) ** 2).sum(-1).mean())

    before = loss_on_replay()
    stats = trainer.train_consmac(150)
    after = loss_on_replay()
    assert stats["consmac_steps"] == 150 and trainer.consmac_steps == 150 and trainer.consmac_rounds == 1
    assert after < 0.3 * before, (before, after)
    assert stats["consmac_loss_last"] < stats["consmac_loss_first"]


def test_a_checkpointed_trainer_continues_exactly_as_an_uninterrupted_one(tmp_path):
    cfg = tiny_config("consmac-a", pretrain_share=0.5, consmac_every=2)
    straight = make_trainer(cfg)
    for _ in range(2):
        straight.iterate()
    first = make_trainer(cfg)
    first.iterate()
    torch.save(first.state_dict(), tmp_path / "state.pt")
    resumed = make_trainer(cfg)
    resumed.load_state_dict(torch.load(tmp_path / "state.pt", weights_only=True))
    row = resumed.iterate()
    assert row["phase"] == 1 and row["consmac_steps"] == 4 and resumed.replay.size == 160
    for a, b in ((straight.policy, resumed.policy), (straight.critic, resumed.critic)):
        for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
            assert torch.equal(x, y), name
    assert torch.equal(straight.generator.get_state(), resumed.generator.get_state())


def test_a_state_saved_while_the_replay_is_refilled_before_its_next_read_leaves_the_rows_out_and_resumes_exactly(
    tmp_path,
):
    # 80 rows per iteration (2 envs x 5 decisions x 8 agents), a replay of 160 (two iterations), a
    # ConsMAC round every 3 iterations: after iteration 1 the two iterations before the round refill
    # the replay, after iteration 2 one iteration does not.
    cfg = tiny_config(
        "consmac-a", budget=Budget(iterations=4), pretrain_share=0.5, consmac_every=3, replay_capacity=160
    )

    def run(saved_at: int, force_compact: bool = False):
        first = make_trainer(cfg)
        for _ in range(saved_at):
            first.iterate()
        assert first.replay_rows_per_iteration == 80
        state = first.state_dict()
        if force_compact:  # what a wrong rule would save: the rows the next round still reads
            state["replay"] = first.replay.state_dict(keep_rows=False)
        torch.save(state, tmp_path / "state.pt")
        resumed = make_trainer(cfg)
        resumed.load_state_dict(torch.load(tmp_path / "state.pt", weights_only=True))
        rows = [resumed.iterate() for _ in range(4 - saved_at)]
        return state, resumed, rows

    straight = make_trainer(cfg)
    straight_rows = [straight.iterate() for _ in range(4)]

    def same_as_straight(trainer, rows) -> bool:
        weights = all(
            torch.equal(x, y)
            for a, b in ((straight.policy, trainer.policy), (straight.critic, trainer.critic))
            for x, y in zip(a.state_dict().values(), b.state_dict().values())
        )
        losses = np.array_equal(  # NaN between rounds
            [r["consmac_loss"] for r in rows], [r["consmac_loss"] for r in straight_rows[-len(rows) :]], equal_nan=True
        )
        return weights and losses and torch.equal(straight.generator.get_state(), trainer.generator.get_state())

    state, resumed, rows = run(1)
    assert state["replay"]["size"] == 0 and all(len(v) == 0 for v in state["replay"]["data"].values())
    assert rows[1]["consmac_steps"] == 4 and resumed.replay.size == 160 and same_as_straight(resumed, rows)
    state, resumed, rows = run(2)
    assert state["replay"]["size"] == 160 and same_as_straight(resumed, rows)
    _, resumed, rows = run(2, force_compact=True)  # the check above can fail: rows left out too early
    assert not same_as_straight(resumed, rows)
    # The final state keeps its rows: a finished run's re-export reads the newest of them.
    assert straight.state_dict()["replay"]["size"] == 160


# ---------------------------------------------------------------------------- the command line
TINY = [
    "highlevel",
    "--envs",
    "2",
    "--epochs",
    "2",
    "--minibatches",
    "2",
    "--episode-steps",
    "50",
    "--consmac-steps",
    "3",
    "--consmac-batch",
    "32",
    "--pretrain-share",
    "0.5",
    "--eval-episodes",
    "1",
    "--threads",
    "1",
    "--no-progress",
]


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def usage_error(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    assert err.count("\n") == 1 and err.startswith("cefc-train"), err
    return err.strip()


def test_cli_trains_exports_and_resumes_a_run(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    shipped = {p.name: digest(p) for p in paths.POLICIES_DIR.iterdir() if p.is_file()}
    main_ok(TINY + ["--budget", "2"])
    run = tmp_path / "runs" / "highlevel" / "cihrl_consmac_a"
    policy = tmp_path / "runs" / "highlevel" / "policies" / "cihrl_consmac_a.pt"
    assert {p.name for p in run.iterdir()} >= {"config.json", "progress.csv", "state.pt", "tb"}
    config = json.loads((run / "config.json").read_text())
    assert config["highlevel"]["variant"] == "consmac-a" and config["low_level"]["finetune"]["name"] == "atm_student"
    card = json.loads(policy.with_suffix(".json").read_text())
    assert card["iterations"] == 2 and card["episodes"] == 4 and card["config"]["consmac_steps"] == 3
    assert [p["iterations"] for p in card["phases"]] == [1, 1]
    assert [p["low_level"] for p in card["phases"]] == ["navigation", "atm_student"]
    assert card["consmac_training"]["steps"] == 6 and card["consmac_training"]["paper"]["steps"] == 5000
    assert config["highlevel"]["schedule"] == "short" and card["schedule"]["name"] == "short"
    assert card["schedule"]["consmac_steps"] == 200 and not card["schedule"]["fixed"]
    fit = card["consmac_training"]["label_fit"]  # the newest iteration's rows: 2 envs x 5 decisions x 8 agents
    assert (
        fit["rows"] == 2 * 5 * 8
        and fit["loss"] > 0
        and fit["explained"] == pytest.approx(1 - fit["loss"] / fit["mean_guess_loss"])
    )
    assert card["low_level"]["finetune"]["file"]["sha256"] == digest(paths.POLICIES_DIR / "atm_student.pt")
    assert set(card["evaluation"]["ours"]) == {"R_H", "R_t", "R_n", "R_e", "E", "E_agents", "F", "C"}
    loaded, meta = load_highlevel_policy(policy)
    assert meta["iterations"] == 2 and loaded.comm is not None
    with open(run / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["phase"] for r in rows] == ["0", "1"] and rows[1]["low_level"] == "atm_student"

    # wo-FT: the weights when pre-training ended, exported beside the fine-tuned policy. They are
    # those of a run that stops there (same seed, budget 1 = one pre-training iteration).
    wo_ft = policy.with_name("cihrl_consmac_a_wo_ft.pt")
    card_wo_ft = json.loads(wo_ft.with_suffix(".json").read_text())
    assert card_wo_ft["iterations"] == 1 and [p["phase"] for p in card_wo_ft["phases"]] == ["pretrain"]
    assert "wo-FT" in card_wo_ft["method"] and set(card_wo_ft["evaluation"]["ours"]) == set(card["evaluation"]["ours"])
    main_ok(TINY + ["--budget", "1", "--out", "one"])
    assert not (tmp_path / "one" / "policies" / "cihrl_consmac_a_wo_ft.pt").exists()  # no fine-tuning, no wo-FT
    stopped, _ = load_highlevel_policy(tmp_path / "one" / "policies" / "cihrl_consmac_a.pt")
    snapshot, _ = load_highlevel_policy(wo_ft)
    assert all(torch.equal(a, b) for a, b in zip(stopped.state_dict().values(), snapshot.state_dict().values()))
    assert not all(torch.equal(a, b) for a, b in zip(loaded.state_dict().values(), snapshot.state_dict().values()))

    # A second start without --resume refuses; --resume extends the run to 3 iterations (the larger
    # budget moves the pre-training boundary to 2 iterations, but a run never goes back to pre-training).
    assert "already holds a run" in usage_error(TINY + ["--budget", "3"], capsys)
    main_ok(TINY + ["--budget", "3", "--resume"])
    with open(run / "progress.csv", newline="") as f:
        assert [(r["iteration"], r["phase"]) for r in csv.DictReader(f)] == [("1", "0"), ("2", "1"), ("3", "1")]
    card = json.loads(policy.with_suffix(".json").read_text())
    assert card["iterations"] == 3 and [p["iterations"] for p in card["phases"]] == [1, 2]
    assert card["consmac_training"]["rounds"] == 3
    assert "different settings (consmac_steps)" in usage_error(
        [a if a != "3" else "4" for a in TINY] + ["--budget", "4", "--resume"], capsys
    )
    assert {p.name: digest(p) for p in paths.POLICIES_DIR.iterdir() if p.is_file()} == shipped


def main_ok(argv) -> None:
    assert main(argv) == 0


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["--budget", "0"], "--budget '0'"),
        (["--variant", "consmac"], "invalid choice"),
        (["--consmac-steps", "0"], "--consmac-steps 0"),
        (["--consmac-lr", "nan"], "--consmac-lr nan"),
        (["--density", "0.5"], "--density 0.5"),
        (["--pretrain-share", "1.5"], "--pretrain-share 1.5"),
        (["--episode-steps", "45"], "--episode-steps 45: must be a multiple"),
        (["--envs", "1", "--episode-steps", "50", "--minibatches", "8"], "--minibatches 8: must be at most the 5"),
        (["--low-level", "no_such_policy"], "--low-level: no policy 'no_such_policy'"),
        (["--low-level", "navigation"], "--low-level 'navigation'"),
        (["--replay", "0"], "--replay 0"),
        (["--policies-dir", str(paths.POLICIES_DIR)], "written only with --install"),
        (["--resume"], "--resume: no run to continue"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line_and_writes_nothing(argv, needle, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert needle in usage_error(["highlevel", "--budget", "1", *argv], capsys)
    assert not any(tmp_path.iterdir())


def test_cli_install_copies_the_policy_and_card_into_the_shipped_folder(tmp_path, monkeypatch, capsys):
    """--install is the one way into policies/; here policies/ is a stand-in folder."""
    monkeypatch.chdir(tmp_path)
    fake_shipped = tmp_path / "shipped"
    fake_shipped.mkdir()
    for name in ("atm_student.pt", f"{GAME_ADVERSARY}.pt"):  # the game's low level and adversary
        (fake_shipped / name).write_bytes((paths.POLICIES_DIR / name).read_bytes())
    monkeypatch.setattr(paths, "POLICIES_DIR", fake_shipped)
    main_ok(TINY + ["--budget", "1", "--variant", "mappo", "--eval-episodes", "0", "--install"])
    assert "installed cihrl_mappo" in capsys.readouterr().out
    exported = tmp_path / "runs" / "highlevel" / "policies"
    for name in ("cihrl_mappo.pt", "cihrl_mappo.json"):
        assert (fake_shipped / name).read_bytes() == (exported / name).read_bytes()
    policy, _ = load_highlevel_policy(fake_shipped / "cihrl_mappo.pt")
    assert policy.comm is None and policy.selector.cfg.consensus_dim == 0
    card = json.loads((fake_shipped / "cihrl_mappo.json").read_text())
    assert card["consmac_training"] is None and "evaluation" not in card
    # A policy file whose weights were edited fails to load, with one line.
    payload = torch.load(fake_shipped / "cihrl_mappo.pt", weights_only=True)
    next(iter(payload["state_dict"].values())).add_(1.0)
    torch.save(payload, tmp_path / "edited.pt")
    with pytest.raises(CheckpointError, match="SHA-256"):
        load_highlevel_policy(tmp_path / "edited.pt")


def test_trains_against_a_trained_adversary_named_by_the_config():
    """--adversary adversary_ppo: the envs fly the shipped PPO adversary (not the rule), and the
    run records which file it was."""
    cfg = tiny_config("mappo", adversary="adversary_ppo")
    trainer = make_trainer(cfg)
    assert trainer.task.adversary == "learned" and trainer.adversary_record["policy"] == "adversary_ppo.pt"
    row = trainer.iterate()
    assert np.isfinite(row["episode_return"])
    env = trainer.envs[trainer.progress["phase"]]
    assert env.env.adversary_policy is trainer.adversary_policy
    with pytest.raises(ConfigError, match="adversary='learned'"):
        tiny_config("mappo", adversary="learned")
