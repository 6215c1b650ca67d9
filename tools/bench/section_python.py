#!/usr/bin/python3
"""Benchmark section: the Python package's overhead per call at 512², and batch runs on Dask.

usage: section_python.py [--build DIR] [--quick]

Prints its markdown section of docs/performance.md on stdout (tools/bench/run assembles the
file); progress on stderr. Needs Debian's python3-cffi (and python3-distributed for the batch
part); runs svpsf from python/ over the built library (build/libsvpsf.so.MAJOR).

Overhead: the wrapper (svpsf.correct / forward / deconvolve with a prebuilt Blur) against the
same library call made directly through cffi with prebuilt structs, interleaved call by call
(median of the differences), and the wrapper's own work alone (the library call replaced by a
stub that returns at once). Batch: 8 datasets of 512² corrected by svpsf.batch on a Dask
LocalCluster of 1 and of 2 single-threaded workers (cluster start-up excluded), interleaved.
"""
import argparse
import os
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from benchlib import ROOT, built_library, interleaved, loadavg, log  # noqa: E402

TARGET_OVERHEAD = 0.05  # the issue's: Python overhead per call <= 5 % at 512²
TARGET_SPEEDUP = 1.6    # the issue's: 2 workers >= 1.6 x one worker on 8 datasets


def setup(build):
    library = built_library(build)
    if not library:
        sys.exit(f"no libsvpsf.so.* in {build}: build first")
    os.environ["SVPSF_LIBRARY"] = library
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    sys.path.insert(0, os.path.join(ROOT, "python"))


def maps(n, seed=0):
    import numpy as np

    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n].astype(float)
    pl = 1.0 - 0.85 * np.exp(-0.5 * ((x - 0.55 * n) / (0.04 * n)) ** 2)
    pl *= 0.6 + 0.4 * np.cos(2 * np.pi * y / n) ** 2
    pl = rng.poisson(2000 * pl) / 2000.0
    field = 1e-4 * np.tanh((x - 0.4 * n) / 6.0) + 2e-6 * rng.standard_normal((n, n))
    return pl, field


class _Stub:
    """lib with one function replaced by an immediate return: the wrapper's own cost."""

    def __init__(self, lib, name):
        self._lib, self._name = lib, name

    def __getattr__(self, a):
        if a == self._name:
            return lambda *args: 0
        return getattr(self._lib, a)


def overhead(reps):
    import numpy as np
    import svpsf
    from svpsf import ffi, lib

    n = 512
    svpsf.set_threads(2)
    psf = svpsf.PSF("moffat", fwhm=6.1, beta=1.5)
    blur = svpsf.Blur(psf, (n, n))
    pl, field = svpsf.forward(*maps(n), blur)[:2]  # measured maps: T of the truth
    rows = []

    # raw calls: the structs made once, outside the timing
    keep = []

    def img(a):
        s = ffi.new("svp_image *")
        s.height, s.width = a.shape
        b = ffi.from_buffer("double[]", a)
        s.data = b
        keep.append((a, b))
        return s

    outs = [np.empty((n, n)) for _ in range(3)]
    ipl, ifl = img(pl), img(field)
    opl, ofl, oval = (img(o) for o in outs)
    fin = ffi.new("svp_image *[1]", [ifl])
    fout = ffi.new("svp_image *[1]", [ofl])
    copt = ffi.new("svp_correct_options *")
    lib.svp_correct_defaults(copt)
    copt.keep_doubtful = 1
    copt.method = lib.SVP_METHOD_RW
    nmiss = ffi.new("size_t *")
    dopt = ffi.new("svp_deconv_options *")
    lib.svp_deconv_defaults(dopt)

    cases = [
        ("correct (R&W, 75 RL iterations)", "svp_inverse_transform",
         lambda: svpsf.correct(pl, field, blur, method="rw", keep_doubtful=True),
         lambda: lib.svp_inverse_transform(blur._ptr, ipl, fin, 1, copt, opl, fout, oval, nmiss)),
        ("forward (T)", "svp_forward_transform",
         lambda: svpsf.forward(pl, field, blur),
         lambda: lib.svp_forward_transform(blur._ptr, ipl, fin, 1, opl, fout, oval)),
        ("deconvolve (Wiener–Hunt, zero boundary: CG)", "svp_deconv_wiener",
         lambda: svpsf.deconvolve(pl, blur),
         lambda: lib.svp_deconv_wiener(blur._ptr, ipl, dopt, opl)),
    ]
    for name, fn, wrapped, raw in cases:
        log(f"python overhead: {name}")
        wrapped(), raw()  # warm
        tw, tr = interleaved(wrapped, raw, reps)
        diff = statistics.median(w - r for w, r in zip(tw, tr))
        # the wrapper's own work, the library call stubbed out
        real = svpsf.lib
        svpsf.lib = _Stub(real, fn)
        try:
            k = 200
            t0 = time.perf_counter()
            for _ in range(k):
                wrapped()
            own = (time.perf_counter() - t0) / k
        finally:
            svpsf.lib = real
        c = statistics.median(tr)
        rows.append((name, c, statistics.median(tw), diff, own))
    return rows


