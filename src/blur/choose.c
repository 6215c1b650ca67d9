/* Choosing the space-variant representation by an error budget (docs/model.md §9, "Choosing
 * the representation").
 *
 * The error of a representation is measured as the relative Frobenius norm of H − H_exact,
 * ‖H − H_exact‖_F / ‖H_exact‖_F: the expected relative error of H x for a white-noise x, and
 * the root-mean-square over sources of ‖k̂_s − k_s‖ / rms ‖k_s‖, k_s the exact kernel at source
 * s and k̂_s the representation's. It is estimated at P probe sources spread over the image,
 * with kernels of a compact radius (their core holds nearly all of their squared norm):
 *   tent g x g:     k̂_p = Σ_k hat_k(p) k_node_k (the node kernels themselves);
 *   low rank R:     k̂_p = K̄ + Σ_{q < R−1} c_q(p) e_q, e_q the eigen-PSFs of the compact sampled
 *                   kernels' deviations from their mean, c_q bilinear in the samples — this
 *                   carries both the truncated spectrum's tail and the interpolation between
 *                   the samples.
 * The cost model counts FFTs of the frame: an application and its adjoint are 2 (K + 1) for K
 * terms, times the H + Hᵀ pairs the caller expects (options->applications: svpsf correct
 * passes the count its method runs, e.g. 2 x 75 for --method r on one field), plus the build
 * (cost_of: per-pixel work of renders and Gram products in FFT-equivalents, the low-rank one
 * over the fold of the kernels the Gram build renders). The cheapest candidate within the
 * budget and within the memory limit wins; when none meets the budget, the cheapest whose error
 * is within 1.25 x the smallest estimated. */
#include "blur_internal.h"
#include "../psf/field_internal.h"

#include <lapacke.h>
#include <math.h>
#include <omp.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

enum { PROBES = 96, RC_MIN = 6, RC_MAX = 40, RANK_MAX = 24 };

static const int tent_grids[] = {1, 2, 3, 4, 5, 6, 8, 10, 12, 16};
static const int lowrank_samples[] = {6, 8, 12, 16};

typedef struct est_ctx {
    const svp_psf_field *field;
    int width, height;
    double support; /* the operator's support (0: whole field) */
    int rc;         /* the compact radius of the estimates */
    size_t mc;      /* (2 rc + 1)² */
    int probes;
    double *px, *py;  /* probe positions */
    double *pk;       /* probe kernels, probes x mc */
    double norm2;     /* Σ_p ‖k_p‖² */
} est_ctx;

/* Σ a_i b_i in a fixed order: four interleaved partial sums (independent chains the compiler
 * can pipeline and vectorise), then the tail. */
static double dotp(const double *a, const double *b, size_t n)
{
    double s0 = 0, s1 = 0, s2 = 0, s3 = 0;
    size_t i = 0;
    for (; i + 4 <= n; i += 4) {
        s0 += a[i] * b[i];
        s1 += a[i + 1] * b[i + 1];
        s2 += a[i + 2] * b[i + 2];
        s3 += a[i + 3] * b[i + 3];
    }
    for (; i < n; i++) s0 += a[i] * b[i];
    return (s0 + s1) + (s2 + s3);
}

static double node_at(int i, int g, int size)
{
    return g == 1 ? 0.5 * (size - 1) : (double)i * (size - 1) / (g - 1);
}

/* Lower node and fraction towards the next of position x on g nodes over size pixels. */
static void hat_of(double x, int g, int size, int *i0, double *t)
{
    if (g == 1) {
        *i0 = 0;
        *t = 0;
        return;
    }
    double u = x * (g - 1) / (size - 1);
    int i = (int)floor(u);
    if (i > g - 2) i = g - 2;
    if (i < 0) i = 0;
    *i0 = i;
    *t = u - i;
}

/* The field's kernel at (x, y) on the compact radius, scaled to the share of the flux the
 * operator's kernel has there (its encircled energy). Serial (the callers run kernels in
 * parallel), so every value is the same on any number of threads. */
