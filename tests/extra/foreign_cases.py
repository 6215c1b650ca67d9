#!/usr/bin/python3
"""T⁻¹ on foreign data (docs/model.md §3): the cases a new user met, rebuilt from their
description with an independent numpy forward model (tools/bench/foreign.py), run through the
svpsf program, and judged against the truth.

usage: foreign_cases.py SVPSF

1. 512², Moffat 0.6 µm β 1.1, field peak 40 µT: `--method rw --balance auto` (the former default
   method with an automatic balance) once wrote a field of ±1.7e6 µT with exit 0. It must now
   exit 2 or 3, or be sound. The same command without --method (now R, which has no balance)
   is a usage error naming the option.
2. 384², light from a 6 µm margin, the PSF 5 % wider than the file says (the file's FWHM is
   the true one / 1.05), Poisson PL of ~1000 photons, fit noise of 1 µT at the lit peak growing
   as 1/√PL where dark, NaN pixels: the default correction must beat the uncorrected map in
   dark and in lit regions, and (its margin domain, --margin auto by default) keep the error in
   the 2 µm band at the view's edge within 2 × the interior's. (With 0.3 µT, the benchmark's level, the former default R&W beat
   the uncorrected map too, so the case would not tell the two apart; with 1 µT its dark error
   is 0.87 against the uncorrected 0.83.)
3. The same data with `--method w --balance auto` once returned ≈ 0 everywhere with exit 0: it
   must exit 2 or 3, or be sound.
4. A sharp metal / oxide region map (tools/bench/variant_data.py: a 1 µm quenched metal strip,
   FWHM 1.05 µm β 1.25, on oxide 0.7 µm β 1.9, whole-field support, 160²), blurred by that
   file's numpy per-region model: `forward --regions` reproduces the model to 1e-9 of the peak
   (PL and field); on the model's data `correct`'s automatic choice is that exact operator and
   beats the uncorrected map in dark and lit regions, where the approximations that miss the
   budget (forced here: low rank 2 on 8 x 8 samples, the cheapest near the smallest error
   without regions) are worse than no correction in the lit regions (docs/model.md §9 "Region
   maps"). Then with the PSF file 5 % too wide and Poisson PL of 10⁴ photons at the peak: the
   default still beats the uncorrected map.
5. Accelerated Richardson–Lucy (`--iterations 30 --acceleration biggs-andrews`, docs/model.md
   §6) on case 2's data and on a 256² wire of 100 photons with the PSF file 5 % too wide and β
   10 % too large: it exits 0 (the former additive rule refused such data: dark pixels were
   halved until the field blew up) and its dark and lit errors are within 1.05 × the default's
   (plain RL, 75 iterations; measured 0.287 / 0.235 against 0.333 / 0.242, and 0.329 / 0.223
   against 0.368 / 0.240).
6. A smooth polynomial Moffat map (tools/bench/variant_data.py: FWHM 0.8 µm ± 0.25 µm across
   the view, β 1.6 ∓ 0.4, whole field) over foreign.py's array scene (3 x 3 dipoles spread over
   the view under oxide fringes), 192², blurred by the numpy model of the per-source operator:
   the default correction with the map (`correct --method r`, the automatic representation)
   beats the uncorrected map and has at most 0.7 x the error of the same correction with the
   map's centre PSF alone, in dark and in lit regions (issue 17's target, docs/performance.md;
   measured 0.031 / 0.067 against 0.132 / 0.603); the map's default takes its far tail on a
   coarse grid (docs/model.md §9) and its errors are within 1 % of `--tail-tol 0`'s (measured
   equal to 4 digits, nodes every 2 px); then with the map's FWHMs 5 % too wide and Poisson PL
   of 10⁴ photons at the peak it still beats the centre PSF.
7. A Gaussian-like PSF (Moffat β 20, whose margin the view's data barely see) on the 256² wire,
   light from a 6 µm margin, the PSF file 5 % too wide, 10⁴ photons, fit noise, NaN pixels: the
   default correction's dark / lit errors ≤ 0.80 / 0.65 × uncorrected and its 2 µm edge band
   within 1.2 × the interior's (measured 0.77 / 0.61, edge 1.04 ×). A start continued from the
   measured maps (tried for the reference study's Gaussian scenes, docs/model.md §3) gave 0.88 /
   0.72 here, worse at 10³ and 10⁶ photons alike, and was not kept.

8. The current reconstructed from the corrected field (`svpsf reconstruct --quantity
   current_from_bz`, docs/model.md §11) on the 256² wire of 1000 photons with the PSF right:
   |J| on the wire (its middle half of the rows, away from where the strip leaves the view)
   against the same reconstruction of the true field. The default's rms error ≤ 0.35 × the
   uncorrected map's (measured 0.163 against 0.653), and 75 iterations no worse than 30
   (0.246): docs/cli.md and docs/reference-study.md §2 say that on such data a current keeps
   improving with the count, while the study's magnetisations were best at 30–50.

9. The default's PSF tail on a coarse grid (docs/model.md §5) against the plain frame
   (`--tail-tol 0`) on case 2's data: the tail is taken, the fields agree to 1e-3 of the true
   field's peak, the dark and lit errors to 1 % of the plain frame's.

"Sound": exit 0 with a field whose lit-region error is below the uncorrected map's, within
10 × the measured range, and not shrunk below a tenth of the measured spread. Exits 77 (skip)
without numpy.

10. Single precision with a margin wider than the PSF's reach, on case 7's data: `--margin 40`
    and `60` in single precision agree with double to 1e-3 of the true peak and beat the
    uncorrected map (before rl.c's SEEN_SINGLE: refused as light lost, and before that doubt a
    field of 0 with exit 0).

11. Light from outside the view with a PSF map (`--margin`, the map's edge PSFs carried
    outward): a map of one PSF gives that PSF's field with the same margin to 1e-9 and a better
    edge band than without the margin; a metal / oxide map with --margin auto beats the
    uncorrected map with its 2 µm edge band within 2 x the interior, noiseless and as measured
    (Poisson PL, fit noise, NaN pixels, the map's FWHMs 5 % wide; map_margin_case).
"""
import json
import os
import subprocess
import sys
import tempfile

