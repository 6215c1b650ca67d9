#!/bin/sh
# `meson install` into a temporary folder (DESTDIR) and use what it installed, as a user would:
# docs/api.md's example built with `pkg-config --cflags --libs svpsf` and run against the
# installed libsvpsf.so.MAJOR (its SONAME); the man page rendered (man -l, else groff, else
# only found); docs/ and the scenes where `svpsf --help` says they are; the installed program;
# the Python package imported from the installed site directory over the installed library.
# usage: install_test.sh BUILD_DIR EXAMPLE_C PREFIX LIBDIR MANDIR DOCDIR PYDIR SONAME
set -u
BUILD=$1 EXAMPLE=$2 PREFIX=$3 LIBDIR=$4 MANDIR=$5 DOCDIR=$6 PYDIR=$7 SONAME=$8
T=$(mktemp -d)
trap 'rm -rf "$T"' EXIT
fails=0
ok() { echo "ok: $*"; }
bad() { echo "FAIL: $*"; fails=$((fails + 1)); }

if ! meson install -C "$BUILD" --destdir "$T/root" --no-rebuild --quiet >"$T/install.log" 2>&1; then
    cat "$T/install.log"
    echo "FAIL: meson install"
    exit 1
fi
R=$T/root$PREFIX
case $LIBDIR in /*) L=$T/root$LIBDIR ;; *) L=$R/$LIBDIR ;; esac
case $MANDIR in /*) M=$T/root$MANDIR ;; *) M=$R/$MANDIR ;; esac

# the library: versioned file, SONAME symlink, development symlink, SONAME inside
[ -L "$L/libsvpsf.so" ] && [ -L "$L/$SONAME" ] && ok "libsvpsf.so -> $SONAME symlinks" ||
    bad "symlinks libsvpsf.so / $SONAME missing in $L: $(ls "$L" | tr '\n' ' ')"
soname=$(objdump -p "$L/$SONAME" 2>/dev/null | awk '$1 == "SONAME" {print $2}')
[ "$soname" = "$SONAME" ] && ok "SONAME $soname" || bad "SONAME is '$soname', expected $SONAME"
[ -f "$R/include/svpsf.h" ] && ok "header installed" || bad "no $R/include/svpsf.h"

# pkg-config from the installed .pc, its prefix moved to where DESTDIR put it
export PKG_CONFIG_PATH="$L/pkgconfig"
if flags=$(pkg-config --define-variable=prefix="$R" --cflags --libs svpsf); then
    ok "pkg-config --cflags --libs svpsf: $flags"
    case $flags in *"-I$R/include"*) ok "cflags point at the installed header" ;;
                   *) bad "cflags '$flags' do not name $R/include" ;; esac
    # shellcheck disable=SC2086
    if ${CC:-cc} -std=c11 -o "$T/example" "$EXAMPLE" $flags -lm 2>"$T/cc.log"; then
        ok "docs/api.md's example builds with pkg-config"
        if LD_LIBRARY_PATH="$L" OMP_NUM_THREADS=2 "$T/example" >"$T/ex.out" 2>&1; then
            ok "the example runs: $(tail -n 1 "$T/ex.out")"
        else
            bad "the example failed: $(cat "$T/ex.out")"
        fi
        lib=$(LD_LIBRARY_PATH="$L" ldd "$T/example" | awk '/libsvpsf/ {print $3}')
        [ "$lib" = "$L/$SONAME" ] && ok "the example loads the installed $SONAME" ||
            bad "the example loads '$lib', not $L/$SONAME"
    else
        bad "the example does not build: $(cat "$T/cc.log")"
    fi
else
    bad "pkg-config does not find svpsf in $L/pkgconfig"
fi
# the numerics alone: the same example (it calls only the core) built with
# `pkg-config svpsf_core`, run against the installed libsvpsf_core, which loads no OpenCV,
# cairo or YAML library (docs/architecture.md §Layers)
if flags=$(pkg-config --define-variable=prefix="$R" --cflags --libs svpsf_core); then
    # shellcheck disable=SC2086
    if ${CC:-cc} -std=c11 -o "$T/example_core" "$EXAMPLE" $flags -lm 2>"$T/cc.log"; then
        if LD_LIBRARY_PATH="$L" OMP_NUM_THREADS=2 "$T/example_core" >"$T/ex.out" 2>&1; then
            ok "the example links libsvpsf_core alone and runs: $(tail -n 1 "$T/ex.out")"
        else
            bad "the example on libsvpsf_core failed: $(cat "$T/ex.out")"
        fi
        libs=$(LD_LIBRARY_PATH="$L" ldd "$T/example_core" | awk '{print $1}' | tr '\n' ' ')
        case $libs in
            *libsvpsf_core.so.*) ;;
            *) bad "the core example does not load libsvpsf_core: $libs" ;;
        esac
        case $libs in
            *opencv* | *cairo* | *yaml* | *fontconfig* | *"libsvpsf.so"*)
                bad "the core example loads more than the numerics: $libs" ;;
            *) ok "the core example loads no OpenCV, cairo, YAML or libsvpsf" ;;
        esac
    else
        bad "the example does not build against svpsf_core: $(cat "$T/cc.log")"
    fi
else
    bad "pkg-config does not find svpsf_core in $L/pkgconfig"
fi
[ "$(pkg-config --modversion svpsf)" = "$(LD_LIBRARY_PATH="$L" "$R/bin/svpsf" --version | awk 'NR == 1 {print $2}')" ] &&
    ok "pkg-config version = svpsf --version" || bad "pkg-config and svpsf --version disagree"

# the man page
page="$M/man1/svpsf.1"
if [ -f "$page" ]; then
    ok "man page installed"
    if command -v man >/dev/null 2>&1; then
        MANWIDTH=100 man -l "$page" >"$T/man.txt" 2>"$T/man.err"
        render="man -l"
    elif command -v groff >/dev/null 2>&1; then
        groff -man -Tutf8 "$page" >"$T/man.txt" 2>"$T/man.err"
        render="groff"
    else
        render=""
        ok "(neither man nor groff: the page is not rendered)"
    fi
    if [ -n "$render" ]; then
        if grep -q "SYNOPSIS" "$T/man.txt" && grep -q "SVPSF CORRECT" "$T/man.txt" &&
            grep -q -- "--pl-floor" "$T/man.txt" && [ ! -s "$T/man.err" ]; then
            ok "$render renders it ($(wc -l <"$T/man.txt") lines, every command's section)"
        else
            bad "$render: $(head -c 300 "$T/man.err")"
        fi
    fi
else
    bad "no man page at $page"
fi

# docs and scenes where the installed program's --help says they are
help_dir=$("$R/bin/svpsf" --help | tail -n 1 | sed 's/^ *//')
[ "$help_dir" = "$DOCDIR" ] && ok "svpsf --help names $DOCDIR" || bad "svpsf --help names '$help_dir'"
for f in cli.md model.md api.md scenes.md scenes/micromagnet-chessboard-lorentzian-1um.yaml; do
    [ -f "$T/root$DOCDIR/$f" ] || bad "$DOCDIR/$f not installed"
