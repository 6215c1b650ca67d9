#!/bin/bash
# End-to-end tests of the svpsf program: runs the real binary in a temporary folder on inputs
# it writes itself (printf/awk text matrices, or files made by svpsf), compares numbers with
# awk (no Python), and checks every bad input exits exactly 1 with a message that names the
# file and the fault.
#   usage: cli_test.sh /path/to/svpsf
# Prints one line per check and a final "N passed, M failed"; exits nonzero on any failure.
set -u

SVPSF=${1:?usage: cli_test.sh /path/to/svpsf}
case $SVPSF in /*) ;; *) SVPSF=$PWD/$SVPSF ;; esac
WORK=$(mktemp -d "${TMPDIR:-/tmp}/svpsf-cli.XXXXXX")
trap 'rm -rf "$WORK"' EXIT
cd "$WORK" || exit 1
# One thread: the test machine is shared, and the results must not depend on it anyway.
export OMP_NUM_THREADS=1
FAST="--fft estimate"

n_pass=0
n_fail=0
pass() { n_pass=$((n_pass + 1)); echo "ok    $1"; }
fail() { n_fail=$((n_fail + 1)); echo "FAIL  $1: $2"; }

# run NAME CMD...: runs svpsf with CMD, keeping stdout/stderr in out.NAME / err.NAME
run() {
    local name=$1
    shift
    "$SVPSF" "$@" >"out.$name" 2>"err.$name"
    echo $? >"rc.$name"
}

# expect_ok NAME CMD...: exit 0
expect_ok() {
    local name=$1
    shift
    run "$name" "$@"
    local rc
    rc=$(cat "rc.$name")
    if [ "$rc" = 0 ]; then pass "$name"; else fail "$name" "exit $rc: $(head -c 400 "err.$name")"; fi
}

# expect_bad NAME "TEXT1|TEXT2|..." CMD...: exit exactly 1, one message line on stderr starting
# with "svpsf", containing every TEXT (fixed strings)
expect_bad() {
    local name=$1 texts=$2
    shift 2
    run "$name" "$@"
    local rc msg
    rc=$(cat "rc.$name")
    msg=$(cat "err.$name")
    if [ "$rc" != 1 ]; then
        fail "$name" "exit $rc (expected 1): $msg"
        return
    fi
    case $msg in svpsf*) ;; *) fail "$name" "message does not start with 'svpsf': $msg"; return ;; esac
    local IFS='|'
    for t in $texts; do
        if ! grep -qiF -- "$t" "err.$name"; then
            fail "$name" "message lacks '$t': $msg"
            return
        fi
    done
    pass "$name ($msg)"
}

# maxdiff A B: "max|A-B| max|A|" over two numpy.savetxt matrices of the same shape
maxdiff() {
    awk 'NR == FNR { for (i = 1; i <= NF; i++) a[FNR, i] = $i; rows = FNR; cols = NF; next }
         { if (NF != cols) bad = 1
           for (i = 1; i <= NF; i++) {
               d = $i - a[FNR, i]; if (d < 0) d = -d; if (d > m) m = d
               v = a[FNR, i]; if (v < 0) v = -v; if (v > peak) peak = v } }
         END { if (bad || FNR != rows) print "shape-mismatch 1"; else printf "%.6g %.6g\n", m, peak }' "$1" "$2"
}

# check_close NAME A B REL: max|A-B| <= REL * max|A|
check_close() {
    local name=$1 a=$2 b=$3 rel=$4 r
    if [ ! -f "$a" ] || [ ! -f "$b" ]; then fail "$name" "missing $a or $b"; return; fi
    r=$(maxdiff "$a" "$b")
    if awk -v r="$r" -v rel="$rel" 'BEGIN { split(r, x, " "); exit !(x[1] != "shape-mismatch" && x[1] <= rel * x[2]) }'; then
        pass "$name (max error $(echo "$r" | cut -d' ' -f1) of peak $(echo "$r" | cut -d' ' -f2), bound $rel x peak)"
    else
        fail "$name" "max error / peak = $r exceeds $rel"
    fi
}

# ---- inputs written by awk/printf -------------------------------------------------------------
# 32 x 32: a signed field (two Gaussian bumps) and a smooth PL that never reaches 0
awk 'BEGIN { n = 32; for (y = 0; y < n; y++) { l = ""; for (x = 0; x < n; x++) {
    v = 10 * exp(-((x - 12) ^ 2 + (y - 14) ^ 2) / 50) - 6 * exp(-((x - 22) ^ 2 + (y - 18) ^ 2) / 30)
    l = l (x ? " " : "") sprintf("%.17g", v) }; print l } }' >Bz.txt
awk 'BEGIN { n = 32; for (y = 0; y < n; y++) { l = ""; for (x = 0; x < n; x++) {
    v = 3 * sin(x / 5) * cos(y / 7)
    l = l (x ? " " : "") sprintf("%.17g", v) }; print l } }' >Bx.txt
awk 'BEGIN { n = 32; for (y = 0; y < n; y++) { l = ""; for (x = 0; x < n; x++) {
    v = 0.3 + 0.7 * exp(-((x - 15.5) ^ 2 + (y - 15.5) ^ 2) / 300)
    l = l (x ? " " : "") sprintf("%.17g", v) }; print l } }' >pl.txt
awk 'BEGIN { for (y = 0; y < 33; y++) { l = ""; for (x = 0; x < 32; x++) l = l (x ? " " : "") 1; print l } }' >pl33.txt
printf '0 0 0\n0 1 0\n0 0 0\n' >delta.txt
printf 'pixel_um: 0.5\npsf: {model: moffat, fwhm_um: 1.0, beta: 2.5}\n' >moffat.yaml
printf 'pixel_um: 0.5\npsf: {model: moffat, fwhm_um: 1.0, beta: 2.5}\nboundary: periodic\n' >moffat_periodic.yaml
printf 'pixel_um: 1\npsf: {model: gaussian, fwhm_um: -2}\n' >neg_fwhm.yaml
printf 'pixel_um: 1\npsf: {model: gaussian, fwhm_um: 0}\n' >zero_fwhm.yaml
printf 'pixel_um: 1\npsf: {model: moffat, fwhm_um: 2, beta: 0}\n' >beta0.yaml
printf 'pixel_um: 1\npsf: {model: moffat, fwhm_um: 2, beta: -1.5}\n' >beta_neg.yaml
printf 'pixel_um: 1\npsf:\n  model: gaussian\n  fwhm_um: 2\n  fwhm_umm: 3\n' >typo.yaml

# ---- --version, --help ------------------------------------------------------------------------
run version --version
if [ "$(cat rc.version)" = 0 ] && grep -qE '^svpsf [0-9]+\.[0-9]+' out.version &&
    grep -qE '^FFTW .*[0-9]' out.version && grep -qE '^OpenCV [0-9]' out.version &&
    grep -qE '^libyaml [0-9]' out.version; then
    pass "--version prints svpsf, FFTW, OpenCV, libyaml: $(tr '\n' ';' <out.version)"
else
    fail "--version" "$(cat out.version err.version)"
fi
run help --help
if [ "$(cat rc.help)" = 0 ] && grep -q forward out.help && grep -q correct out.help &&
    grep -q deconvolve out.help && grep -q demo out.help; then
    pass "--help lists the commands"
else
    fail "--help" "$(cat out.help err.help)"
fi
# every command's help exits 0 and describes every option it accepts, with defaults
check_help() {
    local cmd=$1
    shift
    run "help_$cmd" "$cmd" --help
    if [ "$(cat "rc.help_$cmd")" != 0 ]; then fail "$cmd --help" "exit $(cat "rc.help_$cmd")"; return; fi
    for opt in "$@"; do
        if ! grep -qF -- "$opt" "out.help_$cmd"; then fail "$cmd --help" "does not describe $opt"; return; fi
    done
    if ! grep -q default "out.help_$cmd"; then fail "$cmd --help" "states no defaults"; return; fi
    pass "$cmd --help (exit 0, describes $*)"
}
check_help forward --field --pl --psf --output --boundary --format --force --threads --fft --wisdom --quiet
check_help correct --field --pl --psf --output --method --iterations --precision --balance --noise --cg-max-steps --pl-floor --shift --boundary --format --force --threads --quiet
check_help deconvolve --psf --output --method --balance --iterations --precision --cg-max-steps --boundary --compat --format --force --quiet
check_help psf --output --size --force --quiet
check_help demo --output --format --force --threads --quiet
run help_word help correct
if [ "$(cat rc.help_word)" = 0 ] && cmp -s out.help_word out.help_correct; then
    pass "svpsf help correct = svpsf correct --help"
else
    fail "svpsf help correct" "differs from correct --help"
fi

# ---- demo -------------------------------------------------------------------------------------
expect_ok demo demo -o demo
missing=""
for f in field_true pl_true field_apparent pl_apparent field_corrected pl_corrected validity; do
    [ -s "demo/$f.tif" ] || missing="$missing $f.tif"
done
for f in psf.yaml summary.json field_corrected.png; do [ -s "demo/$f" ] || missing="$missing $f"; done
if [ -z "$missing" ]; then pass "demo writes its maps, psf.yaml, figures, summary.json"; else fail "demo files" "missing:$missing"; fi
# the corrected error in the lit regions is smaller than the apparent one
errs=$(awk '/apparent  \(T\)/ { a = $4 } /corrected \(T\^-1\)/ { c = $4 } END { print a, c }' out.demo)
if awk -v e="$errs" 'BEGIN { split(e, x, " "); exit !(x[1] > 0 && x[2] > 0 && x[2] < x[1]) }'; then
    pass "demo: max error in lit regions apparent $(echo "$errs" | cut -d' ' -f1) uT > corrected $(echo "$errs" | cut -d' ' -f2) uT"
else
    fail "demo errors" "apparent/corrected = '$errs': $(cat out.demo)"
fi
# the demo corrects as `svpsf correct` does with its defaults (R, margin auto): the same bits
expect_ok demo_npy demo -o demo_npy --format npy
expect_ok demo_correct correct --field demo_npy/field_apparent.npy --pl demo_npy/pl_apparent.npy \
    --psf demo_npy/psf.yaml --format npy --fft estimate -o demo_c
if cmp -s demo_npy/field_corrected.npy demo_c/field.npy && cmp -s demo_npy/validity.npy demo_c/validity.npy; then
    pass "demo: its correction is svpsf correct's with the defaults, bit for bit"
else
    fail "demo vs correct" "demo_npy/field_corrected.npy differs from demo_c/field.npy"
fi
sum_before=$(cat demo/*.tif demo/summary.json | cksum)
expect_bad demo_exists "demo/|exists|--force" demo -o demo
if [ "$(cat demo/*.tif demo/summary.json | cksum)" = "$sum_before" ]; then
    pass "demo without --force leaves the old outputs unchanged"
else
    fail "demo without --force" "old outputs changed"
fi
# the demo's PSF file is a valid PSF file
expect_ok psf_demo psf demo/psf.yaml -o demo_kernel.tif
if grep -q "1 um = 10 px" out.psf_demo && grep -qi lorentzian out.psf_demo &&
    grep -q "50 %" out.psf_demo && grep -q "95 %" out.psf_demo; then
    pass "psf prints the demo PSF's FWHM (1 um = 10 px), model and encircled-energy radii"
else
    fail "psf output" "$(cat out.psf_demo)"
fi

# ---- forward: identity for a delta kernel -----------------------------------------------------
expect_ok fwd_delta forward --field Bz.txt --pl pl.txt --psf delta.txt -o fwd_delta --format txt $FAST
check_close "delta PSF: apparent field = true field" Bz.txt fwd_delta/field.txt 1e-12
check_close "delta PSF: apparent PL = true PL" pl.txt fwd_delta/pl.txt 1e-12

# ---- forward then correct reproduce the inputs ------------------------------------------------
expect_ok fwd_periodic forward --field Bz.txt --pl pl.txt --psf moffat_periodic.yaml -o fwd_p --format npy $FAST
expect_ok corr_w correct --field fwd_p/field.npy --pl fwd_p/pl.npy --psf moffat_periodic.yaml \
    --method w --balance 1e-10 -o corr_w --format txt $FAST
check_close "T^-1(T(B)), W balance 1e-10, periodic: field" Bz.txt corr_w/field.txt 1e-4
check_close "T^-1(T(B)), W balance 1e-10, periodic: PL" pl.txt corr_w/pl.txt 1e-4
expect_ok fwd_mirror forward --field Bz.txt --pl pl.txt --psf moffat.yaml --boundary mirror -o fwd_m --format npy $FAST
expect_ok corr_rw correct --field fwd_m/field.npy --pl fwd_m/pl.npy --psf moffat.yaml --boundary mirror \
    --method rw --iterations 500 --balance 1e-8 -o corr_rw --format txt $FAST
check_close "T^-1(T(B)), R&W 500 iterations, mirror: field" Bz.txt corr_rw/field.txt 1e-3
expect_ok fwd_zero forward --field Bz.txt --pl pl.txt --psf moffat.yaml -o fwd_z --format tif $FAST
expect_ok corr_r correct --field fwd_z/field.tif --pl fwd_z/pl.tif --psf moffat.yaml \
    --method rl-signed --iterations 500 --margin 0 --precision double -o corr_r --format txt $FAST
# float32 TIFF inputs: 1e-7 relative rounding before the deconvolution
check_close "T^-1(T(B)), signed RL 500 iterations, zero boundary, float32 TIFF: field" Bz.txt corr_r/field.txt 5e-3
expect_ok corr_r32 correct --field fwd_z/field.tif --pl fwd_z/pl.tif --psf moffat.yaml \
    --method rl-signed --iterations 500 --precision single --margin 0 -o corr_r32 --format txt $FAST
check_close "correct --precision single (500 iterations) agrees with double" corr_r/field.txt corr_r32/field.txt 1e-3
# the default precision: double below 1024² pixels (the same numbers as --precision double),
# single from 1024² for r and rl-signed with one PSF, double for rw
expect_ok corr_rdef correct --field fwd_z/field.tif --pl fwd_z/pl.tif --psf moffat.yaml \
    --method rl-signed --iterations 500 --margin 0 -o corr_rdef --format txt $FAST
cmp -s corr_rdef/field.txt corr_r/field.txt && grep -q '"precision": "double"' corr_rdef/summary.json &&
    pass "correct rl-signed at 32² defaults to --precision double" ||
    fail "default precision of rl-signed at 32²" "$(grep precision corr_rdef/summary.json)"
grep -q '"precision": "double"' corr_rw/summary.json && pass "correct rw defaults to double" ||
    fail "default precision of rw" "$(grep precision corr_rw/summary.json)"
awk 'BEGIN { for (y = 0; y < 1024; y++) { l = ""; for (x = 0; x < 1024; x++)
    l = l (x ? " " : "") (1 + ((x + y) % 7)); print l } }' >pl1024.txt
awk 'BEGIN { for (y = 0; y < 1024; y++) { l = ""; for (x = 0; x < 1024; x++)
    l = l (x ? " " : "") ((x % 5) - 2); print l } }' >b1024.txt
printf 'pixel_um: 0.5\npsf: {model: moffat, fwhm_um: 1.0, beta: 2.5, support_um: 2}\n' >moffat_s.yaml
for m in r rw; do
    expect_ok corr_1024$m correct --field b1024.txt --pl pl1024.txt --psf moffat_s.yaml --method $m \
        --iterations 2 --margin 0 -o corr_1024$m --format npy $FAST
done
grep -q '"precision": "single"' corr_1024r/summary.json &&
    grep -q '"precision": "double"' corr_1024rw/summary.json &&
    pass "correct at 1024²: r defaults to single precision, rw to double" ||
    fail "default precision at 1024²" "$(grep -h precision corr_1024r*/summary.json)"
