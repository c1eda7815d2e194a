"""Issue 34: nothing a user owns is ever overwritten or lost (io_utils's output-path policy).

Every command that writes refuses to replace a file it did not write unless ``--force``; ``--force``
removes only what the folder's manifest says the tool wrote; a folder is locked while a command writes
into it; nothing is written inside the installed package; files read back on ``--resume`` are checked;
a scenario's name cannot lead an output out of ``--out``. Through ``idas_sumo.cli.main`` in process.
"""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from conftest import TINY_TRAIN_TOML, main_in_process

from idas_sumo.cli import main
from idas_sumo.io_utils import LOCK_NAME, MANIFEST_NAME, PACKAGE_DIR, OutputFolder, output_directory
from idas_sumo.resources import DEFAULT_NET


def code_and_err(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """``main_in_process``'s exit code and stderr, as ``assert_refused`` takes them."""
    code, _, err = main_in_process(capsys, *args)
    return code, err


def assert_refused(code: int, err: str, *needles: str) -> None:
    """Exit 2, one line on stderr naming each of ``needles``."""
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.splitlines()
    assert len(lines) == 1, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def snapshot(directory: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()
    }


def train(out: Path, tmp_path: Path, *extra: str) -> list[str]:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_TRAIN_TOML)
    return [
        "train", "--net", str(DEFAULT_NET), "--out", str(out), "--no-progress", "--config", str(config),
        "--stage", "robot", "--episodes", "1", *extra,
    ]  # fmt: skip


def evaluate(out: Path, *extra: str) -> list[str]:
    return [
        "evaluate", "--baseline", "idm", "--others", "idm", "--net", str(DEFAULT_NET), "--out", str(out),
        "--no-progress", "--scenarios", "1", *extra,
    ]  # fmt: skip


# --- netgen and nets sample: files they did not write, and the package ----------------------------------


@pytest.mark.sumo
@pytest.mark.parametrize("command", [["netgen"], ["nets", "sample", "onramp"]])
def test_net_commands_never_replace_a_file_they_did_not_write(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: list[str]
) -> None:
    """``netgen --out notes.py`` replaced the user's file (exit 0) and wrote notes.py.nod.xml beside it."""
    notes = tmp_path / "notes.py"
    notes.write_text("print('mine')\n")
    assert_refused(*code_and_err(capsys, *command, "--out", str(notes)), str(notes), ".net.xml")
    user_net = tmp_path / "mine.net.xml"
    user_net.write_text("<net>hand-written</net>\n")
    assert_refused(*code_and_err(capsys, *command, "--out", str(user_net)), str(user_net), "--force")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.net.xml", "notes.py"]
    assert notes.read_text() == "print('mine')\n" and user_net.read_text() == "<net>hand-written</net>\n"
    # A net the tool wrote is replaced as before; one the user owns only with --force.
    ours = tmp_path / "ours.net.xml"
    assert main_in_process(capsys, *command, "--out", str(ours))[0] == 0
    assert main_in_process(capsys, *command, "--out", str(ours))[0] == 0
    assert main_in_process(capsys, *command, "--out", str(user_net), "--force")[0] == 0
    assert "hand-written" not in user_net.read_text()


