#!/usr/bin/env bash
# Reconstruction benchmarks (needs ../shared/data): engine CT rendered by the
# grid ray marcher, and NeRF-synthetic Lego. Results: out/*_fit/metrics.json.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=../shared/data
mi-tetvr make-dataset $DATA/engine-ct/engine_256x256x128_uint8.raw.gz --value-range 0,255 \
    --tf scenes/tf_engine.json --views 64 --test-views 8 --res 256 --fov 40 --out out/engine_data
mi-tetvr fit out/engine_data --out out/engine_fit --restart --config benchmarks/fit_engine.json
mi-tetvr fit $DATA/nerf-lego --downscale 4 --out out/lego_fit --restart --config benchmarks/fit_lego.json
# Coarse-to-fine on the engine: start at grid 24, three splits of the top vertices by
# accumulated absolute gradient (after joint position stages), against the uniform grid-48 run
# above and a uniform grid with about the coarse-to-fine run's final vertex count (grid 34).
mi-tetvr fit out/engine_data --out out/engine_c2f --restart --config benchmarks/fit_engine_c2f.json
mi-tetvr fit out/engine_data --out out/engine_fit34 --restart --config benchmarks/fit_engine_34.json