# the deconvolutions side by side (docs/model.md §3, one worker per thread, one FFT thread each):
# 1 and 2 threads give the same maps bit for bit, with two field maps (three runs, two workers)
for t in 1 2; do
    expect_ok corr_side$t correct --field b1024.txt --field pl1024.txt --pl pl1024.txt \
        --psf moffat_s.yaml --iterations 2 --margin 0 -o corr_side$t --format npy --threads $t $FAST
done
if cmp -s corr_side1/pl.npy corr_side2/pl.npy && cmp -s corr_side1/field_b1024.npy corr_side2/field_b1024.npy &&
    cmp -s corr_side1/field_pl1024.npy corr_side2/field_pl1024.npy; then
    pass "correct at 1024² with two fields: 2 threads (side by side) = 1 thread, bit for bit"
else
    fail "side by side" "$(ls corr_side1 corr_side2 | tr '\n' ' ')"
fi
# and the summary says how they ran: 2 workers with 2 threads, in order (1) with one
grep -q '"side_by_side": 2' corr_side2/summary.json && grep -q '"side_by_side": 1' corr_side1/summary.json &&
    ! grep -q side_by_side_fallback corr_side2/summary.json &&
    pass "correct: summary.json records side by side (2 workers) and in order (1)" ||
    fail "side_by_side in summary.json" "$(grep -h side_by_side corr_side1/summary.json corr_side2/summary.json)"
# --side-by-side off: in order with 2 threads (one operator's memory), recorded both ways
expect_ok corr_side_off correct --field b1024.txt --pl pl1024.txt --psf moffat_s.yaml --iterations 2 \
    --margin 0 -o corr_side_off --format npy --threads 2 --side-by-side off $FAST
grep -q '"side_by_side": 1' corr_side_off/summary.json && grep -q '"side_by_side": "off"' corr_side_off/summary.json &&
    pass "correct --side-by-side off: the runs in order with 2 threads, in summary.json" ||
    fail "--side-by-side off" "$(grep -h side_by_side corr_side_off/summary.json)"
expect_bad corr_side_bad "--side-by-side" correct --field b1024.txt --pl pl1024.txt --psf moffat_s.yaml \
    -o corr_side_bad --side-by-side maybe $FAST
expect_bad corr_w32 "--precision single|--method w" correct --field fwd_p/field.npy --pl fwd_p/pl.npy \
    --psf moffat_periodic.yaml --method w --precision single -o corr_w32
if grep -q "corrected with" out.corr_r && grep -q "flagged" out.corr_r && grep -q "missing" out.corr_r; then
    pass "correct prints its result paragraph (missing, flagged, time)"
else
    fail "correct paragraph" "$(cat out.corr_r)"
fi

# ---- several field components share the PL -----------------------------------------------------
expect_ok fwd_two forward --field Bz.txt --field Bx.txt --pl pl.txt --psf moffat_periodic.yaml -o fwd_two --format txt $FAST
expect_ok fwd_x forward --field Bx.txt --pl pl.txt --psf moffat_periodic.yaml -o fwd_x --format txt $FAST
expect_ok fwd_zp forward --field Bz.txt --pl pl.txt --psf moffat_periodic.yaml -o fwd_zp --format txt $FAST
if [ -f fwd_two/field_Bz.txt ] && [ -f fwd_two/field_Bx.txt ] && [ ! -e fwd_two/field.txt ]; then
    pass "two --field inputs give field_Bz and field_Bx"
else
    fail "two fields" "$(ls fwd_two)"
fi
check_close "field_Bx of a two-field run = the one-field run" fwd_x/field.txt fwd_two/field_Bx.txt 1e-12
check_close "field_Bz of a two-field run = the one-field run" fwd_zp/field.txt fwd_two/field_Bz.txt 1e-12
expect_bad same_stem "Bz.txt|same name" forward --field Bz.txt --field ./Bz.txt --pl pl.txt --psf moffat.yaml -o same_stem $FAST

# ---- a kernel image made by `svpsf psf` acts as the YAML model ---------------------------------
# 32 x 32 with the whole field of view as support: the model's kernel is 63 x 63
expect_ok psf_k63 psf moffat.yaml --size 63 -o k63.txt
expect_ok fwd_kernel forward --field Bz.txt --pl pl.txt --psf k63.txt -o fwd_k --format txt $FAST
expect_ok fwd_model forward --field Bz.txt --pl pl.txt --psf moffat.yaml -o fwd_model --format txt $FAST
check_close "kernel image from svpsf psf = YAML model (forward field)" fwd_model/field.txt fwd_k/field.txt 1e-10