static svp_status compact_psf_kernel(const est_ctx *c, svp_psf psf, double x, double y,
                                     double *out)
{
    psf.support = c->support;
    SVP_CHECK(svp_psf_render_rows(&psf, c->rc, c->rc, 0, 2 * c->rc + 1, out));
    double sum = 0;
    for (size_t i = 0; i < c->mc; i++) sum += out[i];
    if (!(sum > 0) || !isfinite(sum))
        return svp_fail(SVP_ERR_NUMERIC,
                        "PSF kernel at (%g, %g) has no flux on its %d x %d support", x, y,
                        2 * c->rc + 1, 2 * c->rc + 1);
    double R = c->support > 0 ? c->support : 0.0;
    double ee = svp_psf_encircled_energy(&psf, c->rc + 0.5, R);
    if (!(ee > 0 && ee <= 1)) /* heavy tails over the whole field: the image's extent */
        ee = svp_psf_encircled_energy(&psf, c->rc + 0.5, fmax(c->width, c->height));
    if (!(ee > 0 && ee <= 1)) ee = 1;
    const double scale = ee / sum;
    for (size_t i = 0; i < c->mc; i++) out[i] *= scale;
    return SVP_OK;
}

static svp_status compact_kernel(const est_ctx *c, double x, double y, double *out)
{
    svp_psf psf;
    SVP_CHECK(svp_psf_field_at(c->field, x, y, &psf));
    return compact_psf_kernel(c, psf, x, y, out);
}

/* compact_kernel at n positions (x[i], y[i]) into out + i mc, in parallel; the first failure's
 * status (its message set again on the calling thread). */
static svp_status compact_kernels(const est_ctx *c, int n, const double *x, const double *y,
                                  double *out)
{
    int bad = -1;
#pragma omp parallel for schedule(dynamic, 1)
    for (int i = 0; i < n; i++) {
        int failed;
#pragma omp atomic read
        failed = bad;
        if (failed >= 0) continue;
        if (compact_kernel(c, x[i], y[i], out + (size_t)i * c->mc) != SVP_OK) {
#pragma omp critical(svp_choose_bad)
            if (bad < 0 || i < bad) bad = i;
        }
    }
    if (bad >= 0) return compact_kernel(c, x[bad], y[bad], out + (size_t)bad * c->mc);
    return SVP_OK;
}

/* Kernels at the nodes of a gx x gy grid (x fastest), into out. */
static svp_status grid_kernels(const est_ctx *c, int gx, int gy, double *out)
{
    const int n = gx * gy;
    double *x = malloc((size_t)n * sizeof(double)), *y = malloc((size_t)n * sizeof(double));
    if (!x || !y) {
        free(x);
        free(y);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for estimates");
    }
    for (int k = 0; k < n; k++) {
        x[k] = node_at(k % gx, gx, c->width);
        y[k] = node_at(k / gx, gy, c->height);
    }
    svp_status st = compact_kernels(c, n, x, y, out);
    free(x);
    free(y);
    return st;
}

static void est_release(est_ctx *c)
{
    free(c->px);
    free(c->py);
    free(c->pk);
    memset(c, 0, sizeof *c);
}

static svp_status est_init(est_ctx *c, const svp_psf_field *field, int width, int height,
                           double support)
{
    memset(c, 0, sizeof *c);
    c->field = field;
    c->width = width;
    c->height = height;
    const double sup = support > 0 ? support : svp_psf_field_base(field)->support;
    c->support = sup;
    /* radius: 5 x the largest FWHM among a few positions, within RC_MIN .. RC_MAX and the
     * operator's support */
    double fmax_px = 0;
    for (int j = 0; j < 9; j++) {
        svp_psf p;
        SVP_CHECK(svp_psf_field_at(field, 0.5 * (j % 3) * (width - 1), 0.5 * (j / 3) * (height - 1),
                                   &p));
        fmax_px = fmax(fmax_px, fmax(p.fwhm, p.fwhm_minor));
    }
    int rc = (int)ceil(5 * fmax_px);
    if (rc < RC_MIN) rc = RC_MIN;
    if (rc > RC_MAX) rc = RC_MAX;
    if (sup > 0 && rc > (int)ceil(sup)) rc = (int)ceil(sup);
    const int lim = (width > height ? width : height) - 1;
    if (rc > lim) rc = lim > 0 ? lim : 0;
    c->rc = rc;
    c->mc = (size_t)(2 * rc + 1) * (2 * rc + 1);
    c->probes = PROBES;
    c->px = malloc(PROBES * sizeof(double));
    c->py = malloc(PROBES * sizeof(double));
    c->pk = malloc(PROBES * c->mc * sizeof(double));
    if (!c->px || !c->py || !c->pk) {
        est_release(c);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for the operator's error estimate");
    }
    /* a rank-1 lattice (golden ratio) over the image: every row and column band sampled */
    for (int p = 0; p < PROBES; p++) {
        const double u = (p + 0.5) / PROBES, v = fmod(0.5 + p * 0.6180339887498949, 1.0);
        c->px[p] = u * (width - 1);
        c->py[p] = v * (height - 1);
    }
    svp_status st = compact_kernels(c, PROBES, c->px, c->py, c->pk);
    c->norm2 = 0;
    for (int p = 0; p < PROBES && st == SVP_OK; p++) {
        const double *k = c->pk + (size_t)p * c->mc;
        c->norm2 += dotp(k, k, c->mc);
    }
    if (st != SVP_OK) est_release(c);
    return st;
}

