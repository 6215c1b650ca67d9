/* PSF fields: how the PSF parameters vary over the image (docs/model.md §9).
 *
 * Everything that varies is the parameter vector p = {fwhm, e1, e2, beta, halo} (svpsf.h):
 * mean FWHM, ellipticity as (e cos 2θ, e sin 2θ) so that orientation interpolates without the
 * θ = 0 / π wrap, Moffat beta and halo fraction. Model, support and subsample are one per
 * field. The kinds store their data in parameter space and svp_psf_field_params_at turns a
 * position into a parameter vector; svp_psf_from_params makes the local PSF. */
#include "field_internal.h"

#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* ---- parameter vectors ------------------------------------------------------------------- */

#define FWHM_MIN 0.05
#define ELLIPTICITY_MAX 0.95
#define BETA_MIN SVP_PSF_BETA_MIN /* the smallest beta a PSF may have (core/internal.h) */
#define HALO_MAX 0.999

svp_status svp_psf_to_params(const svp_psf *psf, double p[SVP_FIELD_NPARAM])
{
    SVP_CHECK(svp_psf_validate(psf));
    double a = psf->fwhm;
    double b = psf->fwhm_minor > 0 ? psf->fwhm_minor : psf->fwhm;
    /* signed ellipticity: b > a is the same shape turned by 90°, which the sign encodes */
    double e = (a - b) / (a + b);
    p[SVP_FIELD_FWHM] = 0.5 * (a + b);
    p[SVP_FIELD_E1] = e == 0 ? 0.0 : e * cos(2.0 * psf->angle);
    p[SVP_FIELD_E2] = e == 0 ? 0.0 : e * sin(2.0 * psf->angle);
    p[SVP_FIELD_BETA] = psf->model == SVP_PSF_LORENTZIAN ? 1.0 : psf->beta;
    p[SVP_FIELD_HALO] = psf->halo;
    return SVP_OK;
}

static double clamp(double v, double lo, double hi)
{
    if (!(v >= lo)) return lo; /* also NaN → lo */
    return v > hi ? hi : v;
}

void svp_psf_from_params(const svp_psf *base, const double p[SVP_FIELD_NPARAM], svp_psf *out)
{
    svp_psf psf = *base;
    double s = clamp(p[SVP_FIELD_FWHM], FWHM_MIN, INFINITY);
    double e1 = isfinite(p[SVP_FIELD_E1]) ? p[SVP_FIELD_E1] : 0.0;
    double e2 = isfinite(p[SVP_FIELD_E2]) ? p[SVP_FIELD_E2] : 0.0;
    double e = hypot(e1, e2);
    if (e > 0) {
        double theta = 0.5 * atan2(e2, e1);
        if (e > ELLIPTICITY_MAX) e = ELLIPTICITY_MAX;
        psf.fwhm = s * (1.0 + e);
        psf.fwhm_minor = s * (1.0 - e);
        psf.angle = theta;
    } else {
        psf.fwhm = s;
        psf.fwhm_minor = 0.0;
        psf.angle = 0.0;
    }
    psf.beta = psf.model == SVP_PSF_LORENTZIAN ? 1.0 : clamp(p[SVP_FIELD_BETA], BETA_MIN, 1e6);
    if (psf.model == SVP_PSF_GAUSSIAN) psf.beta = base->beta > 0 ? base->beta : 2.5;
    psf.halo = clamp(p[SVP_FIELD_HALO], 0.0, HALO_MAX);
    *out = psf;
}

/* ---- construction ------------------------------------------------------------------------ */

static svp_status check_size(int width, int height, int allow_zero)
{
    if (allow_zero && width == 0 && height == 0) return SVP_OK;
    if (width < 1 || height < 1)
        return svp_fail(SVP_ERR_INVALID, "PSF field image size %d x %d: both must be >= 1", width,
                        height);
    return SVP_OK;
}

static svp_status field_alloc(svp_psf_field_kind kind, int width, int height, const svp_psf *base,
                              svp_psf_field **out)
{
    svp_psf_field *f = calloc(1, sizeof *f);
    if (!f) return svp_fail(SVP_ERR_NOMEM, "out of memory for a PSF field");
    f->kind = kind;
    f->width = width;
    f->height = height;
    f->base = *base;
    if (f->base.model == SVP_PSF_LORENTZIAN) f->base.beta = 1.0;
    *out = f;
    return SVP_OK;
}

