"""Behaviour check for refactors: are a tree's results identical to another tree's?

    python benchmarks/identical.py record OUT [--src SRC] [--full]   # run every problem, write digests
    python benchmarks/identical.py compare A B [--ignore KEY ...]    # exit 1 if any result differs
    python benchmarks/identical.py guarantees A B                    # exit 1 if B loses a guarantee of A

``record`` runs ``robust-imdp run`` on every shipped problem file (``examples/problems``, the
newcomer problems of ``examples/newcomer`` with their data generators, the case studies written
by ``robust-imdp example``) and on small variants of the first case study that take the other code
paths (ridge and local weights, the GP route, iid noise, known nonlinear parts, per-component
settings, refinement, a finite horizon, other noise kinds, a 1-D problem). ``--src`` puts another
checkout's ``src`` first on ``PYTHONPATH`` (the tree before a change); the problem files always
come from *this* checkout, so both trees solve the same problems.

Compared: ``result.json`` with the fields that measure the run rather than the result removed
(``version``, ``timings`` and, anywhere in ``diagnostics``, keys naming seconds, times, memory or
progress; the removed key paths are listed in the digest file), and every array of ``result.npz``
(dtype, shape and bytes). The npz *file* bytes differ from run to run by design (zip entries
carry the write time), so its arrays are compared instead. The digests and the full outputs are
kept in OUT; ``compare`` prints the first differing key of a differing result.

Slow problems (the 3-D and 4-D newcomer problems, the 3-D case study at 16^3) run only with
``--full``.

``guarantees`` is for a change meant to alter the strategy but no guarantee (e.g. how modes of equal
robust value are ranked, README "What the controller does"): per problem, from both records' ``result.npz``,
every Q_yes cell of A is Q_yes in B with ``p_low`` unchanged or higher, and it reports what did change: the
strategy's entries, the cells whose ``p_up`` (the strategy's own upper bound) or class moved.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: keys (anywhere under diagnostics) that measure the run, not the result
_RUN_KEYS = re.compile(r"(seconds|_s$|^time|_time|elapsed|rss|memory|wall|progress|workers|threads)", re.I)

_VARIANT_BASE = ROOT / "examples" / "problems" / "three_mode_linear.toml"


def _variants() -> dict[str, tuple[str, str]]:
    """name -> (edit to the coarse three-mode problem, what path it takes)."""
    return {
        "v_ridge": ('[learning]\nerror_bound = "ridge"\n', "ridge weights"),
        "v_local": ("[learning]\nlocal_points = 40\n", "local optimal weights"),
        "v_local_ridge": ('[learning]\nlocal_points = 40\nerror_bound = "ridge"\n', "local ridge weights"),
        "v_gp": ('[learning]\nerror_bound = "chowdhury"\nmisspecification = 0.0\n', "GP route (Chowdhury & Gopalan)"),
        "v_iid": ("[learning]\niid_noise = true\n", "iid (sub-Gaussian) route"),
        "v_known_f": ("MODES_F", "known nonlinear parts f = [...]"),
        "v_per_component": ('[learning]\nrkhs_bound = {"1" = [6.0, 5.0], "2" = [6.0, 6.0], "3" = [5.5, 6.0]}\n'
                            'misspecification = [0.001, 0.002]\n', "per-mode and per-component settings"),
        "v_refine": ("[refine]\nmax_cells = 160\nmax_rounds = 2\n", "adaptive refinement"),
        "v_horizon": ("[spec]\nhorizon = 6\n", "finite horizon"),
        "v_uniform": ('[noise]\nkind = "uniform"\nbound = [0.01, 0.01]\n', "uniform noise"),
        "v_abstraction": ('[abstraction]\neps_rule = "paper"\neta = [0.05, 0.05]\n', "the paper's eps rule"),
    }


#: The learning table's name and its former one (a tree before the rename reads only ``[gp]``).
_LEARNING = ("[learning]", "[gp]")


def _reads_learning(env: dict) -> bool:
    """Whether the tree under test reads the ``[learning]`` table (else its problems say ``[gp]``)."""
    code = "from robust_imdp.io.problem_file import LEARNING_TABLE"
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True).returncode == 0


def _to_former_names(probs: list[tuple[str, Path]]) -> None:
    """Rename the ``[learning]`` table of every problem file to ``[gp]`` (same keys, same problem)."""
    for _name, p in probs:
        t = p.read_text()
        p.write_text(re.sub(r"^\[learning\]$", "[gp]", t, flags=re.M))


def _edit_toml(text: str, edit: str) -> str:
    """Apply an edit to a problem text: table keys in ``edit`` replace or join those of the same table."""
    if edit == "MODES_F":
        for m in ("1", "2", "3"):
            text = text.replace(f'[modes."{m}"]\nA = [[0.0, 0.0], [0.0, 0.0]]\nb = [0.0, 0.0]\n',
                                f'[modes."{m}"]\nf = ["0.0*sin(x1) + 0.0*x2", "0.0*cos(x2)"]\n')
        return text
    table, body = edit.split("\n", 1)
    lines = text.splitlines(keepends=True)
    if table in _LEARNING:  # the learning table under the name the text uses
        table = next((t for t in _LEARNING if t + "\n" in lines), table)
        edit = table + "\n" + body
    new_keys = {ln.split("=", 1)[0].strip(): ln for ln in body.splitlines(keepends=True) if "=" in ln}
    if table + "\n" not in lines:
        return text.rstrip("\n") + "\n\n" + edit
    out, inside = [], False
    for ln in lines:
        if ln.startswith("["):
            if inside:  # keys not present yet join at the table's end
                out.extend(new_keys.values())
                new_keys = {}
            inside = ln == table + "\n"
            out.append(ln)
            continue
        key = ln.split("=", 1)[0].strip() if "=" in ln else None
        if inside and key in new_keys:
            out.append(new_keys.pop(key))
            continue
        if inside and table == "[noise]" and key in ("sigma",):
            continue  # another noise kind: its own keys only
        out.append(ln)
    if inside:
        out.extend(new_keys.values())
    return "".join(out)


def _problems(work: Path, full: bool, env: dict) -> list[tuple[str, Path]]:
    """Write every problem (and its data) under ``work``; return (name, problem file)."""
    probs: list[tuple[str, Path]] = []
    src = ROOT / "examples" / "problems"
    d = work / "problems"
    d.mkdir(parents=True)
    for f in sorted(src.iterdir()):
        shutil.copy(f, d / f.name)
    for f in sorted(d.glob("*.toml")):
        probs.append((f.stem, f))
    # variants of the first case study on a coarse grid (64 cells)
    base = _VARIANT_BASE.read_text().replace("cell_size = [0.125, 0.125]", "cell_size = [0.5, 0.5]")
    for name, (edit, _what) in _variants().items():
        p = d / f"{name}.toml"
        p.write_text(_edit_toml(base, edit))
        probs.append((name, p))
    # a 1-D problem
    one = work / "one_d"
    one.mkdir()
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 4.0, 200)
    with open(one / "d.csv", "w") as fh:
        fh.write("x_1,u,x_next_1\n")
        for xi, vi in zip(x, rng.uniform(-0.01, 0.01, 200)):
            fh.write(f"{float(xi)!r},a,{float(0.5 * xi + 1.0 + 0.05 * np.sin(xi) + vi)!r}\n")
    sys.path.insert(0, str(ROOT / "tests"))
    from problem_texts import ONE_D  # noqa: E402

    (one / "one_d.toml").write_text(ONE_D)
    probs.append(("one_d", one / "one_d.toml"))
    # newcomer problems (data from their generators, run in their folder)
    nc = work / "newcomer"
    nc.mkdir()
    for f in (ROOT / "examples" / "newcomer").glob("*.toml"):
        shutil.copy(f, nc / f.name)
    gens = [("robot2d_data.py", [])] + ([("unicycle3d_data.py", ["plain", "uni.csv"]), ("di4d_data.py", [])]
                                        if full else [])
    for gen, args in gens:
        subprocess.run([sys.executable, str(ROOT / "examples" / "newcomer" / gen), *args], cwd=nc, check=True, env=env)
    for stem in ["robot2d_16", "robot2d_32"] + (["unicycle3d_16", "di4d_8"] if full else []):
        probs.append((stem, nc / f"{stem}.toml"))
    # the case studies as `robust-imdp example` writes them (the 3-D one only with --full)
    ex = work / "example"
    for name in ["three_mode_linear", "four_mode_nonlinear"] + (["unicycle_3d"] if full else []):
        subprocess.run([_cli(), "example", name, "--out", str(ex / name)], check=True, env=env,
                       stdout=subprocess.DEVNULL)
        p = ex / name / f"{name}.toml"
        if name == "unicycle_3d":  # 16^3 instead of 64^3: the same code paths, minutes instead of a quarter hour
            t = p.read_text()
            t = re.sub(r"cell_size = \[[^\]]*\]", "cell_size = [0.25, 0.25, 0.39269908169872414]", t)
            p.write_text(t)
        probs.append((f"example_{name}", p))
    if not _reads_learning(env):
        _to_former_names(probs)
    return probs


def _cli() -> str:
    return str(Path(sys.executable).parent / "robust-imdp")


def _strip(obj, path: str, removed: list):
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            p = f"{path}.{k}" if path else k
            if (path == "" and k in ("version", "timings")) or (path.startswith("diagnostics") and _RUN_KEYS.search(k)):
                removed.append(p)
                continue
            out[k] = _strip(v, p, removed)
        return out
    if isinstance(obj, list):
        return [_strip(v, f"{path}[]", removed) for v in obj]
    return obj


def digest(out_dir: Path) -> dict:
    """Digests of one result directory: the stripped result.json and every npz array."""
    doc = json.loads((out_dir / "result.json").read_text())
    removed: list[str] = []
    kept = _strip(doc, "", removed)
    canon = json.dumps(kept, sort_keys=True, separators=(",", ":"))
    arrays = {}
    with np.load(out_dir / "result.npz") as z:
        for k in sorted(z.files):
            a = z[k]
            arrays[k] = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode() + np.ascontiguousarray(a).tobytes()).hexdigest()
    return {"json": hashlib.sha256(canon.encode()).hexdigest(), "npz": arrays,
            "removed": sorted(set(removed))}


def record(out: Path, src: str | None, full: bool, only: list[str] | None) -> int:
    out = out.resolve()
    previous = {}
    if only and (out / "digests.json").exists():  # add to (or redo some of) an earlier record
        previous = json.loads((out / "digests.json").read_text())["problems"]
        shutil.rmtree(out / "work")
    elif out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = str(Path(src).resolve()) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    work = out / "work"
    probs = _problems(work, full, env)
    digests, rc = dict(previous), 0
    for name, prob in probs:
        if only and name not in only:
            continue
        t0 = time.perf_counter()
        res = out / "results" / name
        shutil.rmtree(res, ignore_errors=True)
        p = subprocess.run([_cli(), "run", str(prob), "--out", str(res), "--no-figures", "--quiet"], env=env, cwd=prob.parent,
                           capture_output=True, text=True)
        dt = time.perf_counter() - t0
        if p.returncode not in (0,) or not (res / "result.json").exists():
            print(f"{name}: exit {p.returncode}\n{p.stderr[-2000:]}", flush=True)
            digests[name] = {"error": p.returncode, "stderr": p.stderr[-2000:]}
            rc = 1
            continue
        digests[name] = {**digest(res), "seconds": round(dt, 1)}
        print(f"{name}: {dt:.1f} s  json {digests[name]['json'][:12]}", flush=True)
    (out / "digests.json").write_text(json.dumps({"src": src or str(ROOT / "src"), "full": full,
                                                  "problems": digests}, indent=1))
    return rc


def _first_difference(a, b, path=""):
    if type(a) is not type(b):
        return path or "(root)"
    if isinstance(a, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                return f"{path}.{k}"
            d = _first_difference(a[k], b[k], f"{path}.{k}")
            if d:
                return d
        return None
    if isinstance(a, list):
        if len(a) != len(b):
            return f"{path} (length {len(a)} vs {len(b)})"
        for i, (x, y) in enumerate(zip(a, b)):
            d = _first_difference(x, y, f"{path}[{i}]")
            if d:
                return d
        return None
    return None if a == b else path


def _drop(doc: dict, dotted: str) -> None:
    """Remove the key at ``dotted`` (e.g. ``diagnostics.advice``) from ``doc`` where it exists."""
    *parents, last = dotted.split(".")
    for k in parents:
        doc = doc.get(k) if isinstance(doc, dict) else None
        if doc is None:
            return
    if isinstance(doc, dict):
        doc.pop(last, None)


def compare(a: Path, b: Path, ignore: list[str] | None = None) -> int:
    """Compare two records; ``ignore``: result.json keys (dotted paths) left out of the comparison, for a
    change that is meant to alter them only (the npz arrays are always compared)."""
    ignore = list(ignore or [])
    da = json.loads((a / "digests.json").read_text())["problems"]
    db = json.loads((b / "digests.json").read_text())["problems"]
    rows, bad = [], 0
    for name in sorted(set(da) | set(db)):
        x, y = da.get(name), db.get(name)
        if x is None or y is None or "error" in x or "error" in y:
            rows.append((name, "missing or failed"))
            bad += 1
            continue
        diff = [k for k in sorted(set(x["npz"]) | set(y["npz"])) if x["npz"].get(k) != y["npz"].get(k)]
        if x["json"] != y["json"]:
            ja = _strip(json.loads((a / "results" / name / "result.json").read_text()), "", [])
            jb = _strip(json.loads((b / "results" / name / "result.json").read_text()), "", [])
            for key in ignore:
                _drop(ja, key)
                _drop(jb, key)
            where = _first_difference(ja, jb)
            if where is not None:
                diff.append(f"result.json at {where}")
        if x["removed"] != y["removed"]:
            diff.append(f"removed run fields differ: {sorted(set(x['removed']) ^ set(y['removed']))}")
        rows.append((name, "identical" if not diff else "DIFFERS: " + ", ".join(diff)))
        bad += bool(diff)
    for name, what in rows:
        print(f"{name:32s} {what}")
    print(f"{len(rows) - bad} of {len(rows)} identical" + (f" (result.json without {', '.join(ignore)})" if ignore else ""))
    return 1 if bad else 0


def guarantees(a: Path, b: Path) -> int:
    """B keeps every guarantee of A (module docstring); prints the changes per problem."""
    da = json.loads((a / "digests.json").read_text())["problems"]
    db = json.loads((b / "digests.json").read_text())["problems"]
    bad = 0
    for name in sorted(set(da) | set(db)):
        x, y = da.get(name), db.get(name)
        if x is None or y is None or "error" in x or "error" in y:
            print(f"{name:32s} missing or failed")
            bad += 1
            continue
        with np.load(a / "results" / name / "result.npz") as za, np.load(b / "results" / name / "result.npz") as zb:
            A = {k: za[k] for k in ("p_low", "p_up", "classes", "strategy")}
            B = {k: zb[k] for k in ("p_low", "p_up", "classes", "strategy")}
        if A["p_low"].shape != B["p_low"].shape:
            print(f"{name:32s} LOST: different cells ({A['p_low'].size} vs {B['p_low'].size})")
            bad += 1
            continue
        yes = A["classes"] == "yes"
        lost = int(np.count_nonzero(yes & (B["classes"] != "yes")))
        drop = float(np.max(A["p_low"][yes] - B["p_low"][yes], initial=0.0))
        changed = int(np.count_nonzero(A["strategy"] != B["strategy"])) if A["strategy"].shape == B["strategy"].shape \
            else -1
        what = (f"Q_yes {int(yes.sum())} -> {int(np.count_nonzero(B['classes'] == 'yes'))} (lost {lost}), "
                f"largest p_low drop on Q_yes {drop:.3g}, strategy entries changed {changed}, p_up changed in "
                f"{int(np.count_nonzero(A['p_up'] != B['p_up']))} cells, classes changed in "
                f"{int(np.count_nonzero(A['classes'] != B['classes']))}")
        ok = lost == 0 and drop <= 0.0
        bad += not ok
        print(f"{name:32s} {'kept' if ok else 'LOST'}: {what}")
    print(f"{'every guarantee kept' if not bad else f'{bad} problem(s) lost a guarantee'}")
    return 1 if bad else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("out", type=Path)
    r.add_argument("--src", help="another checkout's src directory, first on PYTHONPATH")
    r.add_argument("--full", action="store_true", help="also the slow 3-D and 4-D problems")
    r.add_argument("--only", nargs="*", help="only these problem names")
    c = sub.add_parser("compare")
    c.add_argument("a", type=Path)
    c.add_argument("b", type=Path)
    c.add_argument("--ignore", nargs="+", metavar="KEY", default=[],
                   help="result.json keys (dotted, e.g. diagnostics.advice) a change is meant to alter")
    g = sub.add_parser("guarantees")
    g.add_argument("a", type=Path)
    g.add_argument("b", type=Path)
    args = ap.parse_args(argv)
    if args.cmd == "record":
        return record(args.out, args.src, args.full, args.only)
    if args.cmd == "guarantees":
        return guarantees(args.a, args.b)
    return compare(args.a, args.b, args.ignore)


if __name__ == "__main__":
    sys.exit(main())
