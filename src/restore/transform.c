/* The transforms T (eq. 3) and T⁻¹ (eq. 4; signed shift eq. 5, validity eq. 6) of
 * docs/model.md, and the closed-form halo correction (eq. 7). Everything goes through
 * svp_blur_apply / svp_blur_adjoint and the two deconvolutions, so the same code serves
 * space-invariant and space-variant operators. */
#include "../blur/blur_internal.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Forward model: Ĩ at or below FORWARD_PL_TINY · max Ĩ is dark (B̃ = 0, validity 0). The FFT
 * convolution leaves round-off of ~1e-16 · max Ĩ where the true Ĩ is 0; dividing by that would
 * return noise, so the threshold sits 1e6 above it and far below any PL a camera records. */
#define FORWARD_PL_TINY 1e-10
/* Halo correction: denominators Ĩ − α<Ĩ> at or below HALO_DEN_TINY · max|Ĩ| carry no light
 * (the subtraction itself leaves round-off of ~1e-16 · max|Ĩ|). */
#define HALO_DEN_TINY 1e-10
/* Pointwise loops run in parallel only above this many pixels (below, threads cost more). */
#define PAR_MIN 32768
/* Coverage of a missing pixel by measured ones below this is FFT round-off: nothing covers it. */
#define COVERAGE_TINY 1e-9

/* Used by the tests to assert that the last-resort NaN/Inf repair of T⁻¹ never fires. */
svp_status svp_inverse_transform_counted(svp_blur *blur, const svp_image *pl_apparent,
                                         const svp_image *const *field_apparent, int n_fields,
                                         const svp_correct_options *options, svp_image *pl_true,
                                         svp_image *const *field_true, svp_image *validity,
                                         size_t *n_missing, size_t *n_repaired);

void svp_correct_defaults(svp_correct_options *options)
{
    options->method = SVP_METHOD_RW;
    svp_deconv_defaults(&options->deconv);
    options->deconv.iterations = 75; /* the reference study's RL count for measured data */
    options->pl_floor = 1e-3;
    options->shift = 0.0;
    options->balance_auto = 0;
    options->noise_sigma = 0.0;
    options->reports = NULL;
    options->field_names = NULL;
}

/* ---- argument checks --------------------------------------------------------------------- */

static const char *indexed(char *buf, size_t size, const char *what, int index)
{
    if (index < 0)
        snprintf(buf, size, "%s", what);
    else
        snprintf(buf, size, "%s[%d]", what, index);
    return buf;
}

/* `image` (named what[index]) must exist and have the size of `ref` (named ref_name). */
static svp_status check_same(const svp_image *image, const char *what, int index,
                             const svp_image *ref, const char *ref_name)
{
    char name[64];
    indexed(name, sizeof name, what, index);
    if (!image || !image->data) return svp_fail(SVP_ERR_INVALID, "%s is NULL", name);
    return svp_image_same_size(ref, image, ref_name, name);
}

static svp_status check_operator(const svp_blur *blur, const svp_image *image, const char *what)
{
    if (!blur) return svp_fail(SVP_ERR_INVALID, "the blur operator is NULL");
    if (!image || !image->data) return svp_fail(SVP_ERR_INVALID, "%s is NULL", what);
    if (image->width != svp_blur_width(blur) || image->height != svp_blur_height(blur))
        return svp_fail(SVP_ERR_SIZE, "%s is %d x %d but the blur operator is %d x %d", what,
                        image->width, image->height, svp_blur_width(blur), svp_blur_height(blur));
    return SVP_OK;
}

typedef struct named_image {
    const double *data;
    char name[40];
} named_image;

/* Outputs must not share pixels with an input or with each other (the transforms read inputs
 * after writing outputs). */
