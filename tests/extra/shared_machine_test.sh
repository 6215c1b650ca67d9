#!/bin/sh
# svpsf on a shared machine (docs/cli.md, "Shared machines"): the OpenMP wait policy the
# program runs with (as libgomp itself reports it, OMP_DISPLAY_ENV=verbose), the FFTW wisdom
# cache (created, used, merged, replaced when corrupt, opted out of) and the planning note.
# Every cache lives in this test's temporary folder (XDG_CACHE_HOME, HOME), never the user's.
# Usage: shared_machine_test.sh SVPSF
set -u
svpsf=$1
dir=$(mktemp -d "${TMPDIR:-/tmp}/svpsf-shared.XXXXXX") || exit 1
trap 'rm -rf "$dir"' EXIT
cd "$dir" || exit 1
failures=0
fail() { echo "FAIL: $*"; failures=$((failures + 1)); }
ok() { echo "ok    $*"; }
# the test decides these itself
unset OMP_WAIT_POLICY GOMP_SPINCOUNT OMP_DISPLAY_ENV SVPSF_OMP_PASSIVE SVPSF_NO_WISDOM_CACHE
export OMP_NUM_THREADS=2
export XDG_CACHE_HOME="$dir/cache"
export HOME="$dir/home"
mkdir -p "$HOME"

# ---- 1. the OpenMP wait policy -----------------------------------------------------------
# libgomp prints its settings at start-up, in the first process and (when svpsf runs itself
# again with OMP_WAIT_POLICY=passive) in the second: the last block is what the run used.
# GOMP_SPINCOUNT tells them apart: 0 for passive, 300000 for libgomp's unset default.
spin_counts() { # prints the GOMP_SPINCOUNT of every block in err.$1
    sed -n "s/^ *GOMP_SPINCOUNT = '\([0-9]*\)'.*/\1/p" "err.$1" | tr '\n' ' '
}
OMP_DISPLAY_ENV=verbose "$svpsf" --version >out.policy 2>err.policy
counts=$(spin_counts policy)
last=$(echo "$counts" | awk '{print $NF}')
if [ "$last" = 0 ] && grep -q "OMP_WAIT_POLICY = 'PASSIVE'" err.policy; then
    ok "unset: the program runs with a passive wait policy (spin counts per process: $counts)"
else
    fail "unset: GOMP_SPINCOUNT per process '$counts', expected the last to be 0"
    sed 's/^/  /' err.policy
fi
OMP_WAIT_POLICY=active OMP_DISPLAY_ENV=verbose "$svpsf" --version >out.active 2>err.active
counts=$(spin_counts active)
if [ "$(echo "$counts" | wc -w)" = 1 ] && grep -q "OMP_WAIT_POLICY = 'ACTIVE'" err.active; then
    ok "OMP_WAIT_POLICY=active set by the user: kept, no second start (spin count $counts)"
else
    fail "OMP_WAIT_POLICY=active: spin counts '$counts'"
    sed 's/^/  /' err.active
fi
GOMP_SPINCOUNT=1234 OMP_DISPLAY_ENV=verbose "$svpsf" --version >out.spin 2>err.spin
counts=$(spin_counts spin)
[ "$counts" = "1234 " ] && ok "GOMP_SPINCOUNT=1234 set by the user: kept" ||
    fail "GOMP_SPINCOUNT=1234: spin counts '$counts'"
# the arguments survive the second start, and the summary says who set the policy
awk 'BEGIN { for (y = 0; y < 24; y++) { l = ""; for (x = 0; x < 24; x++)
    l = l sprintf("%s%.6f", x ? " " : "", 50 + 10 * sin(x / 3.0) * cos(y / 4.0)); print l } }' \
    >pl24.txt
printf 'pixel_um: 0.5\npsf: {model: moffat, fwhm_um: 1.0, beta: 2.5}\n' >psf.yaml
if "$svpsf" forward --field pl24.txt --pl pl24.txt --psf psf.yaml -o f24 --fft estimate \
    >out.f24 2>err.f24 && grep -q '"omp_wait_policy": "passive"' f24/summary.json &&
    grep -q '"omp_wait_policy_from": "svpsf"' f24/summary.json; then
    ok "forward after the second start: outputs written, summary.json: passive, set by svpsf"
else
    fail "forward with the passive policy"
    sed 's/^/  /' err.f24
fi
OMP_WAIT_POLICY=active "$svpsf" forward --field pl24.txt --pl pl24.txt --psf psf.yaml -o f24a \
    --fft estimate >/dev/null 2>&1
