"""The driver-type sweep in the paper's Fig. 6 set-up: the main car at b_type -1 instead of the suite's 0.

    python scripts/driver_types_fig6.py --baseline idas --seed 2019 --out results/driver-types-fig6

Fig. 6 fixes "all parameters in the scenario considered in Fig. 5(a) except for the driver type of the merging
car" (paper L358), and Fig. 5's caption sets "the driver type for the main-lane car and merge-lane car [to] -1
and 1 respectively" (L301). ``idas-sumo evaluate --suite driver-types`` keeps the main car at
``evaluation.sweep.MAIN_CAR_B_TYPE`` (0); this runs the same suite, the same starts and merge-car b_types, with
the main car at -1. Every other flag is ``idas-sumo evaluate``'s (one worker: the sweep is drawn in this
process).
"""

from __future__ import annotations

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import sys

from idas_sumo.cli import main
from idas_sumo.evaluation import sweep

FIG6_MAIN_CAR_B_TYPE = -1.0
"""Paper L301: the main-lane car's driver type in Fig. 5, whose scenario (a) Fig. 6 sweeps (L358)."""

if __name__ == "__main__":
    if any(a == "--suite" or a.startswith("--suite=") for a in sys.argv[1:]):
        print("driver_types_fig6: error: the suite is driver-types, do not pass --suite", file=sys.stderr)
        raise SystemExit(2)
    sweep.MAIN_CAR_B_TYPE = FIG6_MAIN_CAR_B_TYPE  # read by sweep_scenarios and the verdict line when they run
    raise SystemExit(main(["evaluate", "--suite", "driver-types", *sys.argv[1:]]))