static svp_status check_no_alias(const named_image *in, int n_in, const named_image *out, int n_out)
{
    for (int o = 0; o < n_out; o++) {
        if (!out[o].data) continue;
        for (int i = 0; i < n_in; i++)
            if (out[o].data == in[i].data)
                return svp_fail(SVP_ERR_INVALID,
                                "%s shares its pixels with the input %s: outputs must be "
                                "separate images",
                                out[o].name, in[i].name);
        for (int p = 0; p < o; p++)
            if (out[o].data == out[p].data)
                return svp_fail(SVP_ERR_INVALID, "outputs %s and %s are the same image",
                                out[p].name, out[o].name);
    }
    return SVP_OK;
}

static svp_status alias_lists(const svp_image *pl_in, const svp_image *const *fields_in,
                              const char *in_pl, const char *in_field, const svp_image *pl_out,
                              svp_image *const *fields_out, const svp_image *validity,
                              const char *out_pl, const char *out_field, int n_fields)
{
    named_image *in = calloc((size_t)n_fields + 1, sizeof *in);
    named_image *out = calloc((size_t)n_fields + 2, sizeof *out);
    svp_status st = SVP_OK;
    if (!in || !out) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for argument checks");
        goto cleanup;
    }
    in[0].data = pl_in->data;
    indexed(in[0].name, sizeof in[0].name, in_pl, -1);
    out[0].data = pl_out->data;
    indexed(out[0].name, sizeof out[0].name, out_pl, -1);
    out[1].data = validity ? validity->data : NULL;
    indexed(out[1].name, sizeof out[1].name, "validity", -1);
    for (int c = 0; c < n_fields; c++) {
        in[c + 1].data = fields_in[c]->data;
        indexed(in[c + 1].name, sizeof in[c + 1].name, in_field, c);
        out[c + 2].data = fields_out[c]->data;
        indexed(out[c + 2].name, sizeof out[c + 2].name, out_field, c);
    }
    st = check_no_alias(in, n_fields + 1, out, n_fields + 2);
cleanup:
    free(in);
    free(out);
    return st;
}

/* Checks pl, fields (inputs) and pl_out, fields_out, validity (outputs) against the operator. */
static svp_status check_transform_args(const svp_blur *blur, const svp_image *pl,
                                       const svp_image *const *fields, int n_fields,
                                       const svp_image *pl_out, svp_image *const *fields_out,
                                       const svp_image *validity, const char *in_pl,
                                       const char *in_field, const char *out_pl,
                                       const char *out_field)
{
    if (!blur) return svp_fail(SVP_ERR_INVALID, "the blur operator is NULL");
    if (n_fields < 1)
        return svp_fail(SVP_ERR_INVALID, "n_fields = %d: at least one field component is needed",
                        n_fields);
    if (!fields) return svp_fail(SVP_ERR_INVALID, "the %s array is NULL", in_field);
    if (!fields_out) return svp_fail(SVP_ERR_INVALID, "the %s array is NULL", out_field);
    SVP_CHECK(check_operator(blur, pl, in_pl));
    for (int c = 0; c < n_fields; c++) SVP_CHECK(check_same(fields[c], in_field, c, pl, in_pl));
    SVP_CHECK(check_same(pl_out, out_pl, -1, pl, in_pl));
    for (int c = 0; c < n_fields; c++)
        SVP_CHECK(check_same(fields_out[c], out_field, c, pl, in_pl));
    if (validity) SVP_CHECK(check_same(validity, "validity", -1, pl, in_pl));
    return alias_lists(pl, fields, in_pl, in_field, pl_out, fields_out, validity, out_pl, out_field,
                       n_fields);
}

/* ---- forward transform T (eq. 3) --------------------------------------------------------- */

