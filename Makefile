# Two commands set up everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
export PYTHONUNBUFFERED := 1

.PHONY: demo test test-fast lint format bench venv clean-venv

venv: $(STAMP)

# torch is installed first (pinned) so that pip never pulls the multi-GB CUDA build.
$(STAMP): pyproject.toml constraints.txt
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt torch
	$(PY) -m pip install -q -c constraints.txt -e '.[test]'
	@touch $(STAMP)

# The main job on the embedded default: synthetic capture (reused when present) -> rig calibration from its
# ChArUco shots (written to its calibration/ folder and compared with the true cameras; the fit keeps the
# capture's own annots.npy) -> fit (CPU default, time budget DEMO_MINUTES) -> evaluation on the novel-pose
# split (both protocols, and the exported surface against the true one) -> orbit video.
DEMO_MINUTES ?= 8
DEMO_RUN     ?= runs/demo
demo: $(STAMP)
	$(VENV)/bin/narf-synth --subject taichi
	$(VENV)/bin/narf-calibrate $${NARF_DATA:-data}/synthetic/taichi
	rm -rf $(DEMO_RUN)
	$(VENV)/bin/narf-fit --subject taichi --out $(DEMO_RUN) --max-minutes $(DEMO_MINUTES)
	$(VENV)/bin/narf-eval --run $(DEMO_RUN) --split novel_pose --limit 34 --mesh
	$(VENV)/bin/narf-render-video --run $(DEMO_RUN) --kind orbit --frames 48
	@echo
	@echo "Results: $${NARF_DATA:-data}/synthetic/taichi/calibration/report.json, $(DEMO_RUN)/eval/metrics.md, $(DEMO_RUN)/eval/grids/, $(DEMO_RUN)/eval/meshes/, $(DEMO_RUN)/videos/orbit.mp4, $(DEMO_RUN)/curve.png"

# Lint and formatting are checked first: a tree that ruff would change or flag fails `make test` (and CI).
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

test: lint
	$(PY) -m pytest -q -n 2 --durations=15 tests

test-fast: lint
	$(PY) -m pytest -q -n 2 -m "not slow" tests

bench: $(STAMP)
	$(PY) -m bench

clean-venv:
	rm -rf $(VENV)