def batch_speedup(reps, size, count, iterations):
    import numpy as np
    import svpsf
    from dask.distributed import Client, LocalCluster
    from svpsf import batch

    with tempfile.TemporaryDirectory() as tmp:
        data = os.path.join(tmp, "data")
        os.makedirs(data)
        psf = svpsf.PSF("moffat", fwhm=6.1, beta=1.5)
        for i in range(count):
            d = os.path.join(data, "d%02d" % i)
            os.makedirs(d)
            pl, field = maps(size, seed=i)
            a = svpsf.forward(pl, field, psf)
            np.save(os.path.join(d, "pl.npy"), a.pl)
            np.save(os.path.join(d, "field.npy"), a.fields)
        with open(os.path.join(data, "psf.yaml"), "w") as f:
            f.write("pixel_um: 0.1\npsf: {model: moffat, fwhm_um: 0.61, beta: 1.5}\n")
        opts = {"method": "rw", "iterations": iterations}
        times = {1: [], 2: []}
        clusters = {}
        try:
            for w in (1, 2):
                cl = LocalCluster(n_workers=w, threads_per_worker=1, processes=True,
                                  dashboard_address=":0",
                                  env={"OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "passive"})
                clusters[w] = (cl, Client(cl))
            k = 0
            for _ in range(reps):
                for w in (1, 2):
                    out = os.path.join(tmp, "out%d" % k)
                    k += 1
                    log(f"batch: {count} datasets of {size}² on {w} worker(s)")
                    t0 = time.perf_counter()
                    rows = batch.run([data], out, psf=os.path.join(data, "psf.yaml"),
                                     options=opts, client=clusters[w][1])
                    times[w].append(time.perf_counter() - t0)
                    bad = [r for r in rows if r["status"] != "ok"]
                    if bad:
                        raise RuntimeError(bad[0]["message"])
            # the serial batch in this process, one thread, for reference
            t0 = time.perf_counter()
            batch.run([data], os.path.join(tmp, "serial"), psf=os.path.join(data, "psf.yaml"),
                      options=opts, threads=1)
            serial = time.perf_counter() - t0
        finally:
            for cl, c in clusters.values():
                c.close()
                cl.close()
    return times, serial


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--build", default=os.path.join(ROOT, "build"))
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    setup(args.build)
    load0 = loadavg()
    rows = overhead(3 if args.quick else 9)
    load1 = loadavg()
    out = ["## Python package: overhead per call, batch runs on Dask\n",
           "`tools/bench/section_python.py`: the Python package `svpsf` (python/, cffi in ABI "
           "mode, docs/python.md) over the library built here, 512² images, 2 threads, "
           "FFTW_MEASURE plans, a prebuilt `svpsf.Blur`. *C call*: the library function called "
           "through cffi with structs made beforehand; *wrapper*: the `svpsf` function doing "
           "everything a user call does (checks, struct building, output arrays, results); "
           "interleaved call by call, medians of %d. *Own work*: the wrapper with the library "
           "call stubbed out (200 calls). Load average %s before, %s after.\n"
           % (3 if args.quick else 9, load0, load1),
           "| call | C call | wrapper | wrapper − C (median) | own work | overhead | target ≤ 5 % |",
           "|---|---|---|---|---|---|---|"]
    for name, c, w, diff, own in rows:
        ratio = own / c
        out.append("| %s | %.1f ms | %.1f ms | %+.2f ms | %.0f µs | %.3f %% | %s |"
                   % (name, 1e3 * c, 1e3 * w, 1e3 * diff, 1e6 * own, 100 * ratio,
                      "met" if ratio <= TARGET_OVERHEAD else "NOT met"))
    out.append("")
    out.append("*Overhead* = own work / C call: what Python adds to each call, measured without "
               "the noise of the C call's own time (the wrapper − C column carries that noise, "
               "of either sign, on a shared machine).\n")
    try:
        import dask.distributed  # noqa: F401
    except ImportError:
        out.append("Batch runs: not measured (python3-distributed is not installed).\n")
        print("\n".join(out))
        return
    size, count, iters = (256, 8, 75) if args.quick else (512, 8, 75)
    load2 = loadavg()
    times, serial = batch_speedup(1 if args.quick else 2, size, count, iters)
    load3 = loadavg()
    t1, t2 = min(times[1]), min(times[2])
    speedup = t1 / t2
    out += ["### Batch: %d datasets of %d² on a Dask LocalCluster\n" % (count, size),
            "`svpsf.batch.run` (T⁻¹ R&W, %d RL iterations, FFTW_ESTIMATE plans: the batch "
            "default) on a LocalCluster of 1 and of 2 worker processes, one thread each "
            "(`OMP_NUM_THREADS=1`), cluster start-up excluded; best of %d interleaved runs. "
            "Load average %s before, %s after (this machine has 2 cores and is shared with "
            "other work during the run: the 2-worker time needs both cores free).\n"
            % (iters, len(times[1]), load2, load3),
            "| workers | batch time | per dataset | speed-up | target ≥ %.1f× |" % TARGET_SPEEDUP,
            "|---|---|---|---|---|",
            "| 1 | %.2f s | %.2f s | 1 | |" % (t1, t1 / count),
            "| 2 | %.2f s | %.2f s | %.2f× | %s |" % (t2, t2 / count, speedup,
                                                    "met" if speedup >= TARGET_SPEEDUP
                                                    else "NOT met"),
            "",
            "All runs: 1 worker %s s; 2 workers %s s. The same batch serially in one process "
            "(1 thread): %.2f s.\n" % (", ".join("%.2f" % t for t in times[1]),
                                       ", ".join("%.2f" % t for t in times[2]), serial)]
    print("\n".join(out))


if __name__ == "__main__":
    main()
