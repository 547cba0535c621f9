#!/usr/bin/env bash
# The paper's training step on the CPU, himap and PyTorch side by side in one run (issue #12):
# `himap bench --config step` (the paper's model over a 4 m cube, 2048 rays x 64 samples, L1
# colour loss, Adam on every group), then scripts/bench_step_torch.py with the same model and
# batch. Dev-only: needs `pip install torch`.
#
# Usage: scripts/bench_vs_torch.sh [THREADS (default 2)] [STEPS (default 5)]
# Environment: HIMAP (default: target/release/himap, built if missing), PYTHON (python3).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
threads=${1:-2}
steps=${2:-5}
HIMAP=${HIMAP:-${CARGO_TARGET_DIR:-$root/target}/release/himap}
if [ ! -x "$HIMAP" ]; then
    (cd "$root" && cargo build --release -p himap)
fi
echo "== himap ($HIMAP)"
"$HIMAP" bench --backend cpu --config step --threads "$threads" --steps "$steps"
echo
echo "== PyTorch"
"${PYTHON:-python3}" "$root/scripts/bench_step_torch.py" --threads "$threads" --steps "$steps"
