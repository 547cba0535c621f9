#!/usr/bin/env bash
# Mapping quality of the `small` preset on the CPU (issue #5): the demo room, ICL living room 1,
# 7-Scenes redkitchen, and the ablations on ICL. Prints one table of the issue's metrics and
# one ablation table; every run's outputs (metrics.csv, summary.json, mesh.ply, renders/) stay
# in $OUT.
#
# Time on the 2-core development VM (release build, THREADS=2, measured 2026-12-01 with the
# 48-sample, 64..4 cm `small` preset):
#   demo room (60 frames 128x96)                        about 1 min (100-150 ms per iteration)
#   ICL living room 1 (frames 0..30, 320x240)           about 1 min (150 ms per iteration)
#   7-Scenes redkitchen (frames 0..30, 320x240)         about 1 min (150 ms per iteration)
#   ablations on ICL: 5 more runs                       about 6 min
#   total                                               about 10 min
# Per-region mesh metrics of the demo room: scripts/demo_regions.py (numpy, scipy).
#
# Usage: scripts/quality.sh [--no-ablation] [--only demo|icl|7scenes] [--table-only]
#   --table-only prints the tables from the summaries already in $OUT without running.
# Environment:
#   HIMAP    the himap binary (default: target/release/himap, built if missing)
#   DATA     the shared datasets (default: ../shared/data next to the repository)
#   OUT      output folder (default: out/quality)
#   THREADS  worker threads (default 2)
#   FRAMES   source frames of ICL and 7-Scenes as start:end:stride (default 0:30:1)
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
HIMAP=${HIMAP:-$root/target/release/himap}
DATA=${DATA:-$root/../shared/data}
OUT=${OUT:-$root/out/quality}
THREADS=${THREADS:-2}
FRAMES=${FRAMES:-0:30:1}
ablation=1
only=""
table_only=0
while [ $# -gt 0 ]; do
    case "$1" in
        --no-ablation) ablation=0 ;;
        --only) only="$2"; shift ;;
        --table-only) table_only=1 ;;
        *) echo "unknown argument $1" >&2; exit 2 ;;
    esac
    shift
done

if [ "$table_only" = 0 ] && [ ! -x "$HIMAP" ]; then
    echo "building himap (release)" >&2
    (cd "$root" && cargo build --release -p himap)
    HIMAP=${CARGO_TARGET_DIR:-$root/target}/release/himap
fi
command -v jq >/dev/null || { echo "quality.sh needs jq" >&2; exit 1; }
mkdir -p "$OUT"

# run NAME DATASET [extra himap map args...]: maps with the small preset, logs to NAME.log.
run_map() {
    local name=$1 data=$2
    shift 2
    if [ ! -d "$data" ]; then
        echo "skipping $name: $data not found" >&2
        return 0
    fi
    echo "running $name" >&2
    local t0=$SECONDS
    "$HIMAP" map "$data" --out "$OUT/$name" --preset small --threads "$THREADS" "$@" \
        >"$OUT/$name.log" 2>&1 || { echo "$name failed, see $OUT/$name.log" >&2; return 0; }
    echo "  $name: $((SECONDS - t0)) s" >&2
}

run_demo() {
    echo "running demo" >&2
    local t0=$SECONDS
    "$HIMAP" demo --out "$OUT/demo" --threads "$THREADS" "$@" >"$OUT/demo.log" 2>&1 \
        || { echo "demo failed, see $OUT/demo.log" >&2; return 0; }
    echo "  demo: $((SECONDS - t0)) s" >&2
}

