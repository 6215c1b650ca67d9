/* Image registration (docs/cli.md, svpsf register and fit-psf): the transform that maps reference pixel
 * coordinates to moving pixel coordinates, by phase correlation (translation, here, with the
 * library's cached FFTs) or by ECC (OpenCV findTransformECC, io/image_io.cpp), and svp_warp to
 * bring a moving image or label mask onto the reference grid. Conventions: include/svpsf.h,
 * section "register".
 *
 * Phase correlation. With the windowed, mean-free images r and m and their spectra R̂, M̂
 * (FFTW's sign: R̂(ω) = Σ r(x) e^{−iω·x}), a moving image m(x) = r(x − d) has M̂ = R̂ e^{−iω·d},
 * so the cross-power spectrum X = M̂ conj(R̂) = |R̂|² e^{−iω·d} and its inverse transform
 *     c(t) = Σ_ω W(ω) e^{iω·t},   W = X / (|X| + ε max|X|) · exp(−σ² |ω|²)
 * peaks at t = d. The integer peak of c is refined by maximising the Fourier interpolation
 * c(t) itself (Newton with backtracking on the analytic gradient and Hessian of the spectral
 * sum): no peak-shape model, so no bias from fitting a parabola or centroid to a sinc-like
 * peak. OpenCV's cv::phaseCorrelate (5 x 5 centroid, full whitening, the window applied to
 * the image with its mean) was measured at 0.2–0.9 px error on smooth blob scenes, which is
 * why this is done here.
 * A fixed window makes r·w and m·w differ by more than a shift (the window does not move with
 * the scene), which pulls d towards 0 by a few 0.01 px. Later passes therefore put a Hann
 * window over the region both images see, for the current d, in the reference and the same
 * window moved by d in the moving image (window_axis): for m(x) = r(x − d) the windowed images
 * are then exact shifted copies. Two or three passes reach a fixed point (|Δd| < 1e-4 px). */
#include "../core/internal.h"
#include "image_io.h"

#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define PHASE_MAX_PASSES 6
#define PHASE_PASS_TOL 1e-4   /* px: stop re-windowing when the shift moves less */
#define NEWTON_MAX_STEPS 60
#define MIN_SIDE 8

void svp_register_defaults(svp_register_options *options)
{
    if (!options) return;
    memset(options, 0, sizeof *options);
    options->method = SVP_REGISTER_PHASE;
    options->motion = SVP_MOTION_TRANSLATION;
    options->normalise = 1;
    options->smooth_sigma = 1.0;
    options->window = 1;
    options->whitening = 0.1;
    options->min_significance = 10;
    options->iterations = 100;
    options->epsilon = 1e-6;
    options->initial_affine = NULL;
    options->progress = NULL;
    options->progress_user = NULL;
    options->reference_name = NULL;
    options->moving_name = NULL;
    options->contrast = SVP_CONTRAST_AUTO;
}

static const char *motion_name(svp_register_motion m)
{
    switch (m) {
    case SVP_MOTION_TRANSLATION: return "translation";
    case SVP_MOTION_EUCLIDEAN: return "euclidean";
    case SVP_MOTION_AFFINE: return "affine";
    }
    return "?";
}

/* ---- affine helpers ------------------------------------------------------------------------ */

static inline void affine_apply(const double a[6], double x, double y, double *xm, double *ym)
{
    *xm = a[0] * x + a[1] * y + a[2];
    *ym = a[3] * x + a[4] * y + a[5];
}

svp_status svp_affine_invert(const double affine[6], double inverse[6])
{
    if (!affine || !inverse) return svp_fail(SVP_ERR_INVALID, "affine inverse: NULL argument");
    for (int i = 0; i < 6; i++)
        if (!isfinite(affine[i]))
            return svp_fail(SVP_ERR_INVALID, "affine inverse: element %d is %g", i, affine[i]);
    const double det = affine[0] * affine[4] - affine[1] * affine[3];
    if (!(fabs(det) >= 1e-12))
        return svp_fail(SVP_ERR_NUMERIC,
                        "affine inverse: the linear part is singular (determinant %g)", det);
    const double i00 = affine[4] / det, i01 = -affine[1] / det;
    const double i10 = -affine[3] / det, i11 = affine[0] / det;
    double out[6] = {i00, i01, -(i00 * affine[2] + i01 * affine[5]),
                     i10, i11, -(i10 * affine[2] + i11 * affine[5])};
    memcpy(inverse, out, sizeof out);
    return SVP_OK;
}

/* ---- warping ------------------------------------------------------------------------------- */

