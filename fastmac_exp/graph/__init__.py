"""Compatibility graphs (spec 2.2-2.3) and the samplers' node signals (spec 7.2-7.3).

`numpy_graph` is the reference (sparse W and G), `torch_graph` FastMAC's dense formulation for a GPU,
and the C++ core (`fastmac_exp.core`) the fast path; `compute_signals` picks one of the three.
"""

from fastmac_exp.graph.numpy_graph import first_order, graph_signals, second_order, signals_from_graph
from fastmac_exp.graph.signals import ENGINES, GraphSignals, compute_signals

__all__ = [
    "ENGINES",
    "GraphSignals",
    "compute_signals",
    "first_order",
    "graph_signals",
    "second_order",
    "signals_from_graph",
]