/* Relative error of the tent gx x gy. */
static svp_status est_tent(const est_ctx *c, int gx, int gy, double *err)
{
    const size_t mc = c->mc;
    double *nodes = malloc((size_t)gx * gy * mc * sizeof(double));
    double *r = malloc(mc * sizeof(double));
    svp_status st = nodes && r ? SVP_OK : svp_fail(SVP_ERR_NOMEM, "out of memory for estimates");
    if (st == SVP_OK) st = grid_kernels(c, gx, gy, nodes);
    double e2 = 0;
    for (int p = 0; p < c->probes && st == SVP_OK; p++) {
        int i0, j0;
        double tx, ty;
        hat_of(c->px[p], gx, c->width, &i0, &tx);
        hat_of(c->py[p], gy, c->height, &j0, &ty);
        const int i1 = i0 + 1 < gx ? i0 + 1 : i0, j1 = j0 + 1 < gy ? j0 + 1 : j0;
        const double w00 = (1 - tx) * (1 - ty), w10 = tx * (1 - ty), w01 = (1 - tx) * ty,
                     w11 = tx * ty;
        const double *a = nodes + (size_t)(j0 * gx + i0) * mc, *b = nodes + (size_t)(j0 * gx + i1) * mc;
        const double *d = nodes + (size_t)(j1 * gx + i0) * mc, *e = nodes + (size_t)(j1 * gx + i1) * mc;
        const double *k = c->pk + (size_t)p * mc;
        for (size_t i = 0; i < mc; i++) {
            const double x = k[i] - (w00 * a[i] + w10 * b[i] + w01 * d[i] + w11 * e[i]);
            e2 += x * x;
        }
    }
    free(nodes);
    free(r);
    if (st == SVP_OK) *err = sqrt(e2 / c->norm2);
    return st;
}

/* Relative errors of the mean-centred low rank on sx x sy samples at ranks 1 .. nr (err[R − 1]),
 * nr <= S + 1. */
static svp_status est_lowrank(const est_ctx *c, int sx, int sy, int nr, double *err)
{
    const size_t mc = c->mc;
    const int S = sx * sy, Q = nr - 1;
    double *k = malloc((size_t)S * mc * sizeof(double)), *mean = calloc(mc, sizeof(double));
    double *g = malloc((size_t)S * S * sizeof(double)), *z = malloc((size_t)S * S * sizeof(double));
    double *lam = malloc((size_t)S * sizeof(double));
    double *e = malloc((size_t)(Q > 0 ? Q : 1) * mc * sizeof(double));
    double *cf = malloc((size_t)(Q > 0 ? Q : 1) * S * sizeof(double));
    double *r = malloc(mc * sizeof(double)), *e2 = calloc((size_t)nr, sizeof(double));
    lapack_int *isuppz = malloc(2 * (size_t)S * sizeof(lapack_int));
    svp_status st = SVP_OK;
    if (!k || !mean || !g || !z || !lam || !e || !cf || !r || !e2 || !isuppz) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for estimates");
        goto done;
    }
    st = grid_kernels(c, sx, sy, k);
    if (st != SVP_OK) goto done;
    for (int j = 0; j < S; j++)
        for (size_t i = 0; i < mc; i++) mean[i] += k[(size_t)j * mc + i] / S;
    for (int j = 0; j < S; j++)
        for (size_t i = 0; i < mc; i++) k[(size_t)j * mc + i] -= mean[i];
    /* the Gram matrix, each entry one serial dot product (the same on any thread count) */
