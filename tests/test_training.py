"""Training: config validation, checkpoints (atomic, checked), rollouts, the curriculum loop, resume."""

from __future__ import annotations

import csv
import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from conftest import checkpoint_payload

from idas_sumo.agents.checkpoint_file import PolicyCheckpoint, load_actor
from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.layout import OBS_LAYOUT_ID
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.errors import InputError
from idas_sumo.io_utils import MANIFEST_NAME
from idas_sumo.resources import DEFAULT_TRAIN_CONFIG
from idas_sumo.training.checkpoint import load_checkpoint, save_checkpoint
from idas_sumo.training.config import TrainConfig, load_train_config
from idas_sumo.training.curriculum import plan_stages


def tiny_config(**changes: Any) -> TrainConfig:
    """Two episodes per stage, short episodes, few cars: the whole curriculum in a few seconds."""
    base = TrainConfig(
        robot_episodes=2,
        intelligent_episodes=2,
        direct_episodes=2,
        robot_traffic=TrafficConfig(
            n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=3, max_controlled=1
        ),
        intelligent_traffic=TrafficConfig(n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=2),
        episodes_per_update=1,
        checkpoint_every=1,
        env=EnvConfig(max_episode_s=12.0),
    )
    return dataclasses.replace(base, **changes)


def read_metrics(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _payload(learner: Any, /, **extra: Any) -> Any:
    return checkpoint_payload(learner, **extra)


# --- config --------------------------------------------------------------------------------------
def test_defaults_are_the_papers_and_the_shipped_toml_matches() -> None:
    c = TrainConfig()
    assert (c.robot_episodes, c.intelligent_episodes, c.direct_episodes) == (20_000, 50_000, 70_000)
    assert c.learner.alpha == 0.7 and c.learner.gamma == 0.9
    assert c.robot_traffic.max_controlled == 1
    assert load_train_config(DEFAULT_TRAIN_CONFIG) == c


def test_default_workers_are_the_cpus_per_eight_episodes_of_a_round() -> None:
    from idas_sumo.sim.processes import max_workers

    assert TrainConfig().workers == 0
    assert TrainConfig().rollout_workers() == max(1, min(max_workers(), 2))  # 16 episodes a round
    assert TrainConfig(episodes_per_update=7).rollout_workers() == 1
    assert TrainConfig().with_overrides(episodes=3).rollout_workers() == 1  # rounds of 3 episodes
    assert TrainConfig(episodes_per_update=64).rollout_workers(gui=True) == 1
    assert TrainConfig(workers=3, episodes_per_update=1).rollout_workers() == 3  # as asked


def test_bad_values_name_the_key(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="robot_episodes"):
        TrainConfig(robot_episodes=0)
    with pytest.raises(InputError, match="workers"):
        TrainConfig().with_overrides(workers=-1)
    bad = tmp_path / "bad.toml"
    bad.write_text("episodes_per_updat = 3\n")
    with pytest.raises(InputError, match=r"bad\.toml.*episodes_per_updat.*did you mean"):
        load_train_config(bad)
    bad.write_text("[learner]\nalpha = 1.5\n")
    with pytest.raises(InputError, match=r"bad\.toml.*alpha"):
        load_train_config(bad)
    bad.write_text("intelligent_episodes = -1\n")
    with pytest.raises(InputError, match=r"bad\.toml.*intelligent_episodes"):
        load_train_config(bad)


def test_episodes_override_sets_every_stage_and_stages_plan() -> None:
    c = TrainConfig().with_overrides(episodes=5, stage="curriculum")
    plans = plan_stages(c)
    assert [(p.name, p.episodes, p.central, p.init_from_previous) for p in plans] == [
        ("robot", 5, False, False),
        ("intelligent", 5, True, True),
    ]
    assert [p.name for p in plan_stages(c.with_overrides(stage="direct"))] == ["direct"]
    assert plan_stages(c.with_overrides(stage="robot"))[0].traffic.max_controlled == 1


# --- checkpoints ---------------------------------------------------------------------------------
def test_checkpoint_round_trip(tmp_path: Path) -> None:
    learner = Learner(LearnerConfig(), seed=1)
    path = tmp_path / "c.pt"
    save_checkpoint(path, _payload(learner))
    data = load_checkpoint(path)
    assert data.episode == 7 and data.obs_layout_id == OBS_LAYOUT_ID
    rng = np.random.default_rng(0)
    rng.bit_generator.state = data.numpy_rng
    assert rng.random() == np.random.default_rng(3).random()
    gen = torch.Generator()
    gen.set_state(data.torch_rng)
    assert torch.equal(
        torch.rand(3, generator=gen), torch.rand(3, generator=torch.Generator().manual_seed(3))
    )
    actor = load_actor(path).actor.state_dict()
    for k, v in learner.actor.state_dict().items():
        assert torch.equal(actor[k], v)
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]  # no temp files left


@pytest.mark.parametrize("damage", ["missing", "empty", "truncated", "text", "foreign", "layout", "nan"])
def test_bad_checkpoints_are_one_line_input_errors(tmp_path: Path, damage: str) -> None:
    path = tmp_path / "c.pt"
    learner = Learner(LearnerConfig(), seed=1)
    if damage != "missing":
        save_checkpoint(path, _payload(learner))
    if damage == "empty":
        path.write_bytes(b"")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif damage == "text":
        path.write_text("hello\n")
    elif damage == "foreign":
        torch.save({"weights": torch.zeros(3)}, path)
    elif damage == "layout":
        save_checkpoint(path, _payload(learner, obs_layout_id="scalars5-other"))
    elif damage == "nan":
        state = learner.state_dict()
        name = next(iter(state["actor"]))
        state["actor"][name] = torch.full_like(state["actor"][name], float("nan"))
        save_checkpoint(path, _payload(learner, learner=state))
    with pytest.raises(InputError) as err:
        load_checkpoint(path)
    message = str(err.value)
    assert str(path) in message and "\n" not in message


