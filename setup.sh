#!/usr/bin/env bash
# Install mi_tetvr and everything it needs, then render the default scene.
#   bash setup.sh            install + render out/default.exr and out/default.png
#   bash setup.sh --install  install only
set -euo pipefail
cd "$(dirname "$0")"
# Dr.Jit's LLVM backend crashes with libLLVM 14/15; Debian's libllvm19 works
# and is picked up automatically once installed.
if ! ls /usr/lib/x86_64-linux-gnu/libLLVM-19.so* /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi
python3 -m pip install -q -e ".[test]"
python3 -m mi_tetvr.cli make-scenes >/dev/null
if [ "${1:-}" != "--install" ]; then
    mi-tetvr render scenes/default.xml -o out/default.exr -o out/default.png
fi
