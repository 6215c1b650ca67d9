"""Foreign data for the space-variant correction benchmark (section_variant.py): PSF maps, a
true scene and its blur by an independent numpy model of the per-source operator.

Nothing here calls svpsf's operators. The maps (docs/cli.md, "PSF-map files") are

  smooth   a polynomial Moffat map over the whole field (support 0): FWHM 0.8 µm ± 0.25 µm
           across the view (rising along x, a little curvature along y), β 1.6 ∓ 0.4 (falling
           along x and y);
  regions  metal / oxide: the scene's current strip is metal (FWHM 1.05 µm, β 1.25), the rest
           oxide (FWHM 0.7 µm, β 1.9), whole-field support; transition 0 (sharp boundary) or
           --blend-um (the library blends the parameters across the boundary).

The true scene is foreign.py's wire scene (a current strip whose metal quenches the PL to 5 %
under a Gaussian illumination spot, plus a dipole), so the dark pixels are the metal's.

The numpy forward model of H x = Σ_s k_s(· − s) x(s) (k_s the PSF at source s, point-sampled at
pixel centres over every offset up to the view's size − 1 and normalised to unit sum there, the
zero boundary):
  - pixels whose PSF is one of a few parameter sets (a sharp region map: exactly; a blended
    one: the blend weight binned into `bins` levels, each level's mean parameters) are summed
    per set: Σ_m k_m ⊛ (1_m x), exact for a sharp map;
  - a smooth map: the kernel interpolated between g × g nodes by cubic Lagrange weights,
    Σ_k k_k ⊛ (w_k x) (fourth order in the node spacing; smooth_model_error measures it
    against the exact kernels at probe sources, and the section prints it).
"""
import os

import numpy as np

try:
    import scipy.fft as sfft

    def rfft2(a):
        return sfft.rfft2(a, workers=-1)

    def irfft2(a, s):
        return sfft.irfft2(a, s=s, workers=-1)
except ImportError:  # pragma: no cover
    rfft2 = np.fft.rfft2

    def irfft2(a, s):
        return np.fft.irfft2(a, s=s)

PIXEL_UM = 0.1
SMOOTH = dict(fwhm=[0.8, 0.2, 0.0, 0.0, 0.0, 0.05], beta=[1.6, -0.3, -0.1, 0.0, 0.0, 0.0])
OXIDE = dict(fwhm_um=0.7, beta=1.9)
METAL = dict(fwhm_um=1.05, beta=1.25)


def poly_basis(n, degree=2):
    """Terms 1, u, v, u², u v, v² on the n x n grid, u, v in [-1, 1] (docs/cli.md)."""
    t = (2.0 * np.arange(n) - (n - 1)) / max(n - 1, 1)
    u, v = t[None, :], t[:, None]
    terms = []
    for k in range(degree + 1):
        for j in range(k + 1):
            terms.append(u ** (k - j) * v ** j * np.ones((n, n)))
    return terms


def smooth_params(n):
    """FWHM (px) and β maps of the smooth map."""
    b = poly_basis(n)
    fwhm = sum(c * t for c, t in zip(SMOOTH["fwhm"], b)) / PIXEL_UM
    beta = sum(c * t for c, t in zip(SMOOTH["beta"], b))
    return fwhm, beta


def write_smooth_map(path, n):
    fw = ", ".join(f"{c:g}" for c in SMOOTH["fwhm"])
    be = ", ".join(f"{c:g}" for c in SMOOTH["beta"])
    with open(path, "w") as f:
        f.write(f"version: 1\npixel_um: {PIXEL_UM}\nimage: {{width: {n}, height: {n}}}\n"
                "model: moffat\nsupport_um: 0\nkind: poly\ndegree: 2\n"
                f"coefficients: {{fwhm_um: [{fw}], beta: [{be}]}}\n"
                "provenance: \"tools/bench/variant_data.py: smooth polynomial Moffat map\"\n")