try:
    import numpy as np
except ImportError:
    print("SKIP: numpy is not installed (Debian python3-numpy): no foreign-data cases")
    sys.exit(77)

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "tools", "bench"))
import foreign  # noqa: E402
import variant_data as vd  # noqa: E402

failures = []


def check(cond, what):
    print(("ok   " if cond else "FAIL ") + what, flush=True)
    if not cond:
        failures.append(what)


def correct(svpsf, data, out, extra):
    cmd = [svpsf, "correct", "--field", os.path.join(data, "field.npy"), "--pl",
           os.path.join(data, "pl.npy"), "--psf", os.path.join(data, "psf.yaml"), "-o", out,
           "--format", "npy", "--quiet", "--threads", "2"] + extra
    p = subprocess.run(cmd, capture_output=True, text=True)
    return p.returncode, p.stderr.strip()


def errors(data, field):
    truth = np.load(os.path.join(data, "truth_field.npy"))
    masks = np.load(os.path.join(data, "masks.npz"))
    return {k: foreign.rel_rms(field, truth, masks[k]) for k in ("dark", "lit", "edge", "interior")}


def sound_or_refused(svpsf, data, out, extra, name):
    rc, msg = correct(svpsf, data, out, extra)
    measured = np.load(os.path.join(data, "field.npy"))
    u = errors(data, measured)
    if rc in (2, 3):
        check(not os.path.exists(out) or not os.listdir(out),
              f"{name}: exit {rc} and nothing written ({msg[:160]})")
        check("result in doubt" in msg or rc == 2, f"{name}: the message says why ({msg[:120]})")
        return
    check(rc == 0, f"{name}: exit {rc} is 0, 2 or 3 ({msg[:160]})")
    if rc != 0:
        return
    b = np.load(os.path.join(out, "field.npy"))
    e = errors(data, b)
    rng = np.nanmax(np.abs(measured))
    check(e["lit"] < u["lit"], f"{name}: exit 0 and lit error {e['lit']:.3f} < uncorrected "
          f"{u['lit']:.3f}")
    check(np.abs(b).max() <= 10 * rng, f"{name}: max |B| {np.abs(b).max():.3g} within 10x the "
          f"measured range {rng:.3g}")
    check(np.std(b) > 0.1 * np.nanstd(measured), f"{name}: not regularised away (spread "
          f"{np.std(b):.3g} vs measured {np.nanstd(measured):.3g})")


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    svpsf = sys.argv[1]
    with tempfile.TemporaryDirectory() as tmp:
        # case 1: 512², no misspecification, field peak 40 µT
        d1 = os.path.join(tmp, "case1")
        foreign.main(["make", "-o", d1, "--scene", "wire", "--size", "512", "--counts", "1000",
                      "--margin-um", "0", "--seed", "11"])
        sound_or_refused(svpsf, d1, os.path.join(tmp, "out1"), ["--method", "rw", "--balance",
                                                                "auto"],
                         "case 1 (512², rw, --balance auto)")
        rc, msg = correct(svpsf, d1, os.path.join(tmp, "out1b"), ["--balance", "auto"])
        check(rc == 1 and "--balance auto needs a method with a Wiener" in msg,
              f"case 1 with the default method: exit {rc}, '{msg[:100]}'")
        # case 2: the default on realistic foreign data
        d2 = os.path.join(tmp, "case2")
        foreign.main(["make", "-o", d2, "--scene", "wire", "--size", "384", "--counts", "1000",
                      "--margin-um", "6", "--fwhm-err", str(1 / 1.05 - 1),
                      "--field-noise-ut", "1.0", "--seed", "12"])
        rc, msg = correct(svpsf, d2, os.path.join(tmp, "out2"), [])
        check(rc == 0, f"case 2: the default correction exits 0 ({msg[:160]})")
        if rc == 0:
            u = errors(d2, np.load(os.path.join(d2, "field.npy")))
            e = errors(d2, np.load(os.path.join(tmp, "out2", "field.npy")))
            print(f"case 2: dark {e['dark']:.3f} (uncorrected {u['dark']:.3f}), lit "
                  f"{e['lit']:.3f} (uncorrected {u['lit']:.3f})")
            check(e["dark"] < u["dark"], f"case 2: dark error {e['dark']:.3f} < uncorrected "
                  f"{u['dark']:.3f}")
            check(e["lit"] < u["lit"], f"case 2: lit error {e['lit']:.3f} < uncorrected "
                  f"{u['lit']:.3f}")
            # the border: light enters from a 6 µm margin; the default estimates the object
            # beyond the view (--margin auto), so the 2 µm band at the view's edge is no worse
            # than twice the interior (without it: the edge's own light is misplaced)
            print(f"case 2: edge band {e['edge']:.3f}, interior {e['interior']:.3f} "
                  f"({e['edge'] / e['interior']:.2f}x)")
            check(e["edge"] <= 2 * e["interior"], f"case 2: 2 µm edge band error "
                  f"{e['edge']:.3f} <= 2 x interior {e['interior']:.3f}")
            tail_case(svpsf, d2, os.path.join(tmp, "out2"), os.path.join(tmp, "out2p"))
        # case 3: W with an automatic balance on the same data
        sound_or_refused(svpsf, d2, os.path.join(tmp, "out3"), ["--method", "w", "--balance",
                                                                "auto"],
                         "case 3 (384², w, --balance auto)")
        region_case(svpsf, os.path.join(tmp, "case4"))
        d5 = os.path.join(tmp, "case5")
        foreign.main(["make", "-o", d5, "--scene", "wire", "--size", "256", "--counts", "100",
                      "--fwhm-err", "0.05", "--beta-err", "0.1", "--seed", "15"])
        for i, (data, name) in enumerate(((d2, "case 2's data"),
                                          (d5, "256², 100 photons, PSF off"))):
            accelerated_case(svpsf, data, os.path.join(tmp, f"out5{i}"), name)
        smooth_map_case(svpsf, os.path.join(tmp, "case6"))
        d7 = os.path.join(tmp, "case7")
        foreign.main(["make", "-o", d7, "--scene", "wire", "--size", "256", "--counts", "10000",
                      "--beta", "20", "--fwhm-err", "0.05", "--seed", "7"])
        rc, msg = correct(svpsf, d7, os.path.join(tmp, "out7"), [])
        check(rc == 0, f"case 7: the default correction exits 0 ({msg[:160]})")
        if rc == 0:
            e = errors(d7, np.load(os.path.join(tmp, "out7", "field.npy")))
            u = errors(d7, np.load(os.path.join(d7, "field.npy")))
            print(f"case 7: dark {e['dark']:.3f} / lit {e['lit']:.3f} (uncorrected "
                  f"{u['dark']:.3f} / {u['lit']:.3f}), edge {e['edge']:.3f}, interior "
                  f"{e['interior']:.3f}")
            check(e["dark"] <= 0.80 * u["dark"] and e["lit"] <= 0.65 * u["lit"],
                  "case 7 (Gaussian-like PSF): dark / lit errors within 0.80 / 0.65 x uncorrected")
            check(e["edge"] <= 1.2 * e["interior"],
                  "case 7 (Gaussian-like PSF): 2 µm edge band within 1.2 x the interior")
            margin_single_case(svpsf, d7, tmp)
        current_case(svpsf, os.path.join(tmp, "case8"))
        map_margin_case(svpsf, os.path.join(tmp, "case11"))
    print(f"{len(failures)} failed")
    return 1 if failures else 0