done
"$R/bin/svpsf" simulate --help | tr '\n' ' ' | grep -q "$DOCDIR" &&
    ok "svpsf simulate --help names the installed scenes" || bad "simulate --help lacks $DOCDIR"
if "$R/bin/svpsf" simulate "$T/root$DOCDIR/scenes/micromagnet-chessboard-lorentzian-1um.yaml" \
    --dry-run >/dev/null 2>"$T/sim.err"; then
    ok "an installed scene checks (simulate --dry-run)"
else
    bad "installed scene: $(cat "$T/sim.err")"
fi

# the Python package from the installed site directory, over the installed library
case $PYDIR in
"") ok "(no Python package installed: no Python 3 with cffi and numpy)" ;;
*)
    P=$T/root${PYDIR%/}
    case $PREFIX in
    /usr | /usr/local)
        /usr/bin/python3 -c 'import sys; sys.exit(sys.argv[1].rstrip("/") not in sys.path)' "$PYDIR" &&
            ok "$PYDIR is on /usr/bin/python3's sys.path (import svpsf works once installed)" ||
            bad "$PYDIR is not on /usr/bin/python3's sys.path" ;;
    esac
    if [ -f "$P/svpsf/__init__.py" ] && [ -f "$P/svpsf/svpsf.h" ]; then
        ok "Python package installed in $PYDIR"
        grep -q "LIBRARY = \"$LIBDIR/$SONAME\"\|LIBRARY = \"$PREFIX/$LIBDIR/$SONAME\"" "$P/svpsf/_config.py" &&
            ok "_config.py names the installed library" || bad "_config.py: $(cat "$P/svpsf/_config.py")"
        if out=$(cd "$T" && env -u SVPSF_HEADER PYTHONPATH="$P" SVPSF_LIBRARY="$L/$SONAME" \
            /usr/bin/python3 -c 'import numpy as np, svpsf
p = svpsf.PSF("moffat", fwhm=3.0, beta=2.0)
a = svpsf.forward(np.ones((32, 32)), np.ones((32, 32)), p)
assert abs(a.fields[16, 16] - 1) < 1e-12
print(svpsf.version(), svpsf.HEADER, svpsf.LIBRARY)' 2>&1); then
            case $out in *"$P/svpsf/svpsf.h"*) ok "installed package works: $out" ;;
                         *) bad "the package read another header: $out" ;; esac
        else
            bad "installed package: $out"
        fi
    else
        bad "Python package not installed in $P"
    fi
    ;;
esac

echo "$fails failure(s)"
[ "$fails" -eq 0 ]