# ---- 1 and 2 threads agree ----------------------------------------------------------------------
expect_ok fwd_t2 forward --field Bz.txt --pl pl.txt --psf moffat.yaml -o fwd_t2 --format txt --threads 2 $FAST
check_close "forward with 2 threads = 1 thread" fwd_model/field.txt fwd_t2/field.txt 1e-12

# ---- deconvolve -------------------------------------------------------------------------------
expect_ok dec_w deconvolve fwd_p/pl.npy --psf moffat_periodic.yaml -o dec/pl_w.txt --method wiener --balance 1e-10 $FAST
check_close "deconvolve wiener recovers the PL" pl.txt dec/pl_w.txt 1e-4
[ -s dec/pl_w.summary.json ] && pass "deconvolve writes OUT_STEM.summary.json" || fail "deconvolve summary" "$(ls dec)"
expect_ok dec_rl deconvolve fwd_m/pl.npy --psf moffat.yaml --boundary mirror -o dec/pl_rl.txt --method rl --iterations 300 $FAST
check_close "deconvolve rl (300 iterations, mirror) recovers the PL" pl.txt dec/pl_rl.txt 1e-2
# single precision: the same 300 iterations with float transforms, within float round-off
expect_ok dec_rl32 deconvolve fwd_m/pl.npy --psf moffat.yaml --boundary mirror -o dec/pl_rl32.txt --method rl --iterations 300 --precision single $FAST
check_close "deconvolve rl --precision single agrees with double" dec/pl_rl.txt dec/pl_rl32.txt 2e-4
grep -q '"precision": "single"' dec/pl_rl32.summary.json && pass "summary.json records the precision" ||
    fail "precision in summary" "$(grep precision dec/pl_rl32.summary.json)"
expect_bad dec_w32 "--precision single|--method rl" deconvolve fwd_p/pl.npy --psf moffat.yaml -o dec/w32.txt --method wiener --precision single
expect_bad dec_prec_bad "--precision|half" deconvolve fwd_p/pl.npy --psf moffat.yaml -o dec/h.txt --method rl --precision half
expect_ok psf_k19 psf moffat.yaml -o k19.txt
expect_ok dec_sk deconvolve fwd_zp/field.txt --psf k19.txt -o dec/sk.txt --method wiener --compat skimage --balance 0.1
if awk '{ for (i = 1; i <= NF; i++) if ($i < -1 || $i > 1) bad = 1 } END { exit bad }' dec/sk.txt; then
    pass "deconvolve --compat skimage clips to [-1, 1] as scikit-image does"
else
    fail "skimage clip" "values outside [-1, 1]"
fi
expect_bad dec_sk_large "k63.txt|larger" deconvolve fwd_zp/field.txt --psf k63.txt -o dec/sk2.txt --method rl --compat skimage
expect_bad dec_no_method "--method" deconvolve fwd_p/pl.npy --psf moffat.yaml -o dec/x.txt
# --balance auto: the discrepancy principle picks lambda (its accuracy: test_restore's
# test_balance_discrepancy); here the plumbing: it runs, reports lambda and sigma, refuses misuse
expect_ok dec_auto deconvolve fwd_z/pl.tif --psf moffat.yaml -o dec/pl_auto.txt --method wiener --balance auto --noise 0.001 $FAST
grep -q "discrepancy" out.dec_auto && grep -q '"noise_sigma"' dec/pl_auto.summary.json &&
    pass "deconvolve --balance auto reports the chosen balance and sigma" ||
    fail "balance auto" "$(cat out.dec_auto)"
expect_bad dec_auto_rl "--balance auto|wiener" deconvolve fwd_p/pl.npy --psf moffat.yaml -o dec/y.txt --method rl --balance auto
expect_bad dec_noise_alone "--noise|auto" deconvolve fwd_p/pl.npy --psf moffat.yaml -o dec/y.txt --method wiener --noise 0.1

# ---- missing data ------------------------------------------------------------------------------
awk 'NR == 10 { $7 = "nan"; $8 = "nan" } { print }' fwd_z/../fwd_zp/field.txt >field_nan.txt
expect_ok corr_nan correct --field field_nan.txt --pl fwd_zp/pl.txt --psf moffat_periodic.yaml -o corr_nan --format txt $FAST
if grep -q '"n_missing": 2' corr_nan/summary.json && ! grep -qiE 'nan|inf' corr_nan/field.txt corr_nan/validity.txt corr_nan/pl.txt; then
    pass "NaN input pixels: n_missing = 2 in summary.json, no NaN/Inf in the outputs"
else
    fail "missing data" "$(grep n_missing corr_nan/summary.json) $(grep -ciE 'nan|inf' corr_nan/field.txt)"
fi
# a margin wider than the view is refused before its operator is built (it would take hours)
expect_bad corr_margin_wide "margin of 5000 pixels|wider than the view's larger side (32 pixels)|pl.txt" correct \
    --field fwd_zp/field.txt --pl fwd_zp/pl.txt --psf moffat.yaml --margin 5000 -o corr_wide \
    --format txt $FAST
# nothing measured: the input without a finite pixel is named by its file; two maps missing
# complementary rows have no pixel in common
awk '{ for (i = 1; i <= NF; i++) $i = "nan"; print }' fwd_zp/pl.txt >pl_allnan.txt
awk '{ for (i = 1; i <= NF; i++) $i = "inf"; print }' fwd_zp/field.txt >field_allinf.txt
awk 'NR % 2 { for (i = 1; i <= NF; i++) $i = "nan" } { print }' fwd_zp/pl.txt >pl_odd_nan.txt
awk 'NR % 2 == 0 { for (i = 1; i <= NF; i++) $i = "nan" } { print }' fwd_zp/field.txt >field_even_nan.txt
expect_bad corr_pl_allnan "every pixel of pl_allnan.txt is NaN or Inf" correct --field fwd_zp/field.txt \
    --pl pl_allnan.txt --psf moffat_periodic.yaml -o corr_allnan --format txt $FAST
expect_bad corr_field_allinf "field_allinf.txt is NaN or Inf" correct --field field_allinf.txt \
    --pl fwd_zp/pl.txt --psf moffat_periodic.yaml -o corr_allnan --format txt $FAST
expect_bad corr_disjoint "no pixel is measured in pl_odd_nan.txt and every field map" correct \
    --field field_even_nan.txt --pl pl_odd_nan.txt --psf moffat_periodic.yaml -o corr_allnan \
    --format txt $FAST

# ---- summary.json -----------------------------------------------------------------------------
s=corr_w/summary.json
ok=1
for key in '"command": "correct"' '"command_line"' '"inputs"' '"width": 32' '"bytes"' '"settings"' \
    '"method": "w"' '"versions"' '"fftw"' '"opencv"' '"libyaml"' '"timings_s"' '"transform"' \
    '"total"' '"peak_memory_bytes"' '"n_missing"' '"flagged_fraction"'; do
    grep -qF -- "$key" "$s" || { ok=0; fail "summary.json" "lacks $key"; break; }
done
[ $ok = 1 ] && pass "summary.json has command line, inputs with sizes, settings, versions, timings, peak memory, n_missing"

# ---- wisdom -----------------------------------------------------------------------------------
expect_ok wisdom forward --field Bz.txt --pl pl.txt --psf moffat.yaml -o fwd_wis --wisdom wisdom.dat --fft measure
[ -s wisdom.dat ] && pass "--wisdom saves FFTW wisdom" || fail "--wisdom" "wisdom.dat not written"
expect_ok wisdom2 forward --field Bz.txt --pl pl.txt --psf moffat.yaml -o fwd_wis2 --wisdom wisdom.dat --fft measure
# both precisions in one wisdom file: the float plans of --precision single are kept too, and
# the file loads again (also into a double-only run)
expect_ok wisdom32 deconvolve fwd_m/pl.npy --psf moffat.yaml -o dec/w32a.txt --method rl --iterations 3 \
    --precision single --wisdom wisdom2.dat --fft measure
grep -q " fftw_wisdom" wisdom2.dat && grep -q " fftwf_wisdom" wisdom2.dat &&
    pass "--wisdom keeps double and single-precision wisdom" || fail "--wisdom single" "$(head -c 200 wisdom2.dat)"
expect_ok wisdom32b deconvolve fwd_m/pl.npy --psf moffat.yaml -o dec/w32b.txt --method rl --iterations 3 \
    --precision single --wisdom wisdom2.dat --fft measure
expect_ok wisdom32c forward --field Bz.txt --pl pl.txt --psf moffat.yaml -o fwd_wis4 --wisdom wisdom2.dat --fft measure
# a wisdom file that could not be saved is refused before any work: no output, no folder
expect_bad wisdom_no_dir "--wisdom|nodir/w.dat|nodir|does not exist" forward --field Bz.txt --pl pl.txt \
    --psf moffat.yaml -o fwd_wis3 --wisdom nodir/w.dat $FAST
[ -e fwd_wis3 ] && fail "--wisdom in a missing folder" "fwd_wis3 was written" ||
    pass "--wisdom in a missing folder: refused up front, nothing written"
expect_bad wisdom_folder "--wisdom|fwd_wis|folder" forward --field Bz.txt --pl pl.txt \
    --psf moffat.yaml -o fwd_wis3 --wisdom fwd_wis $FAST

# ---- bad input: exit 1, the message names the file and the fault --------------------------------
expect_bad missing_file "nope.npy|no such file" forward --field nope.npy --pl pl.txt --psf moffat.yaml -o bad $FAST
head -c 1000 fwd_p/field.npy >trunc.npy
expect_bad truncated_npy "trunc.npy|truncated" correct --field trunc.npy --pl fwd_p/pl.npy --psf moffat.yaml -o bad $FAST
head -c 2000 demo/pl_true.tif >trunc.tif
expect_bad truncated_tiff "trunc.tif|TIFF" correct --field fwd_z/field.tif --pl trunc.tif --psf moffat.yaml -o bad $FAST
printf 'not a numpy file at all, just text\n' >garbage.npy
expect_bad garbage_npy "garbage.npy" correct --field garbage.npy --pl fwd_p/pl.npy --psf moffat.yaml -o bad $FAST
printf 'II*\0garbage after a TIFF magic' >garbage.tif
expect_bad garbage_tiff "garbage.tif" forward --field Bz.txt --pl garbage.tif --psf moffat.yaml -o bad $FAST
expect_bad missing_pl "nope_pl.tif|no such file" correct --field Bz.txt --pl nope_pl.tif --psf moffat.yaml -o bad $FAST
# forward's checks of the true maps name the file, not the library's role (pl_true, field_true[0])
awk 'NR == 3 { $2 = -1 } { print }' pl.txt >pl_negative.txt
expect_bad forward_negative_pl "pl_negative.txt: pl_true is negative (-1) at pixel (1, 2)" \
    forward --field Bz.txt --pl pl_negative.txt --psf moffat.yaml -o bad $FAST
