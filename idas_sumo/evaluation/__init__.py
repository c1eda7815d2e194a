"""The paper's evaluation protocol, its metrics and CSV export."""

DEFAULT_EVAL_COPIES = 8
"""Episodes one evaluation process runs side by side in one SUMO run (``evaluate --copies``); here,
not in runner.py, so that the CLI can show it without importing pandas. Chosen by measurement
(README, performance)."""
