/* Wiener–Hunt deconvolution (docs/model.md §Deconvolution): X = conj(P) Y / (|P|² + λ |L|²),
 * L the 5-point Laplacian, in a frame where the invariant operator is Fourier-diagonal, the
 * halo inverted exactly through a scalar equation for the mean, and missing (NaN/Inf) data
 * filled first (normalised convolution, refined by CG to the masked Tikhonov fill: a plain
 * normalised-convolution fill is inconsistent with the blur and the inverse filter amplifies
 * the mismatch — 0.19 of the peak at balance 1e-4 in tests/test_restore.c, 2e-4 refined).
 * The zero boundary (light leaving the field is lost: no frame makes it Fourier-diagonal)
 * solves the same regularised problem of the linear operator by preconditioned CG
 * (wiener_zero below). Space-variant operators go to svp_deconv_tikhonov_cg (cg.c). */
#include "restore_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define PI 3.14159265358979323846

#define ZERO_CG_MAX 400 /* default step cap of the zero-boundary CG */

void svp_deconv_defaults(svp_deconv_options *o)
{
    if (!o) return;
    o->balance = 1e-3;
    o->iterations = 50;
    o->floor = 1e-9;
    o->boundary_weights = 1;
    o->progress = NULL;
    o->progress_user = NULL;
    o->cg_max_steps = ZERO_CG_MAX;
    o->report = NULL;
    o->single_precision = 0;
    o->acceleration = SVP_RL_PLAIN;
    o->auto_stop = 0;
    o->variance = NULL;
}

svp_status svp_deconv_check_images(const svp_blur *blur, const svp_image *y, const svp_image *x,
                                   const char *what)
{
    if (!blur) return svp_fail(SVP_ERR_INVALID, "%s: the blur operator is NULL", what);
    if (!y || !y->data) return svp_fail(SVP_ERR_INVALID, "%s: the data image y is NULL", what);
    if (!x || !x->data) return svp_fail(SVP_ERR_INVALID, "%s: the output image x is NULL", what);
    if (y->width != blur->width || y->height != blur->height)
        return svp_fail(SVP_ERR_SIZE, "%s: the operator is %d x %d but the data y are %d x %d",
                        what, blur->width, blur->height, y->width, y->height);
    if (x->width != blur->width || x->height != blur->height)
        return svp_fail(SVP_ERR_SIZE, "%s: the operator is %d x %d but the output x is %d x %d",
                        what, blur->width, blur->height, x->width, x->height);
    if (x->data == y->data)
        return svp_fail(SVP_ERR_INVALID, "%s: the output x must not be the data y", what);
    char name[96];
    snprintf(name, sizeof name, "%s: the data y", what);
    return svp_image_check_scale(y, name);
}

/* 2 − 2 cos(2π k / n) = 4 sin²(π k / n): one axis of the Laplacian's transfer function,
 * written with the sine so it stays accurate near zero frequency. */
static double laplacian_axis(int k, int n)
{
    double s = sin(PI * (double)k / (double)n);
    return 4.0 * s * s;
}

/* Missing data: y_filled = y where finite, else H(m y) / H(m) (normalised convolution with
 * the operator itself, m the finite mask); where H(m) is ~0 (no finite pixel within reach),
 * the mean of the finite values. */
static svp_status fill_missing(svp_blur *blur, const svp_image *y, size_t n_finite,
                               double *restrict filled)
{
    const size_t n = (size_t)y->width * y->height;
    svp_status st = SVP_OK;
    double *mask = svp_alloc(n * sizeof(double)), *h_masked = svp_alloc(n * sizeof(double)),
           *h_mask = svp_alloc(n * sizeof(double));
    if (!mask || !h_masked || !h_mask) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory filling missing pixels");
        goto cleanup;
    }
    const double *restrict yd = y->data;
#pragma omp parallel for schedule(static) if (n > 32768)
    for (size_t i = 0; i < n; i++) {
        int ok = isfinite(yd[i]);
        mask[i] = ok ? 1.0 : 0.0;
        filled[i] = ok ? yd[i] : 0.0;
    }
    const double mean_finite = svp_sum(filled, n) / (double)n_finite;
    svp_image img_mask = {y->width, y->height, mask}, img_masked = {y->width, y->height, filled};
    svp_image img_h_mask = {y->width, y->height, h_mask};
    svp_image img_h_masked = {y->width, y->height, h_masked};
    if ((st = svp_blur_apply(blur, &img_masked, &img_h_masked)) != SVP_OK) goto cleanup;
    if ((st = svp_blur_apply(blur, &img_mask, &img_h_mask)) != SVP_OK) goto cleanup;
    /* below this weight the ratio is dominated by FFT round-off (~1e-16 of the peak) */
    const double reach = 1e-10 * svp_max(h_mask, n);
#pragma omp parallel for schedule(static) if (n > 32768)
    for (size_t i = 0; i < n; i++) {
        if (mask[i] != 0) continue;
        double v = h_mask[i] > reach ? h_masked[i] / h_mask[i] : mean_finite;
        filled[i] = isfinite(v) ? v : mean_finite;
    }
cleanup:
    svp_free(mask);
    svp_free(h_masked);
    svp_free(h_mask);
    return st;
}

/* CG on the fill values z of the missing pixels: minimise Q(z) = <E y_z, R E y_z>, y_z = y
 * with z at the missing pixels, E the frame extension and R = λ|L|² / (|P|² + λ|L|²) the
 * Wiener residual filter (the part of the data no smooth object explains). Its minimiser is
 * the masked Tikhonov solution's prediction H x at the holes: for a periodic frame it gives
 * exactly argmin ‖m (Hx − y)‖² + λ ‖Lx‖². Started at the normalised-convolution fill; at most
 * FILL_CG_MAX steps of one FFT pair each (isolated missing pixels converge in a few). */