/* out(x, y) = src(a · (x, y, 1)); domain [−0.5, w − 0.5) x [−0.5, h − 0.5), else border. */
static void warp_plane(const double *restrict src, int sw, int sh, const double a[6],
                       svp_interpolation interp, double border, double *restrict out, int ow,
                       int oh)
{
    const size_t n = (size_t)ow * oh;
    (void)n;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (int y = 0; y < oh; y++) {
        double *row = out + (size_t)y * ow;
        for (int x = 0; x < ow; x++) {
            double qx, qy;
            affine_apply(a, x, y, &qx, &qy);
            /* one test for both methods, so masks and images cover the same pixels */
            if (!(qx >= -0.5 && qx < sw - 0.5 && qy >= -0.5 && qy < sh - 0.5)) {
                row[x] = border;
                continue;
            }
            if (interp == SVP_INTERP_NEAREST) {
                int ix = (int)floor(qx + 0.5), iy = (int)floor(qy + 0.5);
                if (ix > sw - 1) ix = sw - 1; /* round-off at the upper edge */
                if (iy > sh - 1) iy = sh - 1;
                row[x] = src[(size_t)iy * sw + ix];
                continue;
            }
            /* bilinear; the outer half pixel repeats the edge pixel */
            double cx = qx < 0 ? 0 : qx > sw - 1 ? sw - 1 : qx;
            double cy = qy < 0 ? 0 : qy > sh - 1 ? sh - 1 : qy;
            int x0 = (int)floor(cx), y0 = (int)floor(cy);
            if (x0 > sw - 1) x0 = sw - 1;
            if (y0 > sh - 1) y0 = sh - 1;
            const double fx = cx - x0, fy = cy - y0;
            const int x1 = x0 + 1 < sw ? x0 + 1 : x0, y1 = y0 + 1 < sh ? y0 + 1 : y0;
            const double w[4] = {(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy};
            const size_t k[4] = {(size_t)y0 * sw + x0, (size_t)y0 * sw + x1,
                                 (size_t)y1 * sw + x0, (size_t)y1 * sw + x1};
            double v = 0;
            for (int t = 0; t < 4; t++)
                if (w[t] != 0) v += w[t] * src[k[t]]; /* a NaN neighbour of weight 0 is unused */
            row[x] = v;
        }
    }
}

svp_status svp_warp(const svp_image *moving, const double affine[6],
                    svp_interpolation interpolation, double border_value, svp_image *out)
{
    if (!moving || !moving->data || moving->width < 1 || moving->height < 1)
        return svp_fail(SVP_ERR_INVALID, "warp: no moving image");
    if (!out || !out->data || out->width < 1 || out->height < 1)
        return svp_fail(SVP_ERR_INVALID, "warp: no output image (allocate it at the reference "
                                         "size)");
    if (out == moving || out->data == moving->data)
        return svp_fail(SVP_ERR_INVALID, "warp: the output must not be the moving image");
    if (!affine) return svp_fail(SVP_ERR_INVALID, "warp: affine is NULL");
    for (int i = 0; i < 6; i++)
        if (!isfinite(affine[i]))
            return svp_fail(SVP_ERR_INVALID, "warp: affine element %d is %g", i, affine[i]);
    if (interpolation != SVP_INTERP_NEAREST && interpolation != SVP_INTERP_LINEAR)
        return svp_fail(SVP_ERR_INVALID, "warp: interpolation %d is not nearest (0) or "
                                         "linear (1)",
                        (int)interpolation);
    warp_plane(moving->data, moving->width, moving->height, affine, interpolation, border_value,
               out->data, out->width, out->height);
    return SVP_OK;
}

/* ---- preprocessing ------------------------------------------------------------------------- */

/* large holes: what the neighbour fill leaves after this many rings gets the fallback */
#define FILL_PASSES 8
static svp_status fill_holes(double *restrict v, int w, int h, double fallback)
{
    return svp_fill_nan(v, w, h, FILL_PASSES, fallback);
}

/* out = (x − mean) / sd (normalise) or x, with mean and sd over the finite pixels; non-finite
 * pixels are filled from their neighbours (fill_holes). out_nan: the same but NaN there (for
 * the residual). */
static svp_status prepare(const svp_image *img, const char *what, int normalise, double *out,
                          double *out_nan, size_t *nonfinite)
{
    SVP_CHECK(svp_image_check_scale(img, what)); /* the texture test squares the data */
    const size_t n = (size_t)img->width * img->height;
    const double *restrict x = img->data;
    size_t count = 0;
    double sum = 0;
    for (size_t i = 0; i < n; i++)
        if (isfinite(x[i])) {
            sum += x[i];
            count++;
        }
    *nonfinite = n - count;
    if (count == 0)
        return svp_fail(SVP_ERR_INVALID, "%s: no finite pixel (all %zu are NaN or Inf)", what,
                        n);
    const double mean = sum / count;
    double ss = 0;
    for (size_t i = 0; i < n; i++)
        if (isfinite(x[i])) ss += (x[i] - mean) * (x[i] - mean);
    const double sd = sqrt(ss / count);
    if (!(sd > 1e-12 * fabs(mean)) || !(sd > DBL_MIN))
        return svp_fail(SVP_ERR_INVALID,
                        "%s is constant (every finite pixel is %.6g): no texture to "
                        "register",
                        what, mean);
    const double shift = normalise ? mean : 0, scale = normalise ? 1 / sd : 1;
    for (size_t i = 0; i < n; i++) {
        out_nan[i] = isfinite(x[i]) ? (x[i] - shift) * scale : NAN;
        out[i] = out_nan[i];
    }
    if (*nonfinite) SVP_CHECK(fill_holes(out, img->width, img->height, (mean - shift) * scale));
    return SVP_OK;
}

/* ---- phase correlation --------------------------------------------------------------------- */

typedef struct phase_work {
    int w, h, ncx;
    const svp_fft_plan *plan;
    double *real;        /* h x w */
    fftw_complex *spec_ref, *spec_mov, *weight; /* h x ncx */
    double *wx_ref, *wx_mov, *wy_ref, *wy_mov;  /* window factors */
    double *omega_x, *omega_y;                  /* ncx, h: angular frequencies (rad/px) */
    fftw_complex *ex, *ey;                      /* e^{iω t} per column / row */
    double *partial;                            /* 6 per row: phase_surface's row sums */
} phase_work;

static void phase_work_free(phase_work *pw)
{
    svp_free(pw->real);
    svp_free(pw->spec_ref);
    svp_free(pw->spec_mov);
    svp_free(pw->weight);
    svp_free(pw->wx_ref);
    svp_free(pw->wx_mov);
    svp_free(pw->wy_ref);
    svp_free(pw->wy_mov);
    svp_free(pw->omega_x);
    svp_free(pw->omega_y);
    svp_free(pw->ex);
    svp_free(pw->ey);
    svp_free(pw->partial);
}

static svp_status phase_work_init(phase_work *pw, int w, int h)
{
    memset(pw, 0, sizeof *pw);
    pw->w = w;
    pw->h = h;
    pw->ncx = w / 2 + 1;
    SVP_CHECK(svp_fft_plan_get(h, w, &pw->plan));
    const size_t nr = (size_t)w * h, nc = (size_t)pw->ncx * h;
    pw->real = svp_alloc(nr * sizeof(double));
    pw->spec_ref = svp_alloc(nc * sizeof(fftw_complex));
    pw->spec_mov = svp_alloc(nc * sizeof(fftw_complex));
    pw->weight = svp_alloc(nc * sizeof(fftw_complex));
    pw->wx_ref = svp_alloc((size_t)w * sizeof(double));
    pw->wx_mov = svp_alloc((size_t)w * sizeof(double));
    pw->wy_ref = svp_alloc((size_t)h * sizeof(double));
    pw->wy_mov = svp_alloc((size_t)h * sizeof(double));
    pw->omega_x = svp_alloc((size_t)pw->ncx * sizeof(double));
    pw->omega_y = svp_alloc((size_t)h * sizeof(double));
    pw->ex = svp_alloc((size_t)pw->ncx * sizeof(fftw_complex));
    pw->ey = svp_alloc((size_t)h * sizeof(fftw_complex));
    pw->partial = svp_alloc(6 * (size_t)h * sizeof(double));
    if (!pw->real || !pw->spec_ref || !pw->spec_mov || !pw->weight || !pw->wx_ref ||
        !pw->wx_mov || !pw->wy_ref || !pw->wy_mov || !pw->omega_x || !pw->omega_y || !pw->ex ||
        !pw->ey || !pw->partial) {
        phase_work_free(pw);
        return svp_fail(SVP_ERR_NOMEM, "registration: out of memory for %d x %d phase "
                                       "correlation",
                        w, h);
    }
    for (int kx = 0; kx < pw->ncx; kx++) pw->omega_x[kx] = 2 * M_PI * kx / w;
    for (int ky = 0; ky < h; ky++) pw->omega_y[ky] = 2 * M_PI * (ky <= h / 2 ? ky : ky - h) / h;
    return SVP_OK;
}

/* The Hann window sin²(π (t − lo) / len) on [lo, lo + len], 0 outside. */
static double hann(double t, double lo, double len)
{
    if (!(t > lo && t < lo + len)) return 0;
    const double s = sin(M_PI * (t - lo) / len);
    return s * s;
}

/* Window factors along one axis of n pixels for a shift d: a Hann window over the part both
 * images see, [max(0, −d), min(n, n − d)] − 1/2 in reference coordinates (length n − |d|), and
 * the same window moved by d for the moving image. Both fall to zero inside the frames, so the
 * windowed images are exact shifted copies: no truncated edge, no content only one image has.
 * d = 0: the full Hann window, zero half a pixel beyond the outer pixel centres. */
static void window_axis(int n, double d, int on, double *restrict ref, double *restrict mov)
{
    const double len = fmax(n - fabs(d), 0.5 * n), lo = fmax(0, -d) - 0.5;
    for (int t = 0; t < n; t++) {
        ref[t] = on ? hann(t, lo, len) : 1;
        mov[t] = on ? hann(t, lo + d, len) : 1;
    }
}

static void window_image(const phase_work *pw, const double *restrict img, double mean,
                         const double *restrict wx, const double *restrict wy,
                         double *restrict out)
{
    const int w = pw->w, h = pw->h;
    const size_t n = (size_t)w * h;
    (void)n;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++)
            out[(size_t)y * w + x] = (img[(size_t)y * w + x] - mean) * wx[x] * wy[y];
}

