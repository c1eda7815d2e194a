"""The paper's evaluation protocol, its metrics and CSV export."""
