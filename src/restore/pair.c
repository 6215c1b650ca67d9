/* The PSF from an excitation/emission pair (docs/model.md §8, "Pair method"): I_PL = I_G ⊛ p,
 * so the emission spot deconvolved (Richardson–Lucy) by the fitted excitation spot is p. It
 * lives with RL, above the spot fits (src/psf/fit.c) and the blur operator it uses. */
#include "../psf/spot_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

void svp_pair_defaults(svp_pair_options *o)
{
    svp_spot_defaults(&o->spot);
    o->iterations = 75;
    o->kernel_radius = 0.0;
    o->kernel_from_fit = 0;
    o->boundary = SVP_BOUNDARY_ZERO;
}

svp_status svp_psf_from_pair(const svp_image *excitation, const svp_image *emission,
                             const svp_pair_options *options, svp_pair_result *result,
                             svp_image *deconvolved)
{
    if (!excitation || !emission || !result)
        return svp_fail(SVP_ERR_INVALID, "PSF from pair: excitation, emission and result are "
                        "required");
    svp_pair_options o;
    if (options)
        o = *options;
    else
        svp_pair_defaults(&o);
    if (o.iterations < 1)
        return svp_fail(SVP_ERR_INVALID, "PSF from pair: RL iterations must be >= 1, got %d",
                        o.iterations);
    if (!(o.kernel_radius >= 0) || !isfinite(o.kernel_radius))
        return svp_fail(SVP_ERR_INVALID, "PSF from pair: kernel_radius must be >= 0, got %g",
                        o.kernel_radius);
    SVP_CHECK(svp_image_same_size(excitation, emission, "excitation image", "emission image"));
    if (deconvolved)
        SVP_CHECK(svp_image_same_size(emission, deconvolved, "emission image",
                                      "deconvolved image"));
    memset(result, 0, sizeof *result);
    const int w = emission->width, h = emission->height;
    const size_t N = (size_t)w * h;
    svp_status st;
    svp_image *kernel = NULL, *y = NULL, *x = NULL;
    unsigned char *used = NULL;
    svp_blur *blur = NULL;

    st = svp_spot_fit(excitation, &o.spot, &result->excitation, NULL, NULL);
    if (st != SVP_OK) return svp_fail_context(st, "PSF from pair: excitation spot");
    used = malloc(N);
    if (!used) return svp_fail(SVP_ERR_NOMEM, "PSF from pair: out of memory");
    st = svp_spot_fit_used(emission, &o.spot, &result->direct, used);
    if (st != SVP_OK) {
        st = svp_fail_context(st, "PSF from pair: emission spot");
        goto cleanup;
    }
    result->offset_x = result->direct.x0 - result->excitation.x0;
    result->offset_y = result->direct.y0 - result->excitation.y0;

    int R = (int)ceil(o.kernel_radius > 0 ? o.kernel_radius
                                          : 3.0 * result->excitation.fwhm_major);
    int Rmax = ((w < h ? w : h) - 1) / 2;
    if (R > Rmax) R = Rmax;
    if (R < 1) R = 1;
    st = svp_spot_kernel(excitation, &result->excitation, &o.spot, R, o.kernel_from_fit,
                         &kernel);
    if (st != SVP_OK) goto cleanup;
    st = svp_blur_new_kernel(kernel, R, R, 1, w, h, o.boundary, &blur);
    if (st != SVP_OK) {
        st = svp_fail_context(st, "PSF from pair: excitation kernel");
        goto cleanup;
    }

    /* The emission spot without its background; pixels the direct fit could not use
     * (saturated, hot, clipped, non-finite) are missing data for RL (NaN). */
    st = svp_image_new(w, h, &y);
    if (st == SVP_OK) st = svp_image_new(w, h, &x);
    if (st != SVP_OK) goto cleanup;
    for (size_t i = 0; i < N; i++)
        y->data[i] = used[i] ? fmax(emission->data[i] - result->direct.background, 0.0) : NAN;
    svp_deconv_options d;
    svp_deconv_defaults(&d);
    d.iterations = o.iterations;
    st = svp_deconv_rl(blur, y, &d, x);
    if (st != SVP_OK) {
        st = svp_fail_context(st, "PSF from pair: Richardson-Lucy deconvolution of the "
                              "emission spot by the excitation spot");
        goto cleanup;
    }
    if (deconvolved) memcpy(deconvolved->data, x->data, N * sizeof(double));
    {
        /* The deconvolved spot is not Poisson data: unit weights, errors from the scatter. */
        svp_spot_options so = o.spot;
        so.noise.sigma_bg = so.noise.gain = so.noise.excess = 0.0;
        so.saturation = -1.0;
        so.hot_pixels = 0;
        so.x0 = so.y0 = NAN;
        st = svp_spot_fit(x, &so, &result->deconvolved, NULL, NULL);
        if (st != SVP_OK) {
            st = svp_fail_context(st, "PSF from pair: fit of the deconvolved emission spot");
            goto cleanup;
        }
    }
    result->deconvolved_ok = 1;
    st = SVP_OK;
cleanup:
    svp_blur_free(blur);
    svp_image_free(kernel);
    svp_image_free(y);
    svp_image_free(x);
    free(used);
    return st;
}
