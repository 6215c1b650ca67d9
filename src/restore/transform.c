/* The transforms T (eq. 3) and T⁻¹ (eq. 4; signed shift eq. 5, validity eq. 6) of
 * docs/model.md, and the closed-form halo correction (eq. 7). Everything goes through
 * svp_blur_apply / svp_blur_adjoint and the two deconvolutions, so the same code serves
 * space-invariant and space-variant operators. */
#include "restore_internal.h"

#include <omp.h>

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Forward model: Ĩ at or below FORWARD_PL_TINY · max Ĩ is dark (B̃ = 0, validity 0). The FFT
 * convolution leaves round-off of ~1e-16 · max Ĩ where the true Ĩ is 0; dividing by that would
 * return noise, so the threshold sits 1e6 above it and far below any PL a camera records. */
#define FORWARD_PL_TINY 1e-10
/* The same for an operator in single precision, whose round-off is ~1e-7 · max Ĩ. */
#define FORWARD_PL_TINY_SINGLE 1e-5
/* Maps whose largest |value| lies beyond 2^±FORWARD_SCALE_BITS are scaled to unit size (and
 * back) by a power of two: B I and a float FFT's sums stay finite (float's range is 2^±126). */
#define FORWARD_SCALE_BITS 60
/* Halo correction: denominators Ĩ − α<Ĩ> at or below HALO_DEN_TINY · max|Ĩ| carry no light
 * (the subtraction itself leaves round-off of ~1e-16 · max|Ĩ|). */
#define HALO_DEN_TINY 1e-10
/* Pointwise loops run in parallel only above this many pixels (below, threads cost more). */
#define PAR_MIN 32768
/* Coverage of a missing pixel by measured ones below this is FFT round-off: nothing covers it. */
#define COVERAGE_TINY 1e-9
/* The automatic signed shift c = SHIFT_FACTOR · max|B̃| (eq. 5; docs/model.md §3) */
#define SHIFT_FACTOR 100.0

/* Used by the tests to assert that the last-resort NaN/Inf repair of T⁻¹ never fires. */
svp_status svp_inverse_transform_counted(svp_blur *blur, const svp_image *pl_apparent,
                                         const svp_image *const *field_apparent, int n_fields,
                                         const svp_correct_options *options, svp_image *pl_true,
                                         svp_image *const *field_true, svp_image *validity,
                                         size_t *n_missing, size_t *n_repaired);

void svp_correct_defaults(svp_correct_options *options)
{
    options->method = SVP_METHOD_R; /* the foreign-data benchmark's winner (docs/accuracy.md) */
    svp_deconv_defaults(&options->deconv);
    options->deconv.iterations = 75; /* the reference study's RL count for measured data */
    options->pl_floor = 1e-3;
    options->shift = 0.0;
    options->balance_auto = 0;
    options->noise_sigma = 0.0;
    options->reports = NULL;
    options->field_names = NULL;
    options->pl_name = NULL;
    options->margin = 0;
    options->auto_iterations = 0;
    options->pl_gain = 0.0;
    options->pl_offset = 0.0;
    options->field_sigma = NULL;
    options->keep_doubtful = 0;
    options->plausible_factor = 10.0;
    options->shrink_factor = 0.1;
    options->summary = NULL;
    options->side_by_side = 1;
    options->tail_tol = SVP_TAIL_TOL_DEFAULT;
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

/* The operator covers the image plus `margin` pixels on every side. */
static svp_status check_operator(const svp_blur *blur, const svp_image *image, const char *what,
                                 int margin)
{
    if (!blur) return svp_fail(SVP_ERR_INVALID, "the blur operator is NULL");
    if (!image || !image->data) return svp_fail(SVP_ERR_INVALID, "%s is NULL", what);
    if (image->width + 2 * margin != svp_blur_width(blur) ||
        image->height + 2 * margin != svp_blur_height(blur)) {
        if (margin)
            return svp_fail(SVP_ERR_SIZE,
                            "%s is %d x %d: with a margin of %d pixels the blur operator must be "
                            "%d x %d, but it is %d x %d",
                            what, image->width, image->height, margin,
                            image->width + 2 * margin, image->height + 2 * margin,
                            svp_blur_width(blur), svp_blur_height(blur));
        return svp_fail(SVP_ERR_SIZE, "%s is %d x %d but the blur operator is %d x %d", what,
                        image->width, image->height, svp_blur_width(blur), svp_blur_height(blur));
    }
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
                                       const char *out_field, int margin)
{
    if (!blur) return svp_fail(SVP_ERR_INVALID, "the blur operator is NULL");
    if (n_fields < 1)
        return svp_fail(SVP_ERR_INVALID, "n_fields = %d: at least one field component is needed",
                        n_fields);
    if (!fields) return svp_fail(SVP_ERR_INVALID, "the %s array is NULL", in_field);
    if (!fields_out) return svp_fail(SVP_ERR_INVALID, "the %s array is NULL", out_field);
    SVP_CHECK(check_operator(blur, pl, in_pl, margin));
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
                                   "field_apparent", 0));
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
    /* no light: every apparent field would be undefined (0 with validity 0 at every pixel) */
    if (!(svp_max(pl_true->data, n) > 0))
        return svp_fail(SVP_ERR_INVALID,
                        "pl_true holds no light (0 at every pixel): the apparent field is "
                        "undefined everywhere");

    svp_image *product = NULL, *pl_unit = NULL;
    svp_status st = svp_image_new(w, h, &product);
    if (st != SVP_OK) return st;

    /* Maps of extreme magnitude (beyond 2^±60) are brought to unit size by powers of two and
     * back: exact, so ordinary maps give the same bits, and neither B I nor a float FFT
     * overflows (a PL and a field of 1e160 each, or 1e20 in single precision, gave NaN fields
     * of validity 1; a PL of 1e36 in single precision a PL of 0) */
    const int ki = svp_unit_exponent(pl_true->data, n, FORWARD_SCALE_BITS);
    const svp_image *pl_in = pl_true;
    if (ki) {
        if ((st = svp_image_new(w, h, &pl_unit)) != SVP_OK) goto cleanup;
        for (size_t i = 0; i < n; i++) pl_unit->data[i] = ldexp(pl_true->data[i], ki);
        pl_in = pl_unit;
    }

    /* Ĩ = H I (eq. 3b). Ĩ of a non-negative I is non-negative: negative values are round-off. */
    st = svp_blur_apply(blur, pl_in, pl_apparent);
    if (st != SVP_OK) goto cleanup;
    double *restrict pl_app = pl_apparent->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++)
        if (!(pl_app[i] > 0)) pl_app[i] = 0.0;
    const double pl_max = svp_max(pl_app, n);
    const double tiny = blur->single ? FORWARD_PL_TINY_SINGLE : FORWARD_PL_TINY;
    const double dark = pl_max > 0 ? tiny * pl_max : INFINITY;

    /* B̃_c Ĩ = H(B_c I) (eq. 3a), one application per component. */
    for (int c = 0; c < n_fields; c++) {
        const double *restrict b_true = field_true[c]->data;
        const double *restrict i_true = pl_in->data;
        double *restrict prod = product->data;
        const int kb = svp_unit_exponent(b_true, n, FORWARD_SCALE_BITS);
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++)
            prod[i] = (kb ? ldexp(b_true[i], kb) : b_true[i]) * i_true[i];
        st = svp_blur_apply(blur, product, field_apparent[c]);
        if (st != SVP_OK) goto cleanup;
        double *restrict b_app = field_apparent[c]->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            const double v = pl_app[i] > dark ? b_app[i] / pl_app[i] : 0.0;
            b_app[i] = kb ? ldexp(v, -kb) : v;
        }
    }
    if (validity) {
        double *restrict v = validity->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) v[i] = pl_app[i] > dark ? 1.0 : 0.0;
    }
    if (ki)
        for (size_t i = 0; i < n; i++) pl_app[i] = ldexp(pl_app[i], -ki);
cleanup:
    svp_image_free(product);
    svp_image_free(pl_unit);
    return st;
}

