# stillmap: `make demo` and `make test` install what is missing, build, and run.
SHELL := /bin/bash
SHARED ?= $(abspath ../shared)
TUM ?= $(SHARED)/data/tum/rgbd_dataset_freiburg1_rpy
ORT_VERSION := 1.31.1
ORT_LIB := $(abspath .deps/ort/libonnxruntime.so.$(ORT_VERSION))
CARGO ?= cargo

export SHARED TUM
# ONNX Runtime for `ort` (loaded with dlopen at run time; see deploy/install-deps.sh).
export ORT_DYLIB_PATH := $(ORT_LIB)

.PHONY: deps dashboard build demo test bench bench-codecs bench-transport clean

deps:
	@deploy/install-deps.sh

# The dashboard is plain ES modules (dashboard/src) plus three.js from npm; `deps`
# installs the npm packages, the server serves them (no bundling step).
dashboard: deps

build: deps
	$(CARGO) build --workspace --bins

demo: build
	deploy/demo.sh target/debug

test: build
	$(CARGO) test --workspace --no-fail-fast

bench: bench-codecs bench-transport

bench-codecs: deps
	$(CARGO) run --release -q -p stillmap-client -- bench-codecs --tum $(TUM)

bench-transport: deps
	$(CARGO) build --release --workspace --bins
	deploy/bench-transport.sh target/release

clean:
	$(CARGO) clean
