/* Source reconstruction by Fourier inversion (docs/model.md §11): magnetisation from B_z, current
 * density from B_z or from the in-plane field, the in-plane field from B_z, and ∇·J.
 * Frame and signs: include/svpsf.h, section physics (right-handed, rows down, sensor on +z for
 * side = +1); every sign is pinned by tests/test_physics.c against closed forms. */
#include "physics_internal.h"

#include <math.h>
#include <string.h>

void svp_recon_defaults(svp_recon_options *o)
{
    memset(o, 0, sizeof *o);
    svp_sensor_defaults(&o->sensor);
    o->cutoff = 0;
    o->window = 1;
    o->pad = SVP_PAD_TAPER;
    o->pad_factor = 2;
    o->source_thickness_m = 0;
    o->zero_border = 1;
    o->method = SVP_RECON_FOURIER;
    o->max_iterations = 200;
    o->tolerance = 1e-9;
}

static svp_status recon_validate(const svp_recon_options *o)
{
    if (!o) return svp_fail(SVP_ERR_INVALID, "reconstruction options are NULL");
    SVP_CHECK(svp_sensor_validate(&o->sensor));
    if (!(o->cutoff >= 0) || !isfinite(o->cutoff))
        return svp_fail(SVP_ERR_INVALID, "reconstruction cutoff %g rad/m: must be >= 0",
                        o->cutoff);
    if (o->pad != SVP_PAD_TAPER && o->pad != SVP_PAD_MEAN && o->pad != SVP_PAD_NONE)
        return svp_fail(SVP_ERR_INVALID, "reconstruction pad mode %d is unknown", (int)o->pad);
    if (o->pad != SVP_PAD_NONE && (o->pad_factor < 2 || o->pad_factor > 16))
        return svp_fail(SVP_ERR_INVALID, "reconstruction pad_factor %d: must be in [2, 16]",
                        o->pad_factor);
    if (!(o->source_thickness_m >= 0) || !isfinite(o->source_thickness_m))
        return svp_fail(SVP_ERR_INVALID, "reconstruction source_thickness_m %g: must be >= 0",
                        o->source_thickness_m);
    if (o->method != SVP_RECON_FOURIER && o->method != SVP_RECON_SUPPORT)
        return svp_fail(SVP_ERR_INVALID, "reconstruction method %d is unknown", (int)o->method);
    if (o->method == SVP_RECON_SUPPORT) {
        if (o->max_iterations < 1)
            return svp_fail(SVP_ERR_INVALID,
                            "reconstruction max_iterations %d: must be at least 1",
                            o->max_iterations);
        if (!(o->tolerance > 0 && o->tolerance < 1))
            return svp_fail(SVP_ERR_INVALID, "reconstruction tolerance %g: must be in (0, 1)",
                            o->tolerance);
        if (o->pad == SVP_PAD_NONE)
            return svp_fail(SVP_ERR_INVALID,
                            "the support reconstruction needs a padded canvas (pad taper or "
                            "mean, pad_factor >= 2): m_z is zero outside the view");
    }
    return SVP_OK;
}

/* The filters differ only in their multiplier of the input spectrum. */
typedef enum recon_kind {
    MAGNETISATION,   /* m_z = W 2 / (μ0 k f g) B_z                */
    JX_FROM_BZ,      /* J_x = +i (ky/k) α W B_z                   */
    JY_FROM_BZ,      /* J_y = −i (kx/k) α W B_z                   */
    JY_FROM_BX,      /* J_y = s α W B_x                           */
    JX_FROM_BY,      /* J_x = −s α W B_y                          */
    BX_FROM_BZ,      /* B_x = −i s (kx/k) W B_z                   */
    BY_FROM_BZ       /* B_y = −i s (ky/k) W B_z                   */
} recon_kind;

typedef struct recon_filter {
    double h, t_nv, t_src, s, kc;
    int window;
} recon_filter;

