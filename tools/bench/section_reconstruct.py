#!/usr/bin/python3
"""Benchmark section: the magnetisation from B_z by the Fourier and the support method.

usage: section_reconstruct.py [--build DIR] [--quick]

Runs `tools/bench/bench_scene recon` (build it first) at 256², 512² and 1024² (--quick: 128²,
256²) and prints its markdown section of docs/performance.md on stdout; progress on stderr.
About 2 minutes on 2 idle cores.
"""
import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from benchlib import ROOT, built, describe_error, loadavg, log, ok, run_json  # noqa: E402
from benchlib import sig as f  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--build", default=os.path.join(ROOT, "build"))
    ap.add_argument("--quick", action="store_true", help="128² and 256², 1 repetition")
    args = ap.parse_args()
    exe = built(args.build, "tools", "bench", "bench_scene")
    sizes = [128, 256] if args.quick else [256, 512, 1024]
    reps = 1 if args.quick else 3
    load0 = loadavg()
    runs = {}
    for n in sizes:
        log(f"recon: {n}²")
        runs[n] = run_json([exe, "recon", "--size", str(n), "--threads", "2", "--reps",
                            str(reps)])
    sys.stdout.write(render(runs, sizes, reps, args.quick, load0, loadavg()))
    return 1 if any(not ok(r) for r in runs.values()) else 0


def render(runs, sizes, reps, quick, load0, load1):
    out = []
    w = out.append
    w("## Source reconstruction: the magnetisation by the Fourier and the support method\n")
    if quick:
        w("**Quick run** (--quick): small sizes, 1 repetition.\n")
    w("- Data: the closed-form B_z of a thin square flake of 1 mA (side 0.5 N + 0.5 px, its edges "
      "a quarter pixel off the pixel grid), 100 nm pixels, standoff 100 nm, written in the "
      "benchmark (not by the library); `tools/bench/bench_scene.c`, mode `recon`.")
    w("- Methods ([model.md](model.md) §11): Fourier (the padded map's spectrum divided by the "
      "transfer function, the outermost ring set to zero) and support (least squares for the "
      "m_z on the view, conjugate gradients preconditioned by the Fourier inverse, tolerance "
      "10⁻⁹). Both with the Hann window and the ×2 padded canvas.")
    w("- Bound: the transform pairs (r2c + c2r) of the canvas each method needs — Fourier 1, "
      "support 6 + 3 per step — times one pair's median time, measured in the same process. "
      f"Times: medians of {reps} run(s) after a warm-up, 2 threads, FFTW estimate planning; "
      f"machine load {load0} at the start, {load1} at the end.")
    w("- Error: median and largest |m_z − 1 mA| / 1 mA at least 1 µm inside the flake.\n")
    w("| size | canvas | one pair (ms) | Fourier (s) | × its bound | support (s) | steps | × its "
      "bound | support / Fourier | error Fourier, median / max % | error support, median / "
      "max % | peak MB |")
    w("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n in sizes:
        r = runs[n]
        if not ok(r):
            w(f"| {n}² | {describe_error(r)} | | | | | | | | | | |")
            continue
        pair = r["fft_pair_s"]
        w(f"| {n}² | {r['canvas']}² | {1e3 * pair:.2f} | {f(r['fourier_s'])} | "
          f"{r['fourier_s'] / pair:.2f} | {f(r['support_s'])} | {r['support_steps']} | "
          f"{r['support_s'] / (r['support_pairs'] * pair):.2f} | "
          f"{r['support_s'] / r['fourier_s']:.0f} | "
          f"{f(r['fourier_median_err_pct'])} / {f(r['fourier_max_err_pct'])} | "
          f"{f(r['support_median_err_pct'])} / {f(r['support_max_err_pct'])} | "
          f"{r['maxrss_mb']:.0f} |")
    w("")
    good = [runs[n] for n in sizes if ok(runs[n])]
    if good:
        r = good[-1]
        w(f"At {r['size']}² the support method takes {r['support_s'] / r['fourier_s']:.0f}× the "
          f"Fourier method's time, {r['support_s'] / (r['support_pairs'] * r['fft_pair_s']):.2f}× "
          f"the transforms its {r['support_steps']} steps need; its largest error inside the "
          f"flake is {r['fourier_max_err_pct'] / r['support_max_err_pct']:.1f}× smaller "
          "(an error in the map's outermost pixels also stays local: [model.md](model.md) "
          "§11).\n")
    return "\n".join(out) + "\n"


if __name__ == "__main__":
    sys.exit(main())
