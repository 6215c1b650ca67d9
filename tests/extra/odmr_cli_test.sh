#!/bin/sh
# svpsf fit-odmr from the command line, and stacks where one image is expected: a 5-page TIFF
# given as --pl is refused naming its page count; a 100-frame float32 TIFF stack simulated by
# odmr_cli_make's own lines (with noise) is fitted back to the known field within a stated
# tolerance (and σ matches the scatter); its maps feed `svpsf correct` directly, --field-sigma
# included; bad frequencies (a count that differs, named with both counts), a stack of one
# page, and no overwrite without --force.
# Usage: odmr_cli_test.sh SVPSF ODMR_CLI_MAKE [CLI_MD]
set -u
svpsf=$1
make=$2
cli_md=${3:-}
dir=$(mktemp -d "${TMPDIR:-/tmp}/svpsf-odmr.XXXXXX") || exit 1
trap 'rm -rf "$dir"' EXIT
export XDG_CACHE_HOME="$dir/cache"
failures=0
fail() { echo "FAIL: $*"; failures=$((failures + 1)); }

# run EXPECTED_EXIT ARGS...: runs svpsf with ARGS, output in $dir/out and $dir/err
run() {
    expect=$1
    shift
    "$svpsf" "$@" >"$dir/out" 2>"$dir/err"
    code=$?
    if [ "$code" -ne "$expect" ]; then
        fail "svpsf $* exited $code, expected $expect"
        sed 's/^/  stdout: /' "$dir/out"
        sed 's/^/  stderr: /' "$dir/err"
    fi
}
expect_in() { # FILE TEXT
    grep -q -- "$2" "$1" || { fail "'$2' not in $1:"; sed 's/^/  /' "$1"; }
}
cd "$dir" || exit 1

# 1. one image expected: a 5-page TIFF is refused naming the file and the page count; a 1-page
#    TIFF is that image
"$make" pages pages5.tif 5 && "$make" pages pages1.tif 1 || { echo "FAIL: cannot write TIFFs"; exit 1; }
printf '0 0 0\n0 1 0\n0 0 0\n' >delta.txt
awk 'BEGIN {for (y = 0; y < 6; y++) {for (x = 0; x < 8; x++) printf "%s%g", x ? " " : "", 1e-6 * x; print ""}}' >f.txt
run 1 correct --pl pages5.tif --field f.txt --psf delta.txt -o out5
expect_in err "pages5.tif: multi-page TIFF of 5 pages: expected one image"
[ -e out5 ] && fail "out5 was created by a refused run"
run 0 correct --pl pages1.tif --field f.txt --psf delta.txt -o out1 --fft estimate
run 1 deconvolve pages5.tif --method wiener --psf delta.txt -o d5.tif
expect_in err "pages5.tif: multi-page TIFF of 5 pages"

# 2. fit-odmr round trip: 100 frames, 48 x 40 pixels, lines shifted by 0.5 MHz from D
"$make" stack stack.tif freq.txt truth.npy pl_true.npy 48 40 100 1 || { echo "FAIL: cannot write the stack"; exit 1; }
run 0 fit-odmr stack.tif --frequencies freq.txt --lines two --linewidth 4e6 -o fit --format npy --quiet
for m in field field_sigma field_lower field_lower_sigma field_upper field_upper_sigma pl \
         pl_sigma contrast contrast_sigma linewidth linewidth_sigma quality; do
    [ -s "fit/$m.npy" ] || fail "fit/$m.npy not written"
done
[ -s fit/summary.json ] || fail "fit/summary.json not written"
expect_in fit/summary.json '"n_failed": 0'
expect_in fit/summary.json '"lines": "two"'
# σ_B is about 4 uT here: stated tolerance mean 10 uT, max 50 uT; σ within 0.8..1.25 of the scatter
echo "fit-odmr --lines two, field:"
"$make" compare fit/field.npy truth.npy 1 10e-6 50e-6 fit/field_sigma.npy || fail "fit-odmr --lines two: field off"
echo "fit-odmr --lines two, PL:"
"$make" compare fit/pl.npy pl_true.npy 1 1.5 8 fit/pl_sigma.npy || fail "fit-odmr --lines two: PL off"

# the frequencies as START:STOP:N in MHz, the pair model about the shifted D, field in uT:
# the same field within the noise
run 0 fit-odmr stack.tif --frequencies 2750:2990:100 --frequency-unit MHz --zero-field 2.8705e9 \
    --linewidth 4e6 --unit uT -o fit_pair --format npy
