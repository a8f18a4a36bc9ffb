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


def test_three_d_result_is_refused():
    doc = grid_doc()
    doc["cells"] = {"lower": [[0, 0, 0]] * len(doc["labels"]), "upper": [[1, 1, 1]] * len(doc["labels"])}
    with pytest.raises(DimensionError, match="2-D"):
        plotting.plot_classes(doc)