svp_status svp_forward_transform(svp_blur *blur, const svp_image *pl_true,
                                 const svp_image *const *field_true, int n_fields,
                                 svp_image *pl_apparent, svp_image *const *field_apparent,
                                 svp_image *validity)
{
    SVP_CHECK(check_transform_args(blur, pl_true, field_true, n_fields, pl_apparent, field_apparent,
                                   validity, "pl_true", "field_true", "pl_apparent",
                                   "field_apparent"));
    const int w = pl_true->width, h = pl_true->height;
    const size_t n = (size_t)w * h;

    /* The forward model needs complete, physical true maps. */
    size_t bad = svp_image_count_nonfinite(pl_true);
    if (bad)
        return svp_fail(SVP_ERR_INVALID,
                        "pl_true has %zu NaN/Inf pixels: the forward transform needs a complete "
                        "true PL map",
                        bad);
    for (int c = 0; c < n_fields; c++) {
        bad = svp_image_count_nonfinite(field_true[c]);
        if (bad)
            return svp_fail(SVP_ERR_INVALID,
                            "field_true[%d] has %zu NaN/Inf pixels: the forward transform needs "
                            "complete true field maps",
                            c, bad);
    }
    for (size_t i = 0; i < n; i++)
        if (pl_true->data[i] < 0)
            return svp_fail(SVP_ERR_INVALID,
                            "pl_true is negative (%g) at pixel (%zu, %zu): PL is an intensity",
                            pl_true->data[i], i % (size_t)w, i / (size_t)w);

    svp_image *product = NULL;
    svp_status st = svp_image_new(w, h, &product);
    if (st != SVP_OK) return st;

    /* Ĩ = H I (eq. 3b). Ĩ of a non-negative I is non-negative: negative values are round-off. */
    st = svp_blur_apply(blur, pl_true, pl_apparent);
    if (st != SVP_OK) goto cleanup;
    double *restrict pl_app = pl_apparent->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++)
        if (!(pl_app[i] > 0)) pl_app[i] = 0.0;
    const double pl_max = svp_max(pl_app, n);
    const double dark = pl_max > 0 ? FORWARD_PL_TINY * pl_max : INFINITY;

    /* B̃_c Ĩ = H(B_c I) (eq. 3a), one application per component. */
    for (int c = 0; c < n_fields; c++) {
        const double *restrict b_true = field_true[c]->data;
        const double *restrict i_true = pl_true->data;
        double *restrict prod = product->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) prod[i] = b_true[i] * i_true[i];
        st = svp_blur_apply(blur, product, field_apparent[c]);
        if (st != SVP_OK) goto cleanup;
        double *restrict b_app = field_apparent[c]->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) b_app[i] = pl_app[i] > dark ? b_app[i] / pl_app[i] : 0.0;
    }
    if (validity) {
        double *restrict v = validity->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) v[i] = pl_app[i] > dark ? 1.0 : 0.0;
    }
cleanup:
    svp_image_free(product);
    return st;
}

/* ---- inverse transform T⁻¹ (eq. 4) ------------------------------------------------------- */

static int uses_rl_for_pl(svp_method m) { return m != SVP_METHOD_W; }
static int uses_rl_for_field(svp_method m)
{
    return m == SVP_METHOD_R || m == SVP_METHOD_RL_SIGNED;
}

/* y ⊘ p with the method's deconvolution, progress forwarded as the share `share`. A Wiener
 * deconvolution with balance_auto first chooses its balance by the discrepancy principle (noise
 * σ noise_sigma, or estimated from y when <= 0). report (may be NULL) receives what it did. */
static svp_status deconvolve(svp_blur *blur, const svp_image *y, int use_rl,
                             const svp_deconv_options *base, int balance_auto, double noise_sigma,
                             svp_progress_share *share, svp_deconv_report *report, svp_image *x)
{
    svp_deconv_options o = *base;
    o.report = report;
    if (base->progress) {
        o.progress = svp_progress_share_fn;
        o.progress_user = share;
    }
    double sigma_used = 0;
    if (!use_rl && balance_auto)
        SVP_CHECK(svp_wiener_balance_discrepancy(blur, y, noise_sigma, &o.balance, &sigma_used));
    svp_status st = use_rl ? svp_deconv_rl(blur, y, &o, x) : svp_deconv_wiener(blur, y, &o, x);
    if (report) {
        if (use_rl) memset(report, 0, sizeof *report);
        report->noise_sigma = sigma_used;
    }
    if (st != SVP_OK) return st;
    if (base->progress) {
        if (share->fn(share->user, share->base + share->span))
            return svp_fail(SVP_ERR_CANCELLED, "cancelled by the progress callback");
    }
    return SVP_OK;
}

