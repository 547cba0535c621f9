#!/usr/bin/env bash
# Two himap binaries' paper step side by side, at the same time: A pinned to one core and B to
# the other, then swapped, ROUNDS times. On a shared VM, runs one after the other drift by 20 %
# and more; run concurrently, both see the same neighbours (they do share the L3 cache and the
# memory bandwidth, which a sequential comparison does not). Each run reports its fastest of
# 8 steps (`--fastest`: a neighbour's burst slows some steps, never speeds one up). Prints each
# binary's forward samples/s and ms per step, and the mean.
#
# Usage: scripts/ab_bench.sh A_BINARY B_BINARY [ROUNDS (default 2)] [extra `himap bench` args]
# Needs taskset (util-linux) and 2 cores.
set -euo pipefail
if [ $# -lt 2 ]; then
    sed -n 2,9p "$0" >&2
    exit 2
fi
a=$1 b=$2
rounds=${3:-2}
shift $(( $# >= 3 ? 3 : 2 ))
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
one() { # BINARY CORE LABEL [extra bench args]
    local bin=$1 core=$2 label=$3
    shift 3
    taskset -c "$core" "$bin" bench --backend cpu --config step --threads 1 --steps 8 --fastest "$@" 2>&1 |
        awk -v l="$label" '/^cpu/ {print l, $(NF-2), $NF}'
}
for _ in $(seq "$rounds"); do
    for swap in 0 1; do
        one "$a" "$swap" A "$@" >"$tmp/a" &
        one "$b" $((1 - swap)) B "$@" >"$tmp/b" &
        wait
        cat "$tmp/a" "$tmp/b"
    done
done | awk '{ f[$1] = f[$1] " " $2; m[$1] = m[$1] " " $3; s[$1] += $3; n[$1]++ }
    END { for (k in f) printf "%s  forward samples/s:%s  ms/step:%s  mean %.1f ms\n", k, f[k], m[k], s[k] / n[k] }' |
    sort