/* Every PSF of a field shares the model, support and subsample of the first one. */
static svp_status check_member(const svp_psf *first, const svp_psf *psf, const char *what,
                               int index)
{
    svp_status st = svp_psf_validate(psf);
    if (st != SVP_OK) return svp_fail_context(st, "%s %d", what, index);
    if (psf->model != first->model)
        return svp_fail(SVP_ERR_INVALID,
                        "%s %d has model %d but the field's model is %d: one model per field "
                        "(use a Moffat with a large beta for Gaussian-like parts)",
                        what, index, (int)psf->model, (int)first->model);
    if (psf->support != first->support || psf->subsample != first->subsample)
        return svp_fail(SVP_ERR_INVALID,
                        "%s %d: support %g / subsample %d differ from the field's %g / %d", what,
                        index, psf->support, psf->subsample, first->support, first->subsample);
    return SVP_OK;
}

svp_status svp_psf_field_new_uniform(const svp_psf *psf, int width, int height, svp_psf_field **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_new_uniform: out is NULL");
    *out = NULL;
    SVP_CHECK(svp_psf_validate(psf));
    SVP_CHECK(check_size(width, height, 1));
    svp_psf_field *f = NULL;
    SVP_CHECK(field_alloc(SVP_FIELD_UNIFORM, width, height, psf, &f));
    f->uniform = *psf;
    SVP_CHECK(svp_psf_to_params(psf, f->uniform_p));
    *out = f;
    return SVP_OK;
}

static svp_status check_positions(const double *pos, int n, const char *axis)
{
    for (int i = 0; i < n; i++) {
        if (!isfinite(pos[i]))
            return svp_fail(SVP_ERR_INVALID, "node %s position %d is not finite", axis, i);
        if (i > 0 && !(pos[i] > pos[i - 1]))
            return svp_fail(SVP_ERR_INVALID,
                            "node %s positions must increase strictly: %g at %d after %g", axis,
                            pos[i], i, pos[i - 1]);
    }
    return SVP_OK;
}

svp_status svp_psf_field_new_grid(int width, int height, int nx, int ny, const double *node_x,
                                  const double *node_y, const svp_psf *node_psfs,
                                  svp_psf_field **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_new_grid: out is NULL");
    *out = NULL;
    SVP_CHECK(check_size(width, height, 0));
    if (nx < 1 || ny < 1 || nx > 4096 || ny > 4096)
        return svp_fail(SVP_ERR_INVALID, "node grid %d x %d: each side must be in 1..4096", nx, ny);
    if (!node_psfs) return svp_fail(SVP_ERR_INVALID, "node PSFs are missing");
    const size_t nk = (size_t)nx * ny;
    for (size_t k = 0; k < nk; k++)
        SVP_CHECK(check_member(&node_psfs[0], &node_psfs[k], "node PSF", (int)k));
    if (node_x) SVP_CHECK(check_positions(node_x, nx, "x"));
    if (node_y) SVP_CHECK(check_positions(node_y, ny, "y"));
    svp_psf_field *f = NULL;
    SVP_CHECK(field_alloc(SVP_FIELD_GRID, width, height, &node_psfs[0], &f));
    f->nx = nx;
    f->ny = ny;
    f->grid_default_nodes = !node_x && !node_y;
    f->node_x = malloc((size_t)nx * sizeof(double));
    f->node_y = malloc((size_t)ny * sizeof(double));
    f->node_p = malloc(nk * SVP_FIELD_NPARAM * sizeof(double));
    if (!f->node_x || !f->node_y || !f->node_p) {
        svp_psf_field_free(f);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d node grid", nx, ny);
    }
    for (int i = 0; i < nx; i++) f->node_x[i] = node_x ? node_x[i] : (i + 0.5) * width / nx - 0.5;
    for (int j = 0; j < ny; j++) f->node_y[j] = node_y ? node_y[j] : (j + 0.5) * height / ny - 0.5;
    for (size_t k = 0; k < nk; k++)
        svp_psf_to_params(&node_psfs[k], f->node_p + k * SVP_FIELD_NPARAM);
    *out = f;
    return SVP_OK;
}

int svp_psf_field_poly_terms(int degree)
{
    if (degree < 0) return 0;
    return (degree + 1) * (degree + 2) / 2;
}

void svp_psf_field_poly_basis(int degree, int width, int height, double x, double y, double *basis)
{
    double u = (2.0 * x - (width - 1)) / (width > 1 ? width - 1 : 1);
    double v = (2.0 * y - (height - 1)) / (height > 1 ? height - 1 : 1);
    double up[SVP_FIELD_POLY_MAX_DEGREE + 1], vp[SVP_FIELD_POLY_MAX_DEGREE + 1];
    if (degree > SVP_FIELD_POLY_MAX_DEGREE) degree = SVP_FIELD_POLY_MAX_DEGREE;
    up[0] = vp[0] = 1.0;
    for (int k = 1; k <= degree; k++) {
        up[k] = up[k - 1] * u;
        vp[k] = vp[k - 1] * v;
    }
    int t = 0;
    for (int k = 0; k <= degree; k++)
        for (int j = 0; j <= k; j++) basis[t++] = up[k - j] * vp[j];
}

