"""``idas-sumo replay``: run one evaluated episode again, exactly, and show it.

``evaluate`` keeps what a replay needs in ``<results>/replay/``: every case's scenario as it ran (the
vehicles, not the seed that drew them, so a later change to the generator cannot change a replay), the
SUMO seed, the episode rules, a copy of the net and the SHA-256 of every policy file. A replay runs the
job through the evaluation's own path (``protocol.run_jobs`` on a one-copy ``MergeEngine``); since an
episode's numbers do not depend on what ran beside or before it (evaluate's CSVs do not depend on
``--copies`` or ``--workers``), the replayed ``episodes.csv`` row equals the evaluated one byte for byte,
and the replay says so.

It then opens sumo-gui (cars coloured by road and driver type) or writes an animation: the merge from
above beside the position-time diagram, merging zone shaded, hard brakes and collisions marked.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pandas as pd

from idas_sumo.config import from_dict
from idas_sumo.env.drawing import ROBOT_COLOUR, ZONE_COLOUR, draw_roads, vehicle_colour
from idas_sumo.env.drawing import view_xy as _view_xy
from idas_sumo.env.engine import (
    AgentBatch,
    EnvConfig,
    EpisodeOutcome,
    MergeEngine,
    Policy,
    StepResult,
)
from idas_sumo.env.net_needs import check_road_lengths, road_needs
from idas_sumo.env.rewards import MERGE_ZONE_RADIUS_M
from idas_sumo.env.scenario import Road, Scenario, VehicleSpec
from idas_sumo.errors import IdasError, InputError
from idas_sumo.evaluation.metrics import EPISODE_COLUMNS
from idas_sumo.evaluation.policies import LEARNED_METHODS, METHOD_LABELS, check_method, resolve_policy
from idas_sumo.evaluation.protocol import (
    EpisodeResult,
    EvalCase,
    EvalJob,
    eval_jobs,
    run_jobs,
)
from idas_sumo.io_utils import TEMP_SUFFIX, atomic_open, file_digest, write_csv_atomic
from idas_sumo.resources import POLICY_DIR
from idas_sumo.sim.backend import STEP_LENGTH_S, require_display
from idas_sumo.sim.merge_detect import MergeSite, choose_merge
from idas_sumo.sim.processes import SEED_LIMIT

REPLAY_DIR = "replay"
"""The results directory's folder of replay data (written by ``evaluate``)."""
RUN_NAME = "run.json"
SCENARIOS_NAME = "scenarios.jsonl"
NET_NAME = "net.net.xml"
REPLAY_FORMAT = 1
"""Bumped when the replay files change in a way an older reader would misread."""
GUI_OPTIONS: tuple[str, ...] = ("--start", "--delay", str(int(STEP_LENGTH_S * 1000)))
"""sumo-gui runs at once (no play button to press) and in real time: one 0.2 s step per 200 ms."""
FRAME_STEP_S = 0.4
"""Simulated seconds between two animation frames (every other SUMO step)."""
FRAMES_PER_S = 10
"""Animation frames per second of playback: with FRAME_STEP_S, four times real time."""
BRAKE_MARK_S = 1.0
"""How long (simulated seconds) a car that hard-braked stays ringed in the view from above."""
ANIMATION_SUFFIXES = (".gif", ".mp4")


# -- what evaluate keeps ---------------------------------------------------------------------------


@dataclass(frozen=True)
class PolicyRecord:
    """A method's policy as evaluated: its file (None for a rule-based method) and that file's SHA-256."""

    method: str
    path: str | None = None
    sha256: str | None = None


def policy_record(method: str, override: Path | None = None) -> PolicyRecord:
    """What ``resolve_policy(method, override)`` loads, identified by path and content."""
    if method not in LEARNED_METHODS:
        return PolicyRecord(method)
    path = (override or POLICY_DIR / LEARNED_METHODS[method]).resolve()
    return PolicyRecord(method, str(path), file_digest(path))