static double complex multiplier(const recon_filter *f, recon_kind kind, double kx, double ky,
                                 int odd_ok)
{
    double k = hypot(kx, ky);
    double w = 1;
    if (f->window) {
        if (k >= f->kc) return 0;
        w = 0.5 * (1 + cos(M_PI * k / f->kc));
    }
    if (kind == BX_FROM_BZ || kind == BY_FROM_BZ) {
        if (k == 0 || !odd_ok) return 0;
        return -I * f->s * (kind == BX_FROM_BZ ? kx : ky) / k * w;
    }
    /* α = 2 / (μ0 f(k)); without a window the gain is dropped where it would overflow */
    if (k * f->h > 700) return 0;
    double alpha = 2 / (SVP_MU0 * svp_layer_decay(k, f->h, f->t_nv));
    switch (kind) {
    case MAGNETISATION: {
        if (k == 0) return 0; /* the mean is lost */
        double thick = f->t_src > 0 ? -expm1(-k * f->t_src) / (k * f->t_src) : 1.0;
        return w * alpha / (k * thick);
    }
    case JX_FROM_BZ: return (k == 0 || !odd_ok) ? 0 : I * (ky / k) * alpha * w;
    case JY_FROM_BZ: return (k == 0 || !odd_ok) ? 0 : -I * (kx / k) * alpha * w;
    case JY_FROM_BX: return f->s * alpha * w;
    case JX_FROM_BY: return -f->s * alpha * w;
    default: return 0;
    }
}

/* The lowest frequency of the padded map must pass the filter: else every component but the
 * mean is removed and the result is 0 (or uniform) whatever the map holds. */
static svp_status recon_check_passband(const recon_filter *f, const svp_canvas *c,
                                       const char *in_name)
{
    const double kmin = fmin(c->nx > 1 ? c->dkx : INFINITY, c->ny > 1 ? c->dky : INFINITY);
    if (!isfinite(kmin)) return SVP_OK;
    if (f->window && kmin >= f->kc)
        return svp_fail(SVP_ERR_INVALID,
                        "reconstruction of %s: the window's cut-off k_c = %.3g rad/um lies below "
                        "the lowest frequency of the %d x %d padded map (%.3g rad/um), so nothing "
                        "but the mean would pass; raise k_c (by default 2 pi / standoff: is the "
                        "standoff of %.4g nm right?) or give a larger view",
                        in_name, f->kc * 1e-6, c->nx, c->ny, kmin * 1e-6, f->h * 1e9);
    if (kmin * f->h > 700)
        return svp_fail(SVP_ERR_INVALID,
                        "reconstruction of %s: the gain e^(k h) at the lowest frequency of the "
                        "map (%.3g rad/um, standoff %.4g nm) exceeds e^700, so nothing but the "
                        "mean would pass; check the standoff and the pixel size",
                        in_name, kmin * 1e-6, f->h * 1e9);
    return SVP_OK;
}

/* The checks every reconstruction makes of its options, input map (a B_z map needs an
 * interior: at least 3 x 3) and outputs (either may be NULL), and the filter they give. */
static svp_status recon_input(const svp_image *in, const char *in_name,
                              const svp_recon_options *o, int from_bz, const svp_image *out_a,
                              const svp_image *out_b, recon_filter *f)
{
    SVP_CHECK(recon_validate(o));
    if (!in) return svp_fail(SVP_ERR_INVALID, "reconstruction input %s is NULL", in_name);
    if (out_a) SVP_CHECK(svp_image_same_size(in, out_a, in_name, "output"));
    if (out_b) SVP_CHECK(svp_image_same_size(in, out_b, in_name, "output"));
    if (svp_image_count_nonfinite(in))
        return svp_fail(SVP_ERR_INVALID, "reconstruction input %s has NaN or Inf pixels",
                        in_name);
    if (from_bz && (in->width < 3 || in->height < 3))
        return svp_fail(SVP_ERR_INVALID,
                        "reconstruction input %s is %d x %d pixels: a reconstruction "
                        "from B_z needs a map of at least 3 x 3",
                        in_name, in->width, in->height);
    *f = (recon_filter){.h = o->sensor.standoff_m,
                        .t_nv = o->sensor.nv_thickness_m,
                        .t_src = o->source_thickness_m,
                        .s = o->sensor.side,
                        .kc = o->cutoff > 0 ? o->cutoff : 2 * M_PI / o->sensor.standoff_m,
                        .window = o->window};
    return SVP_OK;
}

