# jaxvox: `make run` and `make test` do all the set-up on a fresh machine.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: run test check docs bench bench-smoke clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	touch $(STAMP)

run: $(STAMP)  ## voxelize the built-in default scene, report, write out/voxels.png; path-trace it to out/image.exr + .png
	$(PY) -m jaxvox run --out out
	$(PY) -m jaxvox render --resolution 256 --size 384x216 --spp 16 --bounces 8 --env sky --out out/image.exr

check: $(STAMP)  ## lint and format check (ruff), type check (mypy)
	$(VENV)/bin/ruff check jaxvox tests experiments
	$(VENV)/bin/ruff format --check jaxvox tests experiments
	$(VENV)/bin/mypy

docs: $(STAMP)  ## the documentation site (mkdocs, API reference from the docstrings) into site/
	$(PY) -m pip install --quiet -e ".[docs]"
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

test: $(STAMP)  ## the whole test suite (slow checks run at a small size unless JAXVOX_SLOW_SCALE=full)
	GLIBC_TUNABLES=glibc.malloc.hugetlb=1 $(PY) -m pytest -q  # huge pages, as the jaxvox command (jaxvox.cli)

$(VENV)/.bench-installed: $(STAMP)
	@if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq libusb-1.0-0; \
	  else echo "Open3D needs the system library libusb-1.0: run 'sudo apt-get install libusb-1.0-0'" >&2; exit 1; fi; \
	fi
	@if ! /usr/bin/python3 -c "import pyopenvdb" 2>/dev/null; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq python3-openvdb; \
	  else echo "experiments/sparse_distance.py compares with OpenVDB: run 'sudo apt-get install python3-openvdb'" >&2; fi; \
	fi
	@if [ ! -f /usr/include/eigen3/Eigen/Core ]; then \
	  if [ "$$(id -u)" = 0 ]; then apt-get update -qq && apt-get install -y -qq libeigen3-dev; \
	  else echo "pysdf (experiments/bench_points.py) builds against Eigen: run 'sudo apt-get install libeigen3-dev'" >&2; fi; \
	fi
	CPATH=/usr/include/eigen3 $(PY) -m pip install --quiet -e ".[test,bench]"
	touch $@

bench: $(VENV)/.bench-installed  ## voxelization against Open3D and trimesh (R=128..2048, bunny at 8192^3); traversal against Embree
	$(PY) experiments/bench_voxelize.py --huge 8192
	$(PY) experiments/bench_trace.py

bench-smoke: $(VENV)/.bench-installed  ## the same at R=64,128 (a few minutes)
	$(PY) experiments/bench_voxelize.py --smoke
	$(PY) experiments/bench_trace.py --smoke

clean:
	rm -rf $(VENV) out .pytest_cache site
