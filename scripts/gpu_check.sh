#!/usr/bin/env bash
# Every check that needs a GPU, in one run of under 8 minutes (a device session has ~15), logs in $LOGS:
#   1. the GPU step kernel (CUDA C, compiled by NVRTC) against the CPU reference, Ant and Humanoid, float64 and
#      float32 (scripts/check_cuda.py);
#   2. the physics bench: Ant and Humanoid at 4096 to 262144 envs, float32, each block size, MuJoCo C on the
#      machine's cores beside it (benchmarks/bench_gpu_step.py);
#   3. timed training runs of the main job on the GPU, each with the collector's step captured (capture=true: the
#      env step and the policy as CUDA graphs): the CPU's settings for 70 s, then Brax's Ant batch (4096 envs, 32
#      minibatches of 10,240 samples, 4 epochs; brax.md, section 3.1) for 90 s;
#   4. the render bench: 64x64 depth of the Ant scene, eager (benchmarks/bench_render.py).
# The GPU machine has no network: first run scripts/gpu_wheels.sh here, then on the device
#   bash scripts/gpu_check.sh        (carry .whl; LOGS defaults to $OUT, else docs/logs/gpu_<commit>)
set -uo pipefail
cd "$(dirname "$0")/.."
commit=$(git rev-parse --short HEAD 2>/dev/null || echo unknown)
LOGS=${LOGS:-${OUT:-docs/logs/gpu_$commit}}
mkdir -p "$LOGS"
export PYTHONUNBUFFERED=1 TORCHSIM_CACHE_DIR=${TORCHSIM_CACHE_DIR:-/tmp/torchsim_cache}
if [ -d .whl ]; then  # the project's own dependencies, and the project, without a network
  python3 -m pip install -q --no-index --no-deps --no-build-isolation .whl/* >"$LOGS/install.log" 2>&1 \
    && python3 -m pip install -q --no-index --no-deps --no-build-isolation -e . >>"$LOGS/install.log" 2>&1 \
    || { echo "install failed:"; tail -20 "$LOGS/install.log"; exit 1; }
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$LOGS/gpu.txt"
status=0
run() {  # run NAME SECONDS COMMAND...: its output in $LOGS/NAME.log, its time and exit code on the console
  local name=$1 limit=$2; shift 2
  local start=$SECONDS
  timeout "$limit" "$@" >"$LOGS/$name.log" 2>&1
  local rc=$?
  echo "$name: exit $rc after $((SECONDS - start)) s (limit $limit s)"
  tail -n 25 "$LOGS/$name.log"
  [ $rc -eq 0 ] || status=1
}
run check_kernel 120 python3 scripts/check_cuda.py --strategy kernel --methods spring --skip-envs --skip-render \
  --models ant.xml humanoid.xml --steps 10 --out "$LOGS/check_kernel.md"
run bench_gpu_step 180 python3 benchmarks/bench_gpu_step.py --models ant humanoid --batches 4096 65536 262144 \
  --sweep --mujoco-steps 5 --out "$LOGS/bench_gpu_step.md"
run train_cuda 80 python3 -m torchsim.train device=cuda capture=true budget.minutes=1.1 video.enabled=false \
  print_every=5
run train_cuda_brax_batch 100 python3 -m torchsim.train device=cuda capture=true budget.minutes=1.4 \
  video.enabled=false algo.num_envs=4096 algo.unroll=80 algo.minibatches=32 algo.lr=3e-4 print_every=1 \
  eval.interval_steps=2_000_000
run bench_render 30 python3 benchmarks/bench_render.py --device cuda --no-mujoco --size 64 --batches 4096 16384
exit $status
