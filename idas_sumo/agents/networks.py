"""The actor, the decentralised critic V(o, b) and the centralised COMA critic Q(s, a, b).

Sizes follow the paper's Fig. 4 and Sec. V-B: a conv layer of 2 filters 3×30, stride 1, on the
grids; fc 32-32-32 on the scalars; fc 64-64-64 after the concatenation; ReLU everywhere. The
centralised critic is two FC layers of 128 units (Fig. 3).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn
from torch.distributions import Categorical

from idas_sumo.agents.coma import coma_advantage
from idas_sumo.agents.critic_input import OTHERS_ACTIONS_DIM
from idas_sumo.agents.run_blocks import BlockedConvLayer, ConvGeometry
from idas_sumo.agents.run_conv import RunConv, RunPieces, actor_logits
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.layout import GRID_CELLS, N_CHANNELS, N_LANES, N_SCALARS, OBS_DIM
from idas_sumo.env.state_layout import STATE_DIM, STATE_FEATURES, STATE_SLOTS

__all__ = [
    "BLOCKS_CHUNK_ROWS",
    "CENTRAL_INPUT_DIM",
    "MASKED_LOGIT",
    "STATE_DIM",
    "STATE_FEATURES",
    "STATE_SLOTS",
    "Actor",
    "CentralCritic",
    "CentralCriticBase",
    "GridEncoder",
    "ObsWindows",
    "ValueCritic",
]

CONV_FILTERS = 2
KERNEL_LANES = 3  # kernel height along the lane axis
KERNEL_CELLS = 30  # kernel width along the road: 30 cells = 15 m
LANE_PAD = 1  # one empty row above and below the two lanes so the 3-tall kernel fits
CONV_OUT_LANES = N_LANES + 2 * LANE_PAD - KERNEL_LANES + 1  # 2
CONV_OUT_CELLS = GRID_CELLS - KERNEL_CELLS + 1  # 371
CONV_FEATURES = CONV_FILTERS * CONV_OUT_LANES * CONV_OUT_CELLS  # 1484
SCALAR_HIDDEN = 32  # fc1..fc3
JOINT_HIDDEN = 64  # fc4..fc6
CENTRAL_HIDDEN = 128
CENTRAL_INPUT_DIM = STATE_DIM + OTHERS_ACTIONS_DIM + STATE_SLOTS  # 288

# Finite rather than -inf: a fully masked row then stays NaN-free, and 0·MASKED_LOGIT = 0 in the
# entropy. exp(-1e9) underflows to exactly 0, so a masked action has probability exactly 0.
MASKED_LOGIT = -1e9
ACTOR_HEAD_GAIN = 0.01  # near-uniform initial policy (CleanRL's choice for policy heads)


def _mlp(sizes: list[int]) -> nn.Sequential:
    """Linear layers with a ReLU after every one (the paper uses ReLU on all hidden layers)."""
    layers: list[nn.Module] = []
    for n_in, n_out in itertools.pairwise(sizes):
        layers += [nn.Linear(n_in, n_out), nn.ReLU()]
    return nn.Sequential(*layers)


# How the lane convolution is computed (ours: the maths is the paper's conv, only the arithmetic is
# arranged for speed). A grid row is mostly zeros, and each car is a run of about ten equal cells (its
# occupancy, its relative speed). A conv over a run of n cells of value v starting at cell s adds, at output
# cell p, v · Σ_k w[k] over the kernel taps k with s ≤ p + k < s + n: a box sum of the kernel, which
# depends only on n and on t = p - s + 29, the output's place in the 29 + n cells the run reaches. So the
# encoder finds the runs (``ObsWindows``), reads each run's contribution from a table of those box sums
# (one small GEMM of the kernel taps, built from the weights) and adds it at its place: a few hundred
# multiply-adds per car instead of the dense conv's ~1 million per observation, the same function.
# A run longer than RUN_PIECE cells is cut into pieces (the sum of their contributions is the run's).
# The result equals torch's conv2d to float rounding (tests/test_agents_networks.py), on every input, not
# only on runs: a lone cell is a run of one. The conv's output stays in (cell, filter·row) order: instead of
# permuting activations, the first joint layer's weight columns are permuted to match. The Conv2d and
# Linear modules stay the parameters' homes, so checkpoints keep their keys and layout.
RUN_PIECE = 16
_REACH = RUN_PIECE + KERNEL_CELLS - 1  # output cells one piece reaches: 45
_ROWS_IN = N_LANES * N_CHANNELS  # (lane, channel) rows, in the observation's own order
_ROWS_OUT = CONV_FILTERS * CONV_OUT_LANES  # (filter, output row)
_GEOMETRY = ConvGeometry(cells=CONV_OUT_CELLS, outs=_ROWS_OUT, reach=_REACH, lead=KERNEL_CELLS - 1)


def _box_taps() -> torch.Tensor:
    """(30, RUN_PIECE · 45) of 0/1: entry (k, (n - 1, t)) is 1 where kernel tap k meets a piece of n cells at
    output place t, i.e. 29 - t ≤ k < 29 - t + n."""
    k = torch.arange(KERNEL_CELLS).view(-1, 1, 1)
    n = torch.arange(1, RUN_PIECE + 1).view(1, -1, 1)
    first = KERNEL_CELLS - 1 - torch.arange(_REACH).view(1, 1, -1)
    return ((k >= first) & (k < first + n)).float().reshape(KERNEL_CELLS, RUN_PIECE * _REACH)


def _kernel_pairs(weight: torch.Tensor) -> torch.Tensor:
    """The conv weight (F, C, 3, 30) as the 1-D kernel (4 in rows, 4 out rows, 30) each (lane, channel) input
    row meets in each (filter, output row): weight[f, c, lane - r + 1]."""
    # Output row r is centred on padded row r + 1, where lane `lane` sits at padded row lane + 1: it
    # meets kernel row lane - r + 1 (the kernel's third row only ever meets the zero padding).
    return torch.stack(
        [
            torch.stack(
                [
                    weight[f, c, lane - r + LANE_PAD]
                    for f, r in itertools.product(range(CONV_FILTERS), range(CONV_OUT_LANES))
                ]
            )
            for lane, c in itertools.product(range(N_LANES), range(N_CHANNELS))
        ]
    )


def _run_table(weight: torch.Tensor, box_taps: torch.Tensor) -> torch.Tensor:
    """(RUN_PIECE · 4, 45 · 4): row (n - 1, in row) holds a unit piece of n cells' conv output at its 45
    places (t, out row). One GEMM and reshapes, so its gradient is deterministic (no scatter)."""
    sums = _kernel_pairs(weight).reshape(_ROWS_IN * _ROWS_OUT, KERNEL_CELLS) @ box_taps
    return (
        sums.reshape(_ROWS_IN, _ROWS_OUT, RUN_PIECE, _REACH)
        .permute(2, 0, 3, 1)
        .reshape(RUN_PIECE * _ROWS_IN, _REACH * _ROWS_OUT)
    )


def _feature_order() -> torch.Tensor:
    """For each conv feature in our order (cell, filter·row), its index in conv2d's flattened
    (filter, row, cell) order."""
    cell, out_row = torch.meshgrid(torch.arange(CONV_OUT_CELLS), torch.arange(_ROWS_OUT), indexing="ij")
    return (out_row * CONV_OUT_CELLS + cell).flatten()


@dataclass(frozen=True)
class _ConvOperands:
    run_table: torch.Tensor
    """``_run_table`` of the conv weight."""
    bias: torch.Tensor
    """The conv bias per (filter, output row)."""
    joint_conv_weight: torch.Tensor
    """The first joint layer's weight for the conv features, transposed, rows in (cell, filter·row) order."""


