"""Issue #16: nothing a user types, and nothing the machine does, ends in a traceback or a lie.

Each test here failed before its fix. CLI cases run the real command line (``python -m idas_sumo.cli``)
in a subprocess; the helpers come from test_hardening (issue #7), whose contract this extends: exit 2
and one ``idas-sumo: error: ...`` line for bad input, 130 / 143 and one line for Ctrl-C / SIGTERM.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from conftest import checkpoint_payload, interrupt_when, run_cli
from test_hardening import (
    REPO_ROOT,
    assert_one_line,
    assert_usage_error,
    eval_args,
    run_many,
    train_args,
)

from idas_sumo.resources import DEFAULT_NET as NET

# --- helpers ------------------------------------------------------------------------------------------


def _learner() -> Any:
    from idas_sumo.agents.learner import Learner, LearnerConfig

    return Learner(LearnerConfig(), seed=1)


def build_net(path: Path, length_m: float = 250.0, junction: str = "priority") -> Path:
    """A merge net of the right shape with every road ``length_m`` long and a merge junction of type
    ``junction``, built with the project's own plain XML and netconvert (``generate_net``'s NetParams
    refuses such lengths, as it should)."""
    from idas_sumo.sim.netgen import MERGE_JUNCTION, NetParams, _plain_xml, sumo_binary

    fields = dataclasses.asdict(NetParams())
    fields.update(main_length_m=length_m, merge_length_m=length_m, out_length_m=length_m)
    node_xml, edge_xml = _plain_xml(SimpleNamespace(**fields))  # type: ignore[arg-type]
    merge_node = f'<node id="{MERGE_JUNCTION}" x="0.000" y="0.000" type="priority"/>'
    assert merge_node in node_xml
    node_xml = node_xml.replace(merge_node, merge_node.replace('"priority"', f'"{junction}"'))
    nod, edg = path.with_suffix(".nod.xml"), path.with_suffix(".edg.xml")
    nod.write_text(node_xml)
    edg.write_text(edge_xml)
    cmd = [str(sumo_binary("netconvert")), "--node-files", str(nod), "--edge-files", str(edg)]
    subprocess.run(
        [*cmd, "--output-file", str(path), "--no-warnings", "true"], check=True, capture_output=True
    )
    return path


def popen_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "idas_sumo.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO_ROOT,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
    )


def descendants_of(pid: int) -> list[int]:
    """The pids of ``pid``'s children, their children, and so on (Linux /proc)."""
    found = children_of(pid)
    for child in list(found):
        found += descendants_of(child)
    return found


def children_of(pid: int) -> list[int]:
    """The pids of ``pid``'s child processes (Linux /proc)."""
    found = []
    for status in Path("/proc").glob("[0-9]*/status"):
        with contextlib.suppress(OSError):
            fields = dict(line.split(":\t", 1) for line in status.read_text().splitlines() if ":\t" in line)
            if fields.get("PPid", "").strip() == str(pid):
                found.append(int(status.parent.name))
    return found


TINY_TOML = """\
episodes_per_update = 1
checkpoint_every = 1000
max_episode_s = 12.0
[robot_traffic]
min_vehicles_per_road = 2
max_vehicles_per_road = 4
max_controlled = 1
[intelligent_traffic]
min_vehicles_per_road = 2
max_vehicles_per_road = 4
"""
"""A run of a few seconds (test_hardening's TINY_TRAIN_TOML, with room for the paper's 8 cars)."""


def tiny_config(tmp_path: Path) -> Path:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TOML)
    return config


# --- net geometry -------------------------------------------------------------------------------------


@pytest.mark.sumo
def test_net_with_roads_too_short_or_too_long_is_refused(tmp_path: Path) -> None:
    """1 m roads made every scenario collide and 100 km roads every episode time out, both with exit 0.
    Short approaches run now (their starts drawn on what they have); a 1 m road after the merge cannot
    hold the finish line."""
    short = build_net(tmp_path / "short.net.xml", 1.0)
    long = build_net(tmp_path / "long.net.xml", 100_000.0)
    results = run_many(
        eval_args(tmp_path / "e1", "--scenarios", "2", net=short),
        eval_args(tmp_path / "e2", "--scenarios", "2", net=long),
        eval_args(tmp_path / "e3", "--suite", "representative", net=short),
        ["train", "--net", str(short), "--out", str(tmp_path / "t1"), "--episodes", "1", "--no-progress"],
        ["train", "--net", str(long), "--out", str(tmp_path / "t2"), "--episodes", "1", "--no-progress"],
    )
    for result, net in zip(results, [short, long, short, short, long], strict=True):
        road = "outgoing road" if net == short else "main road"
        line = assert_usage_error(result, str(net), road, "m long", "need")
        assert "finish" in line, line
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_dir()) == []  # nothing was started


@pytest.mark.sumo
def test_scenario_file_car_beyond_the_road_is_refused(tmp_path: Path) -> None:
    """A car 1e308 m down a 250 m road ran with exit 0 (``check_against_net`` got no road lengths)."""
    scenario = tmp_path / "far.toml"
    scenario.write_text(
        'name = "far"\n[[vehicles]]\nid = "ego"\nroad = "main"\nstart_pos_m = 1e308\nspeed_mps = 10.0\n'
    )
    result = run_cli(*eval_args(tmp_path / "out", "--scenario", str(scenario)))
    assert_usage_error(result, str(scenario), "'ego'", "beyond the main road's length")
    assert not (tmp_path / "out").exists()


