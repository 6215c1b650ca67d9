/* The exact per-source reference operator (docs/model.md §9), no approximation:
 *   Ĩ(o) = Σ_s [(1 − α_s) k_s(o − s) + α_s / N] I(s)
 * k_s the core kernel of the field's PSF at source pixel s, sampled and truncated like
 * svp_psf_render (pixel integration for small FWHM, disc support) and normalised to unit sum
 * over its own (2 rx + 1) x (2 ry + 1) support. Boundaries as svp_blur_new: the scene beyond
 * the edges is zero, mirrored (each mirrored copy of a source spreads with the source's own
 * PSF) or periodic. Direct sums: apply gathers over sources (parallel over output rows), the
 * adjoint gathers over outputs (parallel over source rows); both deterministic. Kernels are
 * tabulated once when N · kernel area <= 2^23 values, else evaluated on the fly. */
#include "blur_internal.h"
#include "../psf/field_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

typedef struct source_eval {
    double c, s;      /* cos, sin of the major-axis angle */
    double ia2, ib2;  /* 1 / scale² per axis */
    double beta;      /* effective Moffat index */
    double sub_r2;    /* pixel integration inside this radius² */
    double weight;    /* (1 − α) / kernel sum */
    int gaussian, ns; /* ns samples per pixel side */
} source_eval;

struct svp_exact_data {
    int rx, ry;
    double support2;
    source_eval *src;   /* per source pixel */
    double *alpha;      /* per-pixel halo, NULL when none */
    int *map_x, *map_y; /* extended index t + r → image index or −1 */
    int *inv_x_start, *inv_x, *inv_y_start, *inv_y; /* extended indices per image index */
    double *table; /* N x kw x kh normalised kernels (times 1 − α), or NULL */
};

#define TABLE_MAX ((size_t)1 << 23)

static int reflect(int t, int size)
{
    int period = 2 * size;
    t %= period;
    if (t < 0) t += period;
    return t < size ? t : period - 1 - t;
}

static int source_index(int t, int size, svp_boundary b)
{
    switch (b) {
    case SVP_BOUNDARY_ZERO: return t >= 0 && t < size ? t : -1;
    case SVP_BOUNDARY_PERIODIC: return ((t % size) + size) % size;
    default: return reflect(t, size);
    }
}

static void eval_setup(const svp_psf *psf, source_eval *e)
{
    const int gaussian = psf->model == SVP_PSF_GAUSSIAN;
    const double beta = psf->model == SVP_PSF_LORENTZIAN ? 1.0 : psf->beta;
    const double fa = psf->fwhm, fb = psf->fwhm_minor > 0 ? psf->fwhm_minor : psf->fwhm;
    const double sa = svp_psf_fwhm_to_r0(fa, gaussian ? 0.0 : beta);
    const double sb = svp_psf_fwhm_to_r0(fb, gaussian ? 0.0 : beta);
    e->c = cos(psf->angle);
    e->s = sin(psf->angle);
    e->ia2 = 1.0 / (sa * sa);
    e->ib2 = 1.0 / (sb * sb);
    e->beta = beta;
    e->gaussian = gaussian;
    /* the sampling rule of svp_psf_render */
    const double fmin =
        psf->fwhm_minor > 0 && psf->fwhm_minor < psf->fwhm ? psf->fwhm_minor : psf->fwhm;
    e->ns = psf->subsample > 0 ? psf->subsample : (fmin < 2.0 ? 9 : 1);
    const double fwhm_max = psf->fwhm_minor > psf->fwhm ? psf->fwhm_minor : psf->fwhm;
    e->sub_r2 = pow(fmax(3.0, 4.0 * fwhm_max), 2);
}

static inline double profile(const source_eval *e, double dx, double dy)
{
    double u = dx * e->c + dy * e->s;
    double v = -dx * e->s + dy * e->c;
    double q = u * u * e->ia2 + v * v * e->ib2;
    if (e->gaussian) return exp(-0.5 * q);
    if (e->beta == 1.0) return 1.0 / (1.0 + q);
    return exp(-e->beta * log1p(q));
}

/* Un-normalised kernel value at integer offset (dx, dy). */
static inline double kernel_raw(const source_eval *e, int dx, int dy, double support2)
{
    double r2 = (double)dx * dx + (double)dy * dy;
    if (r2 > support2) return 0.0;
    if (e->ns > 1 && r2 <= e->sub_r2) {
        const int ns = e->ns;
        double acc = 0;
        for (int j = 0; j < ns; j++) {
            double sy = dy - 0.5 + (j + 0.5) / ns;
            for (int i = 0; i < ns; i++) acc += profile(e, dx - 0.5 + (i + 0.5) / ns, sy);
        }
        return acc / (ns * ns);
    }
    return profile(e, dx, dy);
}

