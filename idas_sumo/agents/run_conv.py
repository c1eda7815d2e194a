"""The encoder's lane convolution from the grids' runs, forward and backward, as compiled loops.

``networks.GridEncoder`` finds the runs of equal cells in a batch's grids and builds, from the conv weight, the
table of a unit run's outputs (``networks._run_table``); this module adds each run's outputs at its places,
adds the bias and applies the ReLU (``RunConv``), and gives the gradients of the table and the bias. A loop
over a few pieces per grid row touches only the outputs a car reaches, in one pass with the bias and the
ReLU, where torch's ops (gather, scale, scatter-add, slice, add, ReLU: each a pass over the whole output, and
as many again backward) were slower than the dense conv they replace. The loops run in a fixed order, so the
results do not vary from run to run.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import torch

from idas_sumo.env.jit import kernel

__all__ = ["RunConv", "RunPieces", "actor_logits", "add_piece", "add_piece_grad", "four_rows", "piece_span"]

PIECES_PER_ROW_GUESS = 16
"""Room for this many pieces per observation on ``RunPieces.of``'s first scan (real ones hold about 5.5)."""


_SKIP_BLOCK = 32
"""Cells the scans for runs test at once for being all empty (a grid row is ~97 % zeros)."""
_MAGNITUDE = np.uint32(0x7FFFFFFF)
"""A float32's bits but the sign: zero exactly for 0.0 and -0.0, which ``v == 0.0`` takes as empty too."""


def _next_nonzero(bits: npt.NDArray[np.uint32], c: int, end: int) -> int:
    """The first index in [c, end) of a non-zero float32 (its ``bits``), or ``end``. A block of cells is tested at
    once with an OR of their bits, which vectorises (a float compare per cell does not); read through a slice of
    the block (indexed from ``c`` inside the loop, numba's loop did not vectorise: 3x slower)."""
    while c + _SKIP_BLOCK <= end:
        block = bits[c : c + _SKIP_BLOCK]
        acc = np.uint32(0)
        for q in range(_SKIP_BLOCK):
            acc |= block[q]
        if acc & _MAGNITUDE:
            break
        c += _SKIP_BLOCK
    while c < end and (bits[c] & _MAGNITUDE) == 0:
        c += 1
    return c


_next_nonzero_kernel = kernel(_next_nonzero)


def _run_end(values: npt.NDArray[np.float32], base: int, c: int, cells: int) -> int:
    """The end (exclusive, counted from ``base``) of the run of cells equal to cell ``c`` of the grid row that
    starts at ``values[base]`` and holds ``cells`` cells."""
    v = values[base + c]
    e = c + 1
    while e < cells and values[base + e] == v:
        e += 1
    return e


_run_end_kernel = kernel(_run_end)


def _runs(
    obs: npt.NDArray[np.float32], first: int, rows_in: int, cells: int, piece: int, capacity: int
) -> tuple[
    npt.NDArray[np.int64], npt.NDArray[np.float32], npt.NDArray[np.int64], npt.NDArray[np.int64], bool
]:
    """The pieces of the runs of equal non-zero cells in the grids of ``obs`` (B rows; from column ``first``,
    ``rows_in`` grid rows of ``cells`` cells each), read in place: each run cut into pieces of at most ``piece``
    cells. Per piece: its table row ((length - 1) · rows_in + input row), its value, its batch row and its
    first cell; and whether they all fitted in ``capacity`` (else the caller asks again with more)."""
    table_row = np.empty(capacity, dtype=np.int64)
    value = np.empty(capacity, dtype=np.float32)
    grid_row = np.empty(capacity, dtype=np.int64)
    start = np.empty(capacity, dtype=np.int64)
    j = 0
    bits = obs.view(np.uint32)
    for b in range(obs.shape[0]):
        row, row_bits = obs[b], bits[b]
        for i in range(rows_in):
            base = first + i * cells
            c = _next_nonzero_kernel(row_bits, base, base + cells) - base
            while c < cells:
                v = row[base + c]
                e = _run_end_kernel(row, base, c, cells)
                for s in range(c, e, piece):
                    if j == capacity:
                        return table_row[:j], value[:j], grid_row[:j], start[:j], False
                    table_row[j] = (min(piece, e - s) - 1) * rows_in + i
                    value[j], grid_row[j], start[j] = v, b, s
                    j += 1
                c = _next_nonzero_kernel(row_bits, base + e, base + cells) - base
    return table_row[:j], value[:j], grid_row[:j], start[:j], True


