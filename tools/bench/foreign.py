#!/usr/bin/python3
"""Foreign data for svpsf: measured-like field and PL maps made by an independent forward model.

usage: foreign.py make -o DIR [--scene wire|chessboard|oxide|array] [--size N] [--counts C]
                       [--pixel-um P] [--fwhm-um F] [--beta B] [--fwhm-err E] [--beta-err E]
                       [--margin-um M] [--quench Q] [--gain G] [--offset O] [--read-noise R]
                       [--nan-fraction F] [--field-noise-ut S] [--seed S]

Nothing here calls svpsf: the blur is numpy's FFT convolution of a scene that extends
--margin-um beyond the view (so light enters the view from outside), cropped to the view,
with the model of docs/model.md §1-2 (PL-weighted averaging, eq. 2):

    Ĩ = (I ⊛ p)|view,    B̃ = ((B I) ⊛ p)|view / Ĩ

Then what a measurement adds: Poisson PL at a peak of --counts detected photons, written as a
camera's counts = G · photons + O + N(0, R²) (--gain, --offset, --read-noise; default 1, 0, 0:
the photons themselves), the field's fit noise σ_B = S · √(C / photons) (an ODMR Lorentzian fit's uncertainty
scales as linewidth / (contrast √photons); S is σ_B at the peak), NaN pixels (failed fits: a
random --nan-fraction and one 4 x 4 cluster). The PSF file written for the user may be wrong:
FWHM × (1 + fwhm_err), β × (1 + beta_err).

Scenes (0.1 µm pixels by default):
  wire        a 1 µm wide current strip (sheet current, Bz by Biot–Savart at 50 nm standoff,
              docs/model.md's sign conventions do not matter here: the field is what it is) whose
              metal quenches the PL to --quench (default 0.05: 20x darker), under a Gaussian
              illumination spot, plus a magnetic dipole (a flake) beside it; peak |Bz| 40 µT.
  chessboard  the reference study's emission pattern (a Gaussian spot times a random chessboard
              of levels 0.1, 0.8, 1.0 on 1 µm squares) under the dipole and the strip's field.
  oxide       the same field under the spot with an oxide ramp: the PL falls linearly from 1 to
              --quench across a 4 µm wide band left of the view's centre line (lit to its left,
              dark to its right).
  array       a field spread over the whole view: 3 x 3 dipoles of alternating sign 1.5 µm deep
              (flakes seen from a distance) at 0, ±0.66 of the half-width from the centre, under
              a broad spot (σ 0.9 of the half-width) whose PL an oxide's interference modulates:
              fringes of 8 µm period (tilted), from 1 down to --quench. Where the field is, the
              PSF of a space-variant map differs from its centre's (tools/bench/variant_data.py).

The folder gets field.npy (µT, measured), pl.npy (photons), field_sigma.npy (µT), psf.yaml (as
the user believes it), truth_field.npy, truth_pl.npy (the view's true maps), masks.npz
(significant: |B| > 10 % of its max; lit / dark: true PL above / below 30 % of its max, within
significant; edge: within 2 µm of the view's border; wire: the current strip's pixels, none in
the array scene) and meta.json.
"""
import argparse
import json
import os
import sys

import numpy as np

MU0 = 4e-7 * np.pi


def moffat_kernel(shape, pixel_um, fwhm_um, beta):
    """Moffat (1 + r²/r0²)^-β on a periodic grid of `shape`, centred at (0, 0), unit sum."""
    ny, nx = shape
    y = np.minimum(np.arange(ny), ny - np.arange(ny))[:, None]
    x = np.minimum(np.arange(nx), nx - np.arange(nx))[None, :]
    fwhm = fwhm_um / pixel_um
    r0 = fwhm / (2 * np.sqrt(2 ** (1 / beta) - 1))
    k = (1 + (x * x + y * y) / r0 ** 2) ** (-beta)
    return k / k.sum()


def convolve(a, kernel_fft, shape):
    """Linear convolution: a zero-padded into the 2x frame whose FFT kernel_fft is."""
    pad = np.zeros(shape)
    pad[:a.shape[0], :a.shape[1]] = a
    out = np.fft.irfft2(np.fft.rfft2(pad) * kernel_fft, s=shape)
    return out[:a.shape[0], :a.shape[1]]


def strip_bz(x_um, width_um, standoff_um, current_a):
    """Bz (T) at height d above a thin strip |x| < w/2 carrying a sheet current K = I / w."""
    k = current_a / (width_um * 1e-6)
    a, b = x_um - width_um / 2, x_um + width_um / 2
    d = standoff_um
    return -MU0 * k / (4 * np.pi) * np.log((a * a + d * d) / (b * b + d * d))


