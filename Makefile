# The README's two commands: `make demo` (headless GI render of a bundled scene) and `make test`.
# Both set everything up on a fresh machine first (apt packages, .venv); re-running is cheap.
VENV := .venv
STAMP := $(VENV)/.setup-done
OUT ?= out

.PHONY: setup test demo bench compare scenes lint extension clean

$(STAMP): pyproject.toml scripts/setup.sh
	bash scripts/setup.sh
	touch $@

setup: $(STAMP)

test: setup scenes
	$(VENV)/bin/pytest -q

bench: setup
	$(VENV)/bin/python bench/bench_core.py

# Time to quality (issue #10): HybridGI vs Cycles + OIDN vs EEVEE against cached Cycles references;
# writes docs/time_to_quality.{md,png}; last stdout line is JSON. Dev runs: bench/time_to_quality.py --quick.
compare: setup scenes
	$(VENV)/bin/python bench/time_to_quality.py --docs docs

# The bundled .blend files are build outputs of procedural.py + build.py (not kept in git).
SCENES := $(addprefix blend_scenes/,$(addsuffix .blend,cornell atrium spheres car animated))
scenes: $(SCENES)
blend_scenes/%.blend: blend_scenes/procedural.py blend_scenes/build.py | $(STAMP)
	$(VENV)/bin/python blend_scenes/build.py --only $*

demo: setup
	$(VENV)/bin/python bench/demo.py --out $(OUT)/demo

# Installable zips, one per platform, into dist/ (Blender's own extension tool; wheels cached in build/wheels/).
extension: setup
	$(VENV)/bin/python scripts/build_extension.py

lint: setup
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(OUT) dist build/extension .pytest_cache
