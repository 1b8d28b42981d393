"""Sparse-convolution kernel maps as MinkowskiEngine (ME) makes them, in numpy: what FCGF's ResUNetBN2C needs.

The rules (ME's src/kernel_region.hpp, coordinate_map_cpu.hpp, coordinate_map_manager.cpp; the 2019 ME
0.2/0.3 that trained the published checkpoints enumerates kernels the same way, src/region.cpp):

- a sparse tensor at tensor stride s holds integer coordinates, multiples of s; the input cloud is at s = 1,
  its coordinates floor(xyz / voxel) (FCGF's util/misc.py `extract_features`);
- kernel offsets of an odd kernel size k run over -(k//2)..k//2 per axis, times the tensor stride of the
  input (dilation 1), enumerated x fastest, then y, then z: offset index = ix + k iy + k^2 iz. A weight
  `kernel` of shape (k^3, in, out) holds offset i's (in, out) matrix in row i;
- convolution at stride 1 keeps the coordinates; the output of input row i at offset d is the output row
  whose coordinate + d = the input's coordinate (out[u] += W_d x[u + d]);
- a stride-2 convolution from tensor stride s to 2s has the output coordinates floor(c / 2s) * 2s of the
  input coordinates c (one each), and the same rule with offsets d in multiples of s around each output;
- a transposed stride-2 convolution from 2s back to s has as output the coordinates that already exist at
  stride s (ME without `expand_coordinates`, which FCGF relies on to concatenate its skip connections), and
  its kernel map is the stride-2 convolution's with inputs and outputs swapped (ME's `is_transpose`).

A `KernelMap` lists the (input row, output row) pairs of each offset; the convolution is then a
gather-GEMM-scatter per offset. Row order of a level is lexicographic (sorted coordinates): convolutions are
equivariant to it, so the features of a point do not depend on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fastmac_exp.errors import InputError

DENSE_CELLS = 1 << 24  # a level's bounding box up to this many cells is looked up in a dense grid


@dataclass(frozen=True)
class KernelMap:
    """The pairs of one convolution: offset k's are rows bounds[k]:bounds[k+1] of in_rows / out_rows."""

    in_rows: np.ndarray  # (P,) int64
    out_rows: np.ndarray  # (P,) int64
    bounds: np.ndarray  # (K + 1,) int64
    n_in: int
    n_out: int

    @property
    def volume(self) -> int:
        return len(self.bounds) - 1

    def transposed(self) -> KernelMap:
        return KernelMap(self.out_rows, self.in_rows, self.bounds, self.n_out, self.n_in)


