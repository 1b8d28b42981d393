"""studies/: the paper's numbers in studies/paper agree with the paper's LaTeX and the README table the spec
quotes, and make_results renders a page from a small hand-made studies directory."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fastmac_exp.run.results import ResultsLog
from studies import common, make_results

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


# ---- the paper's numbers ----------------------------------------------------------------------------------
def _paper_tex() -> str:
    for f in sorted((SHARED / "paper").glob("*")):
        if f.is_file() and "FastMAC: Stochastic Spectral Sampling" in (t := f.read_text(errors="replace")):
            return t
    pytest.skip("the paper's LaTeX is not in ../shared/paper")


def _tex_table(tex: str, anchor: str) -> list[tuple[str, list[float]]]:
    """The rows of the table (\\begin{table} .. \\end{table}) around `anchor`: (name cell, the numbers of
    the other cells), one per line with a `&`; bold, underline, \\cite and \\multirow taken out."""
    at = tex.index(anchor)
    body = tex[tex.rindex("\\begin{table}", 0, at) : tex.index("\\end{table}", at)]
    rows = []
    for line in body.splitlines():
        if "&" not in line or "multicolumn" in line:  # a header row
            continue
        line = re.sub(
            r"\\cite\{[^}]*\}|\\multirow\{\d+\}\{\*\}|\\begin\{tabular\}\[c\]\{@\{\}c@\{\}\}", "", line
        )
        name, *cells = line.split("&")
        name = re.sub(r"\\(textbf|ul)|[{}]", "", name.split("\\\\")[0]).strip()
        nums = [float(m) for c in cells for m in re.findall(r"-?\d+(?:\.\d+)?", re.sub(r"\\\\.*", "", c))]
        if nums:  # else a header row
            rows.append((name, nums))
    return rows


def test_paper_profile_is_table_profile():
    rows = _tex_table(_paper_tex(), "\\label{tab:profile}")
    got = {n[0]: tuple(n[1:]) for _, n in rows}  # ratio (%) -> Sampling, GC, MCS, NCS, PE, Total
    assert set(got) == {100, 50, 20, 10, 5, 1}
    for pct, stages in got.items():
        assert common.PAPER_PROFILE[pct / 100] == pytest.approx(stages, abs=1e-9)
    assert common.PAPER_PROFILE[1.0][-1] == 961.312 and common.PAPER_PROFILE[0.05][0] == 14.99  # spot values


def test_paper_filter_is_table_filter():
    rows = _tex_table(_paper_tex(), "\\label{tab:filter}")
    assert len(rows) == 5
    for pct, cells in rows:  # ratio (%), then RR, RE, TE of high-pass, all-pass, low-pass
        for i, f in enumerate(("highpass", "allpass", "lowpass")):
            assert common.PAPER_FILTER[f][float(pct) / 100] == pytest.approx(
                cells[3 * i : 3 * i + 3], abs=1e-9
            )
    assert common.PAPER_FILTER["lowpass"][0.01] == (13.33, 3.516, 106.211)  # spot value, read in the .tex


@pytest.mark.parametrize(
    "bench,label", [("KITTI", "tab:kitti"), ("3DMatch", "tab:3dmatch"), ("3DLoMatch", "tab:3dlomatch")]
)
def test_paper_sota_is_the_fpfh_columns(bench, label):
    # (not `benchmark`: pytest-benchmark, where installed, owns that fixture name)
    names = {"mac": "MAC", "fastmac50": "FastMAC@50", "fastmac20": "FastMAC@20", "fgr": "FGR"}
    rows = dict(_tex_table(_paper_tex(), f"\\label{{{label}}}"))
    src = common.read_data(common.PAPER / "table_sota.csv")
    methods = src.loc[src["benchmark"].eq(bench) & src["source"].eq(label), "method"]
    assert len(methods) >= 3
    for m in methods:
        nums = rows[names[m]]  # FPFH RR, RE, TE, FCGF RR, RE, TE, Time (s)
        assert common.PAPER_SOTA[bench][m] == pytest.approx((*nums[:3], 1000 * nums[-1]), abs=1e-6)


def test_paper_ransac_is_the_appendix_table():
    rows = dict(
        _tex_table(_paper_tex(), "Comparison on RR, RE and TE with SOTA methods on the KITTI dataset")
    )
    for m, name in (("ransac1k", "RANSAC 1K"), ("ransac10k", "RANSAC 10K")):
        assert common.PAPER_SOTA["KITTI"][m] == pytest.approx(rows[name][-4:])  # RR, RE, TE, ms
    assert common.PAPER_SOTA["KITTI"]["ransac10k"] == (88.47, 1.15, 25.33, 158.4)  # spot value


def test_paper_rr_is_the_readme_table_of_the_spec():
    spec = SHARED / "spec" / "mac-fastmac-algorithm.md"
    if not spec.exists():
        pytest.skip("../shared/spec is absent")
    text = spec.read_text()
    table = text[text.index("FastMAC README, RR at ratios") :].split("\n\n")[1]
    got = {}
    for line in table.splitlines()[2:]:
        name, *vals = [c.strip() for c in line.strip("| ").split("|")]
        bench, desc = name.split()
        got[(bench, desc.lower())] = tuple(float(v) for v in vals)
    assert got == common.PAPER_RR
    assert common.PAPER_RR[("3DLoMatch", "fcgf")][4] == 51.49  # 5 %, spot value


# ---- make_results on a hand-made studies directory --------------------------------------------------------
def _run(directory: Path, rows: list[dict]) -> None:
    log = ResultsLog(directory)
    for i, r in enumerate(rows):
        log.append({"index": i, "protocol": "honest", "error": "", "cap_hit": "", "re_deg": 1.0, "te_cm": 5.0,
                    "n_in": 1000, "inliers_in": 50, "inlier_ratio_in": 0.05, "inlier_ratio_kept": 0.2,
                    "t_sampling_ms": 2.0, "t_total_ms": 10.0} | r)  # fmt: skip
    log.write_tables()


def _pairs(n: int, ok: int, **fields) -> list[dict]:
    """n pairs of which the first `ok` registered."""
    return [dict(pair=f"p{i}", success=i < ok, **fields) for i in range(n)]


@pytest.fixture(scope="module")
def page(tmp_path_factory) -> tuple[str, Path]:
    root = tmp_path_factory.mktemp("results")
    studies = root / "studies"
    base = dict(dataset="synthetic", descriptor="fpfh", backend="cpp")
    # sampling strategy, synthetic 3DMatch-like: 4 pairs x 2 seeds; MAC 4/4, at 5 % high-pass 4/4 and 3/4
    # (RR 87.5 ± 17.7), random 2/4 and 2/4, FPS 0/4
    sweep = studies / "sampling_strategy_3dmatch"
    for seed in (0, 1):
        _run(sweep / "mac" / str(seed), _pairs(4, 4, sampler="none", ratio=1.0, seed=seed, **base))
        rows = _pairs(4, 4 - seed, sampler="highpass", ratio=0.05, seed=seed, **base)
        rows += _pairs(4, 2, sampler="random", ratio=0.05, seed=seed, **base)
        rows += _pairs(4, 0, sampler="fps", ratio=0.05, seed=seed, **base)
        _run(sweep / "sweep" / str(seed), rows)
    # state of the art, real indoor: MAC 4/4 at 80 ms, FastMAC@20 3/4 at 20 ms, RANSAC 1k 1/4 (one failed)
    sota = studies / "state_of_the_art_real_indoor"
    real = dict(base, dataset="shared_real", seed=0)
    _run(sota / "mac", _pairs(4, 4, sampler="none", ratio=1.0, **real | {"t_total_ms": 80.0}))
    _run(sota / "f20", _pairs(4, 3, sampler="highpass", ratio=0.2, **real | {"t_total_ms": 20.0}))
    ransac = _pairs(4, 1, sampler="none", ratio=1.0, **real | {"backend": "ransac1k"})
    ransac[3]["error"] = "RegistrationFailed: no consensus"
    _run(sota / "ransac", ransac)
    md = make_results.make_results(studies, root / "docs")
    return md, root / "docs"


def _table_row(md: str, section: str, first_cell: str) -> list[str]:
    """The cells of the first table row starting with `first_cell` after the line `section`."""
    rest = md[md.index(section) :]
    line = next(ln for ln in rest.splitlines() if ln.startswith(f"| {first_cell} |"))
    return [c.strip() for c in line.strip("|").split("|")]


def test_make_results_puts_the_numbers_in_their_tables(page):
    md, docs = page
    assert (docs / "results.md").read_text() == md
    heading = "### 3dmatch: synthetic indoor (3DMatch-like) — 4 pairs × 2 seeds"
    assert _table_row(md, heading, "0.05") == ["0.05", "87.5 ± 17.7", "50.0 ± 0.0", "0.0 ± 0.0", "74.49"]
    assert _table_row(md, heading, "1")[1:] == ["100.0 ± 0.0"] * 3 + ["83.86"]
    assert _table_row(md, heading, "0.2")[1:] == ["–", "–", "–", "80.71"]  # not run; the paper's column stays
    sota = "### real_indoor: real indoor pairs (3DMatch/3DLoMatch fragments) — 4 pairs"
    mac = (
        "MAC | 100.0 | 1.00 | 5.00 | 80.0 | 0 | 83.90 | 2.11 | 6.80 | 914.0"  # ours, then the paper's 3DMatch
    )
    assert " | ".join(_table_row(md, sota, "MAC")) == mac
    assert _table_row(md, sota, "FastMAC@20")[:6] == ["FastMAC@20", "75.0", "1.00", "5.00", "20.0", "0"]
    assert _table_row(md, sota, "RANSAC 1k")[1:6] == ["25.0", "1.00", "5.00", "10.0", "1"]
    # the paper's tables are printed whatever ran
    assert _table_row(md, "Paper (KITTI, FCGF):", "0.01")[1:4] == ["71.89", "28.11", "13.33"]
    assert _table_row(md, "Paper (3DMatch, FCGF, GPU sampling):", "1")[-1] == "961.3"


def test_make_results_claims_notes_and_layout(page):
    md, docs = page
    assert "**How much data:** 3dmatch: 4 pairs × 2 seeds." in md
    assert "MAC's RR at ratio 1: 3dmatch 100.0 ± 0.0 %;" in md
    claims = md[md.index("## Where we agree") : md.index("## 1. Sampling strategy")]
    assert "- **High-pass beats random and FPS at 0.05** — synthetic: agrees 1 (of 1 data sets)" in claims
    assert (
        "  - 3dmatch (4 pairs × 2 seeds): high-pass 87.5 ± 17.7 vs random 50.0 ± 0.0, FPS 0.0 ± 0.0 → agrees"
        in claims
    )
    assert (
        "- **FastMAC@20 loses little RR against MAC (paper: KITTI 97.66 → 98.02 %, 3DMatch 83.90 → 80.71 %, "
        "3DLoMatch 40.88 → 34.31 %; agrees: at most the paper's loss plus one pair)** — real: agrees 1"
        in claims
    )
    assert "  - real_indoor (4 pairs, seed 0): RR 100.0 → 75.0 %, at 80.0 → 20.0 ms (4.0×) → agrees" in claims
    assert (
        "state of the art, real_indoor, RANSAC 1k: 1 failed pair(s), e.g. `RegistrationFailed: no consensus`"
        in md
    )
    sections = [ln for ln in md.splitlines() if ln.startswith("## ")]
    expected = ["## Summary", "## Where we agree", "## 1. Sampling strategy", "## 2. High-pass vs low-pass",
                "## 3. Degree signal", "## 4. Stochastic vs deterministic", "## 5. Descriptor robustness",
                "## 6. Time profile", "## 7. State of the art", "## Notes", "## What ran"]  # fmt: skip
    assert len(sections) == len(expected) and all(s.startswith(e) for s, e in zip(sections, expected))
    assert "$" not in md and "<!--" not in md
    assert sorted(p.name for p in (docs / "figures").glob("*.png")) == [
        "sampling_strategy.png",
        "state_of_the_art.png",
    ]
    assert sorted(p.name for p in (docs / "results").glob("*.csv")) == [
        "sampling_strategy_3dmatch.csv", "state_of_the_art_real_indoor.csv"]  # fmt: skip
    csv = pd.read_csv(docs / "results" / "sampling_strategy_3dmatch.csv")
    hp = csv[csv["sampler"].eq("highpass")].iloc[0]
    assert hp["RR"] == 87.5 and np.isclose(hp["RR_seed_std"], 17.67767)


def test_text_needs_every_placeholder():
    with pytest.raises(KeyError):
        common.text("header", machine="m", core="", counts="c")  # mac_rr missing
    lines = common.text("header", machine="M", core=" C.", counts="c", mac_rr="r")
    assert lines[:2] == ["# Results: the FastMAC paper's studies on this project", ""]
    assert lines[4].startswith("**Machine:** M; the two cores") and lines[4].endswith("each other. C.")


def test_descriptor_study_splices_section_5(tmp_path):
    """studies.descriptor_robustness: a strong descriptor (IR > 2x FPFH's) that keeps RR at 1 % while FPFH
    loses a pair -> the claim holds; per-pair inlier ratios; section 5 replaced, the rest kept."""
    from studies import descriptor_robustness

    studies, docs = tmp_path / "studies", tmp_path / "docs"
    base = dict(dataset="shared_real", backend="cpp", sampler="highpass", seed=0)
    rows = []
    for ratio in (1.0, 0.01):
        rows += _pairs(4, 4 if ratio == 1.0 else 3, descriptor="fpfh", ratio=ratio, **base)
        rows += _pairs(4, 4, descriptor="spinnet", ratio=ratio, **base | {"inlier_ratio_in": 0.2})
    _run(studies / "descriptor_robustness_real_indoor" / "0", rows)
    docs.mkdir()
    (docs / "results.md").write_text(
        "# R\n\n## 4. Before\n\nKEEP-4\n\n## 5. Old\n\nold text\n\n## 6. After\n\nKEEP-6\n"
    )
    descriptor_robustness.splice(studies, docs)
    md = (docs / "results.md").read_text()
    assert (
        "old text" not in md
        and "KEEP-4" in md
        and "KEEP-6" in md
        and md.index("## 5.") < md.index("## 6. After")
    )
    heading = "### real_indoor: real indoor pairs (3DMatch/3DLoMatch fragments) — 4 pairs"
    assert _table_row(md, heading, "0.01")[1:3] == ["75.0", "100.0"]
    assert _table_row(md, heading, "`p0`") == ["`p0`", "5.0", "20.0"]
    assert "Mean inlier ratio of the correspondences: fpfh 5.0 %, spinnet 20.0 %." in md
    assert "here: **holds**. RR at 100 % → 1 %: fpfh 100.0 → 75.0, spinnet 100.0 → 100.0" in md
    assert (docs / "figures" / "descriptor_robustness_indoor.png").is_file()


def test_descriptor_splice_replaces_its_claim_notes_and_counts_trust(tmp_path):
    """The splice replaces the descriptor claim in the recomputed list and the section's notes in the page's
    notes (the other claims and notes stay), and counts the `trusted` verdict against the GT: at ratio 0.2
    one wrong pose trusted (a false accept) and one right pose not (a false reject); failed rows have no
    pose and are not counted."""
    from studies import descriptor_robustness as dr

    studies, docs = tmp_path / "studies", tmp_path / "docs"
    base = dict(dataset="shared_real", backend="cpp", sampler="highpass", seed=0)
    rows = []
    for ratio in (1.0, 0.2, 0.01):
        for i in range(4):
            ok = i < 3
            trusted = ok if ratio != 0.2 else {0: True, 1: False, 2: True, 3: True}[i]  # p1: FR, p3: FA
            rows.append(dict(pair=f"p{i}", success=ok, trusted=trusted, descriptor="fpfh", ratio=ratio,
                             **base))  # fmt: skip
        rows.append(dict(pair="p4", success=False, trusted=False, descriptor="fpfh", ratio=ratio,
                         error="RegistrationFailed: no clique", **base))  # fmt: skip
    _run(studies / "descriptor_robustness_real_indoor" / "0", rows)
    ran = dict(started="2026-12-07T02:16:47Z", ended="2026-12-07T02:25:20Z", wall_s=513, status="done",
               load_start="1.50 1.2 1.0", load_end="2.25 2.0 1.5", core_commit="abcdef1234",
               core_sha1="0123abcd99", cpu="CPU X", nproc=2)  # fmt: skip
    (studies / "descriptor_robustness_real_indoor" / "ran.json").write_text(json.dumps(ran))
    docs.mkdir()
    claim = f"- **{dr.CLAIM}** — real: holds 1 (of 1 data sets)"
    (docs / "results.md").write_text(
        f"# R\n\n- **Other claim** — real: agrees 1\n  - real_indoor: x → agrees\n{claim}\n"
        "  - real_indoor (9 pairs): OLD → holds\n- **Last claim** — real: agrees 1\n\n## 5. Old\n\nold\n\n"
        "## 6. After\n\n## Notes\n\n- filter ablation, kitti: KEEP\n- descriptor robustness, x: OLD NOTE\n"
    )
    dr.splice(studies, docs)
    md = (docs / "results.md").read_text()
    assert "## 5. Descriptor robustness (paper Fig. desc)\n\n_Ran on the C++ core of commit `abcdef1` " in md
    assert "2026-12-07 02:16–02:25 UTC, 1 sweep(s), 513 s of wall time in all, on CPU X (2 cores)" in md
    assert "OLD" not in md and "- **Other claim** — real: agrees 1\n  - real_indoor: x → agrees\n" in md
    assert "  - real_indoor (5 pairs): RR 100 % → 1 %: fpfh 60.0 → 60.0 → not tested" in md
    assert "\n- **Last claim**" in md and "- filter ablation, kitti: KEEP" in md
    assert "- descriptor robustness, real_indoor, fpfh: 3 failed row(s), e.g. `RegistrationFailed" in md
    heading = "### real_indoor: real indoor pairs (3DMatch/3DLoMatch fragments) — 5 pairs"
    assert _table_row(md, heading, "fpfh") == ["fpfh", "12", "9", "1", "1", "4, 3, 1, 1"]
    t = pd.DataFrame(rows).assign(error=lambda d: d["error"].fillna(""))
    assert dr.trust_counts(t, "fpfh", 1.0) == (4, 3, 0, 0)


def test_make_results_names_each_sections_core_and_keeps_the_others(tmp_path):
    """Another page's figure survives; section 1 ran here (its sweep's ran.json): a line under its heading
    names the core, when and the load; section 5 did not run: the previous page's text stays, said so with
    the previous core; sections 8 and 10 (their own scripts') stay as they were, in order, before the
    notes."""
    import json

    studies, docs = tmp_path / "studies", tmp_path / "docs"
    base = dict(dataset="synthetic", descriptor="fpfh", backend="cpp", seed=0)
    sweep = studies / "sampling_strategy_3dmatch" / "sweep"
    _run(sweep / "0", _pairs(4, 3, sampler="highpass", ratio=0.05, **base))
    ran = {"started": "2026-12-06T06:03:39Z", "ended": "2026-12-06T06:20:00Z", "wall_s": 981,
           "status": "done", "load_start": "1.45 1.20 1.20", "load_end": "3.10 2.50 1.90",
           "core_commit": "6525ec9" + "0" * 33, "core_sha1": "20e10e1a" + "0" * 32, "code_commit": "abc",
           "cpu": "AMD EPYC", "nproc": 2}  # fmt: skip
    (sweep / "ran.json").write_text(json.dumps(ran))
    (studies / "run_studies.log").write_text(
        "[06:03:39] python run.py -m +experiment=sampling_strategy hydra.sweep.dir="
        "outputs/studies/sampling_strategy_3dmatch/sweep\n[06:20:00]   done in 981 s\n"
    )
    docs.mkdir()
    (docs / "results.md").write_text(
        "# R\n\nC++ core: the extension built from commit `cb48309e3322` (copied once).\n\n"
        "## 1. Sampling\n\nOLD-1\n\n## 5. Descriptor robustness (paper Fig. desc)\n\nOLD-5\n\n"
        "## 8. Estimated\n\nKEEP-8\n\n### sub\n\nKEEP-8b\n\n## 10. Raw clouds\n\nKEEP-10\n\n## Notes\n\n- n\n"
    )
    (docs / "figures").mkdir()
    for name in ("tracking.png", "sampling_strategy.png", "gone.png"):
        (docs / "figures" / name).write_bytes(b"png")
    (docs / "tracking.md").write_text("![ui](figures/tracking.png)\n")
    md = make_results.make_results(studies, docs)
    figures = sorted(f.name for f in (docs / "figures").iterdir())
    assert figures == ["sampling_strategy.png", "tracking.png"]  # another page's figure stays, the old go
    assert (docs / "figures" / "sampling_strategy.png").read_bytes() != b"png"  # drawn again
    one = md[md.index("## 1. Sampling strategy") : md.index("## 2. ")]
    assert "OLD-1" not in md
    assert one.splitlines()[2] == (
        "_Ran on the C++ core of commit `6525ec9` (extension sha1 20e10e1a), 2026-12-06 06:03–06:20 UTC, "
        "1 sweep(s), 981 s of wall time in all, on AMD EPYC (2 cores), load average (1 min) 1.4–3.1 at the "
        "sweeps' starts and ends._"
    )
    five = md[md.index("## 5. ") : md.index("## 6. ")]
    assert five.splitlines()[:5] == [
        "## 5. Descriptor robustness (paper Fig. desc)", "",
        "_Not rerun on this core: the section as the previous page had it (C++ core `cb48309`)._",
        "", "OLD-5"]  # fmt: skip
    assert "_Ran on" not in md[md.index("## 2. ") : md.index("## 5. ")]  # no ran.json, no old text: as is
    heads = [ln for ln in md.splitlines() if ln.startswith("## ")]
    assert [h[:14] for h in heads[-5:]] == [
        "## 7. State of", "## 8. Estimate", "## 10. Raw clo", "## Notes", "## What ran"]  # fmt: skip
    assert "KEEP-8b" in md[md.index("## 8. ") : md.index("## 10. ")]
    row = _table_row(md, "## What ran", "`sampling_strategy_3dmatch/sweep`")
    assert row[1:] == ["981", "06:03", "1.45 → 3.10"]
