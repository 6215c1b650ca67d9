/* Library-internal file I/O helpers: OpenCV image codecs (implemented in image_io.cpp, the only
 * C++ file; this header is plain C) and atomic writes (formats.c). Not installed.
 *
 * Every function returns svp_status and leaves a message (svp_last_error) that starts with the
 * file name: "<path>: <fault>". Nothing is printed; OpenCV's own log output is silenced unless
 * the user sets OPENCV_LOG_LEVEL. */
#ifndef SVP_IMAGE_IO_H
#define SVP_IMAGE_IO_H

#include "svpsf.h"

#include <stddef.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ---- atomic writes (formats.c) --------------------------------------------------------------
 * The bytes go to a temporary file in the same folder (".<name>.svpsf-tmp-<pid>-XXXXXX", mode
 * 0666 & ~umask; recorded for svp_io_temp_remove_all, and stale ones of dead processes removed),
 * are fsync'ed, then:
 *   overwrite != 0: rename() over the final name;
 *   overwrite == 0: link() to the final name, so an existing file is never replaced:
 *                   SVP_ERR_EXISTS "<path> exists (use --force to overwrite)".
 * On any failure the temporary file is removed and no partial output remains (SVP_ERR_IO,
 * "<path>: cannot write (<strerror>)"). */
svp_status svp_io_atomic_write_bytes(const char *path, const void *data, size_t size,
                                     int overwrite);
/* The same for a NUL-terminated text (summary.json, PSF-map YAML, CSV tables). */
svp_status svp_io_atomic_write_text(const char *path, const char *text, int overwrite);

/* ---- limits, memory budget, temporary files (guard.c; docs/reliability.md) -------------------
 * The largest image a reader accepts: each side at most SVP_IO_MAX_SIDE, at most
 * SVP_IO_MAX_PIXELS pixels (16384 x 16384, 2 GiB as float64). */
#define SVP_IO_MAX_SIDE 1048576
#define SVP_IO_MAX_PIXELS (1LL << 28)
/* SVP_ERR_FORMAT "<path>: <where>W x H pixels: larger than an image may be (...)" */
svp_status svp_io_check_image_size(const char *path, const char *where, long long width,
                                   long long height);
/* The memory budget: SVPSF_MAX_MEMORY (512M, 4G, ...) when set, else the kernel's MemAvailable
 * (0 when unknown). *source names it for messages. SVP_ERR_INVALID for a malformed variable. */
svp_status svp_io_memory_budget(double *bytes, char *source, size_t source_size);
/* SVP_OK when `bytes` fit the budget (or the budget is unknown), else SVP_ERR_INVALID
 * "<path>: <what> needs N GiB of memory, more than the M GiB allowed (<source>; ...)".
 * Called before a large allocation, with the peak the step will need. path may be NULL. */
svp_status svp_io_check_memory(const char *path, const char *what, double bytes);
/* Temporary files of atomic writes are named ".<name>" SVP_IO_TEMP_TAG "<pid>-XXXXXX". */
#define SVP_IO_TEMP_TAG ".svpsf-tmp-"
/* Records a temporary file's name for svp_io_temp_remove_all (a slot, or -1 when all are
 * taken); svp_io_temp_release(slot) once it was renamed or removed. */
int svp_io_temp_register(const char *name);
void svp_io_temp_release(int slot);
/* Unlinks every recorded temporary file: async-signal-safe, for a SIGTERM/SIGINT handler. */
void svp_io_temp_remove_all(void);
/* Removes ".<base>" SVP_IO_TEMP_TAG "<pid>-*" in `folder` ("" = ".") whose process is gone
 * (left by a run killed with SIGKILL). */
void svp_io_temp_remove_stale(const char *folder, const char *base);

