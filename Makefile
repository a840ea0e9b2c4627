# Two commands do all set-up on a fresh machine:  make demo   and   make test
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# shared libraries the wheels need: open3d wants libusb; VTK offscreen rendering wants OSMesa/EGL
SYSLIBS := libusb-1.0.so.0 libOSMesa.so.8 libEGL.so.1 libEGL_mesa.so.0 libgbm.so.1 libGL.so.1 libgomp.so.1
APT_PKGS := libusb-1.0-0 libosmesa6 libegl1 libegl-mesa0 libgl1-mesa-dri libgbm1 libgl1 libgomp1

.PHONY: setup demo test bench stability clean-cache sys-deps

sys-deps:
	@missing=""; for lib in $(SYSLIBS); do ldconfig -p | grep -q "$$lib" || missing="$$missing $$lib"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system libraries for:$$missing"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $(APT_PKGS) >/dev/null; \
	fi

$(STAMP): pyproject.toml
	$(MAKE) sys-deps
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	# uv (Astral's installer, from PyPI) fetches and unpacks the wheels in parallel: the set-up took 1 min 48 s
	# with pip and a warm pip cache, 45 s with uv and a cold one; pip does it where uv cannot be had
	# --compile-bytecode: uv leaves the wheels uncompiled, and where PYTHONDONTWRITEBYTECODE is set (many
	# containers, this machine) Python then compiled numba, pyvista, pydantic... from source in every process: 1.3-3 s
	# of each pipeline run's start (cProfile: builtins.compile); compileall does the project's own modules
	$(BIN)/pip install -q uv && $(BIN)/uv pip install -q --compile-bytecode --python $(BIN)/python -e ".[test]" \
	  || $(BIN)/pip install -q -e ".[test]"
	$(BIN)/python -m compileall -q pipeline stages >/dev/null
	touch $(STAMP)

setup: $(STAMP)

# the dam break (WCSPH: DFSPH is cheaper but its late splash still churns, issue 17) and a moving wall pouring
# into a shell, side by side: from a fresh clone much of the time is numba compiling (one core per process),
# so each shot compiles while the other computes. The pour (1,000 particles) runs on one numba thread, the dam
# break on all, their OpenMP threads sleeping when idle (two processes share the 2 cores: spinning threads
# made the dam break's steps 25 instead of 20 ms); results do not depend on either. The pour's log is printed
# when both are done.
demo: setup
	@log=$$(mktemp); export OMP_WAIT_POLICY=PASSIVE; \
	NUMBA_NUM_THREADS=1 $(BIN)/pipeline run configs/pour.yaml >$$log 2>&1 & pour=$$!; \
	trap 'kill $$pour 2>/dev/null' INT TERM; \
	$(BIN)/pipeline run configs/dam_break.yaml; dam=$$?; \
	wait $$pour; poured=$$?; cat $$log; rm -f $$log; \
	test $$dam = 0 -a $$poured = 0

# two pytest workers: most of the suite's time is numba compiling, which is single-threaded
test: setup
	$(BIN)/python -m pytest -q -n 2

bench: setup
	$(BIN)/python benchmarks/run_all.py

# the long stability suite (tests/stability/stability_cases.py), printed as a table
stability: setup
	$(BIN)/python tests/stability/stability_cases.py --long

clean-cache:
	rm -rf configs/.pipeline configs/out
