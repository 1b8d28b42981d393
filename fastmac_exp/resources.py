"""Files the package ships (the learned descriptors' ONNX models, the Hydra configs) and how a relative
path in a config finds them, so that an installed wheel works without the source tree."""

from __future__ import annotations

import os
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
MODELS_DIR = PACKAGE_DIR / "models"


def config_dir() -> Path:
    """The Hydra configs: inside the package in an installed wheel, the repository's conf/ in a checkout."""
    packaged = PACKAGE_DIR / "conf"
    return packaged if packaged.is_dir() else PACKAGE_DIR.parent / "conf"


def candidates(value: str | os.PathLike) -> list[Path]:
    """Where a path from a config may be: as given (absolute, or relative to the cwd), else relative to
    the package (`models/fcgf_lite.onnx` is the shipped model however the package was installed)."""
    p = Path(os.path.expanduser(str(value)))
    return [p] if p.is_absolute() else [p, PACKAGE_DIR / p]


def find_file(value: str | os.PathLike) -> Path | None:
    """The first existing file among `candidates(value)`, else None."""
    return next((c for c in candidates(value) if c.is_file()), None)


HOME_ENV = "FASTMAC_DATA"


def data_home() -> Path:
    """Where the user's data lives (fetched benchmarks, converted models): $FASTMAC_DATA, else the
    platform's user data directory of fastmac-exp (platformdirs)."""
    given = os.environ.get(HOME_ENV)
    if given:
        return Path(given).expanduser()
    import platformdirs

    return Path(platformdirs.user_data_dir("fastmac-exp", appauthor=False))
