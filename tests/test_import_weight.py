"""`import fastmac_exp` stays light (issue 40: a one-shot user pays the first call): the heavy libraries
load where they are first needed, not at import."""

from __future__ import annotations

import subprocess
import sys

HEAVY = ("pandas", "scipy.stats", "scipy.spatial", "scipy.sparse", "scipy.linalg", "open3d", "torch", "wandb",
         "rerun", "onnxruntime", "matplotlib", "hydra")  # fmt: skip


def test_importing_the_package_loads_no_heavy_library():
    code = f"import sys, fastmac_exp; print(' '.join(m for m in {HEAVY!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "", f"import fastmac_exp loads {out.strip()}"