def test_crash_while_saving_keeps_the_previous_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "c.pt"
    learner = Learner(LearnerConfig(), seed=1)
    save_checkpoint(path, _payload(learner))

    def crash(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        save_checkpoint(path, _payload(learner, episode=99))
    monkeypatch.undo()
    assert load_checkpoint(path).episode == 7
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]


EARLIER_CHECKPOINT_KEYS = {
    "kind",
    "format",
    "package_version",
    "obs_layout_id",
    "learner",
    "config",
    "stage",
    "stage_index",
    "episode",
    "global_episode",
    "numpy_rng",
    "torch_rng",
}
"""The keys of a checkpoint written before checkpoints were typed (a ``<stage>_best.pt`` adds
``validation``): the file format the typed checkpoint must keep."""


def test_a_checkpoint_on_disk_is_the_flat_dict_it_always_was(tmp_path: Path) -> None:
    from idas_sumo.training.validation import ValidationScore

    learner = Learner(LearnerConfig(), seed=1)
    score = ValidationScore(joint_return=3.5, perfect_rate=0.5, success_rate=1.0, mean_end_time_s=20.0)
    save_checkpoint(tmp_path / "c.pt", _payload(learner))
    save_checkpoint(tmp_path / "best.pt", _payload(learner, validation=score))
    plain = torch.load(tmp_path / "c.pt", weights_only=True)
    best = torch.load(tmp_path / "best.pt", weights_only=True)
    # One key more than before: the checksum (older files without it still load).
    assert set(plain) == EARLIER_CHECKPOINT_KEYS | {"content_sha256"}
    assert set(best) == EARLIER_CHECKPOINT_KEYS | {"validation", "content_sha256"}
    assert best["validation"] == dataclasses.asdict(score)
    assert plain["config"] == TrainConfig().as_dict() and plain["episode"] == 7
    assert load_checkpoint(tmp_path / "best.pt").validation == score
    assert load_checkpoint(tmp_path / "c.pt").validation is None


def test_shipped_policies_still_load(tmp_path: Path) -> None:
    """The committed policies were written before checkpoints were typed: they load, and saving one
    again writes the same keys and the same weights. One trained under a retired variant still acts
    (``load_actor``); as a training checkpoint (``init_from``, ``--resume``) it is refused in one line."""
    from idas_sumo.resources import POLICY_DIR

    shipped = sorted(POLICY_DIR.glob("*.pt"))
    assert shipped, f"no policies in {POLICY_DIR}"
    for path in shipped:
        raw = torch.load(path, weights_only=True)
        load_actor(path)
        if raw["learner"]["config"].get("central_head", "per_action") != "per_action":
            with pytest.raises(InputError, match="a retired experiment variant"):
                load_checkpoint(path)
            continue
        checkpoint = load_checkpoint(path)
        assert (checkpoint.stage, checkpoint.episode) == (raw["stage"], raw["episode"])
        assert (checkpoint.validation is None) == ("validation" not in raw)
        save_checkpoint(tmp_path / path.name, checkpoint)
        again = torch.load(tmp_path / path.name, weights_only=True)
        assert set(again) == set(raw) | {"content_sha256"}  # saved again, it carries a checksum
        for net in ("actor", "value", "central"):
            for name, tensor in raw["learner"][net].items():
                assert torch.equal(again["learner"][net][name], tensor)


@pytest.mark.parametrize(
    ("change", "needle"),
    [
        ({"episode": None}, "lacks 'episode'"),
        ({"global_episode": -1}, "global_episode must be a non-negative integer, got -1"),
        ({"stage_index": True}, "stage_index must be a non-negative integer"),
        ({"stage": 3}, "stage must be a str"),
        ({"torch_rng": [1, 2]}, "torch_rng must be a Tensor"),
        ({"config": {"robot_episods": 3}}, "config: unknown key 'robot_episods'"),
        ({"config": {"robot_episodes": 0}}, "config: robot_episodes must be at least 1"),
        ({"validation": {"joint_return": 1.0}}, "validation: missing required key"),
        ({"obs_layout_id": None}, "lacks 'obs_layout_id'"),
    ],
)
def test_a_missing_or_ill_typed_value_is_one_line_naming_it(
    tmp_path: Path, change: dict[str, Any], needle: str
) -> None:
    path = tmp_path / "c.pt"
    data = _payload(Learner(LearnerConfig(), seed=1)).to_dict()
    for key, value in change.items():
        if value is None:
            del data[key]
        else:
            data[key] = value
    torch.save(data, path)
    with pytest.raises(InputError) as err:
        load_checkpoint(path)
    message = str(err.value)
    assert message.startswith(f"{path}: ") and needle in message and "\n" not in message, message


def test_evaluation_reads_only_the_policy_part(tmp_path: Path) -> None:
    """A file without the training state is a policy (``load_actor``), not a training checkpoint."""
    learner = Learner(LearnerConfig(), seed=1)
    path = tmp_path / "policy.pt"
    data = PolicyCheckpoint(learner=learner.state_dict()).to_dict()  # the policy part, its own checksum
    assert not {"config", "stage", "episode", "numpy_rng", "torch_rng"} & set(data)
    torch.save(data, path)
    actor = load_actor(path).actor.state_dict()
    assert all(torch.equal(actor[k], v) for k, v in learner.actor.state_dict().items())
    with pytest.raises(InputError, match="lacks 'config'"):
        load_checkpoint(path)