def write_region_map(path, labels, blend_um):
    d = os.path.dirname(path)
    stem = os.path.splitext(os.path.basename(path))[0]
    np.save(os.path.join(d, stem + ".labels.npy"), labels.astype(np.float64))
    n = labels.shape[0]
    with open(path, "w") as f:
        f.write(f"version: 1\npixel_um: {PIXEL_UM}\nimage: {{width: {n}, height: {n}}}\n"
                "model: moffat\nsupport_um: 0\nkind: regions\n"
                f"labels_file: {stem}.labels.npy\ntransition_um: {blend_um:g}\n"
                f"regions: [{{label: 0, name: oxide, fwhm_um: {OXIDE['fwhm_um']}, "
                f"beta: {OXIDE['beta']}}}, {{label: 1, name: metal, fwhm_um: "
                f"{METAL['fwhm_um']}, beta: {METAL['beta']}}}]\n"
                "provenance: \"tools/bench/variant_data.py: metal / oxide region map\"\n")


def moffat_spectrum(n, fwhm_px, beta):
    """rfft2 of the Moffat kernel over offsets |dx|, |dy| <= n − 1 (unit sum there), placed
    periodically in the 2n x 2n frame (offset n, never reached, is 0)."""
    m = 2 * n
    o = np.minimum(np.arange(m), m - np.arange(m)).astype(float)
    r0 = fwhm_px / (2 * np.sqrt(2 ** (1 / beta) - 1))
    k = (1 + (o[None, :] ** 2 + o[:, None] ** 2) / r0 ** 2) ** (-beta)
    k[n, :] = 0
    k[:, n] = 0
    return rfft2(k / k.sum())


def blur_sets(images, weights, params, n):
    """Σ_m k_m ⊛ (w_m x) for each image x (zero boundary, linear convolution in the 2n frame):
    weights[m] (n x n), params[m] = (fwhm px, β)."""
    m2 = 2 * n
    acc = [np.zeros((m2, n + 1), complex) for _ in images]
    pad = np.zeros((m2, m2))
    for w, (fw, be) in zip(weights, params):
        if not np.any(w):
            continue
        ks = moffat_spectrum(n, fw, be)
        for a, x in zip(acc, images):
            pad[:n, :n] = w * x
            a += rfft2(pad) * ks
    return [irfft2(a, s=(m2, m2))[:n, :n] for a in acc]


def cubic_weights(n, g):
    """Cubic Lagrange interpolation weights of g >= 4 evenly spread nodes (node i at
    i (n − 1) / (g − 1)) at each of n pixels, g x n: every pixel takes the 4 nodes around it
    (the stencil shifted inwards at the ends), so the interpolant is continuous and its error
    falls as the node spacing to the fourth power."""
    x = np.arange(n, dtype=float) * (g - 1) / (n - 1)
    w = np.zeros((g, n))
    i = np.clip(np.floor(x).astype(int), 0, g - 2)
    j0 = np.clip(i - 1, 0, g - 4)
    for a in range(4):
        num = np.ones(n)
        for b in range(4):
            if b != a:
                num *= (x - (j0 + b)) / (a - b)
        np.add.at(w, (j0 + a, np.arange(n)), num)
    return w


def smooth_node_params(n, g):
    nodes = np.arange(g) * (n - 1) / (g - 1)
    out = []
    for j in range(g):
        for i in range(g):
            u = (2 * nodes[i] - (n - 1)) / (n - 1)
            v = (2 * nodes[j] - (n - 1)) / (n - 1)
            terms = [1, u, v, u * u, u * v, v * v]
            out.append((sum(c * t for c, t in zip(SMOOTH["fwhm"], terms)) / PIXEL_UM,
                        sum(c * t for c, t in zip(SMOOTH["beta"], terms))))
    return out


def blur_smooth(images, n, g=10):
    """The smooth map's blur, its kernels interpolated between g x g nodes by cubic Lagrange
    weights: Σ_k k_k ⊛ (w_k x)."""
    w = cubic_weights(n, g)
    weights = [w[j][:, None] * w[i][None, :] for j in range(g) for i in range(g)]
    return blur_sets(images, weights, smooth_node_params(n, g), n)