# A learner batch goes through the encoder in slices of this many rows (the same maths; the float rounding
# of a GEMM depends on its row count, and the weight gradient sums the slices in turn). A slice's conv output
# (2048 · 454 · 4 floats, 15 MB) stays in a common L3 cache, where a whole stage-2 batch of 16 episodes
# (about 9,800 rows) does not: in one piece the update ran at half the speed. Batches up to this size,
# every rollout's and evaluation's, go through in one piece.
ENCODER_CHUNK_ROWS = 2048
# The blocks path (the learner's) keeps about a third of that per row, so its slices are longer: a worker's group
# of 8 episodes (about 5,000 rows) goes in one piece. V's forward and backward on 5,070 rows took 44.9 ms
# against 47.9 in slices of 2,048 (medians of 14, interleaved).
BLOCKS_CHUNK_ROWS = 8192


@dataclass(frozen=True)
class _RunChunk:
    """Up to ``ENCODER_CHUNK_ROWS`` (``BLOCKS_CHUNK_ROWS``) observations and their grids' runs, cut into pieces."""

    obs: torch.Tensor
    """The rows (B, OBS_DIM); the scalars are read from here."""
    pieces: RunPieces
    """The pieces of its grids' runs (agents/run_conv.py)."""

    @classmethod
    def of(cls, obs: torch.Tensor) -> _RunChunk:
        # layout.py orders the grid lane-major, [cl occ, cl rel, ol occ, ol rel]: (lane, channel) rows.
        return cls(obs=obs, pieces=RunPieces.of(obs, N_SCALARS, _ROWS_IN, GRID_CELLS, RUN_PIECE))