#define FILL_CG_MAX 40
#define FILL_CG_TOL 1e-9

typedef struct residual_op {
    const svp_frame *f;
    const double *residual_filter; /* R, ny x ncx, already scaled by 1 / (nx ny) */
    double *frame;
    fftw_complex *spectrum;
    double *image; /* width x height scratch */
} residual_op;

/* out = [Eᵀ R E v]_missing for v nonzero only at the missing pixels idx[0..nm). */
static void residual_apply(residual_op *op, const size_t *idx, size_t nm, const double *v,
                           double *out)
{
    const svp_frame *f = op->f;
    const size_t n = (size_t)f->width * f->height;
    memset(op->image, 0, n * sizeof(double));
    for (size_t k = 0; k < nm; k++) op->image[idx[k]] = v[k];
    svp_frame_extend(f, op->image, op->frame);
    svp_fft_forward(f->plan, op->frame, op->spectrum);
    const size_t nc = (size_t)f->ny * f->ncx;
#pragma omp parallel for schedule(static) if (nc > 32768)
    for (size_t k = 0; k < nc; k++) op->spectrum[k] *= op->residual_filter[k];
    svp_fft_inverse_unscaled(f->plan, op->spectrum, op->frame);
    svp_frame_fold(f, op->frame, op->image);
    for (size_t k = 0; k < nm; k++) out[k] = op->image[idx[k]];
}

static double dot(const double *a, const double *b, size_t n)
{
    double s = 0;
    for (size_t i = 0; i < n; i++) s += a[i] * b[i];
    return s;
}

static svp_status refine_fill(residual_op *op, const double *y_data, double *filled)
{
    const size_t n = (size_t)op->f->width * op->f->height;
    size_t nm = 0;
    for (size_t i = 0; i < n; i++) nm += !isfinite(y_data[i]);
    size_t *idx = malloc(nm * sizeof *idx);
    double *z = malloc(nm * sizeof *z), *r = malloc(nm * sizeof *r), *p = malloc(nm * sizeof *p),
           *ap = malloc(nm * sizeof *ap);
    svp_status st = SVP_OK;
    if (!idx || !z || !r || !p || !ap) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for %zu missing pixels", nm);
        goto cleanup;
    }
    nm = 0;
    for (size_t i = 0; i < n; i++)
        if (!isfinite(y_data[i])) {
            idx[nm] = i;
            z[nm++] = filled[i];
        }
    /* r = −[Eᵀ R E y_z]_m: the negative gradient of Q at the start */
    const svp_frame *f = op->f;
    svp_frame_extend(f, filled, op->frame);
    svp_fft_forward(f->plan, op->frame, op->spectrum);
    const size_t nc = (size_t)f->ny * f->ncx;
    for (size_t k = 0; k < nc; k++) op->spectrum[k] *= op->residual_filter[k];
    svp_fft_inverse_unscaled(f->plan, op->spectrum, op->frame);
    svp_frame_fold(f, op->frame, op->image);
    for (size_t k = 0; k < nm; k++) p[k] = r[k] = -op->image[idx[k]];
    double rr = dot(r, r, nm);
    const double stop = FILL_CG_TOL * FILL_CG_TOL * rr;
    for (int it = 0; it < FILL_CG_MAX && rr > stop && rr > 0; it++) {
        residual_apply(op, idx, nm, p, ap);
        double pap = dot(p, ap, nm);
        if (!(pap > 0)) break; /* Q flat along p (e.g. balance 0): keep what we have */
        double step = rr / pap;
        for (size_t k = 0; k < nm; k++) {
            z[k] += step * p[k];
            r[k] -= step * ap[k];
        }
        double rr_new = dot(r, r, nm);
        for (size_t k = 0; k < nm; k++) p[k] = r[k] + (rr_new / rr) * p[k];
        rr = rr_new;
    }
    for (size_t k = 0; k < nm; k++)
        if (isfinite(z[k])) filled[idx[k]] = z[k];
cleanup:
    free(idx);
    free(z);
    free(r);
    free(p);
    free(ap);
    return st;
}

/* ---- the solvers' workspace kept with the operator ---------------------------------------- */

static void cache_release(void *data)
{
    svp_restore_cache *c = data;
    if (!c) return;
    svp_free(c->wiener_filter);
    svp_free(c->wiener_gain);
    if (c->wiener_frame) {
        svp_frame_release(c->wiener_frame);
        free(c->wiener_frame);
    }
    svp_free(c->wiener_work_r);
    svp_free(c->wiener_work_c);
    free(c);
}

/* The caches once made: the zero-boundary filter (on the operator's frame), the gain and the
 * mirror Wiener's own frame with its buffers. */
static size_t cache_memory(const void *data)
{
    const svp_restore_cache *c = data;
    if (!c) return 0;
    size_t bytes = sizeof *c;
    const svp_frame *wf = c->wiener_frame;
    if (c->wiener_filter) bytes += c->filter_bytes;
    if (c->wiener_gain) bytes += c->gain_bytes;
    if (wf)
        bytes += svp_frame_memory(wf) + (size_t)wf->ny * wf->nx * sizeof(double) +
                 (size_t)wf->ny * wf->ncx * sizeof(fftw_complex);
    return bytes;
}

svp_restore_cache *svp_restore_cache_of(svp_blur *blur)
{
    if (blur->restore.data) return blur->restore.data;
    svp_restore_cache *c = calloc(1, sizeof *c);
    if (!c) {
        svp_fail(SVP_ERR_NOMEM, "out of memory for the solver's workspace");
        return NULL;
    }
    blur->restore.data = c;
    blur->restore.release = cache_release;
    blur->restore.memory = cache_memory;
    return c;
}

void svp_restore_wiener_counts(const svp_blur *blur, int *steps, int *pairs)
{
    const svp_restore_cache *c = blur->restore.data;
    *steps = c ? c->wiener_steps : 0;
    *pairs = c ? c->wiener_pairs : 0;
}