awk '{ for (i = 1; i <= NF; i++) $i = 0; print }' pl.txt >pl_zero.txt
expect_bad forward_dark_pl "pl_zero.txt: pl_true holds no light" \
    forward --field Bz.txt --pl pl_zero.txt --psf moffat.yaml -o bad $FAST
# correct names the pixel in the view's coordinates, also with its default margin (auto: the
# deconvolutions run on the view plus that margin)
expect_bad correct_negative_pl "pl_negative.txt|is negative (-1) at pixel (1, 2)" \
    correct --field Bz.txt --pl pl_negative.txt --psf moffat.yaml -o bad $FAST
expect_bad correct_negative_pl_margin "pl_negative.txt|is negative (-1) at pixel (1, 2)" \
    correct --field Bz.txt --pl pl_negative.txt --psf moffat.yaml --margin 7 -o bad $FAST
awk 'NR == 3 { $2 = -1000 } { print }' Bz.txt >Bz_dip.txt
expect_bad correct_shift_pixel "Bz_dip.txt: the shift c = 1 leaves the field + c = -999 <= 0 at pixel (x 1, y 2)" \
    correct --field Bz_dip.txt --pl pl.txt --psf moffat.yaml --method r --shift 1 --margin 7 -o bad $FAST
# a PL without light (an offset above every value) has nothing to restore: exit 1, not a field of
# 0 with validity 0 everywhere
expect_bad correct_no_light "pl.txt holds no light|after the offset is subtracted" \
    correct --field Bz.txt --pl pl.txt --psf moffat.yaml --offset 1e9 -o bad $FAST
awk 'NR == 2 { $5 = "nan" } { print }' Bz.txt >Bz_nan.txt
expect_bad forward_nan_field "Bz_nan.txt: field_true[0] has 1 NaN/Inf pixels" \
    forward --field Bz_nan.txt --pl pl.txt --psf moffat.yaml -o bad $FAST
expect_bad missing_psf "nope.yaml" forward --field Bz.txt --pl pl.txt --psf nope.yaml -o bad $FAST
if [ "$(id -u)" != 0 ]; then # root reads anything: the permission case means nothing there
    cp fwd_p/field.npy unreadable.npy && chmod 000 unreadable.npy
    expect_bad unreadable_npy "unreadable.npy" correct --field unreadable.npy --pl fwd_p/pl.npy --psf moffat.yaml -o bad $FAST
    chmod 600 unreadable.npy
fi
expect_bad size_mismatch "size mismatch|Bz.txt|pl33.txt|32 x 33" forward --field Bz.txt --pl pl33.txt --psf moffat.yaml -o bad $FAST
expect_bad negative_fwhm "neg_fwhm.yaml|fwhm|-2" forward --field Bz.txt --pl pl.txt --psf neg_fwhm.yaml -o bad $FAST
# lengths whose ratio underflows (FWHM 1e-300 um on pixels of 1e300 um): named as such, not
# as "FWHM must be positive, got 0"
printf 'pixel_um: 1e300\npsf: {model: gaussian, fwhm_um: 1e-300}\n' >ratio_fwhm.yaml
expect_bad ratio_fwhm "ratio_fwhm.yaml:2:33|fwhm_um 1e-300 over pixel_um 1e+300 is 0 pixels" \
    psf ratio_fwhm.yaml -o bad.tif
expect_bad zero_fwhm "zero_fwhm.yaml|fwhm" forward --field Bz.txt --pl pl.txt --psf zero_fwhm.yaml -o bad $FAST
expect_bad beta_zero "beta0.yaml|beta" correct --field Bz.txt --pl pl.txt --psf beta0.yaml -o bad $FAST
expect_bad beta_negative "beta_neg.yaml|beta" psf beta_neg.yaml -o bad.tif
expect_bad unknown_yaml_key "typo.yaml:5:3|fwhm_umm" forward --field Bz.txt --pl pl.txt --psf typo.yaml -o bad $FAST
[ -e bad ] && fail "bad inputs" "the output folder 'bad' was created" || pass "no output folder after bad inputs"
# a run that fails after its output folders were made removes the ones it created (still
# empty), deepest first, and never a folder that existed before: here the signed shift is
# refused only once the inputs are read and the outputs planned
mkdir -p kept_empty
expect_bad fail_late_dirs "Bz.txt|shift c = -50|at pixel (x |needs c >" correct --field Bz.txt --pl pl.txt --psf moffat.yaml \
    -o kept_empty/new1/new2 --method r --shift -50 $FAST
if [ -d kept_empty ] && [ -z "$(ls -A kept_empty)" ]; then
    pass "failed run: the folders it created are removed, the empty folder that existed is kept"
else
    fail "failed run folders" "kept_empty: $(ls -AR kept_empty 2>&1)"
fi
expect_bad fail_late_dec "k63.txt|larger" deconvolve fwd_zp/field.txt --psf k63.txt -o nd1/x.tif --method rl --compat skimage
[ -e nd1 ] && fail "failed deconvolve" "left the folder nd1" || pass "failed deconvolve leaves no new folder"
mkdir -p exists
echo "old validity" >exists/validity.txt
expect_bad output_exists "exists/validity.txt|exists|--force" forward --field Bz.txt --pl pl.txt --psf moffat.yaml -o exists --format txt $FAST
if [ "$(cat exists/validity.txt)" = "old validity" ] && [ ! -e exists/pl.txt ] && [ ! -e exists/field.txt ]; then
    pass "output exists: the old file is unchanged and no other output was written"
else
    fail "output exists" "$(ls exists)"
fi
expect_ok output_force forward --field Bz.txt --pl pl.txt --psf moffat.yaml -o exists --format txt --force $FAST
[ "$(cat exists/validity.txt)" != "old validity" ] && pass "--force overwrites" || fail "--force" "not overwritten"
# a run that fails after writing some of its outputs removes them (all or none): a field of
# 1e300 fits a float64 PL output but not the float32 TIFF of field.tif, written after pl.tif
awk '{ for (i = 1; i <= NF; i++) $i = $i * 1e300; print }' Bz.txt >Bz_huge.txt
mkdir -p partial
echo "old pl" >partial/old.txt
expect_bad fail_after_write "partial/field.tif|exceed a float32 TIFF" forward --field Bz_huge.txt --pl pl.txt \
    --psf moffat.yaml -o partial $FAST
if [ "$(ls partial)" = "old.txt" ] && grep -q "removed the 1 output written before the failure" err.fail_after_write; then
    pass "failed run: the output it had written (pl.tif) is removed, the file that was there kept"
else
    fail "failed run partial outputs" "partial holds: $(ls partial); $(cat err.fail_after_write)"
fi
expect_bad unknown_option "--bogus|unknown option" forward --bogus
expect_bad unknown_command "frobnicate|unknown command" frobnicate
expect_bad bad_number "--balance|abc" correct --field Bz.txt --pl pl.txt --psf moffat.yaml -o bad --balance abc
expect_bad bad_method "--method|foo" correct --field Bz.txt --pl pl.txt --psf moffat.yaml -o bad --method foo
expect_bad missing_value "--pl|needs a value" forward --field Bz.txt --pl
expect_bad missing_required "--psf|required" forward --field Bz.txt --pl pl.txt -o bad
expect_bad even_size "--size|odd" psf moffat.yaml -o k.tif --size 4
expect_bad big_size "--size|16387|16385" psf moffat.yaml -o k.tif --size 16387
run help_psf_size psf --help
grep -q -- "--size N .*1\.\.16385" out.help_psf_size && grep -q "default is at most 2049" out.help_psf_size &&
    pass "psf --help states --size 1..16385 and the default's 2049 cap" || fail "psf --help --size" "$(grep -A4 -- --size out.help_psf_size)"
run no_args
[ "$(cat rc.no_args)" = 1 ] && grep -q usage err.no_args && pass "no command: usage on stderr, exit 1" || fail "no command" "exit $(cat rc.no_args)"

