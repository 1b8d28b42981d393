"""The report's figures (issue 42 item 9): the time profile's legend beside, not on, the bars and their
total labels, with the stage names spelt out; the clouds inside their panel; snapshots of the failed and
worst pairs of the whole sweep first."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from tests.test_trackers import make_outcome, run_tracker


def _captured(monkeypatch, module) -> list:
    figs: list = []
    monkeypatch.setattr(module.plt, "close", lambda fig=None: figs.append(fig))
    return figs


def test_the_time_profiles_legend_covers_no_panel_and_spells_the_stages_out(tmp_path, monkeypatch):
    from fastmac_exp.report import plots

    figs = _captured(monkeypatch, plots)
    agg = pd.DataFrame({
        "dataset": "synthetic", "descriptor": "fpfh", "sampler": "highpass", "backend": "cpp",
        "protocol": "honest", "ratio": [0.2, 0.02], "t_sampling_ms": [19.0, 23.9], "t_graph_ms": [5.0, 0.1],
        "t_cliques_ms": [1.0, 0.0], "t_selection_ms": [0.1, 0.0], "t_pose_ms": [0.6, 0.1],
        "t_total_ms": [24.8, 24.1],
    })  # fmt: skip
    assert plots.plot_time_profile(agg, tmp_path / "t.png") is not None
    (fig,) = figs
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    (legend,) = fig.legends
    texts = [t.get_text() for t in legend.get_texts()]
    for long in ("GC: graph construction", "MCS: maximal clique search", "NCS: node-guided clique selection",
                 "PE: pose estimation"):  # fmt: skip
        assert long in texts
    box = legend.get_window_extent(renderer)
    for ax in fig.axes:
        assert not box.overlaps(ax.get_window_extent(renderer))
        labels = [t for t in ax.texts if t.get_text() in ("24.8", "24.1")]
        for t in labels:  # inside its panel, above its bar
            assert ax.get_window_extent(renderer).contains(*t.get_window_extent(renderer).get_points()[1])


def test_a_far_source_before_registration_stays_inside_its_panel(tmp_path, monkeypatch):
    from fastmac_exp.trackers import rerun_snapshot
    from fastmac_exp.trackers.rerun_snapshot import PairGeometry, render_pair

    rng = np.random.default_rng(0)
    cloud = rng.uniform(0, 1, (2000, 3))
    geo = PairGeometry(name="p", clouds={
        "registration/target": cloud, "registration/estimate/source": cloud,
        "registration/source_before/source": cloud + [30.0, 0, 0],
    }, poses={"estimate": np.eye(4)})  # fmt: skip
    figs = _captured(monkeypatch, rerun_snapshot)
    render_pair(geo, tmp_path / "p.png")
    (fig,) = figs
    ax = fig.axes[1]
    lo = np.array([ax.get_xlim()[0], ax.get_ylim()[0], ax.get_zlim()[0]])
    hi = np.array([ax.get_xlim()[1], ax.get_ylim()[1], ax.get_zlim()[1]])
    for coll in ax.collections:
        pts = np.column_stack([np.asarray(c) for c in coll._offsets3d])
        assert ((pts >= lo - 1e-9) & (pts <= hi + 1e-9)).all()


def test_snapshots_go_to_the_failed_pairs_of_the_whole_sweep_first(tmp_path):
    """Member a registered everything; member b, later in the order, has a pair not registered: with one
    snapshot allowed it is b's (it used to be a's, the first member's)."""
    pytest.importorskip("rerun")
    from fastmac_exp.report import pair_snapshots
    from fastmac_exp.trackers.rerun_tracker import RerunTracker

    tables = []
    for run, bad in (("a", None), ("b", 1)):
        outcomes = [make_outcome(i, f"p{i}") for i in range(3)]
        if bad is not None:
            outcomes[bad].row.update(success=False, re_deg=40.0)
        table, _ = run_tracker(RerunTracker(max_pairs=3, max_points=200), tmp_path / run, outcomes)
        table["run"] = run
        tables.append(table)
    pngs = pair_snapshots(tmp_path, pd.concat(tables, ignore_index=True), tmp_path / "report", max_pairs=1)
    assert [p.relative_to(tmp_path / "report").as_posix() for p in pngs] == ["pairs/b/p1.png"]


