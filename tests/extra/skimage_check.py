#!/usr/bin/python3
"""Cross-check of svpsf's deconvolution against independent references.

  1. scikit-image 0.19's restoration.wiener and restoration.richardson_lucy (defaults, with
     their clipping) against svp_skimage_wiener / svp_skimage_richardson_lucy: random images
     and PSFs, odd and even PSF sizes, non-square images, values beyond [-1, 1] so the clipping
     matters, several balances and iteration counts.
  2. Our own Richardson-Lucy (periodic boundary, boundary weights on, default floor) and
     Wiener-Hunt (periodic) against plain numpy FFT implementations written here.

Fails when any maximum relative difference, max|ours - ref| / max|ref|, exceeds 1e-6.
Usage: /usr/bin/python3 skimage_check.py PATH_TO_skimage_driver
Exits 77 (meson: skipped) with a message when numpy, scipy or scikit-image 0.19 is missing.
"""
import os
import struct
import subprocess
import sys
import tempfile

SKIP = 77
TOLERANCE = 1e-6

try:
    import numpy as np
    import scipy  # noqa: F401  (skimage's richardson_lucy needs scipy.signal)
    import skimage
    from skimage import restoration
except ImportError as exc:
    print(f"SKIP: the cross-check needs numpy, scipy and scikit-image for /usr/bin/python3 "
          f"({exc}); install them with: apt-get install python3-skimage")
    sys.exit(SKIP)

if not skimage.__version__.startswith("0.19"):
    print(f"SKIP: the compatibility target is scikit-image 0.19, found {skimage.__version__}")
    sys.exit(SKIP)


def write_raw(path, a):
    a = np.ascontiguousarray(a, dtype="<f8")
    with open(path, "wb") as f:
        f.write(b"SVPD" + struct.pack("<ii", a.shape[0], a.shape[1]) + a.tobytes())


def read_raw(path):
    with open(path, "rb") as f:
        data = f.read()
    assert data[:4] == b"SVPD", path
    h, w = struct.unpack("<ii", data[4:12])
    return np.frombuffer(data[12:], dtype="<f8").reshape(h, w)


class Driver:
    def __init__(self, exe, tmp):
        self.exe, self.tmp, self.count = exe, tmp, 0

    def run(self, mode, image, psf, param):
        self.count += 1
        base = os.path.join(self.tmp, f"case{self.count}")
        write_raw(base + ".image", image)
        write_raw(base + ".psf", psf)
        res = subprocess.run([self.exe, mode, base + ".image", base + ".psf", repr(param),
                              base + ".out"], capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"driver {mode} failed ({res.returncode}): {res.stderr.strip()}")
        return read_raw(base + ".out")


def rel_diff(ours, ref):
    scale = np.max(np.abs(ref))
    return np.max(np.abs(ours - ref)) / (scale if scale > 0 else 1.0)