def map_margin_case(svpsf, d, n=160):
    """Case 11: light from outside the view with a PSF map (`--margin`, the map's edge PSFs
    carried outward, svp_psf_field_pad). The wire scene of variant_data.py on a canvas 4–6 µm
    wider than the view, blurred there by the numpy per-region model and cropped: (a) both
    regions holding the foreign benchmark's PSF (Moffat 0.6 µm, β 1.1): the map with `--margin
    auto` gives the single PSF's field with `--margin auto --tail-tol 0` to 1e-9 of the peak,
    its 2 µm edge band within 2 x the interior and below `--margin 0`'s (measured 0.223 and
    0.274, interior 0.220); (b) metal / oxide (FWHM 1.05 / 0.7 µm, β 1.25 / 1.9): `--margin auto`
    beats the uncorrected map in dark and lit regions with its edge band within 2 x the interior
    (measured edge 0.355, interior 0.343; `--margin 0` 0.325 / 0.344, which is why a map gets no
    margin by default); (c) that map measured: Poisson PL of 10⁴ photons, fit noise, NaN pixels,
    the file's FWHMs 5 % too wide: `--margin auto` and the default (no margin) both beat the
    uncorrected map with their edge bands within 2 x the interior (measured dark / lit / edge /
    interior 0.470 / 0.333 / 0.397 / 0.375 and 0.483 / 0.307 / 0.352 / 0.376, uncorrected
    0.503 / 0.362 / 0.410 / 0.410)."""
    os.makedirs(d)
    base = ["--format", "npy", "--quiet", "--threads", "2"]

    def make(sub, mc, psfs, counts=0, fwhm_file=1.0):
        """Data on the view of a canvas mc px wider; psfs = (oxide, metal) (fwhm px, β). With
        counts > 0 a measurement's noise as foreign.py's: Poisson PL of that many photons at
        the peak, fit noise 0.3 µT · √(counts / photons), 0.5 % NaN pixels; the map file's
        FWHMs are fwhm_file × the true ones."""
        dd = os.path.join(d, sub)
        os.makedirs(dd)
        nc = n + 2 * mc
        pl, bz, labels = vd.scene(nc)
        metal = labels == 1
        plb, numb = vd.blur_sets([pl, bz * pl], [(~metal).astype(float), metal.astype(float)],
                                 list(psfs), nc)
        v = (slice(mc, mc + n), slice(mc, mc + n))
        with open(os.path.join(dd, "map.yaml"), "w") as f:
            f.write(f"pixel_um: {vd.PIXEL_UM}\nimage: {{width: {n}, height: {n}}}\n"
                    "model: moffat\nsupport_um: 0\nkind: regions\nlabels_file: map.labels.npy\n"
                    "regions: [" + ", ".join(f"{{label: {k}, fwhm_um: {fw * vd.PIXEL_UM:g}, "
                                             f"beta: {be:g}}}" for k, (fw, be) in
                                             enumerate((fw * fwhm_file, be)
                                                       for fw, be in psfs)) + "]\n")
        np.save(os.path.join(dd, "map.labels.npy"), labels[v].astype(np.float64))
        plm, field = plb[v], numb[v] / plb[v]
        if counts > 0:
            rng = np.random.default_rng(31)
            plm = rng.poisson(plm * counts / plm.max()).astype(float)
            sigma = 0.3 * np.sqrt(counts / np.maximum(plm, 1.0))
            field = field + sigma * rng.standard_normal(field.shape)
            field[rng.random(field.shape) < 0.005] = np.nan
        np.save(os.path.join(dd, "pl.npy"), plm)
        np.save(os.path.join(dd, "field.npy"), field)
        truth, plv = bz[v], pl[v]
        band = int(round(2.0 / vd.PIXEL_UM))
        edge = np.zeros((n, n), bool)
        edge[:band] = edge[-band:] = edge[:, :band] = edge[:, -band:] = True
        sig = np.abs(truth) > 0.1 * np.abs(truth).max()
        masks = dict(vd.masks(plv, truth), edge=edge & sig, interior=~edge & sig)
        return dd, truth, masks

    def run(dd, truth, masks, label, psf, extra):
        out = os.path.join(dd, "out" + "".join(ch for ch in label if ch.isalnum()))
        p = subprocess.run([svpsf, "correct", "--field", os.path.join(dd, "field.npy"), "--pl",
                            os.path.join(dd, "pl.npy"), "--psf", os.path.join(dd, psf), "-o",
                            out] + base + extra, capture_output=True, text=True)
        check(p.returncode == 0, f"case 11: correct {label} exits 0 ({p.stderr.strip()[:160]})")
        if p.returncode:
            return None, None
        b = np.load(os.path.join(out, "field.npy"))
        e = {k: vd.rel_rms(b, truth, m) for k, m in masks.items()}
        with open(os.path.join(out, "summary.json")) as f:
            e["margin"] = json.load(f)["settings"]["margin"]
        print(f"case 11: {label}: " + ", ".join(f"{k} {x:.3f}" for k, x in e.items()
                                                if k != "margin") + f", margin {e['margin']}")
        return b, e

    one = (0.6 / vd.PIXEL_UM, 1.1)
    dd, truth, masks = make("one", 60, (one, one))
    with open(os.path.join(dd, "psf.yaml"), "w") as f:
        f.write(f"pixel_um: {vd.PIXEL_UM}\npsf: {{model: moffat, fwhm_um: 0.6, beta: 1.1}}\n")
    bm, em = run(dd, truth, masks, "map, --margin auto", "map.yaml", ["--margin", "auto"])
    b0, e0 = run(dd, truth, masks, "map, --margin 0", "map.yaml", ["--margin", "0"])
    bs, es = run(dd, truth, masks, "its PSF alone", "psf.yaml", ["--tail-tol", "0"])
    if em and es:
        diff = np.abs(bm - bs).max() / np.abs(bs).max()
        check(em["margin"] == es["margin"] > 0 and diff <= 1e-9,
              f"case 11 (a): the map of one PSF with --margin auto ({em['margin']} px) = the single "
              f"PSF's ({es['margin']} px) to {diff:.1e} of the peak")
        check(em["edge"] <= 2 * em["interior"], f"case 11 (a): edge band {em['edge']:.3f} <= 2 x "
              f"interior {em['interior']:.3f}")
    if em and e0:
        check(e0["margin"] == 0 and em["edge"] < e0["edge"],
              f"case 11 (a): the margin's edge band {em['edge']:.3f} < without it "
              f"{e0['edge']:.3f}")
    ox = (vd.OXIDE["fwhm_um"] / vd.PIXEL_UM, vd.OXIDE["beta"])
    me = (vd.METAL["fwhm_um"] / vd.PIXEL_UM, vd.METAL["beta"])
    dd, truth, masks = make("regions", 40, (ox, me))
    raw = np.load(os.path.join(dd, "field.npy"))
    u = {k: vd.rel_rms(raw, truth, m) for k, m in masks.items()}
    _, em = run(dd, truth, masks, "metal / oxide map, --margin auto", "map.yaml",
                ["--margin", "auto"])
    if em:
        check(em["margin"] > 0 and em["dark"] < u["dark"] and em["lit"] < u["lit"],
              f"case 11 (b): --margin auto ({em['margin']} px) beats the uncorrected map "
              f"(dark {u['dark']:.3f}, lit {u['lit']:.3f})")
        check(em["edge"] <= 2 * em["interior"], f"case 11 (b): edge band {em['edge']:.3f} <= 2 x "
              f"interior {em['interior']:.3f}")
    # (c) the same map as measured: Poisson PL of 10⁴ photons, fit noise, NaN pixels, the map
    # file's FWHMs 5 % too wide
    dd, truth, masks = make("noisy", 40, (ox, me), counts=1e4, fwhm_file=1.05)
    raw = np.load(os.path.join(dd, "field.npy"))
    u = {k: vd.rel_rms(raw, truth, m) for k, m in masks.items()}
    print("case 11 (c): uncorrected: " + ", ".join(f"{k} {x:.3f}" for k, x in u.items()))
    _, em = run(dd, truth, masks, "noisy, map 5 % wide, --margin auto", "map.yaml",
                ["--margin", "auto"])
    _, e0 = run(dd, truth, masks, "noisy, map 5 % wide, --margin 0", "map.yaml", [])
    for e, label in ((em, "--margin auto"), (e0, "--margin 0 (the default for maps)")):
        if e:
            check(e["dark"] < u["dark"] and e["lit"] < u["lit"],
                  f"case 11 (c): {label} beats the uncorrected map (dark {e['dark']:.3f} < "
                  f"{u['dark']:.3f}, lit {e['lit']:.3f} < {u['lit']:.3f})")
            check(e["edge"] <= 2 * e["interior"], f"case 11 (c): {label}: edge band "
                  f"{e['edge']:.3f} <= 2 x interior {e['interior']:.3f}")


