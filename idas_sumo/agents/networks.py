"""The actor, the decentralised critic V(o, b) and the centralised COMA critic Q(s, a, b).

Sizes follow the paper's Fig. 4 and Sec. V-B: a conv layer of 2 filters 3×30, stride 1, on the
grids; fc 32-32-32 on the scalars; fc 64-64-64 after the concatenation; ReLU everywhere. The
centralised critic is two FC layers of 128 units (Fig. 3).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import nn
from torch.distributions import Categorical

from idas_sumo.agents.coma import coma_advantage
from idas_sumo.agents.critic_input import OTHERS_ACTIONS_DIM
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.layout import GRID_CELLS, N_CHANNELS, N_LANES, N_SCALARS, OBS_DIM
from idas_sumo.env.state_layout import STATE_DIM, STATE_FEATURES, STATE_SLOTS

__all__ = [
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
# arranged for speed). A conv with a 3×30 kernel on 2 lanes padded to 4 rows is, per output row, a 1-D
# correlation over the 4 (lane, channel) input rows; over a block of BLOCK_CELLS output cells that
# correlation is one dense (Toeplitz) matrix built from the kernel. 371 = 7 × 53 output cells, so 7
# blocks read the 400 cells exactly, and the conv is one GEMM (B·7, 4·82) @ (4·82, 4·53) with the bias
# fused. Its output stays in (block, filter·row, cell) order: instead of permuting activations, the
# first joint layer's weight columns are permuted to match. Faster than torch's conv2d
# (benchmarks/learner_update.py); the result is the same to float rounding (tests/test_agents_networks.py).
# The Conv2d and Linear modules stay the parameters' homes, so checkpoints keep their keys and layout.
BLOCK_CELLS = 53
# A learner batch goes through the encoder in slices of this many rows (the same maths; the float rounding
# of a GEMM depends on its row count, and the weight gradient sums the slices in turn). A slice's windows
# (2048 · 7 · 328 floats, 19 MB) fit a common L3 cache, where a whole stage-2 batch of 16 episodes (about
# 9,600 rows, 88 MB of windows) does not. Batches up to this size, every rollout's and evaluation's, go
# through in one piece.
ENCODER_CHUNK_ROWS = 2048
_BLOCKS = CONV_OUT_CELLS // BLOCK_CELLS  # 7
assert _BLOCKS * BLOCK_CELLS == CONV_OUT_CELLS, "blocks must tile the conv output exactly"
_BLOCK_IN = BLOCK_CELLS + KERNEL_CELLS - 1  # 82 input cells per block; the 7 blocks end at cell 400
_ROWS_IN = N_LANES * N_CHANNELS  # (lane, channel) rows, in the observation's own order
_ROWS_OUT = CONV_FILTERS * CONV_OUT_LANES  # (filter, output row)


def _toeplitz(weight: torch.Tensor) -> torch.Tensor:
    """The block matrix (4·82, 4·53) of the conv weight (F, C, 3, 30): entry ((lane, c, j), (f, r, p)) is
    weight[f, c, lane - r + 1, j - p] where 0 ≤ j - p < 30, else 0.

    Built from slices, flips, a pad and an unfold only, so its gradient is a deterministic sum (a
    gather by index would scatter-add the gradient, and torch does that in a nondeterministic order).
    """
    # Output row r is centred on padded row r + 1, where lane `lane` sits at padded row lane + 1: it
    # meets kernel row lane - r + 1 (the kernel's third row only ever meets the zero padding).
    per_pair = torch.stack(
        [
            torch.stack(
                [
                    weight[f, c, lane - r + LANE_PAD]
                    for f, r in itertools.product(range(CONV_FILTERS), range(CONV_OUT_LANES))
                ]
            )
            for lane, c in itertools.product(range(N_LANES), range(N_CHANNELS))
        ]
    )  # (in row (lane, c), out row (f, r), k)
    # T[j, p] = w[j - p] = u[j + p'] with p' = 52 - p and u = w padded by 52 zeros on the left and
    # right: an unfold of u, then flip p' back to p.
    padded = nn.functional.pad(per_pair, (BLOCK_CELLS - 1, BLOCK_CELLS - 1))
    bands = padded.unfold(2, BLOCK_CELLS, 1)[:, :, :_BLOCK_IN].flip(3)  # (in, out, j, p)
    return bands.permute(0, 2, 1, 3).reshape(_ROWS_IN * _BLOCK_IN, _ROWS_OUT * BLOCK_CELLS)


def _feature_order() -> torch.Tensor:
    """For each conv feature in block order (block, filter, row, cell), its index in conv2d's
    flattened (filter, row, cell) order."""
    block, out_row, cell = torch.meshgrid(
        torch.arange(_BLOCKS), torch.arange(_ROWS_OUT), torch.arange(BLOCK_CELLS), indexing="ij"
    )
    return (out_row * CONV_OUT_CELLS + block * BLOCK_CELLS + cell).flatten()


@dataclass(frozen=True)
class _ConvOperands:
    toeplitz: torch.Tensor
    """(4·82, 4·53): ``_toeplitz`` of the conv weight."""
    bias: torch.Tensor
    """The conv bias per output column of one block."""
    joint_conv_weight: torch.Tensor
    """The first joint layer's weight for the conv features, transposed, rows in block order."""


