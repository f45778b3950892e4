# The two commands of the README. Each installs what it needs first (tools/setup.sh).
PYTHON ?= python3
export PYTHON

.PHONY: setup demo test test-all test-widths docs
setup:
	@bash tools/setup.sh

demo: setup
	$(PYTHON) -m usdfiber render examples/demo.usda -o build/demo.exr

test: setup
	$(PYTHON) -m pytest -q

# Includes the long physics runs (marked slow).
test-all: setup
	$(PYTHON) -m pytest -q -m ""

# The Monte-Carlo test files with Dr.Jit's kernels compiled for 8 float lanes (AVX2) and for
# 16 (AVX-512, where the CPU has it): random streams differ between the two, and every
# statistical assertion must hold on both (docs/testing.md).
MC_TESTS ?= tests/mitsuba/test_integrator.py tests/mitsuba/test_fiber_bsdf.py tests/bake/test_tracer.py \
	tests/bake/test_reference_tracer.py tests/bake/test_table.py tests/mitsuba/test_yarn_far_field.py \
	tests/mitsuba/test_hair_comparison.py tests/mitsuba/test_lod_bound.py tests/mitsuba/test_translate_lights.py \
	tests/bake/test_recolour.py tests/bake/test_expected_estimator.py tests/bake/test_estimators.py \
	tests/bake/test_incoming_grid.py tests/bake/test_box_incoming.py tests/bake/test_reciprocity.py tests/core/test_dye_match.py tests/fit/test_silk_loss.py \
	tests/geometry/test_volume_voxelize.py tests/geometry/test_yarns.py tests/mitsuba/test_compressed_render.py \
	tests/mitsuba/test_far_field_cost.py tests/mitsuba/test_khungurn_bsdf.py tests/mitsuba/test_model_render.py \
	tests/mitsuba/test_volume_agreement.py tests/mitsuba/test_volume_phase.py
test-widths: setup
	USDFIBER_TEST_VECTOR_WIDTH=8 $(PYTHON) -m pytest -q $(MC_TESTS)
	@if grep -qw avx512f /proc/cpuinfo; then \
		echo USDFIBER_TEST_VECTOR_WIDTH=16 $(PYTHON) -m pytest -q $(MC_TESTS); \
		USDFIBER_TEST_VECTOR_WIDTH=16 $(PYTHON) -m pytest -q $(MC_TESTS); \
	else echo "test-widths: no AVX-512 on this CPU, 16 lanes not run"; fi

# The API reference of usdfiber and usdfiber.translators (pdoc): build/docs/index.html.
# Fails on a module that does not import or has no docstring, a pdoc warning or a broken
# docstring reference.
docs: setup
	$(PYTHON) docs/api_reference.py -o build/docs
