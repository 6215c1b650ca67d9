#!/usr/bin/python3
"""Benchmark section: Richardson–Lucy, scikit-image and T⁻¹ with a space-invariant PSF.

usage: section_restore.py [--build DIR] [--quick] [--threads 2,1] [--no-skimage]

Prints its markdown section of docs/performance.md on stdout (tools/bench/run assembles the
file). Every figure comes from this one run: the FFT bounds are measured in the same processes
as the solvers they bound. scikit-image is timed through /usr/bin/python3 (Debian's
python3-skimage 0.19); without it the comparison is skipped with a note.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from benchlib import ROOT, built, describe_error, log, ms, ok, run_json, verdict  # noqa: E402

TARGET_BOUND = 1.3
TARGET_SKIMAGE = 30.0
TARGET_ACCEL = 0.4


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--build", default=os.path.join(ROOT, "build"))
    ap.add_argument("--quick", action="store_true", help="512² only, 2 repetitions")
    ap.add_argument("--threads", default="2,1")
    ap.add_argument("--no-skimage", action="store_true")
    args = ap.parse_args()

    exe = built(args.build, "tools", "bench", "svpsf_bench")
    wisdom = os.path.join(args.build, "tools", "bench", "fftw.wisdom")
    threads = [int(t) for t in args.threads.split(",")]
    rl_sizes = [512] if args.quick else [512, 1024, 2048]
    sk_sizes = [512] if args.quick else [512, 1024]
    reps = {512: 2, 1024: 2, 2048: 2} if args.quick else {512: 7, 1024: 5, 2048: 3}
    inv_size = 512 if args.quick else 1024

    def bench(mode, size, t, r):
        return run_json([exe, mode, "--size", str(size), "--threads", str(t), "--reps", str(r),
                         "--wisdom", wisdom])

    results = {"rl": {}, "rl32": {}, "compat": {}, "skimage": {}, "inverse": {}, "ceiling": {},
               "rlaccel": {}}
    # one untimed run first: the first process of a run was measured up to 2.5x slow (page
    # cache, clocks, the wisdom file), which would land on whichever case comes first
    bench("rl", rl_sizes[0], threads[0], 1)
    for size in rl_sizes:
        for t in threads:
            results["rl"][(size, t)] = bench("rl", size, t, reps[size])
            results["rl32"][(size, t)] = bench("rl32", size, t, reps[size])
    for size in sk_sizes:
        for t in threads:
            results["compat"][(size, t)] = bench("skimage", size, t, 3 if not args.quick else 2)
    for t in threads:
        results["inverse"][t] = bench("inverse", inv_size, t, 3 if not args.quick else 2)
    for size in ([256] if args.quick else [256, 512, 1024]):
        # more repetitions where a solve is short (0.1-0.2 s at 256²) and the load's swings
        # weigh most
        results["rlaccel"][(size, threads[0])] = bench("rlaccel", size, threads[0],
                                                       2 if args.quick else
                                                       {256: 15, 512: 7}.get(size, 3))
    ceiling = os.path.join(args.build, "tools", "bench", "bench_ceiling")
    if os.access(ceiling, os.X_OK):
        for size in sk_sizes:
            for t in threads:
                results["ceiling"][(size, t)] = run_json(
                    [ceiling, "--size", str(size), "--threads", str(t), "--reps", "5"])

    skimage_note = ""
    py = "/usr/bin/python3"
    if args.no_skimage:
        skimage_note = "scikit-image was not run (--no-skimage)."
    else:
        with tempfile.TemporaryDirectory() as tmp:
            for size in sk_sizes:
                for kernel in ("full", "image"):
                    exp = run_json([exe, "export", "--size", str(size), "--out", tmp,
                                    "--kernel", kernel])
                    if not ok(exp):
                        skimage_note = f"export failed: {exp.get('error')}"
                        break
                    # k2 - k1 = 4 iterations: a difference of one or two iterations drowns in the noise of
                    # scipy's set-up (its first call costs more than an iteration)
                    k2, r = 5, 3
                    res = run_json([py, os.path.join(ROOT, "tools", "bench", "skimage_rl.py"),
                                    os.path.join(tmp, "image.npy"), os.path.join(tmp, "psf.npy"),
                                    "1", str(k2), str(1 if args.quick else r)])
                    if res.get("error") == "missing" or res.get("returncode") == 77:
                        skimage_note = ("scikit-image is not installed for /usr/bin/python3 "
                                        "(apt-get install python3-skimage): comparison skipped.")
                        break
                    results["skimage"][(size, kernel)] = res
                    if size == 1024 and kernel == "full":
                        # the same input cast to float32: scikit-image then computes in single
                        # precision, the peer of svpsf's single-precision ceiling below
                        results["skimage"][(size, "full32")] = run_json(
                            [py, os.path.join(ROOT, "tools", "bench", "skimage_rl.py"),
                             os.path.join(tmp, "image.npy"), os.path.join(tmp, "psf.npy"),
                             "1", str(k2), str(1 if args.quick else r), "float32"])
                if skimage_note:
                    break
    results["cli"] = {} if args.quick else cli_default(args.build)
    md = render(results, threads, rl_sizes, sk_sizes, inv_size, skimage_note, args.quick)
    sys.stdout.write(md)
    raw = {k: {str(kk): vv for kk, vv in v.items()} for k, v in results.items()}  # tuple keys
    with open(os.path.join(args.build, "tools", "bench", "results-restore.json"), "w") as f:
        json.dump({"results": raw}, f, indent=1)
    failed = [k for k, v in results.items() for vv in v.values() if not ok(vv)]
    return 1 if failed else 0



CLI_CONFIGS = [("default", []), ("--tail-tol 0", ["--tail-tol", "0"]),
               ("--precision double", ["--precision", "double"]),
               ("--margin 0", ["--margin", "0"]),
               ("--precision double --margin 0", ["--precision", "double", "--margin", "0"])]


def cli_default(build):
    """`svpsf correct` with its defaults on a foreign 1024² map (tools/bench/foreign.py: the
    quenched wire, Moffat 0.6 µm, β 1.1, whole-field support, 1000 photons), 2 threads, FFTW
    wisdom warmed by one untimed run per configuration; the best of two timed runs."""
    import tempfile
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import foreign  # noqa: E402
    svpsf = os.path.join(build, "tools", "svpsf", "svpsf")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        data = os.path.join(tmp, "wire")
        import contextlib
        with contextlib.redirect_stdout(sys.stderr):  # its JSON line is not the page's
            foreign.main(["make", "-o", data, "--scene", "wire", "--size", "1024", "--counts",
                          "1000"])
        for label, extra in CLI_CONFIGS:
            best = None
            for rep in range(3):
                o = os.path.join(tmp, "out")
                cmd = [svpsf, "correct", "--field", os.path.join(data, "field.npy"), "--pl",
                       os.path.join(data, "pl.npy"), "--psf", os.path.join(data, "psf.yaml"),
                       "-o", o, "--format", "npy", "--force", "--quiet", "--threads", "2",
                       "--wisdom", os.path.join(tmp, "wisdom")] + extra
                p = subprocess.run(cmd, capture_output=True, text=True)
                if p.returncode != 0:
                    best = {"error": p.stderr.strip()[-200:]}
                    break
                with open(os.path.join(o, "summary.json")) as f:
                    sm = json.load(f)
                r = {"total_s": sm["timings_s"]["total"], "transform_s": sm["timings_s"]["transform"],
                     "margin": sm["settings"].get("margin"),
                     "precision": sm["settings"].get("precision"),
                     "tail": (sm["results"].get("tail_step_px", 0),
                              sm["results"].get("tail_split_px", 0)),
                     "peak_mb": sm.get("peak_memory_bytes", 0) / 2 ** 20}
                if rep > 0 and (best is None or r["total_s"] < best["total_s"]):
                    best = r
            out[label] = best
            log(f"restore: correct {label}: {best}")
    return out


def render_cli(res, w):
    rows = res.get("cli") or {}
    if not rows:
        return
    rl = {t: res["rl"].get((1024, t)) or {} for t in (1, 2)}
    rl32 = {t: res["rl32"].get((1024, t)) or {} for t in (1, 2)}
    w("### `svpsf correct` with its defaults on a 1024² map\n")
    w("Target: ≤ 5 s on 2 threads. A foreign 1024² dataset (tools/bench/foreign.py: the "
      "quenched wire, Moffat 0.6 µm, β 1.1 with whole-field support, 1000 photons, light from "
      "a 6 µm margin); `correct` with its defaults (R, 75 iterations, margin auto = 26 px, "
      "single precision at this size) and with each default turned off; 2 threads, FFTW "
      "wisdom warmed by an untimed run, the best of two. The PL's and the numerator's RL run "
      "side by side, one FFT thread each (docs/model.md §3, \"Side by side\"). *bound, in "
      "order*: the two RLs' 2 × 75 iterations one after the other at the RL benchmark's 1024² "
      "2-thread bound per iteration above; *bound, side by side*: 75 iterations at its 1-thread "
      "bound (two such runs at once on two cores). Both are of its 2048² frame; with the margin "
      "the RLs transform on the view's frame, 2100², ≈ 5 % more points: docs/model.md §5. "
      "*ratio*: transform time / the side-by-side bound. *tail s / r0*: the PSF's far tail on "
      "a coarse grid (`--tail-tol`, default 10⁻³; docs/model.md §5): nodes every s px, the core "
      "exact to radius 2 r0 on a smaller frame; – the plain frame. The bounds are the plain "
      "frame's, so with the tail the ratio falls below 1: the tail does less transform work "
      "than the exact scheme's bound.\n")
    w("| correct | margin px | precision | tail s / r0 | total s | transform s | "
      "bound, in order s | bound, side by side s | ratio | target | peak MB |")
    w("|---|---|---|---|---|---|---|---|---|---|---|")
    for label, r in rows.items():
        if not r or "error" in r:
            w(f"| {label} | {(r or {}).get('error', 'failed')} | | | | | | | | | |")
            continue
        table = rl32 if r["precision"] == "single" else rl
        b2, b1 = table[2].get("bound_s"), table[1].get("bound_s")
        in_order = 150 * b2 if b2 else None
        side = 75 * b1 if b1 else None
        ratio = r["transform_s"] / side if side else None
        ts, tr = r.get("tail") or (0, 0)
        tail = f"{ts} / {tr}" if ts else "–"
        w(f"| {label} | {r['margin']} | {r['precision']} | {tail} | {r['total_s']:.2f} | "
          f"{r['transform_s']:.2f} | {fmt_s(in_order)} | {fmt_s(side)} | {fmt_s(ratio)} | "
          f"{verdict(r['total_s'] / 5.0, 1.0)} | {r['peak_mb']:.0f} |")
    w("")


def fmt_s(x):
    return "–" if x is None else f"{x:.2f}"


def render_ceiling(res, threads, sk_sizes, w):
    """The exact scheme's own ceiling (bench_ceiling) in double and single precision, against
    scikit-image computing in the same precision."""
    rows = [(k, v) for k, v in sorted(res["ceiling"].items()) if ok(v)]
    if not rows:
        return
    w("#### What the exact computation can reach here, in double and in single precision\n")
    w("`tools/bench/bench_ceiling` times one RL iteration of the same size done the way "
      "`svp_deconv_rl` does it (the pruned transforms, one product each, the pointwise RL "
      "steps) and nothing else, with FFTW_MEASURE plans, in double (fftw3) and in float "
      "(fftw3f) with the same code: the ceiling of this scheme on this machine. scikit-image "
      "0.19 computes in the precision of its input, so the fair peer of a single-precision "
      "svpsf is scikit-image on the same input cast to float32 (timed at 1024² only). "
      "`float diff` is the relative max difference of the double and float iterates after "
      "the timed iterations.\n")
    w("| N² | threads | frame | svpsf RL ms/iter | ceiling double ms | ceiling float ms | "
      "float gain | float diff | scikit-image f64 s | scikit-image f32 s | double vs f64 | "
      "float vs f32 |")
    w("|---|---|---|---|---|---|---|---|---|---|---|---|")
    best = {}
    for (size, t), c in rows:
        rl = res["rl"].get((size, t))
        rl_s = rl["iter_s"] if ok(rl) else None
        sk64 = res["skimage"].get((size, "full"))
        sk32 = res["skimage"].get((size, "full32"))
        s64 = sk64["iter_s"] if ok(sk64) else None
        s32 = sk32["iter_s"] if ok(sk32) else None
        up64 = s64 / rl_s if s64 and rl_s else None
        up32 = s32 / c["float_s"] if s32 else None
        if size == 1024:
            best[t] = (up64, up32)
        w(f"| {size}² | {c['threads']} | {c['frame'][0]}² | {ms(rl_s)} | {ms(c['double_s'])} | "
          f"{ms(c['float_s'])} | {c['speedup']:.2f}× | {c['float_rel_diff']:.1e} | "
          f"{f'{s64:.2f}' if s64 else '–'} | {f'{s32:.2f}' if s32 else '–'} | "
          f"{f'{up64:.0f}×' if up64 else '–'} | {f'{up32:.0f}×' if up32 else '–'} |")
    w("")
    if best:
        t_max = max(best)
        up64, up32 = best[t_max]
        if up64 and up32 and max(up64, up32) >= TARGET_SKIMAGE:
            w(f"At 1024² with {t_max} thread(s): double {up64:.0f}× scikit-image in double, "
              f"single-precision ceiling {up32:.0f}× scikit-image in single precision.\n")
        elif up64 and up32:
            w(f"At 1024² with {t_max} thread(s), the most this machine has, the library's double "
              f"RL is {up64:.0f}× scikit-image in double, and even the single-precision ceiling "
              f"is only {up32:.0f}× scikit-image in single precision: an exact full-frame RL "
              f"is FFT-bound (the library runs at its scheme's ceiling), so the {TARGET_SKIMAGE:.0f}× "
              "target needs more cores than this machine has (the speed-up grows with the "
              "threads: compare the 1- and 2-thread rows), not another implementation of the "
              "same arithmetic. Mixing precisions (svpsf in float against scikit-image in "
              "double) would pass it without being a like-for-like comparison.\n")


def render(res, threads, rl_sizes, sk_sizes, inv_size, skimage_note, quick):
    out = []
    w = out.append
    w("## Deconvolution and T⁻¹ (space-invariant PSF)\n")
    if quick:
        w("**Quick run** (--quick): 512² only, 2 repetitions.\n")
    w("### Method\n")
    w("- PSF: Moffat β = 1.1, FWHM 6.1 px (a real set-up's PL PSF: 610 nm at 100 nm per pixel), "
      "support 0 = the whole field of view, so the kernel is (2N − 1)² and every pixel reaches "
      "every other; zero boundary (linear convolution). The operator's padded frame is the "
      "smallest 2·3·5·7-smooth size ≥ 2N − 1 per axis (2N for these N).")
    w("- Input: the reference study's emission pattern (Gaussian spot of FWHM 0.6 N times a "
      "random chessboard of levels 0.1, 0.8, 1.0) blurred by the operator.")
    w("- FFT bound: the operator's own cached FFTW plans (FFTW_MEASURE, wisdom kept in "
      "`build/tools/bench/fftw.wisdom`), one r2c and one c2r of the padded frame timed in the "
      "same process right after each repetition of the solver (median of 5 runs each); one RL "
      "iteration needs H x and Hᵀ r, so its bound is 2 × (r2c + c2r) of the **full** frame.")
    w("- The library's own transforms are **pruned** (zero boundary): the image fills only the "
      "first N of the frame's 2N rows, so its r2c transforms those N rows and then every column, "
      "and its c2r every column and then only the N rows it keeps — about 3/4 of the work of "
      "the full pair the bound counts. A ratio below 1 is therefore possible and means the "
      "solver does less FFT work than the bound, not that the bound is wrong.")
    w("- Time per iteration = (t(k₂) − t(k₁)) / (k₂ − k₁) of whole solver calls, so set-up "
      "(buffers, Hᵀ1, start) cancels. Times are medians over the repetitions; the ratio is the "
      "median of the per-repetition ratios (solver / the bound measured right after it), "
      "which a change of machine load between repetitions moves less.")
    w("- Peak memory: the benchmark process's maximum resident set size (getrusage ru_maxrss), "
      "which includes the FFTW plans, the input images and the operator.")
    w("- Threads: svp_set_threads(T) sets both the FFTW threads (fftw3_omp) and the OpenMP "
      "loops.\n")

    # (a) RL per iteration
    w("### Richardson–Lucy per iteration vs the FFT bound\n")
    w(f"Target: ratio ≤ {TARGET_BOUND}.\n")
    w("| N² | threads | frame | RL ms/iter | r2c ms | c2r ms | bound ms | ratio | target | "
      "peak MB |")
    w("|---|---|---|---|---|---|---|---|---|---|")
    for size in rl_sizes:
        for t in threads:
            r = res["rl"].get((size, t))
            if not ok(r):
                w(f"| {size}² | {t} | – | {describe_error(r)} | | | | | | |")
                continue
            w(f"| {size}² | {r['threads']} | {r['frame'][0]}² | {ms(r['iter_s'])} | "
              f"{ms(r['r2c_s'])} | {ms(r['c2r_s'])} | {ms(r['bound_s'])} | {r['ratio']:.2f} | "
              f"{verdict(r['ratio'], TARGET_BOUND)} | {r['maxrss_mb']:.0f} |")
    w("")
    single = [(k, v) for k, v in sorted(res["rl32"].items()) if ok(v)]
    if single:
        w("The same with `svp_deconv_options.single_precision` (`--precision single`): the "
          "operator's transforms in float (fftw3f, the same pruned frame), the iteration in "
          "double. Its bound is the float r2c + c2r pair of the full frame (the library's cached "
          "float plans, rows then columns over every row), timed the same way; "
          "`vs double` is the time per iteration of the double run above divided by this one; "
          "`difference` is max |single − double| / max |double| after k₂ iterations of the same "
          "input (what single precision costs in accuracy; the tests bound it by 5·10⁻⁷ per "
          "iteration).\n")
        w("| N² | threads | RL single ms/iter | float r2c ms | float c2r ms | bound ms | ratio | "
          "vs double | difference | k₂ | peak MB |")
        w("|---|---|---|---|---|---|---|---|---|---|---|")
        for (size, t), r in single:
            d = res["rl"].get((size, t))
            gain = d["iter_s"] / r["iter_s"] if ok(d) else None
            w(f"| {size}² | {r['threads']} | {ms(r['iter_s'])} | {ms(r['r2c_s'])} | "
              f"{ms(r['c2r_s'])} | {ms(r['bound_s'])} | {r['ratio']:.2f} | "
              f"{f'{gain:.2f}×' if gain else '–'} | {r['single_rel_diff']:.1e} | {r['k2']} | "
              f"{r['maxrss_mb']:.0f} |")
        w("")

    # (b) scikit-image
    w("### Against scikit-image 0.19 `restoration.richardson_lucy`\n")
    w(f"Target: at least {TARGET_SKIMAGE:.0f}× faster at 1024². The same input image and the "
      "same PSF array (written to .npy by `svpsf_bench export`) are given to "
      "`skimage.restoration.richardson_lucy(image, psf, num_iter=k)` under /usr/bin/python3; it "
      "is slow, so only a few iterations are timed (k₁ = 1 and k₂ = 5, median of 3 repetitions) "
      "and the difference is scaled per iteration. scipy's FFT convolution inside it "
      "(`scipy.signal.convolve`, method chosen automatically: FFT for these kernels) runs on "
      "one thread and re-transforms the PSF on every call; its peak memory is that Python "
      "process's. The 30× target is a comparison with this single-threaded peer: the FFT work "
      "alone differs by about 5× (two 3072² convolutions of three real transforms each per "
      "iteration against svpsf's four row-pruned 2048² transforms), the rest is FFTW against "
      "scipy's pocketfft and the threads.\n")
    w("- **full-frame PSF**, the (2N − 1)² kernel of the operator above: scikit-image's "
      "zero-padded 'same' convolution with it is the same linear operator as svpsf's zero "
      "boundary, so this compares the library's own RL (`svp_deconv_rl`: floored denominator, "
      "boundary weights) with scikit-image's on one problem.")
    w("- **image-size PSF**, the same Moffat cut to (N − 1)², the largest kernel "
      "`svp_skimage_richardson_lucy` (the `--compat skimage` mode, which reproduces "
      "scikit-image's numbers) accepts: compat mode against scikit-image, same numbers out.\n")
    if skimage_note:
        w(f"Note: {skimage_note}\n")
    w("| N² | PSF | scikit-image s/iter | its peak MB | svpsf | threads | svpsf ms/iter | "
      "speed-up | target |")
    w("|---|---|---|---|---|---|---|---|---|")
    for size in sk_sizes:
        for kernel, label, table, name in (("full", f"{2 * size - 1}²", "rl", "RL"),
                                           ("image", f"{size - 1}²", "compat", "compat")):
            sk = res["skimage"].get((size, kernel))
            sk_s = sk["iter_s"] if ok(sk) else None
            for t in threads:
                r = res[table].get((size, t))
                r_s = r["iter_s"] if ok(r) else None
                up = sk_s / r_s if sk_s and r_s else None
                sk_cell = f"{sk_s:.2f}" if sk_s else describe_error(sk)
                mem_cell = f"{sk['maxrss_mb']:.0f}" if ok(sk) else "–"
                tgt = verdict(up, TARGET_SKIMAGE, False) if size == 1024 and kernel == "full" \
                    else "–"
                w(f"| {size}² | {label} | {sk_cell} | {mem_cell} | {name} | {t} | "
                  f"{ms(r_s) if r_s else describe_error(r)} | {f'{up:.0f}×' if up else '–'} | "
                  f"{tgt} |")
            if kernel == "full":
                # single precision against scikit-image in single precision (float32 input);
                # where that was not timed, against its double run, marked as mixed
                sk32 = res["skimage"].get((size, "full32"))
                peer = sk32 if ok(sk32) else sk
                mixed = not ok(sk32)
                p_s = peer["iter_s"] if ok(peer) else None
                for t in threads:
                    r = res["rl32"].get((size, t))
                    r_s = r["iter_s"] if ok(r) else None
                    if r_s is None:
                        continue
                    up = p_s / r_s if p_s else None
                    tgt = verdict(up, TARGET_SKIMAGE, False) \
                        if size == 1024 and not mixed else "–"
                    peer_mem = f"{peer['maxrss_mb']:.0f}" if ok(peer) else "–"
                    w(f"| {size}² | {label}, {'float64 (mixed)' if mixed else 'float32'} input | "
                      f"{f'{p_s:.2f}' if p_s else '–'} | {peer_mem} | RL single | {t} | "
                      f"{ms(r_s)} | {f'{up:.0f}×' if up else '–'} | {tgt} |")
    w("")
    render_ceiling(res, threads, sk_sizes, w)
    compat_rows = [(k, v) for k, v in res["compat"].items() if ok(v)]
    if compat_rows:
        w("The compatibility mode against the FFT bound of its own zero-padded frame "
          "(not a target; it follows scikit-image's arithmetic step by step):\n")
        w("| N² | threads | kernel | frame | compat ms/iter | bound ms | ratio | peak MB |")
        w("|---|---|---|---|---|---|---|---|")
        for (size, t), c in sorted(compat_rows):
            w(f"| {size}² | {t} | {c['kernel']}² | {c['frame'][0]}² | {ms(c['iter_s'])} | "
              f"{ms(c['bound_s'])} | {c['ratio']:.2f} | {c['maxrss_mb']:.0f} |")
        w("")

    # (c) inverse transform
    w(f"### T⁻¹ (R&W, 75 RL iterations) on a {inv_size}² map\n")
    w(f"Target: ratio ≤ {TARGET_BOUND}. The bound is the transforms T⁻¹ needs, as full r2c + "
      "c2r pairs of the operator's padded frame: 1 + 75 × 2 for RL on Ĩ (Hᵀ1 once, H and Hᵀ per "
      "iteration) plus what the Wiener on B̃Ĩ used. With the zero boundary the Wiener solves "
      "the linear operator's Tikhonov problem by conjugate gradients preconditioned with the "
      "Wiener filter on the same frame (docs/model.md §6): 1 + 3 pairs per CG step (H, Hᵀ, "
      "preconditioner); the library counts them and the bound includes exactly that count "
      "(`W steps` / `W pairs`). Before this, the Wiener filtered once in a mirror frame, which "
      "was cheap but wrong for zero-boundary data (field error > 1). `RL alone` and "
      "`Wiener alone` are the two deconvolutions called directly on the same inputs, for the "
      "breakdown.\n")
    w("| threads | T⁻¹ s | RL alone s | Wiener alone s | W steps | W pairs | bound s | ratio | "
      "target | field error RW | field error W | peak MB |")
    w("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for t in threads:
        r = res["inverse"].get(t)
        if not ok(r):
            w(f"| {t} | {describe_error(r)} | | | | | | | | | | |")
            continue
        w(f"| {r['threads']} | {r['total_s']:.2f} | {r['rl_s']:.2f} | {r['wiener_s']:.3f} | "
          f"{r.get('wiener_steps', '–')} | {r.get('wiener_pairs', '–')} | "
          f"{r['bound_s']:.2f} | {r['ratio']:.2f} | {verdict(r['ratio'], TARGET_BOUND)} | "
          f"{r['field_err_rel']:.2g} | {r.get('field_err_rel_w', float('nan')):.2g} | "
          f"{r['maxrss_mb']:.0f} |")
    w("\n`field error`: max |B − B_true| / max |B_true| where the true PL is above 10 % of its "
      "peak, after T⁻¹(T(B)) without noise, on this sharp-edged chessboard with the zero "
      "boundary and the default balance 10⁻³ (a sanity figure, not a test; the tests assert "
      "the round trip on their own cases): `RW` is the timed R&W, `W` the same T⁻¹ with the "
      "Wiener on both (untimed). R&W divides a 75-iteration RL map of Ĩ by a Wiener map of B̃Ĩ, "
      "which resolve the pixel-sharp chessboard edges differently, so its error beside the "
      "edges is large whatever the boundary (tests/test_transform.c, test_round_trip: 18.9 % "
      "with 1000 iterations and the mirror boundary); W's two maps share one regularisation "
      "and the ratio cancels it.\n")
    render_cli(res, w)
    # (d) accelerated RL
    w(f"### Accelerated Richardson–Lucy: time to plain RL's 100-iteration error\n")
    w(f"Target: ≤ {TARGET_ACCEL:.0%} of plain RL's time. Noiseless data (the input above, "
      "zero boundary); plain RL's relative L2 error after 100 iterations, then the fewest "
      "Biggs–Andrews iterations that reach it (bisection on the count; docs/model.md §6), both "
      "timed as whole solver calls, plain and accelerated in turn in each repetition; the times "
      "are medians, the ratio the median of the repetitions' ratios (15 repetitions at 256², 7 "
      "at 512², 3 at 1024²), so that a change of load between the two lands on both. On noisy data the extrapolation reaches the "
      "over-fitted regime sooner as well: on the foreign data of docs/accuracy.md 30 "
      "accelerated iterations tie with the default's 75 plain ones, but the reference study "
      "got worse with them (docs/model.md §6): it is an option, not the default.\n")
    w("| N² | threads | plain: iterations | s | error | accelerated: iterations | s | error | "
      "time ratio | target |")
    w("|---|---|---|---|---|---|---|---|---|---|")
    for (size, t), r in sorted(res["rlaccel"].items()):
        if not ok(r):
            w(f"| {size}² | {t} | {describe_error(r)} | | | | | | | |")
            continue
        ratio = r.get("ratio", r["accel_seconds"] / r["plain_seconds"])
        w(f"| {size}² | {t} | {r['plain_iterations']} | {r['plain_seconds']:.3f} | "
          f"{r['plain_error']:.4g} | {r['accel_iterations']} | {r['accel_seconds']:.3f} | "
          f"{r['accel_error']:.4g} | {ratio:.2f} | {verdict(ratio, TARGET_ACCEL)} |")
    w("")
    notes = os.path.join(ROOT, "tools", "bench", "analysis.md")
    if os.path.exists(notes):
        with open(notes) as f:
            w(f.read().rstrip() + "\n")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    sys.exit(main())