# =============================================================================================
# ---- PSF maps (docs/model.md §9): forward / correct with a space-variant PSF-map file --------
# =============================================================================================
# kind uniform = the plain PSF file; a grid whose nodes are all that PSF = the invariant operator
printf 'pixel_um: 0.5\nmodel: moffat\nkind: uniform\npsf: {fwhm_um: 1.0, beta: 2.5}\n' >map_uniform.yaml
{
    printf 'pixel_um: 0.5\nimage: {width: 32, height: 32}\nmodel: moffat\nkind: grid\n'
    printf 'nodes: {nx: 2, ny: 2}\nnode_psfs:\n'
    for i in 1 2 3 4; do printf '  - {fwhm_um: 1.0, beta: 2.5}\n'; done
} >map_same.yaml
# a PSF that really varies: FWHM 1.6 .. 4 px, beta 3 .. 1.2 over the field
{
    printf 'pixel_um: 0.5\nimage: {width: 32, height: 32}\nmodel: moffat\nkind: grid\n'
    printf 'nodes: {nx: 2, ny: 2}\nnode_psfs:\n'
    printf '  - {fwhm_um: 0.8, beta: 3.0}\n  - {fwhm_um: 1.6, beta: 1.5}\n'
    printf '  - {fwhm_um: 1.0, beta: 2.5}\n  - {fwhm_um: 2.0, beta: 1.2}\n'
    printf 'provenance: "cli_test.sh"\n'
} >map_grid.yaml
# regions: a metal stripe (label 1, columns 12..19) on oxide (label 0), labels as a text image
awk 'BEGIN { for (y = 0; y < 32; y++) { l = ""; for (x = 0; x < 32; x++) l = l (x ? " " : "") (x >= 12 && x < 20); print l } }' >map_labels.txt
{
    printf 'pixel_um: 0.5\nimage: {width: 32, height: 32}\nmodel: moffat\nkind: regions\n'
    printf 'labels_file: map_labels.txt\ntransition_um: 0.5\nregions:\n'
    printf '  - {label: 0, name: oxide, fwhm_um: 1.0, beta: 2.5}\n'
    printf '  - {label: 1, name: metal, fwhm_um: 2.0, beta: 1.3}\n'
} >map_regions.yaml
check_help forward --nodes --rank --regions --operator-tol --max-memory
check_help correct --nodes --rank --regions --operator-tol --max-memory
expect_ok map_fwd_plain forward --field Bz.txt --pl pl.txt --psf moffat.yaml --boundary mirror -o map_plain --format txt $FAST
expect_ok map_fwd_uniform forward --field Bz.txt --pl pl.txt --psf map_uniform.yaml --boundary mirror -o map_uni --format txt $FAST
check_close "PSF map of kind uniform = the plain PSF file (forward field)" map_plain/field.txt map_uni/field.txt 1e-12
expect_ok map_fwd_same forward --field Bz.txt --pl pl.txt --psf map_same.yaml --boundary mirror --nodes 3x5 -o map_same --format txt $FAST
check_close "grid map with identical nodes, tent 3x5 = invariant operator (forward field)" map_plain/field.txt map_same/field.txt 1e-12
check_close "grid map with identical nodes, tent 3x5 = invariant operator (forward PL)" map_plain/pl.txt map_same/pl.txt 1e-12
if grep -q '"psf_kind": "map"' map_same/summary.json && grep -q '"psf_map_kind": "grid"' map_same/summary.json &&
    grep -q '"psf_representation": "tent"' map_same/summary.json && grep -q '"psf_nodes": "3 x 5"' map_same/summary.json &&
    grep -q '"psf_operator_bytes"' map_same/summary.json; then
    pass "summary.json records the PSF map, its kind, the representation, nodes and operator memory"
else
    fail "map summary" "$(grep psf map_same/summary.json)"
fi
# T^-1(T(B)) with the map on both sides (W = Tikhonov by CG for a variant operator) recovers B;
# assuming one PSF instead does not. Measured (max error / peak B): map 1.4e-3, single PSF 0.19.
expect_ok map_fwd_grid forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --nodes 4x4 --boundary mirror -o map_g --format npy $FAST
expect_ok map_corr_grid correct --field map_g/field.npy --pl map_g/pl.npy --psf map_grid.yaml --nodes 4x4 \
    --boundary mirror --method w --balance 1e-4 --iterations 100 -o map_gc --format txt $FAST
expect_ok map_corr_single correct --field map_g/field.npy --pl map_g/pl.npy --psf moffat.yaml \
    --boundary mirror --method w --balance 1e-4 --iterations 100 -o map_sc --format txt $FAST
check_close "T^-1(T(B)) with the PSF map on both sides, W balance 1e-4" Bz.txt map_gc/field.txt 5e-3
r=$(maxdiff Bz.txt map_sc/field.txt)
if awk -v r="$r" 'BEGIN { split(r, x, " "); exit !(x[1] > 0.05 * x[2]) }'; then
    pass "correcting with one PSF instead of the map leaves a larger error ($(echo "$r" | cut -d' ' -f1) of peak $(echo "$r" | cut -d' ' -f2))"
else
    fail "single PSF vs map" "max error / peak = $r, expected > 5 %"
fi
# a margin with a map (docs/model.md §9 "Light from outside the view"): the map's edge PSFs
# carried outward; 0 by default for a map, auto = its widest PSF's reach, a number as given
expect_ok map_corr_m0 correct --field map_g/field.npy --pl map_g/pl.npy --psf map_grid.yaml --nodes 4x4 \
    --iterations 20 -o map_m0 --format txt $FAST
expect_ok map_corr_mauto correct --field map_g/field.npy --pl map_g/pl.npy --psf map_grid.yaml --nodes 4x4 \
    --iterations 20 --margin auto -o map_mauto --format txt $FAST
expect_ok map_corr_m5 correct --field map_g/field.npy --pl map_g/pl.npy --psf map_grid.yaml --nodes 4x4 \
    --iterations 20 --margin 5 -o map_m5 --format txt $FAST
if grep -q '"margin": 0' map_m0/summary.json && grep -q '"margin": [1-9]' map_mauto/summary.json &&
    grep -q '"margin": 5' map_m5/summary.json; then
    pass "correct with a PSF map: margin 0 by default, $(sed -n 's/.*"margin": \([0-9]*\).*/\1/p' map_mauto/summary.json | head -1) px for auto, 5 as given"
else
    fail "map margin" "$(grep -h '"margin"' map_m0/summary.json map_mauto/summary.json map_m5/summary.json)"
fi
expect_ok map_fwd_regions forward --field Bz.txt --pl pl.txt --psf map_regions.yaml --rank 4 --nodes 6 -o map_r --format txt $FAST
if grep -q '"psf_map_kind": "regions"' map_r/summary.json && grep -q '"psf_rank": 4' map_r/summary.json &&
    grep -q '"psf_samples": "6 x 6"' map_r/summary.json; then
    pass "regions map with a label image, low rank 4 on 6 x 6 samples: summary records it"
else
    fail "regions map summary" "$(grep psf map_r/summary.json)"
fi
# --regions: one kernel per region (docs/model.md §9 "Region maps"), for forward and correct; on
# a sharp map it is exact, and the automatic choice (--operator-tol 1e-3) picks it too (no tent
# grid or low rank meets that budget on a sharp boundary): the same fields to round-off
sed 's/transition_um: 0.5/transition_um: 0/' map_regions.yaml >map_regions_sharp.yaml
expect_ok map_fwd_regions_forced forward --field Bz.txt --pl pl.txt --psf map_regions_sharp.yaml --regions \
    --boundary mirror -o map_rf --format txt $FAST
expect_ok map_fwd_regions_auto forward --field Bz.txt --pl pl.txt --psf map_regions_sharp.yaml --operator-tol 1e-3 \
    --boundary mirror -o map_ra --format txt $FAST
if grep -q '"psf_representation": "regions"' map_rf/summary.json && grep -q '"psf_region_kernels": 2' map_rf/summary.json &&
    grep -q '"psf_representation_chosen_by": "option"' map_rf/summary.json &&
    grep -q 'Operator: regions (2 region kernels)' out.map_fwd_regions_forced &&
    grep -q '"psf_representation": "regions"' map_ra/summary.json &&
    grep -q '"psf_representation_chosen_by": "operator-tol"' map_ra/summary.json &&
    grep -q '"operator_tolerance_met": 1' map_ra/summary.json; then
    pass "--regions: summary.json and the report record regions and 2 region kernels; --operator-tol 1e-3 picks it on a sharp map"
else
    fail "--regions summary" "$(grep -hE 'psf_rep|region|tolerance' map_rf/summary.json map_ra/summary.json) / $(cat out.map_fwd_regions_forced)"
fi
check_close "sharp region map: --regions = the automatic choice (forward field)" map_rf/field.txt map_ra/field.txt 1e-12
expect_ok map_corr_regions correct --field map_rf/field.txt --pl map_rf/pl.txt --psf map_regions_sharp.yaml --regions \
    --boundary mirror --method r --iterations 20 -o map_rc --format txt $FAST
if grep -q '"psf_representation": "regions"' map_rc/summary.json && grep -q '"psf_region_kernels": 2' map_rc/summary.json &&
    grep -q 'Operator: regions (2 region kernels)' out.map_corr_regions; then
    pass "correct --regions: summary.json and the report record the region operator"
else
    fail "correct --regions" "$(grep -hE 'psf_rep|region' map_rc/summary.json) / $(cat out.map_corr_regions)"
fi
expect_bad map_regions_on_grid "kind regions|kind grid" forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --regions \
    -o map_rg --format txt $FAST
run map_regions_nodes forward --field Bz.txt --pl pl.txt --psf map_regions.yaml --regions --nodes 4 -o map_rn --format txt
if [ "$(cat rc.map_regions_nodes)" != 0 ] && grep -qF -- "--nodes cannot be combined with --regions" err.map_regions_nodes; then
    pass "--regions with --nodes is refused"
else
    fail "--regions with --nodes" "exit $(cat rc.map_regions_nodes): $(cat err.map_regions_nodes)"
fi
# without --nodes / --rank the representation is chosen by --operator-tol: summary and report
expect_ok map_fwd_auto forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --operator-tol 3e-2 -o map_auto --format txt $FAST
if grep -q '"psf_representation_chosen_by": "operator-tol"' map_auto/summary.json &&
    grep -q '"operator_tolerance": 0.03' map_auto/summary.json &&
    grep -q '"operator_tolerance_met": 1' map_auto/summary.json &&
    grep -q '"operator_estimated_error"' map_auto/summary.json &&
    grep -q '"operator_build_s"' map_auto/summary.json &&
    grep -q 'Operator: .*estimated error .*budget 0.03.*built in' out.map_fwd_auto; then
    pass "--operator-tol: summary.json and the report state the choice, its estimated error, build time and memory"
else
    fail "--operator-tol summary" "$(grep -E 'operator|psf_rep' map_auto/summary.json) / $(cat out.map_fwd_auto)"
fi
awk -F': ' '/"operator_estimated_error"/ { gsub(/,/, "", $2); exit !($2 + 0 <= 0.03) }' map_auto/summary.json &&
    pass "--operator-tol 3e-2: the choice's estimated error is within it" ||
    fail "--operator-tol estimate" "$(grep operator_estimated_error map_auto/summary.json)"
# the choice's cost model counts the correction's own H + Hᵀ pairs (r: RL iterations on the PL
# and on the numerator; w: about 40 CG steps per Wiener deconvolution; forward: 1), and correct
# records one application's and one adjoint's measured time
expect_ok map_corr_auto correct --field map_auto/field.txt --pl map_auto/pl.txt --psf map_grid.yaml --operator-tol 3e-2 \
    --method r --iterations 7 -o map_ca --format txt $FAST
expect_ok map_corr_auto_w correct --field map_auto/field.txt --pl map_auto/pl.txt --psf map_grid.yaml --operator-tol 3e-2 \
    --method w --balance 1e-3 -o map_caw --format txt $FAST
