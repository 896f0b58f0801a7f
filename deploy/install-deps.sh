#!/usr/bin/env bash
# Installs what the build and the tests need, skipping what is already there:
# Debian packages (OpenCV, clang for its bindings, OpenNI2, protoc) and the
# ONNX Runtime shared library from PyPI's onnxruntime wheel (Debian has none).
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(libopencv-dev clang libclang-dev libopenni2-dev protobuf-compiler pkg-config curl)
ORT_VERSION=1.31.1

missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "install-deps: installing ${missing[*]}"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if ! command -v cargo >/dev/null; then
  echo "install-deps: cargo not found; install Rust with rustup (https://rustup.rs)" >&2
  exit 1
fi

lib=".deps/ort/libonnxruntime.so.${ORT_VERSION}"
if [ ! -f "$lib" ]; then
  echo "install-deps: fetching onnxruntime ${ORT_VERSION} from PyPI"
  mkdir -p .deps/ort-wheel .deps/ort
  python3 -m pip download -q --no-deps --only-binary=:all: "onnxruntime==${ORT_VERSION}" -d .deps/ort-wheel
  python3 - "$ORT_VERSION" <<'PY'
import glob, os, sys, zipfile
wheel = zipfile.ZipFile(glob.glob(".deps/ort-wheel/onnxruntime-*.whl")[0])
for name in wheel.namelist():
    if name.startswith("onnxruntime/capi/libonnxruntime"):
        with open(".deps/ort/" + os.path.basename(name), "wb") as out:
            out.write(wheel.read(name))
PY
  test -f "$lib"
fi