/* Applies up to two filters to one input map. */
static svp_status recon_run(const svp_image *in, const char *in_name,
                            const svp_recon_options *o, recon_kind kind_a, svp_image *out_a,
                            recon_kind kind_b, svp_image *out_b)
{
    if (o && kind_a != MAGNETISATION && o->method != SVP_RECON_FOURIER)
        return svp_fail(SVP_ERR_INVALID,
                        "the support reconstruction finds magnetisation only; current density "
                        "and the in-plane field use the Fourier method");
    recon_filter f;
    SVP_CHECK(recon_input(in, in_name, o, kind_a != JY_FROM_BX && kind_a != JX_FROM_BY, out_a,
                          out_b, &f));
    svp_canvas c;
    int pad_factor = o->pad == SVP_PAD_NONE ? 1 : o->pad_factor;
    SVP_CHECK(svp_canvas_init(&c, in->width, in->height, pad_factor, o->sensor.pixel_m));
    svp_status pass = recon_check_passband(&f, &c, in_name);
    if (pass != SVP_OK) {
        svp_canvas_release(&c);
        return pass;
    }
    svp_status st =
        svp_canvas_load(&c, in, o->pad == SVP_PAD_TAPER ? SVP_FILL_TAPER : SVP_FILL_MEAN);
    const recon_kind kinds[2] = {kind_a, kind_b};
    svp_image *outs[2] = {out_a, out_b};
    for (int q = 0; q < 2 && st == SVP_OK; q++) {
        if (!outs[q]) continue;
        const recon_kind kind = kinds[q];
#pragma omp parallel for schedule(static)
        for (int j = 0; j < c.ny; j++) {
            int oky, okx;
            double ky = svp_canvas_ky(&c, j, &oky);
            for (int i = 0; i < c.ncx; i++) {
                double kx = svp_canvas_kx(&c, i, &okx);
                int odd_ok = (kind == JX_FROM_BZ || kind == BY_FROM_BZ) ? oky : okx;
                size_t idx = (size_t)j * c.ncx + i;
                c.work[idx] = c.spec[idx] * multiplier(&f, kind, kx, ky, odd_ok);
            }
        }
        svp_canvas_emit(&c, outs[q]);
    }
    svp_canvas_release(&c);
    return st;
}

/* ---- magnetisation on the view (SVP_RECON_SUPPORT) ------------------------------------------- */

/* A: m_z on the view (uniform over each pixel, zero outside the view) to B_z at the view's
 * pixel centres: a linear (not periodic) convolution with the field of one pixel, in closed
 * form (pixel_kernel), applied on the zero-padded canvas, which holds every offset the view
 * can have without wrapping. (The transfer function (15) sampled on the canvas would convolve
 * periodically: every source would also act through its images one canvas away, which the data
 * do not contain, and least squares then bends m_z's smooth modes to explain them: a 1.7 % bowl
 * on tests/test_physics.c's flake, 0.2 % with twice the canvas.) The kernel is even, so its
 * spectrum is real and Aᵀ is the same operation; AᵀA is two. The preconditioner applies
 * 1/(G² + ε) with G the transfer function of (15) (the Fourier inverse; ε = G² at the canvas's
 * lowest frequency, as G vanishes at k = 0). */
typedef struct support_solver {
    svp_canvas c;
    double *g;              /* per spectrum bin: the pixel kernel's spectrum (real) */
    double *pinv, *win;     /* per bin: 1/(G² + ε) with G of (15), the window (NULL: none) */
    double *scratch;        /* svp_dot's products */
    size_t n;
    double pixel_m;
    int gexp;               /* the kernel's spectrum is stored times 2^−gexp (support_tables) */
} support_solver;

/* out = crop(F⁻¹[mult · F[pad(in)]]); in and out may be the same. */
static svp_status support_apply(support_solver *s, const double *mult, double *in, double *out)
{
    svp_image img_in = {s->c.w, s->c.h, in}, img_out = {s->c.w, s->c.h, out};
    SVP_CHECK(svp_canvas_load(&s->c, &img_in, SVP_FILL_ZERO));
    const size_t nbins = (size_t)s->c.ny * s->c.ncx;
#pragma omp parallel for schedule(static)
    for (size_t b = 0; b < nbins; b++) s->c.work[b] = s->c.spec[b] * mult[b];
    svp_canvas_emit(&s->c, &img_out);
    return SVP_OK;
}