/* ---- OpenCV codecs (image_io.cpp) ----------------------------------------------------------
 * Decodes a TIFF or PNG held in memory (the caller read the file; `path` only names it in
 * messages). Accepts one channel of 8/16-bit unsigned, 8/16-bit signed, 32-bit signed, float32,
 * float64; integers are converted to double as they are (no scaling). Errors (SVP_ERR_FORMAT):
 *   "<path>: cannot decode TIFF (truncated or corrupt)"      (PNG likewise)
 *   "<path>: 3-channel image: expected a single-channel (grayscale) image"
 *   "<path>: unsupported pixel type <depth>" */
svp_status svp_io_decode_cv(const char *path, const unsigned char *bytes, size_t size, int is_tiff,
                            svp_image **out);
/* Every page of a multi-page TIFF file through cv::imreadmulti (the caller counted `n_pages`
 * >= 1 in the file's directory chain; the file is read again by path). Each page must be one
 * channel of a type svp_io_decode_cv accepts, and all pages the first one's size. *pages gets
 * n_pages new images (free each, then the array with free()). Errors (SVP_ERR_FORMAT):
 *   "<path>: cannot decode TIFF stack (truncated or corrupt)"
 *   "<path>: page 3 of 5: 3-channel image: expected a single-channel (grayscale) image"
 *   "<path>: page 3 of 5 is 64 x 32 but page 1 is 32 x 32" */
svp_status svp_io_read_tiff_pages(const char *path, int n_pages, svp_image ***pages);
/* float32 TIFF (uncompressed; values beyond the float32 range become ±Inf, NaN is kept). */
svp_status svp_io_write_tiff(const char *path, const svp_image *img, int overwrite);
/* 16-bit PNG, v = round(65535 (x − min) / (max − min)) over the finite pixels; NaN/Inf → 0; a
 * constant image → 0. For figures: the scale is not stored. */
svp_status svp_io_write_png16(const char *path, const svp_image *img, int overwrite);
/* An 8-bit colour PNG for figures. diverging != 0: a blue–white–red map centred on zero over
 * [−m, m], m = max(|lo|, |hi|); diverging == 0: viridis over [lo, hi]. lo >= hi selects the
 * range from the finite pixels (min..max, or ±max|x| when diverging). NaN/Inf pixels are grey
 * (128, 128, 128). */
svp_status svp_io_write_colormap_png(const char *path, const svp_image *img, double lo, double hi,
                                     int diverging, int overwrite);
/* The colour maps of svp_io_write_colormap_png as RGB bytes, for figures composed around them
 * (src/figure): values[n] -> rgb[3 n] over exactly [lo, hi] (clamped; no symmetric widening),
 * NaN/Inf grey. */
svp_status svp_io_colormap_rgb(const double *values, size_t n, double lo, double hi, int diverging,
                               unsigned char *rgb);
/* OpenCV's version string (CV_VERSION), for --version and summary.json. */
const char *svp_io_opencv_version(void);

/* ---- registration helpers (image_io.cpp; used by io/register.c) -----------------------------
 * ECC alignment through cv::findTransformECC (template = reference, input = moving), one
 * iteration per call so that convergence is checked here and progress can be reported.
 * reference/moving: width x height row-major doubles, already normalised, without NaN.
 * smooth_sigma > 0: cv::GaussianBlur of both (sigma in pixels) once, before the iterations.
 * motion: 0 translation, 1 euclidean, 2 affine (svp_register_motion). warp[6]: in = the
 * starting transform, out = the result (reference → moving coordinates; see svpsf.h).
 * Stops when the ECC coefficient changes by less than epsilon; otherwise after `iterations`
 * steps returns SVP_ERR_NUMERIC "registration did not converge after N iterations
 * (correlation r)". OpenCV failures (no convergence, NaN) → SVP_ERR_NUMERIC with its reason.
 * *iterations_done and *correlation (the last ECC coefficient) are set in every case. */
svp_status svp_io_register_ecc(const double *reference, const double *moving, int width,
                               int height, int motion, double smooth_sigma, int iterations,
                               double epsilon, double warp[6], int *iterations_done,
                               double *correlation, svp_progress_fn progress,
                               void *progress_user);

#ifdef __cplusplus
}
#endif
#endif
