"""SpinNet's descriptor network in torch, for conversion and as the yardstick of the ONNX export.

SpinNet: Ao, Hu, Yang, Markham, Guo, "SpinNet: Learning a General Surface Descriptor for 3D Point Cloud
Registration", CVPR 2021 (code: QingyongHu/SpinNet). Written here from the paper and the published
architecture (network/SpinNet.py, network/ThreeDCCN.py, script/common.py at commit 5581e7d1); no upstream
code is copied. Runtime code never imports this module (torch is needed only to convert and to test).

Upstream's forward on a patch `(M, P, 3)` (P = 2048 points within des_r of the keypoint, keypoint last):

1. offsets from the keypoint; 3DMatch: rotated so that the patch's normal (the least eigenvector of the
   uncentred scatter, signed so that axis . keypoint <= 0) becomes +z (Rodrigues); KITTI: unrotated;
2. a spherical grid of rad_n x ele_n x azi_n cell centres (shells at (i + 1/2) / rad_n x des_r, elevation
   (j + 1/2) pi / ele_n, azimuth (k + 1/2) 2 pi / azi_n); per cell the first `samples` patch points (slot
   order) with float32 squared distance below voxel_r^2 (pointnet2's ball_query); slots beyond the count
   repeat the first hit and are replaced by the centre; a cell with no hit holds patch slot 0 in its slot 0
   (ball_query's zero-initialised indices) and the centre elsewhere;
3. each cell's points minus its centre, rotated by -k 2 pi / azi_n about z (var_to_invar);
4. point MLP 3 -> 16 (1x1 conv, affine BatchNorm, ReLU), max over the samples -> (16, rad, ele, azi);
5. four 3-D convolutions (k = 3, circular azimuth padding, zero elevation padding, no radial padding:
   radius 9 -> 1), non-affine BatchNorm + ReLU, then seven 2-D convolutions with circular azimuth and zero
   elevation padding (dilations 1, 2, 2, 4, 4, 8, 16; the last three 2 x 2 kernels, no ReLU, the last
   without BatchNorm), max over the whole (ele, azi) map -> 32 values (the runtime L2-normalises).

- `SpinNetReference`: parameters named as the published state dict (minus `module.`), loaded with
  strict=True; `forward_cells` runs steps 4-5 from the grouped cells, `forward_aligned` runs 2-5 from aligned
  patches by brute force in torch (the ball query, the masks and var_to_invar as upstream writes them).
- `SpinNetExport`: steps 4-5 for ONNX (BatchNorm folded into the convolutions, the circular padding by
  concatenation, the elevation padding inside Conv); `descriptors/spinnet/export.py` exports it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

DESC_DIM = 32

# (des_r, rad_n, azi_n, ele_n, voxel_r, samples, patch points, align) as upstream's test scripts
# (ThreeDMatch/Test/preparation.py: Descriptor_Net(0.30, 9, 80, 40, 0.04, 30, '3DMatch'), 2048-point patches
# within 0.3 m; KITTI/Test/test_kitti.py: Descriptor_Net(2.0, 9, 60, 30, 0.3, 30, 'KITTI'), 2048 within 2 m)
CONFIGS = {
    "3dmatch": dict(des_r=0.30, rad_n=9, azi_n=80, ele_n=40, voxel_r=0.04, samples=30, patch_points=2048,
                    align="pca"),
    "kitti": dict(des_r=2.0, rad_n=9, azi_n=60, ele_n=30, voxel_r=0.3, samples=30, patch_points=2048,
                  align="none"),
}  # fmt: skip


def cell_centres(des_r: float, rad_n: int, azi_n: int, ele_n: int) -> np.ndarray:
    """(rad_n * ele_n * azi_n, 3) float32 cell centres in metres, radial-major, then elevation, azimuth."""
    beta = np.linspace(0, np.pi, ele_n, endpoint=False) + np.pi / ele_n / 2
    alpha = np.linspace(0, 2 * np.pi, azi_n, endpoint=False) + np.pi / azi_n
    b, a = np.meshgrid(beta, alpha, indexing="ij")
    unit = np.stack([np.sin(b) * np.cos(a), np.sin(b) * np.sin(a), np.cos(b)], -1) * des_r  # (ele, azi, 3)
    shells = np.arange(rad_n) / rad_n + 1 / (2 * rad_n)
    return (shells[:, None, None, None] * unit[None]).reshape(-1, 3).astype(np.float32)


def azimuth_rotations(azi_n: int) -> np.ndarray:
    """(azi_n, 3, 3) float32: rotation by -k 2 pi / azi_n about z (upstream angles2rotation_matrix)."""
    out = np.zeros((azi_n, 3, 3))
    for k in range(azi_n):
        t = -k * 2 * np.pi / azi_n
        out[k] = [[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]]
    return out.astype(np.float32)


def load_published(module: nn.Module, path: str | Path) -> dict:
    """The published `.pkl` (a DataParallel state dict, keys `module.*`) into `module`, strict=True."""
    state = torch.load(str(path), map_location="cpu", weights_only=True)
    if "state_dict" in state and not isinstance(state["state_dict"], torch.Tensor):
        state = state["state_dict"]
    sub = {(k[len("module.") :] if k.startswith("module.") else k): v for k, v in state.items()}
    result = module.load_state_dict(sub, strict=True)
    return {
        "missing": list(result.missing_keys),
        "unexpected": list(result.unexpected_keys),
        "loaded": len(sub),
    }


def _circular(x: torch.Tensor, pad: int) -> torch.Tensor:
    """Circular padding of the last (azimuth) axis by `pad` each side."""
    if pad == 0:
        return x
    return torch.cat([x[..., -pad:], x, x[..., :pad]], dim=-1)


def _zeros_ele(x: torch.Tensor, pad: int) -> torch.Tensor:
    """Zero padding of the elevation axis (second to last) by `pad` each side, by concatenation."""
    if pad == 0:
        return x
    z = torch.zeros(x.shape[:-2] + (pad, x.shape[-1]), dtype=x.dtype)
    return torch.cat([z, x, z], dim=-2)


class _Ops(nn.Module):
    """Holds the cylindrical CNN's modules under upstream's indices (`conv_net.ops.<i>`)."""

    def __init__(self, inchan: int = 16, dim: int = DESC_DIM) -> None:
        super().__init__()
        ops: list[nn.Module] = []
        cur, dilation = inchan, 1
        plan = [  # (dims, out, k, stride, bn, relu)
            (3, 32, 3, 1, True, True), (3, 32, 3, 1, True, True), (3, 64, 3, 1, True, True),
            (3, 64, 3, 1, True, True), (2, 128, 3, 2, True, True), (2, 128, 3, 1, True, True),
            (2, 64, 3, 2, True, True), (2, 64, 3, 1, True, True), (2, 32, 2, 2, True, False),
            (2, 32, 2, 2, True, False), (2, dim, 2, 2, False, False),
        ]  # fmt: skip
        for dims, out, k, stride, bn, relu in plan:
            d = dilation
            dilation *= stride  # upstream's "stride" only dilates the following layers
            if dims == 3:
                ops.append(nn.Conv3d(cur, out, kernel_size=(k, k, k), dilation=d))
                if bn:
                    ops.append(nn.BatchNorm3d(out, affine=False))
            else:
                ops.append(nn.Conv2d(cur, out, kernel_size=(k, k), dilation=d))
                if bn:
                    ops.append(nn.BatchNorm2d(out, affine=False))
            if relu:
                ops.append(nn.ReLU())
            cur = out
        self.ops = nn.ModuleList(ops)


def _pad_amount(op) -> int:
    """Upstream's padding for a conv (pad_image / pad_image_3d): the dilated kernel's span, halved."""
    k = op.kernel_size[-1]
    span = k + (k - 1) * (op.dilation[0] - 1)
    return span // 2 if span % 2 == 0 else (span - 1) // 2


def _hits(pts: torch.Tensor, centres: torch.Tensor, r2: torch.Tensor) -> torch.Tensor:
    """(cells, P) bool: float32 squared distance below r2 (pointnet2's ball_query test)."""
    d = pts[None, :, :] - centres[:, None, :]
    d2 = (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]
    return d2 < r2


class SpinNetReference(nn.Module):
    """SpinNet's Descriptor_Net with the published parameter names (bn_mapping is unused upstream too)."""

    def __init__(self, des_r: float, rad_n: int, azi_n: int, ele_n: int, voxel_r: float, samples: int, **_):
        super().__init__()
        self.des_r, self.rad_n, self.azi_n, self.ele_n = des_r, rad_n, azi_n, ele_n
        self.voxel_r, self.samples = voxel_r, samples
        self.bn_xyz_raising = nn.BatchNorm2d(16)
        self.bn_mapping = nn.BatchNorm2d(16)
        self.xyz_raising = nn.Conv2d(3, 16, kernel_size=(1, 1))
        self.conv_net = _Ops()

    @property
    def cells(self) -> int:
        return self.rad_n * self.ele_n * self.azi_n

    def forward_cells(self, cells: torch.Tensor) -> torch.Tensor:
        """`cells (M, cells * samples, 3)` (each cell's points minus its centre, in its azimuth frame) ->
        raw descriptors `(M, 32)`."""
        m = cells.shape[0]
        x = cells.reshape(m, self.cells, self.samples, 3).permute(0, 3, 1, 2)
        x = F.relu(self.bn_xyz_raising(self.xyz_raising(x)))
        x = F.max_pool2d(x, kernel_size=(1, self.samples)).squeeze(3)
        x = x.reshape(m, 16, self.rad_n, self.ele_n, self.azi_n)
        for op in self.conv_net.ops:
            if isinstance(op, nn.Conv3d | nn.Conv2d):
                if isinstance(op, nn.Conv2d) and x.dim() == 5:
                    x = x.squeeze(2)
                p = _pad_amount(op)
                x = _zeros_ele(_circular(x, p), p)
            x = op(x)
        x = F.max_pool2d(x, kernel_size=(x.shape[2], x.shape[3]))
        return x.reshape(m, -1)

    def group(self, aligned: torch.Tensor) -> torch.Tensor:
        """Steps 2-3 of the module docstring by brute force: `aligned (M, P, 3)` float32 offsets (metres)
        -> `(M, cells * samples, 3)`."""
        centres = torch.from_numpy(cell_centres(self.des_r, self.rad_n, self.azi_n, self.ele_n))
        rot = torch.from_numpy(azimuth_rotations(self.azi_n))
        r2 = torch.tensor(self.voxel_r, dtype=torch.float32) ** 2
        ns = self.samples
        outs = []
        for pts in aligned:  # one keypoint at a time: (cells, P) distances
            hit = torch.cat([_hits(pts, centres[c : c + 2048], r2) for c in range(0, self.cells, 2048)])
            rank = torch.cumsum(hit.long(), dim=1) - 1
            count = hit.sum(1)
            idx = torch.zeros(self.cells, ns, dtype=torch.long)  # ball_query's zero-initialised indices
            first = torch.where(count > 0, hit.float().argmax(1), torch.zeros_like(count))
            idx[:] = first[:, None]
            c, s = torch.nonzero(hit & (rank < ns), as_tuple=True)
            idx[c, rank[c, s]] = s
            grouped = pts[idx]  # (cells, ns, 3)
            mask = idx == idx[:, :1]
            mask[:, 0] = False
            grouped = torch.where(mask[..., None], centres[:, None, :].expand_as(grouped), grouped)
            rel = grouped - centres[:, None, :]
            rel = rel.reshape(self.rad_n, self.ele_n, self.azi_n, ns, 3)
            rel = torch.matmul(rel, rot.view(1, 1, self.azi_n, 3, 3).transpose(-1, -2))
            outs.append(rel.reshape(-1, 3))
        return torch.stack(outs)

    def forward_aligned(self, aligned: torch.Tensor) -> torch.Tensor:
        return self.forward_cells(self.group(aligned))


def _fold_bn(conv_w, conv_b, bn) -> tuple[torch.Tensor, torch.Tensor]:
    scale = 1.0 / torch.sqrt(bn.running_var.double() + bn.eps)
    if bn.affine:
        scale = scale * bn.weight.double()
    bias = (conv_b.double() - bn.running_mean.double()) * scale + (bn.bias.double() if bn.affine else 0.0)
    shape = (-1,) + (1,) * (conv_w.dim() - 1)
    return (conv_w.double() * scale.view(shape)).float().detach(), bias.float().detach()


class SpinNetExport(nn.Module):
    """`SpinNetReference.forward_cells` for ONNX: BatchNorm folded, the point MLP as one MatMul, the
    circular azimuth padding by concatenation, the elevation zero padding inside Conv."""

    def __init__(self, ref: SpinNetReference) -> None:
        super().__init__()
        self.rad_n, self.ele_n, self.azi_n, self.samples = ref.rad_n, ref.ele_n, ref.azi_n, ref.samples
        w, b = _fold_bn(ref.xyz_raising.weight, ref.xyz_raising.bias, ref.bn_xyz_raising)
        self.register_buffer("pnt_w", w.view(16, 3).t().contiguous())  # (3, 16)
        self.register_buffer("pnt_b", b.view(1, 1, 1, 16))
        ops = list(ref.conv_net.ops)
        self.convs = nn.ModuleList()
        self.relu: list[bool] = []
        self.pads: list[int] = []
        for i, op in enumerate(ops):
            if not isinstance(op, nn.Conv3d | nn.Conv2d):
                continue
            nxt = ops[i + 1] if i + 1 < len(ops) else None
            if isinstance(nxt, nn.BatchNorm2d | nn.BatchNorm3d):
                w, b = _fold_bn(op.weight, op.bias, nxt)
                after = ops[i + 2] if i + 2 < len(ops) else None
            else:
                w, b = op.weight.detach(), op.bias.detach()
                after = nxt
            p = _pad_amount(op)
            if isinstance(op, nn.Conv3d):
                c = nn.Conv3d(op.in_channels, op.out_channels, op.kernel_size, dilation=op.dilation,
                              padding=(0, p, 0))  # fmt: skip
            else:
                c = nn.Conv2d(op.in_channels, op.out_channels, op.kernel_size, dilation=op.dilation,
                              padding=(p, 0))  # fmt: skip
            c.weight.data.copy_(w)
            c.bias.data.copy_(b)
            self.convs.append(c)
            self.relu.append(isinstance(after, nn.ReLU))
            self.pads.append(p)

    def forward(self, cells: torch.Tensor) -> torch.Tensor:
        m = cells.shape[0]
        x = cells.reshape(m, self.rad_n * self.ele_n * self.azi_n, self.samples, 3)
        x = torch.matmul(x, self.pnt_w) + self.pnt_b  # (M, cells, samples, 16)
        x = F.relu(x.max(dim=2).values)  # max commutes with the monotone ReLU
        x = x.transpose(1, 2).reshape(m, 16, self.rad_n, self.ele_n, self.azi_n)
        for conv, relu, p in zip(self.convs, self.relu, self.pads, strict=True):
            if isinstance(conv, nn.Conv2d) and x.dim() == 5:
                x = x.reshape(m, x.shape[1], x.shape[3], x.shape[4])
            x = conv(_circular(x, p))
            if relu:
                x = F.relu(x)
        return torch.amax(x, dim=(2, 3)).reshape(m, -1)


def patch_flops(cfg: dict) -> float:
    """Multiply-adds of the network per keypoint (for the model card)."""
    e, a, r, s = cfg["ele_n"], cfg["azi_n"], cfg["rad_n"], cfg["samples"]
    macs = r * e * a * s * 3 * 16
    chans = [(16, 32), (32, 32), (32, 64), (64, 64)]
    for i, (ci, co) in enumerate(chans):
        macs += (r - 2 * (i + 1)) * e * a * ci * co * 27
    for ci, co, k in [
        (64, 128, 3),
        (128, 128, 3),
        (128, 64, 3),
        (64, 64, 3),
        (64, 32, 2),
        (32, 32, 2),
        (32, 32, 2),
    ]:
        macs += e * a * ci * co * k * k
    return float(macs)


__all__ = [
    "CONFIGS",
    "SpinNetExport",
    "SpinNetReference",
    "azimuth_rotations",
    "cell_centres",
    "load_published",
    "patch_flops",
]