/* Wiener–Hunt for the invariant operator with the periodic or mirror boundary, in a frame that
 * makes the problem Fourier-diagonal: periodic → the periodic frame at the image size; mirror
 * → the full symmetric period (2 width x 2 height) with the data mirror-extended.
 *
 * Halo α: H = (1 − α) K + α mean. With D the Wiener filter of K, D y = (1 − α) x + α m D1,
 * m = mean(x), so x = (D y − α m D1) / (1 − α) and, taking means,
 * m = mean(D y) / (1 − α + α mean(D1)); D1 is the constant D(0) = 1 / P(0).
 *
 * filled != NULL: y_data holds NaN/Inf at missing pixels and filled their normalised-
 * convolution fill; the fill is refined (refine_fill) in this frame before filtering. */
static svp_status wiener_invariant(svp_blur *blur, const double *y_data, double *filled,
                                   double balance,
                                   double *restrict x_data)
{
    const int w = blur->width, h = blur->height;
    const size_t n = (size_t)w * h;
    SVP_CHECK(svp_blur_ready(blur)); /* the operator's frame and buffers are used below */
    svp_restore_cache *rc = svp_restore_cache_of(blur);
    if (!rc) return SVP_ERR_NOMEM;
    double *lap_x = NULL, *lap_y = NULL, *residual = NULL, *scratch = NULL;
    svp_status st = SVP_OK;
    /* The frame, its OTF, its buffers and the gain are cached in the operator: periodic uses
     * the operator's own frame and work buffers (the same placement of the same kernel);
     * mirror a full-period frame (radii = the image size force it) made on first use. */
    svp_frame *fp = &blur->frame;
    double *frame = blur->work_r;
    fftw_complex *spectrum = blur->work_c;
    if (blur->boundary == SVP_BOUNDARY_MIRROR) {
        if (!rc->wiener_frame) {
            svp_frame *nf = calloc(1, sizeof *nf);
            if (!nf) return svp_fail(SVP_ERR_NOMEM, "out of memory for a Wiener frame");
            if ((st = svp_frame_init(nf, w, h, w, h, SVP_BOUNDARY_MIRROR)) == SVP_OK)
                st = svp_frame_set_kernel(nf, blur->kernel, blur->kcx, blur->kcy,
                                          SVP_BOUNDARY_MIRROR);
            if (st == SVP_OK) {
                rc->wiener_work_r = svp_alloc((size_t)nf->ny * nf->nx * sizeof(double));
                rc->wiener_work_c = svp_alloc((size_t)nf->ny * nf->ncx * sizeof(fftw_complex));
                if (!rc->wiener_work_r || !rc->wiener_work_c)
                    st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d Wiener frame",
                                  nf->nx, nf->ny);
            }
            if (st != SVP_OK) {
                svp_frame_release(nf);
                free(nf);
                svp_free(rc->wiener_work_r);
                svp_free(rc->wiener_work_c);
                rc->wiener_work_r = NULL;
                rc->wiener_work_c = NULL;
                return st;
            }
            rc->wiener_frame = nf;
            rc->wiener_gain_ok = 0;
        }
        fp = rc->wiener_frame;
        frame = rc->wiener_work_r;
        spectrum = rc->wiener_work_c;
    }
    const svp_frame *f = fp;
    const int nx = f->nx, ny = f->ny, ncx = f->ncx;
    const size_t nc = (size_t)ny * ncx;
    if (!rc->wiener_gain) {
        rc->wiener_gain = svp_alloc(nc * sizeof(fftw_complex));
        rc->gain_bytes = nc * sizeof(fftw_complex);
        rc->wiener_gain_ok = 0;
    }
    fftw_complex *gain = rc->wiener_gain;
    const int need_gain = !(rc->wiener_gain_ok && rc->wiener_balance == balance);
    if (need_gain || filled) {
        lap_x = malloc((size_t)ncx * sizeof(double));
        lap_y = malloc((size_t)ny * sizeof(double));
    }
    if (filled) {
        residual = svp_alloc(nc * sizeof(double));
        scratch = svp_alloc(n * sizeof(double));
    }
    if (!gain || ((need_gain || filled) && (!lap_x || !lap_y)) ||
        (filled && (!residual || !scratch))) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d Wiener frame", nx, ny);
        goto cleanup;
    }
    if (lap_x) {
        for (int u = 0; u < ncx; u++) lap_x[u] = laplacian_axis(u, nx);
        for (int v = 0; v < ny; v++) lap_y[v] = laplacian_axis(v, ny);
    }

    /* gain G = conj(P) / (|P|² + λ|L|²) / (nx ny); residual filter R = λ|L|² / (...) too */
    const double scale = 1.0 / ((double)nx * ny);
    if (need_gain || filled) {
        rc->wiener_gain_ok = 0;
#pragma omp parallel for schedule(static) if (nc > 32768)
        for (int v = 0; v < ny; v++) {
            for (int u = 0; u < ncx; u++) {
                size_t k = (size_t)v * ncx + u;
                double lap = lap_x[u] + lap_y[v];
                double prior = balance * lap * lap;
                const double complex o = svp_frame_otf(f, k);
                double denom = creal(o) * creal(o) + cimag(o) * cimag(o) + prior;
                /* a frequency neither the PSF nor the prior sees: the pseudo-inverse gives 0 */
                fftw_complex g = denom > 0 ? conj(o) * (scale / denom) : 0;
                if (!isfinite(creal(g)) || !isfinite(cimag(g))) g = 0;
                gain[k] = g;
                if (residual) residual[k] = denom > 0 ? prior / denom * scale : 0.0;
            }
        }
        rc->wiener_balance = balance;
        rc->wiener_gain_ok = 1;
    }
    if (filled) {
        residual_op op = {f, residual, frame, spectrum, scratch};
        if ((st = refine_fill(&op, y_data, filled)) != SVP_OK) goto cleanup;
        y_data = filled;
    }

    svp_frame_extend(f, y_data, frame);
    svp_fft_forward(f->plan, frame, spectrum);
    svp_spectrum_product((const double *)gain, (double *)spectrum, nc, 0, 1.0);
    /* D1 = the gain at zero frequency (L(0) = 0), unscaled */
    const double p0 = creal(svp_frame_otf(f, 0));
    const double d_one = p0 != 0 && isfinite(1.0 / p0) ? 1.0 / p0 : 0.0;
    svp_fft_inverse_unscaled(f->plan, spectrum, frame);
    svp_frame_crop(f, frame, x_data);

    const double alpha = blur->halo;
    double shift = 0, stretch = 1;
    if (alpha > 0) {
        const double mean_dy = svp_sum(x_data, n) / (double)n;
        const double denom = 1.0 - alpha + alpha * d_one;
        const double mean_x = denom != 0 ? mean_dy / denom : 0.0;
        shift = alpha * mean_x * d_one;
        stretch = 1.0 / (1.0 - alpha);
    }