svp_status svp_psf_field_new_poly(const svp_psf *base, int width, int height, int degree,
                                  const double *coeffs, svp_psf_field **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_new_poly: out is NULL");
    *out = NULL;
    SVP_CHECK(svp_psf_validate(base));
    SVP_CHECK(check_size(width, height, 0));
    if (degree < 0 || degree > SVP_FIELD_POLY_MAX_DEGREE)
        return svp_fail(SVP_ERR_INVALID, "polynomial degree %d: must be in 0..%d", degree,
                        SVP_FIELD_POLY_MAX_DEGREE);
    if (!coeffs) return svp_fail(SVP_ERR_INVALID, "polynomial coefficients are missing");
    const int nt = svp_psf_field_poly_terms(degree);
    for (int i = 0; i < nt * SVP_FIELD_NPARAM; i++)
        if (!isfinite(coeffs[i]))
            return svp_fail(SVP_ERR_INVALID,
                            "polynomial coefficient %d of parameter %d is not "
                            "finite",
                            i % nt, i / nt);
    svp_psf_field *f = NULL;
    SVP_CHECK(field_alloc(SVP_FIELD_POLY, width, height, base, &f));
    f->degree = degree;
    f->coeffs = malloc((size_t)nt * SVP_FIELD_NPARAM * sizeof(double));
    if (!f->coeffs) {
        svp_psf_field_free(f);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for polynomial coefficients");
    }
    memcpy(f->coeffs, coeffs, (size_t)nt * SVP_FIELD_NPARAM * sizeof(double));
    *out = f;
    return SVP_OK;
}

/* Separable Gaussian smoothing of one map in place, mirror (half-sample) boundary; kernel
 * normalised, so smoothing a constant returns it and smoothed one-hot maps sum to 1. */
static int reflect_index(int t, int size)
{
    int period = 2 * size;
    t %= period;
    if (t < 0) t += period;
    return t < size ? t : period - 1 - t;
}

/* The taps of a Gaussian of `sigma` pixels along an axis of `size` pixels with the mirror
 * boundary, offsets −*r .. *r (g[d + *r]), unit sum. The mirrored axis repeats every 2 size
 * pixels, so a kernel wider than the axis folds onto one period (2 size taps): that bounds the
 * work at any width, and from sigma >= 2 size on the blend is the axis mean (the periodic
 * Gaussian's first Fourier coefficient is exp(−2π²) ≈ 3·10⁻⁹ there). */
static double *axis_taps(double sigma, int size, int *r)
{
    const double reach = ceil(4.0 * sigma);
    const int fold = reach >= size;
    *r = fold ? size : (int)reach;
    if (*r < 1) *r = 1;
    double *g = calloc((size_t)(2 * *r + 1), sizeof(double));
    if (!g) return NULL;
    double sum = 0;
    for (int d = -*r; d <= *r; d++) {
        double v = 0;
        if (fold && d == *r) continue; /* −size and +size are the same pixel: counted once */
        if (!fold)
            v = exp(-0.5 * d * d / (sigma * sigma));
        else if (sigma >= 2.0 * size)
            v = 1.0;
        else
            for (int k = -5; k <= 5; k++) {
                const double t = (d + 2.0 * size * k) / sigma;
                v += exp(-0.5 * t * t);
            }
        sum += g[d + *r] = v;
    }
    for (int d = 0; d <= 2 * *r; d++) g[d] /= sum;
    return g;
}

/* Blends a region's one-hot map by a Gaussian of sigma pixels (mirror boundary). Below 10⁻³ px
 * the map stays sharp (the taps beside the centre are below e^(−5·10⁵)), as it would be
 * bit for bit, without the 0/0 of sigma² underflowing. */