/* AᵀA in, into out (tmp: scratch of n) */
static svp_status support_normal(support_solver *s, double *in, double *tmp, double *out)
{
    SVP_CHECK(support_apply(s, s->g, in, tmp));
    return support_apply(s, s->g, tmp, out);
}

/* B_z (T per A of areal moment) at the centre of pixel (0, 0), height z above the sources,
 * from a uniformly magnetised square pixel (side px) centred dx, dy pixels away: the thin
 * rectangle's closed form (a dipole sheet: φ = m Ω / 4π, H_z = −∂φ/∂z, summed over the corners
 * with signs (−1)^(i+j)). */
static double pixel_bz(double px, int dx, int dy, double z)
{
    const double xs[2] = {(dx - 0.5) * px, (dx + 0.5) * px};
    const double ys[2] = {(dy - 0.5) * px, (dy + 0.5) * px};
    double hz = 0;
    for (int i = 0; i < 2; i++)
        for (int j = 0; j < 2; j++) {
            const double X = xs[i], Y = ys[j], r = sqrt(X * X + Y * Y + z * z);
            const double term = X * Y * (r * r + z * z) / (r * (X * X + z * z) * (Y * Y + z * z));
            hz += i == j ? term : -term;
        }
    return SVP_MU0 / (4 * M_PI) * hz;
}

/* Gauss–Legendre nodes and weights on [-1, 1], 8 points (exact for polynomials of degree 15) */
static const double GL_X[8] = {-0.9602898564975363, -0.7966664774136267, -0.5255324099163290,
                               -0.1834346424956498, 0.1834346424956498,  0.5255324099163290,
                               0.7966664774136267,  0.9602898564975363};
static const double GL_W[8] = {0.1012285362903763, 0.2223810344533745, 0.3137066458778873,
                               0.3626837833783620, 0.3626837833783620, 0.3137066458778873,
                               0.2223810344533745, 0.1012285362903763};

/* The pixel kernel averaged over the NV layer's depth [h − t_nv/2, h + t_nv/2] and the source's
 * thickness (standoff h + [0, t_src]), as f(k) and the thickness factor of (15) average e^(−kz). */
static double pixel_kernel(const recon_filter *f, double px, int dx, int dy)
{
    const int nv = f->t_nv > 0 ? 8 : 1, ns = f->t_src > 0 ? 8 : 1;
    double sum = 0;
    for (int a = 0; a < nv; a++)
        for (int b = 0; b < ns; b++) {
            double z = f->h, w = 1;
            if (nv > 1) z += 0.5 * f->t_nv * GL_X[a], w *= 0.5 * GL_W[a];
            if (ns > 1) z += 0.5 * f->t_src * (1 + GL_X[b]), w *= 0.5 * GL_W[b];
            sum += w * pixel_bz(px, dx, dy, z);
        }
    return sum;
}

/* s->g: the spectrum on the solver's canvas of the pixel kernel at the offsets the view can
 * hold (|dx| < w, |dy| < h; even in both), i.e. of A's linear convolution (support_solver). */
static void support_linear_kernel(support_solver *s, const recon_filter *f)
{
    svp_canvas *c = &s->c;
    memset(c->real, 0, (size_t)c->nx * c->ny * sizeof(double));
#pragma omp parallel for schedule(static)
    for (int dy = 0; dy < c->h; dy++) {
        for (int dx = 0; dx < c->w; dx++) {
            const double k = pixel_kernel(f, s->pixel_m, dx, dy);
            const int xs[2] = {dx, (c->nx - dx) % c->nx}, ys[2] = {dy, (c->ny - dy) % c->ny};
            for (int a = 0; a < 2; a++)
                for (int b = 0; b < 2; b++) c->real[(size_t)ys[a] * c->nx + xs[b]] = k;
        }
    }
    svp_fft_forward(c->plan, c->real, c->spec);
    const size_t nbins = (size_t)c->ny * c->ncx;
    for (size_t b = 0; b < nbins; b++) s->g[b] = creal(c->spec[b]);
}

