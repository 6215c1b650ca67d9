#!/usr/bin/python3
"""What accuracy costs in time: `svpsf correct` on foreign data (tools/bench/foreign.py).

usage: accuracy.py [--svpsf PATH] [--quick] [--output docs/accuracy.md] [--json FILE]
                   [--threads T] [--work DIR] [--commit LABEL] [--scenes S,S] [--counts C,C]
                   [--camera G,O,R]

--svpsf may be another commit's build (its commit named by --commit): option sets whose flags
or keyword values (`--iterations auto`, `--margin auto`, ...) its `correct --help` lacks are
skipped and listed, so the same table measures the program before and after a change.

For every scene (wire, chessboard), photon level (100, 1000, 1e4 at the peak) and PSF file
(right, or 5 % too wide with β 10 % too large — the misspecification of a PSF known to a few per
cent), one dataset with light from 6 µm beyond the view, shot noise, fit noise and NaN pixels is
made by the independent model, then corrected with each option set of OPTION_SETS. Recorded per
run: the relative rms field error in the dark and in the lit regions where the field is
significant (|B| > 10 % of its max), the same for the uncorrected map, the error in the 2 µm band
at the view's edge and in the interior, wall time, RL iterations or λ from summary.json, and the
exit status (3: the program refused to vouch for the result — itself a result). Writes the
markdown page and a JSON of every run.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, HERE)
import foreign  # noqa: E402

# (label, arguments of svpsf correct). A row whose flags the program lacks is skipped, said so.
OPTION_SETS = [
    ("default", []),
    # the PSF's far tail on a coarse grid off (the default takes it within 1e-3)
    ("default, --tail-tol 0", ["--tail-tol", "0"]),
    # plain RL, said explicitly ("--acceleration none", today's default) so that these rows
    # keep their meaning whatever the default becomes
    ("r, 75 it, margin auto, single", ["--method", "r", "--iterations", "75", "--acceleration",
                                       "none", "--margin", "auto", "--precision", "single"]),
    ("r, 75 it, margin 0", ["--method", "r", "--iterations", "75", "--acceleration", "none",
                            "--margin", "0"]),
    ("r, 75 it, margin auto, double", ["--method", "r", "--iterations", "75", "--acceleration",
                                       "none", "--margin", "auto", "--precision", "double"]),
    ("r, 150 it, margin auto, single", ["--method", "r", "--iterations", "150", "--acceleration",
                                        "none", "--margin", "auto", "--precision", "single"]),
    # fewer iterations: what the reference study's noisy scenes prefer (reference-study.md §2)
    ("r, 30 it", ["--method", "r", "--iterations", "30", "--acceleration", "none"]),
    ("r, 50 it", ["--method", "r", "--iterations", "50", "--acceleration", "none"]),
    ("r, 15 it, Biggs–Andrews", ["--method", "r", "--iterations", "15",
                                 "--acceleration", "biggs-andrews"]),
    ("r, 25 it, Biggs–Andrews", ["--method", "r", "--iterations", "25",
                                 "--acceleration", "biggs-andrews"]),
    ("r, auto iterations", ["--method", "r", "--iterations", "300", "--iterations", "auto",
                            "--acceleration", "none"]),
    ("r, 30 it, Biggs–Andrews, margin 0", ["--method", "r", "--iterations", "30",
                                           "--acceleration", "biggs-andrews", "--margin", "0"]),
    ("r, 30 it, Biggs–Andrews, double", ["--method", "r", "--iterations", "30",
                                         "--acceleration", "biggs-andrews", "--precision",
                                         "double"]),
    ("r, 40 it, Biggs–Andrews", ["--method", "r", "--iterations", "40",
                                 "--acceleration", "biggs-andrews"]),
    ("rw, balance 1e-3", ["--method", "rw"]),
    ("rw, balance auto", ["--method", "rw", "--balance", "auto", "--field-sigma", "{sigma}"]),
    ("rw, balance auto, σ estimated", ["--method", "rw", "--balance", "auto"]),
    ("w, balance 1e-3", ["--method", "w"]),
    ("w, balance auto", ["--method", "w", "--balance", "auto", "--field-sigma", "{sigma}"]),
    ("w, balance auto, σ estimated", ["--method", "w", "--balance", "auto"]),
]

SCENES = ["wire", "chessboard"]
COUNTS = [100, 1000, 10000]
PSF_ERRORS = [(0.0, 0.0), (0.05, 0.10)]
TIE = 0.05
# The PSF error one parameter at a time (FWHM, β relative errors of the file the program is
# given), default correction and 300 iterations, 10⁴ photons: which of the two limits the error.
SENSITIVITY = [(0.05, 0.0), (-0.05, 0.0), (0.0, 0.10), (0.0, -0.10), (0.05, 0.10)]
SENSITIVITY_SETS = [("default", []), ("r, 300 it", ["--method", "r", "--iterations", "300",
                                                   "--acceleration", "none"])]


def correct_help(svpsf):
    return subprocess.run([svpsf, "correct", "--help"], capture_output=True, text=True).stdout


def supported(help_text, args):
    """Every flag of args in the help, and every keyword value after a flag (not a number, not
    a {placeholder}) on that flag's help line: `--iterations auto` needs `--iterations N|auto`."""
    lines = help_text.splitlines()
    for i, a in enumerate(args):
        if not a.startswith("--"):
            continue
        own = [ln for ln in lines if ln.strip().startswith(a + " ") or ln.strip() == a]
        if not own:
            return False
        v = args[i + 1] if i + 1 < len(args) else ""
        if v and not v.startswith("-") and not v.startswith("{"):
            try:
                float(v)
            except ValueError:
                if not any(v in ln.split()[1] if len(ln.split()) > 1 else False for ln in own):
                    return False
    return True


