/* Noise models of the measured maps (docs/model.md §6, "Noise models"): the PL's shot noise
 * through a camera gain, var Ĩ = g · (Ĩ − o), and the field's fit noise, σ_B² = k² / Ĩ where the
 * caller gives no per-pixel σ. Both are estimated from the images with the Immerkær mask
 * N = [1 −2 1; −2 4 −2; 1 −2 1], whose response to white noise of variance v has variance 36 v
 * and which cancels locally quadratic signal. */
#include "restore_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define BLOCK 16
#define MIN_BLOCKS 8

/* Immerkær response at interior pixel (i, j); NaN when a neighbour is not finite. */
static double mask_response(const double *d, int w, int i, int j)
{
    const double *u = d + (size_t)(j - 1) * w, *c = d + (size_t)j * w, *l = d + (size_t)(j + 1) * w;
    return (u[i - 1] + u[i + 1] + l[i - 1] + l[i + 1]) - 2 * (u[i] + l[i] + c[i - 1] + c[i + 1]) +
           4 * c[i];
}

svp_status svp_pl_noise_estimate(const svp_image *pl, double *gain, double *offset)
{
    if (!pl || !pl->data || !gain || !offset)
        return svp_fail(SVP_ERR_INVALID, "PL noise estimate: NULL argument");
    const int w = pl->width, h = pl->height;
    if (w < 2 * BLOCK || h < 2 * BLOCK)
        return svp_fail(SVP_ERR_INVALID,
                        "PL noise estimate: the PL is %d x %d, at least %d x %d is needed", w, h,
                        2 * BLOCK, 2 * BLOCK);
    const int bx = (w - 2) / BLOCK, by = (h - 2) / BLOCK;
    double *mean = malloc((size_t)bx * by * sizeof(double));
    double *var = malloc((size_t)bx * by * sizeof(double));
    if (!mean || !var) {
        free(mean);
        free(var);
        return svp_fail(SVP_ERR_NOMEM, "PL noise estimate: out of memory");
    }
    size_t nb = 0;
    for (int b = 0; b < by; b++)
        for (int a = 0; a < bx; a++) {
            double s = 0, s2 = 0;
            int k = 0;
            for (int j = 1 + b * BLOCK; j < 1 + (b + 1) * BLOCK; j++)
                for (int i = 1 + a * BLOCK; i < 1 + (a + 1) * BLOCK; i++) {
                    const double r = mask_response(pl->data, w, i, j);
                    const double v = pl->data[(size_t)j * w + i];
                    if (!isfinite(r) || !isfinite(v)) continue;
                    s += v;
                    s2 += r * r;
                    k++;
                }
            if (k < BLOCK * BLOCK / 2) continue;
            mean[nb] = s / k;
            var[nb] = s2 / (36.0 * k);
            nb++;
        }
    svp_status st = SVP_OK;
    if (nb < MIN_BLOCKS) {
        st = svp_fail(SVP_ERR_INVALID,
                      "PL noise estimate: only %zu blocks of %d x %d pixels are free of NaN/Inf "
                      "(at least %d are needed)",
                      nb, BLOCK, BLOCK, MIN_BLOCKS);
        goto cleanup;
    }
    /* Theil–Sen slope over the pairs of blocks whose means differ (a sample of at most
     * 4096 x 4096 pairs, in a fixed order), and the median intercept. */
    {
        const size_t step = nb > 4096 ? nb / 4096 : 1;
        size_t m = 0, cap = 0;
        for (size_t p = 0; p < nb; p += step)
            for (size_t q = p + step; q < nb; q += step) cap++;
        double *slopes = malloc((cap ? cap : 1) * sizeof(double));
        if (!slopes) {
            st = svp_fail(SVP_ERR_NOMEM, "PL noise estimate: out of memory");
            goto cleanup;
        }
        for (size_t p = 0; p < nb; p += step)
            for (size_t q = p + step; q < nb; q += step) {
                const double dm = mean[q] - mean[p];
                if (fabs(dm) > 1e-12 * (fabs(mean[p]) + fabs(mean[q]))) slopes[m++] = (var[q] - var[p]) / dm;
            }
        double g = m ? svp_median(slopes, m) : 0.0;
        free(slopes);
        if (!(g > 0) || !isfinite(g)) {
            *gain = 0;
            *offset = 0;
            goto cleanup;
        }
        for (size_t p = 0; p < nb; p++) var[p] -= g * mean[p];
        const double intercept = svp_median(var, nb);
        *gain = g;
        *offset = -intercept / g;
    }
cleanup:
    free(mean);
    free(var);
    return st;
}

/* k² of σ_B² = k² / Ĩ: the median over interior pixels of (N ∗ B̃)² Ĩ / 36, divided by the
 * median of χ²₁ (0.4549) so it estimates the mean (robust to edges, where the mask sees
 * structure). Pixels with Ĩ <= 0 or a non-finite neighbour are skipped; 0 when none is left. */
svp_status svp_field_noise_k2(const svp_image *field, const svp_image *pl, double *k2)
{
    const int w = field->width, h = field->height;
    *k2 = 0;
    if (w < 3 || h < 3) return SVP_OK;
    double *v = malloc((size_t)(w - 2) * (h - 2) * sizeof(double));
    if (!v) return svp_fail(SVP_ERR_NOMEM, "field noise estimate: out of memory");
    size_t m = 0;
    for (int j = 1; j < h - 1; j++)
        for (int i = 1; i < w - 1; i++) {
            const double r = mask_response(field->data, w, i, j);
            const double p = pl->data[(size_t)j * w + i];
            if (!isfinite(r) || !(p > 0) || !isfinite(p)) continue;
            v[m++] = r * r * p / 36.0;
        }
    if (m) *k2 = svp_median(v, m) / 0.454936423119572;
    free(v);
    return SVP_OK;
}