expect_in out "fits converged"
echo "fit-odmr --lines pair (uT):"
"$make" compare fit_pair/field.npy truth.npy 1e6 10e-6 50e-6 fit_pair/field_sigma.npy || fail "fit-odmr pair: field off"
# a stack without dips (pages of a smooth pattern): no pixel finds one, a result in doubt (exit
# 3, nothing written; it exited 0 with maps of NaN); the numbers in MHz without their unit are
# refused (14 pixels "converged" to ~100 T with them), and so are negative frequencies (every
# fit "converged" to 0.2 T with them)
"$make" pages nodip.tif 20 || fail "cannot write nodip.tif"
run 3 fit-odmr nodip.tif --frequencies 2.8e9:2.94e9:20 -o fit_none --format npy
expect_in err "none of the 48 pixel fits found a dip in the sweep"
[ -e fit_none ] && fail "fit_none was written by a run in doubt"
# a frame of NaN (a failed frame): every pixel is fitted on its other frames, to the bit as
# the stack without that frame (it made every pixel missing, and the run said "none of the pixel
# fits found a dip ... no light", exit 3)
"$make" nanframe stack.tif nanframe.npy 10 || fail "cannot write nanframe.npy"
"$make" dropframe stack.tif dropframe.npy 10 || fail "cannot write dropframe.npy"
awk 'BEGIN {for (k = 0; k < 100; k++) if (k != 10) printf "%.17g\n", (2750 + k * 240 / 99) * 1e6}' >f_drop.txt
run 0 fit-odmr nanframe.npy --frequencies 2750:2990:100 --frequency-unit MHz -o fit_nan --format npy
run 0 fit-odmr dropframe.npy --frequencies f_drop.txt -o fit_drop --format npy
for m in field field_sigma pl contrast linewidth quality; do
    cmp -s fit_nan/$m.npy fit_drop/$m.npy || fail "a NaN frame: $m differs from the fit without that frame"
done
# ... also through --psf (the frame stays NaN, the others deconvolved as without it: the same
# bits) and --register (it has no say in the drift and gets the polynomial's shift)
printf 'pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.2}\n' >g02.yaml
run 0 fit-odmr nanframe.npy --frequencies 2750:2990:100 --frequency-unit MHz --psf g02.yaml \
    -o fit_nan_psf --format npy
run 0 fit-odmr dropframe.npy --frequencies f_drop.txt --psf g02.yaml -o fit_drop_psf --format npy
cmp -s fit_nan_psf/field.npy fit_drop_psf/field.npy || fail "a NaN frame with --psf: field differs"
run 0 fit-odmr nanframe.npy --frequencies 2750:2990:100 --frequency-unit MHz --register \
    -o fit_nan_reg --format npy
[ "$(wc -l <fit_nan_reg/drift.csv)" -eq 101 ] || fail "a NaN frame with --register: drift.csv rows"
# more than half the frames missing at every pixel: no pixel can be fitted, said so, naming a
# frame of NaN and its frequency; exit 1, nothing written
"$make" nanframe stack.tif nanhalf.npy 0 51 || fail "cannot write nanhalf.npy"
run 1 fit-odmr nanhalf.npy --frequencies 2750:2990:100 --frequency-unit MHz -o fit_half --format npy
expect_in err "nanhalf.npy: ODMR fit: every one of the 1920 pixels holds NaN or Inf in more than 50 of its 100 frames"
expect_in err "(the frame at 2.75 GHz is NaN or Inf at every pixel)"
[ -e fit_half ] && fail "fit_half was written"
run 1 fit-odmr stack.tif --frequencies 2750:2990:100 -o fit_unit --format npy
expect_in err "below 1 MHz where no NV line lies: give their unit with --frequency-unit"
run 1 fit-odmr stack.tif --frequencies -2.99e9:-2.75e9:100 -o fit_neg --format npy
expect_in err "frequencies must be > 0 Hz"
run 1 fit-odmr stack.tif --frequencies 2.75e9:2.99e9:100.5 -o fit_range --format npy
expect_in err "neither a file nor START:STOP:N"
[ -e fit_pair/field_lower.npy ] && fail "field_lower written without --lines two"

# 3. its outputs feed correct, --field-sigma included
run 0 correct --pl fit/pl.npy --field fit/field.npy --field-sigma fit/field_sigma.npy \
    --psf delta.txt -o corr --format npy --fft estimate --quiet
[ -s corr/field.npy ] || fail "correct on fit-odmr's maps wrote no field"