@pytest.mark.sumo
def test_net_commands_never_replace_plain_xml_they_did_not_write(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    nodes = tmp_path / "x.nod.xml"
    nodes.write_text("<nodes/>\n")  # the user's own plain XML, beside the name asked for
    assert_refused(
        *code_and_err(capsys, "netgen", "--out", str(tmp_path / "x.net.xml")), str(nodes), "--force"
    )
    assert nodes.read_text() == "<nodes/>\n" and not (tmp_path / "x.net.xml").exists()


@pytest.mark.parametrize("force", [[], ["--force"]])
def test_netgen_never_writes_into_the_installed_package(
    capsys: pytest.CaptureFixture[str], force: list[str]
) -> None:
    """``netgen --out`` at the shipped default replaced it (a warning only); every default run then failed."""
    shipped = PACKAGE_DIR / "sumo_nets" / "tjunction.net.xml"
    before = snapshot(shipped.parent)
    assert_refused(
        *code_and_err(capsys, "netgen", "--out", str(shipped), *force), "installed idas_sumo package"
    )
    assert snapshot(shipped.parent) == before


# --- --force removes only what the tool wrote --------------------------------------------------------


@pytest.mark.sumo
def test_train_force_keeps_files_it_did_not_write(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``train --force`` removed the whole tensorboard/ folder and any ``.*.tmp`` dotfile."""
    run = tmp_path / "run"
    assert main_in_process(capsys, *train(run, tmp_path))[0] == 0
    recorded = set((run / MANIFEST_NAME).read_text().splitlines())
    assert {"checkpoint.pt", "metrics.csv", "robot.pt"} <= recorded
    (run / "tensorboard").mkdir(exist_ok=True)
    mine = {run / "tensorboard" / "notes.txt": "mine", run / ".notes.tmp": "mine", run / "README": "mine"}
    for path, text in mine.items():
        path.write_text(text)
    stale = run / ".checkpoint.pt.k1l2l3ed.tmp"  # a write killed before its rename
    stale.write_bytes(b"\0")
    assert main_in_process(capsys, *train(run, tmp_path, "--force"))[0] == 0
    assert all(path.read_text() == text for path, text in mine.items())
    assert not stale.exists() and not (run / LOCK_NAME).exists()


@pytest.mark.sumo
def test_train_force_checks_before_it_deletes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """With ``RUN/tensorboard`` a symlink, ``--force`` deleted checkpoint.pt and metrics.csv, then exit 1."""
    run, elsewhere = tmp_path / "run", tmp_path / "elsewhere"
    run.mkdir()
    elsewhere.mkdir()
    (elsewhere / "events.out.tfevents.1").write_text("someone else's")
    (run / "tensorboard").symlink_to(elsewhere)
    for name in ("checkpoint.pt", "metrics.csv"):
        (run / name).write_text("a run's file")
    (run / MANIFEST_NAME).write_text("checkpoint.pt\nmetrics.csv\ntensorboard/events.out.tfevents.1\n")
    args = train(run, tmp_path, "--force")
    before = snapshot(tmp_path)
    assert_refused(*code_and_err(capsys, *args), "symlink", "nothing was removed")
    assert snapshot(tmp_path) == before


@pytest.mark.sumo
def test_evaluate_force_removes_only_what_it_wrote(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert main_in_process(capsys, *evaluate(out, "--trajectories"))[0] == 0
    assert "trajectories.csv" in (out / MANIFEST_NAME).read_text()
    (out / "notes.txt").write_text("mine")
    assert main_in_process(capsys, *evaluate(out, "--force"))[0] == 0
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / "trajectories.csv").exists()  # the earlier run's, which this one did not write
    (out / "sumo").symlink_to(tmp_path)
    before = snapshot(out)
    assert_refused(*code_and_err(capsys, *evaluate(out, "--force", "--sumo-output")), "symlink")
    assert snapshot(out) == before


def test_a_damaged_manifest_is_refused_and_nothing_is_removed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "precious").write_text("mine")
    (out / MANIFEST_NAME).write_text("../precious\n")
    with pytest.raises(Exception, match="not a path inside"), output_directory(out, force=True):
        pass
    assert (tmp_path / "precious").read_text() == "mine"


# --- one command per output folder -------------------------------------------------------------------


@pytest.mark.parametrize("command", ["evaluate", "train"])
def test_a_second_command_into_a_locked_folder_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    """Two ``evaluate`` with one ``--out`` both exited 0 and one run's results were lost."""
    out = tmp_path / "out"
    out.mkdir()
    args = evaluate(out, "--force") if command == "evaluate" else train(out, tmp_path, "--force")
    with OutputFolder.open(out):  # the first command, still writing
        (out / "checkpoint.pt").write_text("the first run's")
        code, _, err = main_in_process(capsys, *args)
        assert_refused(code, err, str(out), "another idas-sumo command is writing")
        assert (out / "checkpoint.pt").read_text() == "the first run's"
    assert not (out / LOCK_NAME).exists()


# --- --resume never rewrites history ----------------------------------------------------------------


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp_path = tmp_path_factory.mktemp("run")
    run = tmp_path / "run"
    assert main(train(run, tmp_path)) == 0
    return run


@pytest.mark.sumo
@pytest.mark.parametrize("damage", ["foreign", "garbage row", "extra column"])
def test_resume_refuses_a_metrics_file_it_cannot_trust(
    finished_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], damage: str
) -> None:
    """A foreign metrics.csv or a garbage row lost rows silently (exit 0); an extra column was a traceback."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    metrics = run / "metrics.csv"
    header, *rows = metrics.read_text().splitlines()
    edited = {
        "foreign": "time,loss\n1,0.5\n2,0.4\n",
        "garbage row": "\n".join([header, "not,a,row", *rows]) + "\n",
        "extra column": "\n".join([header, *(r + ",extra" for r in rows)]) + "\n",
    }[damage]
    metrics.write_text(edited)
    before = snapshot(run)
    code, _, err = main_in_process(capsys, *train(run, tmp_path, "--resume", "--episodes", "2"))
    assert_refused(code, err, str(metrics), "nothing was changed")
    assert snapshot(run) == before


def test_resume_keeps_complete_rows_and_drops_only_a_cut_last_line(tmp_path: Path) -> None:
    from idas_sumo.training.metrics import MetricsSink

    columns = ("stage", "global_episode")
    (tmp_path / "m.csv").write_text("stage,global_episode\nrobot,0\nrobot,1\nrobot,2\nrob")
    with MetricsSink(tmp_path, 2, name="m.csv", columns=columns, tensorboard_keys=()) as sink:
        assert [row["global_episode"] for row in sink.kept] == ["0", "1"]
    with (tmp_path / "m.csv").open() as f:
        assert [row["global_episode"] for row in csv.DictReader(f)] == ["0", "1"]


# --- names that become paths --------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["../../escaped", "sub/x", "..", "a\\b", " "])
def test_a_scenario_name_that_is_a_path_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    """``name = "../x"`` made ``--sumo-output`` write outside ``--out``; ``sub/x`` blamed the net."""
    scenario = tmp_path / "s.toml"
    scenario.write_text(
        f'name = "{name.replace(chr(92), chr(92) * 2)}"\n'
        '[[vehicles]]\nid = "ego"\nroad = "main"\nstart_pos_m = 50.0\nspeed_mps = 10.0\n'
    )
    out = tmp_path / "out"
    code, _, err = main_in_process(capsys, *evaluate(out, "--scenario", str(scenario), "--sumo-output"))
    assert_refused(code, err, str(scenario), "scenario name")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml"]


# --- the other commands that write ---------------------------------------------------------------------


def test_plot_and_replay_never_replace_a_file_they_did_not_write(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``plot --out`` and ``replay --out`` replaced any file at their path."""
    mine = tmp_path / "mine.png"
    mine.write_bytes(b"my own picture")
    runs = [tmp_path / "a", tmp_path / "b"]
    for run in runs:
        run.mkdir()
    plot = ["plot", *map(str, runs), "--out", str(mine)]
    assert_refused(*code_and_err(capsys, *plot), str(mine), "--force")
    gif = tmp_path / "mine.gif"
    gif.write_bytes(b"GIF89a mine")
    assert_refused(
        *code_and_err(capsys, "replay", str(tmp_path), "--scenario", "0", "--out", str(gif)), "--force"
    )
    assert mine.read_bytes() == b"my own picture" and gif.read_bytes() == b"GIF89a mine"
    # With --force the command goes on (and here fails on the empty run folders, not on the file).
    code, _, err = main_in_process(capsys, *plot, "--force")
    assert code == 2 and "not a training run" in err


@pytest.mark.parametrize("command", ["evaluate", "train", "sweep", "plot"])
def test_no_command_writes_into_the_installed_package(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    target = PACKAGE_DIR / "policies" / "written-by-a-test"
    args = {
        "evaluate": evaluate(target),
        "train": train(target, tmp_path),
        "sweep": ["sweep", str(tmp_path / "tiny.toml"), "--seeds", "1", "--out", str(target)],
        "plot": ["plot", str(tmp_path), str(tmp_path), "--out", str(target / "x.png")],
    }[command]
    (tmp_path / "tiny.toml").write_text("validate_every = 1\n" + TINY_TRAIN_TOML)
    assert_refused(*code_and_err(capsys, *args), "installed idas_sumo package")
    assert not target.exists()