/* c(t), its gradient and Hessian: the Fourier interpolation of the correlation surface.
 * Sums over the half spectrum count the columns 0 < kx < w/2 twice (Hermitian symmetry).
 * Rows are summed in parallel into per-row partial sums, which are then added in row order:
 * the same result for every thread count. */
static double phase_surface(phase_work *pw, double tx, double ty, double g[2], double hs[3])
{
    const int ncx = pw->ncx, h = pw->h, w = pw->w;
    for (int kx = 0; kx < ncx; kx++) pw->ex[kx] = cexp(I * pw->omega_x[kx] * tx);
    for (int ky = 0; ky < h; ky++) pw->ey[ky] = cexp(I * pw->omega_y[ky] * ty);
    double *restrict part = pw->partial;
    const size_t n = (size_t)ncx * h;
    (void)n;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (int ky = 0; ky < h; ky++) {
        const double wy = pw->omega_y[ky];
        const fftw_complex *restrict row = pw->weight + (size_t)ky * ncx;
        const fftw_complex eyk = pw->ey[ky];
        double c = 0, sx = 0, sxx = 0, sre_y = 0;
        double im_sum = 0;
        for (int kx = 0; kx < ncx; kx++) {
            const double m = (kx == 0 || 2 * kx == w) ? 1.0 : 2.0;
            const fftw_complex z = row[kx] * eyk * pw->ex[kx];
            const double re = m * creal(z), im = m * cimag(z), wx = pw->omega_x[kx];
            c += re;
            sx += wx * im;      /* → −∂c/∂tx */
            sxx += wx * wx * re;
            sre_y += wx * re;   /* → ∂²c/∂tx∂ty / (−ωy) */
            im_sum += im;
        }
        double *p = part + 6 * (size_t)ky;
        p[0] = c;
        p[1] = -sx;
        p[2] = -wy * im_sum;
        p[3] = -sxx;
        p[4] = -wy * sre_y;
        p[5] = -wy * wy * c;
    }
    double c = 0, gx = 0, gy = 0, hxx = 0, hxy = 0, hyy = 0;
    for (int ky = 0; ky < h; ky++) {
        const double *p = part + 6 * (size_t)ky;
        c += p[0];
        gx += p[1];
        gy += p[2];
        hxx += p[3];
        hxy += p[4];
        hyy += p[5];
    }
    if (g) {
        g[0] = gx;
        g[1] = gy;
    }
    if (hs) {
        hs[0] = hxx;
        hs[1] = hxy;
        hs[2] = hyy;
    }
    return c;
}

/* Maximises c(t) from (tx, ty): Newton steps (gradient steps where the Hessian is not negative
 * definite), each at most 0.5 px per axis, halved until c does not decrease. */
static double phase_maximise(phase_work *pw, double *tx, double *ty)
{
    double g[2], hs[3];
    double c = phase_surface(pw, *tx, *ty, g, hs);
    for (int it = 0; it < NEWTON_MAX_STEPS; it++) {
        double sx, sy;
        const double det = hs[0] * hs[2] - hs[1] * hs[1];
        if (hs[0] < 0 && det > 0) {
            sx = -(hs[2] * g[0] - hs[1] * g[1]) / det;
            sy = -(-hs[1] * g[0] + hs[0] * g[1]) / det;
        } else {
            const double gn = hypot(g[0], g[1]);
            if (!(gn > 0)) break;
            sx = 0.25 * g[0] / gn;
            sy = 0.25 * g[1] / gn;
        }
        const double big = fmax(fabs(sx), fabs(sy));
        if (big > 0.5) {
            sx *= 0.5 / big;
            sy *= 0.5 / big;
        }
        int accepted = 0;
        for (int half = 0; half < 30; half++) {
            double g2[2], hs2[3];
            const double c2 = phase_surface(pw, *tx + sx, *ty + sy, g2, hs2);
            if (c2 >= c) {
                *tx += sx;
                *ty += sy;
                c = c2;
                memcpy(g, g2, sizeof g2);
                memcpy(hs, hs2, sizeof hs2);
                accepted = 1;
                break;
            }
            sx *= 0.5;
            sy *= 0.5;
        }
        if (!accepted || hypot(sx, sy) < 1e-9) break;
    }
    return c;
}

/* sign · (peak − mean) / sd of the correlation surface c, the mean and sd taken away from
 * the peak (circular distance > 5 + 2 σ px, beyond its main lobe); sign −1 measures a trough
 * of c as the peak of −c. */
static double peak_significance(const double *c, int w, int h, int px, int py, double sigma,
                                double sign)
{
    const double r_ex = 5 + 2 * sigma;
    size_t count = 0;
    double sum = 0, sum2 = 0;
    for (int y = 0; y < h; y++) {
        int dy = abs(y - py);
        if (dy > h - dy) dy = h - dy;
        for (int x = 0; x < w; x++) {
            int dx = abs(x - px);
            if (dx > w - dx) dx = w - dx;
            if ((double)dx * dx + (double)dy * dy <= r_ex * r_ex) continue;
            const double v = c[(size_t)y * w + x];
            sum += v;
            sum2 += v * v;
            count++;
        }
    }
    if (count < 2) return NAN;
    const double mean = sum / count, var = sum2 / count - mean * mean;
    return var > 0 ? sign * (c[(size_t)py * w + px] - mean) / sqrt(var) : INFINITY;
}

