"""The paper's evaluation protocol, its metrics and CSV export."""

DEFAULT_EVAL_COPIES = 16
"""Episodes one evaluation process runs side by side in one SUMO run (``evaluate --copies``); here,
not in runner.py, so that the CLI can show it without importing pandas.

Measured: ``evaluate --baseline all --suite paper --scenarios 100`` (5 methods x 100 scenarios, others
IDAS) on the 2 shared cores, wall time with copies = 1 / 8 / 16 / 32: 85 / 32.5 / 27.2 / 29.3 s
(load about 1 from other work). The pre-engine loop took 85 and 89 s in the same sitting."""