def margin_single_case(svpsf, data, tmp):
    """Case 10: single precision with a margin wider than the PSF's reach (case 7's data:
    Moffat β 20, light from a 6 µm margin, the PSF file 5 % too wide, 10⁴ photons, fit noise, NaN
    pixels): `--margin 40` and `60 --precision single` exit 0 and agree with double precision
    to 1e-3 of the true peak (measured 3e-5 – 8e-5; FFTW's plans vary from run to run), and
    beat the uncorrected map in dark and lit regions. Before rl.c's SEEN_SINGLE both were
    refused as light lost (exit 3), and before that doubt they exited 0 with a field of 0."""
    peak = np.nanmax(np.abs(np.load(os.path.join(data, "truth_field.npy"))))
    u = errors(data, np.load(os.path.join(data, "field.npy")))
    for m in ("40", "60"):
        fields = {}
        for prec in ("single", "double"):
            out = os.path.join(tmp, f"out10_{m}_{prec}")
            rc, msg = correct(svpsf, data, out, ["--margin", m, "--precision", prec])
            check(rc == 0, f"case 10: --margin {m} --precision {prec} exits 0 ({msg[:160]})")
            if rc != 0:
                return
            fields[prec] = np.load(os.path.join(out, "field.npy"))
        d = np.nanmax(np.abs(fields["single"] - fields["double"])) / peak
        e = errors(data, fields["single"])
        print(f"case 10: margin {m}, single against double {d:.2g} of the peak; dark "
              f"{e['dark']:.3f} / lit {e['lit']:.3f} (uncorrected {u['dark']:.3f} / "
              f"{u['lit']:.3f})")
        check(d <= 1e-3, f"case 10: margin {m}: single within 1e-3 of the peak of double ({d:.2g})")
        check(e["dark"] < u["dark"] and e["lit"] < u["lit"],
              f"case 10: margin {m}, single precision: beats the uncorrected map")