def dipole_bz(x_um, y_um, x0, y0, depth_um):
    """Bz of a point dipole along z at depth d, up to scale: (2d² − ρ²) / (ρ² + d²)^(5/2)."""
    rho2 = (x_um - x0) ** 2 + (y_um - y0) ** 2
    return (2 * depth_um ** 2 - rho2) / (rho2 + depth_um ** 2) ** 2.5


def canvas_um(n_canvas, pixel_um):
    """x and y (µm) of the canvas pixels from its centre, and its half-width."""
    c = 0.5 * (n_canvas - 1)
    yy, xx = np.mgrid[0:n_canvas, 0:n_canvas].astype(float)
    return (xx - c) * pixel_um, (yy - c) * pixel_um, c * pixel_um


def strip(n_canvas, pixel_um):
    """The current strip's centre x and width (µm), and its pixels on the canvas."""
    x_um, _, half = canvas_um(n_canvas, pixel_um)
    wire_x, wire_w = -0.15 * half, 1.0
    return wire_x, wire_w, np.abs(x_um - wire_x) < wire_w / 2


def scene_maps(kind, n_canvas, pixel_um, rng, quench=0.05):
    """True PL I and field B (µT) on the canvas (view in the middle)."""
    x_um, y_um, half = canvas_um(n_canvas, pixel_um)
    spot = np.exp(-0.5 * (x_um ** 2 + y_um ** 2) / (0.6 * half) ** 2)
    wire_x, wire_w, on_wire = strip(n_canvas, pixel_um)
    bz = strip_bz(x_um - wire_x, wire_w, 0.05, 1e-3) * 1e6  # µT
    dip = dipole_bz(x_um, y_um, 0.35 * half, 0.2 * half, 0.6)
    bz = 30 * bz / np.abs(bz).max() + 25 * dip / np.abs(dip).max()
    bz *= 40 / np.abs(bz).max()
    if kind == "wire":
        pl = spot * np.where(on_wire, quench, 1.0)
    elif kind == "chessboard":
        side = max(1, int(round(1.0 / pixel_um)))
        ns = n_canvas // side + 1
        levels = rng.choice([0.1, 0.8, 1.0], size=(ns, ns))
        yy, xx = np.mgrid[0:n_canvas, 0:n_canvas]
        pl = spot * levels[yy // side, xx // side]
    elif kind == "oxide":
        t = np.clip((x_um + 0.3 * half) / 4.0 + 0.5, 0.0, 1.0)  # 0 left of the ramp, 1 right
        pl = spot * (1.0 - (1.0 - quench) * t)
    elif kind == "array":
        bz = np.zeros_like(x_um)
        sign = 1.0
        for v in (-0.66, 0.0, 0.66):
            for u in (-0.66, 0.0, 0.66):
                bz += sign * dipole_bz(x_um, y_um, u * half, v * half, 1.5)
                sign = -sign
        bz *= 40 / np.abs(bz).max()
        broad = np.exp(-0.5 * (x_um ** 2 + y_um ** 2) / (0.9 * half) ** 2)
        t = 0.5 + 0.5 * np.sin(2 * np.pi * (x_um + 0.37 * y_um) / 8.0)
        pl = broad * (1.0 - (1.0 - quench) * t)
    else:
        raise SystemExit(f"foreign.py: unknown scene '{kind}' (wire, chessboard, oxide, array)")
    return pl, bz


def make(args):
    rng = np.random.default_rng(args.seed)
    n = args.size
    m = int(round(args.margin_um / args.pixel_um))
    nc = n + 2 * m
    pl_true_c, b_true_c = scene_maps(args.scene, nc, args.pixel_um, rng, args.quench)
    frame = (2 * nc, 2 * nc)
    kernel = np.fft.rfft2(moffat_kernel(frame, args.pixel_um, args.fwhm_um, args.beta))
    pl_blur = convolve(pl_true_c, kernel, frame)[m:m + n, m:m + n]
    num_blur = convolve(b_true_c * pl_true_c, kernel, frame)[m:m + n, m:m + n]
    pl_blur = np.maximum(pl_blur, 1e-300)
    field_app = num_blur / pl_blur
    scale = args.counts / pl_blur.max()
    photons = rng.poisson(pl_blur * scale).astype(float)
    sigma = args.field_noise_ut * np.sqrt(args.counts / np.maximum(pl_blur * scale, 1.0))
    field = field_app + sigma * rng.standard_normal(field_app.shape)
    nan = rng.random(field.shape) < args.nan_fraction
    nan[n // 3:n // 3 + 4, n // 2:n // 2 + 4] = True
    field[nan] = np.nan
    pl_true = pl_true_c[m:m + n, m:m + n] * scale
    b_true = b_true_c[m:m + n, m:m + n]
    # the camera: counts = G · photons + O + read noise (drawn last: the defaults leave every
    # other draw, and so the datasets, as they were without a camera)
    counts = args.gain * photons + args.offset
    if args.read_noise > 0:
        counts = counts + args.read_noise * rng.standard_normal(counts.shape)
    os.makedirs(args.output, exist_ok=True)
    np.save(os.path.join(args.output, "field.npy"), field)
    np.save(os.path.join(args.output, "pl.npy"), counts)
    np.save(os.path.join(args.output, "field_sigma.npy"), sigma)
    np.save(os.path.join(args.output, "truth_field.npy"), b_true)
    np.save(os.path.join(args.output, "truth_pl.npy"), pl_true)
    fwhm_file = args.fwhm_um * (1 + args.fwhm_err)
    beta_file = args.beta * (1 + args.beta_err)
    with open(os.path.join(args.output, "psf.yaml"), "w") as f:
        f.write(f"pixel_um: {args.pixel_um}\n"
                f"psf: {{model: moffat, fwhm_um: {fwhm_file:.6g}, beta: {beta_file:.6g}}}\n")
    significant = np.abs(b_true) > 0.1 * np.abs(b_true).max()
    lit = pl_true > 0.3 * pl_true.max()
    band = int(round(2.0 / args.pixel_um))
    edge = np.zeros((n, n), bool)
    edge[:band, :] = edge[-band:, :] = edge[:, :band] = edge[:, -band:] = True
    # the current strip's pixels (scenes with the strip's field: all but array)
    wire = strip(nc, args.pixel_um)[2][m:m + n, m:m + n] & (args.scene != "array")
    np.savez(os.path.join(args.output, "masks.npz"), significant=significant,
             lit=lit & significant, dark=~lit & significant, edge=edge & significant,
             interior=~edge & significant, measured=~nan, wire=wire)
    meta = dict(vars(args), margin_px=m, canvas=nc, fwhm_file_um=fwhm_file, beta_file=beta_file,
                nan_pixels=int(nan.sum()), peak_field_ut=float(np.abs(b_true).max()))
    meta.pop("func", None)
    with open(os.path.join(args.output, "meta.json"), "w") as f:
        json.dump(meta, f, indent=1)
    return meta


def rel_rms(est, truth, mask):
    """√(Σ (est − truth)² / Σ truth²) over mask (finite est only)."""
    ok = mask & np.isfinite(est)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(((est - truth)[ok] ** 2).sum() / (truth[ok] ** 2).sum()))


def parser():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    mk = sub.add_parser("make", help="write one dataset")
    mk.add_argument("-o", "--output", required=True)
    mk.add_argument("--scene", default="wire")
    mk.add_argument("--size", type=int, default=384)
    mk.add_argument("--counts", type=float, default=1000.0)
    mk.add_argument("--pixel-um", type=float, default=0.1)
    mk.add_argument("--fwhm-um", type=float, default=0.6)
    mk.add_argument("--beta", type=float, default=1.1)
    mk.add_argument("--fwhm-err", type=float, default=0.0)
    mk.add_argument("--beta-err", type=float, default=0.0)
    mk.add_argument("--margin-um", type=float, default=6.0)
    mk.add_argument("--quench", type=float, default=0.05,
                    help="PL of the wire's metal / the oxide ramp's dark end, relative to lit")
    mk.add_argument("--gain", type=float, default=1.0, help="camera counts per photon")
    mk.add_argument("--offset", type=float, default=0.0, help="camera offset (counts)")
    mk.add_argument("--read-noise", type=float, default=0.0, help="read noise σ (counts)")
    mk.add_argument("--nan-fraction", type=float, default=0.005)
    mk.add_argument("--field-noise-ut", type=float, default=0.3)
    mk.add_argument("--seed", type=int, default=1)
    return ap


def main(argv=None):
    args = parser().parse_args(argv)
    if args.cmd == "make":
        meta = make(args)
        print(json.dumps({k: meta[k] for k in ("output", "scene", "size", "counts", "margin_px",
                                               "nan_pixels", "peak_field_ut")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