/* ---- inverse transform T⁻¹ (eq. 4) ------------------------------------------------------- */

static int uses_rl_for_pl(svp_method m) { return m != SVP_METHOD_W; }
static int uses_rl_for_field(svp_method m)
{
    return m == SVP_METHOD_R || m == SVP_METHOD_RL_SIGNED;
}

/* y ⊘ p with the method's deconvolution, progress forwarded as the share `share`. variance
 * (may be NULL) is y's noise variance: RL's stopping rule (with auto_stop) and the Wiener
 * discrepancy principle (balance_auto; noise_sigma > 0 overrides it with one σ) use it.
 * report (may be NULL) receives what it did. */
static svp_status deconvolve(svp_blur *blur, const svp_image *y, int use_rl,
                             const svp_deconv_options *base, int balance_auto, double noise_sigma,
                             const svp_image *variance, svp_progress_share *share,
                             svp_deconv_report *report, svp_image *x, const double *alpha_in,
                             double *alpha_out, svp_rl_levels **levels)
{
    svp_deconv_options o = *base;
    o.report = report;
    if (use_rl && o.auto_stop) o.variance = variance;
    if (base->progress) {
        o.progress = svp_progress_share_fn;
        o.progress_user = share;
    }
    double sigma_used = 0;
    int at_bound = 0, lcurve = 0;
    if (!use_rl && balance_auto) {
        /* the search's solves take the default step cap; the final solve the caller's */
        svp_deconv_options d;
        svp_deconv_defaults(&d);
        SVP_CHECK(svp_wiener_balance_discrepancy_var(blur, y, noise_sigma > 0 ? NULL : variance,
                                                     noise_sigma, d.cg_max_steps, &o.balance,
                                                     &sigma_used, &at_bound, &lcurve));
    }
    if (!share) o.progress = NULL;
    svp_status st = use_rl ? svp_deconv_rl_path(blur, y, &o, x, alpha_in, alpha_out, levels)
                           : svp_deconv_wiener(blur, y, &o, x);
    if (report && !use_rl) {
        report->noise_sigma = sigma_used;
        report->noise_per_pixel = balance_auto && noise_sigma <= 0 && variance != NULL;
        report->balance_at_bound = at_bound;
        report->balance_lcurve = lcurve;
    }
    if (st != SVP_OK) return st;
    if (base->progress && share) {
        /* the share's end; the last share's is 1 exactly, which base + span (rescaled after a
         * fallback from side by side) can miss by an ulp */
        double end = share->base + share->span;
        if (end > 1 - 1e-12) end = 1;
        if (share->fn(share->user, end))
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
    if (!(o->noise_sigma >= 0) || !isfinite(o->noise_sigma))
        return svp_fail(SVP_ERR_INVALID,
                        "noise_sigma must be >= 0 and finite (0: estimated), got %g",
                        o->noise_sigma);
    if (!(o->tail_tol >= 0 && o->tail_tol < 1))
        return svp_fail(SVP_ERR_INVALID, "tail_tol must be in [0, 1), got %g", o->tail_tol);
    if (o->margin < 0)
        return svp_fail(SVP_ERR_INVALID, "margin must be >= 0 pixels, got %d", o->margin);
    if (!(o->pl_gain >= 0) || !isfinite(o->pl_gain))
        return svp_fail(SVP_ERR_INVALID, "pl_gain must be >= 0 and finite, got %g", o->pl_gain);
    if (!isfinite(o->pl_offset))
        return svp_fail(SVP_ERR_INVALID, "pl_offset must be finite, got %g", o->pl_offset);
    if (o->side_by_side != 0 && o->side_by_side != 1)
        return svp_fail(SVP_ERR_INVALID, "side_by_side must be 0 or 1, got %d", o->side_by_side);
    if (!(o->plausible_factor > 1) || !isfinite(o->plausible_factor))
        return svp_fail(SVP_ERR_INVALID, "plausible_factor must be > 1 and finite, got %g",
                        o->plausible_factor);
    if (!(o->shrink_factor >= 0 && o->shrink_factor < 1))
        return svp_fail(SVP_ERR_INVALID, "shrink_factor must be in [0, 1), got %g",
                        o->shrink_factor);
    if (o->auto_iterations && o->method == SVP_METHOD_W)
        return svp_fail(SVP_ERR_INVALID,
                        "auto_iterations needs a Richardson-Lucy method (RW, R, RL_SIGNED), not W");
    if (o->method != SVP_METHOD_R && o->method != SVP_METHOD_RL_SIGNED && !o->balance_auto &&
        !(o->deconv.balance >= 0 && isfinite(o->deconv.balance)))
        return svp_fail(SVP_ERR_INVALID, "Wiener balance must be >= 0 and finite, got %g",
                        o->deconv.balance);
    return SVP_OK;
}

svp_status svp_correct_check_margin(int margin, int width, int height)
{
    const int side = width > height ? width : height;
    if (margin > side)
        return svp_fail(SVP_ERR_INVALID,
                        "a margin of %d pixels is wider than the view's larger side (%d pixels): "
                        "the data barely see pixels that far, and the work grows with the square "
                        "of the grid; use at most %d (auto: the PSF's reach)",
                        margin, side, side);
    return SVP_OK;
}

/* What messages call the PL map. */
static const char *pl_name(const svp_correct_options *o)
{
    return o->pl_name ? o->pl_name : "pl_apparent";
}

/* What messages call field map c. */
static const char *field_name(const svp_correct_options *o, int c, char *buf, size_t size)
{
    if (o->field_names && o->field_names[c]) return o->field_names[c];
    snprintf(buf, size, "field_apparent[%d]", c);
    return buf;
}

/* The shift c of eq. 5 for component `c`: B̃ + c > 0 at every measured pixel. RL's result is
 * >= 0, so c must clear the true field's minimum, which blurring hides (a narrow strip's true
 * peak is several times its measured one): the automatic c = 100 max|B̃| does, and it makes the
 * numerator's RL the PL's own plus a small linear response, so their residual errors cancel in
 * eq. 5 (docs/model.md §3, "Why this c"). */
static svp_status signed_shift(const svp_image *field, const unsigned char *missing, size_t n,
                               const svp_correct_options *o, int c, double *shift)
{
    const double requested = o->shift;
    double lo = INFINITY, big = 0;
    size_t at = 0;
    for (size_t i = 0; i < n; i++) {
        if (missing[i]) continue;
        double v = field->data[i];
        if (v < lo) {
            lo = v;
            at = i;
        }
        if (fabs(v) > big) big = fabs(v);
    }
    if (requested == 0) {
        *shift = big > 0 ? SHIFT_FACTOR * big : 1.0;
        return SVP_OK;
    }
    char buf[32];
    const size_t w = (size_t)field->width, m = (size_t)o->margin; /* named in the view's pixels */
    if (!(lo + requested > 0))
        return svp_fail(SVP_ERR_INVALID,
                        "%s: the shift c = %g leaves the field + c = %g <= 0 at pixel (x %zu, "
                        "y %zu) (field minimum %g there): the signed shift needs c > %g (or c = "
                        "0: automatic)",
                        field_name(o, c, buf, sizeof buf), requested, lo + requested,
                        at % w - m, at / w - m, lo, -lo);
    *shift = requested;
    return SVP_OK;
}

/* The noise variance of a numerator (B̃ + shift) Ĩ: (B̃ + shift)² var Ĩ + Ĩ² σ_B², var Ĩ from the
 * PL map (else pl_var_const), σ_B from the caller's map (else k²/Ĩ, k² estimated). *out = var,
 * or NULL when no part of the model is known (the caller then estimates one σ). */
static svp_status numerator_variance(const svp_image *field, double shift, const svp_image *pl,
                                     const unsigned char *missing, const svp_image *pl_var,
                                     double pl_var_const, const svp_image *sigma,
                                     svp_image *var, const svp_image **out)
{
    const size_t n = (size_t)pl->width * pl->height;
    double k2 = 0;
    *out = NULL;
    if (!sigma) SVP_CHECK(svp_field_noise_k2(field, pl, &k2));
    const double *restrict p = pl->data, *restrict b = field->data;
    const double *restrict sig = sigma ? sigma->data : NULL;
    double *restrict v = var->data;
    double v_max = 0;
    for (size_t i = 0; i < n; i++) {
        if (missing[i]) {
            v[i] = 1.0;
            continue;
        }
        const double vi = pl_var ? pl_var->data[i] : pl_var_const;
        const double pi = p[i] > 0 ? p[i] : 0.0, bs = b[i] + shift;
        const double sb2 = sig ? (isfinite(sig[i]) ? sig[i] * sig[i] : 0.0) : (pi > 0 ? k2 / pi : 0.0);
        v[i] = bs * bs * vi + pi * pi * sb2;
        if (v[i] > v_max) v_max = v[i];
    }
    if (!(v_max > 0)) return SVP_OK;
    for (size_t i = 0; i < n; i++)
        if (!missing[i] && !(v[i] > 1e-12 * v_max)) v[i] = 1e-12 * v_max;
    *out = var;
    return SVP_OK;
}

/* The state of one T⁻¹ on the operator's grid (the view plus any margin, whose pixels arrive as
 * NaN: missing), shared by its stages below. */
typedef struct inverse_run {
    svp_blur *blur;
    const svp_image *pl_apparent;
    const svp_image *const *field_apparent;
    const svp_image *const *field_sigma; /* may be NULL */
    int n_fields, w, h, rl_pl, rl_field, accel;
    size_t n, n_miss;
    svp_correct_options opt;
    svp_image *pl_true, *const *field_true;
    double *valid; /* the validity map's pixels */
    svp_deconv_report *reports;
    double *shifts;
    unsigned char *missing;
    svp_image *work, *pl_var, *num_var;
    svp_progress_share *shares;
    double *alphas; /* the PL's extrapolation path (accelerated RL) */
    svp_rl_levels *levels; /* the PL's RL levels (operator built in single precision), which
                              the numerators' RL use too: their float round-off cancels in (4) */
    int *counts;    /* RL iterations of every numerator */
    /* side by side (deconvolve_side_by_side): one copy of the operator per worker, the first
     * kept for the validity map */
    svp_blur **copies;
    int n_copies;
    double progress_reached; /* the last fraction side by side reported, before a fallback */
} inverse_run;

/* Missing data: a pixel where Ĩ or any B̃_c is NaN/Inf is missing in every deconvolution, so
 * numerator and denominator of (4) see the same measurements; so is one whose σ (field_sigma)
 * is NaN/Inf, a fit that failed to say its uncertainty (its NaN σ poisoned the discrepancy
 * sums: λ blew the field up). *pl_max: the largest measured Ĩ. */
static svp_status mark_missing(inverse_run *r, double *pl_max)
{
    const size_t n = r->n;
    const double *restrict pl = r->pl_apparent->data;
    size_t n_miss = 0;
#pragma omp parallel for schedule(static) if (n > PAR_MIN) reduction(+ : n_miss)
    for (size_t i = 0; i < n; i++) {
        int m = !isfinite(pl[i]);
        for (int c = 0; c < r->n_fields && !m; c++) m = !isfinite(r->field_apparent[c]->data[i]);
        for (int c = 0; r->field_sigma && c < r->n_fields && !m; c++)
            m = r->field_sigma[c] && !isfinite(r->field_sigma[c]->data[i]);
        r->missing[i] = (unsigned char)m;
        n_miss += (size_t)m;
    }
    r->n_miss = n_miss;
    if (n_miss == n) {
        /* name the input that has no measured pixel, else say that no pixel has them all */
        char buf[64];
        if (svp_image_count_nonfinite(r->pl_apparent) == n)
            return svp_fail(SVP_ERR_INVALID, "every pixel of %s is NaN or Inf: nothing to restore",
                            pl_name(&r->opt));
        for (int c = 0; c < r->n_fields; c++)
            if (svp_image_count_nonfinite(r->field_apparent[c]) == n)
                return svp_fail(SVP_ERR_INVALID, "every pixel of %s is NaN or Inf: nothing to "
                                "restore", field_name(&r->opt, c, buf, sizeof buf));
        return svp_fail(SVP_ERR_INVALID, "no pixel is measured in %s and every field map at "
                        "once (each has NaN or Inf in one of them): nothing to restore",
                        pl_name(&r->opt));
    }
    double top = -INFINITY;
    for (size_t i = 0; i < n; i++) {
        if (r->missing[i]) continue;
        if (pl[i] > top) top = pl[i];
        if (r->rl_pl && pl[i] < 0) /* named in the view's pixels: the grid holds the margin */
            return svp_fail(SVP_ERR_INVALID,
                            "%s is negative (%g) at pixel (%zu, %zu): Richardson-Lucy "
                            "needs non-negative PL (clip the background or use method W)",
                            pl_name(&r->opt), pl[i], i % (size_t)r->w - (size_t)r->opt.margin,
                            i / (size_t)r->w - (size_t)r->opt.margin);
    }
    /* no light anywhere (a PL of zeros, or an offset above every value): every pixel would
     * come back with validity 0 and a field of 0 */
    if (!(top > 0))
        return svp_fail(SVP_ERR_INVALID,
                        "%s holds no light: its largest measured value is %g%s: nothing to "
                        "restore",
                        pl_name(&r->opt), top,
                        r->opt.pl_offset != 0 ? " after the offset is subtracted (check it)" : "");
    *pl_max = top;
    return SVP_OK;
}

/* Progress: each deconvolution's share is proportional to its FFT count (RL: iterations,
 * Wiener: about one; with the zero boundary its CG takes typically 25–80 steps of 1.5 RL
 * iterations' work each: counted as 40 iterations; the discrepancy principle adds 16 solves). */
static void plan_progress(inverse_run *r)
{
    const svp_correct_options *o = &r->opt;
    const double cost_w = (svp_blur_boundary(r->blur) == SVP_BOUNDARY_ZERO ? 40.0 : 1.0) *
                          (o->balance_auto ? 17.0 : 1.0);
    const double cost_pl = r->rl_pl ? o->deconv.iterations : cost_w;
    const double cost_field = r->rl_field ? o->deconv.iterations : cost_w;
    const double total = cost_pl + r->n_fields * cost_field;
    double at = 0;
    for (int k = 0; k <= r->n_fields; k++) {
        const double cost = k == 0 ? cost_pl : cost_field;
        r->shares[k].fn = o->deconv.progress;
        r->shares[k].user = o->deconv.progress_user;
        r->shares[k].base = at / total;
        r->shares[k].span = cost / total;
        at += cost;
    }
}

/* work = Ĩ with the missing pixels NaN. */
static void load_pl(inverse_run *r, svp_image *work)
{
    const double *restrict pl = r->pl_apparent->data;
    double *restrict y = work->data;
#pragma omp parallel for schedule(static) if (r->n > PAR_MIN)
    for (size_t i = 0; i < r->n; i++) y[i] = r->missing[i] ? NAN : pl[i];
}

/* Ĩ ⊘ p (eq. 4, denominator), once for all components; the PL's noise variance
 * var Ĩ = g · max(Ĩ, g) (at least one photon's) for RL's stopping rule and W's discrepancy. */
static svp_status deconvolve_pl(inverse_run *r, svp_blur *blur, svp_image *work)
{
    const svp_correct_options *o = &r->opt;
    if ((o->auto_iterations || o->balance_auto) && o->pl_gain > 0) {
        SVP_CHECK(svp_image_new(r->w, r->h, &r->pl_var));
        const double g = o->pl_gain;
        const double *restrict pl = r->pl_apparent->data;
        double *restrict v = r->pl_var->data;
#pragma omp parallel for schedule(static) if (r->n > PAR_MIN)
        for (size_t i = 0; i < r->n; i++) v[i] = r->missing[i] ? 1.0 : g * (pl[i] > g ? pl[i] : g);
    }
    if (r->accel && !(r->alphas = malloc((size_t)o->deconv.iterations * sizeof *r->alphas)))
        return svp_fail(SVP_ERR_NOMEM, "out of memory for the extrapolation path");
    svp_deconv_options d = o->deconv;
    d.auto_stop = o->auto_iterations;
    load_pl(r, work);
    svp_status st = deconvolve(blur, work, r->rl_pl, &d, o->balance_auto, o->noise_sigma,
                               r->pl_var, &r->shares[0], &r->reports[0], r->pl_true, NULL,
                               r->alphas, &r->levels);
    if (st != SVP_OK) return svp_fail_context(st, "deconvolving %s", pl_name(o));
    return SVP_OK;
}

/* Numerator c: (B̃_c Ĩ) ⊘ p, or ((B̃_c + c) Ĩ) ⊘ p for the RL methods (the shift is removed in
 * divide_fields), into field_true[c]; RL runs at most `count` iterations on the PL's path and,
 * with automatic iterations on the first pass, stops by its own noise. */
static svp_status deconvolve_numerator(inverse_run *r, svp_blur *blur, svp_image *work, int c,
                                       int count, int first_pass, double pl_var_const)
{
    const svp_correct_options *o = &r->opt;
    const double shift = r->shifts[c]; /* 0 unless rl_field */
    {
        const double *restrict pl = r->pl_apparent->data;
        const double *restrict b_app = r->field_apparent[c]->data;
        double *restrict y = work->data;
#pragma omp parallel for schedule(static) if (r->n > PAR_MIN)
        for (size_t i = 0; i < r->n; i++) y[i] = r->missing[i] ? NAN : (b_app[i] + shift) * pl[i];
    }
    const svp_image *var_c = NULL;
    const int auto_num = first_pass && o->auto_iterations && r->rl_field;
    if ((o->balance_auto && !r->rl_field) || auto_num) {
        if (!r->num_var) SVP_CHECK(svp_image_new(r->w, r->h, &r->num_var));
        SVP_CHECK(numerator_variance(r->field_apparent[c], shift, r->pl_apparent, r->missing,
                                     r->pl_var, pl_var_const,
                                     r->field_sigma ? r->field_sigma[c] : NULL, r->num_var,
                                     &var_c));
    }
    svp_deconv_options d = o->deconv;
    d.auto_stop = auto_num;
    if (r->rl_field) d.iterations = count;
    svp_status st = deconvolve(blur, work, r->rl_field, &d, o->balance_auto,
                               o->noise_sigma, var_c, first_pass ? &r->shares[c + 1] : NULL,
                               &r->reports[c + 1], r->field_true[c],
                               r->accel ? r->alphas : NULL, NULL, &r->levels);
    if (st != SVP_OK) {
        char buf[32];
        return svp_fail_context(st, "deconvolving %s x %s", field_name(o, c, buf, sizeof buf),
                                pl_name(o));
    }
    r->counts[c] = r->rl_field ? r->reports[c + 1].iterations : count;
    return SVP_OK;
}

/* Every numerator, at the same RL count as the PL so both halves of (4) share their resolution.
 * With automatic iterations each numerator may stop earlier (its noise includes the field's):
 * the smallest count wins, and whatever ran longer — the PL included, on its own path — is run
 * again to it. */
static svp_status deconvolve_numerators(inverse_run *r)
{
    const svp_correct_options *o = &r->opt;
    int count = o->deconv.iterations;
    if (r->rl_pl && o->auto_iterations)
        count = r->reports[0].iterations > 0 ? r->reports[0].iterations : 1;
    double pl_var_const = 0; /* without a gain: one PL variance for the numerators' noise */
    if ((o->balance_auto || o->auto_iterations) && !r->pl_var) {
        double sigma = 0;
        if (svp_noise_sigma_estimate(r->pl_apparent, &sigma) == SVP_OK) pl_var_const = sigma * sigma;
    }
    const int k_pl = count;
    for (int c = 0; c < r->n_fields; c++) {
        SVP_CHECK(deconvolve_numerator(r, r->blur, r->work, c, count, 1, pl_var_const));
        if (r->counts[c] < count) count = r->counts[c];
    }
    if (count == k_pl) return SVP_OK;
    for (int c = 0; c < r->n_fields; c++)
        if (r->counts[c] != count)
            SVP_CHECK(deconvolve_numerator(r, r->blur, r->work, c, count, 0, pl_var_const));
    svp_deconv_options d = o->deconv;
    d.auto_stop = 0;
    d.iterations = count;
    const int stop = r->reports[0].stop;
    const double chi2 = r->reports[0].chi2;
    load_pl(r, r->work);
    SVP_CHECK(deconvolve(r->blur, r->work, 1, &d, 0, 0, NULL, NULL, &r->reports[0], r->pl_true,
                         r->accel ? r->alphas : NULL, NULL, &r->levels));
    /* the count was the numerators' noise's choice, not the cap */
    r->reports[0].stop = stop == SVP_RL_STOP_CAP ? SVP_RL_STOP_DISCREPANCY : stop;
    r->reports[0].chi2 = chi2;
    return SVP_OK;
}

/* Side by side: plain Richardson–Lucy with a fixed count on both halves of (4) (method R
 * without acceleration or automatic choices) needs no result of one deconvolution in another,
 * so with two or more threads the PL's and each numerator's run at the same time, each worker
 * on its own copy of the operator (svp_blur_clone: a second frame and its buffers; for a PSF
 * map in double precision also its accumulators, the term spectra shared).
 * FFTW's own threads gain 1.0–1.55× on two cores at these sizes, two one-thread transforms at
 * once nearly 2× (docs/performance.md). The arithmetic of each run is unchanged; only its FFT
 * plans (thread count) differ, so results agree with the sequential order to the transforms'
 * round-off.
 *
 * A worker's FFTs (fftw3_omp) and loops are OpenMP regions nested in the workers' region, which
 * OpenMP runs on one thread unless nesting is allowed (OMP_MAX_ACTIVE_LEVELS ≥ 2; the default
 * is 1). So the runs go side by side when there are no more threads than runs (a worker per
 * thread, one thread each), or with more threads when nesting is allowed (threads / workers
 * each); otherwise in order, every FFT on all threads, which on a machine with more cores than
 * runs is faster than leaving cores idle. */
#define SIDE_BY_SIDE_MIN (128 * 128)

static int side_by_side_workers(const inverse_run *r)
{
    const svp_correct_options *o = &r->opt;
    if (!o->side_by_side) return 1; /* the caller's choice: in order */
    if (!r->rl_pl || !r->rl_field || r->accel || o->auto_iterations || o->balance_auto) return 1;
    if (!svp_blur_clonable(r->blur) || r->n < SIDE_BY_SIDE_MIN) return 1;
    const int threads = svp_get_threads(), tasks = 1 + r->n_fields;
    /* the levels still free: the workers' region needs one, their threads another */
    const int free_levels = omp_get_max_active_levels() - omp_get_active_level();
    if (threads < 2 || free_levels < 1) return 1;
    if (threads <= tasks) return threads;
    return free_levels >= 2 ? tasks : 1;
}

/* The progress of runs side by side: each run reports its own fraction, the caller gets their
 * sum weighted by the runs' shares, one call at a time; a cancel stops every run. */
typedef struct progress_sum {
    svp_progress_fn fn;
    void *user;
    const svp_progress_share *shares; /* each run's share of the whole (plan_progress) */
    double *done;                     /* each run's fraction */
    double *reached;                  /* the last sum reported */
    int n, stop;
} progress_sum;

typedef struct progress_part {
    progress_sum *sum;
    int k;
} progress_part;

static int progress_part_fn(void *user, double fraction)
{
    progress_part *p = user;
    progress_sum *s = p->sum;
    int stop;
#pragma omp critical(svp_inverse_progress)
    {
        s->done[p->k] = fraction;
        double at = 0;
        for (int k = 0; k < s->n; k++) at += s->shares[k].span * s->done[k];
        if (!s->stop && s->fn(s->user, at)) s->stop = 1;
        *s->reached = at;
        stop = s->stop;
    }
    return stop;
}

static void drop_copies(inverse_run *r)
{
    if (r->copies)
        for (int t = 0; t < r->n_copies; t++) svp_blur_free(r->copies[t]);
    free(r->copies);
    r->copies = NULL;
    r->n_copies = 0;
}

static svp_status deconvolve_side_by_side(inverse_run *r, int workers)
{
    const int tasks = 1 + r->n_fields;
    svp_status st = SVP_OK;
    svp_image **works = calloc((size_t)workers, sizeof *works);
    svp_status *status = calloc((size_t)tasks, sizeof *status);
    char(*msg)[SVP_ERROR_LEN] = calloc((size_t)tasks, sizeof *msg);
    svp_progress_share *all = calloc((size_t)tasks, sizeof *all);
    double *done = calloc((size_t)tasks, sizeof *done);
    progress_part *parts = calloc((size_t)tasks, sizeof *parts);
    r->copies = calloc((size_t)workers, sizeof *r->copies);
    if (!works || !status || !msg || !all || !done || !parts || !r->copies) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d inverse transform", r->w, r->h);
        goto cleanup;
    }
    r->n_copies = workers;
    /* each worker's share of the threads, for its FFT plans and its own loops (which only get
     * them where nesting is allowed: side_by_side_workers); a PSF map's copy takes its plans
     * when it is made, an invariant one when first used in its worker */
    const int per_worker = svp_get_threads() / workers > 1 ? svp_get_threads() / workers : 1;
    svp_fft_local_threads(per_worker);
    for (int t = 0; t < workers && st == SVP_OK; t++) {
        st = svp_blur_clone(r->blur, &r->copies[t]);
        if (st == SVP_OK) st = svp_image_new(r->w, r->h, &works[t]);
    }
    svp_fft_local_threads(0);
    if (st != SVP_OK) goto cleanup;
    /* progress: each run's own fraction, summed for the caller */
    memcpy(all, r->shares, (size_t)tasks * sizeof *all);
    progress_sum sum = {.fn = r->opt.deconv.progress, .user = r->opt.deconv.progress_user,
                        .shares = all, .done = done, .reached = &r->progress_reached,
                        .n = tasks};
    for (int k = 0; k < tasks; k++) {
        parts[k] = (progress_part){.sum = &sum, .k = k};
        r->shares[k] = (svp_progress_share){.fn = progress_part_fn, .user = &parts[k], .base = 0,
                                            .span = 1};
    }
#pragma omp parallel num_threads(workers)
    {
        const int t = omp_get_thread_num();
        svp_fft_local_threads(per_worker);
        omp_set_num_threads(per_worker);
#pragma omp for schedule(dynamic, 1)
        for (int k = 0; k < tasks; k++) {
            svp_clear_error();
            status[k] = k == 0 ? deconvolve_pl(r, r->copies[t], works[t])
                               : deconvolve_numerator(r, r->copies[t], works[t], k - 1,
                                                      r->opt.deconv.iterations, 1, 0);
            if (status[k] != SVP_OK) snprintf(msg[k], SVP_ERROR_LEN, "%s", svp_last_error());
        }
        svp_fft_local_threads(0);
    }
    memcpy(r->shares, all, (size_t)tasks * sizeof *all);
    for (int k = 0; k < tasks; k++)
        if (status[k] != SVP_OK) {
            st = svp_fail(status[k], "%s", msg[k]);
            break;
        }
cleanup:
    if (works)
        for (int t = 0; t < workers; t++) svp_image_free(works[t]);
    free(works);
    free(status);
    free(msg);
    free(all);
    free(done);
    free(parts);
    return st;
}

