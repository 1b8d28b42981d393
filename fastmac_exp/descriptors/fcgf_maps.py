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
gather-GEMM-scatter per offset. Row order of a level is np.unique's (sorted coordinates): convolutions are
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

    def table(self) -> np.ndarray:
        """(n_out, K) int64: the input row of each output and offset, n_in where there is none (a map in
        which an output has at most one input per offset: stride 1 or 2, not transposed)."""
        t = np.full((self.n_out, self.volume), self.n_in, dtype=np.int64)
        for k in range(self.volume):
            s, e = self.bounds[k], self.bounds[k + 1]
            t[self.out_rows[s:e], k] = self.in_rows[s:e]
        return t


def kernel_offsets(kernel_size: int) -> np.ndarray:
    """(k^3, 3) int64 offsets in units of the input's tensor stride, x fastest (ME's order)."""
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise InputError(f"kernel size must be odd and positive, got {kernel_size}")
    r = np.arange(-(kernel_size // 2), kernel_size // 2 + 1)
    z, y, x = np.meshgrid(r, r, r, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.int64)


class CoordTable:
    """Row lookup of the coordinates of one level (multiples of `stride`): a dense grid over the bounding
    box when it has at most `dense_cells` cells, else binary search over the sorted keys (the same rows)."""

    def __init__(self, coords: np.ndarray, stride: int, dense_cells: int = DENSE_CELLS) -> None:
        c = np.asarray(coords, dtype=np.int64) // stride
        self.stride = stride
        self.lo = c.min(axis=0)
        self.dims = c.max(axis=0) - self.lo + 1
        keys = self._keys(c - self.lo)
        self.dense = int(np.prod(self.dims)) <= dense_cells
        if self.dense:
            self.grid = np.full(int(np.prod(self.dims)), -1, dtype=np.int64)
            self.grid[keys] = np.arange(len(c))
        else:
            order = np.argsort(keys, kind="stable")
            self.sorted_keys, self.rows = keys[order], order

    def _keys(self, rel: np.ndarray) -> np.ndarray:
        return (rel[:, 2] * self.dims[1] + rel[:, 1]) * self.dims[0] + rel[:, 0]

    def find(self, coords: np.ndarray) -> np.ndarray:
        """The row of each coordinate (multiples of the stride), -1 where the level has none."""
        rel = np.asarray(coords, dtype=np.int64) // self.stride - self.lo
        inside = np.all((rel >= 0) & (rel < self.dims), axis=1)
        keys = self._keys(np.where(inside[:, None], rel, 0))
        if self.dense:
            return np.where(inside, self.grid[keys], -1)
        pos = np.minimum(np.searchsorted(self.sorted_keys, keys), len(self.sorted_keys) - 1)
        return np.where(inside & (self.sorted_keys[pos] == keys), self.rows[pos], -1)


def voxelize(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """(coordinates (M, 3) int64 = floor(xyz / voxel), the row of the first point of each voxel (M,)),
    the voxels in np.unique's order (FCGF: ME.utils.sparse_quantize(..., return_index=True) keeps each
    voxel's first point too)."""
    c = np.floor(np.asarray(points, dtype=np.float64) / voxel).astype(np.int64)
    _, first = np.unique(c, axis=0, return_index=True)
    return c[first], first


def downsample(coords: np.ndarray, out_stride: int) -> np.ndarray:
    """The coordinates at tensor stride `out_stride` of coordinates at a finer stride: floor(c / s) * s,
    unique, in np.unique's order (ME's `stride_coordinate` with floor division)."""
    return np.unique(np.floor_divide(coords, out_stride) * out_stride, axis=0)


def kernel_map(
    in_coords: np.ndarray,
    out_coords: np.ndarray,
    kernel_size: int,
    in_stride: int,
    in_table: CoordTable | None = None,
) -> KernelMap:
    """The pairs of a convolution with `kernel_size` from `in_coords` (tensor stride `in_stride`) onto
    `out_coords`: for each offset d (units of in_stride, ME's order) and output u, the input at u + d."""
    table = in_table or CoordTable(in_coords, in_stride)
    offsets = kernel_offsets(kernel_size) * in_stride
    ins, outs, bounds = [], [], [0]
    out_rows = np.arange(len(out_coords), dtype=np.int64)
    for d in offsets:
        rows = table.find(out_coords + d)
        hit = rows >= 0
        ins.append(rows[hit])
        outs.append(out_rows[hit])
        bounds.append(bounds[-1] + int(hit.sum()))
    return KernelMap(
        np.concatenate(ins),
        np.concatenate(outs),
        np.asarray(bounds, dtype=np.int64),
        len(in_coords),
        len(out_coords),
    )


@dataclass(frozen=True)
class UNetMaps:
    """Everything ResUNetBN2C's forward pass needs of one cloud, computed before the network runs:
    `coords[l]` the coordinates at tensor stride 2^l (l = 0..3), `conv1` the first convolution's map,
    `same[l]` the 3x3x3 stride-1 maps at level l, `down[l]` the stride-2 maps from level l to l + 1 (the
    transposed convolutions take them swapped)."""

    coords: tuple[np.ndarray, ...]
    conv1: KernelMap
    same: tuple[KernelMap, ...]
    down: tuple[KernelMap, ...]

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
    tables = [CoordTable(c, 1 << lv) for lv, c in enumerate(levels_c)]
    same = tuple(kernel_map(c, c, 3, 1 << lv, tables[lv]) for lv, c in enumerate(levels_c))
    down = tuple(
        kernel_map(levels_c[lv], levels_c[lv + 1], 3, 1 << lv, tables[lv]) for lv in range(levels - 1)
    )
    conv1 = same[0] if conv1_kernel_size == 3 else kernel_map(coords, coords, conv1_kernel_size, 1, tables[0])
    return UNetMaps(tuple(levels_c), conv1, same, down)