/* One pass: windows over the region both images see for the shift (dx, dy) (window_axis),
 * spectra, weights W; returns the refined shift. first (dx = dy = 0): start from the integer
 * peak of c (inverse FFT) and measure its significance, and that of the deepest trough (the
 * peak of an inverted moving image); with contrast AUTO the more significant of the two is
 * taken, and for the trough (or contrast INVERTED) W is negated (= the moving image inverted)
 * and *inverted set, so the caller inverts the moving image for the later passes. Else start
 * from (dx, dy). */
static svp_status phase_pass(phase_work *pw, const double *ref, double mean_ref,
                             const double *mov, double mean_mov, const svp_register_options *o,
                             int first, double *dx, double *dy, double *response,
                             double *significance, double *significance_other, int *inverted)
{
    const int w = pw->w, h = pw->h, ncx = pw->ncx;
    const size_t nc = (size_t)ncx * h;
    window_axis(w, *dx, o->window, pw->wx_ref, pw->wx_mov);
    window_axis(h, *dy, o->window, pw->wy_ref, pw->wy_mov);
    window_image(pw, ref, mean_ref, pw->wx_ref, pw->wy_ref, pw->real);
    svp_fft_forward(pw->plan, pw->real, pw->spec_ref);
    window_image(pw, mov, mean_mov, pw->wx_mov, pw->wy_mov, pw->real);
    svp_fft_forward(pw->plan, pw->real, pw->spec_mov);

    double max_abs = 0;
    for (size_t k = 0; k < nc; k++) {
        pw->weight[k] = pw->spec_mov[k] * conj(pw->spec_ref[k]);
        const double a = cabs(pw->weight[k]);
        if (a > max_abs) max_abs = a;
    }
    if (!(max_abs > 0) || !isfinite(max_abs))
        return svp_fail(SVP_ERR_NUMERIC, "phase correlation: the windowed images have no "
                                         "common frequency (cross-power spectrum %g)",
                        max_abs);
    const double floor_abs = o->whitening * max_abs, s2 = o->smooth_sigma * o->smooth_sigma;
    double total = 0;
    for (int ky = 0; ky < h; ky++)
        for (int kx = 0; kx < ncx; kx++) {
            const size_t k = (size_t)ky * ncx + kx;
            /* DC carries no shift; Nyquist bins have no sign for ω */
            if ((kx == 0 && ky == 0) || 2 * kx == w || 2 * ky == h) {
                pw->weight[k] = 0;
                continue;
            }
            const double wx = pw->omega_x[kx], wy = pw->omega_y[ky];
            const double a = cabs(pw->weight[k]);
            pw->weight[k] *= exp(-s2 * (wx * wx + wy * wy)) / (a + floor_abs);
            total += (kx == 0 ? 1.0 : 2.0) * cabs(pw->weight[k]);
        }
    if (!(total > 0))
        return svp_fail(SVP_ERR_NUMERIC, "phase correlation: no usable frequency (image too "
                                         "small or too smooth for smooth_sigma %g)",
                        o->smooth_sigma);

    double tx = *dx, ty = *dy;
    if (first) {
        /* integer peak: inverse FFT of W (c2r destroys its input: use spec_ref as scratch) */
        memcpy(pw->spec_ref, pw->weight, nc * sizeof(fftw_complex));
        svp_fft_inverse_unscaled(pw->plan, pw->spec_ref, pw->real);
        size_t best = 0, worst = 0;
        for (size_t i = 1; i < (size_t)w * h; i++) {
            if (pw->real[i] > pw->real[best]) best = i;
            if (pw->real[i] < pw->real[worst]) worst = i;
        }
        const double s_peak = peak_significance(pw->real, w, h, (int)(best % w),
                                                (int)(best / w), o->smooth_sigma, 1);
        const double s_trough = peak_significance(pw->real, w, h, (int)(worst % w),
                                                  (int)(worst / w), o->smooth_sigma, -1);
        /* the moving image arrives already inverted when the caller forced INVERTED */
        *inverted = o->contrast == SVP_CONTRAST_AUTO && s_trough > s_peak;
        if (*inverted) {
            best = worst;
            for (size_t k = 0; k < nc; k++) pw->weight[k] = -pw->weight[k];
        }
        *significance = *inverted ? s_trough : s_peak;
        *significance_other = *inverted ? s_peak : s_trough;
        int px = (int)(best % w), py = (int)(best / w);
        tx = px > w / 2 ? px - w : px;
        ty = py > h / 2 ? py - h : py;
    }
    const double c = phase_maximise(pw, &tx, &ty);
    *dx = tx;
    *dy = ty;
    *response = c / total;
    return SVP_OK;
}

/* *inverted = 1 when the first pass chose the trough (contrast AUTO): mov and mov_nan are then
 * negated here, for the later passes and for the caller (ECC, quality). */
static svp_status phase_correlate(const double *ref, double *mov, double *mov_nan, int w, int h,
                                  const svp_register_options *o, double *dx, double *dy,
                                  double *response, double *significance,
                                  double *significance_other, int *inverted)
{
    phase_work pw;
    SVP_CHECK(phase_work_init(&pw, w, h));
    const size_t n = (size_t)w * h;
    const double mean_ref = svp_sum(ref, n) / n;
    double mean_mov = svp_sum(mov, n) / n;
    double sx = 0, sy = 0, resp = 0;
    svp_status st = phase_pass(&pw, ref, mean_ref, mov, mean_mov, o, 1, &sx, &sy, &resp,
                               significance, significance_other, inverted);
    if (st == SVP_OK && *inverted) {
        for (size_t i = 0; i < n; i++) {
            mov[i] = -mov[i];
            mov_nan[i] = -mov_nan[i];
        }
        mean_mov = -mean_mov;
    }
    /* Without a window there is nothing to move: one pass is the answer. */
    for (int pass = 1; st == SVP_OK && o->window && pass < PHASE_MAX_PASSES; pass++) {
        double nx = sx, ny = sy;
        st = phase_pass(&pw, ref, mean_ref, mov, mean_mov, o, 0, &nx, &ny, &resp, NULL, NULL,
                        NULL);
        const double moved = hypot(nx - sx, ny - sy);
        sx = nx;
        sy = ny;
        if (moved < PHASE_PASS_TOL) break;
    }
    phase_work_free(&pw);
    if (st != SVP_OK) return st;
    *dx = sx;
    *dy = sy;
    *response = resp;
    return SVP_OK;
}

/* ---- quality over the overlap -------------------------------------------------------------- */