def _piece_span(first: int, outs: int, reach: int, cells: int) -> tuple[int, int]:
    """The columns [lo, hi) of a piece's table row that land inside its grid row, the piece's first output cell
    being ``first`` (negative: before the row starts); with ``outs`` 1, its output cells there, from ``first``."""
    return max(0, -first) * outs, min(reach, cells - first) * outs


piece_span = kernel(_piece_span)


def _add_piece(
    summed: npt.NDArray[np.float32],
    table_row: npt.NDArray[np.float32],
    v: float,
    first: int,
    outs: int,
    reach: int,
    cells: int,
) -> None:
    """Add ``v`` times a piece's table row into a grid row's sums at output cell ``first``. Over slices: written
    with the offsets inside the index, numba's loop did not vectorise (8x slower)."""
    lo, hi = piece_span(first, outs, reach, cells)
    dst, src = summed[first * outs + lo : first * outs + hi], table_row[lo:hi]
    for k in range(hi - lo):
        dst[k] += v * src[k]


def _add_piece_grad(
    grad_row: npt.NDArray[np.float64],
    live: npt.NDArray[np.float32],
    v: float,
    first: int,
    outs: int,
    reach: int,
    cells: int,
) -> None:
    """``_add_piece``'s gradient: ``v`` times the row's live gradient where the piece reaches, into its table
    row's gradient."""
    lo, hi = piece_span(first, outs, reach, cells)
    dst, src = grad_row[lo:hi], live[first * outs + lo : first * outs + hi]
    for k in range(hi - lo):
        dst[k] += v * src[k]


add_piece = kernel(_add_piece)
add_piece_grad = kernel(_add_piece_grad)


def _forward(
    table: npt.NDArray[np.float32],
    bias: npt.NDArray[np.float32],
    table_row: npt.NDArray[np.int64],
    value: npt.NDArray[np.float32],
    grid_row: npt.NDArray[np.int64],
    start: npt.NDArray[np.int64],
    rows: int,
    cells: int,
    lead: int,
) -> npt.NDArray[np.float32]:
    """ReLU(bias + Σ pieces) (rows, cells, outs): piece j adds value[j] · table[table_row[j], (t, o)] at cell
    start[j] - lead + t of its grid row. Row by row (the pieces come in row order): a row's sums in a small
    buffer, then bias and ReLU in one contiguous pass (the bias tiled over the cells, so the pass vectorises)."""
    outs = bias.shape[0]
    reach = table.shape[1] // outs
    width = cells * outs
    tiled = np.empty(width, dtype=np.float32)
    for k in range(width):
        tiled[k] = bias[k % outs]
    summed = np.zeros(width, dtype=np.float32)
    out = np.empty(rows * width, dtype=np.float32)
    zero = np.float32(0.0)
    j = 0
    for b in range(rows):
        while j < table_row.shape[0] and grid_row[j] == b:
            add_piece(summed, table[table_row[j]], value[j], start[j] - lead, outs, reach, cells)
            j += 1
        row = out[b * width : (b + 1) * width]  # (over a slice, as numba vectorises it)
        for k in range(width):
            row[k] = max(summed[k] + tiled[k], zero)
            summed[k] = zero
    return out.reshape(rows, cells, outs)