if grep -q '"operator_applications": 14' map_ca/summary.json && grep -q '"operator_applications": 80' map_caw/summary.json &&
    grep -qE '"operator_applications": 1(,|$)' map_auto/summary.json &&
    awk -F': ' '/"operator_(apply|adjoint)_s"/ { gsub(/,/, "", $2); n++; if (!($2 + 0 > 0)) bad = 1 } END { exit !(n == 2 && !bad) }' map_ca/summary.json &&
    grep -q 'Operator: .*built in .*one application .* s (adjoint .* s)' out.map_corr_auto; then
    pass "--operator-tol: the cost model counts the method's applications (r 7 it: 14, w: 80, forward: 1); correct records and reports one application's and adjoint's time"
else
    fail "operator applications / apply time" "$(grep -hE 'operator_(appl|adj)' map_ca/summary.json map_caw/summary.json map_auto/summary.json) / $(cat out.map_corr_auto)"
fi
expect_bad map_bad_tol "--operator-tol|0|(0, 1)" forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --operator-tol 0 -o bad $FAST
expect_bad map_bad_mem "--max-memory|12x" forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --max-memory 12x -o bad $FAST
# an operator beyond the memory limit is refused up front (exit 1) with what it would need
expect_bad map_mem_refused "needs about|MB|memory limit" forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --rank 4 --max-memory 64k -o bad_mem $FAST
[ -e bad_mem ] && fail "refused --max-memory" "left bad_mem" || pass "an operator over --max-memory writes nothing"
SVPSF_MAX_MEMORY=64k run map_mem_env forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --nodes 4 -o bad_mem $FAST
if [ "$(cat rc.map_mem_env)" = 1 ] && grep -qF "needs" err.map_mem_env; then
    pass "SVPSF_MAX_MEMORY bounds the operator like --max-memory"
else
    fail "SVPSF_MAX_MEMORY" "exit $(cat rc.map_mem_env): $(cat err.map_mem_env)"
fi
# a map no representation follows (FWHM 0.5 px at the left node, 150 px at the right): the
# automatic choice misses its budget by far, a result in doubt (exit 3, nothing written); kept on
# request it is recorded; the caller's own representation passes
{
    printf 'pixel_um: 0.5\nimage: {width: 32, height: 32}\nmodel: moffat\nkind: grid\n'
    printf 'nodes: {nx: 2, ny: 1}\nnode_psfs:\n'
    printf '  - {fwhm_um: 0.25, beta: 1.1}\n  - {fwhm_um: 75, beta: 1.1}\n'
} >map_wild.yaml
run map_wild correct --field map_auto/field.txt --pl map_auto/pl.txt --psf map_wild.yaml -o map_wild --format txt $FAST
if [ "$(cat rc.map_wild)" = 3 ] && [ ! -e map_wild ] &&
    grep -qF "estimated relative error of" err.map_wild && grep -qF "operator tolerance" err.map_wild; then
    pass "a PSF map whose automatic operator misses its budget by far: exit 3, nothing written"
else
    fail "map_wild" "exit $(cat rc.map_wild): $(cat err.map_wild)"
fi
expect_ok map_wild_kept correct --field map_auto/field.txt --pl map_auto/pl.txt --psf map_wild.yaml \
    --keep-doubtful -o map_wild_k --format txt $FAST
grep -q '"doubts": "operator_error"' map_wild_k/summary.json &&
    pass "--keep-doubtful records operator_error" ||
    fail "map_wild_kept" "$(grep doubts map_wild_k/summary.json)"
expect_ok map_wild_nodes correct --field map_auto/field.txt --pl map_auto/pl.txt --psf map_wild.yaml \
    --nodes 8x1 -o map_wild_n --format txt $FAST
# a polynomial map extrapolated out of range (FWHM 1 + 1.5 u um < 0.025 um on columns 0-5): clamped
# there, with a warning that says where and how far
{
    printf 'pixel_um: 0.5\nimage: {width: 32, height: 32}\nmodel: moffat\nkind: poly\n'
    printf 'degree: 1\ncoefficients: {fwhm_um: [1.0, 1.5, 0.0], beta: [2.5, 0, 0]}\n'
} >map_poly_neg.yaml
run map_poly_neg forward --field Bz.txt --pl pl.txt --psf map_poly_neg.yaml --nodes 4 -o map_pn --format txt $FAST
if [ "$(cat rc.map_poly_neg)" = 0 ] &&
    grep -qF "map_poly_neg.yaml: the PSF map's parameters leave their valid range on 18.8 % of its pixels" err.map_poly_neg &&
    grep -qF "the FWHM down to -0.5 um at pixel (0, 0)" err.map_poly_neg; then
    pass "a polynomial map out of range: a warning with the share, the worst pixel and its value"
else
    fail "map_poly_neg" "exit $(cat rc.map_poly_neg): $(cat err.map_poly_neg)"
fi
# a point source keeps its flux through the region map
awk 'BEGIN { for (y = 0; y < 32; y++) { l = ""; for (x = 0; x < 32; x++) l = l (x ? " " : "") (x == 15 && y == 16); print l } }' >map_point.txt
expect_ok map_fwd_point forward --field Bz.txt --pl map_point.txt --psf map_regions.yaml --boundary periodic -o map_pt --format txt $FAST
s=$(awk '{ for (i = 1; i <= NF; i++) t += $i } END { printf "%.15f", t }' map_pt/pl.txt)
if awk -v s="$s" 'BEGIN { exit !(s > 1 - 1e-9 && s < 1 + 1e-9) }'; then
    pass "region map: a point source keeps unit flux ($s)"
else
    fail "region map flux" "sum $s"
fi
# a PSF map where one PSF is expected: named as a PSF map, with the commands that take maps;
# a map of kind uniform is that one PSF
expect_bad map_to_psf "map_grid.yaml|PSF map|kind grid|single PSF file|correct --psf" psf map_grid.yaml -o bad_map_k.txt
expect_bad map_to_dec "map_grid.yaml|PSF map|single PSF file|forward --psf" deconvolve pl.txt --psf map_grid.yaml \
    -o bad/x.txt --method rl $FAST
expect_ok map_uniform_psf psf map_uniform.yaml --size 63 -o k63_uniform.txt
check_close "psf on a PSF map of kind uniform = on the plain PSF file" k63.txt k63_uniform.txt 1e-12
# --precision single with a map (docs/cli.md): float transforms of the map's operator, its
# spectra in float only; forward and correct agree with double within the stated bounds
expect_ok map_fwd_d forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --rank 4 --boundary mirror -o map_fd --format txt $FAST
expect_ok map_fwd_s forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --rank 4 --boundary mirror --precision single -o map_fs --format txt $FAST
check_close "forward --precision single with a map (low rank 4): PL agrees with double" map_fd/pl.txt map_fs/pl.txt 2e-6
check_close "forward --precision single with a map (low rank 4): field agrees with double" map_fd/field.txt map_fs/field.txt 1e-5
bd=$(sed -n 's/.*"psf_operator_bytes": \([0-9]*\).*/\1/p' map_fd/summary.json)
bs=$(sed -n 's/.*"psf_operator_bytes": \([0-9]*\).*/\1/p' map_fs/summary.json)
if [ -n "$bd" ] && [ -n "$bs" ] && [ "$bs" -lt "$bd" ] && grep -q '"precision": "single"' map_fs/summary.json; then
    pass "a map's operator in single precision holds less ($bs bytes against $bd) and summary.json says single"
else
    fail "map single memory" "single $bs, double $bd bytes"
