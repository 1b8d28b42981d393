"""The report: aggregation against numbers computed by hand, the loader (parquet and an interrupted
run's JSON-lines log), the markdown/CSV files and the PNG plots."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from fastmac_exp.report import aggregate, load_results, main, make_report
from fastmac_exp.run.results import ResultsLog

NAN = math.nan
BASE = {"dataset": "toy", "descriptor": "fpfh", "backend": "python", "protocol": "honest"}


def _row(i, sampler, ratio, seed, success, re, te, t_graph, t_total, error=""):
    return {
        "index": i, "pair": f"p{i}", **BASE, "sampler": sampler, "ratio": ratio, "seed": seed,
        "success": success, "re_deg": re, "te_cm": te, "t_graph_ms": t_graph, "t_total_ms": t_total,
        "error": error,
    }  # fmt: skip


# highpass@0.5: seed 0 with 4 pairs (2 registered, 1 wrong pose, 1 failed), seed 1 with 2 (both registered)
RUN_A = [
    _row(0, "highpass", 0.5, 0, True, 1.0, 2.0, 10.0, 20.0),
    _row(1, "highpass", 0.5, 0, True, 3.0, 4.0, 30.0, 40.0),
    _row(2, "highpass", 0.5, 0, False, 20.0, 50.0, 50.0, 60.0),
    _row(3, "highpass", 0.5, 0, False, None, None, None, None, error="InputError: too few"),
]
RUN_B = [
    _row(0, "highpass", 0.5, 1, True, 2.0, 1.0, 5.0, 10.0),
    _row(1, "highpass", 0.5, 1, True, 4.0, 3.0, 7.0, 12.0),
]
# random@0.1, seed 0, interrupted: only the JSON-lines log exists
RUN_C = [
    _row(0, "random", 0.1, 0, True, 5.0, 6.0, 1.0, 3.0),
    _row(1, "random", 0.1, 0, False, 30.0, 100.0, 2.0, 5.0),
]

# by hand: highpass@0.5 pools 6 pairs, 4 registered -> RR 66.67 %; RE over the 4 registered
# (1+3+2+4)/4 = 2.5, TE (2+4+1+3)/4 = 2.5; graph median of (10, 30, 50, 5, 7) = 10, total median of
# (20, 40, 60, 10, 12) = 20; per-seed RR 50 and 100 -> mean 75, sample std 35.355
EXPECTED = pd.DataFrame(
    {
        "sampler": ["highpass", "random"],
        "ratio": [0.5, 0.1],
        "pairs": [6, 2],
        "failed": [1, 0],
        "registered": [4, 1],
        "RR": [200 / 3, 50.0],
        "RE_deg": [2.5, 5.0],
        "TE_cm": [2.5, 6.0],
        "t_graph_ms": [10.0, 1.5],
        "t_total_ms": [20.0, 4.0],
        "seeds": [2, 1],
        "RR_seed_mean": [75.0, NAN],
        "RR_seed_std": [35.35533905932738, NAN],
    }
)


def test_aggregate_matches_hand_computation():
    table = pd.DataFrame(RUN_A + RUN_B + RUN_C)
    agg = aggregate(table)
    assert list(agg.columns[:6]) == ["dataset", "descriptor", "sampler", "ratio", "backend", "protocol"]
    got = agg[EXPECTED.columns].reset_index(drop=True)
    pd.testing.assert_frame_equal(got, EXPECTED, check_dtype=False, rtol=1e-9)
    assert (agg["dataset"] == "toy").all() and agg["t_describe_ms"].isna().all()


def test_aggregate_separates_groups_and_sorts_ratio_descending():
    rows = [
        _row(0, "random", 0.1, 0, True, 1, 1, 1, 1),
        _row(0, "random", 1.0, 0, False, 9, 9, 9, 9),
        {**_row(0, "random", 1.0, 0, True, 2, 2, 2, 2), "backend": "cpp"},
        {**_row(0, "random", 1.0, 0, None, NAN, NAN, 2, 2), "backend": "cpp"},  # no GT: not registered
    ]
    agg = aggregate(pd.DataFrame(rows))
    assert agg[["backend", "ratio"]].values.tolist() == [["cpp", 1.0], ["python", 1.0], ["python", 0.1]]
    assert agg["RR"].tolist() == [50.0, 0.0, 100.0]
    assert np.isnan(agg["RE_deg"].iloc[1]) and agg["RE_deg"].iloc[0] == 2.0


def _write_runs(root):
    for name, rows, complete in (("0_a", RUN_A, True), ("1_b", RUN_B, True), ("2_c", RUN_C, False)):
        log = ResultsLog(root / name)
        for r in rows:
            log.append(r)
        if complete:
            log.write_tables()
    (root / "0_a" / "wandb").mkdir()  # unrelated files are ignored


def test_report_files(tmp_path):
    root = tmp_path / "multirun"
    _write_runs(root)
    assert (root / "0_a" / "results.parquet").exists() and not (root / "2_c" / "results.parquet").exists()
    table = load_results(root)
    assert sorted(table["run"].unique()) == ["0_a", "1_b", "2_c"] and len(table) == 8

    assert main([str(root)]) == 0
    out = root / "report"
    csv = pd.read_csv(out / "report.csv")
    pd.testing.assert_frame_equal(csv[EXPECTED.columns], EXPECTED, check_dtype=False, rtol=1e-9)
    md = (out / "report.md").read_text()
    assert "## dataset toy × descriptor fpfh" in md
    assert (
        "| sampler | ratio | pairs | failed | RR (%) | RE (deg) | TE (cm) | RR across seeds (%) | seeds |"
        in md
    )
    assert "| highpass | 0.5 | 6 | 1 | 66.7 | 2.50 | 2.50 | 75.0 ± 35.4 | 2 |" in md
    assert "| random | 0.1 | 2 | 0 | 50.0 | 5.00 | 6.00 | 50.0 | 1 |" in md
    assert "| sampler | ratio | GC | total |" in md and "| highpass | 0.5 | 10.0 | 20.0 |" in md
    assert "All rows: backend = python, protocol = honest." in md
    for name in ("sampling.png", "time_profile.png", "rr_vs_time.png"):
        png = out / name
        assert png.stat().st_size > 5000, name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"]({name})" in md

    # a second report into another directory does not pick up the first one's files as results
    res = make_report(root, tmp_path / "elsewhere", plots=False)
    assert len(res["table"]) == 8 and res["plots"] == []


def test_report_on_a_single_run_dir(tmp_path):
    log = ResultsLog(tmp_path / "run")
    for r in RUN_A:
        log.append(r)
    log.write_tables()
    res = make_report(tmp_path / "run")
    assert res["aggregate"]["pairs"].tolist() == [4] and res["aggregate"]["RR"].tolist() == [50.0]
    assert (tmp_path / "run" / "report" / "sampling.png").stat().st_size > 0


def test_report_errors(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "no results" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError):
        make_report(tmp_path / "missing")


def test_plots_with_several_datasets_backends_and_seeds(tmp_path):
    from fastmac_exp.report.plots import plot_all

    rng = np.random.default_rng(0)
    rows = []
    for ds in ("3dmatch", "kitti"):
        for backend in ("cpp", "python"):
            for sampler in ("highpass", "random", "fps"):
                for ratio in (1.0, 0.5, 0.2, 0.1, 0.05, 0.01):
                    for seed in (0, 1):
                        for i in range(3):
                            ok = bool(rng.random() < ratio + 0.3)
                            re, te = rng.random() * 3, rng.random() * 9
                            row = _row(i, sampler, ratio, seed, ok, re, te, 100 * ratio, 150 * ratio + 1)
                            row.update(dataset=ds, backend=backend, t_sampling_ms=2.0, t_cliques_ms=5 * ratio)
                            rows.append(row)
    agg = aggregate(pd.DataFrame(rows))
    assert len(agg) == 2 * 2 * 3 * 6 and (agg["seeds"] == 2).all() and agg["RR_seed_std"].notna().all()
    paths = plot_all(agg, tmp_path)
    assert [p.name for p in paths] == ["sampling.png", "time_profile.png", "rr_vs_time.png"]
    assert all(p.stat().st_size > 20000 for p in paths)


def _figures(monkeypatch):
    """The figures the plot functions make (captured when they close them)."""
    from fastmac_exp.report import plots

    figs = []
    real_close = plots.plt.close
    monkeypatch.setattr(plots.plt, "close", lambda fig=None: (figs.append(fig), real_close(fig)))
    return figs


def test_time_profile_panels_keep_their_own_scale_and_ratio_axes_show_only_data(tmp_path, monkeypatch):
    """A slow method (FPS, ~400 ms) must not flatten a fast one's bars (~10 ms), and a ratio axis has ticks
    only where there are data."""
    from fastmac_exp.report.plots import plot_sampling, plot_time_profile

    rows = []
    for sampler, ms in (("fps", 400.0), ("highpass", 10.0)):
        for ratio in (0.5, 0.2):
            row = _row(0, sampler, ratio, 0, True, 1.0, 2.0, ms / 4, ms)
            row.update(t_sampling_ms=ms / 2)
            rows.append(row)
    agg = aggregate(pd.DataFrame(rows))
    figs = _figures(monkeypatch)
    plot_time_profile(agg, tmp_path / "t.png")
    plot_sampling(agg, tmp_path / "s.png")
    (profile, sampling) = figs
    tops = sorted(ax.get_ylim()[1] for ax in profile.axes if ax.get_visible())
    assert tops[0] < 50 and tops[-1] > 300  # each panel on its own scale
    ticks = {round(t, 6) for t in sampling.axes[0].get_xticks()}
    assert ticks == {0.5, 0.2}


def test_report_says_which_search_ran_and_how_many_pairs_were_capped(tmp_path):
    cap = "max_nodes=1000000"
    rows = [
        {**_row(0, "highpass", 0.2, 0, True, 1, 1, 5, 10), "search": "auto:bnb", "cap_hit": cap},
        {**_row(1, "highpass", 0.2, 0, True, 1, 1, 5, 10), "search": "auto:enumerate", "cap_hit": ""},
        {**_row(2, "highpass", 0.2, 0, True, 1, 1, 5, 10), "search": "auto:bnb", "cap_hit": None},
        {**_row(0, "highpass", 1.0, 0, False, None, None, None, None, error="RegistrationFailed: x"),
         "search": None, "cap_hit": None},
    ]  # fmt: skip
    agg = aggregate(pd.DataFrame(rows))
    assert agg["searches"].tolist() == ["", "auto:bnb 2, auto:enumerate 1"]  # ratio 1.0 first
    assert agg["capped"].tolist() == [0, 1]
    root = tmp_path / "run"
    log = ResultsLog(root)
    for r in rows:
        log.append(r)
    log.write_tables()
    res = make_report(root, tmp_path / "out", plots=False)
    md = (tmp_path / "out" / "report.md").read_text()
    assert "| ratio | GC | total | search (pairs) | capped |" in md, md
    assert "| 0.2 | 5.00 | 10.0 | auto:bnb 2, auto:enumerate 1 | 1 |" in md, md
    assert "| 1 | – | – | – | 0 |" in md, md
    assert len(res["table"]) == 4
    # without a search column the time table has no such columns
    plain = aggregate(pd.DataFrame(RUN_A))
    assert plain["searches"].tolist() == [""] and plain["capped"].tolist() == [0]


def test_re_te_panels_say_when_no_pair_registered(tmp_path, monkeypatch):
    from fastmac_exp.report.plots import plot_sampling

    figs = _figures(monkeypatch)
    rows = [
        _row(i, "random", ratio, 0, False, np.nan, np.nan, 10.0, 20.0)
        for ratio in (0.5, 0.1)
        for i in range(3)
    ]
    plot_sampling(aggregate(pd.DataFrame(rows)), tmp_path / "s.png")
    (fig,) = figs
    texts = [[t.get_text() for t in ax.texts] for ax in fig.axes]
    assert texts == [[], ["no successful pair"], ["no successful pair"]]  # RR, RE, TE