#pragma omp parallel for schedule(static) if (n > 32768)
    for (size_t i = 0; i < n; i++) {
        double v = (x_data[i] - shift) * stretch;
        x_data[i] = isfinite(v) ? v : 0.0;
    }
cleanup:
    svp_free(residual);
    svp_free(scratch);
    free(lap_x);
    free(lap_y);
    return st;
}

/* ---- zero boundary: the Tikhonov problem of the linear operator, by PCG ------------------ */

/* With the zero boundary the data are y = C K E0 x (light leaving the field of view is lost),
 * which no Fourier-diagonal frame reproduces: a mirror-extended frame mistakes the lost light
 * for a darker object (with a β = 1.1 tail the error reached 2.2 × the peak over the whole
 * image). So the zero boundary solves the regularised problem of the true operator,
 *     (Hᵀ M H + λ LᵀL) x = Hᵀ M y,
 * M the finite-data mask and L the 5-point Laplacian with reflecting (Neumann) ends — the
 * smoothness prior says nothing about the object beyond the field, a Dirichlet L would pull the
 * border to zero (measured: 1.6 % of the peak at λ = 1e-6 against 0.05 % with Neumann) — by
 * conjugate gradients preconditioned with the Wiener filter 1 / (|Ĥ|² + λ|L̂|²) on the
 * operator's own zero-padded frame: the filter would be exact if the light spilled beyond the
 * field were observed too, so the preconditioned system differs from the identity only by that
 * smooth spill term and CG converges in tens of steps (76 to a residual of 1e-10 for 128², β =
 * 1.1, λ = 1e-6, against 182 with a periodic image-size preconditioner). Each step costs three
 * FFT pairs at the operator's padded size (H, Hᵀ, the preconditioner). */
#define ZERO_CG_TOL 1e-8

/* out = L in, Neumann ends: Σ over the in-image neighbours of (in(p) − in(q)). */
static void laplacian_neumann(int w, int h, const double *restrict in, double *restrict out)
{
#pragma omp parallel for schedule(static) if ((size_t)w * h > SVP_PARALLEL_MIN)
    for (int y = 0; y < h; y++) {
        const double *row = in + (size_t)y * w;
        const double *up = y > 0 ? row - w : row, *down = y < h - 1 ? row + w : row;
        double *o = out + (size_t)y * w;
        for (int x = 0; x < w; x++) {
            const double c = row[x];
            double v = (c - up[x]) + (c - down[x]);
            if (x > 0) v += c - row[x - 1];
            if (x < w - 1) v += c - row[x + 1];
            o[x] = v;
        }
    }
}

void svp_tikhonov_invert(double *restrict filt, int nx, int ny, int ncx, double balance)
{
    const size_t nc = (size_t)ny * ncx;
    const double scale = 1.0 / ((double)nx * ny);
    double hmax2 = 0;
    for (size_t k = 0; k < nc; k++)
        if (filt[k] > hmax2) hmax2 = filt[k];
    /* a floor keeps the filter bounded where neither H nor L passes anything */
    const double floor = 1e-12 * (hmax2 > 0 ? hmax2 : 1.0);
#pragma omp parallel for schedule(static) if (nc > SVP_PARALLEL_MIN)
    for (int v = 0; v < ny; v++) {
        const double ly = laplacian_axis(v, ny);
        for (int u = 0; u < ncx; u++) {
            const double lap = laplacian_axis(u, nx) + ly;
            const size_t k = (size_t)v * ncx + u;
            const double d = filt[k] + balance * lap * lap;
            filt[k] = scale / (d > floor ? d : floor);
        }
    }
}

/* The preconditioner's filter on the operator's frame for this balance, cached in the blur. */
static svp_status zero_filter(svp_blur *blur, double balance, const double **out)
{
    svp_restore_cache *rc = svp_restore_cache_of(blur);
    if (!rc) return SVP_ERR_NOMEM;
    const svp_frame *f = &blur->frame;
    const int ncx = f->ncx, ny = f->ny;
    const size_t nc = (size_t)ny * ncx;
    if (rc->wiener_filter && rc->wiener_balance == balance) {
        *out = rc->wiener_filter;
        return SVP_OK;
    }
    if (!rc->wiener_filter) {
        rc->wiener_filter = svp_alloc(nc * sizeof(double));
        rc->filter_bytes = nc * sizeof(double);
    }
    if (!rc->wiener_filter)
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d Wiener filter", f->nx, ny);
    double *restrict filt = rc->wiener_filter;
    const double keep = 1.0 - blur->halo;
    for (size_t k = 0; k < nc; k++) {
        double complex hk = keep * svp_frame_otf(f, k) + (k == 0 ? blur->halo : 0.0);
        filt[k] = creal(hk) * creal(hk) + cimag(hk) * cimag(hk);
    }
    svp_tikhonov_invert(filt, f->nx, ny, ncx, balance);
    rc->wiener_balance = balance;
    *out = filt;
    return SVP_OK;
}

