/* Richardson–Lucy deconvolution (docs/model.md §Deconvolution) for any operator H, through
 * svp_blur_apply / svp_blur_adjoint only:
 *     x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm
 * m the finite-data mask (NaN/Inf pixels of y are missing data), Hᵀm the Bertero–Boccacci
 * boundary weights (with options->boundary_weights = 0 the scalar mean of Hᵀm instead: plain
 * RL, exact for a periodic unit-flux operator without missing data), floor = options->floor ·
 * max(y). Started flat at the mean of the finite data (RL forgets the start's scale after one
 * iteration). */
#include "restore_internal.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Pointwise loops run in parallel only above this many pixels (below, threads cost more). */
#define PAR_MIN 32768
/* auto_stop: stalled when χ² fell by less than STALL_FALL of itself over STALL_SPAN iterations */
#define STALL_SPAN 10
#define STALL_FALL 0.001
/* Biggs–Andrews: the extrapolation weight's cap (α → 1 can overshoot without bound) */
#define ALPHA_MAX 0.95
/* an extrapolated pixel keeps at least this fraction of its value */
#define KEEP_FRACTION 0.5

/* Biggs–Andrews: x ← z = x_k + α (x_k − x_{k−1}) in place, x_prev ← x_k; α = <g_{k−1}, g_{k−2}> /
 * <g_{k−2}, g_{k−2}> in [0, ALPHA_MAX] from the last two RL steps (0 for the first two), or
 * alpha_in[k] when given; alpha_out[k] records it. A pixel the extrapolation would push below
 * KEEP_FRACTION of its value keeps that fraction (RL cannot bring a zero back). scratch: n
 * values for the dot products. */
static void extrapolate(double *restrict x, double *restrict x_prev, const double *step_1,
                        const double *step_2, double *scratch, size_t n, int k,
                        const double *alpha_in, double *alpha_out)
{
    double alpha = 0;
    if (alpha_in) {
        alpha = alpha_in[k];
    } else if (k >= 2) {
        const double num = svp_dot(step_1, step_2, scratch, n);
        const double den = svp_dot(step_2, step_2, scratch, n);
        alpha = den > 0 ? num / den : 0.0;
        alpha = alpha > 0 ? (alpha < ALPHA_MAX ? alpha : ALPHA_MAX) : 0.0;
    }
    if (alpha_out) alpha_out[k] = alpha;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        const double xk = x[i], z = xk + alpha * (xk - x_prev[i]);
        x_prev[i] = xk;
        x[i] = z > KEEP_FRACTION * xk ? z : KEEP_FRACTION * xk;
    }
}

/* Σ over finite data of (Hx − y)² / var (var_map, at least var_const; or var_const), in
 * svp_sum's fixed order (scratch: n values). */
static double residual_chi2(const double *y, const double *hx, const double *var_map,
                            double var_const, double *scratch, size_t n)
{
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        const double r = isfinite(y[i]) ? hx[i] - y[i] : 0.0;
        const double v = var_map ? fmax(var_map[i], var_const) : var_const;
        scratch[i] = isfinite(y[i]) ? r * r / v : 0.0;
    }
    return svp_sum(scratch, n);
}

/* The stopping rule after iteration k's χ² per datum (history: the last STALL_SPAN + 1 values,
 * shifted here): SVP_RL_STOP_DISCREPANCY at χ² <= 1, SVP_RL_STOP_STALLED when χ² fell by less
 * than STALL_FALL of itself over STALL_SPAN iterations, else SVP_RL_STOP_CAP (go on). */
static int stopping_rule(double *history, double chi2, int k)
{
    for (int j = 0; j < STALL_SPAN; j++) history[j] = history[j + 1];
    history[STALL_SPAN] = chi2;
    if (chi2 <= 1.0) return SVP_RL_STOP_DISCREPANCY;
    if (k >= STALL_SPAN && history[0] - chi2 < STALL_FALL * chi2) return SVP_RL_STOP_STALLED;
    return SVP_RL_STOP_CAP;
}

static svp_status check_args(const svp_blur *blur, const svp_image *y, const svp_deconv_options *o,
                             const svp_image *x)
{
    const char *what = "Richardson–Lucy";
    SVP_CHECK(svp_deconv_check_images(blur, y, x, what));
    if (o->iterations < 1)
        return svp_fail(SVP_ERR_INVALID, "%s: iterations = %d: at least 1 is needed", what,
                        o->iterations);
    if (o->acceleration != SVP_RL_PLAIN && o->acceleration != SVP_RL_BIGGS_ANDREWS)
        return svp_fail(SVP_ERR_INVALID, "%s: unknown acceleration %d", what, (int)o->acceleration);
    if (!(o->floor >= 0) || !isfinite(o->floor))
        return svp_fail(SVP_ERR_INVALID, "%s: floor %g is invalid: it must be finite and >= 0",
                        what, o->floor);
    return SVP_OK;
}

