/* Tikhonov deconvolution for any operator by preconditioned conjugate gradients on the normal
 * equations (the Wiener–Hunt analogue for space-variant H, docs/model.md §6 and §9):
 *   (Hᵀ M H + λ LᵀL) x = Hᵀ M y,
 * M the 0/1 mask of finite data, L the 5-point Laplacian with H's boundary (a symmetric matrix
 * in all three modes: Dirichlet for zero, Neumann for mirror, circulant for periodic). The
 * preconditioner is the Wiener filter 1 / (|Ĥ_c|² + λ |L̂|²) of the central PSF (core and halo)
 * in a periodic frame of the image size: exact for an invariant periodic H without missing
 * data, where CG then stops after one step at the Wiener–Hunt solution. For a space-variant H
 * |Ĥ_c|² is replaced by the envelope max_s |Ĥ_s|² of PSFs sampled on a 5 x 5 grid. */
#include "restore_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define CG_TOL 1e-10

typedef struct cg_work {
    int w, h;
    svp_boundary boundary;
    double lambda;
    svp_frame pre;      /* periodic frame of the image size with the central OTF */
    double *pre_filter; /* 1 / (nx ny (|Ĥ_c|² + λ |L̂|²)), ny x ncx */
    double *frame_r;
    fftw_complex *frame_c;
    double *mask;       /* 1 where y is finite */
    svp_image *t1, *t2; /* image-sized work */
    double *prod;       /* for deterministic dot products */
} cg_work;

static double dot(cg_work *c, const double *a, const double *b)
{
    return svp_dot(a, b, c->prod, (size_t)c->w * c->h);
}

static inline int neighbour(int t, int size, svp_boundary b)
{
    if (t >= 0 && t < size) return t;
    switch (b) {
    case SVP_BOUNDARY_ZERO: return -1;
    case SVP_BOUNDARY_PERIODIC: return t < 0 ? t + size : t - size;
    default: return t < 0 ? -1 - t : 2 * size - 1 - t; /* half-sample reflection */
    }
}

/* out = L in: 4 in(x) − the four neighbours (boundary as H). */
static void laplacian(const cg_work *c, const double *restrict in, double *restrict out)
{
    const int w = c->w, h = c->h;
#pragma omp parallel for schedule(static) if ((size_t)w * h > SVP_PARALLEL_MIN)
    for (int y = 0; y < h; y++) {
        const int yu = neighbour(y - 1, h, c->boundary), yd = neighbour(y + 1, h, c->boundary);
        for (int x = 0; x < w; x++) {
            const int xl = neighbour(x - 1, w, c->boundary), xr = neighbour(x + 1, w, c->boundary);
            double v = 4.0 * in[(size_t)y * w + x];
            if (xl >= 0) v -= in[(size_t)y * w + xl];
            if (xr >= 0) v -= in[(size_t)y * w + xr];
            if (yu >= 0) v -= in[(size_t)yu * w + x];
            if (yd >= 0) v -= in[(size_t)yd * w + x];
            out[(size_t)y * w + x] = v;
        }
    }
}

/* out = (Hᵀ M H + λ L L) in; uses t1, t2. */
static svp_status normal_apply(svp_blur *b, cg_work *c, const svp_image *in, svp_image *out)
{
    const size_t n = (size_t)c->w * c->h;
    SVP_CHECK(svp_blur_apply(b, in, c->t1));
    double *restrict t1 = c->t1->data;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (size_t i = 0; i < n; i++) t1[i] *= c->mask[i];
    SVP_CHECK(svp_blur_adjoint(b, c->t1, out));
    if (c->lambda > 0) {
        laplacian(c, in->data, c->t1->data);
        laplacian(c, c->t1->data, c->t2->data);
        const double *restrict t2 = c->t2->data;
        double *restrict o = out->data;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
        for (size_t i = 0; i < n; i++) o[i] += c->lambda * t2[i];
    }
    return SVP_OK;
}

static void precondition(cg_work *c, const double *in, double *out)
{
    svp_frame *f = &c->pre;
    const size_t ns = (size_t)f->ny * f->ncx;
    svp_frame_extend(f, in, c->frame_r);
    svp_fft_forward(f->plan, c->frame_r, c->frame_c);
#pragma omp parallel for schedule(static) if (ns > SVP_PARALLEL_MIN / 2)
    for (size_t i = 0; i < ns; i++) c->frame_c[i] *= c->pre_filter[i];
    svp_fft_inverse_unscaled(f->plan, c->frame_c, c->frame_r);
    svp_frame_crop(f, c->frame_r, out);
}