#pragma omp parallel for schedule(dynamic, 1)
    for (int j = 0; j < S; j++)
        for (int i = j; i < S; i++)
            g[(size_t)j * S + i] = g[(size_t)i * S + j] =
                dotp(k + (size_t)i * mc, k + (size_t)j * mc, mc);
    if (Q > 0) {
        lapack_int found = 0;
        lapack_int info = LAPACKE_dsyevr(LAPACK_COL_MAJOR, 'V', 'A', 'L', S, g, S, 0, 0, 0, 0,
                                         0.0, &found, lam, z, S, isuppz);
        if (info != 0) {
            st = svp_fail(SVP_ERR_NUMERIC, "low rank estimate: dsyevr info %d", (int)info);
            goto done;
        }
        for (int q = 0; q < Q; q++) {
            const double *v = z + (size_t)(S - 1 - q) * S, l = lam[S - 1 - q];
            const double s = l > 0 ? sqrt(l) : 0;
            double *eq = e + (size_t)q * mc;
            memset(eq, 0, mc * sizeof(double));
            if (s > 0)
                for (int j = 0; j < S; j++)
                    for (size_t i = 0; i < mc; i++) eq[i] += v[j] / s * k[(size_t)j * mc + i];
            for (int j = 0; j < S; j++) cf[(size_t)q * S + j] = s * v[j];
        }
    }
    for (int p = 0; p < c->probes; p++) {
        int i0, j0;
        double tx, ty;
        hat_of(c->px[p], sx, c->width, &i0, &tx);
        hat_of(c->py[p], sy, c->height, &j0, &ty);
        const int i1 = i0 + 1 < sx ? i0 + 1 : i0, j1 = j0 + 1 < sy ? j0 + 1 : j0;
        const double *kp = c->pk + (size_t)p * mc;
        for (size_t i = 0; i < mc; i++) r[i] = kp[i] - mean[i];
        e2[0] += dotp(r, r, mc);
        for (int q = 0; q < Q; q++) {
            const double *cq = cf + (size_t)q * S;
            const double cp = (1 - ty) * ((1 - tx) * cq[j0 * sx + i0] + tx * cq[j0 * sx + i1]) +
                              ty * ((1 - tx) * cq[j1 * sx + i0] + tx * cq[j1 * sx + i1]);
            const double *eq = e + (size_t)q * mc;
            for (size_t i = 0; i < mc; i++) r[i] -= cp * eq[i];
            e2[q + 1] += dotp(r, r, mc);
        }
    }
    for (int q = 0; q < nr; q++) err[q] = sqrt(e2[q] / c->norm2);
done:
    free(k);
    free(mean);
    free(g);
    free(z);
    free(lam);
    free(e);
    free(cf);
    free(r);
    free(e2);
    free(isuppz);
    return st;
}

/* Relative error of the region representation (docs/model.md §9, "Region maps"): zero at
 * every pixel whose weights are one-hot (its kernel is its label's), so the probes are spread
 * over the M "mixed" pixels (some weight in (0, 1)) only, in raster order, and
 * ε² = (M / N) mean_probes ‖k_s − Σ_k w_k(s) e_k‖² / (mean ‖k_p‖² over the usual probes).
 * A sharp map has M = 0: ε = 0. keep (may be NULL): the terms made, handed over on success
 * (the build uses them: the weight maps are smoothed once). */
