/* The PSF field's layout, shared by field.c and the operators that sample it (blur/). */
#ifndef SVP_FIELD_INTERNAL_H
#define SVP_FIELD_INTERNAL_H

#include "../core/internal.h"

#define SVP_FIELD_POLY_MAX_DEGREE 8

struct svp_psf_field {
    svp_psf_field_kind kind;
    int width, height; /* 0 x 0: a uniform field valid for any size */
    svp_psf base;      /* model, support, subsample (and, for Gaussian fields, beta unused) */
    /* uniform */
    svp_psf uniform;
    double uniform_p[SVP_FIELD_NPARAM];
    /* grid: nx x ny nodes, node_p[(j nx + i) NPARAM + q] */
    int nx, ny, grid_default_nodes;
    double *node_x, *node_y, *node_p;
    /* poly: coeffs[q n_terms + t] */
    int degree;
    double *coeffs;
    /* regions: labels, per-label PSFs and parameters, blended parameter maps pmap[q N + i] */
    int n_labels;
    int *labels;
    svp_psf *region_psfs;
    double *region_p;
    double transition;
    double *pmap;
    /* grid, poly: the map's own image lies `margin` pixels inside width x height
     * (svp_psf_field_pad): positions are clamped to it, the polynomial's u, v are its own */
    int margin;
};

/* The field's common model / support / subsample. */
const svp_psf *svp_psf_field_base(const svp_psf_field *field);

/* Region fields: label's blend weight w_l at every pixel into w (width x height): its one-hot
 * map, smoothed as the field blends parameters when the transition is > 0 (the weights of all
 * labels are >= 0 and sum to 1); *count = the label's pixels (0: w is all zero). */
svp_status svp_psf_field_region_weight(const svp_psf_field *field, int label, double *w,
                                       size_t *count);
/* Region fields: the PSF of label `label` itself, as svp_psf_field_at gives it at a pixel of
 * that label in a sharp map (the same parameters, clamped, the same round trip). */
void svp_psf_field_region_psf(const svp_psf_field *field, int label, svp_psf *out);

/* Rows y0 .. y0 + rows − 1 of svp_psf_render's (2 rx + 1) x (2 ry + 1) kernel before its
 * normalisation (the same values), rows 2 rx + 1 apart in out; the PSF must be valid
 * (svp_psf_validate). Serial: callers render blocks of rows in parallel (model.c). */
svp_status svp_psf_render_rows(const svp_psf *psf, int rx, int ry, int y0, int rows,
                               double *out);

/* The symmetry of svp_psf_render's kernel beyond the point symmetry every model has:
 * 2 = circular (fwhm_minor 0 or equal to fwhm): k(dx, dy) = k(±dx, ±dy) = k(dy, dx);
 * 1 = an ellipse whose axes are the grid's (angle a multiple of π / 2): k(dx, dy) = k(±dx, ±dy);
 * 0 = neither. Exact at the pixel centres for angle 0 (a rotated frame's, and the sub-pixel
 * means', to round-off). */
int svp_psf_symmetry(const svp_psf *psf);

/* The kernel's fold (symmetry >= 1): rows dy = y0 .. y0 + rows − 1 of its quadrant dx, dy >= 0,
 * dx <= rx, from dx = dy when octant (symmetry 2, dx >= dy), before svp_psf_render's
 * normalisation (the same values up to round-off), packed row after row (row dy holds
 * rx + 1 − (octant ? dy : 0) values). The PSF must be valid. Serial. */
void svp_psf_render_fold(const svp_psf *psf, int rx, int octant, int y0, int rows,
                         double *out);

#endif
