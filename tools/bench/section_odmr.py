#!/usr/bin/python3
"""Benchmark section: `svpsf fit-odmr` at 512² × 100 frequencies against the scene engine's fitter.

usage: section_odmr.py [--build DIR] [--quick]

Runs tools/bench/bench_scene in its `odmr` mode and the built `svpsf fit-odmr` program, and
prints its markdown section of docs/performance.md on stdout; progress on stderr. The stack is
the blurred ODMR cube of the scene section (bench_scene.c), without and with noise. In one
process, interleaved: the scene engine's call (svp_odmr_fit, the field alone, as `svpsf
simulate` makes it) and the fit of `svpsf fit-odmr` (svp_odmr_fit_maps with every map the
program writes: field, PL, contrast, linewidth, their σ, R², converged), on 2 threads and on 1
(whose maps must be bit-identical). Then the program end to end on the same cube written as a
100-page float32 TIFF: read, fit, write (float32 TIFF maps), from its summary.json. Then the
Python package's fit_odmr against the same library call made directly (its overhead per call).
About 2-3 min on 2 idle cores; --quick (128²) under half a minute.
"""
import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from benchlib import (ROOT, built, built_library, interleaved, loadavg, log, ok,  # noqa: E402
                      run_json)
from benchlib import sig as f  # noqa: E402

TARGET_RATIO = 1.5        # the issue's: fit-odmr within 1.5 x of the scene engine's fitter
SCENE_FIGURE = 3.2e5      # the scene engine's fits per second on 2 threads (scene section, 256²)
NOISES = (0.0, 0.002)     # shot-noise-like σ = S √(b · b_peak) (bench_scene odmr --noise S)


def cli_runs(svpsf, work, reps, extra=(), threads=2, out_name="fit"):
    """`svpsf fit-odmr` on work/stack.tif, reps times; per run the summary's timings."""
    runs = []
    for r in range(reps):
        out = os.path.join(work, out_name)
        cmd = [svpsf, "fit-odmr", os.path.join(work, "stack.tif"), "--frequencies",
               os.path.join(work, "freq.txt"), "-o", out, "--threads", str(threads), "--quiet",
               "--force", *extra]
        log(" ".join(os.path.relpath(c, ROOT) if c.startswith(ROOT) else c for c in cmd))
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.monotonic()
        p = subprocess.run(cmd, capture_output=True, text=True)
        wall = time.monotonic() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        if p.returncode != 0:
            log(f"  failed ({p.returncode}): {p.stderr.strip()}")
            return None
        with open(os.path.join(out, "summary.json")) as fh:
            s = json.load(fh)
        t = s.get("timings_s", {})
        runs.append({"wall": wall, "cpu": cpu, "read": t.get("read"), "fit": t.get("fit"),
                     "register": t.get("register"),
                     "max_shift": s["results"].get("register_max_shift_px"),
                     "write": t.get("write"), "total": t.get("total"),
                     "fits_per_second": s["results"].get("fits_per_second"),
                     "n_failed": s["results"].get("n_failed"),
                     "peak_mb": (s["peak_memory_bytes"] / 1e6 if s.get("peak_memory_bytes") else None)})
    return runs