class ObsWindows:
    """A batch of observations with its grids' runs found once, for every encoder that reads it.

    The learner runs the actor, V and (with one-step targets) V̂ on the same rows; finding the runs depends on
    the observations only, so the networks compute what they would from ``obs``, bit for bit. Batches above
    ``ENCODER_CHUNK_ROWS`` are cut in chunks of that many rows. ``blocks``: the encoders compute the conv and
    the first joint layer over only the blocks of cells the cars reach (agents/run_blocks.py), in chunks of
    ``BLOCKS_CHUNK_ROWS``; that pays on a learner's batch of thousands of rows, and acting's few dozen rows a
    call take the other path (the same function, floats differing in the last bits).
    """

    def __init__(self, obs: torch.Tensor, blocks: bool = False) -> None:
        if obs.ndim != 2 or obs.shape[-1] != OBS_DIM:
            raise ValueError(f"observation must have {OBS_DIM} features, got {tuple(obs.shape)}")
        self.obs = obs
        self.blocks = blocks
        size = BLOCKS_CHUNK_ROWS if blocks else ENCODER_CHUNK_ROWS
        parts = (obs,) if obs.shape[0] <= size else obs.split(size)
        self.chunks = tuple(_RunChunk.of(part) for part in parts)


class GridEncoder(nn.Module):
    """Observation (B, OBS_DIM) -> features (B, JOINT_HIDDEN).

    How a 3×30 kernel meets two 1-D grids (the paper does not say; this is our reading): the two
    lanes' grids form one image with 2 channels (occupancy, relative speed), 2 rows (obs_cl, obs_ol)
    and 400 columns. The row (lane) axis is zero-padded by one row on each side, giving 4 rows, so
    the 3-tall kernel sees both lanes plus one padding row: output row 0 is centred on obs_cl,
    row 1 on obs_ol. Two 3×30 filters, stride 1, give (2, 2, 371) = 1484 features, flattened.
    The 5 scalars go through fc 32-32-32; both parts are concatenated and go through fc 64-64-64.
    """

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(
            N_CHANNELS,
            CONV_FILTERS,
            kernel_size=(KERNEL_LANES, KERNEL_CELLS),
            stride=1,
            padding=(LANE_PAD, 0),
        )
        self.scalars = _mlp([N_SCALARS, SCALAR_HIDDEN, SCALAR_HIDDEN, SCALAR_HIDDEN])
        self.joint = _mlp([SCALAR_HIDDEN + CONV_FEATURES, JOINT_HIDDEN, JOINT_HIDDEN, JOINT_HIDDEN])
        self._feature_order: torch.Tensor
        self.register_buffer("_feature_order", _feature_order() + SCALAR_HIDDEN, persistent=False)
        self._box_taps: torch.Tensor
        self.register_buffer("_box_taps", _box_taps(), persistent=False)
        self._frozen: tuple[tuple[object, ...], _ConvOperands] | None = None

    def forward(self, obs: torch.Tensor | ObsWindows) -> torch.Tensor:
        """``obs`` (B, OBS_DIM), or the same rows with their runs already found (``ObsWindows``: the
        learner's networks share them)."""
        runs = obs if isinstance(obs, ObsWindows) else ObsWindows(obs)
        operands = self._operands()
        layer = self._joint_input_layer_by_blocks if runs.blocks else self._joint_input_layer
        if len(runs.chunks) == 1:
            first = layer(runs.chunks[0], operands)
        else:
            first = torch.cat([layer(chunk, operands) for chunk in runs.chunks])
        return self.joint[1:](first)

    def reference_forward(self, obs: torch.Tensor) -> torch.Tensor:
        """``forward`` written the plain way (conv2d, flatten, cat, Linear): the specification the fast
        path is tested and benchmarked against."""
        grid = obs[:, N_SCALARS:].reshape(-1, N_LANES, N_CHANNELS, GRID_CELLS).transpose(1, 2)
        conv = torch.relu(self.conv(grid)).flatten(1)
        out: torch.Tensor = self.joint(torch.cat([self.scalars(obs[:, :N_SCALARS]), conv], dim=1))
        return out

    def _operands(self) -> _ConvOperands:
        """The run table, the conv bias and the first joint layer's conv columns, built from the weights.

        With autograd off (a rollout or an evaluation acts thousands of times between two weight changes)
        they are built once and reused while the weights stay the same tensors at the same version:
        an optimizer step or ``load_state_dict`` changes them in place, which bumps the version.
        """
        first = self.joint[0]
        assert isinstance(first, nn.Linear) and self.conv.bias is not None  # built with a bias
        key: tuple[object, ...] = ()
        if not torch.is_grad_enabled():
            params = (self.conv.weight, self.conv.bias, first.weight)
            key = (torch.is_inference_mode_enabled(), *((p.data_ptr(), p._version) for p in params))
            if self._frozen is not None and self._frozen[0] == key:
                return self._frozen[1]
        operands = _ConvOperands(
            run_table=_run_table(self.conv.weight, self._box_taps),
            bias=self.conv.bias.repeat_interleave(CONV_OUT_LANES),  # (filter, row)
            joint_conv_weight=first.weight.index_select(1, self._feature_order).t(),
        )
        self._frozen = (key, operands) if key else None
        return operands

    @staticmethod
    def _conv(runs: _RunChunk, operands: _ConvOperands) -> torch.Tensor:
        """ReLU(conv) (B, CONV_FEATURES) in (cell, filter·row) order: each piece's outputs added at its places
        (agents/run_conv.py); a cell no run reaches is the bias alone, exactly."""
        b = runs.obs.shape[0]
        conv: torch.Tensor = RunConv.apply(
            operands.run_table, operands.bias, runs.pieces, b, CONV_OUT_CELLS, KERNEL_CELLS - 1
        )
        return conv.reshape(b, CONV_FEATURES)

    def _scalar_part(self, runs: _RunChunk) -> torch.Tensor:
        """The first joint layer's bias plus its product with the scalar features (its conv part comes next)."""
        first = self.joint[0]
        assert isinstance(first, nn.Linear)
        w_scalars = first.weight[:, :SCALAR_HIDDEN]
        return torch.addmm(first.bias, self.scalars(runs.obs[:, :N_SCALARS]), w_scalars.t())

    def _joint_input_layer(self, runs: _RunChunk, operands: _ConvOperands) -> torch.Tensor:
        """The first joint layer on cat(scalar features, conv features), without building the cat."""
        return self._scalar_part(runs).addmm_(self._conv(runs, operands), operands.joint_conv_weight)

    def _joint_input_layer_by_blocks(self, runs: _RunChunk, operands: _ConvOperands) -> torch.Tensor:
        """``_joint_input_layer`` with the conv and its columns over only the reached blocks of cells."""
        conv: torch.Tensor = BlockedConvLayer.apply(
            operands.run_table,
            operands.bias,
            operands.joint_conv_weight,
            runs.pieces,
            runs.obs.shape[0],
            _GEOMETRY,
        )
        return self._scalar_part(runs) + conv


