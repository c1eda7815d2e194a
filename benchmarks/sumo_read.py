"""The cheapest way to read SUMO's vehicle state through libsumo, and K subprocesses vs one K-copy run.

For N = 8, 32, 128, 512 vehicles (one copy of the merge net with 8 vehicles for N = 8; N/16 copies of it
with 16 vehicles each above, all in one libsumo run over a K-copy net from sim/multinet.py), each method
below steps SUMO and reads every vehicle's road, lane position, speed and acceleration into numpy
arrays, every step:

* getters: ``vehicle.getIDList()`` and the four getters per vehicle in one tight loop;
* getters-map: the same getters, each mapped over the id list into ``np.fromiter``;
* getters-raw: the same with libsumo's SWIG functions (``libsumo._libsumo.vehicle_getSpeed`` ...),
  which the ``libsumo.vehicle`` methods wrap in a Python call each;
* sub-all: a variable subscription per vehicle (made on departure), read with
  ``vehicle.getAllSubscriptionResults()`` in one call;
* sub-each: the same subscriptions, read with ``getIDList()`` + ``getSubscriptionResults(id)`` per vehicle;
* context: one context subscription around copy 0's junction, with a range that covers every copy,
  read with ``junction.getContextSubscriptionResults`` in one call (no per-vehicle subscribing);
* batch: ``BatchBackend.vehicle_states()`` itself (its reader plus copy/edge bookkeeping).

Subscriptions are filled inside ``simulationStep``, so each method is timed as step + read; the "step
only" row (no read) shows what the step alone costs. ``setSpeed`` for every vehicle is timed separately
in every run (its row is the median over all of them), once in a loop over ``vehicle.setSpeed`` and
once with the SWIG function mapped over the ids. Every vehicle is controlled, at a constant
2.5 m/s, 12 m apart, and episodes are short enough that nobody reaches the merge point, so N stays
constant; loading (``libsumo.load``) and the insertion step are not timed. Methods are interleaved
(the order rotates each repeat) and each cell is the median over repeats: the machine is shared.
The script checks that every method read the same values.

Then, for the record, at K = 8 copies of 16 vehicles: the wall time of one step of all K scenarios
(commands, step, states) with K ``SubprocessBackend``s (sim/backend.py, called one after the other, as
its synchronous interface allows) and with one K-copy ``BatchBackend``.

Run:  python benchmarks/sumo_read.py [--repeats 5] [--steps 100] [--sizes 8 32 128 512]

Measured (libsumo 1.28, the 2 shared cores, defaults), µs per vehicle-step, the read's share in brackets:

    method         N=8 (1×8)     N=32 (2×16)   N=128 (8×16)  N=512 (32×16)
    step only      0.92          0.76          0.75          0.82
    getters        1.75 (+0.83)  1.52 (+0.76)  1.52 (+0.77)  1.55 (+0.73)
    getters-map    1.73 (+0.82)  1.45 (+0.69)  1.40 (+0.66)  1.44 (+0.62)
    getters-raw    1.58 (+0.66)  1.28 (+0.52)  1.26 (+0.51)  1.27 (+0.46)
    sub-all        2.31 (+1.39)  1.90 (+1.14)  2.09 (+1.34)  2.19 (+1.38)
    sub-each       2.39 (+1.48)  1.95 (+1.19)  1.99 (+1.24)  2.12 (+1.30)
    context        2.35 (+1.43)  1.93 (+1.17)  2.18 (+1.43)  2.41 (+1.59)
    batch          2.36 (+1.44)  1.60 (+0.84)  1.47 (+0.72)  1.49 (+0.68)
    setSpeed loop  0.17          0.16          0.16          0.17
    setSpeed raw   0.17          0.14          0.13          0.13

getters-raw is the cheapest at every N, so ``BatchBackend.vehicle_states`` reads that way; subscriptions
lose everywhere here (they also make ``simulationStep`` slower). One step of all 8 scenarios: 8
``SubprocessBackend``s 3.58 ms, one 8-copy ``BatchBackend`` 0.31 ms (11.6×).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from idas_sumo.env.scenario import ROADS, Scenario, VehicleSpec  # noqa: E402
from idas_sumo.resources import DEFAULT_NET  # noqa: E402
from idas_sumo.sim.backend import SubprocessBackend  # noqa: E402
from idas_sumo.sim.batch import BatchBackend  # noqa: E402
from idas_sumo.sim.multinet import MultiNet, multi_net  # noqa: E402
from idas_sumo.sim.netgen import MergeNet, read_merge_net  # noqa: E402

PITCH_M = 12.0
"""Front-to-front spacing on each road (a 7 m gap)."""
SPEED_MPS = 2.5
FIRST_POS_M = 5.0
PER_COPY = 16
"""Vehicles per copy above N = 16 (8 per road)."""
SUBPROCESS_K = 8

Reading = tuple[list[str], np.ndarray, np.ndarray, np.ndarray]
"""(road ids, lane positions, speeds, accelerations) of every vehicle, in getIDList order."""


def scenario(n: int) -> Scenario:
    per_road = n // 2
    return Scenario(
        f"bench{n}",
        tuple(
            VehicleSpec(f"{road}{i}", road, FIRST_POS_M + i * PITCH_M, SPEED_MPS)
            for road in ROADS
            for i in range(per_road)
        ),
    )


def layout(n: int) -> tuple[int, int]:
    """(copies, vehicles per copy) for N vehicles."""
    if n <= PER_COPY:
        return 1, n
    if n % PER_COPY:
        raise SystemExit(f"N={n}: above {PER_COPY}, N must be a multiple of {PER_COPY}")
    return n // PER_COPY, PER_COPY


# -- the readers (each gets the libsumo module and the copy-0 junction id) --------------------------


def _vars(libsumo: Any) -> list[int]:
    c = libsumo.constants
    return [c.VAR_ROAD_ID, c.VAR_LANEPOSITION, c.VAR_SPEED, c.VAR_ACCELERATION]


def read_getters(libsumo: Any) -> Reading:
    vehicle = libsumo.vehicle
    get_road, get_pos, get_speed, get_accel = (
        vehicle.getRoadID,
        vehicle.getLanePosition,
        vehicle.getSpeed,
        vehicle.getAcceleration,
    )
    ids = vehicle.getIDList()
    n = len(ids)
    pos, speed, accel = np.empty(n), np.empty(n), np.empty(n)
    roads = []
    for i, vid in enumerate(ids):
        roads.append(get_road(vid))
        pos[i] = get_pos(vid)
        speed[i] = get_speed(vid)
        accel[i] = get_accel(vid)
    return roads, pos, speed, accel


def read_getters_map(libsumo: Any) -> Reading:
    vehicle = libsumo.vehicle
    ids = vehicle.getIDList()
    n = len(ids)
    return (
        list(map(vehicle.getRoadID, ids)),
        np.fromiter(map(vehicle.getLanePosition, ids), np.float64, n),
        np.fromiter(map(vehicle.getSpeed, ids), np.float64, n),
        np.fromiter(map(vehicle.getAcceleration, ids), np.float64, n),
    )


def read_getters_raw(libsumo: Any) -> Reading:
    from libsumo import _libsumo

    ids = _libsumo.vehicle_getIDList()
    n = len(ids)
    return (
        list(map(_libsumo.vehicle_getRoadID, ids)),
        np.fromiter(map(_libsumo.vehicle_getLanePosition, ids), np.float64, n),
        np.fromiter(map(_libsumo.vehicle_getSpeed, ids), np.float64, n),
        np.fromiter(map(_libsumo.vehicle_getAcceleration, ids), np.float64, n),
    )


def _from_results(values: Any, n: int, road: int, lane_pos: int, spd: int, acc: int) -> Reading:
    rows = list(values)
    return (
        [r[road] for r in rows],
        np.fromiter((r[lane_pos] for r in rows), dtype=np.float64, count=n),
        np.fromiter((r[spd] for r in rows), dtype=np.float64, count=n),
        np.fromiter((r[acc] for r in rows), dtype=np.float64, count=n),
    )


def read_sub_all(libsumo: Any) -> Reading:
    results = libsumo.vehicle.getAllSubscriptionResults()
    return _from_results(results.values(), len(results), *_vars(libsumo))


def read_sub_each(libsumo: Any) -> Reading:
    vehicle = libsumo.vehicle
    get = vehicle.getSubscriptionResults
    ids = vehicle.getIDList()
    return _from_results((get(v) for v in ids), len(ids), *_vars(libsumo))


def make_read_context(junction: str) -> Callable[[Any], Reading]:
    def read_context(libsumo: Any) -> Reading:
        results = libsumo.junction.getContextSubscriptionResults(junction)
        return _from_results(results.values(), len(results), *_vars(libsumo))

    return read_context


# -- one measurement --------------------------------------------------------------------------------


@dataclass
class Timing:
    step_read_s: float = 0.0
    set_s: float = 0.0
    set_raw_s: float = 0.0
    vehicle_steps: int = 0
    last: Reading | None = None


def run_method(
    method: str,
    backend: BatchBackend,
    scenarios: list[Scenario],
    steps: int,
) -> Timing:
    """One episode: load, insertion step, subscriptions if any, then ``steps`` timed steps."""
    import libsumo

    vehicle = libsumo.vehicle
    backend.reset(scenarios)
    events = backend.step()  # insertion (not timed), sets the controlled speed mode
    junction = backend.net.copy_net(0).junction_id
    reader: Callable[[Any], Reading] | None = None
    batch_reader = False
    if method in ("sub-all", "sub-each"):
        variables = _vars(libsumo)
        for k, ev in enumerate(events.copies):
            for vid in ev.departed:  # every car departs in the insertion step here
                vehicle.subscribe(backend.global_id(k, vid), variables)
        reader = read_sub_all if method == "sub-all" else read_sub_each
    elif method == "context":
        libsumo.junction.subscribeContext(
            junction, libsumo.constants.CMD_GET_VEHICLE_VARIABLE, 1.0e7, _vars(libsumo)
        )
        reader = make_read_context(junction)
    elif method == "getters":
        reader = read_getters
    elif method == "getters-map":
        reader = read_getters_map
    elif method == "getters-raw":
        reader = read_getters_raw
    elif method == "batch":
        batch_reader = True
    elif method != "step only":
        raise ValueError(method)
    ids = vehicle.getIDList()
    perf = time.perf_counter
    step = libsumo.simulationStep
    set_speed = vehicle.setSpeed
    from libsumo import _libsumo

    raw_set_speed = _libsumo.vehicle_setSpeed
    speeds = [SPEED_MPS] * len(ids)
    t = Timing()
    for _ in range(steps):
        t0 = perf()
        step()
        if reader is not None:
            t.last = reader(libsumo)
        elif batch_reader:
            st = backend.vehicle_states()
            t.last = (list(st.edge), st.lane_pos_m, st.speed_mps, st.accel_mps2)
        t1 = perf()
        for vid in ids:
            set_speed(vid, SPEED_MPS)
        t2 = perf()
        deque(map(raw_set_speed, ids, speeds), maxlen=0)  # the same speed again: harmless
        t3 = perf()
        t.step_read_s += t1 - t0
        t.set_s += t2 - t1
        t.set_raw_s += t3 - t2
        t.vehicle_steps += len(ids)
    if method == "context":
        libsumo.junction.unsubscribeContext(junction, libsumo.constants.CMD_GET_VEHICLE_VARIABLE, 1.0e7)
    return t


METHODS = ("step only", "getters", "getters-map", "getters-raw", "sub-all", "sub-each", "context", "batch")


def _same(a: Reading, b: Reading, local_edges: bool) -> bool:
    roads_a, *arrays_a = a
    roads_b, *arrays_b = b
    if len(roads_a) != len(roads_b):
        return False
    if not local_edges:
        # BatchBackend gives copy-local edge ids: compare the prefix-free part.
        roads_a = [r.split("_", 1)[1] for r in roads_a]
    return roads_a == roads_b and all(np.array_equal(x, y) for x, y in zip(arrays_a, arrays_b, strict=True))


def measure_reads(
    source: MergeNet, sizes: list[int], repeats: int, steps: int, cache: Path | None
) -> tuple[dict[tuple[str, int], float], dict[tuple[str, int], float], dict[int, bool]]:
    """µs per vehicle-step: (method, N) -> step + read; (loop|raw, N) -> setSpeed; N -> all read the same."""
    cells: dict[tuple[str, int], list[float]] = {}
    setters: dict[tuple[str, int], list[float]] = {}
    consistent: dict[int, bool] = {}
    for n in sizes:
        copies, per_copy = layout(n)
        net: MultiNet = multi_net(source, copies, cache)
        scenarios = [scenario(per_copy)] * copies
        backend = BatchBackend(net)
        try:
            run_method("getters", backend, scenarios, 5)  # warm-up
            last: dict[str, Reading] = {}
            for rep in range(repeats):
                order = METHODS[rep % len(METHODS) :] + METHODS[: rep % len(METHODS)]
                for method in order:
                    t = run_method(method, backend, scenarios, steps)
                    if t.vehicle_steps != n * steps:
                        raise SystemExit(f"N={n} {method}: {t.vehicle_steps / steps:.1f} vehicles per step")
                    cells.setdefault((method, n), []).append(1e6 * t.step_read_s / t.vehicle_steps)
                    setters.setdefault(("loop", n), []).append(1e6 * t.set_s / t.vehicle_steps)
                    setters.setdefault(("raw", n), []).append(1e6 * t.set_raw_s / t.vehicle_steps)
                    if t.last is not None:
                        last[method] = t.last
            reference = last["getters"]
            consistent[n] = all(_same(reference, r, m != "batch") for m, r in last.items())
        finally:
            backend.close()
    medians = {key: statistics.median(v) for key, v in cells.items()}
    return medians, {key: statistics.median(v) for key, v in setters.items()}, consistent


# -- K subprocesses vs one K-copy run ----------------------------------------------------------------


def measure_subprocesses(source: MergeNet, repeats: int, steps: int, cache: Path | None) -> dict[str, float]:
    """ms per step of all K scenarios: K SubprocessBackends vs one K-copy BatchBackend (median)."""
    scen = scenario(PER_COPY)
    results: dict[str, list[float]] = {"subprocess": [], "batch": []}
    batch = BatchBackend(multi_net(source, SUBPROCESS_K, cache))
    subs: list[SubprocessBackend] = []
    try:
        subs = [SubprocessBackend(source) for _ in range(SUBPROCESS_K)]
        for _ in range(repeats):
            for b in subs:
                b.reset(scen)
                b.step()
            ids = [v.id for v in scen.vehicles]
            t0 = time.perf_counter()
            for _ in range(steps):
                for b in subs:
                    b.set_speeds(dict.fromkeys(ids, SPEED_MPS))
                    b.step()
                    b.vehicle_states()
            results["subprocess"].append(1e3 * (time.perf_counter() - t0) / steps)

            batch.reset([scen] * SUBPROCESS_K)
            batch.step()
            all_ids = ids * SUBPROCESS_K
            copies = np.repeat(np.arange(SUBPROCESS_K), len(ids))
            speeds = np.full(len(all_ids), SPEED_MPS)
            t0 = time.perf_counter()
            for _ in range(steps):
                batch.set_speeds(all_ids, speeds, copy=copies)
                batch.step()
                batch.vehicle_states()
            results["batch"].append(1e3 * (time.perf_counter() - t0) / steps)
    finally:
        batch.close()
        for b in subs:
            b.close()
    return {k: statistics.median(v) for k, v in results.items()}


# -- output -----------------------------------------------------------------------------------------


def print_tables(
    sizes: list[int],
    reads: dict[tuple[str, int], float],
    setters: dict[tuple[str, int], float],
    consistent: dict[int, bool],
    subprocess_ms: dict[str, float] | None,
    subprocess_error: str | None,
) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    table = Table(title="µs per vehicle-step: step + read of road, lane position, speed, acceleration")
    table.add_column("method")
    for n in sizes:
        copies, per_copy = layout(n)
        table.add_column(f"N={n}\n({copies}×{per_copy})", justify="right")
    for method in METHODS:
        cells = []
        for n in sizes:
            total = reads[(method, n)]
            read = total - reads[("step only", n)]
            cells.append(f"{total:.2f}" if method == "step only" else f"{total:.2f} ({read:+.2f})")
        table.add_row(method, *cells)
    table.add_row("setSpeed, loop", *(f"{setters[('loop', n)]:.2f}" for n in sizes))
    table.add_row("setSpeed, SWIG + map", *(f"{setters[('raw', n)]:.2f}" for n in sizes))
    table.add_row("same values", *("yes" if consistent[n] else "NO" for n in sizes))
    console.print(table)
    console.print("(in brackets: the read's share, step + read minus step only)")
    best = {
        n: min((m for m in METHODS if m not in ("step only", "batch")), key=lambda m: reads[(m, n)])
        for n in sizes
    }
    console.print("cheapest reader per N: " + ", ".join(f"N={n}: {best[n]}" for n in sizes))
    sub = Table(title=f"one step of all K = {SUBPROCESS_K} scenarios ({PER_COPY} vehicles each), ms")
    sub.add_column("engine")
    sub.add_column("ms per step", justify="right")
    if subprocess_ms is not None:
        sub.add_row(
            f"{SUBPROCESS_K} × SubprocessBackend (one after the other)", f"{subprocess_ms['subprocess']:.2f}"
        )
        sub.add_row(f"BatchBackend, {SUBPROCESS_K} copies", f"{subprocess_ms['batch']:.2f}")
        sub.add_row("ratio", f"{subprocess_ms['subprocess'] / subprocess_ms['batch']:.1f}×")
    else:
        sub.add_row("SubprocessBackend", f"skipped: {subprocess_error}")
    console.print(sub)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--repeats", type=int, default=5, help="repeats per cell (median)")
    parser.add_argument(
        "--steps", type=int, default=100, help="timed steps per run (max 200: no car may merge)"
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 32, 128, 512])
    parser.add_argument("--no-subprocess", action="store_true", help="skip the subprocess comparison")
    parser.add_argument(
        "--cache",
        type=Path,
        default=None,
        help="net cache directory (default: IDAS_SUMO_CACHE or ~/.cache/idas_sumo/nets)",
    )
    args = parser.parse_args(argv)
    if (
        not 1 <= args.steps <= 200
    ):  # 200 steps at 2.5 m/s: the front car (89 m) stays 111 m short of the merge
        parser.error("--steps must lie in [1, 200]")
    source = read_merge_net(DEFAULT_NET)
    reads, setters, consistent = measure_reads(source, args.sizes, args.repeats, args.steps, args.cache)
    subprocess_ms: dict[str, float] | None = None
    error: str | None = None
    if args.no_subprocess:
        error = "--no-subprocess"
    else:
        try:
            subprocess_ms = measure_subprocesses(source, args.repeats, args.steps, args.cache)
        except Exception as err:  # the subprocess backend may be mid-rewrite: report, don't fail
            error = f"{type(err).__name__}: {err}"
    print_tables(args.sizes, reads, setters, consistent, subprocess_ms, error)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