static svp_status check_correct_options(const svp_correct_options *o)
{
    if (o->method != SVP_METHOD_RW && o->method != SVP_METHOD_R && o->method != SVP_METHOD_W &&
        o->method != SVP_METHOD_RL_SIGNED)
        return svp_fail(SVP_ERR_INVALID, "unknown correction method %d", (int)o->method);
    if (!(o->pl_floor > 0 && o->pl_floor < 1))
        return svp_fail(SVP_ERR_INVALID, "pl_floor must be in (0, 1), got %g", o->pl_floor);
    if (!isfinite(o->shift))
        return svp_fail(SVP_ERR_INVALID, "shift must be finite, got %g", o->shift);
    if (o->method != SVP_METHOD_W && o->deconv.iterations < 1)
        return svp_fail(SVP_ERR_INVALID, "Richardson-Lucy iterations must be >= 1, got %d",
                        o->deconv.iterations);
    if (!isfinite(o->noise_sigma))
        return svp_fail(SVP_ERR_INVALID, "noise_sigma must be finite, got %g", o->noise_sigma);
    if (o->method != SVP_METHOD_R && o->method != SVP_METHOD_RL_SIGNED && !o->balance_auto &&
        !(o->deconv.balance >= 0 && isfinite(o->deconv.balance)))
        return svp_fail(SVP_ERR_INVALID, "Wiener balance must be >= 0 and finite, got %g",
                        o->deconv.balance);
    return SVP_OK;
}

/* What messages call field map c. */
static const char *field_name(const svp_correct_options *o, int c, char *buf, size_t size)
{
    if (o->field_names && o->field_names[c]) return o->field_names[c];
    snprintf(buf, size, "field_apparent[%d]", c);
    return buf;
}

/* The shift c of eq. 5 for component `c`: B̃ + c > 0 at every measured pixel. */
static svp_status signed_shift(const svp_image *field, const unsigned char *missing, size_t n,
                               const svp_correct_options *o, int c, double *shift)
{
    const double requested = o->shift;
    double lo = INFINITY, hi = -INFINITY;
    size_t at = 0;
    for (size_t i = 0; i < n; i++) {
        if (missing[i]) continue;
        double v = field->data[i];
        if (v < lo) {
            lo = v;
            at = i;
        }
        if (v > hi) hi = v;
    }
    if (requested == 0) {
        /* c = 0.1 · range − min; a constant map has no range: use its magnitude (or 1). */
        double range = hi - lo;
        if (!(range > 0)) range = fabs(lo) > 0 ? fabs(lo) : 1.0;
        *shift = 0.1 * range - lo;
        /* keep B̃ + c > 0 against rounding when |min| dwarfs the range */
        for (double step = 0.1 * range + 1e-15 * fabs(lo); !(lo + *shift > 0); step *= 2)
            *shift += step;
        return SVP_OK;
    }
    char buf[32];
    const size_t w = (size_t)field->width;
    if (!(lo + requested > 0))
        return svp_fail(SVP_ERR_INVALID,
                        "%s: the shift c = %g leaves the field + c = %g <= 0 at pixel (x %zu, "
                        "y %zu) (field minimum %g there): the signed shift needs c > %g (or c = "
                        "0: automatic)",
                        field_name(o, c, buf, sizeof buf), requested, lo + requested, at % w,
                        at / w, lo, -lo);
    *shift = requested;
    return SVP_OK;
}