def moffat_kernel(n, fwhm_px, beta):
    """The (2n − 1)² kernel of offsets up to n − 1, unit sum."""
    o = np.arange(-(n - 1), n, dtype=float)
    r0 = fwhm_px / (2 * np.sqrt(2 ** (1 / beta) - 1))
    k = (1 + (o[None, :] ** 2 + o[:, None] ** 2) / r0 ** 2) ** (-beta)
    return k / k.sum()


def smooth_model_error(n, g=10, probes=6):
    """Relative error of blur_smooth's kernel against the exact one at `probes` sources,
    sqrt(Σ ‖Σ_k w_k(s) k_k − k_s‖² / Σ ‖k_s‖²) over all offsets (no FFT needed: a point
    source's image is the weighted sum of the node kernels)."""
    w = cubic_weights(n, g)
    params = smooth_node_params(n, g)
    fw, be = smooth_params(n)
    rng = np.random.default_rng(7)
    e2 = n2 = 0.0
    for _ in range(probes):
        sx, sy = rng.integers(0, n, 2)
        exact = moffat_kernel(n, fw[sy, sx], be[sy, sx])
        model = np.zeros_like(exact)
        for k, (f, b) in enumerate(params):
            c = w[k // g][sy] * w[k % g][sx]
            if c != 0:
                model += c * moffat_kernel(n, f, b)
        e2 += ((model - exact) ** 2).sum()
        n2 += (exact ** 2).sum()
    return float(np.sqrt(e2 / n2))


def blur_regions(images, fwhm_px, beta, bins=12):
    """Per-parameter-set sum: pixels grouped by their blend weight between oxide and metal
    (from the FWHM map the library's field gives; exact for a sharp map)."""
    n = fwhm_px.shape[0]
    f0, f1 = OXIDE["fwhm_um"] / PIXEL_UM, METAL["fwhm_um"] / PIXEL_UM
    t = np.clip((fwhm_px - f0) / (f1 - f0), 0.0, 1.0)
    eps = 1e-9
    weights, params = [], []
    ends = [(t <= eps), (t >= 1 - eps)]
    for w in ends:
        weights.append(w.astype(float))
    params += [(f0, OXIDE["beta"]), (f1, METAL["beta"])]
    mid = ~(ends[0] | ends[1])
    if mid.any():
        edges = np.linspace(0, 1, bins + 1)
        for a, b in zip(edges[:-1], edges[1:]):
            w = mid & (t > a) & (t <= b)
            if not w.any():
                continue
            weights.append(w.astype(float))
            params.append((float(fwhm_px[w].mean()), float(beta[w].mean())))
    return blur_sets(images, weights, params, n)


def scene(n, kind="wire"):
    """True PL (peak 1), true field (µT) and the metal labels (the strip) of the n x n view:
    foreign.py's scene `kind` (wire: the strip quenched to 5 %; oxide: a PL ramp over 4 µm
    instead, the same field; array: 3 x 3 dipoles over the view under oxide fringes)."""
    import foreign  # tools/bench/foreign.py: the wire, oxide and array scenes

    rng = np.random.default_rng(1)
    pl, bz = foreign.scene_maps(kind, n, PIXEL_UM, rng)
    c = 0.5 * (n - 1)
    x_um = (np.arange(n) - c) * PIXEL_UM
    half = c * PIXEL_UM
    metal = np.abs(x_um - (-0.15 * half)) < 0.5
    labels = np.repeat(metal[None, :], n, axis=0).astype(int)
    return pl / pl.max(), bz, labels


def masks(pl, bz):
    """lit / dark as foreign.py: significant |B| > 10 % of its max, true PL above / below 30 %
    of its max."""
    significant = np.abs(bz) > 0.1 * np.abs(bz).max()
    lit = pl > 0.3 * pl.max()
    return {"lit": lit & significant, "dark": ~lit & significant}


def rel_rms(est, truth, mask):
    ok = mask & np.isfinite(est)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(((est - truth)[ok] ** 2).sum() / (truth[ok] ** 2).sum()))
