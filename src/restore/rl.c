/* Richardson–Lucy deconvolution (docs/model.md §Deconvolution) for any operator H, through
 * svp_blur_apply / svp_blur_adjoint only:
 *     x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm
 * m the finite-data mask (NaN/Inf pixels of y are missing data), Hᵀm the Bertero–Boccacci
 * boundary weights (with options->boundary_weights = 0 the scalar mean of Hᵀm instead: plain
 * RL, exact for a periodic unit-flux operator without missing data), floor = options->floor ·
 * max(y). Started flat at the mean of the finite data (RL forgets the start's scale after one
 * iteration). In single precision H and Hᵀ transform only deviations from known levels (see
 * rl_level_setup), so their float round-off scales with the deviations. */
#include "restore_internal.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Pointwise loops run in parallel only above this many pixels (below, threads cost more). */
#define PAR_MIN 32768
/* single precision: the levels' fits (rl_fit_levels) run on about this many rows */
#define FIT_ROWS 64
/* auto_stop: stalled when χ² fell by less than STALL_FALL of itself over STALL_SPAN iterations */
#define STALL_SPAN 10
#define STALL_FALL 0.001
/* Boundary weights: a pixel whose Hᵀm is below this fraction of its largest value keeps its
 * start (the light it sends into the data is that small). In single precision Hᵀ's round-off,
 * about 1e-7 of what it transforms, exceeds such a pixel's true Hᵀ(m y / Hx) and Hᵀm: divided
 * by Hᵀm it made a step of any size, and a margin wider than a Gaussian PSF's reach (Hᵀm
 * 1e-12 there) blew up within ten iterations or left errors of 1 % (docs/model.md §6). */
#define SEEN_DOUBLE 1e-12
#define SEEN_SINGLE 1e-6
/* Biggs–Andrews: the extrapolation weight's cap. Repeated with weight α, a step moves the
 * iterate 1 / (1 − α) RL steps' worth; on noisy data α climbs towards 1 as RL starts fitting the
 * noise, and a cap of 0.95 (20 steps' worth) let the lit field's error of 100-photon foreign
 * data stall above plain RL's at 75 iterations; 0.8 (5) keeps noiseless data's speed-up
 * (docs/model.md §6). */
#define ALPHA_MAX 0.8
/* Biggs–Andrews: no extrapolation (α = 0) while the last RL step is below this fraction of the
 * iterate (rms): such a step is converged or round-off (a uniform PL converges at once), its
 * direction float's or double's noise, and an α drawn from it would make single and double
 * precision extrapolate differently */
#define STEP_FLOOR 1e-5

/* x ← x (x / x_prev)^α where x, x_prev > 0 (else, or on overflow, x stays), x_prev ← x. With
 * glibc's vector math (libmvec) pow runs four (AVX2) or two at a time, every pixel through the
 * vector function, padded lanes included, so a pixel's value does not depend on the thread
 * count (each lane is computed on its own; src/psf/model.c does the same). */
#if defined(SVP_HAVE_MVEC) && defined(__x86_64__)
typedef double rl_v2d __attribute__((vector_size(16)));
typedef double rl_v4d __attribute__((vector_size(32)));
rl_v2d _ZGVbN2vv_pow(rl_v2d, rl_v2d);
__attribute__((target("avx2"))) rl_v4d _ZGVdN4vv_pow(rl_v4d, rl_v4d);

/* the ratio x / x_prev of pixel i, 1 where either is 0 */
static inline double ratio_at(const double *x, const double *x_prev, size_t i)
{
    return x[i] > 0 && x_prev[i] > 0 ? x[i] / x_prev[i] : 1.0;
}

/* pixel i from its factor (x / x_prev)^α */
static inline void apply_at(double *restrict x, double *restrict x_prev, size_t i, double f)
{
    const double xk = x[i], z = xk * f;
    if (xk > 0 && x_prev[i] > 0 && z <= DBL_MAX) x[i] = z;
    x_prev[i] = xk;
}

/* pixels [i0, i1) (i0 a multiple of 4) four at a time; its own function with the avx2 target,
 * since an OpenMP region outlined from an avx2 function does not inherit the target (clang) */
__attribute__((target("avx2"))) static void log_chunk_avx2(double *restrict x,
                                                           double *restrict x_prev, size_t i0,
                                                           size_t i1, double alpha)
{
    const rl_v4d a = {alpha, alpha, alpha, alpha};
    for (size_t b = i0; b < i1; b += 4) {
        const size_t lanes = i1 - b < 4 ? i1 - b : 4;
        rl_v4d r = {1.0, 1.0, 1.0, 1.0};
        for (size_t t = 0; t < lanes; t++) r[t] = ratio_at(x, x_prev, b + t);
        const rl_v4d f = _ZGVdN4vv_pow(r, a);
        for (size_t t = 0; t < lanes; t++) apply_at(x, x_prev, b + t, f[t]);
    }
}

/* chunks of LOG_CHUNK pixels (a multiple of 4, so the lanes group as in one pass) */
#define LOG_CHUNK 4096
static void log_extrapolate_avx2(double *restrict x, double *restrict x_prev, size_t n,
                                 double alpha)
{
    const size_t chunks = (n + LOG_CHUNK - 1) / LOG_CHUNK;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t c = 0; c < chunks; c++) {
        const size_t i0 = c * LOG_CHUNK, i1 = i0 + LOG_CHUNK < n ? i0 + LOG_CHUNK : n;
        log_chunk_avx2(x, x_prev, i0, i1, alpha);
    }
}