svp_status svp_inverse_transform_counted(svp_blur *blur, const svp_image *pl_apparent,
                                         const svp_image *const *field_apparent, int n_fields,
                                         const svp_correct_options *options, svp_image *pl_true,
                                         svp_image *const *field_true, svp_image *validity,
                                         size_t *n_missing, size_t *n_repaired)
{
    if (n_missing) *n_missing = 0;
    if (n_repaired) *n_repaired = 0;
    svp_correct_options opt;
    if (options)
        opt = *options;
    else
        svp_correct_defaults(&opt);
    SVP_CHECK(check_correct_options(&opt));
    SVP_CHECK(check_transform_args(blur, pl_apparent, field_apparent, n_fields, pl_true, field_true,
                                   validity, "pl_apparent", "field_apparent", "pl_true",
                                   "field_true"));
    if (opt.reports) memset(opt.reports, 0, ((size_t)n_fields + 1) * sizeof *opt.reports);
    const int w = pl_apparent->width, h = pl_apparent->height;
    const size_t n = (size_t)w * h;
    const int rl_pl = uses_rl_for_pl(opt.method), rl_field = uses_rl_for_field(opt.method);

    svp_status st = SVP_OK;
    unsigned char *missing = NULL;
    double *valid = NULL;
    svp_image *work = NULL, *coverage = NULL;
    svp_progress_share *shares = NULL;
    double *shifts = NULL;

    missing = malloc(n);
    valid = svp_alloc(n * sizeof(double));
    shares = calloc((size_t)n_fields + 1, sizeof *shares);
    shifts = calloc((size_t)n_fields, sizeof *shifts);
    if (!missing || !valid || !shares || !shifts) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d inverse transform", w, h);
        goto cleanup;
    }
    st = svp_image_new(w, h, &work);
    if (st != SVP_OK) goto cleanup;

    /* Missing data: a pixel where Ĩ or any B̃_c is NaN/Inf is missing in every deconvolution,
     * so numerator and denominator of (4) see the same measurements. */
    size_t n_miss = 0;
    {
        const double *restrict pl = pl_apparent->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN) reduction(+ : n_miss)
        for (size_t i = 0; i < n; i++) {
            int m = !isfinite(pl[i]);
            for (int c = 0; c < n_fields && !m; c++) m = !isfinite(field_apparent[c]->data[i]);
            missing[i] = (unsigned char)m;
            n_miss += (size_t)m;
        }
    }
    if (n_missing) *n_missing = n_miss;
    if (n_miss == n) {
        st = svp_fail(SVP_ERR_INVALID,
                      "every pixel of pl_apparent / field_apparent is NaN or Inf: nothing to "
                      "restore");
        goto cleanup;
    }
    double pl_in_max = -INFINITY;
    for (size_t i = 0; i < n; i++) {
        if (missing[i]) continue;
        double v = pl_apparent->data[i];
        if (v > pl_in_max) pl_in_max = v;
        if (rl_pl && v < 0) {
            st = svp_fail(SVP_ERR_INVALID,
                          "pl_apparent is negative (%g) at pixel (%zu, %zu): Richardson-Lucy "
                          "needs non-negative PL (clip the background or use method W)",
                          v, i % (size_t)w, i / (size_t)w);
            goto cleanup;
        }
    }

    if (!(pl_in_max > 0)) {
        /* No light anywhere: nothing to deconvolve, nothing known about the field. */
        memset(pl_true->data, 0, n * sizeof(double));
        for (int c = 0; c < n_fields; c++) memset(field_true[c]->data, 0, n * sizeof(double));
        memset(valid, 0, n * sizeof(double));
        goto finish;
    }

    /* Progress: each deconvolution's share is proportional to its FFT count (RL: iterations,
     * Wiener: about one; with the zero boundary its CG takes typically 25–80 steps of 1.5 RL
     * iterations' work each: counted as 40 iterations). */
    {
        /* the discrepancy principle adds 16 Wiener solves */
        const double cost_w = (svp_blur_boundary(blur) == SVP_BOUNDARY_ZERO ? 40.0 : 1.0) *
                              (opt.balance_auto ? 17.0 : 1.0);
        double cost_pl = rl_pl ? opt.deconv.iterations : cost_w;
        double cost_field = rl_field ? opt.deconv.iterations : cost_w;
        double total = cost_pl + n_fields * cost_field, at = 0;
        for (int k = 0; k <= n_fields; k++) {
            double cost = k == 0 ? cost_pl : cost_field;
            shares[k].fn = opt.deconv.progress;
            shares[k].user = opt.deconv.progress_user;
            shares[k].base = at / total;
            shares[k].span = cost / total;
            at += cost;
        }
    }

    /* The signed shifts (eq. 5), all checked before any deconvolution. */
    if (rl_field)
        for (int c = 0; c < n_fields; c++) {
            st = signed_shift(field_apparent[c], missing, n, &opt, c, &shifts[c]);
            if (st != SVP_OK) goto cleanup;
        }

    /* Ĩ ⊘ p, once for all components (eq. 4, denominator). */
    {
        const double *restrict pl = pl_apparent->data;
        double *restrict y = work->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) y[i] = missing[i] ? NAN : pl[i];
    }
    st = deconvolve(blur, work, rl_pl, &opt.deconv, opt.balance_auto, opt.noise_sigma, &shares[0],
                    opt.reports, pl_true);
    if (st != SVP_OK) {
        svp_fail_context(st, "deconvolving pl_apparent");
        goto cleanup;
    }
    const double pl_rec_max = svp_max(pl_true->data, n);
    const double floor_pl = opt.pl_floor * pl_rec_max;
    const int no_light = !(floor_pl > 0) || !isfinite(floor_pl);

    /* Validity (eq. 6): the recovered PL against the floor, times, at missing pixels, the share
     * of their light that the core PSF puts on measured pixels, c_i = (Hᵀm − α<m>)/(1 − α). */
    {
        const double *restrict pl_rec = pl_true->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            double v = no_light ? 0.0 : pl_rec[i] / floor_pl;
            valid[i] = v > 1 ? 1.0 : (v > 0 ? v : 0.0);
        }
    }
    if (n_miss > 0) {
        st = svp_image_new(w, h, &coverage);
        if (st != SVP_OK) goto cleanup;
        double *restrict m = work->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) m[i] = missing[i] ? 0.0 : 1.0;
        st = svp_blur_adjoint(blur, work, coverage);
        if (st != SVP_OK) goto cleanup;
        const double alpha = svp_blur_halo(blur);
        const double halo_part = alpha * (double)(n - n_miss) / (double)n;
        const double *restrict cov = coverage->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            if (!missing[i]) continue;
            double c = (cov[i] - halo_part) / (1.0 - alpha);
            c = c > 1 ? 1.0 : c;
            valid[i] *= c > COVERAGE_TINY ? c : 0.0;
        }
    }

    /* Numerators (B̃_c Ĩ) ⊘ p, or ((B̃_c + c) Ĩ) ⊘ p − c (Ĩ ⊘ p) for the RL methods. */
    for (int c = 0; c < n_fields; c++) {
        const double shift = shifts[c]; /* 0 unless rl_field */
        {
            const double *restrict pl = pl_apparent->data;
            const double *restrict b_app = field_apparent[c]->data;
            double *restrict y = work->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
            for (size_t i = 0; i < n; i++) y[i] = missing[i] ? NAN : (b_app[i] + shift) * pl[i];
        }
        st = deconvolve(blur, work, rl_field, &opt.deconv, opt.balance_auto, opt.noise_sigma,
                        &shares[c + 1], opt.reports ? &opt.reports[c + 1] : NULL, field_true[c]);
        if (st != SVP_OK) {
            char buf[32];
            svp_fail_context(st, "deconvolving %s x pl_apparent",
                             field_name(&opt, c, buf, sizeof buf));
            goto cleanup;
        }
        const double *restrict pl_rec = pl_true->data;
        double *restrict b = field_true[c]->data;
        /* Floored division (eq. 4): the recovered PL never drops below pl_floor · max. */
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            double num = b[i] - shift * pl_rec[i];
            b[i] = no_light ? 0.0 : num / (pl_rec[i] > floor_pl ? pl_rec[i] : floor_pl);
        }
    }

