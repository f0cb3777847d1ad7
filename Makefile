# Two set-up commands (see README):
#   make demo  - install everything into .venv and run `argen capture-sim` on its built-in default
#   make test  - install everything into .venv and run the fast test suite (every test not marked slow)
# Other targets: make test-slow (the rest: the slow-marked tests), make test-all (both), make bench,
# make lock (refresh the pins), make clean.

PY      ?= python3
VENV    ?= .venv
VPY     := $(VENV)/bin/python
PIP     := $(VPY) -m pip
STAMP   := $(VENV)/.installed
SUDO    := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
export PYOPENGL_PLATFORM ?= osmesa

# Pinned install: every package, direct and indirect, at the version CI ran (lock/py3.X.txt, per Python
# version since wheels and requirements differ between them). PyOpenGL is pinned apart (lock/py3.X-nodeps.txt)
# because it is installed over pyrender's own pin with --no-deps. `make lock` refreshes both files.
PYVER   := $(shell $(PY) -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null)
LOCK    := lock/py$(PYVER).txt
NODEPS  := lock/py$(PYVER)-nodeps.txt
LOCKVENV := .venv-lock

.PHONY: install sysdeps demo test test-slow test-all bench lock clean

# Debian packages: OSMesa for off-screen rendering, libusb for open3d. Installed only when missing.
sysdeps:
	@missing=""; \
	for lib in libOSMesa.so.8 libusb-1.0.so.0 libgomp.so.1; do \
	  ldconfig -p | grep -q "$$lib" || missing="$$missing $$lib"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages for:$$missing"; \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq libosmesa6 libusb-1.0-0 libgomp1 >/dev/null; \
	fi

$(STAMP): pyproject.toml $(wildcard $(LOCK) $(NODEPS)) | sysdeps
	$(PY) -m venv $(VENV)
ifneq ($(wildcard $(LOCK)),)
	# pinned: pip, setuptools and every dependency exactly as in $(LOCK) (torch: the CPU wheel on these machines)
	$(PIP) install -q -c $(LOCK) --upgrade pip setuptools
	$(PIP) install -q -c $(LOCK) torch
	$(PIP) install -q -c $(LOCK) --no-build-isolation -e '.[test]'
	# pyrender pins PyOpenGL 3.1.0, which lacks OSMesaCreateContextAttribs: the pinned newer one over it
	$(PIP) install -q --no-deps -r $(NODEPS)
else
	@echo "WARNING: no $(LOCK) for Python $(PYVER): installing the newest versions (run 'make lock' to pin them)"
	$(PIP) install -q --upgrade pip
	# torch first, pinned: the CPU wheel on these machines (a bare `torch` pulls GBs of CUDA packages)
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[test]'
	# pyrender pins PyOpenGL 3.1.0, which lacks OSMesaCreateContextAttribs: upgrade it afterwards
	# (not a dependency in pyproject.toml: pip would refuse the conflict with the pin)
	$(PIP) install -q --no-deps 'PyOpenGL>=3.1.4'
endif
	touch $(STAMP)

install: sysdeps $(STAMP)

demo: install
	$(VENV)/bin/argen capture-sim --scene linemod --frames 8 --out demo_out --overwrite
	@echo "wrote BOP dataset to demo_out/ (see demo_out/argen.json and capture_log.json)"

test: install
	@echo "make test: the fast suite (pytest -m 'not slow'); make test-slow runs the rest (the slow-marked tests)"
	$(VPY) -m pytest -q -m "not slow"

test-slow: install
	@echo "make test-slow: the slow-marked tests, the rest of the suite that make test leaves out"
	$(VPY) -m pytest -q -m slow

test-all: install
	$(VPY) -m pytest -q

bench: install
	$(VPY) bench/bench_capture.py

# Refresh the pins: resolve the newest versions allowed by pyproject.toml in a scratch venv, then write them
# to lock/py$(PYVER).txt. Run it on each Python you support when you change a dependency or want newer
# packages, then `make test` and commit the lock with the code it was tested with.
lock: sysdeps
	rm -rf $(LOCKVENV)
	$(PY) -m venv $(LOCKVENV)
	$(LOCKVENV)/bin/python -m pip install -q --upgrade pip setuptools
	$(LOCKVENV)/bin/python -m pip install -q torch==2.13.0
	$(LOCKVENV)/bin/python -m pip install -q -e '.[test]'
	$(LOCKVENV)/bin/python -m pip install -q --no-deps --upgrade 'PyOpenGL>=3.1.4'
	mkdir -p lock
	{ echo "# pip constraints for Python $(PYVER), written by 'make lock' ($$(date -u +%F)); used by make install"; \
	  $(LOCKVENV)/bin/python -m pip freeze --all --exclude-editable | grep -vi '^pyopengl==' | \
	  sed 's/^torch==\([^+]*\)+cpu$$/torch==\1/'; } > $(LOCK).tmp
	{ echo "# installed with --no-deps after $(LOCK) (pyrender pins an older PyOpenGL)"; \
	  $(LOCKVENV)/bin/python -m pip freeze | grep -i '^pyopengl=='; } > $(NODEPS).tmp
	mv $(LOCK).tmp $(LOCK); mv $(NODEPS).tmp $(NODEPS)
	rm -rf $(LOCKVENV)
	@echo "wrote $(LOCK) and $(NODEPS): run 'make clean test' to check them, then commit them"

clean:
	rm -rf $(VENV) $(LOCKVENV) demo_out .pytest_cache
