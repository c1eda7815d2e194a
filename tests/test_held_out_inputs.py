"""Issue 34's held-out cases: bad inputs like the issue's, with values the issue did not use, through the
real CLI in this process (and the Python API). Each is one line and exit 2 (or, for a runtime failure,
exit 1 with a true message), and leaves every file the user had as it was: no file changed, none
added but what a refused command may never write (nothing)."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import TINY_TRAIN_TOML, main_in_process

from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.errors import InputError
from idas_sumo.resources import DEFAULT_NET

REPLAY_BASE = Path(__file__).parent / "data" / "replay_base"
"""A stored evaluation (IDM among IDM others, two scenarios)."""


def files(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (hidden ones too) with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def refused(capsys: pytest.CaptureFixture[str], root: Path, *args: str) -> str:
    """Run the CLI: exit 2, one 'error:' line on stderr, no traceback, and ``root`` as it was; the line."""
    before = files(root)
    code, _, err = main_in_process(capsys, *args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "error: " in lines[0] and "Traceback" not in err, (code, err)
    assert files(root) == before
    return lines[0]


def _vehicles(n: int, start_pos_m: float = 10.0) -> str:
    return "".join(
        f'[[vehicles]]\nid = "v{i}"\nroad = "{("main", "merge")[i % 2]}"\nstart_pos_m = {start_pos_m + 10 * (i // 2)}\n'
        "speed_mps = 5.0\n"
        for i in range(n)
    )


def _user_files(tmp: Path) -> dict[str, Path]:
    """A user's folder: notes, a results file, a net of their own and config files to hand to commands."""
    user = tmp / "user"
    user.mkdir()
    made = {
        "notes": user / "results.json",
        "net": user / "mine.net.xml",
        "garbage_net": user / "broken.net.xml",
        "crowd": user / "crowd.toml",
        "at_zero": user / "at_zero.toml",
        "big_batch": user / "big_batch.toml",
        "big_traffic": user / "big_traffic.toml",
        "eval_crowd": user / "eval_crowd.toml",
        "train_crowd": user / "train_crowd.toml",
        "sweep": user / "sweep.toml",
        "many_merges": user / "many_merges.toml",
    }
    made["notes"].write_text('{"keep": "me"}\n')
    shutil.copy(DEFAULT_NET, made["net"])
    made["garbage_net"].write_text("<net><edge id='a' from='x'")  # cut off: not XML
    made["crowd"].write_text(_vehicles(1001))
    made["at_zero"].write_text(_vehicles(2, start_pos_m=0.0))
    made["big_batch"].write_text(
        "episodes_per_update = 250000\n" + TINY_TRAIN_TOML.replace("episodes_per_update", "#")
    )
    made["big_traffic"].write_text("[traffic]\nn_vehicles = 4000\nmax_vehicles_per_road = 2000\n")
    made["eval_crowd"].write_text("[traffic]\nmin_speed_frac = 1.5\n")
    made["train_crowd"].write_text("[robot_traffic]\nmax_vehicles_per_road = 600\nmax_controlled = 1\n")
    made["sweep"].write_text(TINY_TRAIN_TOML + "validate_every = 2\n")
    made["many_merges"].write_text("validation_scenarios = 4000\n[geometry]\nvalidation_geometries = 3500\n")
    return made


