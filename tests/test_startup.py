"""Start-up imports only what the command needs: ``import robust_imdp`` loads the package's errors (every re-export
is imported on first use), ``robust-imdp run --help`` and ``--version`` load none of the numerical back-ends, and a
helper process of the side lane starts without them too (its tasks import what they use)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("numba", "scipy", "matplotlib", "cvxpy", "clarabel", "dask", "distributed", "casadi", "stormpy",
         "robust_imdp.bounds.rkhs", "robust_imdp.pipeline.run", "robust_imdp.solvers.api")


def _imported(code: str) -> list:
    """The modules of :data:`HEAVY` that ``code`` leaves in ``sys.modules`` (in a fresh interpreter)."""
    probe = f"import json, sys\n{code}\nprint(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.parametrize("code", [
    "import robust_imdp",
    "import robust_imdp; dir(robust_imdp)",
    "import robust_imdp.errors",
    "from robust_imdp.pipeline.parallel import _helper_main",  # a side lane's helper before its first task
    "import robust_imdp.cli\ntry:\n    robust_imdp.cli.main(['run', '--help'])\nexcept SystemExit:\n    pass",
    "import robust_imdp.cli\ntry:\n    robust_imdp.cli.main(['--version'])\nexcept SystemExit:\n    pass",
], ids=["package", "dir", "errors", "helper", "run-help", "version"])
def test_start_up_imports_no_numerical_back_end(code):
    assert _imported(code) == []


def test_a_re_exported_name_imports_its_module_on_first_use():
    code = "import robust_imdp\nbefore = 'robust_imdp.pipeline.run' in sys.modules\nrobust_imdp.synthesize_from_data\n" \
           "print(json.dumps([before, 'robust_imdp.pipeline.run' in sys.modules]))"
    out = subprocess.run([sys.executable, "-c", f"import json, sys\n{code}"], capture_output=True, text=True,
                         check=True).stdout
    assert json.loads(out.strip()) == [False, True]
    import robust_imdp
    from robust_imdp.pipeline.run import synthesize_from_data

    assert robust_imdp.synthesize_from_data is synthesize_from_data  # the same object, not a wrapper
    assert set(robust_imdp.__all__) <= set(dir(robust_imdp)) and len(robust_imdp.__all__) == len(set(robust_imdp.__all__))
