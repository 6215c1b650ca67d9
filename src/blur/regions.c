/* The region representation of the space-variant operator (docs/model.md §9, "Region maps"):
 * for a PSF field of kind regions,
 *   H x = Σ_k e_k ⊛ (c_k (1 − α) ⊙ x) + <α x>_FOV,
 * e_k the normalised core kernel of used label k's PSF and c_k its blend weight map (one-hot
 * for a sharp map, the field's smoothed one-hot map for a blended one). This is the low-rank
 * operator's shape (terms = kernels, per-pixel coefficient maps), so variant.c builds and
 * applies it with the low-rank machinery; this file makes the terms and counts the memory. */
#include "blur_internal.h"
#include "../psf/field_internal.h"

#include <stdint.h>
#include <stdlib.h>
#include <string.h>

static const char *field_kind_name(svp_psf_field_kind kind)
{
    switch (kind) {
    case SVP_FIELD_UNIFORM: return "uniform";
    case SVP_FIELD_GRID: return "grid";
    case SVP_FIELD_POLY: return "poly";
    case SVP_FIELD_REGIONS: return "regions";
    }
    return "unknown";
}

svp_status svp_region_check(const svp_psf_field *field)
{
    if (field->kind != SVP_FIELD_REGIONS)
        return svp_fail(SVP_ERR_INVALID,
                        "the region representation needs a PSF map of kind regions (a label "
                        "image, one PSF per label); this map is of kind %s",
                        field_kind_name(field->kind));
    return SVP_OK;
}

/* used[l] = 1 for the labels with a pixel (n_labels values); the number of them. */
static int used_labels(const svp_psf_field *field, char *used)
{
    memset(used, 0, (size_t)field->n_labels);
    const size_t n = (size_t)field->width * field->height;
    for (size_t i = 0; i < n; i++) used[field->labels[i]] = 1;
    int K = 0;
    for (int l = 0; l < field->n_labels; l++) K += used[l];
    return K;
}

int svp_region_count(const svp_psf_field *field)
{
    if (field->kind != SVP_FIELD_REGIONS) return 0;
    char *used = malloc((size_t)field->n_labels);
    if (!used) return field->n_labels; /* an upper bound */
    const int K = used_labels(field, used);
    free(used);
    return K;
}

void svp_region_terms_free(svp_region_terms *t)
{
    free(t->label);
    free(t->psf);
    free(t->weight);
    memset(t, 0, sizeof *t);
}

svp_status svp_region_terms_make(const svp_psf_field *field, svp_region_terms *t)
{
    memset(t, 0, sizeof *t);
    SVP_CHECK(svp_region_check(field));
    char *used = malloc((size_t)field->n_labels);
    if (!used) return svp_fail(SVP_ERR_NOMEM, "out of memory for %d labels", field->n_labels);
    const int K = used_labels(field, used);
    const size_t n = (size_t)field->width * field->height;
    t->label = malloc((size_t)K * sizeof(int));
    t->psf = malloc((size_t)K * sizeof(svp_psf));
    t->weight = malloc((size_t)K * n * sizeof(double));
    svp_status st = t->label && t->psf && t->weight
                        ? SVP_OK
                        : svp_fail(SVP_ERR_NOMEM, "out of memory for %d region weight maps of "
                                                  "%d x %d", K, field->width, field->height);
    for (int l = 0; l < field->n_labels && st == SVP_OK; l++) {
        if (!used[l]) continue; /* a label with no pixel: no term */
        size_t count = 0;
        st = svp_psf_field_region_weight(field, l, t->weight + (size_t)t->K * n, &count);
        t->label[t->K] = l;
        svp_psf_field_region_psf(field, l, &t->psf[t->K]);
        t->K++;
    }
    free(used);
    if (st != SVP_OK) svp_region_terms_free(t);
    return st;
}

size_t svp_region_peak_bytes(int width, int height, svp_boundary boundary, int K, int rx, int ry)
{
    int nx = 0, ny = 0;
    if (svp_frame_size(width, height, rx, ry, boundary, &nx, &ny) != SVP_OK) return SIZE_MAX;
    const size_t image = (size_t)width * height * sizeof(double);
    /* a tent of K nodes (K spectra, the same work buffers, one kernel while a spectrum is
     * made), plus: the smoothing buffer, the K weight maps while the tables are made, and the
     * weight tables on the frame's columns (K x height x nx; the tent counts K x nx) */
    return svp_variant_peak_bytes(width, height, boundary, 0, K, 0, rx, ry) + image +
           (size_t)K * image + (size_t)K * (height - 1) * nx * sizeof(double);
}
