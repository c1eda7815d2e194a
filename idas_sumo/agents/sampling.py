"""A rollout's action draws: each episode's own counter-based stream, every row of a step in one compiled call.

An episode's k-th sampled row takes its seven uniforms from Philox4x32-10 (Salmon et al., "Parallel random numbers:
as easy as 1, 2, 3", SC 2011; the generator of Random123, cuRAND and JAX) keyed by the episode's ``action_seed``,
at counters (k, 0) and (k, 1): a pure function of the seed and how many rows the episode sampled before, so its
draws do not depend on which episodes share the step, on ``--copies`` or on ``--workers``, and a step's rows of
all episodes cost one call instead of a torch generator call per episode. A row's action is the Gumbel-max
race over its allowed actions: argmax(logit - log E) with E = -log U ~ Exp(1), a draw from softmax(logits)
(what ``torch.multinomial`` computes on the CPU as argmax(p / E)). A greedy episode's row takes the first
largest allowed logit, as ``argmax`` of the masked logits does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.jit import kernel

__all__ = ["ActionStreams", "philox4x32"]

_M0, _M1 = np.uint64(0xD2511F53), np.uint64(0xCD9E8D57)
"""Philox4x32's multipliers."""
_W0, _W1 = np.uint64(0x9E3779B9), np.uint64(0xBB67AE85)
"""Its key schedule's increments (the golden ratio's and sqrt(3) - 1's bits)."""
_ROUNDS = 10
_LOW = np.uint64(0xFFFFFFFF)
_HIGH = np.uint64(32)
_UNIT = 2.0**-32


def _philox4x32(
    c0: np.uint64, c1: np.uint64, c2: np.uint64, c3: np.uint64, k0: np.uint64, k1: np.uint64
) -> tuple[np.uint64, np.uint64, np.uint64, np.uint64]:
    """Philox4x32-10 of the counter (c0, c1, c2, c3) under the key (k0, k1): 32-bit words, each held in a uint64
    (so a word times a multiplier is exact)."""
    for r in range(_ROUNDS):
        if r:
            k0, k1 = (k0 + _W0) & _LOW, (k1 + _W1) & _LOW
        p0, p1 = _M0 * c0, _M1 * c2
        c0, c1, c2, c3 = (p1 >> _HIGH) ^ c1 ^ k0, p1 & _LOW, (p0 >> _HIGH) ^ c3 ^ k1, p0 & _LOW
    return c0, c1, c2, c3


philox4x32 = kernel(_philox4x32)


def _race(
    logits: npt.NDArray[np.float32],
    allowed: npt.NDArray[np.int8],
    r: int,
    words: tuple[np.uint64, np.uint64, np.uint64, np.uint64],
    first: int,
    best: int,
    best_score: float,
) -> tuple[int, float]:
    """The Gumbel-max race of row r's allowed actions first .. first + 3 (one uniform per word), carried on
    from (best, best_score)."""
    for i in range(4):
        a = first + i
        if a >= logits.shape[1] or not allowed[r, a]:
            continue
        u = (np.float64(words[i]) + 0.5) * _UNIT  # in (0, 1): E = -log u is finite and positive
        score = np.float64(logits[r, a]) - math.log(-math.log(u))
        if best < 0 or score > best_score:
            best, best_score = a, score
    return best, best_score


_race_kernel = kernel(_race)


def _draw_actions(
    logits: npt.NDArray[np.float32],
    allowed: npt.NDArray[np.int8],
    jobs: npt.NDArray[np.int64],
    greedy: npt.NDArray[np.bool_],
    keys: npt.NDArray[np.uint64],
    drawn: npt.NDArray[np.uint64],
    out: npt.NDArray[np.int64],
) -> int:
    """Each row's action into ``out``, rows in order (an episode's rows, in its own order, advance its ``drawn``
    count); returns the first row with no allowed action, or -1."""
    for r in range(logits.shape[0]):
        j = jobs[r]
        best, best_score = -1, -np.inf
        if greedy[j]:
            for a in range(logits.shape[1]):
                if allowed[r, a] and (best < 0 or logits[r, a] > best_score):
                    best, best_score = a, np.float64(logits[r, a])
        else:
            k, key = drawn[j], keys[j]
            drawn[j] = k + np.uint64(1)
            for half in range(2):
                words = philox4x32(
                    k & _LOW, k >> _HIGH, np.uint64(half), np.uint64(0), key & _LOW, key >> _HIGH
                )
                best, best_score = _race_kernel(logits, allowed, r, words, 4 * half, best, best_score)
        if best < 0:
            return r
        out[r] = best
    return -1


_draw_actions_kernel = kernel(_draw_actions)


class ActionStreams:
    """The draws of one rollout's episodes (job j: ``seeds[j]``, greedy if ``greedy[j]``): ``draw`` turns a
    step's rows (each naming its job) into actions."""

    def __init__(self, seeds: Sequence[int], greedy: Sequence[bool]) -> None:
        if any(not 0 <= s < 2**64 for s in seeds):
            raise ValueError("an action seed must be in [0, 2^64)")
        self.keys = np.array(seeds, dtype=np.uint64)
        self.greedy = np.array(greedy, dtype=np.bool_)
        self.drawn = np.zeros(len(self.keys), dtype=np.uint64)
        """How many rows each episode has sampled: its next row's counter."""

    def draw(
        self, logits: npt.NDArray[np.float32], allowed: npt.NDArray[np.int8], jobs: npt.NDArray[np.int64]
    ) -> npt.NDArray[np.int64]:
        """One action per row of (unmasked) ``logits``, never one ``allowed`` forbids; ``jobs``: each row's episode."""
        n = len(logits)
        if logits.shape != (n, N_ACTIONS) or allowed.shape != logits.shape or np.shape(jobs) != (n,):
            raise ValueError(
                f"expected logits and masks (B, {N_ACTIONS}) and jobs (B,), got shapes {logits.shape}, "
                f"{allowed.shape} and {np.shape(jobs)}"
            )
        if n and not (int(jobs.min()) >= 0 and int(jobs.max()) < len(self.keys)):
            raise ValueError(f"a row's episode is not one of the {len(self.keys)} streams")
        out = np.empty(n, dtype=np.int64)
        bad = _draw_actions_kernel(
            np.ascontiguousarray(logits, dtype=np.float32),
            np.ascontiguousarray(allowed, dtype=np.int8),
            np.ascontiguousarray(jobs, dtype=np.int64),
            self.greedy,
            self.keys,
            self.drawn,
            out,
        )
        if bad >= 0:
            raise ValueError(f"row {bad} has no allowed action (hard brake is never masked)")
        return out
