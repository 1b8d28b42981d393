"""FCGF's sparse convolutions held to dense torch conv3d (float64, so any wrong pair or offset shows far above
rounding), and MinkowskiEngine's coordinate rules as hand cases (fastmac_exp/descriptors/fcgf_maps.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fastmac_exp.descriptors.fcgf_maps import (
    CoordTable,
    downsample,
    kernel_map,
    kernel_offsets,
    kernel_table,
    unet_maps,
    unique_rows,
    voxelize,
)
from fastmac_exp.descriptors.fcgf_plan import BN_EPS, NetConfig, expected_shapes, resunet
from fastmac_exp.descriptors.fcgf_torch import ResUNetBN2C, TorchOps, sparse_conv
from fastmac_exp.errors import InputError

TOL = 1e-10  # float64 sums in another order; a wrong weight or pair is O(1)


def me_to_dense(kernel: torch.Tensor) -> torch.Tensor:
    """ME's (k^3, in, out), offset index ix + k iy + k^2 iz, as conv3d's (out, in, x, y, z)."""
    k = round(kernel.shape[0] ** (1 / 3))
    return kernel.reshape(k, k, k, kernel.shape[1], kernel.shape[2]).permute(4, 3, 2, 1, 0)


def grid(coords: np.ndarray, feats: torch.Tensor, lo: np.ndarray, n: int, stride: int) -> torch.Tensor:
    """A (1, C, n, n, n) dense tensor of features at coordinates (multiples of stride) from origin lo."""
    g = feats.new_zeros((1, feats.shape[1], n, n, n))
    ijk = (coords - lo) // stride
    g[0, :, ijk[:, 0], ijk[:, 1], ijk[:, 2]] = feats.T
    return g


def read(g: torch.Tensor, coords: np.ndarray, lo: np.ndarray, stride: int) -> torch.Tensor:
    ijk = (coords - lo) // stride
    return g[0, :, ijk[:, 0], ijk[:, 1], ijk[:, 2]].T


def random_cloud(rng, n=8, occupancy=0.35, lo=(-8, 0, 8)):
    lo = np.asarray(lo)
    cells = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3) + lo
    return cells[rng.random(len(cells)) < occupancy], lo


# -- hand cases for the coordinate rules


def test_offsets_run_x_fastest_as_minkowski_engine():
    off = kernel_offsets(3)
    assert off.shape == (27, 3)
    assert off[[0, 1, 3, 9, 13, 26]].tolist() == [
        [-1, -1, -1],
        [0, -1, -1],
        [-1, 0, -1],
        [-1, -1, 0],
        [0, 0, 0],
        [1, 1, 1],
    ]
    assert kernel_offsets(7)[0].tolist() == [-3, -3, -3] and kernel_offsets(7)[171].tolist() == [0, 0, 0]
    with pytest.raises(InputError, match="odd"):
        kernel_offsets(4)


def test_strided_coordinates_floor_negative_coordinates():
    c = np.array([[-1, 0, 3], [-2, 1, 2], [1, 1, 1], [0, 0, 0]])
    assert downsample(c, 2).tolist() == [[-2, 0, 2], [0, 0, 0]]
    assert downsample(np.array([[-3, 5, -4]]), 4).tolist() == [[-4, 4, -4]]


def test_unique_rows_packed_and_generic_agree():
    rng = np.random.default_rng(7)
    for span in (5, 1 << 20, 1 << 40):  # the last one does not pack into an int64
        c = rng.integers(-span, span, (3000, 3))
        c = np.concatenate([c, c[:500]])[rng.permutation(3500)]
        _, want = np.unique(c, axis=0, return_index=True)
        assert np.array_equal(unique_rows(c), want)


def test_voxelize_keeps_the_first_point_of_each_voxel():
    pts = np.array([[0.26, 0.0, 0.0], [0.24, 0.0, 0.0], [0.27, 0.01, 0.0], [-0.01, 0.0, 0.0]])
    coords, first = voxelize(pts, 0.25)
    assert coords.tolist() == [[-1, 0, 0], [0, 0, 0], [1, 0, 0]] and first.tolist() == [3, 1, 0]


def test_stride_two_map_and_its_transpose_by_hand():
    fine = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [-1, 0, 0]])
    coarse = downsample(fine, 2)
    assert coarse.tolist() == [[-2, 0, 0], [0, 0, 0], [2, 0, 0]]
    m = kernel_map(fine, coarse, 3, 1)
    pairs = {
        (int(k), int(i), int(o))
        for k in range(27)
        for i, o in zip(m.in_rows[m.bounds[k] : m.bounds[k + 1]], m.out_rows[m.bounds[k] : m.bounds[k + 1]])
    }
    # offset index of (dx, 0, 0) is 13 + dx; out[u] takes in[u + d]
    assert pairs == {(14, 3, 0), (12, 3, 1), (13, 0, 1), (14, 1, 1), (12, 1, 2), (13, 2, 2)}
    t = m.transposed()  # output: the four fine coordinates that exist, no new ones
    assert (t.n_in, t.n_out) == (3, 4)
    swapped = sorted(zip(m.out_rows.tolist(), m.in_rows.tolist()))
    assert sorted(zip(t.in_rows.tolist(), t.out_rows.tolist())) == swapped


def test_dense_grid_and_sorted_lookup_agree():
    rng = np.random.default_rng(3)
    coords = np.unique(rng.integers(-6, 6, (800, 3)) * 2, axis=0)
    q = np.concatenate([coords[rng.permutation(len(coords))[:300]], rng.integers(-9, 9, (4000, 3)) * 2])
    dense, hashed = CoordTable(coords, 2, margin=3), CoordTable(coords, 2, dense_cells=0)
    assert dense.dense and not hashed.dense
    a, b = dense.find(q), hashed.find(q)
    assert np.array_equal(a, b) and (a >= 0).sum() >= 300 and (a < 0).sum() > 2000
    hit = a >= 0
    assert np.array_equal(coords[a[hit]], q[hit])
    # neighbour tables: the grid-index fast path, the chunked lookups and the brute force agree
    off = kernel_offsets(7)
    fast = dense.neighbours(coords, off, chunk=5000)
    assert np.array_equal(fast, hashed.neighbours(coords, off))
    assert np.array_equal(fast, CoordTable(coords, 2).neighbours(coords, off))  # no margin: no fast path
    brute = {tuple(c): i for i, c in enumerate(coords)}
    want = [[brute.get(tuple(c + 2 * d), -1) for d in off] for c in coords[:50]]
    assert fast[:50].tolist() == want and (fast >= 0).sum() > 2 * len(coords)


# -- single convolutions on partly occupied grids: the dense result read at the occupied sites


@pytest.mark.parametrize("kernel_size", [1, 3, 5, 7])
def test_stride_one_conv_equals_dense(kernel_size):
    rng = np.random.default_rng(kernel_size)
    coords, lo = random_cloud(rng)
    x = torch.from_numpy(rng.normal(size=(len(coords), 3)))
    w = torch.from_numpy(rng.normal(size=(kernel_size**3, 3, 4)))
    got = sparse_conv(x, w, kernel_map(coords, coords, kernel_size, 1))
    dense = F.conv3d(grid(coords, x, lo, 8, 1), me_to_dense(w), padding=kernel_size // 2)
    assert torch.allclose(got, read(dense, coords, lo, 1), atol=TOL, rtol=0)


@pytest.mark.parametrize("stride", [1, 2, 4])
def test_stride_two_conv_and_transposed_equal_dense(stride):
    rng = np.random.default_rng(10 + stride)
    n = 16 // stride
    cells, lo = random_cloud(rng, n=n, occupancy=0.5, lo=(-16, 0, 16))
    fine = lo + (cells - lo) * stride  # coordinates at tensor stride `stride`
    coarse = downsample(fine, 2 * stride)
    w = torch.from_numpy(rng.normal(size=(27, 3, 5)))
    x = torch.from_numpy(rng.normal(size=(len(fine), 3)))
    m = kernel_map(fine, coarse, 3, stride)
    down = F.conv3d(grid(fine, x, lo, n, stride), me_to_dense(w), stride=2, padding=1)
    assert torch.allclose(sparse_conv(x, w, m), read(down, coarse, lo, 2 * stride), atol=TOL, rtol=0)
    xc = torch.from_numpy(rng.normal(size=(len(coarse), 3)))
    wt = torch.from_numpy(rng.normal(size=(27, 3, 5)))
    dense_w = me_to_dense(wt).transpose(0, 1)  # conv_transpose3d: (in, out, x, y, z)
    xg = grid(coarse, xc, lo, n // 2, 2 * stride)
    up = F.conv_transpose3d(xg, dense_w, stride=2, padding=1, output_padding=1)
    assert torch.allclose(sparse_conv(xc, wt, m.transposed()), read(up, fine, lo, stride), atol=TOL, rtol=0)


def test_conv1_table_equals_the_pairs():
    rng = np.random.default_rng(5)
    coords, _ = random_cloud(rng)
    m = kernel_map(coords, coords, 5, 1)
    table = kernel_table(coords, coords, 5, 1)
    x = torch.from_numpy(rng.normal(size=(len(coords), 2)))
    w = torch.from_numpy(rng.normal(size=(125, 2, 3)))
    padded = torch.cat([x, x.new_zeros((1, 2))])
    by_table = padded[torch.from_numpy(table)].reshape(len(coords), -1) @ w.reshape(-1, 3)
    assert torch.allclose(by_table, sparse_conv(x, w, m), atol=TOL, rtol=0)


# -- the whole network on a fully occupied grid: dense conv3d / conv_transpose3d everywhere


class DenseOps:
    """The plan on dense (1, C, n, n, n) grids (every site occupied at every level)."""

    def __init__(self, p):
        self.p = p

    def conv(self, key, x, out, kmap, transposed=False):
        w = me_to_dense(self.p[f"{key}.kernel"])
        if transposed:
            return F.conv_transpose3d(x, w.transpose(0, 1), stride=2, padding=1, output_padding=1)
        return F.conv3d(x, w, stride=2 if kmap[0] == "down" else 1, padding=w.shape[-1] // 2)

    def linear(self, key, x, out, bias):
        w = self.p[f"{key}.kernel"].reshape(x.shape[1], out).T[:, :, None, None, None]
        return F.conv3d(x, w, self.p[f"{key}.bias"].reshape(out) if bias else None)

    def bn(self, key, x):
        g = lambda n: self.p[f"{key}.bn.{n}"]  # noqa: E731
        mean, var = g("running_mean"), g("running_var")
        return F.batch_norm(x, mean, var, g("weight"), g("bias"), False, 0.0, BN_EPS)

    relu = staticmethod(torch.relu)
    add = staticmethod(torch.add)

    def cat(self, a, b):
        return torch.cat([a, b], dim=1)

    def normalize(self, x):
        return x / torch.norm(x, p=2, dim=1, keepdim=True)


def random_state(cfg: NetConfig, seed: int, dtype=torch.float64) -> dict[str, torch.Tensor]:
    """A checkpoint-shaped state dict with weights of a trained net's scale (BN statistics included)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for key, shape in expected_shapes(cfg).items():
        if key.endswith("num_batches_tracked"):
            out[key] = torch.tensor(1000)
        elif key.endswith("running_var") or key.endswith("bn.weight"):
            out[key] = (0.5 + torch.rand(shape, generator=g)).to(dtype)
        elif key.endswith(".kernel"):
            fan_in = int(np.prod(shape[:-1]))
            out[key] = (torch.randn(shape, generator=g) / fan_in**0.5).to(dtype)
        else:
            out[key] = (0.1 * torch.randn(shape, generator=g)).to(dtype)
    return out


