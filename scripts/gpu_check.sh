#!/usr/bin/env bash
# Issue #13's checks on real GPU hardware, in one run of about 4 minutes (an NVIDIA H200,
# 2026-12-04): what the machine offers for Vulkan (every shader entry point built), the paper
# configuration's training step with per-pass timings, the first 30 ICL frames mapped with
# the paper preset and a short schedule on the GPU (per-pass profile of the mapping steps) and
# on the CPU (the two maps' tensors must be identical), the conformance tests on the GPU (bit
# for bit against the CPU core), and the whole ICL sequence (ms per iteration, frames/s).
#
# Build here (the GPU machine has no network), then carry the binaries:
#   bash scripts/gpu_check.sh --prepare          # writes gpu_bin/ (ignored by git)
# With the device tool: run(command="bash scripts/gpu_check.sh", carry=["gpu_bin", "gpu_data", ".gl"]);
# .gl/ holds Debian's Vulkan loader packages for a machine without one (unpacked when needed):
#   mkdir -p .gl && (cd .gl && apt-get download libvulkan1)
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
    # the data and the probe, for a machine that gets only the checkout (the device tool)
    rm -rf gpu_data
    mkdir -p gpu_data
    cp -r ../shared/data/icl-livingroom1 gpu_data/
    cp ../shared/tools/gpu-probe.sh gpu_data/
    exit 0
fi

out=${1:-${OUT:-gpu_check_out}}
mkdir -p "$out"
log="$out/log.txt"
# The maps, renders and meshes go to a scratch folder; OUT keeps the log and the summaries
# (the device tool brings back at most 8 files).
work=${GPU_CHECK_WORK:-/tmp/gpu_check_work}
mkdir -p "$work"
bin=gpu_bin/himap
[ -x "$bin" ] || bin=${CARGO_TARGET_DIR:-target}/release/himap
export XDG_RUNTIME_DIR=${XDG_RUNTIME_DIR:-/tmp}
# The whole run's budget in seconds (GPU_CHECK_BUDGET, default 600): a step whose limit does
# not fit in what is left runs with what is left, or is skipped under 20 s.
budget=${GPU_CHECK_BUDGET:-600}
# Data and the probe: ../shared where it is beside the checkout, else gpu_data/ (the device
# tool carries only the checkout: copy them there with --prepare).
icl=../shared/data/icl-livingroom1
[ -d "$icl" ] || icl=gpu_data/icl-livingroom1
probe=../shared/tools/gpu-probe.sh
[ -f "$probe" ] || probe=gpu_data/gpu-probe.sh
step() {
    local limit=$1
    shift
    local left=$((budget - SECONDS))
    if [ "$left" -lt 20 ]; then
        printf '\n== %s: skipped (%s s left)\n' "$*" "$left" | tee -a "$log"
        return
    fi
    [ "$limit" -gt "$left" ] && limit=$left
    printf '\n== %s (limit %s s, at %s s)\n' "$*" "$limit" "$SECONDS" | tee -a "$log"
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
summary() {
    [ -f "$1/summary.json" ] && python3 -c '
import json, sys
s = json.load(open(sys.argv[1] + "/summary.json"))
print(sys.argv[1], s["backend"], "frames", s["frames"], "iterations", s["iterations"],
      "ms/iteration %.2f" % (1e3 * s["seconds_per_iteration"]),
      "frames/s %.2f" % (s["frames"] / max(s["seconds_mapping"], 1e-9)),
      "PSNR", s["mean_psnr"])
' "$1" | tee -a "$log"
}

# A Vulkan loader where the machine has none (the device tool's advice: Debian packages
# downloaded beforehand into .gl/).
if ! ldconfig -p 2>/dev/null | grep -q libvulkan.so.1 && ls .gl/*.deb >/dev/null 2>&1; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
    echo "unpacked the Vulkan loader from .gl/" | tee -a "$log"
fi
step 40 bash "$probe" "$bin"
# The NVIDIA ICD where the loader does not find it by itself.
if ! "$bin" devices 2>/dev/null | grep -qi "discrete"; then
    for j in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/share/vulkan/icd.d/nvidia_icd.json \
        /etc/vulkan/icd.d/nvidia_icd.json; do
        if [ -f "$j" ]; then
            export VK_DRIVER_FILES=$j VK_ICD_FILENAMES=$j
            echo "no discrete GPU listed; retrying with VK_DRIVER_FILES=$j" | tee -a "$log"
            break
        fi
    done
fi
step 90 "$bin" devices --pipelines
step 40 "$bin" devices --divide 1000000
[ -x gpu_bin/test-conformance ] && HIMAP_REQUIRE_VULKAN=1 step 120 gpu_bin/test-conformance --test-threads 4
step 120 "$bin" bench --backend all --config paper --profile --steps 5
step 150 "$bin" map "$icl" --preset paper --backend vulkan --frames 0:30 --config scripts/configs/icl-livingroom1.toml --config scripts/gpu_check_short.toml --profile --out "$work/icl30_gpu"
step 150 "$bin" map "$icl" --preset paper --backend cpu --frames 0:30 --config scripts/configs/icl-livingroom1.toml --config scripts/gpu_check_short.toml --out "$work/icl30_cpu"
if [ -f "$work/icl30_gpu/map.safetensors" ] && [ -f "$work/icl30_cpu/map.safetensors" ]; then
    g=$(tensors_hash "$work/icl30_gpu/map.safetensors")
    c=$(tensors_hash "$work/icl30_cpu/map.safetensors")
    if [ "$g" = "$c" ]; then verdict="identical"; else verdict="DIFFERENT"; fi
    echo "ICL 0..30, paper preset, short schedule: GPU map $g, CPU map $c: $verdict" | tee -a "$log"
fi
summary "$work/icl30_gpu"
summary "$work/icl30_cpu"
[ -x gpu_bin/test-vulkan ] && HIMAP_REQUIRE_VULKAN=1 step 120 gpu_bin/test-vulkan --test-threads 4
[ -x gpu_bin/test-query ] && HIMAP_REQUIRE_VULKAN=1 step 60 gpu_bin/test-query --test-threads 4
step 300 "$bin" map "$icl" --preset paper --config scripts/configs/icl-livingroom1.toml --backend vulkan --out "$work/icl_gpu"
summary "$work/icl_gpu"
step 60 "$bin" bench --backend vulkan --config step --profile --steps 5
HIMAP_BENCH_GLOBAL_ATOMICS=1 step 60 "$bin" bench --backend vulkan --config paper --profile --steps 5
# Keep the small outputs (the device tool brings back at most 8 files): the summaries.
for s in icl30_gpu icl30_cpu icl_gpu; do
    [ -f "$work/$s/summary.json" ] && cp "$work/$s/summary.json" "$out/summary_$s.json"
done
[ -f "$work/icl_gpu/metrics.csv" ] && cp "$work/icl_gpu/metrics.csv" "$out/metrics_icl_gpu.csv"
echo "log: $log (run took $SECONDS s)"