static svp_status overlap_quality(const double *ref_nan, const double *mov_nan, int w, int h,
                                  const double a[6], svp_register_result *r)
{
    const size_t n = (size_t)w * h;
    double *warped = svp_alloc(n * sizeof(double));
    if (!warped) return svp_fail(SVP_ERR_NOMEM, "registration: out of memory");
    warp_plane(mov_nan, w, h, a, SVP_INTERP_LINEAR, NAN, warped, w, h);
    /* serial sums: the same for every thread count */
    size_t count = 0;
    double sr = 0, sm = 0;
    for (size_t i = 0; i < n; i++)
        if (isfinite(ref_nan[i]) && isfinite(warped[i])) {
            count++;
            sr += ref_nan[i];
            sm += warped[i];
        }
    r->overlap = (double)count / n;
    if (count < 2) {
        r->correlation = r->residual_rms = NAN;
        svp_free(warped);
        return SVP_OK;
    }
    const double mr = sr / count, mm = sm / count;
    double srr = 0, smm = 0, srm = 0, sd2 = 0;
    for (size_t i = 0; i < n; i++)
        if (isfinite(ref_nan[i]) && isfinite(warped[i])) {
            const double u = ref_nan[i] - mr, v = warped[i] - mm, d = ref_nan[i] - warped[i];
            srr += u * u;
            smm += v * v;
            srm += u * v;
            sd2 += d * d;
        }
    r->correlation = srr > 0 && smm > 0 ? srm / sqrt(srr * smm) : NAN;
    r->residual_rms = sqrt(sd2 / count);
    svp_free(warped);
    return SVP_OK;
}

static void describe(svp_register_result *r, int w, int h)
{
    const double *a = r->affine;
    const double cx = (w - 1) / 2.0, cy = (h - 1) / 2.0;
    double mx, my;
    affine_apply(a, cx, cy, &mx, &my);
    r->shift_x = mx - cx;
    r->shift_y = my - cy;
    r->rotation = atan2(a[3] - a[1], a[0] + a[4]);
    r->scale = sqrt(fabs(a[0] * a[4] - a[1] * a[3]));
}

/* ---- svp_register ------------------------------------------------------------------------- */

static svp_status check_options(const svp_register_options *o)
{
    if (o->method != SVP_REGISTER_PHASE && o->method != SVP_REGISTER_ECC)
        return svp_fail(SVP_ERR_INVALID, "registration: method %d is not phase (0) or ECC (1)",
                        (int)o->method);
    if (o->motion != SVP_MOTION_TRANSLATION && o->motion != SVP_MOTION_EUCLIDEAN &&
        o->motion != SVP_MOTION_AFFINE)
        return svp_fail(SVP_ERR_INVALID, "registration: motion %d is not translation (0), "
                                         "euclidean (1) or affine (2)",
                        (int)o->motion);
    if (o->method == SVP_REGISTER_PHASE && o->motion != SVP_MOTION_TRANSLATION)
        return svp_fail(SVP_ERR_INVALID,
                        "registration: phase correlation estimates a translation only (motion "
                        "%s requested): use method ECC",
                        motion_name(o->motion));
    if (!(o->smooth_sigma >= 0) || !isfinite(o->smooth_sigma))
        return svp_fail(SVP_ERR_INVALID, "registration: smooth_sigma %g (must be >= 0 px)",
                        o->smooth_sigma);
    if (!(o->whitening >= 0) || !isfinite(o->whitening))
        return svp_fail(SVP_ERR_INVALID, "registration: whitening %g (must be >= 0)",
                        o->whitening);
    if (o->contrast != SVP_CONTRAST_AUTO && o->contrast != SVP_CONTRAST_SAME &&
        o->contrast != SVP_CONTRAST_INVERTED)
        return svp_fail(SVP_ERR_INVALID, "registration: contrast %d is not auto (0), same (1) "
                                         "or inverted (2)",
                        (int)o->contrast);
    if (isnan(o->min_significance))
        return svp_fail(SVP_ERR_INVALID, "registration: min_significance is NaN");
    if (o->method == SVP_REGISTER_ECC) {
        if (o->iterations < 2)
            return svp_fail(SVP_ERR_INVALID,
                            "registration: ECC iterations %d (must be >= 2: convergence is "
                            "judged between two iterations)",
                            o->iterations);
        if (!(o->epsilon > 0) || !isfinite(o->epsilon))
            return svp_fail(SVP_ERR_INVALID, "registration: ECC epsilon %g (must be > 0)",
                            o->epsilon);
        if (o->initial_affine)
            for (int i = 0; i < 6; i++)
                if (!isfinite(o->initial_affine[i]))
                    return svp_fail(SVP_ERR_INVALID,
                                    "registration: initial_affine element %d is %g", i,
                                    o->initial_affine[i]);
    }
    return SVP_OK;
}

svp_status svp_register(const svp_image *reference, const svp_image *moving,
                        const svp_register_options *options, svp_register_result *result)
{
    if (!result) return svp_fail(SVP_ERR_INVALID, "registration: result is NULL");
    memset(result, 0, sizeof *result);
    result->response = result->significance = result->correlation = NAN;
    result->residual_rms = result->significance_other = NAN;
    if (!reference || !reference->data)
        return svp_fail(SVP_ERR_INVALID, "registration: no reference image");
    if (!moving || !moving->data)
        return svp_fail(SVP_ERR_INVALID, "registration: no moving image");
    svp_register_options defaults;
    svp_register_defaults(&defaults);
    const svp_register_options *o = options ? options : &defaults;
    SVP_CHECK(check_options(o));
    if (reference->width != moving->width || reference->height != moving->height)
        return svp_fail(SVP_ERR_SIZE,
                        "registration: reference is %d x %d but moving is %d x %d (crop or pad "
                        "to one size; svp_warp accepts different sizes)",
                        reference->width, reference->height, moving->width, moving->height);
    const int w = reference->width, h = reference->height;
    if (w < MIN_SIDE || h < MIN_SIDE)
        return svp_fail(SVP_ERR_INVALID,
                        "registration: images are %d x %d; at least %d x %d pixels needed", w, h,
                        MIN_SIDE, MIN_SIDE);

    const size_t n = (size_t)w * h;
    svp_status st = SVP_OK;
    double *ref = svp_alloc(n * sizeof(double)), *mov = svp_alloc(n * sizeof(double));
    double *ref_nan = svp_alloc(n * sizeof(double)), *mov_nan = svp_alloc(n * sizeof(double));
    if (!ref || !mov || !ref_nan || !mov_nan) {
        st = svp_fail(SVP_ERR_NOMEM, "registration: out of memory for %d x %d images", w, h);
        goto cleanup;
    }
    const char *ref_name = o->reference_name ? o->reference_name : "reference image";
    const char *mov_name = o->moving_name ? o->moving_name : "moving image";
    if ((st = prepare(reference, ref_name, o->normalise, ref, ref_nan,
                      &result->nonfinite_reference)) != SVP_OK)
        goto cleanup;
    if ((st = prepare(moving, mov_name, o->normalise, mov, mov_nan, &result->nonfinite_moving)) !=
        SVP_OK)
        goto cleanup;

    if (o->contrast == SVP_CONTRAST_INVERTED) {
        for (size_t i = 0; i < n; i++) {
            mov[i] = -mov[i];
            mov_nan[i] = -mov_nan[i];
        }
        result->inverted = 1;
    }
    double *a = result->affine;
    if (o->method == SVP_REGISTER_PHASE || !o->initial_affine) {
        double dx = 0, dy = 0, response = 0, significance = 0, other = NAN;
        int flipped = 0;
        if ((st = phase_correlate(ref, mov, mov_nan, w, h, o, &dx, &dy, &response,
                                  &significance, &other, &flipped)) != SVP_OK)
            goto cleanup;
        if (flipped) result->inverted = 1;
        result->significance = significance;
        result->significance_other = other;
        const double t[6] = {1, 0, dx, 0, 1, dy};
        memcpy(a, t, sizeof t);
        result->response = response;
        result->low_significance = !(significance >= o->min_significance);
    } else {
        memcpy(a, o->initial_affine, 6 * sizeof(double));
    }
    if (o->method == SVP_REGISTER_ECC) {
        double rho = NAN;
        st = svp_io_register_ecc(ref, mov, w, h, (int)o->motion, o->smooth_sigma, o->iterations,
                                 o->epsilon, a, &result->iterations, &rho, o->progress,
                                 o->progress_user);
        if (st != SVP_OK) goto cleanup;
    }
    describe(result, w, h);
    st = overlap_quality(ref_nan, mov_nan, w, h, a, result);

cleanup:
    svp_free(ref);
    svp_free(mov);
    svp_free(ref_nan);
    svp_free(mov_nan);
    return st;
}