def write_replay_data(
    out: Path,
    net_path: Path,
    cases: Sequence[EvalCase],
    methods: Sequence[str],
    policy: Path | None,
    others: str,
    others_policy: Path | None,
    seed: int,
    env: EnvConfig,
) -> str:
    """Write ``out/replay/`` (each file atomically); returns the folder's name for the "wrote" line.

    ``env``: the evaluation's episode rules, its ``junction`` the merge of the net it ran on."""
    folder = out / REPLAY_DIR
    folder.mkdir(exist_ok=True)
    with atomic_open(folder / NET_NAME, "wb") as f, net_path.open("rb") as net:
        shutil.copyfileobj(net, f)  # the run's net may live in a temp folder or be regenerated later
    run = {
        "format": REPLAY_FORMAT,
        "seed": seed,
        "max_episode_s": env.max_episode_s,
        "safety_mask": env.safety_mask,
        "net_sha256": file_digest(folder / NET_NAME),
        "junction": env.junction,
        "methods": {m: asdict(policy_record(m, policy)) for m in methods},
        "others": asdict(policy_record(others, others_policy)),
    }
    with atomic_open(folder / RUN_NAME) as f:
        json.dump(run, f, indent=2)
        f.write("\n")
    with atomic_open(folder / SCENARIOS_NAME) as f:
        for case in cases:
            # json writes floats as repr: they read back as the very same numbers.
            line = {
                "name": case.scenario.name,
                "ego": case.ego,
                "seed": case.seed,
                "method_vehicles": list(case.method_vehicles),
                "main_prio": case.scenario.main_prio,
                "merge_prio": case.scenario.merge_prio,
                "vehicles": [asdict(v) for v in case.scenario.vehicles],
            }
            f.write(json.dumps(line) + "\n")
    return f"{REPLAY_DIR}/"


@dataclass(frozen=True)
class ReplayData:
    """``<results>/replay/`` read back."""

    directory: Path
    seed: int
    env: EnvConfig
    """The episode rules evaluated; ``junction``: the merge of the net evaluated, None: the net's only one
    (also in replay data written before the junction was kept, all on single-merge nets)."""
    net_path: Path
    methods: dict[str, PolicyRecord]
    others: PolicyRecord
    cases: tuple[EvalCase, ...]


@dataclass(frozen=True)
class _RunRecord:
    """``run.json`` as ``write_replay_data`` writes it, read through ``config.from_dict``: every key's type
    and range checked once, each problem one line naming the file and the key."""

    FLAT_FIELDS: ClassVar[tuple[str, ...]] = ("env",)

    format: int
    seed: int
    net_sha256: str
    methods: Any
    """{method: PolicyRecord as a table}: checked by ``_policy_records``."""
    others: Any
    env: EnvConfig = field(default_factory=EnvConfig)


@dataclass(frozen=True)
class _CaseLine:
    """One line of ``scenarios.jsonl``."""

    name: str
    ego: str
    seed: int
    method_vehicles: tuple[str, ...]
    vehicles: tuple[VehicleSpec, ...]
    main_prio: int = 1
    merge_prio: int = 0


def _json(text: str, where: str) -> Any:
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as err:
        raise InputError(f"{where}: not JSON ({err})") from None


def _policy_record(data: Any, where: str, method: str | None = None) -> PolicyRecord:
    record = from_dict(PolicyRecord, data, where)
    check_method(record.method, where)
    if method is not None and record.method != method:
        raise InputError(f"{where}.method: {record.method!r}, but it is listed under {method!r}")
    learned = record.method in LEARNED_METHODS
    if learned != (record.path is not None) or learned != (record.sha256 is not None):
        kind = "a learned method needs" if learned else "a rule-based method has no"
        raise InputError(f"{where}: {kind} path and sha256")
    return record


