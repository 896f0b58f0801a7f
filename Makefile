# stillmap: `make demo` and `make test` install what is missing, build, and run.
SHELL := /bin/bash
SHARED ?= $(abspath ../shared)
TUM ?= $(SHARED)/data/tum/rgbd_dataset_freiburg1_rpy
ORT_VERSION := 1.31.1
ORT_LIB := $(abspath .deps/ort/libonnxruntime.so.$(ORT_VERSION))
CARGO ?= cargo

# GPU=1 (GPU machines, after `make gpu-deps`): the GPU build of ONNX Runtime and the
# CUDA libraries from .deps, and segmentation on CUDA.
GPU ?=
ifeq ($(GPU),1)
ORT_LIB := $(abspath .deps/ort-gpu/libonnxruntime.so.$(ORT_VERSION))
export LD_LIBRARY_PATH := $(abspath .deps/cuda/lib):$(abspath .deps/ort-gpu)$(if $(LD_LIBRARY_PATH),:$(LD_LIBRARY_PATH))
export STILLMAP_EXECUTION_PROVIDER := cuda
export GPU
endif

export SHARED TUM
# ONNX Runtime for `ort` (loaded with dlopen at run time; see deploy/install-deps.sh).
export ORT_DYLIB_PATH := $(ORT_LIB)

.PHONY: deps gpu-deps dashboard build demo lint test bench bench-codecs bench-transport bench-fleet cluster-demo soak fuzz vocabulary clean

deps:
	@deploy/install-deps.sh $(if $(filter 1,$(GPU)),--gpu)

# The third command on a GPU machine: the GPU build of ONNX Runtime and the CUDA 13 /
# cuDNN 9 libraries from PyPI wheels (then `make demo GPU=1`, `make bench-fleet GPU=1`).
gpu-deps:
	@deploy/install-deps.sh --gpu

# The dashboard is plain ES modules (dashboard/src) plus three.js from npm; `deps`
# installs the npm packages, the server serves them (no bundling step).
dashboard: deps

build: deps
	$(CARGO) build --workspace --bins

demo: build
	deploy/demo.sh target/debug

# The lint policy (rustfmt.toml, [workspace.lints] in Cargo.toml, clippy.toml):
# formatting, clippy with warnings as errors, and rustdoc with warnings as errors
# (every intra-doc link resolves). `make test` runs it first.
lint: deps
	$(CARGO) fmt --all --check
	$(CARGO) clippy --workspace --all-targets -- -D warnings
	$(CARGO) clippy -p stillmap-server --no-default-features -- -D warnings  # the server without Zenoh (the fuzz targets build it so)
	$(CARGO) clippy -p stillmap-client --no-default-features -- -D warnings  # a robot's client without Zenoh and OpenNI2
	RUSTDOCFLAGS="-D warnings" $(CARGO) doc --workspace --no-deps

test: build lint
	$(CARGO) test --workspace --no-fail-fast

bench: bench-codecs bench-transport

# Fleet capacity: N robots against a fresh release server per run; prints the
# README's Markdown table (deploy/bench-fleet.sh says what the sweep is).
bench-fleet: deps
	$(CARGO) build --release --workspace --bins
	deploy/bench-fleet.sh target/release

# Several servers on one Zenoh network on this machine: a router, two servers, four
# robots; placement, kill -9 of a server and where its robots went, latency through
# the router (deploy/cluster-demo.sh says what it runs).
cluster-demo: deps
	$(CARGO) build --release --workspace --bins
	deploy/cluster-demo.sh target/release

# Soak: 8 robots in back-to-back sessions for 10 min against a release server, its
# memory, threads and open files every 10 s (deploy/soak.sh says what it varies).
soak: deps
	$(CARGO) build --release --workspace --bins
	deploy/soak.sh target/release

# Fuzzing: every cargo-fuzz target in fuzz/ for FUZZ_RUNS executions (nightly; prints
# executions and crashes per target; deploy/fuzz.sh says more).
FUZZ_RUNS ?= 1000000
fuzz: deps
	deploy/fuzz.sh $(FUZZ_RUNS)

bench-codecs: deps
	$(CARGO) run --release -q -p stillmap-client -- bench-codecs --tum $(TUM)

bench-transport: deps
	$(CARGO) build --release --workspace --bins
	deploy/bench-transport.sh target/release

# The shipped place-recognition vocabulary, trained from the public clip (deterministic:
# places/tests/vocabulary.rs checks the committed file is this step's output).
vocabulary: deps
	$(CARGO) run --release -p stillmap-places --example train_vocabulary

clean:
	$(CARGO) clean
