# Every target sets itself up on a fresh machine: venv, OSMesa, the package with dev extras.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
export PYOPENGL_PLATFORM ?= osmesa

.PHONY: setup demo test net bench docs clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	@# OSMesa: the offscreen renderer; Xvfb: the human-in-the-loop window test runs in a real X11 server;
	@# EGL with Mesa's software device: the GPU path's renderer (pyrender's framebuffer) tested on the CPU
	@{ ldconfig -p | grep -q libOSMesa && ldconfig -p | grep -q libEGL_mesa && command -v Xvfb >/dev/null; } || { (apt-get update -qq && apt-get install -y -qq libosmesa6 libegl1 libegl-mesa0 xvfb >/dev/null) || { echo "could not install libosmesa6, libegl-mesa0 and xvfb (need root and apt)"; exit 1; }; }
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev,commonroad]'
	@# CommonRoad (reader, export, the CriMe cross-check): commonroad-io pins protobuf 3.20.2, which onnx (dev)
	@# refuses, so these go in without their pins; their other dependencies are the commonroad and dev extras
	@# (pyproject.toml). commonroad-io 2024.3: the release CriMe 0.4 and CommonRoad's tools are built on.
	$(PY) -m pip install -q --no-deps 'commonroad-io==2024.3' 'commonroad-crime==0.4.5' \
	  'commonroad-drivability-checker==2025.3.1' 'commonroad-reach==2025.2.1' 'commonroad-clcs==2025.2.0' \
	  'commonroad-route-planner==2025.1.0' 'casadi>=3.6.3,<4' 'osqp==0.6.7.post3' 'qdldl>=0.1.5,<0.2' \
	  'polygon3>=3.0.8,<4' 'seaborn>=0.10,<1' 'cython>=3.0,<4' 'imageio>=2.9,<3'
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/vcfusion demo

test: $(STAMP)
	$(PY) -m pytest -q

# Rebuild sumo_net/highway.net.xml from the plain-XML sources with the netconvert of the eclipse-sumo wheel.
net: $(STAMP)
	$(VENV)/bin/vcfusion build-net

bench: $(STAMP)
	$(VENV)/bin/vcfusion bench

# The documentation site: the generated reference pages, then mkdocs (strict) into site/.
docs: $(STAMP)
	@test -x $(VENV)/bin/mkdocs || $(PY) -m pip install -q -e '.[docs]'
	$(PY) -m vcfusion.reference --write docs/reference/
	$(VENV)/bin/mkdocs build --strict

clean:
	rm -rf runs .pytest_cache site
