"""BUFFER's reference-axis network (`Ref`) and patch descriptor (`Desc`) in torch, for conversion only.

BUFFER: Ao et al., "BUFFER: Balancing Accuracy, Efficiency, and Generalizability in Point Cloud
Registration", CVPR 2023 (code: aosheng1996/BUFFER). Written here from the published architecture
(models/point_learner.py, models/vn_layers.py, models/patch_embedder.py, models/patchnet.py at commit
6f905699); no upstream code is copied. Two forms of each network:

- `RefReference`, `DescReference`: parameters named exactly as the published state dicts (minus the
  `Ref.` / `Desc.` prefix), so `load_published` loads them with `strict=True` (no missing or unexpected
  key). Their forward passes are a direct transcription of the upstream computation (the fake support
  point at 1e6, the shadow rows, `torch.linalg.cross`, BatchNorm modules in eval mode, the explicit
  circular padding by concatenation, a 3-D convolution); they are the yardstick for the exports.
- `RefExport`, `DescExport`: the same functions rewritten for ONNX and speed (BatchNorm folded into the
  preceding linear map, vectors laid out (..., 3, C) so every linear map is one MatMul, the first 3-D
  convolution as a 2-D one over radius x channel, zero padding of the elevation axis inside Conv);
  `descriptors/buffer/export.py` exports these and checks onnxruntime against the references.

Runtime code never imports this module (torch is needed only to convert).

Shapes (N = points of the Ref's finest layer, M = keypoints):

- Ref inputs: `normals (N0, 3)`, `points0..2 (N_l, 3)` (layer l = grid subsampling at 2^l x 0.07 m),
  `neighbors0..2 (N_l, K_l)` int64 (radius 2^l x 0.07 m, sorted by distance, shadow index N_l),
  `pools0..1 (N_{l+1}, P_l)` (layer-l points within 2^l x 0.07 m of each layer-(l+1) point, shadow N_l),
  `upsamples0..1 (N_l,)` (the nearest layer-(l+1) point within 2^(l+1) x 0.07 m, shadow N_{l+1}).
  Output `axis (N0, 3)`: the raw reference axis (normalise and orient it outside, as upstream does).
- Desc input `grouped (M, 4200, 3)`: per keypoint, 3 radial x 7 elevation x 20 azimuth cells x 10
  points of the aligned patch (units of the descriptor radius; empty slots are 0), cell-major in that
  order (see fastmac_exp.descriptors.buffer.group_cells). Output `descriptors (M, 32)`, unit norm.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

EPS_VN = 1e-6  # vn_layers.EPS
SLOPE = 0.2  # VN leaky ReLU negative slope
RAD_N, ELE_N, AZI_N, SAMPLES = 3, 7, 20, 10
CELLS = RAD_N * ELE_N * AZI_N
DESC_DIM = 32


# ----------------------------------------------------------------------------------------------------
# loading the published weights


def load_published(module: nn.Module, path: str | Path, prefix: str) -> dict:
    """Load the `prefix.*` tensors of a published BUFFER `best.pth` into `module` with strict=True.

    Returns {"missing": [...], "unexpected": [...], "loaded": n}; both lists are empty when it loads
    (strict loading raises otherwise, so a non-empty list never comes back).
    """
    state = torch.load(str(path), map_location="cpu", weights_only=True)
    sub = {k[len(prefix) + 1 :]: v for k, v in state.items() if k.startswith(prefix + ".")}
    result = module.load_state_dict(sub, strict=True)
    return {
        "missing": list(result.missing_keys),
        "unexpected": list(result.unexpected_keys),
        "loaded": len(sub),
    }


# ----------------------------------------------------------------------------------------------------
# Ref: the vector-neuron point network (reference form)


class _BN(nn.Module):
    """Holds a BatchNorm's tensors under the name `bn` (upstream's VNBatchNorm wrapper)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.bn = nn.BatchNorm1d(channels)

    def normalise(self, v: torch.Tensor) -> torch.Tensor:
        """Eval-mode BatchNorm of `v (..., C)` with the running statistics."""
        bn = self.bn
        return (v - bn.running_mean) / torch.sqrt(bn.running_var + bn.eps) * bn.weight + bn.bias


