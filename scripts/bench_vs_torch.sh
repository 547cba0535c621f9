#!/usr/bin/env bash
# The paper's training step on the CPU, himap and PyTorch side by side in one run (issue #12):
# `himap bench --config step` (the paper's model over a 4 m cube, 2048 rays x 64 samples, L1
# colour loss, Adam on every group), then scripts/bench_step_torch.py with the same model and
# batch, and a last line with the ratio of the two steps. Dev-only: needs `pip install torch`.
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
ours=$("$HIMAP" bench --backend cpu --config step --threads "$threads" --steps "$steps")
echo "$ours"
echo
echo "== PyTorch"
theirs=$("${PYTHON:-python3}" "$root/scripts/bench_step_torch.py" --threads "$threads" --steps "$steps")
echo "$theirs"
# The issue's ratio: PyTorch's training step over ours, and the forward rates.
h_ms=$(echo "$ours" | awk '/^cpu/ {print $NF}')
h_fwd=$(echo "$ours" | awk '/^cpu/ {print $(NF-2)}')
t_ms=$(echo "$theirs" | awk '/^pytorch train step/ {print $4}')
if [ -n "$h_ms" ] && [ -n "$t_ms" ]; then
    echo
    awk -v h="$h_ms" -v t="$t_ms" -v f="$h_fwd" 'BEGIN {
        printf "== side by side: himap %.1f ms per step, PyTorch %.1f ms: %.1fx (bar: 10x, <= 100 ms); himap forward %.2f M samples/s (bar: 3 M)\n", h, t, t / h, f / 1e6
    }'
fi