fi
expect_ok map_fwd_tent_s forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --nodes 4x4 --boundary mirror --precision single -o map_gs --format txt $FAST
expect_ok map_fwd_tent_d forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --nodes 4x4 --boundary mirror -o map_gd --format txt $FAST
check_close "forward --precision single with a map (tent 4x4): field agrees with double" map_gd/field.txt map_gs/field.txt 1e-5
expect_ok fwd_one_s forward --field Bz.txt --pl pl.txt --psf moffat.yaml --boundary mirror --precision single -o map_ps --format txt $FAST
check_close "forward --precision single with one PSF: field agrees with double" map_plain/field.txt map_ps/field.txt 1e-5
# bounds: the PL 5e-7 x iterations of its peak (as for one PSF); r's field 2e-5 of its peak, plain
# and accelerated alike: RL transforms only deviations from its levels, and the numerators use
# the PL's levels (docs/model.md §6; measured PL 9.9e-7 / 2.0e-6, field 2.9e-6 / 4.0e-6 plain /
# accelerated; before, when RL transformed its iterate whole: field 2.5e-4 / 1.0e-3); rw's field
# (Wiener by CG, double) 1e-4
for m in r:none:2e-5 r:biggs-andrews:2e-5 rw:none:1e-4; do
    fb=${m##*:}
    acc=${m#*:}
    acc=${acc%%:*}
    m=${m%%:*}
    expect_ok map_corr_d_$m$acc correct --field map_g/field.npy --pl map_g/pl.npy --psf map_grid.yaml --rank 4 \
        --boundary mirror --method $m --iterations 100 --acceleration $acc -o map_cd_$m$acc --format txt $FAST
    expect_ok map_corr_s_$m$acc correct --field map_g/field.npy --pl map_g/pl.npy --psf map_grid.yaml --rank 4 \
        --boundary mirror --method $m --iterations 100 --acceleration $acc --precision single -o map_cs_$m$acc --format txt $FAST
    check_close "correct --method $m --acceleration $acc --precision single with a map (100 iterations): PL agrees with double" map_cd_$m$acc/pl.txt map_cs_$m$acc/pl.txt 5e-5
    check_close "correct --method $m --acceleration $acc --precision single with a map (100 iterations): field agrees with double" map_cd_$m$acc/field.txt map_cs_$m$acc/field.txt $fb
done
expect_bad map_bad_nodes "--nodes|0x2|1..64" forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --nodes 0x2 -o bad $FAST
expect_bad map_bad_nodes_text "--nodes|4y4" forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --nodes 4y4 -o bad $FAST
expect_bad map_bad_rank "map_grid.yaml|low rank 9|2 x 2" forward --field Bz.txt --pl pl.txt --psf map_grid.yaml --nodes 2x2 --rank 9 -o bad $FAST
awk 'BEGIN { for (y = 0; y < 30; y++) { l = ""; for (x = 0; x < 32; x++) l = l (x ? " " : "") 1; print l } }' >pl30.txt
awk 'BEGIN { for (y = 0; y < 30; y++) { l = ""; for (x = 0; x < 32; x++) l = l (x ? " " : "") 0; print l } }' >B30.txt
expect_bad map_bad_size "map_grid.yaml|32 x 32|32 x 30|PSF map" forward --field B30.txt --pl pl30.txt --psf map_grid.yaml -o bad $FAST
{
    printf 'pixel_um: 0.5\nimage: {width: 32, height: 32}\nmodel: moffat\nkind: grid\n'
    printf 'nodes: {nx: 2, ny: 2}\nnode_psfs:\n  - {fwhm_um: 1.0, beta: 2.5}\n'
} >map_short.yaml
expect_bad map_bad_count "map_short.yaml|node_psfs" correct --field Bz.txt --pl pl.txt --psf map_short.yaml -o bad $FAST
# where one PSF is expected, a faulty PSF map is reported by its own fault, not as a PSF file
expect_bad map_bad_count_psf "map_short.yaml|node_psfs" psf map_short.yaml -o bad_short.txt
if [ -e bad ]; then fail "bad PSF maps" "the output folder 'bad' was created"; else pass "no output folder after bad PSF maps"; fi

# ---- correct --balance auto: the discrepancy principle per Wiener deconvolution ---------------
# Noisy apparent maps (Box-Muller in awk, fixed seeds): sigma 0.01 on the PL (peak ~1), 0.05 on
# the field. Method W deconvolves both the PL and field x PL with Wiener-Hunt, each with its own
# balance. Checks: the recorded noise estimate of the PL is within 15 % of the true 0.01
# (measured 0.0108); the PL's balance is the one `deconvolve --balance auto` picks on the same
# image (an independent call of the library function); the chosen balance meets the discrepancy
# principle, mean (H x - y)^2 = sigma^2 within 2 % (H x by `svpsf forward` of the recovered PL);
# three times the noise gives a larger balance; both lie strictly inside the search interval.
noisy() {
    awk -v s="$2" -v seed="$3" 'BEGIN { srand(seed) } { l = ""; for (i = 1; i <= NF; i++) {
        u = rand(); if (u < 1e-300) u = 1e-300
        g = sqrt(-2 * log(u)) * cos(6.283185307179586 * rand())
        l = l (i > 1 ? " " : "") sprintf("%.17g", $i + s * g) }; print l }' "$1"
}
# jnum FILE KEY: the number after "KEY": in a summary.json
jnum() { sed -n "s/.*\"$2\": \([-0-9][-0-9.eE+]*\).*/\1/p" "$1" | head -1; }
expect_ok fwd_pn forward --field Bz.txt --pl pl.txt --psf moffat_periodic.yaml -o fwd_pn --format txt $FAST
noisy fwd_pn/pl.txt 0.01 11 >pl_noisy.txt
noisy fwd_pn/field.txt 0.05 12 >field_noisy.txt
noisy fwd_pn/pl.txt 0.03 13 >pl_noisier.txt
expect_ok corr_auto correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat_periodic.yaml \
    --method w --balance auto -o corr_auto --format txt $FAST
expect_ok corr_auto10 correct --field field_noisy.txt --pl pl_noisier.txt --psf moffat_periodic.yaml \
    --method w --balance auto -o corr_auto10 --format txt $FAST
expect_ok dec_auto_pl deconvolve pl_noisy.txt --psf moffat_periodic.yaml -o dec_auto_pl.txt \
    --method wiener --balance auto $FAST
# a search that ends on a bound of [1e-12, 1e2] cannot be vouched for: exit 3, nothing written;
# --keep-doubtful writes it, warned and recorded
run dec_auto_lo deconvolve pl_noisy.txt --psf moffat_periodic.yaml -o dec_auto_lo.txt \
    --method wiener --balance auto --noise 1e-20 $FAST
run corr_auto_hi correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat_periodic.yaml \
    --method w --balance auto --noise 10 -o corr_auto_hi --format txt $FAST
expect_ok corr_auto_keep correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat_periodic.yaml \
    --method w --balance auto --noise 10 -o corr_auto_keep --format txt --keep-doubtful $FAST
if [ "$(cat rc.dec_auto_lo)" = 3 ] && grep -q 'pl_noisy.txt: result in doubt: --balance auto ended on the lower end' err.dec_auto_lo &&
    [ ! -e dec_auto_lo.txt ] && [ "$(cat rc.corr_auto_hi)" = 3 ] && [ ! -e corr_auto_hi ] &&
    grep -q 'result in doubt: the automatic balance of pl_noisy.txt ended on the upper end' err.corr_auto_hi &&
    grep -q '"balance_at_bound_pl": "upper"' corr_auto_keep/summary.json &&
    grep -q '"doubts": "balance_at_bound' corr_auto_keep/summary.json &&
    grep -q 'kept by --keep-doubtful' err.corr_auto_keep &&
    ! grep -q 'warning' err.corr_auto && ! grep -q 'at_bound' corr_auto/summary.json; then
    pass "--balance auto on a bound of its search: exit 3, nothing written (lower: deconvolve --noise 1e-20; upper: correct --noise 10); --keep-doubtful writes and records it; not inside"
else
    fail "--balance auto at a bound" "$(cat rc.dec_auto_lo err.dec_auto_lo rc.corr_auto_hi err.corr_auto_hi err.corr_auto_keep err.corr_auto)"
fi
# a PL of about 1e-322 (written as text, since awk cannot hold it): outside the solvers' range
# [1e-150, 1e150] of magnitudes, refused with exit 1 naming the file (it deconvolved to zeros,
# exit 0); deconvolve likewise
awk '{ for (i = 1; i <= NF; i++) printf "%s%.12fe-322", (i > 1 ? " " : ""), $i; print "" }' \
    pl_noisy.txt >pl_subnormal.txt
expect_bad corr_tiny "pl_subnormal.txt|lies outside [1e-150, 1e+150]|rescale" correct \
    --field field_noisy.txt --pl pl_subnormal.txt --psf moffat_periodic.yaml -o corr_tiny $FAST
expect_bad dec_tiny "pl_subnormal.txt|Wiener deconvolution: the data y|lies outside" deconvolve \
    pl_subnormal.txt --psf moffat_periodic.yaml -o dec_tiny.txt --method wiener $FAST
# a measured PSF kernel whose background was over-subtracted (a negative ring): RL clips the PL
# to 0 and the field with it; the light-lost check refuses it (exit 3, it used to exit 0), and
# --keep-doubtful records light_lost
awk 'BEGIN { for (y = -7; y <= 7; y++) { for (x = -7; x <= 7; x++) { r2 = x * x + y * y
    printf "%s%.17g", (x > -7 ? " " : ""), exp(-r2 / 4.5) - 0.1 * exp(-r2 / 32) } print "" } }' \
    >ring_kernel.txt
run corr_lost correct --field field_noisy.txt --pl pl_noisy.txt --psf ring_kernel.txt \
    -o corr_lost --format txt $FAST
run corr_lost_keep correct --field field_noisy.txt --pl pl_noisy.txt --psf ring_kernel.txt \
    -o corr_lost_keep --format txt --keep-doubtful $FAST
if [ "$(cat rc.corr_lost)" = 3 ] && [ ! -e corr_lost ] &&
    grep -q 'result in doubt: the corrected pl_noisy.txt holds 0 of the measured light' err.corr_lost &&
    grep -q 'warning: ring_kernel.txt: the PSF kernel has 188 negative pixels (down to -0.0419' err.corr_lost &&
    [ "$(cat rc.corr_lost_keep)" = 0 ] && grep -q '"doubts": "light_lost"' corr_lost_keep/summary.json &&
    grep -q 'result in doubt (light_lost), kept by --keep-doubtful' err.corr_lost_keep; then
    pass "a PSF kernel with a negative ring loses the light: exit 3, nothing written; --keep-doubtful records light_lost"
else
    fail "negative-ring kernel" "$(cat rc.corr_lost err.corr_lost rc.corr_lost_keep err.corr_lost_keep)"
fi
lam=$(jnum corr_auto/summary.json balance_pl)
lam_f=$(jnum corr_auto/summary.json balance_field)
sig=$(jnum corr_auto/summary.json noise_sigma_pl)
lam10=$(jnum corr_auto10/summary.json balance_pl)
lam_dec=$(jnum dec_auto_pl.summary.json balance)
if grep -q '"noise_sigma_from": "estimated"' corr_auto/summary.json && [ -n "$lam_f" ] &&
    grep -q "automatic balance: PL [0-9.e+-]* (discrepancy principle" out.corr_auto &&
    grep -q "\"balance_rule_pl\": \"discrepancy\"" corr_auto/summary.json &&
    awk -v s="$sig" 'BEGIN { exit !(s > 0.0085 && s < 0.0115) }'; then
    pass "correct --balance auto records balance_pl $lam, balance_field $lam_f and the PL's noise estimate $sig (true 0.01)"
else
    fail "correct --balance auto summary" "sigma '$sig' balances '$lam' '$lam_f': $(cat out.corr_auto)"
fi
if awk -v a="$lam" -v b="$lam_dec" 'BEGIN { exit !(a > 0 && (a - b) ^ 2 <= (1e-9 * a) ^ 2) }'; then
    pass "correct --balance auto: the PL's balance $lam = deconvolve --balance auto's $lam_dec"
else
    fail "correct vs deconvolve balance" "'$lam' vs '$lam_dec'"
fi
if awk -v a="$lam" -v b="$lam10" 'BEGIN { exit !(a > 1e-12 && b > a && b < 1e2) }'; then
    pass "correct --balance auto: 3x the noise, larger balance ($lam -> $lam10), inside (1e-12, 1e2)"
else
    fail "balance vs noise" "'$lam' at sigma 0.01, '$lam10' at 0.03"
