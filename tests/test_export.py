"""``robust-imdp export``: the abstraction and its product with the DFA, read back and checked by Storm.

One small run through the command line (64 cells, 3 modes, 20 points per mode, 3-step
horizon) is shared by the tests. The product's values are our p_low (max-min: the robust
strategy's guaranteed value) and p_up_star (max-max); Storm must find the same numbers in
the exported files. The horizon makes this possible at all: Storm refuses unbounded
reachability on interval models with zero lower bounds, and the abstraction has many.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from robust_imdp.cli import main

pytestmark = pytest.mark.slow  # one pipeline run (about 3 s on 2 cores) shared by the module

HORIZON = 3
N = 64  # cells: [-2, 2]^2 in steps of 0.5


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from robust_imdp.casestudies.systems import get_case_study, problem_toml
    from robust_imdp.io.files import write_data_file

    d = tmp_path_factory.mktemp("export")
    case = get_case_study("three_mode_linear")
    x, u, xn = case.system.sample_dataset(20, case.lower, case.upper, rng=3)
    write_data_file(d / "d.csv", x, u, xn, modes=case.system.mode_names)
    text = problem_toml(case, "G !obs & F des", "d.csv").replace(
        "cell_size = [0.125, 0.125]", "cell_size = [0.5, 0.5]").replace(
        "threshold = 0.95", f"threshold = 0.95\nhorizon = {HORIZON}")
    (d / "p.toml").write_text(text)
    assert main(["run", str(d / "p.toml"), "--out", str(d / "out"), "--quiet", "--no-figures"]) == 0
    return d / "out"


def _export(run_dir, capsys, *args):
    code = main(["export", str(run_dir), *args])
    out, err = capsys.readouterr()
    assert code == 0, err
    return out


def test_abstraction_export_reads_back_as_the_cached_imdp(run_dir, tmp_path, capsys):
    from robust_imdp.abstraction.rows import Abstraction
    from robust_imdp.io.formats import load_drn, load_prism_explicit

    doc = json.loads((run_dir / "result.json").read_text())
    cached = Abstraction.load(run_dir / "cache" / f"abstraction-{doc['parameters']['abstraction_key']}.npz").imdp
    out = _export(run_dir, capsys, "--format", "drn", "--out", str(tmp_path / "a.drn"))
    assert f"{N + 1} states, {3 * (N + 1)} choices ({N} cells + the outside state {N})" in out  # 3 modes each
    f = load_drn(tmp_path / "a.drn")
    _export(run_dir, capsys, "--format", "prism", "--out", str(tmp_path / "a.tra"))
    g = load_prism_explicit(tmp_path / "a")  # ".tra" dropped from the prefix
    for model in (f, g):
        # floors are written out as explicit [0, floor] entries: compare the dense forms
        for ours, theirs in zip(cached.to_dense(), model.imdp.to_dense()):
            np.testing.assert_array_equal(ours, theirs)
        in_des = np.array(["des" in lab for lab in doc["labels"]] + [False])
        np.testing.assert_array_equal(model.labels["des"], in_des)
        np.testing.assert_array_equal(np.flatnonzero(model.labels["outside"]), [N])
        np.testing.assert_array_equal(np.flatnonzero(model.labels["init"]), np.arange(N))
    states = json.loads((tmp_path / "a.states.json").read_text())
    assert states["kind"] == "abstraction" and states["actions"] == ["1", "2", "3"]


@pytest.mark.stormpy
def test_product_export_has_our_values_in_storm(run_dir, tmp_path, capsys):
    stormpy = pytest.importorskip("stormpy")
    from robust_imdp.io.formats import load_prism_explicit, storm_reachability, to_stormpy

    doc = json.loads((run_dir / "result.json").read_text())
    p_low, p_up_star = np.array(doc["p_low"]), np.array(doc["p_up_star"])
    assert 0 < np.sum((p_low > 0) & (p_low < 1))  # values strictly inside (0, 1): not a trivial check
    _export(run_dir, capsys, "--format", "drn", "--out", str(tmp_path / "p.drn"), "--product")
    states = json.loads((tmp_path / "p.states.json").read_text())
    S = states["dfa_states"]
    init = np.array(states["initial"])
    assert states["kind"] == "product" and states["horizon"] == HORIZON and init.shape == (N,)
    model = stormpy.build_model_from_drn[stormpy.Interval](str(tmp_path / "p.drn"))
    assert model.nr_states == S * (N + 1)
    for adversary, ours in (("pessimistic", p_low), ("optimistic", p_up_star)):
        storm = storm_reachability(model, True, adversary=adversary, horizon=HORIZON, precision=1e-12)
        # k-step values are exact sums of products up to rounding: agreement to 1e-9
        np.testing.assert_allclose(storm[init], ours, atol=1e-9, err_msg=adversary)
    # the PRISM files hold the same model; their .props ask for the 3-step values
    _export(run_dir, capsys, "--format", "prism", "--out", str(tmp_path / "p"), "--product")
    g = load_prism_explicit(tmp_path / "p")
    assert (tmp_path / "p.props").read_text().splitlines() == [
        f'Pmaxmin=? [ F<={HORIZON} "target" ]', f'Pmaxmax=? [ F<={HORIZON} "target" ]']
    storm = storm_reachability(to_stormpy(g.imdp, g.labels["target"]), True, adversary="pessimistic",
                               horizon=HORIZON, precision=1e-12)
    np.testing.assert_allclose(storm[init], p_low, atol=1e-9)


def test_export_without_the_cache_says_what_is_missing(run_dir, tmp_path, capsys):
    code = main(["export", str(run_dir), "--format", "drn", "--out", str(tmp_path / "x.drn"),
                 "--cache", str(tmp_path / "nocache")])
    err = capsys.readouterr().err
    assert code == 1 and "export needs the abstraction of this result" in err and "nocache" in err
    assert not (tmp_path / "x.drn").exists()


def test_result_json_of_a_real_run_follows_the_schema(run_dir):
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from test_result_schema import SCHEMA, validate_schema

    assert validate_schema(json.loads((run_dir / "result.json").read_text()), SCHEMA) == []
