"""descriptors/: every recipe script answers `--help` from its place (run from another directory, as the
model cards write it: `python descriptors/<family>/<script>.py`), and every repository path or module that
the cards, the README, the descriptor configs and front ends name exists."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
RECIPES = [
    "descriptors/evaluate.py",
    "descriptors/buffer/export.py",
    "descriptors/buffer/quantize.py",
    "descriptors/buffer/bench.py",
    "descriptors/buffer/matched.py",
    "descriptors/spinnet/export.py",
    "descriptors/spinnet/bench.py",
    "descriptors/spinnet/describe_once.py",
    "descriptors/spinnet/agreement.py",
    "descriptors/spinnet/quantize.py",
    "descriptors/spinnet/keypoints_study.py",
    "descriptors/fcgf_lite/train.py",
]
# the texts that give commands or paths into descriptors/
TEXTS = [
    "README.md",
    "docs/descriptors.md",
    "docs/running.md",
    "docs/development.md",
    "descriptors/**/*.md",
    "descriptors/**/*.py",
    "conf/descriptor/*.yaml",
    "fastmac_exp/descriptors/*.py",
    "studies/text/*.md",
]
# repository paths (training/ is where the recipes were: any mention of it is stale)
ROOTS = "descriptors|training|benchmarks|studies|tests|fastmac_exp|conf"
PATH = re.compile(rf"(?<![\w/.-])((?:{ROOTS})/[\w./-]*\w\.(?:py|md|json|png|yaml))")
MODULE = re.compile(rf"python -m ((?:{ROOTS})(?:\.\w+)+)")


def test_every_recipe_with_a_command_line_is_listed():
    scripts = {
        str(p.relative_to(REPO))
        for p in (REPO / "descriptors").rglob("*.py")
        if "ArgumentParser(" in p.read_text()
    }
    assert scripts == set(RECIPES)


@pytest.mark.parametrize("script", RECIPES)
def test_recipe_answers_help_from_another_directory(script, tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run(
        [sys.executable, str(REPO / script), "--help"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("usage:"), done.stdout[:200]


def test_paths_and_modules_named_in_the_cards_and_readme_exist():
    texts = sorted({p for pattern in TEXTS for p in REPO.glob(pattern)})
    assert len(texts) > 10
    missing, seen = [], 0
    for f in texts:
        body = f.read_text()
        # inside the package, `descriptors/x.py` is the package's own folder (fastmac_exp/descriptors/)
        roots = [REPO, REPO / "fastmac_exp"] if f.is_relative_to(REPO / "fastmac_exp") else [REPO]
        for m in PATH.finditer(body):
            seen += 1
            if not any((root / m.group(1)).exists() for root in roots):
                missing.append(f"{f.relative_to(REPO)}: {m.group(1)}")
        for m in MODULE.finditer(body):
            seen += 1
            base = REPO / m.group(1).replace(".", "/")
            if not (base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()):
                missing.append(f"{f.relative_to(REPO)}: python -m {m.group(1)}")
    assert seen > 50
    assert not missing, "\n".join(missing)