/* out = P in: embed in the zero-padded frame, filter, crop (uses the blur's work buffers). */
static void zero_precondition(svp_blur *blur, const double *filter, const double *in, double *out)
{
    const svp_frame *f = &blur->frame;
    const size_t nc = (size_t)f->ny * f->ncx;
    svp_blur_spectrum_in(blur, in, 1);
    fftw_complex *restrict c = blur->work_c;
#pragma omp parallel for schedule(static) if (nc > SVP_PARALLEL_MIN / 2)
    for (size_t k = 0; k < nc; k++) c[k] *= filter[k];
    svp_blur_spectrum_out(blur, out, 0);
}

static svp_status wiener_zero(svp_blur *blur, const double *y_data, size_t n_missing,
                              double balance, int max_steps, svp_deconv_report *report,
                              double *restrict x_data)
{
    const int w = blur->width, h = blur->height;
    const size_t n = (size_t)w * h;
    SVP_CHECK(svp_blur_ready(blur)); /* the filter is on the operator's frame */
    svp_restore_cache *rc = svp_restore_cache_of(blur);
    if (!rc) return SVP_ERR_NOMEM;
    const double *filter = NULL;
    svp_status st = zero_filter(blur, balance, &filter);
    if (st != SVP_OK) return st;
    double *buf = svp_alloc(7 * n * sizeof(double));
    if (!buf) return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d Wiener solve", w, h);
    double *r = buf, *z = buf + n, *p = buf + 2 * n, *ap = buf + 3 * n, *t1 = buf + 4 * n,
           *t2 = buf + 5 * n, *prod = buf + 6 * n;
    svp_image img_p = {w, h, p}, img_t1 = {w, h, t1}, img_ap = {w, h, ap}, img_r = {w, h, r};

    /* rhs = Hᵀ M y (missing pixels contribute nothing); x0 = 0, r0 = rhs */
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (size_t i = 0; i < n; i++) t1[i] = isfinite(y_data[i]) ? y_data[i] : 0.0;
    if ((st = svp_blur_adjoint(blur, &img_t1, &img_r)) != SVP_OK) goto cleanup;
    memset(x_data, 0, n * sizeof(double));
    const double rhs_norm = sqrt(svp_dot(r, r, prod, n));
    int it = 0, pairs = 1, converged = 1;
    double res_norm = 0;
    if (rhs_norm > 0 && isfinite(rhs_norm)) {
        converged = 0;
        zero_precondition(blur, filter, r, z);
        pairs++;
        memcpy(p, z, n * sizeof(double));
        double rz = svp_dot(r, z, prod, n);
        for (it = 0; it < max_steps; it++) {
            /* ap = (Hᵀ M H + λ L L) p */
            if ((st = svp_blur_apply(blur, &img_p, &img_t1)) != SVP_OK) goto cleanup;
            if (n_missing > 0) {
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
                for (size_t i = 0; i < n; i++)
                    if (!isfinite(y_data[i])) t1[i] = 0.0;
            }
            if ((st = svp_blur_adjoint(blur, &img_t1, &img_ap)) != SVP_OK) goto cleanup;
            pairs += 2;
            if (balance > 0) {
                laplacian_neumann(w, h, p, t1);
                laplacian_neumann(w, h, t1, t2);
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
                for (size_t i = 0; i < n; i++) ap[i] += balance * t2[i];
            }
            const double pap = svp_dot(p, ap, prod, n);
            if (!(pap > 0) || !isfinite(pap)) { /* exact convergence or a flat direction */
                converged = 1;
                break;
            }
            const double step = rz / pap;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
            for (size_t i = 0; i < n; i++) {
                x_data[i] += step * p[i];
                r[i] -= step * ap[i];
            }
            res_norm = sqrt(svp_dot(r, r, prod, n));
            if (res_norm <= ZERO_CG_TOL * rhs_norm) {
                converged = 1;
                it++;
                break;
            }
            zero_precondition(blur, filter, r, z);
            pairs++;
            const double rz_new = svp_dot(r, z, prod, n);
            const double beta = rz_new / rz;
            rz = rz_new;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
            for (size_t i = 0; i < n; i++) p[i] = z[i] + beta * p[i];
        }
    }
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (size_t i = 0; i < n; i++)
        if (!isfinite(x_data[i])) x_data[i] = 0.0;
    rc->wiener_steps = it;
    rc->wiener_pairs = pairs;
    if (report) {
        report->cg_steps = it;
        report->cg_residual = rhs_norm > 0 && isfinite(rhs_norm) ? res_norm / rhs_norm : 0.0;
        report->cg_capped = !converged;
    }
cleanup:
    svp_free(buf);
    return st;
}