fi
awk '{ for (i = 1; i <= NF; i++) printf "%s1", (i > 1 ? " " : ""); print "" }' pl.txt >ones.txt
expect_ok fwd_hx forward --field ones.txt --pl corr_auto/pl.txt --psf moffat_periodic.yaml -o fwd_hx --format txt $FAST
msr=$(paste -d' ' fwd_hx/pl.txt pl_noisy.txt | awk '{ h = NF / 2; for (i = 1; i <= h; i++) { d = $i - $(i + h); t += d * d; n++ } } END { printf "%.6g", t / n }')
if awk -v m="$msr" -v s="$sig" 'BEGIN { r = m / (s * s); exit !(r > 0.98 && r < 1.02) }'; then
    pass "discrepancy principle met: mean (H x - y)^2 = $msr, sigma^2 = $(awk -v s="$sig" 'BEGIN { printf "%.6g", s * s }')"
else
    fail "discrepancy principle" "mean (H x - y)^2 = $msr, sigma = $sig"
fi
expect_ok corr_auto_n correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat_periodic.yaml \
    --method rw --balance auto --noise 0.02 -o corr_auto_n --format txt $FAST
if grep -q '"noise_sigma_field": 0.02,' corr_auto_n/summary.json && ! grep -q balance_pl corr_auto_n/summary.json &&
    grep -q '"noise_sigma_from": "--noise"' corr_auto_n/summary.json; then
    pass "correct --method rw --balance auto --noise: one Wiener balance (field x PL) with the given sigma"
else
    fail "rw --balance auto --noise" "$(grep -E 'balance|noise' corr_auto_n/summary.json)"
fi
expect_bad corr_auto_r "--balance auto|rw or w" correct --field Bz.txt --pl pl.txt --psf moffat.yaml -o bad --method r --balance auto
expect_bad corr_noise_alone "--noise|--balance auto" correct --field Bz.txt --pl pl.txt --psf moffat.yaml -o bad --noise 0.1
expect_bad corr_bad_balance "--balance|-1|auto" correct --field Bz.txt --pl pl.txt --psf moffat.yaml -o bad --balance -1

# ---- the options of trustworthy corrections (docs/model.md §3, §6) ---------------------------
# an object beyond the view: recorded; refused where it cannot apply
expect_ok corr_margin correct --field fwd_z/field.tif --pl fwd_z/pl.tif --psf moffat.yaml --margin 6 \
    -o corr_margin --format txt $FAST
expect_ok corr_margin_auto correct --field fwd_z/field.tif --pl fwd_z/pl.tif --psf moffat.yaml \
    --margin auto -o corr_margin_auto --format txt $FAST
if grep -q '"margin": 6' corr_margin/summary.json && grep -q '"margin": [1-9]' corr_margin_auto/summary.json; then
    pass "correct --margin 6 / auto: recorded ($(jnum corr_margin_auto/summary.json margin) px for auto)"
else
    fail "--margin" "$(grep margin corr_margin/summary.json corr_margin_auto/summary.json)"
fi
expect_bad corr_margin_mirror "--margin needs the zero boundary" correct --field Bz.txt \
    --pl pl.txt --psf moffat.yaml --boundary mirror --margin 4 -o bad
# automatic iterations: why RL stopped is recorded; not for W
expect_ok corr_auto_it correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat_periodic.yaml \
    --iterations 400 --iterations auto --gain 1e-4 -o corr_auto_it --format txt $FAST
if grep -q '"rl_stop": "\(discrepancy\|stalled\)"' corr_auto_it/summary.json &&
    grep -q '"iterations": "auto"' corr_auto_it/summary.json && grep -q '"pl_gain_from": "--gain"' corr_auto_it/summary.json; then
    pass "correct --iterations auto: $(jnum corr_auto_it/summary.json rl_iterations) iterations, stopped by $(sed -n 's/.*"rl_stop": "\([a-z]*\)".*/\1/p' corr_auto_it/summary.json)"
else
    fail "--iterations auto" "$(cat err.corr_auto_it) $(grep rl_ corr_auto_it/summary.json)"
fi
expect_bad corr_auto_it_w "--iterations auto|Richardson-Lucy|--method w" correct --field Bz.txt --pl pl.txt \
    --psf moffat.yaml --method w --iterations auto -o bad
expect_bad corr_bad_gain "--gain|0|> 0" correct --field Bz.txt --pl pl.txt --psf moffat.yaml --gain 0 -o bad
# per-pixel field sigma: one per field, the PL's size, never negative
expect_bad corr_sigma_count "--field-sigma|2 maps for 1 --field map" correct --field Bz.txt --pl pl.txt \
    --psf moffat.yaml --field-sigma Bz.txt --field-sigma Bz.txt -o bad
awk '{for (i = 1; i <= NF; i++) $i = -1} 1' Bz.txt >sigma_neg.txt
expect_bad corr_sigma_neg "sigma_neg.txt|negative" correct --field Bz.txt --pl pl.txt --psf moffat.yaml \
    --field-sigma sigma_neg.txt -o bad
# deconvolve: automatic iterations and acceleration
expect_ok dec_auto_it deconvolve pl_noisy.txt --psf moffat_periodic.yaml -o dec_auto_it.txt --method rl \
    --iterations 400 --iterations auto --acceleration biggs-andrews $FAST
if grep -q '"rl_stop": "\(discrepancy\|stalled\)"' dec_auto_it.summary.json &&
    grep -q '"acceleration": "biggs-andrews"' dec_auto_it.summary.json; then
    pass "deconvolve --iterations auto --acceleration biggs-andrews: $(jnum dec_auto_it.summary.json rl_iterations) iterations"
else
    fail "deconvolve --iterations auto" "$(cat err.dec_auto_it) $(grep rl_ dec_auto_it.summary.json)"
fi

# ---- the zero-boundary Wiener's CG step cap is reported --------------------------------------
# 2 steps cannot converge: exit 3, nothing written; with --keep-doubtful a warning per capped
# solve, recorded, validity 0
run corr_cap correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat.yaml --method w \
    --cg-max-steps 2 -o corr_cap --format txt $FAST
expect_ok corr_cap_keep correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat.yaml --method w \
    --cg-max-steps 2 -o corr_cap_keep --format txt --keep-doubtful $FAST
if [ "$(cat rc.corr_cap)" = 3 ] && [ ! -e corr_cap ] && grep -q 'stopped at its step cap (2 conjugate-gradient steps' err.corr_cap &&
    [ "$(grep -c 'warning: .*step cap' err.corr_cap_keep)" = 2 ] && grep -q '"n_cg_capped": 2' corr_cap_keep/summary.json &&
    grep -q '"cg_capped_pl": 1' corr_cap_keep/summary.json && grep -q '"cg_capped_field": 1' corr_cap_keep/summary.json &&
    grep -q '"doubts": "cg_not_converged' corr_cap_keep/summary.json &&
    /usr/bin/awk '{for (i = 1; i <= NF; i++) if ($i + 0 != 0) bad = 1} END {exit bad}' corr_cap_keep/validity.txt; then
    pass "correct --cg-max-steps 2: exit 3 and nothing written; kept: both solves warn, are recorded as capped, validity 0 ($(tr '\n' ' ' <err.corr_cap | head -c 160))"
else
    fail "CG step cap" "$(cat rc.corr_cap err.corr_cap err.corr_cap_keep) $(grep cg corr_cap_keep/summary.json)"
fi
expect_ok corr_nocap correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat.yaml --method w \
    -o corr_nocap --format txt $FAST
if grep -q '"n_cg_capped": 0' corr_nocap/summary.json && ! grep -q warning err.corr_nocap &&
    grep -q '"cg_steps_pl"' corr_nocap/summary.json; then
    pass "correct with the default cap: the CG converges ($(jnum corr_nocap/summary.json cg_steps_pl) steps for the PL), no warning"
else
    fail "CG default cap" "$(cat err.corr_nocap) $(grep cg corr_nocap/summary.json)"
fi
# capped two steps before it converges: the residual is above the CG's 1e-8 but below 1e-4
# (SVP_CG_DOUBT_RESIDUAL), so the result is kept (exit 0, no doubt, validity not zeroed) and the
# warning says so instead of blaming --keep-doubtful
near=$(( $(jnum corr_nocap/summary.json cg_steps_pl) - 2 ))
expect_ok corr_near correct --field field_noisy.txt --pl pl_noisy.txt --psf moffat.yaml --method w \
    --cg-max-steps "$near" -o corr_near --format txt $FAST
res=$(jnum corr_near/summary.json cg_residual_pl)
if grep -q '"cg_capped_pl": 1' corr_near/summary.json && grep -q '"doubts": ""' corr_near/summary.json &&
    /usr/bin/awk -v r="$res" 'BEGIN {exit !(r > 1e-8 && r < 1e-4)}' &&
    grep -q 'warning: the Wiener deconvolution of the PL stopped at the step cap.*converged well enough to keep' err.corr_near &&
    ! grep -q 'kept by --keep-doubtful' err.corr_near &&
    /usr/bin/awk '{for (i = 1; i <= NF; i++) if ($i + 0 > 0) ok = 1} END {exit !ok}' corr_near/validity.txt; then
    pass "correct --cg-max-steps $near (2 short of convergence): residual $res kept, exit 0, no doubt, warned as converged enough"
else
    fail "CG capped near convergence" "$(cat err.corr_near) $(grep -E 'cg|doubts' corr_near/summary.json)"
fi
run dec_cap deconvolve pl_noisy.txt --psf moffat.yaml -o dec_cap.txt --method wiener --cg-max-steps 2 $FAST
expect_ok dec_cap_keep deconvolve pl_noisy.txt --psf moffat.yaml -o dec_cap_keep.txt --method wiener \
    --cg-max-steps 2 --keep-doubtful $FAST
if [ "$(cat rc.dec_cap)" = 3 ] && [ ! -e dec_cap.txt ] && grep -q 'result in doubt: the Wiener solve did not converge' err.dec_cap &&
    grep -q 'warning: .*pl_noisy.txt.*step cap' err.dec_cap_keep && grep -q '"cg_capped": 1' dec_cap_keep.summary.json; then
    pass "deconvolve --cg-max-steps 2: exit 3 and nothing written; kept with --keep-doubtful, warned and recorded"
else
    fail "deconvolve CG cap" "$(cat rc.dec_cap err.dec_cap err.dec_cap_keep) $(grep cg dec_cap_keep.summary.json)"
fi

echo "$n_pass passed, $n_fail failed"
[ "$n_fail" = 0 ]
