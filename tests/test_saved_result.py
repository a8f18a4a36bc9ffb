"""A saved result is deployable, and a Python problem can be written as a problem file.

``load_result(dir)`` gives a short repr, ``summary()``, ``counts`` and ``controller()``, the same refined
switching controller as the live ``Result.controller()`` (grid, letters, strategy, and the modes it
returns along random runs); ``Controller.from_result`` takes a saved result. ``save_problem`` writes a
``Problem`` as TOML + data, and ``load_problem`` reads back a problem with the same inputs and the same
result.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from robust_imdp import Controller, Problem, TruncatedGaussianNoise, load_problem, load_result, save_problem, \
    save_result, synthesize_from_data
from robust_imdp.errors import InvalidInputError


def robot(**changes):
    """2-D robot (east / north), obstacle in the middle, goal top right: 64 cells of 0.5; exact drift plus a
    small unknown sin term (seeded)."""
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 4, (120, 2))
    u = np.where(np.arange(120) < 60, "east", "north")
    x_next = x + np.where(u[:, None] == "east", [0.3, 0.0], [0.0, 0.3]) + 0.02 * np.sin(x)
    kw = dict(lower=[0, 0], upper=[4, 4], cell_size=0.5,
              regions={"goal": ([3, 3], [4, 4]), "obstacle": ([1.5, 1], [2.5, 3])},
              formula="G !obstacle & F goal", threshold=0.9,
              modes={"east": (np.eye(2), [0.3, 0]), "north": (np.eye(2), [0, 0.3])},
              noise=TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]), rkhs_bound=0.2, lengthscale=1.0)
    kw.update(changes)
    return Problem.from_arrays(x, u, x_next, **kw)


def _unit_step(ctrl_mode, x):
    # a deterministic step for comparing two controllers' decisions: each mode moves 0.3 along its axis
    return x + (np.array([0.3, 0.0]) if ctrl_mode == "east" else np.array([0.0, 0.3]))


@pytest.fixture(scope="module", params=["grid", "k-step", "refined", "periodic"])
def saved(request, tmp_path_factory):
    changes = {"grid": {}, "k-step": {"horizon": 6}, "refined": {"refine": {"max_cells": 120}},
               "periodic": {"periodic": (True, False)}}[request.param]
    result = synthesize_from_data(robot(**changes), progress=False, advice=False)
    out = tmp_path_factory.mktemp(request.param)
    save_result(result, out)
    return request.param, result, out


def test_loaded_result_controller_is_the_live_controller(saved):
    kind, result, out = saved
    live = result.controller()
    loaded = load_result(out)
    for ctrl in (loaded.controller(), Controller.from_result(loaded), Controller.from_result(result)):
        assert ctrl.modes == live.modes and ctrl.horizon == live.horizon and ctrl.periodic == live.periodic
        np.testing.assert_array_equal(ctrl.strategy, live.strategy)
        np.testing.assert_array_equal(ctrl.cell_letters, live.cell_letters)
        np.testing.assert_array_equal(ctrl.dfa_delta, live.dfa_delta)
        np.testing.assert_array_equal(ctrl.p_low, live.p_low)
        for a, b in zip(ctrl.breakpoints, live.breakpoints):
            np.testing.assert_array_equal(a, b)
        assert (ctrl.cell_map is None) == (live.cell_map is None) == (kind != "refined")
        # the same cell for points inside, on cell faces and outside X (and across the seam when periodic)
        rng = np.random.default_rng(1)
        pts = np.r_[rng.uniform(-0.5, 4.5, (500, 2)), np.stack(np.meshgrid(*[np.arange(0, 4.01, 0.25)] * 2), -1)
                    .reshape(-1, 2)]
        np.testing.assert_array_equal(ctrl.batch_locate(pts) if hasattr(ctrl, "batch_locate") else ctrl.locate(pts),
                                      live.locate(pts))
        # the same modes along the same runs from 20 random starts
        for x0 in rng.uniform(0, 4, (20, 2)):
            runs = []
            for c in (ctrl, live):
                x, modes = c.reset(x0) and x0, []
                while (m := c.act(x)) is not None and len(modes) < 30:
                    modes.append(m)
                    x = _unit_step(m, x)
                runs.append((modes, c.status))
            assert runs[0] == runs[1]


def test_loaded_result_reads_like_the_live_one(saved):
    kind, result, out = saved
    loaded = load_result(out)
    text = repr(loaded)
    assert len(text) < 400 and text.count("\n") <= 3, text  # the dataclass repr printed every array
    c = loaded.counts
    assert c == result.counts and c() == c  # the property, and the call of earlier code
    assert c["yes"] + c["no"] + c["maybe"] == result.n_cells
    assert f"Q_yes {c['yes']}" in text
    live, back = result.summary().splitlines(), loaded.summary().splitlines()
    # the same lines but where the abstraction came from (built / read from result.json)
    assert len(live) == len(back) and [a for a, b in zip(live, back) if a != b] == [live[3]]
    assert back[3].endswith("(read from result.json)")


def test_saved_result_npz_holds_the_controller_tables(saved):
    # result.npz alone describes the controller: the letters, the DFA and X were missing from it
    kind, result, out = saved
    ctrl = result.controller()
    with np.load(out / "result.npz", allow_pickle=False) as z:
        np.testing.assert_array_equal(z["label_letters"], ctrl.cell_letters)
        assert z["dfa_atoms"].tolist() == list(ctrl.atoms) and int(z["dfa_initial"]) == ctrl.dfa_initial
        np.testing.assert_array_equal(z["dfa_accepting"], ctrl.dfa_accepting)
        np.testing.assert_array_equal(z["space_lower"], ctrl.space_lower)
        assert ("periodic" in z.files) == (kind == "periodic")


def test_an_old_result_file_without_diagnostics_still_loads_and_deploys(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_plotting import grid_doc

    doc = grid_doc(h=1.0)  # a result.json of the contract without diagnostics, advice or npz
    (tmp_path / "result.json").write_text(json.dumps(doc))
    res = load_result(tmp_path)
    assert res.diagnostics == {} and res.advice == {}
    assert "cells: 16" in res.summary()
    ctrl = Controller.from_result(res)
    assert ctrl.modes == ("1", "2", "3") and ctrl.locate(np.array([-1.5, -1.5])) == 0


def test_controller_from_result_names_what_it_accepts():
    with pytest.raises(InvalidInputError, match="needs a pipeline Result, a saved result"):
        Controller.from_result(object())


# --------------------------------------------------------------------------- Problem -> TOML
def _same_problem(a, b):
    """The inputs a result depends on, compared by value (types may differ: a float lengthscale is read back as
    one per dimension)."""
    from robust_imdp.pipeline.cache import _map_key
    from robust_imdp.pipeline.problem import _settings

    for name in ("space_lower", "space_upper", "cell_size"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert list(a.regions) == list(b.regions)
    for name in a.regions:
        for (lo1, up1), (lo2, up2) in zip(a.regions[name], b.regions[name], strict=True):
            np.testing.assert_array_equal(lo1, lo2)
            np.testing.assert_array_equal(up1, up2)
    assert (a.formula, float(a.threshold), a.horizon) == (b.formula, float(b.threshold), b.horizon)
    np.testing.assert_array_equal(a.data.x, b.data.x)  # repr in the CSV: exact
    np.testing.assert_array_equal(a.data.x_next, b.data.x_next)
    np.testing.assert_array_equal(a.data.u, b.data.u)
    assert a.mode_names == b.mode_names
    for m1, m2 in zip(a.maps, b.maps, strict=True):
        k1, k2 = _map_key(m1), _map_key(m2)
        if isinstance(k1[0], str):  # ("known", fingerprint) of a nonlinear known part
            assert k1 == k2
        else:
            np.testing.assert_array_equal(k1[0], k2[0])
            np.testing.assert_array_equal(k1[1], k2[1])
    assert type(a.noise) is type(b.noise) and repr(a.noise) == repr(b.noise)
    sa, sb = _settings(a), _settings(b)
    for name in ("rkhs_bound", "lengthscale", "misspecification"):
        np.testing.assert_array_equal(getattr(sa, name), getattr(sb, name))
    for name in ("error_bound", "iid_noise", "local_points", "split_tol", "eps_rule", "combine", "guarantee",
                 "confidence", "periodic", "dim_names", "bound_tol", "bound_max_boxes"):
        assert getattr(a, name) == getattr(b, name), name
    assert (a.eta is None) == (b.eta is None)
    if a.eta is not None:
        np.testing.assert_array_equal(a.eta, b.eta)
    assert (a.refine is None) == (b.refine is None)
    if a.refine is not None:
        assert a.refine.to_dict() == b.refine.to_dict()


@pytest.mark.parametrize("changes", [
    {},
    {"horizon": 6, "names": ("px", "py"), "misspecification": 0.001, "eta": [0.015, 0.015], "local_points": 50},
    {"periodic": (True, False), "rkhs_bound": {"east": [0.2, 0.0], "north": 0.3}, "split_tol": 0.002},
    {"modes": {"east": ["x1 + 0.3", "x2"], "north": (np.eye(2), [0, 0.3])}, "refine": {"max_cells": 90},
     "noise": __import__("robust_imdp").UniformNoise([0.02, 0.02])},
])
def test_problem_round_trips_through_a_problem_file(tmp_path, changes):
    p = robot(**changes)
    path = save_problem(p, tmp_path / "robot.toml")
    assert (tmp_path / "robot_data.csv").exists()
    q = load_problem(path)
    _same_problem(p, q)
    # from a problem read from a file on, writing and reading change nothing: the same text, the same cache keys
    # (the first write may widen a value's form: lengthscale 1.0 is read back as one per dimension)
    from robust_imdp.pipeline.cache import abstraction_key

    again = load_problem(save_problem(q, tmp_path / "again.toml", data_path="again.csv"))
    assert abstraction_key(again) == abstraction_key(q)
    third = save_problem(again, tmp_path / "third.toml", data_path="again.csv")
    assert third.read_text() == (tmp_path / "again.toml").read_text()


def test_a_written_problem_gives_the_same_result_and_serves_suggest(tmp_path, capsys):
    from robust_imdp.cli import main

    p = robot()
    live = synthesize_from_data(p, progress=False, advice=False)
    save_problem(p, tmp_path / "robot.toml")
    assert main(["run", str(tmp_path / "robot.toml"), "--out", str(tmp_path / "k"), "--quiet", "--no-figures",
                 "--advice", "off"]) == 0
    back = load_result(tmp_path / "k")
    np.testing.assert_array_equal(back.p_low, live.p_low)
    np.testing.assert_array_equal(back.p_up, live.p_up)
    np.testing.assert_array_equal(back.strategy, live.strategy)
    assert main(["suggest", str(tmp_path / "k"), "--problem", str(tmp_path / "robot.toml"), "--budget", "2"]) == 0
    assert "sample requests" in capsys.readouterr().out


def test_what_a_problem_file_cannot_say_is_refused_before_anything_is_written(tmp_path):
    from robust_imdp import UniformNoise

    class Wider(UniformNoise):  # another law: a file's kind = "uniform" would not be it
        pass

    p = robot(noise=Wider([0.02, 0.02]))
    with pytest.raises(InvalidInputError, match=r"\[noise\] is a TruncatedGaussianNoise, GaussianNoise or "
                                                r"UniformNoise; the problem's noise is a Wider"):
        save_problem(p, tmp_path / "p.toml")
    assert list(tmp_path.iterdir()) == []
