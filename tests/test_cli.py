"""The command line's contract (docs/design-notes.md, "Command line and exit codes"): exit 0 / 1 / 2 / 130; bad input is one line on stderr
that names the flag or file, never a traceback; nothing is overwritten or half-written."""

from __future__ import annotations

import argparse
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import evaluate_args, interrupt_when, run_cli

from idas_sumo.cli import build_parser, main
from idas_sumo.cli.evaluate import MISSING
from idas_sumo.resources import DEFAULT_NET

REPO_ROOT = Path(__file__).resolve().parents[1]


def assert_usage_error(result: subprocess.CompletedProcess[str], *needles: str) -> str:
    """Exit 2 with exactly one stderr line, no traceback, containing every needle; returns the line."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    return assert_one_line(result.stderr, *needles)


def assert_one_line(stderr: str, *needles: str) -> str:
    """Exactly one 'idas-sumo ... error' line on stderr, no traceback, containing every needle."""
    assert "Traceback" not in stderr
    lines = stderr.splitlines()
    assert len(lines) == 1, f"expected one stderr line, got {len(lines)}:\n{stderr}"
    line = lines[0]
    assert line.startswith("idas-sumo"), line
    assert "error" in line, line
    for needle in needles:
        assert needle in line, f"{needle!r} not in {line!r}"
    return line


# --- methods ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("typed", "meant"), [("fsm_idn", "fsm_idm"), ("IDAS", "idas"), ("ALL", "all")])
def test_unknown_baseline_suggests_the_close_name(
    tmp_path: Path, net_path: Path, capsys: pytest.CaptureFixture[str], typed: str, meant: str
) -> None:
    args = evaluate_args(tmp_path / "out", net_path)
    args[args.index("idm")] = typed
    assert main(args) == 2
    line = assert_one_line(capsys.readouterr().err, "--baseline", typed)
    assert f'did you mean "{meant}"' in line
    assert not (tmp_path / "out").exists()


def test_unknown_others_method(tmp_path: Path, net_path: Path) -> None:
    result = run_cli(*evaluate_args(tmp_path / "out", net_path, "--others", "idmm"))
    line = assert_usage_error(result, "--others", "idmm")
    assert 'did you mean "idm"' in line


def test_learned_method_without_policy_file(tmp_path: Path, net_path: Path) -> None:
    missing = tmp_path / "nowhere.pt"
    args = evaluate_args(tmp_path / "out", net_path, "--policy", str(missing))
    args[args.index("idm")] = "idas"
    assert_usage_error(run_cli(*args), str(missing))


# --- the output directory ---------------------------------------------------------------------------


@pytest.mark.sumo
def test_existing_out_is_not_overwritten_without_force(tmp_path: Path, net_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    keep = out / "episodes.csv"
    keep.write_text("precious results\n")
    result = run_cli(*evaluate_args(out, net_path, "--scenarios", "3"))
    assert_usage_error(result, str(out), "--force")
    assert keep.read_text() == "precious results\n"
    assert sorted(p.name for p in out.iterdir()) == ["episodes.csv"]

    forced = run_cli(*evaluate_args(out, net_path, "--scenarios", "3", "--force"))
    assert forced.returncode == 0, forced.stderr
    assert "Traceback" not in forced.stderr
    assert keep.read_text().startswith("scenario,seed,method,")
    assert {"episodes.csv", "summary.csv", "flow.csv"} <= {p.name for p in out.iterdir()}


@pytest.mark.sumo
def test_evaluate_without_out_writes_a_new_directory_per_run(
    tmp_path: Path, net_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The quick start's `--out results/idas`, then `evaluate --baseline fsm_idm` as the README says."""
    monkeypatch.chdir(tmp_path)
    common = ["--net", str(net_path), "--scenarios", "2", "--others", "idm", "--no-progress"]
    assert main(["evaluate", "--baseline", "idas", "--out", "results/idas", *common]) == 0
    assert main(["evaluate", "--baseline", "fsm_idm", *common]) == 0
    assert main(["evaluate", "--baseline", "fsm_idm", *common]) == 0
    out = capsys.readouterr().out
    first, second = Path("results/fsm_idm-paper-2019"), Path("results/fsm_idm-paper-2019-2")
    assert f"wrote {first}/: episodes.csv, summary.csv, flow.csv" in out
    assert f"wrote {second}/: episodes.csv, summary.csv, flow.csv" in out
    assert (first / "episodes.csv").read_text() == (second / "episodes.csv").read_text()  # same seed
    assert sorted(p.name for p in (tmp_path / "results").iterdir()) == [
        "fsm_idm-paper-2019",
        "fsm_idm-paper-2019-2",
        "idas",
    ]
    # --force without --out reuses the first name; an explicit --out still needs --force.
    assert main(["evaluate", "--baseline", "fsm_idm", "--force", *common]) == 0
    assert f"wrote {first}/" in capsys.readouterr().out
    assert len(list((tmp_path / "results").iterdir())) == 3
    assert main(["evaluate", "--baseline", "idm", "--out", "results/idas", *common]) == 2
    assert_one_line(capsys.readouterr().err, "results/idas", "--force")


