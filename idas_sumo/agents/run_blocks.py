"""The encoder's conv and first joint layer over only the blocks of cells the cars reach, for the learner.

The first joint layer reads 1,484 conv outputs a row, but a car reaches only the ~40 output cells its run
overlaps; everywhere else the conv output is ReLU(bias) exactly. Here the output cells are cut into blocks of
``BLOCK_CELLS``; a (row, block) pair that some piece of the row's runs reaches is *reached*. The reached pairs'
ReLU(conv) is stored block by block (all of block 0's rows, then block 1's, ...), so each block's share of the
first joint layer is one dense product (BLAS) over only its rows: forward, the input's and the weight's
gradients. An unreached pair's outputs are ReLU(bias), so its share is one vector per block, forward and
backward. On ``benchmarks/learner_update.py``'s rollout-like batch 8.6 of a row's 24 blocks are reached, and
one thread took 4.5 ms for the three products of 2,048 rows against 18 ms over every cell. The same function
as the conv and the dense layer; the sums run in another order, so floats differ in the last bits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from idas_sumo.agents.run_conv import RunPieces, add_piece, add_piece_grad, four_rows, piece_span
from idas_sumo.env.jit import kernel

__all__ = ["BLOCK_CELLS", "BlockedConvLayer", "ConvGeometry"]

Pieces = tuple[npt.NDArray[np.int64], npt.NDArray[np.float32], npt.NDArray[np.int64], npt.NDArray[np.int64]]
"""``RunPieces``' arrays as the kernels take them: table row, value, batch row, first cell."""

BLOCK_CELLS = 16
"""Output cells per block (16 cells · 4 outputs = 64 columns a product). Measured on a rollout-like batch of
2,048 rows, the three products took 4.5 ms with blocks of 16 cells against 6.3 ms with 32 and 18 ms dense."""


