#!/usr/bin/env bash
# Wheels the GPU machine lacks (it has no network; its image holds torch, numpy, matplotlib, pyyaml, lxml,
# absl-py, etils), downloaded here into .whl/ for its Python (3.12, x86-64). Run once before scripts/gpu_check.sh;
# the device call carries .whl (about 20 MB).
set -euo pipefail
cd "$(dirname "$0")/.."
rm -rf .whl && mkdir -p .whl
get() {
  python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d .whl "$@"
}
get "mujoco>=3.2" mujoco-core mujoco-studio glfw pyopengl "tensordict>=0.14,<0.15" "torchrl>=0.14.1,<0.15" "pytorch-kinematics>=0.7" \
  arm-pytorch-utilities pytorch-seed "hydra-core>=1.3" "omegaconf<2.4" "pytorch-optimizer>=3.0" importlib-metadata orjson \
  cloudpickle pyvers hoptorch lazy-importer zipp websockets
# hydra's parser runtime is published as source only (pure Python: it installs there without a network)
python -m pip download -q --no-deps --no-binary=:all: -d .whl antlr4-python3-runtime==4.9.3
du -sh .whl
