"""Smoke tests of plotting.py on a synthetic result: files are written, content is sane."""

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from robust_imdp import plotting  # noqa: E402
from robust_imdp.errors import DimensionError  # noqa: E402
from robust_imdp.validate import ResultFile, Trajectories  # noqa: E402


def grid_doc(h=0.5, seed=0):
    """The three-mode case study's regions on an (4/h)^2 grid with random bounds."""
    rng = np.random.default_rng(seed)
    b = np.arange(-2.0, 2.0, h)
    lo = np.array([[x, y] for x in b for y in b])
    up = lo + h

    def inside(boxes):
        return np.array([any(np.all(l >= bl) and np.all(u <= bu) for bl, bu in boxes)
                         for l, u in zip(lo, up)])

    des = inside([((-1, -1), (0, 0)), ((0, 0), (1, 1))])
    obs = inside([((-2, -2), (-1, -1)), ((-1, 0), (0, 1)), ((0, -1), (1, 0)), ((1, 1), (2, 2))])
    labels = [["des"] * int(d) + ["obs"] * int(o) for d, o in zip(des, obs)]
    p_low = np.where(des, 1.0, np.where(obs, 0.0, rng.uniform(0, 1, len(lo))))
    p_up = np.minimum(1.0, p_low + np.where(des | obs, 0.0, rng.uniform(0, 0.3, len(lo))))
    cls = np.where(p_low >= 0.95, "yes", np.where(p_up < 0.95, "no", "maybe"))
    return {
        "format": "robust_imdp.result/1", "space": {"lower": [-2, -2], "upper": [2, 2]},
        "cells": {"lower": lo.tolist(), "upper": up.tolist()}, "labels": labels,
        "modes": ["1", "2", "3"],
        # G !obs & F des over (des, obs): 0 wait, 1 accept, 2 sink
        "dfa": {"atoms": ["des", "obs"], "initial": 0, "accepting": [1],
                "delta": [[0, 1, 2, 2], [1, 1, 1, 1], [2, 2, 2, 2]]},
        "strategy": [["1", "2", "3"]] * len(lo),
        "p_low": p_low.tolist(), "p_up": p_up.tolist(), "p_up_star": p_up.tolist(),
        "error": (p_up - p_low).tolist(), "classes": cls.tolist(), "formula": "G !obs & F des",
        "threshold": 0.95, "horizon": None, "parameters": {}, "timings": {},
    }


def test_save_figures_writes_pngs(tmp_path):
    res = ResultFile.from_dict(grid_doc())
    paths = [np.array([[1.6, -1.6], [1.2, -1.0], [0.5, 0.5]]), np.array([[-1.5, 1.5]])]
    tr = Trajectories(paths=paths, outcome=np.array([1, 2]), steps=np.array([2, 0]))
    written = plotting.save_figures(res, tmp_path, trajectories=tr)
    assert [p.name for p in written] == ["partition.png", "classes.png", "p_low.png",
                                         "error.png", "trajectories.png"]
    for p in written:
        assert p.stat().st_size > 5000  # a real image, not an empty canvas
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not plt.get_fignums()  # every figure closed


def test_classes_legend_counts_and_region_labels():
    doc = grid_doc()
    ax = plotting.plot_classes(doc)
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    n_yes = doc["classes"].count("yes")
    assert any(t.startswith("Q_yes") and t.endswith(f": {n_yes}") for t in texts)
    # obs has 4 disjoint boxes, des 2 touching at a corner (not 4-connected): 6 region labels
    names = sorted(t.get_text() for t in ax.texts)
    assert names == ["des"] * 2 + ["obs"] * 4
    assert ax.get_xlabel() == "$x_1$" and ax.get_ylabel() == "$x_2$"
    plt.close("all")


def test_outline_segments_of_one_box():
    bx = by = np.array([0.0, 1.0, 2.0])
    ind = np.array([[True, False], [False, False]])
    segs = plotting._outline_segments(bx, by, ind)
    assert len(segs) == 4  # the unit square's four sides
    assert {tuple(map(tuple, s)) for s in segs} == {
        ((0.0, 0.0), (0.0, 1.0)), ((1.0, 0.0), (1.0, 1.0)),
        ((0.0, 0.0), (1.0, 0.0)), ((0.0, 1.0), (1.0, 1.0))}


def test_eta_sweep_panel(tmp_path):
    docs = [grid_doc(seed=s) for s in range(4)]
    fig = plotting.plot_eta_sweep(docs, ["0.96 sigma", "0.97 sigma", "0.985 sigma", "0.995 sigma"])
    fig.savefig(tmp_path / "sweep.png", dpi=60)
    assert (tmp_path / "sweep.png").stat().st_size > 5000
    assert "eta = 0.96 sigma" in fig.axes[0].get_title()
    plt.close(fig)
    with pytest.raises(DimensionError, match="etas"):
        plotting.plot_eta_sweep(docs, ["a"])


