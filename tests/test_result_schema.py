"""docs/result.schema.json: the published schema of result.json, and written files checked against it.

The project does not depend on ``jsonschema``; :func:`validate_schema` implements the keywords
the schema uses (listed in ``KEYWORDS``), and a test checks that the schema uses no other, so
no constraint can be ignored silently. Real files are checked here (a synthetic result) and in
``test_export.py`` (a pipeline run through the command line).
"""

import copy
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_io import _fake_result  # noqa: E402  (a hand-built 2-cell result)

ROOT = Path(__file__).parents[1]
SCHEMA = json.loads((ROOT / "docs" / "result.schema.json").read_text())

#: Keywords validate_schema enforces, and annotations it may skip.
KEYWORDS = {"type", "properties", "required", "additionalProperties", "items", "minItems", "maxProperties",
            "enum", "const", "minimum", "maximum", "anyOf", "$ref"}
ANNOTATIONS = {"$schema", "$id", "title", "description", "$defs"}

_TYPES = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
}


def validate_schema(value, schema, root=None, path="$") -> list:
    """Errors (``"$.path: what"``) of ``value`` against ``schema`` (JSON Schema subset KEYWORDS)."""
    root = schema if root is None else root
    if "$ref" in schema:
        target = root
        for part in schema["$ref"].removeprefix("#/").split("/"):
            target = target[part]
        return validate_schema(value, target, root, path)
    errors = []
    if "type" in schema:
        types = schema["type"] if isinstance(schema["type"], list) else [schema["type"]]
        if not any(_TYPES[t](value) for t in types):
            return [f"{path}: expected {' or '.join(types)}, got {type(value).__name__}"]
    if "const" in schema and value != schema["const"]:
        errors.append(f"{path}: expected {schema['const']!r}, got {value!r}")
    if "enum" in schema and value not in schema["enum"]:
        errors.append(f"{path}: {value!r} not in {schema['enum']}")
    if "minimum" in schema and _TYPES["number"](value) and value < schema["minimum"]:
        errors.append(f"{path}: {value} < minimum {schema['minimum']}")
    if "maximum" in schema and _TYPES["number"](value) and value > schema["maximum"]:
        errors.append(f"{path}: {value} > maximum {schema['maximum']}")
    if "anyOf" in schema and all(validate_schema(value, s, root, path) for s in schema["anyOf"]):
        errors.append(f"{path}: matches none of anyOf")
    if isinstance(value, dict):
        if "maxProperties" in schema and len(value) > schema["maxProperties"]:
            errors.append(f"{path}: more than {schema['maxProperties']} properties")
        errors += [f"{path}: missing {k!r}" for k in schema.get("required", []) if k not in value]
        props = schema.get("properties", {})
        extra = schema.get("additionalProperties", True)
        for k, v in value.items():
            if k in props:
                errors += validate_schema(v, props[k], root, f"{path}.{k}")
            elif extra is False:
                errors.append(f"{path}: unexpected key {k!r}")
            elif isinstance(extra, dict):
                errors += validate_schema(v, extra, root, f"{path}.{k}")
    if isinstance(value, list):
        if "minItems" in schema and len(value) < schema["minItems"]:
            errors.append(f"{path}: fewer than {schema['minItems']} items")
        if "items" in schema:
            for i, v in enumerate(value):
                errors += validate_schema(v, schema["items"], root, f"{path}[{i}]")
    return errors


def _keywords(schema, found, in_properties=False):
    if isinstance(schema, dict):
        for k, v in schema.items():
            if in_properties:  # keys of "properties" / "$defs" are names, not keywords
                _keywords(v, found)
                continue
            found.add(k)
            _keywords(v, found, in_properties=k in ("properties", "$defs"))
    elif isinstance(schema, list):
        for v in schema:
            _keywords(v, found)
    return found


def test_schema_uses_only_keywords_the_validator_enforces():
    assert _keywords(SCHEMA, set()) - KEYWORDS - ANNOTATIONS == set()


def synthetic_doc():
    """A result.json as written by io.save_result for a hand-built 2x1 result with diagnostics."""
    from robust_imdp.io.files import result_to_dict

    res = _fake_result()
    res.diagnostics = {
        "error_bound": "optimal", "confidence": 1.0, "statement": "with probability 1, ...",
        "cell_half_width": [0.5, 0.5], "successors_per_row": 2.0,
        "eps": [{"mode": "m1", "component": 1, "median": 0.1, "max": float("nan"), "median_over_half_cell": 0.2}],
        "assumption": {"rkhs_bound": 2.0, "lengthscale": [1.0, 1.0], "misspecification": 0.0,
                       "min_norm": [{"mode": "m1", "component": 1, "minimum": 0.5, "n_points": 3}]},
    }
    return json.loads(json.dumps(result_to_dict(res)))  # through JSON: what a reader sees


def test_written_result_follows_the_schema(tmp_path):
    from robust_imdp.io.files import save_result

    doc = synthetic_doc()
    assert validate_schema(doc, SCHEMA) == []
    assert doc["diagnostics"]["eps"][0]["max"] is None  # NaN is written as null, which the schema allows
    save_result(_fake_result(), tmp_path)  # no diagnostics at all: the empty object is allowed
    assert validate_schema(json.loads((tmp_path / "result.json").read_text()), SCHEMA) == []


@pytest.mark.parametrize("change,error", [
    (lambda d: d.pop("diagnostics"), "$: missing 'diagnostics'"),
    (lambda d: d.update(extra=1), "$: unexpected key 'extra'"),
    (lambda d: d.update(format="robust_imdp.result/2"), "$.format: expected 'robust_imdp.result/1'"),
    (lambda d: d["p_low"].__setitem__(0, 1.5), "$.p_low[0]: 1.5 > maximum 1"),
    (lambda d: d["classes"].__setitem__(1, "unknown"), "$.classes[1]: 'unknown' not in"),
    (lambda d: d.update(horizon=0), "$.horizon: matches none of anyOf"),
    (lambda d: d["dfa"].update(initial=True), "$.dfa.initial: expected integer, got bool"),
    (lambda d: d["strategy"][0].__setitem__(0, 3), "$.strategy[0][0]: matches none of anyOf"),
    (lambda d: d["diagnostics"].pop("statement"), "$.diagnostics: matches none of anyOf"),
    (lambda d: d["diagnostics"]["assumption"]["min_norm"][0].update(minimum="big"),
     "$.diagnostics: matches none of anyOf"),
    (lambda d: d["timings"].update(total=-1.0), "$.timings.total: -1.0 < minimum 0"),
    (lambda d: d["cells"]["lower"][0].clear(), "$.cells.lower[0]: fewer than 1 items"),
])
def test_schema_rejects_broken_documents(change, error):
    doc = copy.deepcopy(synthetic_doc())
    change(doc)
    errors = validate_schema(doc, SCHEMA)
    assert any(e.startswith(error) for e in errors), errors


def test_per_cell_lengths_are_checked_by_the_reader():
    # What the schema cannot say (one entry per cell) the reader checks.
    from robust_imdp.errors import DimensionError
    from robust_imdp.io.files import ResultFile

    doc = synthetic_doc()
    ResultFile.from_dict(doc)
    doc["p_low"] = doc["p_low"][:1]
    with pytest.raises(DimensionError, match="inconsistent shapes"):
        ResultFile.from_dict(doc)