static inline double kernel_at(const svp_exact_data *d, size_t s, int dx, int dy)
{
    if (d->table) {
        const size_t kw = 2 * (size_t)d->rx + 1, kh = 2 * (size_t)d->ry + 1;
        return d->table[s * kw * kh + (size_t)(dy + d->ry) * kw + (size_t)(dx + d->rx)];
    }
    return d->src[s].weight * kernel_raw(&d->src[s], dx, dy, d->support2);
}

static svp_status axis_maps(int size, int r, svp_boundary b, int **map, int **start, int **inv)
{
    const int n = size + 2 * r;
    *map = malloc((size_t)n * sizeof(int));
    *start = calloc((size_t)size + 1, sizeof(int));
    *inv = malloc((size_t)n * sizeof(int));
    if (!*map || !*start || !*inv) return svp_fail(SVP_ERR_NOMEM, "out of memory for maps");
    for (int j = 0; j < n; j++) {
        int s = source_index(j - r, size, b);
        (*map)[j] = s;
        if (s >= 0) (*start)[s + 1]++;
    }
    for (int s = 0; s < size; s++) (*start)[s + 1] += (*start)[s];
    int *fill = malloc((size_t)size * sizeof(int));
    if (!fill) return svp_fail(SVP_ERR_NOMEM, "out of memory for maps");
    memcpy(fill, *start, (size_t)size * sizeof(int));
    for (int j = 0; j < n; j++)
        if ((*map)[j] >= 0) (*inv)[fill[(*map)[j]]++] = j - r; /* the extended position t */
    free(fill);
    return SVP_OK;
}

svp_status svp_blur_new_exact(const svp_psf_field *field, int width, int height,
                              svp_boundary boundary, double support, svp_blur **out)
{
    return svp_blur_new_exact_tab(field, width, height, boundary, support, -1, out);
}

svp_status svp_blur_new_exact_tab(const svp_psf_field *field, int width, int height,
                                  svp_boundary boundary, double support, int tabulate,
                                  svp_blur **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_blur_new_exact: out is NULL");
    svp_blur *b = NULL;
    int rx, ry;
    double sup;
    SVP_CHECK(svp_variant_begin(field, width, height, boundary, support, SVP_BLUR_EXACT, &b, &rx,
                                &ry, &sup));
    b->ops = &svp_exact_ops;
    svp_status st = SVP_OK;
    const size_t n = (size_t)width * height;
    const int kw = 2 * rx + 1, kh = 2 * ry + 1;
    svp_exact_data *d = b->exact = calloc(1, sizeof *d);
    if (!d) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for the exact operator");
        goto cleanup;
    }
    d->rx = rx;
    d->ry = ry;
    d->support2 = sup > 0 ? sup * sup : INFINITY;
    d->src = malloc(n * sizeof *d->src);
    if (!d->src) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for %zu source PSFs", n);
        goto cleanup;
    }
    st = axis_maps(width, rx, boundary, &d->map_x, &d->inv_x_start, &d->inv_x);
    if (st == SVP_OK) st = axis_maps(height, ry, boundary, &d->map_y, &d->inv_y_start, &d->inv_y);
    if (st == SVP_OK) st = svp_variant_halo_map(b->field, width, height, &d->alpha);
    for (size_t i = 0; i < n && st == SVP_OK; i++) {
        svp_psf psf;
        st = svp_psf_field_at(b->field, (double)(i % (size_t)width), (double)(i / (size_t)width),
                              &psf);
        if (st == SVP_OK) st = svp_psf_validate(&psf);
        if (st == SVP_OK) eval_setup(&psf, &d->src[i]);
    }
    if (st != SVP_OK) goto cleanup;
    if (tabulate > 0 || (tabulate < 0 && n * (size_t)kw * kh <= TABLE_MAX)) {
        d->table = svp_alloc(n * (size_t)kw * kh * sizeof(double));
        if (!d->table) {
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for the kernel table");
            goto cleanup;
        }
    }
    /* Normalise each source's kernel over its support (and tabulate it when small). */
    int bad = -1;
#pragma omp parallel for schedule(dynamic, 16) if (n * (size_t)kw * kh > SVP_PARALLEL_MIN)
    for (size_t i = 0; i < n; i++) {
        source_eval *e = &d->src[i];
        double *k = d->table ? d->table + i * (size_t)kw * kh : NULL;
        double sum = 0;
        for (int dy = -ry; dy <= ry; dy++)
            for (int dx = -rx; dx <= rx; dx++) {
                double v = kernel_raw(e, dx, dy, d->support2);
                if (k) k[(size_t)(dy + ry) * kw + (dx + rx)] = v;
                sum += v;
            }
        const double keep = d->alpha ? 1.0 - d->alpha[i] : 1.0;
        if (!(sum > 0) || !isfinite(sum)) {
#pragma omp critical
            bad = (int)i;
            e->weight = 0;
            continue;
        }
        e->weight = keep / sum;
        if (k)
            for (size_t j = 0; j < (size_t)kw * kh; j++) k[j] *= e->weight;
    }
    if (bad >= 0) {
        st = svp_fail(SVP_ERR_NUMERIC,
                      "exact operator: the PSF at pixel (%d, %d) has no flux "
                      "on its support",
                      bad % width, bad / width);
        goto cleanup;
    }