def kernel_offsets(kernel_size: int) -> np.ndarray:
    """(k^3, 3) int64 offsets in units of the input's tensor stride, x fastest (ME's order)."""
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise InputError(f"kernel size must be odd and positive, got {kernel_size}")
    r = np.arange(-(kernel_size // 2), kernel_size // 2 + 1)
    z, y, x = np.meshgrid(r, r, r, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.int64)


class CoordTable:
    """Row lookup of the coordinates of one level (multiples of `stride`): a dense grid over the bounding
    box grown by `margin` cells a side when that has at most `dense_cells` cells (then a neighbour of a
    stored coordinate within the margin is one addition to its grid index), else binary search over the
    sorted keys; both give the same rows."""

    def __init__(
        self, coords: np.ndarray, stride: int, margin: int = 0, dense_cells: int = DENSE_CELLS
    ) -> None:
        c = np.asarray(coords, dtype=np.int64) // stride
        self.stride, self.margin = stride, margin
        self.lo = c.min(axis=0) - margin
        self.dims = c.max(axis=0) + margin - self.lo + 1
        self.keys = self._keys(c - self.lo)
        self.dense = int(np.prod(self.dims)) <= dense_cells
        if self.dense:
            self.grid = np.full(int(np.prod(self.dims)), -1, dtype=np.int32)
            self.grid[self.keys] = np.arange(len(c), dtype=np.int32)
        else:
            order = np.argsort(self.keys, kind="stable")
            self.sorted_keys, self.rows = self.keys[order], order

    def _keys(self, rel: np.ndarray) -> np.ndarray:
        return (rel[..., 2] * self.dims[1] + rel[..., 1]) * self.dims[0] + rel[..., 0]

    def find(self, coords: np.ndarray) -> np.ndarray:
        """The row of each coordinate (multiples of the stride), -1 where the level has none."""
        rel = np.asarray(coords, dtype=np.int64) // self.stride - self.lo
        inside = np.all((rel >= 0) & (rel < self.dims), axis=-1)
        keys = self._keys(np.where(inside[..., None], rel, 0))
        if self.dense:
            return np.where(inside, self.grid[keys], -1).astype(np.int64)
        pos = np.minimum(np.searchsorted(self.sorted_keys, keys), len(self.sorted_keys) - 1)
        return np.where(inside & (self.sorted_keys[pos] == keys), self.rows[pos], -1)

    def neighbours(self, centres: np.ndarray, offsets: np.ndarray, chunk: int = 1 << 22) -> np.ndarray:
        """(M, K) int64: the row at centre + offset (offsets in units of the stride) for each centre (a
        multiple of the stride) and offset, -1 where there is none."""
        centres = np.asarray(centres, dtype=np.int64)
        out = np.empty((len(centres), len(offsets)), dtype=np.int64)
        reach = int(np.abs(offsets).max()) if len(offsets) else 0
        rel = centres // self.stride - self.lo
        fast = (
            self.dense and reach <= self.margin and bool(np.all((rel >= reach) & (rel < self.dims - reach)))
        )
        step = max(1, chunk // max(1, len(offsets)))
        if fast:  # every neighbour lies in the grid: a grid index plus the offset's
            delta = self._keys(offsets) - self._keys(np.zeros(3, dtype=np.int64))
            base = self._keys(rel)
            for i in range(0, len(centres), step):
                out[i : i + step] = self.grid[base[i : i + step, None] + delta[None, :]]
            return out
        for i in range(0, len(centres), step):
            out[i : i + step] = self.find(centres[i : i + step, None, :] + offsets[None] * self.stride)
        return out


def voxelize(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """(coordinates (M, 3) int64 = floor(xyz / voxel), the row of the first point of each voxel (M,)),
    the voxels in lexicographic order (FCGF: ME.utils.sparse_quantize(..., return_index=True) keeps each
    voxel's first point too)."""
    c = np.floor(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64)
    first = unique_rows(c)
    return c[first], first


def unique_rows(c: np.ndarray) -> np.ndarray:
    """The row of the first occurrence of each distinct row of integer coordinates (N, 3), the distinct rows
    in lexicographic order (z, y, x keys packed into one int64 where they fit: np.unique's order)."""
    lo = c.min(axis=0)
    dims = c.max(axis=0) - lo + 1
    if len(c) == 0 or float(np.prod(dims.astype(np.float64))) >= 2.0**62:
        return np.unique(c, axis=0, return_index=True)[1]
    rel = c - lo
    keys = (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]
    return np.unique(keys, return_index=True)[1]


def downsample(coords: np.ndarray, out_stride: int) -> np.ndarray:
    """The coordinates at tensor stride `out_stride` of coordinates at a finer stride: floor(c / s) * s,
    unique, in lexicographic order (ME's `stride_coordinate` with floor division)."""
    c = np.floor_divide(coords, out_stride) * out_stride
    return c[unique_rows(c)]


def pairs_from_table(table: np.ndarray, n_in: int) -> KernelMap:
    """The KernelMap of a (n_out, K) table of input rows (-1 or n_in: none), pairs grouped by offset."""
    t = np.asarray(table).T
    hit = (t >= 0) & (t < n_in)
    counts = hit.sum(axis=1)
    bounds = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return KernelMap(
        t[hit].astype(np.int64), np.nonzero(hit)[1].astype(np.int64), bounds, n_in, table.shape[0]
    )


def kernel_table(
    in_coords: np.ndarray,
    out_coords: np.ndarray,
    kernel_size: int,
    in_stride: int,
    in_table: CoordTable | None = None,
) -> np.ndarray:
    """(n_out, k^3) int64: for each output u and offset d (units of in_stride, ME's order) the input row at
    u + d, n_in where there is none (conv1's table, an index into the inputs with a zero row appended)."""
    table = in_table or CoordTable(in_coords, in_stride, margin=kernel_size // 2)
    rows = table.neighbours(out_coords, kernel_offsets(kernel_size))
    rows[rows < 0] = len(in_coords)
    return rows


def kernel_map(
    in_coords: np.ndarray,
    out_coords: np.ndarray,
    kernel_size: int,
    in_stride: int,
    in_table: CoordTable | None = None,
) -> KernelMap:
    """The pairs of a convolution with `kernel_size` from `in_coords` (tensor stride `in_stride`) onto
    `out_coords`: for each offset d (units of in_stride, ME's order) and output u, the input at u + d."""
    t = kernel_table(in_coords, out_coords, kernel_size, in_stride, in_table)
    return pairs_from_table(t, len(in_coords))


@dataclass(frozen=True)
class UNetMaps:
    """Everything ResUNetBN2C's forward pass needs of one cloud, computed before the network runs:
    `coords[l]` the coordinates at tensor stride 2^l (l = 0..3), `conv1` the first convolution's map,
    `same[l]` the 3x3x3 stride-1 maps at level l, `down[l]` the stride-2 maps from level l to l + 1 (the
    transposed convolutions take them swapped)."""

    coords: tuple[np.ndarray, ...]
    conv1_table: np.ndarray
    same: tuple[KernelMap, ...]
    down: tuple[KernelMap, ...]

    @property
    def conv1(self) -> KernelMap:
        return pairs_from_table(self.conv1_table, len(self.coords[0]))

    @property
    def sizes(self) -> tuple[int, ...]:
        return tuple(len(c) for c in self.coords)


def unet_maps(coords: np.ndarray, conv1_kernel_size: int, levels: int = 4) -> UNetMaps:
    """The maps of a `levels`-level sparse U-Net over voxel coordinates `coords` (tensor stride 1)."""
    coords = np.asarray(coords, dtype=np.int64)
    if coords.ndim != 2 or coords.shape[1] != 3 or len(coords) == 0:
        raise InputError(f"voxel coordinates must have shape (M, 3) with M > 0, got {coords.shape}")
    levels_c = [coords]
    for lv in range(1, levels):
        levels_c.append(downsample(levels_c[-1], 1 << lv))
    margins = [max(1, conv1_kernel_size // 2)] + [1] * (levels - 1)
    tables = [CoordTable(c, 1 << lv, margins[lv]) for lv, c in enumerate(levels_c)]
    same = tuple(kernel_map(c, c, 3, 1 << lv, tables[lv]) for lv, c in enumerate(levels_c))
    down = tuple(
        kernel_map(levels_c[lv], levels_c[lv + 1], 3, 1 << lv, tables[lv]) for lv in range(levels - 1)
    )
    conv1 = kernel_table(coords, coords, conv1_kernel_size, 1, tables[0])
    return UNetMaps(tuple(levels_c), conv1, same, down)
