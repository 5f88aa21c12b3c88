#!/usr/bin/env bash
# One prepared run for a lent NVIDIA GPU machine (at most about 9 minutes; each part
# has its own time limit and writes its results as it ends): DLCTUS inference at 720p,
# 1080p and 4K, 2x and 4x, float32 and bfloat16, with the XLA trunk and the fused Pallas
# trunk (Config.kernels), PyTorch beside it when the machine has a CUDA build of torch
# (never downloaded); the training step at the thesis's scale (crop 256, 30 frames, batch 4),
# the parity tests on the GPU, and a short training run at that scale from a CPU run's checkpoint. Results (JSON
# and logs; seven files at most, what the device tool brings back) go to $OUT
# (default out/gpu).
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
PARTS=${PARTS:-bench,tests,train}   # e.g. PARTS=train to rerun the training part alone
has() { [[ ",$PARTS," == *",$1,"* ]]; }
log() { echo "== $(date +%T) $*" | tee -a "$OUT/run.log"; }

if ! $PY -c "import jax, sys; sys.exit(jax.devices()[0].platform != 'gpu')" 2>/dev/null; then
  log "installing the cuda extra"
  $PY -m pip install -q -e ".[cuda]" || exit 1
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv > "$OUT/env.txt" 2>&1
$PY - <<'EOF' | tee -a "$OUT/env.txt"
import jax, jaxlib, flax, optax
print("jax", jax.__version__, "jaxlib", jaxlib.__version__, "flax", flax.__version__,
      "optax", optax.__version__, "devices", jax.devices())
EOF

# 1. inference, XLA against Pallas, and the training step at paper scale
if has bench; then
TORCH=--no-torch
$PY -c "import torch, sys; sys.exit(not torch.cuda.is_available())" 2>/dev/null && TORCH=--torch
log "bench: inference ($TORCH)"
timeout 180 $PY -m jtus.bench --what peak infer --models dlctus --sizes 720p 1080p 4k \
  --factors 2 4 --dtypes float32 bfloat16 --kernels xla pallas $TORCH --repeats 30 \
  --out "$OUT/bench-infer.json" 2>&1 | grep -v "it/s\]" | tail -n 30 >> "$OUT/run.log"
log "bench: training step, crop 256, 30 frames, batch 4"
for cb in autodiff custom; do
  timeout 90 $PY -m jtus.bench --what train --train-models dlctus --factors 4 \
    --train-crop 256 --train-batch 4 \
    --train-seq 30 --train-loss-frames 5 --train-conv-backward $cb --no-torch --repeats 10 \
    --out "$OUT/bench-train-$cb.json" 2>&1 | grep -v "it/s\]" | tail -n 8 >> "$OUT/run.log"
done

fi

# 2. the numerics against PyTorch and the rollout's own checks, on the GPU. Float32
# matmuls and convolutions at full precision: XLA's GPU default uses TF32 (10-bit
# mantissa), far from the 1e-5 these tests hold.
if has tests; then
log "parity tests"
JAX_DEFAULT_MATMUL_PRECISION=highest timeout 100 $PY -m pytest -q -x -p no:cacheprovider \
  tests/test_dlctus_torch.py tests/test_warp_torch.py tests/test_rollout.py \
  2>&1 | tail -n 25 > "$OUT/tests.txt"
tail -n 3 "$OUT/tests.txt" | tee -a "$OUT/run.log"

fi

# 3. a short run at the thesis's scale from the CPU checkpoint, on randomized scenes
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