# an 18-member sweep (3 samplers x 6 ratios, 2 synthetic pairs each; measured here): 9 points at RR 100 %
# between 10 and 45 ms, the members at ratio 0.01 of fps and random without a time (every pair failed)
SWEEP_18 = pd.DataFrame({
    "dataset": "synthetic", "descriptor": "fpfh", "backend": "cpp", "protocol": "honest",
    "sampler": ["fps"] * 6 + ["highpass"] * 6 + ["random"] * 6, "ratio": [1.0, 0.5, 0.2, 0.1, 0.05, 0.01] * 3,
    "RR": [100.0, 100, 50, 50, 0, 0, 100, 100, 100, 100, 100, 50, 100, 100, 100, 0, 0, 0],
    "t_total_ms": [41.15, 231.11, 90.47, 44.07, 21.96, np.nan, 44.32, 21.75, 14.05, 10.58, 11.43, 9.81, 42.82,
                   10.94, 2.65, 0.6, 0.32, np.nan],
})  # fmt: skip


def test_rr_vs_time_labels_of_an_18_member_sweep_collide_with_nothing():
    """Issue 49 item 9: 'random@0.5', 'fps@1', 'highpass@0.5', 'random@1' ran into each other at RR 100 %
    ('fps@0.05fps@0.1'): every label now sits inside its panel, clear of the other labels, the points and
    the legend."""
    from fastmac_exp.report import plots
    from fastmac_exp.report.plots import text_box

    fig, (anns,) = plots.rr_vs_time_figure(SWEEP_18)
    renderer = fig.canvas.get_renderer()
    (ax,) = fig.axes
    frame = ax.get_window_extent(renderer)
    assert sorted(a.get_text() for a in anns) == sorted(
        f"{s}@{r:g}" for s, r, t in zip(SWEEP_18.sampler, SWEEP_18.ratio, SWEEP_18.t_total_ms) if t == t
    )
    boxes = [text_box(a, renderer) for a in anns]
    points = [ax.transData.transform(a.xy) for a in anns]
    legend = ax.get_legend().get_window_extent(renderer)
    for k, (a, box) in enumerate(zip(anns, boxes)):
        assert frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1, a
        assert not box.overlaps(legend), a.get_text()
        for j, other in enumerate(boxes[:k]):
            assert not box.overlaps(other), (a.get_text(), anns[j].get_text())
        for j, (x, y) in enumerate(points):
            assert j == k or not box.contains(x, y), (a.get_text(), anns[j].get_text())
    plots.plt.close(fig)


def test_the_time_profile_says_where_every_pair_failed_and_a_single_panel_claims_no_scales(
    tmp_path, monkeypatch
):
    """Issue 49 item 9: the member whose pairs all failed left an empty slot without a word; a one-panel
    chart's title said 'y scales differ'."""
    from fastmac_exp.report import plots

    agg = SWEEP_18.copy()
    for stage, share in (
        ("sampling", 0.5),
        ("graph", 0.2),
        ("cliques", 0.2),
        ("selection", 0.0),
        ("pose", 0.1),
    ):
        agg[f"t_{stage}_ms"] = agg["t_total_ms"] * share
    figs = _captured(monkeypatch, plots)
    plots.plot_time_profile(agg, tmp_path / "t.png")
    plots.plot_time_profile(agg[agg.sampler == "highpass"], tmp_path / "one.png")
    three, one = figs
    notes = {
        ax.get_title(): [t.get_text() for t in ax.texts if "failed" in t.get_text()] for ax in three.axes
    }
    note = ["no times:\nevery pair\nfailed"]
    assert notes == {"synthetic / fpfh: fps": note, "synthetic / fpfh: highpass": [],
                     "synthetic / fpfh: random": note}  # fmt: skip
    assert "each panel its own y scale" in three._suptitle.get_text()
    assert "scale" not in one._suptitle.get_text()
    one.canvas.draw()  # and its legend fits the narrow figure (three columns ran off its sides)
    box, page = one.legends[0].get_window_extent(), one.bbox
    assert page.x0 <= box.x0 and box.x1 <= page.x1