def tail_case(svpsf, data, out, out_plain):
    """Case 9: the default's PSF tail on a coarse grid against the plain frame (--tail-tol 0)
    on case 2's data: the tail is taken, the fields agree to 1e-3 of the true field's peak and
    the dark and lit errors to 1 % of the plain frame's."""
    with open(os.path.join(out, "summary.json")) as f:
        step = json.load(f)["results"].get("tail_step_px", 0)
    check(step > 0, f"case 9: the default takes the tail on a coarse grid (nodes every {step} px)")
    rc, msg = correct(svpsf, data, out_plain, ["--tail-tol", "0"])
    check(rc == 0, f"case 9: --tail-tol 0 exits 0 ({msg[:160]})")
    if rc != 0:
        return
    tail = np.load(os.path.join(out, "field.npy"))
    plain = np.load(os.path.join(out_plain, "field.npy"))
    peak = np.nanmax(np.abs(np.load(os.path.join(data, "truth_field.npy"))))
    d = np.max(np.abs(tail - plain)) / peak
    et, ep = errors(data, tail), errors(data, plain)
    print(f"case 9: tail against plain frame: max difference {d:.2g} of the peak; dark "
          f"{et['dark']:.4f} / {ep['dark']:.4f}, lit {et['lit']:.4f} / {ep['lit']:.4f}")
    check(d <= 1e-3, f"case 9: the tail's field within 1e-3 of the peak of the plain frame's "
          f"({d:.2g})")
    check(all(abs(et[k] - ep[k]) <= 0.01 * ep[k] for k in ("dark", "lit")),
          "case 9: dark and lit errors within 1 % of the plain frame's")


