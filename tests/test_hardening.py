"""Issue #7, hardening: every failure is clear, early and harmless, through the real entry points.

The cases already covered elsewhere (bad nets in test_cli/test_netgen, scenario TOMLs in test_scenario,
checkpoints through ``load_checkpoint`` in test_training, env misuse in test_env_api, the second backend
in test_sim_control) are not repeated here. CLI cases run ``python -m idas_sumo.cli`` in a subprocess;
a few that need a fault injected (a full disk, a directory the test cannot make unwritable as root) call
``idas_sumo.cli.main`` in process with one function patched.
"""

from __future__ import annotations

import errno
import os
import pickle
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import TINY_TRAIN_TOML, checkpoint_payload, interrupt_when, main_in_process, run_cli

from idas_sumo.cli.exits import INTERRUPTED
from idas_sumo.env.outcome import END_REASONS
from idas_sumo.resources import DEFAULT_NET as NET

REPO_ROOT = Path(__file__).resolve().parents[1]
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


# --- helpers ------------------------------------------------------------------------------------------


def assert_one_line(stderr: str, code: int, returncode: int, *needles: str) -> str:
    """Exit ``code`` with exactly one 'idas-sumo: error: ...' line on stderr, no traceback."""
    assert returncode == code, (returncode, stderr)
    assert "Traceback" not in stderr, stderr
    lines = stderr.splitlines()
    assert len(lines) == 1, f"expected one stderr line, got {len(lines)}:\n{stderr}"
    line = lines[0]
    assert line.startswith("idas-sumo") and "error: " in line, line
    for needle in needles:
        assert needle in line, f"{needle!r} not in {line!r}"
    return line


def check_cli_cases(
    cases: dict[str, tuple[list[str], list[str]]], in_subprocess: set[str], capsys: pytest.CaptureFixture[str]
) -> None:
    """Exit 2 and one line with the needles for every case: those named in ``in_subprocess`` through
    ``python -m idas_sumo.cli`` (in parallel), the rest through ``idas_sumo.cli.main`` in this process
    (the same function; it saves the ~1.5 s of imports a subprocess pays)."""
    names = [n for n in cases if n in in_subprocess]
    results = dict(zip(names, run_many(*(cases[n][0] for n in names)), strict=True))
    for name, (args, needles) in cases.items():
        try:
            if name in results:
                assert_usage_error(results[name], *needles)
            else:
                code, _, err = main_in_process(capsys, *args)
                assert_one_line(err, 2, code, *needles)
        except AssertionError as err:
            raise AssertionError(f"case {name}: {err}") from None


def run_many(
    *commands: list[str], env: dict[str, str] | None = None
) -> list[subprocess.CompletedProcess[str]]:
    """Several CLI runs at once (each pays ~1.5 s of imports; the machine has cores to spare)."""
    with ThreadPoolExecutor(max_workers=max(os.cpu_count() or 1, 2)) as pool:
        return list(pool.map(lambda args: run_cli(*args, env=env), commands))


def assert_usage_error(result: subprocess.CompletedProcess[str], *needles: str) -> str:
    return assert_one_line(result.stderr, 2, result.returncode, *needles)