svp_status svp_deconv_wiener(svp_blur *blur, const svp_image *y,
                             const svp_deconv_options *options, svp_image *x)
{
    svp_deconv_options defaults;
    if (!options) {
        svp_deconv_defaults(&defaults);
        options = &defaults;
    }
    SVP_CHECK(svp_deconv_check_images(blur, y, x, "Wiener deconvolution"));
    if (!(options->balance >= 0) || !isfinite(options->balance))
        return svp_fail(SVP_ERR_INVALID,
                        "Wiener deconvolution: balance %g is invalid: it must be finite and >= 0",
                        options->balance);
    /* space-variant operators: the same regularised problem by conjugate gradients, which
     * masks missing data itself */
    if (options->cg_max_steps < 1)
        return svp_fail(SVP_ERR_INVALID, "Wiener deconvolution: cg_max_steps %d must be >= 1",
                        options->cg_max_steps);
    svp_deconv_report *report = options->report;
    if (report) {
        memset(report, 0, sizeof *report);
        report->wiener = 1;
        report->balance = options->balance;
    }
    if (blur->kind != SVP_BLUR_INVARIANT) {
        /* its steps are the Wiener's CG cap, not RL's iteration count; it fills the report's
         * cg_steps / cg_residual / cg_capped, so T⁻¹ can refuse an unconverged solve */
        svp_deconv_options o = *options;
        o.iterations = options->cg_max_steps;
        return svp_deconv_tikhonov_cg(blur, y, &o, x);
    }

    const size_t n = (size_t)y->width * y->height;
    const size_t n_missing = svp_image_count_nonfinite(y);
    if (n_missing == n)
        return svp_fail(SVP_ERR_INVALID,
                        "Wiener deconvolution: all %zu pixels of the data y are NaN or Inf", n);
    svp_status st = SVP_OK;
    double *filled = NULL;
    if (blur->boundary == SVP_BOUNDARY_ZERO) {
        st = wiener_zero(blur, y->data, n_missing, options->balance, options->cg_max_steps, report,
                         x->data);
    } else {
        if (n_missing > 0) {
            filled = svp_alloc(n * sizeof(double));
            if (!filled)
                return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d image", y->width,
                                y->height);
            st = fill_missing(blur, y, n - n_missing, filled);
        }
        if (st == SVP_OK) st = wiener_invariant(blur, y->data, filled, options->balance, x->data);
    }
    if (st == SVP_OK) st = svp_report_progress(options->progress, options->progress_user, 1.0);
    svp_free(filled);
    return st;
}

/* ---- choosing the balance: the discrepancy principle --------------------------------------- */

/* Immerkær's estimate (Fast noise variance estimation, CVIU 64 (1996) 300–302): the mask
 * N = [1 −2 1; −2 4 −2; 1 −2 1] cancels every locally quadratic signal, and for white noise
 * of deviation σ, E|N ∗ n| = 6 σ √(2/π); so σ ≈ √(π/2) mean|N ∗ y| / 6 over the interior
 * pixels whose 3 x 3 neighbourhood is finite. */
svp_status svp_noise_sigma_estimate(const svp_image *y, double *sigma)
{
    if (!y || !y->data || !sigma)
        return svp_fail(SVP_ERR_INVALID, "noise estimate: NULL argument");
    const int w = y->width, h = y->height;
    if (w < 3 || h < 3)
        return svp_fail(SVP_ERR_INVALID,
                        "noise estimate: the image is %d x %d, at least 3 x 3 is needed", w, h);
    double *row_sum = calloc((size_t)h, sizeof(double));
    long long *row_count = calloc((size_t)h, sizeof(long long));
    if (!row_sum || !row_count) {
        free(row_sum);
        free(row_count);
        return svp_fail(SVP_ERR_NOMEM, "noise estimate: out of memory");
    }
    const double *d = y->data;
#pragma omp parallel for schedule(static) if ((size_t)w * h > SVP_PARALLEL_MIN)
    for (int j = 1; j < h - 1; j++) {
        const double *u = d + (size_t)(j - 1) * w, *c = d + (size_t)j * w,
                     *l = d + (size_t)(j + 1) * w;
        double s = 0;
        long long k = 0;
        for (int i = 1; i < w - 1; i++) {
            double v = (u[i - 1] + u[i + 1] + l[i - 1] + l[i + 1]) -
                       2 * (u[i] + l[i] + c[i - 1] + c[i + 1]) + 4 * c[i];
            if (!isfinite(v)) continue;
            s += fabs(v);
            k++;
        }
        row_sum[j] = s;
        row_count[j] = k;
    }
    double s = 0;
    long long k = 0;
    for (int j = 1; j < h - 1; j++) { /* fixed order: the same sum for any thread count */
        s += row_sum[j];
        k += row_count[j];
    }
    free(row_sum);
    free(row_count);
    if (k == 0)
        return svp_fail(SVP_ERR_INVALID,
                        "noise estimate: no 3 x 3 neighbourhood of the image is free of NaN/Inf");
    *sigma = sqrt(PI / 2.0) * s / (6.0 * (double)k);
    return SVP_OK;
}

#define DISCREPANCY_LOG_MIN (-12.0)
#define DISCREPANCY_LOG_MAX 2.0
#define DISCREPANCY_BISECTIONS 8 /* within a decade: λ to a factor 1.005 */
/* a search solve stopped at its CG cap above this relative residual has not converged */
#define DISCREPANCY_CG_RESIDUAL 1e-4
/* solves recorded for the L-curve fallback: 15 decades and two refinements of five points */
#define LCURVE_MAX 32

/* Morozov's discrepancy principle: the λ whose Wiener–Hunt solution x_λ leaves a residual
 * ‖M (H x_λ − y)‖² equal to what the noise alone explains, n_finite σ². The residual grows
 * with λ, so a walk down from 1e2 by decades finds the decade of the crossing and 8
 * bisections narrow it (λ to within a factor 1.005); when even an end fits (or misses), or
 * the solves stop converging, that end is returned and reported. */
svp_status svp_wiener_balance_discrepancy(svp_blur *blur, const svp_image *y, double sigma,
                                          double *balance, double *sigma_used)
{
    return svp_wiener_balance_discrepancy_var(blur, y, NULL, sigma, ZERO_CG_MAX, balance,
                                              sigma_used, NULL, NULL);
}

/* The L-curve's corner over points (t_k = log10 λ_k, uniform spacing, ascending) with
 * ρ_k = log10 residual and η_k = log10 ‖L x_λ‖²: the interior point of largest curvature
 * κ = (ρ′η″ − ρ″η′) / (ρ′² + η′²)^{3/2} (the curve turns from steep — λ too small, the solution
 * grows, the residual barely falls — to flat — λ too large). Returns its index, or -1 when no
 * interior point bends that way. */