static void log_extrapolate_sse2(double *restrict x, double *restrict x_prev, size_t n,
                                 double alpha)
{
    const size_t blocks = (n + 1) / 2;
    const rl_v2d a = {alpha, alpha};
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t b = 0; b < blocks; b++) {
        const size_t i0 = 2 * b, lanes = n - i0 < 2 ? n - i0 : 2;
        rl_v2d r = {1.0, 1.0};
        for (size_t t = 0; t < lanes; t++) r[t] = ratio_at(x, x_prev, i0 + t);
        const rl_v2d f = _ZGVbN2vv_pow(r, a);
        for (size_t t = 0; t < lanes; t++) apply_at(x, x_prev, i0 + t, f[t]);
    }
}
#endif

static void log_extrapolate(double *restrict x, double *restrict x_prev, size_t n, double alpha)
{
#if defined(SVP_HAVE_MVEC) && defined(__x86_64__)
    if (__builtin_cpu_supports("avx2"))
        log_extrapolate_avx2(x, x_prev, n, alpha);
    else
        log_extrapolate_sse2(x, x_prev, n, alpha);
#else
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        const double xk = x[i], xp = x_prev[i];
        x_prev[i] = xk;
        if (xk > 0 && xp > 0) {
            const double z = xk * pow(xk / xp, alpha);
            x[i] = z <= DBL_MAX ? z : xk;
        }
    }
#endif
}

/* <g_{k−1}, g_{k−1}> of iteration k's extrapolation, which is <g_{k−2}, g_{k−2}> of the next */
typedef struct step_dot {
    int k; /* the iteration that computed it, −1 none */
    double value;
} step_dot;

/* Biggs–Andrews in the multiplicative (log) domain: x ← z = x_k (x_k / x_{k−1})^α in place,
 * x_prev ← x_k; α = <g_{k−1}, g_{k−2}> / <g_{k−2}, g_{k−2}> in [0, ALPHA_MAX] from the last two
 * RL steps (0 for the first two), or alpha_in[k] when given; alpha_out[k] records it. z > 0
 * wherever x_k, x_{k−1} > 0 (a zero stays), and with one α for two images their ratio is
 * extrapolated the same way, (x/y)_k ((x/y)_k / (x/y)_{k−1})^α: the numerator and the PL of T⁻¹
 * (eq. 4) keep their ratio. *last carries <g_{k−1}, g_{k−1}> to the next iteration, whose
 * <g_{k−2}, g_{k−2}> it is (the same sum). */
static void extrapolate(double *restrict x, double *restrict x_prev, const double *step_1,
                        const double *step_2, size_t n, int k,
                        const double *alpha_in, double *alpha_out, step_dot *last_dot)
{
    double alpha = 0;
    if (alpha_in) {
        alpha = alpha_in[k];
    } else if (k >= 2) {
        /* <g_{k−1}, g_{k−2}>, <g_{k−1}, g_{k−1}>, <x, x> and, unless the last iteration made
         * it, <g_{k−2}, g_{k−2}>: in one pass */
        const double *a[4] = {step_1, step_1, x, step_2}, *b[4] = {step_2, step_1, x, step_2};
        double d[4];
        const int have_den = last_dot->k == k - 1;
        svp_dots(a, b, have_den ? 3 : 4, n, d);
        const double num = d[0], last = d[1], size = d[2];
        const double den = have_den ? last_dot->value : d[3];
        last_dot->k = k;
        last_dot->value = last;
        alpha = den > 0 && last > STEP_FLOOR * STEP_FLOOR * size ? num / den : 0.0;
        alpha = alpha > 0 ? (alpha < ALPHA_MAX ? alpha : ALPHA_MAX) : 0.0;
    }
    if (alpha_out) alpha_out[k] = alpha;
    if (alpha > 0) {
        log_extrapolate(x, x_prev, n, alpha);
        return;
    }
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) x_prev[i] = x[i];
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
    return svp_deconv_rl_path(blur, y, options, x, NULL, NULL, NULL);
}

/* Single precision with an operator built in single precision: the levels of (11b), made by
 * one run and used by others (svp_deconv_rl_path's `levels`). */
struct svp_rl_levels {
    int w, h;
    double *shape, *h_one, *h_s, *ht_mask, *ht_s; /* n values each */
    int fit_step;
    double fit_n, fit_n_finite, fit_s, fit_ss;
};

void svp_rl_levels_free(svp_rl_levels *l)
{
    if (!l) return;
    svp_free(l->shape);
    svp_free(l->h_one);
    svp_free(l->h_s);
    svp_free(l->ht_mask);
    svp_free(l->ht_s);
    free(l);
}