def periodic_otf(psf, shape):
    """OTF of the unit-sum PSF centred at (kh // 2, kw // 2) on a periodic frame."""
    k = psf / psf.sum()
    pad = np.zeros(shape)
    pad[:k.shape[0], :k.shape[1]] = k
    pad = np.roll(pad, (-(k.shape[0] // 2), -(k.shape[1] // 2)), axis=(0, 1))
    return np.fft.rfft2(pad)


def rl_periodic_reference(y, psf, num_iter, floor=1e-9):
    """x <- x * H^T(y / max(Hx, floor max y)) / H^T 1, started at mean(y)."""
    otf = periodic_otf(psf, y.shape)
    conv = lambda a: np.fft.irfft2(np.fft.rfft2(a) * otf, s=y.shape)
    corr = lambda a: np.fft.irfft2(np.fft.rfft2(a) * np.conj(otf), s=y.shape)
    norm = corr(np.ones_like(y))
    x = np.full_like(y, y.mean())
    for _ in range(num_iter):
        x = x * corr(y / np.maximum(conv(x), floor * y.max())) / norm
    return x


def wiener_periodic_reference(y, psf, balance):
    otf = periodic_otf(psf, y.shape)
    v = np.arange(y.shape[0])[:, None]
    u = np.arange(otf.shape[1])[None, :]
    lap = 4 - 2 * np.cos(2 * np.pi * u / y.shape[1]) - 2 * np.cos(2 * np.pi * v / y.shape[0])
    filt = np.conj(otf) / (np.abs(otf) ** 2 + balance * lap ** 2)
    return np.fft.irfft2(filt * np.fft.rfft2(y), s=y.shape)


def main():
    if len(sys.argv) != 2:
        print(__doc__)
        return 2
    exe = sys.argv[1]
    rng = np.random.default_rng(20240519)
    worst, failures = 0.0, []

    def check(label, ours, ref, must_clip=False):
        nonlocal worst
        d = rel_diff(ours, ref)
        worst = max(worst, d)
        clipped = int(np.sum(np.abs(ref) == 1.0))
        print(f"{label:58s} max rel diff {d:.3g}" + (f"  ({clipped} clipped)" if must_clip else ""))
        if not d <= TOLERANCE:
            failures.append(f"{label}: {d:.3g}")
        if must_clip and clipped == 0:
            failures.append(f"{label}: the case was meant to exercise clipping but nothing clipped")

    with tempfile.TemporaryDirectory(prefix="svpsf-skimage-") as tmp:
        drv = Driver(exe, tmp)

        # image shape, psf shape, image scale (beyond 1: clipping), balances
        wiener_cases = [((32, 48), (5, 5), 0.9, [0.01, 1.0]),
                        ((41, 29), (4, 6), 0.9, [0.1]),
                        ((30, 30), (7, 2), 0.9, [1.0, 10.0]),
                        ((25, 36), (3, 3), 4.0, [0.05, 0.5]),
                        ((19, 23), (1, 1), 3.0, [0.2]),
                        ((24, 20), (6, 9), 2.0, [0.003])]
        for shape, kshape, amp, balances in wiener_cases:
            image = amp * (2 * rng.random(shape) - 1)
            psf = rng.random(kshape)
            psf /= psf.sum()
            for balance in balances:
                ref = restoration.wiener(image, psf, balance)
                ours = drv.run("wiener", image, psf, balance)
                check(f"wiener image {shape} psf {kshape} balance {balance}", ours, ref,
                      must_clip=amp > 1)
        # skimage's quirk: a PSF shaped like the half spectrum is taken as a transfer function
        image = rng.random((16, 20))
        psf = 0.2 + rng.random((16, 11))
        check("wiener psf (16, 11) read as a transfer function",
              drv.run("wiener", image, psf, 0.05), restoration.wiener(image, psf, 0.05))

        rl_cases = [((32, 48), (5, 5), 0.9, [1, 10]),
                    ((41, 29), (4, 6), 0.9, [5, 20]),
                    ((30, 30), (2, 7), 3.0, [15]),
                    ((27, 40), (6, 3), 2.0, [8]),
                    ((20, 20), (1, 1), 1.5, [3])]
        for shape, kshape, amp, iters in rl_cases:
            image = amp * rng.random(shape)
            psf = rng.random(kshape)
            psf /= psf.sum()
            for num_iter in iters:
                ref = restoration.richardson_lucy(image, psf, num_iter)
                ours = drv.run("rl", image, psf, num_iter)
                check(f"richardson_lucy image {shape} psf {kshape} num_iter {num_iter}", ours,
                      ref, must_clip=amp > 1)
        # a PSF that is not normalised is used as given
        image = rng.random((22, 26))
        psf = 0.5 * rng.random((4, 4))
        check("richardson_lucy unnormalised psf (4, 4), 6 iterations",
              drv.run("rl", image, psf, 6), restoration.richardson_lucy(image, psf, 6))

        # our own RL and Wiener (periodic) against the numpy references above
        for shape, kshape, num_iter in [((32, 40), (7, 7), 25), ((33, 27), (4, 5), 10)]:
            y = 0.1 + rng.random(shape)
            psf = rng.random(kshape)
            check(f"svp_deconv_rl periodic {shape} psf {kshape} {num_iter} iterations",
                  drv.run("rl-periodic", y, psf, num_iter),
                  rl_periodic_reference(y, psf, num_iter))
            for balance in [1e-3, 0.3]:
                check(f"svp_deconv_wiener periodic {shape} psf {kshape} balance {balance}",
                      drv.run("wiener-periodic", y, psf, balance),
                      wiener_periodic_reference(y, psf, balance))

    print(f"scikit-image {skimage.__version__}, numpy {np.__version__}: {drv.count} cases, "
          f"worst max relative difference {worst:.3g} (tolerance {TOLERANCE:g})")
    if failures:
        print("FAILED:\n  " + "\n  ".join(failures))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