static int lcurve_corner(const double *rho, const double *eta, int n, double *kappa_out)
{
    int best = -1;
    double best_k = 0;
    for (int k = 1; k + 1 < n; k++) {
        const double r1 = 0.5 * (rho[k + 1] - rho[k - 1]), e1 = 0.5 * (eta[k + 1] - eta[k - 1]);
        const double r2 = rho[k + 1] - 2 * rho[k] + rho[k - 1];
        const double e2 = eta[k + 1] - 2 * eta[k] + eta[k - 1];
        const double d = r1 * r1 + e1 * e1;
        if (!(d > 0)) continue;
        const double kappa = (r1 * e2 - r2 * e1) / (d * sqrt(d));
        if (kappa > best_k) {
            best_k = kappa;
            best = k;
        }
    }
    if (kappa_out) *kappa_out = best_k;
    return best;
}

/* The discrepancy search (svp_wiener_balance_discrepancy_var): its data, its solver's options
 * and buffers, and the L-curve's points along the walk. */
typedef struct disc_search {
    svp_blur *blur;
    const svp_image *y, *variance;
    int w, h;
    size_t n;
    svp_image *x, *hx;  /* the solution at the current λ and H x */
    double *prod, *lx;  /* n values each; lx (L x) only for the L-curve */
    double target;      /* Σ r² / var = n_finite; a constant variance folds into the target */
    double var_floor;
    svp_deconv_options o;
    svp_deconv_report rep;
    /* the L-curve's points along the walk (log10 λ, log10 residual, log10 ‖L x‖²) */
    double lc_t[LCURVE_MAX], lc_rho[LCURVE_MAX], lc_eta[LCURVE_MAX];
    int lc_n;
} disc_search;

/* The residual's excess over the target at log10 λ = t (> 0: λ too large) into *excess;
 * *unsolved = 1 when the solve stopped at its step cap short of convergence (its residual says
 * nothing). A converged point joins the L-curve's (while lx is there and room is left). */
static svp_status disc_excess(disc_search *d, double t, double *excess, int *unsolved)
{
    const size_t n = d->n;
    const svp_image *y = d->y, *variance = d->variance;
    double *prod = d->prod;
    d->o.balance = pow(10.0, t);
    SVP_CHECK(svp_deconv_wiener(d->blur, y, &d->o, d->x));
    SVP_CHECK(svp_blur_apply(d->blur, d->x, d->hx));
    for (size_t i = 0; i < n; i++) {
        double r = isfinite(y->data[i]) ? d->hx->data[i] - y->data[i] : 0.0;
        double v = variance ? variance->data[i] : 1.0;
        prod[i] = r * r / (v > d->var_floor ? v : d->var_floor);
    }
    *excess = svp_sum(prod, n) - d->target;
    *unsolved = d->rep.cg_capped && d->rep.cg_residual > DISCREPANCY_CG_RESIDUAL;
    if (d->lx && !*unsolved && d->lc_n < LCURVE_MAX) {
        laplacian_neumann(d->w, d->h, d->x->data, d->lx);
        for (size_t i = 0; i < n; i++) prod[i] = d->lx[i] * d->lx[i];
        d->lc_t[d->lc_n] = t;
        d->lc_rho[d->lc_n] = log10(fmax(*excess + d->target, 1e-300));
        d->lc_eta[d->lc_n] = log10(fmax(svp_sum(prod, n), 1e-300));
        d->lc_n++;
    }
    return SVP_OK;
}

/* Down from the largest λ a decade at a time until the residual fits the noise (the crossing
 * lies in the last decade: bisected there) or the solves stop converging (the lower bound of
 * what can be searched: the choice ends there, in doubt) — so a search whose small λ cannot be
 * solved costs a few solves, not sixteen capped ones. On return [*lo, *hi] holds the crossing
 * (log10 λ); *bound = 1 when even the largest λ fits, -1 when no λ searched does (or the solves
 * stopped converging), else 0. */
static svp_status disc_walk(disc_search *d, double *lo_out, double *hi_out, int *bound_out)
{
    double lo = DISCREPANCY_LOG_MAX, hi = DISCREPANCY_LOG_MAX, excess = 0;
    int unsolved = 0, bound = 0;
    svp_status st = disc_excess(d, hi, &excess, &unsolved);
    if (st == SVP_OK && !(excess > 0)) { /* even the largest λ fits: take it */
        bound = 1;
    } else if (st == SVP_OK) {
        for (double t = DISCREPANCY_LOG_MAX - 1; t >= DISCREPANCY_LOG_MIN - 1e-9; t -= 1.0) {
            if ((st = disc_excess(d, t, &excess, &unsolved)) != SVP_OK) break;
            if (unsolved) { /* below here nothing converges: the search ends on its bound */
                lo = hi;
                bound = -1;
                break;
            }
            if (!(excess > 0)) {
                lo = t;
                break;
            }
            hi = t;
            lo = t;
            if (t - 1.0 < DISCREPANCY_LOG_MIN - 1e-9) bound = -1; /* even 1e-12 misses */
        }
        /* bisect the decade [lo, hi] (lo fits, hi misses) */
        for (int step = 0; st == SVP_OK && !bound && step < DISCREPANCY_BISECTIONS; step++) {
            const double t = 0.5 * (lo + hi);
            if ((st = disc_excess(d, t, &excess, &unsolved)) != SVP_OK) break;
            if (unsolved || excess > 0)
                hi = t;
            else
                lo = t;
        }
    }
    *lo_out = lo;
    *hi_out = hi;
    *bound_out = bound;
    return st;
}

/* The model cannot reach the noise (light from outside the view, a wrong PSF, a noise estimate
 * that is too small): the L-curve's corner over the decades walked, refined by half and quarter
 * decades about it. *found = 1 and *corner_t (log10 λ) when the decades bend; a corner on the
 * walk's end stays in doubt (*found = 0). */