def _backward(
    grad: npt.NDArray[np.float32],
    out: npt.NDArray[np.float32],
    table_rows: int,
    table_row: npt.NDArray[np.int64],
    value: npt.NDArray[np.float32],
    grid_row: npt.NDArray[np.int64],
    start: npt.NDArray[np.int64],
    reach: int,
    lead: int,
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """The gradients of the table and the bias, given the output's ``grad`` and the output (ReLU's mask). Row
    by row: the row's gradient where its ReLU passes into a small buffer (one contiguous pass), summed per
    output place for the bias and read by the row's pieces for the table."""
    rows, cells, outs = out.shape
    width = cells * outs
    flat_grad, flat_out = grad.reshape(-1), out.reshape(-1)
    live = np.empty(width, dtype=np.float32)
    per_place = np.zeros(width)  # float64 sums: thousands of rows
    grad_table = np.zeros((table_rows, reach * outs))
    zero = np.float32(0.0)
    j = 0
    for b in range(rows):
        row_grad, row_out = flat_grad[b * width : (b + 1) * width], flat_out[b * width : (b + 1) * width]
        for k in range(width):
            g = row_grad[k] if row_out[k] > zero else zero
            live[k] = g
            per_place[k] += g
        while j < table_row.shape[0] and grid_row[j] == b:
            add_piece_grad(grad_table[table_row[j]], live, value[j], start[j] - lead, outs, reach, cells)
            j += 1
    grad_bias = np.zeros(outs)
    for k in range(width):
        grad_bias[k % outs] += per_place[k]
    return grad_table.astype(np.float32), grad_bias.astype(np.float32)


def _dense(
    x: npt.NDArray[np.float32],
    w_t: npt.NDArray[np.float32],
    b: npt.NDArray[np.float32],
    relu: bool,
    out: npt.NDArray[np.float32],
) -> None:
    """``out`` = x · w_t + b (w_t: the weight transposed, (in, out)), then ReLU if ``relu``; one row, float32,
    into a buffer the caller reuses. Each output sums its terms in input order; the loop over the outputs is
    the inner one, so it vectorises, and it adds four inputs' terms a pass (in order, so the same floats as one
    a pass), which reads and writes ``out`` a quarter as often."""
    n_in = w_t.shape[0]
    for j in range(out.shape[0]):
        out[j] = b[j]
    i = 0
    while i + 4 <= n_in:
        x0, x1, x2, x3 = x[i], x[i + 1], x[i + 2], x[i + 3]
        w0, w1, w2, w3 = w_t[i], w_t[i + 1], w_t[i + 2], w_t[i + 3]
        for j in range(out.shape[0]):
            out[j] = (((out[j] + x0 * w0[j]) + x1 * w1[j]) + x2 * w2[j]) + x3 * w3[j]
        i += 4
    for rest in range(i, n_in):
        xi, w_row = x[rest], w_t[rest]
        for j in range(out.shape[0]):
            out[j] += xi * w_row[j]
    if relu:
        for j in range(out.shape[0]):
            out[j] = max(out[j], np.float32(0.0))


_dense_kernel = kernel(_dense)


def _conv_row_terms(
    grids: npt.NDArray[np.float32],
    grid_bits: npt.NDArray[np.uint32],
    table: npt.NDArray[np.float32],
    bias: npt.NDArray[np.float32],
    shape: tuple[int, int, int],
    conv: npt.NDArray[np.float32],
    reached: npt.NDArray[np.bool_],
    terms: tuple[npt.NDArray[np.int32], npt.NDArray[np.int32], npt.NDArray[np.float32]],
    row: int,
    count: int,
) -> int:
    """Append to ``terms`` (conv output, batch row, factor) one row's non-zero (ReLU(conv)_k - ReLU(bias)), conv
    output k ascending, from the runs of its ``grids`` (rows_in · cells_in cells; ``grid_bits``: the same as
    uint32); returns the new count. ``conv`` and ``reached``: zeroed scratch, left zeroed."""
    rows_in, cells_in, piece = shape[0], shape[1], shape[2]
    lead = table.shape[1] // bias.shape[0] - piece
    outs = bias.shape[0]
    cells_out = reached.shape[0]
    reach = table.shape[1] // outs
    zero = np.float32(0.0)
    for i in range(rows_in):
        base = i * cells_in
        c = _next_nonzero_kernel(grid_bits, base, base + cells_in) - base
        while c < cells_in:
            v = grids[base + c]
            e = _run_end_kernel(grids, base, c, cells_in)
            for start in range(c, e, piece):
                first = start - lead
                lo, hi = piece_span(first, 1, reach, cells_out)
                for t in range(lo, hi):
                    reached[first + t] = True
                add_piece(
                    conv, table[(min(piece, e - start) - 1) * rows_in + i], v, first, outs, reach, cells_out
                )
            c = _next_nonzero_kernel(grid_bits, base + e, base + cells_in) - base
    output, batch_row, factor = terms
    for p in range(cells_out):
        if not reached[p]:
            continue
        reached[p] = False
        for o in range(outs):
            k = p * outs + o
            d = max(conv[k] + bias[o], zero) - max(bias[o], zero)
            conv[k] = zero
            if d != zero:
                output[count], batch_row[count], factor[count] = k, row, d
                count += 1
    return count


_conv_row_terms_kernel = kernel(_conv_row_terms)


def _four_rows(
    table: npt.NDArray[np.float32], index: npt.NDArray[Any], at: int
) -> tuple[npt.NDArray[np.float32], ...]:
    """Rows ``index[at]`` to ``index[at + 3]`` of ``table`` (the terms a pass of the loops below adds)."""
    return table[index[at]], table[index[at + 1]], table[index[at + 2]], table[index[at + 3]]


four_rows = kernel(_four_rows)


def _add_terms(
    terms: tuple[npt.NDArray[np.int32], npt.NDArray[np.int32], npt.NDArray[np.float32]],
    count: int,
    joint_conv: npt.NDArray[np.float32],
    h: npt.NDArray[np.float32],
) -> None:
    """h[row] += factor · joint_conv[k] for every term; the terms come row by row, each row's in ascending k, and
    are added in that order (the same floats as one term at a time), eight terms a pass over the row: its
    hidden units are read and written an eighth as often."""
    output, batch_row, factor = terms
    t = 0
    while t < count:
        end = t
        while end < count and batch_row[end] == batch_row[t]:
            end += 1
        h_row = h[batch_row[t]]
        while t + 8 <= end:
            w0, w1, w2, w3 = four_rows(joint_conv, output, t)
            w4, w5, w6, w7 = four_rows(joint_conv, output, t + 4)
            d0, d1, d2, d3, d4, d5, d6, d7 = (
                factor[t],
                factor[t + 1],
                factor[t + 2],
                factor[t + 3],
                factor[t + 4],
                factor[t + 5],
                factor[t + 6],
                factor[t + 7],
            )
            for j in range(h_row.shape[0]):
                first = (((h_row[j] + d0 * w0[j]) + d1 * w1[j]) + d2 * w2[j]) + d3 * w3[j]
                h_row[j] = (((first + d4 * w4[j]) + d5 * w5[j]) + d6 * w6[j]) + d7 * w7[j]
            t += 8
        for rest in range(t, end):
            w_row, d = joint_conv[output[rest]], factor[rest]
            for j in range(h_row.shape[0]):
                h_row[j] += d * w_row[j]
        t = end


_add_terms_kernel = kernel(_add_terms)


def _actor_logits(
    obs: npt.NDArray[np.float32],
    scalar_weights: tuple[npt.NDArray[np.float32], ...],
    scalar_biases: tuple[npt.NDArray[np.float32], ...],
    conv_operands: tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.float32]],
    joint_scalars: npt.NDArray[np.float32],
    joint_base: npt.NDArray[np.float32],
    joint_weights: tuple[npt.NDArray[np.float32], ...],
    joint_biases: tuple[npt.NDArray[np.float32], ...],
    shape: tuple[int, int, int],
) -> npt.NDArray[np.float32]:
    """The actor's logits (B, actions) for inference, each row's arithmetic its own (so a row's logits do not
    depend on the others): the scalar MLP, the conv from the grids' runs fused with the first joint layer, the
    later joint layers and the head. ``*_weights``: each layer's weight transposed (in, out); ReLU after every
    layer but the head. ``conv_operands``: the run table, the conv bias and the first joint layer's conv
    columns ((cell, filter·row), hidden).

    A conv output that no run reaches is ReLU(bias) exactly, so its share of the first joint layer is one
    constant for every row, folded into ``joint_base`` with that layer's bias; a row adds only the difference
    at the cells its runs reach (a car reaches ~40 of 371) instead of the product over all 1,484 conv outputs.
    Those additions run row by row, several terms a pass (``_add_terms``).
    ``shape``: (grid rows, cells per grid row, run piece); the scalars come first in a row."""
    table, bias, joint_conv = conv_operands
    n_scalars = scalar_weights[0].shape[0]
    rows = obs.shape[0]
    logits = np.empty((rows, joint_biases[-1].shape[0]), dtype=np.float32)
    conv = np.zeros(joint_conv.shape[0], dtype=np.float32)
    reached = np.zeros(joint_conv.shape[0] // bias.shape[0], dtype=np.bool_)
    bits = obs.view(np.uint32)
    # Two buffers the layers write in turn (each reads the other), and the first joint layer's rows.
    width = joint_base.shape[0]
    for w in scalar_weights + joint_weights:
        width = max(width, w.shape[1])
    ping, pong = np.empty(width, dtype=np.float32), np.empty(width, dtype=np.float32)
    h = np.empty((rows, joint_base.shape[0]), dtype=np.float32)
    capacity = rows * joint_conv.shape[0]
    terms = (
        np.empty(capacity, dtype=np.int32),
        np.empty(capacity, dtype=np.int32),
        np.empty(capacity, dtype=np.float32),
    )
    count = 0
    for b in range(rows):
        x, n = obs[b, :n_scalars], n_scalars
        for layer in range(len(scalar_weights)):
            y = ping if layer % 2 == 0 else pong
            m = scalar_weights[layer].shape[1]
            _dense_kernel(x[:n], scalar_weights[layer], scalar_biases[layer], True, y[:m])
            x, n = y, m
        _dense_kernel(x[:n], joint_scalars, joint_base, False, h[b])
        count = _conv_row_terms_kernel(
            obs[b, n_scalars:], bits[b, n_scalars:], table, bias, shape, conv, reached, terms, b, count
        )
    _add_terms_kernel(terms, count, joint_conv, h)
    for b in range(rows):
        h_row = h[b]
        for j in range(h_row.shape[0]):
            h_row[j] = max(h_row[j], np.float32(0.0))
        x, n = h_row, h_row.shape[0]
        for layer in range(len(joint_weights)):
            y = ping if layer % 2 == 0 else pong
            m = joint_weights[layer].shape[1]
            _dense_kernel(
                x[:n], joint_weights[layer], joint_biases[layer], layer < len(joint_weights) - 1, y[:m]
            )
            x, n = y, m
        logits[b] = x[:n]
    return logits


_runs_kernel = kernel(_runs)
_forward_kernel = kernel(_forward)
_backward_kernel = kernel(_backward)
actor_logits = kernel(_actor_logits)


@dataclass(frozen=True)
class RunPieces:
    """The runs of equal non-zero cells of a batch's grid rows, cut into pieces (``_runs``)."""

    table_row: npt.NDArray[np.int64]
    """Each piece's row of the run table: (its length - 1) · rows_in + its input row."""
    value: npt.NDArray[np.float32]
    """Each piece's cell value."""
    grid_row: npt.NDArray[np.int64]
    """Each piece's row in the batch."""
    start: npt.NDArray[np.int64]
    """Each piece's first cell."""

    @classmethod
    def of(cls, obs: torch.Tensor, first: int, rows_in: int, cells: int, piece: int) -> RunPieces:
        """The pieces of the runs in a (B, features) float32 tensor's grids (from column ``first``, ``rows_in``
        grid rows of ``cells`` cells each), at most ``piece`` cells long."""
        rows = np.ascontiguousarray(obs.detach().cpu().numpy(), dtype=np.float32)
        # A rollout's observations hold about 5.5 pieces each; a batch with more is scanned again with room for
        # a piece per non-zero cell (a piece holds at least one), which always suffices.
        table_row, value, grid_row, start, fitted = _runs_kernel(
            rows, first, rows_in, cells, piece, rows.shape[0] * PIECES_PER_ROW_GUESS
        )
        if not fitted:
            capacity = int(np.count_nonzero(rows[:, first : first + rows_in * cells]))
            table_row, value, grid_row, start, _ = _runs_kernel(rows, first, rows_in, cells, piece, capacity)
        return cls(table_row=table_row, value=value, grid_row=grid_row, start=start)


class RunConv(torch.autograd.Function):
    """ReLU(conv) from the pieces of a batch's runs: ``apply(table, bias, pieces, rows, cells, lead)`` gives
    (rows, cells, outs); gradients reach ``table`` and ``bias`` (float32)."""

    @staticmethod
    def forward(
        ctx: Any,
        table: torch.Tensor,
        bias: torch.Tensor,
        pieces: RunPieces,
        rows: int,
        cells: int,
        lead: int,
    ) -> torch.Tensor:
        arrays = (pieces.table_row, pieces.value, pieces.grid_row, pieces.start)
        out = torch.from_numpy(
            _forward_kernel(
                np.ascontiguousarray(table.detach().cpu().numpy()),
                bias.detach().cpu().numpy(),
                *arrays,
                rows,
                cells,
                lead,
            )
        ).to(table.device)
        ctx.arrays, ctx.table_shape, ctx.lead = arrays, table.shape, lead
        ctx.save_for_backward(out)
        return out

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        (out,) = ctx.saved_tensors
        rows, reach_outs = ctx.table_shape
        table_row, value, grid_row, start = ctx.arrays
        grad_table, grad_bias = _backward_kernel(
            np.ascontiguousarray(grad.detach().cpu().numpy()),
            out.detach().cpu().numpy(),
            rows,
            table_row,
            value,
            grid_row,
            start,
            reach_outs // out.shape[2],
            ctx.lead,
        )
        device = grad.device
        return (
            torch.from_numpy(grad_table).to(device),
            torch.from_numpy(grad_bias).to(device),
            None,
            None,
            None,
            None,
        )
