/* scikit-image 0.19 compatibility: skimage.restoration.wiener(image, psf, balance) and
 * skimage.restoration.richardson_lucy(image, psf, num_iter) with their defaults, computed with
 * our FFT frames but reproducing their conventions exactly (checked against Debian's
 * python3-skimage by tests/extra/skimage_check.py).
 *
 * wiener: circular convolution at the image size; the PSF is zero-padded to the image size and
 * rolled by −floor(k/2) per axis (uft.ir2tf), so its centre is pixel (kw/2, kh/2); the
 * regulariser is the real part of the 5-point Laplacian's transfer function (uft.laplacian),
 * 4 − 2 cos(2πu/nx) − 2 cos(2πv/ny); filter conj(H) / (|H|² + balance |reg|²); result clipped
 * to [−1, 1]. Quirk kept: a PSF whose shape equals the half-spectrum's, height x (width/2 + 1),
 * is taken by skimage as a (real) transfer function, not an impulse response.
 *
 * richardson_lucy: start 0.5; per iteration conv = convolve(x, psf, 'same') + 1e-12,
 * x *= convolve(image / conv, flip(psf), 'same'); clipped to [−1, 1]. scipy's 'same' mode is
 * the linear (zero-padded) convolution cropped at offset (K − 1) // 2, so the PSF's centre is
 * c = (K − 1) // 2; the flipped PSF's 'same' convolution is a correlation centred at K − 1 − c,
 * which is NOT the adjoint of the first for even K (off by one pixel). Both are reproduced. */
#include "../blur/blur_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define PI 3.14159265358979323846

static svp_status check_compat(const svp_image *image, const svp_image *psf, const svp_image *out,
                               const char *what, int allow_half_spectrum)
{
    if (!image || !image->data) return svp_fail(SVP_ERR_INVALID, "%s: image is NULL", what);
    if (!psf || !psf->data) return svp_fail(SVP_ERR_INVALID, "%s: psf is NULL", what);
    if (!out || !out->data) return svp_fail(SVP_ERR_INVALID, "%s: output is NULL", what);
    if (out->width != image->width || out->height != image->height)
        return svp_fail(SVP_ERR_SIZE, "%s: image is %d x %d but the output is %d x %d", what,
                        image->width, image->height, out->width, out->height);
    int half = allow_half_spectrum && psf->height == image->height &&
               psf->width == image->width / 2 + 1;
    if (!half && (psf->width > image->width || psf->height > image->height))
        return svp_fail(SVP_ERR_SIZE, "%s: psf is %d x %d, larger than the %d x %d image", what,
                        psf->width, psf->height, image->width, image->height);
    return SVP_OK;
}

svp_status svp_skimage_wiener(const svp_image *image, const svp_image *psf, double balance,
                              svp_image *out)
{
    const char *what = "scikit-image wiener";
    SVP_CHECK(check_compat(image, psf, out, what, 1));
    const int w = image->width, h = image->height;
    const int as_transfer = psf->height == h && psf->width == w / 2 + 1;
    svp_frame f;
    double *frame = NULL, *lap_x = NULL, *lap_y = NULL;
    fftw_complex *spectrum = NULL;
    svp_status st = svp_frame_init(&f, w, h, 0, 0, SVP_BOUNDARY_PERIODIC);
    if (st != SVP_OK) return st;
    const int nx = f.nx, ny = f.ny, ncx = f.ncx;
    frame = svp_alloc((size_t)ny * nx * sizeof(double));
    spectrum = svp_alloc((size_t)ny * ncx * sizeof(fftw_complex));
    lap_x = malloc((size_t)ncx * sizeof(double));
    lap_y = malloc((size_t)ny * sizeof(double));
    if (!frame || !spectrum || !lap_x || !lap_y) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory for a %d x %d frame", what, nx, ny);
        goto cleanup;
    }
    if (!as_transfer &&
        (st = svp_frame_set_kernel(&f, psf, psf->width / 2, psf->height / 2,
                                   SVP_BOUNDARY_PERIODIC)) != SVP_OK)
        goto cleanup;
    /* reg = 4 − 2 cos(2πu/nx) − 2 cos(2πv/ny), as (2 − 2 cos) per axis */
    for (int u = 0; u < ncx; u++) lap_x[u] = 2.0 - 2.0 * cos(2.0 * PI * u / nx);
    for (int v = 0; v < ny; v++) lap_y[v] = 2.0 - 2.0 * cos(2.0 * PI * v / ny);

    memcpy(frame, image->data, (size_t)w * h * sizeof(double));
    svp_fft_forward(f.plan, frame, spectrum);
    const double scale = 1.0 / ((double)nx * ny);
#pragma omp parallel for schedule(static) if ((size_t)ny * ncx > 32768)
    for (int v = 0; v < ny; v++) {
        for (int u = 0; u < ncx; u++) {
            size_t k = (size_t)v * ncx + u;
            fftw_complex tf = as_transfer ? psf->data[k] : f.otf[k];
            double reg = lap_x[u] + lap_y[v];
            /* IEEE arithmetic as numpy does it (0/0 → NaN is reproduced, not hidden) */
            fftw_complex filter =
                conj(tf) / (creal(tf) * creal(tf) + cimag(tf) * cimag(tf) + balance * reg * reg);
            spectrum[k] *= filter * scale;
        }
    }
    svp_fft_inverse_unscaled(f.plan, spectrum, frame);
    const size_t n = (size_t)w * h;
    double *restrict o = out->data;