static svp_status smooth_map(double *map, int width, int height, double sigma)
{
    if (!(sigma >= 1e-3)) return SVP_OK;
    int rx, ry;
    double *gx = axis_taps(sigma, width, &rx), *gy = axis_taps(sigma, height, &ry);
    double *tmp = svp_alloc((size_t)width * height * sizeof(double));
    if (!gx || !gy || !tmp) {
        free(gx);
        free(gy);
        svp_free(tmp);
        return svp_fail(SVP_ERR_NOMEM, "out of memory smoothing a region map");
    }
#pragma omp parallel for schedule(static) if ((size_t)width * height > SVP_PARALLEL_MIN)
    for (int y = 0; y < height; y++) {
        const double *row = map + (size_t)y * width;
        for (int x = 0; x < width; x++) {
            double acc = 0;
            for (int d = -rx; d <= rx; d++) acc += gx[d + rx] * row[reflect_index(x + d, width)];
            tmp[(size_t)y * width + x] = acc;
        }
    }
#pragma omp parallel for schedule(static) if ((size_t)width * height > SVP_PARALLEL_MIN)
    for (int y = 0; y < height; y++) {
        for (int x = 0; x < width; x++) {
            double acc = 0;
            for (int d = -ry; d <= ry; d++)
                acc += gy[d + ry] * tmp[(size_t)reflect_index(y + d, height) * width + x];
            map[(size_t)y * width + x] = acc;
        }
    }
    free(gx);
    free(gy);
    svp_free(tmp);
    return SVP_OK;
}

/* Blend sigma from the 10 %–90 % transition width of a smoothed step: 2 · 1.2816 σ. */
#define TRANSITION_PER_SIGMA 2.5631

svp_status svp_psf_field_new_regions(int width, int height, const int *labels, int n_labels,
                                     const svp_psf *region_psfs, double transition,
                                     svp_psf_field **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_new_regions: out is NULL");
    *out = NULL;
    SVP_CHECK(check_size(width, height, 0));
    if (!labels) return svp_fail(SVP_ERR_INVALID, "label image is missing");
    if (n_labels < 1 || n_labels > 65536)
        return svp_fail(SVP_ERR_INVALID, "number of regions %d: must be in 1..65536", n_labels);
    if (!region_psfs) return svp_fail(SVP_ERR_INVALID, "region PSFs are missing");
    if (!(transition >= 0) || !isfinite(transition))
        return svp_fail(SVP_ERR_INVALID, "region transition width must be >= 0 pixels, got %g",
                        transition);
    for (int l = 0; l < n_labels; l++)
        SVP_CHECK(check_member(&region_psfs[0], &region_psfs[l], "region PSF", l));
    const size_t n = (size_t)width * height;
    for (size_t i = 0; i < n; i++)
        if (labels[i] < 0 || labels[i] >= n_labels)
            return svp_fail(
                SVP_ERR_INVALID, "label %d at pixel (%d, %d) is outside 0..%d (one PSF per label)",
                labels[i], (int)(i % (size_t)width), (int)(i / (size_t)width), n_labels - 1);
    svp_psf_field *f = NULL;
    SVP_CHECK(field_alloc(SVP_FIELD_REGIONS, width, height, &region_psfs[0], &f));
    svp_status st = SVP_OK;
    double *onehot = NULL;
    f->n_labels = n_labels;
    f->transition = transition;
    f->labels = malloc(n * sizeof(int));
    f->region_psfs = malloc((size_t)n_labels * sizeof(svp_psf));
    f->region_p = malloc((size_t)n_labels * SVP_FIELD_NPARAM * sizeof(double));
    f->pmap = svp_calloc(n * SVP_FIELD_NPARAM, sizeof(double));
    if (!f->labels || !f->region_psfs || !f->region_p || !f->pmap) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d region field", width, height);
        goto cleanup;
    }
    memcpy(f->labels, labels, n * sizeof(int));
    memcpy(f->region_psfs, region_psfs, (size_t)n_labels * sizeof(svp_psf));
    for (int l = 0; l < n_labels; l++)
        svp_psf_to_params(&region_psfs[l], f->region_p + (size_t)l * SVP_FIELD_NPARAM);
    if (transition == 0) {
        for (size_t i = 0; i < n; i++)
            for (int q = 0; q < SVP_FIELD_NPARAM; q++)
                f->pmap[(size_t)q * n + i] = f->region_p[(size_t)labels[i] * SVP_FIELD_NPARAM + q];
    } else {
        /* p(x) = Σ_l w_l(x) p_l with w_l the smoothed one-hot map of label l: w_l >= 0 and
         * Σ_l w_l = 1 (the smoothing of a constant), so blended parameters stay in the hull. */
        onehot = svp_alloc(n * sizeof(double));
        if (!onehot) {
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for a region weight map");
            goto cleanup;
        }
        for (int l = 0; l < n_labels; l++) {
            size_t count = 0;
            st = svp_psf_field_region_weight(f, l, onehot, &count);
            if (st != SVP_OK) goto cleanup;
            if (!count) continue;
            const double *pl = f->region_p + (size_t)l * SVP_FIELD_NPARAM;
            for (int q = 0; q < SVP_FIELD_NPARAM; q++) {
                double *mq = f->pmap + (size_t)q * n;
                for (size_t i = 0; i < n; i++) mq[i] += onehot[i] * pl[q];
            }
        }
    }
