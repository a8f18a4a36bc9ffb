"""A failed or interrupted command leaves the previous complete result exactly as it was.

``run base.toml --out k`` then a failing ``run typo.toml --out k`` (formula syntax error, missing key,
NaN data, refuted B, Ctrl-C at any stage, including during the swap of the files) must leave result.json,
result.npz, the figures and the validation files byte-identical; ``simulate`` and ``suggest`` likewise
(STYLE.md rule 17; io.result_file.staged_outputs). A run that succeeds replaces the whole set, so the
previous result's validation never sits beside the new result.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

import robust_imdp.io.result_file as result_file
from robust_imdp.cli import main
from problem_texts import write_one_d

# x+ = 0.5 x + 1 + 0.1 sin(x) + v (the data's system, problem_texts.write_one_d), as a --true-system file
TRUE_SYSTEM = """
import numpy as np

class OneD:
    mode_names = ("a",)

    def step(self, x, modes, rng):
        return 0.5 * x + 1 + 0.1 * np.sin(x) + rng.uniform(-0.01, 0.01, x.shape)
"""


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """A folder with the 1-D problem, its data, a true system and k/ = a complete run + simulate."""
    d = tmp_path_factory.mktemp("base")
    write_one_d(d)
    (d / "truth.py").write_text(TRUE_SYSTEM)
    assert main(["run", str(d / "p.toml"), "--out", str(d / "k"), "--quiet", "--advice", "off"]) == 0
    assert main(["simulate", str(d / "k"), "--true-system", f"{d / 'truth.py'}:OneD", "--n-per-cell", "4",
                 "--paths", "3"]) == 0
    (d / "k" / "notes.txt").write_text("mine")  # a file of the user's: never touched
    return d


@pytest.fixture
def work(base, tmp_path, capsys):
    shutil.copytree(base, tmp_path / "w")
    capsys.readouterr()
    return tmp_path / "w"


def snapshot(k: Path) -> dict:
    """Every file in k outside the cache, by relative path -> bytes (staging leftovers would show here)."""
    return {str(p.relative_to(k)): p.read_bytes() for p in sorted(k.rglob("*"))
            if p.is_file() and "cache" not in p.relative_to(k).parts}


def test_the_base_result_has_every_kind_of_output(base):
    names = set(snapshot(base / "k"))
    assert names == {"result.json", "result.npz", "bounds.png", "validation.json", "trajectories.png", "notes.txt"}


def _typo(work: Path, old: str, new: str) -> Path:
    text = (work / "p.toml").read_text()
    assert old in text
    (work / "typo.toml").write_text(text.replace(old, new))
    return work / "typo.toml"


def _nan_data(work: Path) -> Path:
    lines = (work / "d.csv").read_text().splitlines()
    first = lines[1].split(",")
    lines[1] = ",".join([first[0], first[1], "nan"])
    (work / "nan.csv").write_text("\n".join(lines) + "\n")
    return _typo(work, 'path = "d.csv"', 'path = "nan.csv"')


FAILURES = {
    "formula syntax error": (lambda w: _typo(w, 'formula = "F des"', 'formula = "F (des"'), "cannot parse formula"),
    "missing key": (lambda w: _typo(w, "cell_size = [0.25]\n", ""), "cell_size"),
    "NaN data": (_nan_data, "nan"),
    "refuted B": (lambda w: _typo(w, "rkhs_bound = 1.0", "rkhs_bound = 0.001"), "rkhs_bound"),
    "unknown region": (lambda w: _typo(w, 'formula = "F des"', 'formula = "F goal"'), "goal"),
}


@pytest.mark.parametrize("kind", list(FAILURES))
def test_a_failing_run_leaves_the_previous_result_byte_identical(work, capsys, kind):
    make, said = FAILURES[kind]
    before = snapshot(work / "k")
    code = main(["run", str(make(work)), "--out", str(work / "k"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and said in err.lower(), err
    assert snapshot(work / "k") == before


def test_a_bad_formula_option_leaves_the_previous_result(work, capsys):
    before = snapshot(work / "k")
    assert main(["run", str(work / "p.toml"), "--out", str(work / "k"), "--formula", "F (des"]) == 1
    assert snapshot(work / "k") == before


def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def _after(real, when="after"):
    """``real`` that raises KeyboardInterrupt after (or before) doing its work."""
    def wrapped(*args, **kwargs):
        if when == "before":
            raise KeyboardInterrupt
        real(*args, **kwargs)
        raise KeyboardInterrupt
    return wrapped


@pytest.mark.parametrize("where", ["synthesize", "first figure written", "figures written", "result.npz written",
                                   "result written"])
def test_ctrl_c_at_any_stage_of_a_run_leaves_the_previous_result(work, capsys, monkeypatch, where):
    import matplotlib.figure

    import robust_imdp.io.files as files
    import robust_imdp.pipeline.run as pipeline
    import robust_imdp.plotting as plotting

    if where == "synthesize":
        monkeypatch.setattr(pipeline, "synthesize_from_data", _interrupt)
    elif where == "first figure written":
        monkeypatch.setattr(matplotlib.figure.Figure, "savefig", _after(matplotlib.figure.Figure.savefig))
    elif where == "figures written":
        monkeypatch.setattr(plotting, "save_figures", _after(plotting.save_figures))
    elif where == "result.npz written":
        real = result_file._atomic_write

        def write(path, fn):
            real(path, fn)
            if path.name == "result.npz":
                raise KeyboardInterrupt
        monkeypatch.setattr(result_file, "_atomic_write", write)
    else:
        monkeypatch.setattr(files, "save_result", _after(files.save_result))
    # a changed threshold: the new result would differ from the old one in result.json
    before = snapshot(work / "k")
    code = main(["run", str(work / "p.toml"), "--out", str(work / "k"), "--quiet", "--threshold", "0.5",
                 "--advice", "off"])
    err = capsys.readouterr().err
    assert code == 130, err
    assert "previous result is unchanged" in err
    assert snapshot(work / "k") == before


class _ReplaceInterrupted:
    """``os`` for io.result_file, whose ``replace`` raises KeyboardInterrupt at the ``at``-th rename of the
    swap (a rename into or out of the output directory ``out``); all other calls go to ``os``."""

    def __init__(self, out: Path, at: int):
        self.out, self.at, self.seen, self.raised = out.resolve(), at, 0, False

    def __getattr__(self, name):
        return getattr(os, name)

    def replace(self, src, dst):
        if self.out in (Path(src).resolve().parent, Path(dst).resolve().parent):
            self.seen += 1
            if self.seen == self.at:
                self.raised = True
                raise KeyboardInterrupt
        return os.replace(src, dst)


# the base holds 5 outputs (result.json, result.npz, bounds.png, validation.json, trajectories.png) and a new
# run writes 3: 5 renames out of k, then 3 into it
@pytest.mark.parametrize("at", range(1, 9))
def test_ctrl_c_during_the_swap_puts_the_previous_result_back(work, capsys, monkeypatch, at):
    fake = _ReplaceInterrupted(work / "k", at)
    monkeypatch.setattr(result_file, "os", fake)
    before = snapshot(work / "k")
    code = main(["run", str(work / "p.toml"), "--out", str(work / "k"), "--quiet", "--threshold", "0.5",
                 "--advice", "off"])
    assert code == 130, capsys.readouterr().err
    assert fake.raised  # the interrupt came at that rename of the swap (the roll-back's renames follow it)
    assert snapshot(work / "k") == before


def test_a_successful_run_replaces_the_whole_result_and_leaves_no_staging(work, capsys):
    old = snapshot(work / "k")
    code = main(["run", str(work / "p.toml"), "--out", str(work / "k"), "--quiet", "--threshold", "0.5",
                 "--advice", "off"])
    assert code == 0, capsys.readouterr().err
    new = snapshot(work / "k")
    # the previous result's validation is gone with it; the user's file stays; no hidden folder is left
    assert set(new) == {"result.json", "result.npz", "bounds.png", "notes.txt"}
    assert new["notes.txt"] == old["notes.txt"] and new["result.json"] != old["result.json"]
    assert sorted(p.name for p in (work / "k").iterdir()) == ["bounds.png", "cache", "notes.txt", "result.json",
                                                             "result.npz"]
    from robust_imdp.io.files import load_result

    assert load_result(work / "k").threshold == 0.5


def test_a_failing_first_run_leaves_nothing(tmp_path, capsys):
    write_one_d(tmp_path)
    (tmp_path / "typo.toml").write_text((tmp_path / "p.toml").read_text().replace("F des", "F (des"))
    assert main(["run", str(tmp_path / "typo.toml"), "--out", str(tmp_path / "new"), "--quiet"]) == 1
    assert not (tmp_path / "new").exists()


# --------------------------------------------------------------------------- simulate
@pytest.mark.parametrize("where", ["step raises", "figure"])
def test_a_failing_or_interrupted_simulate_leaves_the_previous_validation(work, capsys, monkeypatch, where):
    before = snapshot(work / "k")
    if where == "step raises":
        (work / "bad.py").write_text("class Bad:\n    mode_names = ('a',)\n    def step(self, x, m, rng):\n"
                                     "        raise RuntimeError('broken')\n")
        code = main(["simulate", str(work / "k"), "--true-system", f"{work / 'bad.py'}:Bad", "--n-per-cell", "2"])
        assert code == 1
    else:  # validation.json is written into the stage, then Ctrl-C while the figure is drawn
        import robust_imdp.plotting as plotting

        monkeypatch.setattr(plotting, "plot_trajectory_panels", _interrupt)
        code = main(["simulate", str(work / "k"), "--true-system", f"{work / 'truth.py'}:OneD", "--n-per-cell", "2",
                     "--seed", "5"])
        assert code == 130
    assert snapshot(work / "k") == before


def test_simulate_replaces_validation_and_figure_together(work, capsys):
    old = snapshot(work / "k")
    code = main(["simulate", str(work / "k"), "--true-system", f"{work / 'truth.py'}:OneD", "--n-per-cell", "2",
                 "--seed", "5", "--no-figures"])
    assert code == 0, capsys.readouterr().err
    new = snapshot(work / "k")
    # the old figure showed the old validation's runs: it goes with it; the result is untouched
    assert "trajectories.png" not in new and new["validation.json"] != old["validation.json"]
    assert all(new[n] == old[n] for n in ("result.json", "result.npz", "bounds.png", "notes.txt"))


# --------------------------------------------------------------------------- suggest
def test_an_interrupted_suggest_leaves_the_previous_suggestions(work, capsys, monkeypatch):
    import robust_imdp.synthesis.suggest as suggest

    args = ["suggest", str(work / "k"), "--problem", str(work / "p.toml"), "--budget", "3"]
    assert main(args) == 0, capsys.readouterr().err
    before = snapshot(work / "k")
    assert "suggestions.csv" in before
    real = suggest.write_requests

    def half_written(requests, path, names):
        real(requests[:1], path, names)
        raise KeyboardInterrupt
    monkeypatch.setattr(suggest, "write_requests", half_written)
    assert main(args) == 130
    assert snapshot(work / "k") == before


def test_stage_commit_roll_back_restores_a_file_replaced_by_name(tmp_path, monkeypatch):
    # The library function on its own: the stage's file list and the owned names overlap in part, an
    # owned file the new outputs lack is removed on success, and a failed rename restores everything.
    out = tmp_path / "o"
    out.mkdir()
    for name, text in (("a.txt", "old a"), ("b.txt", "old b"), ("keep.txt", "mine")):
        (out / name).write_text(text)
    with result_file.staged_outputs(out, ("a.txt", "b.txt")) as stage:
        (stage.path / "a.txt").write_text("new a")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt", "keep.txt"]
    assert (out / "a.txt").read_text() == "new a" and stage.written == [out / "a.txt"]
    failing = _ReplaceInterrupted(out, 2)
    monkeypatch.setattr(result_file, "os", failing)
    with pytest.raises(KeyboardInterrupt):
        with result_file.staged_outputs(out, ("a.txt", "b.txt")) as stage:
            (stage.path / "a.txt").write_text("newer a")
            (stage.path / "b.txt").write_text("new b")
    assert {p.name: p.read_text() for p in out.iterdir()} == {"a.txt": "new a", "keep.txt": "mine"}
    with pytest.raises(ValueError):  # an error inside the block: nothing is swapped, the stage is removed
        with result_file.staged_outputs(out, ("a.txt",)) as stage:
            (stage.path / "a.txt").write_text("x")
            raise ValueError("bad")
    assert {p.name: p.read_text() for p in out.iterdir()} == {"a.txt": "new a", "keep.txt": "mine"}
    assert np.all([not p.name.startswith(".robust-imdp") for p in out.iterdir()])


def test_ctrl_c_is_held_back_during_the_swap_and_delivered_after_it():
    import signal

    done = []
    with pytest.raises(KeyboardInterrupt):
        with result_file._sigint_deferred():
            os.kill(os.getpid(), signal.SIGINT)  # a real Ctrl-C, in the middle of the renames
            done.append("the block ran to its end")
    assert done == ["the block ran to its end"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is put back


def test_a_real_ctrl_c_during_the_swap_lets_it_finish_and_says_so(work, capsys, monkeypatch):
    # SIGINT itself (not a raised KeyboardInterrupt) at the first rename of the swap: the handler holds it,
    # the swap completes, then the command stops with 130 and says the new result is there
    import signal

    class Kill(_ReplaceInterrupted):
        def replace(self, src, dst):
            if self.out in (Path(src).resolve().parent, Path(dst).resolve().parent) and not self.raised:
                self.raised = True
                os.kill(os.getpid(), signal.SIGINT)
            return os.replace(src, dst)

    monkeypatch.setattr(result_file, "os", Kill(work / "k", 1))
    code = main(["run", str(work / "p.toml"), "--out", str(work / "k"), "--quiet", "--threshold", "0.5",
                 "--advice", "off"])
    err = capsys.readouterr().err
    assert code == 130 and "interrupted after the new result was complete" in err, err
    from robust_imdp.io.files import load_result

    assert load_result(work / "k").threshold == 0.5  # the new result, whole
    assert sorted(p.name for p in (work / "k").iterdir()) == ["bounds.png", "cache", "notes.txt", "result.json",
                                                             "result.npz"]  # no staging or backup folder left


# --------------------------------------------------------------------------- after SIGKILL
def _dead_pid() -> int:
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_a_killed_commands_staging_folder_is_removed_by_the_next_one_and_a_live_ones_kept(tmp_path):
    dead, live = _dead_pid(), os.getpid()
    (tmp_path / "result.json").write_text("old")
    stale = tmp_path / f"{result_file.STAGE_PREFIX}{dead}-abc"
    mine = tmp_path / f"{result_file.STAGE_PREFIX}{live}-abc"
    for f in (stale, mine):
        f.mkdir()
        (f / "result.npz").write_text("half")
    with result_file.staged_outputs(tmp_path, ("result.json", "result.npz")) as stage:
        (stage.path / "result.json").write_text("new")
    assert not stale.exists() and (mine / "result.npz").read_text() == "half"
    assert (tmp_path / "result.json").read_text() == "new"


def test_a_swap_cut_by_sigkill_is_rolled_back_or_finished_by_the_next_command(tmp_path):
    owned = ("result.json", "result.npz", "p_low.png")
    dead = _dead_pid()
    # cut before result.json arrived: the new result.npz and p_low.png are in, the old files in the backup
    backup = tmp_path / f"{result_file.BACKUP_PREFIX}{dead}-x"
    backup.mkdir()
    (backup / "result.json").write_text("old json")
    (backup / "result.npz").write_text("old npz")
    (tmp_path / "result.npz").write_text("new npz")
    (tmp_path / "p_low.png").write_text("new png")  # no old counterpart: it goes
    (tmp_path / "mine.txt").write_text("user")
    result_file.recover_stale(tmp_path, owned)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt", "result.json", "result.npz"]
    assert (tmp_path / "result.json").read_text() == "old json" and (tmp_path / "result.npz").read_text() == "old npz"
    # cut after result.json arrived: the new result is complete, only the backup goes
    backup.mkdir()
    (backup / "result.npz").write_text("older npz")
    (tmp_path / "result.json").write_text("new json")
    result_file.recover_stale(tmp_path, owned)
    assert not backup.exists() and (tmp_path / "result.npz").read_text() == "old npz"
    # a live process's backup is its own swap in progress: untouched
    live = tmp_path / f"{result_file.BACKUP_PREFIX}{os.getpid()}-y"
    live.mkdir()
    (live / "result.json").write_text("x")
    assert result_file.recover_stale(tmp_path, owned) == [] and (live / "result.json").exists()