static svp_status support_tables(support_solver *s, const recon_filter *f)
{
    const svp_canvas *c = &s->c;
    const size_t nbins = (size_t)c->ny * c->ncx;
    s->g = svp_alloc(nbins * sizeof(double));
    s->pinv = svp_alloc(nbins * sizeof(double));
    s->win = f->window ? svp_alloc(nbins * sizeof(double)) : NULL;
    s->scratch = svp_alloc(s->n * sizeof(double));
    if (!s->g || !s->pinv || (f->window && !s->win) || !s->scratch)
        return svp_fail(SVP_ERR_NOMEM, "out of memory for the support reconstruction's tables");
    /* the preconditioner from G(k) = (μ0/2) k f(k) (thick), the inverse of the Fourier
     * method's multiplier without its window */
    const double kmin = fmin(c->nx > 1 ? c->dkx : INFINITY, c->ny > 1 ? c->dky : INFINITY);
    const double thick_min =
        f->t_src > 0 ? -expm1(-kmin * f->t_src) / (kmin * f->t_src) : 1.0;
    const double gmin = 0.5 * SVP_MU0 * kmin * svp_layer_decay(kmin, f->h, f->t_nv) * thick_min;
    const double eps = gmin * gmin;
#pragma omp parallel for schedule(static)
    for (int j = 0; j < c->ny; j++) {
        int ok;
        double ky = svp_canvas_ky(c, j, &ok);
        for (int i = 0; i < c->ncx; i++) {
            double k = hypot(svp_canvas_kx(c, i, &ok), ky);
            double thick = f->t_src > 0 && k > 0 ? -expm1(-k * f->t_src) / (k * f->t_src) : 1.0;
            double g = 0.5 * SVP_MU0 * k * svp_layer_decay(k, f->h, f->t_nv) * thick;
            size_t b = (size_t)j * c->ncx + i;
            s->pinv[b] = 1 / (g * g + eps);
            if (s->win) s->win[b] = k >= f->kc ? 0 : 0.5 * (1 + cos(M_PI * k / f->kc));
        }
    }
    support_linear_kernel(s, f);
    /* A scaled by a power of two to a largest |spectrum| in [1, 2) (P by its square, so that
     * P AᵀA keeps its scale; exact, so the iterates are the same bits, only scaled): the CG's
     * sums of squares then stay in range whatever the pixel size and standoff */
    double gmax = 0;
    for (size_t b = 0; b < nbins; b++) gmax = fmax(gmax, fabs(s->g[b]));
    if (!(gmax > 0 && isfinite(gmax)))
        return svp_fail(SVP_ERR_INVALID,
                        "support reconstruction of m_z: the pixel kernel's spectrum is %g at "
                        "most: pixel size or standoff out of range",
                        gmax);
    s->gexp = ilogb(gmax);
    for (size_t b = 0; b < nbins; b++) {
        s->g[b] = ldexp(s->g[b], -s->gexp);
        s->pinv[b] = ldexp(s->pinv[b], 2 * s->gexp);
    }
    return SVP_OK;
}

/* Preconditioned conjugate gradients on AᵀA m = Aᵀ B_z from the preconditioned start
 * P Aᵀ B_z (the Fourier inverse of the zero-padded map). */