cleanup:
    svp_free(onehot);
    if (st != SVP_OK) {
        svp_psf_field_free(f);
        return st;
    }
    *out = f;
    return SVP_OK;
}

svp_status svp_psf_field_copy(const svp_psf_field *src, svp_psf_field **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_copy: out is NULL");
    *out = NULL;
    if (!src) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_copy: field is NULL");
    switch (src->kind) {
    case SVP_FIELD_UNIFORM:
        return svp_psf_field_new_uniform(&src->uniform, src->width, src->height, out);
    case SVP_FIELD_GRID: {
        svp_psf_field *f = NULL;
        SVP_CHECK(field_alloc(SVP_FIELD_GRID, src->width, src->height, &src->base, &f));
        size_t nk = (size_t)src->nx * src->ny;
        f->nx = src->nx;
        f->ny = src->ny;
        f->grid_default_nodes = src->grid_default_nodes;
        f->node_x = malloc((size_t)f->nx * sizeof(double));
        f->node_y = malloc((size_t)f->ny * sizeof(double));
        f->node_p = malloc(nk * SVP_FIELD_NPARAM * sizeof(double));
        if (!f->node_x || !f->node_y || !f->node_p) {
            svp_psf_field_free(f);
            return svp_fail(SVP_ERR_NOMEM, "out of memory copying a node grid");
        }
        memcpy(f->node_x, src->node_x, (size_t)f->nx * sizeof(double));
        memcpy(f->node_y, src->node_y, (size_t)f->ny * sizeof(double));
        memcpy(f->node_p, src->node_p, nk * SVP_FIELD_NPARAM * sizeof(double));
        f->margin = src->margin;
        *out = f;
        return SVP_OK;
    }
    case SVP_FIELD_POLY:
        SVP_CHECK(svp_psf_field_new_poly(&src->base, src->width, src->height, src->degree,
                                         src->coeffs, out));
        (*out)->margin = src->margin;
        return SVP_OK;
    case SVP_FIELD_REGIONS:
        return svp_psf_field_new_regions(src->width, src->height, src->labels, src->n_labels,
                                         src->region_psfs, src->transition, out);
    }
    return svp_fail(SVP_ERR_INTERNAL, "PSF field of unknown kind %d", (int)src->kind);
}

void svp_psf_field_free(svp_psf_field *f)
{
    if (!f) return;
    free(f->node_x);
    free(f->node_y);
    free(f->node_p);
    free(f->coeffs);
    free(f->labels);
    free(f->region_psfs);
    free(f->region_p);
    svp_free(f->pmap);
    free(f);
}

svp_psf_field_kind svp_psf_field_get_kind(const svp_psf_field *f) { return f->kind; }
int svp_psf_field_width(const svp_psf_field *f) { return f->width; }
int svp_psf_field_height(const svp_psf_field *f) { return f->height; }

/* ---- evaluation -------------------------------------------------------------------------- */

/* Interval i and fraction t with pos[i] + t (pos[i+1] − pos[i]) = v, clamped to the ends. */
static void locate(const double *pos, int n, double v, int *i, double *t)
{
    if (n == 1 || v <= pos[0]) {
        *i = 0;
        *t = 0;
        return;
    }
    if (v >= pos[n - 1]) {
        *i = n - 2;
        *t = 1;
        return;
    }
    int lo = 0, hi = n - 1; /* pos[lo] <= v < pos[hi] */
    while (hi - lo > 1) {
        int mid = (lo + hi) / 2;
        if (pos[mid] <= v)
            lo = mid;
        else
            hi = mid;
    }
    *i = lo;
    *t = (v - pos[lo]) / (pos[hi] - pos[lo]);
}

static void clamp_params(double p[SVP_FIELD_NPARAM])
{
    p[SVP_FIELD_FWHM] = clamp(p[SVP_FIELD_FWHM], FWHM_MIN, INFINITY);
    double e = hypot(p[SVP_FIELD_E1], p[SVP_FIELD_E2]);
    if (!isfinite(e)) {
        p[SVP_FIELD_E1] = p[SVP_FIELD_E2] = 0;
    } else if (e > ELLIPTICITY_MAX) {
        p[SVP_FIELD_E1] *= ELLIPTICITY_MAX / e;
        p[SVP_FIELD_E2] *= ELLIPTICITY_MAX / e;
    }
    p[SVP_FIELD_BETA] = clamp(p[SVP_FIELD_BETA], BETA_MIN, 1e6);
    p[SVP_FIELD_HALO] = clamp(p[SVP_FIELD_HALO], 0.0, HALO_MAX);
}

