# The two commands of the README. Each creates (or reuses) the virtual environment itself.
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
# Every pip install (also tools/build_msgs.sh's) takes the versions CI tested.
export PIP_CONSTRAINT := $(CURDIR)/constraints.txt

.PHONY: demo test lint validate

$(STAMP): setup.py constraints.txt axispose_msgs/CMakeLists.txt axispose_msgs/package.xml axispose_msgs/build-requirements.txt $(wildcard axispose_msgs/msg/*.msg)
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q -e ".[ros,dev,train]"
	tools/build_msgs.sh $(VENV)
	touch $(STAMP)

# The shipped checkpoint on the shipped sample bag, through the real node (axispose replay).
demo: $(STAMP)
	rm -rf out/demo/replay_bag
	$(VENV)/bin/axispose replay demo/lmo_sample_bag --checkpoint axispose_core/models/axispose_lmo.safetensors \
		--out out/demo/replay_bag --report out/demo/report.json --overlays out/demo/overlays

# A checkpoint on real frames, GT crops and the localiser's side by side (default: the shipped model on the real
# validation slice, ../shared/data/lmo_real_val): make validate [CHECKPOINT=...] [DATA=.../test] [OUT=...]
CHECKPOINT ?= axispose_core/models/axispose_lmo.safetensors
DATA ?= ../shared/data/lmo_real_val/test
OUT ?= out/validate
validate: $(STAMP)
	$(VENV)/bin/axispose validate --checkpoint $(CHECKPOINT) --data $(DATA) --out $(OUT)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

test: lint
	$(PY) -m pytest -q test --durations=15
