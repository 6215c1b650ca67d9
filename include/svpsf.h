/*
 * svpsf — space-variant PSF restoration for widefield spectral imaging.
 *
 * The whole public API of libsvpsf. Conventions:
 *  - every fallible function returns svp_status (SVP_OK == 0); results come back through
 *    pointers; every object X has svp_X_new / svp_X_free (free accepts NULL);
 *  - on failure svp_last_error() holds a thread-local message naming the input at fault;
 *  - the library never prints, exits or aborts;
 *  - option structs are initialised with svp_X_defaults(); the defaults are documented beside
 *    each field;
 *  - images are row-major doubles, 64-byte aligned, width = number of columns (x), height =
 *    number of rows (y); pixel (x, y) is data[y * width + x];
 *  - lengths inside the library are in pixels unless a name says otherwise (_um = micrometre);
 *  - long work reports progress through an optional svp_progress_fn and can be cancelled.
 *
 * Equation numbers refer to docs/model.md.
 */
#ifndef SVPSF_H
#define SVPSF_H

#include <stddef.h>

#ifdef __cplusplus
extern "C" {
#endif

#if defined(_WIN32)
#define SVP_API
#elif defined(__GNUC__)
#define SVP_API __attribute__((visibility("default")))
#else
#define SVP_API
#endif

/* ---------------------------------------------------------------------------------------- */
/* Status codes and errors                                                                   */

typedef enum svp_status {
    SVP_OK = 0,
    SVP_ERR_INVALID = 1,     /* an argument or input value is out of its domain */
    SVP_ERR_IO = 2,          /* a file cannot be opened, read or written */
    SVP_ERR_FORMAT = 3,      /* a file's content is malformed or truncated */
    SVP_ERR_SIZE = 4,        /* image sizes do not match */
    SVP_ERR_NOMEM = 5,       /* allocation failed */
    SVP_ERR_EXISTS = 6,      /* the output exists and overwriting was not allowed */
    SVP_ERR_CANCELLED = 7,   /* the progress callback asked to stop */
    SVP_ERR_NUMERIC = 8,     /* a numerical failure (no convergence, singular system) */
    SVP_ERR_UNSUPPORTED = 9, /* a feature that is not available in this build */
    SVP_ERR_INTERNAL = 10    /* a bug: please report it */
} svp_status;

/* A short constant description of a status code ("invalid argument", ...). */
SVP_API const char *svp_status_string(svp_status status);
/* The detailed message of the last failure on this thread ("" when none). */
SVP_API const char *svp_last_error(void);

/* Progress callback: fraction in [0, 1]; return nonzero to cancel (SVP_ERR_CANCELLED). */
typedef int (*svp_progress_fn)(void *user, double fraction);

/* ---------------------------------------------------------------------------------------- */
/* Versions and global settings                                                              */

SVP_API const char *svp_version(void);       /* "0.1.0" */
SVP_API const char *svp_fftw_version(void);  /* FFTW's own version string */

/* Threads used by FFTs and loops (default: all cores OpenMP reports). n < 1 → 1.
 * Results are the same for every thread count to round-off (docs/api.md states the bound). */
SVP_API void svp_set_threads(int n);
SVP_API int svp_get_threads(void);

/* FFT planning effort. */
typedef enum svp_fft_effort {
    SVP_FFT_ESTIMATE = 0, /* no measurement: fastest planning */
    SVP_FFT_MEASURE = 1   /* FFTW_MEASURE (default): slower first plan per size, faster FFTs */
} svp_fft_effort;
SVP_API void svp_set_fft_effort(svp_fft_effort effort);
/* FFTW wisdom: plans measured once can be saved and reused across runs. */
SVP_API svp_status svp_fft_wisdom_load(const char *path);
SVP_API svp_status svp_fft_wisdom_save(const char *path);
/* The smallest 2,3,5,7-smooth integer >= n (n >= 1). */
SVP_API int svp_fft_good_size(int n);

/* ---------------------------------------------------------------------------------------- */
/* Images                                                                                    */

typedef struct svp_image {
    int width;    /* columns (x) */
    int height;   /* rows (y) */
    double *data; /* width * height values, row-major, 64-byte aligned */
} svp_image;

/* A new image filled with zeros. width, height >= 1. */
SVP_API svp_status svp_image_new(int width, int height, svp_image **out);
SVP_API svp_status svp_image_copy(const svp_image *src, svp_image **out);
SVP_API void svp_image_free(svp_image *image);
/* SVP_ERR_SIZE with a message naming what_a and what_b when the sizes differ. */
SVP_API svp_status svp_image_same_size(const svp_image *a, const svp_image *b, const char *what_a,
                                       const char *what_b);
/* Counts the NaN and ±Inf pixels. */
SVP_API size_t svp_image_count_nonfinite(const svp_image *image);

/* ---------------------------------------------------------------------------------------- */
/* Image files                                                                               */

/* Reads a single-channel image. The format follows the extension: .tif/.tiff (float32,
 * float64, 8/16-bit integer), .png (8/16-bit), .npy (float32/float64/integers, C or Fortran
 * order, 2-D), .txt/.csv/.dat (numbers as numpy.savetxt writes them, whitespace or comma
 * separated, '#' comments). Errors name the file and the fault. */
SVP_API svp_status svp_image_read(const char *path, svp_image **out);

typedef enum svp_file_format {
    SVP_FORMAT_AUTO = 0,  /* from the extension; unknown extension → error */
    SVP_FORMAT_TIFF = 1,  /* float32 TIFF */
    SVP_FORMAT_NPY = 2,   /* float64 .npy */
    SVP_FORMAT_TXT = 3,   /* numpy.savetxt-compatible text, %.17g */
    SVP_FORMAT_PNG16 = 4  /* 16-bit PNG scaled from [lo, hi] of the data (figures only) */
} svp_file_format;

/* Writes atomically (temporary file in the same folder, then rename). With overwrite == 0 an
 * existing file is left alone and SVP_ERR_EXISTS is returned. */
SVP_API svp_status svp_image_write(const char *path, const svp_image *image,
                                   svp_file_format format, int overwrite);

/* ---------------------------------------------------------------------------------------- */
/* PSF models (docs/model.md §PSF)                                                           */

typedef enum svp_psf_model {
    SVP_PSF_GAUSSIAN = 0,
    SVP_PSF_LORENTZIAN = 1, /* Moffat with beta = 1 */
    SVP_PSF_MOFFAT = 2
} svp_psf_model;

typedef struct svp_psf {
    svp_psf_model model; /* default SVP_PSF_GAUSSIAN */
    double fwhm;         /* FWHM along the major axis, pixels (> 0); default 2 */
    double fwhm_minor;   /* FWHM along the minor axis, pixels; 0 (default) = circular */
    double angle;        /* major-axis angle from +x towards +y (row index), radians; default 0 */
    double beta;         /* Moffat index (> 0); ignored for Gaussian, forced 1 for Lorentzian;
                            default 2.5 */
    double halo;         /* alpha_b in [0, 1): fraction of the light spread evenly over the
                            field of view (a separate term, never folded into the kernel);
                            default 0 */
    double support;      /* truncation radius of the core in pixels; 0 (default) = the whole
                            field of view: every pixel of the image reaches every other */
    int subsample;       /* samples per pixel side for pixel integration; 0 (default) = auto:
                            9 when the FWHM is below 2 px, else 1 (centre sampling) */
} svp_psf;

SVP_API void svp_psf_defaults(svp_psf *psf);
/* SVP_ERR_INVALID with a message for FWHM <= 0, beta <= 0, halo outside [0, 1), ... */
SVP_API svp_status svp_psf_validate(const svp_psf *psf);
/* Moffat r0 from FWHM: r0 = FWHM / (2 sqrt(2^(1/beta) - 1)); Gaussian: sigma. */
SVP_API double svp_psf_fwhm_to_r0(double fwhm, double beta);
/* Un-normalised profile value at offset (dx, dy) in pixels (peak 1, no pixel integration). */
SVP_API double svp_psf_profile(const svp_psf *psf, double dx, double dy);
/* Fraction of the flux of a circular profile inside radius r of a disc of radius R (both in
 * units of pixels; R = 0: infinite plane when the flux converges). Analytic, stable near
 * beta = 1 (expm1/log1p). */
SVP_API double svp_psf_encircled_energy(const svp_psf *psf, double r, double R);
/* Radius (pixels) enclosing `fraction` of the flux over a disc of radius R. */
SVP_API svp_status svp_psf_encircled_radius(const svp_psf *psf, double fraction, double R,
                                            double *radius);
/* Renders the core kernel (no halo term) sampled on a (2 rx + 1) x (2 ry + 1) grid centred at
 * (rx, ry), truncated to the support radius, normalised to unit sum over what was sampled. */
SVP_API svp_status svp_psf_render(const svp_psf *psf, int rx, int ry, svp_image **kernel);

/* ---------------------------------------------------------------------------------------- */
/* Blur operators H                                                                          */

typedef enum svp_boundary {
    SVP_BOUNDARY_ZERO = 0,    /* no light outside the image (linear convolution; default) */
    SVP_BOUNDARY_MIRROR = 1,  /* the scene continues mirrored about the edges (d c b a|a b c d) */
    SVP_BOUNDARY_PERIODIC = 2 /* the scene repeats (circular convolution at the image size) */
} svp_boundary;

typedef struct svp_blur svp_blur;

/* The space-invariant operator for a PSF model on a width x height image:
 * H x = (1 - halo) (p_core ⊛ x) + halo <x>_FOV. Plans the FFTs and computes the OTF once. */
SVP_API svp_status svp_blur_new(const svp_psf *psf, int width, int height,
                                svp_boundary boundary, svp_blur **out);
/* The space-invariant operator for a sampled kernel whose centre is pixel (cx, cy) of the
 * kernel image (pass -1, -1 for (kw / 2, kh / 2)). normalise != 0 scales it to unit sum. */
SVP_API svp_status svp_blur_new_kernel(const svp_image *kernel, int cx, int cy, int normalise,
                                       int width, int height, svp_boundary boundary,
                                       svp_blur **out);
SVP_API void svp_blur_free(svp_blur *blur);
SVP_API int svp_blur_width(const svp_blur *blur);
SVP_API int svp_blur_height(const svp_blur *blur);
SVP_API svp_boundary svp_blur_boundary(const svp_blur *blur);
/* The halo fraction alpha_b of the operator (0 when none). */
SVP_API double svp_blur_halo(const svp_blur *blur);
/* y = H x and x = Hᵀ y (the exact adjoint). Input and output may not alias. The operator keeps
 * work buffers: one svp_blur must not be applied from two threads at once. */
SVP_API svp_status svp_blur_apply(svp_blur *blur, const svp_image *x, svp_image *y);
SVP_API svp_status svp_blur_adjoint(svp_blur *blur, const svp_image *y, svp_image *x);
/* Bytes held by the operator (OTFs and work buffers). */
SVP_API size_t svp_blur_memory(const svp_blur *blur);

/* ---------------------------------------------------------------------------------------- */
/* Deconvolution (the ⊘ of eq. 4)                                                            */

typedef struct svp_deconv_options {
    double balance;        /* Wiener–Hunt λ in conj(P) / (|P|² + λ |L|²), L the Laplacian;
                              default 1e-3 */
    int iterations;        /* Richardson–Lucy iterations; default 50 */
    double floor;          /* RL: denominators Hx are floored at floor * max(y); default 1e-9 */
    int boundary_weights;  /* RL: Bertero–Boccacci normalisation by Hᵀ1 (default 1) */
    svp_progress_fn progress; /* optional */
    void *progress_user;
} svp_deconv_options;

SVP_API void svp_deconv_defaults(svp_deconv_options *options);

/* Wiener–Hunt deconvolution of y by H. NaN/Inf pixels of y are missing data: they are filled
 * from their neighbours (normalised convolution with the PSF) before filtering. The halo term
 * is inverted exactly (a scalar equation for the mean). x may be y's twin size, not y. */
SVP_API svp_status svp_deconv_wiener(svp_blur *blur, const svp_image *y,
                                     const svp_deconv_options *options, svp_image *x);
/* Richardson–Lucy: x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm, started flat at the data mean; m is
 * 0 on NaN/Inf pixels of y (missing data), 1 elsewhere. y must be >= 0 where finite. */
SVP_API svp_status svp_deconv_rl(svp_blur *blur, const svp_image *y,
                                 const svp_deconv_options *options, svp_image *x);

/* scikit-image 0.19 compatibility: the same numbers as
 *   skimage.restoration.wiener(image, psf, balance)            (circular, Laplacian, clip)
 *   skimage.restoration.richardson_lucy(image, psf, num_iter)  (start 0.5, eps 1e-12, 'same'
 *                                                              zero-padded, clip)
 * on the same inputs (to ~1e-6 relative or better). The psf is used as given (no
 * normalisation); its shape must not exceed the image's. */
SVP_API svp_status svp_skimage_wiener(const svp_image *image, const svp_image *psf,
                                      double balance, svp_image *out);
SVP_API svp_status svp_skimage_richardson_lucy(const svp_image *image, const svp_image *psf,
                                               int num_iter, svp_progress_fn progress,
                                               void *progress_user, svp_image *out);

/* ---------------------------------------------------------------------------------------- */
/* The transforms T and T⁻¹ (eqs. 3 and 4)                                                   */

/* Forward transform T: pl_apparent = H pl_true; for each component c
 * field_apparent[c] = H(field_true[c] · pl_true) / pl_apparent, where pl_apparent > 0; where
 * pl_apparent is 0 the apparent field is set to 0 and validity (if not NULL) to 0, else 1. */
SVP_API svp_status svp_forward_transform(svp_blur *blur, const svp_image *pl_true,
                                         const svp_image *const *field_true, int n_fields,
                                         svp_image *pl_apparent, svp_image *const *field_apparent,
                                         svp_image *validity);

typedef enum svp_method {
    SVP_METHOD_RW = 0,       /* RL on Ĩ, Wiener on B̃Ĩ (reference study's "R&W"; default) */
    SVP_METHOD_R = 1,        /* RL on both; the signed numerator through the shift of §2 */
    SVP_METHOD_W = 2,        /* Wiener on both */
    SVP_METHOD_RL_SIGNED = 3 /* RL on Ĩ and on (B̃ + c)Ĩ, minus c (Ĩ ⊘ p): same as R, the name
                                says what it does */
} svp_method;

typedef struct svp_correct_options {
    svp_method method;           /* default SVP_METHOD_RW */
    svp_deconv_options deconv;   /* iterations (75 for RL), balance, ... */
    double pl_floor;             /* the recovered PL is floored at pl_floor · max(PL) before
                                    dividing; pixels below it have validity < 1; default 1e-3 */
    double shift;                /* c of the signed shift; 0 (default) = automatic:
                                    c = 0.1 · range(B̃) − min(B̃) per component */
} svp_correct_options;

SVP_API void svp_correct_defaults(svp_correct_options *options);

/* Inverse transform T⁻¹ (eq. 4): pl_true = Ĩ ⊘ p; field_true[c] = ((B̃_c Ĩ) ⊘ p) / max(pl_true,
 * floor). All components share the one deconvolution of Ĩ. validity in [0, 1]: 1 where the
 * recovered PL is above the floor, falling linearly to 0 at zero PL, 0 at NaN input pixels
 * that no neighbour covers. No NaN or Inf is ever written. n_missing (may be NULL) returns the
 * number of NaN/Inf input pixels that were treated as missing data. */
SVP_API svp_status svp_inverse_transform(svp_blur *blur, const svp_image *pl_apparent,
                                         const svp_image *const *field_apparent, int n_fields,
                                         const svp_correct_options *options,
                                         svp_image *pl_true, svp_image *const *field_true,
                                         svp_image *validity, size_t *n_missing);

/* Closed-form inverse for a halo-only PSF p = (1 − α) δ + α / A (PHYSICS.md §2, exact for any
 * PL): Ĩ = (1 − α) I + α <Ĩ>, B̃Ĩ = (1 − α) BI + α <B̃Ĩ>, so
 * B = (B̃Ĩ − α <B̃Ĩ>) / (Ĩ − α <Ĩ>). With uniform PL: ΔB = ΔB̃ / (1 − α). */
SVP_API svp_status svp_halo_correct(double halo, const svp_image *pl_apparent,
                                    const svp_image *field_apparent, svp_image *field_true);

/* ---------------------------------------------------------------------------------------- */
/* PSF files (YAML; docs/cli.md §PSF files)                                                  */

/* Reads a PSF file:
 *   pixel_um: 0.1
 *   psf: {model: moffat, fwhm_um: 0.61, beta: 1.1, halo: 0.0,
 *         fwhm_minor_um: 0.5, angle_deg: 30, support_um: 20, subsample: 0}
 *   boundary: zero | mirror | periodic      (optional)
 * Lengths are converted to pixels. Unknown keys, wrong types and impossible values are errors
 * naming file:line:column and the key. boundary may be NULL. */
SVP_API svp_status svp_psf_file_read(const char *path, svp_psf *psf, double *pixel_um,
                                     svp_boundary *boundary);

/* ---------------------------------------------------------------------------------------- */
/* Space-variant PSF fields and operators (docs/model.md §Space-variant)                     */
/* @@section variant */

/* ---------------------------------------------------------------------------------------- */
/* Fitting: Levenberg–Marquardt, PSF spot fits, PSF maps                                     */
/* @@section fit */

/* ---------------------------------------------------------------------------------------- */
/* Physics: source fields, reconstruction, spectra                                           */
/* @@section physics */

#ifdef __cplusplus
}
#endif
#endif /* SVPSF_H */
