"""ResUNetBN2C as an ONNX graph for onnxruntime (CPU or CUDA): the plan of fcgf_plan.py emitted node by node
from a checked state dict, with the kernel maps as graph inputs (computed in numpy, fcgf_maps.py).

Inputs: `feats` (N, 1) float32; `sizes` (4,) int64, the rows of each level; `conv1_table` (N, k^3) int64,
conv1's input row of each voxel and offset (N where there is none: an appended zero row), so conv1 is one
gather and one GEMM; and per 3x3x3 map (`same0..3` at stride 1, 2, 4, 8; `down0..2` from level l to l + 1)
`<map>_in`, `<map>_out` (P,) int64 and `<map>_bounds` (28,) int64, the pairs grouped by offset. A
convolution gathers its input rows once, multiplies each offset's slice by that offset's weight, and
scatter-adds the products onto its output rows (ScatterND, reduction add); a transposed one swaps in and out.
Output `features` (N, D). The model's metadata carries `fastmac.preprocess = fcgf` and the checkpoint's
shape, voxel size and sha256 (`fcgf.*`).
"""

from __future__ import annotations

import numpy as np

from fastmac_exp.descriptors.fcgf_maps import UNetMaps
from fastmac_exp.descriptors.fcgf_plan import BN_EPS, NetConfig, resunet

OPSET = 17
MAPS = ("same0", "same1", "same2", "same3", "down0", "down1", "down2")


def _map_tag(kmap) -> str:
    return "conv1" if kmap[0] == "conv1" else f"{kmap[0]}{kmap[1]}"


def _out_level(kmap, transposed: bool) -> int:
    if kmap[0] in ("conv1", "same"):
        return 0 if kmap[0] == "conv1" else kmap[1]
    return kmap[1] if transposed else kmap[1] + 1


class OnnxOps:
    """The plan's operations as ONNX nodes; values are tensor names."""

    def __init__(self, state: dict[str, np.ndarray], cfg: NetConfig) -> None:
        from onnx import TensorProto, helper, numpy_helper

        self.h, self.nh, self.tp = helper, numpy_helper, TensorProto
        self.state, self.cfg = state, cfg
        self.nodes, self.inits, self.inputs = [], [], []
        self._n = 0
        self._bounds: dict[str, list[str]] = {}
        self._dst_rows: dict[str, list[str]] = {}

    def _name(self, stem: str) -> str:
        self._n += 1
        return f"{stem}_{self._n}"

    def node(self, op: str, inputs: list[str], stem: str | None = None, **attrs) -> str:
        out = self._name(stem or op.lower())
        self.nodes.append(self.h.make_node(op, inputs, [out], **attrs))
        return out

    def const(self, array: np.ndarray, stem: str) -> str:
        name = self._name(stem)
        self.inits.append(self.nh.from_array(np.ascontiguousarray(array), name))
        return name

    def graph_input(self, name: str, elem, shape) -> str:
        self.inputs.append(self.h.make_tensor_value_info(name, elem, shape))
        return name

    def _offset_bounds(self, tag: str) -> list[str]:
        """The names of (1,) tensors start_0 .. start_27 of a map's offsets, sliced once from its bounds."""
        if tag not in self._bounds:
            b = self.graph_input(f"{tag}_bounds", self.tp.INT64, [28])
            self.graph_input(f"{tag}_in", self.tp.INT64, ["P_" + tag])
            self.graph_input(f"{tag}_out", self.tp.INT64, ["P_" + tag])
            self._bounds[tag] = [
                self.node("Slice", [b, self.const(np.array([k]), "k"), self.const(np.array([k + 1]), "k1")])
                for k in range(28)
            ]
        return self._bounds[tag]

    def _zeros_rows(self, level: int, channels: int) -> str:
        i = self.const(np.array([level]), "lv")
        rows = self.node("Slice", ["sizes", i, self.const(np.array([level + 1]), "lv1")])
        shape = self.node("Concat", [rows, self.const(np.array([channels]), "ch")], axis=0)
        value = self.h.make_tensor("zero", self.tp.FLOAT, [1], [0.0])
        return self.node("ConstantOfShape", [shape], "zeros", value=value)

    def conv(self, key, x, out, kmap, transposed=False):
        w = self.state[f"{key}.kernel"]
        if kmap[0] == "conv1":
            k3, cin = w.shape[0], w.shape[1]
            pad = self.node("Concat", [x, self.const(np.zeros((1, cin), np.float32), "pad")], axis=0)
            cols = self.node("Gather", [pad, "conv1_table"], axis=0)
            cols = self.node("Reshape", [cols, self.const(np.array([-1, k3 * cin]), "shape")])
            return self.node("MatMul", [cols, self.const(w.reshape(k3 * cin, out), key)])
        tag = _map_tag(kmap)
        starts = self._offset_bounds(tag)
        src, dst = (f"{tag}_out", f"{tag}_in") if transposed else (f"{tag}_in", f"{tag}_out")
        gathered = self.node("Gather", [x, src], axis=0)
        rows = self._rows(dst, starts)
        axis0 = self.const(np.array([0]), "axis")
        acc = self._zeros_rows(_out_level(kmap, transposed), out)
        for k in range(w.shape[0]):
            part = self.node("Slice", [gathered, starts[k], starts[k + 1], axis0])
            y = self.node("MatMul", [part, self.const(w[k], f"{key}_k{k}")])
            # one offset's output rows are distinct: a scatter-add per offset has no write races (one over
            # all offsets, with repeated rows, gives thread-dependent sums in onnxruntime 1.32's CPU kernel)
            acc = self.node("ScatterND", [acc, rows[k], y], reduction="add")
        return acc

    def _rows(self, dst: str, starts: list[str]) -> list[str]:
        """Per offset, the (n_k, 1) output rows of `dst` (a map's `_in` or `_out`), sliced once."""
        if dst not in self._dst_rows:
            col = self.node("Unsqueeze", [dst, self.const(np.array([1]), "axes")])
            axis0 = self.const(np.array([0]), "axis")
            self._dst_rows[dst] = [
                self.node("Slice", [col, starts[k], starts[k + 1], axis0]) for k in range(len(starts) - 1)
            ]
        return self._dst_rows[dst]

    def linear(self, key, x, out, bias):
        w = self.state[f"{key}.kernel"].reshape(-1, out)
        y = self.node("MatMul", [x, self.const(w, key)])
        return (
            self.node("Add", [y, self.const(self.state[f"{key}.bias"].reshape(1, out), key + "_b")])
            if bias
            else y
        )

    def bn(self, key, x):
        g = lambda n: self.state[f"{key}.bn.{n}"].astype(np.float64)  # noqa: E731
        scale = g("weight") / np.sqrt(g("running_var") + BN_EPS)
        shift = g("bias") - g("running_mean") * scale
        y = self.node("Mul", [x, self.const(scale.astype(np.float32)[None], key + "_s")])
        return self.node("Add", [y, self.const(shift.astype(np.float32)[None], key + "_t")])

    def relu(self, x):
        return self.node("Relu", [x])

    def add(self, a, b):
        return self.node("Add", [a, b])

    def cat(self, a, b):
        return self.node("Concat", [a, b], axis=1)

    def normalize(self, x):
        norm = self.node("ReduceL2", [x], axes=[1], keepdims=1)  # axes an attribute until opset 18
        return self.node("Div", [x, norm])