def doc_nd(d, h=0.5, threshold=0.9, seed=0):
    """A synthetic result on [-2, 2]^d with cells of width h: des = [0, 1]^d, obs = [-2, -1]^d,
    p_low falling off with the distance from des's centre, p_up = p_low + U(0, 0.2) elsewhere."""
    rng = np.random.default_rng(seed)
    lo = np.stack(np.meshgrid(*[np.arange(-2.0, 2.0, h)] * d, indexing="ij"), -1).reshape(-1, d)
    up = lo + h
    des = np.all(lo >= 0, axis=1) & np.all(up <= 1, axis=1)
    obs = np.all(up <= -1, axis=1)
    base = np.clip(1.2 - np.linalg.norm(0.5 * (lo + up) - 0.5, axis=1) / 2, 0, 1)
    p_low = np.where(des, 1.0, np.where(obs, 0.0, base))
    p_up = np.minimum(1.0, p_low + np.where(des | obs, 0.0, rng.uniform(0, 0.2, len(lo))))
    doc = grid_doc(h=1.0)  # the DFA, modes and formula of the 2-D document
    doc.update({"space": {"lower": [-2.0] * d, "upper": [2.0] * d},
                "cells": {"lower": lo.tolist(), "upper": up.tolist()},
                "labels": [["des"] * int(a) + ["obs"] * int(b) for a, b in zip(des, obs)],
                "strategy": [["1", "2", "3"]] * len(lo), "p_low": p_low.tolist(), "p_up": p_up.tolist(),
                "p_up_star": p_up.tolist(), "error": (p_up - p_low).tolist(), "threshold": threshold,
                "classes": np.where(p_low >= threshold, "yes", np.where(p_up < threshold, "no", "maybe")).tolist()})
    return doc


def test_one_d_bounds_against_x(tmp_path):
    doc = doc_nd(1, h=0.25)
    written = plotting.save_figures(doc, tmp_path)
    assert [p.name for p in written] == ["bounds.png"] and written[0].stat().st_size > 5000
    ax = plotting.plot_bounds_1d(doc)
    # the p_low and p_up step lines carry exactly the per-cell values (cells are in x order here)
    lines = {s.get_label(): s for s in ax.patches if s.get_label() in ("p_low", "p_up")}
    values, edges, _ = lines["p_low"].get_data()
    np.testing.assert_array_equal(values, doc["p_low"])
    np.testing.assert_array_equal(edges, np.arange(-2.0, 2.01, 0.25))
    np.testing.assert_array_equal(lines["p_up"].get_data()[0], doc["p_up"])
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    n_yes = doc["classes"].count("yes")  # des = [0, 1]: 4 cells at p_low = 1, plus neighbours >= 0.9
    assert f"Q_yes (p_low >= threshold): {n_yes}" in texts and n_yes >= 4
    assert sorted(t.get_text() for t in ax.texts) == ["des", "obs"]  # one bar per region, named
    plt.close("all")


def test_three_d_slices(tmp_path):
    from robust_imdp.io.files import ResultFile

    doc = doc_nd(3)  # 8 x 8 x 8 cells of width 0.5
    res = ResultFile.from_dict(doc)
    view = plotting.slice_result(res, 0.75, axis=2)
    # the plane x_3 = 0.75 meets the 64 cells with x_3 in [0.5, 1.0), drawn by (x_1, x_2)
    q = np.flatnonzero(res.cells_lower[:, 2] == 0.5)
    assert view.n_cells == 64 and q.size == 64
    np.testing.assert_array_equal(view.cells_lower, res.cells_lower[q][:, :2])
    np.testing.assert_array_equal(view.classes, res.classes[q])
    assert view.labels.count(("des",)) == 4  # des = [0, 1]^3 meets the plane in 2 x 2 cells
    fig = plotting.plot_slices(res, "classes", n_slices=4)
    titles = [a.get_title() for a in fig.axes if a.get_visible()]
    assert titles == ["x_3 = -1.75", "x_3 = -0.75", "x_3 = 0.75", "x_3 = 1.75"]  # 4 of the 8 midpoints, spread
    plt.close(fig)
    written = plotting.save_figures(doc_nd(3, h=2.0), tmp_path, dpi=40)  # 8 cells, 2 slices, small: fast
    assert [p.name for p in written] == ["partition.png", "classes.png", "p_low.png", "error.png"]
    assert not plt.get_fignums()


