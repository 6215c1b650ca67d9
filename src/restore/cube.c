/* Richardson–Lucy on every frame of a cube (svp_cube_deconvolve; docs/model.md §10, "Blur
 * before the estimate"): the frames of an ODMR stack are PL images, each blurred by the same
 * PSF, so deconvolving them one by one undoes the blur before any per-pixel estimate — the
 * correction for estimators that are not linear in the frames (a Lorentzian fit), where T⁻¹
 * on the estimated maps only approximates. */
#include "restore_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

typedef struct cube_job {
    svp_cube *cube;
    svp_blur **ops;   /* one operator per worker: a copy each (svp_blur_clone), or the caller's */
    svp_image **grid; /* per worker: the frame on the view plus the margin (the margin NaN) */
    svp_image **out;  /* per worker: RL's result on that grid */
    int margin;
    size_t *negative; /* per frame: values below 0 taken as 0 */
    svp_deconv_options o;
} cube_job;

static svp_status deconvolve_frame(void *ctx, int worker, int f)
{
    const cube_job *j = ctx;
    svp_image *frame = j->cube->frame[f], *grid = j->grid[worker], *out = j->out[worker];
    const int w = frame->width, h = frame->height, m = j->margin, gw = grid->width;
    const size_t n = (size_t)gw * grid->height;
    j->negative[f] = 0;
    if (svp_image_count_nonfinite(frame) == (size_t)w * h) return SVP_OK; /* missing: stays */
    for (size_t i = 0; i < n; i++) grid->data[i] = NAN;
    /* RL needs data >= 0: a value below 0 (noise about a zero level, a subtracted
     * background) is taken as 0, and counted */
    size_t negative = 0;
    for (int y = 0; y < h; y++) {
        double *dst = grid->data + (size_t)(y + m) * gw + m;
        const double *src = frame->data + (size_t)y * w;
        for (int x = 0; x < w; x++) {
            negative += src[x] < 0;
            dst[x] = src[x] < 0 ? 0 : src[x];
        }
    }
    j->negative[f] = negative;
    svp_status st = svp_deconv_rl(j->ops[worker], grid, &j->o, out);
    if (st != SVP_OK) return svp_fail_context(st, "frame %d", f);
    for (int y = 0; y < h; y++) {
        double *row = frame->data + (size_t)y * w;
        const double *src = out->data + (size_t)(y + m) * gw + m;
        for (int x = 0; x < w; x++) row[x] = isfinite(row[x]) ? src[x] : NAN; /* missing stays */
    }
    return SVP_OK;
}

static svp_status check_cube(const svp_blur *blur, const svp_cube *cube, int margin)
{
    if (!blur) return svp_fail(SVP_ERR_INVALID, "cube deconvolution: no operator");
    if (!cube || !cube->frame || cube->n_freq < 1)
        return svp_fail(SVP_ERR_INVALID, "cube deconvolution: no cube (or no frame)");
    if (margin < 0)
        return svp_fail(SVP_ERR_INVALID, "cube deconvolution: margin %d (must be >= 0)", margin);
    const int w = cube->width, h = cube->height;
    for (int f = 0; f < cube->n_freq; f++)
        if (!cube->frame[f] || !cube->frame[f]->data || cube->frame[f]->width != w ||
            cube->frame[f]->height != h)
            return svp_fail(SVP_ERR_SIZE, "cube deconvolution: frame %d is missing or not %d x %d",
                            f, w, h);
    if (svp_blur_width(blur) != w + 2 * margin || svp_blur_height(blur) != h + 2 * margin)
        return svp_fail(SVP_ERR_SIZE,
                        "cube deconvolution: the operator is %d x %d, but %d x %d frames with a "
                        "margin of %d need %d x %d",
                        svp_blur_width(blur), svp_blur_height(blur), w, h, margin, w + 2 * margin,
                        h + 2 * margin);
    return SVP_OK;
}

svp_status svp_cube_deconvolve(svp_blur *blur, svp_cube *cube, int margin,
                               const svp_deconv_options *options, size_t *n_negative,
                               svp_progress_fn progress, void *progress_user)
{
    if (n_negative) *n_negative = 0;
    SVP_CHECK(check_cube(blur, cube, margin));
    cube_job j = {.cube = cube, .margin = margin};
    svp_deconv_defaults(&j.o);
    if (options) j.o = *options;
    j.o.progress = NULL; /* the frames report, not their iterations */
    j.o.progress_user = NULL;
    /* the frames over the threads, each on its own copy of the operator when it has one */
    int workers = svp_get_threads() < cube->n_freq ? svp_get_threads() : cube->n_freq;
    if (workers < 1 || !svp_blur_clonable(blur)) workers = 1;
    const int gw = cube->width + 2 * margin, gh = cube->height + 2 * margin;
    j.ops = calloc((size_t)workers, sizeof *j.ops);
    j.grid = calloc((size_t)workers, sizeof *j.grid);
    j.out = calloc((size_t)workers, sizeof *j.out);
    j.negative = calloc((size_t)cube->n_freq, sizeof *j.negative);
    svp_status st = j.ops && j.grid && j.out && j.negative ? SVP_OK
                                              : svp_fail(SVP_ERR_NOMEM, "cube deconvolution: out "
                                                                        "of memory");
    svp_fft_local_threads(1); /* a map's copy takes its plans when it is made */
    for (int t = 0; t < workers && st == SVP_OK; t++) {
        if (workers > 1) st = svp_blur_clone(blur, &j.ops[t]);
        else j.ops[t] = blur;
        if (st == SVP_OK) st = svp_image_new(gw, gh, &j.grid[t]);
        if (st == SVP_OK) st = svp_image_new(gw, gh, &j.out[t]);
    }
    svp_fft_local_threads(0);
    if (st == SVP_OK)
        st = svp_items_parallel(cube->n_freq, workers, deconvolve_frame, &j, progress,
                                progress_user, 0, 1);
    for (int f = 0; f < cube->n_freq && st == SVP_OK && n_negative; f++)
        *n_negative += j.negative[f];
    for (int t = 0; t < workers && j.ops; t++) {
        if (workers > 1) svp_blur_free(j.ops[t]);
        if (j.grid) svp_image_free(j.grid[t]);
        if (j.out) svp_image_free(j.out[t]);
    }
    free(j.ops);
    free(j.grid);
    free(j.out);
    free(j.negative);
    return st;
}