/* One Richardson–Lucy run (svp_deconv_rl_path): its data, buffers and constants. */
typedef struct rl_run {
    svp_blur *blur;
    const svp_deconv_options *o;
    int w, h;
    size_t n, n_finite;
    const double *yd;                                    /* the data y */
    unsigned char *finite; /* 1 where y is finite, 0 where missing (n values) */
    double *y_masked, *blurred, *correction, *inv_norm; /* n values each */
    double *x_prev, *step_1, *step_2;                    /* Biggs–Andrews, else NULL */
    double y_max;
    const double *var_map; /* the stopping rule's noise variance: a map, or */
    double var_const;      /* one σ² (and the floor under the map) */
    /* single precision only (rl_level_setup; else NULL): H x = λ₁ H1 + λ₂ Hs + H(x − λ₁ − λ₂ s)
     * and Hᵀq = μ₁ Hᵀm + μ₂ Hᵀs + Hᵀ(q − μ₁ m − μ₂ s), q the ratio, s = m y / H1 the data's
     * shape, the four transforms of the levels once (in float for an operator built in single
     * precision, and then possibly another run's: borrowed) */
    double *shape, *h_one, *h_s, *ht_mask, *ht_s;
    int float_levels; /* the levels transformed in float (an operator built in single) */
    int borrowed;     /* the levels are another run's (svp_deconv_rl_path's `levels`) */
    /* the fits run on every fit_step-th row: there Σ 1, Σ m, Σ s, Σ s² */
    int fit_step;
    double fit_n, fit_n_finite, fit_s, fit_ss;
    double lambda[2]; /* the iterate's fit: its part λ₁ H1 + λ₂ Hs not yet in `blurred`, */
    int lambda_pending; /* when this is 1 (rl_forward) */
    double mu[2];       /* the ratio's fit, whose part rl_row_step adds */
    /* the row stages (rl_row_*): the iterate, the step's output (NULL: none), the floor, and
     * where the ratio's Hx is: in `blurred` (else in the row itself, chained) */
    double *x, *g;
    double floor_abs;
    int hx_whole, ratio_from_blurred;
    /* the operator takes its input and gives its output a row at a time (svp_blur_rows), and
     * while frame_holds_hx its frame still holds the last H's output (the ratio's input) */
    int rows, frame_holds_hx;
} rl_run;

/* One pass: the finite mask folded into y (missing → 0), the range and the count; the data
 * RL cannot take (no finite pixel, a negative one) as an error. */
static svp_status rl_scan(rl_run *r)
{
    const size_t n = r->n;
    const double *restrict yd = r->yd;
    double *y_masked = r->y_masked;
    double y_min = INFINITY, y_max = -INFINITY;
    size_t n_finite = 0;
#pragma omp parallel for schedule(static) if (n > PAR_MIN) reduction(min : y_min)              \
    reduction(max : y_max) reduction(+ : n_finite)
    for (size_t i = 0; i < n; i++) {
        double v = yd[i];
        r->finite[i] = isfinite(v) != 0;
        if (isfinite(v)) {
            y_masked[i] = v;
            y_min = v < y_min ? v : y_min;
            y_max = v > y_max ? v : y_max;
            n_finite++;
        } else {
            y_masked[i] = 0.0;
        }
    }
    r->y_max = y_max;
    r->n_finite = n_finite;
    if (n_finite == 0)
        return svp_fail(SVP_ERR_INVALID,
                        "Richardson–Lucy: all %zu pixels of the data y are NaN "
                        "or Inf",
                        n);
    if (y_min < 0) {
        size_t at = 0;
        while (at < n && !(yd[at] == y_min)) at++;
        return svp_fail(SVP_ERR_INVALID,
                        "Richardson–Lucy needs data >= 0 but y has minimum %.17g at pixel (%d, "
                        "%d); for signed data use the signed shift (method rl-signed)",
                        y_min, (int)(at % (size_t)r->w), (int)(at / (size_t)r->w));
    }
    return SVP_OK;
}

/* Single precision: float round-off is relative to what is transformed, and RL's iterates
 * and ratios are mostly a known part plus a smaller deviation: with the signed shift of T⁻¹ the
 * data are c Ĩ + B̃Ĩ, c ≫ |B̃|, so the iterate is mostly level and data shape (a flat start, then
 * the PL's deconvolution scaled by c) and the ratio m y / Hx mostly m (s / a at the start).
 * So H and Hᵀ transform only the deviation from the least-squares fit of their input by
 * λ₁ (1 or m) + λ₂ s (rl_fit_levels; s = m y / H1, the data's shape, flat edges where light
 * leaves a zero-boundary field), and the fit's transforms, made here once, are added back: in
 * double, or, for an operator built in single precision (no double spectra), in float. Float
 * levels carry round-off of the levels' size, but once: the same error every iteration (a
 * fixed error scaled by the fit, not one drawn afresh from the whole iterate each time, which
 * accelerated RL's extrapolation amplifies); and from `levels` (T⁻¹'s numerators take the
 * PL's) it is the same bits in both halves of (4), so it cancels there. Nothing in double. */