# 3b. --register: a sample that drifts by (0.4, -0.25) px during the sweep (frames rendered
#     analytically at their positions by odmr_cli_make). Without alignment the PL edges moving
#     under a pixel change its PL across the sweep by more than the 3 % dips: measured max error
#     2.6 mT (mean 2.7 uT); aligned, the field is the noise-limited fit at the sweep's mean
#     position (measured max 11.5 uT, mean 2.1 uT; stated tolerances 60 and 10 uT), and
#     drift.csv holds each frame's shift (the first frame at -(0.2, -0.125), the last at
#     +(0.2, -0.125): measured 0.0012 px off, asserted 0.01). A stack of uniform PL has nothing
#     to register on: exit 3, nothing written.
"$make" drift drift.tif dfreq.txt dtruth.npy dpl.npy 64 56 100 3 0.4 -0.25 || { echo "FAIL: cannot write the drifting stack"; exit 1; }
run 0 fit-odmr drift.tif --frequencies dfreq.txt --linewidth 4e6 -o nodrift --format npy --quiet
echo "fit-odmr of a drifting sweep, not aligned (expected far off):"
"$make" compare nodrift/field.npy dtruth.npy 1 10e-6 60e-6 && fail "the drifting sweep fits within the tolerance without --register: the test has no drift to correct"
run 0 fit-odmr drift.tif --frequencies dfreq.txt --linewidth 4e6 --register -o aligned --format npy
expect_in err "frames aligned: largest drift"
echo "fit-odmr --register:"
"$make" compare aligned/field.npy dtruth.npy 1 10e-6 60e-6 || fail "fit-odmr --register: field off"
expect_in aligned/summary.json '"register": 1'
expect_in aligned/summary.json '"drift_degree": 1'
expect_in aligned/summary.json '"align_to": -1'
expect_in aligned/summary.json '"register_max_shift_px"'
expect_in aligned/drift.csv 'frame,frequency_hz,shift_x_px,shift_y_px'
awk -F, 'NR == 2 {e = (($3 + 0.2) ^ 2 + ($4 - 0.125) ^ 2) ^ 0.5}
         NR == 101 {e2 = (($3 - 0.2) ^ 2 + ($4 + 0.125) ^ 2) ^ 0.5}
         END {printf "drift.csv: first frame off by %.4f px, last by %.4f px\n", e, e2;
              exit !(NR == 101 && e < 0.01 && e2 < 0.01)}' aligned/drift.csv || fail "drift.csv shifts off"
# --save-stack: the aligned stack as fitted, a 3-D .npy whose own fit gives the same field bit
# for bit; a name without .npy is refused
run 0 fit-odmr drift.tif --frequencies dfreq.txt --linewidth 4e6 --register --save-stack aligned.npy -o aligned_s --format npy --quiet
run 0 fit-odmr aligned.npy --frequencies dfreq.txt --linewidth 4e6 -o refit --format npy --quiet
cmp -s aligned_s/field.npy refit/field.npy || fail "the saved aligned stack does not fit to the same field"
run 1 fit-odmr drift.tif --frequencies dfreq.txt --register --save-stack aligned.tif -o bad17
expect_in err "--save-stack aligned.tif: the stack is written as a 3-D .npy"
run 1 fit-odmr drift.tif --frequencies dfreq.txt --register --save-stack aligned.npy -o bad18
expect_in err "aligned.npy exists"
# --align-to 0: the frames go to the first frame's position: its shift is 0, the last's
# (0.4, -0.25)
run 0 fit-odmr drift.tif --frequencies dfreq.txt --linewidth 4e6 --register --align-to 0 -o aligned0 --format npy --quiet
awk -F, 'NR == 2 {e = ($3 ^ 2 + $4 ^ 2) ^ 0.5}
         NR == 101 {e2 = (($3 - 0.4) ^ 2 + ($4 + 0.25) ^ 2) ^ 0.5}
         END {printf "--align-to 0: first frame shift %.2g px, last off by %.4f px\n", e, e2;
              exit !(NR == 101 && e < 1e-12 && e2 < 0.01)}' aligned0/drift.csv || fail "--align-to 0: drift.csv shifts off"
run 1 fit-odmr drift.tif --frequencies dfreq.txt --register --align-to 100 -o bad12
expect_in err "--align-to 100: the stack's frames are 0 to 99"
run 1 fit-odmr drift.tif --frequencies dfreq.txt --align-to mean -o bad13
expect_in err "--align-to needs --register"
run 1 fit-odmr drift.tif --frequencies dfreq.txt --drift-degree 2 -o bad9
expect_in err "--drift-degree needs --register"
run 1 fit-odmr drift.tif --frequencies dfreq.txt --register --drift-degree 6 -o bad10
expect_in err "--drift-degree"
# a stack without texture to register on (uniform PL, noise only): exit 3, nothing written
"$make" drift flat.tif ffreq.txt ftruth.npy fpl.npy 32 32 20 5 0 0 || { echo "FAIL: cannot write"; exit 1; }
run 3 fit-odmr flat.tif --frequencies ffreq.txt --register -o bad11
expect_in err "flat.tif: --register: .* frames correlate too weakly with the mean frame to be aligned"