svp_status svp_psf_field_region_weight(const svp_psf_field *f, int label, double *w,
                                       size_t *count)
{
    const size_t n = (size_t)f->width * f->height;
    size_t c = 0;
    for (size_t i = 0; i < n; i++) c += (w[i] = f->labels[i] == label) != 0;
    *count = c;
    if (c && f->transition > 0)
        return smooth_map(w, f->width, f->height, f->transition / TRANSITION_PER_SIGMA);
    return SVP_OK;
}

void svp_psf_field_region_psf(const svp_psf_field *f, int label, svp_psf *out)
{
    double p[SVP_FIELD_NPARAM];
    memcpy(p, f->region_p + (size_t)label * SVP_FIELD_NPARAM, sizeof p);
    clamp_params(p);
    svp_psf_from_params(&f->base, p, out);
}

/* The parameter vector at (x, y) before clamping. */
static svp_status raw_params_at(const svp_psf_field *f, double x, double y,
                                double p[SVP_FIELD_NPARAM])
{
    /* a padded grid or poly field: the nearest position of the map's own image */
    const int m = f->margin, iw = f->width - 2 * m, ih = f->height - 2 * m;
    if (m > 0) {
        x = clamp(x - m, 0, iw - 1);
        y = clamp(y - m, 0, ih - 1);
    }
    switch (f->kind) {
    case SVP_FIELD_UNIFORM: memcpy(p, f->uniform_p, sizeof f->uniform_p); return SVP_OK;
    case SVP_FIELD_GRID: {
        int i, j;
        double tx, ty;
        locate(f->node_x, f->nx, x, &i, &tx);
        locate(f->node_y, f->ny, y, &j, &ty);
        int i1 = f->nx > 1 ? i + 1 : i, j1 = f->ny > 1 ? j + 1 : j;
        const double *p00 = f->node_p + ((size_t)j * f->nx + i) * SVP_FIELD_NPARAM;
        const double *p10 = f->node_p + ((size_t)j * f->nx + i1) * SVP_FIELD_NPARAM;
        const double *p01 = f->node_p + ((size_t)j1 * f->nx + i) * SVP_FIELD_NPARAM;
        const double *p11 = f->node_p + ((size_t)j1 * f->nx + i1) * SVP_FIELD_NPARAM;
        for (int q = 0; q < SVP_FIELD_NPARAM; q++)
            p[q] = (1 - ty) * ((1 - tx) * p00[q] + tx * p10[q]) +
                   ty * ((1 - tx) * p01[q] + tx * p11[q]);
        break;
    }
    case SVP_FIELD_POLY: {
        double basis[(SVP_FIELD_POLY_MAX_DEGREE + 1) * (SVP_FIELD_POLY_MAX_DEGREE + 2) / 2];
        const int nt = svp_psf_field_poly_terms(f->degree);
        svp_psf_field_poly_basis(f->degree, iw, ih, x, y, basis);
        for (int q = 0; q < SVP_FIELD_NPARAM; q++) {
            double acc = 0;
            for (int t = 0; t < nt; t++) acc += f->coeffs[q * nt + t] * basis[t];
            p[q] = acc;
        }
        break;
    }
    case SVP_FIELD_REGIONS: {
        /* bilinear between pixel centres, clamped to the image */
        double cx = clamp(x, 0, f->width - 1), cy = clamp(y, 0, f->height - 1);
        int i = (int)floor(cx), j = (int)floor(cy);
        double tx = cx - i, ty = cy - j;
        int i1 = i + 1 < f->width ? i + 1 : i, j1 = j + 1 < f->height ? j + 1 : j;
        const size_t n = (size_t)f->width * f->height, w = (size_t)f->width;
        for (int q = 0; q < SVP_FIELD_NPARAM; q++) {
            const double *m = f->pmap + (size_t)q * n;
            double v = (1 - ty) * (1 - tx) * m[j * w + i];
            if (tx > 0) v += (1 - ty) * tx * m[j * w + i1];
            if (ty > 0) v += ty * (1 - tx) * m[j1 * w + i];
            if (tx > 0 && ty > 0) v += ty * tx * m[j1 * w + i1];
            p[q] = v;
        }
        break;
    }
    default: return svp_fail(SVP_ERR_INTERNAL, "PSF field of unknown kind %d", (int)f->kind);
    }
    return SVP_OK;
}