static svp_status rl_level_setup(rl_run *r, svp_rl_levels **levels)
{
    svp_blur *blur = r->blur;
    if (!blur->single) return SVP_OK;
    const int dbl = svp_blur_has_double(blur);
    r->float_levels = !dbl;
    if (!dbl && levels && *levels) {
        const svp_rl_levels *l = *levels;
        if (l->w != r->w || l->h != r->h)
            return svp_fail(SVP_ERR_SIZE, "Richardson–Lucy: levels of %d x %d for %d x %d data",
                            l->w, l->h, r->w, r->h);
        r->shape = l->shape, r->h_one = l->h_one, r->h_s = l->h_s;
        r->ht_mask = l->ht_mask, r->ht_s = l->ht_s;
        r->fit_step = l->fit_step, r->fit_n = l->fit_n, r->fit_n_finite = l->fit_n_finite;
        r->fit_s = l->fit_s, r->fit_ss = l->fit_ss;
        r->borrowed = 1;
        return SVP_OK;
    }
    const size_t n = r->n;
    double **bufs[5] = {&r->shape, &r->h_one, &r->h_s, &r->ht_mask, &r->ht_s};
    for (int k = 0; k < 5; k++)
        if (!(*bufs[k] = svp_alloc(n * sizeof(double))))
            return svp_fail(SVP_ERR_NOMEM, "Richardson–Lucy: out of memory for %d x %d buffers",
                            r->w, r->h);
    const double *yd = r->yd, *y_masked = r->y_masked;
    double *buf = r->blurred, *shape = r->shape, *h_one = r->h_one;
    if (dbl) SVP_CHECK(svp_blur_set_single(blur, 0));
    svp_image img_buf = {r->w, r->h, buf}, img_s = {r->w, r->h, shape};
    svp_image out[4] = {{r->w, r->h, h_one}, {r->w, r->h, r->h_s}, {r->w, r->h, r->ht_mask},
                        {r->w, r->h, r->ht_s}};
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) buf[i] = 1.0;
    svp_status st = svp_blur_apply(blur, &img_buf, &out[0]);
    const double dim = 1e-3 * svp_max(h_one, n); /* pixels the operator barely reaches: s = 0 */
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) shape[i] = h_one[i] > dim ? y_masked[i] / h_one[i] : 0.0;
    if (st == SVP_OK) st = svp_blur_apply(blur, &img_s, &out[1]);
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) buf[i] = isfinite(yd[i]) ? 1.0 : 0.0;
    if (st == SVP_OK) st = svp_blur_adjoint(blur, &img_buf, &out[2]);
    if (st == SVP_OK) st = svp_blur_adjoint(blur, &img_s, &out[3]);
    r->fit_step = r->h > FIT_ROWS ? r->h / FIT_ROWS : 1;
    for (int j = 0; j < r->h; j += r->fit_step)
        for (size_t i = (size_t)j * r->w; i < (size_t)(j + 1) * r->w; i++) {
            r->fit_n += 1.0;
            r->fit_n_finite += isfinite(yd[i]) ? 1.0 : 0.0;
            r->fit_s += shape[i];
            r->fit_ss += shape[i] * shape[i];
        }
    const svp_status back = dbl ? svp_blur_set_single(blur, 1) : SVP_OK;
    return st != SVP_OK ? st : back;
}

/* The run's float levels to *levels (svp_deconv_rl_path), when asked for and not borrowed. */
static svp_status rl_level_export(rl_run *r, svp_rl_levels **levels)
{
    if (!levels || *levels || !r->float_levels || r->borrowed || !r->shape) return SVP_OK;
    svp_rl_levels *l = calloc(1, sizeof *l);
    if (!l) return svp_fail(SVP_ERR_NOMEM, "Richardson–Lucy: out of memory for the levels");
    *l = (svp_rl_levels){.w = r->w, .h = r->h, .shape = r->shape, .h_one = r->h_one,
                         .h_s = r->h_s, .ht_mask = r->ht_mask, .ht_s = r->ht_s,
                         .fit_step = r->fit_step, .fit_n = r->fit_n,
                         .fit_n_finite = r->fit_n_finite, .fit_s = r->fit_s, .fit_ss = r->fit_ss};
    r->shape = r->h_one = r->h_s = r->ht_mask = r->ht_s = NULL;
    *levels = l;
    return SVP_OK;
}

/* The least-squares fit v ≈ l[0] e + l[1] s on every fit_step-th row (any fit keeps (11b)
 * exact; a good one keeps the deviation small): v = x and e = 1 (ratio 0), or v = the ratio
 * m y / max(Hx, floor) from Hx in `blurred` and e = m (ratio 1); s the data's shape (0 where y
 * is missing); the constant alone (l[1] = 0) when s is nearly flat. */
static void rl_fit_levels(const rl_run *r, const double *x, int ratio, double floor_abs,
                          double l[2])
{
    const double *restrict s = r->shape, *restrict y = r->y_masked, *restrict hd = r->blurred;
    const double *restrict h1 = r->h_one, *restrict hs = r->h_s;
    const double l0 = r->lambda_pending ? r->lambda[0] : 0.0;
    const double l1 = r->lambda_pending ? r->lambda[1] : 0.0;
    double sv = 0, svs = 0;
    for (int j = 0; j < r->h; j += r->fit_step)
        for (size_t i = (size_t)j * r->w; i < (size_t)(j + 1) * r->w; i++) {
            const double hx = hd[i] + l0 * h1[i] + l1 * hs[i];
            const double v = ratio ? y[i] / (hx > floor_abs ? hx : floor_abs) : x[i];
            sv += v;
            svs += v * s[i];
        }
    const double count = ratio ? r->fit_n_finite : r->fit_n;
    const double det = count * r->fit_ss - r->fit_s * r->fit_s;
    if (!(det > 1e-9 * count * r->fit_ss)) {
        l[0] = sv / count;
        l[1] = 0.0;
        return;
    }
    l[0] = (r->fit_ss * sv - r->fit_s * svs) / det;
    l[1] = (count * svs - r->fit_s * sv) / det;
}