def _read_run(path: Path) -> tuple[_RunRecord, dict[str, PolicyRecord], PolicyRecord]:
    """``run.json`` read and checked whole, before anything runs."""
    data = _json(path.read_text(encoding="utf-8"), str(path))
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(data).__name__}")
    if data.get("format") != REPLAY_FORMAT:
        raise InputError(
            f"{path}: replay format {data.get('format')!r}, this idas-sumo reads {REPLAY_FORMAT}"
        )
    run = from_dict(_RunRecord, data, str(path))
    if not 0 <= run.seed < SEED_LIMIT:
        raise InputError(f"{path}.seed: must be in [0, {SEED_LIMIT}) (SUMO's seed range), got {run.seed}")
    if not isinstance(run.methods, dict) or not run.methods:
        raise InputError(f"{path}.methods: expected a table of one or more methods, got {run.methods!r}")
    methods = {str(m): _policy_record(r, f"{path}.methods.{m}", str(m)) for m, r in run.methods.items()}
    return run, methods, _policy_record(run.others, f"{path}.others")


def _read_cases(path: Path) -> tuple[EvalCase, ...]:
    """``scenarios.jsonl``, each line checked (``path:LINE`` in the message)."""
    cases = []
    for n, text in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        if not text:
            continue
        where = f"{path}:{n}"
        line = from_dict(_CaseLine, _json(text, where), where)
        try:
            scenario = Scenario(line.name, line.vehicles, line.main_prio, line.merge_prio)
        except ValueError as err:
            raise InputError(f"{where}: {err}") from None
        ids = {v.id for v in line.vehicles}
        if line.ego not in ids or not set(line.method_vehicles) <= ids:
            raise InputError(f"{where}: ego and method_vehicles must be vehicles of the scenario")
        if not 0 <= line.seed < SEED_LIMIT:
            raise InputError(f"{where}.seed: must be in [0, {SEED_LIMIT}), got {line.seed}")
        cases.append(EvalCase(scenario, line.ego, line.seed, line.method_vehicles))
    if not cases:
        raise InputError(f"{path}: no scenarios")
    return tuple(cases)


def load_replay_data(directory: Path) -> ReplayData:
    """``directory``'s replay data, every file checked whole when read: an ``InputError`` names the file,
    the key (or line) and what is wrong."""
    folder = directory / REPLAY_DIR
    if not directory.is_dir():
        raise InputError(f"{directory}: not a directory written by `idas-sumo evaluate`")
    if not (folder / RUN_NAME).is_file() or not (folder / SCENARIOS_NAME).is_file():
        raise InputError(
            f"{directory}: no {REPLAY_DIR}/{RUN_NAME} (written by an evaluate older than replay, or not "
            "an evaluation directory); evaluate again to replay its episodes"
        )
    where = folder / RUN_NAME
    try:
        run, methods, others = _read_run(where)
        where = folder / SCENARIOS_NAME
        cases = _read_cases(where)
        where = folder / NET_NAME
        if file_digest(where) != run.net_sha256:
            raise InputError(f"{where}: changed since the evaluation (its SHA-256 differs)")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"{where}: cannot read replay data ({err})") from None
    return ReplayData(directory, run.seed, run.env, folder / NET_NAME, methods, others, cases)


def pick_case(data: ReplayData, scenario: str) -> EvalCase:
    """The case named ``scenario`` (``paper-037``, ``s1``), else the one at that index (``37``)."""
    for case in data.cases:
        if case.scenario.name == scenario:
            return case
    if scenario.isdigit() and int(scenario) < len(data.cases):
        return data.cases[int(scenario)]
    names = [c.scenario.name for c in data.cases]
    shown = ", ".join(names[:3]) + (f", … {names[-1]}" if len(names) > 3 else "")
    raise InputError(
        f"--scenario {scenario}: not in {data.directory} (its {len(names)} scenarios: {shown}; "
        f"or an index 0-{len(names) - 1})"
    )


