"""Writing a result fast and unchanged (``jsonable.py``, ``io/result_file.py``'s ``save_result``).

* ``jsonable``'s array fast path gives what the element-wise walk gives (the previous implementation, kept here
  as the reference) for every dtype, with NaN, +-inf, -0.0, 0-d and empty arrays, numpy scalars, nested
  containers; compared strictly (types, and the sign of zero);
* ``result_to_dict`` of a hand-built result with non-finite values, a k-step strategy and atoms in another order
  in the DFA than in the partition gives the document derived by hand;
* ``save_result``: ``result.json`` parses to exactly ``result_to_dict``'s document (also when a name collides
  with the placeholder of a one-line list, and when every try collides), the indented layout is kept outside the
  per-cell lists, the document is not changed by the writing, and ``result.npz`` holds the arrays read from the
  document as the previous writer built them; on a real pipeline run (64 cells) likewise, and ``load_result``
  reads the same arrays back.
"""

from __future__ import annotations

import copy
import json
import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from robust_imdp.errors import InvalidInputError
from robust_imdp.io import result_file
from robust_imdp.io.result_file import load_result, result_to_dict, save_result
from robust_imdp.jsonable import jsonable

sys.path.insert(0, str(Path(__file__).parent))


# ----------------------------------------------------------------------------- the reference
def reference_jsonable(obj):
    """``jsonable`` as it was before the array fast path: every element walked."""
    if isinstance(obj, dict):
        return {str(k): reference_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [reference_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return reference_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return reference_jsonable(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def assert_same(a, b, path="$"):
    """``a == b`` with the same types all the way down (bool is not int, float is not int) and the same sign of
    every zero (``0.0 == -0.0`` would hide a lost sign)."""
    assert type(a) is type(b), f"{path}: {type(a).__name__} != {type(b).__name__}"
    if isinstance(a, dict):
        assert list(a) == list(b), path
        for k in a:
            assert_same(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        assert a == b and math.copysign(1.0, a) == math.copysign(1.0, b), f"{path}: {a!r} != {b!r}"
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


# ----------------------------------------------------------------------------- jsonable
FLOATS = [0.5, -0.0, 0.0, np.nan, np.inf, -np.inf, 1e-310, -2.5e300, 0.1]

CASES = {
    "float64 with NaN, +-inf, -0.0, subnormal": np.array(FLOATS),
    "float64 all finite": np.array([0.25, -0.0, 3.0]),
    "float32": np.array([0.1, -0.0, np.nan, -np.inf, 1e-40, 3e38], dtype=np.float32),
    "float16": np.array([0.1, np.nan, -0.0, np.inf], dtype=np.float16),
    "2-D float with inf": np.array(FLOATS[:8]).reshape(2, 4),
    "3-D float": np.arange(24.0).reshape(2, 3, 4) / 7.0,
    "0-d nan": np.array(np.nan),
    "0-d -0.0": np.array(-0.0),
    "0-d int": np.array(7),
    "empty float": np.zeros((0,)),
    "empty 2-D float": np.zeros((0, 3)),
    "empty int": np.zeros((2, 0), dtype=np.int64),
    "int64": np.array([-3, 0, 2**62]),
    "uint8": np.array([0, 255], dtype=np.uint8),
    "bool": np.array([[True, False], [False, True]]),
    "str": np.array(["yes", "no", "maybe"]),
    "object mixing numpy scalars": np.array([np.float64(np.inf), 1, "a", None, np.int32(4)], dtype=object),
    "non-contiguous float view": np.array(FLOATS)[::2],
    "Fortran-ordered float": np.asfortranarray(np.array(FLOATS[:6]).reshape(2, 3)),
    "numpy scalars": [np.float64(np.nan), np.float32(0.5), np.int64(3), np.bool_(True), np.str_("s")],
    "nested": {1: (np.array([np.inf, 2.0]), {"k": [np.array([True]), np.float64(-0.0)]}), "s": "x",
               "n": None, "f": float("nan"), "i": 5, "b": False},
    "masked array (a subclass: element-wise)": np.ma.masked_array([1.0, np.inf, 3.0], mask=[False, False, True]),
}


@pytest.mark.parametrize("name", list(CASES))
def test_jsonable_gives_what_the_elementwise_walk_gives(name):
    value = CASES[name]
    got = jsonable(value)
    assert_same(got, reference_jsonable(value))
    json.dumps(got, allow_nan=False)  # plain JSON: no NaN or infinity left


def test_jsonable_of_a_large_random_array_with_non_finite_entries():
    rng = np.random.default_rng(7)
    a = rng.standard_normal((500, 3))
    a[rng.random(a.shape) < 0.1] = np.nan
    a[rng.random(a.shape) < 0.05] = -np.inf
    a[rng.random(a.shape) < 0.05] = -0.0
    assert_same(jsonable(a), reference_jsonable(a))
    assert_same(jsonable({"x": a.astype(np.float32)}), reference_jsonable({"x": a.astype(np.float32)}))


# ----------------------------------------------------------------------------- per-cell floats as text
def float_arrays():
    rng = np.random.default_rng(5)
    grid = np.stack(np.meshgrid(np.linspace(-np.pi, np.pi, 9), [0.0, -0.0, 0.1, 1e-310], indexing="ij"), -1)
    wild = rng.standard_normal(400) * 10.0 ** rng.integers(-300, 300, 400)
    wild[rng.random(400) < 0.1] = np.nan
    wild[rng.random(400) < 0.05] = np.inf
    wild[rng.random(400) < 0.05] = -np.inf
    wild[rng.random(400) < 0.05] = -0.0
    neg_nan = np.array([1.0, -np.nan, np.nan, 0.0 * np.inf])  # NaNs of other bits: all null
    return {"grid cells (n, 2)": grid.reshape(-1, 2), "1-D wild": wild, "(n, 4) wild": wild.reshape(100, 4),
            "(1, 3)": np.array([[0.5, np.nan, -0.0]]), "(3, 1)": np.array([[0.5], [np.inf], [-0.0]]),
            "one value": np.array([2.5]), "NaN bits": neg_nan, "empty": np.zeros(0), "empty (0, 3)": np.zeros((0, 3)),
            "(2, 0)": np.zeros((2, 0)), "0-d": np.array(1.5), "3-D": np.arange(8.0).reshape(2, 2, 2)}


@pytest.mark.parametrize("name", list(float_arrays()))
def test_float_text_reads_back_as_jsonable_gives_it(name):
    a = float_arrays()[name]
    assert_same(json.loads(result_file._float_text(a)), reference_jsonable(a))


# ----------------------------------------------------------------------------- a hand-built result
def hand_result(mode_names=("m1", "m2"), k_step=False):
    """Three cells on [0, 3] x [0, 1]; partition atoms (a, b), DFA atoms (b, a); p_low with NaN, error with inf."""
    part = SimpleNamespace(atoms=("a", "b"), labels=np.array([0, 3, 2]),
                           cells_lower=np.array([[0.0, 0.0], [1.0, -0.0], [2.0, 0.0]]),
                           cells_upper=np.array([[1.0, 1.0], [2.0, 1.0], [3.0, 1.0]]), periodic=None)
    dfa = SimpleNamespace(atoms=("b", "a"), initial=0, accepting=np.array([False, True]),
                          delta=np.array([[0, 1, 0, 1], [1, 1, 1, 1]]))
    strategy = np.array([[0, -1], [1, 1], [-1, 0]])
    if k_step:
        strategy = np.stack([strategy, strategy[::-1]])
    syn = SimpleNamespace(strategy=strategy, p_low=np.array([0.5, np.nan, 1.0]),
                          p_up=np.array([0.75, 1.0, 1.0]), p_up_star=np.array([1.0, 1.0, 1.0]),
                          error=np.array([0.25, np.inf, -0.0]))
    return SimpleNamespace(partition=part, dfa=dfa, synthesis=syn, mode_names=mode_names,
                           space_lower=np.array([0.0, 0.0]), space_upper=np.array([3.0, 1.0]), dim_names=("x", "y"),
                           class_names=np.array(["maybe", "yes", "no"]), formula="F a", threshold=0.9, horizon=None,
                           b_margin=np.array([np.nan, 2.0, 1.25]), parameters={"eta": np.array([0.01, np.inf])},
                           diagnostics={"confidence": np.float64(1.0)}, timings={"total": 1.5})


def test_result_to_dict_of_a_hand_built_result():
    doc = result_to_dict(hand_result())
    assert_same(doc["labels"], [[], ["a", "b"], ["b"]])  # bits of (a, b): 0, 3 = both, 2 = b
    assert_same(doc["strategy"], [["m1", None], ["m2", "m2"], [None, "m1"]])  # -1: no mode
    assert_same(doc["p_low"], [0.5, None, 1.0])  # NaN -> null
    assert_same(doc["error"], [0.25, None, -0.0])  # inf -> null, -0.0 kept
    assert_same(doc["cells"]["lower"], [[0.0, 0.0], [1.0, -0.0], [2.0, 0.0]])
    assert_same(doc["classes"], ["maybe", "yes", "no"])
    assert_same(doc["b_margin"], [None, 2.0, 1.25])
    assert_same(doc["parameters"], {"eta": [0.01, None]})
    assert_same(doc["diagnostics"], {"confidence": 1.0})
    assert_same(doc["no_strategy_can"], [False, False, False])
    assert doc["strategy_by_time"] is None
    k = result_to_dict(hand_result(k_step=True))
    assert_same(k["strategy_by_time"], [[["m1", None], ["m2", "m2"], [None, "m1"]],
                                        [[None, "m1"], ["m2", "m2"], ["m1", None]]])
    assert_same(k["strategy"], doc["strategy"])  # the time-0 table
    # a fresh list per cell: changing one label does not change another of the same letter
    labels = result_file._label_lists(["a", "b"], np.array([1, 3, 1]))
    assert labels == [["a"], ["a", "b"], ["a"]]
    labels[0].append("z")
    assert labels[2] == ["a"]


def previous_npz(doc: dict, result) -> dict:
    """The arrays of result.npz as the previous ``save_result`` built them (from the document)."""
    atoms = list(doc["dfa"]["atoms"])
    letters = np.zeros(len(doc["labels"]), dtype=np.int64)
    for i, a in enumerate(atoms):
        letters |= np.array([a in lab for lab in doc["labels"]], dtype=np.int64) << i
    accepting = np.zeros(len(doc["dfa"]["delta"]), dtype=bool)
    accepting[np.asarray(doc["dfa"]["accepting"], dtype=np.int64)] = True
    out = {
        "cells_lower": np.asarray(doc["cells"]["lower"], dtype=float),
        "cells_upper": np.asarray(doc["cells"]["upper"], dtype=float),
        "strategy": np.asarray(result.synthesis.strategy, dtype=np.int64),
        "dfa_delta": np.asarray(doc["dfa"]["delta"], dtype=np.int64),
        **{k: np.asarray(doc[k], dtype=float) for k in ("p_low", "p_up", "p_up_star", "error")},
        "classes": np.asarray(doc["classes"], dtype=str),
        "no_strategy_can": np.asarray(doc["no_strategy_can"], dtype=bool),
        "modes": np.asarray(doc["modes"], dtype=str),
        "label_letters": letters, "dfa_atoms": np.asarray(atoms, dtype=str),
        "dfa_initial": np.int64(doc["dfa"]["initial"]), "dfa_accepting": accepting,
        "space_lower": np.asarray(doc["space"]["lower"], dtype=float),
        "space_upper": np.asarray(doc["space"]["upper"], dtype=float),
    }
    if "periodic" in doc["space"]:
        out["periodic"] = np.asarray(doc["space"]["periodic"], dtype=bool)
    if getattr(result, "b_margin", None) is not None:
        out["b_margin"] = np.asarray(result.b_margin, float)
    return out


def check_written(result, out: Path) -> dict:
    """save_result into ``out``; the files against result_to_dict and the previous writer; returns the document."""
    doc = result_to_dict(result)
    before = copy.deepcopy(doc)
    save_result(result, out)
    text = (out / "result.json").read_text()
    assert_same(json.loads(text), json.loads(json.dumps(doc, indent=1)))  # the content of the previous writer
    expected = previous_npz(doc, result)
    with np.load(out / "result.npz") as z:
        assert sorted(z.files) == sorted(expected)
        for k, v in expected.items():
            assert z[k].dtype == v.dtype and z[k].shape == v.shape, k
            # bytes: NaN where the document has null, with the same bits (float == would pass any NaN)
            assert z[k].tobytes() == v.tobytes(), k
    assert_same(doc, before)  # the writing did not change the document
    return doc


def test_save_result_of_a_hand_built_result(tmp_path):
    res = hand_result()
    # what save_result writes from: the per-cell floats stay arrays (no lists of them are made), NaN for null
    doc = result_file._document(res, arrays=True)
    assert all(type(doc["cells"][k]) is np.ndarray for k in ("lower", "upper"))
    assert all(type(doc[k]) is np.ndarray for k in ("p_low", "p_up", "p_up_star", "error", "b_margin"))
    np.testing.assert_array_equal(doc["error"], [0.25, np.nan, -0.0])
    check_written(res, tmp_path)
    text = (tmp_path / "result.json").read_text()
    # the indented layout outside the per-cell lists (indent=1), each per-cell list on one line
    assert text.startswith('{\n "format": "robust_imdp.result/1",\n "space": {\n  "lower": [\n   0.0,')
    line = next(s for s in text.splitlines() if s.startswith(' "p_low": '))
    assert json.loads(line[len(' "p_low": '):].rstrip(",")) == [0.5, None, 1.0]
    assert not list(tmp_path.glob(".*.part"))
    back = load_result(tmp_path)
    assert back.label_letters.tolist() == [0, 3, 1]  # DFA order (b, a): cell 1 both, cell 2 b = bit 0
    np.testing.assert_array_equal(back.p_low, [0.5, np.nan, 1.0])
    np.testing.assert_array_equal(back.strategy, [[0, -1], [1, 1], [-1, 0]])
    k = hand_result(k_step=True)
    check_written(k, tmp_path / "k")
    np.testing.assert_array_equal(load_result(tmp_path / "k").strategy_by_time, k.synthesis.strategy)
    bad = json.loads((tmp_path / "result.json").read_text())
    bad["strategy"][2][1] = "m3"  # a mode the file does not have
    with pytest.raises(InvalidInputError, match="KeyError"):
        result_file.ResultFile.from_dict(bad)


def test_a_name_equal_to_a_placeholder_is_written_as_it_is(tmp_path, monkeypatch):
    import secrets

    nonces = iter(["0" * 32, "0" * 32, "1" * 32])
    monkeypatch.setattr(secrets, "token_hex", lambda n: next(nonces))
    index = result_file._ONE_LINE.index(("p_low",))
    trap = f"robust_imdp-one-line-{'0' * 32}-{index}"
    res = hand_result(mode_names=(trap, "m2"))  # collides with the first two tries, not with the third
    doc = check_written(res, tmp_path)
    assert doc["modes"][0] == trap and doc["strategy"][0][0] == trap
    assert next(nonces, None) is None  # three tries were made


def test_when_every_try_collides_the_whole_document_is_indented(tmp_path, monkeypatch):
    import secrets

    monkeypatch.setattr(secrets, "token_hex", lambda n: "0" * 32)
    index = result_file._ONE_LINE.index(("classes",))
    res = hand_result(mode_names=(f"robust_imdp-one-line-{'0' * 32}-{index}", "m2"))
    check_written(res, tmp_path)
    assert ' "classes": [\n  "maybe",' in (tmp_path / "result.json").read_text()


def test_a_failed_write_keeps_the_previous_result(tmp_path):
    save_result(hand_result(), tmp_path)
    old = (tmp_path / "result.json").read_bytes()
    bad = hand_result()
    bad.timings = {"x": object()}  # not JSON-serialisable: json.dumps of the indented rest raises
    with pytest.raises(TypeError):
        save_result(bad, tmp_path)
    assert (tmp_path / "result.json").read_bytes() == old
    assert not list(tmp_path.glob(".*.part"))


# ----------------------------------------------------------------------------- a real run
@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from test_pipeline import tiny_problem

    from robust_imdp.pipeline.run import synthesize_from_data

    cache = tmp_path_factory.mktemp("cache")
    return synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=cache, advice=False)


def test_save_result_of_a_pipeline_run(run, tmp_path):
    from test_result_schema import SCHEMA, validate_schema

    doc = check_written(run, tmp_path)
    assert validate_schema(json.loads((tmp_path / "result.json").read_text()), SCHEMA) == []
    # result_to_dict's per-cell entries as the previous implementation built them
    part_atoms = list(run.partition.atoms)
    assert_same(doc["labels"], reference_jsonable(
        [[a for i, a in enumerate(part_atoms) if (int(v) >> i) & 1] for v in np.asarray(run.partition.labels)]))
    assert_same(doc["classes"], reference_jsonable(list(run.class_names)))
    assert_same(doc["p_low"], reference_jsonable(np.asarray(run.synthesis.p_low, float)))
    back, direct = load_result(tmp_path), result_file.ResultFile.from_dict(json.loads(json.dumps(doc, indent=1)))
    for name, value in vars(direct).items():
        if isinstance(value, np.ndarray):
            got = getattr(back, name)
            assert got.dtype == value.dtype and np.array_equal(got, value, equal_nan=value.dtype.kind == "f"), name
