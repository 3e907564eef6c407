#!/usr/bin/env bash
# Install mi_tetvr and everything it needs, then run the main job on the
# project's own default data set: render the default volume into a multi-view
# data set, reconstruct it as a tet mesh, print the test PSNR.
#   bash setup.sh            install + render out/default.{exr,png} + fit out/default_fit
#   bash setup.sh --install  install only
set -euo pipefail
cd "$(dirname "$0")"
# Dr.Jit's LLVM backend crashes with libLLVM 14/15; Debian's libllvm19 works
# and is picked up automatically once installed.
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
if ! ls /usr/lib/x86_64-linux-gnu/libLLVM-19.so* /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1; then
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi
# Debian's Chromium and its driver run the viewer's test in a real browser
# (where they cannot be installed that test skips and says why).
if ! command -v chromium >/dev/null 2>&1 || ! command -v chromedriver >/dev/null 2>&1; then
    { $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -qq chromium chromium-driver >/dev/null; } \
        || echo "setup.sh: could not install chromium and chromium-driver" >&2
fi
# PyTorch, for the torch extra: the release the tests run with, which pip takes as a
# CPU build where one lies in its find-links (PyPI's Linux wheels are CUDA builds of
# several GB; a newer release than a local CPU build would fetch one)
python3 -m pip install -q "torch==2.13.0"
# the package with every extra (rendering alone needs none: pip install mi_tetvr)
python3 -m pip install -q -e ".[all,test,docs]"
# the bundled scenes, their meshes and the default volume into scenes/
python3 -m mi_tetvr.cli make-scenes -o scenes >/dev/null
if [ "${1:-}" != "--install" ]; then
    mi-tetvr render scenes/default.xml -o out/default.exr -o out/default.png
    mi-tetvr make-dataset scenes/volumes/default.npy --tf scenes/tf_default.json \
        --views 32 --test-views 8 --res 64 --fov 30 --out out/default_data
    mi-tetvr fit out/default_data --out out/default_fit --restart --time-budget 1
fi
