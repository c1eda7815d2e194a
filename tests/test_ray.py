"""The Ray backend (``--ray-address``), ``idas-sumo sweep`` and the ``ray`` extra.

The Ray tests start a Ray instance on this machine (``--ray-address local``: ``ray.init(num_cpus=...)``)
and compare with the local workers: the same episodes in the same order, so the same files.
"""

from __future__ import annotations

import csv
import functools
import math
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
from conftest import main_in_process

from idas_sumo.resources import DEFAULT_NET

REPO_ROOT = Path(__file__).resolve().parents[1]
EXTRA = 'pip install "idas-sumo[ray]"'

TINY = """\
stage = "direct"
direct_episodes = 4
episodes_per_update = 2
checkpoint_every = 2
max_episode_s = 15.0
copies = 2
validate_every = 2
validation_scenarios = 2
"""


def one_error_line(stderr: str, *needles: str) -> None:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and "Traceback" not in stderr, stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    return path


@pytest.fixture
def ray_rounds(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """How many requests each ``RayPool.submit`` sent: proof that the work went to Ray actors."""
    from idas_sumo.distributed.ray_pool import RayPool

    sent: list[int] = []
    submit = RayPool.submit

    def spy(self: RayPool, requests: Any, shared: Any = None) -> None:
        sent.append(len(requests))
        submit(self, requests, shared)

    monkeypatch.setattr(RayPool, "submit", spy)
    return sent


def rows(path: Path, drop: tuple[str, ...] = ("wall_time_s",)) -> list[dict[str, str]]:
    """A CSV's rows without the columns that measure time."""
    with path.open() as f:
        return [{k: v for k, v in r.items() if k not in drop} for r in csv.DictReader(f)]


# --- without Ray ----------------------------------------------------------------------------------------


@pytest.mark.sumo
def test_runs_without_ray_address_never_import_ray(tmp_path: Path, tiny: Path) -> None:
    code = textwrap.dedent(
        f"""
        import sys
        from idas_sumo.cli import main
        assert main(["train", "--config", {str(tiny)!r}, "--out", {str(tmp_path / "run")!r},
                     "--workers", "2", "--no-progress"]) == 0
        assert main(["evaluate", "--baseline", "idm", "--scenarios", "2", "--workers", "2",
                     "--out", {str(tmp_path / "eval")!r}, "--no-progress"]) == 0
        print("ray imported:", sorted(m for m in sys.modules if m == "ray" or m.startswith("ray.")))
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=300
    )
    assert result.returncode == 0, result.stderr
    assert "ray imported: []" in result.stdout, result.stdout


def test_missing_extra_is_exit_2_naming_it(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, tiny: Path
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # ``import ray`` raises ImportError
    for args in (
        ["train", "--config", str(tiny), "--out", str(tmp_path / "t"), "--ray-address", "local"],
        ["evaluate", "--baseline", "idm", "--out", str(tmp_path / "e"), "--ray-address", "auto"],
        ["sweep", str(tiny), "--seeds", "0-1", "--out", str(tmp_path / "s"), "--ray-address", "local"],
    ):
        code, _, err = main_in_process(capsys, *args)
        assert code == 2, (args, err)
        one_error_line(err, EXTRA)
    assert not (tmp_path / "t").exists() and not (tmp_path / "e").exists()


def test_bad_ray_address_is_a_usage_error(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    for address in ("cluster", "host:", "host:99999", ":6379"):
        code, _, err = main_in_process(
            capsys, "train", "--out", str(tmp_path / "t"), "--ray-address", address
        )
        assert code == 2, (address, err)
        one_error_line(err, "--ray-address", "auto, local or HOST:PORT")


def test_ray_addresses_that_are_accepted() -> None:
    from idas_sumo.distributed import check_ray_address

    for address in ("auto", "local", "10.0.0.5:6379", "head.lab:6379"):
        assert check_ray_address(address) == address


# --- sweep's arguments ----------------------------------------------------------------------------------


def test_sweep_seeds_and_sets_parse() -> None:
    from idas_sumo.training.sweep import parse_seeds, parse_sets

    assert parse_seeds("0-4") == [0, 1, 2, 3, 4]
    assert parse_seeds("7,2-3") == [7, 2, 3]
    assert parse_sets(["learner.gamma=0.9,0.99", "stage=robot,direct", "copies=4"]) == [
        ("learner.gamma", [0.9, 0.99]),
        ("stage", ["robot", "direct"]),
        ("copies", [4]),
    ]


def test_sweep_bad_arguments_are_exit_2(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, tiny: Path
) -> None:
    no_validation = tmp_path / "noval.toml"
    no_validation.write_text(TINY.replace("validate_every = 2", "validate_every = 0"))
    out = tmp_path / "s"
    cases = {
        "nested key": (["--seeds", "0", "--set", "learner.gama=0.9"], ["learner", "'gama'", '"gamma"']),
        "top key": (
            ["--seeds", "0", "--set", "episodes_per_updat=2"],
            ["'episodes_per_updat'", "did you mean"],
        ),
        "bad value": (["--seeds", "0", "--set", "copies=many"], ["copies", "many"]),
        "seed set": (["--seeds", "0", "--set", "seed=1,2"], ["--seeds"]),
        "no values": (["--seeds", "0", "--set", "copies"], ["KEY=V1,V2"]),
        "backwards": (["--seeds", "4-1"], ["backwards"]),
        "not seeds": (["--seeds", "a"], ["--seeds"]),
    }
    for name, (args, needles) in cases.items():
        code, _, err = main_in_process(capsys, "sweep", str(tiny), "--out", str(out), *args)
        assert code == 2, (name, err)
        one_error_line(err, *needles)
    code, _, err = main_in_process(capsys, "sweep", str(no_validation), "--seeds", "0", "--out", str(out))
    assert code == 2
    one_error_line(err, "validate_every")
    assert not out.exists()  # refused before anything was written


# --- on Ray ---------------------------------------------------------------------------------------------


@pytest.mark.sumo
def test_train_on_ray_is_the_same_run_as_local_workers(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, tiny: Path, ray_rounds: list[int]
) -> None:
    import torch

    from idas_sumo.training.checkpoint import load_checkpoint

    common = ["train", "--config", str(tiny), "--workers", "2", "--no-progress"]
    assert main_in_process(capsys, *common, "--out", str(tmp_path / "local"))[0] == 0
    assert ray_rounds == []
    code, _, err = main_in_process(capsys, *common, "--out", str(tmp_path / "ray"), "--ray-address", "local")
    assert code == 0, err
    # 2 training rounds, each one group of gradients (training/workers.py: GROUP_EPISODES) on one actor, and 2
    # validations of 2 scenarios, each split over 2 actors.
    assert ray_rounds == [1, 2, 1, 2]
    import ray

    assert not ray.is_initialized()  # the instance the command started is stopped

    local, on_ray = tmp_path / "local", tmp_path / "ray"
    assert rows(on_ray / "metrics.csv") == rows(local / "metrics.csv")
    assert len(rows(local / "metrics.csv")) == 4
    assert rows(on_ray / "validation.csv") == rows(local / "validation.csv")
    for name in ("direct.pt", "direct_best.pt"):
        a, b = load_checkpoint(local / name).learner, load_checkpoint(on_ray / name).learner
        for net in ("actor", "value", "central"):
            assert a[net].keys() == b[net].keys()
            for key, value in a[net].items():
                assert torch.equal(value, b[net][key]), (name, net, key)


@pytest.mark.sumo
def test_evaluate_on_ray_writes_byte_identical_csvs(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, ray_rounds: list[int]
) -> None:
    common = ["evaluate", "--baseline", "idm", "--scenarios", "4", "--workers", "2", "--no-progress"]
    assert main_in_process(capsys, *common, "--out", str(tmp_path / "local"))[0] == 0
    assert ray_rounds == []
    code, _, err = main_in_process(capsys, *common, "--out", str(tmp_path / "ray"), "--ray-address", "local")
    assert code == 0, err
    assert ray_rounds == [2]  # one task per actor
    names = sorted(p.name for p in (tmp_path / "local").glob("*.csv"))
    assert {"episodes.csv", "summary.csv", "flow.csv"} <= set(names)
    assert sorted(p.name for p in (tmp_path / "ray").glob("*.csv")) == names
    for name in names:
        assert (tmp_path / "ray" / name).read_bytes() == (tmp_path / "local" / name).read_bytes(), name


@pytest.mark.sumo
def test_two_seed_sweep_on_ray_writes_its_table_and_resumes_locally(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, tiny: Path
) -> None:
    out = tmp_path / "sweep"
    args = ["sweep", str(tiny), "--seeds", "0-1", "--out", str(out), "--net", str(DEFAULT_NET)]
    args += ["--evaluate", "--eval-scenarios", "2"]
    code, stdout, err = main_in_process(capsys, *args, "--ray-address", "local")
    assert code == 0, err
    table = rows(out / "sweep.csv", drop=())
    assert [r["run"] for r in table] == ["seed-0", "seed-1"]
    assert [r["seed"] for r in table] == ["0", "1"]
    for r in table:
        assert math.isfinite(float(r["best_joint_return"]))
        assert r["eval_scenarios"] == "2" and 0 <= float(r["eval_success_pct"]) <= 100
        assert (Path(r["run_dir"]) / "direct_best.pt").is_file()
    assert (out / "sweep.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "run seed-0" in stdout and "run seed-1" in stdout
    # Without Ray, on the same folder: the runs are done, so only their results are read (and the
    # evaluations run again, here), and the table is the same.
    first = (out / "sweep.csv").read_bytes()
    assert main_in_process(capsys, *args)[0] == 0
    assert (out / "sweep.csv").read_bytes() == first


@pytest.fixture
def sigterm_after_submit(monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGTERM to this process half a second after the first ``RayPool.submit``: while the driver
    waits on Ray for the replies (the actors are still starting their SUMO)."""
    import os
    import signal
    import threading

    from idas_sumo.distributed.ray_pool import RayPool

    submit = RayPool.submit
    sent: list[bool] = []

    def submit_then_signal(self: RayPool, requests: Any, shared: Any = None) -> None:
        submit(self, requests, shared)
        if not sent:
            sent.append(True)
            threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGTERM)).start()

    monkeypatch.setattr(RayPool, "submit", submit_then_signal)