/* The normalisation 1 / Hᵀm (m = 1 without missing data) into inv_norm, computed once: per
 * pixel with boundary weights (0 where no finite datum sees the pixel), else its mean. */
static svp_status rl_normalisation(rl_run *r)
{
    const size_t n = r->n;
    const double *yd = r->yd;
    double *blurred = r->blurred, *inv_norm = r->inv_norm;
    svp_image img_blurred = {r->w, r->h, blurred}, img_norm = {r->w, r->h, inv_norm};
    if (r->ht_mask) {
        memcpy(inv_norm, r->ht_mask, n * sizeof(double));
    } else {
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) blurred[i] = isfinite(yd[i]) ? 1.0 : 0.0;
        SVP_CHECK(svp_blur_adjoint(r->blur, &img_blurred, &img_norm));
    }
    if (r->o->boundary_weights) {
        /* Pixels no finite datum sees (Hᵀm ~ 0) keep their value: 0 marks them. */
        const double seen = r->blur->single ? SEEN_SINGLE : SEEN_DOUBLE;
        const double tiny = seen * svp_max(inv_norm, n);
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) inv_norm[i] = inv_norm[i] > tiny ? 1.0 / inv_norm[i] : 0.0;
    } else {
        const double mean_norm = svp_sum(inv_norm, n) / (double)n;
        const double inv = mean_norm > 0 ? 1.0 / mean_norm : 1.0;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) inv_norm[i] = inv;
    }
    return SVP_OK;
}

/* The stopping rule's noise variance (auto_stop): the caller's map, or one σ² estimated from
 * y; at least round-off of y_max², so noiseless data never reach χ² = 1 and the stall decides. */
static svp_status rl_variance(rl_run *r, const svp_image *y)
{
    const svp_deconv_options *o = r->o;
    r->var_map = NULL;
    r->var_const = 0;
    if (!o->auto_stop) return SVP_OK;
    if (o->variance) {
        SVP_CHECK(svp_image_same_size(y, o->variance, "y", "variance"));
        r->var_map = o->variance->data;
    } else {
        double sigma = 0;
        SVP_CHECK(svp_noise_sigma_estimate(y, &sigma));
        r->var_const = sigma * sigma;
    }
    r->var_const = fmax(r->var_const, 1e-24 * r->y_max * r->y_max);
    return SVP_OK;
}

/* ---- one iteration's pointwise stages, a row at a time (svp_blur_rows, or loops over rows) ---- */

/* H's input, row y: the iterate, or in single precision its deviation from the levels' fit */
static void rl_row_input(void *user, int y, double *restrict row)
{
    const rl_run *r = user;
    const size_t i0 = (size_t)y * r->w;
    const double *restrict x = r->x + i0;
    if (!r->h_one) {
        memcpy(row, x, (size_t)r->w * sizeof(double));
        return;
    }
    const double *restrict sv = r->shape + i0;
    const double l0 = r->lambda[0], l1 = r->lambda[1];
    for (int i = 0; i < r->w; i++) row[i] = x[i] - l0 - l1 * sv[i];
}

/* H's output, row y, into `blurred`: with hx_whole plus the levels' part λ₁ H1 + λ₂ Hs (row may
 * be `blurred`'s own row) */
static void rl_row_hx(void *user, int y, double *row)
{
    const rl_run *r = user;
    const size_t i0 = (size_t)y * r->w;
    double *out = r->blurred + i0;
    if (!r->hx_whole || !r->h_one) {
        if (out != row) memcpy(out, row, (size_t)r->w * sizeof(double));
        return;
    }
    const double *restrict h1 = r->h_one + i0, *restrict hs = r->h_s + i0;
    const double l0 = r->lambda[0], l1 = r->lambda[1];
    for (int i = 0; i < r->w; i++) {
        double v = row[i];
        v += l0 * h1[i] + l1 * hs[i];
        out[i] = v;
    }
}

/* Hᵀ's input, row y: the ratio m y / max(Hx, floor), Hx from `blurred` (ratio_from_blurred)
 * or the row itself; in single precision with the pending levels' part of Hx added and the
 * ratio's deviation from its fit r->mu taken */