finish:;
    /* Last resort: never emit NaN/Inf (the tests assert this never fires). */
    size_t repaired = 0;
    for (int k = -1; k < n_fields; k++) {
        double *restrict d = k < 0 ? pl_true->data : field_true[k]->data;
        for (size_t i = 0; i < n; i++)
            if (!isfinite(d[i])) {
                d[i] = 0.0;
                valid[i] = 0.0;
                repaired++;
            }
    }
    for (size_t i = 0; i < n; i++)
        if (!isfinite(valid[i])) {
            valid[i] = 0.0;
            repaired++;
        }
    if (n_repaired) *n_repaired = repaired;
    if (validity) memcpy(validity->data, valid, n * sizeof(double));

cleanup:
    free(missing);
    svp_free(valid);
    free(shares);
    free(shifts);
    svp_image_free(work);
    svp_image_free(coverage);
    return st;
}

svp_status svp_inverse_transform(svp_blur *blur, const svp_image *pl_apparent,
                                 const svp_image *const *field_apparent, int n_fields,
                                 const svp_correct_options *options, svp_image *pl_true,
                                 svp_image *const *field_true, svp_image *validity,
                                 size_t *n_missing)
{
    return svp_inverse_transform_counted(blur, pl_apparent, field_apparent, n_fields, options,
                                         pl_true, field_true, validity, n_missing, NULL);
}

