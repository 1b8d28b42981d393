"""FCGF's ResUNetBN2C (Choy, Park, Koltun, ICCV 2019; chrischoy/FCGF model/resunet.py, MIT licence) as one
plan that each backend runs: the torch model (fcgf_torch.py), the ONNX graph builder (fcgf_onnx.py) and the
state-dict shape check (`expected_shapes`). Parameter names are FCGF's own state_dict keys, so a published
checkpoint loads as it is.

The network (eval mode): conv1 (kernel 5 or 7, no bias) -> norm1 -> block1 -> relu; three times a stride-2
3x3x3 convolution -> norm -> residual block -> relu (32, 64, 128, 256 channels at tensor strides 1, 2, 4,
8); then three transposed stride-2 convolutions -> norm -> block -> relu, each concatenated (decoder
channels first) with the encoder's output at its stride; conv1_tr (1x1) -> relu -> final (1x1, bias);
unit rows when the checkpoint says normalize_feature. A residual block is conv 3x3x3 -> BN -> relu ->
conv -> BN, plus its input, relu. Batch norm has eps 1e-5 (ME's MinkowskiBatchNorm default).
"""

from __future__ import annotations

from dataclasses import dataclass

CHANNELS = (32, 64, 128, 256)  # ResUNetBN2C's encoder
TR_CHANNELS = (64, 64, 64, 128)  # and decoder (TR_CHANNELS[1:] of FCGF)
BN_EPS = 1e-5
CONV1_KERNELS = (3, 5, 7)


@dataclass(frozen=True)
class NetConfig:
    """The shape of one ResUNetBN2C: input channels (1 for FCGF's occupancy input), conv1's kernel size,
    output channels (model_n_out) and whether the rows are L2-normalised."""

    in_channels: int = 1
    conv1_kernel_size: int = 7
    out_channels: int = 32
    normalize_feature: bool = True


def resunet(ops, x, cfg: NetConfig):
    """Run ResUNetBN2C with `ops` (see the backends) on input features `x` at tensor stride 1.

    Maps: ("conv1",) conv1's; ("same", l) the 3x3x3 maps at level l; ("down", l) the stride-2 maps from
    level l to l + 1, which a transposed convolution takes swapped (`transposed=True`)."""
    c1, c2, c3, c4 = CHANNELS
    t1, t2, t3, t4 = TR_CHANNELS

    def block(name, inp, channels, level):
        out = ops.conv(f"{name}.conv1", inp, channels, ("same", level))
        out = ops.relu(ops.bn(f"{name}.norm1", out))
        out = ops.bn(f"{name}.norm2", ops.conv(f"{name}.conv2", out, channels, ("same", level)))
        return ops.relu(ops.add(out, inp))

    def down(i, inp, channels):  # conv{i} -> norm{i} -> block{i}, from level i - 2 to i - 1
        out = ops.bn(f"norm{i}", ops.conv(f"conv{i}", inp, channels, ("down", i - 2)))
        return block(f"block{i}", out, channels, i - 1)

    def up(i, inp, channels):  # conv{i}_tr -> norm{i}_tr -> block{i}_tr -> relu, from level i - 1 to i - 2
        out = ops.conv(f"conv{i}_tr", inp, channels, ("down", i - 2), transposed=True)
        out = block(f"block{i}_tr", ops.bn(f"norm{i}_tr", out), channels, i - 2)
        return ops.relu(out)

    s1 = block("block1", ops.bn("norm1", ops.conv("conv1", x, c1, ("conv1",))), c1, 0)
    s2 = down(2, ops.relu(s1), c2)
    s4 = down(3, ops.relu(s2), c3)
    s8 = down(4, ops.relu(s4), c4)
    out = ops.cat(up(4, ops.relu(s8), t4), s4)
    out = ops.cat(up(3, out, t3), s2)
    out = ops.cat(up(2, out, t2), s1)
    out = ops.relu(ops.linear("conv1_tr", out, t1, bias=False))
    out = ops.linear("final", out, cfg.out_channels, bias=True)
    return ops.normalize(out) if cfg.normalize_feature else out


class ShapeOps:
    """A backend that runs the plan on channel counts and records every parameter's shape."""

    def __init__(self, cfg: NetConfig) -> None:
        self.cfg = cfg
        self.shapes: dict[str, tuple[int, ...]] = {}

    def conv(self, key, c, out, kmap, transposed=False):
        k = self.cfg.conv1_kernel_size if kmap == ("conv1",) else 3
        self.shapes[f"{key}.kernel"] = (k**3, c, out)
        return out

    def linear(self, key, c, out, bias):
        self.shapes[f"{key}.kernel"] = (c, out)  # ME >= 0.5 stores 1x1x1 kernels 2-D; older ones (1, c, out)
        if bias:
            self.shapes[f"{key}.bias"] = (1, out)
        return out

    def bn(self, key, c):
        for p in ("weight", "bias", "running_mean", "running_var"):
            self.shapes[f"{key}.bn.{p}"] = (c,)
        self.shapes[f"{key}.bn.num_batches_tracked"] = ()
        return c

    def relu(self, c):
        return c

    def add(self, a, b):
        if a != b:
            raise ValueError(f"residual of {a} and {b} channels")
        return a

    def cat(self, a, b):
        return a + b

    def normalize(self, c):
        return c


def expected_shapes(cfg: NetConfig) -> dict[str, tuple[int, ...]]:
    """FCGF's state_dict keys of a ResUNetBN2C and their shapes (1x1 kernels 2-D, as ME 0.5's)."""
    ops = ShapeOps(cfg)
    resunet(ops, cfg.in_channels, cfg)
    return ops.shapes