cleanup:
    if (st != SVP_OK) {
        svp_blur_free(b);
        *out = NULL;
        return st;
    }
    *out = b;
    return SVP_OK;
}

static svp_status exact_apply(svp_blur *b, const double *restrict x, double *restrict y)
{
    const svp_exact_data *d = b->exact;
    const int w = b->width, h = b->height, rx = d->rx, ry = d->ry;
    const size_t work = (size_t)w * h * (2 * (size_t)rx + 1) * (2 * (size_t)ry + 1);
#pragma omp parallel for schedule(dynamic, 1) if (work > SVP_PARALLEL_MIN)
    for (int oy = 0; oy < h; oy++) {
        for (int ox = 0; ox < w; ox++) {
            double acc = 0;
            for (int ty = oy - ry; ty <= oy + ry; ty++) {
                const int sy = d->map_y[ty + ry];
                if (sy < 0) continue;
                const int dy = oy - ty;
                for (int tx = ox - rx; tx <= ox + rx; tx++) {
                    const int sx = d->map_x[tx + rx];
                    if (sx < 0) continue;
                    const size_t s = (size_t)sy * w + sx;
                    if (x[s] == 0) continue;
                    acc += kernel_at(d, s, ox - tx, dy) * x[s];
                }
            }
            y[(size_t)oy * w + ox] = acc;
        }
    }
    if (d->alpha) svp_halo_scatter(d->alpha, (size_t)w * h, x, y, b->work_r_image);
    return SVP_OK;
}

static svp_status exact_adjoint(svp_blur *b, const double *restrict y, double *restrict x)
{
    const svp_exact_data *d = b->exact;
    const int w = b->width, h = b->height, rx = d->rx, ry = d->ry;
    const size_t work = (size_t)w * h * (2 * (size_t)rx + 1) * (2 * (size_t)ry + 1);
#pragma omp parallel for schedule(dynamic, 1) if (work > SVP_PARALLEL_MIN)
    for (int sy = 0; sy < h; sy++) {
        for (int sx = 0; sx < w; sx++) {
            const size_t s = (size_t)sy * w + sx;
            double acc = 0;
            /* every extended copy t of the source, every output it reaches */
            for (int a = d->inv_y_start[sy]; a < d->inv_y_start[sy + 1]; a++) {
                const int ty = d->inv_y[a];
                const int oy0 = ty - ry > 0 ? ty - ry : 0, oy1 = ty + ry < h - 1 ? ty + ry : h - 1;
                for (int c = d->inv_x_start[sx]; c < d->inv_x_start[sx + 1]; c++) {
                    const int tx = d->inv_x[c];
                    const int ox0 = tx - rx > 0 ? tx - rx : 0;
                    const int ox1 = tx + rx < w - 1 ? tx + rx : w - 1;
                    for (int oy = oy0; oy <= oy1; oy++) {
                        const double *row = y + (size_t)oy * w;
                        for (int ox = ox0; ox <= ox1; ox++)
                            if (row[ox] != 0) acc += kernel_at(d, s, ox - tx, oy - ty) * row[ox];
                    }
                }
            }
            x[s] = acc;
        }
    }
    if (d->alpha) svp_halo_gather(d->alpha, (size_t)w * h, y, x);
    return SVP_OK;
}

static const double *exact_halo_map(const svp_blur *b)
{
    return b->exact ? b->exact->alpha : NULL;
}

static void exact_release(svp_blur *b)
{
    svp_exact_data *d = b->exact;
    svp_variant_common_release(b);
    if (!d) return;
    free(d->src);
    svp_free(d->alpha);
    free(d->map_x);
    free(d->map_y);
    free(d->inv_x_start);
    free(d->inv_x);
    free(d->inv_y_start);
    free(d->inv_y);
    svp_free(d->table);
    free(d);
    b->exact = NULL;
}

static size_t exact_memory(const svp_blur *b)
{
    const svp_exact_data *d = b->exact;
    if (!d) return svp_variant_common_memory(b);
    const size_t n = (size_t)b->width * b->height;
    size_t bytes = svp_variant_common_memory(b) + sizeof *d + n * sizeof(source_eval);
    if (d->alpha) bytes += n * sizeof(double);
    bytes += (size_t)(2 * (b->width + 2 * d->rx) + 2 * (b->height + 2 * d->ry) + b->width +
                      b->height + 2) *
             sizeof(int);
    if (d->table) bytes += n * (size_t)(2 * d->rx + 1) * (2 * d->ry + 1) * sizeof(double);
    return bytes;
}

const svp_blur_ops svp_exact_ops = {"exact",      exact_apply,   exact_adjoint,
                                    exact_memory, exact_release, exact_halo_map};