/* Validity (eq. 6): the recovered PL against the floor, times, at missing pixels, the share of
 * their light that the core PSF puts on measured pixels, c_i = (Hᵀm − α<m>)/(1 − α). */
static svp_status validity_map(inverse_run *r, double floor_pl, int no_light)
{
    const size_t n = r->n;
    const double *restrict pl_rec = r->pl_true->data;
    double *restrict valid = r->valid;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        double v = no_light ? 0.0 : pl_rec[i] / floor_pl;
        valid[i] = v > 1 ? 1.0 : (v > 0 ? v : 0.0);
    }
    if (r->n_miss == 0) return SVP_OK;
    svp_image *coverage = NULL;
    SVP_CHECK(svp_image_new(r->w, r->h, &coverage));
    double *restrict m = r->work->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) m[i] = r->missing[i] ? 0.0 : 1.0;
    svp_blur *blur = r->n_copies ? r->copies[0] : r->blur;
    svp_status st = svp_blur_adjoint(blur, r->work, coverage);
    if (st == SVP_OK) {
        const double alpha = svp_blur_halo(blur);
        const double halo_part = alpha * (double)(n - r->n_miss) / (double)n;
        const double *restrict cov = coverage->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) {
            if (!r->missing[i]) continue;
            double c = (cov[i] - halo_part) / (1.0 - alpha);
            c = c > 1 ? 1.0 : c;
            valid[i] *= c > COVERAGE_TINY ? c : 0.0;
        }
    }
    svp_image_free(coverage);
    return st;
}