# Ours: the initial policy's prior over actions. With uniform logits a fresh policy hard-brakes on one
# step in six and stalls (80 % timeouts in the robot world), and with γ = 0.9 at 5 Hz the finish reward is
# invisible from further than ~2 s away, so it never learns to stop. Starting from "rarely hard-brake,
# release right after one" lets early episodes reach the merge, where the rewards are.
INITIAL_ACTION_BIAS: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, -3.0, 3.0)


def _linears(seq: nn.Sequential) -> list[nn.Linear]:
    return [m for m in seq if isinstance(m, nn.Linear)]


@dataclass(frozen=True)
class _InferenceOperands:
    """An actor's weights as float32 numpy arrays for ``Actor.inference_logits`` (weights transposed)."""

    scalars: tuple[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]], ...]
    conv: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]]
    """The run table, the conv bias and the first joint layer's conv columns (``conv_joint``'s)."""
    joint_scalars: npt.NDArray[np.float32]
    joint_base: npt.NDArray[np.float32]
    """The first joint layer's bias plus what the conv outputs no run reaches (ReLU(bias)) add to it."""
    layers: tuple[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]], ...]
    """The later joint layers (ReLU after each) and the head (none)."""

    @classmethod
    def of(cls, actor: Actor) -> _InferenceOperands:
        encoder = actor.encoder

        def arr(t: torch.Tensor) -> npt.NDArray[np.float32]:
            return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32)

        def pairs(
            layers: list[nn.Linear],
        ) -> tuple[tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]], ...]:
            return tuple((arr(m.weight.t()), arr(m.bias)) for m in layers)

        with torch.no_grad():
            conv = encoder._operands()
            first, *later = _linears(encoder.joint)
            idle = conv.bias.clamp(min=0.0).repeat(CONV_OUT_CELLS) @ conv.joint_conv_weight
            return cls(
                scalars=pairs(_linears(encoder.scalars)),
                conv=(arr(conv.run_table), arr(conv.bias), arr(conv.joint_conv_weight)),
                joint_scalars=arr(first.weight[:, :SCALAR_HIDDEN].t()),
                joint_base=arr(first.bias + idle),
                layers=pairs([*later, actor.head]),
            )

    def kernel_args(self) -> tuple[Any, ...]:
        """``run_conv.actor_logits``'s arguments after the observations."""
        return (
            tuple(w for w, _ in self.scalars),
            tuple(b for _, b in self.scalars),
            self.conv,
            self.joint_scalars,
            self.joint_base,
            tuple(w for w, _ in self.layers),
            tuple(b for _, b in self.layers),
            (_ROWS_IN, GRID_CELLS, RUN_PIECE),
        )