def build_model(state: dict[str, np.ndarray], cfg: NetConfig, metadata: dict[str, str]):
    """The onnx.ModelProto of ResUNetBN2C with these weights (module docstring)."""
    from onnx import checker, helper

    ops = OnnxOps(state, cfg)
    feats = ops.graph_input("feats", ops.tp.FLOAT, ["N", cfg.in_channels])
    ops.graph_input("sizes", ops.tp.INT64, [4])
    ops.graph_input("conv1_table", ops.tp.INT64, ["N", cfg.conv1_kernel_size**3])
    out = resunet(ops, feats, cfg)
    ops.nodes.append(helper.make_node("Identity", [out], ["features"]))
    outputs = [helper.make_tensor_value_info("features", ops.tp.FLOAT, ["N", cfg.out_channels])]
    graph = helper.make_graph(ops.nodes, "fcgf_resunetbn2c", ops.inputs, outputs, ops.inits)
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="fastmac-exp"
    )
    model.ir_version = 8
    helper.set_model_props(model, metadata)
    checker.check_model(model)
    return model


def onnx_feeds(feats: np.ndarray, maps: UNetMaps, input_names) -> dict[str, np.ndarray]:
    """The graph inputs for one cloud (only those the model declares)."""
    feeds = {
        "feats": np.ascontiguousarray(feats, dtype=np.float32),
        "sizes": np.asarray(maps.sizes, dtype=np.int64),
        "conv1_table": maps.conv1_table,
    }
    for tag in MAPS:
        m = getattr(maps, tag[:-1])[int(tag[-1])]
        feeds[f"{tag}_in"], feeds[f"{tag}_out"], feeds[f"{tag}_bounds"] = m.in_rows, m.out_rows, m.bounds
    return {k: v for k, v in feeds.items() if k in set(input_names)}