def filled(field):
    """NaN pixels (failed fits) replaced by the mean of their measured neighbours, repeated
    until none is left: reconstruct needs a complete map."""
    f = field.copy()
    n_y, n_x = f.shape
    bad = ~np.isfinite(f)
    while bad.any():
        v = np.pad(np.where(bad, 0.0, f), 1)
        w = np.pad((~bad).astype(float), 1)
        s = sum(v[1 + dy:n_y + 1 + dy, 1 + dx:n_x + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        k = sum(w[1 + dy:n_y + 1 + dy, 1 + dx:n_x + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1))
        fill = bad & (k > 0)
        f[fill] = s[fill] / k[fill]
        bad &= ~fill
    return f


def current_case(svpsf, d, n=256):
    foreign.main(["make", "-o", d, "--scene", "wire", "--size", str(n), "--counts", "1000",
                  "--seed", "8"])
    with open(os.path.join(d, "meta.json")) as f:
        meta = json.load(f)
    # the strip's pixels (foreign.py's mask), in the middle half of the rows
    on_wire = np.load(os.path.join(d, "masks.npz"))["wire"]
    on_wire[:n // 4] = on_wire[3 * n // 4:] = False

    def current(field, tag):
        path = os.path.join(d, f"bz_{tag}.npy")
        np.save(path, filled(field))
        out = os.path.join(d, f"j_{tag}")
        p = subprocess.run([svpsf, "reconstruct", "--quantity", "current_from_bz", "--bz", path,
                            "--unit", "uT", "--pixel-um", str(meta["pixel_um"]),
                            "--standoff-nm", "50", "-o", out, "--format", "npy", "--quiet"],
                           capture_output=True, text=True)
        check(p.returncode == 0, f"case 8: reconstruct ({tag}) exits 0 ({p.stderr.strip()[:160]})")
        if p.returncode != 0:
            return None
        return np.load(os.path.join(out, "J_norm.npy"))[on_wire]

    ref = current(np.load(os.path.join(d, "truth_field.npy")), "truth")
    res = {"uncorrected": current(np.load(os.path.join(d, "field.npy")), "uncorrected")}
    for it in (30, 75):
        out = os.path.join(d, f"out{it}")
        rc, msg = correct(svpsf, d, out, [] if it == 75 else ["--iterations", str(it)])
        check(rc == 0, f"case 8: correct with {it} iterations exits 0 ({msg[:160]})")
        if rc == 0:
            res[it] = current(np.load(os.path.join(out, "field.npy")), f"it{it}")
    if ref is None or any(v is None for v in res.values()) or len(res) < 3:
        return
    err = {k: float(np.sqrt(np.mean((v - ref) ** 2) / np.mean(ref ** 2))) for k, v in res.items()}
    print(f"case 8: rms error of |J| on the wire: uncorrected {err['uncorrected']:.3f}, 30 "
          f"iterations {err[30]:.3f}, 75 (the default) {err[75]:.3f}")
    check(err[75] <= 0.35 * err["uncorrected"],
          "case 8: the current from the default correction within 0.35 x the uncorrected error")
    check(err[75] <= err[30],
          "case 8: the current's error with 75 iterations no worse than with 30")


def accelerated_case(svpsf, data, out, name):
    res = {}
    for label, extra in (("plain 75", []),
                         ("accelerated 30", ["--iterations", "30", "--acceleration",
                                             "biggs-andrews"])):
        o = f"{out}-{len(res)}"
        rc, msg = correct(svpsf, data, o, extra)
        check(rc == 0, f"case 5 ({name}): {label} exits 0 ({msg[:160]})")
        if rc != 0:
            return
        res[label] = errors(data, np.load(os.path.join(o, "field.npy")))
    p, a = res["plain 75"], res["accelerated 30"]
    print(f"case 5 ({name}): accelerated dark {a['dark']:.3f} / lit {a['lit']:.3f}, plain 75 "
          f"{p['dark']:.3f} / {p['lit']:.3f}")
    check(a["dark"] <= 1.05 * p["dark"] and a["lit"] <= 1.05 * p["lit"],
          f"case 5 ({name}): 30 accelerated iterations within 1.05 x plain 75's errors")


def region_case(svpsf, d, n=160):
    """Case 4: the region operator against the numpy per-region model, and the corrections."""
    os.makedirs(d)
    pl, bz, labels = vd.scene(n)
    metal = labels == 1
    fw = np.where(metal, vd.METAL["fwhm_um"], vd.OXIDE["fwhm_um"]) / vd.PIXEL_UM
    be = np.where(metal, vd.METAL["beta"], vd.OXIDE["beta"])
    plb, numb = vd.blur_regions([pl, bz * pl], fw, be)
    vd.write_region_map(os.path.join(d, "map.yaml"), labels, 0.0)
    for name, a in (("pl_true", pl), ("field_true", bz), ("pl", plb), ("field", numb / plb)):
        np.save(os.path.join(d, name + ".npy"), a)
    base = ["--format", "npy", "--quiet", "--threads", "2"]
    p = subprocess.run([svpsf, "forward", "--field", os.path.join(d, "field_true.npy"), "--pl",
                        os.path.join(d, "pl_true.npy"), "--psf", os.path.join(d, "map.yaml"),
                        "--regions", "-o", os.path.join(d, "fwd")] + base,
                       capture_output=True, text=True)
    check(p.returncode == 0, f"case 4: forward --regions exits 0 ({p.stderr.strip()[:160]})")
    if p.returncode == 0:
        e_pl = np.abs(np.load(os.path.join(d, "fwd", "pl.npy")) - plb).max() / plb.max()
        e_b = np.abs(np.load(os.path.join(d, "fwd", "field.npy")) * plb - numb).max() / \
            np.abs(numb).max()
        check(max(e_pl, e_b) <= 1e-9, f"case 4: forward --regions = the numpy per-region model "
              f"(PL {e_pl:.1e}, field x PL {e_b:.1e} of the peak)")
    masks = vd.masks(pl, bz)
    unc = {k: vd.rel_rms(numb / plb, bz, m) for k, m in masks.items()}
    res = {}
    for label, extra in (("default", []), ("--rank 2", ["--rank", "2", "--nodes", "8x8"])):
        out = os.path.join(d, "out" + "".join(ch for ch in label if ch.isalnum()))
        p = subprocess.run([svpsf, "correct", "--field", os.path.join(d, "field.npy"), "--pl",
                            os.path.join(d, "pl.npy"), "--psf", os.path.join(d, "map.yaml"),
                            "-o", out] + base + extra, capture_output=True, text=True)
        check(p.returncode == 0, f"case 4: correct {label} exits 0 ({p.stderr.strip()[:160]})")
        if p.returncode == 0:
            b = np.load(os.path.join(out, "field.npy"))
            res[label] = {k: vd.rel_rms(b, bz, m) for k, m in masks.items()}
            with open(os.path.join(out, "summary.json")) as f:
                res[label]["repr"] = json.load(f)["settings"].get("psf_representation")
            print(f"case 4: correct {label}: dark {res[label]['dark']:.3f}, lit "
                  f"{res[label]['lit']:.3f} (uncorrected {unc['dark']:.3f}, {unc['lit']:.3f})")
    if "default" in res:
        e = res["default"]
        check(e["repr"] == "regions", f"case 4: correct's automatic choice is the region "
              f"operator ({e['repr']})")
        check(e["dark"] < unc["dark"] and e["lit"] < unc["lit"],
              "case 4: the default correction beats the uncorrected map in dark and lit regions")
        if "--rank 2" in res:
            check(res["--rank 2"]["lit"] > unc["lit"],
                  f"case 4: the budget-missing low rank 2's lit error {res['--rank 2']['lit']:.3f}"
                  f" > uncorrected {unc['lit']:.3f} (why the exact operator stays in the choice)")
    # the PSF 5 % too wide in both regions and shot noise: the default still helps
    rng = np.random.default_rng(4)
    counts = 1e4 / plb.max()
    pl_noisy = rng.poisson(plb * counts) / counts
    np.save(os.path.join(d, "pl_noisy.npy"), pl_noisy)
    with open(os.path.join(d, "map.yaml")) as f:
        text = f.read()
    for reg in (vd.OXIDE, vd.METAL):
        text = text.replace(f"fwhm_um: {reg['fwhm_um']},", f"fwhm_um: {reg['fwhm_um'] * 1.05:.6g},")
    with open(os.path.join(d, "map_off.yaml"), "w") as f:
        f.write(text)
    out = os.path.join(d, "out_off")
    p = subprocess.run([svpsf, "correct", "--field", os.path.join(d, "field.npy"), "--pl",
                        os.path.join(d, "pl_noisy.npy"), "--psf", os.path.join(d, "map_off.yaml"),
                        "-o", out] + base, capture_output=True, text=True)
    check(p.returncode == 0, f"case 4 (PSF 5 % off, 10⁴ photons): correct exits 0 "
          f"({p.stderr.strip()[:160]})")
    if p.returncode == 0:
        e = {k: vd.rel_rms(np.load(os.path.join(out, "field.npy")), bz, m)
             for k, m in masks.items()}
        print(f"case 4, PSF 5 % off, 10⁴ photons: dark {e['dark']:.3f}, lit {e['lit']:.3f}")
        check(e["dark"] < unc["dark"] and e["lit"] < unc["lit"],
              "case 4 (PSF 5 % off, 10⁴ photons): the default beats the uncorrected map")


def smooth_map_case(svpsf, d, n=192):
    """Case 6: a smooth PSF map over a field spread across the view: the map against its centre
    PSF alone."""
    os.makedirs(d)
    pl, bz, _ = vd.scene(n, "array")
    plb, numb = vd.blur_smooth([pl, bz * pl], n)
    vd.write_smooth_map(os.path.join(d, "map.yaml"), n)
    fw, be = vd.smooth_params(n)
    c = (n - 1) // 2
    with open(os.path.join(d, "centre.yaml"), "w") as f:
        f.write(f"pixel_um: {vd.PIXEL_UM}\npsf: {{model: moffat, fwhm_um: "
                f"{fw[c, c] * vd.PIXEL_UM:.6g}, beta: {be[c, c]:.6g}}}\n")
    with open(os.path.join(d, "map.yaml")) as f:
        text = f.read()
    lead = f"fwhm_um: [{vd.SMOOTH['fwhm'][0]:g},"
    check(lead in text, "case 6: the map file states its FWHM coefficients")
    with open(os.path.join(d, "map_off.yaml"), "w") as f:
        f.write(text.replace(lead, f"fwhm_um: [{vd.SMOOTH['fwhm'][0] * 1.05:.6g},"))
    rng = np.random.default_rng(6)
    counts = 1e4 / plb.max()
    np.save(os.path.join(d, "pl.npy"), plb)
    np.save(os.path.join(d, "pl_noisy.npy"), rng.poisson(plb * counts) / counts)
    np.save(os.path.join(d, "field.npy"), numb / plb)
    masks = vd.masks(pl, bz)
    unc = {k: vd.rel_rms(numb / plb, bz, m) for k, m in masks.items()}
    res = {}
    tail = {}
    for label, psf, pln, extra in (
            ("map", "map.yaml", "pl", []), ("centre PSF", "centre.yaml", "pl", []),
            ("map, --tail-tol 0", "map.yaml", "pl", ["--tail-tol", "0"]),
            ("map 5 % off, 10⁴ photons", "map_off.yaml", "pl_noisy", []),
            ("centre PSF, 10⁴ photons", "centre.yaml", "pl_noisy", [])):
        out = os.path.join(d, "out" + "".join(ch for ch in label if ch.isalnum()))
        p = subprocess.run([svpsf, "correct", "--field", os.path.join(d, "field.npy"), "--pl",
                            os.path.join(d, pln + ".npy"), "--psf", os.path.join(d, psf),
                            "--method", "r", "-o", out, "--format", "npy", "--quiet",
                            "--threads", "2"] + extra, capture_output=True, text=True)
        check(p.returncode == 0, f"case 6: correct with the {label} exits 0 "
              f"({p.stderr.strip()[:160]})")
        if p.returncode == 0:
            b = np.load(os.path.join(out, "field.npy"))
            res[label] = {k: vd.rel_rms(b, bz, m) for k, m in masks.items()}
            print(f"case 6: {label}: dark {res[label]['dark']:.3f}, lit {res[label]['lit']:.3f}"
                  f" (uncorrected {unc['dark']:.3f}, {unc['lit']:.3f})")
            with open(os.path.join(out, "summary.json")) as f:
                tail[label] = json.load(f)["results"].get("tail_step_px", 0)
    if "map" in res and "centre PSF" in res:
        m, c = res["map"], res["centre PSF"]
        check(m["dark"] < unc["dark"] and m["lit"] < unc["lit"],
              "case 6: the map's correction beats the uncorrected map in dark and lit regions")
        check(m["dark"] <= 0.7 * c["dark"] and m["lit"] <= 0.7 * c["lit"],
              "case 6: the map's correction has at most 0.7 x the centre PSF's error, dark and lit")
    # the map's far tail on a coarse grid (docs/model.md §9), on by default: taken here, and
    # the field's error within 1 % of the plain frame's, dark and lit
    if "map" in res and "map, --tail-tol 0" in res:
        m, z = res["map"], res["map, --tail-tol 0"]
        check(tail["map"] > 0 and tail["map, --tail-tol 0"] == 0,
              f"case 6: the map's default takes the far tail (nodes every {tail['map']} px), "
              "--tail-tol 0 the plain frame")
        check(abs(m["dark"] - z["dark"]) <= 0.01 * z["dark"] and
              abs(m["lit"] - z["lit"]) <= 0.01 * z["lit"],
              f"case 6: with the far tail the field error is within 1 % of the plain frame's "
              f"(dark {m['dark']:.4f} / {z['dark']:.4f}, lit {m['lit']:.4f} / {z['lit']:.4f})")
    off, c = res.get("map 5 % off, 10⁴ photons"), res.get("centre PSF, 10⁴ photons")
    if off and c:
        check(off["dark"] < c["dark"] and off["lit"] < c["lit"],
              "case 6: with its FWHMs 5 % off and 10⁴ photons the map still beats the centre PSF")


if __name__ == "__main__":
    sys.exit(main())
