#!/usr/bin/env bash
# Installs what the build and the tests need, skipping what is already there:
# Debian packages (OpenCV, clang for its bindings, OpenNI2, protoc, chromium and
# Node.js for the dashboard and its browser test, PostgreSQL for the replica
# test), the dashboard's npm packages
# (dashboard/package-lock.json), the ONNX
# Runtime shared library from PyPI's onnxruntime wheel (Debian has none), and evo
# (PyPI, in a virtual environment) for the trajectory-evaluation parity test.
#
# --gpu also fetches the GPU libraries (below). --server-only installs only what
# building and running the binaries needs (the container images' build stage,
# deploy/docker/Dockerfile): no chromium, evo, test tools or batched test models.
set -euo pipefail
cd "$(dirname "$0")/.."
GPU=""
SERVER_ONLY=""
for arg in "$@"; do
  case "$arg" in
    --gpu) GPU=1 ;;
    --server-only) SERVER_ONLY=1 ;;
    *) echo "install-deps: unknown option $arg (use --gpu, --server-only)" >&2; exit 2 ;;
  esac
done

APT_PACKAGES=(libopencv-dev clang libclang-dev libopenni2-dev protobuf-compiler pkg-config curl fonts-dejavu-core)
# chromium for the dashboard's browser test; PostgreSQL, whose server the replica
# test starts on a free port of its own (store.replica_url).
[ -n "$SERVER_ONLY" ] || APT_PACKAGES+=(chromium postgresql)
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
# `make lint` (run by `make test`) needs rustfmt and clippy.
if command -v rustup >/dev/null; then
  for component in rustfmt clippy; do
    rustup component list --installed 2>/dev/null | grep -q "^${component}" || rustup component add "$component"
  done
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

if [ -z "$SERVER_ONLY" ]; then
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

# A virtual environment .deps/NAME with the pins of REQUIREMENTS, made again when the
# pins change.
pinned_venv() {
  local name=$1 requirements=$2 what=$3
  if [ ! -x ".deps/$name/bin/python" ] || [ "$requirements" -nt ".deps/$name/installed" ]; then
    echo "install-deps: installing $what into .deps/$name"
    rm -rf ".deps/$name"
    python3 -m venv ".deps/$name"
    ".deps/$name/bin/pip" install -q --disable-pip-version-check -r "$requirements"
    touch ".deps/$name/installed"
  fi
}
# The Python client example's gRPC stack (examples/python, run by
# tests/tests/python_client.rs): ~5 s, ~60 MB.
pinned_venv pyclient examples/python/requirements.txt "the Python client's packages"
# The ROS recording writer and the MCAP reader of the tests (tests/scripts: rosbags,
# Pillow, numpy, mcap), and the Kubernetes manifests' schema check (kubernetes-validate,
# offline: it carries the API's schemas): ~15 s, ~110 MB.
pinned_venv bagtools tests/scripts/requirements.txt "the recording tools' packages"
fi

# The dashboard's npm packages, exactly as locked: three.js (served to browsers by the
# server) and playwright-core (drives chromium in tests/tests/dashboard.rs).
# --server-only: three.js alone (--omit=dev), for the image.
if [ -n "$SERVER_ONLY" ]; then
  if [ ! -d dashboard/node_modules/three ] || [ dashboard/package-lock.json -nt dashboard/node_modules ]; then
    echo "install-deps: npm ci --omit=dev in dashboard/"
    (cd dashboard && npm ci --omit=dev --no-audit --no-fund --loglevel=error)
    touch dashboard/node_modules
  fi
elif [ ! -d dashboard/node_modules/three ] || [ ! -d dashboard/node_modules/playwright-core ] || [ dashboard/package-lock.json -nt dashboard/node_modules ]; then
  echo "install-deps: npm ci in dashboard/"
  (cd dashboard && npm ci --no-audit --no-fund --loglevel=error)
  touch dashboard/node_modules
fi