# --- rollouts and the loop (SUMO) ----------------------------------------------------------------
@pytest.mark.sumo
def test_a_wave_in_which_no_agent_acts_gives_episodes_without_rows(net_path: Path) -> None:
    """Both episodes' learning car enters after the timeout: the wave logs no step, and each episode comes back
    with no rows and nothing in its bank (it crashed on the empty collision log); and such an episode beside one
    whose car acts (it crashed linking its rows' steps)."""
    from idas_sumo.agents.rollout import RolloutTask, collect_episodes
    from idas_sumo.env.engine import MergeEngine
    from idas_sumo.env.scenario import Scenario, VehicleSpec

    engine = MergeEngine(net_path, copies=2, config=EnvConfig(max_episode_s=2.0))
    learner = Learner(LearnerConfig(), seed=0)
    scenario = Scenario(
        "late",
        (
            VehicleSpec("robot", "main", 30.0, 10.0, controlled=False),
            VehicleSpec("late", "merge", 10.0, 10.0, depart_s=5.0),
        ),
    )
    on_time = Scenario("on time", (VehicleSpec("now", "merge", 10.0, 10.0),))
    try:
        episodes = collect_episodes(engine, learner, [RolloutTask(scenario, i) for i in range(2)])
        mixed = collect_episodes(engine, learner, [RolloutTask(scenario, 0), RolloutTask(on_time, 1)])
    finally:
        engine.close()
    assert [len(e) for e in episodes] == [0, 0]
    assert all(e.obs_bank.shape == (0, e.obs_bank.shape[1]) and e.stats.collisions == 0 for e in episodes)
    assert len(mixed[0]) == 0 and len(mixed[1]) == mixed[1].stats.agent_steps > 0  # beside a wave with steps


@pytest.mark.sumo
def test_collected_batch_is_consistent_and_never_masked(net_path: Path) -> None:
    from idas_sumo.agents.rollout import RolloutTask, batch_from_episodes, collect_episodes
    from idas_sumo.env.engine import EnvConfig, MergeEngine
    from idas_sumo.env.scenario import generate_scenario

    engine = MergeEngine(net_path, copies=2, config=EnvConfig(max_episode_s=15.0))
    learner = Learner(LearnerConfig(use_central_critic=True), seed=0)
    rng = np.random.default_rng(4)
    traffic = TrafficConfig(n_vehicles=0, min_vehicles_per_road=3, max_vehicles_per_road=3)
    try:
        tasks = [RolloutTask(generate_scenario(rng, traffic, engine.speed_limits_mps), i) for i in range(2)]
        episodes = collect_episodes(engine, learner, tasks)
        short = [dataclasses.replace(t, max_episode_s=2.0) for t in tasks]  # validation's own timeout
        cut = collect_episodes(engine, learner, short)
        assert engine.config.max_episode_s == 15.0  # the engine's own limit again afterwards
        with pytest.raises(ValueError, match="share their timeout"):
            collect_episodes(engine, learner, [tasks[0], short[1]])
    finally:
        engine.close()
    assert all(e.stats.timed_out and e.stats.sim_time_s <= 2.0 + 1e-9 for e in cut)
    assert all(e.stats.sim_time_s > 2.0 for e in episodes)
    for e in episodes:
        n = len(e)
        assert n == e.stats.agent_steps > 0 and e.stats.agents == 6
        assert e.mask[np.arange(n), e.action].all()  # a masked action never reaches the batch
        valid = e.next_valid.astype(bool)
        # the next step of a row is the same agent: same slot; no successor after done
        assert not (valid & (e.done == 1)).any()
        assert (e.slot[valid] == e.next_slot[valid]).all()
        assert np.isfinite(e.obs).all() and np.isfinite(e.next_obs).all()
        no_next = ~valid & (e.done == 0)  # cut off by the timeout: bootstraps from its last observation
        assert (np.abs(e.next_obs[no_next]).sum(axis=1) > 0).all()
        every_car_finished = (
            all(r == "finished" for r in e.stats.end_reasons.values()) and e.stats.agents == 6
        )
        assert e.stats.success == (e.stats.collisions == 0 and every_car_finished)
        # Q's link past an agent's last step: the first row of the episode's next step, where the same
        # (per-step) state was recorded as at the agent's own next row; -1 only in the last step.
        team = e.team_next_row
        assert team is not None and (team[team >= 0] > np.flatnonzero(team >= 0)).all()
        assert (team[-1] == -1) and (team == -1).sum() == (e.state == e.state[-1]).all(axis=1).sum()
        own = e.next_row >= 0
        assert (e.state[team[own]] == e.state[e.next_row[own]]).all()
    batch = batch_from_episodes(episodes)
    assert batch.team_next_row is not None and len(batch.team_next_row) == len(batch.action)
    assert batch.obs.shape[0] == sum(len(e) for e in episodes)
    assert learner.update(batch)["q_loss"] > 0.0


@pytest.mark.sumo
def test_tiny_curriculum_end_to_end(net_path: Path, tmp_path: Path) -> None:
    from idas_sumo.training.loop import run_training

    run = tmp_path / "run"
    final = run_training(net_path, tiny_config(), run, progress=False)
    assert final == run / "intelligent.pt"
    for name in ("robot.pt", "intelligent.pt", "checkpoint.pt", "metrics.csv"):
        assert (run / name).is_file()
    rows = read_metrics(run)
    assert [(r["stage"], r["episode"], r["global_episode"]) for r in rows] == [
        ("robot", "0", "0"),
        ("robot", "1", "1"),
        ("intelligent", "0", "2"),
        ("intelligent", "1", "3"),
    ]
    assert {r["agents"] for r in rows if r["stage"] == "robot"} == {"1"}
    assert float(rows[-1]["q_loss"]) > 0.0 and float(rows[0]["q_loss"]) == 0.0
    ckpt = load_checkpoint(final)
    assert (ckpt.stage, ckpt.episode, ckpt.global_episode) == ("intelligent", 2, 4)
    with pytest.raises(InputError, match="already holds"):
        run_training(net_path, tiny_config(), run, progress=False)


