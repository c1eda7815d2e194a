"""What the centralised critic Q gets besides the global state (``env/state_layout.py``).

The other agents' actions one-hot (STATE_SLOTS × N_ACTIONS, the own slot and absent or uncontrolled
slots zeroed) and the own slot one-hot (STATE_SLOTS), so one shared network answers for every agent
(COMA's agent-id input).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.state_layout import STATE_FEATURES, STATE_SLOTS

OTHERS_ACTIONS_DIM = STATE_SLOTS * N_ACTIONS  # 112

# Row n keeps every slot's block but slot n's own (a product with 0/1 values, exact).
_OTHERS_ONLY = 1.0 - np.kron(np.eye(STATE_SLOTS, dtype=np.float32), np.ones((1, N_ACTIONS), dtype=np.float32))

# Recorded in checkpoints so a critic trained on another state layout is refused on load.
STATE_LAYOUT_ID = f"slots{STATE_SLOTS}-features{STATE_FEATURES}-actions{N_ACTIONS}-v1"


def others_actions_onehot(actions: npt.ArrayLike, acting: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """(STATE_SLOTS, OTHERS_ACTIONS_DIM) float32: row n is what slot n's critic input sees.

    ``actions``: (STATE_SLOTS,) int action per slot (ignored where ``acting`` is false);
    ``acting``: (STATE_SLOTS,) bool, true for slots whose vehicle is a learning agent that acted.
    Row n holds every acting slot's action one-hot except slot n's own, which COMA marginalises.
    """
    act = np.asarray(actions, dtype=np.int64)
    on = np.asarray(acting, dtype=np.bool_)
    if act.shape != (STATE_SLOTS,) or on.shape != (STATE_SLOTS,):
        raise ValueError(f"actions and acting must have shape ({STATE_SLOTS},)")
    if np.any(on & ((act < 0) | (act >= N_ACTIONS))):
        raise ValueError(f"acting slots need actions in [0, {N_ACTIONS}), got {act[on].tolist()}")
    joint = np.zeros((STATE_SLOTS, N_ACTIONS), dtype=np.float32)
    joint[np.flatnonzero(on), act[on]] = 1.0
    return joint.reshape(1, -1) * _OTHERS_ONLY