def one_run(svpsf, data, label, extra, threads, wisdom):
    out = os.path.join(data, "out_" + "".join(ch if ch.isalnum() else "_" for ch in label))
    args = [a.replace("{sigma}", os.path.join(data, "field_sigma.npy")) for a in extra]
    cmd = [svpsf, "correct", "--field", os.path.join(data, "field.npy"), "--pl",
           os.path.join(data, "pl.npy"), "--psf", os.path.join(data, "psf.yaml"), "-o", out,
           "--format", "npy", "--force", "--quiet", "--threads", str(threads),
           "--wisdom", wisdom] + args
    t0 = time.time()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.time() - t0
    res = {"label": label, "exit": p.returncode, "seconds": wall,
           "message": (p.stderr.strip().splitlines()[-1] if p.stderr.strip() else "").replace(
               data + os.sep, "")}
    if p.returncode != 0:
        return res
    b = np.load(os.path.join(out, "field.npy"))
    truth = np.load(os.path.join(data, "truth_field.npy"))
    masks = np.load(os.path.join(data, "masks.npz"))
    for key in ("dark", "lit", "edge", "interior"):
        res[key] = foreign.rel_rms(b, truth, masks[key])
    res.update(dark_split(b, truth, masks))
    with open(os.path.join(out, "summary.json")) as f:
        s = json.load(f)
    r = s.get("results", {})
    st = s.get("settings", {})
    res["method"] = st.get("method")
    res["iterations_setting"] = st.get("iterations", st.get("iteration_cap"))
    res["acceleration_setting"] = st.get("acceleration")
    res["iterations"] = r.get("rl_iterations")
    res["rl_stop"] = r.get("rl_stop")
    res["balance"] = r.get("balance_field", r.get("balance_pl"))
    res["doubts"] = r.get("doubts", "")
    return res


def make_dataset(data, scene, size, counts, fwhm_err, beta_err, extra=()):
    """A foreign dataset in folder data (tools/bench/foreign.py), its seed from the photon
    count; returns data."""
    foreign.main(["make", "-o", data, "--scene", scene, "--size", str(size), "--counts",
                  str(counts), "--fwhm-err", str(fwhm_err), "--beta-err", str(beta_err),
                  "--seed", str(7 + int(counts) % 97)] + list(extra))
    return data


STRIP_BAND_PX = 2


def strip_band(wire):
    """The pixels within STRIP_BAND_PX of the current strip's edges (its first and last pixels
    across it), where the field at 50 nm stand-off peaks within a pixel."""
    edge = wire & ~(np.roll(wire, 1, axis=1) & np.roll(wire, -1, axis=1))
    edge |= ~wire & (np.roll(wire, 1, axis=1) | np.roll(wire, -1, axis=1))
    band = edge.copy()
    for k in range(1, STRIP_BAND_PX + 1):
        band |= np.roll(edge, k, axis=1) | np.roll(edge, -k, axis=1)
    return band


