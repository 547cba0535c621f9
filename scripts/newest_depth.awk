# Newest-frame depth of a run, from its metrics.csv (column 5: Depth L1 of the update's newest
# frame, cm): prints the mean over the updates, the worst average over 5 consecutive updates
# (issue #11's house bar; "-" with fewer than 5 updates) and the share of updates off by more
# than 30 cm (%). Used by whole_sequences.sh and house_spread.sh:
#   awk -F, -f scripts/newest_depth.awk RUN/metrics.csv
NR > 1 && $5 != "" { d[n++] = $5; s += $5; if ($5 > 30) o++ }
END {
    if (n == 0) { print "- - -"; exit }
    w = -1
    for (i = 0; i + 5 <= n; i++) {
        t = 0
        for (j = i; j < i + 5; j++) t += d[j]
        if (t / 5 > w) w = t / 5
    }
    printf "%.1f %s %.0f\n", s / n, (w < 0 ? "-" : sprintf("%.1f", w)), 100 * o / n
}