def python_overhead(build, work, reps):
    """svpsf.fit_odmr against svp_odmr_fit_maps called through cffi with prebuilt structs,
    interleaved; the wrapper's own work with the library call stubbed out."""
    library = built_library(build)
    if not library:
        return None
    os.environ["SVPSF_LIBRARY"] = library
    sys.path.insert(0, os.path.join(ROOT, "python"))
    try:
        import numpy as np
        import svpsf
        from svpsf import ffi, lib
    except ImportError as e:
        log(f"python overhead skipped: {e}")
        return None
    svpsf.set_threads(2)
    stack = svpsf.read_stack(os.path.join(work, "stack.tif"))
    freq = np.loadtxt(os.path.join(work, "freq.txt"))
    nf, h, w = stack.shape
    keep = []

    def img(a):
        s = ffi.new("svp_image *")
        s.height, s.width = a.shape
        b = ffi.from_buffer("double[]", a)
        s.data = b
        keep.append((a, b, s))
        return s

    frames = ffi.new("svp_image *[]", [img(stack[i]) for i in range(nf)])
    fbuf = ffi.from_buffer("double[]", freq)
    cube = ffi.new("svp_cube *", {"width": w, "height": h, "n_freq": nf, "freq": fbuf,
                                  "frame": frames})
    odmr = ffi.new("svp_odmr *")
    lib.svp_odmr_defaults(odmr)
    opt = ffi.new("svp_odmr_fit_options *")
    lib.svp_odmr_fit_defaults(opt)
    maps = ffi.new("svp_odmr_maps *")
    outs = [np.empty((h, w)) for _ in range(10)]
    for name, a in zip(("field", "field_sigma", "baseline", "baseline_sigma", "contrast",
                        "contrast_sigma", "linewidth", "linewidth_sigma", "quality",
                        "converged"), outs):
        setattr(maps, name, img(a))
    nfail = ffi.new("size_t *")

    def raw():
        return lib.svp_odmr_fit_maps(odmr, cube, opt, maps, nfail)

    def wrapped():
        return svpsf.fit_odmr(stack, freq)

    log("python overhead: fit_odmr")
    wrapped(), raw()
    tw, tr = interleaved(wrapped, raw, reps)
    real = svpsf.lib

    class Stub:
        def __getattr__(self, a):
            return (lambda *args: 0) if a == "svp_odmr_fit_maps" else getattr(real, a)

    svpsf.lib = Stub()
    try:
        k = 20
        t0 = time.perf_counter()
        for _ in range(k):
            wrapped()
        own = (time.perf_counter() - t0) / k
    finally:
        svpsf.lib = real
    return {"c": statistics.median(tr), "wrapper": statistics.median(tw),
            "diff": statistics.median(a - b for a, b in zip(tw, tr)), "own": own,
            "size": (h, w, nf)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--build", default=os.path.join(ROOT, "build"))
    ap.add_argument("--quick", action="store_true", help="128², 1 repetition")
    args = ap.parse_args()
    exe = built(args.build, "tools", "bench", "bench_scene")
    svpsf = built(args.build, "tools", "svpsf", "svpsf")
    # idle OpenMP threads sleep instead of spinning (as the program's default does), so CPU
    # time counts work only
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    size = 128 if args.quick else 512
    points = 100
    reps = 1 if args.quick else 3
    work = os.path.join(args.build, "tools", "bench", "odmr")
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    load0 = loadavg()

    fits = {}
    for noise in NOISES:
        for t in (2, 1):
            log(f"odmr: {size}², {points} points, noise {noise}, {t} thread(s)")
            cmd = [exe, "odmr", "--size", str(size), "--points", str(points), "--threads", str(t),
                   "--reps", str(reps if t == 2 else 1), "--noise", str(noise)]
            if noise == NOISES[-1] and t == 2:
                cmd += ["--out", work]  # the noisy cube, for the program and Python
            fits[(noise, t)] = run_json(cmd)
    cli = cli_runs(svpsf, work, reps) if ok(fits[(NOISES[-1], 2)]) else None
    # --register: the frames aligned before the fit, on 2 threads and on 1 (the same maps)
    reg = None
    if cli:
        reg = {t: cli_runs(svpsf, work, 1, ["--register", "--format", "npy"], t, f"reg{t}")
               for t in (2, 1)}
        if reg[1] and reg[2]:
            with open(os.path.join(work, "reg1", "field.npy"), "rb") as a, \
                    open(os.path.join(work, "reg2", "field.npy"), "rb") as b:
                reg["same"] = a.read() == b.read()
    py = python_overhead(args.build, work, reps) if cli else None
    shutil.rmtree(work, ignore_errors=True)
    md = render(fits, cli, py, size, points, reps, args.quick, load0, loadavg(), reg)
    sys.stdout.write(md)
    try:
        with open(os.path.join(args.build, "tools", "bench", "results-odmr.json"), "w") as fh:
            json.dump({"fits": {f"{k[0]}/{k[1]}": v for k, v in fits.items()}, "cli": cli,
                       "python": py, "register": {str(k): v for k, v in (reg or {}).items()}},
                      fh, indent=1)
    except OSError:
        pass
    bad = [r for r in fits.values() if not ok(r)] or (cli is None)
    return 1 if bad else 0


def render(fits, cli, py, size, points, reps, quick, load0, load1, reg=None):
    out = []
    w = out.append
    w("## ODMR stacks: `svpsf fit-odmr` against the scene engine's fitter\n")
    if quick:
        w(f"**Quick run** (--quick): {size}², 1 repetition.\n")
    w("### Method\n")
    w(f"- Stack: the blurred ODMR cube of the scene section above at {size}² × {points} "
      "frequencies (the bias and sweep of `svpsf simulate`: the upper line ± 6 Γ; "
      "`tools/bench/bench_scene.c`, mode `odmr`), without noise and with shot-noise-like Gaussian "
      "noise σ = 0.002 √(b · b_peak) per frame, b a pixel's off-resonance PL (the dip is 2 % "
      "of b: 10 σ deep at the peak PL, 3 σ where b is a tenth of it; fixed seed).")
    w("- *Scene engine*: `svp_odmr_fit` with the field map alone, the call `svpsf simulate` "
      "makes. *fit-odmr*: `svp_odmr_fit_maps` with every map the program writes (field, PL, "
      "contrast, linewidth, their 1σ, R², converged), two lines about D (`--lines pair`, the "
      "default); *one line*: the same with `--lines one`. Interleaved in one process, median "
      f"of {reps} run(s) each on 2 threads, 1 run on 1 thread; the maps of 1 and 2 threads "
      "compared bit for bit (a hash of all 20 maps).")
    w(f"- *Program*: `svpsf fit-odmr stack.tif --frequencies freq.txt -o DIR --threads 2` on "
      f"the noisy cube written as a {points}-page float32 TIFF "
      f"({size * size * points * 4 / 1e6:.0f} MB) and its frequencies as text, float32 TIFF maps "
      f"out; stage times from its summary.json, median of {reps} run(s). Load average "
      f"{load0} before, {load1} after (2 cores, shared); `OMP_WAIT_POLICY=passive`.")
    w("- *CPU s*: the process's CPU time (all threads). On a shared machine wall-clock "
      "fits per second fall with the load; fits per CPU-second change little, and on 2 idle "
      "cores the fit runs at about 2 × that (the scene section's 2-thread figure was 2.05 × "
      "its 1-thread one).\n")
    w("### Fits per second\n")
    w("| noise | threads | scene engine (s) | fit-odmr fit (s) | ratio | scene fits/s | "
      "fit-odmr fits/s | scene / fit-odmr CPU s | fit-odmr fits per CPU-s | one line (s) | "
      "not converged | field = scene's | 1 = 2 threads |")
    w("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (noise, t), r in fits.items():
        if not ok(r):
            w(f"| {noise:g} | {t} | failed ({r.get('error')}) | | | | | | | | | | |")
            continue
        other = fits.get((noise, 3 - t))
        same = "–" if not ok(other) else ("yes" if other["maps_hash"] == r["maps_hash"]
                                           else "**no**")
        w(f"| {'none' if noise == 0 else f'S = {noise:g}'} | {t} | {f(r['scene_seconds'])} | {f(r['pair_seconds'])} | "
          f"{r['pair_seconds'] / r['scene_seconds']:.2f} | {f(r['scene_fits_per_second'])} | "
          f"{f(r['pair_fits_per_second'])} | {f(r['scene_cpu_seconds'])} / "
          f"{f(r['pair_cpu_seconds'])} | {f(r['fits'] / r['pair_cpu_seconds'])} | "
          f"{f(r['one_seconds'])} | {r['pair_failed']} | "
          f"{'yes' if r['field_identical'] else '**no**'} | {same} |")
    w("")
    w("*ratio* = fit-odmr's time / the scene engine's on the same cube; *field = scene's*: the "
      "two calls' field maps are bit-identical (one code path; the maps beyond the field cost "
      "their writes and a 4 × 4 inverse per pixel).\n")
    if cli:
        w("### The program end to end\n")
        w("| run | read (s) | fit (s) | write (s) | total (s) | wall (s) | CPU s | fit's fits/s | "
          "not converged | peak MB |")
        w("|---|---|---|---|---|---|---|---|---|---|")
        for k, c in enumerate(cli):
            w(f"| {k + 1} | {f(c['read'])} | {f(c['fit'])} | {f(c['write'])} | {f(c['total'])} "
              f"| {f(c['wall'])} | {f(c['cpu'])} | {f(c['fits_per_second'])} | {c['n_failed']} | "
              f"{f(c['peak_mb'])} |")
        w("")
    if reg and reg.get(1) and reg.get(2):
        w("### Drift alignment (`--register`)\n")
        w("The same program with `--register --format npy` (each frame registered on the mean "
          "frame and moved back by Fourier interpolation before the fit; docs/model.md §10 "
          "\"Drift\"), one run each on 2 threads and on 1. This cube has no drift: the "
          "shifts are the registration's own scatter.\n")
        w("| threads | register (s) | fit (s) | total (s) | register / fit | largest shift (px) | "
          "field = other thread count's |")
        w("|---|---|---|---|---|---|---|")
        for t in (2, 1):
            c = reg[t][0]
            w(f"| {t} | {f(c['register'])} | {f(c['fit'])} | {f(c['total'])} | "
              f"{c['register'] / c['fit']:.2f} | {f(c['max_shift'])} | "
              f"{'yes' if reg.get('same') else '**no**'} |")
        w("")
    if py:
        h, wd, nf = py["size"]
        w("### The Python package\n")
        w(f"`svpsf.fit_odmr(stack, freq)` on the same stack (read with `svpsf.read_stack`, "
          f"{nf} × {h} × {wd}) against `svp_odmr_fit_maps` called through cffi with structs made "
          f"beforehand, interleaved, medians of {reps}; own work: the wrapper with the library "
          "call stubbed out (20 calls).\n")
        w("| call | C call | wrapper | wrapper − C (median) | own work | overhead | "
          "target ≤ 5 % |")
        w("|---|---|---|---|---|---|---|")
        ov = py["own"] / py["c"]
        w(f"| fit_odmr (pair, every map) | {py['c']:.3f} s | {py['wrapper']:.3f} s | "
          f"{py['diff'] * 1e3:+.1f} ms | {py['own'] * 1e3:.2f} ms | {ov * 100:.3f} % | "
          f"{'met' if ov <= 0.05 else '**missed**'} |")
        w("")
    w("### Targets\n")
    r2 = fits.get((NOISES[-1], 2))
    r0 = fits.get((NOISES[0], 2))
    for r, what in ((r0, "noiseless"), (r2, "noisy")):
        if ok(r):
            ratio = r["pair_seconds"] / r["scene_seconds"]
            w(f"- fit-odmr's fit within {TARGET_RATIO}× of the scene engine's fitter on the same "
              f"{what} cube, same process: {ratio:.2f}× — "
              f"{'met' if ratio <= TARGET_RATIO else '**missed**'}")
    if cli and ok(r2):
        fit_s = statistics.median(c["fit"] for c in cli)
        ratio = fit_s / r2["scene_seconds"]
        w(f"- the program's fit stage (median {fit_s:.3g} s, "
          f"{size * size / fit_s:.3g} fits/s) against the scene engine in the bench process "
          f"({r2['scene_seconds']:.3g} s): {ratio:.2f}× — "
          f"{'met' if ratio <= TARGET_RATIO else '**missed**'}")
    if ok(r0):
        need = SCENE_FIGURE / TARGET_RATIO
        got = r0["pair_fits_per_second"]
        idle = 2 * r0["fits"] / r0["pair_cpu_seconds"]
        w(f"- against the scene section's figure ({SCENE_FIGURE:.2g} fits/s on 2 threads, so "
          f"≥ {need:.3g} fits/s), the noiseless cube: wall clock {got:.3g} fits/s at load "
          f"{load0}–{load1} — {'met' if got >= need else '**missed**'}; 2 × fits per "
          f"CPU-second (2 idle cores) {idle:.3g} — {'met' if idle >= need else '**missed**'}")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    sys.exit(main())
