#!/bin/sh
# Runs every shipped scene of the reference study and writes the tables of
# docs/reference-study.md from their summary.json files.
#   docs/scenes/run-study.sh [SVPSF [OUT]]
#   docs/scenes/run-study.sh --support [SVPSF [OUT]]
#   docs/scenes/run-study.sh --tables-only [OUT]     (the tables from an earlier run)
# --support: every scene that reconstructs magnetisation does it by the support method
# (`reconstruct: {quantity: magnetisation, method: support}`, docs/model.md §11) instead of the
# Fourier method; the scenes run from copies in a temporary folder; OUT defaults to
# out/study-support.
# SVPSF: the svpsf program (default build/tools/svpsf/svpsf), OUT: the output folder (default
# out/study). Each scene goes to OUT/<scene name>/ (report.md, figures/, tables/, summary.json);
# the tables go to OUT/tables.md. About 5 minutes on 2 idle cores (the corrections-* scenes
# run seven corrections each). Python 3 (standard library only)
# formats the tables.
set -eu
HERE=$(cd "$(dirname "$0")" && pwd)
if [ "${1:-}" = --tables-only ]; then
    OUT=${2:-out/study}
else
    SUPPORT=
    if [ "${1:-}" = --support ]; then
        SUPPORT=$(mktemp -d)
        trap 'rm -rf "$SUPPORT"' EXIT
        shift
    fi
    SVPSF=${1:-build/tools/svpsf/svpsf}
    OUT=${2:-out/study${SUPPORT:+-support}}
    mkdir -p "$OUT"
    for scene in "$HERE"/*.yaml; do
        name=$(basename "$scene" .yaml)
        echo "== $name" >&2
        if [ -n "$SUPPORT" ]; then
            sed 's/^reconstruct: magnetisation$/reconstruct: {quantity: magnetisation, method: support}/' \
                "$scene" >"$SUPPORT/$name.yaml"
            scene=$SUPPORT/$name.yaml
        fi
        "$SVPSF" simulate "$scene" -o "$OUT/$name" --force --quiet
    done
fi
python3 - "$OUT" >"$OUT/tables.md" <<'EOF'
import json, math, os, sys

out = sys.argv[1]
S = {}
for name in sorted(os.listdir(out)):
    p = os.path.join(out, name, "summary.json")
    if os.path.exists(p):
        with open(p) as f:
            S[name] = json.load(f)

def v(name, key):
    x = S[name]["results"].get(key)
    return float("nan") if x is None else x

def f(x, fmt="%.3g"):
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else fmt % x

def total(name):
    return S[name]["timings_s"]["total"]

print("## Micromagnet: 3 emission patterns x 5 PSFs\n")
print("m_z = M_z t inside the flake (mask `flake`: the 100 µm square eroded by 2 µm). "
      "Reductions: 1 − mean|m_z| / mean|m_z,true| and 1 − peak|m_z| / peak|m_z,true| of the "
      "apparent map; medians of |relative error| (histogram medians) before (apparent) and "
      "after correction. B_z: peak reduction over the whole view.\n")
print("| emission | PSF | m_z mean red. % | m_z peak red. % | B_z peak red. % (view) | "
      "median abs err. % apparent | R&W | R | default | time (s) |")
print("|---|---|---|---|---|---|---|---|---|---|")
for em in ["uniform", "spot", "chessboard"]:
    for psf in ["gaussian-300nm", "gaussian-1um", "gaussian-300nm-halo", "lorentzian-300nm",
                "lorentzian-1um"]:
        n = "micromagnet-%s-%s" % (em, psf)
        if n not in S:
            continue
        print("| %s | %s | %s | %s | %s | %s | %s | %s | %s | %.1f |" % (
            em, psf,
            f(v(n, "m_z/flake/apparent/mean_reduction_pct")),
            f(v(n, "m_z/flake/apparent/peak_reduction_pct")),
            f(v(n, "B_z/view/apparent/peak_reduction_pct")),
            f(v(n, "m_z/flake/apparent/median_abs_rel_err_pct")),
            f(v(n, "m_z/flake/corrected_rw/median_abs_rel_err_pct")),
            f(v(n, "m_z/flake/corrected_r/median_abs_rel_err_pct")),
            f(v(n, "m_z/flake/corrected_default/median_abs_rel_err_pct")), total(n)))

def corrections(n, quantities, masks):
    versions = ["apparent"] + ["corrected_" + c["name"] for c in S[n]["settings"]["corrections"]]
    print("| quantity | mask | version | mean | mean red. % | peak red. % | median err. % | "
          "median abs err. % | p95 abs err. % |")
    print("|---|---|---|---|---|---|---|---|---|")
    for q, scale, unit in quantities:
        for m in masks:
            t = v(n, "%s/%s/true/mean" % (q, m))
            print("| %s | %s | true | %s %s | | | | | |" % (q, m, f(t * scale, "%.4g"), unit))
            for ver in versions:
                k = "%s/%s/%s/" % (q, m, ver)
                print("| %s | %s | %s | %s %s | %s | %s | %s | %s | %s |" % (
                    q, m, ver, f(v(n, k + "mean") * scale, "%.4g"), unit,
                    f(v(n, k + "mean_reduction_pct")), f(v(n, k + "peak_reduction_pct")),
                    f(v(n, k + "median_rel_err_pct")), f(v(n, k + "median_abs_rel_err_pct")),
                    f(v(n, k + "p95_abs_rel_err_pct"))))
    print()

for n, qs, ms in [
        ("micromagnet-chessboard-lorentzian-1um", [("m_z", 1e3, "mA"), ("B_z", 1e6, "µT")],
         ["flake", "lit_flake", "outside"]),
        ("strip-chessboard-lorentzian-1um", [("J_bxy", 1, "A/m"), ("J_bz", 1, "A/m"),
                                             ("B_x", 1e6, "µT")], ["strip", "middle"]),
        ("device-wire-on-ramp", [("J_bxy", 1, "A/m"), ("J_bz", 1, "A/m"), ("B_x", 1e6, "µT")],
         ["wire", "beside_wire"])]:
    if n not in S:
        continue
    print("\n## %s: corrections compared (%.1f s)\n" % (n, total(n)))
    corrections(n, qs, ms)

print("\n## What the corrections do: settings compared\n")
print("The same apparent maps corrected with the study's settings (R&W and W with Wiener balance "
      "1, RL 15 iterations) and others; margin 10 µm (light from outside the view enters it, as "
      "in a measurement) or 0. m_z inside the flake (mask `flake`); low validity: the share of pixels whose recovered PL fell below the "
      "floor.\n")
print("| scene | margin (µm) | correction | method | RL iterations | balance | m_z median abs "
      "err. % | m_z p95 abs err. % | m_z mean red. % | low validity % |")
print("|---|---|---|---|---|---|---|---|---|---|")
for n in ["corrections-uniform-gaussian-1um", "corrections-uniform-gaussian-1um-no-margin",
          "corrections-chessboard-lorentzian-1um",
          "corrections-chessboard-lorentzian-1um-no-margin"]:
    if n not in S:
        continue
    margin = S[n]["geometry"]["margin_px"] * S[n]["geometry"]["pixel_um"]
    print("| %s | %s | apparent | – | – | – | %s | %s | %s | – |" % (
        n, f(margin), f(v(n, "m_z/flake/apparent/median_abs_rel_err_pct")),
        f(v(n, "m_z/flake/apparent/p95_abs_rel_err_pct")),
        f(v(n, "m_z/flake/apparent/mean_reduction_pct"))))
    for c in S[n]["settings"]["corrections"]:
        k = "corrected_" + c["name"]
        m = c["method"]
        print("| %s | %s | %s | %s | %s | %s | %s | %s | %s | %s |" % (
            n, f(margin), c["name"], m.upper().replace("RW", "R&W"),
            c["iterations"] if m != "w" else "–", f(c["balance"]) if m != "r" else "–",
            f(v(n, "m_z/flake/%s/median_abs_rel_err_pct" % k)),
            f(v(n, "m_z/flake/%s/p95_abs_rel_err_pct" % k)),
            f(v(n, "m_z/flake/%s/mean_reduction_pct" % k)),
            f(100 * v(n, "correct/%s/low_validity_fraction" % c["name"]))))

print("\n## Iterations and acceleration: what the default's count costs and gains\n")
print("The default correction (R, margin auto, single precision) with plain Richardson-Lucy at "
      "30, 50, 75 (the default) and 150 iterations and with Biggs-Andrews acceleration at 15, "
      "25 and 40, on the same apparent maps of three scenes: the flagship without noise, with "
      "shot noise (1e4 photons at the brightest pixel) and chessboard emission under a Gaussian "
      "300 nm PSF with a halo. m_z inside the flake (mask `flake`), B_z over the view "
      "(relative to its peak); time: the correction's wall time on 2 threads, its operator's "
      "build included (`correct/<name>/seconds`).\n")
print("| scene | correction | acceleration | RL iterations | m_z median abs err. % | "
      "B_z median abs err. % (view) | time (s) |")
print("|---|---|---|---|---|---|---|")
for n in ["corrections-iterations-chessboard-lorentzian-1um", "corrections-iterations-noise-1e4",
          "corrections-iterations-gaussian-300nm-halo"]:
    if n not in S:
        continue
    print("| %s | apparent | – | – | %s | %s | – |" % (
        n, f(v(n, "m_z/flake/apparent/median_abs_rel_err_pct")),
        f(v(n, "B_z/view/apparent/median_abs_rel_err_pct"))))
    for c in S[n]["settings"]["corrections"]:
        k = "corrected_" + c["name"]
        print("| %s | %s | %s | %d | %s | %s | %s |" % (
            n, c["name"], c.get("acceleration", "none"), c["iterations"],
            f(v(n, "m_z/flake/%s/median_abs_rel_err_pct" % k)),
            f(v(n, "B_z/view/%s/median_abs_rel_err_pct" % k)),
            f(v(n, "correct/%s/seconds" % c["name"]), "%.2f")))

import array, ast, struct

def npy(name, map_name):
    """A float64 .npy map written by the scene (stdlib only)."""
    with open(os.path.join(out, name, "maps", map_name + ".npy"), "rb") as fh:
        if fh.read(6) != b"\x93NUMPY":
            raise ValueError("not a .npy file")
        major = fh.read(2)[0]
        n = struct.unpack("<H" if major == 1 else "<I", fh.read(2 if major == 1 else 4))[0]
        header = ast.literal_eval(fh.read(n).decode("latin1"))
        assert header["descr"] == "<f8" and not header["fortran_order"]
        a = array.array("d")
        a.frombytes(fh.read())
        return a

def rms_diff(a, b, mask=None):
    s, k = 0.0, 0
    for i in range(len(a)):
        if mask is None or mask[i] != 0:
            s += (a[i] - b[i]) ** 2
            k += 1
    return math.sqrt(s / k) if k else float("nan")

print("\n## Noise: the flagship scene at falling photon counts\n")
print("Shot noise with N photons at the brightest pixel over the whole measurement: the PL "
      "gets sqrt(N) noise, the field 0.77 Γ / (γ C sqrt(N)) (Γ = 1 MHz, C = 2 %), larger in dim "
      "pixels as 1/sqrt(PL). The noise part is the rms difference from the same scene without "
      "noise (micromagnet-noise-none): B_z over the view in % of the peak |B_z|, m_z inside the "
      "flake in % of 1 mA. Total: the median |relative error| of m_z inside the flake against "
      "the truth.\n")
print("| photons N | field SNR at the brightest pixel | sigma_B there (µT) | B_z noise, apparent "
      "% | B_z noise, corrected R % | m_z noise, R&W % | m_z noise, R % | m_z total, apparent % "
      "| R&W % | R % |")
print("|---|---|---|---|---|---|---|---|---|---|")
ref = "micromagnet-noise-none"
rows = sorted((v(n, "noise/photons_per_pixel"), n) for n in S
              if n.startswith("micromagnet-noise-") and n != ref)
if ref in S:
    mask = npy(ref, "mask_flake")
    peak = max(abs(x) for x in npy(ref, "B_z_true"))
    base = {m: npy(ref, m) for m in ["B_z_apparent", "B_z_corrected_r", "m_z_corrected_rw",
                                     "m_z_corrected_r"]}
    print("| no noise | ∞ | 0 | 0 | 0 | 0 | 0 | %s | %s | %s |" % (
        f(v(ref, "m_z/flake/apparent/median_abs_rel_err_pct")),
        f(v(ref, "m_z/flake/corrected_rw/median_abs_rel_err_pct")),
        f(v(ref, "m_z/flake/corrected_r/median_abs_rel_err_pct"))))
    for photons, n in sorted(rows, reverse=True):
        noise = [100 * rms_diff(npy(n, "B_z_apparent"), base["B_z_apparent"]) / peak,
                 100 * rms_diff(npy(n, "B_z_corrected_r"), base["B_z_corrected_r"]) / peak,
                 100 * rms_diff(npy(n, "m_z_corrected_rw"), base["m_z_corrected_rw"], mask) / 1e-3,
                 100 * rms_diff(npy(n, "m_z_corrected_r"), base["m_z_corrected_r"], mask) / 1e-3]
        print("| %.0e | %s | %s | %s | %s | %s | %s | %s | %s | %s |" % (
            photons, f(v(n, "noise/field_snr")), f(1e6 * v(n, "noise/sigma_B_at_brightest_T")),
            f(noise[0]), f(noise[1]), f(noise[2]), f(noise[3]),
            f(v(n, "m_z/flake/apparent/median_abs_rel_err_pct")),
            f(v(n, "m_z/flake/corrected_rw/median_abs_rel_err_pct")),
            f(v(n, "m_z/flake/corrected_r/median_abs_rel_err_pct"))))

print("\n## The ODMR cube against the closed form\n")
print("| scene | estimator | mean abs diff (µT) | max abs diff (µT) | where contrast varies "
      "(mean µT) | elsewhere (mean µT) | m_z median abs err. % apparent | R | cube + "
      "estimate time (s) |")
print("|---|---|---|---|---|---|---|---|---|")
for n in ["spectrum-centroid", "spectrum-fit", "spectrum-fit-contrast", "spectrum-drift"]:
    if n not in S:
        continue
    est = [p["detail"] for p in S[n]["plan"] if p["stage"] == "estimate"][0].split(" per")[0]
    t = sum(p["seconds"] for p in S[n]["plan"] if p["stage"] in ("cube", "drift", "estimate"))
    print("| %s | %s | %s | %s | %s | %s | %s | %s | %.1f |" % (
        n, est, f(1e6 * v(n, "cube_vs_closed_form/B_z/mean_abs_T")),
        f(1e6 * v(n, "cube_vs_closed_form/B_z/max_abs_T")),
        f(1e6 * v(n, "cube_vs_closed_form/B_z/contrast_varies/mean_abs_T")),
        f(1e6 * v(n, "cube_vs_closed_form/B_z/contrast_uniform/mean_abs_T")),
        f(v(n, "m_z/flake/apparent/median_abs_rel_err_pct")),
        f(v(n, "m_z/flake/corrected_r/median_abs_rel_err_pct")), t))

if "spectrum-fit" in S and "spectrum-fit-contrast" in S:
    a = npy("spectrum-fit-contrast", "B_z_apparent")
    b = npy("spectrum-fit", "B_z_apparent")
    c = npy("spectrum-fit-contrast", "B_z_closed_form")
    peak = max(abs(x) for x in npy("spectrum-fit", "B_z_true"))
    print("\nThe contrast pattern's own effect on the fitted map: rms %.3g µT, max %.3g µT "
          "(%.2g %% and %.2g %% of the peak |B_z| = %.3g µT); the fit against the closed form "
          "with uniform contrast: rms %.3g µT." % (
              1e6 * rms_diff(a, b), 1e6 * max(abs(x - y) for x, y in zip(a, b)),
              100 * rms_diff(a, b) / peak, 100 * max(abs(x - y) for x, y in zip(a, b)) / peak,
              1e6 * peak, 1e6 * rms_diff(b, npy("spectrum-fit", "B_z_closed_form"))))

print("\n## The default correction against none\n")
print("`default` is `svpsf correct`'s defaults (R, 75 RL iterations, margin auto, single-precision "
      "transforms). For every scene with corrections: the scene's headline quantity and mask, "
      "its median |relative error| apparent and after the default correction, and how many of "
      "the scene's (quantity, mask) pairs the default leaves worse than the apparent map.\n")
print("| scene | quantity / mask | apparent % | default % | default / apparent | pairs worse |")
print("|---|---|---|---|---|---|")
HEADLINE = [("m_z", "flake"), ("J_bxy", "middle"), ("J_bxy", "wire"), ("B_z", "view")]
n_worse = 0
for n in S:
    names = [c["name"] for c in S[n]["settings"].get("corrections", [])]
    if "default" not in names or n.startswith("corrections-iterations-"):
        continue  # the iterations scenes repeat scenes of the study with other corrections
    res = S[n]["results"]
    pairs = sorted({tuple(k.split("/")[:2]) for k in res
                    if k.endswith("/corrected_default/median_abs_rel_err_pct")})
    worse = [p for p in pairs
             if v(n, "%s/%s/corrected_default/median_abs_rel_err_pct" % p) >
             v(n, "%s/%s/apparent/median_abs_rel_err_pct" % p)]
    head = next((p for p in HEADLINE if p in pairs), pairs[0] if pairs else None)
    if head is None:
        continue
    a = v(n, "%s/%s/apparent/median_abs_rel_err_pct" % head)
    d = v(n, "%s/%s/corrected_default/median_abs_rel_err_pct" % head)
    n_worse += d > a
    print("| %s | %s / %s | %s | %s | %s | %d of %d%s |" % (
        n, head[0], head[1], f(a), f(d), f(d / a if a else float("nan"), "%.2f"), len(worse),
        len(pairs), ": " + ", ".join("%s/%s" % p for p in worse) if worse else ""))
print("\nScenes whose headline error the default correction makes worse: %d." % n_worse)

print("\n## Run times\n")
print("| scene | view | stages | total (s) | slowest stage |")
print("|---|---|---|---|---|")
for n in S:
    g = S[n]["geometry"]
    slow = max(S[n]["plan"], key=lambda p: p["seconds"])
    print("| %s | %d x %d (canvas %d x %d) | %d | %.1f | %s %.1f s |" % (
        n, g["view_width"], g["view_height"], g["canvas_width"], g["canvas_height"],
        len(S[n]["plan"]), total(n), slow["stage"], slow["seconds"]))
EOF
echo "tables: $OUT/tables.md" >&2