grep -q '"omp_wait_policy_from": "environment"' f24a/summary.json &&
    ok "summary.json: a policy from the environment is recorded as such" ||
    fail "summary.json of an OMP_WAIT_POLICY=active run: $(grep omp_wait f24a/summary.json)"

# ---- 2. the FFTW wisdom cache --------------------------------------------------------------
# a 256 x 256 map: forward's zero boundary pads it to a 512 x 512 frame, large enough for the
# planning note
awk 'BEGIN { for (y = 0; y < 256; y++) { l = ""; for (x = 0; x < 256; x++)
    l = l sprintf("%s%.5f", x ? " " : "", 100 + 20 * sin(x / 7.0) * cos(y / 9.0)); print l } }' \
    >pl.txt
cache=$XDG_CACHE_HOME/svpsf/wisdom
pl=pl.txt # what fwd corrects; the checks that need no planning note use pl24.txt (quicker)
fwd() { # NAME EXPECTED_EXIT ARGS...: forward of pl.txt into out_NAME, stderr in err.NAME
    fwd_with "" "$@"
}
fwd_with() { # "VAR=VALUE ..." NAME EXPECTED_EXIT ARGS...: fwd in that environment
    assign=$1 name=$2 expect=$3
    shift 3
    # shellcheck disable=SC2086 # the assignments are words
    env $assign "$svpsf" forward --field "$pl" --pl "$pl" --psf psf.yaml -o "out_$name" "$@" \
        >"out.$name" 2>"err.$name"
    code=$?
    [ "$code" = "$expect" ] || { fail "$name: exit $code, expected $expect"; sed 's/^/  /' "err.$name"; }
}
# a. the first run measures its plans, says so, and caches them
fwd first 0
if grep -q "planning FFTs for 512 x 512 (first run of this size on this machine; cached afterwards in $cache)" err.first &&
    grep -q " fftw_wisdom" "$cache"; then
    ok "first run: planning note, wisdom cached in \$XDG_CACHE_HOME/svpsf/wisdom"
else
    fail "first run: note or cache missing"
    sed 's/^/  /' err.first
fi
grep -q "\"fft_wisdom\": \"$cache\"" out_first/summary.json &&
    ok "summary.json names the cache" || fail "summary.json lacks the cache: $(grep fft_wisdom out_first/summary.json)"
[ "$(stat -c %a "$XDG_CACHE_HOME/svpsf")" = 700 ] && ok "the cache folder is private (0700)" ||
    fail "cache folder mode $(stat -c %a "$XDG_CACHE_HOME/svpsf")"
# b. the second run finds every plan in the cache: nothing to measure, no note, file unchanged
cp "$cache" cache.before
fwd second 0
if grep -q "planning" err.second; then
    fail "second run measured again: $(cat err.second)"
else
    ok "second run: plans from the cache (no planning note)"
fi
cmp -s "$cache" cache.before && ok "second run: cache left as it was (nothing new to save)" ||
    fail "second run rewrote the cache"
# c. --quiet: no note, the plans still cached (a new size: a 300 x 300 map)
awk 'BEGIN { for (y = 0; y < 300; y++) { l = ""; for (x = 0; x < 300; x++)
    l = l sprintf("%s%.4f", x ? " " : "", 100 + 20 * sin(x / 5.0) * cos(y / 8.0)); print l } }' \
    >pl300.txt
"$svpsf" forward --field pl300.txt --pl pl300.txt --psf psf.yaml -o out_q300 -q >out.q300 2>err.q300 ||
    fail "--quiet run failed"
[ -s err.q300 ] && fail "--quiet printed: $(cat err.q300)" || ok "--quiet: no note"
cmp -s "$cache" cache.before && fail "--quiet: the new size was not cached" ||
    ok "--quiet: the new size merged into the cache"
"$svpsf" forward --field pl300.txt --pl pl300.txt --psf psf.yaml -o out_q300b >/dev/null 2>err.q300b
fwd after_q 0
if grep -q planning err.q300b err.after_q; then
    fail "after the merge a size was measured again: $(cat err.q300b err.after_q)"
else
    ok "both sizes in the cache after the merge"
fi
pl=pl24.txt
# d. a corrupt cache: a warning, the run goes on, the cache is replaced by a valid one
printf '(fftw-3.3.10 fftw_wisdom #x12 garbage' >"$cache"
fwd corrupt 0
grep -q "warning: ignoring the FFTW wisdom cache: $cache: not an FFTW wisdom file" err.corrupt &&
    ok "corrupt cache: warned, not fatal" || { fail "corrupt cache message"; sed 's/^/  /' err.corrupt; }
fwd repaired 0
if grep -q " fftw_wisdom" "$cache" && ! grep -q "warning" err.repaired; then
    ok "corrupt cache replaced after the run; the next run uses it"