static svp_status est_regions(const est_ctx *c, svp_region_terms *keep, double *err)
{
    svp_region_terms t;
    SVP_CHECK(svp_region_terms_make(c->field, &t));
    const size_t n = (size_t)c->width * c->height, mc = c->mc;
    const int K = t.K;
    size_t *mixed = malloc(n * sizeof(size_t));
    double *ek = malloc((size_t)K * mc * sizeof(double));
    double *px = malloc(PROBES * sizeof(double)), *py = malloc(PROBES * sizeof(double));
    double *pk = malloc(PROBES * mc * sizeof(double));
    svp_status st = mixed && ek && px && py && pk
                        ? SVP_OK
                        : svp_fail(SVP_ERR_NOMEM, "out of memory for the region estimate");
    size_t M = 0;
    for (size_t i = 0; i < n && st == SVP_OK; i++) {
        int one_hot = 0;
        for (int k = 0; k < K; k++) one_hot |= t.weight[(size_t)k * n + i] >= 1.0 - 1e-12;
        if (!one_hot) mixed[M++] = i;
    }
    *err = 0;
    if (st == SVP_OK && M > 0) {
        for (int k = 0; k < K && st == SVP_OK; k++)
            st = compact_psf_kernel(c, t.psf[k], 0.5 * (c->width - 1), 0.5 * (c->height - 1),
                                    ek + (size_t)k * mc);
        const int P = M < PROBES ? (int)M : PROBES;
        for (int p = 0; p < P; p++) {
            const size_t i = mixed[(size_t)((p + 0.5) * M / P)];
            mixed[p] = i; /* the probe's pixel (p <= its index in mixed) */
            px[p] = (double)(i % (size_t)c->width);
            py[p] = (double)(i / (size_t)c->width);
        }
        if (st == SVP_OK) st = compact_kernels(c, P, px, py, pk);
        double e2 = 0;
        for (int p = 0; p < P && st == SVP_OK; p++) {
            double *kp = pk + (size_t)p * mc;
            for (int k = 0; k < K; k++) {
                const double w = t.weight[(size_t)k * n + mixed[p]];
                const double *e = ek + (size_t)k * mc;
                for (size_t i = 0; i < mc; i++) kp[i] -= w * e[i];
            }
            e2 += dotp(kp, kp, mc);
        }
        if (st == SVP_OK) *err = sqrt((double)M / n * (e2 / P) / (c->norm2 / c->probes));
    }
    if (keep && st == SVP_OK)
        *keep = t;
    else
        svp_region_terms_free(&t);
    free(mixed);
    free(ek);
    free(px);
    free(py);
    free(pk);
    return st;
}

/* Kernel radii and support as svp_variant_begin chooses them. */
static void radii(const svp_psf_field *field, int width, int height, double support, int *rx,
                  int *ry)
{
    const double sup = support > 0 ? support : svp_psf_field_base(field)->support;
    *rx = width - 1;
    *ry = height - 1;
    if (sup > 0) *rx = *ry = (int)ceil(sup);
}

double svp_variant_memory_limit(const svp_variant_options *o)
{
    if (o->max_memory > 0) return o->max_memory;
    const long pages = sysconf(_SC_PHYS_PAGES), page = sysconf(_SC_PAGESIZE);
    return pages > 0 && page > 0 ? (double)pages * page : INFINITY;
}

/* The geometry a candidate's cost depends on: the frame's and the kernel's pixels, the image's,
 * the radii, and one FFT's cost in pixel work, f = 5 N log2 N (1 + N / (N + 2^19)) (cost_of). */
typedef struct cost_geom {
    double frame_px, kernel_px, image_px, fft;
    int rx, ry;
} cost_geom;

static svp_status cost_geometry(const svp_psf_field *field, int width, int height,
                                svp_boundary boundary, double support, cost_geom *g)
{
    int nx, ny;
    radii(field, width, height, support, &g->rx, &g->ry);
    SVP_CHECK(svp_frame_size(width, height, g->rx, g->ry, boundary, &nx, &ny));
    g->frame_px = (double)nx * ny;
    g->kernel_px = (2.0 * g->rx + 1) * (2.0 * g->ry + 1);
    g->image_px = (double)width * height;
    g->fft = 5.0 * g->frame_px * log2(g->frame_px > 2 ? g->frame_px : 2) *
             (1 + g->frame_px / (g->frame_px + 524288.0));
    return SVP_OK;
}

/* The pixels of the fold the Gram build renders of sx x sy samples (variant.c, gram_layout):
 * the lowest svp_psf_symmetry of the samples' PSFs (half: point symmetry only). */
static double fold_pixels(const svp_psf_field *field, int width, int height, int sx, int sy,
                          const cost_geom *g, int half)
{
    int sym = half ? 0 : 2;
    for (int j = 0; j < sx * sy && sym > 0; j++) {
        svp_psf p;
        if (svp_psf_field_at(field, node_at(j % sx, sx, width), node_at(j / sx, sy, height), &p) !=
            SVP_OK)
            sym = 0;
        else if (svp_psf_symmetry(&p) < sym)
            sym = svp_psf_symmetry(&p);
    }
    if (sym == 2 && g->rx != g->ry) sym = 1;
    const double hr = g->ry + 1.0, kw = 2.0 * g->rx + 1;
    if (sym == 0) return hr * kw;
    if (sym == 1) return hr * (g->rx + 1.0);
    /* rows t = 0 .. ry of rx + 1 − t pixels */
    return hr * (g->rx + 1.0) - 0.5 * g->ry * hr;
}

