# gridnerf: every target creates and reuses .venv on first use.
SCENE   ?= bucket
PRESET  ?= default
PYTHON  ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
TCMALLOC := /usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4
# Preload tcmalloc when present: JAX train steps ran 1.3-2x faster than with glibc malloc
# (measured on this project's 2-core machines, jax 0.10). Tested when the recipe runs, not
# when make reads this file, so the first run on a fresh machine (system-deps installs it
# on the way) preloads it too.
RUN     = env $$(test -e $(TCMALLOC) && echo LD_PRELOAD=$(TCMALLOC)) XLA_FLAGS="$(XLA_FLAGS)" $(BIN)/
# A scene name means the built-in simulated scene data/sim/<name>; anything with a slash is a folder.
SCENE_DIR := $(if $(findstring /,$(SCENE)),$(SCENE),data/sim/$(SCENE))
# basename in the shell, not $(notdir): make's functions split words on spaces, so
# "my scenes/a b" became "my a b" (tests/test_makefile.py)
SCENE_NAME := $(shell basename -- "$(SCENE_DIR)")
RUN_DIR := runs/$(SCENE_NAME)/$(PRESET)

.PHONY: venv system-deps data cycles poses train eval render view ablate report recon bench test lint clean

venv: $(STAMP)

# Debian packages: tcmalloc, and chromium for the viewer's browser test (tests/test_viewer.py
# skips without it). Each skipped when already present or when not root.
system-deps:
	@if [ ! -e $(TCMALLOC) ] && [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	  echo "installing libtcmalloc-minimal4"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libtcmalloc-minimal4 >/dev/null) \
	    || echo "warning: could not install libtcmalloc-minimal4; continuing with glibc malloc"; \
	fi
	@if ! command -v chromium >/dev/null && [ "$$(id -u)" = "0" ] && command -v apt-get >/dev/null; then \
	  echo "installing chromium"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
	    || echo "warning: could not install chromium; the viewer's browser test will be skipped"; \
	fi

$(STAMP): pyproject.toml
	@$(MAKE) --no-print-directory system-deps
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]'
	touch $(STAMP)

data: $(STAMP)
	@if [ -n "$(findstring /,$(SCENE))" ]; then \
	  test -d "$(SCENE_DIR)" || { echo "error: scene folder $(SCENE_DIR) does not exist" >&2; exit 2; }; \
	else \
	  $(RUN)gridnerf simulate "$(SCENE)" --out "$(SCENE_DIR)"; \
	fi

poses: $(STAMP)
	$(RUN)gridnerf poses "$(SCENE_DIR)"

train: data
	$(RUN)gridnerf train "$(SCENE_DIR)" --out "$(RUN_DIR)" --preset "$(PRESET)"
	$(RUN)gridnerf eval "$(RUN_DIR)"

eval: $(STAMP)
	$(RUN)gridnerf eval "$(RUN_DIR)"

render: $(STAMP)
	$(RUN)gridnerf render "$(RUN_DIR)" --path spiral

# one self-contained HTML file: $(RUN_DIR)/viewer.html (docs/viewer.md)
view: $(STAMP)
	$(RUN)gridnerf view "$(RUN_DIR)"

# every scene unless SCENE is given on the command line (make ablate SCENE=bucket)
ABLATE_SCENES = $(if $(filter command line,$(origin SCENE)),$(SCENE),all)
ablate: $(STAMP)
	$(RUN)python -m experiments.ablate --scenes "$(ABLATE_SCENES)"

# QUICK=1: the whole report small (160x90 scenes, shrunk presets) under reports/quick/
# path-traced captures (Blender Cycles: Debian's `blender` package) under data/cycles/
cycles: $(STAMP)
	@command -v blender >/dev/null || { echo "error: blender is not installed (Debian: apt-get install blender)" >&2; exit 2; }
	$(RUN)gridnerf simulate cycles

report: $(STAMP)
	$(RUN)python -m experiments.report $(if $(QUICK),--quick)

recon: $(STAMP)
	$(RUN)python -m experiments.recon --scenes all --oracle heldout

# speed and scale benchmark: bench/results.json + bench/results.md, cached per item
# in bench/cache (delete it, or BENCH_ARGS=--fresh, to measure again); docs/speed.md
bench: $(STAMP)
	$(RUN)python -m experiments.bench --scene "$(SCENE)" $(BENCH_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check gridnerf experiments tests

test: $(STAMP)
	$(BIN)/ruff check gridnerf experiments tests
	$(RUN)pytest

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
