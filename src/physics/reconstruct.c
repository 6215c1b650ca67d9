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

/* Applies up to two filters to one input map. */
static svp_status recon_run(const svp_image *in, const char *in_name,
                            const svp_recon_options *o, recon_kind kind_a, svp_image *out_a,
                            recon_kind kind_b, svp_image *out_b)
{
    SVP_CHECK(recon_validate(o));
    if (!in) return svp_fail(SVP_ERR_INVALID, "reconstruction input %s is NULL", in_name);
    if (out_a) SVP_CHECK(svp_image_same_size(in, out_a, in_name, "output"));
    if (out_b) SVP_CHECK(svp_image_same_size(in, out_b, in_name, "output"));
    if (svp_image_count_nonfinite(in))
        return svp_fail(SVP_ERR_INVALID, "reconstruction input %s has NaN or Inf pixels",
                        in_name);
    recon_filter f = {.h = o->sensor.standoff_m,
                      .t_nv = o->sensor.nv_thickness_m,
                      .t_src = o->source_thickness_m,
                      .s = o->sensor.side,
                      .kc = o->cutoff > 0 ? o->cutoff : 2 * M_PI / o->sensor.standoff_m,
                      .window = o->window};
    const int local = kind_a == JY_FROM_BX || kind_a == JX_FROM_BY;
    if (!local && (in->width < 3 || in->height < 3))
        return svp_fail(SVP_ERR_INVALID,
                        "reconstruction input %s is %d x %d pixels: the Fourier reconstruction "
                        "from B_z needs a map of at least 3 x 3",
                        in_name, in->width, in->height);
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

svp_status svp_reconstruct_magnetisation(const svp_image *bz, const svp_recon_options *options,
                                         svp_image *mz)
{
    if (!mz) return svp_fail(SVP_ERR_INVALID, "magnetisation output is NULL");
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