CASES: dict[str, tuple[Callable[[dict[str, Path], Path], list[str]], tuple[str, ...]]] = {
    "netgen onto a user's JSON": (
        lambda f, out: ["netgen", "--out", str(f["notes"])],
        ("results.json", ".net.xml"),
    ),
    "netgen road longer than its bound": (
        lambda f, out: ["netgen", "--out", str(out / "n.net.xml"), "--merge-length", "10001"],
        ("--merge-length",),
    ),
    "netgen infinite speed": (
        lambda f, out: ["netgen", "--out", str(out / "n.net.xml"), "--main-speed", "inf"],
        ("--main-speed",),
    ),
    "nets inspect a cut-off net": (
        lambda f, out: ["nets", "inspect", str(f["garbage_net"])],
        ("broken.net.xml",),
    ),
    "nets inspect an unknown junction": (
        lambda f, out: ["nets", "inspect", str(f["net"]), "--junction", "gneJ99"],
        ("--junction gneJ99", "merge_point"),
    ),
    "train a batch above the bound": (
        lambda f, out: ["train", "--config", str(f["big_batch"]), "--out", str(out / "run")],
        ("episodes_per_update must be at most 100000",),
    ),
    "train 1200 cars a scenario": (
        lambda f, out: ["train", "--config", str(f["train_crowd"]), "--out", str(out / "run")],
        ("train_crowd.toml", "max_vehicles_per_road", "at most 1000"),
    ),
    "train 3500 validation merges": (
        lambda f, out: ["train", "--config", str(f["many_merges"]), "--out", str(out / "run")],
        ("many_merges.toml", "validation_geometries must be in [0, 1000]"),
    ),
    "train --episodes above the bound": (
        lambda f, out: ["train", "--episodes", "123456789012", "--out", str(out / "run")],
        ("--episodes", "at most"),
    ),
    "evaluate a scenario of 1001 cars": (
        lambda f, out: [
            "evaluate",
            "--baseline",
            "idm",
            "--scenario",
            str(f["crowd"]),
            "--out",
            str(out / "e"),
        ],
        ("crowd.toml", "at most 1000 vehicles"),
    ),
    "evaluate a car at 0 m": (
        lambda f, out: [
            "evaluate",
            "--baseline",
            "idm",
            "--scenario",
            str(f["at_zero"]),
            "--out",
            str(out / "e"),
        ],
        ("at_zero.toml", "start_pos_m", "positive"),
    ),
    "evaluate 4000 cars a scenario": (
        lambda f, out: [
            "evaluate",
            "--baseline",
            "idm",
            "--config",
            str(f["big_traffic"]),
            "--out",
            str(out / "e"),
        ],
        ("big_traffic.toml", "n_vehicles must be at most 1000"),
    ),
    "evaluate speeds above the limit": (
        lambda f, out: [
            "evaluate",
            "--baseline",
            "idm",
            "--config",
            str(f["eval_crowd"]),
            "--out",
            str(out / "e"),
        ],
        ("eval_crowd.toml", "max_speed_frac"),
    ),
    "evaluate --out onto a user's file": (
        lambda f, out: ["evaluate", "--baseline", "idm", "--scenarios", "1", "--out", str(f["notes"])],
        ("results.json", "not a directory"),
    ),
    "sweep seeds counting down": (
        lambda f, out: ["sweep", str(f["sweep"]), "--seeds", "9-4", "--out", str(out / "sw")],
        ("--seeds",),
    ),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_a_held_out_bad_input_is_one_line_and_changes_nothing(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    made = _user_files(tmp_path)
    args, needles = CASES[name]
    line = refused(capsys, tmp_path, *args(made, tmp_path))
    for needle in needles:
        assert needle in line, (needle, line)


def test_replay_and_plot_of_an_edited_evaluation(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A scenario the folder does not hold; a run record whose episode length is a word; a flow.csv with
    a word for a speed: one line each, and no PNG written (summary.png used to come first)."""
    ev = tmp_path / "ev"
    shutil.copytree(REPLAY_BASE, ev)
    line = refused(capsys, tmp_path, "replay", str(ev), "--scenario", "77")
    assert "77" in line
    run = ev / "replay" / "run.json"
    run.write_text(run.read_text().replace('"max_episode_s": 60.0', '"max_episode_s": "sixty"'))
    assert '"sixty"' in run.read_text()
    assert "max_episode_s" in refused(capsys, tmp_path, "replay", str(ev), "--scenario", "0")
    flow = ev / "flow.csv"
    flow.write_text(flow.read_text().replace("17.9092", "fast"))
    line = refused(capsys, tmp_path, "plot", str(ev))
    assert "flow.csv" in line and "mean_speed_mps" in line and "'fast'" in line
    assert not list(ev.glob("*.png"))


def test_the_python_api_checks_its_traffic_and_net(tmp_path: Path) -> None:
    from idas_sumo.env.parallel import MergeParallelEnv

    with pytest.raises(ValueError, match="n_vehicles must be at most 1000"):
        TrafficConfig(n_vehicles=1500, max_vehicles_per_road=750)
    broken = tmp_path / "cut.net.xml"
    broken.write_text("<net><edge")
    with pytest.raises(InputError, match=r"cut\.net\.xml"):
        MergeParallelEnv(net=broken)


@pytest.mark.sumo
def test_sumo_dying_mid_run_is_exit_1_and_the_rerun_is_not_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """With --sumo-output, SUMO had written part of a tripinfo file into --out when it died: the folder
    then held a file and the same command again was refused. The failed run now takes its files away."""
    from idas_sumo.errors import SimulationError
    from idas_sumo.sim import backend

    step = backend.SumoBackend.step
    calls = {"n": 0}

    def dies_on_step_40(self: backend.SumoBackend) -> backend.StepEvents:
        calls["n"] += 1
        if calls["n"] == 40:
            raise SimulationError("SUMO died: connection closed by peer (held-out case)")
        return step(self)

    out = tmp_path / "ev"
    args = ["evaluate", "--baseline", "idm", "--scenarios", "1", "--sumo-output", "--copies", "1"]
    args += ["--no-progress", "--out", str(out)]
    with monkeypatch.context() as m:
        m.setattr(backend.SumoBackend, "step", dies_on_step_40)
        code, _, err = main_in_process(capsys, *args)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1 and "SUMO died" in lines[0], err
    assert calls["n"] >= 40 and not list(out.rglob("*.xml"))
    code, _, err = main_in_process(capsys, *args)
    assert code == 0, err
    assert [p.name for p in (out / "sumo").iterdir()] == ["idm-paper-000.tripinfo.xml"]