static svp_status disc_lcurve(disc_search *d, double *corner_t, int *found)
{
    *found = 0;
    /* the decade points, ascending in λ (the walk went down) */
    double t[LCURVE_MAX], rho[LCURVE_MAX], eta[LCURVE_MAX];
    int m = 0;
    for (int k = d->lc_n - 1; k >= 0; k--)
        if (fabs(d->lc_t[k] - round(d->lc_t[k])) < 1e-9) {
            t[m] = d->lc_t[k];
            rho[m] = d->lc_rho[k];
            eta[m] = d->lc_eta[k];
            m++;
        }
    int c = lcurve_corner(rho, eta, m, NULL);
    if (c <= 0) return SVP_OK;
    svp_status st = SVP_OK;
    double step = 1.0, ct = t[c], excess;
    int unsolved;
    double ft[5], fr[5], fe[5]; /* five points at spacing step/2 about the corner */
    for (int level = 0; st == SVP_OK && level < 2; level++) {
        const double h2 = 0.5 * step;
        for (int j = 0; j < 5; j++) ft[j] = ct + (j - 2) * h2;
        int ok = 1;
        for (int j = 0; st == SVP_OK && j < 5 && ok; j++) {
            /* reuse a point already solved */
            int at = -1;
            for (int k = 0; k < d->lc_n; k++)
                if (fabs(d->lc_t[k] - ft[j]) < 1e-9) at = k;
            if (at < 0) {
                const int before = d->lc_n;
                st = disc_excess(d, ft[j], &excess, &unsolved);
                if (st != SVP_OK || unsolved || d->lc_n == before) {
                    ok = 0;
                    break;
                }
                at = d->lc_n - 1;
            }
            fr[j] = d->lc_rho[at];
            fe[j] = d->lc_eta[at];
        }
        if (st != SVP_OK || !ok) break;
        const int cc = lcurve_corner(fr, fe, 5, NULL);
        if (cc < 0) break;
        ct = ft[cc];
        step = h2;
    }
    *corner_t = ct;
    *found = 1;
    return st;
}

svp_status svp_wiener_balance_discrepancy_var(svp_blur *blur, const svp_image *y,
                                              const svp_image *variance, double sigma,
                                              int cg_max_steps, double *balance,
                                              double *sigma_used, int *at_bound, int *lcurve)
{
    const char *what = "discrepancy principle";
    if (at_bound) *at_bound = 0;
    if (lcurve) *lcurve = 0;
    if (!blur || !y || !y->data || !balance)
        return svp_fail(SVP_ERR_INVALID, "%s: NULL argument", what);
    if (y->width != blur->width || y->height != blur->height)
        return svp_fail(SVP_ERR_SIZE, "%s: the operator is %d x %d but the data y are %d x %d",
                        what, blur->width, blur->height, y->width, y->height);
    if (variance) SVP_CHECK(svp_image_same_size(y, variance, "y", "variance"));
    if (!isfinite(sigma))
        return svp_fail(SVP_ERR_INVALID, "%s: noise deviation %g is not finite", what, sigma);
    if (!variance && sigma <= 0) SVP_CHECK(svp_noise_sigma_estimate(y, &sigma));
    const int w = y->width, h = y->height;
    const size_t n = (size_t)w * h;
    if (sigma_used && !variance) *sigma_used = sigma;
    if (sigma_used && variance) { /* the per-pixel noise's rms over the measured pixels */
        double sum = 0;
        size_t count = 0;
        for (size_t i = 0; i < n; i++)
            if (isfinite(y->data[i]) && isfinite(variance->data[i]) && variance->data[i] > 0) {
                sum += variance->data[i];
                count++;
            }
        *sigma_used = count ? sqrt(sum / (double)count) : 0.0;
    }
    const size_t n_finite = n - svp_image_count_nonfinite(y);
    if (n_finite == 0)
        return svp_fail(SVP_ERR_INVALID, "%s: all %zu pixels of the data y are NaN or Inf",
                        what, n);
    disc_search search = {.blur = blur, .y = y, .variance = variance, .w = w, .h = h, .n = n};
    disc_search *d = &search;
    svp_status st = svp_image_new(w, h, &d->x);
    if (st == SVP_OK) st = svp_image_new(w, h, &d->hx);
    d->prod = svp_alloc(n * sizeof(double));
    d->lx = lcurve ? svp_alloc(n * sizeof(double)) : NULL;
    if (st == SVP_OK && (!d->prod || (lcurve && !d->lx)))
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", what);
    d->target = variance ? (double)n_finite : (double)n_finite * sigma * sigma;
    d->var_floor = variance ? 1e-300 : 1.0;
    svp_deconv_defaults(&d->o);
    d->o.cg_max_steps = cg_max_steps;
    d->o.report = &d->rep;
    double lo = DISCREPANCY_LOG_MAX, hi = DISCREPANCY_LOG_MAX, corner_t = 0;
    int bound = 0, corner = 0;
    if (st == SVP_OK) st = disc_walk(d, &lo, &hi, &bound);
    if (st == SVP_OK && d->lx && bound < 0 && d->lc_n >= 3)
        st = disc_lcurve(d, &corner_t, &corner);
    if (bound == 1) lo = hi;
    if (st == SVP_OK) *balance = pow(10.0, bound ? (bound < 0 ? hi : lo) : 0.5 * (lo + hi));
    if (st == SVP_OK && corner) {
        *balance = pow(10.0, corner_t);
        bound = 0;
        *lcurve = 1;
    }
    if (at_bound) *at_bound = bound;
    svp_image_free(d->x);
    svp_image_free(d->hx);
    svp_free(d->prod);
    svp_free(d->lx);
    return st;
}