VARIANTS = [
    NetConfig(1, 5, 16, True),
    NetConfig(1, 7, 32, True),
    NetConfig(1, 5, 32, False),
    NetConfig(1, 7, 16, False),
]


def variant_id(c: NetConfig) -> str:
    return f"conv1-{c.conv1_kernel_size}-out{c.out_channels}-norm{int(c.normalize_feature)}"


@pytest.mark.parametrize("cfg", VARIANTS, ids=variant_id)
def test_resunet_equals_dense_on_a_full_grid(cfg):
    n, lo = 8, np.array([-8, 16, 0])
    coords = lo + np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    coords = coords[np.random.default_rng(0).permutation(len(coords))]  # row order must not matter
    maps = unet_maps(coords, cfg.conv1_kernel_size)
    assert maps.sizes == (512, 64, 8, 1)
    state = random_state(cfg, seed=cfg.conv1_kernel_size + cfg.out_channels)
    x = torch.from_numpy(np.random.default_rng(1).normal(size=(len(coords), 1)))
    model = ResUNetBN2C(cfg).double()
    model.load_fcgf(state)
    got = model(x, maps)
    dense = resunet(DenseOps(state), grid(coords, x, lo, n, 1), cfg)
    want = read(dense, coords, lo, 1)
    assert got.shape == (512, cfg.out_channels)
    assert torch.allclose(got, want, atol=TOL, rtol=0), float((got - want).abs().max())
    if cfg.normalize_feature:
        assert torch.allclose(got.norm(dim=1), torch.ones(512, dtype=torch.float64))
    # the sparse path on the same weights with one voxel fewer is a different answer (the test can fail)
    fewer = unet_maps(coords[1:], cfg.conv1_kernel_size)
    assert not torch.allclose(model(x[1:], fewer), want[1:], atol=1e-3)


def test_sparse_path_uses_every_parameter():
    """Each parameter reaches the output (no layer silently skipped): every gradient is nonzero."""
    cfg = NetConfig(1, 5, 16, True)
    rng = np.random.default_rng(2)
    coords, _ = random_cloud(rng, n=8, occupancy=0.6)
    state = {k: v.requires_grad_(v.is_floating_point()) for k, v in random_state(cfg, 4).items()}
    out = resunet(
        TorchOps(state, unet_maps(coords, 5)), torch.ones((len(coords), 1), dtype=torch.float64), cfg
    )
    (out * torch.from_numpy(rng.normal(size=out.shape))).sum().backward()
    for key, t in state.items():
        if t.is_floating_point():
            assert t.grad is not None and t.grad.abs().max() > 1e-9, key