/* ---- sub-pixel shifts and cube alignment ---------------------------------------------------- */

/* e^{−iωd} per frequency bin of one axis of length n (ω = 2π k / n, k folded to [−n/2, n/2));
 * at the Nyquist bin (even n) the real cos(π d), so the product keeps the spectrum Hermitian. */
static void shift_phases(int n, int bins, double d, fftw_complex *e)
{
    for (int k = 0; k < bins; k++) {
        const int kk = k <= n / 2 ? k : k - n;
        const double w = 2 * M_PI * kk / n;
        e[k] = n % 2 == 0 && k == n / 2 ? cos(M_PI * d) : cexp(-I * w * d);
    }
}

/* svp_shift's continuation of one line v[0 .. n − 1] (stride sv) into out (length len, stride
 * so): the data, then p pixels each side continued by odd reflection about the end pixel
 * (2 v_end − v_mirror: value and slope continue, so a sub-pixel shift extrapolates the edge
 * linearly instead of flattening it), tapered by cos² to the mean of the two end pixels,
 * which fills the rest of the period: continuous with continuous slope all round, so the
 * spectrum has no edge jump or kink to ring from. */
#define SHIFT_PAD 16
static void continue_line(const double *v, size_t sv, int n, int p, int len, double *out,
                          size_t so)
{
    const double first = v[0], last = v[(size_t)(n - 1) * sv], m = 0.5 * (first + last);
    for (int x = 0; x < n; x++) out[(size_t)x * so] = v[(size_t)x * sv];
    for (int x = n; x < len; x++) out[(size_t)x * so] = m;
    for (int j = 1; j <= p; j++) {
        const double c = cos(0.5 * M_PI * j / p), t = c * c;
        const int k = j < n - 1 ? j : n - 1;
        const double right = 2 * last - v[(size_t)(n - 1 - k) * sv];
        const double left = 2 * first - v[(size_t)k * sv];
        out[(size_t)(n - 1 + j) * so] = m + (right - m) * t;
        out[(size_t)(len - j) * so] = m + (left - m) * t;
    }
}

svp_status svp_shift(const svp_image *in, double dx, double dy, svp_image *out)
{
    if (!in || !in->data || in->width < 1 || in->height < 1)
        return svp_fail(SVP_ERR_INVALID, "shift: no input image");
    if (!out || !out->data) return svp_fail(SVP_ERR_INVALID, "shift: no output image");
    if (out->width != in->width || out->height != in->height)
        return svp_fail(SVP_ERR_SIZE, "shift: input %d x %d but output %d x %d", in->width,
                        in->height, out->width, out->height);
    const int w = in->width, h = in->height;
    if (!(fabs(dx) < w) || !(fabs(dy) < h))
        return svp_fail(SVP_ERR_INVALID,
                        "shift: (%g, %g) px for a %d x %d image (|d| must be "
                        "below the size)",
                        dx, dy, w, h);
    /* the continuation: P pixels or more each side, enough for the shift and a taper */
    const int px = (int)ceil(fabs(dx)) + SHIFT_PAD, py = (int)ceil(fabs(dy)) + SHIFT_PAD;
    const int W = svp_fft_good_size(w + 2 * px), H = svp_fft_good_size(h + 2 * py);
    const int ncx = W / 2 + 1;
    const size_t n = (size_t)w * h;
    const svp_fft_plan *plan = NULL;
    SVP_CHECK(svp_fft_plan_get(H, W, &plan));
    double *img = svp_alloc(n * sizeof(double)), *ext = svp_alloc((size_t)W * H * sizeof(double));
    fftw_complex *spec = svp_alloc((size_t)H * ncx * sizeof(fftw_complex));
    fftw_complex *ex = svp_alloc((size_t)ncx * sizeof(fftw_complex));
    fftw_complex *ey = svp_alloc((size_t)H * sizeof(fftw_complex));
    double *line = svp_alloc((size_t)(W > H ? W : H) * sizeof(double));
    unsigned char *bad = calloc(n, 1);
    svp_status st = SVP_OK;
    if (!img || !ext || !spec || !ex || !ey || !line || !bad) {
        st = svp_fail(SVP_ERR_NOMEM, "shift: out of memory for a %d x %d image", w, h);
        goto done;
    }
    size_t n_bad = 0;
    double sum = 0;
    for (size_t i = 0; i < n; i++) {
        const double v = in->data[i];
        if (isfinite(v)) {
            img[i] = v;
            sum += v;
        } else {
            img[i] = NAN;
            bad[i] = 1;
            n_bad++;
        }
    }
    if (n_bad == n) {
        for (size_t i = 0; i < n; i++) out->data[i] = NAN;
        goto done;
    }
    if (n_bad && (st = fill_holes(img, w, h, sum / (double)(n - n_bad))) != SVP_OK) goto done;
    /* rows continued along x (data at 0 .. w − 1, the right side next, the left side at the
     * end: the period wraps), then every column along y */
    for (int y = 0; y < h; y++)
        continue_line(img + (size_t)y * w, 1, w, px, W, ext + (size_t)y * W, 1);
    for (int x = 0; x < W; x++) {
        for (int y = 0; y < h; y++) line[y] = ext[(size_t)y * W + x];
        continue_line(line, 1, h, py, H, ext + x, W);
    }
    svp_fft_forward(plan, ext, spec);
    shift_phases(W, ncx, dx, ex);
    shift_phases(H, H, dy, ey);
    const double scale = 1.0 / ((double)W * H);
    for (int ky = 0; ky < H; ky++) {
        fftw_complex *restrict row = spec + (size_t)ky * ncx;
        const fftw_complex eyk = ey[ky] * scale;
        for (int kx = 0; kx < ncx; kx++) row[kx] *= eyk * ex[kx];
    }
    svp_fft_inverse_unscaled(plan, spec, ext);
    /* NaN where the nearest source pixel (x − dx, y − dy) was not finite */
    const int ix = (int)floor(dx + 0.5), iy = (int)floor(dy + 0.5);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double v = ext[(size_t)y * W + x];
            if (n_bad) {
                int sx = x - ix, sy = y - iy;
                sx = sx < 0 ? 0 : sx >= w ? w - 1 : sx;
                sy = sy < 0 ? 0 : sy >= h ? h - 1 : sy;
                if (bad[(size_t)sy * w + sx]) v = NAN;
            }
            out->data[(size_t)y * w + x] = v;
        }
