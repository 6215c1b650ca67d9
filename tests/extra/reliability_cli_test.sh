#!/bin/sh
# Inputs that once hung or crashed a reader (docs/reliability.md): every one must end, within a
# time limit, with exit 1 and a message naming the file and the fault. A hang fails the check
# (timeout) instead of blocking the suite. Also replays the regression inputs kept beside the
# fuzz targets (tests/fuzz/regressions/<target>/*) through the CLI command that reads them.
#   usage: reliability_cli_test.sh /path/to/svpsf /path/to/tests/fuzz/regressions
# POSIX sh; prints one line per check and "N passed, M failed"; exits nonzero on any failure.
set -u

S=${1:?usage: reliability_cli_test.sh /path/to/svpsf REGRESSIONS_DIR}
REG=${2:-}
case $S in /*) ;; *) S=$PWD/$S ;; esac
case $REG in /* | '') ;; *) REG=$PWD/$REG ;; esac
WORK=$(mktemp -d "${TMPDIR:-/tmp}/svpsf-rel.XXXXXX")
trap 'rm -rf "$WORK"' EXIT
cd "$WORK" || exit 1
export OMP_NUM_THREADS=1
LIMIT=20 # seconds: every case below takes milliseconds; a hang is stopped here

n_pass=0
n_fail=0
pass() { n_pass=$((n_pass + 1)); echo "ok    $1"; }
fail() { n_fail=$((n_fail + 1)); echo "FAIL  $1: $2"; }

# expect_refused NAME "TEXT|TEXT..." CMD...: exits 1 within LIMIT s, stderr has every TEXT
expect_refused() {
    name=$1 texts=$2
    shift 2
    timeout -s KILL "$LIMIT" "$S" "$@" >out.txt 2>err.txt
    rc=$?
    if [ "$rc" = 137 ] || [ "$rc" = 124 ]; then
        fail "$name" "still running after $LIMIT s (a hang)"
        return
    fi
    if [ "$rc" != 1 ]; then
        fail "$name" "exit $rc (expected 1): $(head -c 300 err.txt)"
        return
    fi
    old_ifs=$IFS
    IFS='|'
    for t in $texts; do
        if ! grep -qF -- "$t" err.txt; then
            IFS=$old_ifs
            fail "$name" "message lacks '$t': $(head -c 300 err.txt)"
            return
        fi
    done
    IFS=$old_ifs
    pass "$name"
}

# expect_ends NAME CMD...: ends within LIMIT s with exit 0 or 1 (a clean refusal), never a
# crash (signal), an internal error (4) or a hang
expect_ends() {
    name=$1
    shift
    timeout -s KILL "$LIMIT" "$S" "$@" >out.txt 2>err.txt
    rc=$?
    case $rc in
    0 | 1) pass "$name" ;;
    137 | 124) fail "$name" "still running after $LIMIT s (a hang)" ;;
    *) fail "$name" "exit $rc: $(head -c 300 err.txt)" ;;
    esac
}

printf '1 2\n3 4\n' >f.txt
printf '1 1\n1 1\n' >pl.txt
printf 'pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.3}\n' >good.yaml

# the 2-byte files libfyaml 0.7.12 loops on, and a PDF given by mistake
printf '%%\350' >dir1.yaml
printf '%%\377\377m' >dir2.yaml
printf '%%PDF-1.4\n%%\342\343\317\323\n1 0 obj\n<< /Type /Catalog >>\nendobj\n' >doc.pdf
cp doc.pdf pdf.yaml # a PDF saved under a YAML name
printf 'pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.3\001}\n' >ctrl.yaml

for f in dir1.yaml dir2.yaml pdf.yaml ctrl.yaml; do
    case $f in dir1.yaml) off=1 ;; dir2.yaml) off=1 ;; pdf.yaml) off=10 ;; ctrl.yaml) off=49 ;; esac
    expect_refused "psf $f" "$f: not a text file|byte offset $off" psf "$f" -o k.npy
    expect_refused "correct --psf $f" "$f: not a text file|byte offset $off" \
        correct --field f.txt --pl pl.txt --psf "$f" -o corr --fft estimate
    expect_refused "forward --psf $f" "$f: not a text file|byte offset $off" \
        forward --field f.txt --pl pl.txt --psf "$f" -o fwd --fft estimate
    expect_refused "simulate $f" "$f: not a text file|byte offset $off" simulate "$f" -o sim
    expect_refused "map-psf $f" "$f: not a text file|byte offset $off" map-psf "$f" -o map.yaml
done
# a PDF under its own name: the PSF readers pick by extension and refuse it
expect_refused "correct --psf doc.pdf" "doc.pdf|unknown image format" \
    correct --field f.txt --pl pl.txt --psf doc.pdf -o corr --fft estimate
expect_refused "simulate doc.pdf" "doc.pdf: not a text file|byte offset 10" simulate doc.pdf -o sim
for d in k.npy corr fwd sim map.yaml; do
    if [ -e "$d" ]; then fail "no output after a refusal" "$d exists"; fi
done

# a file over the 16 MiB limit is refused before it is parsed
awk 'BEGIN { for (i = 0; i < 600000; i++) printf "# a comment line of thirty bytes\n" }' >big.yaml
expect_refused "psf: over 16 MiB" "big.yaml|larger than the 16 MiB" psf big.yaml -o k.npy

# the good file still reads (the check does not refuse YAML text, UTF-8 included)
printf '# \303\251t\303\251 \342\200\224 caf\303\251\npixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.3}\n' >utf8.yaml
timeout -s KILL "$LIMIT" "$S" psf utf8.yaml -o k_utf8.npy >/dev/null 2>err.txt &&
    pass "UTF-8 comments are text" || fail "UTF-8 comments are text" "$(cat err.txt)"

# the size limits and the memory budget of the image readers (docs/reliability.md): checked
# from the header, before the decoder allocates anything
DEC="deconvolve --psf good.yaml --method wiener --fft estimate -o dec.npy"
cp "$REG/tiff/opencv-3gb-allocation.tif" huge.tif 2>/dev/null &&
    expect_refused "TIFF claiming 12090 x 65282 float32 (3 GB)" \
        "huge.tif: 12090 x 65282 pixels: larger than an image may be|268435456 pixels" $DEC huge.tif
# PNG headers (IHDR) of 20000 x 20000 and 10000 x 10000 16-bit gray, no pixel data
printf '\211PNG\r\n\032\n\000\000\000\015IHDR\000\000\116\040\000\000\116\040\020\000\000\000\000\226\213\305\246\000\000\000\000IEND\256\102\140\202' >huge.png
printf '\211PNG\r\n\032\n\000\000\000\015IHDR\000\000\047\020\000\000\047\020\020\000\000\000\000\317\265\341\270\000\000\000\000IEND\256\102\140\202' >big.png
expect_refused "PNG claiming 20000 x 20000" "huge.png: 20000 x 20000 pixels: larger than an image may be" $DEC huge.png
# 10000 x 10000 x (2 bytes as decoded + 8 as float64) = 954 MiB: within the size limit, not
# within a 256 MiB budget
export SVPSF_MAX_MEMORY=256M
expect_refused "PNG of 10000 x 10000 over SVPSF_MAX_MEMORY=256M" \
    "big.png: decoding the PNG needs 953.7 MiB of memory, more than the 256.0 MiB allowed (SVPSF_MAX_MEMORY=256M" \
    $DEC big.png
# a 400 x 400 float64 .npy (1.2 MiB of data) takes 2.4 MiB to read: over 2M
SVPSF_MAX_MEMORY=2M
{ printf '\223NUMPY\001\000\166\000'
  printf "{'descr': '<f8', 'fortran_order': False, 'shape': (400, 400), }%*s\n" 54 ''
  head -c 1280000 /dev/zero; } >z.npy
expect_refused "npy over SVPSF_MAX_MEMORY=2M" \
    "z.npy: reading the array as float64 needs 2.4 MiB of memory, more than the 2.0 MiB allowed" \
    $DEC z.npy
# 3 million numbers of text: the value buffer's growth past 2^21 numbers is checked
SVPSF_MAX_MEMORY=24M
awk 'BEGIN { for (y = 0; y < 1500; y++) { l = ""; for (x = 0; x < 2000; x++) l = l "0 "; print l } }' >z.txt
expect_refused "text over SVPSF_MAX_MEMORY=24M" "z.txt: reading its numbers needs|more than the 24.0 MiB allowed" $DEC z.txt
# a PSF map's operator is estimated before it is built: 64 tent nodes on a frame of at least
# 399 x 399 pixels (no support: the whole view), 2 x 64 x 8 x 399^2 bytes, and 10 images
awk 'BEGIN { for (y = 0; y < 200; y++) { l = ""; for (x = 0; x < 200; x++) l = l "1 "; print l } }' >f200.txt
printf 'pixel_um: 0.1\nimage: {width: 200, height: 200}\nkind: poly\nmodel: gaussian\ndegree: 1\ncoefficients: {fwhm_um: [0.4, 0.05, 0.0]}\n' >map200.yaml
SVPSF_MAX_MEMORY=64M
expect_refused "PSF-map operator over SVPSF_MAX_MEMORY=64M" \
    "map200.yaml: building the space-variant operator (64 tent nodes on a frame of at least 399 x 399 pixels) needs 158.5 MiB of memory, more than the 64.0 MiB allowed" \
    forward --field f200.txt --pl f200.txt --psf map200.yaml --nodes 8x8 -o fwd200 --fft estimate
[ -e fwd200 ] && fail "no output after a refusal" "fwd200 exists"
# one PSF (no support: the whole view): the kernel, three frames of at least 399 x 399 and
# twelve 200 x 200 images, about 8.5 MiB, over 2M; the inputs themselves fit
printf 'pixel_um: 0.1\npsf: {model: moffat, fwhm_um: 0.4, beta: 1.5}\n' >one200.yaml
SVPSF_MAX_MEMORY=2M
expect_refused "invariant operator over SVPSF_MAX_MEMORY=2M" \
    "one200.yaml: the blur operator and its deconvolutions (a frame of at least 399 x 399 pixels) needs 8.5 MiB of memory, more than the 2.0 MiB allowed" \
    correct --field f200.txt --pl f200.txt --psf one200.yaml --margin 0 -o cor200 --fft estimate
[ -e cor200 ] && fail "no output after a refusal" "cor200 exists"
SVPSF_MAX_MEMORY=lots
expect_refused "SVPSF_MAX_MEMORY=lots" "SVPSF_MAX_MEMORY=lots is not a memory size" $DEC z.txt
unset SVPSF_MAX_MEMORY
[ -e dec.npy ] && fail "no output after a refusal" "dec.npy exists"

# impossible parameters are exit 1 naming the key; options that would be ignored are refused
printf 'pixel_um: 0.1\npsf: {model: moffat, fwhm_um: 0.3, beta: 1e-9}\n' >beta.yaml
expect_refused "Moffat beta 1e-9" "beta.yaml:2:|beta must be >= 0.5" psf beta.yaml -o k.npy
printf 'pixel_um: 1e-300\npsf: {model: gaussian, fwhm_um: 0.3}\n' >px.yaml
expect_refused "pixel_um 1e-300" "px.yaml:1:11|pixel_um must be >= 1e-06" psf px.yaml -o k.npy
expect_refused "fit-psf --pixel-um 1e-300" "--pixel-um 1e-300|must be >= 1e-06" \
    fit-psf f.txt --pixel-um 1e-300 -o fit.yaml
printf 'pixel_um: 0.1\nmodel: moffat\nkind: uniform\npsf: {fwhm_um: 0.6, beta: 0.01}\n' >mapbeta.yaml
expect_refused "PSF map: Moffat beta 0.01" "mapbeta.yaml:4:|beta must be >= 0.5" \
    correct --field f.txt --pl pl.txt --psf mapbeta.yaml -o corr --fft estimate
expect_refused "correct --method r --balance" "--balance|--method r" \
    correct --field f.txt --pl pl.txt --psf good.yaml -o corr --method r --balance 0.1 --fft estimate
expect_refused "deconvolve --method rl --balance" "--balance|--method rl" \
    deconvolve f.txt --psf good.yaml -o d.npy --method rl --balance 0.1 --fft estimate
printf '0.1 0.2\n0.3 0.4\n' >even.txt
timeout -s KILL "$LIMIT" "$S" deconvolve f.txt --psf even.txt -o d_even.npy --method wiener \
    --fft estimate >/dev/null 2>err.txt
if [ $? = 0 ] && grep -qF "even.txt: the kernel is 2 x 2: an even side has no middle pixel" err.txt; then
    pass "an even-sized kernel is named in a warning"
else
    fail "an even-sized kernel is named in a warning" "$(cat err.txt)"
fi

# a run killed (SIGTERM, SIGKILL) at several points, writing over the outputs of an earlier run
# with --force: every file under a final name is whole (the earlier one or the new one, byte for
# byte), and no earlier output is removed (outputs are written to a hidden temporary name and
# renamed; docs/reliability.md)
awk 'BEGIN { for (y = 0; y < 384; y++) { l = ""; for (x = 0; x < 384; x++)
    l = l sprintf("%.3f ", sin(x * 0.05) * cos(y * 0.07)); print l } }' >big_f.txt
awk 'BEGIN { for (y = 0; y < 384; y++) { l = ""; for (x = 0; x < 384; x++) l = l "1 "; print l } }' >big_pl.txt
printf 'pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.8}\n' >wide.yaml
KILLRUN="correct --field big_f.txt --pl big_pl.txt --format npy --method r --iterations 30 --fft estimate --quiet"
"$S" $KILLRUN --psf wide.yaml -o old >/dev/null 2>&1 && "$S" $KILLRUN --psf good.yaml -o new >/dev/null 2>&1
if [ $? != 0 ] || [ ! -f old/field.npy ] || [ ! -f new/field.npy ]; then
    fail "killed runs" "the reference runs failed"
else
    n_stale=0
    for sig in TERM KILL; do
        for delay in 0.1 0.4 0.7 0.9 1.0 1.2; do
            rm -rf k
            cp -r old k
            "$S" $KILLRUN --psf good.yaml -o k --force >/dev/null 2>&1 &
            pid=$!
            sleep "$delay"
            kill -s "$sig" "$pid" 2>/dev/null
            wait "$pid" 2>/dev/null
            bad=""
            # summary.json records times: whole means one JSON object, closed
            whole() { if [ "$1" = summary.json ]; then
                [ "$(head -c 1 "k/$1")" = "{" ] && [ "$(tail -c 2 "k/$1")" = "}" ]
            else cmp -s "k/$1" "old/$1" || cmp -s "k/$1" "new/$1"; fi; }
            for f in old/*; do
                b=$(basename "$f")
                if [ ! -f "k/$b" ]; then bad="$bad $b removed;"; continue; fi
                whole "$b" || bad="$bad $b partial;"
            done
            for f in k/*; do
                b=$(basename "$f")
                [ -f "new/$b" ] || [ -f "old/$b" ] || bad="$bad $b unexpected;"
                if [ -f "new/$b" ] && [ ! -f "old/$b" ]; then
                    whole "$b" || bad="$bad $b partial;"
                fi
            done
            # SIGTERM: the handler removes the temporary files; SIGKILL cannot be caught and
            # may leave one, named .<output>.svpsf-tmp-<pid>-XXXXXX
            temps=$(find k -name '.*.svpsf-tmp-*' | wc -l)
            if [ "$sig" = TERM ] && [ "$temps" != 0 ]; then
                bad="$bad $temps temporary file(s) left: $(ls -A k | tr '\n' ' ');"
            fi
            if [ "$sig" = KILL ]; then n_stale=$((n_stale + temps)); fi
            if [ -z "$bad" ]; then
                pass "SIG$sig after $delay s: every output whole, none removed, $temps temporary file(s) left"
            else
                fail "SIG$sig after $delay s" "$bad"
            fi
        done
    done
fi

# a signal while an output is being written: the writer is stopped (SIGSTOP) as soon as its
# temporary file appears, then sent the signal. SIGTERM, SIGHUP (and SIGINT, SIGQUIT, but a
# shell starts background jobs with those ignored): the handler removes the temporary file and
# the earlier output stays; SIGKILL: the temporary file stays (it cannot be caught) and the
# next run writing the same output removes it.
printf 'earlier kernel\n' >earlier.npy
# mid_write SIG: 0 when the writer was caught mid-write and sent SIG (up to 3 tries)
mid_write() {
    for try in 1 2 3; do
        rm -rf mw && mkdir mw && cp earlier.npy mw/k.npy
        "$S" psf good.yaml -o mw/k.npy --size 2049 --force --quiet >/dev/null 2>&1 &
        pid=$!
        tmp=""
        while kill -0 "$pid" 2>/dev/null; do
            tmp=$(find mw -name '.k.npy.svpsf-tmp-*' | head -n 1)
            [ -n "$tmp" ] && break
        done
        if [ -n "$tmp" ] && kill -s STOP "$pid" 2>/dev/null && [ -f "$tmp" ] &&
            cmp -s mw/k.npy earlier.npy; then
            kill -s "$1" "$pid"
            kill -s CONT "$pid"
            wait "$pid" 2>/dev/null
            return 0
        fi
        wait "$pid" 2>/dev/null
    done
    return 1
}
# a signal ignored when this test starts (nohup ignores SIGHUP) stays ignored in the program
# (docs/cli.md): the writer then finishes and replaces the output whole
ignored() { case $1 in HUP) bit=0 ;; TERM) bit=14 ;; *) return 1 ;; esac
    mask=$(awk '/^SigIgn:/ { print $2 }' /proc/$$/status 2>/dev/null)
    [ -n "$mask" ] && [ $(( (0x$mask >> bit) & 1 )) = 1 ]; }
for sig in TERM HUP KILL; do
    if [ "$sig" != KILL ] && ignored "$sig"; then
        if ! mid_write "$sig"; then
            fail "SIG$sig (ignored here) mid-write" "the writer was never caught (3 tries)"
        elif [ "$(wc -c <mw/k.npy)" -gt 33000000 ] &&
            [ "$(find mw -name '.k.npy.svpsf-tmp-*' | wc -l)" = 0 ]; then
            pass "SIG$sig mid-write, ignored in this environment: the writer went on, output whole"
        else
            fail "SIG$sig (ignored here) mid-write" "the output is not the whole new one"
        fi
        continue
    fi
    if ! mid_write "$sig"; then
        fail "SIG$sig mid-write" "the writer was never caught with its temporary file (3 tries)"
        continue
    fi
    left=$(find mw -name '.k.npy.svpsf-tmp-*' | wc -l)
    if ! cmp -s mw/k.npy earlier.npy; then
        fail "SIG$sig mid-write" "the earlier output was replaced or removed"
    elif [ "$sig" != KILL ] && [ "$left" != 0 ]; then
        fail "SIG$sig mid-write" "$left temporary file(s) left"
    elif [ "$sig" = KILL ] && [ "$left" != 1 ]; then
        fail "SIG$sig mid-write" "expected the temporary file to stay, found $left"
    else
        pass "SIG$sig mid-write: earlier output intact, $left temporary file(s) left"
    fi
done
# the run after the SIGKILL: removes the dead writer's temporary file, writes the output whole
timeout -s KILL "$LIMIT" "$S" psf good.yaml -o mw/k.npy --size 2049 --force --quiet >/dev/null 2>err.txt
rc=$?
left=$(find mw -name '.k.npy.svpsf-tmp-*' | wc -l)
if [ $rc = 0 ] && [ "$left" = 0 ] && [ "$(wc -c <mw/k.npy)" -gt 33000000 ]; then
    pass "the next run removes the killed run's temporary file"
else
    fail "the next run removes the killed run's temporary file" "exit $rc, $left left: $(head -c 300 err.txt)"
fi
rm -rf mw

# what a SIGKILL leaves: the next run writing the same outputs removes temporary files whose
# process is gone, and keeps those of a live process (it may still be writing) and other files
if [ -f old/field.npy ]; then
    rm -rf k && cp -r old k
    sh -c 'exit 0' &
    dead=$!
    wait "$dead"
    while kill -0 "$dead" 2>/dev/null; do dead=$((dead + 100000)); done
    : >"k/.field.npy.svpsf-tmp-$dead-aB3xYz"
    : >"k/.summary.json.svpsf-tmp-$dead-Qw3rTy"
    : >"k/.field.npy.svpsf-tmp-$$-live01"
    : >"k/.field.npy.tmp-someone-else"
    "$S" $KILLRUN --psf good.yaml -o k --force >/dev/null 2>err.txt
    rc=$?
    left=$(cd k && ls -A | grep -F svpsf-tmp | tr '\n' ' ')
    if [ $rc = 0 ] && [ "$left" = ".field.npy.svpsf-tmp-$$-live01 " ] &&
        [ -f k/.field.npy.tmp-someone-else ] && cmp -s k/field.npy new/field.npy; then
        pass "stale temporary files of a dead process removed, a live one's kept"
    else
        fail "stale temporary files" "exit $rc, left: $left $(head -c 300 err.txt)"
    fi
fi

# inputs the fuzzers found (tests/fuzz/regressions/<target>/), through the CLI
if [ -n "$REG" ] && [ -d "$REG" ]; then
    for f in "$REG"/*/*; do
        [ -f "$f" ] || continue
        t=$(basename "$(dirname "$f")")
        b=$(basename "$f")
        case $t in
        psf) cp "$f" in.yaml && expect_ends "fuzz psf $b" psf in.yaml -o "k_$b.npy" ;;
        psf_map) cp "$f" in.yaml && expect_ends "fuzz psf_map $b" \
            correct --field f.txt --pl pl.txt --psf in.yaml -o "c_$b" --fft estimate ;;
        scene) cp "$f" in.yaml && expect_ends "fuzz scene $b" simulate in.yaml --dry-run ;;
        spots) cp "$f" in.yaml && expect_ends "fuzz spots $b" map-psf in.yaml -o "m_$b.yaml" ;;
        npy) cp "$f" in.npy && expect_ends "fuzz npy $b" deconvolve in.npy --psf good.yaml -o "d_$b.npy" --method wiener --fft estimate ;;
        txt) cp "$f" in.txt && expect_ends "fuzz txt $b" deconvolve in.txt --psf good.yaml -o "d_$b.npy" --method wiener --fft estimate ;;
        tiff) cp "$f" in.tif && expect_ends "fuzz tiff $b" deconvolve in.tif --psf good.yaml -o "d_$b.npy" --method wiener --fft estimate ;;
        png) cp "$f" in.png && expect_ends "fuzz png $b" deconvolve in.png --psf good.yaml -o "d_$b.npy" --method wiener --fft estimate ;;
        stack) case $(head -c 2 "$f") in II | MM) e=tif ;; *) e=npy ;; esac
            cp "$f" "in_stack.$e" && expect_ends "fuzz stack $b" \
                fit-odmr "in_stack.$e" --frequencies 2.80:2.94:5 -o "o_$b" ;;
        mat) cp "$f" in.mat && expect_ends "fuzz mat $b" deconvolve in.mat --psf good.yaml -o "d_$b.npy" --method wiener --fft estimate ;;
        wisdom) cp "$f" in.wisdom && expect_ends "fuzz wisdom $b" \
            forward --field f.txt --pl pl.txt --psf good.yaml -o "w_$b" --wisdom in.wisdom ;;
        esac
    done
fi

echo "$n_pass passed, $n_fail failed"
[ "$n_fail" = 0 ]