def pick_method(data: ReplayData, method: str | None) -> str:
    evaluated = list(data.methods)
    if method is None:
        if len(evaluated) > 1:
            raise InputError(f"{data.directory} evaluated {', '.join(evaluated)}: choose one with --method")
        return evaluated[0]
    if method not in evaluated:
        raise InputError(
            f"--method {method}: not evaluated in {data.directory} (it has {', '.join(evaluated)})"
        )
    return method


def checked_policy(
    record: PolicyRecord, seed: int, override: Path | None = None, flag: str = "--policy"
) -> Policy:
    """The evaluated policy, from ``override`` or its recorded file, refused unless its SHA-256 matches."""
    if record.path is None or record.sha256 is None:
        if override is not None:
            raise InputError(f"{flag}: {record.method} is rule-based and reads no policy file")
        return resolve_policy(record.method, None, seed)
    path = override or Path(record.path)
    if not path.is_file():
        raise InputError(
            f"{path}: the {record.method} policy evaluated is not there any more; pass {flag} FILE "
            f"(SHA-256 {record.sha256[:12]}…)"
        )
    digest = file_digest(path)
    if digest != record.sha256:
        raise InputError(
            f"{path}: not the {record.method} policy evaluated (SHA-256 {digest[:12]}…, evaluated "
            f"{record.sha256[:12]}…); pass {flag} FILE with the evaluated weights"
        )
    return resolve_policy(record.method, path, seed)


# -- running it again ------------------------------------------------------------------------------


@dataclass
class Marks:
    """What the animation marks, seen through the engine's observer hooks of a one-copy run."""

    colour_gui: bool = False
    """Colour each car in sumo-gui as it enters (``vehicle_colour``)."""
    brakes: list[tuple[float, str, float]] = field(default_factory=list)
    """(time, vehicle, position rel. to the merge point) of each hard brake, placed as the engine counts
    it: where the car was when it decided."""
    collisions: list[tuple[float, str, str, float]] = field(default_factory=list)
    """(time, vehicle, other vehicle, position) of each collision pair."""
    outcome: EpisodeOutcome | None = None
    _before: dict[str, float] = field(default_factory=dict)
    _time_before: float = 0.0
    _coloured: set[str] = field(default_factory=set)

    def decided(
        self, engine: MergeEngine, jobs: Sequence[int], batch: AgentBatch, actions: np.ndarray
    ) -> None:
        snap = engine.snapshot
        span = engine.rows_of(0)
        self._time_before = engine.time_s
        self._before = {snap.ids[i]: -float(snap.dist_to_merge_m[i]) for i in range(span.start, span.stop)}
        if self.colour_gui:
            for vid in self._before:
                if vid not in self._coloured:
                    spec = engine.spec(0, vid)
                    rgb = vehicle_colour(spec.road, spec.b_type, spec.controlled)
                    engine.single_backend.raw_call("vehicle", "setColor", vid, (*rgb, 255))
                    self._coloured.add(vid)

    def stepped(
        self,
        engine: MergeEngine,
        jobs: Sequence[int],
        batch: AgentBatch,
        actions: np.ndarray,
        result: StepResult,
    ) -> None:
        # The engine's own count, placed where each car was when it decided (the step's start).
        for vid in result.hard_brake_ids[0]:
            self.brakes.append((self._time_before, vid, self._before[vid]))
        for a, b in result.collisions[0]:
            self.collisions.append((engine.time_s, a, b, self._before.get(a, float("nan"))))

    def ended(self, engine: MergeEngine, slot: int, job: int, outcome: EpisodeOutcome) -> None:
        self.outcome = outcome


@dataclass(frozen=True)
class Replay:
    job: EvalJob
    result: EpisodeResult
    marks: Marks
    site: MergeSite
    """The merge the episode ran on (the evaluation's: its kept net and junction)."""
    replayed_line: str
    """The replayed episode's episodes.csv line, written as evaluate writes it."""
    original_line: str | None
    """The evaluated line of the same scenario and method (None: episodes.csv lacks it)."""
    original_row: int | None
    """Its row number in episodes.csv (1 = the first row after the header)."""

    @property
    def identical(self) -> bool:
        return self.replayed_line == self.original_line


