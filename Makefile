# Two commands do all set-up on a fresh machine:
#   make demo   -> creates .venv, installs the package, compiles its numba kernels (cached), runs the
#                  paper's first case study end to end
#   make test   -> creates .venv, installs the package with test extras, compiles the kernels, runs the test suite
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python

.PHONY: demo test venv bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

# Compile the numba kernels once, on tiny problems, into numba's cache next to the sources
# (src/robust_imdp/*/__pycache__, git-ignored): the first real run then only loads them. Re-run
# when a source is newer than the stamp.
# numba keys a kernel's cache by its own file only, and a kernel compiled with callees from another
# file keeps their old code when only that file changes: start from an empty cache whenever any
# source changed.
$(VENV)/.warm: $(VENV)/.installed $(shell find src/robust_imdp -name "*.py")
	find src/robust_imdp -name '*.nbi' -delete -o -name '*.nbc' -delete
	$(PY) -m robust_imdp.warmup
	touch $@

venv: $(VENV)/.warm

demo: venv
	$(PY) examples/three_mode_linear.py --out results/three_mode_linear

test: venv
	$(PY) -m pytest -q

# The README's Performance table; other suites: $(PY) benchmarks/run.py --list
bench: venv
	$(PY) benchmarks/run.py perf

clean:
	rm -rf $(VENV) results