/* Floored division (eq. 4), the shift removed (eq. 5): the recovered PL never drops below
 * pl_floor · max. */
static void divide_fields(inverse_run *r, double floor_pl, int no_light)
{
    for (int c = 0; c < r->n_fields; c++) {
        const double shift = r->shifts[c];
        const double *restrict pl_rec = r->pl_true->data;
        double *restrict b = r->field_true[c]->data;
#pragma omp parallel for schedule(static) if (r->n > PAR_MIN)
        for (size_t i = 0; i < r->n; i++) {
            double num = b[i] - shift * pl_rec[i];
            b[i] = no_light ? 0.0 : num / (pl_rec[i] > floor_pl ? pl_rec[i] : floor_pl);
        }
    }
}

/* Last resort: never emit NaN/Inf (the tests assert this never fires). Returns the count. */
static size_t repair_nonfinite(inverse_run *r)
{
    size_t repaired = 0;
    for (int k = -1; k < r->n_fields; k++) {
        double *restrict d = k < 0 ? r->pl_true->data : r->field_true[k]->data;
        for (size_t i = 0; i < r->n; i++)
            if (!isfinite(d[i])) {
                d[i] = 0.0;
                r->valid[i] = 0.0;
                repaired++;
            }
    }
    for (size_t i = 0; i < r->n; i++)
        if (!isfinite(r->valid[i])) {
            r->valid[i] = 0.0;
            repaired++;
        }
    return repaired;
}