def replay_episode(
    directory: Path,
    scenario: str,
    method: str | None = None,
    gui: bool = False,
    policy: Path | None = None,
    hold_gui: bool = False,
) -> Replay:
    """Run the evaluated episode of ``scenario`` and ``method`` again; ``gui``: in sumo-gui.

    ``hold_gui``: after the episode, wait for Enter before sumo-gui closes."""
    data = load_replay_data(directory)
    case = pick_case(data, scenario)
    method = pick_method(data, method)
    if policy is not None and method not in LEARNED_METHODS:
        raise InputError(f"--policy: {method} is rule-based and reads no policy file")
    require_display(gui)
    policies = {method: checked_policy(data.methods[method], data.seed, policy)}
    others = checked_policy(data.others, data.seed, flag="(others)")
    site = choose_merge(data.net_path, data.env.junction)
    # As evaluate checks it: a max_episode_s no car can finish in is one line, not a ZeroDivisionError.
    check_road_lengths(site, road_needs(None, data.env.max_episode_s, str(directory / REPLAY_DIR / RUN_NAME)))
    job = eval_jobs([case], [method])[0]
    marks = Marks(colour_gui=gui)
    engine = MergeEngine(site, copies=1, seed=data.seed, config=data.env, gui=gui)
    try:
        options = GUI_OPTIONS if gui else ()
        ((_, result),) = list(run_jobs(engine, [job], policies, others, observer=marks, sumo_options=options))
        if gui and hold_gui:
            input("replay over: press Enter to close sumo-gui ")
    finally:
        engine.close()
    replayed = _csv_line(result.episode)
    original, row = _original_line(directory, case.scenario.name, method)
    return Replay(job, result, marks, site, replayed, original, row)


def _csv_line(episode: dict[str, object]) -> str:
    """The row as evaluate's own writer puts it into episodes.csv (so that a comparison is byte-exact)."""
    with tempfile.TemporaryDirectory(prefix="idas_sumo_replay_") as tmp:
        path = Path(tmp) / "episodes.csv"
        write_csv_atomic(pd.DataFrame([episode], columns=list(EPISODE_COLUMNS)), path)
        return path.read_text(encoding="utf-8").splitlines()[1]


def _original_line(directory: Path, scenario: str, method: str) -> tuple[str | None, int | None]:
    path = directory / "episodes.csv"
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
        frame = pd.read_csv(path, dtype={"scenario": str, "method": str})
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: cannot read CSV ({err})") from None
    if "scenario" not in frame.columns or "method" not in frame.columns:
        raise InputError(f"{path}: not written by `idas-sumo evaluate`")
    hits = np.flatnonzero((frame["scenario"] == scenario).to_numpy() & (frame["method"] == method).to_numpy())
    if len(hits) == 0:
        return None, None
    row = int(hits[0]) + 1
    return lines[row], row


# -- the animation ---------------------------------------------------------------------------------


def check_animation_path(path: Path) -> None:
    """Refuse, before anything runs, an animation that cannot be written."""
    suffix = path.suffix.lower()
    if suffix not in ANIMATION_SUFFIXES:
        raise InputError(f"--out {path}: write an animation as .gif or .mp4, not {suffix or 'no suffix'!r}")
    if suffix == ".mp4":
        from matplotlib import animation

        if not animation.writers.is_available("ffmpeg"):
            raise InputError(f"--out {path}: .mp4 needs ffmpeg, which is not installed; write a .gif instead")
    if path.exists() and not path.is_file():
        raise InputError(f"--out {path}: exists and is not a file")
    if not path.parent.is_dir():
        raise InputError(f"--out {path}: folder {path.parent} does not exist")
    try:  # the very folder ``_save`` writes into: a read-only one is refused before the episode runs
        os.rmdir(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=TEMP_SUFFIX))
    except OSError as err:
        raise InputError(f"--out {path}: cannot write into {path.parent} ({err.strerror or err})") from None