@dataclass(frozen=True)
class _WindowChunk:
    """Up to ``ENCODER_CHUNK_ROWS`` observations and the conv's input windows of their grids."""

    obs: torch.Tensor
    """The rows (B, OBS_DIM); the scalars are read from here."""
    windows: torch.Tensor
    """The occupied windows (n, 4·82), in (row, block) order; every window when ``occupied`` is None."""
    occupied: torch.Tensor | None
    """Where ``windows`` sit among the B·7 windows; None when every window is occupied."""

    @classmethod
    def of(cls, obs: torch.Tensor) -> _WindowChunk:
        b = obs.shape[0]
        # layout.py orders the grid lane-major, [cl occ, cl rel, ol occ, ol rel]: (lane, channel) rows.
        rows = obs[:, N_SCALARS:].reshape(b, _ROWS_IN, GRID_CELLS)
        windows = (
            rows.unfold(2, _BLOCK_IN, BLOCK_CELLS).transpose(1, 2).reshape(b * _BLOCKS, _ROWS_IN * _BLOCK_IN)
        )
        # Most windows of a grid are empty road (in the intelligent world about 40 %): their conv output is
        # the bias alone, exactly, so only the others go through the GEMM. Empty rows add nothing to the
        # weight gradient either; the bias still receives every row's gradient.
        occupied = torch.nonzero(windows.ne(0).any(dim=1)).squeeze(1)
        if occupied.numel() == b * _BLOCKS:
            return cls(obs=obs, windows=windows, occupied=None)
        return cls(obs=obs, windows=windows.index_select(0, occupied), occupied=occupied)


