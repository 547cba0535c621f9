#!/usr/bin/env bash
# Issue #13's checks on real GPU hardware, in one run of about 10 minutes: what the machine
# offers for Vulkan, the conformance tests on the GPU (bit for bit against the CPU core), the
# paper configuration's training step with per-pass timings, the first 40 ICL frames mapped
# with the paper preset on the GPU and on the CPU (the two maps' tensors must be identical),
# and as much of the whole ICL sequence as fits in the time left (frames per second).
#
# Build here (the GPU machine has no network), then carry the binaries:
#   bash scripts/gpu_check.sh --prepare          # writes gpu_bin/ (ignored by git)
# With the device tool: run(command="bash scripts/gpu_check.sh", carry=["gpu_bin"]).
# On the GPU machine, from the repository root with ../shared beside it:
#   bash scripts/gpu_check.sh [OUT (default: $OUT or gpu_check_out)]
# Everything is logged to OUT/log.txt; each step has its own time limit, so a hung driver
# does not eat the whole run.
set -u
root=$(cd "$(dirname "$0")/.." && pwd)
cd "$root"

if [ "${1:-}" = "--prepare" ]; then
    set -e
    target=${CARGO_TARGET_DIR:-$root/target}
    cargo build --locked --release -p himap
    mkdir -p gpu_bin
    cp "$target/release/himap" gpu_bin/
    # the test executables of the GPU tests (cargo prints their paths as JSON)
    cargo test --locked --release -p himap-tests --no-run --message-format=json 2>/dev/null |
        python3 -c '
import json, sys, shutil
for line in sys.stdin:
    try:
        m = json.loads(line)
    except ValueError:
        continue
    exe = m.get("executable")
    name = m.get("target", {}).get("name", "")
    if exe and name in ("conformance", "vulkan", "query"):
        shutil.copy(exe, "gpu_bin/test-" + name)
        print("gpu_bin/test-" + name)
'
    ls -l gpu_bin
    exit 0
fi

out=${1:-${OUT:-gpu_check_out}}
mkdir -p "$out"
log="$out/log.txt"
bin=gpu_bin/himap
[ -x "$bin" ] || bin=${CARGO_TARGET_DIR:-target}/release/himap
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp}
step() {
    local limit=$1
    shift
    printf '\n== %s (limit %s s)\n' "$*" "$limit" | tee -a "$log"
    local t0=$SECONDS
    timeout "$limit" "$@" 2>&1 | tee -a "$log" | tail -40
    printf -- '-- exit %s after %s s\n' "${PIPESTATUS[0]}" "$((SECONDS - t0))" | tee -a "$log"
}
tensors_hash() {
    # sha256 of a safetensors file's tensor data (the header holds metadata in no fixed order)
    python3 -c '
import hashlib, struct, sys
b = open(sys.argv[1], "rb").read()
n = struct.unpack("<Q", b[:8])[0]
print(hashlib.sha256(b[8 + n:]).hexdigest())
' "$1"
}

step 60 bash ../shared/tools/gpu-probe.sh "$bin"
step 30 "$bin" devices
for t in gpu_bin/test-conformance gpu_bin/test-vulkan gpu_bin/test-query; do
    [ -x "$t" ] && HIMAP_REQUIRE_VULKAN=1 step 240 "$t" --test-threads 1
done
step 120 "$bin" bench --backend all --config paper --profile --steps 5
step 120 "$bin" bench --backend vulkan --config step --profile --steps 5
HIMAP_BENCH_GLOBAL_ATOMICS=1 step 120 "$bin" bench --backend vulkan --config paper --profile --steps 5
icl=../shared/data/icl-livingroom1
step 240 "$bin" map "$icl" --preset paper --backend vulkan --frames 0:40 --out "$out/icl40_gpu"
step 300 "$bin" map "$icl" --preset paper --backend cpu --frames 0:40 --out "$out/icl40_cpu"
if [ -f "$out/icl40_gpu/map.safetensors" ] && [ -f "$out/icl40_cpu/map.safetensors" ]; then
    g=$(tensors_hash "$out/icl40_gpu/map.safetensors")
    c=$(tensors_hash "$out/icl40_cpu/map.safetensors")
    if [ "$g" = "$c" ]; then verdict="identical"; else verdict="DIFFERENT"; fi
    echo "ICL 0..40, paper preset: GPU map $g, CPU map $c: $verdict" | tee -a "$log"
fi
step 480 "$bin" map "$icl" --preset paper --backend vulkan --out "$out/icl_gpu"
for s in "$out"/icl40_gpu "$out"/icl40_cpu "$out"/icl_gpu; do
    [ -f "$s/summary.json" ] && python3 -c '
import json, sys
s = json.load(open(sys.argv[1] + "/summary.json"))
print(sys.argv[1], s["backend"], "frames", s["frames"], "iterations", s["iterations"],
      "ms/iteration %.2f" % (1e3 * s["seconds_per_iteration"]),
      "frames/s %.2f" % (s["frames"] / max(s["seconds_mapping"], 1e-9)),
      "PSNR", s["mean_psnr"])
' "$s" | tee -a "$log"
done
echo "log: $log"
