#!/usr/bin/env bash
# The OpenMP wait policy on a shared machine (docs/cli.md, "Shared machines"): times one
# `svpsf correct` of a 512 x 512 map alone and beside a competing OpenMP program (a second
# svpsf correct in a loop, spinning as libgomp does by default), with svpsf's default (passive,
# set by the program itself) and with OMP_WAIT_POLICY=active (what it did before).
# Usage: tools/bench/shared_machine.sh [SVPSF] [REPEATS]   (default build/tools/svpsf/svpsf, 3)
# Needs /usr/bin/python3 with numpy for the inputs. Prints a markdown table on stdout.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
SVPSF=$(realpath "${1:-$ROOT/build/tools/svpsf/svpsf}")
REPEATS=${2:-3}
dir=$(mktemp -d "${TMPDIR:-/tmp}/svpsf-shared.XXXXXX")
competitor=
cleanup() {
    if [[ -n $competitor ]]; then
        kill "$competitor" 2>/dev/null || true
        wait "$competitor" 2>/dev/null || true
    fi
    rm -rf "$dir"
}
trap cleanup EXIT
cd "$dir"
export XDG_CACHE_HOME=$dir/cache # plans measured once, in the warm-up run below
/usr/bin/python3 - <<'EOF'
import numpy as np
rng = np.random.default_rng(1)
n = 512
y, x = np.mgrid[0:n, 0:n]
np.save("pl.npy", 1000 * np.exp(-((x - n / 2) ** 2 + (y - n / 2) ** 2) / (2 * (0.4 * n) ** 2))
        + rng.normal(0, 5, (n, n)))
np.save("b.npy", 10 * np.sin(x / 17.0) * np.cos(y / 23.0) + rng.normal(0, 0.5, (n, n)))
EOF
printf 'pixel_um: 0.5\npsf: {model: moffat, fwhm_um: 1.0, beta: 2.5}\n' >psf.yaml
run=0
correct() { # ENV... : one correct run, prints its wall time in seconds
    run=$((run + 1))
    local t0 t1
    t0=$(date +%s.%N)
    env "$@" "$SVPSF" correct --field b.npy --pl pl.npy --psf psf.yaml -o "out$run" -q >/dev/null
    t1=$(date +%s.%N)
    rm -rf "out$run"
    echo "$t0 $t1" | awk '{printf "%.2f", $2 - $1}'
}
series() { # LABEL ENV...: REPEATS runs, prints "min / median / max"
    local label=$1 times=()
    shift
    for ((i = 0; i < REPEATS; i++)); do times+=("$(correct "$@")"); done
    printf '%s\n' "${times[@]}" | sort -n |
        awk -v l="$label" '{t[NR] = $1} END {printf "| %s | %.2f | %.2f | %.2f |\n", l, t[1], t[int((NR + 1) / 2)], t[NR]}'
}
correct OMP_WAIT_POLICY=passive >/dev/null # warm-up: measures and caches the FFT plans
echo "| 512 x 512 correct (R, 75 iterations, 2 threads) | min s | median s | max s |"
echo "|---|---|---|---|"
series "no competitor of its own, svpsf default (passive)" SVPSF_BENCH=1
series "no competitor of its own, OMP_WAIT_POLICY=active" OMP_WAIT_POLICY=active
# the competitor: another OpenMP program with libgomp's default (spinning) wait policy
(
    child=
    trap '[[ -n $child ]] && kill "$child" 2>/dev/null; exit 0' TERM
    while :; do
        OMP_WAIT_POLICY=active "$SVPSF" correct --field b.npy --pl pl.npy --psf psf.yaml \
            -o "comp" -q --force >/dev/null 2>&1 &
        child=$!
        wait "$child" || true
    done
) &
competitor=$!
sleep 2
series "beside a spinning OpenMP program, svpsf default (passive)" SVPSF_BENCH=1
series "beside a spinning OpenMP program, OMP_WAIT_POLICY=active" OMP_WAIT_POLICY=active
echo
echo "load average (1 min) at the end: $(cut -d' ' -f1 /proc/loadavg); $(nproc) CPUs"
