"""`python run.py ...` with the C++ extension loaded from a private copy (docs/run_studies.sh uses it).

    FASTMAC_CORE_SO=outputs/studies/_core/_mac_core.so python docs/pinned_run.py -m +experiment=...

The editable install's extension lives in site-packages and is rewritten in place whenever anyone runs
`pip install -e .`; a sweep that has it loaded then crashes (SIGSEGV in _mac_core). Loading a copy made
once at the start of the studies keeps every sweep on the same core. Without FASTMAC_CORE_SO this is
`python run.py` plus the empty-clique shim below (a no-op once the core bug it works around is fixed).
"""

from __future__ import annotations

import importlib.util
import os
import runpy
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

so = os.environ.get("FASTMAC_CORE_SO")
if so:
    spec = importlib.util.spec_from_file_location("fastmac_exp._mac_core", so)
    if spec is None or spec.loader is None:
        raise SystemExit(f"FASTMAC_CORE_SO={so}: not an extension module")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    sys.modules["fastmac_exp._mac_core"] = module
    import fastmac_exp  # noqa: E402

    fastmac_exp._mac_core = module  # the attribute `from fastmac_exp import _mac_core` reads


def _empty_clique_shim() -> None:
    """Work around a core bug while it lasts: the peer backends (ransac, fgr, kiss_matcher) return an empty
    clique, and pipeline.check_not_degenerate takes max() of the empty point set, so every peer pair fails
    with ValueError. The shim skips the check for an empty set only; once the bug is fixed it does nothing."""
    import numpy as np

    from fastmac_exp import pipeline

    try:
        pipeline.check_not_degenerate(np.zeros((0, 3)), np.zeros((0, 3)))
    except ValueError:
        original = pipeline.check_not_degenerate

        def check(src: np.ndarray, tgt: np.ndarray) -> None:
            if len(src):
                original(src, tgt)

        pipeline.check_not_degenerate = check
        print("pinned_run: empty-clique shim active (peer backends)", file=sys.stderr)
    except Exception:  # noqa: BLE001 - any other outcome: the check handles empty sets itself
        pass


_empty_clique_shim()
sys.argv[0] = str(REPO / "run.py")
runpy.run_path(str(REPO / "run.py"), run_name="__main__")