# 3c. --psf: a sweep blurred by the test's own direct convolution with a Gaussian (σ 1.7 px,
#     from a canvas 10 px beyond the view) over a field step of 240 uT, where a blurred pixel
#     holds separated dips. Measured field error, mean / max: the fit of the blurred stack
#     2.1 / 111 uT (one fit failed), T^-1 (`correct`) on its maps 15.4 / 203 uT (its model,
#     the PL-weighted mean field, is not what a fit of mixed dips gives), the fit of the stack
#     deconvolved frame by frame (--psf) 1.05 / 20 uT. Asserted: --psf within 3 / 60 uT, and
#     correct's result not.
"$make" blurred blur.tif bfreq.txt btruth.npy bpl.npy 64 56 60 4 1.7 || { echo "FAIL: cannot write the blurred stack"; exit 1; }
printf 'pixel_um: 1\npsf: {model: gaussian, fwhm_um: 4.003}\n' >gauss.yaml
run 0 fit-odmr blur.tif --frequencies bfreq.txt -o bfit --format npy --failed keep --quiet
run 0 fit-odmr blur.tif --frequencies bfreq.txt --psf gauss.yaml -o bdec --format npy
expect_in bdec/summary.json '"iterations": 75'
expect_in bdec/summary.json '"margin": '
expect_in bdec/summary.json '"deconvolve"'
echo "fit-odmr --psf:"
"$make" compare bdec/field.npy btruth.npy 1 3e-6 60e-6 || fail "fit-odmr --psf: field off"
run 0 correct --pl bfit/pl.npy --field bfit/field.npy --psf gauss.yaml -o bcor --format npy --fft estimate --quiet
echo "correct on the fitted maps (expected outside the tolerance):"
"$make" compare bcor/field.npy btruth.npy 1 3e-6 60e-6 && fail "T^-1 on the fitted maps is as good as --psf: the test shows nothing"
# a PSF map whose four nodes hold that Gaussian: the single PSF's field with --margin 0
# (measured 5e-17 T apart; a map gets no margin unless given)
printf 'pixel_um: 1\nimage: {width: 64, height: 56}\nmodel: gaussian\nkind: grid\nnodes: {nx: 2, ny: 2}\nnode_psfs:\n  - {fwhm_um: 4.003}\n  - {fwhm_um: 4.003}\n  - {fwhm_um: 4.003}\n  - {fwhm_um: 4.003}\n' >gmap.yaml
run 0 fit-odmr blur.tif --frequencies bfreq.txt --psf gmap.yaml -o bmap --format npy --quiet
run 0 fit-odmr blur.tif --frequencies bfreq.txt --psf gauss.yaml --margin 0 --tail-tol 0 -o bdec0 --format npy --quiet
echo "fit-odmr --psf MAP against the single PSF:"
"$make" compare bmap/field.npy bdec0/field.npy 1 1e-12 1e-12 || fail "fit-odmr --psf MAP differs from its single PSF"
# the single PSF with its default --tail-tol: a Gaussian's tail is ~0, so the core's small frame
# serves with nodes that carry almost nothing (docs/model.md §5): the same field to 1e-10 T
run 0 fit-odmr blur.tif --frequencies bfreq.txt --psf gauss.yaml --margin 0 -o bdect --format npy --quiet
grep -q '"deconvolve_tail_step_px": [1-9]' bdect/summary.json || fail "fit-odmr --psf: no tail on a coarse grid taken"
grep -q '"tail_step_px"\|"deconvolve_tail_step_px": 0' bdec0/summary.json || fail "fit-odmr --tail-tol 0: a tail was taken"
echo "fit-odmr --psf with the tail on a coarse grid against the plain frame:"
"$make" compare bdect/field.npy bdec0/field.npy 1 1e-10 1e-10 || fail "fit-odmr --psf: the tail on a coarse grid changed the field"
# with a margin the map's edge PSFs are carried outward (svp_psf_field_pad): the single PSF's
# field with the same margin
run 0 fit-odmr blur.tif --frequencies bfreq.txt --psf gmap.yaml --margin 5 -o bmap5 --format npy --quiet
run 0 fit-odmr blur.tif --frequencies bfreq.txt --psf gauss.yaml --margin 5 --tail-tol 0 -o bdec5 --format npy --quiet
echo "fit-odmr --psf MAP --margin 5 against the single PSF:"
"$make" compare bmap5/field.npy bdec5/field.npy 1 1e-12 1e-12 || fail "fit-odmr --psf MAP --margin 5 differs from its single PSF"
grep -q '"margin": 5' bmap5/summary.json || fail "fit-odmr --psf MAP --margin 5: margin not recorded"
run 1 fit-odmr blur.tif --frequencies bfreq.txt --iterations 10 -o bad14
expect_in err "--iterations needs --psf"
run 1 fit-odmr blur.tif --frequencies bfreq.txt --psf nosuch.yaml -o bad15
expect_in err "nosuch.yaml"