svp_status svp_psf_field_params_at(const svp_psf_field *f, double x, double y,
                                   double p[SVP_FIELD_NPARAM])
{
    if (!f) return svp_fail(SVP_ERR_INVALID, "PSF field is NULL");
    if (!isfinite(x) || !isfinite(y))
        return svp_fail(SVP_ERR_INVALID, "PSF field position (%g, %g) is not finite", x, y);
    SVP_CHECK(raw_params_at(f, x, y, p));
    clamp_params(p);
    return SVP_OK;
}

/* How far p[q] lies beyond its valid range (0 inside), from c = p after clamp_params (the one
 * place the ranges are set): *bound the value it is clamped to, *value the one it had. The
 * ellipticity |e| is checked at SVP_FIELD_E1, E2 is not checked on its own; β only for Moffat. */
static double excursion(const double p[SVP_FIELD_NPARAM], const double c[SVP_FIELD_NPARAM], int q,
                        svp_psf_model model, double *bound, double *value)
{
    if (q == SVP_FIELD_E2 || (q == SVP_FIELD_BETA && model != SVP_PSF_MOFFAT)) return 0;
    if (q == SVP_FIELD_E1) {
        *value = hypot(p[SVP_FIELD_E1], p[SVP_FIELD_E2]);
        *bound = hypot(c[SVP_FIELD_E1], c[SVP_FIELD_E2]);
        return isfinite(*value) ? *value - *bound : 1;
    }
    *value = p[q];
    *bound = c[q];
    return isfinite(p[q]) ? fabs(c[q] - p[q]) : 1;
}