class VNLinearLeakyReLU(nn.Module):
    """Vector-neuron linear map + norm BatchNorm + vector leaky ReLU on `(..., C, 3)` features."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.map_to_feat = nn.Linear(cin, cout, bias=False)
        self.batchnorm = _BN(cout)
        self.map_to_dir = nn.Linear(cin, cout, bias=False)
        self.cout = cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = torch.einsum("oc,...ck->...ok", self.map_to_feat.weight, x)
        if self.cout != 1:  # upstream skips the norm BatchNorm for a single channel
            norm = torch.linalg.vector_norm(p, dim=-1) + EPS_VN
            p = p / norm.unsqueeze(-1) * self.batchnorm.normalise(norm).unsqueeze(-1)
        d = torch.einsum("oc,...ck->...ok", self.map_to_dir.weight, x)
        dot = (p * d).sum(-1, keepdim=True)
        keep = (dot >= 0).float()
        dsq = (d * d).sum(-1, keepdim=True)
        return SLOPE * p + (1 - SLOPE) * (keep * p + (1 - keep) * (p - dot / (dsq + EPS_VN) * d))


class _Conv(nn.Module):
    """First block (`conv` only)."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.conv = VNLinearLeakyReLU(cin, cout)


class _Resnet(nn.Module):
    """Residual block: `conv` (neighbourhood), `unary`, `unary_shortcut`."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.conv = VNLinearLeakyReLU(cin + 1, cout // 2)
        self.unary = VNLinearLeakyReLU(cout // 2, cout)
        self.unary_shortcut = VNLinearLeakyReLU(cin, cout)


class _Mlp(nn.Module):
    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.mlp = VNLinearLeakyReLU(cin, cout)


class _StdFeature(nn.Module):
    """The invariant head's parameters (upstream `VNStdFeature`); not used for the axis."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.vn1 = VNLinearLeakyReLU(c, c)
        self.vn2 = VNLinearLeakyReLU(c, c // 2)
        self.vn_lin = nn.Linear(c // 2, 3, bias=False)


def _neighbourhood(
    x: torch.Tensor, q: torch.Tensor, s: torch.Tensor, idx: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Neighbour features `(Q, K, C, 3)` (shadow rows zero) and centred neighbour offsets `(Q, K, 3)`."""
    s_pad = torch.cat([s, torch.full_like(s[:1], 1e6)], 0)
    nb = s_pad[idx]
    fake = nb == 1e6
    nb = torch.where(fake, q[:, None, :].expand_as(nb), nb)
    x_pad = torch.cat([x, torch.zeros_like(x[:1])], 0)
    return x_pad[idx], nb - q[:, None, :]


class RefReference(nn.Module):
    """BUFFER's `Ref` (EFCNN): a KPConv-style U-Net of vector-neuron layers that regresses one axis a point.

    Architecture (first_feats_dim 32 -> 10 vector channels, input = the oriented normal, 1 channel):
    first block (mode 6: neighbour normal, offset, their cross product, mean offset) -> strided residual
    -> residual -> strided residual -> residual -> nearest upsample + skip -> VN -> nearest upsample +
    skip -> VN -> two VN layers to 1 vector channel = the axis. Mean pooling over the K neighbour slots,
    shadow slots included (so the neighbour limits K_l are part of the model).
    """

    def __init__(self) -> None:
        super().__init__()
        self.epsilon = nn.Parameter(torch.tensor(-5.0))
        self.encoder_blocks = nn.ModuleList(
            [_Conv(4, 10), _Resnet(10, 10), _Resnet(10, 20), _Resnet(20, 20), _Resnet(20, 40)]
        )
        self.decoder_blocks = nn.ModuleList([nn.Identity(), _Mlp(60, 20), nn.Identity(), _Mlp(30, 10)])
        self.fc_layer = nn.Sequential(VNLinearLeakyReLU(10, 5), VNLinearLeakyReLU(5, 1))
        self.inv_layer = nn.Sequential(
            _StdFeature(10),
            nn.Conv1d(30, 20, 1),
            nn.InstanceNorm1d(20),
            nn.Conv1d(20, 10, 1),
            nn.InstanceNorm1d(10),
            nn.Conv1d(10, 1, 1),
            nn.Sigmoid(),
        )

    @staticmethod
    def _conv_pool(block: nn.Module, x, q, s, idx, first: bool) -> torch.Tensor:
        nx, eqv = _neighbourhood(x, q, s, idx)
        parts = [nx, eqv[:, :, None, :]]
        if first:
            cross = torch.linalg.cross(nx[:, :, 0, :], eqv, dim=-1)
            mean = eqv.mean(1, keepdim=True).expand_as(eqv)
            parts += [cross[:, :, None, :], mean[:, :, None, :]]
        return block.conv(torch.cat(parts, 2)).mean(1)

    def _resnet(self, i: int, x, q, s, idx, strided: bool) -> torch.Tensor:
        block = self.encoder_blocks[i]
        y = block.unary(self._conv_pool(block, x, q, s, idx, first=False))
        if strided:
            x_pad = torch.cat([x, torch.zeros_like(x[:1])], 0)
            shortcut = x_pad[idx].max(dim=1).values
        else:
            shortcut = x
        return y + block.unary_shortcut(shortcut)

    def forward(self, batch: dict) -> torch.Tensor:
        """`batch`: normals, points [3], neighbors [3], pools [2], upsamples [2] (index matrices)."""
        p, nb, pools, ups = batch["points"], batch["neighbors"], batch["pools"], batch["upsamples"]
        x = batch["normals"][:, None, :]
        x = self._conv_pool(self.encoder_blocks[0], x, p[0], p[0], nb[0], first=True)
        skips = [x]
        x = self._resnet(1, x, p[1], p[0], pools[0], strided=True)
        x = self._resnet(2, x, p[1], p[1], nb[1], strided=False)
        skips.append(x)
        x = self._resnet(3, x, p[2], p[1], pools[1], strided=True)
        x = self._resnet(4, x, p[2], p[2], nb[2], strided=False)
        for up, dec in ((ups[1], self.decoder_blocks[1]), (ups[0], self.decoder_blocks[3])):
            x_pad = torch.cat([x, torch.zeros_like(x[:1])], 0)
            x = x_pad[up[:, 0]]
            x = dec.mlp(torch.cat([x, skips.pop()], 1))
        return self.fc_layer(x)[:, 0, :]


# ----------------------------------------------------------------------------------------------------
# Ref: export form


def _fold_vn(layer: VNLinearLeakyReLU) -> dict:
    bn = layer.batchnorm.bn
    a = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    return {
        "wf": layer.map_to_feat.weight.detach().t().contiguous(),
        "wd": layer.map_to_dir.weight.detach().t().contiguous(),
        "a": a.detach(),
        "b": (bn.bias - bn.running_mean * a).detach(),
        "bn": layer.cout != 1,
    }


class _VN(nn.Module):
    """VNLinearLeakyReLU on `(..., 3, C)` features, BatchNorm folded to one scale and shift."""

    def __init__(self, layer: VNLinearLeakyReLU) -> None:
        super().__init__()
        f = _fold_vn(layer)
        self.register_buffer("wf", f["wf"])
        self.register_buffer("wd", f["wd"])
        self.register_buffer("a", f["a"])
        self.register_buffer("b", f["b"])
        self.bn = f["bn"]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = torch.matmul(x, self.wf)
        if self.bn:
            norm = torch.sqrt((p * p).sum(-2, keepdim=True)) + EPS_VN
            p = p * ((norm * self.a + self.b) / norm)
        d = torch.matmul(x, self.wd)
        dot = (p * d).sum(-2, keepdim=True)
        dsq = (d * d).sum(-2, keepdim=True)
        neg = (dot < 0).to(p.dtype)
        return p - (1 - SLOPE) * neg * (dot / (dsq + EPS_VN)) * d


def _cross_last(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


class RefExport(nn.Module):
    """`RefReference` for ONNX: vectors as (N, 3, C); inputs as listed in the module docstring."""

    def __init__(self, ref: RefReference) -> None:
        super().__init__()
        enc = ref.encoder_blocks
        self.first = _VN(enc[0].conv)
        self.res = nn.ModuleList(
            [
                nn.ModuleList([_VN(enc[i].conv), _VN(enc[i].unary), _VN(enc[i].unary_shortcut)])
                for i in (1, 2, 3, 4)
            ]
        )
        self.dec1 = _VN(ref.decoder_blocks[1].mlp)
        self.dec3 = _VN(ref.decoder_blocks[3].mlp)
        self.fc0 = _VN(ref.fc_layer[0])
        self.fc1 = _VN(ref.fc_layer[1])

    @staticmethod
    def _gather(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        return torch.cat([x, torch.zeros_like(x[:1])], 0)[idx]

    @staticmethod
    def _offsets(q: torch.Tensor, s: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """(Q, K, 3, 1) neighbour offsets, zero for shadow slots."""
        valid = (idx < s.shape[0]).to(q.dtype).unsqueeze(-1)
        s_pad = torch.cat([s, torch.zeros_like(s[:1])], 0)
        return ((s_pad[idx] - q.unsqueeze(1)) * valid).unsqueeze(-1)

    def _block(self, i: int, x, q, s, idx, strided: bool) -> torch.Tensor:
        conv, unary, shortcut = self.res[i]
        inp = torch.cat([self._gather(x, idx), self._offsets(q, s, idx)], -1)
        y = unary(conv(inp).mean(1))
        sc = self._gather(x, idx).amax(1) if strided else x
        return y + shortcut(sc)

    def forward(self, normals, points0, points1, points2, neighbors0, neighbors1, neighbors2, pools0, pools1,
                upsamples0, upsamples1):  # fmt: skip
        n = self._gather(normals, neighbors0)  # (N, K, 3)
        e = self._offsets(points0, points0, neighbors0)[..., 0]
        cross = _cross_last(n, e)
        mean = e.mean(1, keepdim=True).expand_as(e)
        x = self.first(torch.stack([n, e, cross, mean], -1)).mean(1)  # (N0, 3, 10)
        s0 = x
        x = self._block(0, x, points1, points0, pools0, True)
        x = self._block(1, x, points1, points1, neighbors1, False)
        s1 = x
        x = self._block(2, x, points2, points1, pools1, True)
        x = self._block(3, x, points2, points2, neighbors2, False)
        x = self.dec1(torch.cat([self._gather(x, upsamples1), s1], -1))
        x = self.dec3(torch.cat([self._gather(x, upsamples0), s0], -1))
        return self.fc1(self.fc0(x))[..., 0]


# ----------------------------------------------------------------------------------------------------
# Desc: the cylindrical patch descriptor (MiniSpinNet), reference form


def azimuth_rotations() -> np.ndarray:
    """(AZI_N, 3, 3) float64: rotation about z by -i * 2 pi / AZI_N (upstream `var_to_invar`)."""
    out = np.zeros((AZI_N, 3, 3))
    for i in range(AZI_N):
        t = -i * 2 * np.pi / AZI_N
        out[i] = [[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]]
    return out


def cell_centres(radius: float = 1.0) -> np.ndarray:
    """(CELLS, 3) float64 centres of the cylindrical-spherical cells, radial-major then elevation, azimuth."""
    beta = np.linspace(0, np.pi, ELE_N, endpoint=False) + np.pi / ELE_N / 2
    alpha = np.linspace(0, 2 * np.pi, AZI_N, endpoint=False) + np.pi / AZI_N
    b, a = np.meshgrid(beta, alpha, indexing="ij")
    unit = np.stack([np.sin(b) * np.cos(a), np.sin(b) * np.sin(a), np.cos(b)], -1).reshape(-1, 3) * radius
    shells = np.arange(RAD_N) / RAD_N + 1 / (2 * RAD_N)
    return (shells[:, None, None] * unit[None]).reshape(-1, 3)


class _ConvNet(nn.Module):
    """Holds `ops` exactly as upstream's Cylindrical_Net (BatchNorm without affine parameters)."""

    def __init__(self) -> None:
        super().__init__()
        ops: list[nn.Module] = [nn.Conv3d(16, 64, 3), nn.BatchNorm3d(64, affine=False), nn.ReLU()]
        chans = [64, 64, 128, 128, 64, 64, 32, 32]
        for i in range(7):
            ops.append(nn.Conv2d(chans[i], chans[i + 1], 3))
            if i < 6:
                ops += [nn.BatchNorm2d(chans[i + 1], affine=False), nn.ReLU()]
        self.ops = nn.ModuleList(ops)


def _pad_circular_azimuth(x: torch.Tensor) -> torch.Tensor:
    """Azimuth (last axis) wraps by one column; elevation (axis -2) gets one zero row each side."""
    x = torch.cat([x[..., -1:], x, x[..., :1]], -1)
    z = torch.zeros_like(x[..., :1, :])
    return torch.cat([z, x, z], -2)


class DescReference(nn.Module):
    """BUFFER's `Desc` (MiniSpinNet) from the grouped cells on: per-azimuth rotation into each cell's
    frame, shared point MLP 3->16 and max over the 10 points, cylindrical CNN (3-D conv over radius,
    then 2-D convs with circular azimuth padding), attention-weighted average over the cylinder, L2
    normalisation. Parameter names as the published state dict."""

    def __init__(self) -> None:
        super().__init__()
        self.pnt_layer = nn.Sequential(nn.Conv2d(3, 16, 1), nn.BatchNorm2d(16), nn.ReLU())
        self.pool_layer = nn.Sequential(
            nn.Conv2d(32, 16, 1),
            nn.BatchNorm2d(16),
            nn.ReLU(),
            nn.Conv2d(16, 1, 1),
            nn.BatchNorm2d(1),
            nn.ReLU(),
        )
        self.conv_net = _ConvNet()

    def forward(self, grouped: torch.Tensor) -> torch.Tensor:
        m = grouped.shape[0]
        x = grouped.reshape(m, RAD_N, ELE_N, AZI_N, SAMPLES, 3)
        rot = torch.from_numpy(azimuth_rotations()).float().view(1, 1, 1, AZI_N, 3, 3)
        x = torch.matmul(x, rot.transpose(-1, -2))
        x = x.reshape(m, CELLS, SAMPLES, 3).permute(0, 3, 1, 2)
        x = self.pnt_layer(x)
        x = F.max_pool2d(x, kernel_size=(1, SAMPLES)).squeeze(3)
        x = x.view(m, 16, RAD_N, ELE_N, AZI_N)
        for op in self.conv_net.ops:
            if isinstance(op, nn.Conv3d):
                x = _pad_circular_azimuth(x)
            elif isinstance(op, nn.Conv2d):
                if x.dim() == 5:
                    x = x.squeeze(2)
                x = _pad_circular_azimuth(x)
            x = op(x)
        w = self.pool_layer(x)
        f = F.avg_pool2d(x * w, kernel_size=(x.shape[2], x.shape[3]))
        return F.normalize(f.view(m, -1), p=2, dim=1)


# ----------------------------------------------------------------------------------------------------
# Desc: export form


def _fold_bn(conv_w, conv_b, bn) -> tuple[torch.Tensor, torch.Tensor]:
    scale = 1.0 / torch.sqrt(bn.running_var + bn.eps)
    if bn.affine:
        scale = scale * bn.weight
    bias = (conv_b - bn.running_mean) * scale + (bn.bias if bn.affine else 0.0)
    shape = (-1,) + (1,) * (conv_w.dim() - 1)
    return (conv_w * scale.view(shape)).detach(), bias.detach()


class DescExport(nn.Module):
    """`DescReference` for ONNX: each cell's azimuth rotation folded into its point-MLP weights (one GEMM
    a cell), the max over the cell's points taken before bias and ReLU, BatchNorm folded, the 3-D radial
    convolution as a 2-D convolution over (channel x radius), elevation zero padding inside Conv."""

    def __init__(self, ref: DescReference) -> None:
        super().__init__()
        rot = torch.from_numpy(azimuth_rotations()[np.tile(np.arange(AZI_N), RAD_N * ELE_N)])
        w, b = _fold_bn(ref.pnt_layer[0].weight, ref.pnt_layer[0].bias, ref.pnt_layer[1])
        # rotate-then-project folded into one (3, 16) map per cell: (R_v p) . w = p . (R_v^T w)
        per_cell = torch.einsum("vji,jc->vic", rot, w.view(16, 3).t().double())
        self.register_buffer("pnt_w", per_cell.float().contiguous())  # (CELLS, 3, 16)
        self.register_buffer("pnt_b", b.view(1, 1, 16))
        ops = ref.conv_net.ops
        convs = [op for op in ops if isinstance(op, nn.Conv2d | nn.Conv3d)]
        bns = [op for op in ops if isinstance(op, nn.BatchNorm2d | nn.BatchNorm3d)]
        self.convs = nn.ModuleList()
        for i, conv in enumerate(convs):
            if i < len(bns):
                w, b = _fold_bn(conv.weight, conv.bias, bns[i])
            else:
                w, b = conv.weight.detach(), conv.bias.detach()
            if w.dim() == 5:  # (64, 16, r, e, a) -> (64, 16 * r, e, a): radius folded into channels
                w = w.reshape(w.shape[0], -1, 3, 3)
            c = nn.Conv2d(w.shape[1], w.shape[0], 3, padding=(1, 0))
            c.weight.data.copy_(w)
            c.bias.data.copy_(b)
            self.convs.append(c)
        p = ref.pool_layer
        w1, b1 = _fold_bn(p[0].weight, p[0].bias, p[1])
        w2, b2 = _fold_bn(p[3].weight, p[3].bias, p[4])
        self.pool1 = nn.Conv2d(32, 16, 1)
        self.pool2 = nn.Conv2d(16, 1, 1)
        for c, w, b in ((self.pool1, w1, b1), (self.pool2, w2, b2)):
            c.weight.data.copy_(w)
            c.bias.data.copy_(b)

    def forward(self, grouped: torch.Tensor) -> torch.Tensor:
        m = grouped.shape[0]
        g = grouped.reshape(m, CELLS, SAMPLES * 3).transpose(0, 1).reshape(CELLS, -1, 3)
        f = torch.matmul(g, self.pnt_w).reshape(CELLS, m, SAMPLES, 16)  # one GEMM per cell
        f = torch.relu(f.amax(2) + self.pnt_b)  # max before bias + ReLU (both monotone): (CELLS, M, 16)
        h = f.permute(1, 2, 0).reshape(m, 16 * RAD_N, ELE_N, AZI_N)
        last = len(self.convs) - 1
        for i, conv in enumerate(self.convs):
            h = conv(torch.cat([h[..., -1:], h, h[..., :1]], -1))
            if i < last:
                h = torch.relu(h)
        w = torch.relu(self.pool2(torch.relu(self.pool1(h))))
        d = (h * w).mean((2, 3))
        return d / torch.clamp(torch.linalg.vector_norm(d, dim=1, keepdim=True), min=1e-12)