/* FFT-equivalents of a candidate (one real FFT of the frame = 1): *build once, *pair per
 * H + Hᵀ pair. repr: tent (K nodes), low rank (K terms from S samples, `fold` pixels of each
 * sample rendered by the Gram build) or regions (K kernels; blend: the weight maps' smoothing
 * window, 0 for a sharp map). Calibrated on CPU time, 1 thread (tools/bench/bench_variant
 * cost: whole-field Moffat maps, zero boundary, 128², 256², 512², low rank also at 1024²;
 * docs/model.md §9 gives the figures). A pair measured 0.8–1.1 x 2 (K + 1) FFTs for tent, low
 * rank and regions alike. A build's work is per pixel (renders, Gram products, placing on the
 * frame), while the FFT's cost per pixel grows with log2 N and, measured, about twice as fast
 * once the frame leaves the cache (1.8, 2.6, 5.3, 5.0 ns a pixel for frames of 256², 512²,
 * 1024², 2048²): pixel work w costs w / f FFTs, f = 5 N log2 N (1 + N / (N + 2^19)), N the
 * frame's pixels. Terms: C_F N / f fixed (frame, tables); per tent node or region kernel
 * 1 + C_K m / f (its whole kernel of m pixels rendered, one FFT); per low-rank term
 * 1 + C_U m / f (unfolded, placed, one FFT); per low-rank build (C_R S + C_G S²) n / f over the
 * n fold pixels (two renders of each sample's fold, the Gram matrix's products); per blended
 * region map C_S K P w / f (the separable smoothing of K weight maps of P pixels, window w).
 * Fitted by least squares in the ratio: model / measured build 0.56–1.6 over 48 builds, fold
 * and half (point symmetry only) alike; the octant fold's at 128² and 256² 0.61–0.76. The
 * model before (1.5 FFTs a sample, the Gram's S² m at 2.5 / f over the whole kernel, 2 FFTs a
 * node) overestimated the fold build 5–14 x and underestimated the tent's 2.5–4 x. */
enum { C_F = 341, C_K = 609, C_U = 708, C_R = 227, C_S = 256 };
static const double C_G = 2.27;

static void cost_of(svp_variant_repr repr, int K, int S, double fold, double blend,
                    const cost_geom *g, double *build, double *pair)
{
    *pair = 2.0 * (K + 1);
    double b = C_F * g->frame_px;
    if (repr == SVP_VARIANT_LOWRANK)
        b += K * C_U * g->kernel_px + (C_R * S + C_G * (double)S * S) * fold;
    else
        b += K * C_K * g->kernel_px + C_S * K * g->image_px * blend;
    *build = K + b / g->fft;
}

/* The smoothing window of a region map's weight maps (psf/field.c: σ = transition / 2.5631,
 * radius ⌈4σ⌉); 0 for a sharp map. */
static double blend_window(const svp_psf_field *field)
{
    if (svp_psf_field_get_kind(field) != SVP_FIELD_REGIONS || !(field->transition > 0)) return 0;
    int r = (int)ceil(4.0 * field->transition / 2.5631);
    if (r < 1) r = 1;
    return 2.0 * r + 1;
}

svp_status svp_variant_cost(const svp_psf_field *field, int width, int height,
                            svp_boundary boundary, const svp_variant_options *o, int half,
                            double *build, double *pair)
{
    if (!field || !o || !build || !pair)
        return svp_fail(SVP_ERR_INVALID, "svp_variant_cost: NULL argument");
    cost_geom g;
    SVP_CHECK(cost_geometry(field, width, height, boundary, o->support, &g));
    if (o->representation == SVP_VARIANT_REGIONS) {
        SVP_CHECK(svp_region_check(field));
        cost_of(SVP_VARIANT_REGIONS, svp_region_count(field), 0, 0, blend_window(field), &g, build,
                pair);
    } else if (o->representation == SVP_VARIANT_TENT) {
        const int gx = o->grid_x < width ? o->grid_x : width;
        const int gy = o->grid_y < height ? o->grid_y : height;
        cost_of(SVP_VARIANT_TENT, gx * gy, 0, 0, 0, &g, build, pair);
    } else if (o->representation == SVP_VARIANT_LOWRANK) {
        const int sx = o->samples_x < width ? o->samples_x : width;
        const int sy = o->samples_y < height ? o->samples_y : height;
        cost_of(SVP_VARIANT_LOWRANK, o->rank, sx * sy,
                fold_pixels(field, width, height, sx, sy, &g, half), 0, &g, build, pair);
    } else
        return svp_fail(SVP_ERR_INVALID,
                        "svp_variant_cost: the options must force tent, low rank or regions");
    return SVP_OK;
}