class Actor(nn.Module):
    """π(a | o, b): GridEncoder then a linear head of N_ACTIONS logits, masked before the softmax."""

    def __init__(self) -> None:
        super().__init__()
        self.encoder = GridEncoder()
        self.head = nn.Linear(JOINT_HIDDEN, N_ACTIONS)
        nn.init.orthogonal_(self.head.weight, gain=ACTOR_HEAD_GAIN)
        with torch.no_grad():
            self.head.bias.copy_(torch.tensor(INITIAL_ACTION_BIAS))
        self._inference: tuple[tuple[object, ...], tuple[Any, ...]] | None = None
        self._params: list[nn.Parameter] | None = None

    def inference_logits(self, obs: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """Unmasked logits (B, N_ACTIONS) of ``forward``, without autograd, as one compiled loop per row
        (``run_conv.actor_logits``: a rollout step's few dozen rows cost torch's fixed cost per op dozens of
        times over). The same function; floats differ from ``forward``'s in the last bits (another summation
        order), and a row's logits do not depend on the other rows. The weights' operands are rebuilt when a
        weight changes (an optimiser step or ``load_state_dict`` bumps its version)."""
        # The module's own tensors: optimiser steps and load_state_dict write into them in place.
        if self._params is None:
            self._params = list(self.parameters())
        key = tuple((p.data_ptr(), p._version) for p in self._params)
        if self._inference is None or self._inference[0] != key:
            self._inference = (key, _InferenceOperands.of(self).kernel_args())
        x = np.ascontiguousarray(obs, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != OBS_DIM:
            raise ValueError(f"observation must have {OBS_DIM} features, got {x.shape}")
        out: npt.NDArray[np.float32] = actor_logits(x, *self._inference[1])
        return out

    def forward(self, obs: torch.Tensor | ObsWindows) -> torch.Tensor:
        """Unmasked logits (B, N_ACTIONS)."""
        out: torch.Tensor = self.head(self.encoder(obs))
        return out

    def masked_logits(self, obs: torch.Tensor | ObsWindows, mask: torch.Tensor) -> torch.Tensor:
        """Logits with disallowed actions (mask false/0) set to MASKED_LOGIT."""
        return self(obs).masked_fill(~mask.bool(), MASKED_LOGIT)

    def distribution(self, obs: torch.Tensor | ObsWindows, mask: torch.Tensor) -> Categorical:
        """The masked policy; masked actions get probability exactly 0."""
        return Categorical(logits=self.masked_logits(obs, mask))


class ValueCritic(nn.Module):
    """Decentralised critic V(o, b): the actor's structure with one output; gives ∇J1."""

    def __init__(self) -> None:
        super().__init__()
        self.encoder = GridEncoder()
        self.head = nn.Linear(JOINT_HIDDEN, 1)

    def forward(self, obs: torch.Tensor | ObsWindows) -> torch.Tensor:
        """Values (B,)."""
        out: torch.Tensor = self.head(self.encoder(obs)).squeeze(-1)
        return out


class CentralCriticBase(nn.Module):
    """What the learner asks of a centralised critic Q(s, (a⁻ⁿ, ·), b) (``agents/critics.py`` builds one by name):
    ``forward`` gives one Q-value per own action of agent n; ``loss`` (L(φ2)) and ``advantage`` (A2, COMA's
    by default) may be overridden by a critic that needs other ones."""

    def forward(self, state: torch.Tensor, others_actions: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
        """Q-values (B, N_ACTIONS); ``slot`` is (B,) int64 in [0, STATE_SLOTS)."""
        raise NotImplementedError

    def loss(
        self, q_all: torch.Tensor, action: torch.Tensor, target: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(0.5 · mean (target - Q(s, a))², Q(s, a)) for the actions taken, from ``forward``'s Q(s, ·)."""
        q_taken = q_all.gather(1, action.unsqueeze(1)).squeeze(1)
        return 0.5 * (target - q_taken).pow(2).mean(), q_taken

    def advantage(self, q_all: torch.Tensor, probs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """A2 (B,) from Q(s, ·) (detached) and the masked policy π(·|o): COMA's Q(s, a) - Σ_a' π(a'|o) Q(s, a')."""
        return coma_advantage(q_all, probs, action)


class CentralCritic(CentralCriticBase):
    """Centralised COMA critic Q(s, (a⁻ⁿ, ·), b): one Q-value per own action of agent n.

    Input: the global state (STATE_DIM, carries every vehicle's b_prio and b_type), the other
    agents' actions one-hot (OTHERS_ACTIONS_DIM, own slot zeroed) and agent n's slot one-hot
    (STATE_SLOTS), vehicles in the scenario's slot order. Two FC layers of 128 with ReLU, then
    N_ACTIONS outputs, so the counterfactual baseline needs one forward pass (COMA's critic head).
    """

    def __init__(self) -> None:
        super().__init__()
        self.body = _mlp([CENTRAL_INPUT_DIM, CENTRAL_HIDDEN, CENTRAL_HIDDEN])
        self.head = nn.Linear(CENTRAL_HIDDEN, N_ACTIONS)

    def forward(self, state: torch.Tensor, others_actions: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
        """Q-values (B, N_ACTIONS); ``slot`` is (B,) int64 in [0, STATE_SLOTS)."""
        slot_onehot = nn.functional.one_hot(slot.long(), STATE_SLOTS).to(state.dtype)
        out: torch.Tensor = self.head(self.body(torch.cat([state, others_actions, slot_onehot], dim=1)))
        return out
