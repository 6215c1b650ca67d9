#!/bin/sh
# MATLAB .mat files from the command line (docs/cli.md, MATLAB / QDMlab files): QDMlab's
# Bz_uc0.mat and B111dataToPlot.mat, written by mat_cli_make with libmatio, feed `correct` with
# results identical to the same arrays given as .npy; `--format mat` and `-o OUT.mat:VAR` outputs
# hold the same values (read back by svpsf and, when Debian's /usr/bin/python3 has scipy, by
# scipy.io.loadmat); `reconstruct` takes the pixel size and stand-off from the file; `fit-odmr`
# from QDMlab's raw run_00000.mat and from a 3-D variable gives the maps of the same stack as
# .npy; refusals exit 1 naming the file and the fault; no overwrite without --force.
# Usage: mat_cli_test.sh SVPSF MAT_CLI_MAKE
set -u
svpsf=$1
make=$2
dir=$(mktemp -d "${TMPDIR:-/tmp}/svpsf-mat.XXXXXX") || exit 1
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
same() { # A B: every value equal
    "$make" compare "$1" "$2" || fail "$1 and $2 differ"
}
cd "$dir" || exit 1
"$make" qdm . 40 32 || { echo "FAIL: cannot write the QDMlab files"; exit 1; }
cat >psf.yaml <<'YAML'
pixel_um: 4.7
psf:
  model: gaussian
  fwhm_um: 9.4
YAML

# 1. correct from Bz_uc0.mat (Bz by default, newLED named) == correct from the same arrays as .npy
common="--psf psf.yaml --fft estimate --threads 1 --quiet"
run 0 correct --field Bz_uc0.mat --pl Bz_uc0.mat:newLED $common -o outm --format npy
run 0 correct --field Bz.npy --pl led.npy $common -o outn --format npy
for m in field pl validity; do same "outm/$m.npy" "outn/$m.npy"; done
expect_in outm/summary.json 'Bz_uc0.mat:newLED'
# B111dataToPlot.mat: B111ferro by default; two fields from one file get distinct names
run 0 correct --field B111dataToPlot.mat:B111ferro --field B111dataToPlot.mat:B111para \
    --pl B111dataToPlot.mat:ledImg $common -o outb --format npy
[ -s outb/field_B111dataToPlot_B111ferro.npy ] && [ -s outb/field_B111dataToPlot_B111para.npy ] ||
    { fail "outb: field_<file>_<VAR> outputs missing"; ls outb; }

# a file's `step` against the PSF file's pixel size: another scale is refused, naming both
sed 's/pixel_um: 4.7/pixel_um: 0.47/' psf.yaml >psf_small.yaml
run 1 correct --field Bz_uc0.mat --pl led.npy --psf psf_small.yaml -o outs --quiet
expect_in err 'field Bz_uc0.mat holds `step` = 4.7 um (its pixel size), but the PSF file psf_small.yaml is for pixels of 0.47 um'
[ -e outs ] && fail "outs was created by a refused run"
run 1 deconvolve Bz_uc0.mat:newLED --psf psf_small.yaml --method rl -o outs.npy --quiet
expect_in err 'image Bz_uc0.mat:newLED holds `step` = 4.7 um'
[ -e outs.npy ] && fail "outs.npy was created by a refused run"
sed 's/pixel_um: 4.7/pixel_um: 4.72/' psf.yaml >psf_near.yaml # within 1 %: taken
run 0 correct --field Bz_uc0.mat --pl led.npy --psf psf_near.yaml -o outnear --quiet --format npy

# 2. --format mat: one variable per file, named after it, the same values as the .npy run
run 0 correct --field Bz_uc0.mat --pl Bz_uc0.mat:newLED $common -o outmat --format mat
for m in field pl validity; do same "outmat/$m.mat" "outn/$m.npy"; done
"$make" info outmat/field.mat >info.txt || fail "outmat/field.mat unreadable"
expect_in info.txt '^field 40 32 0 0$'
# -o OUT.mat:VAR names the variable (deconvolve); the summary beside OUT
run 0 deconvolve Bz_uc0.mat --method wiener $common -o dec.mat:Bz
"$make" info dec.mat >info.txt || fail "dec.mat unreadable"
expect_in info.txt '^Bz 40 32 '
[ -s dec.summary.json ] || fail "dec.summary.json not written"
run 0 deconvolve Bz.npy --method wiener $common -o decn.npy
same dec.mat decn.npy
# no overwrite without --force; --force replaces
run 1 deconvolve Bz_uc0.mat --method wiener $common -o dec.mat:Bz
expect_in err 'dec.mat exists, and 1 more of the 2 outputs (use --force to overwrite)'
run 0 deconvolve Bz_uc0.mat --method wiener $common -o dec.mat:Bz --force

# 3. scipy.io.loadmat reads svpsf's .mat as svpsf wrote it (skipped without scipy)
if /usr/bin/python3 -c 'import numpy, scipy.io' 2>/dev/null; then
    /usr/bin/python3 - <<'PY' || fail "scipy.io.loadmat cross-check"