/* T⁻¹ on the operator's grid: the stages above in order. opt is resolved (gain known);
 * field_sigma (may be NULL) on the same grid; reports has n_fields + 1 entries; validity
 * receives the validity map (never NULL). */
static svp_status inverse_core(svp_blur *blur, const svp_image *pl_apparent,
                               const svp_image *const *field_apparent, int n_fields,
                               const svp_correct_options *options,
                               const svp_image *const *field_sigma, svp_image *pl_true,
                               svp_image *const *field_true, svp_image *validity,
                               svp_deconv_report *reports, double *shifts, size_t *n_missing,
                               size_t *n_repaired)
{
    if (n_missing) *n_missing = 0;
    if (n_repaired) *n_repaired = 0;
    memset(reports, 0, ((size_t)n_fields + 1) * sizeof *reports);
    inverse_run r = {.blur = blur, .pl_apparent = pl_apparent, .field_apparent = field_apparent,
                     .field_sigma = field_sigma, .n_fields = n_fields, .w = pl_apparent->width,
                     .h = pl_apparent->height, .opt = *options, .pl_true = pl_true,
                     .field_true = field_true, .valid = validity->data, .reports = reports,
                     .shifts = shifts};
    r.n = (size_t)r.w * r.h;
    r.rl_pl = uses_rl_for_pl(r.opt.method);
    r.rl_field = uses_rl_for_field(r.opt.method);
    r.accel = r.rl_pl && r.opt.deconv.acceleration != SVP_RL_PLAIN;
    svp_status st = SVP_OK;
    r.missing = malloc(r.n);
    r.shares = calloc((size_t)n_fields + 1, sizeof *r.shares);
    r.counts = calloc((size_t)n_fields, sizeof *r.counts);
    if (!r.missing || !r.shares || !r.counts) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d inverse transform", r.w, r.h);
        goto cleanup;
    }
    if ((st = svp_image_new(r.w, r.h, &r.work)) != SVP_OK) goto cleanup;
    double pl_max = 0;
    if ((st = mark_missing(&r, &pl_max)) != SVP_OK) goto cleanup;
    if (n_missing) *n_missing = r.n_miss;
    if (!(pl_max > 0)) {
        /* No light anywhere: nothing to deconvolve, nothing known about the field. */
        memset(pl_true->data, 0, r.n * sizeof(double));
        for (int c = 0; c < n_fields; c++) memset(field_true[c]->data, 0, r.n * sizeof(double));
        memset(r.valid, 0, r.n * sizeof(double));
    } else {
        plan_progress(&r);
        /* the signed shifts (eq. 5), all checked before any deconvolution */
        for (int c = 0; r.rl_field && c < n_fields && st == SVP_OK; c++)
            st = signed_shift(field_apparent[c], r.missing, r.n, &r.opt, c, &shifts[c]);
        int in_order = 1;
        const int workers = side_by_side_workers(&r);
        if (st == SVP_OK && workers > 1) {
            st = deconvolve_side_by_side(&r, workers);
            in_order = st == SVP_ERR_NOMEM; /* no room for the copies: in order, one frame */
            if (in_order) {
                drop_copies(&r);
                svp_clear_error();
                st = SVP_OK;
                /* the runs in order report from where side by side got to, so the caller's
                 * progress never goes back */
                const double a = r.progress_reached;
                for (int k = 0; k <= n_fields; k++) {
                    r.shares[k].base = a + (1 - a) * r.shares[k].base;
                    r.shares[k].span *= 1 - a;
                }
            }
            if (options->summary) {
                options->summary->side_by_side = in_order ? 1 : workers;
                options->summary->side_by_side_fallback = in_order;
            }
        }
        if (in_order) {
            if (st == SVP_OK) st = deconvolve_pl(&r, r.blur, r.work);
            if (st == SVP_OK) st = deconvolve_numerators(&r);
        }
        if (st != SVP_OK) goto cleanup;
        const double floor_pl = r.opt.pl_floor * svp_max(pl_true->data, r.n);
        const int no_light = !(floor_pl > 0) || !isfinite(floor_pl);
        if ((st = validity_map(&r, floor_pl, no_light)) != SVP_OK) goto cleanup;
        divide_fields(&r, floor_pl, no_light);
    }
    const size_t repaired = repair_nonfinite(&r);
    if (n_repaired) *n_repaired = repaired;
