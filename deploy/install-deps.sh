#!/usr/bin/env bash
# Installs what the build and the tests need, skipping what is already there:
# Debian packages (OpenCV, clang for its bindings, OpenNI2, protoc, chromium and
# Node.js for the dashboard and its browser test), the dashboard's npm packages
# (dashboard/package-lock.json), the ONNX
# Runtime shared library from PyPI's onnxruntime wheel (Debian has none), and evo
# (PyPI, in a virtual environment) for the trajectory-evaluation parity test.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES=(libopencv-dev clang libclang-dev libopenni2-dev protobuf-compiler pkg-config curl fonts-dejavu-core chromium)
# Node.js for the dashboard's npm packages (three.js; playwright-core for its browser test).
command -v node >/dev/null && command -v npm >/dev/null || APT_PACKAGES+=(nodejs npm)
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

# evo, the reference `stillmap-client eval` is tested against (client/tests/evo_parity.rs),
# in its own virtual environment: ~25 s and ~470 MB (numpy, scipy, matplotlib, pandas).
EVO_VERSION=1.38.1
if [ ! -x .deps/evo/bin/evo_ape ]; then
  echo "install-deps: installing evo ${EVO_VERSION} into .deps/evo"
  if ! python3 -c "import ensurepip, venv" 2>/dev/null; then
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends python3-venv >/dev/null
  fi
  rm -rf .deps/evo
  python3 -m venv .deps/evo
  .deps/evo/bin/pip install -q --disable-pip-version-check "evo==${EVO_VERSION}"
  test -x .deps/evo/bin/evo_ape
fi

# The dashboard's npm packages, exactly as locked: three.js (served to browsers by the
# server) and playwright-core (drives chromium in tests/tests/dashboard.rs).
if [ ! -d dashboard/node_modules/three ] || [ ! -d dashboard/node_modules/playwright-core ] || [ dashboard/package-lock.json -nt dashboard/node_modules ]; then
  echo "install-deps: npm ci in dashboard/"
  (cd dashboard && npm ci --no-audit --no-fund --loglevel=error)
  touch dashboard/node_modules
fi