import numpy as np, scipy.io as sio, sys
ok = True
for mat, var, npy in [("outmat/field.mat", "field", "outn/field.npy"),
                      ("outmat/pl.mat", "pl", "outn/pl.npy"),
                      ("dec.mat", "Bz", "decn.npy"),
                      ("Bz_uc0.mat", "Bz", "Bz.npy")]:
    d = sio.loadmat(mat)
    names = sorted(k for k in d if not k.startswith("__"))
    a, b = d[var], np.load(npy)
    if a.shape != b.shape or a.dtype != np.float64 or not np.array_equal(a, b, equal_nan=True):
        print(f"FAIL: {mat}:{var} {a.shape} {a.dtype} differs from {npy} {b.shape}")
        ok = False
    else:
        print(f"scipy.io.loadmat({mat})[{var!r}] == {npy}: {a.shape}, every value; variables {names}")
sys.exit(0 if ok else 1)
PY
else
    echo "SKIP: /usr/bin/python3 has no numpy/scipy: no scipy.io.loadmat cross-check"
fi

# 4. reconstruct: pixel size (step, m) and stand-off (h, m) from the Bz file
run 0 reconstruct --quantity magnetisation --bz Bz_uc0.mat -o rec --format npy --quiet
expect_in rec/summary.json '"pixel_um": 4.7'
expect_in rec/summary.json '"standoff_nm": 5000'
run 0 reconstruct --quantity magnetisation --bz Bz.npy --pixel-um 4.7 --standoff-nm 5000 \
    -o recn --format npy --quiet
same rec/m_z.npy recn/m_z.npy
run 1 reconstruct --quantity magnetisation --bz B111dataToPlot.mat -o rec2
expect_in err '--pixel-um is required (the map file holds no pixel size)'
run 1 reconstruct --quantity magnetisation --bz Bz_steps.mat -o rec3
expect_in err '--pixel-um is required: Bz_steps.mat holds `step` with 2 elements, not one pixel size (one number, or \[dx dy\] of square pixels)'
[ -e rec3 ] && fail "rec3 was created by a refused run"
run 0 reconstruct --quantity magnetisation --bz Bz_steps.mat --pixel-um 4.7 -o rec3 \
    --format npy --quiet
same rec/m_z.npy rec3/m_z.npy
run 1 reconstruct --quantity magnetisation --bz Bz_stepchar.mat --standoff-nm 5000 -o rec4
expect_in err '--pixel-um is required: Bz_stepchar.mat holds `step`, but not as a real number'
[ -e rec4 ] && fail "rec4 was created by a refused run"

# 5. refusals: exit 1, the file and the fault named, nothing written
run 1 correct --field Bz_uc0.mat:nope --pl led.npy $common -o bad1
expect_in err "Bz_uc0.mat: no variable 'nope' (the file holds: Bz (32 x 40 double), Bt (32 x 40 double), h (1 x 1 double), step (1 x 1 double), corners (2 x 2 double), newLED (32 x 40 double))"
[ -e bad1 ] && fail "bad1 was created by a refused run"
run 1 correct --field Bz_uc0.mat:1x --pl led.npy $common -o bad2
expect_in err "Bz_uc0.mat:1x: '1x' is not a MATLAB variable name"
head -c 100 Bz_uc0.mat >short.mat
run 1 deconvolve short.mat --method wiener $common -o bad3.npy
expect_in err 'short.mat: not a MATLAB .mat file (shorter than the 128-byte MAT-file header)'
head -c 400 Bz_uc0.mat >cut.mat
run 1 deconvolve cut.mat --method wiener $common -o bad4.npy
expect_in err 'cut.mat: truncated: data element 1 (at byte 128) needs [0-9]* bytes, the file ends at 400'
run 1 correct --field Bz_uc0.mat --pl Bz_uc0.mat:corners $common -o bad5
expect_in err 'size mismatch'

# 6. fit-odmr from QDMlab's raw run_00000.mat (imgStack1) and from a 3-D variable: the same maps
#    as from the same stack as a 3-D .npy
"$make" odmr . 12 10 41 || { echo "FAIL: cannot write the ODMR stacks"; exit 1; }
fit="--frequencies 2.84e9:2.90e9:41 --linewidth 4e6 --threads 1 --format npy --quiet"
run 0 fit-odmr stack.npy $fit -o fitn
run 0 fit-odmr run_00000.mat $fit -o fitr
run 0 fit-odmr stack3.mat:odmr $fit -o fit3
for m in field pl contrast linewidth quality; do
    same "fitr/$m.npy" "fitn/$m.npy"
    same "fit3/$m.npy" "fitn/$m.npy"
done
expect_in fitn/summary.json '"n_failed": 0'
# with --psf the stack's `step` is compared with the PSF file's pixel size, as for correct
run 1 fit-odmr stack3.mat:odmr $fit --psf psf_small.yaml -o fit3s
expect_in err 'stack stack3.mat:odmr holds `step` = 4.7 um (its pixel size), but the PSF file psf_small.yaml'
[ -e fit3s ] && fail "fit3s was created by a refused run"
run 0 fit-odmr stack3.mat:odmr $fit --psf psf.yaml --iterations 5 -o fit3p
# one image expected: the raw stack is refused naming its frame count
run 1 deconvolve run_00000.mat:imgStack1 --method wiener $common -o bad6.npy
expect_in err 'run_00000.mat: variable imgStack1 is a stack of 41 frames (QDMlab.s raw layout, 10 x 12 pixels): expected one image'

if [ "$failures" -ne 0 ]; then
    echo "$failures failure(s)"
    exit 1
fi
echo "mat-cli: all checks passed"