/* ---- closed-form halo correction (eq. 7) ------------------------------------------------- */

svp_status svp_halo_correct(double halo, const svp_image *pl_apparent,
                            const svp_image *field_apparent, svp_image *field_true)
{
    if (!(halo >= 0 && halo < 1))
        return svp_fail(SVP_ERR_INVALID, "halo fraction must be in [0, 1), got %g", halo);
    if (!pl_apparent || !pl_apparent->data) return svp_fail(SVP_ERR_INVALID, "pl_apparent is NULL");
    SVP_CHECK(check_same(field_apparent, "field_apparent", -1, pl_apparent, "pl_apparent"));
    SVP_CHECK(check_same(field_true, "field_true", -1, pl_apparent, "pl_apparent"));
    const size_t n = (size_t)pl_apparent->width * pl_apparent->height;
    size_t bad = svp_image_count_nonfinite(pl_apparent);
    if (bad)
        return svp_fail(SVP_ERR_INVALID,
                        "pl_apparent has %zu NaN/Inf pixels: the halo correction needs complete "
                        "maps (the halo is a mean over the whole field of view)",
                        bad);
    bad = svp_image_count_nonfinite(field_apparent);
    if (bad)
        return svp_fail(SVP_ERR_INVALID,
                        "field_apparent has %zu NaN/Inf pixels: the halo correction needs "
                        "complete maps (the halo is a mean over the whole field of view)",
                        bad);
    double *weighted = svp_alloc(n * sizeof(double));
    if (!weighted) return svp_fail(SVP_ERR_NOMEM, "out of memory for the halo correction");
    /* no restrict: field_true may alias either input (everything below is pointwise) */
    const double *pl = pl_apparent->data;
    const double *b_app = field_apparent->data;
    const double mean_pl = svp_sum(pl, n) / (double)n;
    const double mean_weighted = svp_dot(b_app, pl, weighted, n) / (double)n; /* weighted = B̃Ĩ */
    double pl_abs_max = fmax(fabs(svp_max(pl, n)), fabs(svp_min(pl, n)));
    const double tiny = HALO_DEN_TINY * pl_abs_max;
    double *b = field_true->data;
    /* B = (B̃Ĩ − α<B̃Ĩ>) / (Ĩ − α<Ĩ>) (eq. 7) */
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        double den = pl[i] - halo * mean_pl;
        double num = weighted[i] - halo * mean_weighted;
        b[i] = den > tiny ? num / den : 0.0;
    }
    svp_free(weighted);
    return SVP_OK;
}