@dataclass(frozen=True)
class ConvGeometry:
    """The conv's output shape as the blocks need it."""

    cells: int
    """Output cells per output row (371)."""
    outs: int
    """Outputs per cell: filters · output rows (4)."""
    reach: int
    """Output cells one piece reaches (piece + kernel - 1)."""
    lead: int
    """How far before its first cell a piece's first output cell lies (kernel - 1)."""

    @property
    def blocks(self) -> int:
        """Blocks of ``BLOCK_CELLS`` output cells a row is cut into (the last one partial)."""
        return -(-self.cells // BLOCK_CELLS)


def _reached_pairs(
    grid_row: npt.NDArray[np.int64],
    start: npt.NDArray[np.int64],
    rows: int,
    cells: int,
    reach: int,
    lead: int,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """The reached (row, block) pairs, block-major: each pair's index by (row, block) (-1: not reached), each
    pair's row, and where each block's pairs start (blocks + 1)."""
    blocks = -(-cells // BLOCK_CELLS)
    at = np.full((rows, blocks), -1, dtype=np.int64)
    for p in range(grid_row.shape[0]):
        first = start[p] - lead
        lo, hi = piece_span(first, 1, reach, cells)
        for j in range((first + lo) // BLOCK_CELLS, (first + hi - 1) // BLOCK_CELLS + 1):
            at[grid_row[p], j] = 0
    offsets = np.zeros(blocks + 1, dtype=np.int64)
    for j in range(blocks):
        n = 0
        for b in range(rows):
            n += at[b, j] == 0
        offsets[j + 1] = offsets[j] + n
    pair_row = np.empty(offsets[blocks], dtype=np.int64)
    for j in range(blocks):
        k = offsets[j]
        for b in range(rows):
            if at[b, j] == 0:
                at[b, j] = k
                pair_row[k] = b
                k += 1
    return at, pair_row, offsets


def _forward_blocks(
    table: npt.NDArray[np.float32],
    bias: npt.NDArray[np.float32],
    pieces: Pieces,
    at: npt.NDArray[np.int64],
    cells: int,
    lead: int,
    offsets_last: int,
    out: npt.NDArray[np.float32],
) -> None:
    """ReLU(bias + Σ pieces) of every reached pair into its row of ``out`` (pairs, BLOCK_CELLS · outs; columns
    past the last cell zero in the last block's pairs, which start at ``offsets_last``). Row by row: a row's pieces summed into a buffer, then its reached blocks copied
    out with the bias and the ReLU (and the buffer zeroed there)."""
    table_row, value, grid_row, start = pieces
    outs = bias.shape[0]
    reach = table.shape[1] // outs
    width = cells * outs
    span = BLOCK_CELLS * outs
    summed = np.zeros(at.shape[1] * span, dtype=np.float32)
    tiled = np.empty(span, dtype=np.float32)  # the bias over a block's cells, so the copy-out vectorises
    for k in range(span):
        tiled[k] = bias[k % outs]
    zero = np.float32(0.0)
    j = 0
    for b in range(at.shape[0]):
        while j < table_row.shape[0] and grid_row[j] == b:
            add_piece(summed, table[table_row[j]], value[j], start[j] - lead, outs, reach, cells)
            j += 1
        for block in range(at.shape[1]):
            pair = at[b, block]
            if pair < 0:
                continue
            row, sums = out[pair], summed[block * span : (block + 1) * span]
            for k in range(span):  # (over slices: with the offset inside the index it did not vectorise)
                row[k] = max(sums[k] + tiled[k], zero)
                sums[k] = zero
    # Past the last cell (the last block's tail) the buffer stays zero: zero the outputs there.
    tail = width - (at.shape[1] - 1) * span
    for pair in range(offsets_last, out.shape[0]):
        for k in range(tail, span):
            out[pair, k] = zero


def _backward_blocks(
    grad: npt.NDArray[np.float32],
    out: npt.NDArray[np.float32],
    table_rows: int,
    pieces: Pieces,
    at: npt.NDArray[np.int64],
    cells: int,
    reach: int,
    lead: int,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float64]]:
    """The run table's gradient and the reached pairs' share of the bias gradient (per output, float64), given
    the reached pairs' output ``grad`` and ``out`` (ReLU's mask). Row by row: the row's reached blocks' gradient
    where the ReLU passes, into a buffer the row's pieces read (they reach only those blocks)."""
    table_row, value, grid_row, start = pieces
    span = out.shape[1]
    outs = span // BLOCK_CELLS
    live = np.zeros(at.shape[1] * span, dtype=np.float32)
    per_place = np.zeros(span)  # float64 sums over thousands of rows, per place in a block (vectorises)
    grad_table = np.zeros((table_rows, reach * outs))
    zero = np.float32(0.0)
    j = 0
    for b in range(at.shape[0]):
        for block in range(at.shape[1]):
            pair = at[b, block]
            if pair < 0:
                continue
            grad_row, out_row, row_live = grad[pair], out[pair], live[block * span : (block + 1) * span]
            for k in range(span):
                g = grad_row[k] if out_row[k] > zero else zero
                row_live[k] = g
                per_place[k] += g
        while j < table_row.shape[0] and grid_row[j] == b:
            add_piece_grad(grad_table[table_row[j]], live, value[j], start[j] - lead, outs, reach, cells)
            j += 1
    per_out = np.zeros(outs)
    for k in range(span):
        per_out[k % outs] += per_place[k]
    return grad_table.astype(np.float32), per_out


def _sum_pairs(
    shares: npt.NDArray[np.float32],
    per_block: npt.NDArray[np.float32],
    at: npt.NDArray[np.int64],
    out: npt.NDArray[np.float32],
) -> None:
    """Each row of ``out``: the unreached share of every block (Σ ``per_block``), then for each reached block in
    turn its pair's share less the unreached share it replaces. A row reads its own pairs (no scatter), four
    blocks a pass over the row (in turn, so the same floats as one a pass)."""
    hidden = out.shape[1]
    idle = np.zeros(hidden, dtype=np.float32)
    for block in range(per_block.shape[0]):
        for k in range(hidden):
            idle[k] += per_block[block, k]
    pairs, blocks = np.empty(at.shape[1], dtype=np.int64), np.empty(at.shape[1], dtype=np.int64)
    for b in range(at.shape[0]):
        n = 0
        for block in range(at.shape[1]):
            if at[b, block] >= 0:
                pairs[n], blocks[n] = at[b, block], block
                n += 1
        row = out[b]
        for k in range(hidden):
            row[k] = idle[k]
        i = 0
        while i + 4 <= n:
            s0, s1, s2, s3 = four_rows(shares, pairs, i)
            u0, u1, u2, u3 = four_rows(per_block, blocks, i)
            for k in range(hidden):
                row[k] = (((row[k] + (s0[k] - u0[k])) + (s1[k] - u1[k])) + (s2[k] - u2[k])) + (s3[k] - u3[k])
            i += 4
        for rest in range(i, n):
            share, unreached = shares[pairs[rest]], per_block[blocks[rest]]
            for k in range(hidden):
                row[k] += share[k] - unreached[k]


def _gather_rows(
    grad: npt.NDArray[np.float32], pair_row: npt.NDArray[np.int64], out: npt.NDArray[np.float32]
) -> None:
    """Row p of ``out``: row ``pair_row[p]`` of ``grad`` (torch's index_select ran at a tenth of this)."""
    for pair in range(pair_row.shape[0]):
        src, dst = grad[pair_row[pair]], out[pair]
        for k in range(dst.shape[0]):
            dst[k] = src[k]


_reached_pairs_kernel = kernel(_reached_pairs)
_forward_blocks_kernel = kernel(_forward_blocks)
_backward_blocks_kernel = kernel(_backward_blocks)
_sum_pairs_kernel = kernel(_sum_pairs)
_gather_rows_kernel = kernel(_gather_rows)


def _by_block(weight: torch.Tensor, geometry: ConvGeometry) -> torch.Tensor:
    """The (cells · outs, hidden) weight as (blocks, BLOCK_CELLS · outs, hidden), zero past the last cell."""
    pad = geometry.blocks * BLOCK_CELLS * geometry.outs - weight.shape[0]
    padded = torch.nn.functional.pad(weight, (0, 0, 0, pad))
    return padded.view(geometry.blocks, BLOCK_CELLS * geometry.outs, weight.shape[1])


class BlockedConvLayer(torch.autograd.Function):
    """Σ over the conv outputs k of ReLU(conv)_k · weight[k] (rows, hidden): the conv from the pieces of a
    batch's runs and the first joint layer's conv columns in one, over the reached blocks only.
    ``apply(table, bias, weight, pieces, rows, geometry)``; gradients reach ``table``, ``bias`` and ``weight``
    ((cells · outs, hidden), rows in (cell, output) order)."""

    @staticmethod
    def forward(
        ctx: Any,
        table: torch.Tensor,
        bias: torch.Tensor,
        weight: torch.Tensor,
        pieces: RunPieces,
        rows: int,
        geometry: ConvGeometry,
    ) -> torch.Tensor:
        arrays = (pieces.table_row, pieces.value, pieces.grid_row, pieces.start)
        at, pair_row, offsets = _reached_pairs_kernel(
            pieces.grid_row, pieces.start, rows, geometry.cells, geometry.reach, geometry.lead
        )
        reached = np.empty((len(pair_row), BLOCK_CELLS * geometry.outs), dtype=np.float32)
        _forward_blocks_kernel(
            np.ascontiguousarray(table.detach().numpy()),
            bias.detach().numpy(),
            arrays,
            at,
            geometry.cells,
            geometry.lead,
            int(offsets[-2]),
            reached,
        )
        x = torch.from_numpy(reached)
        w = _by_block(weight.detach(), geometry)
        idle = bias.detach().clamp(min=0.0).repeat(BLOCK_CELLS)  # an unreached block's outputs
        per_block = idle @ w  # (blocks, hidden): an unreached block's share
        shares = torch.empty(len(pair_row), weight.shape[1])
        for block in range(geometry.blocks):
            a, b = int(offsets[block]), int(offsets[block + 1])
            torch.mm(x[a:b], w[block], out=shares[a:b])
        result = torch.empty(rows, weight.shape[1])
        _sum_pairs_kernel(shares.numpy(), per_block.numpy(), at, result.numpy())
        ctx.arrays, ctx.table_rows, ctx.geometry = arrays, table.shape[0], geometry
        ctx.blocks = (at, pair_row, offsets)
        ctx.save_for_backward(x, w, idle, bias)
        return result

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        x, w, idle, bias = ctx.saved_tensors
        at, pair_row, offsets = ctx.blocks
        geometry: ConvGeometry = ctx.geometry
        grad = grad.contiguous()
        g = torch.empty(len(pair_row), grad.shape[1])
        _gather_rows_kernel(grad.numpy(), pair_row, g.numpy())
        total = grad.sum(0)
        grad_x = torch.empty_like(x)
        grad_w = torch.empty_like(w)
        # Each block's Σ of the gradient over its unreached rows.
        unreached = torch.empty(geometry.blocks, grad.shape[1])
        for block in range(geometry.blocks):
            a, b = int(offsets[block]), int(offsets[block + 1])
            torch.mm(g[a:b], w[block].t(), out=grad_x[a:b])
            torch.mm(x[a:b].t(), g[a:b], out=grad_w[block])
            unreached[block] = total - g[a:b].sum(0)
        grad_w.add_(idle.view(1, -1, 1) * unreached.unsqueeze(1))
        grad_table, per_out = _backward_blocks_kernel(
            grad_x.numpy(),
            x.numpy(),
            ctx.table_rows,
            ctx.arrays,
            at,
            geometry.cells,
            geometry.reach,
            geometry.lead,
        )
        # An unreached output is the bias exactly: its gradient passes where the bias is > 0.
        idle_grad = torch.einsum("jh,jkh->k", unreached, w).view(BLOCK_CELLS, geometry.outs).sum(0)
        grad_bias = torch.from_numpy(per_out).float() + idle_grad * (bias > 0)
        n_weight = geometry.cells * geometry.outs
        return (
            torch.from_numpy(grad_table),
            grad_bias,
            grad_w.view(-1, grad.shape[1])[:n_weight],
            None,
            None,
            None,
        )
