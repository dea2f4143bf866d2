#!/bin/sh
# Instructions per ray and per reference of every bench case, from callgrind.
#   profile.sh BENCH_BINARY OUTDIR [rays]
# Runs the benchmark once per case under callgrind (one build, one batch) and
# reads the inclusive instruction counts (Ir) of gc_bench_intersect (the timed
# twin over the batch) and gc_grid_build.
set -eu
bin=$1
out=$2
rays=${3:-20000}
mkdir -p "$out"
cases=$("$bin" 1 1 | awk 'NR > 1 {print $1}')
printf '%-20s %12s %14s %12s\n' case Ir/ray build_Ir Ir/ref
for c in $cases; do
    f="$out/callgrind.$c.out"
    valgrind --tool=callgrind --callgrind-out-file="$f" "$bin" "$rays" 1 "$c" >"$out/$c.txt" 2>"$out/$c.log"
    callgrind_annotate --inclusive=yes "$f" >"$out/$c.annotate" 2>/dev/null
    trace=$(awk '/gc_bench_intersect/ {gsub(",", "", $1); print $1; exit}' "$out/$c.annotate")
    build=$(awk '/gc_grid_build[^_]/ || /gc_grid_build$/ {gsub(",", "", $1); print $1; exit}' "$out/$c.annotate")
    refs=$(awk 'NR == 2 {print $5}' "$out/$c.txt")
    awk -v c="$c" -v t="$trace" -v b="$build" -v r="$rays" -v n="$refs" \
        'BEGIN {printf "%-20s %12.1f %14.0f %12.1f\n", c, t / r, b, b / n}'
done