cleanup:
    free(r.missing);
    free(r.shares);
    svp_image_free(r.work);
    svp_image_free(r.pl_var);
    svp_image_free(r.num_var);
    free(r.alphas);
    svp_rl_levels_free(r.levels);
    free(r.counts);
    drop_copies(&r);
    return st;
}

/* A copy of `src` (w x h) in the middle of a (w + 2m) x (h + 2m) image whose margin is NaN
 * (missing: no datum there), minus `offset`, clamped at 0 when `clamp`. */
static svp_status padded_copy(const svp_image *src, int m, double offset, int clamp,
                              svp_image **out)
{
    const int w = src->width, h = src->height, pw = w + 2 * m, ph = h + 2 * m;
    SVP_CHECK(svp_image_new(pw, ph, out));
    double *d = (*out)->data;
    for (int j = 0; j < ph; j++)
        for (int i = 0; i < pw; i++) {
            double v = NAN;
            if (i >= m && i < m + w && j >= m && j < m + h) {
                v = src->data[(size_t)(j - m) * w + (i - m)] - offset;
                if (clamp && v < 0) v = 0.0;
            }
            d[(size_t)j * pw + i] = v;
        }
    return SVP_OK;
}

static void crop_into(const svp_image *big, int m, svp_image *dst)
{
    for (int j = 0; j < dst->height; j++)
        memcpy(dst->data + (size_t)j * dst->width, big->data + (size_t)(j + m) * big->width + m,
               (size_t)dst->width * sizeof(double));
}

/* Spread of the finite values at the pixels where `where` is 1: √mean((v − mean)²). */
static double spread(const double *v, const unsigned char *where, size_t n)
{
    double s = 0, s2 = 0;
    size_t k = 0;
    for (size_t i = 0; i < n; i++)
        if (where[i] && isfinite(v[i])) {
            s += v[i];
            k++;
        }
    if (!k) return 0;
    const double mean = s / (double)k;
    for (size_t i = 0; i < n; i++)
        if (where[i] && isfinite(v[i])) s2 += (v[i] - mean) * (v[i] - mean);
    return sqrt(s2 / (double)k);
}

const char *svp_doubt_name(int bit)
{
    static const char *const names[] = {"cg_not_converged",  "balance_at_bound",
                                        "iterations_at_cap", "implausible_values",
                                        "regularised_away",  "light_lost",
                                        "operator_error"};
    return bit >= 0 && bit < (int)(sizeof names / sizeof *names) ? names[bit] : NULL;
}

void svp_doubt_list(unsigned doubts, char *buf, size_t size)
{
    size_t at = 0;
    if (size) buf[0] = '\0';
    for (int b = 0; svp_doubt_name(b); b++)
        if (doubts & (1u << b) && at < size)
            at += (size_t)snprintf(buf + at, size - at, "%s%s", at ? "," : "", svp_doubt_name(b));
}

/* The doubt "light lost": no pixel of the view lit (validity 1) while the measured PL has light,
 * or the corrected PL's light (its positive part) over the view's measured pixels below this
 * fraction of the measured PL's. RL keeps the data's flux (Σ Hx = Σ y at convergence) and
 * Wiener–Hunt its mean; only light explained by sources outside the view (a margin) leaves the
 * view's sum legitimately, and a view all of whose light comes from outside has nothing to
 * correct. Before rl.c's SEEN_SINGLE a float RL with a wide margin returned a PL of 0
 * everywhere, every pixel validity 0 and the field 0, and before its power-of-two scaling a float
 * RL of a PL of 1e40 did the same; no other check saw either. */
#define LIGHT_KEPT_MIN 0.01

/* The doubt checks (docs/model.md §3, "Results in doubt") on the view: fills sum, and either
 * sets validity 0 where the doubt applies (keep_doubtful) or returns SVP_ERR_DOUBTFUL with a
 * message that says what to change. */
/* The operator's doubt: a space-variant representation chosen by its budget that missed it by
 * far (SVP_DOUBT_OPERATOR and its message in msg, else 0). */
static unsigned doubt_operator(const svp_blur *blur, char *msg, size_t size)
{
    svp_variant_info vi;
    if (!svp_blur_is_variant(blur) || svp_blur_variant_info(blur, &vi) != SVP_OK ||
        !(vi.tolerance > 0) || vi.tolerance_met ||
        !(vi.estimated_error > fmax(vi.tolerance, SVP_OPERATOR_DOUBT_ERROR)))
        return 0;
    snprintf(msg, size,
             "the space-variant operator chosen for the PSF map has an estimated relative "
             "error of %.2g, %.3g times its budget %.2g and above %g: none of the %d "
             "representations compared within the memory limit meets the budget, so the "
             "correction does not follow the map; choose the representation (nodes, rank "
             "or regions), allow more memory, or raise the operator tolerance to accept it",
             vi.estimated_error, vi.estimated_error / vi.tolerance, vi.tolerance,
             SVP_OPERATOR_DOUBT_ERROR, vi.candidates);
    return SVP_DOUBT_OPERATOR;
}

