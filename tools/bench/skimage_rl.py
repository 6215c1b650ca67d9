#!/usr/bin/python3
"""Time scikit-image's richardson_lucy on the benchmark's own input and PSF.

usage: skimage_rl.py IMAGE.npy PSF.npy K1 K2 REPS [float32]
Prints one JSON line: the median time per iteration, (t(K2) - t(K1)) / (K2 - K1) so the
setup cancels, and the peak resident memory of this process. scipy's FFT convolution runs on
one thread (scipy.signal.convolve has no workers argument). With float32 the image and the PSF
are cast to float32 first, and scikit-image 0.19 then computes in single precision.
"""
import json
import resource
import sys
import time

try:
    import numpy as np
    import skimage
    from skimage import restoration
except ImportError as e:  # the driver turns this into a note
    print(json.dumps({"error": "missing", "message": str(e)}))
    sys.exit(77)


def main():
    image = np.load(sys.argv[1])
    psf = np.load(sys.argv[2])
    k1, k2, reps = int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
    dtype = sys.argv[6] if len(sys.argv) > 6 else "float64"
    image, psf = image.astype(dtype), psf.astype(dtype)
    per_iter = []
    for _ in range(reps):
        t0 = time.perf_counter()
        restoration.richardson_lucy(image, psf, num_iter=k1)
        t1 = time.perf_counter()
        out = restoration.richardson_lucy(image, psf, num_iter=k2)
        t2 = time.perf_counter()
        per_iter.append(((t2 - t1) - (t1 - t0)) / (k2 - k1))
    print(json.dumps({
        "case": "skimage", "size": int(image.shape[0]), "kernel": list(psf.shape), "dtype": dtype,
        "skimage": skimage.__version__, "numpy": np.__version__, "k1": k1, "k2": k2,
        "reps": reps, "iter_s": float(np.median(per_iter)),
        "finite": bool(np.isfinite(out).all()),
        "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}))


if __name__ == "__main__":
    main()