def test_four_d_slices_fix_the_rest_at_the_centre():
    res = plotting.slice_result(doc_nd(4, h=1.0), 0.5, axis=2)
    assert res.n_cells == 16  # 4 x 4 cells in (x_1, x_2); x_3 = 0.5 and x_4 = 0 (centre) pick one layer each
    assert res.parameters["_slice"] == "x_3 = 0.5, x_4 = 0"


def test_plots_name_the_dimension_they_need():
    with pytest.raises(DimensionError, match="needs a 2-D state space; got cells of dimension 3 .*plot_slices"):
        plotting.plot_classes(doc_nd(3))
    with pytest.raises(DimensionError, match="needs a 1-D state space"):
        plotting.plot_bounds_1d(grid_doc())
    with pytest.raises(DimensionError, match="dimension >= 3; got 2"):
        plotting.plot_slices(grid_doc())


def test_heat_map_has_region_names_and_the_threshold_contour():
    doc = grid_doc()
    ax = plotting.plot_values(doc, "p_low")
    assert sorted(t.get_text() for t in ax.texts) == ["des"] * 2 + ["obs"] * 4
    # classes are "yes" exactly where p_low >= threshold, so the contour is the outline of Q_yes
    res = plotting._result(doc)
    bx, by, ind = plotting._raster(res, res.classes == "yes")
    want = {tuple(map(tuple, s)) for s in plotting._outline_segments(bx, by, ind)}
    from matplotlib.collections import LineCollection
    from matplotlib.colors import to_rgba

    dashed = [c for c in ax.collections if isinstance(c, LineCollection)
              and c.get_colors().tolist() == [list(to_rgba(plotting.THRESHOLD_COLOUR))]]
    assert len(dashed) == 1 and {tuple(map(tuple, s)) for s in dashed[0].get_segments()} == want and want
    assert "threshold 0.95" in ax.get_legend().get_texts()[0].get_text()
    plt.close("all")


def test_trajectory_markers_and_labels_read_on_every_class_colour():
    from matplotlib.colors import to_rgba

    doc = grid_doc()
    paths = [np.array([[1.6, -1.6], [0.5, 0.5]]), np.array([[-1.5, 1.5], [-1.5, 1.7]]),
             np.array([[1.3, 0.3], [1.6, -0.6]])]
    tr = Trajectories(paths=paths, outcome=np.array([1, 2, 0]), steps=np.array([1, 1, 1]))
    ax = plotting.plot_trajectories(doc, tr)
    class_rgba = {to_rgba(c) for c in plotting.CLASS_COLOURS.values()}
    markers = [c for c in ax.collections if c.get_offsets().shape[0] and c.get_zorder() == 4]
    assert len(markers) == 3  # satisfied, violated, capped: one scatter each
    for m in markers:
        assert tuple(m.get_facecolors()[0]) not in class_rgba  # never a class colour (red on red)
    texts = ax.texts
    assert texts and all(to_rgba(t.get_color()) == to_rgba("black") and t.get_zorder() > 4 for t in texts)
    plt.close("all")


def test_trajectories_are_cut_at_a_periodic_seam_and_only_there():
    from matplotlib.collections import LineCollection

    doc = grid_doc()
    doc["space"]["periodic"] = [False, True]  # x2 wraps: period 4
    # 1.8 -> -1.9 in x2 is a step of 0.3 across the seam (jump 3.7 > T/2 = 2): cut there;
    # 0.5 -> -1.4 (jump 1.9 < 2) is an ordinary move: kept; x1 jumps never cut (not periodic).
    path = np.array([[0.0, 1.2], [0.1, 1.8], [0.2, -1.9], [0.3, -1.4], [1.9, 0.5], [-1.9, -1.4]])
    pieces = plotting.seam_segments(path, doc)
    assert [len(p) for p in pieces] == [2, 4]
    assert np.array_equal(np.vstack(pieces), path)  # nothing lost or added
    doc_flat = grid_doc()
    assert [len(p) for p in plotting.seam_segments(path, doc_flat)] == [6]  # no periodic dims: one piece
    tr = Trajectories(paths=[path], outcome=np.array([1]), steps=np.array([5]))
    ax = plotting.plot_trajectories(doc, tr)
    lines = [c for c in ax.collections if isinstance(c, LineCollection)
             and c.get_colors().tolist() == [[0.0, 0.0, 0.0, 0.8]]]
    segs = [s for c in lines for s in c.get_segments()]
    assert sorted(len(s) for s in segs) == [2, 4]  # the seam jump is not drawn
    plt.close("all")
