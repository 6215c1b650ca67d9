#!/bin/sh
# svpsf register from the command line: transform found and printed, transform files (JSON,
# YAML), a label mask warped onto the reference grid, a mask whose regions are dark in the PL
# (inverted contrast, detected or --invert), results in doubt (exit 3), exit codes, and no
# overwrite without --force. Usage: register_cli_test.sh SVPSF REGISTER_CLI_MAKE
set -u
svpsf=$1
make=$2
dir=$(mktemp -d "${TMPDIR:-/tmp}/svpsf-register.XXXXXX") || exit 1
trap 'rm -rf "$dir"' EXIT
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

"$make" "$dir" || { echo "FAIL: cannot write the test images"; exit 1; }
cd "$dir" || exit 1

# 1. phase correlation: the printed shift is the one rendered, (+2.4, -1.3) px
run 0 register ref.npy mov.npy
expect_in out "x_moving = 1 x_ref +0 y_ref +"
shift=$(awk '$1 == "shift" {print $2, $3}' out)
echo "phase correlation shift: $shift (rendered +2.4 -1.3)"
echo "$shift" | awk '{ex = $1 - 2.4; ey = $2 + 1.3; exit !(ex * ex + ey * ey < 0.05 * 0.05)}' ||
    fail "shift $shift is not (+2.4, -1.3) within 0.05 px"

# 2. transform file (JSON via -o), refused the second time, replaced with --force
run 0 register ref.npy mov.npy -o t.json
[ -s t.json ] || fail "t.json not written"
expect_in t.json '"affine"'
expect_in t.json '"shift_px"'
expect_in t.json '"low_significance": false'
cp t.json t.before
run 1 register ref.npy mov.npy -o t.json
expect_in err "t.json exists (use --force to overwrite)"
cmp -s t.json t.before || fail "t.json changed without --force"
run 0 register ref.npy mov.npy -o t.json --force --method ecc --motion translation
expect_in t.json '"method": "ecc"'

# 3. YAML transform file next to a warped label mask
run 0 register ref.npy mov.npy --warp mov_mask.npy -o warped.npy --transform-out t.yaml
expect_in out "nearest interpolation (integer pixels: a label mask)"
expect_in t.yaml "affine:"
expect_in t.yaml "method: phase"
"$make" compare warped.npy ref_mask.npy || fail "the warped mask differs from the reference mask"
run 1 register ref.npy mov.npy --warp mov_mask.npy -o warped.npy
expect_in err "warped.npy exists (use --force to overwrite)"

# 4. ECC affine (the default motion for ecc)
run 0 register ref.npy mov.npy --method ecc
expect_in out "ECC, affine"
# ... that runs out of iterations: exit 2, nothing written
run 2 register ref.npy mov.npy --method ecc --iterations 2 --epsilon 1e-15 -o never.json
expect_in err "did not converge after 2 iterations"
[ -e never.json ] && fail "never.json written by a failed run"

# 5. bad input and bad usage: exit 1 with the file or option named
run 1 register ref.npy wide.npy
expect_in err "size mismatch: reference ref.npy is 96 x 80"
run 1 register ref.npy flat.npy
expect_in err "flat.npy is constant"
run 1 register ref.npy missing.npy
expect_in err "missing.npy"
run 1 register ref.npy
expect_in err "REFERENCE and MOVING images are required"
run 1 register ref.npy mov.npy --motion affine
expect_in err "--motion affine needs --method ecc"
run 1 register ref.npy mov.npy --warp mov_mask.npy
expect_in err "needs -o OUT"
run 1 register ref.npy mov.npy -o t.txt
expect_in err "needs a .json, .yaml or .yml name"
run 1 register ref.npy mov.npy --method fft
expect_in err "--method: unknown value 'fft'"

# 6. unrelated images: a result in doubt, printed, exit 3, nothing written; with
# --keep-doubtful written with a warning and flagged in the transform file
run 3 register ref.npy other.npy -o doubt.json
expect_in err "the phase-correlation peak is not significant"
expect_in err "nothing written"
expect_in out "significance"
[ -e doubt.json ] && fail "doubt.json written by a run in doubt"
run 0 register ref.npy other.npy -o doubt.json --keep-doubtful
expect_in err "warning: the phase-correlation peak is not significant"
expect_in doubt.json '"low_significance": true'
# featureless pair (two unrelated white-noise images): exit 3, also with --warp
run 3 register noise_a.npy noise_b.npy --warp mov_mask.npy -o never.npy
expect_in err "noise_b.npy onto noise_a.npy: the phase-correlation peak is not significant"
[ -e never.npy ] && fail "never.npy written by a run in doubt"

# 7. a label mask whose regions are dark in the PL (a metal wire, 70 % absorbing, on a Gaussian
# beam with 2 % noise), the mask displaced by (+4.6, -2.3) px: the inverted contrast is
# detected and the shift recovered within 0.5 px (the mask's pixel edges alone round it by up
# to 0.4 px); the transform file says so
check_wire_shift() { # what
    s=$(awk '$1 == "shift" {print $2, $3}' out)
    echo "wire mask, $1: shift $s (rendered +4.6 -2.3)"
    echo "$s" | awk '{ex = $1 - 4.6; ey = $2 + 2.3; exit !(ex * ex + ey * ey < 0.5 * 0.5)}' ||
        fail "$1: shift $s is not (+4.6, -2.3) within 0.5 px"
}
run 0 register wire_pl.npy wire_mask.npy --transform-out wire.json --warp wire_mask.npy \
    -o wire_warped.npy
expect_in out "contrast    inverted (detected"
check_wire_shift "detected"
expect_in wire.json '"contrast": "inverted"'
expect_in wire.json '"low_significance": false'
"$make" compare wire_warped.npy wire_ref_mask.npy ||
    fail "the warped wire mask differs from the mask on the PL's grid"
run 0 register wire_pl.npy wire_mask.npy --invert
expect_in out "contrast    inverted (--invert)"
check_wire_shift "--invert"
run 0 register wire_pl.npy wire_mask.npy --method ecc --motion translation
check_wire_shift "ECC"
# the same contrast forced: the peak is not significant (what the sign-blind search reported
# with exit 0): exit 3
run 3 register wire_pl.npy wire_mask.npy --no-invert
expect_in err "not significant"
run 1 register wire_pl.npy wire_mask.npy --invert --no-invert
expect_in err "--invert and --no-invert: give one"
# an ordinary pair keeps its contrast
run 0 register ref.npy mov.npy
expect_in out "contrast    same (detected"

if [ "$failures" -ne 0 ]; then
    echo "$failures check(s) failed"
    exit 1
fi
echo "register CLI: all checks passed"