static svp_status doubt_checks(const svp_blur *blur, const svp_correct_options *o,
                               const svp_image *pl_apparent,
                               const svp_image *const *field_apparent, int n_fields,
                               const svp_image *pl_true, svp_image *const *field_true,
                               svp_image *validity, const svp_deconv_report *reports,
                               svp_correct_summary *sum)
{
    const int w = pl_apparent->width;
    const size_t n = (size_t)w * pl_apparent->height;
    const int rl_pl = uses_rl_for_pl(o->method);
    char msg[900] = "", name[64];
    unsigned doubts = doubt_operator(blur, msg, sizeof msg);
    /* the solvers */
    for (int k = 0; k <= n_fields; k++) {
        const svp_deconv_report *r = &reports[k];
        const char *what = k == 0 ? pl_name(o) : field_name(o, k - 1, name, sizeof name);
        if (r->wiener && r->cg_capped && r->cg_residual > SVP_CG_DOUBT_RESIDUAL &&
            !(doubts & SVP_DOUBT_CG_CAPPED)) {
            doubts |= SVP_DOUBT_CG_CAPPED;
            if (!msg[0])
                snprintf(msg, sizeof msg,
                         "the Wiener-Hunt solve of %s%s stopped at its step cap (%d conjugate-"
                         "gradient steps, relative residual %.3g): not converged; raise the step "
                         "cap or the balance, or use method R",
                         what, k ? " x PL" : "", r->cg_steps, r->cg_residual);
        }
        if (r->wiener && r->balance_at_bound && !(doubts & SVP_DOUBT_BALANCE_BOUND)) {
            doubts |= SVP_DOUBT_BALANCE_BOUND;
            if (!msg[0])
                snprintf(msg, sizeof msg,
                         "the automatic balance of %s%s ended on the %s end of its search "
                         "(lambda = %g): the noise level (%s) %s; give the balance or the noise, "
                         "or use method R",
                         what, k ? " x PL" : "", r->balance_at_bound < 0 ? "lower" : "upper",
                         r->balance, r->noise_sigma > 0 ? "estimated sigma" : "noise model",
                         r->balance_at_bound < 0
                             ? "is below what any balance leaves (noiseless data, or a noise "
                               "estimate that is too small)"
                             : "explains the data at every balance (the signal would be "
                               "regularised away)");
        }
    }
    if (rl_pl && o->auto_iterations && reports[0].stop == SVP_RL_STOP_CAP) {
        doubts |= SVP_DOUBT_RL_CAP;
        if (!msg[0])
            snprintf(msg, sizeof msg,
                     "the automatic Richardson-Lucy stop was not reached within the cap of %d "
                     "iterations (chi2 per datum %.3g, still falling): raise the iteration cap",
                     reports[0].iterations, reports[0].chi2);
    }
    /* the result: the light kept, implausible values, a field regularised away */
    unsigned char *lit = malloc(n);
    if (!lit) return svp_fail(SVP_ERR_NOMEM, "out of memory for the doubt checks");
    size_t n_lit = 0;
    double light_in = 0, light_out = 0;
    for (size_t i = 0; i < n; i++) {
        int ok = validity->data[i] >= 1.0 && isfinite(pl_apparent->data[i]);
        for (int c = 0; c < n_fields && ok; c++) ok = isfinite(field_apparent[c]->data[i]);
        lit[i] = (unsigned char)ok;
        n_lit += (size_t)ok;
        if (isfinite(pl_apparent->data[i])) {
            light_in += fmax(pl_apparent->data[i], 0.0);
            light_out += fmax(pl_true->data[i], 0.0);
        }
    }
    if (light_in > 0 && (n_lit == 0 || !(light_out >= LIGHT_KEPT_MIN * light_in))) {
        doubts |= SVP_DOUBT_LIGHT_LOST;
        if (!msg[0])
            snprintf(msg, sizeof msg,
                     "the corrected %s holds %.3g of the measured light on the view (doubt below "
                     "%g) and %zu of its pixels are lit (validity 1): the deconvolution lost the "
                     "light, or the view's light comes from outside it; check the PSF, the "
                     "margin and the PL's scale, or use double precision",
                     pl_name(o), light_out / light_in, LIGHT_KEPT_MIN, n_lit);
    }
    size_t n_bad = 0;
    double worst = 0;
    size_t worst_at = 0;
    int worst_c = 0;
    double worst_meas = 0;
    sum->spread_ratio = INFINITY;
    for (int c = 0; c < n_fields; c++) {
        double meas = 0;
        for (size_t i = 0; i < n; i++) {
            const double v = field_apparent[c]->data[i];
            if (isfinite(v) && isfinite(pl_apparent->data[i]) && fabs(v) > meas) meas = fabs(v);
        }
        const double limit = o->plausible_factor * meas;
        for (size_t i = 0; i < n; i++) {
            const double b = fabs(field_true[c]->data[i]);
            if (!(b > limit && meas > 0)) continue;
            /* an already flagged pixel (validity < 1/2: dark, uncovered) just loses the rest
             * of its validity; a lit one puts the result in doubt */
            if (validity->data[i] < 0.5) {
                validity->data[i] = 0.0;
                continue;
            }
            {
                n_bad++;
                if (b / meas > worst) {
                    worst = b / meas;
                    worst_at = i;
                    worst_c = c;
                    worst_meas = meas;
                }
                if (o->keep_doubtful) validity->data[i] = 0.0;
            }
        }
        const double s_meas = spread(field_apparent[c]->data, lit, n);
        if (n_lit > 0 && s_meas > 0) {
            const double ratio = spread(field_true[c]->data, lit, n) / s_meas;
            if (ratio < sum->spread_ratio) sum->spread_ratio = ratio;
            if (ratio < o->shrink_factor && !(doubts & SVP_DOUBT_SHRUNK)) {
                doubts |= SVP_DOUBT_SHRUNK;
                if (!msg[0])
                    snprintf(msg, sizeof msg,
                             "the corrected %s varies %.3g times as much as the measured map "
                             "over the lit pixels (doubt below %g): the signal was regularised "
                             "away; use a smaller balance or method R",
                             field_name(o, c, name, sizeof name), ratio, o->shrink_factor);
            }
        }
    }
    free(lit);
    if (!isfinite(sum->spread_ratio)) sum->spread_ratio = 0;
    sum->n_implausible = n_bad;
    if (n_bad) {
        doubts |= SVP_DOUBT_IMPLAUSIBLE;
        if (!msg[0])
            snprintf(msg, sizeof msg,
                     "the corrected %s reaches %.3g at pixel (%zu, %zu), %.3g times the measured "
                     "map's largest |value| %.3g (%zu pixels beyond %g times): the correction "
                     "amplified noise or model error; use method R, automatic iterations, or a "
                     "larger balance",
                     field_name(o, worst_c, name, sizeof name),
                     field_true[worst_c]->data[worst_at], worst_at % (size_t)w,
                     worst_at / (size_t)w, worst, worst_meas, n_bad, o->plausible_factor);
    }
    sum->doubts = doubts;
    if (!doubts) return SVP_OK;
    if (!o->keep_doubtful) return svp_fail(SVP_ERR_DOUBTFUL, "result in doubt: %s", msg);
    /* kept on request: a doubt about the whole solve takes every pixel's validity */
    if (doubts & ~(unsigned)SVP_DOUBT_IMPLAUSIBLE) memset(validity->data, 0, n * sizeof(double));
    return SVP_OK;
}

/* The inputs' magnitudes (svp_image_check_scale), each named. */
static svp_status check_input_scales(const svp_correct_options *o, const svp_image *pl,
                                     const svp_image *const *fields, int n_fields)
{
    char buf[64];
    SVP_CHECK(svp_image_check_scale(pl, pl_name(o)));
    for (int c = 0; c < n_fields; c++)
        SVP_CHECK(svp_image_check_scale(fields[c], field_name(o, c, buf, sizeof buf)));
    return SVP_OK;
}