def dark_split(b, truth, masks):
    """Where a field b's dark-region error is: the share of its squared error within the strip
    band, the band's dark pixels, and the relative rms error over the dark pixels off it."""
    dark = masks["dark"] & np.isfinite(b)
    band = strip_band(masks["wire"])
    e2 = (b - truth) ** 2
    total = e2[dark].sum()
    return {"dark_band_share": float(e2[dark & band].sum() / total) if total > 0 else 0.0,
            "dark_band_px": int((dark & band).sum()), "dark_px": int(dark.sum()),
            "dark_off_band": foreign.rel_rms(b, truth, masks["dark"] & ~band)}


def uncorrected(data):
    b = np.load(os.path.join(data, "field.npy"))
    truth = np.load(os.path.join(data, "truth_field.npy"))
    masks = np.load(os.path.join(data, "masks.npz"))
    res = {key: foreign.rel_rms(b, truth, masks[key]) for key in ("dark", "lit", "edge",
                                                                  "interior")}
    res.update(dark_split(b, truth, masks))
    return res


def fmt(x, spec=".3f"):
    return "–" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)


TITLE = "Accuracy on foreign data: what each correction costs and gains"


def render(runs, skipped, quick, commit, size, threads, camera=None, title=TITLE, extra=None,
           sens=None):
    out = []
    w = out.append
    w(f"# {title}\n")
    w("Written by `tools/bench/accuracy.py` (part of `tools/run bench`); do not edit by "
             "hand. Every dataset is made by `tools/bench/foreign.py`, an independent numpy "
             "model (no svpsf code): the scene extends 6 µm beyond the view, so light enters "
             "from outside; Poisson PL at the stated peak photon count; the field's fit noise "
             "σ_B = 0.3 µT · √(peak / photons) (ODMR fits: σ ∝ 1/√photons); 0.5 % NaN pixels "
             "and a 4 × 4 cluster; Moffat PSF 0.6 µm FWHM, β 1.1 on 0.1 µm pixels. `PSF off` "
             "means the PSF file the program is given is 5 % too wide with β 10 % too large.\n")
    w(f"- commit {commit} (the program measured), {size}² views, {threads} threads, FFTW wisdom kept across the "
             "runs (the time is the correction's, not the first run's planning)"
             f"{', **quick run**' if quick else ''}")
    if extra:
        w(f"- {extra}")
    w("- error: relative rms field error √(Σ(B − B_true)² / Σ B_true²) over the pixels "
             "where |B_true| > 10 % of its max, split into *dark* (true PL < 30 % of its max: "
             "the quenching wire, the dark squares) and *lit*; *uncorrected* is the measured "
             "map's own error. `edge` / `interior`: the same over the 2 µm band at the view's "
             "border / inside it.")
    w("- exit 3: the program refused to vouch for the result (docs/cli.md); such a run "
             "writes nothing, which is the intended outcome for a correction that would have "
             "been garbage.\n")
    if camera:
        w(f"- camera: PL written as {camera[0]:g} counts per photon + offset {camera[1]:g} + "
          f"read noise σ {camera[2]:g} counts (the program estimates the gain unless told)\n")
    if skipped:
        w("Option sets this build does not have (skipped): " + "; ".join(skipped) + "\n")
    datasets = []
    for r in runs:
        key = (r["scene"], r["counts"], r["psf_err"])
        if key not in datasets:
            datasets.append(key)
    # the default row names what the default was in the program measured
    dflt = next((r for r in runs if r["label"] == "default" and r.get("method")), None)
    if dflt:
        acc = ", Biggs–Andrews" if dflt.get("acceleration_setting") == "biggs-andrews" else ""
        name = f"default ({dflt['method']}, {dflt['iterations_setting']} it{acc})" if dflt[
            "method"] != "w" else "default (w)"
        for r in runs:
            if r["label"] == "default":
                r["label"] = name
                r["is_default"] = True
    labels = []
    for r in runs:
        if r["label"] not in labels:
            labels.append(r["label"])
    for scene, counts, psf_err in datasets:
        rows = [r for r in runs if (r["scene"], r["counts"], r["psf_err"]) == (scene, counts,
                                                                            psf_err)]
        u = rows[0]["uncorrected"]
        w(f"## {scene}, {counts:g} photons at the peak, PSF {'off' if psf_err else 'right'}\n")
        w("| correction | exit | dark | lit | dark / uncorr. | lit / uncorr. | edge | "
                 "interior | time s | RL it. / λ |")
        w("|---|---|---|---|---|---|---|---|---|---|")
        w(f"| uncorrected | | {fmt(u['dark'])} | {fmt(u['lit'])} | 1 | 1 | "
                 f"{fmt(u['edge'])} | {fmt(u['interior'])} | | |")
        for r in rows:
            if r["exit"] != 0:
                w(f"| {r['label']} | {r['exit']} | | | | | | | {r['seconds']:.2f} | "
                         f"{r['message'][:90].replace('|', '/')} |")
                continue
            it = r.get("iterations")
            lam = r.get("balance")
            knob = (f"{it} ({r.get('rl_stop')})" if it else "") + (
                f" λ {lam:.2g}" if isinstance(lam, (int, float)) else "")
            w(f"| {r['label']} | 0 | {fmt(r['dark'])} | {fmt(r['lit'])} | "
                     f"{fmt(r['dark'] / u['dark'], '.2f')} | {fmt(r['lit'] / u['lit'], '.2f')} | "
                     f"{fmt(r['edge'])} | {fmt(r['interior'])} | {r['seconds']:.2f} | {knob} |")
        w("")
    # summary: per option set, the worst ratio over the datasets
    w("## Summary: worst ratio to uncorrected over all datasets\n")
    w("Target for the default: ≤ 0.5 in dark and in lit regions at every photon level.\n")
    w("| correction | worst dark ratio | worst lit ratio | refused (exit ≠ 0) | "
             "median time s |")
    w("|---|---|---|---|---|")
    for label in labels:
        rs = [r for r in runs if r["label"] == label]
        okr = [r for r in rs if r["exit"] == 0]
        dr = max((r["dark"] / r["uncorrected"]["dark"] for r in okr), default=float("nan"))
        lr = max((r["lit"] / r["uncorrected"]["lit"] for r in okr), default=float("nan"))
        t = float(np.median([r["seconds"] for r in rs]))
        w(f"| {label} | {fmt(dr, '.2f')} | {fmt(lr, '.2f')} | "
                 f"{len(rs) - len(okr)} of {len(rs)} | {t:.2f} |")
    w("")
    # the choice the defaults follow: never refused; the smallest worst dark ratio, where ratios
    # within TIE of each other are a tie (one seed per dataset: differences that small are
    # noise) broken by the worst lit ratio within TIE, then by the median time
    cands = []
    for label in labels:
        rs = [r for r in runs if r["label"] == label]
        if any(r["exit"] != 0 for r in rs):
            continue
        cands.append((label, max(r["dark"] / r["uncorrected"]["dark"] for r in rs),
                      max(r["lit"] / r["uncorrected"]["lit"] for r in rs),
                      float(np.median([r["seconds"] for r in rs]))))
    def is_default(label):
        """label is the default row, or every one of its runs has the default's errors."""
        if label.startswith("default"):
            return True
        d = {(r["scene"], r["counts"], r["psf_err"]): (r.get("dark"), r.get("lit"))
             for r in runs if r["label"].startswith("default")}
        mine = [r for r in runs if r["label"] == label]
        return bool(d) and all(d.get((r["scene"], r["counts"], r["psf_err"])) == (
            r.get("dark"), r.get("lit")) for r in mine)

    if cands:
        best_dark = min(c[1] for c in cands)
        near = [c for c in cands if c[1] <= best_dark + TIE]
        best_lit = min(c[2] for c in near)
        near = [c for c in near if c[2] <= best_lit + TIE]
        best = min(near, key=lambda c: c[3])
        w(f"**Winner** (never refused; the smallest worst dark ratio, then lit ratio, ratios "
          f"within {TIE} counted as ties and broken by the median time): **{best[0]}** — worst "
          f"dark ratio {best[1]:.2f}, worst lit ratio {best[2]:.2f}, median {best[3]:.2f} s. "
          + ("`svpsf correct`'s defaults are this option set (or give the same errors).\n"
             if is_default(best[0]) else
             "`svpsf correct`'s defaults are among the tied option sets (both worst ratios "
             f"within {TIE} of the best), slower than the winner.\n"
             if any(is_default(c[0]) for c in near) else
             "`svpsf correct`'s defaults in the program measured are not.\n"))
    split = [r for r in runs if (r.get("is_default") or r["label"] == "default") and r["exit"] == 0
             and "dark_band_share" in r and "dark_band_share" in r["uncorrected"]]
    if split:
        w("## Where the default's dark error is\n")
        w(f"The share of the default's squared dark-region error in the dark pixels within "
          f"{STRIP_BAND_PX} px of the current strip's edges (where the field at 50 nm stand-off "
          "peaks within a pixel, so a correction must restore it to the pixel), and the dark "
          "ratio to uncorrected off that band.\n")
        w("| dataset | dark ratio | band pixels / dark pixels | share of the error in the band, "
          "default / uncorrected | dark ratio off the band |")
        w("|---|---|---|---|---|")
        for r in split:
            u = r["uncorrected"]
            w(f"| {r['scene']}, {r['counts']:g} photons, PSF "
              f"{'off' if r['psf_err'] else 'right'} | {r['dark'] / u['dark']:.2f} | "
              f"{r['dark_band_px']} / {r['dark_px']} | {r['dark_band_share']:.2f} / "
              f"{u['dark_band_share']:.2f} | {r['dark_off_band'] / u['dark_off_band']:.2f} |")
        w("")
    if sens:
        w("## Which PSF error matters: FWHM or β\n")
        w("The same scenes at 10⁴ photons with the PSF file wrong in one parameter at a time "
          "(relative errors; the datasets above use +5 % FWHM and +10 % β together). Ratios to "
          "uncorrected, dark / lit.\n")
        labels_s = []
        for r in sens:
            if r["label"] not in labels_s:
                labels_s.append(r["label"])
        w("| scene | FWHM error | β error | " + " | ".join(labels_s) + " |")
        w("|---|---|---|" + "---|" * len(labels_s))
        keys = []
        for r in sens:
            k = (r["scene"], r["fwhm_err"], r["beta_err"])
            if k not in keys:
                keys.append(k)
        for k in keys:
            cells = []
            for label in labels_s:
                r = next((x for x in sens if (x["scene"], x["fwhm_err"], x["beta_err"]) == k
                          and x["label"] == label), None)
                if r is None or r["exit"] != 0:
                    cells.append(f"exit {r['exit']}" if r else "–")
                else:
                    cells.append(f"{r['dark'] / r['uncorrected']['dark']:.2f} / "
                                 f"{r['lit'] / r['uncorrected']['lit']:.2f}")
            w(f"| {k[0]} | {100 * k[1]:+g} % | {100 * k[2]:+g} % | " + " | ".join(cells) + " |")
        w("")
    return "\n".join(out) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--svpsf", default=os.path.join(ROOT, "build", "tools", "svpsf", "svpsf"))
    ap.add_argument("--quick", action="store_true", help="192² views, 1000 photons only")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--output", default=os.path.join(ROOT, "docs", "accuracy.md"))
    ap.add_argument("--json", default=None)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default=None)
    ap.add_argument("--commit", default=None,
                    help="the commit --svpsf was built from (default: this checkout's HEAD)")
    ap.add_argument("--scenes", default=",".join(SCENES), help="wire,chessboard,oxide")
    ap.add_argument("--counts", default=None, help="peak photon levels (default 100,1000,10000)")
    ap.add_argument("--camera", default=None,
                    help="G,O,R: PL as G counts per photon + offset O + read noise R")
    ap.add_argument("--title", default=TITLE, help="the page's heading")
    ap.add_argument("--field-noise-ut", type=float, default=None,
                    help="σ_B at the peak PL for foreign.py (default its 0.3 µT)")
    ap.add_argument("--fwhm-err", type=float, default=None,
                    help="the 'PSF off' file's FWHM error (default +0.05: 5 %% too wide)")
    ap.add_argument("--no-sensitivity", action="store_true",
                    help="skip the section on FWHM against β errors")
    ap.add_argument("--from-json", default=None,
                    help="render the page from a --json file of an earlier run, running nothing")
    args = ap.parse_args()
    if args.from_json:
        with open(args.from_json) as f:
            saved = json.load(f)
        md = render(saved["runs"], saved["skipped"], saved["quick"], saved["commit"],
                    saved["size"], saved["threads"], saved.get("camera"), args.title,
                    saved.get("extra"), saved.get("sensitivity"))
        with open(args.output, "w") as f:
            f.write(md)
        return 0
    size = 192 if args.quick else args.size
    counts = [float(c) for c in args.counts.split(",")] if args.counts else (
        [1000] if args.quick else COUNTS)
    counts = [int(c) if c == int(c) else c for c in counts]
    scenes = args.scenes.split(",")
    camera = [float(v) for v in args.camera.split(",")] if args.camera else None
    psf_errors = PSF_ERRORS if args.fwhm_err is None else [
        (0.0, 0.0), (args.fwhm_err, 2 * args.fwhm_err)]
    extra = ", ".join(x for x in (
        f"fit noise σ_B = {args.field_noise_ut:g} µT at the peak PL (not 0.3)"
        if args.field_noise_ut is not None else "",
        f"`PSF off`: the file's FWHM {100 * args.fwhm_err:+g} %, β {200 * args.fwhm_err:+g} %"
        f" (not +5 % / +10 %)" if args.fwhm_err is not None else "") if x) or None
    help_text = correct_help(args.svpsf)
    if "usage: svpsf correct" not in help_text:
        sys.exit(f"accuracy.py: {args.svpsf} is not an svpsf program ('correct --help' failed)")
    skipped = [label for label, extra in OPTION_SETS if not supported(help_text, extra)]
    sets = [(label, args_) for label, args_ in OPTION_SETS if label not in skipped]
    commit = args.commit or subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"],
                                           capture_output=True, text=True).stdout.strip()
    runs = []
    with tempfile.TemporaryDirectory(dir=args.work) as tmp:
        for scene in scenes:
            for c in counts:
                for fe, be in psf_errors:
                    data = make_dataset(os.path.join(tmp, f"{scene}_{c}_{fe}"), scene, size,
                                        c, fe, be,
                                        (["--gain", str(camera[0]), "--offset", str(camera[1]),
                                          "--read-noise", str(camera[2])] if camera else [])
                                        + (["--field-noise-ut", str(args.field_noise_ut)]
                                           if args.field_noise_ut is not None else []))
                    u = uncorrected(data)
                    for label, args_ in sets:
                        r = one_run(args.svpsf, data, label, args_, args.threads,
                                    os.path.join(tmp, "fftw.wisdom"))
                        r.update(scene=scene, counts=c, psf_err=fe, uncorrected=u)
                        runs.append(r)
                        print(f"{scene} {c} psf_err {fe}: {label}: exit {r['exit']} "
                              f"dark {fmt(r.get('dark'))} lit {fmt(r.get('lit'))} "
                              f"(uncorrected {fmt(u['dark'])} / {fmt(u['lit'])}) "
                              f"{r['seconds']:.2f} s", file=sys.stderr, flush=True)
        sens = []
        if not args.quick and not args.no_sensitivity:
            for scene in scenes:
                for fe, be in SENSITIVITY:
                    data = make_dataset(os.path.join(tmp, f"sens_{scene}_{fe}_{be}"), scene,
                                        size, 10000, fe, be)
                    u = uncorrected(data)
                    for label, args_ in SENSITIVITY_SETS:
                        r = one_run(args.svpsf, data, label, args_, args.threads,
                                    os.path.join(tmp, "fftw.wisdom"))
                        r.update(scene=scene, fwhm_err=fe, beta_err=be, uncorrected=u)
                        sens.append(r)
                        print(f"sensitivity {scene} FWHM {fe:+g} beta {be:+g}: {label}: exit "
                              f"{r['exit']} dark {fmt(r.get('dark'))} lit {fmt(r.get('lit'))}",
                              file=sys.stderr, flush=True)
    if args.json:  # first: a page that fails to render can be rendered again from it
        with open(args.json, "w") as f:
            json.dump(dict(runs=runs, skipped=skipped, quick=args.quick, commit=commit,
                           size=size, threads=args.threads, camera=camera, extra=extra,
                           sensitivity=sens), f, indent=1)
    md = render(runs, skipped, args.quick, commit, size, args.threads, camera, args.title,
                extra, sens)
    with open(args.output, "w") as f:
        f.write(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
