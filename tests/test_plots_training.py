"""`idas-sumo plot RUN_DIR` on a training run: learning curves from metrics.csv and validation.csv, the
stage boundary marked; a directory that is neither an evaluation nor a training run is exit 2."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import pytest

from idas_sumo.cli import main
from idas_sumo.training.metrics import METRIC_COLUMNS
from idas_sumo.training.plots import LEARNING_CURVES_NAME
from idas_sumo.training.validation import VALIDATION_COLUMNS

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
TINY_RUN = """\
stage = "curriculum"
robot_episodes = 4
intelligent_episodes = 4
episodes_per_update = 2
checkpoint_every = 2
max_episode_s = 15.0
validate_every = 2
validation_scenarios = 2
"""


def assert_png(path: Path) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path.name} is not a PNG"
    assert len(data) > 20_000, f"{path.name} is suspiciously small ({len(data)} bytes)"


def write_csv(path: Path, columns: tuple[str, ...], rows: list[dict[str, Any]]) -> None:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)


def synthetic_run(directory: Path, robot: int = 200, intelligent: int = 100) -> Path:
    """A two-stage run's CSVs with the columns `train` writes (values made up, shapes real)."""
    directory.mkdir()
    rows = []
    for g in range(robot + intelligent):
        stage, episode = ("robot", g) if g < robot else ("intelligent", g - robot)
        row: dict[str, Any] = dict.fromkeys(METRIC_COLUMNS, 0)
        row.update(
            stage=stage,
            episode=episode,
            global_episode=g,
            return_mean=10 + g % 7,
            flow=-(g % 3),
            success=int(g % 4 != 0),
            perfect=int(g % 5 == 0),
            collisions=int(g % 11 == 0),
            entropy=1.5 - g / 1000,
        )
        rows.append(row)
    write_csv(directory / "metrics.csv", METRIC_COLUMNS, rows)
    validations = [
        dict(
            stage=stage,
            episode=e,
            global_episode=e + offset,
            joint_return=e / 10,
            perfect_rate=0.3,
            success_rate=0.9,
            mean_end_time_s=20.0,
            best=int(e % 100 == 50),
            wall_time_s=1.0,
        )
        for stage, n, offset in (("robot", robot, 0), ("intelligent", intelligent, robot))
        for e in range(50, n + 1, 50)
    ]
    write_csv(directory / "validation.csv", VALIDATION_COLUMNS, validations)
    return directory


def test_plot_on_a_training_run_writes_learning_curves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = synthetic_run(tmp_path / "run")
    assert main(["plot", str(run)]) == 0
    assert_png(run / LEARNING_CURVES_NAME)
    assert f"wrote {run / LEARNING_CURVES_NAME}" in capsys.readouterr().out
    assert sorted(p.name for p in run.iterdir()) == [LEARNING_CURVES_NAME, "metrics.csv", "validation.csv"]


def test_learning_curves_mark_the_stage_boundary_and_label_every_panel(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import idas_sumo.training.plots as plots

    figures = []

    def keep(fig: Any, path: Path) -> Path:
        figures.append(fig)
        return path

    monkeypatch.setattr(plots, "save_png", keep)
    run = synthetic_run(tmp_path / "run", robot=200, intelligent=100)
    main(["plot", str(run)])
    (fig,) = figures
    axes = fig.axes
    assert len(axes) == 6
    for ax in axes:
        assert ax.get_title() and ax.get_ylabel(), "every panel has a title and a y label with its unit"
        # The intelligent stage begins at global episode 200: a dashed line there in every panel.
        boundaries = [line.get_xdata()[0] for line in ax.get_lines() if line.get_linestyle() == "--"]
        assert boundaries == [200], ax.get_title()
        assert {t.get_text() for t in ax.texts} >= {"robot", "intelligent"}
    assert all(ax.get_xlabel() for ax in axes[3:])
    rates = axes[1]
    assert [t.get_text() for t in rates.get_legend().get_texts()] == [
        "success",
        "perfect success",
        "collision",
    ]
    # Hard brakes in the merging zone are the flow penalty counted back (r_flow = -1 per brake).
    (brakes,) = [line for line in axes[2].get_lines() if line.get_linestyle() != "--"][:1]
    assert max(brakes.get_ydata()) == pytest.approx(1.0, abs=0.2)


def test_plot_on_a_training_run_with_wrong_columns_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "metrics.csv").write_text("stage,episode\nrobot,0\n")
    assert main(["plot", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "metrics.csv" in err and "return_mean" in err
    assert not (tmp_path / LEARNING_CURVES_NAME).exists()


def test_plot_on_a_run_without_rows_yet_is_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_csv(tmp_path / "metrics.csv", METRIC_COLUMNS, [])
    assert main(["plot", str(tmp_path)]) == 2
    assert "no rows yet" in capsys.readouterr().err


def test_plot_on_neither_kind_of_directory_names_both(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["plot", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "episodes.csv" in err and "metrics.csv" in err


@pytest.mark.sumo
def test_plot_on_a_real_curriculum_run(tmp_path: Path, net_path: Path) -> None:
    config = tmp_path / "tiny.toml"
    config.write_text(TINY_RUN)
    run = tmp_path / "run"
    args = ["train", "--net", str(net_path), "--config", str(config), "--out", str(run), "--no-progress"]
    assert main(args) == 0
    assert main(["plot", str(run)]) == 0
    assert_png(run / LEARNING_CURVES_NAME)


def test_plot_compares_several_training_runs_on_one_figure(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import idas_sumo.training.plots as plots

    runs = [synthetic_run(tmp_path / f"seed{s}", robot=120, intelligent=60) for s in range(3)]
    out = tmp_path / "figs" / "seeds.png"
    assert main(["plot", *map(str, runs), "--out", str(out)]) == 0
    assert_png(out)
    assert f"wrote {out}" in capsys.readouterr().out
    assert not any((run / LEARNING_CURVES_NAME).exists() for run in runs)  # only the comparison is written

    figures = []
    monkeypatch.setattr(plots, "save_png", lambda fig, path: figures.append(fig) or path)
    main(["plot", *map(str, runs[:2]), "--out", str(out)])
    (fig,) = figures
    success, returns, failures, entropy = fig.axes
    assert [t.get_text() for t in success.get_legend().get_texts()] == ["seed0", "seed1"]
    # One star per run, at its last new best (synthetic_run flags each stage's episode 50: global 50 and 170).
    stars = [line for line in returns.get_lines() if line.get_marker() == "*"]
    assert [float(s.get_xdata()[0]) for s in stars] == [170.0, 170.0]
    assert len(failures.get_lines()) == 4  # collision and timeout per run
    assert len(entropy.get_lines()) == 2
    assert all(ax.get_title() and ax.get_ylabel() for ax in fig.axes)


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ([], "needs --out FILE.png"),
        (["--out", "x.svg"], "needs --out FILE.png"),
        (["--only-one", "--out", "x.png"], "two run directories or more"),
        (["--not-a-run", "--out", "x.png"], "not a training run"),
    ],
)
def test_plot_comparison_bad_input_is_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str
) -> None:
    run = synthetic_run(tmp_path / "run")
    dirs = [str(run), str(run)]
    if "--only-one" in extra:
        dirs, extra = [str(run)], extra[1:]
    if "--not-a-run" in extra:
        dirs, extra = [str(run), str(tmp_path)], extra[1:]
    extra = [str(tmp_path / a) if a.startswith("x.") else a for a in extra]
    assert main(["plot", *dirs, *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err
    assert not list(tmp_path.glob("x.*"))