/* The optional σ maps: the PL's size, and no negative σ. */
static svp_status check_field_sigma(const svp_correct_options *o, const svp_image *pl_apparent,
                                    int n_fields)
{
    for (int c = 0; o->field_sigma && c < n_fields; c++) {
        const svp_image *sg = o->field_sigma[c];
        if (!sg) continue;
        SVP_CHECK(check_same(sg, "field_sigma", c, pl_apparent, "pl_apparent"));
        const size_t np = (size_t)sg->width * sg->height;
        for (size_t i = 0; i < np; i++)
            if (sg->data[i] < 0)
                return svp_fail(SVP_ERR_INVALID,
                                "field_sigma[%d] is negative (%g) at pixel (%zu, %zu): an "
                                "uncertainty is >= 0",
                                c, sg->data[i], i % (size_t)sg->width, i / (size_t)sg->width);
    }
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
    const int m = opt.margin;
    SVP_CHECK(check_transform_args(blur, pl_apparent, field_apparent, n_fields, pl_true, field_true,
                                   validity, "pl_apparent", "field_apparent", "pl_true",
                                   "field_true", m));
    if (m > 0 && svp_blur_boundary(blur) != SVP_BOUNDARY_ZERO)
        return svp_fail(SVP_ERR_INVALID,
                        "a margin beyond the view needs the zero boundary (the mirror and periodic "
                        "boundaries already say what lies outside)");
    SVP_CHECK(svp_correct_check_margin(m, pl_apparent->width, pl_apparent->height));
    SVP_CHECK(check_input_scales(&opt, pl_apparent, field_apparent, n_fields));
    SVP_CHECK(check_field_sigma(&opt, pl_apparent, n_fields));
    const int w = pl_apparent->width, h = pl_apparent->height;
    const size_t n = (size_t)w * h;
    svp_correct_summary local_sum, *sum = opt.summary ? opt.summary : &local_sum;
    memset(sum, 0, sizeof *sum);
    sum->side_by_side = 1; /* in order unless inverse_core runs them side by side */
    opt.summary = sum;

    /* The PL noise model: the gain given, or estimated from the view when a choice needs it. */
    if ((opt.auto_iterations || opt.balance_auto) && opt.pl_gain == 0) {
        double g = 0, o_est = 0;
        if (svp_pl_noise_estimate(pl_apparent, &g, &o_est) == SVP_OK && g > 0) {
            opt.pl_gain = g;
            sum->pl_gain_offset = o_est;
        }
    }
    sum->pl_gain = opt.pl_gain;

    svp_status st = SVP_OK;
    const int clamp = opt.pl_offset != 0 && uses_rl_for_pl(opt.method);
    const int copy_pl = m > 0 || opt.pl_offset != 0;
    svp_image *pl_in = NULL, *pl_out = NULL, *valid = NULL;
    svp_image **fields_in = calloc((size_t)n_fields, sizeof *fields_in);
    svp_image **fields_out = calloc((size_t)n_fields, sizeof *fields_out);
    svp_image **sigma_in = calloc((size_t)n_fields, sizeof *sigma_in);
    svp_deconv_report *reports = calloc((size_t)n_fields + 1, sizeof *reports);
    double *shifts = calloc((size_t)n_fields, sizeof *shifts);
    if (!fields_in || !fields_out || !sigma_in || !reports || !shifts) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d inverse transform", w, h);
        goto cleanup;
    }
    if (copy_pl && (st = padded_copy(pl_apparent, m, opt.pl_offset, clamp, &pl_in)) != SVP_OK)
        goto cleanup;
    const int pw = w + 2 * m, ph = h + 2 * m;
    for (int c = 0; c < n_fields && m > 0; c++) {
        if ((st = padded_copy(field_apparent[c], m, 0, 0, &fields_in[c])) != SVP_OK) goto cleanup;
        if (opt.field_sigma && opt.field_sigma[c] &&
            (st = padded_copy(opt.field_sigma[c], m, 0, 0, &sigma_in[c])) != SVP_OK)
            goto cleanup;
        if ((st = svp_image_new(pw, ph, &fields_out[c])) != SVP_OK) goto cleanup;
    }
    if (m > 0 && (st = svp_image_new(pw, ph, &pl_out)) != SVP_OK) goto cleanup;
    if ((st = svp_image_new(pw, ph, &valid)) != SVP_OK) goto cleanup;
    {
        const svp_image *const *f_in = m > 0 ? (const svp_image *const *)fields_in : field_apparent;
        svp_image *const *f_out = m > 0 ? fields_out : field_true;
        const svp_image *const *s_in =
            m > 0 ? (opt.field_sigma ? (const svp_image *const *)sigma_in : NULL) : opt.field_sigma;
        size_t miss = 0;
        /* Richardson–Lucy on both halves uses H x on the data (the view) and Hᵀ of data on the
         * view only: the operator's frame for the view serves, smaller than the grid's */
        int view = 0;
        const int rl_both = uses_rl_for_pl(opt.method) && uses_rl_for_field(opt.method);
        if (m > 0 && rl_both) st = svp_blur_set_view(blur, m, &view);
        /* and the PSF's far tail on a coarse grid, for this call (docs/model.md §5) */
        const double tail_before = svp_blur_tail_tol(blur);
        if (st == SVP_OK && rl_both && opt.tail_tol > 0) st = svp_blur_set_tail(blur, opt.tail_tol);
        if (st == SVP_OK)
            st = svp_blur_tail_info(blur, &sum->tail_step, &sum->tail_split, &sum->tail_error);
        if (st == SVP_OK)
            st = inverse_core(blur, copy_pl ? pl_in : pl_apparent, f_in, n_fields, &opt, s_in,
                              m > 0 ? pl_out : pl_true, f_out, valid, reports, shifts, &miss,
                              n_repaired);
        if (view) {
            svp_status back = svp_blur_set_view(blur, 0, &view);
            if (st == SVP_OK) st = back;
        }
        if (svp_blur_tail_tol(blur) != tail_before) {
            svp_status back = svp_blur_set_tail(blur, tail_before);
            if (st == SVP_OK) st = back;
        }
        if (st != SVP_OK) goto cleanup;
        if (n_missing) *n_missing = miss - ((size_t)pw * ph - n);
    }
    if (m > 0) {
        crop_into(pl_out, m, pl_true);
        for (int c = 0; c < n_fields; c++) crop_into(fields_out[c], m, field_true[c]);
    }
    svp_image *vv = validity;
    if (!vv) {
        if ((st = svp_image_new(w, h, &vv)) != SVP_OK) goto cleanup;
    }
    crop_into(valid, m, vv);
    if (opt.reports) memcpy(opt.reports, reports, ((size_t)n_fields + 1) * sizeof *reports);
    for (int c = 0; c < n_fields && c < 16; c++) sum->shift[c] = shifts[c];
    sum->rl_iterations = uses_rl_for_pl(opt.method) ? reports[0].iterations : 0;
    sum->rl_stop = reports[0].stop;
    sum->rl_chi2 = reports[0].chi2;
    {
        const svp_image *pl_view = opt.pl_offset != 0 ? NULL : pl_apparent;
        svp_image *pl_tmp = NULL;
        if (!pl_view) { /* the doubt checks see the PL as deconvolved */
            st = padded_copy(pl_apparent, 0, opt.pl_offset, clamp, &pl_tmp);
            pl_view = pl_tmp;
        }
        if (st == SVP_OK)
            st = doubt_checks(blur, &opt, pl_view, field_apparent, n_fields, pl_true, field_true, vv,
                              reports, sum);
        svp_image_free(pl_tmp);
    }
    if (vv != validity) svp_image_free(vv);

cleanup:
    svp_image_free(pl_in);
    svp_image_free(pl_out);
    svp_image_free(valid);
    for (int c = 0; c < n_fields; c++) { /* any of the three lists may be missing (NOMEM) */
        if (fields_in) svp_image_free(fields_in[c]);
        if (fields_out) svp_image_free(fields_out[c]);
        if (sigma_in) svp_image_free(sigma_in[c]);
    }
    free(fields_in);
    free(fields_out);
    free(sigma_in);
    free(reports);
    free(shifts);
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