# 4. bad input and no overwrite
run 1 fit-odmr stack.tif --frequencies 2750:2990:99 --frequency-unit MHz -o bad1
expect_in err "2750:2990:99: 99 frequencies for a stack of 100 frames (stack.tif)"
head -n 99 freq.txt >freq99.txt
run 1 fit-odmr stack.tif --frequencies freq99.txt -o bad2
expect_in err "freq99.txt: 99 frequencies for a stack of 100 frames (stack.tif)"
run 1 fit-odmr pages5.tif --frequencies 1:5:5 -o bad3 --lines two
expect_in err "pages5.tif: 5 frames: a Lorentzian fit (--lines two) needs at least 6"
# a stack of one page (or one 2-D image): too few frequencies, before the frequencies are read
run 1 fit-odmr pages1.tif --frequencies 2.87e9 -o bad7
expect_in err "svpsf fit-odmr: pages1.tif: 1 frame: a Lorentzian fit (--lines pair) needs at least 5 (one per frequency)"
run 1 fit-odmr f.txt --frequencies 1:5:5 -o bad8
expect_in err "f.txt: 1 frame: a Lorentzian fit"
run 1 fit-odmr stack.tif --frequencies freq.txt --line lower -o bad4
expect_in err "--line lower needs --lines one"
run 1 fit-odmr stack.tif -o bad5
expect_in err "--frequencies is required"
awk 'NR == 50 {print 2.9e9; next} {print}' freq.txt >freq_bad.txt
run 1 fit-odmr stack.tif --frequencies freq_bad.txt -o bad6
expect_in err "freq_bad.txt: not monotonic"
for d in bad1 bad2 bad3 bad4 bad5 bad6 bad7 bad8 bad9 bad10 bad11 bad12 bad13 bad14 bad15 bad16 bad17 bad18; do [ -e "$d" ] && fail "$d was created by a refused run"; done
cp fit/field.npy field.before
run 1 fit-odmr stack.tif --frequencies freq.txt --lines two -o fit --format npy --quiet
expect_in err "fit/field.npy exists, and 13 more of the 14 outputs (use --force to overwrite)"
cmp -s fit/field.npy field.before || fail "fit/field.npy changed without --force"

# 5. --help and the reference (docs/cli.md, section `svpsf fit-odmr`) name the same options
if [ -n "$cli_md" ] && [ -r "$cli_md" ]; then
    "$svpsf" fit-odmr --help >help.txt || fail "fit-odmr --help exited $?"
    grep -o -- '--[a-z][a-z-]*' help.txt | sort -u >help_opts
    awk '/^## `svpsf fit-odmr`/ {f = 1; next} /^## / {f = 0} f' "$cli_md" >section.md
    [ -s section.md ] || fail "no fit-odmr section in $cli_md"
    grep -o -- '--[a-z][a-z-]*' section.md | sort -u >doc_opts
    # common options the reference names once for all commands
    for o in --help --quiet --threads --format --force --output; do echo "$o"; done | sort -u >common_opts
    missing=$(comm -23 help_opts doc_opts | comm -23 - common_opts)
    extra=$(comm -13 help_opts doc_opts | grep -v -e '^--field-sigma$' -e '^--pl$' -e '^--field$' \
        -e '^--psf$' -e '^--balance$')
    [ -z "$missing" ] || fail "in fit-odmr --help but not in docs/cli.md: $missing"
    [ -z "$extra" ] || fail "in docs/cli.md's fit-odmr section but not in --help: $extra"
else
    echo "SKIP (part): no docs/cli.md given: --help not compared with the reference"
fi

if [ "$failures" -ne 0 ]; then
    echo "$failures failure(s)"
    exit 1
fi
echo "all fit-odmr checks passed"