@pytest.mark.sumo
@pytest.mark.parametrize("command", ["train", "evaluate"])
def test_sigterm_while_waiting_on_ray_is_143(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, tiny: Path, sigterm_after_submit: None, command: str
) -> None:
    """Ray turns what a signal handler raises inside ``ray.wait``/``ray.get`` into a plain
    KeyboardInterrupt: SIGTERM was reported as Ctrl-C (exit 130) before the Ray pool raised the
    handler's own exception again."""
    out = tmp_path / "out"
    args = {
        "train": ["train", "--config", str(tiny), "--episodes", "100000"],
        "evaluate": ["evaluate", "--baseline", "idm", "--scenarios", "40"],
    }[command]
    code, _, err = main_in_process(
        capsys, *args, "--workers", "2", "--out", str(out), "--ray-address", "local"
    )
    assert code == 143, err
    assert err.strip().splitlines()[-1].startswith("idas-sumo: terminated (SIGTERM)"), err
    assert "Traceback" not in err
    import ray

    assert not ray.is_initialized()
    if command == "train":
        assert (out / "checkpoint.pt").is_file()


def test_no_cluster_at_the_address_is_exit_2(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    out = tmp_path / "e"
    args = ["evaluate", "--baseline", "idm", "--scenarios", "2", "--out", str(out), "--ray-address", "auto"]
    code, _, err = main_in_process(capsys, *args)
    assert code == 2, err
    one_error_line(err, "--ray-address auto", "cannot connect to a Ray cluster")
    assert not out.exists()


def test_more_workers_than_the_cluster_has_cpus_is_an_input_error() -> None:
    """Actors that no node can place wait for ever: the pool refused nothing and the run hung."""
    from idas_sumo.distributed.ray_pool import RayPool, ray_session
    from idas_sumo.errors import InputError

    with ray_session("local", num_cpus=1), pytest.raises(InputError, match="has 1 CPUs, fewer than the 2 "):
        RayPool("idas_sumo.training.workers:RolloutServer", [None, None], "rollout worker", "local")
    import ray

    assert not ray.is_initialized()


def test_workers_are_bounded_by_this_machine_unless_they_run_on_a_cluster(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path, tiny: Path
) -> None:
    from idas_sumo.sim.processes import max_workers

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    many = str(max_workers() + 1)
    for command in (["train", "--config", str(tiny)], ["evaluate", "--baseline", "idm"]):
        base = [*command, "--workers", many, "--out", str(tmp_path / "o")]
        for local in ([], ["--ray-address", "local"]):  # a local Ray instance runs on this machine's CPUs
            code, _, err = main_in_process(capsys, *base, *local)
            assert code == 2, err
            one_error_line(err, "--workers", many, "CPUs")
        # On a cluster the cluster's CPUs count: here the refusal is that there is none to connect to ("auto"
        # finds any Ray instance running on this machine, such as another test's beside this one: none here).
        none_running: Any = functools.lru_cache(list)  # (ray clears its cache)
        monkeypatch.setattr("ray._private.services.find_gcs_addresses", none_running)
        monkeypatch.setattr("ray._private.services.find_bootstrap_address", lambda temp_dir: None)
        code, _, err = main_in_process(capsys, *base, "--ray-address", "auto")
        assert code == 2, err
        one_error_line(err, "cannot connect to a Ray cluster")