static void rl_row_ratio(void *user, int y, double *row)
{
    const rl_run *r = user;
    const size_t i0 = (size_t)y * r->w;
    const double *hx_in = r->ratio_from_blurred ? r->blurred + i0 : row;
    const double *restrict ym = r->y_masked + i0;
    const double floor_abs = r->floor_abs;
    if (!r->ht_mask) {
        for (int i = 0; i < r->w; i++) {
            const double hx = hx_in[i];
            row[i] = ym[i] / (hx > floor_abs ? hx : floor_abs);
        }
        return;
    }
    const double mu0 = r->mu[0], mu1 = r->mu[1];
    const double l0 = r->lambda_pending ? r->lambda[0] : 0.0;
    const double l1 = r->lambda_pending ? r->lambda[1] : 0.0;
    const double *restrict h1 = r->h_one + i0, *restrict hs = r->h_s + i0;
    const double *restrict sv = r->shape + i0;
    const unsigned char *restrict fin = r->finite + i0;
    /* the quotient everywhere, then missing pixels zeroed (two loops, so that both vectorise) */
    for (int i = 0; i < r->w; i++) {
        const double hx = hx_in[i] + l0 * h1[i] + l1 * hs[i];
        row[i] = ym[i] / (hx > floor_abs ? hx : floor_abs) - mu0 - mu1 * sv[i];
    }
    if (r->n_finite < r->n)
        for (int i = 0; i < r->w; i++) row[i] = fin[i] ? row[i] : 0.0;
}

/* The multiplicative step of n pixels (rl_row_step), written branch-free so that it vectorises;
 * levels and g constant where it is inlined. */
static inline void rl_step_pixels(double *restrict xd, double *restrict g, const double *row,
                                  const double *restrict inv_norm, const double *restrict ht_mask,
                                  const double *restrict ht_s, double mu0, double mu1, int n,
                                  int levels, int with_g)
{
    for (int i = 0; i < n; i++) {
        const double old = xd[i];
        /* single precision: the levels' part of Hᵀ(...) (rl_row_ratio) */
        const double c = levels ? row[i] + mu0 * ht_mask[i] + mu1 * ht_s[i] : row[i];
        double v = old * c * inv_norm[i];
        /* round-off can make Hᵀ(...) slightly negative; NaN/Inf never leave */
        v = (v > 0 && v <= DBL_MAX) ? v : 0.0;
        /* pixels no finite datum sees (1 / Hᵀm = 0) keep their value */
        const int keep = inv_norm[i] == 0;
        xd[i] = keep ? old : v;
        if (with_g) g[i] = keep ? 0.0 : v - old;
    }
}

/* Hᵀ's output, row y (`row`: Hᵀ(...), in single precision less the levels' part): the
 * multiplicative step x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm; r->g (or NULL) receives x_new − x */
static void rl_row_step(void *user, int y, double *restrict row)
{
    const rl_run *r = user;
    const size_t i0 = (size_t)y * r->w;
    double *xd = r->x + i0, *g = r->g ? r->g + i0 : NULL;
    const double *inv_norm = r->inv_norm + i0;
    const double mu0 = r->mu[0], mu1 = r->mu[1];
    if (r->ht_mask) {
        const double *htm = r->ht_mask + i0, *hts = r->ht_s + i0;
        if (g)
            rl_step_pixels(xd, g, row, inv_norm, htm, hts, mu0, mu1, r->w, 1, 1);
        else
            rl_step_pixels(xd, NULL, row, inv_norm, htm, hts, mu0, mu1, r->w, 1, 0);
    } else if (g) {
        rl_step_pixels(xd, g, row, inv_norm, NULL, NULL, 0.0, 0.0, r->w, 0, 1);
    } else {
        rl_step_pixels(xd, NULL, row, inv_norm, NULL, NULL, 0.0, 0.0, r->w, 0, 0);
    }
}

/* stage(r, y, image + y w) for every row y */
static void rl_rows(rl_run *r, svp_blur_row_fn stage, double *image)
{
#pragma omp parallel for schedule(static) if (r->n > PAR_MIN)
    for (int y = 0; y < r->h; y++) stage(r, y, image + (size_t)y * r->w);
}

/* Hx into `blurred`; in single precision by the levels' fit (rl_level_setup), whose part
 * λ₁ H1 + λ₂ Hs is added here when `whole`, else left pending for rl_adjoint_step. With row-wise
 * transforms (r->rows) and not `whole`, only the levels' fit rows of `blurred` are filled (all
 * rl_fit_levels reads) and the frame keeps Hx for the ratio. */
static svp_status rl_forward(rl_run *r, double *restrict xd, int whole)
{
    svp_image img_x = {r->w, r->h, xd}, img_blurred = {r->w, r->h, r->blurred};
    r->x = xd;
    r->hx_whole = whole;
    r->frame_holds_hx = 0;
    r->lambda_pending = 0;
    if (r->h_one) rl_fit_levels(r, xd, 0, 0.0, r->lambda);
    if (r->rows) {
        const int store = whole || r->h_one;
        SVP_CHECK(svp_blur_rows(r->blur, 0, 0, rl_row_input, store ? rl_row_hx : NULL,
                                whole || !r->h_one ? 1 : r->fit_step, r));
        r->frame_holds_hx = !whole;
    } else if (!r->h_one) {
        return svp_blur_apply(r->blur, &img_x, &img_blurred);
    } else {
        svp_image img_dev = {r->w, r->h, r->correction};
        rl_rows(r, rl_row_input, r->correction);
        SVP_CHECK(svp_blur_apply(r->blur, &img_dev, &img_blurred));
        if (whole) rl_rows(r, rl_row_hx, r->blurred);
    }
    r->lambda_pending = r->h_one && !whole;
    return SVP_OK;
}

