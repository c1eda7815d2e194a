"""Network shapes, masking, the learner's update, target updates and checkpoint round trips."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest
import torch

from idas_sumo.agents import networks
from idas_sumo.agents.critic_input import OTHERS_ACTIONS_DIM, others_actions_onehot
from idas_sumo.agents.learner import Batch, Learner, LearnerConfig
from idas_sumo.agents.networks import (
    BLOCKS_CHUNK_ROWS,
    CENTRAL_INPUT_DIM,
    ENCODER_CHUNK_ROWS,
    STATE_DIM,
    Actor,
    CentralCritic,
    GridEncoder,
    ObsWindows,
    ValueCritic,
)
from idas_sumo.agents.run_blocks import BlockedConvLayer
from idas_sumo.agents.run_conv import PIECES_PER_ROW_GUESS, RunPieces
from idas_sumo.env.actions import HARD_BRAKE, N_ACTIONS, RELEASE_BRAKE
from idas_sumo.env.layout import GRID_CELLS, N_SCALARS, OBS_DIM
from idas_sumo.env.state_layout import STATE_SLOTS
from idas_sumo.errors import InputError

B = 16


def random_batch(seed: int = 0, n: int = B) -> Batch:
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand(n, N_ACTIONS, generator=g) < 0.6
    mask[:, HARD_BRAKE] = True  # never masked, as in env/actions.py
    action = torch.multinomial(mask.float(), 1, generator=g).squeeze(1)
    next_mask = torch.rand(n, N_ACTIONS, generator=g) < 0.6
    next_mask[:, HARD_BRAKE] = True
    return Batch(
        obs=torch.rand(n, OBS_DIM, generator=g),
        mask=mask,
        action=action,
        reward=torch.randn(n, generator=g),
        next_obs=torch.rand(n, OBS_DIM, generator=g),
        done=(torch.rand(n, generator=g) < 0.2).float(),
        state=torch.rand(n, STATE_DIM, generator=g),
        others_actions=(torch.rand(n, OTHERS_ACTIONS_DIM, generator=g) < 0.1).float(),
        slot=torch.randint(0, STATE_SLOTS, (n,), generator=g),
        joint_reward=torch.randn(n, generator=g),
        next_state=torch.rand(n, STATE_DIM, generator=g),
        next_others_actions=(torch.rand(n, OTHERS_ACTIONS_DIM, generator=g) < 0.1).float(),
        next_slot=torch.randint(0, STATE_SLOTS, (n,), generator=g),
        next_action=torch.multinomial(next_mask.float(), 1, generator=g).squeeze(1),
        next_valid=(torch.rand(n, generator=g) < 0.8).float(),
    )


def params(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


def test_output_shapes() -> None:
    torch.manual_seed(0)
    obs = torch.rand(3, OBS_DIM)
    mask = torch.ones(3, N_ACTIONS, dtype=torch.bool)
    enc = GridEncoder()
    assert enc(obs).shape == (3, 64)
    grid = obs[:, N_SCALARS:].reshape(3, 2, 2, GRID_CELLS).transpose(1, 2)
    assert enc.conv(grid).shape == (3, 2, 2, 371)  # 2 filters, 2 lane rows after padding, 400 - 30 + 1
    assert Actor()(obs).shape == (3, N_ACTIONS)
    assert Actor().distribution(obs, mask).probs.shape == (3, N_ACTIONS)
    assert ValueCritic()(obs).shape == (3,)
    slots = torch.tensor([0, 5, 15])
    q = CentralCritic()(torch.rand(3, STATE_DIM), torch.zeros(3, OTHERS_ACTIONS_DIM), slots)
    assert q.shape == (3, N_ACTIONS)
    assert CENTRAL_INPUT_DIM == STATE_DIM + STATE_SLOTS * N_ACTIONS + STATE_SLOTS == 288


def test_encoder_sees_each_lane_and_the_scalars() -> None:
    torch.manual_seed(0)
    enc = GridEncoder()
    base = torch.zeros(1, OBS_DIM)
    out = enc(base)
    for start in (0, N_SCALARS, N_SCALARS + 2 * GRID_CELLS):  # scalars, obs_cl occupancy, obs_ol occupancy
        changed = base.clone()
        changed[0, start : start + 50] = 1.0
        assert not torch.allclose(enc(changed), out)


def _assert_matches_conv2d(enc: GridEncoder, obs: torch.Tensor) -> None:
    """``enc``'s fast paths (acting's, and the learner's over the reached blocks) give the plain conv2d path's
    outputs and parameter gradients on ``obs``."""
    ref = enc.reference_forward(obs)
    weights = torch.randn_like(ref)
    ref_grads = torch.autograd.grad((ref * weights).sum(), list(enc.parameters()))
    for fast in (enc(obs), enc(ObsWindows(obs, blocks=True))):
        # Float32 sums of ~1500 terms in another order: equal to a few ulps of the output's scale.
        torch.testing.assert_close(fast, ref, rtol=1e-5, atol=1e-6 * float(ref.detach().abs().max()))
        grads = torch.autograd.grad((fast * weights).sum(), list(enc.parameters()))
        for name_param, g_fast, g_ref in zip(enc.named_parameters(), grads, ref_grads, strict=True):
            scale = float(g_ref.abs().max())
            torch.testing.assert_close(g_fast, g_ref, rtol=1e-5, atol=1e-6 * scale, msg=name_param[0])


def test_fast_encoder_matches_conv2d_forward_and_gradients() -> None:
    """The conv from the grids' runs is the paper's conv: same outputs and same parameter gradients as the
    plain conv2d → flatten → cat → Linear, for random weights, a non-zero bias and every cell (random
    cells: every cell a run of its own)."""
    torch.manual_seed(0)
    enc = GridEncoder()
    with torch.no_grad():
        for p in enc.parameters():
            p.normal_(0.0, 0.3)
    _assert_matches_conv2d(enc, torch.randn(7, OBS_DIM))
    # A single occupied cell at the right edge reaches the output too (the blocks end at cell 400).
    edge = torch.zeros(1, OBS_DIM)
    edge[0, N_SCALARS + GRID_CELLS - 1] = 1.0
    torch.testing.assert_close(enc(edge), enc.reference_forward(edge), rtol=1e-5, atol=1e-5)
    assert not torch.allclose(enc(edge), enc(torch.zeros(1, OBS_DIM)))
    assert enc(torch.zeros(0, OBS_DIM)).shape == (0, enc(edge).shape[1])  # no agents acting this step
    by_blocks = enc(ObsWindows(edge, blocks=True))  # the edge cell is in the last, partial block
    torch.testing.assert_close(by_blocks, enc.reference_forward(edge), rtol=1e-5, atol=1e-5)
    assert enc(ObsWindows(torch.zeros(0, OBS_DIM), blocks=True)).shape == (0, by_blocks.shape[1])


def test_fast_encoder_on_mostly_empty_road_matches_conv2d_gradients() -> None:
    """Grids with empty road (cells no run reaches) give conv2d's outputs and parameter gradients too."""
    torch.manual_seed(1)
    enc = GridEncoder()
    with torch.no_grad():
        for p in enc.parameters():
            p.normal_(0.0, 0.3)
    obs = torch.zeros(5, OBS_DIM)
    obs[:, :N_SCALARS] = torch.randn(5, N_SCALARS)
    obs[0, N_SCALARS + 10 : N_SCALARS + 21] = 1.0  # one car near the start of obs_cl
    obs[1, N_SCALARS + 3 * GRID_CELLS + 300 : N_SCALARS + 3 * GRID_CELLS + 311] = -0.4  # a speed in obs_ol
    obs[2, N_SCALARS:] = torch.randn(4 * GRID_CELLS)  # every cell its own run
    # rows 3 and 4: empty road
    _assert_matches_conv2d(enc, obs)


