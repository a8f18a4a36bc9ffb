"""What a new user met through the Python API and the command line: clear errors at construction, a
controller that answers one state with one cell, a batch form of ``act``, messages that agree with the
files they describe, figures in every dimension."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from robust_imdp.cli import main  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from test_plotting import doc_nd  # noqa: E402

# a true system for doc_nd's modes "1", "2", "3" in any dimension: contract towards the centre
CONTRACT = """
import numpy as np

class Contract:
    mode_names = ("1", "2", "3")

    def step(self, x, modes, rng):
        return 0.8 * x + rng.uniform(-0.05, 0.05, x.shape)
"""


@pytest.mark.parametrize("d", [1, 3])
def test_simulate_draws_trajectories_in_every_dimension(tmp_path, capsys, d):
    # 3-D results got no trajectories.png and no word about it (only 2-D was drawn)
    (tmp_path / "result.json").write_text(json.dumps(doc_nd(d, h=1.0)))
    (tmp_path / "sys.py").write_text(CONTRACT)
    code = main(["simulate", str(tmp_path), "--true-system", f"{tmp_path / 'sys.py'}:Contract", "--n-per-cell", "2",
                 "--max-steps", "10", "--paths", "4"])
    assert code in (0, 1), capsys.readouterr().err  # doc_nd's bounds are synthetic: the check may flag cells
    png = tmp_path / "trajectories.png"
    assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000


def test_trajectory_panels_project_every_pair_of_the_first_coordinates():
    import matplotlib.pyplot as plt

    from robust_imdp import plotting
    from robust_imdp.validate import Trajectories

    paths = [np.array([[0.5, 0.5, 0.5], [0.1, 0.2, 0.3]]), np.array([[-1.5, 1.0, 0.0]])]
    tr = Trajectories(paths=paths, outcome=np.array([1, 2]), steps=np.array([1, 0]))
    fig = plotting.plot_trajectory_panels(doc_nd(3, h=1.0), tr)
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert [(ax.get_xlabel(), ax.get_ylabel()) for ax in axes] == [("$x_1$", "$x_2$"), ("$x_1$", "$x_3$"),
                                                                  ("$x_2$", "$x_3$")]
    # the first panel's path segment is the (x_1, x_2) projection of the first path
    segs = [c for c in axes[0].collections if type(c).__name__ == "LineCollection"][0].get_segments()
    np.testing.assert_array_equal(segs[0], paths[0][:, [0, 1]])
    with pytest.raises(ValueError, match="pairs must be pairs"):
        plotting.plot_trajectory_panels(doc_nd(3, h=1.0), tr, pairs=[(0, 3)])
    plt.close("all")


def test_suggest_prints_the_radius_change_its_csv_holds(tmp_path, capsys):
    # it printed "radius -0.00161" while the CSV said radius_change 0.00161476
    import csv

    from problem_texts import write_one_d

    write_one_d(tmp_path)
    assert main(["run", str(tmp_path / "p.toml"), "--out", str(tmp_path / "k"), "--quiet", "--no-figures",
                 "--advice", "off"]) == 0
    capsys.readouterr()
    assert main(["suggest", str(tmp_path / "k"), "--problem", str(tmp_path / "p.toml"), "--budget", "3"]) == 0
    out = capsys.readouterr().out
    printed = [float(line.rsplit("radius_change ", 1)[1]) for line in out.splitlines() if "radius_change " in line]
    with open(tmp_path / "k" / "suggestions.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert printed and printed == [float(r["radius_change"]) for r in rows][: len(printed)]
    assert all(v > 0 for v in printed)  # a decrease of the error radius, stated as a positive change