class ObsWindows:
    """A batch of observations cut into the conv's windows once, for every encoder that reads it.

    The learner runs the actor, V and (with one-step targets) V̂ on the same rows; cutting a batch (a copy of
    its grids, the occupancy test and the gather of the occupied windows) is a noticeable share of each
    encoder pass. The cut depends on the observations only, so the networks compute what they would from ``obs``,
    bit for bit. Batches above ``ENCODER_CHUNK_ROWS`` are cut in chunks of that many rows.
    """

    def __init__(self, obs: torch.Tensor) -> None:
        if obs.ndim != 2 or obs.shape[-1] != OBS_DIM:
            raise ValueError(f"observation must have {OBS_DIM} features, got {tuple(obs.shape)}")
        self.obs = obs
        parts = (obs,) if obs.shape[0] <= ENCODER_CHUNK_ROWS else obs.split(ENCODER_CHUNK_ROWS)
        self.chunks = tuple(_WindowChunk.of(part) for part in parts)


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
        self._frozen: tuple[tuple[object, ...], _ConvOperands] | None = None

    def forward(self, obs: torch.Tensor | ObsWindows) -> torch.Tensor:
        """``obs`` (B, OBS_DIM), or the same rows already cut into windows (``ObsWindows``: the learner's
        networks share one cut)."""
        windows = obs if isinstance(obs, ObsWindows) else ObsWindows(obs)
        operands = self._operands()
        if len(windows.chunks) == 1:
            first = self._joint_input_layer(windows.chunks[0], operands)
        else:
            first = torch.cat([self._joint_input_layer(chunk, operands) for chunk in windows.chunks])
        return self.joint[1:](first)

    def reference_forward(self, obs: torch.Tensor) -> torch.Tensor:
        """``forward`` written the plain way (conv2d, flatten, cat, Linear): the specification the fast
        path is tested and benchmarked against."""
        grid = obs[:, N_SCALARS:].reshape(-1, N_LANES, N_CHANNELS, GRID_CELLS).transpose(1, 2)
        conv = torch.relu(self.conv(grid)).flatten(1)
        out: torch.Tensor = self.joint(torch.cat([self.scalars(obs[:, :N_SCALARS]), conv], dim=1))
        return out

    def _operands(self) -> _ConvOperands:
        """The Toeplitz matrix, its bias and the first joint layer's conv columns, built from the weights.

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
            toeplitz=_toeplitz(self.conv.weight),
            bias=self.conv.bias.repeat_interleave(CONV_OUT_LANES * BLOCK_CELLS),  # (filter, row, cell)
            joint_conv_weight=first.weight.index_select(1, self._feature_order).t(),
        )
        self._frozen = (key, operands) if key else None
        return operands

    @staticmethod
    def _conv_blocks(chunk: _WindowChunk, operands: _ConvOperands) -> torch.Tensor:
        """ReLU(conv) (B, CONV_FEATURES) in block order (block, filter, row, cell)."""
        b = chunk.obs.shape[0]
        conv = torch.relu(torch.addmm(operands.bias, chunk.windows, operands.toeplitz))
        if chunk.occupied is not None:
            # An empty window's output is ReLU(bias) exactly. The ReLU runs on the occupied rows and the bias
            # only (its backward too), which gives the bits of one ReLU over every row: the gradient reaching
            # the bias from the empty rows is the same column sums, masked once instead of per row.
            empty = torch.relu(operands.bias).expand(b * _BLOCKS, -1)
            conv = empty.index_copy(0, chunk.occupied, conv)
        return conv.reshape(b, CONV_FEATURES)

    def _joint_input_layer(self, chunk: _WindowChunk, operands: _ConvOperands) -> torch.Tensor:
        """The first joint layer on cat(scalar features, conv features), without building the cat."""
        first = self.joint[0]
        assert isinstance(first, nn.Linear)
        w_scalars = first.weight[:, :SCALAR_HIDDEN]
        out = torch.addmm(first.bias, self.scalars(chunk.obs[:, :N_SCALARS]), w_scalars.t())
        return out.addmm_(self._conv_blocks(chunk, operands), operands.joint_conv_weight)


# Ours: the initial policy's prior over actions. With uniform logits a fresh policy hard-brakes on one
# step in six and stalls (80 % timeouts in the robot world), and with γ = 0.9 at 5 Hz the finish reward is
# invisible from further than ~2 s away, so it never learns to stop. Starting from "rarely hard-brake,
# release right after one" lets early episodes reach the merge, where the rewards are.
INITIAL_ACTION_BIAS: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, -3.0, 3.0)


class Actor(nn.Module):
    """π(a | o, b): GridEncoder then a linear head of N_ACTIONS logits, masked before the softmax."""

    def __init__(self) -> None:
        super().__init__()
        self.encoder = GridEncoder()
        self.head = nn.Linear(JOINT_HIDDEN, N_ACTIONS)
        nn.init.orthogonal_(self.head.weight, gain=ACTOR_HEAD_GAIN)
        with torch.no_grad():
            self.head.bias.copy_(torch.tensor(INITIAL_ACTION_BIAS))

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
