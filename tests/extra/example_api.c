/* The example program of docs/api.md: T and T⁻¹ on synthetic maps through the public API. */
#include <math.h>
#include <stdio.h>
#include <svpsf.h>

/* On failure: print the status and the library's message, then free everything. */
#define CHECK(call)                                                                                \
    do {                                                                                           \
        svp_status st_ = (call);                                                                   \
        if (st_ != SVP_OK) {                                                                       \
            fprintf(stderr, "%s: %s: %s\n", #call, svp_status_string(st_), svp_last_error());      \
            goto cleanup;                                                                          \
        }                                                                                          \
    } while (0)

int main(void)
{
    const int width = 160, height = 120; /* pixels of 100 nm */
    const double pi = 3.14159265358979323846;
    int exit_code = 1;
    svp_blur *blur = NULL;
    svp_image *pl_true = NULL, *field_true = NULL, *pl_apparent = NULL;
    svp_image *field_apparent = NULL, *pl_recovered = NULL, *field_recovered = NULL;
    svp_image *validity = NULL;

    /* The PSF: Moffat, FWHM 610 nm = 6.1 px, beta 1.1; support 0 = the whole field of view. */
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_MOFFAT;
    psf.fwhm = 6.1;
    psf.beta = 1.1;

    /* The operator H: plans the FFTs and computes the OTF once. Mirror boundary: the scene
     * continues beyond the edges as their mirror image. */
    CHECK(svp_blur_new(&psf, width, height, SVP_BOUNDARY_MIRROR, &blur));

    /* Synthetic truth: PL quenched to 10 % under a wire along y at x = 79.5 px; the in-plane
     * field of the current in that wire, in tesla. */
    CHECK(svp_image_new(width, height, &pl_true));
    CHECK(svp_image_new(width, height, &field_true));
    for (int y = 0; y < height; y++)
        for (int x = 0; x < width; x++) {
            double u = (x - 79.5) / 10.0; /* across the wire, in half-widths */
            pl_true->data[y * width + x] = 1.0 - 0.9 * exp(-0.5 * u * u);
            field_true->data[y * width + x] = 1e-4 * (atan(1.0 - u) + atan(1.0 + u)) / pi;
        }

    /* T (eq. 3): what the camera and the per-pixel fits report. */
    CHECK(svp_image_new(width, height, &pl_apparent));
    CHECK(svp_image_new(width, height, &field_apparent));
    const svp_image *fields_in[1] = {field_true};
    svp_image *fields_apparent[1] = {field_apparent};
    CHECK(svp_forward_transform(blur, pl_true, fields_in, 1, pl_apparent, fields_apparent, NULL));

    /* T⁻¹ (eq. 4): Wiener on both deconvolutions, small balance (noiseless data). */
    svp_correct_options options;
    svp_correct_defaults(&options);
    options.method = SVP_METHOD_W;
    options.deconv.balance = 1e-6;
    CHECK(svp_image_new(width, height, &pl_recovered));
    CHECK(svp_image_new(width, height, &field_recovered));
    CHECK(svp_image_new(width, height, &validity));
    const svp_image *fields_measured[1] = {field_apparent};
    svp_image *fields_recovered[1] = {field_recovered};
    size_t n_missing = 0;
    CHECK(svp_inverse_transform(blur, pl_apparent, fields_measured, 1, &options, pl_recovered,
                                fields_recovered, validity, &n_missing));

    /* The error of the round trip, relative to the field's peak, over valid pixels, against
     * the apparent field's error before the correction. */
    double peak = 0, err_apparent = 0, err_recovered = 0;
    for (int i = 0; i < width * height; i++) {
        double truth = field_true->data[i];
        peak = fmax(peak, fabs(truth));
        if (validity->data[i] < 1) continue;
        err_apparent = fmax(err_apparent, fabs(field_apparent->data[i] - truth));
        err_recovered = fmax(err_recovered, fabs(field_recovered->data[i] - truth));
    }
    printf("svpsf %s (FFTW %s), %d threads\n", svp_version(), svp_fftw_version(),
           svp_get_threads());
    printf("max error / peak field: apparent %.3g, after T^-1 %.3g (%zu missing pixels)\n",
           err_apparent / peak, err_recovered / peak, n_missing);
    exit_code = err_recovered < 0.01 * peak && err_recovered < err_apparent ? 0 : 1;

cleanup:
    svp_image_free(pl_true);
    svp_image_free(field_true);
    svp_image_free(pl_apparent);
    svp_image_free(field_apparent);
    svp_image_free(pl_recovered);
    svp_image_free(field_recovered);
    svp_image_free(validity);
    svp_blur_free(blur);
    return exit_code;
}