@pytest.mark.sumo
@pytest.mark.parametrize(("validate_every", "anchor_coef"), [(0, 0.0), (1, 0.0), (0, 0.5)])
def test_interrupt_then_resume_continues_exactly(
    net_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, validate_every: int, anchor_coef: float
) -> None:
    """With ``anchor_coef`` the resumed run must keep the anchor it started from (its first weights), not
    re-anchor on the checkpoint's: the actor's last weights tell the two apart."""
    from idas_sumo.training.loop import run_training

    config = tiny_config(
        stage="robot",
        robot_episodes=3,
        validate_every=validate_every,
        validation_scenarios=1,
        learner=dataclasses.replace(LearnerConfig(), anchor_coef=anchor_coef),
    )
    straight = tmp_path / "straight"
    run_training(net_path, config, straight, progress=False)

    real_update = Learner.apply_gradients  # a training round's update
    calls = {"n": 0}

    def update_then_interrupt(self: Learner, parts: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real_update(self, parts)

    monkeypatch.setattr(Learner, "apply_gradients", update_then_interrupt)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_training(net_path, config, run, progress=False)
    monkeypatch.undo()
    assert load_checkpoint(run / "checkpoint.pt").episode == 1  # only the completed round
    run_training(net_path, config.with_overrides(workers=1), run, resume=True, progress=False)

    def strip(rows: list[dict[str, str]]) -> list[dict[str, str]]:
        return [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows]

    assert strip(read_metrics(run)) == strip(read_metrics(straight))
    if validate_every:
        validated = [
            strip(list(csv.DictReader((d / "validation.csv").open(newline="")))) for d in (run, straight)
        ]
        assert validated[0] == validated[1] and len(validated[0]) == 3
        best_run, best_straight = (
            load_checkpoint(run / "robot_best.pt"),
            load_checkpoint(straight / "robot_best.pt"),
        )
        assert best_run.episode == best_straight.episode
    a, b = load_checkpoint(run / "robot.pt"), load_checkpoint(straight / "robot.pt")
    for k, v in a.learner["actor"].items():
        assert torch.equal(v, b.learner["actor"][k])


@pytest.mark.sumo
def test_a_stop_that_comes_out_as_a_kernels_error_still_saves_the_completed_rounds(
    net_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C while a compiled kernel returns: numba reports a SystemError with the KeyboardInterrupt as its
    context. That is a stop too: the checkpoint holds the completed round (it was left at the starting one)."""
    from idas_sumo.training.loop import run_training

    real_update = Learner.apply_gradients
    calls = {"n": 0}

    def update_then_stop_inside_a_kernel(self: Learner, parts: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 2:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt:
                raise SystemError("CPUDispatcher(...) returned a result with an exception set") from None
        return real_update(self, parts)

    monkeypatch.setattr(Learner, "apply_gradients", update_then_stop_inside_a_kernel)
    run = tmp_path / "run"
    with pytest.raises(SystemError) as raised:
        run_training(
            net_path, tiny_config(stage="robot", robot_episodes=3, checkpoint_every=100), run, progress=False
        )
    assert isinstance(raised.value.__context__, KeyboardInterrupt)
    assert load_checkpoint(run / "checkpoint.pt").episode == 1


@pytest.mark.sumo
def test_ctrl_c_during_a_validation_then_resume_continues_exactly(
    net_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C while the greedy policy is validated after round 2: the round is counted, so the
    checkpoint must hold the generators after its draws (it held those before them, and the resumed
    run drew round 2's scenario again), and the resumed run owes that validation."""
    from idas_sumo.training import loop
    from idas_sumo.training.loop import run_training

    config = tiny_config(stage="robot", robot_episodes=4, validate_every=1, validation_scenarios=1)
    straight = tmp_path / "straight"
    run_training(net_path, config, straight, progress=False)

    real_score = loop.score_episodes
    calls = {"n": 0}

    def score_then_interrupt(stats: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real_score(stats)

    monkeypatch.setattr(loop, "score_episodes", score_then_interrupt)
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_training(net_path, config, run, progress=False)
    monkeypatch.undo()
    assert load_checkpoint(run / "checkpoint.pt").episode == 2  # round 2 is counted
    run_training(net_path, config, run, resume=True, progress=False)

    def strip(rows: list[dict[str, str]]) -> list[dict[str, str]]:
        return [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows]

    assert strip(read_metrics(run)) == strip(read_metrics(straight))
    validated = [
        strip(list(csv.DictReader((d / "validation.csv").open(newline="")))) for d in (run, straight)
    ]
    assert [r["episode"] for r in validated[0]] == ["1", "2", "3", "4"]
    assert validated[0] == validated[1]
    a, b = load_checkpoint(run / "robot.pt"), load_checkpoint(straight / "robot.pt")
    for k, v in a.learner["actor"].items():
        assert torch.equal(v, b.learner["actor"][k])
    assert (
        load_checkpoint(run / "robot_best.pt").episode == load_checkpoint(straight / "robot_best.pt").episode
    )


@pytest.mark.sumo
@pytest.mark.parametrize("normalize", [False, True], ids=["plain", "normalize_advantages"])
def test_two_workers_collect_the_same_episodes(
    net_path: Path, tmp_path: Path, normalize: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    from idas_sumo.training.loop import run_training

    """Two rounds of 16 episodes: each worker collects a group of 8 and computes its gradient part (with
    ``normalize_advantages``, after the round's advantage scale from both groups came back), the second round's
    episodes loaded ahead into the workers' SUMO while they waited (``RolloutServer.work_ahead``); the metrics
    and the weights are those of one worker, bit for bit. No round runs the whole update here."""

    def whole_batch_update(*args: Any) -> None:
        raise AssertionError("a training round ran Learner.update on the whole batch in the training process")

    monkeypatch.setattr(Learner, "update", whole_batch_update)
    config = tiny_config(
        stage="direct",
        episodes_per_update=16,
        direct_episodes=32,
        checkpoint_every=32,
        learner=LearnerConfig(normalize_advantages=normalize),
        workers=1,  # (the default, 0, is one per CPU: two workers on a 2-core machine)
    )
    run_training(net_path, config, tmp_path / "w1", progress=False)
    run_training(net_path, config.with_overrides(workers=2), tmp_path / "w2", progress=False)
    one, two = (
        [{k: v for k, v in r.items() if k != "wall_time_s"} for r in read_metrics(tmp_path / w)]
        for w in ("w1", "w2")
    )
    assert one == two and len(one) == 32
    a, b = (load_checkpoint(tmp_path / w / "direct.pt").learner for w in ("w1", "w2"))
    for net in ("actor", "value", "central"):
        assert all(torch.equal(v, b[net][k]) for k, v in a[net].items())


def test_resume_without_checkpoint_is_input_error(net_path: Path, tmp_path: Path) -> None:
    from idas_sumo.training.loop import run_training

    with pytest.raises(InputError, match="no checkpoint"):
        run_training(net_path, tiny_config(), tmp_path / "nothing", resume=True, progress=False)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_metrics_on_resume_keep_the_rows_before_the_checkpoint(tmp_path: Path) -> None:
    """A checkpoint after 2 episodes (global 0 and 1): the row of episode 2, written before the run was
    killed, goes; the rewritten file has an ordinary file's permissions."""
    from idas_sumo.training.metrics import METRIC_COLUMNS, MetricsSink

    rows = [
        {**dict.fromkeys(METRIC_COLUMNS, 0), "stage": "robot", "episode": e, "global_episode": e}
        for e in range(3)
    ]
    with MetricsSink(tmp_path, tensorboard_keys=()) as sink:
        sink.write(rows)
    with MetricsSink(tmp_path, keep_below_global_episode=2, tensorboard_keys=()) as sink:
        assert [r["global_episode"] for r in sink.kept] == ["0", "1"]
    assert [r["global_episode"] for r in read_metrics(tmp_path)] == ["0", "1"]
    assert (tmp_path / "metrics.csv").stat().st_mode & 0o777 == 0o666 & ~_umask()


@pytest.mark.sumo
def test_resume_after_a_kill_in_stage_two_writes_no_row_twice(
    net_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Killed (no Ctrl-C handler runs) after stage 2's first round: the checkpoint is stage 1's end,
    and resuming must not repeat stage 2's first row (it did: `intelligent,0,2` twice)."""
    from idas_sumo.training.loop import run_training

    config = tiny_config(checkpoint_every=1000, validate_every=1, validation_scenarios=1)
    straight = tmp_path / "straight"
    run_training(net_path, config, straight, progress=False)

    real_update = Learner.apply_gradients  # a training round's update
    calls = {"n": 0}

    def update_then_die(self: Learner, parts: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == 4:  # 2 robot rounds, then stage 2's second round
            raise RuntimeError("killed")
        return real_update(self, parts)

    monkeypatch.setattr(Learner, "apply_gradients", update_then_die)
    run = tmp_path / "run"
    with pytest.raises(RuntimeError, match="killed"):
        run_training(net_path, config, run, progress=False)
    monkeypatch.undo()
    assert load_checkpoint(run / "checkpoint.pt").stage == "robot"
    assert [r["stage"] for r in read_metrics(run)] == ["robot", "robot", "intelligent"]
    run_training(net_path, config, run, resume=True, progress=False)

    def strip(rows: list[dict[str, str]]) -> list[tuple[str, ...]]:
        return [tuple(v for k, v in r.items() if k != "wall_time_s") for r in rows]

    assert strip(read_metrics(run)) == strip(read_metrics(straight))
    validation = [list(csv.DictReader((d / "validation.csv").open(newline=""))) for d in (run, straight)]
    assert [(r["stage"], r["episode"]) for r in validation[0]] == [
        ("robot", "1"),
        ("robot", "2"),
        ("intelligent", "1"),
        ("intelligent", "2"),
    ]
    assert strip(validation[0]) == strip(validation[1])


TINY_TRAIN_TOML = """\
episodes_per_update = 1
max_episode_s = 12.0
[robot_traffic]
n_vehicles = 0
min_vehicles_per_road = 2
max_vehicles_per_road = 3
max_controlled = 1
[intelligent_traffic]
n_vehicles = 0
min_vehicles_per_road = 2
max_vehicles_per_road = 2
"""


def _train_cli(net: Path, *args: str) -> int:
    from idas_sumo.cli import main

    return main(["train", "--net", str(net), "--no-progress", *args])


def _metric_rows(run: Path) -> list[tuple[str, ...]]:
    return [tuple(v for k, v in r.items() if k != "wall_time_s") for r in read_metrics(run)]


@pytest.mark.sumo
def test_resume_warns_only_about_typed_values_and_extends_a_finished_run(
    net_path: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TRAIN_TOML)
    run, straight = tmp_path / "run", tmp_path / "straight"
    assert (
        _train_cli(
            net_path, "--config", str(config), "--stage", "robot", "--episodes", "2", "--out", str(run)
        )
        == 0
    )
    two = _metric_rows(run)
    assert len(two) == 2

    # Nothing typed but --resume: no warning (the shipped default config is not compared with the run).
    caplog.clear()
    assert _train_cli(net_path, "--out", str(run), "--resume") == 0
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == []
    assert _metric_rows(run) == two

    # A larger --episodes extends the finished run; a different --seed is the one value warned about.
    caplog.clear()
    assert _train_cli(net_path, "--out", str(run), "--resume", "--episodes", "4", "--seed", "9") == 0
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and warnings[0].endswith("ignoring new values for seed"), warnings
    four = _metric_rows(run)
    assert [r[:3] for r in four] == [("robot", str(e), str(e)) for e in range(4)]
    assert four[:2] == two

    # Same seed, same numbers: the extended run is the 4-episode run.
    assert (
        _train_cli(
            net_path, "--config", str(config), "--stage", "robot", "--episodes", "4", "--out", str(straight)
        )
        == 0
    )
    assert four == _metric_rows(straight)
    a, b = load_checkpoint(run / "robot.pt"), load_checkpoint(straight / "robot.pt")
    assert a.episode == 4
    for k, v in a.learner["actor"].items():
        assert torch.equal(v, b.learner["actor"][k])

    # A budget below where the run is: refused, nothing changed.
    capsys.readouterr()
    assert _train_cli(net_path, "--out", str(run), "--resume", "--episodes", "3") == 2
    err = capsys.readouterr().err
    assert "--episodes 4 or more" in err and len(err.splitlines()) == 1, err
    assert _metric_rows(run) == four


@pytest.mark.sumo
def test_train_force_starts_over_and_is_needed_for_a_used_out(
    net_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TRAIN_TOML)
    run = tmp_path / "run"
    args = ["--config", str(config), "--stage", "robot", "--episodes", "2", "--out", str(run)]
    assert _train_cli(net_path, *args) == 0
    first = _metric_rows(run)
    (run / "direct.pt").write_bytes((run / "robot.pt").read_bytes())  # a file of an earlier run there,
    with (run / MANIFEST_NAME).open("a") as manifest:  # recorded as the tool's own, as that run would have
        manifest.write("direct.pt\n")
    (run / "notes.txt").write_text("mine\n")
    capsys.readouterr()

    assert _train_cli(net_path, *args) == 2
    err = capsys.readouterr().err
    assert "--force" in err and "--resume" in err and len(err.splitlines()) == 1, err

    assert _train_cli(net_path, *args, "--force") == 0
    assert _metric_rows(run) == first  # replaced, not appended to
    assert not (run / "direct.pt").exists()
    assert (run / "notes.txt").read_text() == "mine\n"  # not a training output: left alone

    with pytest.raises(SystemExit) as exit_:
        _train_cli(net_path, *args, "--force", "--resume")
    assert exit_.value.code == 2
    assert "--resume" in capsys.readouterr().err

    # A folder with other files but no run needs --force too (metrics would be appended to otherwise).
    other = tmp_path / "other"
    other.mkdir()
    (other / "metrics.csv").write_text("stage,episode\n")
    assert _train_cli(net_path, *args[:-1], str(other)) == 2
    assert "--force" in capsys.readouterr().err


# --- validation ----------------------------------------------------------------------------------
def _stats(parts: dict[str, float], perfect: bool, success: bool, end_s: float) -> Any:
    from idas_sumo.agents.rollout import EpisodeStats

    return EpisodeStats(
        agents=2,
        steps=10,
        agent_steps=20,
        sim_time_s=end_s,
        return_mean=0.0,
        reward_parts=parts,
        collisions=0,
        timed_out=not success,
        success=success,
        perfect=perfect,
    )


def test_validation_score_is_the_mean_joint_return() -> None:
    from idas_sumo.training.validation import score_episodes

    # joint return = every agent's finish + collide + impede, plus flow once per step:
    # 20 + 0 - 5 - 2 = 13 and 25 + 0 + 0 + 0 = 25, mean 19.
    score = score_episodes(
        [
            _stats({"finish": 20.0, "collide": 0.0, "impede": -5.0, "flow": -2.0}, False, True, 12.0),
            _stats({"finish": 25.0, "collide": 0.0, "impede": 0.0, "flow": 0.0}, True, True, 14.0),
        ]
    )
    assert score.joint_return == pytest.approx(19.0)
    assert (score.perfect_rate, score.success_rate, score.mean_end_time_s) == (0.5, 1.0, 13.0)
    with pytest.raises(ValueError):
        score_episodes([])


def test_validation_settings_are_checked() -> None:
    with pytest.raises(InputError, match="validate_every"):
        TrainConfig(validate_every=-1)
    with pytest.raises(InputError, match="validation_scenarios"):
        TrainConfig(validation_scenarios=0)


@pytest.mark.sumo
def test_validation_keeps_the_best_weights_and_leaves_training_unchanged(
    net_path: Path, tmp_path: Path
) -> None:
    from idas_sumo.env.engine import MergeEngine
    from idas_sumo.training.loop import run_training
    from idas_sumo.training.validation import score_episodes, validation_tasks
    from idas_sumo.training.workers import InProcessWorkers

    plain = tiny_config(stage="intelligent", intelligent_episodes=3)
    validated = dataclasses.replace(plain, validate_every=1, validation_scenarios=2)
    run_training(net_path, plain, tmp_path / "plain", progress=False)
    run_training(net_path, validated, tmp_path / "validated", progress=False)

    def strip(rows: list[dict[str, str]]) -> list[dict[str, str]]:
        return [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows]

    assert strip(read_metrics(tmp_path / "validated")) == strip(read_metrics(tmp_path / "plain"))
    assert not (tmp_path / "plain" / "validation.csv").exists()
    with (tmp_path / "validated" / "validation.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["episode"] for r in rows] == ["1", "2", "3"]  # the last round's is the stage end's
    assert rows[0]["best"] == "1"
    scores = [float(r["joint_return"]) for r in rows]
    best_path = tmp_path / "validated" / "intelligent_best.pt"
    best = load_checkpoint(best_path)
    assert best.validation is not None
    assert best.validation.joint_return == pytest.approx(max(scores), abs=1e-4)
    assert best.episode == int(rows[scores.index(max(scores))]["episode"])

    # The saved weights score the same when validated again from the file.
    sim = MergeEngine(net_path, seed=0, config=plain.env)
    limits = sim.speed_limits_mps
    sim.close()
    tasks = validation_tasks(plain.intelligent_traffic, limits, 2, validated.validation_seed)
    workers = InProcessWorkers(sim.site, plain.env, seed=0, copies=plain.copies)
    try:
        again = score_episodes([e.stats for e in workers.run(load_actor(best_path), tasks)])
    finally:
        workers.close()
    assert again.joint_return == pytest.approx(best.validation.joint_return, abs=1e-4)


@pytest.mark.sumo
def test_a_smaller_budget_trains_the_first_episodes_of_a_larger_one(net_path: Path, tmp_path: Path) -> None:
    """Nothing in a round depends on the budget, so a short run is a prefix of the long one of its seed (a
    shipped checkpoint of a short run is the same weights as the long run's at that episode)."""
    from idas_sumo.training.loop import run_training

    short = tiny_config(stage="intelligent", intelligent_episodes=2, seed=3)
    run_training(net_path, short, tmp_path / "short", progress=False)
    run_training(
        net_path, dataclasses.replace(short, intelligent_episodes=4), tmp_path / "long", progress=False
    )

    def strip(rows: list[dict[str, str]]) -> list[dict[str, str]]:
        return [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows]

    long_rows = strip(read_metrics(tmp_path / "long"))
    assert len(long_rows) == 4
    assert long_rows[:2] == strip(read_metrics(tmp_path / "short"))  # the losses too: the same weights


def test_copies_is_a_validated_config_value_and_a_train_flag() -> None:
    from idas_sumo.cli import build_parser
    from idas_sumo.sim.multinet import MAX_COPIES
    from idas_sumo.training.cli import config_from_args
    from idas_sumo.training.config import RESUME_FIELDS

    assert TrainConfig().copies == 16
    assert load_train_config(DEFAULT_TRAIN_CONFIG).copies == 16
    for bad in (0, MAX_COPIES + 1):
        with pytest.raises(InputError, match="copies"):
            TrainConfig(copies=bad)
    assert TrainConfig(copies=MAX_COPIES).copies == MAX_COPIES
    args = build_parser().parse_args(["train", "--net", "n.net.xml", "--copies", "3"])
    assert config_from_args(args).copies == 3
    assert config_from_args(args, base=TrainConfig(copies=5, seed=7)) == TrainConfig(copies=3, seed=7)
    assert "copies" in RESUME_FIELDS  # changes no number, so a resumed run may change it freely


@pytest.mark.sumo
def test_copies_change_no_number(net_path: Path, tmp_path: Path) -> None:
    """One episode per SUMO run or three side by side: the same metrics rows and weights."""
    from idas_sumo.training.loop import run_training

    config = tiny_config(stage="direct", direct_episodes=5, episodes_per_update=5)
    one = run_training(net_path, config.with_overrides(copies=1), tmp_path / "c1", progress=False)
    three = run_training(net_path, config.with_overrides(copies=3), tmp_path / "c3", progress=False)

    def strip(rows: list[dict[str, str]]) -> list[dict[str, str]]:
        return [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows]

    rows = strip(read_metrics(tmp_path / "c1"))
    assert rows == strip(read_metrics(tmp_path / "c3")) and len(rows) == 5
    a, b = load_checkpoint(one), load_checkpoint(three)
    assert a.config.copies == 1 and b.config.copies == 3  # stored in the run's config
    for part in ("actor", "value", "central"):
        assert a.learner[part].keys() == b.learner[part].keys()
        for k, v in a.learner[part].items():
            assert torch.equal(v, b.learner[part][k]), (part, k)


@pytest.mark.sumo
def test_unguarded_script_trains_with_two_workers(net_path: Path, tmp_path: Path) -> None:
    """Workers are fresh interpreters: a script without a __main__ guard is not run again by them."""
    import subprocess
    import sys

    script = tmp_path / "train_me.py"
    script.write_text(
        "from pathlib import Path\n"
        "from idas_sumo.env.config import EnvConfig\n"
        "from idas_sumo.env.scenario import TrafficConfig\n"
        "from idas_sumo.training.config import TrainConfig\n"
        "from idas_sumo.training.loop import run_training\n"
        "config = TrainConfig(stage='direct', direct_episodes=2, episodes_per_update=2, workers=2,\n"
        "    intelligent_traffic=TrafficConfig(n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=2),\n"
        "    env=EnvConfig(max_episode_s=12.0))\n"
        f"run_training(Path({str(net_path)!r}), config, Path({str(tmp_path / 'run')!r}), progress=False)\n"
        "print('trained once')\n"
    )
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=300, cwd=tmp_path
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("trained once") == 1
    assert len(read_metrics(tmp_path / "run")) == 2


def test_validation_criterion_ranks_by_return_or_by_success_first() -> None:
    from idas_sumo.training.config import ConfigValueError, TrainConfig
    from idas_sumo.training.validation import ValidationScore, validation_key

    safe = ValidationScore(joint_return=40.0, perfect_rate=0.1, success_rate=0.95, mean_end_time_s=27.0)
    fast = ValidationScore(joint_return=60.0, perfect_rate=0.2, success_rate=0.70, mean_end_time_s=30.0)
    assert validation_key(fast, "joint_return") > validation_key(safe, "joint_return")
    assert validation_key(safe, "success_then_return") > validation_key(fast, "success_then_return")
    tie = ValidationScore(joint_return=45.0, perfect_rate=0.1, success_rate=0.95, mean_end_time_s=27.0)
    assert validation_key(tie, "success_then_return") > validation_key(safe, "success_then_return")
    assert TrainConfig().validation_criterion == "joint_return"
    with pytest.raises(ConfigValueError, match="validation_criterion"):
        TrainConfig(validation_criterion="speed")  # type: ignore[arg-type]
    assert TrainConfig().validation_limit_s is None  # validation keeps the training episodes' timeout
    sixty = TrainConfig(validation_max_episode_s=60.0)
    assert (sixty.validation_limit_s, sixty.longest_episode_s) == (60.0, 60.0)
    for bad in (-1.0, 1e6):
        with pytest.raises(ConfigValueError, match="validation_max_episode_s"):
            TrainConfig(validation_max_episode_s=bad)


def test_critic_exploration_is_retired() -> None:
    """Checkpoints and recipes store critic_exploration: its former default 0 loads, a share of random actions is
    refused in one line."""
    from idas_sumo.training.config import train_config_from_dict

    assert train_config_from_dict({"critic_exploration": 0.0}, "recipe.toml") == TrainConfig()
    with pytest.raises(InputError, match=r"critic_exploration: 0\.1 is a retired experiment variant"):
        train_config_from_dict({"critic_exploration": 0.1}, "recipe.toml")


def test_a_sum_of_zero_penalties_is_written_as_0_not_minus_0() -> None:
    """r_impede and r_flow are -5·0 and -1·0 on a step without a hard brake, which is -0.0: their episode sums
    must still read 0 in metrics.csv, and a real penalty must keep its sign."""
    from idas_sumo.agents.rollout import _sequential_sum

    assert f"{_sequential_sum(np.array([-0.0, -0.0]))}" == "0.0"
    assert _sequential_sum(np.array([-5.0, -0.0, -5.0])) == -10.0


def test_init_from_finds_a_shipped_policy_from_any_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``init_from = "policies/warm_start.pt"`` names the shipped file wherever train runs; a missing path is one
    InputError that names it."""
    from idas_sumo.errors import InputError
    from idas_sumo.training.config import TrainConfig
    from idas_sumo.training.loop import _init_weights

    monkeypatch.chdir(tmp_path)
    weights = _init_weights(TrainConfig(init_from="policies/warm_start.pt"))
    assert weights is not None and "actor" in weights
    with pytest.raises(InputError, match=r"policies/missing\.pt"):
        _init_weights(TrainConfig(init_from="policies/missing.pt"))


def test_a_resumed_stage_keeps_its_best_at_full_precision(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """validation.csv rounds to 6 significant digits: restored from it, the best 9.32078125 would read 9.32078,
    and a later validation equal to the best would replace the earliest of equals (the pick rule's)."""
    from types import SimpleNamespace

    from idas_sumo.training import loop
    from idas_sumo.training.validation import ValidationScore, validation_key

    exact = ValidationScore(
        joint_return=9.32078125, perfect_rate=0.65, success_rate=1.0, mean_end_time_s=18.76
    )
    row = {"joint_return": "9.32078", "perfect_rate": "0.65", "success_rate": "1", "mean_end_time_s": "18.76"}
    best = tmp_path / "robot_best.pt"
    best.write_bytes(b"")
    monkeypatch.setattr(loop, "load_checkpoint", lambda path: SimpleNamespace(validation=exact))
    restored = loop.resumed_best([row], best, "success_then_return")
    assert restored == validation_key(exact, "success_then_return")
    assert not validation_key(exact, "success_then_return") > restored  # an equal later score is no better
    # Without a best file (none saved yet), the CSV's rows.
    assert loop.resumed_best([row], tmp_path / "none.pt", "joint_return") == (9.32078, 0.0)


def test_a_training_process_keeps_freed_blocks_on_glibc() -> None:
    """``keep_freed_blocks`` takes on glibc (this project's Linux machines): a 64 MB array freed and
    allocated again is served from the heap, so its pages are not faulted in a second time."""
    import subprocess
    import sys

    script = (
        "import resource, numpy as np\n"
        "from idas_sumo.training.heap import keep_freed_blocks\n"
        "assert keep_freed_blocks()\n"
        "a = np.ones(16 << 20, dtype=np.float32); del a\n"
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "a = np.ones(16 << 20, dtype=np.float32)\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)\n"
    )
    faults = int(
        subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    )
    # Without it about 500 (numpy asks for huge pages): the freed block went back to the kernel.
    assert faults < 50, f"{faults} page faults: the freed 64 MB went back to the kernel"


def test_a_frozen_heap_keeps_the_objects_alive_at_its_start_out_of_the_collector() -> None:
    """Within ``frozen_heap`` the objects alive at its start are frozen (a full collection does not walk them),
    a young cycle that was garbage already is collected first, not frozen, and at the end nothing is frozen."""
    import gc
    import weakref

    from idas_sumo.training.heap import frozen_heap

    class Node:
        pass

    held = [Node()]  # alive: frozen in the block
    garbage = Node()
    garbage.me = garbage  # type: ignore[attr-defined]  # a cycle nobody holds: collected, not frozen
    gone = weakref.ref(garbage)
    del garbage
    assert gc.get_freeze_count() == 0
    with frozen_heap():
        assert gone() is None
        assert gc.get_freeze_count() >= len(held)
        assert not any(o is held for o in gc.get_objects())  # frozen objects are out of the generations
    assert gc.get_freeze_count() == 0
    assert any(o is held for o in gc.get_objects())


def test_the_workers_fork_server_freezes_what_it_loaded() -> None:
    """``warm_up`` (what the fork server runs before it forks) ends with its objects frozen."""
    import subprocess
    import sys

    script = (
        "import gc\nfrom idas_sumo.training.workers import warm_up\nwarm_up()\nprint(gc.get_freeze_count())\n"
    )
    frozen = int(
        subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    )
    assert frozen > 10_000  # torch, numba and their loaded kernels


@pytest.mark.sumo
def test_a_rounds_step_runs_on_one_torch_thread(
    net_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The training process applies a round's gradient parts on one torch thread (as the parts were computed),
    whatever its own count, which it gets back afterwards: the step's norms then round alike on every machine."""
    from idas_sumo.agents.learner import Learner
    from idas_sumo.training.loop import run_training

    threads: list[int] = []
    apply = Learner.apply_gradients

    def counted(self: Learner, parts: Any) -> dict[str, float]:
        threads.append(torch.get_num_threads())
        return apply(self, parts)

    monkeypatch.setattr(Learner, "apply_gradients", counted)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        run_training(
            net_path, tiny_config(stage="intelligent", intelligent_episodes=2), tmp_path / "r", progress=False
        )
        assert threads and set(threads) == {1}
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