svp_status svp_psf_field_check_range(const svp_psf_field *f, const int *box,
                                     svp_psf_field_range *out)
{
    if (!f || !out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_check_range: NULL argument");
    memset(out, 0, sizeof *out);
    if (f->kind == SVP_FIELD_UNIFORM || f->width < 1 || f->height < 1) return SVP_OK;
    int x0 = 0, y0 = 0, x1 = f->width - 1, y1 = f->height - 1;
    if (box) {
        x0 = box[0] > 0 ? box[0] : 0;
        y0 = box[1] > 0 ? box[1] : 0;
        x1 = box[2] < x1 ? box[2] : x1;
        y1 = box[3] < y1 ? box[3] : y1;
        if (x1 < x0 || y1 < y0) return SVP_OK;
    }
    const int bw = x1 - x0 + 1, bh = y1 - y0 + 1;
    /* every pixel up to 512 per side, else an even subset that keeps the borders */
    const int sx = bw > 512 ? (bw + 511) / 512 : 1;
    const int sy = bh > 512 ? (bh + 511) / 512 : 1;
    double worst[SVP_FIELD_NPARAM] = {0};
    const int nx = (bw - 1 + sx - 1) / sx + 1, ny = (bh - 1 + sy - 1) / sy + 1;
    for (int jj = 0; jj < ny; jj++) {
        const int j = y0 + (jj * sy < bh - 1 ? jj * sy : bh - 1);
        for (int ii = 0; ii < nx; ii++) {
            const int i = x0 + (ii * sx < bw - 1 ? ii * sx : bw - 1);
            double p[SVP_FIELD_NPARAM], c[SVP_FIELD_NPARAM];
            SVP_CHECK(raw_params_at(f, i, j, p));
            memcpy(c, p, sizeof c);
            clamp_params(c);
            out->sampled++;
            int any = 0;
            for (int q = 0; q < SVP_FIELD_NPARAM; q++) {
                double bound = 0, value = 0;
                const double d = excursion(p, c, q, f->base.model, &bound, &value);
                if (!(d > 0)) continue;
                any = 1;
                out->count[q]++;
                if (d > worst[q] || out->count[q] == 1) {
                    worst[q] = d;
                    out->value[q] = value;
                    out->bound[q] = bound;
                    out->x[q] = i;
                    out->y[q] = j;
                }
            }
            out->clamped += (size_t)any;
        }
    }
    return SVP_OK;
}

svp_status svp_psf_field_at(const svp_psf_field *f, double x, double y, svp_psf *out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_at: out is NULL");
    if (f && f->kind == SVP_FIELD_UNIFORM) {
        /* the PSF itself, not its round trip through parameters: uniform fields reproduce
         * the invariant operator bit for bit */
        *out = f->uniform;
        return SVP_OK;
    }
    double p[SVP_FIELD_NPARAM];
    SVP_CHECK(svp_psf_field_params_at(f, x, y, p));
    svp_psf_from_params(&f->base, p, out);
    return SVP_OK;
}

const svp_psf *svp_psf_field_base(const svp_psf_field *f) { return &f->base; }

/* ---- margins (light from outside the view) ------------------------------------------------ */

#define PAD_MAX 100000

/* A region field's labels carried outward: pixel (x, y) of the padded image takes the label of
 * the original's nearest pixel. */
static svp_status pad_regions(const svp_psf_field *f, int margin, svp_psf_field **out)
{
    const int w = f->width + 2 * margin, h = f->height + 2 * margin;
    int *labels = svp_alloc((size_t)w * h * sizeof(int));
    if (!labels)
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d padded label image", w, h);
    for (int y = 0; y < h; y++) {
        const int sy = (int)clamp(y - margin, 0, f->height - 1);
        for (int x = 0; x < w; x++) {
            const int sx = (int)clamp(x - margin, 0, f->width - 1);
            labels[(size_t)y * w + x] = f->labels[(size_t)sy * f->width + sx];
        }
    }
    svp_status st = svp_psf_field_new_regions(w, h, labels, f->n_labels, f->region_psfs,
                                              f->transition, out);
    svp_free(labels);
    return st;
}

svp_status svp_psf_field_pad(const svp_psf_field *f, int margin, svp_psf_field **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_pad: out is NULL");
    *out = NULL;
    if (!f) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_pad: field is NULL");
    if (margin < 0 || margin > PAD_MAX)
        return svp_fail(SVP_ERR_INVALID, "a margin of %d pixels: must be in 0..%d", margin,
                        PAD_MAX);
    if (f->width == 0 || margin == 0) return svp_psf_field_copy(f, out);
    if ((long long)f->width + 2LL * margin > INT_MAX / 4 ||
        (long long)f->height + 2LL * margin > INT_MAX / 4)
        return svp_fail(SVP_ERR_INVALID, "a %d x %d PSF map with a margin of %d pixels is too large",
                        f->width, f->height, margin);
    if (f->kind == SVP_FIELD_UNIFORM)
        return svp_psf_field_new_uniform(&f->uniform, f->width + 2 * margin,
                                         f->height + 2 * margin, out);
    if (f->kind == SVP_FIELD_REGIONS) return pad_regions(f, margin, out);
    SVP_CHECK(svp_psf_field_copy(f, out));
    (*out)->width += 2 * margin;
    (*out)->height += 2 * margin;
    (*out)->margin += margin;
    return SVP_OK;
}

/* The running maximum of svp_psf_auto_margin; -1 once a PSF has a halo. */
static void margin_of(const svp_psf *psf, int width, int height, int *best)
{
    if (*best < 0) return;
    if (psf->halo > 0) {
        *best = -1;
        return;
    }
    const int m = svp_psf_auto_margin(psf, width, height);
    if (m > *best) *best = m;
}

#define AUTO_MARGIN_SAMPLES 128

int svp_psf_field_auto_margin(const svp_psf_field *f, int width, int height)
{
    if (!f || width < 1 || height < 1) return 0;
    if (f->kind == SVP_FIELD_UNIFORM) return svp_psf_auto_margin(&f->uniform, width, height);
    int best = 0;
    const int fw = f->width > 0 ? f->width : width, fh = f->height > 0 ? f->height : height;
    const int nx = fw < AUTO_MARGIN_SAMPLES ? fw : AUTO_MARGIN_SAMPLES;
    const int ny = fh < AUTO_MARGIN_SAMPLES ? fh : AUTO_MARGIN_SAMPLES;
    for (int j = 0; j < ny && best >= 0; j++)
        for (int i = 0; i < nx && best >= 0; i++) {
            const double x = nx > 1 ? (double)i * (fw - 1) / (nx - 1) : 0;
            const double y = ny > 1 ? (double)j * (fh - 1) / (ny - 1) : 0;
            svp_psf psf;
            if (svp_psf_field_at(f, x, y, &psf) == SVP_OK) margin_of(&psf, width, height, &best);
        }
    if (f->kind == SVP_FIELD_REGIONS && best >= 0) {
        /* a thin region the samples miss: every label in use */
        char *used = calloc((size_t)f->n_labels, 1);
        if (used) {
            const size_t n = (size_t)f->width * f->height;
            for (size_t i = 0; i < n; i++) used[f->labels[i]] = 1;
            for (int l = 0; l < f->n_labels; l++) {
                if (!used[l]) continue;
                svp_psf psf;
                svp_psf_field_region_psf(f, l, &psf);
                margin_of(&psf, width, height, &best);
            }
            free(used);
        }
    }
    return best > 0 ? best : 0;
}
