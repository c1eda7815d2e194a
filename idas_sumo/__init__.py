"""idas-sumo: interaction-aware merging policies (IDAS, IROS 2019) trained and evaluated in SUMO."""

__version__ = "0.1.0"