@pytest.mark.sumo
def test_no_nan_speed_when_no_episode_is_perfect(
    tmp_path: Path, net_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "short.toml"
    # 6 s: the nearest car could finish (shorter episodes are refused), the cars behind it cannot:
    # no success, no perfect episode.
    config.write_text("max_episode_s = 6.0\n")
    out = tmp_path / "out"
    assert (
        main([*evaluate_args(out, net_path, "--scenarios", "2", "--config", str(config)), "--others", "idm"])
        == 0
    )
    printed = capsys.readouterr().out
    assert not re.search(r"\bnan\b", printed, re.IGNORECASE), printed
    assert MISSING in printed
    summary = (out / "summary.csv").read_text().splitlines()
    assert summary[0].startswith("method,scenarios,success_pct,perfect_pct,avg_speed_perfect_mps,")
    assert summary[1].startswith("idm,2,0.0,0.0,,")  # an empty cell, which pandas reads back as NaN
    assert main(["plot", str(out)]) == 0


def test_out_that_is_a_file(tmp_path: Path, net_path: Path) -> None:
    out = tmp_path / "out.txt"
    out.write_text("not a directory\n")
    assert_usage_error(run_cli(*evaluate_args(out, net_path)), str(out))
    assert out.read_text() == "not a directory\n"


# --- the net file -----------------------------------------------------------------------------------


def _bad_nets(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    directory = tmp_path / "a_dir.net.xml"
    directory.mkdir()
    text = tmp_path / "text.net.xml"
    text.write_text("this is not xml\n")
    routes = tmp_path / "routes.net.xml"
    routes.write_text('<?xml version="1.0"?>\n<routes><vType id="car"/></routes>\n')
    return {
        "missing": (tmp_path / "missing.net.xml", "not found"),
        "directory": (directory, "directory"),
        "not-xml": (text, "XML"),
        "not-a-net": (routes, "not a SUMO network"),
    }


@pytest.mark.parametrize("kind", ["missing", "directory", "not-xml", "not-a-net"])
def test_bad_net_file(tmp_path: Path, kind: str) -> None:
    net, what = _bad_nets(tmp_path)[kind]
    result = run_cli(*evaluate_args(tmp_path / "out", net, "--scenarios", "3"))
    assert_usage_error(result, str(net), what)
    # Nothing is written when the input is bad.
    assert not any((tmp_path / "out").glob("*.csv"))


@pytest.mark.sumo
def test_net_that_is_not_a_merge(tmp_path: Path) -> None:
    from idas_sumo.sim.netgen import sumo_binary

    grid = tmp_path / "grid.net.xml"
    subprocess.run(
        [str(sumo_binary("netgenerate")), "--grid", "--grid.number", "3", "-o", str(grid)],
        check=True,
        capture_output=True,
    )
    result = run_cli(*evaluate_args(tmp_path / "out", grid, "--scenarios", "3"))
    assert_usage_error(result, str(grid), "merge")


def test_corrupt_policy_file(tmp_path: Path, net_path: Path) -> None:
    policy = tmp_path / "broken.pt"
    policy.write_bytes(b"not a torch checkpoint")
    args = evaluate_args(tmp_path / "out", net_path, "--policy", str(policy), "--scenarios", "3")
    args[args.index("idm")] = "idas"
    assert_usage_error(run_cli(*args), str(policy))
    assert not (tmp_path / "out").exists()


def test_bad_net_file_for_train(tmp_path: Path) -> None:
    net = tmp_path / "missing.net.xml"
    result = run_cli("train", "--net", str(net), "--episodes", "1", "--out", str(tmp_path / "run"))
    assert_usage_error(result, str(net))


@pytest.mark.sumo
def test_train_with_validation_names_the_best_checkpoint(tmp_path: Path) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(
        'stage = "intelligent"\nintelligent_episodes = 4\nepisodes_per_update = 2\nmax_episode_s = 12.0\n'
        "validate_every = 2\nvalidation_scenarios = 1\n"
        "[intelligent_traffic]\nn_vehicles = 4\nmin_vehicles_per_road = 2\nmax_vehicles_per_road = 2\n"
    )
    out = tmp_path / "run"
    net = DEFAULT_NET
    result = run_cli(
        "train", "--net", str(net), "--config", str(config), "--out", str(out), "--no-progress", timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert f"wrote {out / 'intelligent_best.pt'}: best on validation at intelligent episode" in result.stdout
    assert (out / "validation.csv").read_text().count("\nintelligent,") == 2


# --- netgen -----------------------------------------------------------------------------------------


@pytest.mark.sumo
def test_netgen_main_length(tmp_path: Path) -> None:
    import sumolib

    from idas_sumo.sim.netgen import read_merge_net

    result = run_cli("netgen", "--out", "tmp/x.net.xml", "--main-length", "400", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    path = tmp_path / "tmp" / "x.net.xml"
    assert path.is_file()
    merge = read_merge_net(path)
    assert merge.main.length_m == pytest.approx(400.0, abs=0.5)
    assert merge.merge.length_m == pytest.approx(250.0, abs=0.5)
    net = sumolib.net.readNet(str(path))
    assert net.getEdge(merge.main.edge_id).getLength() == pytest.approx(400.0, abs=0.5)
    # The plain XML is kept beside the net on purpose; no temporary file is left.
    assert sorted(p.name for p in path.parent.iterdir()) == ["x.edg.xml", "x.net.xml", "x.nod.xml"]


@pytest.mark.parametrize(
    ("flag", "value"),
    [("--main-length", "-5"), ("--merge-length", "0"), ("--main-speed", "-1"), ("--angle", "180")],
)
def test_netgen_bad_values(tmp_path: Path, flag: str, value: str) -> None:
    result = run_cli("netgen", "--out", "x.net.xml", flag, value, cwd=tmp_path)
    assert_usage_error(result, flag)
    assert not (tmp_path / "x.net.xml").exists()


def test_netgen_bad_number(tmp_path: Path) -> None:
    result = run_cli("netgen", "--out", "x.net.xml", "--main-length", "long", cwd=tmp_path)
    assert_usage_error(result, "--main-length", "long")


# --- flags ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("extra", "needle"),
    [
        (["--scenarios", "0"], "--scenarios"),
        (["--scenarios", "-3"], "--scenarios"),
        (["--scenarios", "abc"], "--scenarios"),
        (["--seed", "x"], "--seed"),
        (["--suite", "nope"], "--suite"),
        (["--no-such-flag"], "--no-such-flag"),
    ],
)
def test_bad_flags(tmp_path: Path, net_path: Path, extra: list[str], needle: str) -> None:
    assert_usage_error(run_cli(*evaluate_args(tmp_path / "out", net_path, *extra)), needle)
    assert not (tmp_path / "out").exists()


def test_missing_baseline_and_subcommand() -> None:
    assert_usage_error(run_cli("evaluate"), "--baseline")
    assert_usage_error(run_cli(), "command")
    assert_usage_error(run_cli("frobnicate"), "frobnicate")


def test_help_exits_zero() -> None:
    result = run_cli("--help")
    assert result.returncode == 0
    for command in ("netgen", "train", "evaluate", "plot"):
        assert command in result.stdout
    assert "``" not in result.stdout  # the description is text, not the module docstring's markup
    assert "Exit codes" in result.stdout


def test_evaluate_help_lists_exactly_the_registered_methods(capsys: pytest.CaptureFixture[str]) -> None:
    """--baseline's help is derived from evaluation/policies.py: the paper's methods, then ours, then nothing
    else (a method removed there leaves the help too)."""
    from idas_sumo.cli.evaluate import baseline_help
    from idas_sumo.evaluation.policies import METHODS, PAPER_METHODS, PAPER_RECIPE_METHODS

    with pytest.raises(SystemExit) as exit_:
        main(["evaluate", "--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
    baseline = text.split("--baseline BASELINE method:", 1)[1].split(" --net NET", 1)[0]
    listed = []
    for part in baseline.split(";"):
        names = part.strip().removeprefix("also").split("(")[0]
        listed += [name.strip() for name in names.split("|")]
    ours = [m for m in METHODS if m not in PAPER_METHODS and m not in PAPER_RECIPE_METHODS]
    assert listed == [*PAPER_METHODS, "all", *ours, *PAPER_RECIPE_METHODS]
    assert set(PAPER_METHODS) <= set(METHODS)
    # Hand-written registries: the text follows them, and a list without variants has no "also".
    assert baseline_help(("idas", "idm", "x_y"), ("idas", "idm"), ()) == (
        "method: idas | idm | all (those 2: the paper's); also x_y (ours, docs/results.md)"
    )
    assert (
        baseline_help(("idas", "idm"), ("idas", "idm"), ())
        == "method: idas | idm | all (those 2: the paper's)"
    )


def test_every_flag_with_a_default_shows_it(capsys: pytest.CaptureFixture[str]) -> None:
    """Every option whose value is not "off" or "unset" says its default in --help."""
    parser = build_parser()
    (commands,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    missing = []
    for name, sub in commands.choices.items():
        for action in sub._actions:
            if action.default in (None, False, [], argparse.SUPPRESS) or action.help is None:
                continue
            if "default" not in action.help:
                missing.append(f"{name} {action.option_strings}")
    assert missing == []
    for command, needles in {
        "evaluate": ["(default: paper)", "(default: 100)", "(default: 2019"],
        "train": ["default: from --config", "curriculum", "20000"],
        "netgen": ["(default: 250.0)", "(default: 150.0)", "(default: 15.0)", "(default: 30.0)"],
    }.items():
        with pytest.raises(SystemExit) as exit_:
            main([command, "--help"])
        assert exit_.value.code == 0
        text = " ".join(capsys.readouterr().out.split())  # argparse wraps lines
        for needle in needles:
            assert needle in text, (command, needle)


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out == f"idas-sumo {version('idas-sumo')}\n"


def test_console_script_is_installed() -> None:
    script = Path(sys.executable).parent / "idas-sumo"
    # The console script is part of the install contract ([project.scripts]): missing is a failure.
    assert script.is_file(), f"{script} is missing: the idas-sumo console script is not installed"
    result = subprocess.run(
        [str(script), "evaluate", "--scenarios", "0", "--baseline", "idm"], capture_output=True, text=True
    )
    assert_usage_error(result, "--scenarios")


# --- Ctrl-C -----------------------------------------------------------------------------------------


@pytest.mark.sumo
@pytest.mark.parametrize(
    ("signum", "code", "said"),
    [
        (signal.SIGINT, 130, "interrupted"),
        (signal.SIGTERM, 143, "terminated"),
    ],
)
def test_stopped_evaluate_exits_and_leaves_nothing(
    tmp_path: Path, net_path: Path, signum: int, code: int, said: str
) -> None:
    """Ctrl-C or SIGTERM mid-run: no CSV, no temp file, and no empty directory the run made (here the
    default results/<method>-<suite>-<seed> and results/ itself)."""
    args = evaluate_args(tmp_path, net_path, "--scenarios", "5000")
    args = args[: args.index("--out")] + args[args.index("--out") + 2 :]  # the default --out
    proc = subprocess.Popen(
        [sys.executable, "-m", "idas_sumo.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    results = tmp_path / "results"
    # The output directory appears once the inputs are checked; one more second is well into the episodes.
    stderr = interrupt_when(proc, results.exists, settle_s=1.0, signum=signum)
    assert proc.returncode == code, stderr
    assert "Traceback" not in stderr
    assert said in stderr
    assert list(tmp_path.iterdir()) == []
