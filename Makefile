# Two set-up commands (see README):
#   make demo  - install everything into .venv and run `argen capture-sim` on its built-in default
#   make test  - install everything into .venv and run the default (fast) test suite
# Other targets: make test-slow (slow-marked tests), make bench, make clean.

PY      ?= python3
VENV    ?= .venv
VPY     := $(VENV)/bin/python
PIP     := $(VPY) -m pip
STAMP   := $(VENV)/.installed
SUDO    := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
export PYOPENGL_PLATFORM ?= osmesa

.PHONY: install sysdeps demo test test-slow test-all bench clean

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

$(STAMP): pyproject.toml | sysdeps
	$(PY) -m venv $(VENV)
	$(PIP) install -q --upgrade pip
	# torch first, pinned: the CPU wheel on these machines (a bare `torch` pulls GBs of CUDA packages)
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -e '.[test]'
	# pyrender pins PyOpenGL 3.1.0, which lacks OSMesaCreateContextAttribs: upgrade it afterwards
	# (not a dependency in pyproject.toml: pip would refuse the conflict with the pin)
	$(PIP) install -q --no-deps 'PyOpenGL>=3.1.4'
	touch $(STAMP)

install: sysdeps $(STAMP)

demo: install
	$(VENV)/bin/argen capture-sim --scene linemod --frames 8 --out demo_out --overwrite
	@echo "wrote BOP dataset to demo_out/ (see demo_out/argen.json and capture_log.json)"

test: install
	$(VPY) -m pytest -q -m "not slow"

test-slow: install
	$(VPY) -m pytest -q -m slow

test-all: install
	$(VPY) -m pytest -q

bench: install
	$(VPY) bench/bench_capture.py

clean:
	rm -rf $(VENV) demo_out .pytest_cache
