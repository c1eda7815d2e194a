"""Memory of a long evaluation: the evaluating process's RSS after the first 100 scenarios and after N.

Runs ``run_evaluation`` (what ``idas-sumo evaluate`` runs) here, in this process, for each method on its
own: the paper suite, ``N`` scenarios, one worker, the default copies. RSS is read from
``/proc/self/status`` each time an episode completes (the progress bar's hook), and printed after 100
episodes, every ``--every`` after, and after the last; the difference (last − after 100) is what the
evaluation keeps per scenario. Done when it stays within 50 MB at N = 2000 (issue 34).

Run:  python benchmarks/eval_memory.py [--scenarios 2000] [--methods idm idas] [--every 500]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from idas_sumo.evaluation import runner  # noqa: E402
from idas_sumo.evaluation.runner import EvalRequest, run_evaluation  # noqa: E402
from idas_sumo.resources import DEFAULT_NET  # noqa: E402

FIRST = 100
"""The episodes after which the reference RSS is taken (numba, torch and SUMO are warm by then)."""
LIMIT_MB = 50.0


def rss_mb() -> float:
    """This process's resident set now (Linux), in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS in /proc/self/status (Linux only)")


class Sampler:
    """Stands in for the runner's progress bar: counts finished episodes and samples RSS."""

    def __init__(self, every: int) -> None:
        self.every = every
        self.samples: list[tuple[int, float]] = []
        self.done = 0

    def __call__(self, enabled: bool, total: int, description: str) -> Sampler:
        self.total = total
        return self

    def __enter__(self) -> Callable[[], None]:
        def advance() -> None:
            self.done += 1
            if (
                self.done == FIRST
                or self.done == self.total
                or (self.done > FIRST and self.done % self.every == 0)
            ):
                self.samples.append((self.done, rss_mb()))

        return advance

    def __exit__(self, *exc: object) -> None:
        pass


def measure(
    method: str, scenarios: int, seed: int, every: int, trajectories: bool
) -> list[tuple[int, float]]:
    sampler = Sampler(every)
    runner._progress = sampler  # type: ignore[assignment,misc]
    with tempfile.TemporaryDirectory() as tmp:
        run_evaluation(
            EvalRequest(
                net=DEFAULT_NET,
                methods=(method,),
                scenarios=scenarios,
                seed=seed,
                out=Path(tmp) / "out",
                trajectories=trajectories,
                progress=False,
            )
        )
    return sampler.samples


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", type=int, default=2000)
    ap.add_argument("--methods", nargs="+", default=["idm", "idas"])
    ap.add_argument("--seed", type=int, default=2019)
    ap.add_argument("--every", type=int, default=500, help="also print RSS every this many episodes")
    ap.add_argument("--trajectories", action="store_true", help="keep trajectories (evaluate --trajectories)")
    args = ap.parse_args()
    if args.scenarios < FIRST:
        ap.error(f"--scenarios: at least {FIRST}")
    worst = 0.0
    for method in args.methods:
        start = time.perf_counter()
        samples = measure(method, args.scenarios, args.seed, args.every, args.trajectories)
        wall = time.perf_counter() - start
        base = samples[0][1]
        print(f"{method}: {args.scenarios} scenarios in {wall:.0f} s")
        for done, mb in samples:
            print(f"  after {done:6d}: RSS {mb:8.1f} MB  ({mb - base:+.1f} MB)")
        growth = samples[-1][1] - base
        worst = max(worst, growth)
        print(
            f"  growth after {FIRST}: {growth:+.1f} MB ({'within' if growth <= LIMIT_MB else 'over'} {LIMIT_MB:.0f} MB)"
        )
    return 0 if worst <= LIMIT_MB else 1


if __name__ == "__main__":
    raise SystemExit(main())