static svp_status support_solve(support_solver *s, const svp_recon_options *o, double *b,
                                double *x, double *r, double *z, double *p, double *q,
                                svp_recon_report *report)
{
    const size_t n = s->n;
    SVP_CHECK(support_apply(s, s->g, b, b)); /* b ← Aᵀ B_z */
    const double bnorm = sqrt(svp_dot(b, b, s->scratch, n));
    if (bnorm == 0) {
        memset(x, 0, n * sizeof(double));
        return SVP_OK;
    }
    SVP_CHECK(support_apply(s, s->pinv, b, x));
    SVP_CHECK(support_normal(s, x, q, r));
    for (size_t i = 0; i < n; i++) r[i] = b[i] - r[i];
    SVP_CHECK(support_apply(s, s->pinv, r, z));
    memcpy(p, z, n * sizeof(double));
    double rz = svp_dot(r, z, s->scratch, n);
    double rel = sqrt(svp_dot(r, r, s->scratch, n)) / bnorm;
    int it = 0;
    while (rel > o->tolerance && it < o->max_iterations) {
        SVP_CHECK(support_normal(s, p, z, q)); /* q = AᵀA p (z as scratch) */
        const double pq = svp_dot(p, q, s->scratch, n);
        if (!(pq > 0)) break; /* exact solution, or round-off: no descent left */
        const double a = rz / pq;
        for (size_t i = 0; i < n; i++) {
            x[i] += a * p[i];
            r[i] -= a * q[i];
        }
        it++;
        rel = sqrt(svp_dot(r, r, s->scratch, n)) / bnorm;
        if (rel <= o->tolerance) break;
        SVP_CHECK(support_apply(s, s->pinv, r, z));
        const double rz_new = svp_dot(r, z, s->scratch, n);
        const double beta = rz_new / rz;
        rz = rz_new;
        for (size_t i = 0; i < n; i++) p[i] = z[i] + beta * p[i];
    }
    if (report) {
        report->iterations = it;
        report->residual = rel;
    }
    if (rel > o->tolerance)
        return svp_fail(SVP_ERR_DOUBTFUL,
                        "support reconstruction of m_z: conjugate gradients stopped after %d "
                        "steps with relative residual %.3g above the tolerance %.3g; raise "
                        "max_iterations or use the Fourier method",
                        it, rel, o->tolerance);
    return SVP_OK;
}

static svp_status recon_support(const svp_image *bz, const svp_recon_options *o, svp_image *mz,
                                svp_recon_report *report)
{
    recon_filter f;
    SVP_CHECK(recon_input(bz, "bz", o, 1, mz, NULL, &f));
    support_solver s = {.n = (size_t)bz->width * bz->height, .pixel_m = o->sensor.pixel_m};
    SVP_CHECK(svp_canvas_init(&s.c, bz->width, bz->height, o->pad_factor, o->sensor.pixel_m));
    svp_status st = recon_check_passband(&f, &s.c, "bz");
    double *v[5] = {NULL};
    if (st == SVP_OK) st = support_tables(&s, &f);
    for (int i = 0; i < 5 && st == SVP_OK; i++)
        if (!(v[i] = svp_alloc(s.n * sizeof(double))))
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for the support reconstruction");
    if (st == SVP_OK) {
        /* B_z scaled by a power of two to a largest |value| in [1, 2) (exact, and ldexp keeps
         * subnormal values), so that the solve's sums of squares neither underflow nor
         * overflow: the method is linear, and the scale is undone on m_z */
        double bmax = 0;
        for (size_t i = 0; i < s.n; i++) bmax = fmax(bmax, fabs(bz->data[i]));
        const int e = bmax > 0 ? ilogb(bmax) : 0;
        for (size_t i = 0; i < s.n; i++) v[0][i] = ldexp(bz->data[i], -e);
        st = support_solve(&s, o, v[0], mz->data, v[1], v[2], v[3], v[4], report);
        /* the window as in the Fourier method, also on an iterate in doubt */
        if ((st == SVP_OK || st == SVP_ERR_DOUBTFUL) && s.win) {
            svp_status sw = support_apply(&s, s.win, mz->data, mz->data);
            if (sw != SVP_OK) st = sw;
        }
        if (st == SVP_OK || st == SVP_ERR_DOUBTFUL)
            for (size_t i = 0; i < s.n; i++) mz->data[i] = ldexp(mz->data[i], e - s.gexp);
    }
    for (int i = 0; i < 5; i++) svp_free(v[i]);
    svp_free(s.g);
    svp_free(s.pinv);
    svp_free(s.win);
    svp_free(s.scratch);
    svp_canvas_release(&s.c);
    return st;
}