def snapshot(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` with its bytes (to prove nothing was damaged)."""
    return {
        str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()
    }


def temp_files(directory: Path) -> list[str]:
    """Temp files and dotfiles left behind (the output folder's manifest of what it holds is meant to stay)."""
    from idas_sumo.io_utils import MANIFEST_NAME

    return sorted(
        p.name
        for p in directory.rglob("*")
        if (p.name.endswith(".tmp") or p.name.startswith(".")) and p.name != MANIFEST_NAME
    )


def eval_args(out: Path, *extra: str, baseline: str = "idm", net: Path = NET) -> list[str]:
    return [
        "evaluate", "--baseline", baseline, "--others", "idm", "--net", str(net), "--out", str(out),
        "--no-progress", *extra,
    ]  # fmt: skip


def train_args(out: Path, *extra: str) -> list[str]:
    return ["train", "--net", str(NET), "--out", str(out), "--no-progress", *extra]


def _learner() -> Any:
    from idas_sumo.agents.learner import Learner, LearnerConfig

    return Learner(LearnerConfig(), seed=1)


def _payload(learner: Any, /, **extra: Any) -> Any:
    return checkpoint_payload(learner, **extra)


class _RunsCode:
    """Unpickling this would run ``touch MARKER``: loading a checkpoint must never do that."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return (os.system, (f"touch {self.marker}",))


def make_bad_checkpoint(path: Path, damage: str, marker: Path) -> None:
    """Write a checkpoint damaged in one way (``save_checkpoint`` first, then tampered)."""
    import torch

    from idas_sumo.training.checkpoint import save_checkpoint

    learner = _learner()
    if damage == "empty":
        path.write_bytes(b"")
    elif damage == "truncated":
        save_checkpoint(path, _payload(learner))
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])
    elif damage == "pickle":  # a plain pickle of an object whose loading runs a shell command
        path.write_bytes(pickle.dumps(_RunsCode(marker)))
    elif damage == "torch-pickle":  # the same object inside a torch zip file
        torch.save({"weights": _RunsCode(marker)}, path)
    elif damage == "foreign":
        torch.save({"state_dict": {"w": torch.zeros(3)}}, path)
    elif damage == "layout":
        save_checkpoint(path, _payload(learner, obs_layout_id="scalars5-some-other-layout"))
    elif damage == "version":
        save_checkpoint(path, _payload(learner))
        data = torch.load(path, weights_only=True)
        data["format"] = 99
        torch.save(data, path)
    elif damage == "nan":
        state = learner.state_dict()
        name = next(iter(state["actor"]))
        state["actor"][name] = torch.full_like(state["actor"][name], float("nan"))
        save_checkpoint(path, _payload(learner, learner=state))
    elif damage == "shapes":
        state = learner.state_dict()
        name = next(iter(state["actor"]))
        state["actor"][name] = torch.zeros(2, 2)
        save_checkpoint(path, _payload(learner, learner=state))
    else:  # pragma: no cover
        raise AssertionError(damage)


CHECKPOINT_DAMAGE = [
    "empty",
    "truncated",
    "pickle",
    "torch-pickle",
    "foreign",
    "layout",
    "version",
    "nan",
    "shapes",
]


# --- training config TOML -----------------------------------------------------------------------------


BAD_TRAIN_TOML = {
    "syntax": ("robot_episodes = 3\nseed = = 1\n", ["line 2"]),
    "unknown-key": ("robot_episods = 3\n", ["'robot_episods'", 'did you mean "robot_episodes"']),
    "unknown-nested-key": ("[learner]\ngama = 0.5\n", ["gama", 'did you mean "gamma"']),
    "wrong-type": ('robot_episodes = "three"\n', ["robot_episodes", "integer"]),
    "float-for-int": ("workers = 1.5\n", ["workers", "integer"]),
    "zero-episodes": ("robot_episodes = 0\n", ["robot_episodes", "at least 1"]),
    "negative-episodes": ("direct_episodes = -4\n", ["direct_episodes", "-4"]),
    "nan": ("max_episode_s = nan\n", ["max_episode_s", "finite"]),
    "traffic-nan": ("[robot_traffic]\nmin_speed_frac = nan\n", ["min_speed_frac", "finite"]),
    "traffic-range": (
        "[robot_traffic]\nmin_vehicles_per_road = 3\nmax_vehicles_per_road = 1\n",
        ["robot_traffic", "min_vehicles_per_road"],
    ),
    "alpha-range": ("[learner]\nalpha = 1.5\n", ["alpha"]),
    "bad-stage": ('stage = "everything"\n', ["stage", "everything"]),
    "not-utf8": (b"\xff\xfe\x00robot", ["not a text file"]),
}


def test_train_config_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Every bad training TOML (and bad count flag) is exit 2, one line naming the file and the key."""
    out = tmp_path / "run"
    cases: dict[str, tuple[list[str], list[str]]] = {}
    for case, (text, needles) in BAD_TRAIN_TOML.items():
        config = tmp_path / f"{case}.toml"
        if isinstance(text, bytes):
            config.write_bytes(text)
        else:
            config.write_text(text)
        cases[case] = (train_args(out, "--config", str(config), "--episodes", "1"), [str(config), *needles])
    missing = tmp_path / "nope.toml"
    cases["missing"] = (train_args(out, "--config", str(missing)), [str(missing), "not found"])
    cases["directory"] = (train_args(out, "--config", str(tmp_path)), [str(tmp_path), "directory"])
    cases["episodes-0"] = (train_args(out, "--episodes", "0"), ["--episodes", "positive"])
    cases["workers-text"] = (train_args(out, "--workers", "two"), ["--workers", "two"])
    subprocess_cases = {
        "syntax",
        "unknown-key",
        "wrong-type",
        "zero-episodes",
        "nan",
        "not-utf8",
        "episodes-0",
    }
    check_cli_cases(cases, subprocess_cases, capsys)
    assert not out.exists()  # refused before anything is written


# --- checkpoints and policies -------------------------------------------------------------------------


def test_evaluate_bad_policy_is_exit_2_naming_the_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    marker = tmp_path / "CODE_WAS_RUN"
    policies = {damage: tmp_path / f"{damage}.pt" for damage in CHECKPOINT_DAMAGE}
    for damage, policy in policies.items():
        make_bad_checkpoint(policy, damage, marker)
    before = snapshot(tmp_path)
    out = tmp_path / "out"
    cases = {
        damage: (eval_args(out, "--policy", str(p), "--scenarios", "2", baseline="idas"), [str(p)])
        for damage, p in policies.items()
    }
    # The pickles run in a subprocess too: if one were unpickled, its code would run there, not here.
    check_cli_cases(cases, {"empty", "truncated", "pickle", "torch-pickle", "nan", "layout"}, capsys)
    assert not marker.exists(), "loading a policy unpickled an arbitrary object and ran its code"
    assert snapshot(tmp_path) == before
    assert not out.exists()


def test_pickled_code_is_refused_through_the_python_api(tmp_path: Path) -> None:
    from idas_sumo.agents.checkpoint_file import load_actor
    from idas_sumo.errors import InputError

    marker = tmp_path / "CODE_WAS_RUN"
    for damage in ("pickle", "torch-pickle"):
        policy = tmp_path / f"{damage}.pt"
        make_bad_checkpoint(policy, damage, marker)
        with pytest.raises(InputError, match="never unpickled") as err:
            load_actor(policy)
        assert str(policy) in str(err.value) and "\n" not in str(err.value)
        assert "weights_only" not in str(
            err.value
        )  # torch's advice to turn the protection off is not passed on
    assert not marker.exists()


def test_resume_or_init_from_a_bad_checkpoint_leaves_it_untouched(tmp_path: Path) -> None:
    marker = tmp_path / "CODE_WAS_RUN"
    commands, needles = [], []
    for damage in ("truncated", "pickle", "nan"):
        run = tmp_path / f"run-{damage}"
        run.mkdir()
        make_bad_checkpoint(run / "checkpoint.pt", damage, marker)
        (run / "metrics.csv").write_text("stage,episode\nrobot,0\n")
        commands.append(train_args(run, "--resume", "--episodes", "1"))
        needles.append(str(run / "checkpoint.pt"))
    bad = tmp_path / "init.pt"
    make_bad_checkpoint(bad, "torch-pickle", marker)
    config = tmp_path / "c.toml"
    config.write_text(f'stage = "intelligent"\ninit_from = "{bad}"\n')
    commands.append(train_args(tmp_path / "fresh", "--config", str(config), "--episodes", "1"))
    needles.append(str(bad))
    before = snapshot(tmp_path)
    for result, needle in zip(run_many(*commands), needles, strict=True):
        assert_usage_error(result, needle)
    assert snapshot(tmp_path) == before  # every checkpoint and metrics file byte for byte
    assert not marker.exists()
    assert not (tmp_path / "fresh").exists()


def test_interrupted_checkpoint_write_keeps_the_previous_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk fills up (or Ctrl-C comes) half-way through writing the file: the old checkpoint
    survives. (A real full disk, on a tmpfs: test_reliability.)"""
    import contextlib

    from idas_sumo.training import checkpoint as ckpt

    path = tmp_path / "checkpoint.pt"
    learner = _learner()
    ckpt.save_checkpoint(path, _payload(learner))
    before = path.read_bytes()
    real_open = ckpt.atomic_open

    for failure in (OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()):

        class HalfThenFail:
            def __init__(self, f: Any, _failure: BaseException = failure) -> None:
                self.f, self.failure = f, _failure

            def write(self, data: Any) -> int:
                self.f.write(bytes(data)[: len(before) // 2])
                raise self.failure

        @contextlib.contextmanager
        def failing_open(*args: Any, **kwargs: Any) -> Any:
            with real_open(*args, **kwargs) as f:
                yield HalfThenFail(f)

        monkeypatch.setattr(ckpt, "atomic_open", failing_open)
        with pytest.raises(type(failure)):
            ckpt.save_checkpoint(path, _payload(learner, episode=99, global_episode=99))
        monkeypatch.undo()
        assert path.read_bytes() == before
        assert ckpt.load_checkpoint(path).episode == 7
        assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]


def test_resume_drops_a_metrics_row_cut_short(tmp_path: Path) -> None:
    """A crash mid-row leaves a partial line in metrics.csv; resuming must not trip over it."""
    from idas_sumo.training.metrics import METRIC_COLUMNS, MetricsSink

    row = ",".join(["robot", "{e}", "{e}", *["0"] * (len(METRIC_COLUMNS) - 3)])
    text = ",".join(METRIC_COLUMNS) + "\n" + "".join(row.format(e=e) + "\n" for e in range(3))
    (tmp_path / "metrics.csv").write_text(text + "robot,3,")  # cut off mid-row
    with MetricsSink(tmp_path, keep_below_global_episode=2):
        pass
    lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert lines == text.splitlines()[:3]  # header + episodes 0 and 1


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_temporary_files_are_made_only_by_io_utils() -> None:
    """io_utils names every temp file ``*.tmp`` (which .gitignore covers) with ordinary permissions;
    a temp file made elsewhere in the package got neither (netgen's ``*.net.xml``, mode 0600)."""
    import re

    from idas_sumo import io_utils

    package = Path(io_utils.__file__).parent
    makers = re.compile(r"\b(mkstemp|NamedTemporaryFile)\(")
    elsewhere = [
        str(p.relative_to(package))
        for p in package.rglob("*.py")
        if p.name != "io_utils.py" and makers.search(p.read_text())
    ]
    assert elsewhere == []
    assert "*.tmp" in (REPO_ROOT / ".gitignore").read_text().splitlines()
    assert io_utils.TEMP_SUFFIX == ".tmp"


@pytest.mark.sumo
def test_generated_net_is_written_through_a_tmp_file_with_normal_permissions(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from idas_sumo.sim import netgen

    outputs: list[str] = []
    real_run = subprocess.run

    def recording_run(cmd: list[str], **kw: Any) -> Any:
        outputs.append(cmd[cmd.index("--output-file") + 1])
        return real_run(cmd, **kw)

    monkeypatch.setattr(netgen.subprocess, "run", recording_run)
    net = netgen.generate_net(tmp_path / "n.net.xml")
    assert len(outputs) == 1 and outputs[0].endswith(".tmp"), outputs
    assert net.stat().st_mode & 0o777 == 0o666 & ~_umask()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["n.edg.xml", "n.net.xml", "n.nod.xml"]


# --- nets ---------------------------------------------------------------------------------------------


@pytest.mark.sumo
def test_route_that_cannot_be_driven(tmp_path: Path) -> None:
    """The merge road is not connected to the outgoing road: refused before SUMO starts."""
    from idas_sumo.sim.netgen import NetParams, _plain_xml, sumo_binary

    node_xml, edge_xml = _plain_xml(NetParams())
    (tmp_path / "n.nod.xml").write_text(node_xml)
    (tmp_path / "n.edg.xml").write_text(edge_xml)
    import xml.etree.ElementTree as ET

    edges = ET.fromstring(edge_xml)
    into = {e.get("to") for e in edges}
    by_from = {e.get("from"): e.get("id") for e in edges}
    junction = next(n for n in into if sum(e.get("to") == n for e in edges) == 2)
    incoming = [e.get("id") for e in edges if e.get("to") == junction]
    out_edge = by_from[junction]
    (tmp_path / "n.con.xml").write_text(
        f'<connections><delete from="{incoming[1]}" to="{out_edge}"/></connections>\n'
    )
    net = tmp_path / "n.net.xml"
    subprocess.run(
        [
            str(sumo_binary("netconvert")),
            "-n", str(tmp_path / "n.nod.xml"),
            "-e", str(tmp_path / "n.edg.xml"),
            "-x", str(tmp_path / "n.con.xml"),
            "-o", str(net),
            "--no-warnings",
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    out = tmp_path / "out"
    result = run_cli(*eval_args(out, "--scenarios", "2", net=net))
    assert_usage_error(result, str(net), "not drivable")
    assert not out.exists()


def test_unreadable_net(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    net = tmp_path / "locked.net.xml"
    net.write_bytes(NET.read_bytes())
    out = tmp_path / "out"
    if not IS_ROOT:  # root reads any file, so chmod 000 proves nothing there
        net.chmod(0)
        try:
            assert_usage_error(
                run_cli(*eval_args(out, "--scenarios", "2", net=net)), str(net), "not readable"
            )
        finally:
            net.chmod(0o644)
    # The same refusal in process, with the permission check answering as for a normal user.
    real_access = os.access
    monkeypatch.setattr(
        os, "access", lambda p, mode, **kw: False if Path(p) == net else real_access(p, mode, **kw)
    )
    code, _, err = main_in_process(capsys, *eval_args(out, "--scenarios", "2", net=net))
    assert_one_line(err, 2, code, str(net), "not readable")
    assert not out.exists()


@pytest.mark.sumo
def test_net_that_sumo_refuses_carries_sumos_own_message(tmp_path: Path) -> None:
    """Our checks (sumolib) accept it, SUMO does not: its reason, printed only on the C++ stderr, is in the line."""
    net = tmp_path / "bogus.net.xml"
    text = NET.read_text()
    assert 'type="priority"' in text
    net.write_text(text.replace('type="priority"', 'type="bogus"'))
    out = tmp_path / "out"
    line = assert_usage_error(run_cli(*eval_args(out, "--scenarios", "1", net=net)), str(net), "Error: ")
    assert "not a valid node type" in line, line
    assert "Process Error" not in line
    assert not out.exists() or not list(out.glob("*.csv"))

    # The Python API: the same message, as an error that is both bad input and a simulation error.
    from idas_sumo.errors import InputError, SimulationError
    from idas_sumo.sim.backend import SumoBackend, slot_taken
    from idas_sumo.sim.netgen import read_merge_net

    backend = SumoBackend(read_merge_net(net))
    try:
        with pytest.raises(SimulationError, match="not a valid node type") as err:
            backend.reset(_one_car())
        assert isinstance(err.value, InputError)
    finally:
        backend.close()
    assert not slot_taken()


# --- outputs ------------------------------------------------------------------------------------------


def test_output_directory_not_writable(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    if not IS_ROOT:
        locked.chmod(0o555)
        try:
            for args in (eval_args(locked / "out"), train_args(locked / "run", "--episodes", "1")):
                assert_usage_error(run_cli(*args), str(locked))
            assert_usage_error(run_cli("netgen", "--out", str(locked / "x.net.xml")), str(locked))
        finally:
            locked.chmod(0o755)
    # As root, an unwritable directory is simulated in process: os.access says no for it, and mkdir fails.
    real_access, real_mkdir = os.access, os.mkdir

    def no_write(p: Any, mode: int, **kw: Any) -> bool:
        inside = Path(p) == locked or locked in Path(p).parents
        return False if inside and mode & os.W_OK else real_access(p, mode, **kw)

    def no_mkdir(p: Any, *a: Any, **kw: Any) -> None:
        if locked in Path(p).parents:
            raise PermissionError(errno.EACCES, "Permission denied", str(p))
        real_mkdir(p, *a, **kw)

    monkeypatch.setattr(os, "access", no_write)
    monkeypatch.setattr(os, "mkdir", no_mkdir)
    for args in (eval_args(locked), train_args(locked, "--episodes", "1")):
        code, _, err = main_in_process(capsys, *args)
        assert_one_line(err, 2, code, str(locked), "not writable")
    for args in (eval_args(locked / "out"), train_args(locked / "run", "--episodes", "1")):
        code, _, err = main_in_process(capsys, *args)
        assert_one_line(
            err, 2, code, str(locked / ("out" if args[0] == "evaluate" else "run")), "Permission denied"
        )
    code, _, err = main_in_process(capsys, "netgen", "--out", str(locked / "x.net.xml"))
    assert_one_line(err, 2, code, str(locked), "not writable")
    assert list(locked.iterdir()) == []


def test_out_paths_that_are_files(tmp_path: Path) -> None:
    blocker = tmp_path / "afile"
    blocker.write_text("keep me\n")
    results = run_many(
        train_args(blocker, "--episodes", "1"),
        train_args(blocker / "run", "--episodes", "1"),
        ["netgen", "--out", str(blocker / "x.net.xml")],
        ["netgen", "--out", str(tmp_path)],
    )
    assert_usage_error(results[0], str(blocker), "not a directory")
    assert_usage_error(results[1], str(blocker / "run"))
    assert_usage_error(results[2], "--out", str(blocker))
    assert_usage_error(results[3], "--out", "directory")
    assert blocker.read_text() == "keep me\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


@pytest.mark.sumo
def test_disk_full_while_writing_csvs_keeps_the_previous_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import pandas as pd

    out = tmp_path / "out"
    code, _, _ = main_in_process(capsys, *eval_args(out, "--scenarios", "2"))
    assert code == 0
    before = snapshot(out)
    real_to_csv = pd.DataFrame.to_csv

    def half_then_full(self: pd.DataFrame, f: Any, **kw: Any) -> None:
        real_to_csv(self.iloc[: max(len(self) // 2, 1)], f, **kw)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pd.DataFrame, "to_csv", half_then_full)
    code, _, err = main_in_process(capsys, *eval_args(out, "--scenarios", "2", "--seed", "7", "--force"))
    assert_one_line(err, 1, code, "No space left on device")
    assert snapshot(out) == before  # the previous good CSVs are all there, byte for byte
    assert temp_files(out) == []


# --- runtime: Ctrl-C, SUMO dying, non-finite values ---------------------------------------------------


@pytest.mark.sumo
def test_ctrl_c_during_train_exits_130_with_a_loadable_checkpoint(tmp_path: Path) -> None:
    from idas_sumo.training.checkpoint import load_checkpoint

    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TRAIN_TOML)
    run = tmp_path / "run"
    args = train_args(run, "--config", str(config), "--stage", "robot", "--episodes", "100000")
    proc = subprocess.Popen(
        [sys.executable, "-m", "idas_sumo.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
    )
    metrics = run / "metrics.csv"

    def two_episodes_done() -> bool:
        return metrics.exists() and len(metrics.read_text().splitlines()) >= 3

    stderr = interrupt_when(proc, two_episodes_done)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    assert stderr.splitlines()[-1:] == [INTERRUPTED], repr(stderr)
    data = load_checkpoint(run / "checkpoint.pt")
    assert data.episode >= 2
    rows = metrics.read_text().splitlines()
    assert len(rows) - 1 >= data.episode
    assert temp_files(run) == []


def _one_car(vid: str = "ego", road: str = "main", pos: float = 50.0, speed: float = 10.0) -> Any:
    from idas_sumo.env.scenario import Scenario, VehicleSpec

    return Scenario("one", (VehicleSpec(vid, road, pos, speed),))  # type: ignore[arg-type]


@pytest.mark.sumo
def test_sumo_subprocess_dying_is_a_prompt_simulation_error() -> None:
    from idas_sumo.errors import SimulationError
    from idas_sumo.sim.backend import SubprocessBackend
    from idas_sumo.sim.netgen import read_merge_net

    backend = SubprocessBackend(read_merge_net(NET))
    try:
        backend.reset(_one_car())
        backend.step()
        os.kill(backend._proc.pid, signal.SIGKILL)
        backend._proc.wait(timeout=10)
        started = time.monotonic()
        with pytest.raises(SimulationError, match="died"):
            backend.step()
        assert time.monotonic() - started < 10.0
        with pytest.raises(SimulationError):
            backend.vehicle_states()
    finally:
        backend.close()
    backend.close()  # twice is fine


@pytest.fixture
def parallel_env() -> Any:
    from idas_sumo.env import MergeParallelEnv
    from idas_sumo.env.scenario import Scenario, VehicleSpec

    scenario = Scenario(
        "two",
        (VehicleSpec("m0", "main", 120.0, 15.0, 1.0), VehicleSpec("g0", "merge", 100.0, 12.0, -1.0)),
    )
    env = MergeParallelEnv(scenario=scenario, seed=0)
    env.reset(seed=0)
    yield env
    env.close()


@pytest.mark.sumo
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), 2.0, 7, -1, np.int64(9), "2", None, True])
def test_invalid_action_names_the_agent(parallel_env: Any, bad: Any) -> None:
    actions = dict.fromkeys(parallel_env.agents, 2)
    actions["g0"] = bad
    with pytest.raises(ValueError, match=r"'g0'.*t = ") as err:
        parallel_env.step(actions)
    assert "\n" not in str(err.value)
    # Refused at the boundary: nothing was applied, the episode goes on.
    obs, *_ = parallel_env.step(dict.fromkeys(parallel_env.agents, 2))
    assert set(obs) == {"m0", "g0"}


@pytest.mark.sumo
def test_non_finite_observation_names_the_agent(parallel_env: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    import idas_sumo.env.contracts as contracts
    import idas_sumo.env.engine as engine_module
    from idas_sumo.errors import SimulationError

    real = contracts.build_observations_checked

    def poisoned(snapshot: Any, egos: Any, prev_accel: Any, *args: Any) -> Any:
        prev_accel = np.array(prev_accel, dtype=np.float64)
        prev_accel[-1] = np.nan  # the last agent asked for: a NaN in its acceleration scalar
        return real(snapshot, egos, prev_accel, *args)

    monkeypatch.setattr(contracts, "build_observations_checked", poisoned)
    # The env's engine builds the observations with the masks (``observe_own_lane_obs``): poisoned there too.
    real_observe = engine_module.observe_own_lane_obs

    def poisoned_observe(
        snap: Any, row_copy: Any, car_row: Any, car_accel: Any, agent_car: Any, *args: Any
    ) -> Any:
        car_accel = np.array(car_accel, dtype=np.float64)
        car_accel[agent_car[-1]] = np.nan
        return real_observe(snap, row_copy, car_row, car_accel, agent_car, *args)

    monkeypatch.setattr(engine_module, "observe_own_lane_obs", poisoned_observe)
    with pytest.raises(SimulationError, match=r"non-finite observation for agent 'g0' at t = "):
        parallel_env.step(dict.fromkeys(parallel_env.agents, 2))


@pytest.mark.parametrize("speed", [np.nan, np.inf, 1e40])
def test_a_non_finite_relative_speed_in_a_grid_names_the_agent(speed: float) -> None:
    """The observation check tests every entry only when the speeds could make a grid non-finite; a car in
    sight with such a speed (NaN, inf, or a spread beyond float32) is caught there, not missed."""
    from idas_sumo.env.engine import AgentBatch
    from idas_sumo.env.snapshot import MAIN, TrafficSnapshot
    from idas_sumo.errors import SimulationError

    snapshot = TrafficSnapshot(
        ids=("ego", "ahead"),
        road=np.array([MAIN, MAIN]),
        dist_to_merge_m=np.array([80.0, 60.0]),
        speed_mps=np.array([10.0, speed]),
        accel_mps2=np.zeros(2),
        length_m=np.full(2, 5.0),
        speed_limit_mps=np.full(2, 20.0),
    )
    batch = AgentBatch(
        ids=("ego",),
        copy=np.zeros(1, dtype=np.int64),
        egos=np.array([0]),
        prev_accel=np.zeros(1),
        masks=np.ones((1, 7), dtype=np.int8),
        snapshot=snapshot,
        b_prio=np.zeros(1),
        b_type=np.zeros(1),
        time_s=3.0,
    )
    with pytest.raises(SimulationError, match=r"non-finite observation for agent 'ego' at t = 3.0 s"):
        _ = batch.obs


@pytest.mark.sumo
def test_vehicle_removed_by_sumo_is_accounted_for(parallel_env: Any) -> None:
    parallel_env.sim.backend.raw_call("vehicle", "remove", "g0")
    obs, rewards, terms, _, infos = parallel_env.step(dict.fromkeys(parallel_env.agents, 2))
    assert terms["g0"] is True and END_REASONS[infos["g0"]["end_reason"]] == "removed"
    assert rewards["g0"] == 0.0
    assert parallel_env.agents == ["m0"]
    obs, *_ = parallel_env.step({"m0": 2})
    assert set(obs) == {"m0"}


# --- environments -------------------------------------------------------------------------------------


@pytest.mark.sumo
def test_two_parallel_envs_in_one_process_run_independently() -> None:
    """The second env gets SUMO in a subprocess; lockstep with the same seed gives the same episode."""
    from idas_sumo.env import MergeParallelEnv
    from idas_sumo.env.scenario import TrafficConfig
    from idas_sumo.sim.backend import SubprocessBackend, SumoBackend

    traffic = TrafficConfig(n_vehicles=4, min_vehicles_per_road=2, max_vehicles_per_road=2)
    first = MergeParallelEnv(traffic=traffic, seed=5)
    second = MergeParallelEnv(traffic=traffic, seed=5)
    try:
        obs_a, _ = first.reset(seed=5)
        obs_b, _ = second.reset(seed=5)
        assert isinstance(first.sim.backend, SumoBackend)
        assert isinstance(second.sim.backend, SubprocessBackend)
        for _ in range(25):
            assert sorted(obs_a) == sorted(obs_b)
            for agent in obs_a:
                np.testing.assert_array_equal(obs_a[agent]["observation"], obs_b[agent]["observation"])
            if not first.agents:
                break
            actions = {a: int(np.flatnonzero(obs_a[a]["action_mask"])[0]) for a in first.agents}
            obs_a, *_ = first.step(actions)
            obs_b, *_ = second.step(actions)
        # Closing one leaves the other running.
        second.close()
        if first.agents:
            first.step(dict.fromkeys(first.agents, 2))
        first.reset(seed=6)
    finally:
        second.close()
        first.close()


def test_env_with_a_scenario_above_the_speed_limit_is_refused() -> None:
    from idas_sumo.env import MergeParallelEnv
    from idas_sumo.errors import InputError

    with pytest.raises(InputError, match=r"'fast'.*above the main road's limit"):
        MergeParallelEnv(scenario=_one_car("fast", "main", 50.0, 25.0))


def test_gui_without_a_display(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    results = run_many(
        eval_args(tmp_path / "eval", "--gui", "--scenarios", "1"),
        train_args(tmp_path / "run", "--gui", "--episodes", "1"),
        env=env,
    )
    for result in results:
        assert_usage_error(result, "--gui", "display")
    assert list(tmp_path.iterdir()) == []  # refused before any directory or file is made


@pytest.mark.sumo
def test_gui_without_a_display_through_the_python_api() -> None:
    from idas_sumo.env import MergeParallelEnv
    from idas_sumo.errors import InputError
    from idas_sumo.sim.backend import slot_taken

    saved = {k: os.environ.pop(k) for k in ("DISPLAY", "WAYLAND_DISPLAY") if k in os.environ}
    try:
        env = MergeParallelEnv(seed=0, gui=True)
        with pytest.raises(InputError, match="display"):
            env.reset(seed=0)
        env.close()
        assert not slot_taken()
    finally:
        os.environ.update(saved)