/* One multiplicative step x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm, with Hx from rl_forward
 * (in `blurred`, or in the operator's frame); g (or NULL) receives the step x_new − x. In
 * single precision Hᵀ transforms the ratio's deviation from its levels' fit r->mu
 * (rl_level_setup), whose part the step adds. */
static svp_status rl_adjoint_step(rl_run *r, double *restrict xd, double *restrict g,
                                  double floor_abs)
{
    r->x = xd;
    r->g = g;
    r->floor_abs = floor_abs;
    if (r->ht_mask) rl_fit_levels(r, NULL, 1, floor_abs, r->mu);
    if (r->rows) {
        r->ratio_from_blurred = !r->frame_holds_hx;
        SVP_CHECK(svp_blur_rows(r->blur, 1, r->frame_holds_hx, rl_row_ratio, rl_row_step, 1, r));
    } else {
        svp_image img_blurred = {r->w, r->h, r->blurred};
        svp_image img_correction = {r->w, r->h, r->correction};
        r->ratio_from_blurred = 1;
        rl_rows(r, rl_row_ratio, r->blurred);
        SVP_CHECK(svp_blur_adjoint(r->blur, &img_blurred, &img_correction));
        rl_rows(r, rl_row_step, r->correction);
    }
    r->lambda_pending = 0;
    r->frame_holds_hx = 0;
    return SVP_OK;
}

/* The flat start: x = the mean of the finite data. */
static void rl_start(const rl_run *r, svp_image *x)
{
    const size_t n = r->n;
    const double start = svp_sum(r->y_masked, n) / (double)r->n_finite;
    double *restrict xd = x->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) xd[i] = start;
}

/* Acceleration (Biggs–Andrews, extrapolate): the previous iterate and the last two RL steps. */
static svp_status rl_alloc_acceleration(rl_run *r)
{
    if (r->o->acceleration != SVP_RL_BIGGS_ANDREWS) return SVP_OK;
    r->x_prev = svp_alloc(r->n * sizeof(double));
    r->step_1 = svp_alloc(r->n * sizeof(double));
    r->step_2 = svp_alloc(r->n * sizeof(double));
    if (!r->x_prev || !r->step_1 || !r->step_2)
        return svp_fail(SVP_ERR_NOMEM, "Richardson–Lucy: out of memory for the acceleration");
    return SVP_OK;
}

/* The iterations from the start in x, until the count or (auto_stop) the stopping rule; the
 * report filled. */
static svp_status rl_iterate(rl_run *r, svp_image *x, const double *alpha_in, double *alpha_out)
{
    const svp_deconv_options *o = r->o;
    const size_t n = r->n;
    /* floor > 0 keeps y / Hx finite; 1e-300 y_max guards floor = 0 without overflowing */
    const double floor_abs = fmax(o->floor * r->y_max, 1e-300 * r->y_max);
    double *restrict xd = x->data;
    const int auto_stop = o->auto_stop, accel = r->x_prev != NULL;
    double chi2_history[STALL_SPAN + 1] = {0};
    int done = 0, stop = auto_stop ? SVP_RL_STOP_CAP : SVP_RL_STOP_COUNT;
    double chi2 = 0;
    step_dot last_dot = {-1, 0.0};
    for (int k = 0; k < o->iterations; k++) {
        if (accel)
            extrapolate(xd, r->x_prev, r->step_1, r->step_2, n, k, alpha_in,
                        alpha_out, &last_dot);
        SVP_CHECK(rl_forward(r, xd, auto_stop)); /* the stopping rule needs Hx whole */
        if (auto_stop) {
            chi2 = residual_chi2(r->yd, r->blurred, r->var_map, r->var_const, r->correction, n) /
                   (double)r->n_finite;
            const int why = stopping_rule(chi2_history, chi2, k);
            if (why != SVP_RL_STOP_CAP) {
                stop = why;
                done = k;
                break;
            }
        }
        double *g = r->step_2; /* becomes the newest step */
        SVP_CHECK(rl_adjoint_step(r, xd, g, floor_abs));
        if (accel) {
            r->step_2 = r->step_1;
            r->step_1 = g;
        }
        done = k + 1;
        SVP_CHECK(svp_report_progress(o->progress, o->progress_user,
                                      (double)(k + 1) / o->iterations));
    }
    svp_status st = SVP_OK;
    if (stop == SVP_RL_STOP_DISCREPANCY || stop == SVP_RL_STOP_STALLED)
        st = svp_report_progress(o->progress, o->progress_user, 1.0);
    if (o->report) {
        o->report->iterations = done;
        o->report->chi2 = chi2;
        o->report->stop = stop;
    }
    return st;
}

static svp_status rl_path_run(svp_blur *blur, const svp_image *y,
                              const svp_deconv_options *options, svp_image *x,
                              const double *alpha_in, double *alpha_out, svp_rl_levels **levels);

/* Single precision: data whose largest value is outside [2^-FLOAT_SCALE_BITS, 2^FLOAT_SCALE_BITS]
 * are scaled by a power of two to a largest value in [1, 2) for the run, and x back. */
#define FLOAT_SCALE_BITS 60

