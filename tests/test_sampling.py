"""agents/sampling.py: the rollouts' per-episode draws (Philox4x32-10 and the Gumbel-max race)."""

from __future__ import annotations

import numpy as np
import pytest

from idas_sumo.agents.sampling import ActionStreams, philox4x32
from idas_sumo.env.actions import HARD_BRAKE, N_ACTIONS

# Random123's tests/kat_vectors, the three "philox4x32 10" lines: counter (4 words), key (2), then the result.
KAT = [
    ((0, 0, 0, 0), (0, 0), (0x6627E8D5, 0xE169C58D, 0xBC57AC4C, 0x9B00DBD8)),
    ((0xFFFFFFFF,) * 4, (0xFFFFFFFF,) * 2, (0x408F276D, 0x41C83B0E, 0xA20BC7C6, 0x6D5451FD)),
    (
        (0x243F6A88, 0x85A308D3, 0x13198A2E, 0x03707344),
        (0xA4093822, 0x299F31D0),
        (0xD16CFE09, 0x94FDCCEB, 0x5001E420, 0x24126EA1),
    ),
]


@pytest.mark.parametrize(("counter", "key", "expected"), KAT)
def test_philox_gives_random123s_known_answers(
    counter: tuple[int, ...], key: tuple[int, ...], expected: tuple[int, ...]
) -> None:
    words = philox4x32(*(np.uint64(w) for w in (*counter, *key)))
    assert [int(w) for w in words] == list(expected)


def test_draws_follow_the_softmax_of_the_allowed_logits() -> None:
    """200,000 draws of one row: each allowed action's share within 4 standard errors of softmax; the masked one
    never drawn."""
    logits = np.array([[0.3, -0.5, 1.0, 2.0, -1.2, 0.1, 0.7]], dtype=np.float32)
    allowed = np.ones((1, N_ACTIONS), dtype=np.int8)
    allowed[0, 3] = 0  # the most likely action, masked
    n = 200_000
    streams = ActionStreams([7], [False])
    actions = streams.draw(np.repeat(logits, n, axis=0), np.repeat(allowed, n, axis=0), np.zeros(n, np.int64))
    p = np.exp(logits[0].astype(np.float64)) * allowed[0]
    p /= p.sum()
    share = np.bincount(actions, minlength=N_ACTIONS) / n
    assert share[3] == 0.0
    assert np.all(np.abs(share - p) <= 4 * np.sqrt(p * (1 - p) / n))
    assert int(streams.drawn[0]) == n


def test_an_episodes_draws_do_not_depend_on_the_rows_beside_it() -> None:
    """Episode 0's rows drawn alone, or between another episode's rows in the same calls, give the same actions;
    each call advances only the streams of the episodes it drew for."""
    rng = np.random.default_rng(1)
    logits = rng.normal(size=(30, N_ACTIONS)).astype(np.float32)
    allowed = (rng.random((30, N_ACTIONS)) < 0.6).astype(np.int8)
    allowed[:, HARD_BRAKE] = 1
    alone = ActionStreams([11], [False])
    solo = np.concatenate(
        [alone.draw(logits[i : i + 3], allowed[i : i + 3], np.zeros(3, np.int64)) for i in (0, 3)]
    )
    shared = ActionStreams([99, 11], [False, False])
    jobs = np.array([0, 1, 1, 0, 1, 0], dtype=np.int64)  # episode 1 (seed 11) in rows 1, 2, 4
    mixed_logits = np.zeros((6, N_ACTIONS), dtype=np.float32)
    mixed_allowed = np.ones((6, N_ACTIONS), dtype=np.int8)
    mixed_logits[[1, 2, 4]], mixed_allowed[[1, 2, 4]] = logits[:3], allowed[:3]
    first = shared.draw(mixed_logits, mixed_allowed, jobs)[[1, 2, 4]]
    second = shared.draw(logits[3:6], allowed[3:6], np.ones(3, np.int64))
    assert np.concatenate([first, second]).tolist() == solo.tolist()
    assert shared.drawn.tolist() == [3, 6]


def test_another_seed_draws_otherwise() -> None:
    logits = np.zeros((500, N_ACTIONS), dtype=np.float32)
    allowed = np.ones((500, N_ACTIONS), dtype=np.int8)
    jobs = np.zeros(500, np.int64)
    a, b = (ActionStreams([s], [False]).draw(logits, allowed, jobs) for s in (1, 2))
    assert (a != b).mean() > 0.7  # (6/7 of uniform draws differ)


def test_a_greedy_episode_takes_the_first_largest_allowed_logit_and_draws_nothing() -> None:
    logits = np.array(
        [[5.0, 1.0, 3.0, 3.0, 0.0, 0.0, 0.0], [1.0, 2.0, 2.0, 0.0, 0.0, 0.0, 0.0]], dtype=np.float32
    )
    allowed = np.array([[0, 1, 1, 1, 1, 1, 1], [1, 1, 1, 1, 1, 1, 1]], dtype=np.int8)
    streams = ActionStreams([3], [True])
    assert streams.draw(logits, allowed, np.zeros(2, np.int64)).tolist() == [2, 1]
    assert int(streams.drawn[0]) == 0


def test_a_row_with_no_allowed_action_is_refused() -> None:
    allowed = np.zeros((2, N_ACTIONS), dtype=np.int8)
    allowed[0, HARD_BRAKE] = 1
    with pytest.raises(ValueError, match="row 1 has no allowed action"):
        ActionStreams([1], [False]).draw(np.zeros((2, N_ACTIONS), np.float32), allowed, np.zeros(2, np.int64))


def test_rows_and_masks_of_other_shapes_are_refused() -> None:
    with pytest.raises(ValueError, match="shape"):
        ActionStreams([1], [False]).draw(
            np.zeros((2, N_ACTIONS), np.float32), np.ones((3, N_ACTIONS), np.int8), np.zeros(2, np.int64)
        )