svp_status svp_variant_choose(const svp_psf_field *field, int width, int height,
                              svp_boundary boundary, const svp_variant_options *o,
                              svp_variant_options *chosen, svp_variant_info *info,
                              svp_region_terms *terms)
{
    if (terms) memset(terms, 0, sizeof *terms);
    const double t0 = omp_get_wtime();
    *chosen = *o;
    memset(info, 0, sizeof *info);
    if (!(o->tolerance > 0) || !isfinite(o->tolerance))
        return svp_fail(SVP_ERR_INVALID, "operator tolerance must be > 0, got %g", o->tolerance);
    cost_geom geo;
    SVP_CHECK(cost_geometry(field, width, height, boundary, o->support, &geo));
    const int rx = geo.rx, ry = geo.ry;
    const double limit = svp_variant_memory_limit(o);
    const double apps = o->applications > 0 ? o->applications : 50;
    est_ctx c;
    SVP_CHECK(est_init(&c, field, width, height, o->support));
    svp_status st = SVP_OK;
    double best_cost = INFINITY, best_err = INFINITY, fallback_err = INFINITY;
    svp_variant_options best = *o, fallback = *o;
    int n = 0;
    /* every candidate, for the fallback: the cheapest within 1.25 x the smallest error */
    enum { MAX_CAND = 256 };
    svp_variant_options cands[MAX_CAND];
    double cerr[MAX_CAND], ccost[MAX_CAND];
    int nc = 0;
    for (size_t i = 0; i < sizeof tent_grids / sizeof *tent_grids && st == SVP_OK; i++) {
        const int gx = tent_grids[i] < width ? tent_grids[i] : width;
        const int gy = tent_grids[i] < height ? tent_grids[i] : height;
        if (i > 0 && gx == (tent_grids[i - 1] < width ? tent_grids[i - 1] : width) &&
            gy == (tent_grids[i - 1] < height ? tent_grids[i - 1] : height))
            continue;
        const double bytes =
            (double)svp_variant_peak_bytes(width, height, boundary, 0, gx * gy, 0, rx, ry);
        if (bytes > limit) break; /* larger grids need more */
        double err;
        st = est_tent(&c, gx, gy, &err);
        if (st != SVP_OK) break;
        n++;
        double build, pair;
        cost_of(SVP_VARIANT_TENT, gx * gy, 0, 0, 0, &geo, &build, &pair);
        const double cost = build + apps * pair;
        svp_variant_options cand = *o;
        cand.representation = SVP_VARIANT_TENT;
        cand.grid_x = gx;
        cand.grid_y = gy;
        if (err <= o->tolerance && cost < best_cost) {
            best_cost = cost;
            best_err = err;
            best = cand;
        }
        if (nc < MAX_CAND) cands[nc] = cand, cerr[nc] = err, ccost[nc++] = cost;
        if (err <= o->tolerance) break; /* finer grids cost more */
    }
    for (size_t i = 0; i < sizeof lowrank_samples / sizeof *lowrank_samples && st == SVP_OK; i++) {
        const int sx = lowrank_samples[i] < width ? lowrank_samples[i] : width;
        const int sy = lowrank_samples[i] < height ? lowrank_samples[i] : height;
        const int S = sx * sy, nr = S + 1 < RANK_MAX ? S + 1 : RANK_MAX;
        double err[RANK_MAX];
        st = est_lowrank(&c, sx, sy, nr, err);
        if (st != SVP_OK) break;
        const double fold = fold_pixels(field, width, height, sx, sy, &geo, 0);
        for (int R = 1; R <= nr && R <= S; R++) {
            const double bytes =
                (double)svp_variant_peak_bytes(width, height, boundary, 1, R, S, rx, ry);
            if (bytes > limit) break;
            n++;
            double build, pair;
            cost_of(SVP_VARIANT_LOWRANK, R, S, fold, 0, &geo, &build, &pair);
            const double cost = build + apps * pair;
            svp_variant_options cand = *o;
            cand.representation = SVP_VARIANT_LOWRANK;
            cand.samples_x = sx;
            cand.samples_y = sy;
            cand.rank = R;
            cand.lowrank_mean = 1;
            if (err[R - 1] <= o->tolerance && cost < best_cost) {
                best_cost = cost;
                best_err = err[R - 1];
                best = cand;
            }
            if (nc < MAX_CAND) cands[nc] = cand, cerr[nc] = err[R - 1], ccost[nc++] = cost;
        }
    }
    if (st == SVP_OK && svp_psf_field_get_kind(field) == SVP_FIELD_REGIONS) {
        /* one term per used label, built like a tent node */
        const int K = svp_region_count(field);
        const double bytes = (double)svp_region_peak_bytes(width, height, boundary, K, rx, ry);
        double err;
        if (bytes <= limit) st = est_regions(&c, terms, &err);
        if (bytes <= limit && st == SVP_OK) {
            n++;
            double build, pair;
            cost_of(SVP_VARIANT_REGIONS, K, 0, 0, blend_window(field), &geo, &build, &pair);
            const double cost = build + apps * pair;
            svp_variant_options cand = *o;
            cand.representation = SVP_VARIANT_REGIONS;
            if (err <= o->tolerance && cost < best_cost) {
                best_cost = cost;
                best_err = err;
                best = cand;
            }
            if (nc < MAX_CAND) cands[nc] = cand, cerr[nc] = err, ccost[nc++] = cost;
        }
    }
    est_release(&c);
    if (st != SVP_OK) return st;
    if (n == 0) {
        if (terms) svp_region_terms_free(terms);
        return svp_fail(SVP_ERR_INVALID,
                        "space-variant operator for %d x %d: even a 1 x 1 tent needs about %.0f "
                        "MB, more than the memory limit of %.0f MB",
                        width, height,
                        svp_variant_peak_bytes(width, height, boundary, 0, 1, 0, rx, ry) / 1e6,
                        limit / 1e6);
    }
    double emin = INFINITY, fcost = INFINITY;
    for (int i = 0; i < nc; i++) emin = fmin(emin, cerr[i]);
    for (int i = 0; i < nc; i++)
        if (cerr[i] <= 1.25 * emin && ccost[i] < fcost) {
            fcost = ccost[i];
            fallback = cands[i];
            fallback_err = cerr[i];
        }
    info->tolerance_met = isfinite(best_cost);
    *chosen = info->tolerance_met ? best : fallback;
    info->estimated_error = info->tolerance_met ? best_err : fallback_err;
    info->tolerance = o->tolerance;
    info->candidates = n;
    info->estimate_seconds = omp_get_wtime() - t0;
    return SVP_OK;
}