/* RL is equivariant under y → 2^k y (x → 2^k x, exactly in binary floating point while nothing
 * underflows), but float transforms hold only magnitudes from about 1e-38 to 3e38: a PL in
 * photons per second and square metre (1e20) or in watts (1e-12) times c max|B̃| came back 0 or
 * implausible. So in single precision the data are scaled to unit size first (a copy, with the
 * stopping rule's variance map), which leaves every result bit for bit 2^k times the unit-size
 * one; double precision and data of ordinary size run as they are. */
svp_status svp_deconv_rl_path(svp_blur *blur, const svp_image *y,
                              const svp_deconv_options *options, svp_image *x,
                              const double *alpha_in, double *alpha_out,
                              svp_rl_levels **levels)
{
    svp_deconv_options defaults;
    if (!options) {
        svp_deconv_defaults(&defaults);
        options = &defaults;
    }
    SVP_CHECK(check_args(blur, y, options, x));
    const int single = options->single_precision || blur->single;
    const size_t n = (size_t)y->width * y->height;
    const int k = single ? svp_unit_exponent(y->data, n, FLOAT_SCALE_BITS) : 0;
    if (k == 0) return rl_path_run(blur, y, options, x, alpha_in, alpha_out, levels);
    svp_image *ys = NULL, *vs = NULL;
    svp_status st = svp_image_new(y->width, y->height, &ys);
    if (st == SVP_OK && options->variance)
        st = svp_image_new(y->width, y->height, &vs);
    if (st == SVP_OK) {
        for (size_t i = 0; i < n; i++) ys->data[i] = ldexp(y->data[i], k);
        if (vs)
            for (size_t i = 0; i < n; i++) vs->data[i] = ldexp(options->variance->data[i], 2 * k);
        svp_deconv_options o = *options;
        if (vs) o.variance = vs;
        st = rl_path_run(blur, ys, &o, x, alpha_in, alpha_out, levels);
    }
    if (st == SVP_OK)
        for (size_t i = 0; i < n; i++) x->data[i] = ldexp(x->data[i], -k);
    svp_image_free(ys);
    svp_image_free(vs);
    return st;
}

static svp_status rl_path_run(svp_blur *blur, const svp_image *y,
                              const svp_deconv_options *options, svp_image *x,
                              const double *alpha_in, double *alpha_out, svp_rl_levels **levels)
{
    /* single precision: the operator's float transforms for this call only */
    const int was_single = blur->single;
    if (options->single_precision) SVP_CHECK(svp_blur_set_single(blur, 1));
    const size_t n = (size_t)y->width * y->height;
    rl_run r = {.blur = blur, .o = options, .w = y->width, .h = y->height, .n = n,
                .yd = y->data, .rows = svp_blur_rows_ok(blur)};
    svp_status st = SVP_OK;
    if (options->report) memset(options->report, 0, sizeof *options->report);

    /* y with its missing pixels at 0, Hx (and the ratio y / Hx), Hᵀ(...), 1 / Hᵀm */
    r.y_masked = svp_alloc(n * sizeof(double));
    r.blurred = svp_alloc(n * sizeof(double));
    r.inv_norm = svp_alloc(n * sizeof(double));
    r.finite = svp_alloc(n);
    /* Hᵀ's output, H's input in single precision, and the acceleration's and the stopping
     * rule's scratch: not needed when H and Hᵀ go a row at a time without either */
    const int accel = options->acceleration == SVP_RL_BIGGS_ANDREWS;
    r.correction = !r.rows || accel || options->auto_stop ? svp_alloc(n * sizeof(double)) : NULL;
    if (!r.y_masked || !r.blurred || !r.inv_norm || !r.finite ||
        (!r.correction && (!r.rows || accel || options->auto_stop))) {
        st = svp_fail(SVP_ERR_NOMEM, "Richardson–Lucy: out of memory for %d x %d buffers", r.w,
                      r.h);
        goto cleanup;
    }
    if ((st = rl_scan(&r)) != SVP_OK) goto cleanup;
    if (r.y_max == 0) {
        /* all-zero data: the only non-negative solution with zero flux */
        memset(x->data, 0, n * sizeof(double));
        for (int k = 1; k <= options->iterations && st == SVP_OK; k++)
            st = svp_report_progress(options->progress, options->progress_user,
                                     (double)k / options->iterations);
        goto cleanup;
    }
    if ((st = rl_level_setup(&r, levels)) != SVP_OK || (st = rl_normalisation(&r)) != SVP_OK)
        goto cleanup;
    rl_start(&r, x);
    if ((st = rl_variance(&r, y)) != SVP_OK || (st = rl_alloc_acceleration(&r)) != SVP_OK)
        goto cleanup;
    st = rl_iterate(&r, x, alpha_in, alpha_out);
    if (st == SVP_OK) st = rl_level_export(&r, levels);
cleanup:
    if (options->single_precision && !was_single) svp_blur_set_single(blur, 0);
    svp_free(r.y_masked);
    svp_free(r.blurred);
    svp_free(r.correction);
    svp_free(r.finite);
    svp_free(r.inv_norm);
    if (!r.borrowed) {
        svp_free(r.shape);
        svp_free(r.h_one);
        svp_free(r.h_s);
        svp_free(r.ht_mask);
        svp_free(r.ht_s);
    }
    svp_free(r.x_prev);
    svp_free(r.step_1); /* rl_iterate swaps the two steps: both are freed either way */
    svp_free(r.step_2);
    return st;
}