def test_road_bounds_follow_from_the_scenarios() -> None:
    """The bounds: none below on an approach (starts are drawn on what it has); a car from its start must
    finish in time; the road after the merge holds the finish line and the sensor range."""
    from idas_sumo.env.net_needs import check_road_lengths, road_needs
    from idas_sumo.errors import InputError
    from idas_sumo.sim.netgen import MergeNet, RoadInfo

    def net(main_m: float, out_m: float = 150.0) -> MergeNet:
        road = RoadInfo("main", main_m, 20.0, 2)
        return MergeNet(
            Path("n.net.xml"), road, RoadInfo("merge", 250.0, 15.0, 1), RoadInfo("out", out_m, 20.0, 2), "j"
        )

    needs = road_needs(200.0, 60.0)
    check_road_lengths(net(250.0), needs)  # the paper's net
    check_road_lengths(net(1155.0), needs)  # 5 m + 20 m/s * (60 s - 50 m / 20 m/s)
    check_road_lengths(net(11.0), needs)  # shorter than the start range and the sensor range
    for bad in (net(1156.0), net(250.0, out_m=99.0)):
        with pytest.raises(InputError, match=r"n\.net\.xml"):
            check_road_lengths(bad, needs)
    # A shorter episode (a smoke run) does not shrink the bound below the evaluation's 60 s.
    assert road_needs(200.0, 15.0).episode_s == needs.episode_s == 60.0
    assert road_needs(None, 60.0).min_out_m == needs.min_out_m == 100.0


@pytest.mark.sumo
def test_netgen_warns_about_a_net_the_scenarios_cannot_use(tmp_path: Path) -> None:
    result = run_cli("netgen", "--out", str(tmp_path / "n.net.xml"), "--main-length", "5000")
    assert result.returncode == 0, result.stderr
    assert "warning" in result.stderr and "main road" in result.stderr, result.stderr


# --- --policy, checksums ------------------------------------------------------------------------------


def test_policy_for_a_rule_based_baseline_is_refused(tmp_path: Path) -> None:
    exists = tmp_path / "p.pt"
    exists.write_bytes(b"x")
    missing = tmp_path / "missing.pt"
    results = run_many(
        eval_args(tmp_path / "o1", "--policy", str(exists), baseline="idm"),
        eval_args(tmp_path / "o2", "--policy", str(missing), baseline="fsm_idm"),
        eval_args(tmp_path / "o3", "--policy", str(missing), baseline="idas"),
        eval_args(tmp_path / "o4", "--policy", str(missing), baseline="all"),
    )
    assert_usage_error(results[0], "--policy only applies to the learned methods", "--baseline idm")
    assert_usage_error(results[1], "--policy only applies to the learned methods", "--baseline fsm_idm")
    assert_usage_error(results[2], str(missing), "not found")
    assert_usage_error(results[3], str(missing), "not found")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.pt"]


def _flip_a_weight_byte(path: Path) -> None:
    """Flip one bit inside the actor's first weight tensor's bytes (torch's zip does not notice)."""
    import torch

    raw = torch.load(path, weights_only=True)
    tensor = next(iter(raw["learner"]["actor"].values()))
    needle = tensor.contiguous().numpy().tobytes()[:64]
    data = bytearray(path.read_bytes())
    at = data.find(needle)
    assert at > 0 and data.find(needle, at + 1) < 0, "the weight bytes must be found exactly once"
    data[at + 10] ^= 0x01
    path.write_bytes(bytes(data))


def test_flipped_bytes_in_a_checkpoint_are_refused(tmp_path: Path) -> None:
    import torch

    from idas_sumo.agents.checkpoint_file import load_actor
    from idas_sumo.errors import InputError
    from idas_sumo.training.checkpoint import load_checkpoint, save_checkpoint

    path = tmp_path / "c.pt"
    save_checkpoint(path, checkpoint_payload(_learner()))
    _flip_a_weight_byte(path)
    torch.load(path, weights_only=True)  # torch itself loads it: the damage is silent without a checksum
    for load in (load_checkpoint, load_actor):
        with pytest.raises(InputError) as err:
            load(path)
        assert str(err.value).startswith(f"{path}: checksum mismatch"), err.value
    result = run_cli(*eval_args(tmp_path / "out", "--scenarios", "1", "--policy", str(path), baseline="idas"))
    assert_usage_error(result, str(path), "checksum mismatch")


