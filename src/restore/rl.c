/* Richardson–Lucy deconvolution (docs/model.md §Deconvolution) for any operator H, through
 * svp_blur_apply / svp_blur_adjoint only:
 *     x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm
 * m the finite-data mask (NaN/Inf pixels of y are missing data), Hᵀm the Bertero–Boccacci
 * boundary weights (with options->boundary_weights = 0 the scalar mean of Hᵀm instead: plain
 * RL, exact for a periodic unit-flux operator without missing data), floor = options->floor ·
 * max(y). Started flat at the mean of the finite data (RL forgets the start's scale after one
 * iteration). */
#include "../blur/blur_internal.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Pointwise loops run in parallel only above this many pixels (below, threads cost more). */
#define PAR_MIN 32768

static svp_status check_args(const svp_blur *blur, const svp_image *y, const svp_deconv_options *o,
                             const svp_image *x)
{
    const char *what = "Richardson–Lucy";
    SVP_CHECK(svp_deconv_check_images(blur, y, x, what));
    if (o->iterations < 1)
        return svp_fail(SVP_ERR_INVALID, "%s: iterations = %d: at least 1 is needed", what,
                        o->iterations);
    if (!(o->floor >= 0) || !isfinite(o->floor))
        return svp_fail(SVP_ERR_INVALID, "%s: floor %g is invalid: it must be finite and >= 0",
                        what, o->floor);
    return SVP_OK;
}

svp_status svp_deconv_rl(svp_blur *blur, const svp_image *y, const svp_deconv_options *options,
                         svp_image *x)
{
    svp_deconv_options defaults;
    if (!options) {
        svp_deconv_defaults(&defaults);
        options = &defaults;
    }
    SVP_CHECK(check_args(blur, y, options, x));
    /* single precision: the operator's float transforms for this call only */
    const int was_single = blur->single;
    if (options->single_precision) SVP_CHECK(svp_blur_set_single(blur, 1));
    const int w = y->width, h = y->height;
    const size_t n = (size_t)w * h;
    const double *restrict yd = y->data;
    svp_status st = SVP_OK;
    double *y_masked = NULL, *blurred = NULL, *correction = NULL, *inv_norm = NULL;

    /* One pass: the finite mask folded into y (missing → 0), the range and the count. */
    y_masked = svp_alloc(n * sizeof(double));
    blurred = svp_alloc(n * sizeof(double));
    correction = svp_alloc(n * sizeof(double));
    inv_norm = svp_alloc(n * sizeof(double));
    if (!y_masked || !blurred || !correction || !inv_norm) {
        st = svp_fail(SVP_ERR_NOMEM, "Richardson–Lucy: out of memory for %d x %d buffers", w, h);
        goto cleanup;
    }
    double y_min = INFINITY, y_max = -INFINITY;
    size_t n_finite = 0;
#pragma omp parallel for schedule(static) if (n > PAR_MIN) reduction(min : y_min)              \
    reduction(max : y_max) reduction(+ : n_finite)
    for (size_t i = 0; i < n; i++) {
        double v = yd[i];
        if (isfinite(v)) {
            y_masked[i] = v;
            y_min = v < y_min ? v : y_min;
            y_max = v > y_max ? v : y_max;
            n_finite++;
        } else {
            y_masked[i] = 0.0;
        }
    }
    if (n_finite == 0) {
        st = svp_fail(SVP_ERR_INVALID,
                      "Richardson–Lucy: all %zu pixels of the data y are NaN "
                      "or Inf",
                      n);
        goto cleanup;
    }
    if (y_min < 0) {
        size_t at = 0;
        while (at < n && !(yd[at] == y_min)) at++;
        st = svp_fail(SVP_ERR_INVALID,
                      "Richardson–Lucy needs data >= 0 but y has minimum %.17g at pixel (%d, %d); "
                      "for signed data use the signed shift (method rl-signed)",
                      y_min, (int)(at % (size_t)w), (int)(at / (size_t)w));
        goto cleanup;
    }
    if (y_max == 0) {
        /* all-zero data: the only non-negative solution with zero flux */
        memset(x->data, 0, n * sizeof(double));
        for (int k = 1; k <= options->iterations && st == SVP_OK; k++)
            st = svp_report_progress(options->progress, options->progress_user,
                                     (double)k / options->iterations);
        goto cleanup;
    }

    svp_image img_x = {w, h, x->data}, img_blurred = {w, h, blurred};
    svp_image img_correction = {w, h, correction}, img_norm = {w, h, inv_norm};

    /* Normalisation Hᵀm (m = 1 without missing data), computed once. */
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) blurred[i] = isfinite(yd[i]) ? 1.0 : 0.0;
    if ((st = svp_blur_adjoint(blur, &img_blurred, &img_norm)) != SVP_OK) goto cleanup;
    if (options->boundary_weights) {
        /* Pixels no finite datum sees (Hᵀm ~ 0) keep their value: 0 marks them. */
        const double tiny = 1e-12 * svp_max(inv_norm, n);
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) inv_norm[i] = inv_norm[i] > tiny ? 1.0 / inv_norm[i] : 0.0;
    } else {
        const double mean_norm = svp_sum(inv_norm, n) / (double)n;
        const double inv = mean_norm > 0 ? 1.0 / mean_norm : 1.0;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) inv_norm[i] = inv;
    }

    /* floor > 0 keeps y / Hx finite; 1e-300 y_max guards floor = 0 without overflowing */
    const double floor_abs = fmax(options->floor * y_max, 1e-300 * y_max);
    const double start = svp_sum(y_masked, n) / (double)n_finite;
    double *restrict xd = x->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) xd[i] = start;

    for (int k = 0; k < options->iterations; k++) {
        if ((st = svp_blur_apply(blur, &img_x, &img_blurred)) != SVP_OK) goto cleanup;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            double hx = blurred[i];
            blurred[i] = y_masked[i] / (hx > floor_abs ? hx : floor_abs);
        }
        if ((st = svp_blur_adjoint(blur, &img_blurred, &img_correction)) != SVP_OK) goto cleanup;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            if (inv_norm[i] == 0) continue;
            double v = xd[i] * correction[i] * inv_norm[i];
            /* round-off can make Hᵀ(...) slightly negative; NaN/Inf never leave */
            xd[i] = (v > 0 && v <= DBL_MAX) ? v : 0.0;
        }
        st = svp_report_progress(options->progress, options->progress_user,
                                 (double)(k + 1) / options->iterations);
        if (st != SVP_OK) goto cleanup;
    }
cleanup:
    if (options->single_precision && !was_single) svp_blur_set_single(blur, 0);
    svp_free(y_masked);
    svp_free(blurred);
    svp_free(correction);
    svp_free(inv_norm);
    return st;
}
