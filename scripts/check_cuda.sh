#!/usr/bin/env bash
# A few minutes on a CUDA machine: does training run there, how fast, in how much memory,
# does it resume, and does its checkpoint export on the CPU? Run from the repository root:
#   bash scripts/check_cuda.sh            # PYTHON=... to pick the interpreter (default .venv/bin/python)
# Prints steps/s and peak GPU memory for resnet50 at 128x416 batch 4 (fp32 and bf16), then
# resume and CPU export checks; with 2+ GPUs also a short torchrun (DDP, nccl) run; last
# (COMPILE=0 skips it) --compile with bf16, whose first steps include the compilation.
# Exit: 0 all checks ran, 2 no CUDA here, otherwise the exit code of the check that failed.
# DEVICE=cpu ARCH=small STEPS=4 AMPS=off runs the same steps on a CPU (to check the script itself).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
STEPS=${STEPS:-60}
ARCH=${ARCH:-resnet50}
DEVICE=${DEVICE:-cuda}
AMPS=${AMPS:-off bf16}
WORK=${WORK:-$(mktemp -d /tmp/geonet_check_cuda.XXXX)}

if [ "$DEVICE" = cuda ] && ! "$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    "$PY" -c "import torch; print(f'check_cuda: no CUDA device visible to torch {torch.__version__} '
                                   f'(built with CUDA {torch.version.cuda}); nothing to check here')" >&2
    exit 2
fi
run() { echo "+ $*" >&2; "$@"; }
"$PY" -c "import torch; print('torch', torch.__version__, '|', torch.cuda.device_count(), 'GPU(s)',
                              torch.cuda.get_device_name(0) if torch.cuda.is_available() else '')"

run "$PY" -m training.synth --out "$WORK/synth" --sequences 2 --frames 12 --seed 0 --workers 2 >/dev/null
run "$PY" -m training.prepare --kind synth --src "$WORK/synth" --out "$WORK/prepared" --heldout 0 --workers 2 >/dev/null
TRAIN=("$PY" -m training.train --arch "$ARCH" --data-dir "$WORK/prepared" --device "$DEVICE" --num-workers 2
       --log-every $(( STEPS < 20 ? 1 : 10 )) --val-every 100000 --save-every 100000)

speed() {  # steps/s between the first and the last logged step (skips start-up), peak memory
    "$PY" - "$1" <<'PYEOF'
import json, sys
rows = [json.loads(line) for line in open(sys.argv[1])]
a, b = rows[0], rows[-1]
print(f"  {(b['step'] - a['step']) / (b['elapsed_s'] - a['elapsed_s']):.2f} steps/s, "
      f"peak GPU memory {b.get('cuda_max_mem_gb', '?')} GiB, loss {a['total']:.3f} -> {b['total']:.3f}")
PYEOF
}
for amp in $AMPS; do
    run "${TRAIN[@]}" --amp "$amp" --out-dir "$WORK/rigid_$amp" --max-steps "$STEPS" >/dev/null
    echo "$ARCH rigid, 128x416, batch 4, --amp $amp:"; speed "$WORK/rigid_$amp/log.jsonl"
done
run "${TRAIN[@]}" --out-dir "$WORK/half" --max-steps $((STEPS / 2)) >/dev/null
run "${TRAIN[@]}" --out-dir "$WORK/half" --max-steps "$STEPS" --resume "$WORK/half/last.pt" >/dev/null
"$PY" - "$WORK" <<'PYEOF'
import sys
from training.checkpoint import load_checkpoint
work = sys.argv[1]
straight, resumed = (load_checkpoint(f"{work}/{d}/last.pt") for d in ("rigid_off", "half"))
assert straight["step"] == resumed["step"], (straight["step"], resumed["step"])
# cuDNN and atomic-add kernels are not bit-reproducible on a GPU, so report instead of assert
diff = max((straight["model"][k].float() - v.float()).abs().max().item() for k, v in resumed["model"].items())
print(f"resume: half + resume vs straight, max weight difference {diff:.2e} (0 on a CPU)")
PYEOF
run "${TRAIN[@]}" --stage flow --init-checkpoint "$WORK/rigid_off/last.pt" --out-dir "$WORK/flow" \
    --max-steps "$STEPS" >/dev/null
echo "$ARCH flow, 128x416, batch 4:"; speed "$WORK/flow/log.jsonl"

# The GPU checkpoints on a machine without a GPU: one more step on the CPU, and the export.
CUDA_VISIBLE_DEVICES="" run "${TRAIN[@]}" --device cpu --num-workers 0 --out-dir "$WORK/cpu_resume" \
    --max-steps $((STEPS + 1)) --resume "$WORK/half/last.pt" >/dev/null
CUDA_VISIBLE_DEVICES="" run "$PY" -m export --checkpoint "$WORK/flow/last.pt" --out "$WORK/onnx" --force --quiet
echo "CPU: resumed the GPU checkpoint for one step and exported $(ls "$WORK/onnx" | grep -c onnx) ONNX file(s)"

if [ "$("$PY" -c 'import torch; print(torch.cuda.device_count())')" -ge 2 ]; then
    run "$PY" -m torch.distributed.run --standalone --nproc_per_node 2 -m training.train --arch "$ARCH" \
        --data-dir "$WORK/prepared" --device cuda --batch-size 2 --sync-bn --out-dir "$WORK/ddp" \
        --max-steps "$STEPS" --log-every 10 --val-every 100000 --save-every 100000 --num-workers 2 >/dev/null
    echo "torchrun 2 GPUs x batch 2 (effective 4), --sync-bn:"; speed "$WORK/ddp/log.jsonl"
fi
if [ "${COMPILE:-1}" = 1 ]; then
    run "${TRAIN[@]}" --amp bf16 --compile --out-dir "$WORK/rigid_compile" --max-steps "$STEPS" >/dev/null
    echo "$ARCH rigid, 128x416, batch 4, --amp bf16 --compile:"; speed "$WORK/rigid_compile/log.jsonl"
fi
echo "check_cuda: all checks ran; outputs in $WORK"