svp_status svp_reconstruct_magnetisation_report(const svp_image *bz,
                                                const svp_recon_options *options, svp_image *mz,
                                                svp_recon_report *report)
{
    if (report) memset(report, 0, sizeof *report);
    if (!mz) return svp_fail(SVP_ERR_INVALID, "magnetisation output is NULL");
    if (options && options->method == SVP_RECON_SUPPORT)
        return recon_support(bz, options, mz, report);
    SVP_CHECK(recon_run(bz, "bz", options, MAGNETISATION, mz, MAGNETISATION, NULL));
    if (options->zero_border) {
        const int w = mz->width, h = mz->height;
        double sum = 0;
        size_t count = 0;
        for (int j = 0; j < h; j++) {
            int step = (j == 0 || j == h - 1) ? 1 : (w > 1 ? w - 1 : 1);
            for (int i = 0; i < w; i += step) {
                sum += mz->data[(size_t)j * w + i];
                count++;
            }
        }
        const double ring = sum / (double)count;
        const size_t n = (size_t)w * h;
        for (size_t p = 0; p < n; p++) mz->data[p] -= ring;
    }
    return SVP_OK;
}

svp_status svp_reconstruct_magnetisation(const svp_image *bz, const svp_recon_options *options,
                                         svp_image *mz)
{
    return svp_reconstruct_magnetisation_report(bz, options, mz, NULL);
}

svp_status svp_reconstruct_current_from_bz(const svp_image *bz, const svp_recon_options *options,
                                           svp_image *jx, svp_image *jy)
{
    if (!jx && !jy) return svp_fail(SVP_ERR_INVALID, "current from bz: no output requested");
    return recon_run(bz, "bz", options, JX_FROM_BZ, jx, JY_FROM_BZ, jy);
}

svp_status svp_reconstruct_current_from_bxy(const svp_image *bx, const svp_image *by,
                                            const svp_recon_options *options, svp_image *jx,
                                            svp_image *jy)
{
    if (!(bx && jy) && !(by && jx))
        return svp_fail(SVP_ERR_INVALID,
                        "current from bx, by: give bx with jy and/or by with jx");
    if (bx && jy) SVP_CHECK(recon_run(bx, "bx", options, JY_FROM_BX, jy, JY_FROM_BX, NULL));
    if (by && jx) SVP_CHECK(recon_run(by, "by", options, JX_FROM_BY, jx, JX_FROM_BY, NULL));
    return SVP_OK;
}

svp_status svp_inplane_from_bz(const svp_image *bz, const svp_recon_options *options,
                               svp_image *bx, svp_image *by)
{
    if (!bx && !by) return svp_fail(SVP_ERR_INVALID, "in-plane from bz: no output requested");
    return recon_run(bz, "bz", options, BX_FROM_BZ, bx, BY_FROM_BZ, by);
}

svp_status svp_current_divergence(const svp_image *jx, const svp_image *jy, double pixel_m,
                                  svp_image *div)
{
    if (!jx || !jy || !div) return svp_fail(SVP_ERR_INVALID, "divergence: NULL argument");
    if (!(pixel_m > 0) || !isfinite(pixel_m))
        return svp_fail(SVP_ERR_INVALID, "divergence: pixel_m %g must be finite > 0", pixel_m);
    SVP_CHECK(svp_image_same_size(jx, jy, "jx", "jy"));
    SVP_CHECK(svp_image_same_size(jx, div, "jx", "div"));
    const int w = jx->width, h = jx->height;
    const double *restrict ax = jx->data, *restrict ay = jy->data;
    double *restrict d = div->data;
#pragma omp parallel for schedule(static)
    for (int j = 0; j < h; j++) {
        for (int i = 0; i < w; i++) {
            /* central differences inside, one-sided at the borders, 0 along a 1-pixel axis */
            int il = i > 0 ? i - 1 : i, ir = i < w - 1 ? i + 1 : i;
            int jd = j > 0 ? j - 1 : j, ju = j < h - 1 ? j + 1 : j;
            double gx = ir > il ? (ax[(size_t)j * w + ir] - ax[(size_t)j * w + il]) / (ir - il)
                                : 0;
            double gy = ju > jd ? (ay[(size_t)ju * w + i] - ay[(size_t)jd * w + i]) / (ju - jd)
                                : 0;
            d[(size_t)j * w + i] = (gx + gy) / pixel_m;
        }
    }
    return SVP_OK;
}