def test_checkpoints_without_a_checksum(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """Older files (no checksum) load with a warning; the shipped ones are checked against their
    metadata's file_sha256, and a damaged copy of one beside its metadata is refused."""
    import torch

    from idas_sumo.agents.checkpoint_file import CHECKSUM_KEY, load_actor
    from idas_sumo.errors import InputError
    from idas_sumo.resources import POLICY_DIR
    from idas_sumo.training.checkpoint import load_checkpoint

    old = tmp_path / "old.pt"
    data = checkpoint_payload(_learner()).to_dict()
    del data[CHECKSUM_KEY]
    torch.save(data, old)
    with caplog.at_level("WARNING"):
        assert load_checkpoint(old).episode == 7
    assert any("no checksum" in r.getMessage() and str(old) in r.getMessage() for r in caplog.records)

    caplog.clear()
    for shipped in sorted(POLICY_DIR.glob("*.pt")):
        assert "file_sha256" in json.loads(shipped.with_suffix(".json").read_text())
        with caplog.at_level("WARNING"):
            load_actor(shipped)
    assert not caplog.records  # verified, no warning

    copy = tmp_path / "idas.pt"
    shutil.copy(POLICY_DIR / "idas.pt", copy)
    shutil.copy(POLICY_DIR / "idas.json", tmp_path / "idas.json")
    load_actor(copy)
    _flip_a_weight_byte(copy)
    with pytest.raises(InputError, match="checksum mismatch"):
        load_actor(copy)


# --- --seed, --workers, --copies ----------------------------------------------------------------------


def test_seed_outside_sumos_range_is_refused_naming_the_flag(tmp_path: Path) -> None:
    cases = []
    for value in ("-1", str(2**31), str(2**64), "1e3"):
        cases.append(eval_args(tmp_path / "e", "--seed", value))
        cases.append(train_args(tmp_path / "t", "--seed", value))
    for result in run_many(*cases):
        assert "argument --seed" in result.stderr
        assert_one_line(result.stderr, 2, result.returncode, "--seed")
    config = tmp_path / "seed.toml"
    config.write_text(f"seed = {2**31}\n")
    result = run_cli(*train_args(tmp_path / "t", "--config", str(config)))
    assert_usage_error(result, str(config), "seed", str(2**31))
    assert not (tmp_path / "t").exists() and not (tmp_path / "e").exists()


def test_seeds_at_the_top_of_the_range_run(tmp_path: Path) -> None:
    """The largest seed is accepted, and the workers' seeds next to it stay in SUMO's range."""
    from idas_sumo.sim.processes import SEED_LIMIT, derived_seed

    assert derived_seed(SEED_LIMIT - 1, 1) == 0 and derived_seed(5, 2) == 7


def test_workers_and_copies_are_bounded(tmp_path: Path) -> None:
    from idas_sumo.sim.multinet import MAX_COPIES
    from idas_sumo.sim.processes import max_workers

    too_many = str(max_workers() + 1)
    config = tmp_path / "w.toml"
    config.write_text("workers = 1000\n")
    start = time.monotonic()
    results = run_many(
        eval_args(tmp_path / "e", "--workers", "1000"),
        eval_args(tmp_path / "e", "--workers", too_many),
        eval_args(tmp_path / "e", "--copies", str(MAX_COPIES + 1)),
        train_args(tmp_path / "t", "--workers", too_many),
        train_args(tmp_path / "t", "--copies", str(10**9)),
        train_args(tmp_path / "t", "--config", str(config)),
    )
    assert time.monotonic() - start < 30  # refused up front, not after forking
    assert_usage_error(results[0], "--workers", "1000", "CPUs")
    assert_usage_error(results[1], "--workers", too_many, "CPUs")
    assert_usage_error(results[2], "--copies", str(MAX_COPIES))
    assert_usage_error(results[3], "--workers", too_many)
    assert_usage_error(results[4], "--copies")
    assert_usage_error(results[5], str(config), "workers", "1000", "CPUs")


# --- files that are not regular files -----------------------------------------------------------------


def test_fifo_as_an_input_file_is_refused(tmp_path: Path) -> None:
    """Reading a FIFO blocks until someone writes to it: --net once hung forever."""
    from idas_sumo.agents.checkpoint_file import load_actor
    from idas_sumo.errors import InputError
    from idas_sumo.sim.netgen import read_merge_net

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    results = run_many(
        eval_args(tmp_path / "o", net=fifo),
        train_args(tmp_path / "t", "--config", str(fifo)),
        ["train", "--net", str(fifo), "--out", str(tmp_path / "t"), "--no-progress"],
        eval_args(tmp_path / "o", "--policy", str(fifo), baseline="idas"),
        eval_args(tmp_path / "o", "--config", str(fifo)),
        eval_args(tmp_path / "o", "--scenario", str(fifo)),
        eval_args(tmp_path / "o", "--scenario", "/dev/zero"),
    )
    plotted = tmp_path / "plotted"
    plotted.mkdir()
    os.mkfifo(plotted / "episodes.csv")
    results.append(run_cli("plot", str(plotted), timeout=30))
    for result in results:
        assert_usage_error(result, "not a regular file")
    for read in (read_merge_net, load_actor):
        with pytest.raises(InputError, match="not a regular file"):
            read(fifo)


# --- disk full ----------------------------------------------------------------------------------------


def on_small_tmpfs(disk: Path, size: str, shell: str) -> subprocess.CompletedProcess[str]:
    """Run ``shell`` (sh) with a real tmpfs of ``size`` mounted at ``disk``, in a private mount namespace
    (``unshare``: as root, or as a user through a user namespace), so the mount vanishes with the
    command, whatever happens to the test. A full tmpfs fails writes with ENOSPC, as a full disk does."""
    disk.mkdir()
    mount = f"mount -t tmpfs -o size={size} tmpfs {disk} || exit 99; "
    result = subprocess.run(
        ["unshare", "--mount", "--map-root-user", "sh", "-c", mount + shell],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        timeout=180,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert result.returncode != 99, f"cannot mount a tmpfs here: {result.stderr}"
    return result


SAVE_ON_A_FULL_DISK = """
import sys
sys.path.insert(0, "tests")
from pathlib import Path
from conftest import checkpoint_payload
from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.training.checkpoint import load_checkpoint, save_checkpoint
path = Path(sys.argv[1])
learner = Learner(LearnerConfig(), seed=1)
save_checkpoint(path, checkpoint_payload(learner))  # ~1.8 MB: fits once, not twice
before = path.read_bytes()
try:
    save_checkpoint(path, checkpoint_payload(learner, episode=99))
except OSError as err:
    assert err.filename == str(path), err.filename
    print("OSError:", err)
else:
    raise AssertionError("the second checkpoint fit on the disk")
assert path.read_bytes() == before and load_checkpoint(path).episode == 7
print("left:", sorted(p.name for p in path.parent.iterdir()))
"""


def test_disk_full_while_saving_a_checkpoint_names_the_file(tmp_path: Path) -> None:
    """torch's own write turns ENOSPC into a RuntimeError ("unexpected pos ..."): it must be the OSError
    it is, naming the checkpoint, with the previous file intact and no temp file left."""
    disk = tmp_path / "disk"
    script = tmp_path / "save.py"
    script.write_text(SAVE_ON_A_FULL_DISK)
    result = on_small_tmpfs(disk, "3m", f"{sys.executable} {script} {disk / 'checkpoint.pt'}")
    assert result.returncode == 0, result.stderr
    assert f"OSError: [Errno 28] No space left on device: '{disk / 'checkpoint.pt'}'" in result.stdout
    assert "left: ['checkpoint.pt']" in result.stdout, result.stdout


@pytest.mark.sumo
def test_disk_full_during_train_is_one_line_naming_the_checkpoint(tmp_path: Path) -> None:
    disk = tmp_path / "disk"
    run = disk / "run"
    args = train_args(run, "--config", str(tiny_config(tmp_path)), "--stage", "robot", "--episodes", "1")
    command = " ".join([sys.executable, "-m", "idas_sumo.cli", *args])
    result = on_small_tmpfs(disk, "1m", f"{command}; code=$?; ls -a {run}; exit $code")
    line = assert_one_line(result.stderr, 1, result.returncode, "No space left on device")
    # The first checkpoint the run writes (robot.pt, its final one here), by its full path.
    assert f"error: {run}/" in line and ".pt: No space left on device" in line, line
    assert ".tmp" not in result.stdout, result.stdout


@pytest.mark.sumo
def test_disk_full_while_writing_csvs_names_the_file(tmp_path: Path) -> None:
    """The write of a CSV names no file when the disk is full: the line said only "No space left"."""
    disk = tmp_path / "disk"
    out = disk / "out"
    command = " ".join([sys.executable, "-m", "idas_sumo.cli", *eval_args(out, "--scenarios", "30")])
    result = on_small_tmpfs(disk, "4k", command)
    line = assert_one_line(result.stderr, 1, result.returncode, "No space left on device")
    assert f"error: {out}/" in line and ".csv: No space left on device" in line, line


# --- stale temp files ---------------------------------------------------------------------------------


@pytest.mark.sumo
def test_stale_temp_files_are_removed_when_a_run_starts(tmp_path: Path) -> None:
    """Writes killed by SIGKILL leave ``.checkpoint.pt.XXXX.tmp`` (MBs each): the next run removes them."""
    run, out = tmp_path / "run", tmp_path / "eval"
    config = tiny_config(tmp_path)
    stale = [".checkpoint.pt.k1l2l3ed.tmp", ".metrics.csv.abcd1234.tmp"]
    for directory in (run, out):
        directory.mkdir()
        for name in stale:
            (directory / name).write_bytes(b"\0" * 1000)
    (run / "keep.tmp").write_text("not ours: no leading dot")
    results = run_many(
        train_args(run, "--config", str(config), "--stage", "robot", "--episodes", "1", "--force"),
        eval_args(out, "--scenarios", "1", "--force"),
    )
    for result in results:
        assert result.returncode == 0, result.stderr
    for directory in (run, out):
        assert not [p.name for p in directory.iterdir() if p.name in stale]
    assert (run / "keep.tmp").exists()


# --- Ctrl-C and SIGTERM ---------------------------------------------------------------------------------


@pytest.mark.sumo
@pytest.mark.parametrize("command", ["train", "evaluate"])
def test_ctrl_c_while_two_workers_start_is_one_line(tmp_path: Path, command: str) -> None:
    """It printed 31 lines of worker tracebacks; now: one line, exit 130, no worker left."""
    if command == "train":
        args = train_args(tmp_path / "run", "--config", str(tiny_config(tmp_path)), "--workers", "2")
    else:
        args = eval_args(tmp_path / "out", "--scenarios", "4", "--workers", "2", "--copies", "1")
    proc = popen_cli(*args)
    workers: list[int] = []
    # train's two workers are forks of its fork server, a third process (sim/rpc.py: ForkServer)
    expected = 3 if command == "train" else 2

    def workers_started() -> bool:
        workers[:] = descendants_of(proc.pid)
        return len(workers) >= expected

    stderr = interrupt_when(proc, workers_started, settle_s=0.3)
    assert proc.returncode == 130, stderr
    # (A tiny round may be over before the stop: train then says where it saved it, on a line before.)
    lines = [line for line in stderr.splitlines() if not line.startswith("WARNING interrupted: saved ")]
    assert lines == ["idas-sumo: interrupted; completed outputs were kept"], stderr
    assert len(workers) >= expected
    assert all(not Path(f"/proc/{pid}").exists() or _is_zombie(pid) for pid in workers)


@pytest.mark.sumo
def test_ctrl_c_while_the_fork_server_imports_leaves_no_process(tmp_path: Path) -> None:
    """Ctrl-C while train's fork server still imports (before any worker): one line, exit 130, nothing left."""
    args = train_args(tmp_path / "run", "--config", str(tiny_config(tmp_path)), "--workers", "2")
    proc = popen_cli(*args)
    started: list[int] = []

    def fork_server_started() -> bool:
        started[:] = descendants_of(proc.pid)
        return len(started) >= 1

    stderr = interrupt_when(proc, fork_server_started, settle_s=0.2)
    assert proc.returncode == 130, stderr
    assert stderr.splitlines() == ["idas-sumo: interrupted; completed outputs were kept"], stderr
    assert started and all(not Path(f"/proc/{pid}").exists() or _is_zombie(pid) for pid in started)


def _is_zombie(pid: int) -> bool:
    with contextlib.suppress(OSError):
        return "\nState:\tZ" in Path(f"/proc/{pid}/status").read_text()
    return True


def test_ctrl_c_while_the_run_cleans_up_is_not_exit_0(tmp_path: Path) -> None:
    """Ctrl-C as a run finishes landed in an exit handler (closing SUMO): a traceback, then exit 0. Now
    the cleanup completes, and the exit says the run was interrupted."""
    script = (
        "import atexit, os, signal, sys, time\n"
        "from idas_sumo import cli\n"
        "from idas_sumo.cli import netgen as command\n"
        "def cleanup():  # an exit handler like the SUMO backend's; Ctrl-C arrives while it runs\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    time.sleep(0.3)\n"
        "    print('cleanup done', file=sys.stderr)\n"
        "real = command.run\n"
        "def netgen(args):\n"
        "    atexit.register(cleanup)  # registered during the command, as the backend's is on import\n"
        "    return real(args)\n"
        "command.run = netgen\n"
        f"sys.argv = ['idas-sumo', 'netgen', '--out', {str(tmp_path / 'n.net.xml')!r}]\n"
        "sys.exit(cli.main())\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO_ROOT)
    assert "Traceback" not in result.stderr and "Exception ignored" not in result.stderr, result.stderr
    assert result.returncode == 130, result.stderr
    assert result.stderr.splitlines() == [
        "cleanup done",
        "idas-sumo: interrupted; completed outputs were kept",
    ]
    assert (tmp_path / "n.net.xml").exists()


@pytest.mark.sumo
@pytest.mark.parametrize(
    ("workers", "signum"), [("1", signal.SIGTERM), ("2", signal.SIGTERM), ("2", signal.SIGHUP)]
)
def test_sigterm_during_evaluate_is_143_and_leaks_no_temp_dir(
    tmp_path: Path, workers: str, signum: signal.Signals
) -> None:
    """SIGTERM (and SIGHUP, a closed terminal, which killed the run without any cleanup) stop a run
    as Ctrl-C does: one line, exit 128 + the signal, nothing left in the temp directory."""
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    args = eval_args(tmp_path / "out", "--scenarios", "40", "--workers", workers, "--copies", "2")
    proc = popen_cli(*args, env={"TMPDIR": str(tmpdir)})

    def sumo_running() -> bool:
        return any(tmpdir.rglob("*.rou.xml"))

    stderr = interrupt_when(proc, sumo_running, settle_s=0.5, signum=signum)
    assert proc.returncode == 128 + signum, stderr
    assert stderr.splitlines() == [f"idas-sumo: terminated ({signum.name}); completed outputs were kept"], (
        stderr
    )
    time.sleep(0.5)  # a killed worker's files would be gone by now, or never
    assert list(tmpdir.glob("idas_sumo*")) == []  # torch may keep its own cache there
    assert not (tmp_path / "out").exists()


@pytest.mark.sumo
def test_sigterm_during_train_is_143_and_leaks_no_temp_dir(tmp_path: Path) -> None:
    tmpdir = tmp_path / "tmp"
    tmpdir.mkdir()
    run = tmp_path / "run"
    args = train_args(run, "--config", str(tiny_config(tmp_path)), "--stage", "robot", "--episodes", "100000")
    proc = popen_cli(*args, env={"TMPDIR": str(tmpdir)})
    metrics = run / "metrics.csv"
    stderr = interrupt_when(
        proc, lambda: metrics.exists() and len(metrics.read_text().splitlines()) >= 2, signum=signal.SIGTERM
    )
    assert proc.returncode == 143, stderr
    assert stderr.splitlines()[-1].startswith("idas-sumo: terminated (SIGTERM)"), stderr
    assert "Traceback" not in stderr
    assert list(tmpdir.glob("idas_sumo*")) == []  # torch may keep its own cache there
    assert (run / "checkpoint.pt").exists()


# --- the shared worker start-up -----------------------------------------------------------------------


def test_worker_start_up_lives_in_one_module() -> None:
    """train and evaluate start workers through sim/processes.py, not each its own subprocess code; and
    the SUMO child and the workers share one launcher and handshake, sim/rpc.py."""
    package = REPO_ROOT / "idas_sumo"
    for module in ("training/workers.py", "evaluation/workers.py"):
        source = (package / module).read_text()
        assert "WorkerProcesses" in source, module
        assert "subprocess" not in source and "Listener" not in source, module
    rpc = package / "sim" / "rpc.py"
    assert all(s in rpc.read_text() for s in ("deliver_challenge(", "sys.executable", "create_server"))
    for path in set(package.rglob("*.py")) - {rpc}:
        source = path.read_text()
        for own_stack in ("challenge(", "sys.executable", "token_bytes", "urandom", "create_server"):
            assert own_stack not in source, (path, own_stack)


# --- siblings found by trying more bad inputs -----------------------------------------------------------


@pytest.mark.sumo
def test_more_bad_inputs_are_one_line_exit_2(tmp_path: Path) -> None:
    """Each of these was a traceback, an exit 1, a SUMO error mid-run or a hang before."""
    text = NET.read_text()
    assert 'speed="20.00"' in text
    zero = tmp_path / "zero.net.xml"
    zero.write_text(text.replace('speed="20.00"', 'speed="0.00"'))  # ZeroDivisionError
    fast = tmp_path / "fast.net.xml"
    fast.write_text(text.replace('speed="20.00"', 'speed="60.00"'))  # SUMO: departure speed too high
    short_episodes = tmp_path / "short.toml"
    short_episodes.write_text("max_episode_s = 0.5\n")  # every episode a timeout (0.01: a traceback)
    deep = tmp_path / "deep.toml"
    deep.write_text("x = " + "[" * 100_000 + "]" * 100_000 + "\n")  # a RecursionError in tomllib
    signal_net = build_net(tmp_path / "signal.net.xml", junction="traffic_light")  # ran, exit 0
    long_name = str(tmp_path / ("a" * 300))
    cases = {
        "zero speed": (eval_args(tmp_path / "o", net=zero), [str(zero), "speed limit of 0 m/s"]),
        "too fast": (eval_args(tmp_path / "o", net=fast), [str(fast), "speed limit of 60 m/s", "top speed"]),
        "0.5 s episodes": (
            eval_args(tmp_path / "o", "--config", str(short_episodes)),
            [str(short_episodes), "max_episode_s = 0.5 s", "time out"],
        ),
        "0.5 s training": (
            train_args(tmp_path / "o", "--config", str(short_episodes)),
            [str(short_episodes), "max_episode_s = 0.5 s", "time out"],
        ),
        "deep TOML": (eval_args(tmp_path / "o", "--config", str(deep)), [str(deep), "nested too deeply"]),
        "traffic light": (
            eval_args(tmp_path / "o", net=signal_net),
            [str(signal_net), "signal (traffic_light)"],
        ),
        "netgen /proc": (["netgen", "--out", "/proc/x.net.xml"], ["--out /proc/x.net.xml", "cannot write"]),
        "scenarios 1e9": (eval_args(tmp_path / "o", "--scenarios", str(10**9)), ["--scenarios", "at most"]),
        "long --net": (eval_args(tmp_path / "o", net=Path(long_name)), ["File name too long"]),
        "long --out": (eval_args(Path(long_name), "--scenarios", "1"), ["File name too long"]),
        "long train --out": (train_args(Path(long_name), "--episodes", "1"), ["File name too long"]),
    }
    start = time.monotonic()
    results = run_many(*(args for args, _ in cases.values()))
    assert time.monotonic() - start < 60
    for (name, (_, needles)), result in zip(cases.items(), results, strict=True):
        try:
            assert_usage_error(result, *needles)
        except AssertionError as err:
            raise AssertionError(f"case {name}: {err}") from None
    assert not (tmp_path / "o").exists()


# --- SIGKILL and --resume -----------------------------------------------------------------------------

KILL_TOML = TINY_TOML.replace("checkpoint_every = 1000", "checkpoint_every = 1")


def _kill_once_metrics_reach(command: list[str], metrics: Path, lines: int) -> None:
    """Start ``command`` and SIGKILL it (no cleanup at all) once ``metrics`` holds ``lines`` lines."""
    proc = popen_cli(*command)
    try:
        deadline = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < deadline:
            # checkpoint.pt exists from the run's start (its starting point is saved first).
            if metrics.exists() and len(metrics.read_text().splitlines()) >= lines:
                break
            time.sleep(0.01)
        assert proc.poll() is None, f"finished before the kill: {proc.communicate()}"
        proc.kill()
    finally:
        proc.communicate()


def _uninterrupted_run(tmp_path: Path, toml: str, episodes: int) -> tuple[list[str], dict[str, Any]]:
    """The robot-stage train arguments for ``toml`` and the final weights of a run never stopped."""
    config = tmp_path / "run.toml"
    config.write_text(toml)
    args = ["--config", str(config), "--stage", "robot", "--episodes", str(episodes)]
    assert run_cli(*train_args(tmp_path / "whole", *args), timeout=120).returncode == 0
    return args, _final_weights(tmp_path / "whole")


def _assert_same_weights(got: dict[str, Any], expected: dict[str, Any]) -> None:
    import torch

    for net in ("actor", "value", "central"):
        for name, tensor in expected[net].items():
            assert torch.equal(got[net][name], tensor), f"{net}.{name} differs after the kill"


def _final_weights(run: Path) -> dict[str, Any]:
    import torch

    return torch.load(run / "robot.pt", weights_only=True)["learner"]


@pytest.mark.sumo
def test_sigkill_at_any_moment_then_resume_gives_the_same_weights(tmp_path: Path) -> None:
    """SIGKILL (no cleanup at all) at several points of a run, each followed by ``--resume``: the run
    ends with the weights of an uninterrupted run with the same seed."""
    args, expected = _uninterrupted_run(tmp_path, KILL_TOML, episodes=12)
    run = tmp_path / "run"
    metrics = run / "metrics.csv"
    command = train_args(run, *args)
    for rows in (2, 5, 9):  # after 1, 4 and 8 episodes (a header line, then one row per episode)
        _kill_once_metrics_reach(command, metrics, rows)
        command = train_args(run, "--resume")
    result = run_cli(*command, timeout=120)
    assert result.returncode == 0, result.stderr
    _assert_same_weights(_final_weights(run), expected)
    assert len(metrics.read_text().splitlines()) == 13  # every episode once
    assert not [p for p in run.iterdir() if p.name.endswith(".tmp")]


@pytest.mark.sumo
def test_sigkill_before_the_first_periodic_checkpoint_then_resume_gives_the_same_weights(
    tmp_path: Path,
) -> None:
    """A run saves its starting point as a checkpoint: SIGKILL after two episodes of a run whose first
    periodic checkpoint is far away, then ``--resume``, ends with the weights of an uninterrupted run (the
    run could not be resumed at all before)."""
    # TINY_TOML: checkpoint_every = 1000, so no periodic checkpoint in this run.
    args, expected = _uninterrupted_run(tmp_path, TINY_TOML, episodes=6)
    run = tmp_path / "run"
    metrics = run / "metrics.csv"
    _kill_once_metrics_reach(train_args(run, *args), metrics, 3)  # after 2 episodes
    result = run_cli(*train_args(run, "--resume"), timeout=120)
    assert result.returncode == 0, result.stderr
    _assert_same_weights(_final_weights(run), expected)
    assert len(metrics.read_text().splitlines()) == 7  # every episode once


@pytest.mark.sumo
def test_resume_of_a_run_killed_before_its_first_checkpoint_says_what_to_do(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "metrics.csv").write_text("stage,episode\nrobot,0\n")  # what a kill before it leaves
    result = run_cli(*train_args(run, "--resume"))
    assert_usage_error(result, str(run), "before its first checkpoint", "--force")


@pytest.mark.sumo
def test_a_damaged_cached_multi_copy_net_is_rebuilt(tmp_path: Path) -> None:
    """A truncated cache file was blamed on the user's net ("SUMO could not load"), an edited one ran
    silently with other roads: the cache's digest catches both, and the net is built again."""
    from idas_sumo.sim.multinet import build_copies, check_copies

    built = build_copies(NET, 2, cache_dir=tmp_path)
    good = built.read_bytes()
    for damage in (good[:2000], good.replace(b'length="250.00"', b'length="25.00"', 1)):
        assert damage != good
        built.write_bytes(damage)
        assert build_copies(NET, 2, cache_dir=tmp_path) == built
        check_copies(NET, built, 2)  # built again (equal but for netconvert's time stamp), and checked


@pytest.mark.sumo
def test_stale_temp_files_in_the_net_cache_are_removed(tmp_path: Path) -> None:
    """Killed builds left ``.<net>.XXXX.tmp`` in the cache forever; one of a live build is spared."""
    from idas_sumo.sim.multinet import STALE_TEMP_S, build_copies

    old, live = tmp_path / ".abc-k2.net.xml.k1l2m3n4.tmp", tmp_path / ".abc-k2.net.xml.x9y8z7w6.tmp"
    for path in (old, live):
        path.write_bytes(b"\0" * 1000)
    hours_ago = time.time() - 2 * STALE_TEMP_S
    os.utime(old, (hours_ago, hours_ago))
    build_copies(NET, 2, cache_dir=tmp_path)
    assert not old.exists() and live.exists()


def test_worker_count_is_bounded_in_the_python_api_too() -> None:
    from idas_sumo.errors import InputError
    from idas_sumo.sim.processes import WorkerProcesses, max_workers

    for count in (0, max_workers() + 1, 1000):
        with pytest.raises(InputError, match=r"workers: \d+ is not in \[1, "):
            WorkerProcesses("builtins:print", count, "test worker")


ECHO_SERVER = """\
class Echo:
    def __init__(self, init):
        self.init = init

    def handle(self, request, shared):
        return (self.init, request, shared)

    def close(self):
        pass
"""


class _OpensAFile:
    """Unpickling this creates ``path``: what a stranger's pickle could do if it were ever loaded."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (str(self.path), "w"))


def test_a_silent_or_unknown_caller_does_not_stop_the_workers_starting(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 34: a local program that connected to the workers' port during start-up and sent nothing
    blocked the start forever. It is dropped after the handshake's timeout, one that sends a pickle
    instead of the key's answer is dropped without the pickle being loaded, and the real workers start."""
    import pickle
    import socket
    import struct
    import threading

    from idas_sumo.sim import rpc
    from idas_sumo.sim.processes import ProcessPool

    assert rpc.HANDSHAKE_TIMEOUT_S <= 10.0  # "a few seconds"
    monkeypatch.setattr(rpc, "HANDSHAKE_TIMEOUT_S", 1.0)
    (tmp_path / "echo_server.py").write_text(ECHO_SERVER)
    paths = [str(tmp_path), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(paths))
    opened = tmp_path / "opened_by_a_pickle"
    payload = pickle.dumps(_OpensAFile(opened))
    strangers: list[socket.socket] = []
    launch = rpc.CallBackServer.launch

    def strangers_first(server: rpc.CallBackServer, *args: Any, **kwargs: Any) -> Any:
        if not strangers:  # in the queue before any worker: accepted first
            silent = socket.create_connection(("127.0.0.1", server.port))
            pickler = socket.create_connection(("127.0.0.1", server.port))
            pickler.sendall(struct.pack("!i", len(payload)) + payload)
            strangers.extend((silent, pickler))
            threading.Timer(30.0, silent.close).start()  # before the fix: fail the time check, not hang
        return launch(server, *args, **kwargs)

    monkeypatch.setattr(rpc.CallBackServer, "launch", strangers_first)
    started = time.monotonic()
    with ProcessPool("echo_server:Echo", [10, 20], "test worker", capture_stderr=True) as pool:
        assert time.monotonic() - started < 20.0
        pool.submit({0: "a", 1: "b"}, shared="s")
        assert [pool.result(i) for i in range(2)] == [(10, "a", "s"), (20, "b", "s")]
    assert len(strangers) == 2
    for stranger in strangers:  # the parent hung up on both
        stranger.settimeout(5.0)
        with contextlib.suppress(OSError):
            while stranger.recv(4096):
                pass
        stranger.close()
    assert not opened.exists()


BUSY_SERVER = """\
import time


class Busy:
    def __init__(self, init):
        self.init = init

    def handle(self, request, shared):
        end = time.process_time() + request
        while time.process_time() < end:
            pass
        return self.init

    def close(self):
        pass
"""


def _server_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, source: str) -> None:
    (tmp_path / f"{name}.py").write_text(source)
    paths = [str(tmp_path), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(paths))


def test_pool_workers_are_forked_from_the_fork_server_and_their_cpu_time_is_counted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Within ``worker_fork_server``, a pool's workers are forks of its one child (none of them this process's
    own), answer as workers do, are gone after the pool closes, and their CPU time reaches this process's
    children's once the fork server has exited (what the benchmarks count)."""
    import resource

    from idas_sumo.sim.processes import ProcessPool, worker_fork_server
    from idas_sumo.sim.rpc import ForkedChild

    _server_module(tmp_path, monkeypatch, "busy_server", BUSY_SERVER)

    def children_cpu_s() -> float:
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        return usage.ru_utime + usage.ru_stime

    before = children_cpu_s()
    with worker_fork_server("busy_server"), ProcessPool("busy_server:Busy", [10, 20], "test worker") as pool:
        procs = list(pool._procs.procs)
        assert all(isinstance(p, ForkedChild) for p in procs)
        assert not {p.pid for p in procs} & set(children_of(os.getpid()))
        pool.submit({0: 0.4, 1: 0.4})  # CPU seconds each
        assert sorted(pool.result(i) for i in range(2)) == [10, 20]
    assert all(p.poll() is not None and not Path(f"/proc/{p.pid}").exists() for p in procs)
    assert children_cpu_s() - before >= 0.8


PREPARED_SERVER = """\
import os

PREPARED_IN = 0


def prepare():
    global PREPARED_IN
    PREPARED_IN = os.getpid()


class Prepared:
    def __init__(self, init):
        pass

    def handle(self, request, shared):
        return PREPARED_IN, os.getppid(), os.getpid()

    def close(self):
        pass
"""


def test_a_fork_server_runs_its_preloads_function_once_before_it_forks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``"module:function"`` as the preload: the fork server calls it once, and its forks start with what it did."""
    from idas_sumo.sim.processes import ProcessPool, worker_fork_server

    _server_module(tmp_path, monkeypatch, "prepared_server", PREPARED_SERVER)
    with (
        worker_fork_server("prepared_server:prepare"),
        ProcessPool("prepared_server:Prepared", [0, 0], "test worker") as pool,
    ):
        pool.submit({0: None, 1: None})
        (prepared_0, parent_0, pid_0), (prepared_1, parent_1, pid_1) = (pool.result(i) for i in range(2))
    assert prepared_0 == prepared_1 == parent_0 == parent_1 != 0  # prepared in the fork server, not per fork
    assert pid_0 != pid_1


def test_a_pools_meanwhile_runs_beside_its_workers_start_and_its_error_comes_out(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ProcessPool(meanwhile=...)``: the caller's own work runs on another thread while the workers start and the
    first requests go out, and is done when the first ``submit`` returns; if it fails, that ``submit`` fails with
    its error, and no worker is left once the pool's block is left."""
    import threading

    from idas_sumo.sim.processes import ProcessPool

    _server_module(tmp_path, monkeypatch, "echo_server", ECHO_SERVER)
    ran: list[str] = []

    def note() -> None:
        time.sleep(0.2)
        ran.append(threading.current_thread().name)

    with ProcessPool("echo_server:Echo", [1], "test worker", meanwhile=note) as pool:
        pool.submit({0: "a"})
        assert ran and ran[0] != threading.current_thread().name
        assert pool.result(0) == (1, "a", None)

    def fail() -> None:
        raise ValueError("the caller's own work failed")

    before = set(children_of(os.getpid()))
    with (
        pytest.raises(ValueError, match="own work failed"),
        ProcessPool("echo_server:Echo", [1], "test worker", meanwhile=fail) as pool,
    ):
        pool.submit({0: "a"})
    assert not set(children_of(os.getpid())) - before


def test_a_fork_server_that_fails_to_start_leaves_the_workers_starting_on_their_own(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from idas_sumo.sim.processes import ProcessPool, worker_fork_server
    from idas_sumo.sim.rpc import ForkedChild

    _server_module(tmp_path, monkeypatch, "echo_server", ECHO_SERVER)
    with (
        worker_fork_server("no_such_module_here"),
        ProcessPool("echo_server:Echo", [10, 20], "test worker") as pool,
    ):
        assert not any(isinstance(p, ForkedChild) for p in pool._procs.procs)
        pool.submit({0: "a", 1: "b"}, shared="s")
        assert [pool.result(i) for i in range(2)] == [(10, "a", "s"), (20, "b", "s")]
    assert "fork server did not start" in caplog.text


def test_train_starts_a_fork_server_for_the_workers_it_expects() -> None:
    """``idas-sumo train`` guesses its rollout workers from the flags and the config file, read as TOML (the
    config's own rule), before anything heavy is imported: a fork server only for two or more."""
    import argparse

    from idas_sumo.cli.train import _expected_workers
    from idas_sumo.sim.processes import max_workers

    def guess(**flags: Any) -> int:
        base = {"config": None, "workers": None, "episodes": None, "gui": False, "ray_address": None}
        return _expected_workers(argparse.Namespace(**(base | flags)))

    default = max(1, min(max_workers(), 16 // 8))  # the shipped config: 16 episodes a round
    assert guess() == (default if default > 1 else 0)
    assert guess(workers=1) == 0 and guess(gui=True) == 0 and guess(ray_address="auto") == 0
    if max_workers() >= 2:
        assert guess(workers=2) == 2
        assert guess(episodes=8) == 0  # a round of 8 episodes earns one worker


def test_train_guesses_no_workers_from_a_config_it_cannot_read(tmp_path: Path) -> None:
    import argparse

    from idas_sumo.cli.train import _expected_workers

    for content in (b"\xff\xfe not utf-8", b"workers = [", b'workers = "two"'):
        bad = tmp_path / "bad.toml"
        bad.write_bytes(content)
        args = argparse.Namespace(config=bad, workers=None, episodes=None, gui=False, ray_address=None)
        assert _expected_workers(args) == 0


def test_workers_start_run_their_entry_and_stop() -> None:
    """``builtins:print`` as the entry: each worker prints its connection and exits 0."""
    from idas_sumo.sim.processes import WorkerProcesses

    pool = WorkerProcesses("builtins:print", 2, "test worker", capture_stderr=True)
    assert len(pool.conns) == 2
    procs = list(pool.procs)
    pool.close()
    assert [p.returncode for p in procs] == [0, 0]


def test_ctrl_c_caught_inside_exec_source_still_exits_130_under_python_m(tmp_path: Path) -> None:
    """A Ctrl-C that lands in source run by ``exec`` (a dataclass built during an import) marked the
    interpreter's Ctrl-C as unhandled though the command caught it: ``python -m`` then died of SIGINT
    (returncode -2) after printing the usual line, in about one run of twenty while workers started."""
    (tmp_path / "exec_stop.py").write_text(
        "import os, signal, sys, time\n"
        "from idas_sumo import cli\n"
        "from idas_sumo.cli import netgen as command\n"
        "def netgen(args):\n"
        "    exec('os.kill(os.getpid(), signal.SIGINT)\\ntime.sleep(0.3)')\n"
        "    return 0\n"
        "command.run = netgen\n"
        "sys.argv = ['idas-sumo', 'netgen', '--out', 'n.net.xml']\n"
        "sys.exit(cli.main())\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    result = subprocess.run(
        [sys.executable, "-m", "exec_stop"], capture_output=True, text=True, cwd=tmp_path, env=env
    )
    assert result.returncode == 130, result.stderr
    assert result.stderr.splitlines() == ["idas-sumo: interrupted; completed outputs were kept"]