def _unit_rgb(rgb: tuple[int, int, int]) -> tuple[float, float, float]:
    return (rgb[0] / 255, rgb[1] / 255, rgb[2] / 255)


def episode_verdict(row: dict[str, object]) -> str:
    """One word for an episodes.csv row: collision, timeout, failure, perfect or success."""
    if bool(row["collisions"]):
        return "collision"
    if not bool(row["success"]):
        return "timeout" if bool(row["timeout"]) else "failure"
    return "perfect" if bool(row["perfect"]) else "success"


def write_animation(replay: Replay, path: Path, frame_step_s: float = FRAME_STEP_S, dpi: int = 80) -> Path:
    """The replayed episode as an animation (.gif with Pillow, .mp4 with ffmpeg): the merge from above
    and the position-time diagram, merging zone shaded, hard brakes and collisions marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation

    check_animation_path(path)
    traj = replay.result.trajectory
    times = np.unique(traj["time_s"].to_numpy())
    stride = max(1, round(frame_step_s / STEP_LENGTH_S))
    frames = list(times[::stride])
    if frames[-1] != times[-1]:
        frames.append(times[-1])

    fig, (top, pt) = plt.subplots(1, 2, figsize=(11, 4.4), gridspec_kw={"width_ratios": [1.25, 1]})
    fig.subplots_adjust(left=0.05, right=0.98, bottom=0.24, top=0.86, wspace=0.22)
    case = replay.job.case
    row = replay.result.episode
    label = METHOD_LABELS.get(replay.job.method, replay.job.method)
    fig.suptitle(
        f"{case.scenario.name}: {label} drives {', '.join(case.method_vehicles)} (ego {case.ego}); "
        f"{episode_verdict(row)}, hard brakes: {row['hard_brakes']} ({row['hard_brakes_merge_zone']} in the "
        "merging zone)",
        fontsize=10,
    )
    colours = car_colours(replay)
    view = _TopView(top, replay.site)
    diagram = _PositionTime(pt, replay, times, colours)
    _legend(fig)
    draw = _Frames(replay, view, diagram, colours).draw
    anim = animation.FuncAnimation(fig, draw, frames=frames, interval=1000 / FRAMES_PER_S, blit=False)
    try:
        _save(anim, path, dpi)
    finally:
        plt.close(fig)
    return path


class _TopView:
    """The view from above: the roads, the merging zone around the merge point, and the artists that
    show the cars (moved each frame)."""

    def __init__(self, top: Any, site: MergeSite) -> None:
        draw_roads(top, site)
        ring = {"s": 150, "marker": "o", "facecolors": "none", "zorder": 4}
        self.cars = top.scatter([], [], s=46, marker="s", edgecolors="none", zorder=3)
        self.ego_ring = top.scatter([], [], edgecolors="black", lw=1.2, **ring)
        self.brake_ring = top.scatter([], [], edgecolors="red", lw=1.6, **ring)
        self.crash_mark = top.scatter([], [], s=120, marker="X", color="red", zorder=5)
        self.clock = top.text(0.98, 0.96, "", transform=top.transAxes, ha="right", va="top", fontsize=9)


class _PositionTime:
    """The position-time diagram: one line per car, drawn up to the current time, with its marks."""

    def __init__(
        self, pt: Any, replay: Replay, times: np.ndarray, colours: dict[str, tuple[float, float, float]]
    ) -> None:
        traj = replay.result.trajectory
        case = replay.job.case
        pt.axhspan(-MERGE_ZONE_RADIUS_M, MERGE_ZONE_RADIUS_M, color=ZONE_COLOUR, alpha=0.5, lw=0)
        self.lines = {}
        for v in colours:
            (self.lines[v],) = pt.plot([], [], color=colours[v], lw=2.2 if v == case.ego else 1.3)
        t0, t1 = float(times[0]), float(times[-1])
        pos = -traj["dist_to_merge_m"].to_numpy()
        pt.set_xlim(t0, t1 + 0.5)
        pt.set_ylim(float(pos.min()) - 5, float(pos.max()) + 5)
        pt.set_xlabel("time, s")
        pt.set_ylabel("position rel. to merge point, m")
        pt.set_title("position-time (merging zone shaded)", fontsize=9)
        self.brakes = pt.scatter(
            [], [], marker="v", s=30, color="orange", edgecolors="black", lw=0.5, zorder=6
        )
        self.crashes = pt.scatter([], [], marker="X", s=90, color="red", zorder=5)
        self.cursor = pt.axvline(t0, color="0.4", lw=0.8, ls=":")


def car_colours(replay: Replay) -> dict[str, tuple[float, float, float]]:
    """The colour of each car of the replayed trajectory, in its order: as in sumo-gui, by road and driver
    type, grey if SUMO drives it."""
    specs = {v.id: v for v in replay.job.case.scenario.vehicles}
    return {
        v: _unit_rgb(vehicle_colour(specs[v].road, specs[v].b_type, specs[v].controlled))
        for v in dict.fromkeys(replay.result.trajectory["vehicle"])
    }


def _legend(fig: Any) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [
        Patch(color=_unit_rgb(vehicle_colour("main", -2.0, True)), label="main road, b_type -2"),
        Patch(color=_unit_rgb(vehicle_colour("main", 2.0, True)), label="main road, b_type +2"),
        Patch(color=_unit_rgb(vehicle_colour("merge", -2.0, True)), label="merge road, b_type -2"),
        Patch(color=_unit_rgb(vehicle_colour("merge", 2.0, True)), label="merge road, b_type +2"),
        Patch(color=_unit_rgb(ROBOT_COLOUR), label="SUMO-driven"),
        Line2D([], [], marker="o", ls="", mfc="none", mec="black", label="ego"),
        Line2D([], [], marker="v", ls="", color="orange", mec="black", label="hard brake"),
        Line2D([], [], marker="X", ls="", color="red", label="collision"),
        Patch(color=ZONE_COLOUR, alpha=0.5, label=f"merging zone (±{MERGE_ZONE_RADIUS_M:.0f} m)"),
    ]
    fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=7.5, frameon=False)


class _Frames:
    """Moves both views' artists to a time of the episode (the animation's frame function)."""

    def __init__(
        self,
        replay: Replay,
        view: _TopView,
        diagram: _PositionTime,
        colours: dict[str, tuple[float, float, float]],
    ) -> None:
        traj = replay.result.trajectory
        specs = {v.id: v for v in replay.job.case.scenario.vehicles}
        self.traj = traj
        self.ego = replay.job.case.ego
        self.view, self.diagram = view, diagram
        self.colour = colours
        self.origin: dict[str, Road] = {v: specs[v].road for v in colours}
        self.by_time = {t: g for t, g in traj.groupby("time_s")}
        marks = replay.marks
        self.brakes = np.array([(t, p) for t, _, p in marks.brakes], dtype=float).reshape(-1, 2)
        self.brake_ids = [v for _, v, _ in marks.brakes]
        self.crashes = np.array([(t, p) for t, _, _, p in marks.collisions], dtype=float).reshape(-1, 2)
        self.crash_ids = {v: t for t, a, b, _ in marks.collisions for v in (a, b)}
        self.last_xy: dict[str, tuple[float, float]] = {}

    def draw(self, t: float) -> None:
        self._draw_top(t)
        upto = self.traj[self.traj["time_s"] <= t]
        for v, g in upto.groupby("vehicle"):
            self.diagram.lines[str(v)].set_data(g["time_s"].to_numpy(), -g["dist_to_merge_m"].to_numpy())
        brakes, crashes = self.brakes, self.crashes
        self.diagram.brakes.set_offsets(brakes[brakes[:, 0] <= t] if len(brakes) else np.empty((0, 2)))
        self.diagram.crashes.set_offsets(
            crashes[crashes[:, 0] <= t + 1e-9] if len(crashes) else np.empty((0, 2))
        )
        self.diagram.cursor.set_xdata([t, t])

    def _draw_top(self, t: float) -> None:
        view = self.view
        now = self.by_time[t]
        ids = now["vehicle"].tolist()
        road = np.array(
            [self.origin[v] if r != "out" else "out" for v, r in zip(ids, now["road"], strict=True)]
        )
        x, y = _view_xy(road, now["dist_to_merge_m"].to_numpy())
        for v, xi, yi in zip(ids, x.tolist(), y.tolist(), strict=True):
            self.last_xy[v] = (xi, yi)
        xy = np.column_stack([x, y]) if len(ids) else np.empty((0, 2))
        view.cars.set_offsets(xy)
        view.cars.set_facecolors([self.colour[v] for v in ids])
        ego = [i for i, v in enumerate(ids) if v == self.ego]
        view.ego_ring.set_offsets(xy[ego] if ego else np.empty((0, 2)))
        recent = {
            v for (bt, _), v in zip(self.brakes, self.brake_ids, strict=True) if t - BRAKE_MARK_S < bt <= t
        }
        ring = [i for i, v in enumerate(ids) if v in recent]
        view.brake_ring.set_offsets(xy[ring] if ring else np.empty((0, 2)))
        crashed = [
            self.last_xy[v] for v, ct in self.crash_ids.items() if ct <= t + 1e-9 and v in self.last_xy
        ]
        view.crash_mark.set_offsets(np.array(crashed) if crashed else np.empty((0, 2)))
        view.clock.set_text(f"t = {t:.1f} s")


def _save(anim: Any, path: Path, dpi: int) -> None:
    """Write ``anim`` into a ``*.tmp`` folder beside ``path`` and rename it: an interrupted run leaves no
    half animation. A folder, not io_utils' temp file, since the writers pick the format by the suffix."""
    from matplotlib import animation

    writer: animation.AbstractMovieWriter
    if path.suffix.lower() == ".gif":
        writer = animation.PillowWriter(fps=FRAMES_PER_S)
    else:
        writer = animation.FFMpegWriter(fps=FRAMES_PER_S)
    folder = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=TEMP_SUFFIX))
    try:
        anim.save(str(folder / path.name), writer=writer, dpi=dpi)
        (folder / path.name).replace(path)
    finally:
        shutil.rmtree(folder, ignore_errors=True)