done:
    svp_free(img);
    svp_free(ext);
    svp_free(spec);
    svp_free(ex);
    svp_free(ey);
    svp_free(line);
    free(bad);
    return st;
}

/* Weighted least squares of a polynomial of degree `deg` in t (the frame index mapped onto
 * [−1, 1]) to v: c[0 .. deg] by Gaussian elimination with partial pivoting of the normal
 * equations (at most 6 x 6, well conditioned on [−1, 1]). 0 when singular. */
static int poly_fit(int n, const double *t, const double *v, const double *wt, int deg, double *c)
{
    const int k = deg + 1;
    double A[6][7] = {{0}};
    for (int i = 0; i < n; i++) {
        if (wt[i] == 0) continue; /* an outlier's or a missing frame's (v may be NaN) */
        double p[6];
        p[0] = 1;
        for (int j = 1; j < k; j++) p[j] = p[j - 1] * t[i];
        for (int r = 0; r < k; r++) {
            for (int q = 0; q < k; q++) A[r][q] += wt[i] * p[r] * p[q];
            A[r][k] += wt[i] * p[r] * v[i];
        }
    }
    for (int col = 0; col < k; col++) {
        int piv = col;
        for (int r = col + 1; r < k; r++)
            if (fabs(A[r][col]) > fabs(A[piv][col])) piv = r;
        if (!(fabs(A[piv][col]) > 1e-12 * (fabs(A[0][0]) + DBL_MIN))) return 0;
        for (int q = 0; q <= k; q++) {
            const double tmp = A[col][q];
            A[col][q] = A[piv][q];
            A[piv][q] = tmp;
        }
        for (int r = 0; r < k; r++) {
            if (r == col) continue;
            const double f = A[r][col] / A[col][col];
            for (int q = col; q <= k; q++) A[r][q] -= f * A[col][q];
        }
    }
    for (int r = 0; r < k; r++) c[r] = A[r][k] / A[r][r];
    return 1;
}

static double poly_eval(const double *c, int deg, double t)
{
    double v = 0;
    for (int j = deg; j >= 0; j--) v = v * t + c[j];
    return v;
}