def test_encoder_in_row_slices_matches_conv2d_and_each_slice_alone() -> None:
    """A batch longer than ENCODER_CHUNK_ROWS goes through in slices: each row's output is what it gives
    in a slice of its own (to float rounding: a GEMM's kernel depends on its row count), and the outputs
    and gradients are still conv2d's."""
    torch.manual_seed(2)
    enc = GridEncoder()
    rows = 2 * ENCODER_CHUNK_ROWS + 3
    obs = torch.zeros(rows, OBS_DIM)
    obs[:, :N_SCALARS] = torch.randn(rows, N_SCALARS)
    cells = torch.randint(0, 4 * GRID_CELLS - 11, (rows,))
    for offset in range(11):  # one car-long run per row, somewhere on the four grid rows
        obs[torch.arange(rows), N_SCALARS + cells + offset] = 0.7
    whole = enc(obs)
    slices = torch.cat([enc(part) for part in obs.split(ENCODER_CHUNK_ROWS)])
    torch.testing.assert_close(whole, slices, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(whole[-3:], enc(obs[-3:]), rtol=1e-6, atol=1e-6)
    _assert_matches_conv2d(enc, obs)


def test_blocks_path_in_row_slices_matches_conv2d() -> None:
    """The learner's blocks path cuts a batch longer than BLOCKS_CHUNK_ROWS too: two chunks, conv2d's outputs and
    gradients, and each row what it gives in a slice of its own (to float rounding)."""
    torch.manual_seed(4)
    enc = GridEncoder()
    rows = BLOCKS_CHUNK_ROWS + 5
    obs = torch.zeros(rows, OBS_DIM)
    obs[:, :N_SCALARS] = torch.randn(rows, N_SCALARS)
    cells = torch.randint(0, 4 * GRID_CELLS - 11, (rows,))
    for offset in range(11):
        obs[torch.arange(rows), N_SCALARS + cells + offset] = 0.7
    windows = ObsWindows(obs, blocks=True)
    assert [len(c.obs) for c in windows.chunks] == [BLOCKS_CHUNK_ROWS, 5]
    torch.testing.assert_close(
        enc(windows)[-5:], enc(ObsWindows(obs[-5:], blocks=True)), rtol=1e-6, atol=1e-6
    )
    _assert_matches_conv2d(enc, obs)


def _ones_kernel_encoder(bias: float) -> GridEncoder:
    """An encoder whose conv weights are all 1 and whose conv bias is ``bias``: its conv output at cell p of
    either output row is bias + the sum of the 30 cells p..p+29 of both lanes and both channels."""
    enc = GridEncoder()
    with torch.no_grad():
        enc.conv.weight.fill_(1.0)
        assert enc.conv.bias is not None
        enc.conv.bias.fill_(bias)
    return enc


def _conv_features(enc: GridEncoder, obs: torch.Tensor) -> torch.Tensor:
    """ReLU(conv) as the fast path computes it, back in conv2d's (filter, row, cell) order: (B, 2, 2, 371)."""
    chunk = ObsWindows(obs).chunks[0]
    ours = enc._conv(chunk, enc._operands()).reshape(obs.shape[0], 371, 2, 2)
    return ours.permute(0, 2, 3, 1)


@pytest.mark.parametrize(
    ("start", "length", "value", "expected"),
    [
        # a car of 11 cells of 0.5 at cells 100..110: a window from p reads min(p + 30, 111) - max(p, 100) cells
        (100, 11, 0.5, {70: 0.0, 71: 0.5, 81: 5.5, 85: 5.5, 100: 5.5, 101: 5.0, 110: 0.5, 111: 0.0}),
        # a queue of 40 equal cells, longer than a piece (cut at 16 and 32): a window inside it reads 30 cells
        (200, 40, 1.0, {171: 1.0, 190: 20.0, 200: 30.0, 210: 30.0, 225: 15.0, 239: 1.0, 240: 0.0}),
        # a car on the last cells: only the last windows reach it
        (395, 5, -0.2, {365: 0.0, 366: -0.2, 370: -1.0}),
        # a car on the first cells
        (0, 3, 2.0, {0: 6.0, 1: 4.0, 2: 2.0, 3: 0.0}),
    ],
)
def test_conv_of_one_run_is_its_overlap_with_each_window(
    start: int, length: int, value: float, expected: dict[int, float]
) -> None:
    """Hand-checked: with a kernel of ones, the conv at cell p is bias + value · (cells of the run among
    p..p+29), on both output rows (the 3-tall kernel sees both lanes). And the whole encoder equals conv2d's."""
    enc = _ones_kernel_encoder(bias=1.5)
    obs = torch.zeros(1, OBS_DIM)
    obs[0, N_SCALARS + start : N_SCALARS + start + length] = value  # obs_cl occupancy channel
    conv = _conv_features(enc, obs)
    for cell, summed in expected.items():
        want = torch.full((2, 2), max(1.5 + summed, 0.0))
        torch.testing.assert_close(conv[0, :, :, cell], want, rtol=0, atol=1e-5, msg=f"cell {cell}")
    torch.testing.assert_close(enc(obs), enc.reference_forward(obs), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(("bias", "total", "passing"), [(1.5, 2886.0, 371), (-1.0, 504.0, 36)])
def test_blocked_conv_layer_sums_relu_conv_times_the_weight_by_hand(
    bias: float, total: float, passing: int
) -> None:
    """Hand-worked, through the learner's path (``BlockedConvLayer``): with a kernel of ones and every weight 1,
    the layer's output is the sum of ReLU(conv) over the 4 · 371 conv outputs, and its gradient by each of the 4
    conv biases is the number of outputs whose ReLU passes. A car of 11 cells of 0.5 at cells 100..110: the
    window from p reads 1..10 of its cells for p = 71..80, all 11 for p = 81..100, 10..1 for p = 101..110.
    Bias 1.5: every output passes, 4 · (371 · 1.5 + 0.5 · 11 · 30) = 2886. Bias -1: only windows reading 3 or
    more cells pass (p = 73..108, 36 of them), 4 · (2 · Σ_{n=3..10} (0.5 n - 1) + 20 · 4.5) = 4 · 126 = 504."""
    enc = _ones_kernel_encoder(bias)
    obs = torch.zeros(1, OBS_DIM)
    obs[0, N_SCALARS + 100 : N_SCALARS + 111] = 0.5
    runs = ObsWindows(obs, blocks=True).chunks[0]
    operands = enc._operands()
    weight = torch.ones_like(operands.joint_conv_weight[:, :1]).requires_grad_()
    conv_bias = operands.bias.detach().clone().requires_grad_()
    out = BlockedConvLayer.apply(
        operands.run_table.detach(), conv_bias, weight, runs.pieces, 1, networks._GEOMETRY
    )
    torch.testing.assert_close(out, torch.tensor([[total]]), rtol=1e-6, atol=1e-4)
    grad_bias, grad_weight = torch.autograd.grad(out.sum(), (conv_bias, weight))
    torch.testing.assert_close(grad_bias, torch.full((4,), float(passing)))
    assert float(grad_weight.sum()) == pytest.approx(total)  # d out / d w_k is ReLU(conv)_k


def test_conv_of_touching_runs_and_both_lanes_adds_up() -> None:
    """Two cars touching (values 1 and 0.3, no gap: two runs) on obs_cl, a relative speed of -0.5 on obs_ol at
    the same 20 cells; with a ones kernel and no bias the window from p sums what it reads of all four rows."""
    enc = _ones_kernel_encoder(bias=0.0)
    obs = torch.zeros(1, OBS_DIM)
    cl_occ, ol_rel = N_SCALARS, N_SCALARS + 3 * GRID_CELLS
    obs[0, cl_occ + 90 : cl_occ + 100] = 1.0
    obs[0, cl_occ + 100 : cl_occ + 110] = 0.3
    obs[0, ol_rel + 90 : ol_rel + 110] = -0.5
    conv = _conv_features(enc, obs)
    # p = 61 reads cell 90 of each; 80 and 90 read all: 10 + 3 - 10; 95: 5 + 3 - 7.5; 100: 3 - 5 < 0 (ReLU)
    for cell, want in {61: 0.5, 80: 3.0, 90: 3.0, 95: 0.5, 100: 0.0}.items():
        torch.testing.assert_close(conv[0, :, :, cell], torch.full((2, 2), want), rtol=0, atol=1e-5)
    enc_random = GridEncoder()
    _assert_matches_conv2d(enc_random, obs)


def test_run_pieces_of_a_batch_past_the_first_guess_are_each_rows_own() -> None:
    """A batch with more pieces than ``RunPieces.of``'s first scan has room for (random cells: a piece per cell)
    is scanned again with room for all: the pieces are those of each row found alone, in row order."""
    obs = torch.zeros(4, OBS_DIM)
    obs[1] = torch.rand(OBS_DIM, generator=torch.Generator().manual_seed(3))
    obs[2, N_SCALARS + 10 : N_SCALARS + 50] = 0.5  # one run of 40 cells: three pieces
    obs[3, N_SCALARS : N_SCALARS + 300] = -0.0  # empty, as 0.0 is (the scans skip empty blocks by their bits)
    obs[3, OBS_DIM - 1] = 2.0  # the very last cell: one piece
    whole = RunPieces.of(obs, N_SCALARS, 4, GRID_CELLS, 16)
    assert len(whole.value) == (OBS_DIM - N_SCALARS) + 3 + 1 > 4 * PIECES_PER_ROW_GUESS
    assert (whole.grid_row[-1], whole.start[-1], whole.value[-1]) == (3, GRID_CELLS - 1, 2.0)
    alone = [RunPieces.of(obs[i : i + 1], N_SCALARS, 4, GRID_CELLS, 16) for i in range(4)]
    assert np.array_equal(
        whole.grid_row, np.concatenate([np.full(len(a.value), i) for i, a in enumerate(alone)])
    )
    for field in ("table_row", "value", "start"):
        assert np.array_equal(getattr(whole, field), np.concatenate([getattr(a, field) for a in alone]))


@pytest.mark.parametrize("rows", [5, ENCODER_CHUNK_ROWS + 7])
def test_networks_on_shared_runs_give_the_bits_of_their_own_cut(rows: int) -> None:
    """The learner finds a batch's runs once (ObsWindows) for the actor, V and V̂: each network's output
    and parameter gradients are exactly those it computes from the observations themselves, on a batch with
    empty, partly and fully occupied grids, in one chunk and in several."""
    torch.manual_seed(3)
    obs = torch.zeros(rows, OBS_DIM)
    obs[:, :N_SCALARS] = torch.randn(rows, N_SCALARS)
    obs[1::3, N_SCALARS + 40 : N_SCALARS + 51] = 0.6  # one car near the start of obs_cl
    obs[2::3, N_SCALARS:] = torch.randn(len(range(2, rows, 3)), 4 * GRID_CELLS)  # every cell its own run
    shared = ObsWindows(obs)
    assert len(shared.chunks) == (1 if rows <= ENCODER_CHUNK_ROWS else 2)
    for net in (Actor(), ValueCritic()):
        own, cut = net(obs), net(shared)
        assert torch.equal(own, cut)
        weights = torch.randn_like(own)
        grads = [torch.autograd.grad((out * weights).sum(), list(net.parameters())) for out in (own, cut)]
        assert all(torch.equal(a, b) for a, b in zip(*grads, strict=True))
    with pytest.raises(ValueError, match="features"):
        ObsWindows(torch.zeros(2, OBS_DIM - 1))


def test_frozen_conv_operands_follow_every_weight_change() -> None:
    """With autograd off the encoder reuses its run table; an optimizer step or a
    load_state_dict (both change the weights in place) must be seen by the very next forward."""
    torch.manual_seed(0)
    actor, other = Actor(), Actor()
    obs = torch.zeros(6, OBS_DIM)
    obs[:, N_SCALARS + 180 : N_SCALARS + 200] = 1.0
    obs[:, :N_SCALARS] = torch.rand(6, N_SCALARS)

    def fresh(net: Actor) -> torch.Tensor:
        with torch.enable_grad():  # autograd on: operands built from the weights as they are
            return net(obs).detach()

    with torch.inference_mode():
        before = actor(obs)
        assert torch.equal(actor(obs), before)  # reused operands give the same numbers
    assert torch.equal(before, fresh(actor))
    opt = torch.optim.SGD(actor.parameters(), lr=0.1)
    for param in actor.parameters():  # a step with no grad-enabled forward in between
        param.grad = torch.full_like(param, 0.01)
    with torch.no_grad():
        actor(obs)  # operands frozen again
    opt.step()
    with torch.no_grad():
        stepped = actor(obs)
    assert not torch.equal(stepped, before)
    assert torch.equal(stepped, fresh(actor))
    with torch.inference_mode():
        actor(obs)
    actor.load_state_dict(other.state_dict())
    with torch.inference_mode():
        loaded = actor(obs)
    assert torch.equal(loaded, fresh(other))


def test_inference_logits_match_the_plain_forward_and_follow_weight_changes() -> None:
    """``Actor.inference_logits`` (the rollout's compiled forward) is the plain conv2d forward to float
    rounding: cars as runs, runs longer than a piece, cells at both edges, every cell its own run, empty road;
    after an optimiser step or a load_state_dict it gives the new weights' logits."""
    torch.manual_seed(2)
    actor, other = Actor(), Actor()
    with torch.no_grad():
        for p in [*actor.parameters(), *other.parameters()]:
            p.normal_(0.0, 0.3)
    obs = torch.zeros(6, OBS_DIM)
    obs[:, :N_SCALARS] = torch.randn(6, N_SCALARS)
    obs[0, N_SCALARS : N_SCALARS + 11] = 1.0  # a car at the left edge of obs_cl
    obs[0, N_SCALARS + GRID_CELLS : N_SCALARS + GRID_CELLS + 11] = 0.3  # its relative speed
    obs[1, N_SCALARS + 3 * GRID_CELLS + 360 :] = -0.4  # a 40-cell run to the right edge of obs_ol
    obs[2, N_SCALARS:] = torch.randn(4 * GRID_CELLS)  # every cell its own run
    obs[3, N_SCALARS + 2 * GRID_CELLS + 100 : N_SCALARS + 2 * GRID_CELLS + 120] = 1.0
    # rows 4 and 5: empty road

    def plain(net: Actor) -> torch.Tensor:
        with torch.no_grad():
            return net.head(net.encoder.reference_forward(obs))

    def close(net: Actor, expected: torch.Tensor) -> None:  # 1,484 terms summed in another order
        got = torch.from_numpy(net.inference_logits(obs.numpy()))
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5 * float(expected.abs().max()))

    close(actor, plain(actor))
    one_by_one = np.concatenate([actor.inference_logits(obs[i : i + 1].numpy()) for i in range(6)])
    assert np.array_equal(one_by_one, actor.inference_logits(obs.numpy()))  # a row does not see the others
    opt = torch.optim.SGD(actor.parameters(), lr=0.1)
    for param in actor.parameters():
        param.grad = torch.full_like(param, 0.01)
    opt.step()
    close(actor, plain(actor))
    actor.load_state_dict(other.state_dict())
    close(actor, plain(other))
    assert actor.inference_logits(np.zeros((0, OBS_DIM), np.float32)).shape == (0, N_ACTIONS)


def test_masked_probabilities_are_exactly_zero() -> None:
    torch.manual_seed(0)
    mask = torch.tensor([[0, 0, 0, 0, 0, 1, 0], [1, 0, 0, 0, 0, 1, 1]], dtype=torch.int8)
    probs = Actor().distribution(torch.rand(2, OBS_DIM), mask).probs
    assert torch.all(probs[mask == 0] == 0.0)
    torch.testing.assert_close(probs.sum(dim=1), torch.ones(2))


@pytest.mark.parametrize("allowed", [(HARD_BRAKE,), (0, RELEASE_BRAKE), (HARD_BRAKE, RELEASE_BRAKE)])
def test_act_never_samples_a_masked_action(allowed: tuple[int, ...]) -> None:
    learner = Learner(LearnerConfig())
    # Push the policy hard towards a masked action so masking, not chance, keeps it out.
    with torch.no_grad():
        learner.actor.head.bias.zero_()
        learner.actor.head.bias[2] = 50.0
    n = 1_000
    mask = np.zeros((n, N_ACTIONS), dtype=np.int8)
    mask[:, list(allowed)] = 1
    obs = np.random.default_rng(0).random((n, OBS_DIM), dtype=np.float32)
    actions = learner.act(obs, mask, torch.Generator().manual_seed(1))
    assert actions.dtype == np.int64 and actions.shape == (n,)
    assert set(np.unique(actions).tolist()) <= set(allowed)
    if len(allowed) == 2:
        assert set(np.unique(actions).tolist()) == set(allowed)  # both allowed ones do come out


def test_act_deterministic_is_masked_argmax() -> None:
    learner = Learner(LearnerConfig())
    with torch.no_grad():
        learner.actor.head.bias.copy_(torch.arange(N_ACTIONS, dtype=torch.float32) * 10.0)
    mask = np.array([[1, 1, 1, 1, 1, 1, 1], [1, 1, 0, 0, 0, 1, 0]], dtype=np.int8)
    obs = np.zeros((2, OBS_DIM), dtype=np.float32)
    actions = learner.act(obs, mask, torch.Generator(), deterministic=True)
    assert actions.tolist() == [6, 5]


def test_act_draws_what_multinomial_draws() -> None:
    """``act`` samples as ``torch.multinomial(probs, 1, generator=g)`` would, and leaves the generator in the
    state multinomial leaves it in (evaluation's and the envs' sampled policies rest on both)."""
    learner = Learner(LearnerConfig(), seed=3)
    rng = np.random.default_rng(5)
    n = 41
    obs = rng.random((n, OBS_DIM), dtype=np.float32)
    mask = (rng.random((n, N_ACTIONS)) < 0.5).astype(np.int8)
    mask[:, HARD_BRAKE] = 1
    mine = torch.Generator().manual_seed(11)
    actions = learner.act(obs, mask, mine)
    with torch.no_grad():
        probs = learner.actor.distribution(torch.from_numpy(obs), torch.from_numpy(mask).bool()).probs
    reference = torch.Generator().manual_seed(11)
    expected = torch.multinomial(probs, 1, generator=reference).squeeze(1)
    assert actions.tolist() == expected.tolist()
    assert torch.equal(mine.get_state(), reference.get_state())


def test_act_rejects_rows_without_allowed_actions() -> None:
    learner = Learner(LearnerConfig())
    with pytest.raises(ValueError):
        learner.act(np.zeros((1, OBS_DIM), np.float32), np.zeros((1, N_ACTIONS), np.int8), torch.Generator())


def test_update_stage2_finite_metrics_and_changes_all_nets() -> None:
    learner = Learner(LearnerConfig(use_central_critic=True))
    before = {n: params(m) for n, m in (("a", learner.actor), ("v", learner.value), ("q", learner.central))}
    metrics = learner.update(random_batch())
    for key in ("actor_loss", "v_loss", "q_loss", "entropy", "adv_v_mean", "adv_q_mean"):
        assert np.isfinite(metrics[key]), key
    assert metrics["q_loss"] > 0.0
    assert not same(before["a"], params(learner.actor))
    assert not same(before["v"], params(learner.value))
    assert not same(before["q"], params(learner.central))


def test_update_stage1_leaves_central_critic_alone() -> None:
    learner = Learner(LearnerConfig(use_central_critic=False))
    q_before, qt_before = params(learner.central), params(learner.central_target)
    batch = dataclasses.replace(
        random_batch(), state=None, others_actions=None, slot=None, joint_reward=None, next_state=None
    )
    metrics = learner.update(batch)
    assert all(np.isfinite(v) for v in metrics.values())
    assert metrics["q_loss"] == 0.0
    assert same(q_before, params(learner.central))
    assert same(qt_before, params(learner.central_target))


def test_targets_move_by_tau() -> None:
    tau = 0.25
    learner = Learner(LearnerConfig(use_central_critic=True, target_tau=tau))
    vt_old, qt_old = params(learner.value_target), params(learner.central_target)
    learner.update(random_batch())
    for target_old, target_new, online in (
        (vt_old, params(learner.value_target), params(learner.value)),
        (qt_old, params(learner.central_target), params(learner.central)),
    ):
        assert not same(target_old, target_new)
        for old, new, on in zip(target_old, target_new, online, strict=True):
            torch.testing.assert_close(new, (1 - tau) * old + tau * on)


def test_update_rejects_an_action_its_mask_forbids() -> None:
    batch = random_batch()
    batch.mask[0] = False
    batch.mask[0, HARD_BRAKE] = True
    batch.action[0] = 0
    with pytest.raises(ValueError):
        Learner(LearnerConfig()).update(batch)


def test_state_dict_round_trip() -> None:
    config = LearnerConfig(use_central_critic=True)
    learner = Learner(config, seed=1)
    learner.update(random_batch(0))
    buffer = io.BytesIO()
    torch.save(learner.state_dict(), buffer)
    buffer.seek(0)
    restored = Learner(config, seed=2)
    restored.load_state_dict(torch.load(buffer, weights_only=True))

    batch = random_batch(1)
    with torch.no_grad():
        torch.testing.assert_close(restored.actor(batch.obs), learner.actor(batch.obs), rtol=0, atol=0)
        torch.testing.assert_close(restored.value_target(batch.obs), learner.value_target(batch.obs))
        assert batch.state is not None and batch.others_actions is not None and batch.slot is not None
        args = (batch.state, batch.others_actions, batch.slot)
        torch.testing.assert_close(restored.central(*args), learner.central(*args))
    # The optimiser state came along too: the next update is identical.
    learner.update(batch)
    restored.update(batch)
    for a, b in ((learner.actor, restored.actor), (learner.central, restored.central)):
        assert same(params(a), params(b))


def test_load_refuses_another_layout() -> None:
    learner = Learner(LearnerConfig())
    state = learner.state_dict()
    state["obs_layout_id"] = "something-else"
    with pytest.raises(InputError):
        learner.load_state_dict(state)


def test_config_is_validated() -> None:
    with pytest.raises(InputError):
        LearnerConfig(alpha=1.5)
    with pytest.raises(InputError):
        LearnerConfig(target_tau=0.0)
    assert LearnerConfig().effective_alpha == 1.0
    assert LearnerConfig(use_central_critic=True).effective_alpha == 0.7


def test_others_actions_onehot() -> None:
    actions = np.zeros(STATE_SLOTS, dtype=np.int64)
    acting = np.zeros(STATE_SLOTS, dtype=np.bool_)
    actions[[0, 3]] = [HARD_BRAKE, 2]
    acting[[0, 3]] = True
    rows = others_actions_onehot(actions, acting)
    assert rows.shape == (STATE_SLOTS, OTHERS_ACTIONS_DIM)
    # slot 0 sees only slot 3's action 2; slot 3 sees only slot 0's hard brake; slot 5 sees both
    assert np.flatnonzero(rows[0]).tolist() == [3 * N_ACTIONS + 2]
    assert np.flatnonzero(rows[3]).tolist() == [HARD_BRAKE]
    assert np.flatnonzero(rows[5]).tolist() == [HARD_BRAKE, 3 * N_ACTIONS + 2]


def test_rollout_others_actions_are_the_onehot_rows() -> None:
    """The rollout's per-agent rows of the others' actions, built for a step of several copies at once, are
    each copy's ``others_actions_onehot`` rows, bit for bit (rows of the copies interleaved)."""
    from idas_sumo.agents.rollout import _others_actions

    rng = np.random.default_rng(0)
    for _ in range(50):
        copies = int(rng.integers(1, 4))
        slots, applied, copy, expected = [], [], [], []
        for k in range(copies):
            n = int(rng.integers(0, 9))
            s = rng.permutation(STATE_SLOTS)[:n].astype(np.int64)
            s[rng.random(n) < 0.2] = -1  # agents without a slot
            a = rng.integers(0, N_ACTIONS, n).astype(np.int64)
            actions = np.zeros(STATE_SLOTS, dtype=np.int64)
            acting = np.zeros(STATE_SLOTS, dtype=np.bool_)
            actions[s[s >= 0]] = a[s >= 0]
            acting[s[s >= 0]] = True
            table = np.vstack(
                [others_actions_onehot(actions, acting), np.zeros((1, OTHERS_ACTIONS_DIM), np.float32)]
            )
            slots.append(s)
            applied.append(a)
            copy.append(np.full(n, k, dtype=np.int64))
            expected.append(table[np.where(s >= 0, s, STATE_SLOTS)])
        order = rng.permutation(sum(len(s) for s in slots))
        got = _others_actions(*(np.concatenate(x)[order] for x in (copy, slots, applied)))
        want = np.concatenate(expected)[order]
        assert got.dtype == np.float32 and got.tobytes() == want.tobytes()


def test_normalised_advantages_change_the_step_but_not_the_direction_of_a_single_sample() -> None:
    from idas_sumo.agents.learner import _moments, _standardised

    def standardised(adv: torch.Tensor) -> torch.Tensor:
        return _standardised(adv, _moments(adv))  # a batch standardised on its own moments

    adv = torch.tensor([1.0, 2.0, 3.0, 6.0])
    # mean 3, deviations [-2, -1, 0, 3], sample std sqrt(14/3) = 2.1602
    torch.testing.assert_close(
        standardised(adv), torch.tensor([-0.9258, -0.4629, 0.0, 1.3887]), atol=1e-4, rtol=0
    )
    torch.testing.assert_close(standardised(torch.tensor([5.0])), torch.tensor([0.0]))


def _sequential(start: np.ndarray, factors: list[float], rows: list[np.ndarray]) -> np.ndarray:
    """start + factor_0 · row_0 + factor_1 · row_1 + ..., one term at a time in float32 (a product, then a sum)."""
    out = start.astype(np.float32).copy()
    for f, r in zip(factors, rows, strict=True):
        out = out + np.float32(f) * r
    return out


@pytest.mark.parametrize("n_out", [1, 7, 64])
def test_compiled_dense_layer_sums_in_the_order_of_one_input_at_a_time(n_out: int) -> None:
    """The actor's compiled dense layer adds several inputs a pass; its floats must stay those of one input at a
    time (inputs of very different sizes, so another order would round differently)."""
    from idas_sumo.agents.run_conv import _dense_kernel

    rng = np.random.default_rng(0)
    for n_in in [*range(1, 10), 32, 64]:
        x = (rng.standard_normal(n_in) * 10.0 ** rng.integers(-4, 5, n_in)).astype(np.float32)
        w_t = rng.standard_normal((n_in, n_out)).astype(np.float32)
        b = rng.standard_normal(n_out).astype(np.float32)
        out = np.empty(n_out, dtype=np.float32)
        _dense_kernel(x, w_t, b, False, out)
        want = _sequential(b, list(x), list(w_t))
        np.testing.assert_array_equal(out.view(np.uint32), want.view(np.uint32), err_msg=f"{n_in} inputs")
        _dense_kernel(x, w_t, b, True, out)
        np.testing.assert_array_equal(out, np.maximum(want, np.float32(0.0)))


def test_compiled_conv_terms_and_block_shares_add_in_the_order_of_one_at_a_time() -> None:
    """``_add_terms`` (eight terms a pass) and ``_sum_pairs`` (four blocks a pass) give each row the floats of
    adding its terms one at a time, in order, whatever their count (0, fewer than a pass, and remainders)."""
    from idas_sumo.agents.run_blocks import _sum_pairs_kernel
    from idas_sumo.agents.run_conv import _add_terms_kernel

    rng = np.random.default_rng(1)
    hidden, outputs = 64, 40
    weights = (rng.standard_normal((outputs, hidden)) * 10.0 ** rng.integers(-3, 4, (outputs, 1))).astype(
        np.float32
    )
    counts = [5, 0, 19, 8, 1]  # terms per row
    rows = np.repeat(np.arange(len(counts)), counts).astype(np.int32)
    k = np.concatenate([np.sort(rng.choice(outputs, c, replace=False)) for c in counts]).astype(np.int32)
    factor = rng.standard_normal(len(k)).astype(np.float32)
    h = rng.standard_normal((len(counts), hidden)).astype(np.float32)
    got = h.copy()
    _add_terms_kernel((k, rows, factor), len(k), weights, got)
    for r in range(len(counts)):
        mine = rows == r
        want = _sequential(h[r], list(factor[mine]), [weights[i] for i in k[mine]])
        np.testing.assert_array_equal(got[r].view(np.uint32), want.view(np.uint32), err_msg=f"row {r}")

    blocks = 11
    at = np.full((len(counts), blocks), -1, dtype=np.int64)
    reached = [rng.choice(blocks, c % blocks, replace=False) for c in counts]
    pair = 0
    for r, picked in enumerate(reached):
        for block in sorted(picked):
            at[r, block] = pair
            pair += 1
    shares = rng.standard_normal((pair, hidden)).astype(np.float32)
    per_block = rng.standard_normal((blocks, hidden)).astype(np.float32)
    out = np.empty((len(counts), hidden), dtype=np.float32)
    _sum_pairs_kernel(shares, per_block, at, out)
    idle = np.zeros(hidden, dtype=np.float32)
    for block in range(blocks):
        idle = idle + per_block[block]
    for r in range(len(counts)):
        picked = [b for b in range(blocks) if at[r, b] >= 0]
        want = idle.copy()
        for b in picked:
            want = want + (shares[at[r, b]] - per_block[b])
        np.testing.assert_array_equal(out[r].view(np.uint32), want.view(np.uint32), err_msg=f"row {r}")