static svp_status setup_preconditioner(const svp_blur *b, cg_work *c)
{
    const svp_image *kernel = b->kernel;
    SVP_CHECK(svp_frame_init(&c->pre, c->w, c->h, 0, 0, SVP_BOUNDARY_PERIODIC));
    svp_frame *f = &c->pre;
    const size_t ns = (size_t)f->ny * f->ncx;
    c->pre_filter = svp_alloc(ns * sizeof(double));
    c->frame_r = svp_alloc((size_t)f->ny * f->nx * sizeof(double));
    c->frame_c = svp_alloc(ns * sizeof(fftw_complex));
    if (!c->pre_filter || !c->frame_r || !c->frame_c)
        return svp_fail(SVP_ERR_NOMEM, "out of memory for the CG preconditioner");
    if (kernel) SVP_CHECK(svp_frame_set_kernel(f, kernel, b->kcx, b->kcy, SVP_BOUNDARY_PERIODIC));
    const double keep = 1.0 - b->halo;
    for (size_t i = 0; i < ns; i++) {
        double complex hk = kernel ? keep * f->otf[i] : 1.0;
        if (i == 0) hk = 1.0; /* the halo keeps the mean: Ĥ(0) = (1 − α) + α */
        c->pre_filter[i] = creal(hk) * creal(hk) + cimag(hk) * cimag(hk);
    }
    if (b->field && kernel) {
        /* Space-variant H: |Ĥ_c|² of the central PSF alone under-estimates HᵀH wherever the
         * PSF elsewhere is sharper, and the preconditioned system's largest eigenvalues then
         * grow as |Ĥ_sharp|² / |Ĥ_c|² (measured: CG diverging to 300 × the peak at λ = 1e-10
         * for FWHM 1.6–4 px). The envelope max_s |Ĥ_s|² over PSFs sampled on a 5 x 5 grid
         * bounds them by about 1 instead. */
        const int ns_x = c->w < 5 ? c->w : 5, ns_y = c->h < 5 ? c->h : 5;
        for (int j = 0; j < ns_y; j++)
            for (int i = 0; i < ns_x; i++) {
                const double px = ns_x > 1 ? (double)i * (c->w - 1) / (ns_x - 1) : 0.5 * (c->w - 1);
                const double py = ns_y > 1 ? (double)j * (c->h - 1) / (ns_y - 1) : 0.5 * (c->h - 1);
                svp_psf psf;
                svp_image *k = NULL;
                SVP_CHECK(svp_blur_psf_at(b, px, py, &psf));
                psf.support = b->psf.support;
                SVP_CHECK(svp_psf_render(&psf, b->kcx, b->kcy, &k));
                svp_status st = svp_frame_set_kernel(f, k, b->kcx, b->kcy, SVP_BOUNDARY_PERIODIC);
                svp_image_free(k);
                SVP_CHECK(st);
                const double keep_s = 1.0 - psf.halo;
                for (size_t q = 1; q < ns; q++) {
                    const double complex hk = keep_s * f->otf[q];
                    const double a2 = creal(hk) * creal(hk) + cimag(hk) * cimag(hk);
                    if (a2 > c->pre_filter[q]) c->pre_filter[q] = a2;
                }
            }
    }
    svp_tikhonov_invert(c->pre_filter, f->nx, f->ny, f->ncx, c->lambda);
    return SVP_OK;
}