svp_status svp_deconv_rl(svp_blur *blur, const svp_image *y, const svp_deconv_options *options,
                         svp_image *x)
{
    return svp_deconv_rl_path(blur, y, options, x, NULL, NULL);
}

svp_status svp_deconv_rl_path(svp_blur *blur, const svp_image *y,
                              const svp_deconv_options *options, svp_image *x,
                              const double *alpha_in, double *alpha_out)
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
    double *x_prev = NULL, *step_1 = NULL, *step_2 = NULL;
    if (options->report) memset(options->report, 0, sizeof *options->report);

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

    /* The stopping rule's noise variance: the caller's map, or one σ² estimated from y. */
    const int auto_stop = options->auto_stop;
    const double *var_map = NULL;
    double var_const = 0;
    if (auto_stop) {
        if (options->variance) {
            if ((st = svp_image_same_size(y, options->variance, "y", "variance")) != SVP_OK)
                goto cleanup;
            var_map = options->variance->data;
        } else {
            double sigma = 0;
            if ((st = svp_noise_sigma_estimate(y, &sigma)) != SVP_OK) goto cleanup;
            var_const = sigma * sigma;
        }
        /* noiseless data: a variance at round-off, so χ² never reaches 1 and the stall decides */
        var_const = fmax(var_const, 1e-24 * y_max * y_max);
    }
    /* Acceleration: the previous iterate and the last two RL steps. */
    const int accel = options->acceleration == SVP_RL_BIGGS_ANDREWS;
    if (accel) {
        x_prev = svp_alloc(n * sizeof(double));
        step_1 = svp_alloc(n * sizeof(double));
        step_2 = svp_alloc(n * sizeof(double));
        if (!x_prev || !step_1 || !step_2) {
            st = svp_fail(SVP_ERR_NOMEM, "Richardson–Lucy: out of memory for the acceleration");
            goto cleanup;
        }
    }
    double chi2_history[STALL_SPAN + 1] = {0};
    int done = 0, stop = auto_stop ? SVP_RL_STOP_CAP : SVP_RL_STOP_COUNT;
    double chi2 = 0;
    for (int k = 0; k < options->iterations; k++) {
        if (accel)
            extrapolate(xd, x_prev, step_1, step_2, correction, n, k, alpha_in, alpha_out);
        if ((st = svp_blur_apply(blur, &img_x, &img_blurred)) != SVP_OK) goto cleanup;
        if (auto_stop) {
            chi2 = residual_chi2(yd, blurred, var_map, var_const, correction, n) /
                   (double)n_finite;
            const int why = stopping_rule(chi2_history, chi2, k);
            if (why != SVP_RL_STOP_CAP) {
                stop = why;
                done = k;
                break;
            }
        }
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            double hx = blurred[i];
            blurred[i] = y_masked[i] / (hx > floor_abs ? hx : floor_abs);
        }
        if ((st = svp_blur_adjoint(blur, &img_blurred, &img_correction)) != SVP_OK) goto cleanup;
        double *restrict g = step_2; /* becomes the newest step */
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            if (inv_norm[i] == 0) {
                if (g) g[i] = 0.0;
                continue;
            }
            const double old = xd[i];
            double v = old * correction[i] * inv_norm[i];
            /* round-off can make Hᵀ(...) slightly negative; NaN/Inf never leave */
            v = (v > 0 && v <= DBL_MAX) ? v : 0.0;
            xd[i] = v;
            if (g) g[i] = v - old;
        }
        if (accel) {
            step_2 = step_1;
            step_1 = g;
        }
        done = k + 1;
        st = svp_report_progress(options->progress, options->progress_user,
                                 (double)(k + 1) / options->iterations);
        if (st != SVP_OK) goto cleanup;
    }
    if (stop == SVP_RL_STOP_DISCREPANCY || stop == SVP_RL_STOP_STALLED)
        st = svp_report_progress(options->progress, options->progress_user, 1.0);
    if (options->report) {
        options->report->iterations = done;
        options->report->chi2 = chi2;
        options->report->stop = stop;
    }
cleanup:
    if (options->single_precision && !was_single) svp_blur_set_single(blur, 0);
    svp_free(y_masked);
    svp_free(blurred);
    svp_free(correction);
    svp_free(inv_norm);
    svp_free(x_prev);
    svp_free(step_1);
    svp_free(step_2);
    return st;
}