# row NAME SUMMARY: one table row from a summary.json.
row() {
    local name=$1 s=$2
    if [ ! -f "$s" ]; then
        printf '%-22s %s\n' "$name" "(no result)"
        return
    fi
    jq -r --arg n "$name" '
        def f(x; p): if x == null then "-" else (x * p | round / p | tostring) end;
        [$n, f(.mean_psnr; 100), f(.mean_ssim; 1000), f(.mean_depth_l1_cm; 10),
         f(.mesh.accuracy_cm; 100), f(.mesh.completion_cm; 100), f(.mesh.completion_ratio_pct; 10),
         (.mesh_faces | tostring), f(.seconds_per_iteration * 1000; 1), f(.seconds_total; 1),
         f(.final_psnr; 100), f(.final_depth_l1_cm; 10)]
        | @tsv' "$s" | awk -F'\t' '{printf "%-22s %7s %6s %8s %7s %7s %7s %8s %8s %7s %8s %8s\n", $1,$2,$3,$4,$5,$6,$7,$8,$9,$10,$11,$12}'
}

# final PSNR / DL1: the final map re-rendered at every eval.final_every-th frame.
header() {
    printf '%-22s %7s %6s %8s %7s %7s %7s %8s %8s %7s %8s %8s\n' \
        run "PSNR" SSIM "DL1(cm)" "Acc" "Comp" "Ratio%" faces "ms/it" "time(s)" "finPSNR" "finDL1"
}

icl=$DATA/icl-livingroom1
kitchen=$DATA/7scenes-redkitchen
if [ "$table_only" = 0 ]; then
    if [ -z "$only" ] || [ "$only" = demo ]; then run_demo; fi
    if [ -z "$only" ] || [ "$only" = icl ]; then
        run_map icl "$icl" --frames "$FRAMES" --resize 320x240
    fi
    if [ -z "$only" ] || [ "$only" = 7scenes ]; then
        run_map 7scenes "$kitchen" --frames "$FRAMES" --resize 320x240
    fi
fi

echo
echo "Quality, small preset, CPU (bars of issue #5: ICL PSNR >= 25, SSIM >= 0.75, DL1 <= 12 cm;"
echo "demo Acc <= 5 cm, Comp <= 6 cm, ratio >= 70 %)"
header
row "demo room" "$OUT/demo/map/summary.json"
row "ICL livingroom1" "$OUT/icl/summary.json"
row "7-Scenes redkitchen" "$OUT/7scenes/summary.json"

if [ "$ablation" = 1 ] && [ -z "$only" ] && [ -d "$icl" ]; then
    abl=$OUT/ablation
    mkdir -p "$abl"
    # A dense 2 cm appearance grid has ~190M parameters on ICL (3.7 GB, hours on 2 cores): the
    # grid ablation compares dense and factorized at a 6 cm appearance level instead.
    printf '[model]\ngrid_kind = "dense"\n[model.appearance]\nchannels = 16\ncell_sizes = [0.24, 0.06]\n' >"$abl/dense.toml"
    printf '[model.appearance]\nchannels = 16\ncell_sizes = [0.24, 0.06]\n' >"$abl/factorized-6cm.toml"
    printf '[model]\ndual_path = false\n' >"$abl/no-dual.toml"
    printf '[model]\nrender_mode = "sdf-direct"\n' >"$abl/sdf-direct.toml"
    printf '[model]\nrender_mode = "occupancy"\n' >"$abl/occupancy.toml"
    for a in factorized-6cm dense no-dual sdf-direct occupancy; do
        [ "$table_only" = 1 ] && continue
        echo "running ablation $a" >&2
        t0=$SECONDS
        "$HIMAP" map "$icl" --out "$abl/$a" --config "$abl/$a.toml" --threads "$THREADS" \
            --frames "$FRAMES" --resize 320x240 >"$abl/$a.log" 2>&1 \
            || echo "ablation $a failed, see $abl/$a.log" >&2
        echo "  $a: $((SECONDS - t0)) s" >&2
    done
    echo
    echo "Ablations on ICL livingroom1 ($FRAMES, 320x240; each changes one setting of small)"
    header
    row "Hi-Map (small)" "$OUT/icl/summary.json"
    row "factorized, app 6 cm" "$abl/factorized-6cm/summary.json"
    row "dense, app 6 cm" "$abl/dense/summary.json"
    row "no dual path" "$abl/no-dual/summary.json"
    row "sdf-direct" "$abl/sdf-direct/summary.json"
    row "occupancy" "$abl/occupancy/summary.json"
fi