else
    fail "the cache was not replaced: $(head -c 100 "$cache"); $(cat err.repaired)"
fi
# e. opting out: --no-wisdom-cache and SVPSF_NO_WISDOM_CACHE (a fresh cache folder each)
pl=pl.txt
fwd_with "XDG_CACHE_HOME=$dir/c_opt" optout 0 --no-wisdom-cache
pl=pl24.txt
if [ ! -e "$dir/c_opt" ] && grep -q "not cached: measured again next run" err.optout; then
    ok "--no-wisdom-cache: no cache read or written"
else
    fail "--no-wisdom-cache: $(ls -R "$dir/c_opt" 2>&1); $(cat err.optout)"
fi
fwd_with "XDG_CACHE_HOME=$dir/c_env SVPSF_NO_WISDOM_CACHE=1" optenv 0
[ ! -e "$dir/c_env" ] && ok "SVPSF_NO_WISDOM_CACHE=1: no cache" || fail "SVPSF_NO_WISDOM_CACHE=1 made $dir/c_env"
fwd_with "XDG_CACHE_HOME=$dir/c_est" estimate 0 --fft estimate
[ ! -e "$dir/c_est" ] && ok "--fft estimate: no cache (nothing measured)" || fail "--fft estimate made a cache"
pl=pl.txt
fwd_with "XDG_CACHE_HOME=$dir/c_wis" wisdom 0 --wisdom own.wisdom
pl=pl24.txt
[ ! -e "$dir/c_wis" ] && grep -q " fftw_wisdom" own.wisdom && grep -q "kept in own.wisdom" err.wisdom &&
    ok "--wisdom FILE: that file instead of the cache" || fail "--wisdom FILE and the cache: $(cat err.wisdom)"
# f. where the cache lives without XDG_CACHE_HOME, or with a relative one: ~/.cache/svpsf
fwd_with "-u XDG_CACHE_HOME" home 0
[ -s "$HOME/.cache/svpsf/wisdom" ] && ok "no XDG_CACHE_HOME: ~/.cache/svpsf/wisdom" ||
    fail "no XDG_CACHE_HOME: $HOME/.cache/svpsf/wisdom missing"
rm -rf "$HOME/.cache"
fwd_with "XDG_CACHE_HOME=relative/cache" relative 0
[ -s "$HOME/.cache/svpsf/wisdom" ] && [ ! -e relative ] &&
    ok "a relative XDG_CACHE_HOME is ignored (the specification's rule)" || fail "relative XDG_CACHE_HOME"
# g. a cache folder that cannot be made: a note, the run goes on
: >not_a_folder
fwd_with "XDG_CACHE_HOME=$dir/not_a_folder" nodir 0
grep -q "no FFTW wisdom cache: cannot create $dir/not_a_folder/svpsf" err.nodir &&
    ok "cache folder impossible: a note, exit 0" || { fail "cache folder impossible"; sed 's/^/  /' err.nodir; }
# h. concurrent runs on one fresh cache: all succeed, the cache stays valid, no temporary file
# is left behind, and the next run finds no corrupt file
export XDG_CACHE_HOME="$dir/c_conc"
i=0
awk 'BEGIN { for (y = 0; y < 40; y++) { l = ""; for (x = 0; x < 40; x++)
    l = l sprintf("%s%.4f", x ? " " : "", 9 + sin(x / 2.0) * cos(y / 3.0)); print l } }' >pl40.txt
for n in 1 2 3 4; do
    f=pl24.txt
    [ "$n" -gt 2 ] && f=pl40.txt
    "$svpsf" forward --field $f --pl $f --psf psf.yaml -o "out_conc$n" --threads 1 \
        >"out.conc$n" 2>"err.conc$n" &
done
"$svpsf" forward --field pl300.txt --pl pl300.txt --psf psf.yaml -o out_conc5 --threads 1 \
    --fft estimate >out.conc5 2>err.conc5 &
wait
for n in 1 2 3 4 5; do [ -s "out_conc$n/summary.json" ] || i=$((i + 1)); done
left=$(ls "$XDG_CACHE_HOME/svpsf" | grep -v '^wisdom$' | tr '\n' ' ')
fwd conc_after 0 --threads 1
if [ "$i" = 0 ] && [ -z "$left" ] && ! grep -q warning err.conc_after; then
    ok "5 concurrent runs on one cache: all done, the cache valid, no temporary file left"
else
    fail "concurrent runs: $i failed, left in the cache folder: '$left'; $(cat err.conc_after)"
fi

if [ "$failures" -ne 0 ]; then
    echo "$failures check(s) failed"
    exit 1
fi
echo "shared machine: all checks passed"
