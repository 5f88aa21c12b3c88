#!/usr/bin/env bash
# One prepared run for a lent NVIDIA GPU machine (at most about 9 minutes; each part
# has its own time limit and writes its results as it goes): DLCTUS's trunk alone in
# its three forms (XLA convolutions, im2col matmuls, Pallas Triton kernels over tiles
# and warp counts); the compiled kernels' parity tests and the PyTorch parity tests on
# the GPU; the whole step at 720p, 1080p and 4K, 2x and 4x, bfloat16 and float32, in
# each form (Config.kernels), PyTorch beside it when the machine has a CUDA build of
# torch (never downloaded); the training step at the thesis's scale (crop 256, 30
# frames, batch 4) in each form; and, given a CPU run's checkpoint, a short training run
# at that scale. Results (JSON, Markdown and logs; at most the 8 files the device tool
# brings back) go to $OUT (default out/gpu).
#
#   bash experiments/gpu/run.sh [CHECKPOINT]      # CHECKPOINT: e.g. runs/diverse-x4/checkpoint.msgpack
#
# JAX: uses the machine's JAX when it already sees a GPU (the lent machines carry one
# with its CUDA plugin and cannot reach PyPI); otherwise installs the `cuda` extra.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-out/gpu}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
CKPT=${1:-}
PARTS=${PARTS:-forms,tests,bench,loop,profile,train}   # e.g. PARTS=train to rerun the training part alone
has() { [[ ",$PARTS," == *",$1,"* ]]; }
log() { echo "== $(date +%T) $*" | tee -a "$OUT/run.log"; }

if ! $PY -c "import jax, sys; sys.exit(jax.devices()[0].platform != 'gpu')" 2>/dev/null; then
  log "installing the cuda extra"
  $PY -m pip install -q -e ".[cuda]" || exit 1
fi
# Packages the lent machine lacks (OpenEXR) travel as wheels in .whl (ignored by git):
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#     --platform manylinux_2_28_x86_64 -d .whl OpenEXR==3.5.3
if ! $PY -c "import OpenEXR" 2>/dev/null && ls .whl/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl \
    && export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv >> "$OUT/run.log" 2>&1
$PY - <<'EOF' | tee -a "$OUT/run.log"
import jax, jaxlib, flax, optax
print("jax", jax.__version__, "jaxlib", jaxlib.__version__, "flax", flax.__version__,
      "optax", optax.__version__, "devices", jax.devices())
EOF

# 1. the trunk alone in its three forms (XLA convolutions, im2col matmuls, the Pallas
# Triton kernels over tiles and warp counts), each checked against the XLA trunk
if has forms; then
log "trunk forms"
timeout 130 $PY experiments/gpu/trunk_forms.py --out "$OUT/trunk-forms.json" 2>&1 \
  | tail -n 60 >> "$OUT/run.log"
fi

# 2. the compiled kernels and the numerics against PyTorch on the GPU. Float32 matmuls
# and convolutions at full precision: XLA's GPU default uses TF32 (10-bit mantissa),
# far from the 1e-5 these tests hold.
if has tests; then
log "parity tests"
JAX_DEFAULT_MATMUL_PRECISION=highest timeout 90 $PY -m pytest -q -x -p no:cacheprovider \
  -n 0 ${TESTS:-tests/test_kernels.py tests/test_dlctus_torch.py} 2>&1 | tail -n 25 > "$OUT/tests.txt"
tail -n 3 "$OUT/tests.txt" | tee -a "$OUT/run.log"
fi

# 3. the whole step in each form, PyTorch beside it when the machine has a CUDA build
# of torch (never downloaded), and the training step at the thesis's scale (crop 256,
# 30 frames, batch 4). Each bench writes its report row by row.
if has bench; then
TORCH=--no-torch
$PY -c "import torch, sys; sys.exit(not torch.cuda.is_available())" 2>/dev/null && TORCH=--torch
log "bench: inference ($TORCH)"
timeout 220 $PY -m jtus.bench --what peak infer --models dlctus --sizes 720p 1080p 4k \
  --factors 2 4 --dtypes bfloat16 float32 --kernels xla im2col pallas $TORCH --repeats 10 \
  --out "$OUT/bench-infer.json" 2>&1 | grep -v "it/s\]" | tail -n 45 >> "$OUT/run.log"
log "bench: training step, crop 256, 30 frames, batch 4"
timeout 120 $PY -m jtus.bench --what train --train-models dlctus --factors 4 \
  --train-crop 256 --train-batch 4 --train-seq 30 --train-loss-frames 5 \
  --train-kernels xla im2col pallas --no-torch --repeats 10 \
  --out "$OUT/bench-train.json" 2>&1 | grep -v "it/s\]" | tail -n 12 >> "$OUT/run.log"
fi

# the step in a frame loop (no wait between frames) beside its blocked latency
if has loop; then
log "frame loop"
timeout 150 $PY experiments/gpu/frame_loop.py --out "$OUT/frame-loop.json" 2>&1 \
  | tail -n 20 >> "$OUT/run.log"
fi

# where the GPU time of the inference and training steps goes, kernel by kernel
if has profile; then
log "profile"
timeout 120 $PY experiments/gpu/profile_step.py --out "$OUT/profile-step.json" 2>&1 \
  | tail -n 60 >> "$OUT/run.log"
fi

# 4. a short run at the thesis's scale from the CPU checkpoint, on randomized scenes
# rendered here (12 scenes x 32 frames: each scene compiles its own renderer)
if has train && [ -n "$CKPT" ]; then
  log "rendering a small randomized dataset at 256x256"
  timeout 120 $PY - <<'EOF' 2>&1 | tail -n 2 | tee -a "$OUT/run.log"
from jtus.sim import generate
from jtus.sampling.jitter import VARIETY
from jtus.sim import randomized
# training seeds past the diverse preset's 200: never a validation or test scene
names = lambda split, n, start=0: tuple(randomized.name_of(s) for s in randomized.split_seeds(split, n, start))
p = generate.Preset((256, 256), (4,), 16, 1, {"train": (names("train", 12, 5000), 1, 32),
                                             "val": (names("val", 2), 1, 32), "test": ((), 1, 1)},
                   VARIETY)
generate.generate(p, "/tmp/gpu-diverse.h5", progress=False)
print("rendered", p.total_frames(), "frames")
EOF
  [ -f /tmp/gpu-diverse.h5 ] || { log "no dataset rendered: no training"; exit 0; }
  log "training from $CKPT: crop 256, 30 frames (loss on the last 5), batch 4"
  timeout 150 $PY -m jtus.train --preset diverse --factor 4 --crop 256 --seq-len 30 \
    --mode bptt --loss-frames 5 --batch 4 --dataset /tmp/gpu-diverse.h5 --epochs 3 \
    --steps-per-epoch 40 --val-videos 2 --val-batches 1 --warmup-steps 20 \
    --init-from "$CKPT" --workdir /tmp/gpu-train --no-eval --quiet 2>&1 | tail -n 8 \
    | tee -a "$OUT/run.log"
  cp /tmp/gpu-train/metrics.csv "$OUT/train-metrics.csv" 2>/dev/null
fi
log "done"