# -- the command ---------------------------------------------------------------------------------


def describe(replay: Replay) -> str:
    row = replay.result.episode
    label = METHOD_LABELS.get(replay.job.method, replay.job.method)
    what = (
        f"{episode_verdict(row)} (success {row['success']}, perfect {row['perfect']}, "
        f"collisions {row['collisions']}, hard brakes {row['hard_brakes']})"
    )
    return f"replayed {replay.job.case.scenario.name} ({label}, ego {replay.job.case.ego}): {what}"


def replay_from_args(args: argparse.Namespace) -> int:
    """``idas-sumo replay DIR --scenario K [--method M] [--gui | --out FILE] [--policy FILE]``."""
    directory = Path(args.dir)
    if args.out is not None:
        check_animation_path(Path(args.out))
    replay = replay_episode(
        directory,
        str(args.scenario),
        args.method,
        gui=args.gui,
        policy=args.policy,
        hold_gui=sys.stdin.isatty(),
    )
    print(describe(replay))
    if replay.original_line is None:
        print(f"note: {directory}/episodes.csv has no row for it to compare with", file=sys.stderr)
    elif replay.identical:
        print(f"identical to episodes.csv row {replay.original_row}")
    else:
        raise IdasError(
            f"the replay differs from episodes.csv row {replay.original_row}:\n"
            f"  evaluated: {replay.original_line}\n  replayed:  {replay.replayed_line}"
        )
    if args.out is not None:
        print(f"wrote {write_animation(replay, Path(args.out))}")
    return 0
