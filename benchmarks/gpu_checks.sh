#!/usr/bin/env bash
# The GPU checks of the pose networks, as one command for a machine with a CUDA GPU.
#
#   bash benchmarks/gpu_checks.sh            # about 6-8 minutes on one H100/H200
#
# 1. the gpu-marked tests of the networks (tests/nn, tests/predict);
# 2. benchmarks/predict.py --preset paper --device cuda on 7 cameras (eager vs optimized vs
#    bf16 frames/s end to end, GFLOP/s, the matmul roofline of the GPU);
# 3. benchmarks/throughput.py --preset paper --device cuda with a few hundred training steps
#    (eager vs optimized step time).
# The benchmark results are written as JSON under benchmarks/results/ (and copied to $OUT when
# that is set, as the device tool's machines do). Runs from the repository root with the
# machine's python3 (PYTHON overrides it); the package is imported from the working tree.
set -u
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1
status=0

"$PY" - <<'EOF' || exit 2
import importlib
import torch
print(f"torch {torch.__version__}, CUDA {torch.version.cuda}, "
      f"GPU: {torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'none'}")
if not torch.cuda.is_available():
    raise SystemExit("no CUDA GPU visible to torch: these checks need one")
missing = []
for mod in ("freipose.nn.fast", "freipose.synth", "freipose.predict.network", "pytest"):
    try:
        importlib.import_module(mod)
    except ImportError as exc:
        missing.append(f"{mod}: {exc}")
if missing:
    raise SystemExit("cannot import what the checks need (carry the missing packages as "
                     "wheels):\n  " + "\n  ".join(missing))
EOF

echo "== gpu-marked tests"
timeout 240 "$PY" -m pytest -q -m gpu tests/nn tests/predict -p no:cacheprovider || status=1

echo "== benchmarks/predict.py, paper preset, 7 cameras, CUDA"
(cd benchmarks && timeout 300 "$PY" predict.py --preset paper --device cuda --cameras 7 \
    --frames 160 --batch 16 --repeat 2) || status=1

echo "== benchmarks/throughput.py, paper preset, CUDA, training steps"
(cd benchmarks && timeout 240 "$PY" throughput.py --preset paper --device cuda --batch 4 \
    --repeats 5 --train-steps 150) || status=1

if [ -n "${OUT:-}" ]; then
    mkdir -p "$OUT"
    find benchmarks/results/predict benchmarks/results/throughput -name '*.json' -newer "$0" \
        -exec cp {} "$OUT"/ \; 2>/dev/null
fi
exit $status