if [ -z "$SERVER_ONLY" ]; then
# The segmentation models with a symbolic batch dimension, made from the shipped
# batch-1 files (deploy/make-batched-model.py, which checks the outputs equal the
# batch-1 model's) into .deps/models: the segmentation service batches with them.
if [ ! -f .deps/models/yolov8n-seg_fp32_320_batch.onnx ] || [ ! -f .deps/models/yolov8n-seg_fp32_640_batch.onnx ] \
   || [ deploy/make-batched-model.py -nt .deps/models/yolov8n-seg_fp32_640_batch.onnx ]; then
  echo "install-deps: making the batching segmentation models in .deps/models"
  if [ ! -x .deps/onnx-tools/bin/python ]; then
    python3 -m venv .deps/onnx-tools
    .deps/onnx-tools/bin/pip install -q --disable-pip-version-check -r deploy/onnx-tools-requirements.txt
  fi
  mkdir -p .deps/models
  for size in 320 640; do
    .deps/onnx-tools/bin/python deploy/make-batched-model.py "${SHARED:-../shared}/models/yolov8n-seg_fp32_${size}.onnx" \
      ".deps/models/yolov8n-seg_fp32_${size}_batch.onnx" --check >/dev/null
  done
fi
fi

# GPU machines (`make gpu-deps`, `deploy/install-deps.sh --gpu`): the GPU build of
# ONNX Runtime (same version, so ort's api-31 fits) and the CUDA 13 / cuDNN 9
# libraries its CUDA provider loads, all from PyPI wheels: no system CUDA toolkit,
# only the NVIDIA driver (580 or newer: CUDA 13). onnxruntime-gpu 1.31 on PyPI is
# built for CUDA 13 (its wheel's `cuda` and `cudnn` extras); the pins are the CUDA
# 13.0 releases, the driver's own minor version. The libraries go to .deps/ort-gpu
# and .deps/cuda/lib; `make ... GPU=1` points ORT_DYLIB_PATH and LD_LIBRARY_PATH there.
if [ -n "$GPU" ]; then
  gpu_lib=".deps/ort-gpu/libonnxruntime.so.${ORT_VERSION}"
  if [ ! -f "$gpu_lib" ] || [ ! -d .deps/cuda/lib ]; then
    echo "install-deps: fetching onnxruntime-gpu ${ORT_VERSION} and the CUDA 13 runtime wheels from PyPI (about 2 GB)"
    mkdir -p .deps/gpu-wheels .deps/ort-gpu .deps/cuda/lib
    python3 -m pip download -q --no-deps --only-binary=:all: -d .deps/gpu-wheels \
      "onnxruntime-gpu==${ORT_VERSION}" \
      "nvidia-cuda-runtime==13.0.96" "nvidia-cublas==13.0.2.14" "nvidia-cudnn-cu13==9.19.1.2" \
      "nvidia-cufft==12.0.0.61" "nvidia-curand==10.4.0.35" "nvidia-cuda-nvrtc==13.0.88" \
      "nvidia-nvjitlink==13.0.88"
    python3 - "$ORT_VERSION" <<'PY'
import glob, os, zipfile
for wheel_path in glob.glob(".deps/gpu-wheels/*.whl"):
    wheel = zipfile.ZipFile(wheel_path)
    for name in wheel.namelist():
        base = os.path.basename(name)
        if name.startswith("onnxruntime/capi/libonnxruntime"):
            # The CUDA/TensorRT providers must sit beside libonnxruntime.so.
            target = ".deps/ort-gpu/" + base
        elif name.startswith("nvidia/") and "/lib/" in name and ".so" in base:
            target = ".deps/cuda/lib/" + base
        else:
            continue
        with open(target, "wb") as out:
            out.write(wheel.read(name))
PY
    test -f "$gpu_lib"
  fi
  echo "install-deps: GPU libraries ready: ORT_DYLIB_PATH=$PWD/$gpu_lib LD_LIBRARY_PATH=$PWD/.deps/cuda/lib:$PWD/.deps/ort-gpu"
fi
