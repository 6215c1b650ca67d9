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
    SVP_ERR_INTERNAL = 10,   /* a bug: please report it */
    SVP_ERR_DOUBTFUL = 11    /* the computation ran, but its result cannot be vouched for (not
                                converged, implausible, regularised away, an automatic choice
                                on the bound of its search); the message says what to change */
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
/* FFTW wisdom: plans measured once can be saved and reused across runs. Loading adds the
 * file's wisdom (double and single precision) to what the process holds; a malformed file is
 * refused (SVP_ERR_IO naming it) before FFTW sees it. Saving writes everything the process
 * holds to a temporary file in the same folder and renames it into place, so a concurrent
 * reader sees the old file or the new one, never a part (in place, when the folder is not
 * writable). To share one file between concurrent processes, load it again just before
 * saving (docs/api.md, "Shared machines"). */
SVP_API svp_status svp_fft_wisdom_load(const char *path);
SVP_API svp_status svp_fft_wisdom_save(const char *path);
/* Called before the library measures FFT plans (SVP_FFT_MEASURE) that no loaded wisdom
 * covers: ny x nx is the transform (ny = 1 for 1-D row transforms), single_precision 1 for
 * float plans. Measuring takes ~0.1 s at 512 x 512 to seconds at 2048 x 2048, so a program
 * can tell its user why it is waiting. The callback runs under the library's FFT lock, on the
 * thread that plans: it must not call the library. NULL (default): none. Process-wide. */
typedef void (*svp_fft_plan_fn)(void *user, int ny, int nx, int single_precision);
SVP_API void svp_set_fft_plan_callback(svp_fft_plan_fn callback, void *user);
/* The smallest even 2,3,5,7-smooth integer >= n (n >= 2; 1 for n <= 1): the FFT frame sizes of
 * the operators (FFTW transforms odd lengths up to 2x slower, docs/model.md §5). */
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
/* The range of magnitudes the solvers take: an image whose largest finite |value| is not 0 and
 * lies outside [SVP_VALUE_MIN, SVP_VALUE_MAX] is SVP_ERR_INVALID (`what` names it in the
 * message). Wiener–Hunt's conjugate gradients and RL's fits square the data, so beyond this
 * range their sums underflow or overflow (a PL of 1e-300 deconvolved to zeros). */
#define SVP_VALUE_MIN 1e-150
#define SVP_VALUE_MAX 1e150
SVP_API svp_status svp_image_check_scale(const svp_image *image, const char *what);

/* ---------------------------------------------------------------------------------------- */
/* Image files                                                                               */

/* Reads a single-channel image. The format follows the extension: .tif/.tiff (float32,
 * float64, 8/16-bit integer), .png (8/16-bit), .npy (float32/float64/integers, C or Fortran
 * order, 2-D), .txt/.csv/.dat (numbers as numpy.savetxt writes them, whitespace or comma
 * separated, '#' comments), .mat ("FILE.mat" or "FILE.mat:VAR": svp_mat_read below). Errors
 * name the file and the fault. An image may have at most
 * 2^28 pixels, each side at most 2^20 (SVP_ERR_FORMAT, checked from the file's header before
 * decoding); the memory the decoding needs is checked first against the environment variable
 * SVPSF_MAX_MEMORY, else the memory available (SVP_ERR_INVALID "<path>: ... needs N of memory,
 * more than the M allowed"; docs/reliability.md). svp_stack_read likewise, for all pages. */
SVP_API svp_status svp_image_read(const char *path, svp_image **out);
/* A stack where one image is expected is refused (SVP_ERR_FORMAT) naming its page count:
 *   "<path>: multi-page TIFF of 5 pages: expected one image (a stack is read as an ODMR stack
 *    by svp_stack_read / svpsf fit-odmr)"
 *   "<path>: a stack of 5 frames (3-D array of shape (5, 32, 48)): expected one image (...)" */

/* An image stack: n_frames images of one size (one per page of a multi-page TIFF, one per
 * leading index of a 3-D .npy array). */
typedef struct svp_stack {
    int width, height, n_frames;
    svp_image **frame; /* n_frames images */
} svp_stack;

/* Reads a stack: a multi-page TIFF (every page one channel of a type svp_image_read accepts,
 * all of the first page's size; pages decoded by OpenCV's imreadmulti), a .npy of shape
 * (n_frames, height, width) (C or Fortran order), or any single image (a stack of one frame).
 * Errors name the file and, for a bad page, the page: "<path>: page 3 of 5 is 64 x 32 but
 * page 1 is 32 x 32". */
SVP_API svp_status svp_stack_read(const char *path, svp_stack **out);
SVP_API void svp_stack_free(svp_stack *stack);
/* Writes frames as a float64 .npy of shape (n_frames, height, width) (the form svp_stack_read
 * and numpy.load read), atomically; an existing file only with overwrite. The name must end in
 * .npy (SVP_ERR_INVALID); frames of another size than the first are SVP_ERR_SIZE. */
SVP_API svp_status svp_stack_write(const char *path, const svp_image *const *frames, int n_frames,
                                   int overwrite);

/* MATLAB .mat files (docs/cli.md "MATLAB / QDMlab files"): the v5/v7 MAT-files MATLAB's save
 * writes by default, as QDMlab's maps are (B111dataToPlot.mat, Bz_uc0.mat) and its raw ODMR
 * runs (run_0000N.mat); read and written through libmatio. v7.3 (HDF5) and v4 files are refused
 * from their header. svp_image_read, svp_stack_read and svp_image_write take "FILE.mat" and
 * "FILE.mat:VAR" too (without the pixel size and stand-off). */
typedef struct svp_mat_info {
    char variable[64];  /* the variable read */
    int n_variables;    /* variables in the file */
    double pixel_um;    /* from the file's `step` (QDMlab: metres; a value >= 1e-3 is taken as
                           micrometres): one number, or two equal ones ([dx dy] of square
                           pixels); 0 when the file has none */
    int step_elements;  /* elements of the file's `step` variable, 0 when it has none: with
                           pixel_um 0 it says why the size was not taken (not 1 or 2 equal) */
    double standoff_um; /* from the file's `h` (metres), 0 when the file has none */
} svp_mat_info;
/* Reads one real numeric 2-D variable (double, single, any integer class, logical) as an image:
 * MATLAB's element (r, c) (column-major) becomes pixel (x = c, y = r). variable NULL or "" (and
 * no ":VAR" in path) picks the first present of Bz, B111ferro, B111para, else the only 2-D
 * numeric array with more than one element. info may be NULL. Errors (SVP_ERR_FORMAT, naming
 * the file): a missing variable (listing those present), a complex, sparse, cell, struct or
 * char variable, more than 2 dimensions (a 3-D array names its frame count), an empty array, a
 * variable larger than the file can hold. */
SVP_API svp_status svp_mat_read(const char *path, const char *variable, svp_image **out,
                                svp_mat_info *info);
/* Reads a stack: a 3-D variable rows x cols x frames (MATLAB's (:, :, k) is frame k), QDMlab's
 * raw layout (imgStackN of numFreqs x imgNumRows*imgNumCols, with the scalars imgNumRows and
 * imgNumCols: row k is frame k, written row after row), or a 2-D variable as one frame. The
 * default variable: the only 3-D numeric array, else imgStack1 in the raw layout, else as
 * svp_mat_read. */
SVP_API svp_status svp_mat_read_stack(const char *path, const char *variable, svp_stack **out,
                                      svp_mat_info *info);
/* Writes n images as double variables names[i] (MATLAB names: a letter, then letters, digits
 * or '_', at most 63; distinct) into one v7 MAT-file (zlib-compressed, as MATLAB's save), and
 * with pixel_um > 0 the scalar `step` = pixel_um / 1e6 (metres, as QDMlab writes it).
 * Atomic like svp_image_write; overwrite == 0 never replaces a file (SVP_ERR_EXISTS). */
SVP_API svp_status svp_mat_write(const char *path, int n, const char *const *names,
                                 const svp_image *const *images, double pixel_um, int overwrite);

