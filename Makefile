# The README's two commands: `make demo` (headless GI render of a bundled scene) and `make test`.
# Both set everything up on a fresh machine first (apt packages, .venv); re-running is cheap.
# BLENDER=4.2|4.5|5.0|5.3 picks the Blender (bpy wheel, and the Python it needs); each version has
# its own environment (.venv for the default, .venv-4.2 ...) and its own built scenes.
DEFAULT_BLENDER := 5.0
BLENDER ?= $(DEFAULT_BLENDER)
ifeq ($(BLENDER),$(DEFAULT_BLENDER))
VENV := .venv
else
VENV := .venv-$(BLENDER)
endif
STAMP := $(VENV)/.setup-done
OUT ?= out

.PHONY: setup test smoke demo bench compare plots scenes lint extension clean

$(STAMP): pyproject.toml scripts/setup.sh
	BLENDER=$(BLENDER) bash scripts/setup.sh $(VENV)
	touch $@

setup: $(STAMP)

test: setup scenes
	$(VENV)/bin/pytest -q

# The smoke suite (pytest -m smoke): build a scene, render it, check passes and pixels, drive the
# viewport once, install the extension zip. CI runs it on every Blender besides the default.
smoke: setup
	$(VENV)/bin/pytest -q -m smoke

bench: setup
	$(VENV)/bin/python bench/bench_core.py

# Time to quality (issue #10): HybridGI vs Cycles + OIDN vs EEVEE against cached Cycles references;
# writes docs/time_to_quality.{md,png}; last stdout line is JSON. Dev runs: bench/time_to_quality.py --quick.
compare: setup scenes
	$(VENV)/bin/python -m pip install -q -e ".[bench]"
	$(VENV)/bin/python bench/time_to_quality.py --docs docs

# docs/timings.png (per-step time against rays per cell, cache and image resolution: one atrium
# render per point) and docs/accuracy.png (from bench/compare_cycles.py's report, when present).
plots: setup scenes
	$(VENV)/bin/python -m pip install -q -e ".[plots]"
	$(VENV)/bin/python bench/plots.py

# The bundled .blend files are build outputs of procedural.py + build.py (not kept in git), one
# set per Blender (hybridgi_cli/blender_compat.py scenes_dir: no version opens a newer one's files).
ifeq ($(BLENDER),$(DEFAULT_BLENDER))
SCENE_DIR := blend_scenes
else
SCENE_DIR := blend_scenes/blender-$(BLENDER)
endif
SCENES := $(addprefix $(SCENE_DIR)/,$(addsuffix .blend,cornell atrium spheres car animated))
scenes: $(SCENES)
$(SCENE_DIR)/%.blend: blend_scenes/procedural.py blend_scenes/build.py | $(STAMP)
	$(VENV)/bin/python blend_scenes/build.py --only $* --out $(SCENE_DIR)

demo: setup
	$(VENV)/bin/python bench/demo.py --out $(OUT)/demo

# Installable zips, one per platform, into dist/ (Blender's own extension tool; wheels cached in build/wheels/).
extension: setup
	$(VENV)/bin/python scripts/build_extension.py

lint: setup
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(OUT) dist build/extension .pytest_cache