static int cmp_double(const void *a, const void *b)
{
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* The smooth drift: the polynomial fit of the measured shifts (mx, my) by Tukey's biweight,
 * iteratively reweighted (scale 1.4826 × the median distance to the fit, at least 1e-4 px;
 * cut-off 4.685 scales); the fitted shifts to (fx, fy). */
static svp_status smooth_drift(int n, int deg, const double *mx, const double *my, double *fx,
                               double *fy, double *median)
{
    double *t = malloc((size_t)n * 4 * sizeof(double));
    if (!t) return svp_fail(SVP_ERR_NOMEM, "align: out of memory");
    double *wt = t + n, *res = t + 2 * n, *sorted = t + 3 * n, cx[6], cy[6];
    for (int i = 0; i < n; i++) {
        t[i] = n > 1 ? 2.0 * i / (n - 1) - 1 : 0;
        wt[i] = isfinite(mx[i]) && isfinite(my[i]); /* a missing frame has no say */
    }
    svp_status st = SVP_OK;
    for (int it = 0; it < 30; it++) {
        if (!poly_fit(n, t, mx, wt, deg, cx) || !poly_fit(n, t, my, wt, deg, cy)) {
            st = svp_fail(SVP_ERR_NUMERIC,
                          "align: the drift polynomial of degree %d is "
                          "undetermined (too few frames agree on a drift)",
                          deg);
            break;
        }
        int m = 0; /* the measured frames' residuals */
        for (int i = 0; i < n; i++) {
            res[i] = hypot(mx[i] - poly_eval(cx, deg, t[i]), my[i] - poly_eval(cy, deg, t[i]));
            if (isfinite(res[i])) sorted[m++] = res[i];
        }
        qsort(sorted, (size_t)m, sizeof(double), cmp_double);
        const double med = m % 2 ? sorted[m / 2] : 0.5 * (sorted[m / 2 - 1] + sorted[m / 2]);
        *median = med;
        const double cut = 4.685 * fmax(1.4826 * med, 1e-4);
        double change = 0;
        for (int i = 0; i < n; i++) {
            const double u = res[i] / cut, w = u < 1 ? (1 - u * u) * (1 - u * u) : 0;
            change = fmax(change, fabs(w - wt[i]));
            wt[i] = w;
        }
        if (change < 1e-6) break;
    }
    for (int i = 0; i < n && st == SVP_OK; i++) {
        fx[i] = poly_eval(cx, deg, t[i]);
        fy[i] = poly_eval(cy, deg, t[i]);
    }
    free(t);
    return st;
}

/* One pass of svp_cube_align over the frames: registered on `mean` (moving 0: the
 * displacement, correlation and significance of each), or moved back by (ax, ay) in place
 * (moving 1). */
typedef struct align_job {
    svp_cube *cube;
    const svp_image *mean;
    const svp_register_options *o;
    double *mx, *my, *corr, *sig;
    const double *ax, *ay;
    int moving;
    svp_progress_fn progress;
    void *progress_user;
    double base, span; /* the pass's share of the progress */
} align_job;

static svp_status align_frame(void *ctx, int worker, int f)
{
    const align_job *j = ctx;
    (void)worker;
    if (svp_image_count_nonfinite(j->cube->frame[f]) ==
        (size_t)j->cube->width * j->cube->height) { /* a missing frame: no shift to measure */
        if (!j->moving) j->mx[f] = j->my[f] = j->corr[f] = j->sig[f] = NAN;
        return SVP_OK;
    }
    if (j->moving) return svp_shift(j->cube->frame[f], -j->ax[f], -j->ay[f], j->cube->frame[f]);
    svp_register_options o = *j->o;
    char name[48];
    snprintf(name, sizeof name, "frame %d", f);
    o.moving_name = name;
    svp_register_result r;
    SVP_CHECK(svp_register(j->mean, j->cube->frame[f], &o, &r));
    j->mx[f] = r.affine[2];
    j->my[f] = r.affine[5];
    j->corr[f] = r.correlation;
    j->sig[f] = r.significance;
    return SVP_OK;
}

/* A pass over the frames on every thread (svp_items_parallel: one-thread FFT plans each, so
 * the results do not depend on the thread count). */
static svp_status align_frames(align_job *j)
{
    return svp_items_parallel(j->cube->n_freq, svp_get_threads(), align_frame, j, j->progress,
                              j->progress_user, j->base, j->span);
}

void svp_align_defaults(svp_align_options *options)
{
    if (!options) return;
    options->degree = 1;
    options->reference_frame = -1;
    options->registration = NULL;
}

svp_status svp_cube_align(svp_cube *cube, const svp_align_options *options, double *shift_x,
                          double *shift_y, svp_align_info *info, svp_progress_fn progress,
                          void *progress_user)
{
    svp_align_options ao;
    svp_align_defaults(&ao);
    if (options) ao = *options;
    const int degree = ao.degree;
    if (info) *info = (svp_align_info){0, 0, 0, INFINITY, -1, 0, INFINITY};
    if (!cube || !cube->frame) return svp_fail(SVP_ERR_INVALID, "align: no cube");
    const int w = cube->width, h = cube->height, nf = cube->n_freq;
    if (degree < -1 || degree > 5)
        return svp_fail(SVP_ERR_INVALID, "align: drift degree %d (must be -1 .. 5)", degree);
    if (nf < 2 || (degree >= 0 && nf <= degree + 1))
        return svp_fail(SVP_ERR_INVALID, "align: %d frame(s); at least %d needed", nf,
                        degree + 2 > 2 ? degree + 2 : 2);
    if (ao.reference_frame < -1 || ao.reference_frame >= nf)
        return svp_fail(SVP_ERR_INVALID, "align: reference frame %d of %d frames (-1: the mean "
                        "position)", ao.reference_frame, nf);
    for (int f = 0; f < nf; f++)
        if (!cube->frame[f] || !cube->frame[f]->data || cube->frame[f]->width != w ||
            cube->frame[f]->height != h)
            return svp_fail(SVP_ERR_SIZE, "align: frame %d is missing or not %d x %d", f, w, h);
    svp_register_options o;
    svp_register_defaults(&o);
    if (ao.registration) o = *ao.registration;
    if (o.motion != SVP_MOTION_TRANSLATION)
        return svp_fail(SVP_ERR_INVALID,
                        "align: frames are aligned by translation only (motion "
                        "%s)",
                        motion_name(o.motion));
    o.initial_affine = NULL;
    o.contrast = SVP_CONTRAST_SAME; /* frames of one scene: a trough is no match */
    const size_t n = (size_t)w * h;
    svp_image *mean = NULL;
    svp_status st = svp_image_new(w, h, &mean);
    double *count = st == SVP_OK ? svp_alloc(n * sizeof(double)) : NULL;
    double *d = st == SVP_OK ? malloc((size_t)nf * 6 * sizeof(double)) : NULL;
    if (st == SVP_OK && (!count || !d)) st = svp_fail(SVP_ERR_NOMEM, "align: out of memory");
    if (st != SVP_OK) goto done;
    double *mx = d, *my = d + nf, *ax = d + 2 * nf, *ay = d + 3 * nf, median = 0;
    double *corr = d + 4 * nf, *sig = d + 5 * nf;
    /* the reference: the mean frame (over the finite values of each pixel) */
    memset(count, 0, n * sizeof(double));
    for (int f = 0; f < nf; f++) {
        const double *v = cube->frame[f]->data;
        for (size_t i = 0; i < n; i++)
            if (isfinite(v[i])) {
                mean->data[i] += v[i];
                count[i] += 1;
            }
    }
    for (size_t i = 0; i < n; i++) mean->data[i] = count[i] > 0 ? mean->data[i] / count[i] : NAN;
    o.reference_name = "the mean frame";
    align_job job = {.cube = cube, .mean = mean, .o = &o, .mx = mx, .my = my, .corr = corr,
                     .sig = sig, .ax = ax, .ay = ay, .moving = 0, .progress = progress,
                     .progress_user = progress_user, .base = 0, .span = 0.5};
    st = align_frames(&job);
    for (int f = 0; f < nf && st == SVP_OK && info; f++) {
        if (isnan(corr[f])) continue; /* a missing frame */
        if (!(corr[f] >= info->min_correlation)) {
            info->min_correlation = corr[f];
            info->worst_frame = f;
        }
        info->n_low_correlation += !(corr[f] >= SVP_ALIGN_MIN_CORRELATION);
        info->min_significance = fmin(info->min_significance, sig[f]);
    }
    if (st == SVP_OK && degree >= 0) st = smooth_drift(nf, degree, mx, my, ax, ay, &median);
    if (st != SVP_OK) goto done;
    if (degree < 0) {
        memcpy(ax, mx, (size_t)nf * sizeof(double));
        memcpy(ay, my, (size_t)nf * sizeof(double));
    }
    if (info) info->median_deviation = median;
    if (st == SVP_OK && ao.reference_frame >= 0 && !isfinite(ax[ao.reference_frame]))
        st = svp_fail(SVP_ERR_INVALID,
                      "align: reference frame %d has no finite pixel, so no position of its "
                      "own (with drift degree -1); choose another frame or a degree >= 0",
                      ao.reference_frame);
    if (st != SVP_OK) goto done;
    if (ao.reference_frame >= 0) { /* to frame k's position: every shift relative to its */
        const double kx = ax[ao.reference_frame], ky = ay[ao.reference_frame];
        for (int f = 0; f < nf; f++) {
            ax[f] -= kx, ay[f] -= ky;
            mx[f] -= kx, my[f] -= ky;
        }
    }
    for (int f = 0; f < nf; f++) {
        if (shift_x) shift_x[f] = ax[f];
        if (shift_y) shift_y[f] = ay[f];
        if (info) {
            info->max_shift = fmax(info->max_shift, hypot(ax[f], ay[f]));
            info->max_deviation = fmax(info->max_deviation, hypot(mx[f] - ax[f], my[f] - ay[f]));
        }
    }
    /* moving(x) = mean(x − d): each frame moved back by −d, in place */
    job.moving = 1;
    job.base = 0.5;
    st = align_frames(&job);
done:
    svp_image_free(mean);
    svp_free(count);
    free(d);
    return st;
}