#pragma omp parallel for schedule(static) if (n > 32768)
    for (size_t i = 0; i < n; i++) {
        double v = frame[i];
        o[i] = v > 1 ? 1.0 : (v < -1 ? -1.0 : v);
    }
cleanup:
    svp_frame_release(&f);
    svp_free(frame);
    svp_free(spectrum);
    free(lap_x);
    free(lap_y);
    return st;
}

svp_status svp_skimage_richardson_lucy(const svp_image *image, const svp_image *psf,
                                       int num_iter, svp_progress_fn progress,
                                       void *progress_user, svp_image *out)
{
    const char *what = "scikit-image richardson_lucy";
    SVP_CHECK(check_compat(image, psf, out, what, 0));
    if (out->data == image->data)
        return svp_fail(SVP_ERR_INVALID, "%s: the output must not be the input image", what);
    if (num_iter < 0)
        return svp_fail(SVP_ERR_INVALID, "%s: num_iter = %d must be >= 0", what, num_iter);
    const int w = image->width, h = image->height, kw = psf->width, kh = psf->height;
    /* 'same' centre of the PSF, and the centre at which the flipped PSF's 'same' convolution
     * correlates with the PSF */
    const int cx = (kw - 1) / 2, cy = (kh - 1) / 2;
    const int cx_flip = kw - 1 - cx, cy_flip = kh - 1 - cy;
    svp_frame conv, corr;
    memset(&corr, 0, sizeof corr);
    double *frame = NULL;
    fftw_complex *spectrum = NULL;
    /* zero frames of at least size + K − 1: no wrap-around reaches the image */
    svp_status st = svp_frame_init(&conv, w, h, kw - 1, kh - 1, SVP_BOUNDARY_ZERO);
    if (st != SVP_OK) return st;
    if ((st = svp_frame_set_kernel(&conv, psf, cx, cy, SVP_BOUNDARY_ZERO)) != SVP_OK)
        goto cleanup;
    /* The correlation's OTF is conv's itself when both centres coincide (odd kernel sides);
     * only an even side shifts it by one pixel and needs a frame of its own. */
    const svp_frame *cf = &conv;
    if (cx_flip != cx || cy_flip != cy) {
        if ((st = svp_frame_init(&corr, w, h, kw - 1, kh - 1, SVP_BOUNDARY_ZERO)) != SVP_OK ||
            (st = svp_frame_set_kernel(&corr, psf, cx_flip, cy_flip, SVP_BOUNDARY_ZERO)) !=
                SVP_OK)
            goto cleanup;
        cf = &corr;
    }
    const int nx = conv.nx, ny = conv.ny;
    frame = svp_alloc((size_t)ny * nx * sizeof(double));
    spectrum = svp_alloc((size_t)ny * conv.ncx * sizeof(fftw_complex));
    if (!frame || !spectrum) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory for a %d x %d frame", what, nx, ny);
        goto cleanup;
    }
    const double scale = 1.0 / ((double)nx * ny), eps = 1e-12;
    const double *restrict img = image->data;
    double *restrict x = out->data;
    for (size_t i = 0; i < (size_t)w * h; i++) x[i] = 0.5;
    /* The frame holds the current estimate, zero-padded; each pass below leaves the next
     * stage's input in it, so an iteration is two FFT pairs and two pointwise passes. */
#pragma omp parallel for schedule(static) if ((size_t)ny * nx > 32768)
    for (int j = 0; j < ny; j++)
        for (int i = 0; i < nx; i++)
            frame[(size_t)j * nx + i] = (j < h && i < w) ? 0.5 : 0.0;
    for (int it = 0; it < num_iter; it++) {
        svp_fft_forward(conv.plan, frame, spectrum);
        svp_frame_multiply(&conv, spectrum, 0, scale);
        svp_fft_inverse_unscaled(conv.plan, spectrum, frame);
        /* relative_blur = image / (conv + eps), zero outside the image */
#pragma omp parallel for schedule(static) if ((size_t)ny * nx > 32768)
        for (int j = 0; j < ny; j++) {
            double *row = frame + (size_t)j * nx;
            if (j >= h) {
                memset(row, 0, (size_t)nx * sizeof(double));
                continue;
            }
            const double *in = img + (size_t)j * w;
            for (int i = 0; i < w; i++) row[i] = in[i] / (row[i] + eps);
            for (int i = w; i < nx; i++) row[i] = 0.0;
        }
        svp_fft_forward(cf->plan, frame, spectrum);
        svp_frame_multiply(cf, spectrum, 1, scale);
        svp_fft_inverse_unscaled(cf->plan, spectrum, frame);
        /* x *= correlation; the frame takes the new x (zero-padded) for the next iteration */
#pragma omp parallel for schedule(static) if ((size_t)ny * nx > 32768)
        for (int j = 0; j < ny; j++) {
            double *row = frame + (size_t)j * nx;
            if (j >= h) {
                memset(row, 0, (size_t)nx * sizeof(double));
                continue;
            }
            double *xr = x + (size_t)j * w;
            for (int i = 0; i < w; i++) row[i] = xr[i] *= row[i];
            for (int i = w; i < nx; i++) row[i] = 0.0;
        }
        st = svp_report_progress(progress, progress_user, (double)(it + 1) / num_iter);
        if (st != SVP_OK) goto cleanup;
    }
    for (size_t i = 0; i < (size_t)w * h; i++) x[i] = x[i] > 1 ? 1.0 : (x[i] < -1 ? -1.0 : x[i]);
cleanup:
    svp_frame_release(&conv);
    svp_frame_release(&corr);
    svp_free(frame);
    svp_free(spectrum);
    return st;
}
