#!/usr/bin/env bash
# The GPU check: the renderer's tests on a Mitsuba variant (default cuda_ad_rgb) and the
# render, backward and memory benchmarks at GPU sizes, with a short markdown report.
#
#   bash benchmarks/gpu_check.sh [--variant V] [--quick] [--out DIR] [--install WHEELS]
#
# --variant V       Mitsuba variant (default cuda_ad_rgb; CI runs llvm_ad_rgb --quick)
# --quick           one test of each kind and the benchmarks' --quick sizes (minutes on a CPU)
# --out DIR         where the report (gpu_check.md), the logs and the JSON go (out/gpu_check)
# --install WHEELS  first install the wheels in WHEELS (the core's, made by
#                   ../shared/tools/slim-wheels.sh) into .site, without an index
#
# On a GPU machine that has only Python, pytest and numpy (and no package index), with the
# core's wheels copied into the ignored folder .whl of the checkout:
#   bash benchmarks/gpu_check.sh --install .whl
# Full mode: the renderer's tests (forward against the float64 reference, gradients
# against finite differences, surfaces, overlapping meshes, tetproj, tetpath), then
# 1.57M tets (64^3 cells) at 1024^2 (render, render + backward, adjoint memory) and
# 10.4M tets (120^3 cells) at 1024^2 (render), render_rays against mi.render on the same
# rays (and, where PyTorch is installed, one step through the PyTorch wrapper). Each step has its own time limit, so
# the whole check ends within 8 minutes and the report is written whatever fails.
set -uo pipefail
cd "$(dirname "$0")/.."
VARIANT=cuda_ad_rgb; QUICK=0; OUT=out/gpu_check; WHEELS=""
while [ $# -gt 0 ]; do
    case "$1" in
        --variant) VARIANT="$2"; shift 2 ;;
        --quick) QUICK=1; shift ;;
        --out) OUT="$2"; shift 2 ;;
        --install) WHEELS="$2"; shift 2 ;;
        *) echo "gpu_check.sh: unknown option $1" >&2; exit 2 ;;
    esac
done
mkdir -p "$OUT"
if [ -n "$WHEELS" ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --target .site "$WHEELS"/*.whl \
        || { echo "gpu_check.sh: cannot install the wheels in $WHEELS" >&2; exit 1; }
    export PYTHONPATH="$PWD/.site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
export MI_TETVR_VARIANT="$VARIANT"
STATUS=0

step() {  # step NAME SECONDS COMMAND...: run it with a time limit, its output to OUT/NAME.log
    local name="$1" limit="$2"; shift 2
    local t0=$SECONDS
    timeout "$limit" "$@" >"$OUT/$name.log" 2>&1
    local rc=$?
    echo "$name $rc $((SECONDS - t0))" >>"$OUT/steps.txt"
    echo "== $name: exit $rc in $((SECONDS - t0)) s"
    [ $rc -eq 0 ] || STATUS=1
}

: >"$OUT/steps.txt"
if [ $QUICK -eq 1 ]; then
    # one test of each kind (an id that no longer exists fails the check)
    TESTS=(tests/render/test_reference.py::test_two_tets_composited_by_hand
           tests/render/test_gradients.py::test_adjoint_matches_finite_differences_jittered
           tests/render/test_surfaces.py::test_against_mitsuba_without_the_volume
           tests/render/test_overlap.py::test_overlapping_meshes_with_coincident_boundary_faces
           tests/render/test_projection.py::test_slice_against_the_reference
           tests/render/test_transport.py::test_free_flight_distances_invert_the_optical_depth
           tests/render/test_rays.py::test_gradients_against_finite_differences)
    SIZES=(--quick); BIG=(--cells 20 --res 64); LIMIT_TESTS=600
else
    # the renderer's tests that need no extra (the VTK comparisons and Ray's blocks need theirs)
    TESTS=(tests/render/test_reference.py tests/render/test_segment.py
           tests/render/test_geometry.py tests/render/test_render.py
           tests/render/test_gradients.py tests/render/test_ray_value_gradients.py
           tests/render/test_models.py tests/render/test_optical.py
           tests/render/test_classified.py tests/render/test_cell_data.py
           tests/render/test_surfaces.py tests/render/test_overlap.py
           tests/render/test_overlay.py tests/render/test_projection.py
           tests/render/test_transport.py tests/render/test_rays.py tests/test_interop.py
           tests/test_scenes.py)
    SIZES=(--cells 64 --res 1024); BIG=(--cells 120 --res 1024); LIMIT_TESTS=200
fi
step tests "$LIMIT_TESTS" python3 -m pytest -q -p no:cacheprovider -o addopts= \
    --junitxml="$OUT/tests.xml" "${TESTS[@]}"
step render 75 python3 benchmarks/bench_render.py --variant "$VARIANT" "${SIZES[@]}" \
    --repeat 3 --json "$OUT/render.json"
step backward 55 python3 benchmarks/bench_backward.py --variant "$VARIANT" "${SIZES[@]}" \
    --json "$OUT/backward.json"
if [ $QUICK -eq 1 ]; then
    step memory 60 python3 benchmarks/bench_memory.py --variant "$VARIANT" --quick \
        --json "$OUT/memory.json"
else
    step memory 40 python3 benchmarks/bench_memory.py --variant "$VARIANT" \
        --json "$OUT/memory.json"
fi
step rays 60 python3 benchmarks/bench_rays.py --variant "$VARIANT" "${SIZES[@]}" \
    --repeat 3 --json "$OUT/rays.json"
step render_10m 90 python3 benchmarks/bench_render.py --variant "$VARIANT" "${BIG[@]}" \
    --repeat 2 --json "$OUT/render_10m.json"
python3 benchmarks/gpu_report.py "$OUT" >"$OUT/gpu_check.md" || STATUS=1
cat "$OUT/gpu_check.md"
exit $STATUS