svp_status svp_deconv_tikhonov_cg(svp_blur *b, const svp_image *y,
                                  const svp_deconv_options *options, svp_image *x)
{
    const char *what = "svp_deconv_tikhonov_cg";
    SVP_CHECK(svp_deconv_check_images(b, y, x, what));
    svp_deconv_options o;
    if (options)
        o = *options;
    else
        svp_deconv_defaults(&o);
    if (!(o.balance >= 0) || !isfinite(o.balance))
        return svp_fail(SVP_ERR_INVALID, "%s: balance (lambda) must be >= 0, got %g", what,
                        o.balance);
    if (o.iterations < 1)
        return svp_fail(SVP_ERR_INVALID, "%s: iterations must be >= 1, got %d", what, o.iterations);

    const int w = b->width, h = b->height;
    const size_t n = (size_t)w * h;
    cg_work c;
    memset(&c, 0, sizeof c);
    c.w = w;
    c.h = h;
    c.boundary = b->boundary;
    c.lambda = o.balance;
    svp_image *r = NULL, *z = NULL, *p = NULL, *ap = NULL;
    svp_status st = SVP_OK;
    c.mask = svp_alloc(n * sizeof(double));
    c.prod = svp_alloc(n * sizeof(double));
    if (!c.mask || !c.prod) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", what);
        goto cleanup;
    }
    if ((st = svp_image_new(w, h, &c.t1)) != SVP_OK ||
        (st = svp_image_new(w, h, &c.t2)) != SVP_OK || (st = svp_image_new(w, h, &r)) != SVP_OK ||
        (st = svp_image_new(w, h, &z)) != SVP_OK || (st = svp_image_new(w, h, &p)) != SVP_OK ||
        (st = svp_image_new(w, h, &ap)) != SVP_OK)
        goto cleanup;
    if ((st = setup_preconditioner(b, &c)) != SVP_OK) goto cleanup;

    /* b = Hᵀ M y (missing pixels contribute nothing), x0 = 0, r0 = b */
    for (size_t i = 0; i < n; i++) {
        int ok = isfinite(y->data[i]);
        c.mask[i] = ok;
        c.t2->data[i] = ok ? y->data[i] : 0.0;
    }
    if ((st = svp_blur_adjoint(b, c.t2, r)) != SVP_OK) goto cleanup;
    memset(x->data, 0, n * sizeof(double));
    const double bnorm = sqrt(dot(&c, r->data, r->data));
    if (!(bnorm > 0)) goto cleanup; /* no data: x = 0 */
    precondition(&c, r->data, z->data);
    memcpy(p->data, z->data, n * sizeof(double));
    double rz = dot(&c, r->data, z->data);
    int it = 0, converged = 0;
    double res_norm = bnorm;
    for (it = 0; it < o.iterations; it++) {
        if ((st = normal_apply(b, &c, p, ap)) != SVP_OK) goto cleanup;
        const double pap = dot(&c, p->data, ap->data);
        if (!(pap > 0) || !isfinite(pap)) {
            if (!isfinite(pap))
                st = svp_fail(SVP_ERR_NUMERIC,
                              "%s: the normal equations went non-finite at "
                              "iteration %d",
                              what, it + 1);
            converged = 1;
            break; /* pᵀAp = 0: converged exactly */
        }
        const double step = rz / pap;
        double *restrict xd = x->data, *restrict rd = r->data;
        const double *restrict pd = p->data, *restrict apd = ap->data;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
        for (size_t i = 0; i < n; i++) {
            xd[i] += step * pd[i];
            rd[i] -= step * apd[i];
        }
        if ((st = svp_report_progress(o.progress, o.progress_user, (it + 1.0) / o.iterations)) !=
            SVP_OK)
            goto cleanup;
        res_norm = sqrt(dot(&c, rd, rd));
        if (res_norm < CG_TOL * bnorm) {
            it++;
            converged = 1;
            break;
        }
        precondition(&c, rd, z->data);
        const double rz_new = dot(&c, rd, z->data);
        const double beta = rz_new / rz;
        rz = rz_new;
        double *restrict pw = p->data;
        const double *restrict zd = z->data;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
        for (size_t i = 0; i < n; i++) pw[i] = zd[i] + beta * pw[i];
    }
    if (o.report) {
        o.report->cg_steps = it;
        o.report->cg_residual = isfinite(res_norm) ? res_norm / bnorm : INFINITY;
        o.report->cg_capped = !converged;
    }
cleanup:
    svp_frame_release(&c.pre);
    svp_free(c.pre_filter);
    svp_free(c.frame_r);
    svp_free(c.frame_c);
    svp_free(c.mask);
    svp_free(c.prod);
    svp_image_free(c.t1);
    svp_image_free(c.t2);
    svp_image_free(r);
    svp_image_free(z);
    svp_image_free(p);
    svp_image_free(ap);
    return st;
}
