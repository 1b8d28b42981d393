"""benchmarks/bench_search.py: the case names it accepts and the graph structure it reports."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_search.py"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        spec = importlib.util.spec_from_file_location("bench_search", SCRIPT)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(SCRIPT.parent))


def test_case_names_parse_and_bad_ones_say_what_is_wrong(bench):
    assert bench.parse_case("syn:kitti_003@100") == ("syn", "kitti_003", 1.0)
    assert bench.parse_case("big:2%@5") == ("big", "2%", 0.05)
    for bad in ("kitti_003", "syn:kitti_003", "web:x@20", "syn:kitti_003@0", "syn:kitti_003@150"):
        with pytest.raises(SystemExit, match="case"):
            bench.parse_case(bad)


def test_structure_of_a_hand_made_near_clique(bench):
    # 7 nodes with edges (node 7 has none): K7 on 0..6 minus the conflicts 0-1, 1-2 (one component of 3
    # nodes) and 4-5 (a second one); 3 and 6 are adjacent to all others.
    missing = {(0, 1), (1, 2), (4, 5)}
    edges = [(a, b) for a in range(7) for b in range(a + 1, 7) if (a, b) not in missing]
    i, j = (np.array(x, dtype=np.int64) for x in zip(*edges))
    graph = {"n": np.int64(8), "i": i, "j": j, "w": np.ones(len(i))}
    assert bench.structure(graph) == {
        "nodes": 7,
        "edges": 21 - 3,
        "universal": 2,
        "conflicts": 3,
        "components": 2,
        "largest": 3,
    }


def test_times_the_search_on_a_graph(bench):
    from fastmac_exp import core

    if not core.available():
        pytest.skip("C++ core not built")
    i, j = np.triu_indices(6, 1)
    graph = {"n": np.int64(6), "i": i.astype(np.int64), "j": j.astype(np.int64), "w": np.ones(len(i))}
    r = bench.time_search(graph, "bnb", 1_000_000, reps=1, threads=1)
    assert r["selected"] == 1 and r["cap"] == "" and r["nodes"] > 0