svp_status svp_variant_estimate(const svp_psf_field *field, int width, int height,
                                svp_boundary boundary, const svp_variant_options *options,
                                double *error)
{
    (void)boundary;
    if (!field || !error) return svp_fail(SVP_ERR_INVALID, "svp_variant_estimate: NULL argument");
    svp_variant_options o;
    if (options)
        o = *options;
    else
        svp_variant_defaults(&o);
    if (o.representation != SVP_VARIANT_TENT && o.representation != SVP_VARIANT_LOWRANK &&
        o.representation != SVP_VARIANT_REGIONS)
        return svp_fail(SVP_ERR_INVALID,
                        "svp_variant_estimate: the options must force tent, low rank or regions");
    if (o.representation == SVP_VARIANT_REGIONS) SVP_CHECK(svp_region_check(field));
    est_ctx c;
    SVP_CHECK(est_init(&c, field, width, height, o.support));
    svp_status st;
    if (o.representation == SVP_VARIANT_REGIONS) {
        st = est_regions(&c, NULL, error);
    } else if (o.representation == SVP_VARIANT_TENT) {
        st = est_tent(&c, o.grid_x < width ? o.grid_x : width,
                      o.grid_y < height ? o.grid_y : height, error);
    } else {
        const int sx = o.samples_x < width ? o.samples_x : width;
        const int sy = o.samples_y < height ? o.samples_y : height;
        double *err = malloc((size_t)o.rank * sizeof(double));
        st = err ? est_lowrank(&c, sx, sy, o.rank, err)
                 : svp_fail(SVP_ERR_NOMEM, "out of memory for estimates");
        if (st == SVP_OK) *error = err[o.rank - 1];
        free(err);
    }
    est_release(&c);
    return st;
}
