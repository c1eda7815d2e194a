"""The global state ``MergeEngine.state(k)`` returns for the centralised critic Q.

The state is a fixed number of vehicle slots (STATE_SLOTS), each a row of STATE_FEATURES floats::

    [present, on_main, on_merge, on_out, dist_to_merge / 250 m, speed / 20 m/s, accel / 4 m/s²,
     b_prio, b_type / 2, controlled]

flattened row-major into a vector of STATE_DIM floats. Empty slots are all zeros (``present`` = 0).
The scales are the observation's (``env/layout.py``), so both critics see the same units. What the
critic gets besides the state (the other agents' actions, its own slot) is agent-side:
``agents/critic_input.py``.
"""

from __future__ import annotations

# 8 learning agents in stage 2 plus room for SUMO's own cars in stage 1 (2 to 8 per road).
STATE_SLOTS = 16
STATE_FEATURE_NAMES: tuple[str, ...] = (
    "present",
    "on_main",
    "on_merge",
    "on_out",
    "dist_to_merge",
    "speed",
    "accel",
    "b_prio",
    "b_type",
    "controlled",
)
STATE_FEATURES = len(STATE_FEATURE_NAMES)  # 10
STATE_DIM = STATE_SLOTS * STATE_FEATURES  # 160
