"""ResUNetBN2C in plain torch over precomputed kernel maps (fcgf_maps.py): the reference the ONNX model is
held to, and what a checkpoint's weights are checked with. Sparse convolution is a gather-GEMM-scatter per
kernel offset (`sparse_conv`); the dtype follows the parameters (float64 for the exactness tests)."""

from __future__ import annotations

import numpy as np
import torch

from fastmac_exp.descriptors.fcgf_maps import KernelMap, UNetMaps
from fastmac_exp.descriptors.fcgf_plan import BN_EPS, NetConfig, expected_shapes, resunet


def sparse_conv(x: torch.Tensor, kernel: torch.Tensor, kmap: KernelMap) -> torch.Tensor:
    """out[o] = sum over offsets k and pairs (i, o) of k: x[i] @ kernel[k]; kernel (K, in, out)."""
    if kernel.shape[0] != kmap.volume:
        raise ValueError(f"kernel of {kernel.shape[0]} offsets for a map of {kmap.volume}")
    gathered = x.index_select(0, torch.from_numpy(kmap.in_rows))
    b = kmap.bounds.tolist()
    products = torch.cat([gathered[b[k] : b[k + 1]] @ kernel[k] for k in range(kmap.volume)])
    out = x.new_zeros((kmap.n_out, kernel.shape[2]))
    return out.index_add_(0, torch.from_numpy(kmap.out_rows), products)


class TorchOps:
    """The plan's operations on torch tensors, with the module's parameters and one cloud's maps."""

    def __init__(self, params: dict[str, torch.Tensor], maps: UNetMaps) -> None:
        self.p, self.maps = params, maps

    def _map(self, kmap, transposed):
        m = self.maps.conv1 if kmap[0] == "conv1" else getattr(self.maps, kmap[0])[kmap[1]]
        return m.transposed() if transposed else m

    def conv(self, key, x, out, kmap, transposed=False):
        return sparse_conv(x, self.p[f"{key}.kernel"], self._map(kmap, transposed))

    def linear(self, key, x, out, bias):
        y = x @ self.p[f"{key}.kernel"].reshape(x.shape[1], out)
        return y + self.p[f"{key}.bias"].reshape(1, out) if bias else y

    def bn(self, key, x):  # eval mode, spelled out so that it is differentiable in every statistic
        g = lambda n: self.p[f"{key}.bn.{n}"]  # noqa: E731
        return (x - g("running_mean")) / torch.sqrt(g("running_var") + BN_EPS) * g("weight") + g("bias")

    def relu(self, x):
        return torch.relu(x)

    def add(self, a, b):
        return a + b

    def cat(self, a, b):
        return torch.cat([a, b], dim=1)

    def normalize(self, x):
        return x / torch.norm(x, p=2, dim=1, keepdim=True)  # FCGF's formula (no epsilon)


class ResUNetBN2C(torch.nn.Module):
    """The network with FCGF's state_dict keys and shapes (1x1 kernels 2-D, as ME 0.5 stores them;
    `fcgf_checkpoint.normalized_state_dict` brings older checkpoints' (1, in, out) to that). Eval only."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self._names = {}
        for key, shape in expected_shapes(cfg).items():
            name = key.replace(".", "__")
            self._names[key] = name
            if key.endswith("num_batches_tracked"):
                self.register_buffer(name, torch.zeros((), dtype=torch.long))
            elif key.endswith(("running_mean", "running_var")):
                self.register_buffer(name, torch.zeros(shape))
            else:
                self.register_parameter(name, torch.nn.Parameter(torch.zeros(shape), requires_grad=False))

    def state_dict_fcgf(self) -> dict[str, torch.Tensor]:
        own = dict(self.named_parameters()) | dict(self.named_buffers())
        return {key: own[name] for key, name in self._names.items()}

    def load_fcgf(self, state: dict[str, torch.Tensor]) -> None:
        """Copy FCGF-keyed tensors (shapes as `expected_shapes`) into the module."""
        own = self.state_dict_fcgf()
        with torch.no_grad():
            for key, t in own.items():
                t.copy_(torch.as_tensor(state[key]).reshape(t.shape))

    @torch.no_grad()
    def forward(self, feats: torch.Tensor, maps: UNetMaps) -> torch.Tensor:
        return resunet(TorchOps(self.state_dict_fcgf(), maps), feats, self.cfg)


def torch_features(model: ResUNetBN2C, feats: np.ndarray, maps: UNetMaps) -> np.ndarray:
    dtype = next(model.parameters()).dtype
    return model(torch.as_tensor(feats, dtype=dtype), maps).numpy()