typedef enum svp_file_format {
    SVP_FORMAT_AUTO = 0,  /* from the extension; unknown extension → error */
    SVP_FORMAT_TIFF = 1,  /* float32 TIFF */
    SVP_FORMAT_NPY = 2,   /* float64 .npy */
    SVP_FORMAT_TXT = 3,   /* numpy.savetxt-compatible text, %.17g */
    SVP_FORMAT_PNG16 = 4, /* 16-bit PNG scaled from [lo, hi] of the data (figures only) */
    SVP_FORMAT_MAT = 5    /* MATLAB v7 .mat, one double variable (svp_mat_write) */
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
    double beta;         /* Moffat index (>= 0.5); ignored for Gaussian, forced 1 for Lorentzian;
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
/* SVP_ERR_INVALID with a message for FWHM <= 0, Moffat beta < 0.5, halo outside [0, 1), ... */
SVP_API svp_status svp_psf_validate(const svp_psf *psf);
/* Moffat r0 from FWHM: r0 = FWHM / (2 sqrt(2^(1/beta) - 1)); Gaussian: sigma. */
SVP_API double svp_psf_fwhm_to_r0(double fwhm, double beta);
/* Un-normalised profile value at offset (dx, dy) in pixels (peak 1, no pixel integration). */
SVP_API double svp_psf_profile(const svp_psf *psf, double dx, double dy);
/* Fraction of the flux inside radius r of a disc of radius R (both in units of pixels; R = 0:
 * infinite plane when the flux converges, else NaN). Circular profiles in closed form, stable
 * near beta = 1 (expm1/log1p); elliptical ones exactly, by a quadrature over the direction
 * (about 1e-13 relative; their disc is rotation invariant, so the angle does not matter). */
SVP_API double svp_psf_encircled_energy(const svp_psf *psf, double r, double R);
/* Radius (pixels) along the major axis where the core profile falls to `level` (in (0, 1)) of
 * its peak, at most the support when one is set: the PSF's significant reach (level 0.01 gives
 * `svpsf correct --margin auto`, docs/model.md §3). 0 for a level outside (0, 1). */
SVP_API double svp_psf_reach(const svp_psf *psf, double level);
/* The margin (pixels per side) `svpsf correct --margin auto` and scenes' `margin: auto` take for
 * a width x height view: ceil(svp_psf_reach(psf, 0.01)), at most a quarter of the larger side;
 * 0 for a PSF with a halo, whose flux a margin's unknowns could take up (docs/model.md §3). */
SVP_API int svp_psf_auto_margin(const svp_psf *psf, int width, int height);
/* Radius (pixels) enclosing `fraction` of the flux over a disc of radius R (R = 0: the plane,
 * SVP_ERR_INVALID when its flux diverges); exact for elliptical profiles too. */
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
 * kernel image (pass -1, -1 for (kw / 2, kh / 2)). normalise != 0 scales it to unit sum (a
 * kernel whose sum is not positive is then SVP_ERR_INVALID). */
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
/* Bytes held by the operator (OTFs and work buffers; a space-invariant operator makes its frame
 * on first use, and holds only its kernel until then). */
SVP_API size_t svp_blur_memory(const svp_blur *blur);
/* H and Hᵀ of this operator in single precision (single 1: float FFTs, fftw3f, on the same
 * frames; the float spectra are made on first use and kept, counted by svp_blur_memory) or
 * double (0). Invariant, tent, low-rank and region operators; agreement with double:
 * docs/model.md §9.
 * SVP_ERR_UNSUPPORTED for the exact operator, and for returning to double an operator built
 * with svp_variant_options.single_precision. */
SVP_API svp_status svp_blur_set_precision(svp_blur *blur, int single);
/* The PSF's far tail on a coarse grid (docs/model.md §5, "The tail on a coarse grid"), for an
 * invariant zero-boundary operator (others: ignored, SVP_OK): tol > 0 lets the operator convolve
 * its kernel's core (radius 2 r0) exactly and the smooth rest on nodes every s pixels, with the
 * (s, r0) that costs least among those whose estimated error ‖ΔH‖₁ / ‖k‖₁ is at most tol, when
 * that costs less than 0.8 of the plain frame; 0 (the default of a new operator) = the plain
 * frame always. The operator stays linear, non-negative for a non-negative kernel, and its
 * adjoint exact. SVP_ERR_INVALID for tol outside [0, 1). */
SVP_API svp_status svp_blur_set_tail(svp_blur *blur, double tol);
/* The tolerance svpsf's corrections take by default (svp_correct_options.tail_tol, `correct` and
 * `fit-odmr --tail-tol`, the scenes' corrections). */
#define SVP_TAIL_TOL_DEFAULT 1e-3
/* The tail in use (made now if the frame is not): node spacing *step and split radius *split in
 * pixels and its estimated error, all 0 when the plain frame serves. */
SVP_API svp_status svp_blur_tail_info(svp_blur *blur, int *step, int *split, double *error);
/* The tolerance svp_blur_set_tail last set (0: none). */
SVP_API double svp_blur_tail_tol(const svp_blur *blur);

/* ---------------------------------------------------------------------------------------- */
/* Deconvolution (the ⊘ of eq. 4)                                                            */

/* What one deconvolution did (the library never prints: callers read this and warn). */
typedef struct svp_deconv_report {
    int wiener;         /* 1: a Wiener–Hunt deconvolution (the fields below apply); 0: RL */
    double balance;     /* the balance λ used (the chosen one with a discrepancy balance) */
    double noise_sigma; /* discrepancy balance: the noise σ used (given or estimated); with a
                           per-pixel noise (noise_per_pixel) the rms of its σ; else 0 */
    int noise_per_pixel; /* discrepancy balance: 1 when each pixel had its own noise variance
                            (svp_inverse_transform's noise models, docs/model.md §6), else 0 */
    int cg_steps;       /* zero-boundary Wiener: conjugate-gradient steps taken; else 0 */
    double cg_residual; /* its final relative residual ‖Hᵀ M y − A x‖ / ‖Hᵀ M y‖ */
    int cg_capped;      /* 1: the CG stopped at the step cap with the residual above its
                           tolerance (1e-8): x is usable but not converged */
    int balance_at_bound; /* discrepancy balance: -1 / +1 when the choice ended on the lower /
                             upper end of its search (the data cannot tell λ: see svp_correct's
                             doubt checks), else 0 */
    int balance_lcurve; /* svp_inverse_transform's automatic balance: 1 when no balance the
                           search could solve met the noise level and the L-curve's corner was
                           taken instead (docs/model.md §6), else 0 */
    /* Richardson–Lucy */
    int iterations;     /* iterations taken */
    double chi2;        /* with auto_stop: the last iterate's residual χ² per finite datum,
                           Σ m (Hx − y)² / var / n_finite (1 = the noise level); else 0 */
    int stop;           /* why RL stopped: an svp_rl_stop */
} svp_deconv_report;

/* Why a Richardson–Lucy run stopped. */
typedef enum svp_rl_stop {
    SVP_RL_STOP_COUNT = 0,       /* the requested number of iterations (auto_stop off) */
    SVP_RL_STOP_DISCREPANCY = 1, /* auto_stop: the residual reached the noise level (χ² ≤ 1) */
    SVP_RL_STOP_STALLED = 2,     /* auto_stop: the residual stopped falling above the noise level
                                    (the model cannot reach it: light from outside the view, a
                                    PSF that is off): fitting on would fit the model's error */
    SVP_RL_STOP_CAP = 3          /* auto_stop: the iteration cap came first (still improving) */
} svp_rl_stop;

/* Richardson–Lucy acceleration. */
typedef enum svp_rl_acceleration {
    SVP_RL_PLAIN = 0,        /* x ← RL(x) */
    SVP_RL_BIGGS_ANDREWS = 1 /* vector extrapolation (Biggs & Andrews, Appl. Opt. 36 (1997)
                                1766) in the log domain: RL is applied to x_k (x_k / x_{k−1})^α,
                                α from the correlation of the last two RL steps, in [0, 0.8] */
} svp_rl_acceleration;

typedef struct svp_deconv_options {
    double balance;        /* Wiener–Hunt λ in conj(P) / (|P|² + λ |L|²), L the Laplacian;
                              default 1e-3 */
    int iterations;        /* Richardson–Lucy iterations; default 50 */
    double floor;          /* RL: denominators Hx are floored at floor * max(y); default 1e-9 */
    int boundary_weights;  /* RL: Bertero–Boccacci normalisation by Hᵀ1 (default 1) */
    svp_progress_fn progress; /* optional */
    void *progress_user;
    int cg_max_steps;          /* zero-boundary Wiener: CG step cap; default 400 */
    svp_deconv_report *report; /* optional out (svp_deconv_wiener fills it); default NULL */
    int single_precision;      /* RL: 1 = the operator's convolutions transform in single
                                  precision (float FFTW, svp_blur_set_precision for this call),
                                  1.4-2.4x faster, results within about 1e-6 of the peak of
                                  double's; the iteration itself stays double. 0 (default):
                                  double. Invariant, tent and low-rank operators
                                  (SVP_ERR_UNSUPPORTED with the exact one). Wiener ignores it. */
    svp_rl_acceleration acceleration; /* RL: default SVP_RL_PLAIN */
    int auto_stop;             /* RL: 1 = iterations is a cap; stop at the discrepancy
                                  principle (χ² per finite datum ≤ 1) or when χ² falls by less
                                  than 0.1 % over 10 iterations (stalled above the noise level),
                                  whichever comes first (docs/model.md §9). Default 0. */
    const svp_image *variance; /* RL auto_stop: the noise variance of every pixel of y (y's
                                  size, > 0 where y is finite); NULL (default) = one σ² from
                                  svp_noise_sigma_estimate(y) */
} svp_deconv_options;

SVP_API void svp_deconv_defaults(svp_deconv_options *options);

/* Wiener–Hunt deconvolution of y by H. NaN/Inf pixels of y are missing data: they are filled
 * from their neighbours (normalised convolution with the PSF, refined by a few conjugate-
 * gradient steps to the fill the regularised model predicts) before filtering. The halo term
 * is inverted exactly (a scalar equation for the mean). Periodic H is filtered at the image
 * size, mirror H in the 2 width x 2 height symmetric frame. Zero-boundary H (no frame makes it
 * diagonal): the same problem (Hᵀ M H + λ LᵀL) x = Hᵀ M y of the linear operator, L with
 * reflecting ends, by CG preconditioned with the Wiener filter on H's padded frame (missing
 * pixels masked by M, no fill). Space-variant H: calls svp_deconv_tikhonov_cg with
 * options->cg_max_steps as its step cap (options->iterations is RL's) and fills the report's
 * cg_steps, cg_residual and cg_capped. Uses
 * options->balance (>= 0); progress once, at the end. x must have y's size and not be y.
 * options NULL = defaults. */
SVP_API svp_status svp_deconv_wiener(svp_blur *blur, const svp_image *y,
                                     const svp_deconv_options *options, svp_image *x);
/* The noise's standard deviation in y, estimated from the data (Immerkær 1996: the mean
 * absolute response to a mask that cancels locally quadratic signals; NaN/Inf neighbourhoods
 * skipped). Images of at least 3 x 3. */
SVP_API svp_status svp_noise_sigma_estimate(const svp_image *y, double *sigma);
/* A Wiener–Hunt balance for noisy data by the discrepancy principle: the λ in [1e-12, 1e2]
 * whose solution leaves the residual ‖M(H x_λ − y)‖² = n_finite σ² (down from 1e2 a decade at
 * a time, then 8 bisections within the decade; a search whose solves stop converging ends
 * there, on its lower bound). sigma <= 0: estimated by svp_noise_sigma_estimate; the σ used is returned
 * in *sigma_used (may be NULL). */
SVP_API svp_status svp_wiener_balance_discrepancy(svp_blur *blur, const svp_image *y,
                                                  double sigma, double *balance,
                                                  double *sigma_used);
/* Richardson–Lucy: x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm, started flat at the data mean; m is
 * 0 on NaN/Inf pixels of y (missing data), 1 elsewhere; pixels no finite datum sees keep the
 * start value. boundary_weights = 0 divides by the scalar mean of Hᵀm instead (plain RL).
 * y must be >= 0 where finite (else SVP_ERR_INVALID; signed data: the shift of method
 * rl-signed). Works for every operator kind; progress once per iteration; the output is >= 0
 * and finite. options NULL = defaults. */
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

/* Forward transform T (eq. 3): pl_apparent = H pl_true (clamped at 0: negative values are
 * FFT round-off); for each of the n_fields >= 1 components
 * field_apparent[c] = H(field_true[c] · pl_true) / pl_apparent. Where pl_apparent <=
 * 1e-10 · max(pl_apparent) (dark: no light, or FFT round-off of none) the apparent field is 0
 * and validity (may be NULL) 0, else 1. The true maps must be complete: NaN/Inf in pl_true or
 * a field_true, a negative pl_true, or one of zeros only (no light: the apparent field would
 * be undefined everywhere) is SVP_ERR_INVALID naming the input. Outputs must not
 * share pixels with inputs or each other. One H application per component plus one. */
SVP_API svp_status svp_forward_transform(svp_blur *blur, const svp_image *pl_true,
                                         const svp_image *const *field_true, int n_fields,
                                         svp_image *pl_apparent, svp_image *const *field_apparent,
                                         svp_image *validity);

typedef enum svp_method {
    SVP_METHOD_RW = 0,       /* RL on Ĩ, Wiener on B̃Ĩ (reference study's "R&W") */
    SVP_METHOD_R = 1,        /* RL on both; the signed numerator through the shift of
                                docs/model.md eq. 5 (default) */
    SVP_METHOD_W = 2,        /* Wiener on both */
    SVP_METHOD_RL_SIGNED = 3 /* RL on Ĩ and on (B̃ + c)Ĩ, minus c (Ĩ ⊘ p): same as R, the name
                                says what it does */
} svp_method;

typedef struct svp_correct_options {
    svp_method method;           /* default SVP_METHOD_R */
    svp_deconv_options deconv;   /* svp_deconv_defaults() except iterations = 75 (the
                                    reference study's RL count for measured data); its
                                    progress callback receives the whole job's fraction */
    double pl_floor;             /* in (0, 1): the recovered PL is floored at
                                    pl_floor · max(PL) before dividing; pixels below it have
                                    validity < 1; default 1e-3 */
    double shift;                /* c of the signed shift (methods R, RL_SIGNED); 0 (default)
                                    = automatic per component: c = 100 · max|B̃| over the
                                    measured pixels (1 for an all-zero map; docs/model.md §3).
                                    An explicit c must give B̃ + c > 0 at every measured pixel
                                    of every component. */
    int balance_auto;            /* 1: every Wiener deconvolution of the method (Ĩ for W, each
                                    B̃_c Ĩ for RW and W) chooses its own balance by the
                                    discrepancy principle (svp_wiener_balance_discrepancy);
                                    deconv.balance is then unused; default 0 */
    double noise_sigma;          /* balance_auto: the noise σ of every Wiener-deconvolved image
                                    (of Ĩ, of B̃_c Ĩ); <= 0 (default) = estimated per image */
    svp_deconv_report *reports;  /* optional out, n_fields + 1 entries: [0] for Ĩ ⊘ p, [1 + c]
                                    for component c's numerator; default NULL */
    const char *const *field_names; /* optional, n_fields entries: what the error messages call
                                       the field maps (their files, say); default NULL =
                                       "field_apparent[c]" */
    const char *pl_name;         /* optional: what the error messages call the PL map (its file,
                                    say); default NULL = "pl_apparent" */
    int margin;                  /* pixels per side of the estimated object beyond the view
                                    (light from outside the view, docs/model.md §3): 0
                                    (default) = the view only; > 0 needs a zero-boundary operator
                                    of (width + 2 margin) x (height + 2 margin) — the data term
                                    covers the view only, every output is the view's size */
    int auto_iterations;         /* RL methods: 1 = deconv.iterations is a cap; the PL's RL stops
                                    by the discrepancy/stall rule (svp_deconv_options.auto_stop,
                                    noise from the PL noise model below) and every numerator RL
                                    runs the same count, so both halves of (4) share their
                                    resolution; default 0 */
    double pl_gain;              /* camera gain of pl_apparent (counts per detected photon):
                                    var Ĩ = gain · max(Ĩ − pl_offset, 0); > 0 = given; 0
                                    (default) = estimated from the PL's variance-mean relation
                                    (svp_pl_noise_estimate) when a noise model is needed */
    double pl_offset;            /* camera offset, subtracted from pl_apparent before anything
                                    else; default 0 */
    const svp_image *const *field_sigma; /* optional, n_fields entries: the 1σ uncertainty of
                                    every pixel of B̃_c (what ODMR fits give); NULL (default) =
                                    σ_c² = k_c² / Ĩ, k_c estimated from B̃_c */
    int keep_doubtful;           /* 0 (default): a result the doubt checks reject returns
                                    SVP_ERR_DOUBTFUL; 1: returns SVP_OK with the affected pixels'
                                    validity 0 (all of them for a global doubt) and the doubts in
                                    summary */
    double plausible_factor;     /* doubt: |B_c| above plausible_factor · max|B̃_c| (measured
                                    pixels) is implausible; default 10 */
    double shrink_factor;        /* doubt: a field whose spread over the lit pixels (validity 1)
                                    is below shrink_factor · the measured field's spread there
                                    was regularised away; default 0.1 */
    struct svp_correct_summary *summary; /* optional out; default NULL */
    int side_by_side;            /* 1 (default): with methods R / RL_SIGNED, plain RL and a fixed
                                    count, the deconvolutions may run side by side, each on a
                                    copy of the operator (docs/model.md §3; a copy's memory
                                    each); 0: always in order on `blur` (one operator's memory,
                                    every FFT on all threads) */
    double tail_tol;             /* methods R / RL_SIGNED with an invariant zero-boundary
                                    operator: the PSF's far tail on a coarse grid for this
                                    call when its estimated error is at most tail_tol
                                    (svp_blur_set_tail; docs/model.md §5); 0 = the plain
                                    frame; default 1e-3 */
} svp_correct_options;

/* A Wiener (CG) solve that stops at its step cap counts as not converged, a result in doubt,
 * when its relative residual (svp_deconv_report.cg_residual) is above this; between the CG's own
 * tolerance 1e-8 and this it is converged to well below plotting accuracy and kept. */
#define SVP_CG_DOUBT_RESIDUAL 1e-4

/* Why T⁻¹'s result is in doubt (bits of svp_correct_summary.doubts). */
enum {
    SVP_DOUBT_CG_CAPPED = 1,     /* a Wiener (CG) solve stopped at its step cap, not converged */
    SVP_DOUBT_BALANCE_BOUND = 2, /* an automatic balance ended on its search's bound */
    SVP_DOUBT_RL_CAP = 4,        /* automatic RL iterations ended on the cap */
    SVP_DOUBT_IMPLAUSIBLE = 8,   /* |B_c| beyond plausible_factor · max|B̃_c| somewhere */
    SVP_DOUBT_SHRUNK = 16,       /* a field regularised away (spread below shrink_factor) */
    SVP_DOUBT_LIGHT_LOST = 32,   /* the corrected PL keeps under 1 % of the measured PL's light
                                    on the view */
    SVP_DOUBT_OPERATOR = 64      /* a space-variant operator chosen by its budget
                                    (svp_variant_options.tolerance) missed it, with an estimated
                                    error above SVP_OPERATOR_DOUBT_ERROR */
};

/* The estimated relative operator error (svp_variant_info.estimated_error) above which an
 * automatically chosen representation that missed its budget puts T⁻¹ in doubt: a PSF is
 * rarely known better than a few per cent, and an operator further from the map than that adds
 * an error of its own. A budget above it is the caller accepting more. */
#define SVP_OPERATOR_DOUBT_ERROR 0.05

/* The name of doubt bit `bit` (SVP_DOUBT_* = 1 << bit) as summary.json writes it
 * ("cg_not_converged", "balance_at_bound", "iterations_at_cap", "implausible_values",
 * "regularised_away", "light_lost", "operator_error"); NULL beyond the last. */
SVP_API const char *svp_doubt_name(int bit);
/* The names of the bits set in `doubts`, comma-separated, into buf (size bytes, truncated). */
SVP_API void svp_doubt_list(unsigned doubts, char *buf, size_t size);

/* What T⁻¹ did and what it doubts (svp_correct_options.summary). */
typedef struct svp_correct_summary {
    unsigned doubts;        /* SVP_DOUBT_* bits */
    size_t n_implausible;   /* pixels with an implausible |B_c| (any component) */
    double spread_ratio;    /* smallest over components: spread(B_c) / spread(B̃_c), lit pixels */
    double pl_gain;         /* the PL gain used by the noise model (given or estimated; 0 when
                               no noise model was needed) */
    double pl_gain_offset;  /* with an estimated gain: the offset its variance-mean line implies
                               (reported, never subtracted) */
    double shift[16];       /* methods R/RL_SIGNED: the shift c of the first 16 components */
    int rl_iterations;      /* RL on Ĩ: iterations taken (0 for method W) */
    int rl_stop;            /* an svp_rl_stop */
    double rl_chi2;         /* auto_iterations: χ² per datum where the PL's RL stopped */
    int side_by_side;       /* the deconvolutions ran side by side on this many workers, each on
                               a copy of the operator (docs/model.md §3), or 1: in order */
    int side_by_side_fallback; /* 1: side by side was chosen, but its copies found no memory,
                                  so the runs went in order on the caller's operator */
    int tail_step;          /* the tail on a coarse grid (tail_tol): node spacing, split radius
                               r0 (px) and estimated error; 0 when the plain frame served */
    int tail_split;
    double tail_error;
} svp_correct_summary;

/* The PL's noise model from the image itself: in blocks of 16 x 16 the local mean and the
 * Immerkær variance of the block; the gain is the slope of variance against mean (a robust
 * line: Theil–Sen), offset where the line reaches variance 0. SVP_ERR_INVALID for images
 * under 32 x 32 or with fewer than 8 usable blocks; gain 0 when the variance does not grow
 * with the mean (noiseless or not Poisson-like). */
SVP_API svp_status svp_pl_noise_estimate(const svp_image *pl, double *gain, double *offset);

SVP_API void svp_correct_defaults(svp_correct_options *options);

/* The margin rule of svp_inverse_transform for a width x height view: a margin wider than the
 * view's larger side is SVP_ERR_INVALID (the data barely see pixels that far, and the work grows
 * with the square of the grid). A caller checks it before building the (w + 2m) x (h + 2m)
 * operator. */
SVP_API svp_status svp_correct_check_margin(int margin, int width, int height);

/* Inverse transform T⁻¹ (eq. 4): pl_true = Ĩ ⊘ p; field_true[c] = ((B̃_c Ĩ) ⊘ p) / max(pl_true,
 * floor), floor = pl_floor · max(pl_true); for R / RL_SIGNED the numerator is
 * ((B̃_c + c) Ĩ) ⊘ p − c · pl_true (eq. 5). All components share the one deconvolution of Ĩ.
 * Missing data: a pixel where Ĩ or any B̃_c (or, given, its field_sigma) is NaN/Inf is missing
 * in every deconvolution (RL masks it, Wiener fills it), so numerator and denominator see the
 * same measurements.
 * validity (may be NULL) in [0, 1] (eq. 6): clamp(pl_true / floor, 0, 1), times at missing
 * pixels the share of their light the core PSF puts on measured pixels (0 where nothing covers
 * them). No NaN or Inf is ever written. n_missing (may be NULL) returns the number of missing
 * pixel positions. options NULL = svp_correct_defaults. RL methods (RW, R, RL_SIGNED) need
 * Ĩ >= 0 (SVP_ERR_INVALID otherwise; W accepts signed PL). No light at all (max Ĩ <= 0) and
 * no measured pixel are SVP_ERR_INVALID ("holds no light", "every pixel of ... is NaN or Inf").
 * Outputs must not share pixels with inputs or each other. */
SVP_API svp_status svp_inverse_transform(svp_blur *blur, const svp_image *pl_apparent,
                                         const svp_image *const *field_apparent, int n_fields,
                                         const svp_correct_options *options,
                                         svp_image *pl_true, svp_image *const *field_true,
                                         svp_image *validity, size_t *n_missing);

/* Closed-form inverse for a halo-only PSF p = (1 − α) δ + α / A (docs/model.md §4, exact for any
 * PL): Ĩ = (1 − α) I + α <Ĩ>, B̃Ĩ = (1 − α) BI + α <B̃Ĩ>, so
 * B = (B̃Ĩ − α <B̃Ĩ>) / (Ĩ − α <Ĩ>) (eq. 7), means over the whole image. With uniform PL:
 * ΔB = ΔB̃ / (1 − α). Where the denominator is <= 1e-10 · max|Ĩ| (no light) B = 0. α must be
 * in [0, 1); NaN/Inf inputs are SVP_ERR_INVALID (the means need complete maps). field_true may
 * be field_apparent or pl_apparent (computed pointwise after the means). */
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

/* A PSF field says how the PSF varies over a width x height image. One model per field
 * (Gaussian, Lorentzian or Moffat; a "Gaussian-like" region inside a Moffat field is a Moffat
 * with a large beta, e.g. 10). support and subsample are common to the whole field (taken from
 * the first PSF given). What varies, and is interpolated, is the parameter vector
 *   p = {fwhm, e1, e2, beta, halo}     (SVP_FIELD_NPARAM = 5, in that order)
 * with fwhm = (FWHM_major + FWHM_minor) / 2 in pixels, ellipticity
 * e = (FWHM_major − FWHM_minor) / (FWHM_major + FWHM_minor) and (e1, e2) = e (cos 2θ, sin 2θ):
 * orientation is interpolated weighted by ellipticity, never as θ. beta is interpolated
 * linearly (ignored for Gaussian, 1 for Lorentzian); halo is alpha_b. Interpolated values are
 * clamped to valid ranges (fwhm >= 0.05 px, |e| <= 0.95, beta >= 0.05, halo in [0, 0.999]).
 * Positions are pixel coordinates: pixel (x, y) is data[y * width + x], x, y may be
 * fractional. */
#define SVP_FIELD_NPARAM 5
typedef enum svp_field_param {
    SVP_FIELD_FWHM = 0, /* mean FWHM (major + minor) / 2, pixels */
    SVP_FIELD_E1 = 1,   /* e cos 2θ */
    SVP_FIELD_E2 = 2,   /* e sin 2θ */
    SVP_FIELD_BETA = 3, /* Moffat beta */
    SVP_FIELD_HALO = 4  /* alpha_b */
} svp_field_param;

typedef enum svp_psf_field_kind {
    SVP_FIELD_UNIFORM = 0, /* one PSF everywhere */
    SVP_FIELD_GRID = 1,    /* PSFs at nodes, bilinear in between, constant beyond */
    SVP_FIELD_POLY = 2,    /* polynomial surfaces in normalised position */
    SVP_FIELD_REGIONS = 3  /* a PSF per label of a label image, blended across boundaries */
} svp_psf_field_kind;

typedef struct svp_psf_field svp_psf_field;

/* PSF <-> parameter vector (see above). svp_psf_to_params needs a valid psf; from_params
 * takes model, support and subsample from `base` and clamps p to the valid ranges. */
SVP_API svp_status svp_psf_to_params(const svp_psf *psf, double p[SVP_FIELD_NPARAM]);
SVP_API void svp_psf_from_params(const svp_psf *base, const double p[SVP_FIELD_NPARAM],
                                 svp_psf *out);

/* Uniform field. width = height = 0 makes a field valid for any image size (the plain PSF
 * file of the foundation issue reads as that). */
SVP_API svp_status svp_psf_field_new_uniform(const svp_psf *psf, int width, int height,
                                             svp_psf_field **out);

/* Node grid: nx x ny nodes, node (i, j) at (node_x[i], node_y[j]) pixels with PSF
 * node_psfs[j * nx + i]. node_x / node_y strictly increasing, may lie outside the image;
 * NULL = evenly spread with nodes at cell centres: x_i = (i + 0.5) width / nx − 0.5.
 * Parameters are bilinear in between and constant beyond the outermost nodes. All node PSFs
 * must share the model. */
SVP_API svp_status svp_psf_field_new_grid(int width, int height, int nx, int ny,
                                          const double *node_x, const double *node_y,
                                          const svp_psf *node_psfs, svp_psf_field **out);

/* Polynomial surfaces of total degree `degree` (0..8) in normalised position
 *   u = (2 x − (width − 1)) / max(width − 1, 1),  v likewise with y and height  (u, v in [-1, 1])
 * p_q(u, v) = Σ_t coeffs[q * n_terms + t] · basis_t(u, v), q over SVP_FIELD_NPARAM parameters,
 * n_terms = svp_psf_field_poly_terms(degree) = (degree + 1)(degree + 2) / 2, and the terms
 * ordered by total degree, then by the power of v: 1, u, v, u², u v, v², u³, u² v, ...
 * For least squares: one row per measured spot is svp_psf_field_poly_basis(...), the
 * right-hand side the spot's parameter vector (svp_psf_to_params). `base` gives model, support,
 * subsample (its own parameters are not used). */
SVP_API int svp_psf_field_poly_terms(int degree);
SVP_API void svp_psf_field_poly_basis(int degree, int width, int height, double x, double y,
                                      double *basis /* n_terms values */);
SVP_API svp_status svp_psf_field_new_poly(const svp_psf *base, int width, int height,
                                          int degree, const double *coeffs,
                                          svp_psf_field **out);

/* Regions: labels[y * width + x] in 0 .. n_labels − 1 picks region_psfs[label]. Across a
 * boundary the parameter vectors blend over `transition` pixels (10 %–90 % width): the blend
 * weights are the one-hot label maps smoothed with a Gaussian of sigma = transition / 2.563
 * (mirror boundary), so they are >= 0 and sum to 1 at every pixel; transition = 0 gives sharp
 * regions. A label with no pixel is allowed (unused). */
SVP_API svp_status svp_psf_field_new_regions(int width, int height, const int *labels,
                                             int n_labels, const svp_psf *region_psfs,
                                             double transition, svp_psf_field **out);

SVP_API svp_status svp_psf_field_copy(const svp_psf_field *field, svp_psf_field **out);
SVP_API void svp_psf_field_free(svp_psf_field *field);
SVP_API svp_psf_field_kind svp_psf_field_get_kind(const svp_psf_field *field);
/* The field's image size (0 x 0 for a uniform field valid for any size). */
SVP_API int svp_psf_field_width(const svp_psf_field *field);
SVP_API int svp_psf_field_height(const svp_psf_field *field);
/* The local PSF at pixel position (x, y) (fractional allowed; regions: bilinear between
 * pixel centres, clamped to the image). */
SVP_API svp_status svp_psf_field_at(const svp_psf_field *field, double x, double y,
                                    svp_psf *out);
/* The local parameter vector at (x, y) (clamped as above). */
SVP_API svp_status svp_psf_field_params_at(const svp_psf_field *field, double x, double y,
                                           double p[SVP_FIELD_NPARAM]);
/* Where a field's parameters leave their valid range inside its image, so that
 * svp_psf_field_params_at clamps them (a polynomial extrapolated beyond the spots it was fitted
 * to, into a corner). Sampled at the image's pixel centres: every pixel up to 512 per side,
 * else every k-th (the last row and column included). Per parameter q (SVP_FIELD_E1 stands for
 * the ellipticity |e|, SVP_FIELD_E2 is unused): how many samples leave the range, and at the
 * one furthest beyond it its position, unclamped value and the bound it is clamped to. box:
 * NULL for the whole image, else {x0, y0, x1, y1} (inclusive, clipped to the image), e.g. the
 * extent of the spots a map was fitted to. A uniform field, or one without an image size,
 * reports nothing. */
typedef struct svp_psf_field_range {
    size_t sampled, clamped;          /* samples; those with any parameter out of range */
    size_t count[SVP_FIELD_NPARAM];
    int x[SVP_FIELD_NPARAM], y[SVP_FIELD_NPARAM];
    double value[SVP_FIELD_NPARAM], bound[SVP_FIELD_NPARAM];
} svp_psf_field_range;
SVP_API svp_status svp_psf_field_check_range(const svp_psf_field *field, const int *box,
                                             svp_psf_field_range *out);
/* The field on its image plus `margin` pixels on every side, for an operator on the grid of
 * svp_correct_options.margin (light from outside the view, docs/model.md §3 and §9): at
 * (x, y) of the larger image, the PSF of the original image's pixel nearest to
 * (x − margin, y − margin) — the map's edge values carried outward (grid and poly fields clamp
 * the position to the image; region fields replicate the edge labels outward and blend them as
 * usual, so a blended map's parameters within a transition of the edge may differ by the
 * blend's boundary). margin 0, a uniform field or one without a size: a copy (a sized uniform
 * field gets the larger size). margin in 0 .. 100000; a padded field cannot be written as a
 * PSF-map file (svp_psf_field_write: SVP_ERR_UNSUPPORTED), being for one operator's grid. */
SVP_API svp_status svp_psf_field_pad(const svp_psf_field *field, int margin, svp_psf_field **out);
/* `--margin auto` for a PSF map over a width x height view: the largest svp_psf_auto_margin of
 * the field's PSFs (sampled on at most 128 x 128 positions of the view, edges included, and for
 * a region map every label's PSF in use), at most a quarter of the larger side; 0 when any of
 * them has a halo (as for one PSF). */
SVP_API int svp_psf_field_auto_margin(const svp_psf_field *field, int width, int height);

/* PSF-map files (YAML; docs/cli.md §PSF maps). Lengths in µm in the file, pixels in memory:
 *   version: 1                             # optional
 *   pixel_um: 0.1                          # required, > 0
 *   image: {width: 512, height: 512}       # required except for uniform
 *   model: moffat                          # gaussian | lorentzian | moffat: one per field
 *   support_um: 0                          # optional; 0 = whole field of view
 *   subsample: 0                           # optional, 0..64
 *   kind: uniform | grid | poly | regions
 *   psf: {fwhm_um: 0.6, fwhm_minor_um: 0.5, angle_deg: 30, beta: 1.1, halo: 0}   # uniform
 *   nodes: {nx: 4, ny: 3}  or  {x_px: [...], y_px: [...]}   # grid (nx/ny: cell centres)
 *   node_psfs: [{fwhm_um: .., beta: .., ...}, ...]  # grid: nx * ny entries, x fastest
 *   degree: 2                              # poly
 *   coefficients: {fwhm_um: [...], e1: [...], e2: [...], beta: [...], halo: [...]}
 *                                          # poly: n_terms each; only fwhm_um required
 *   labels_file: map.labels.npy            # regions: an image of integer labels 0..L-1,
 *                                          #   relative to this file's folder
 *   transition_um: 0.5                     # regions, optional (default 0: sharp)
 *   regions: [{label: 0, name: bare, fwhm_um: .., beta: .., halo: ..}, ...]   # L entries
 *   provenance: "free text"                # optional (also: comment)
 * In every PSF entry fwhm_um is required, beta is required for Moffat fields (and refused for
 * Gaussian ones), the rest is optional (fwhm_minor_um: 0 = circular; angle_deg 0; halo 0).
 * A file without `kind` is read as the plain PSF file (svp_psf_file_read): a uniform field of
 * size 0 x 0. pixel_um (may be NULL) returns the pixel size. Errors name file:line:column and
 * the key (unknown keys, keys of another kind, wrong counts, labels outside 0..L-1).
 * svp_psf_field_write writes atomically (with overwrite == 0 an existing file gives
 * SVP_ERR_EXISTS); a regions field first writes its labels to "<path without .yaml/.yml>
 * .labels.npy" (same rule). Grid nodes are written as PSFs rebuilt from their parameter vectors
 * (identical shapes). provenance may be NULL. */
SVP_API svp_status svp_psf_field_read(const char *path, svp_psf_field **out, double *pixel_um);
SVP_API svp_status svp_psf_field_write(const char *path, const svp_psf_field *field,
                                       double pixel_um, const char *provenance, int overwrite);

/* The space-variant operator (docs/model.md §9): H x = Σ_k p_k ⊛ (w_k (1 − α) ⊙ x) + <α x>_FOV,
 * α the field's per-pixel halo (exact, not interpolated), p_k normalised core kernels.
 *  - tent: K = gx x gy nodes at x_i = i (width − 1) / (gx − 1) (the centre when gx = 1),
 *    bilinear hat weights w_k >= 0 summing to 1 at every pixel; p_k = the field's PSF at node k.
 *    Flux and positivity are kept exactly; error vs the exact operator falls as (node
 *    spacing)². One application: K forward + 1 inverse real FFT; adjoint 1 + K.
 *  - low rank: the field's PSF sampled on sx x sy positions (placed like tent nodes), the
 *    stacked kernels' SVD (from their S x S Gram matrix, LAPACKE_dsyevr, the kernels streamed
 *    in row blocks: docs/model.md §9) gives `rank` eigen-PSFs e_r and coefficients at the
 *    samples, interpolated bilinearly into maps c_r: H x = Σ_r e_r ⊛ (c_r (1 − α) ⊙ x) + ...
 *    With lowrank_mean (default) the first term is the mean sampled kernel (c_0 = 1) and the
 *    others come from the SVD of the deviations from it: they sum to zero, so every source
 *    keeps unit flux at every rank. A plain SVD (lowrank_mean = 0) keeps flux only
 *    approximately (tests measure up to 60 % at rank 1); with renormalise (default) its
 *    coefficient maps are divided per pixel by the expansion's flux so a point source keeps
 *    unit flux exactly (with lowrank_mean and no halo that flux is 1 to round-off, and the
 *    division is skipped). Positivity is not guaranteed by either. rank = sx sy with
 *    renormalise = 0 equals the tent operator on the same grid, so the error never falls below
 *    the tent's on the sample grid. Whole-field kernels are fine at any size that the memory
 *    limit (max_memory) allows.
 * All kernels share one radius: support (pixels) if > 0, else the field's PSF support, else the
 * whole field of view (offsets up to width − 1, height − 1), as svp_blur_new. Memory: one
 * spectrum of the padded frame per node / eigen-PSF (svp_blur_memory), real for point-symmetric
 * PSFs (every Moffat and Gaussian) unless the tent's node transforms are row-pruned, complex
 * otherwise. */
typedef enum svp_variant_repr {
    SVP_VARIANT_TENT = 0,
    SVP_VARIANT_LOWRANK = 1,
    /* default: the cheapest tent grid or low rank whose estimated relative operator error
     * (docs/model.md §9, "Choosing the representation") is at most `tolerance`, by a cost model
     * of `applications` applications plus the build; grid_x / samples_x etc. are ignored.
     * For region maps the region representation is a candidate too */
    SVP_VARIANT_AUTO = 2,
    /* PSF maps of kind regions only (else SVP_ERR_INVALID): one term per label that has a
     * pixel, H x = Σ_k e_k ⊛ (c_k (1 − α) ⊙ x) + <α x>_FOV with e_k the normalised kernel of
     * label k's PSF and c_k its blend weight map (one-hot for a sharp map). Exact to round-off
     * against svp_blur_new_exact for sharp maps; for blended ones (transition > 0) the field
     * blends PSF parameters, so blending kernels is an approximation (its error is estimated
     * like the others'). Built and applied as low rank (single precision included); memory:
     * one spectrum and a per-pixel weight table per term (docs/model.md §9, "Region maps"). */
    SVP_VARIANT_REGIONS = 3
} svp_variant_repr;

typedef struct svp_variant_options {
    svp_variant_repr representation; /* default SVP_VARIANT_AUTO */
    int grid_x, grid_y;    /* tent nodes per axis, 1 .. 64 each; default 8 x 8 (clamped to
                              the image size) */
    int rank;              /* low rank: terms kept (the mean counts as one), 1 .. sx sy;
                              default 6 */
    int samples_x, samples_y; /* low rank: PSF sample grid; default 8 x 8 */
    int renormalise;       /* low rank: exact unit flux per source (default 1) */
    int lowrank_mean;      /* low rank: mean PSF first, SVD of the deviations (default 1) */
    double support;        /* kernel radius in pixels; 0 (default) = as described above */
    svp_progress_fn progress; /* optional, during construction */
    void *progress_user;
    double tolerance;      /* SVP_VARIANT_AUTO: relative operator error budget (default 1e-3) */
    int applications;      /* SVP_VARIANT_AUTO cost model: H + Hᵀ pairs expected (default 50) */
    double max_memory;     /* bytes the operator may hold, its build included; 0 (default) = the
                              machine's physical memory. Checked before anything large is
                              allocated: SVP_ERR_INVALID naming the bytes needed */
    int single_precision;  /* 1: the terms' spectra kept in float only (half the memory) and H,
                              Hᵀ transformed in float (fftw3f) on the same frames, always; the
                              build itself is double (docs/model.md §9). Default 0 */
    double tail_tol;       /* low rank and regions with the zero boundary: each term's
                              far tail on a coarse grid (docs/model.md §9, "The far tail on a coarse grid"), the
                              cores on a frame for their radius, when that is cheaper and the
                              estimated ℓ1 error per unit flux is at most this; 0 (default) =
                              the plain frame. `correct` passes its --tail-tol (10⁻³) */
} svp_variant_options;

/* What svp_blur_new_field built (svp_blur_variant_info). estimated_error: the relative
 * operator error ‖H − H_exact‖_F / ‖H_exact‖_F estimated at probe sources (docs/model.md §9),
 * NaN when not estimated (a forced representation estimates only through
 * svp_variant_estimate). */
typedef struct svp_variant_info {
    svp_variant_repr representation; /* SVP_VARIANT_TENT, _LOWRANK or _REGIONS */
    int grid_x, grid_y;              /* tent nodes, or low-rank samples; regions: 0 */
    int rank;                        /* low rank: terms; regions: region kernels; tent: 0 */
    double estimated_error;
    double tolerance;                /* the budget (auto), else 0 */
    int tolerance_met;               /* auto: 1 when the choice meets the budget */
    int candidates;                  /* auto: representations compared */
    double estimate_seconds;         /* auto: time of the estimates */
    double build_seconds;            /* the operator's build */
    size_t memory_bytes;             /* svp_blur_memory after the build */
    size_t peak_bytes;               /* the estimate checked against max_memory */
    int tail_step, tail_split;       /* low rank, regions with tail_tol: node spacing and split radius of
                                        the far tail on a coarse grid (0: the plain frame) */
    double tail_error;               /* its estimated ℓ1 error per unit flux, all terms */
} svp_variant_info;

SVP_API svp_status svp_blur_variant_info(const svp_blur *blur, svp_variant_info *info);
/* Estimated relative operator error (as svp_variant_info.estimated_error) of the tent grid,
 * low rank or regions that options force (representation TENT, LOWRANK or REGIONS; REGIONS on
 * a field not of kind regions: SVP_ERR_INVALID). */
SVP_API svp_status svp_variant_estimate(const svp_psf_field *field, int width, int height,
                                        svp_boundary boundary,
                                        const svp_variant_options *options, double *error);

SVP_API void svp_variant_defaults(svp_variant_options *options);
/* Builds H for a field (options NULL = defaults). A field with a size must match width x
 * height (SVP_ERR_SIZE). The result works with svp_blur_apply / _adjoint / _free / _memory and
 * the solvers (RL; Wiener dispatches to svp_deconv_tikhonov_cg). */
SVP_API svp_status svp_blur_new_field(const svp_psf_field *field, int width, int height,
                                      svp_boundary boundary, const svp_variant_options *options,
                                      svp_blur **out);
/* The exact per-source reference operator Ĩ(o) = Σ_s [(1 − α_s) k_s(o − s) + α_s / N] I(s),
 * k_s the normalised core kernel of the PSF at source pixel s (same sampling and truncation as
 * svp_psf_render, same boundary modes as svp_blur_new: the scene beyond the edges is zero,
 * mirrored or periodic), and its exact adjoint. Direct sums, O(N · kernel area) per
 * application: meant for images up to ~256² (tests, benchmarks). support as in
 * svp_variant_options (0 = the field's support, else the whole field of view). */
SVP_API svp_status svp_blur_new_exact(const svp_psf_field *field, int width, int height,
                                      svp_boundary boundary, double support, svp_blur **out);
/* 1 for the space-variant kinds (tent, low rank, exact), 0 for the invariant operator. */
SVP_API int svp_blur_is_variant(const svp_blur *blur);
/* The local PSF of the operator's field at (x, y) (for invariant operators built from a model:
 * that model; from a kernel: SVP_ERR_UNSUPPORTED). */
SVP_API svp_status svp_blur_psf_at(const svp_blur *blur, double x, double y, svp_psf *out);

/* Tikhonov deconvolution for any operator: x = argmin ‖m (Hx − y)‖² + λ ‖L x‖², λ =
 * options->balance, L the 5-point Laplacian (same boundary as H), m = 0 at NaN/Inf pixels of
 * y (missing data), 1 elsewhere. Conjugate gradients on the normal equations
 * (Hᵀ m H + λ LᵀL) x = Hᵀ m y, preconditioned by the Wiener filter of the PSF at the image
 * centre (periodic frame), started at 0; at most options->iterations steps (NULL options =
 * svp_deconv_defaults), stopping early when the relative residual ‖Hᵀm y − A x‖ / ‖Hᵀm y‖ falls
 * below 1e-10 (options->report, when given, gets cg_steps, cg_residual and cg_capped). For an
 * invariant periodic H this is the Wiener–Hunt solution (X = conj(Ĥ) Y / (|Ĥ|² + λ |L̂|²)),
 * reached in one step. Progress per iteration. */
SVP_API svp_status svp_deconv_tikhonov_cg(svp_blur *blur, const svp_image *y,
                                          const svp_deconv_options *options, svp_image *x);

/* ---------------------------------------------------------------------------------------- */
/* Registration: align two images of the same scene, warp one onto the other's grid          */
/* @@section register */
/* Coordinates are pixel coordinates: pixel (x, y) is data[y * width + x], its centre at the
 * integer point (x, y) (OpenCV's convention). A transform is a row-major 2 x 3 affine matrix
 * a[6] that maps REFERENCE pixel coordinates to MOVING pixel coordinates:
 *     x_moving = a[0] x_ref + a[1] y_ref + a[2]
 *     y_moving = a[3] x_ref + a[4] y_ref + a[5]
 * so the scene point seen at (x_ref, y_ref) in the reference is seen at (x_moving, y_moving) in
 * the moving image, and warping the moving image onto the reference grid samples it at
 * a · (x_ref, y_ref, 1) (svp_warp; OpenCV's warpAffine with WARP_INVERSE_MAP). A moving image
 * whose content is displaced by +d (moving(x) = reference(x − d)) gives a = [1 0 d_x; 0 1 d_y]. */

typedef enum svp_register_method {
    SVP_REGISTER_PHASE = 0, /* phase correlation: translation only, sub-pixel (default) */
    SVP_REGISTER_ECC = 1    /* OpenCV findTransformECC (enhanced correlation coefficient),
                               started from the phase-correlation translation */
} svp_register_method;

typedef enum svp_register_motion {
    SVP_MOTION_TRANSLATION = 0, /* 2 parameters (default) */
    SVP_MOTION_EUCLIDEAN = 1,   /* rotation + translation, 3 parameters (ECC only) */
    SVP_MOTION_AFFINE = 2       /* full 2 x 3 affine, 6 parameters (ECC only) */
} svp_register_motion;

typedef enum svp_register_contrast {
    SVP_CONTRAST_AUTO = 0,    /* the sign of the correlation peak decides (default) */
    SVP_CONTRAST_SAME = 1,    /* bright in one image is bright in the other */
    SVP_CONTRAST_INVERTED = 2 /* bright in one is dark in the other: a label mask of regions
                                 that are dark in the PL (a metal wire), a negative */
} svp_register_contrast;

typedef struct svp_register_options {
    svp_register_method method; /* default SVP_REGISTER_PHASE */
    svp_register_motion motion; /* default SVP_MOTION_TRANSLATION; phase correlation accepts
                                   only TRANSLATION */
    int normalise;       /* 1 (default): each image is scaled to zero mean and unit variance
                            over its finite pixels before anything else, so images of different
                            brightness (PL vs reflectance) compare; the residual is then in
                            units of the standard deviation. 0: used as they are (the mean is
                            still subtracted for phase correlation, which ignores scale). */
    double smooth_sigma; /* Gaussian pre-smoothing, sigma in pixels, of both images (>= 0; 0 =
                            none); default 1. Phase correlation: applied as the spectral weight
                            exp(−σ² |ω|²) on the cross-power spectrum; ECC: cv::GaussianBlur of
                            both images. Damps pixel noise; does not bias a translation. */
    /* phase correlation */
    int window;          /* 1 (default): Hann window (sin² taper to zero at the edges) so the
                            image edges do not correlate; refined passes lay it over the region
                            both images see and move it with the scene, so the windowed images
                            are exact shifted copies (no pull towards zero shift). 0: no window
                            (periodic images; isolated spots on a flat background, e.g. an
                            excitation/emission spot pair, where it is more accurate). */
    double whitening;    /* regularised whitening of the cross-power spectrum X = M conj(R):
                            X / (|X| + whitening · max|X|) (0 = pure phase correlation, which
                            amplifies noise-only frequencies; large = plain cross-correlation);
                            >= 0, default 0.1 */
    double min_significance; /* results whose phase-correlation peak significance is below
                            this are flagged (result->low_significance); default 10 (measured
                            on blob scenes of 64² to 512²: unrelated images 3–9, shifted
                            copies 12–100, with or without moderate noise) */
    /* ECC */
    int iterations;      /* most ECC iterations (>= 2); default 100 */
    double epsilon;      /* ECC stops when the correlation coefficient changes by less than
                            this between iterations (OpenCV's TermCriteria EPS); default 1e-6.
                            Not reached within `iterations` → SVP_ERR_NUMERIC. */
    const double *initial_affine; /* ECC starting transform (6 values, see above); NULL
                            (default) = the phase-correlation translation */
    svp_progress_fn progress; /* optional: once per ECC iteration */
    void *progress_user;
    const char *reference_name, *moving_name; /* optional: what error messages call the two
                            images (their files, say); NULL (default) = "reference image",
                            "moving image" */
    svp_register_contrast contrast; /* AUTO (default): the phase-correlation surface is
                            searched for its highest peak and its deepest trough; the trough
                            wins when its significance (of the negated surface) is the higher,
                            and the moving image is then registered (and ECC run, and the
                            quality measured) with its contrast inverted. SAME / INVERTED force
                            the sign. ECC with initial_affine and AUTO keeps the contrast as it
                            is (nothing measures it). */
} svp_register_options;

SVP_API void svp_register_defaults(svp_register_options *options);

typedef struct svp_register_result {
    double affine[6];   /* reference → moving pixel coordinates (see above) */
    double shift_x;     /* displacement of the reference image centre c = ((w − 1) / 2,
                           (h − 1) / 2): a · c − c, pixels (= a[2], a[5] for a translation) */
    double shift_y;
    double rotation;    /* angle of the linear part, atan2(a[3] − a[1], a[0] + a[4]), radians
                           from +x towards +y: the moving image shows the reference rotated by
                           this angle (exact for euclidean and similarity transforms) */
    double scale;       /* sqrt|a[0] a[4] − a[1] a[3]|: moving features are this many times
                           larger (1 for translation and euclidean) */
    double response;    /* phase correlation: the interpolated peak height / its largest
                           possible value Σ|W|, in [−1, 1]: 1 for exact shifted copies, lower
                           with noise; smooth unrelated images can still reach 0.2–0.7, so
                           judge by `significance`. ECC: that of its starting translation
                           (NaN when initial_affine is given) */
    double significance; /* peak-to-sidelobe ratio of the correlation surface: (peak − mean) /
                           standard deviation, both taken farther than 5 + 2 smooth_sigma px
                           from the peak (NaN when initial_affine is given) */
    double correlation; /* Pearson correlation of the reference and the warped moving image
                           over the overlap (the quantity ECC maximises), after
                           normalisation, without smoothing */
    double residual_rms; /* RMS of (reference − warped moving) over the overlap, after the
                           normalisation (so in standard deviations when normalise = 1) */
    double overlap;     /* fraction of the reference pixels in the overlap: pixels whose mapped
                           position lies inside the moving image (svp_warp's domain) and whose
                           reference and interpolated moving values are finite */
    int iterations;     /* ECC iterations run (0 for phase correlation) */
    int low_significance; /* 1 when significance < options->min_significance: the images may
                           not overlap or lack common texture; the transform is unreliable
                           (the status is still SVP_OK); 0 when not measured
                           (ECC with initial_affine) */
    size_t nonfinite_reference; /* NaN/Inf pixels, filled from their neighbours for the
                                   estimation and left out of correlation and residual */
    size_t nonfinite_moving;
    int inverted;       /* 1 when the moving image was registered with its contrast inverted
                           (options->contrast INVERTED, or AUTO finding the trough more
                           significant than the peak); correlation and residual_rms are then
                           those of the inverted moving image */
    double significance_other; /* the significance of the opposite sign's extremum (the
                           trough when not inverted, the peak when inverted): how clearly the
                           sign was decided; NaN when not measured */
} svp_register_result;

/* Estimates the transform that maps reference pixel coordinates to moving pixel coordinates
 * (the moving image is brought onto the reference with svp_warp(moving, result->affine, ...)).
 * Both images must have the same size (SVP_ERR_SIZE otherwise: crop or pad first; svp_warp
 * accepts any sizes), at least 8 x 8 pixels, and at least one finite non-constant pixel each
 * (a constant image has no texture to register: SVP_ERR_INVALID naming it). NaN/Inf pixels are
 * filled with the mean of their finite 3 x 3 neighbours (growing inwards over up to 8 rings;
 * the image mean beyond), counted in the result, and left out of correlation and residual.
 * Phase correlation: the integer peak of the inverse transform of the whitened cross-power
 * spectrum, refined to sub-pixel by maximising its Fourier interpolation (Newton on the
 * spectral sum), then re-estimated with Hann windows over the region both images see (moved
 * with the scene) until d changes by less than 1e-4 px (at most 6 passes). Shifts up to half
 * the image size are found; measured error at most 2.5e-3 px on noise-free smooth scenes, for
 * shifts up to 37 px in a 128 x 112 frame (tests/test_register.c).
 * ECC: OpenCV's findTransformECC (reference = template, moving = input) run one iteration at a
 * time from the phase-correlation translation (or options->initial_affine) until the
 * correlation coefficient changes by less than epsilon; SVP_ERR_NUMERIC "registration did not
 * converge after N iterations (correlation r)" when it does not, and SVP_ERR_NUMERIC with
 * OpenCV's reason when ECC breaks down (e.g. the images do not overlap).
 * options NULL = svp_register_defaults. On failure *result is zeroed except for what was
 * known: when ECC fails, affine holds its last transform and iterations the count. */
SVP_API svp_status svp_register(const svp_image *reference, const svp_image *moving,
                                const svp_register_options *options,
                                svp_register_result *result);

typedef enum svp_interpolation {
    SVP_INTERP_NEAREST = 0, /* the nearest pixel (round half up): label masks keep their
                               labels */
    SVP_INTERP_LINEAR = 1   /* bilinear; a NaN neighbour with nonzero weight gives NaN */
} svp_interpolation;

/* Brings the moving image onto the reference grid: out(x, y) = moving(a · (x, y, 1)) for every
 * pixel of out (out's size is the reference grid; moving may have any size). Positions inside
 * [−0.5, width − 0.5) x [−0.5, height − 0.5) of the moving image are sampled (linear: edge
 * pixels are repeated over the outer half pixel); positions outside get border_value. out must
 * not be moving. Exact in double precision (no fixed-point tables). */
SVP_API svp_status svp_warp(const svp_image *moving, const double affine[6],
                            svp_interpolation interpolation, double border_value,
                            svp_image *out);

/* The inverse transform (moving → reference coordinates). SVP_ERR_NUMERIC when the linear
 * part is singular (|det| < 1e-12). */
SVP_API svp_status svp_affine_invert(const double affine[6], double inverse[6]);

/* A sub-pixel translation by Fourier interpolation: out(x, y) = in(x − dx, y − dy), the
 * content moved by (+dx, +dy). The image is continued by 16 + ⌈|d|⌉ pixels each side by odd
 * reflection about its edge pixels (value and slope continue), tapered to the mean of the two
 * edge pixels so that the period closes smoothly (docs/model.md §10, "Drift"), and its
 * spectrum multiplied by e^{−iω·d} (at the Nyquist frequency by cos(π d)); exact for a
 * band-limited image, so sub-pixel shifts neither smooth nor ring the way bilinear
 * interpolation does (svp_warp). The |d| pixels next to an edge that the shift brings in are
 * extrapolated (linearly, by the odd reflection), not data. NaN/Inf pixels are filled from their
 * neighbours for the transform and out is NaN where the nearest source pixel was not finite.
 * |dx| < width and |dy| < height; in and out of one size, out may be in. */
SVP_API svp_status svp_shift(const svp_image *in, double dx, double dy, svp_image *out);

/* ---------------------------------------------------------------------------------------- */
/* Fitting: Levenberg–Marquardt, PSF spot fits, PSF maps                                     */
/* @@section fit */
/* ---- Levenberg–Marquardt for small dense problems (src/lm/lm.c) --------------------------
 * Minimises χ² = Σ_i w_i (y_i − f_i(θ))² over θ (n_params ≤ SVP_LM_MAX_PARAMS values) in the
 * shape of GSL's multifit_nlinear (problem, workspace, init / iterate / finish, driver) but
 * never aborting: every failure is a status with a message. Classic LM with Marquardt
 * scaling D = diag(‖J_j‖) (kept monotone, as MINPACK); each damped step solves the augmented
 * least-squares problem [J; √λ D] δ = [−r; 0] by a QR of J (once per iteration) and a small
 * (2n × n) QR per trial λ (LAPACKE dgeqrf/dormqr/dgels): no normal equations, so the condition
 * number is not squared. Bounds go through smooth transforms (two-sided: x = lo + (hi − lo)
 * (1 + sin u) / 2; one-sided: softplus); lower == upper fixes a parameter.
 * Weights: 1/σ_i² from `sigma` when given, else from the noise model evaluated at the MODEL
 * value f_i (frozen within an iteration, updated after every accepted step: iteratively
 * reweighted; for pure shot noise this solves the Poisson score equations, so the estimate is
 * not biased the way data-weighted χ² is), else unit weights.
 * A workspace is reusable for any problem up to its capacity; init/iterate/finish/solve never
 * allocate. Different workspaces may be used from different threads at the same time. */

#define SVP_LM_MAX_PARAMS 64

/* The model: writes model[i] = f_i(params) for i < n_points and, when jacobian is not NULL,
 * jacobian[i * n_params + j] = ∂f_i/∂params[j] (row-major, every parameter, fixed ones
 * included; they are ignored). Returns 0 on success, nonzero when the model cannot be evaluated
 * at these parameters (the trial step is rejected; at the initial point it is an error). */
typedef int (*svp_lm_model_fn)(void *user, const double *params, int n_params, int n_points,
                               double *model, double *jacobian);

/* Per-point noise, σ² = σ_bg² + max(p, 1/g)/g + (a p)², p the model value. The shot term is
 * floored at one electron (p = 1/g) so pixels of zero model keep a finite weight. All zero =
 * unit weights. */
typedef struct svp_noise_model {
    double sigma_bg; /* additive noise σ_bg (read noise, dark), data units; default 0 */
    double gain;     /* g: electrons (photons) per data unit; 0 = no shot term; default 0 */
    double excess;   /* a: relative noise, e.g. laser fluctuations; default 0 */
} svp_noise_model;

/* σ² of one point with model value p under the noise model (1 when the model is all zero). */
SVP_API double svp_noise_variance(const svp_noise_model *noise, double p);

typedef enum svp_lm_covariance_scaling {
    SVP_LM_COV_AUTO = 0,     /* scaled by χ²_red only with unit weights (σ unknown; default) */
    SVP_LM_COV_UNSCALED = 1, /* (JᵀWJ)⁻¹: right when σ_i are the true noise */
    SVP_LM_COV_SCALED = 2    /* (JᵀWJ)⁻¹ · χ²_red (GSL/scipy curve_fit absolute_sigma=False) */
} svp_lm_covariance_scaling;

typedef struct svp_lm_options {
    int max_iterations;  /* accepted steps before giving up with SVP_ERR_NUMERIC; default 200 */
    double xtol;         /* stop when ‖D δ‖ ≤ xtol (‖D u‖ + xtol); default 1e-8 */
    double gtol;         /* stop when max_j |J_jᵀ r| / (‖J_j‖ ‖r‖) ≤ gtol; default 1e-10 */
    double ftol;         /* stop when the actual and the predicted relative decrease of χ² are
                            both ≤ ftol; default 1e-8 (MINPACK's sqrt(eps) scale: far below a
                            change of 1 in χ², i.e. 1σ, for any realistic number of points) */
    double lambda_init;  /* initial damping relative to D²; default 1e-3 */
    double fd_step;      /* forward-difference step relative to max(|θ_j|, |θ_j initial|, 1e-3)
                            when the model has no Jacobian; default sqrt(DBL_EPSILON) */
    svp_lm_covariance_scaling covariance; /* default SVP_LM_COV_AUTO */
} svp_lm_options;

SVP_API void svp_lm_defaults(svp_lm_options *options);

typedef struct svp_lm_problem {
    int n_params;            /* 1 .. SVP_LM_MAX_PARAMS */
    int n_points;            /* >= the number of free parameters */
    svp_lm_model_fn model;
    void *user;              /* passed to model */
    int analytic_jacobian;   /* nonzero: model fills the Jacobian; 0: forward differences */
    const double *data;      /* y_i; NULL = zeros (then the model values are the residuals) */
    const double *sigma;     /* σ_i > 0 per point; NULL = from `noise` */
    svp_noise_model noise;   /* used when sigma is NULL; all zero = unit weights */
    const double *lower;     /* per-parameter bounds; NULL or -INFINITY = none */
    const double *upper;     /* NULL or +INFINITY = none; lower[j] == upper[j] fixes θ_j */
} svp_lm_problem;

/* Why the iterations stopped. */
typedef enum svp_lm_stop {
    SVP_LM_RUNNING = 0,   /* not yet */
    SVP_LM_XTOL = 1,      /* the step became small */
    SVP_LM_GTOL = 2,      /* the gradient became orthogonal to the residuals (or χ² = 0) */
    SVP_LM_FTOL = 3,      /* χ² stopped decreasing */
    SVP_LM_ROUNDOFF = 4,  /* no further decrease possible at machine precision (converged) */
    SVP_LM_MAX_ITER = 5,  /* not converged: max_iterations reached */
    SVP_LM_STUCK = 6      /* not converged: no step decreases χ² although the gradient is not
                             small (a model that is not smooth, or a bad Jacobian) */
} svp_lm_stop;

typedef struct svp_lm_result {
    double chi2;        /* Σ w_i (y_i − f_i)² at the solution, weights from the model there */
    double chi2_red;    /* chi2 / dof; 0 when dof = 0 */
    int dof;            /* n_points − number of free parameters */
    int iterations;     /* accepted steps */
    int evaluations;    /* model calls (finite-difference calls included) */
    svp_lm_stop stop;
    int covariance_ok;  /* 0: JᵀWJ was singular at the solution; variances are INFINITY */
    unsigned long long at_bound; /* bit j set: θ_j ended at (within 1e-4 of the range of) a
                                    bound; its variance is INFINITY and the others are
                                    conditional on it */
} svp_lm_result;

typedef struct svp_lm_workspace svp_lm_workspace;

/* A workspace for problems with up to max_params parameters and max_points points. */
SVP_API svp_status svp_lm_workspace_new(int max_params, int max_points,
                                        svp_lm_workspace **out);
SVP_API void svp_lm_workspace_free(svp_lm_workspace *ws);

/* Starts a fit at params0 (clamped into the bounds). The problem's arrays must stay valid
 * until the fit is finished. options NULL = defaults. Evaluates the model (and Jacobian). */
SVP_API svp_status svp_lm_init(svp_lm_workspace *ws, const svp_lm_problem *problem,
                               const svp_lm_options *options, const double *params0);
/* One accepted step (trying larger damping until χ² decreases). *stop (may be NULL) becomes
 * nonzero when a convergence test is met. SVP_ERR_NUMERIC when no step can decrease χ² while
 * the gradient is not small (stop = SVP_LM_STUCK). */
SVP_API svp_status svp_lm_iterate(svp_lm_workspace *ws, svp_lm_stop *stop);
/* The current parameters (n_params values). */
SVP_API void svp_lm_params(const svp_lm_workspace *ws, double *params);
/* Statistics and covariance at the current point. params and covariance (n_params² values,
 * row-major, in the user's parameters: the Jacobian is taken w.r.t. θ, not the transformed
 * variable) may be NULL. Fixed parameters have zero rows and columns. */
SVP_API svp_status svp_lm_finish(svp_lm_workspace *ws, double *params, svp_lm_result *result,
                                 double *covariance);
/* The driver: init, iterate until a test is met, finish. params: initial values in, solution
 * out. When the fit does not converge within max_iterations it still writes the last
 * parameters and statistics (result.stop = SVP_LM_MAX_ITER) and returns SVP_ERR_NUMERIC with a
 * message giving χ² and the last step. */
SVP_API svp_status svp_lm_solve(svp_lm_workspace *ws, const svp_lm_problem *problem,
                                const svp_lm_options *options, double *params,
                                svp_lm_result *result, double *covariance);
/* "small step", "small gradient", ... */
SVP_API const char *svp_lm_stop_string(svp_lm_stop stop);

/* ---- Spot fits (docs/model.md §8): elliptical Moffat, Gaussian, Lorentzian -----------------
 * Model of pixel (x, y) (pixel centres at integer coordinates, x = column):
 *   f = background + amplitude · P(q),  q = dᵀ M d / s²,  d = (x − x0, y − y0),
 *   Moffat P = (1 + q)^(−β), s = r0(F, β);  Gaussian P = exp(−q/2), s = σ(F);
 *   M = exp(−G), G = [[g1, g2], [g2, −g1]], (g1, g2) = ln(FWHM_major/FWHM_minor)(cos 2θ, sin 2θ)
 * fitting F = sqrt(FWHM_major · FWHM_minor), g1, g2: det M = 1 and the orientation enters as
 * (cos 2θ, sin 2θ), so the fit is regular for round spots (θ undefined there, only its
 * uncertainty grows). Results are reported in the PSF-field convention (svp_psf_to_params). The model is integrated over each pixel (2 × 2 Gauss–Legendre points,
 * 4 × 4 when the minor FWHM is below 2 px) within max(3, 4 FWHM) of the centre; outside, the
 * centre value is used. */

typedef enum svp_spot_flag {
    SVP_SPOT_NOT_CONVERGED = 1u << 0,  /* the LM fit did not converge (status NUMERIC) */
    SVP_SPOT_NEAR_BORDER = 1u << 1,    /* centre within border_fwhm · FWHM of an edge */
    SVP_SPOT_SATURATED = 1u << 2,      /* saturated pixels were excluded from the fit */
    SVP_SPOT_BETA_AT_BOUND = 1u << 3,  /* β ran to beta_min or beta_max */
    SVP_SPOT_HOT_PIXELS = 1u << 4,     /* single-pixel spikes were excluded */
    SVP_SPOT_CLIPPED = 1u << 5,        /* κ-σ clipping excluded pixels */
    SVP_SPOT_NO_ERRORS = 1u << 6,      /* covariance singular: uncertainties unknown */
    SVP_SPOT_WIDTH_AT_BOUND = 1u << 7, /* FWHM or axis ratio ran to its bound */
    SVP_SPOT_POOR_FIT = 1u << 8        /* χ²_red above chi2_red_max (known noise only) */
} svp_spot_flag;

#define SVP_SPOT_N_FLAGS 9

/* Text for one flag bit ("near border: ..."); "" for 0 or an unknown bit. */
SVP_API const char *svp_spot_flag_string(unsigned flag);
/* All set flags as "not converged; saturated" into buf (always terminated). Returns the length
 * the full text needs. "ok" when no flag is set. */
SVP_API size_t svp_spot_flags_describe(unsigned flags, char *buf, size_t size);

typedef struct svp_spot_options {
    svp_psf_model model;   /* default SVP_PSF_MOFFAT */
    double beta;           /* initial (or fixed) β of a Moffat; default 2.5 */
    int fix_beta;          /* keep β at `beta`; default 0 */
    double beta_min;       /* β bounds of a Moffat fit; default 0.5 */
    double beta_max;       /* default 20 (β → ∞ is a Gaussian) */
    int elliptical;        /* fit two FWHMs and an angle; 0: circular; default 1 */
    svp_noise_model noise; /* default {σ_bg 0, gain 1, a 0}: the data are photon counts. Gain 0
                              and σ_bg 0: unit weights, uncertainties scaled by χ²_red */
    double saturation;     /* pixels >= saturation are excluded and the fit flagged; 0 (default)
                              = detect a plateau of >= 3 pixels equal to the maximum; < 0 off */
    int hot_pixels;        /* exclude single-pixel spikes: above hot_ratio × the brightest of
                              their 8 neighbours (background removed) and hot_sigma σ above it;
                              default 1. Spots narrower than ~1.4 px FWHM look like spikes. */
    double hot_ratio;      /* default 4 */
    double hot_sigma;      /* default 8 */
    double clip_kappa;     /* exclude pixels with |y − f| > κ σ and refit, worst first (per
                              round those above max(κ, max|z|/2)); many moderate outliers are a
                              misfit (POOR_FIT), not clipped; default 5; 0 = off */
    int clip_iterations;   /* clipping rounds at most; default 5 */
    double border_fwhm;    /* near-border distance in units of the major FWHM; default 2 */
    int refuse_near_border; /* SVP_ERR_INVALID instead of the flag; default 0 */
    double min_snr;        /* the 3×3-mean peak must stand this many σ above the background,
                              else the image is empty (SVP_ERR_INVALID); default 5 */
    double chi2_red_max;   /* POOR_FIT threshold; default 3 */
    int pixel_integration; /* 1 (default): integrate the model over pixels; 0: centre values */
    double ee_radius;      /* disc radius (px) for the encircled-energy radii; 0 (default) =
                              min(width, height) / 2 (the flux of β ≤ 1 diverges otherwise) */
    double x0, y0;         /* initial centre (px); NaN (default) = from moments */
    svp_lm_options lm;     /* max_iterations 200, ... */
} svp_spot_options;

SVP_API void svp_spot_defaults(svp_spot_options *options);

typedef struct svp_spot_result {
    svp_psf_model model;
    double amplitude, amplitude_err;   /* peak of the profile above background, data units */
    double x0, x0_err, y0, y0_err;     /* centre, pixels */
    double fwhm, fwhm_err;             /* mean FWHM (major + minor) / 2, pixels (as
                                          SVP_FIELD_FWHM) */
    double fwhm_major, fwhm_major_err; /* pixels */
    double fwhm_minor, fwhm_minor_err;
    double angle, angle_err;           /* major axis from +x towards +y, radians in (−π/2, π/2] */
    double e1, e1_err, e2, e2_err;     /* e (cos 2θ, sin 2θ), e = (major − minor) / (major +
                                          minor): as SVP_FIELD_E1, SVP_FIELD_E2 */
    double beta, beta_err;             /* Moffat β (1 for Lorentzian, 0 for Gaussian) */
    double r0, r0_err;                 /* Moffat r0 (Gaussian σ) of the mean FWHM, pixels */
    double background, background_err; /* data units */
    double ee50, ee80, ee95;           /* encircled-energy radii (px) within ee_radius */
    double ee_radius;                  /* the disc they refer to */
    double chi2, chi2_red;
    int dof, iterations;
    int n_used;                        /* pixels in the final fit */
    int n_hot, n_clipped, n_saturated; /* pixels excluded, by reason */
    double border_distance;            /* centre to the nearest edge, pixels */
    unsigned flags;                    /* svp_spot_flag bits */
    double covariance[8 * 8];          /* of the fitted (amplitude, x0, y0, F, g1, g2, β,
                                          background), F and g as in the model above */
} svp_spot_result;

/* Fits one spot. model_image and residual (data − model) may be NULL, else the spot's size;
 * pixels that were NaN in the spot get residual 0. Errors: SVP_ERR_INVALID for an empty
 * image (no significant peak), no finite pixels, fewer than 25 pixels, bad options or (with
 * refuse_near_border) a spot near the border; SVP_ERR_NUMERIC when the fit did not converge —
 * then the result is still filled and flagged SVP_SPOT_NOT_CONVERGED. A β that creeps along its
 * bound until max_iterations is held at the bound for a last fit (flag BETA_AT_BOUND, beta_err
 * INFINITY) instead. Uncertainties are 1σ from the covariance at the solution: unscaled with a
 * known noise model (they cover the truth at the nominal 68 % on Poisson data), scaled by
 * χ²_red with unit weights; INFINITY where unknown (a parameter at a bound, singular fit). */
SVP_API svp_status svp_spot_fit(const svp_image *spot, const svp_spot_options *options,
                                svp_spot_result *result, svp_image *model_image,
                                svp_image *residual);
/* The fitted PSF as an svp_psf (pixels; subsample 3 when the fit integrated over pixels so that
 * svp_psf_render reproduces the fitted model, halo 0, support 0). */
SVP_API void svp_spot_result_psf(const svp_spot_result *result, svp_psf *psf);

/* ---- PSF from an excitation/emission pair (docs/model.md §8) -------------------------------
 * I_PL = I_G ⊛ p: both spots are fitted directly; the excitation spot (background removed,
 * negatives set to 0, restricted to a disc around its fitted centre) is the kernel of a
 * Richardson–Lucy deconvolution of the emission spot (background removed; saturated and hot
 * pixels treated as missing); the result is fitted again. Registration: the kernel is centred
 * on the fitted excitation centre, which removes any offset between the two images to within
 * half a pixel (the rest only moves p, whose centre is free); the fitted offset is reported.
 * The direct fit is an upper bound on p's width; the deconvolved one approaches p from above as
 * RL iterates (75 iterations leave it a few % wide). */

typedef struct svp_pair_options {
    svp_spot_options spot;   /* for the excitation and the direct emission fit */
    int iterations;          /* Richardson–Lucy iterations; default 75 */
    double kernel_radius;    /* radius of the kernel disc, px; 0 (default) = 3 × the fitted
                                excitation major FWHM */
    int kernel_from_fit;     /* 1: the fitted excitation model (no noise) as the kernel;
                                default 0 (the measured spot) */
    svp_boundary boundary;   /* of the deconvolution; default SVP_BOUNDARY_ZERO */
} svp_pair_options;

SVP_API void svp_pair_defaults(svp_pair_options *options);

typedef struct svp_pair_result {
    svp_spot_result excitation;  /* fit of I_G */
    svp_spot_result direct;      /* fit of I_PL: the upper bound */
    svp_spot_result deconvolved; /* fit of I_PL ⊘ I_G: the estimate of p */
    double offset_x, offset_y;   /* emission centre − excitation centre, px */
    int deconvolved_ok;          /* 0 when the deconvolution or its fit failed */
} svp_pair_result;

/* excitation and emission: the same size. deconvolved (may be NULL, else the same size)
 * receives I_PL ⊘ I_G. On a failure of the deconvolution step (e.g. SVP_ERR_UNSUPPORTED) the
 * excitation and direct fits are still filled and deconvolved_ok is 0. */
SVP_API svp_status svp_psf_from_pair(const svp_image *excitation, const svp_image *emission,
                                     const svp_pair_options *options, svp_pair_result *result,
                                     svp_image *deconvolved);

/* ---- PSF maps from many spot fits (src/psf/map.c) ---------------------------------------
 * Each accepted spot gives the PSF-field parameter vector (fwhm, e1, e2, beta; halo is not
 * measured by a spot and is the constant options.halo) with its 1σ uncertainties. Either
 * polynomial surfaces of each parameter are fitted over the field (weighted least squares,
 * weights 1/σ², LAPACKE dgels) and returned as an SVP_FIELD_POLY field, or, with a label
 * image, per-region statistics are formed and regions that do not differ significantly are
 * merged (SVP_FIELD_REGIONS). Rejections carry a reason per spot and parameter. */

typedef struct svp_psf_sample {
    double x, y;          /* spot centre in the field, pixels (the fit's own x0, y0, which
                             refer to the spot cut-out, are not used) */
    svp_spot_result fit;
} svp_psf_sample;

typedef enum svp_map_reject {
    SVP_MAP_KEPT = 0,
    SVP_MAP_REJECT_FLAGS = 1,   /* the fit carries a flag of options.reject_flags */
    SVP_MAP_REJECT_INVALID = 2, /* value or uncertainty not finite/positive, or another model */
    SVP_MAP_REJECT_OUTSIDE = 3, /* position outside the field (or label out of range) */
    SVP_MAP_REJECT_OUTLIER = 4  /* |residual| > clip_kappa × robust σ of the surface/region */
} svp_map_reject;

SVP_API const char *svp_map_reject_string(svp_map_reject code);

typedef struct svp_map_options {
    int degree;             /* polynomial degree for every parameter, 0..8; -1 (default) =
                               per parameter by k-fold cross-validation over 0..max_degree
                               (smallest degree within one standard error of the best) */
    int max_degree;         /* default 3 */
    int folds;              /* cross-validation folds, >= 2; default 5 */
    unsigned reject_flags;  /* spot flags that reject a spot; default NOT_CONVERGED |
                               NEAR_BORDER | SATURATED | BETA_AT_BOUND | NO_ERRORS |
                               WIDTH_AT_BOUND */
    double clip_kappa;      /* outliers: |z| > clip_kappa × max(1, 1.4826 MAD(z)), z the
                               residual in units of the spot's σ; default 4; 0 = off */
    int clip_iterations;    /* default 5 */
    double alpha;           /* regions: significance level of the Welch tests; default 0.01 */
    double transition;      /* regions: blend width in pixels (svp_psf_field_new_regions);
                               default 0 */
    double halo;            /* alpha_b of the whole map; default 0 */
    double support;         /* PSF support radius (px) of the field; default 0 = whole view */
    int subsample;          /* of the field's PSFs; default 0 (auto) */
} svp_map_options;

SVP_API void svp_map_defaults(svp_map_options *options);

typedef struct svp_region_stats {
    int label;                      /* region label (groups: the smallest member label) */
    int count;                      /* accepted spots */
    double mean[SVP_FIELD_NPARAM];  /* mean of the spots' parameters */
    double std[SVP_FIELD_NPARAM];   /* sample standard deviation (0 when count < 2) */
    double sem[SVP_FIELD_NPARAM];   /* std / sqrt(count) */
    int group;                      /* regions: index of the merged group it belongs to */
} svp_region_stats;

typedef struct svp_map_report {
    int n_samples;
    svp_psf_model model;
    int mapped[SVP_FIELD_NPARAM];   /* 1 for the parameters fitted (beta only for Moffat) */
    /* polynomial maps */
    int degree[SVP_FIELD_NPARAM];   /* chosen degree per parameter (-1: not mapped) */
    double cv_score[SVP_FIELD_NPARAM][9]; /* mean held-out χ² per point for degrees 0..8
                                             (0 where not tried) */
    double chi2_red[SVP_FIELD_NPARAM];    /* of the final surface fit */
    double rms[SVP_FIELD_NPARAM];   /* rms residual of the accepted spots, parameter units */
    int n_used[SVP_FIELD_NPARAM];   /* spots in the final fit */
    /* how well the spots determine each surface over the whole field: the surface's standard
     * error √(bᵀ (AᵀWA)⁻¹ b) · max(1, √χ²_red) at its worst point of a 33 x 33 grid over the
     * field (corners included) and where that is (pixels), against the median standard error
     * of the spots' own fits. A ratio well above 1 means the surface there is an extrapolation
     * the spots do not support (spots along a line, in one corner). */
    double surface_se_max[SVP_FIELD_NPARAM];
    double surface_se_x[SVP_FIELD_NPARAM], surface_se_y[SVP_FIELD_NPARAM];
    double spot_se_median[SVP_FIELD_NPARAM];
    /* per spot and parameter: svp_map_reject code and, for outliers, the z value */
    int *reject;                    /* n_samples * SVP_FIELD_NPARAM */
    double *reject_z;
    /* region maps */
    int n_regions;                  /* = n_labels; 0 for polynomial maps */
    svp_region_stats *regions;      /* n_regions */
    int n_groups;
    svp_region_stats *groups;       /* n_groups: the merged regions */
    double *p_value;                /* n_regions²: Bonferroni-corrected Welch p between regions
                                       (1 on the diagonal; -1 when a region has < 2 spots) */
} svp_map_report;

SVP_API void svp_map_report_free(svp_map_report *report);
/* "spot 7 (x 10.0, y 4.0): rejected: flags: near border" / "... beta outlier (z = 6.1)" /
 * "... kept". Returns the needed length (buf always terminated). */
SVP_API size_t svp_map_describe_sample(const svp_map_report *report,
                                       const svp_psf_sample *samples, int index, char *buf,
                                       size_t size);

/* Polynomial PSF map of a width x height field from n spot fits. field (may be NULL) gets an
 * SVP_FIELD_POLY field of degree max(chosen degrees) (lower-degree surfaces padded with zero
 * coefficients), report (may be NULL) the diagnostics. SVP_ERR_INVALID when fewer accepted
 * spots remain than a constant needs (2) — the message lists the rejection counts. */
SVP_API svp_status svp_psf_map_poly(const svp_psf_sample *samples, int n, int width,
                                    int height, const svp_map_options *options,
                                    svp_psf_field **field, svp_map_report **report);
/* Region PSF map: labels[y * width + x] in 0..n_labels-1 (as svp_psf_field_new_regions); each
 * spot belongs to the label under its rounded centre. Per label: mean, std, count of the
 * parameters (outliers beyond clip_kappa robust σ of the region rejected). Then, greedily, the
 * pair of groups with the largest Welch p value (Bonferroni over the mapped parameters) is
 * merged while that p exceeds alpha; groups with fewer than 2 spots are never merged. Each
 * label's PSF is its group's mean; a label without spots gets the mean of all spots. */
SVP_API svp_status svp_psf_map_regions(const svp_psf_sample *samples, int n, const int *labels,
                                       int width, int height, int n_labels,
                                       const svp_map_options *options, svp_psf_field **field,
                                       svp_map_report **report);


/* ---------------------------------------------------------------------------------------- */
/* Scenes: simulate a sample, its emission and optics; correct, reconstruct, report          */
/* @@section scene */
/* ---- Scenes (docs/scenes.md) ----------------------------------------------------------------
 * A scene file (YAML) describes a sample (field sources: magnetic flakes, current strips, field
 * maps from files), its emission (PL) pattern, the optics (PSF) and the effects to include
 * (noise, the full ODMR spectrum, drift), then optional corrections (T⁻¹), source
 * reconstructions, metrics and outputs. Loading parses and checks the whole file (every error
 * names file:line:column and the key) and compiles it to a PLAN: the list of stages the scene
 * needs, and only those. Running executes the plan into an output folder.
 *
 * Stages (names are stable; the detail line says what each does for the scene):
 *   grid        the canvas: the view plus margin_um on every side
 *   sources     true fields B_x, B_y, B_z on the canvas (Fourier flake field, analytic strip)
 *   projection  the measured components (x, y, z and/or the NV-axis projection)
 *   emission    the true PL map (product of the emission factors)
 *   operator    the blur operator H: invariant = one OTF; a PSF map = space-variant
 *   forward     closed form, eq. (3) (svp_forward_transform): only without `spectrum`
 *   cube        with `spectrum`: ODMR frames simulated, blurred (and drifted) frame by frame
 *   drift       with `drift`: the lateral shift of each frame (inside the cube loop)
 *   estimate    with `spectrum`: per-pixel centroid or Lorentzian fit of the blurred cube
 *   crop        the view cut out of the canvas (only with margin_um > 0)
 *   noise       shot noise (only with `noise`; no random number is drawn otherwise)
 *   correct     T⁻¹ (eq. 4), once per entry of `correct`
 *   reconstruct magnetisation / current density from true, apparent and corrected maps
 *   metrics     relative errors over masks, histograms, line cuts, reductions
 *   figures     PNG maps (colour bar with units, scale bar) and plots
 *   write       maps, CSV tables, report.md, summary.json
 */
typedef struct svp_scene svp_scene;

typedef struct svp_scene_stage {
    const char *name;   /* one of the stage names above */
    const char *detail; /* one line: what the stage does for this scene */
} svp_scene_stage;

/* Reads and checks a scene file; relative paths inside it are relative to its folder. Errors:
 * SVP_ERR_IO (the file or a file it names cannot be read), SVP_ERR_FORMAT (YAML, unknown or
 * missing keys, wrong types, a length key with the wrong unit suffix), SVP_ERR_INVALID
 * (impossible values), each "file:line:col: message" naming the key. Files the scene names
 * (masks, images, field maps, PSF files) are checked to exist and have the right size. */
SVP_API svp_status svp_scene_load(const char *path, svp_scene **out);
/* The same from memory; `name` stands for the file (messages, and the folder that relative
 * paths start from). */
SVP_API svp_status svp_scene_load_string(const char *name, const char *text, size_t len,
                                         svp_scene **out);
SVP_API void svp_scene_free(svp_scene *scene);
/* The plan: *stages (may be NULL) points at the scene's stage list; returns its length. */
SVP_API int svp_scene_plan(const svp_scene *scene, const svp_scene_stage **stages);
/* 1 when the plan has a stage of that name (e.g. "cube", "noise"), else 0. */
SVP_API int svp_scene_has_stage(const svp_scene *scene, const char *name);
/* The scene's name (the `name:` key, else the file name without extension). */
SVP_API const char *svp_scene_name(const svp_scene *scene);
/* Geometry: pixel size (µm), view and canvas sizes (pixels). Any pointer may be NULL. */
SVP_API void svp_scene_geometry(const svp_scene *scene, double *pixel_um, int *view_w,
                                int *view_h, int *canvas_w, int *canvas_h);
/* The estimated peak memory of a run, bytes (from measured runs: about 100 MB + 450 B per canvas
 * pixel + 40 B per canvas pixel and correction + a cube's frames three times). svp_scene_run
 * refuses a scene above the memory budget (SVPSF_MAX_MEMORY, else the memory available;
 * SVP_ERR_INVALID naming the file) before it writes or allocates anything. */
SVP_API double svp_scene_memory(const svp_scene *scene);
/* The files a run writes, relative to the output folder (index 0 .. n − 1; NULL beyond). */
SVP_API int svp_scene_n_outputs(const svp_scene *scene);
SVP_API const char *svp_scene_output(const svp_scene *scene, int index);

/* Called as each stage begins (index in the plan, 0-based); nonzero cancels the run
 * (SVP_ERR_CANCELLED). */
typedef int (*svp_scene_stage_fn)(void *user, int index, int n_stages,
                                  const svp_scene_stage *stage);

typedef struct svp_scene_options {
    int write;               /* 1 (default): write the outputs into out_dir; 0: compute only
                                (the maps and values stay in the result; out_dir may be NULL) */
    int overwrite;           /* 0 (default): if any output exists, SVP_ERR_EXISTS before any
                                work; 1: replace them */
    int keep_maps;           /* 1 (default): the result keeps every map (svp_scene_result_map);
                                0: freed once written */
    svp_progress_fn progress; /* optional: overall fraction in [0, 1] */
    void *progress_user;
    svp_scene_stage_fn on_stage; /* optional */
    void *stage_user;
    int argc;                /* the command line to record in summary.json (optional) */
    char *const *argv;
} svp_scene_options;

SVP_API void svp_scene_defaults(svp_scene_options *options);

typedef struct svp_scene_result svp_scene_result;

/* Runs the plan. out_dir is created when missing (write = 1). Every output is written
 * atomically; summary.json records the plan, each stage's time, the settings and the metrics;
 * report.md lists them with the figures. The result (may be NULL when not wanted) gives the
 * timings, the maps and the metric values. A run that fails or is cancelled after writing some
 * outputs removes those it created (all or none; files it overwrote stay). */
SVP_API svp_status svp_scene_run(const svp_scene *scene, const char *out_dir,
                                 const svp_scene_options *options, svp_scene_result **result);
SVP_API void svp_scene_result_free(svp_scene_result *result);
/* Seconds spent in plan stage `index` (0 when it did not run). */
SVP_API double svp_scene_result_stage_seconds(const svp_scene_result *result, int index);
/* A map of the run by name (SI units), NULL when absent. View-sized: "<q>_<version>" with
 * q = pl, B_x, B_y, B_z, B_nv (tesla), m_z (A), J_bz / J_bxy (|J|, A/m; components
 * "J_bz_x_<version>", ...) and version = true, apparent, corrected_<k> (k = the correction's
 * name); "err_<q>_<version>" (relative error, NaN where undefined), "validity_<k>",
 * "mask_<name>", "B_<c>_closed_form" and "contrast" (spectrum scenes), "m_z_source",
 * "J_x_source", "J_y_source" (the ideal sources); canvas-sized: "canvas_pl_true",
 * "canvas_B_<c>_true", ... (docs/scenes.md §Outputs). */
SVP_API const svp_image *svp_scene_result_map(const svp_scene_result *result, const char *name);
/* A metric by key (docs/scenes.md §Metrics: "<quantity>/<mask>/<version>/<statistic>", e.g.
 * "m_z/flake/corrected_rw/median_abs_rel_err"). Returns 1 and sets *value when present. */
SVP_API int svp_scene_result_value(const svp_scene_result *result, const char *key,
                                   double *value);
SVP_API int svp_scene_result_n_values(const svp_scene_result *result);
/* Key of value `index` (NULL beyond), *value its value. */
SVP_API const char *svp_scene_result_value_at(const svp_scene_result *result, int index,
                                              double *value);


/* ---------------------------------------------------------------------------------------- */
/* Physics: source fields, reconstruction, spectra                                           */
/* @@section physics */

/* Frame and sign conventions of every function in this section (pinned by tests/test_physics.c
 * against the closed-form strip and flake fields):
 *  - SI units: tesla, metre, A/m (sheet current density J), A (areal magnetisation
 *    m_z = M_z t); positions and lengths on images are in pixels, with the pixel size in metres
 *    given explicitly; pixel (i, j) has its centre at (x, y) = (i, j) pixels and covers
 *    [i − ½, i + ½] × [j − ½, j + ½];
 *  - the frame is right-handed: +x along the columns (rightwards), +y along the rows (DOWNWARDS
 *    in a displayed image, row index increasing), +z = x × y (into the screen of a displayed
 *    image). B_x, B_y, B_z and J_x, J_y are the components along these axes;
 *  - the NV layer (sensor) lies at distance h (standoff) from the source plane on the +z side
 *    (sensor.side = +1, "above") or on the −z side (side = −1, "below"). B_z is the same on both
 *    sides; the in-plane components change sign with the side;
 *  - Fourier convention: numpy/FFTW forward kernel e^(−i(kx x + ky y)), k = 2π·fftfreq(N, dx),
 *    k = |k|. In-plane from out-of-plane: B_x(k) = −i s (kx/k) B_z(k), B_y = −i s (ky/k) B_z.
 *    At the Nyquist frequency of an even-length axis the odd (derivative-like) multipliers are 0;
 *  - a measured B_z that is positive towards the viewer of the displayed image is −B_z here
 *    (or flip the rows). */

/* Where the sensor is. */
typedef struct svp_sensor {
    double pixel_m;        /* pixel size, metres (> 0); default 100e-9 */
    double standoff_m;     /* h: distance from the source plane (the near surface of a flake,
                              the plane of a current sheet) to the centre of the NV layer,
                              metres (> 0); default 100e-9 */
    double nv_thickness_m; /* t_NV: thickness of the NV layer, metres, 0 <= t_NV < 2 h: the
                              field is averaged over it, e^(−kh) → e^(−kh) sinh(a)/a with
                              a = k t_NV / 2; default 0 (a plane) */
    int side;              /* +1 (default): sensor on the +z side of the sources; −1: −z side */
} svp_sensor;

SVP_API void svp_sensor_defaults(svp_sensor *sensor);
/* SVP_ERR_INVALID naming the field for pixel_m <= 0, standoff_m <= 0, t_NV outside [0, 2h),
 * side not ±1, or a non-finite value. */
SVP_API svp_status svp_sensor_validate(const svp_sensor *sensor);

/* ---- shapes: add value × (covered area fraction) to each pixel (coordinates in pixels) ---- */

/* Polygon with n >= 3 vertices xy = {x0, y0, x1, y1, ...}, simple (not self-intersecting),
 * either orientation. Exact area coverage (each pixel square clipped against the polygon). */
SVP_API svp_status svp_raster_polygon(svp_image *image, const double *xy, int n, double value);
/* Rectangle of size width x height (pixels) centred at (cx, cy), its width axis rotated by
 * angle (radians, from +x towards +y) — a polygon, exact coverage. */
SVP_API svp_status svp_raster_rectangle(svp_image *image, double cx, double cy, double width,
                                        double height, double angle, double value);
/* Disc of radius r (pixels) centred at (cx, cy). Pixels wholly inside or outside are exact;
 * pixels cut by the circle are sampled on a 16 x 16 sub-grid (area error ~1e-3 of πr²). */
SVP_API svp_status svp_raster_disk(svp_image *image, double cx, double cy, double radius,
                                   double value);

/* ---- source fields ------------------------------------------------------------------------ */

/* Stray field of a thin magnetic flake by the Fourier method (docs/model.md §11). moment is the
 * areal magnetisation m_z = M_z t in A on the sensor's pixel grid (e.g. 1e-3 for M_z = 1 MA/m,
 * t = 1 nm; build it with svp_raster_* or from a mask image times M_z t). Zero outside the
 * image: the canvas is padded with zeros to at least pad_factor times the image size in each
 * axis (pad_factor 0 → 2; 1 = no padding, periodic). thickness_m: the flake's thickness t
 * (0 = the thin-film limit):
 *     B_z(k) = (μ0/2) k e^(−kh) [(1 − e^(−kt)) / (kt)] [sinh(a)/a] m_z(k),  a = k t_NV / 2,
 * (→ (μ0/2) k e^(−kh) m_z(k) for t → 0); B_x, B_y from B_z as in the conventions above. h is
 * measured to the flake's near surface. Outputs (any may be NULL) have the moment's size. For
 * M_z > 0, B_z is positive just inside an edge and negative just outside, on either side.
 * Accuracy (tests): against the exact field of a rectangle with h = 2 pixels, 1.4e-3 of the
 * peak farther than 4h from the edges, 2.7e-2 at the edges (pixel sampling). The padded canvas
 * carries exactly zero flux, so the flux beyond it shifts the map by a tiny constant (at pad 2
 * about 10 % of the already small flux missing from the view; pad 8: < 1 %). */
SVP_API svp_status svp_flake_field(const svp_image *moment, double thickness_m,
                                   const svp_sensor *sensor, int pad_factor, svp_image *bx,
                                   svp_image *by, svp_image *bz);

/* An infinitely long flat strip of current (docs/model.md §11). */
typedef struct svp_strip {
    double width_m;       /* w, metres (> 0); default 40e-6 */
    double sheet_current; /* J, A/m (current per unit width, along the strip); default 200 */
    double centre_x;      /* a point of the centre line, pixels; default 0, 0 */
    double centre_y;
    double angle;         /* direction of the current, radians from +x towards +y (rows);
                             default π/2: current along +y */
} svp_strip;

SVP_API void svp_strip_defaults(svp_strip *strip);
/* Analytic Oersted field of the strip. With u the current direction, n = u × z = (u_y, −u_x)
 * and ξ the distance from the centre line along n (metres):
 *   B_n(ξ) = s (μ0 J / 2π) [atan((w/2 + ξ)/h) + atan((w/2 − ξ)/h)]   (→ s μ0 J / 2 inside),
 *   B_z(ξ) = (μ0 J / 4π) ln[((ξ − w/2)² + h²) / ((ξ + w/2)² + h²)],
 * (B_x, B_y) = B_n n. For current along +y (angle π/2) n = +x: B_x > 0 over the strip for
 * s = +1 and B_z < 0 on the +x side. With t_NV > 0 both are averaged exactly over the NV layer
 * (closed-form antiderivatives in h). Outputs (any may be NULL; at least one) share one size. */
SVP_API svp_status svp_strip_field(const svp_strip *strip, const svp_sensor *sensor,
                                   svp_image *bx, svp_image *by, svp_image *bz);
/* The strip's current density map (A/m): J u times the covered area fraction of each pixel
 * (exact coverage of the band; the width in metres over pixel_m). jx or jy may be NULL. */
SVP_API svp_status svp_strip_current(const svp_strip *strip, double pixel_m, svp_image *jx,
                                     svp_image *jy);

/* Projection on the NV axis: out = (axis · (B_x, B_y, B_z)) / |axis|, |axis| > 0. A component
 * may be NULL only where its axis entry is 0. */
SVP_API svp_status svp_field_project(const svp_image *bx, const svp_image *by,
                                     const svp_image *bz, const double axis[3], svp_image *out);

/* ---- source reconstruction (docs/model.md §11) ------------------------------------------------- */

typedef enum svp_pad_mode {
    SVP_PAD_TAPER = 0, /* default: the map continues from its edge values, cosine-tapered to its
                          mean half-way across the padding (wrap-around meets at the mean) */
    SVP_PAD_MEAN = 1,  /* the padding holds the map's mean (= mean-subtracted, zero-padded) */
    SVP_PAD_NONE = 2   /* no padding: periodic */
} svp_pad_mode;

/* How m_z is found from B_z (docs/model.md §11). */
typedef enum svp_recon_method {
    SVP_RECON_FOURIER = 0, /* default: divide the padded map's spectrum by the flake's transfer
                              function (the padding continues the map; k = 0 is lost) */
    SVP_RECON_SUPPORT = 1  /* magnetisation only: the m_z on the view (zero outside it) whose
                              field fits B_z on the view in least squares, by conjugate gradients
                              preconditioned with the Fourier inverse; then the window */
} svp_recon_method;

typedef struct svp_recon_options {
    svp_sensor sensor;        /* pixel size, standoff, NV thickness, side */
    double cutoff;            /* k_c of the window, rad/m; 0 (default) = 2π / standoff */
    int window;               /* 1 (default): radial Hann W = ½[1 + cos(π k/k_c)] for k < k_c,
                                 else 0; 0: no window (W = 1; the e^(kh) gain is then set to
                                 0 where kh > 700) */
    svp_pad_mode pad;         /* default SVP_PAD_TAPER */
    int pad_factor;           /* padded canvas >= pad_factor × the image per axis; default 2 */
    double source_thickness_m; /* flake thickness t for the magnetisation: divides by
                                 (1 − e^(−kt))/(kt); 0 (default) = thin film */
    int zero_border;          /* magnetisation only: 1 (default) then subtracts the mean of
                                 the image's outermost pixel ring (m_z = 0 around a flake that
                                 lies inside the view); 0: only the k = 0 term set to 0.
                                 Not used by SVP_RECON_SUPPORT, which determines the mean */
    svp_recon_method method;  /* magnetisation: SVP_RECON_FOURIER (default) or _SUPPORT; the
                                 current reconstructions accept only SVP_RECON_FOURIER */
    int max_iterations;       /* SVP_RECON_SUPPORT: conjugate-gradient cap (default 200) */
    double tolerance;         /* SVP_RECON_SUPPORT: stop when the normal equations' residual
                                 falls below this fraction of Aᵀ B_z's norm (default 1e-9) */
} svp_recon_options;

/* What a support reconstruction did (zeros for the Fourier method). */
typedef struct svp_recon_report {
    int iterations;  /* conjugate-gradient steps taken */
    double residual; /* final relative residual of the normal equations */
} svp_recon_report;

SVP_API void svp_recon_defaults(svp_recon_options *options);

/* Areal magnetisation m_z = M_z t (A) from B_z (T): m_z(k) = W · 2 B_z(k) / (μ0 k f(k)), with
 * f(k) = e^(−kh) sinh(a)/a (and the thickness factor when set). k = 0 is undefined and set to
 * 0: the mean of m_z over the padded canvas is lost; by default (zero_border) the map is then
 * shifted to m_z = 0 on the image border. Measured (tests): 20 µm flake of 1 mA, h = 100 nm,
 * 100 nm pixels, 51.2 µm view: 0.980–0.984 mA inside (taper), 0.93–0.94 mA (mean padding),
 * 0.908–0.912 mA without the border shift. A filter that would pass nothing but the mean
 * (k_c, or without the window e^(kh) > e^700, at the padded map's lowest frequency) and a B_z map
 * smaller than 3 x 3 are SVP_ERR_INVALID, for the B_z-based reconstructions alike. */
SVP_API svp_status svp_reconstruct_magnetisation(const svp_image *bz,
                                                 const svp_recon_options *options,
                                                 svp_image *mz);
/* The same with options->method honoured and reported (report may be NULL). With
 * SVP_RECON_SUPPORT, m_z is the least-squares solution on the view: m_z uniform over each pixel
 * and 0 outside the view, its field (a linear convolution with one pixel's closed-form field,
 * averaged over the NV layer and the source thickness, on the canvas padded by pad_factor with
 * zeros) compared with B_z on the view only, so a bad edge pixel moves m_z near that pixel
 * instead of shifting the whole map, and the mean is determined (no border shift). The window then filters the solution as in the Fourier method. Costs about
 * 6 transforms of the padded canvas per step (15–30 steps). A solve that does not reach
 * `tolerance` within `max_iterations` is SVP_ERR_DOUBTFUL (mz holds the last iterate). */
SVP_API svp_status svp_reconstruct_magnetisation_report(const svp_image *bz,
                                                        const svp_recon_options *options,
                                                        svp_image *mz,
                                                        svp_recon_report *report);
/* Sheet current density (A/m) from B_z (T), in the frame above (right-handed, rows down):
 *   J_x(k) = +i (ky/k) α W B_z(k),   J_y(k) = −i (kx/k) α W B_z(k),   α = 2 / (μ0 f(k)),
 * the same for either sensor side; k = 0 set to 0 (a uniform current makes no B_z). NOTE:
 * some references write the opposite signs, which belong to a left-handed frame (x right, y down,
 * z towards the viewer); the tests pin these against the strip's closed form. The Fourier
 * inversion needs the whole field: for a wire that crosses the view, the 1/x tails of B_z
 * outside it are missing and J is underestimated by roughly 4w/(π² L) (strip width w, view L):
 * measured 137 A/m for 200 A/m with a 40 µm strip in a 51.2 µm view, 196.6 A/m with a 2 µm
 * strip; from B_x the same 40 µm strip gives 199.8 A/m. jx or jy may be NULL. */
SVP_API svp_status svp_reconstruct_current_from_bz(const svp_image *bz,
                                                   const svp_recon_options *options,
                                                   svp_image *jx, svp_image *jy);
/* Sheet current density from the in-plane field: J_y = s α W B_x, J_x = −s α W B_y (k = 0
 * kept: α(0) = 2/μ0). Local in practice: insensitive to the view's size. bx → jy and by → jx;
 * either pair may be NULL. */
SVP_API svp_status svp_reconstruct_current_from_bxy(const svp_image *bx, const svp_image *by,
                                                    const svp_recon_options *options,
                                                    svp_image *jx, svp_image *jy);
/* In-plane field from B_z by the relation in the conventions above (sensor, padding and window
 * from options; set options->window = 0 for the unfiltered relation). k = 0 is set to 0: the
 * mean in-plane field is not determined by B_z. bx or by may be NULL. */
SVP_API svp_status svp_inplane_from_bz(const svp_image *bz, const svp_recon_options *options,
                                       svp_image *bx, svp_image *by);
/* ∇·J (A/m²) by central differences (one-sided at the borders); pixel_m > 0. */
SVP_API svp_status svp_current_divergence(const svp_image *jx, const svp_image *jy,
                                          double pixel_m, svp_image *div);

/* ---- ODMR spectra (docs/model.md §10) ---------------------------------------------------------- */

/* A spectral cube: n_freq frames I(x, y, freq[f]), each an svp_image (frame-major, so every
 * frame can be blurred with svp_blur_apply). */
typedef struct svp_cube {
    int width, height, n_freq;
    double *freq;      /* n_freq frequencies, Hz (strictly increasing) */
    svp_image **frame; /* n_freq frames */
} svp_cube;

/* A cube of zero frames; freq (n_freq values, strictly increasing) is copied. */
SVP_API svp_status svp_cube_new(int width, int height, int n_freq, const double *freq,
                                svp_cube **out);
SVP_API void svp_cube_free(svp_cube *cube);

/* What svp_cube_align measured. */
typedef struct svp_align_info {
    double max_shift;        /* the largest |d| of a frame, pixels */
    double max_deviation;    /* the largest distance between a frame's measured shift and the
                                smooth drift applied (0 for degree −1), pixels: the frames the
                                dips pulled */
    double median_deviation; /* the median distance: the scatter of the measured shifts about
                                the polynomial (registration noise: 5e-4 px noiseless, 0.01 px
                                for 1000-count frames in the tests; and any drift the polynomial
                                does not follow: compare degrees) */
    double min_correlation;  /* the lowest correlation of a registered frame with the mean
                                frame (svp_register_result.correlation): near 1 for frames of
                                one scene whose texture stands above the noise */
    int worst_frame;         /* that frame */
    int n_low_correlation;   /* frames below SVP_ALIGN_MIN_CORRELATION: too little texture
                                above their noise (or not the scene of the others) for a shift
                                to be trusted; the caller decides (svpsf fit-odmr --register
                                refuses them) */
    double min_significance; /* the lowest phase-correlation significance (informative only: a
                                regular pattern, a grid of squares, keeps it below 10 while the
                                shift is found to 1e-4 px) */
} svp_align_info;

/* Frames whose correlation with the mean frame is below this are not trusted (no texture above
 * the noise: measured −0.01 for frames of noise on a uniform PL, 0.9995 for the textured frames
 * of tests/test_register.c). */
#define SVP_ALIGN_MIN_CORRELATION 0.5

/* How svp_cube_align aligns (svp_align_defaults). */
typedef struct svp_align_options {
    int degree;          /* the drift applied: a polynomial of this degree in the frame index,
                            fitted robustly to the measured shifts; −1: each frame its own
                            measured shift; −1 .. 5, default 1 (a steady drift) */
    int reference_frame; /* where the frames go: −1 (default) the sweep's mean position (each
                            frame moves by at most half the drift); k >= 0 frame k's position
                            (on the drift polynomial) */
    const svp_register_options *registration; /* each frame's registration; NULL (default) =
                            svp_register_defaults; translation only, its contrast is set to
                            SAME */
} svp_align_options;

SVP_API void svp_align_defaults(svp_align_options *options);

/* Aligns every frame of an ODMR cube (or any stack of images of one scene), in place: the
 * sample drifting during a sweep moves its PL edges by gradient × drift between frames, which
 * a per-pixel spectrum reads as a dip (docs/model.md §10, "Drift"). Each frame is registered
 * on the mean of all frames (svp_register, phase correlation, translation). A frame on a
 * resonance differs from the mean by its dips as well as by the drift, which pulls its
 * measured shift by up to a few 0.01 px; drift is slow, so with degree >= 0 the shifts applied
 * are a polynomial of that degree in the frame index (the order of acquisition), fitted to the
 * measured ones robustly (Tukey's biweight, iteratively reweighted: the frames the dips pull
 * are outliers). Each frame is moved by svp_shift to the reference position. shift_x / shift_y
 * (n_freq values each, may be NULL) receive the displacement of each frame's content from the
 * reference position (moving(x) = reference(x − d); the frame was moved back by it); info (may
 * be NULL) the largest shift, the measured shifts' deviation from the polynomial and the
 * weakest registration. A frame whose correlation with the mean frame is below
 * SVP_ALIGN_MIN_CORRELATION is counted in info->n_low_correlation: the caller decides (svpsf
 * fit-odmr --register refuses it). A frame with no finite pixel (a failed frame) is missing: it
 * has no say in the drift polynomial or info, stays NaN, and its shift is the polynomial's at
 * its place in the sweep (NaN with degree −1, where it cannot be the reference frame:
 * SVP_ERR_INVALID).
 * The frames go to the threads (one-thread FFT plans each: bit-identical for any thread
 * count); progress from the calling thread; options NULL =
 * svp_align_defaults; a cube needs >= 2 frames (> degree + 1 with degree >= 0) of >= 8 x 8
 * pixels. */
SVP_API svp_status svp_cube_align(svp_cube *cube, const svp_align_options *options,
                                  double *shift_x, double *shift_y, svp_align_info *info,
                                  svp_progress_fn progress, void *progress_user);

/* Deconvolves every frame of a cube in place by Richardson–Lucy (svp_deconv_rl with options;
 * NULL = svp_deconv_defaults; their progress is not used): the frames of an ODMR stack are PL
 * images blurred by one PSF, so this undoes the blur before any per-pixel estimate — the
 * correction for an estimator that is not linear in the frames (a Lorentzian fit), where T⁻¹
 * on its maps is only approximate (docs/model.md §10, "Blur before the estimate"). blur is
 * built for the frames plus `margin` pixels per side (zero boundary); each frame is
 * estimated on that grid with the margin missing (NaN: the data term over the frame only, so
 * light from outside the view is explained by the margin, as svp_correct_options.margin does),
 * and the frame's own missing pixels stay NaN (a frame with no finite pixel, a failed frame,
 * is left as it is). RL needs data >= 0: a finite value below 0
 * (noise about a zero level, a subtracted background) is taken as 0, and *n_negative (may be
 * NULL) counts them over the cube. With two or more threads and an operator svp_blur_clone can copy
 * (invariant, or a map's tent, low-rank or region operator in double precision) the frames go
 * to the threads, each on its own copy with one-thread FFT plans: the same result for any
 * thread count. Progress once per frame, from the calling thread. */
SVP_API svp_status svp_cube_deconvolve(svp_blur *blur, svp_cube *cube, int margin,
                                       const svp_deconv_options *options, size_t *n_negative,
                                       svp_progress_fn progress, void *progress_user);

typedef struct svp_odmr {
    double zero_field_hz;  /* D, default 2.870e9 */
    double gamma_hz_per_t; /* γ_NV / 2π, default 28.033e9 Hz/T */
    double linewidth_hz;   /* Γ, FWHM of each Lorentzian dip, default 1e6 */
    double contrast;       /* C when no contrast map is given, in [0, 0.5]; default 0.02 */
} svp_odmr;

SVP_API void svp_odmr_defaults(svp_odmr *odmr);
/* n_freq >= 2 equally spaced frequencies on D ± (γ |B|_max + half_span_linewidths · Γ). */
SVP_API svp_status svp_odmr_sweep(const svp_odmr *odmr, double field_max_t,
                                  double half_span_linewidths, int n_freq, double *freq);
/* Fills the cube: I(ω) = PL [1 − C Σ± L(ω; D ± γ B_NV, Γ)], L(ω; ω0, Γ) = (Γ/2)² /
 * ((ω − ω0)² + (Γ/2)²) (depth 1 at ω0). pl (>= 0) and field_nv (T) have the cube's size;
 * contrast may be NULL (odmr->contrast everywhere) or a map with values in [0, 0.5].
 * drift_px: hook for a lateral drift between frames (2 n_freq shifts in pixels); not yet
 * implemented: must be NULL (else SVP_ERR_UNSUPPORTED). */
SVP_API svp_status svp_odmr_simulate(const svp_odmr *odmr, const svp_image *pl,
                                     const svp_image *field_nv, const svp_image *contrast,
                                     const double *drift_px, svp_cube *cube);

/* The centroid estimator ("split" centroid of the dip depth). With the off-resonance baseline
 * b(x, y) (the PL; for a blurred cube the blurred PL, or any estimate linear in the frames),
 * the depth d_f = b − I_f and trapezoid weights q_f of the frequency grid, over the frames with
 * window_lo_hz <= freq <= window_hi_hz (both 0: all frames):
 *   B = Σ q_f |ω_f − D| d_f / (γ Σ q_f d_f),     weight = Σ q_f d_f   (Hz · intensity).
 * Both sums are linear in the frames, so for a blurred cube B̃ weight̃ = H(B · weight) and
 * weight̃ = H(weight) hold exactly: eq. (3) with I_m = weight (∝ PL when the contrast is uniform
 * and the dips lie inside the sweep). For two symmetric dips contained in their halves of the
 * window it returns |B_NV| exactly; Lorentzian tails beyond the sweep and across D bias it
 * (a gain error of about Γ / (π R) for a sweep reaching R beyond the line): apply a bias field
 * so the dips separate, and subtract it. Pixels whose Σ q d <= 0 get B = 0 and weight 0.
 * weight may be NULL. */
SVP_API svp_status svp_odmr_centroid(const svp_odmr *odmr, const svp_cube *cube,
                                     const svp_image *baseline, double window_lo_hz,
                                     double window_hi_hz, svp_image *field, svp_image *weight);

/* Which resonances a spectrum holds (docs/model.md §10). The model of svp_odmr_simulate puts
 * the two resonances of an NV axis at D ± γ B_NV (B_NV signed, the upper line at D + γ B_NV). */
typedef enum svp_odmr_lines {
    SVP_ODMR_LINES_PAIR = 0, /* both lines at D ± γB about the given D, sharing C and Γ:
                                θ = (b, C, B, Γ); field = |B_NV| (default; what svpsf simulate
                                fits) */
    SVP_ODMR_LINES_TWO = 1,  /* two dips at free frequencies f₋ < f₊ sharing C and Γ:
                                θ = (b, C, f₋, f₊, Γ); field = (f₊ − f₋) / (2γ), which a shift
                                of D (temperature, strain) leaves alone; per resonance
                                field_lower = (D − f₋) / γ, field_upper = (f₊ − D) / γ */
    SVP_ODMR_LINES_ONE = 2   /* one dip at a free f₀ (the sweep holds one line):
                                θ = (b, C, f₀, Γ); field = line_sign · (f₀ − D) / γ (signed) */
} svp_odmr_lines;

typedef struct svp_odmr_fit_options {
    svp_lm_options lm;   /* Levenberg–Marquardt settings (svp_lm_defaults) */
    int baseline_frames; /* frames at each end of the sweep averaged for the starting baseline;
                            default 3 */
    svp_odmr_lines lines; /* default SVP_ODMR_LINES_PAIR */
    int line_sign;       /* SVP_ODMR_LINES_ONE: +1 (default) the dip is the upper line
                            (m_s = +1, at D + γ B_NV), −1 the lower (at D − γ B_NV) */
    svp_progress_fn progress; /* optional: fraction of the pixels done, about every 1 % and
                                 last 1, always from the calling thread; nonzero cancels
                                 (SVP_ERR_CANCELLED) */
    void *progress_user;
} svp_odmr_fit_options;

SVP_API void svp_odmr_fit_defaults(svp_odmr_fit_options *options);

/* The maps svp_odmr_fit_maps fills: caller-allocated images of the cube's size, each optional
 * (NULL = not wanted) except field. σ is the 1σ uncertainty of the least-squares estimate,
 * sqrt(diag((JᵀJ)⁻¹) · χ² / (n_freq − n_params)) at the solution (unit weights, scaled by the
 * residual: scipy curve_fit's absolute_sigma=False), propagated to the field; INFINITY where
 * JᵀJ is singular or a parameter ended on its bound (C = 0 or 1). */
typedef struct svp_odmr_maps {
    svp_image *field, *field_sigma;             /* T, per options->lines */
    svp_image *field_lower, *field_lower_sigma; /* SVP_ODMR_LINES_TWO only (else must be NULL):
                                                   B from the lower resonance, (D − f₋) / γ */
    svp_image *field_upper, *field_upper_sigma; /* ... from the upper one, (f₊ − D) / γ */
    svp_image *baseline, *baseline_sigma;       /* b: the off-resonance PL (intensity) */
    svp_image *contrast, *contrast_sigma;       /* C (per line; 0..1) */
    svp_image *linewidth, *linewidth_sigma;     /* Γ, Hz (FWHM of each dip) */
    svp_image *quality;   /* R² = 1 − χ² / Σ_f (y_f − ȳ)² of the fit (1 = perfect; near 0 or
                             below: no dip found in the noise); 0 for a flat spectrum */
    svp_image *converged; /* 1 where the fit converged, 0 where not (the parameters are the
                             last ones; counted in *n_failed) */
} svp_odmr_maps;

/* The per-pixel Lorentzian fit: least squares (unit weights) of
 *   PAIR: I(ω) = b [1 − C (L(ω; D + γB, Γ) + L(ω; D − γB, Γ))]
 *   TWO:  I(ω) = b [1 − C (L(ω; f₋, Γ) + L(ω; f₊, Γ))]
 *   ONE:  I(ω) = b [1 − C L(ω; f₀, Γ)]
 * with L of svp_odmr_simulate, D = odmr->zero_field_hz and γ = odmr->gamma_hz_per_t fixed,
 * C in [0, 1], Γ > 0: a dedicated Levenberg–Marquardt (parameters scaled to order one, analytic
 * Jacobian, Cholesky of the damped normal equations) stopping on options->lm's xtol / ftol /
 * gtol / max_iterations; where it does not converge, svp_lm_solve from the same start. Start:
 * b from the end frames (options->baseline_frames at each end), the line(s) at the deepest
 * point(s) of the spectrum smoothed over about half a linewidth (TWO: the deepest point at
 * least 1.5 Γ from the first when it is at least 30 % as deep, else its mirror about D),
 * Γ = odmr->linewidth_hz, C from the area of the dips. n_freq >= 5 (and > the parameter
 * count). Pixels run in parallel (one LM workspace per thread); each pixel's result does not
 * depend on the thread count. A pixel with NaN/Inf in some frames (a failed frame, masked
 * samples) is fitted on its finite samples alone — the same bits as the stack without those
 * frames would give it — when it keeps at least svp_odmr_fit_min_finite of them; else it is
 * missing: NaN in every map but converged (0). *n_failed (may be NULL): pixels whose fit did
 * not converge or was missing. Every pixel missing is SVP_ERR_INVALID (nothing to fit; the
 * message names a frame with no finite value by its frequency). */
SVP_API svp_status svp_odmr_fit_maps(const svp_odmr *odmr, const svp_cube *cube,
                                     const svp_odmr_fit_options *options,
                                     const svp_odmr_maps *maps, size_t *n_failed);

/* The finite samples a pixel of an n_freq-frame stack needs to be fitted by
 * svp_odmr_fit_maps: half the frames (rounded up), and at least the parameters + 1, 5, and
 * twice options->baseline_frames (options NULL: the defaults). */
SVP_API int svp_odmr_fit_min_finite(int n_freq, const svp_odmr_fit_options *options);

/* svp_odmr_fit_maps with field, contrast, baseline and linewidth (each but field may be NULL). */
SVP_API svp_status svp_odmr_fit(const svp_odmr *odmr, const svp_cube *cube,
                                const svp_odmr_fit_options *options, svp_image *field,
                                svp_image *contrast, svp_image *baseline, svp_image *linewidth,
                                size_t *n_failed);

#ifdef __cplusplus
}
#endif
#endif /* SVPSF_H */
