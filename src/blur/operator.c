/* The blur operator H: linear convolution with an explicit boundary policy, plus the halo. */
#include "blur_internal.h"

#include <math.h>
#include <omp.h>
#include <stdlib.h>
#include <string.h>

/* ---- frames ------------------------------------------------------------------------------ */

static int reflect(int t, int size)
{
    /* symmetric (half-sample) reflection into [0, size): d c b a | a b c d | d c b a */
    int period = 2 * size;
    t %= period;
    if (t < 0) t += period;
    return t < size ? t : period - 1 - t;
}

/* margin (zero mode only): the data lie on the inner view, `margin` pixels in from each end;
 * offsets that join no grid pixel to the view (beyond size − margin − 1) are dropped, and the
 * frame only has to keep the view free of wrap-around: size − margin + r values suffice
 * (at least size, to hold the grid). margin 0: the plain linear convolution, size + r.
 * *src receives the map from frame position to source pixel; src NULL: the size only, nothing
 * allocated (svp_frame_size, whose callers' memory estimates must not fail for lack of it). */
static svp_status axis_init(int size, int r, svp_boundary b, int margin, int *n, int *off,
                            int **src)
{
    int single = 0;
    switch (b) {
    case SVP_BOUNDARY_ZERO:
        if (r > size - margin - 1) r = size - margin - 1;
        *n = svp_fft_good_size(size - margin + r > size ? size - margin + r : size);
        *off = 0;
        break;
    case SVP_BOUNDARY_PERIODIC:
        *n = size;
        *off = 0;
        break;
    case SVP_BOUNDARY_MIRROR:
        /* one reflection of r pixels each side is exact while r <= size; the symmetric period
         * 2 size is exact for any r. Take the smaller frame. */
        if (r <= size && svp_fft_good_size(size + 2 * r) < 2 * size) {
            single = 1;
            *n = svp_fft_good_size(size + 2 * r);
            *off = r;
        } else {
            *n = 2 * size;
            *off = 0;
        }
        break;
    default: return svp_fail(SVP_ERR_INVALID, "unknown boundary mode %d", (int)b);
    }
    if (!src) return SVP_OK; /* the size only */
    int *s = malloc((size_t)*n * sizeof *s);
    if (!s) return svp_fail(SVP_ERR_NOMEM, "out of memory for a frame map");
    for (int j = 0; j < *n; j++) {
        switch (b) {
        case SVP_BOUNDARY_ZERO: s[j] = j < size ? j : -1; break;
        case SVP_BOUNDARY_PERIODIC: s[j] = j; break;
        default:
            if (single)
                s[j] = j < size + 2 * r ? reflect(j - r, size) : -1;
            else
                s[j] = reflect(j, size);
        }
    }
    *src = s;
    return SVP_OK;
}

/* svp_frame_init, or with margin > 0 (zero mode) the frame for data on the inner view */
static svp_status frame_init(svp_frame *f, int width, int height, int rx, int ry,
                             svp_boundary boundary, int margin)
{
    memset(f, 0, sizeof *f);
    f->width = width;
    f->height = height;
    f->margin = margin;
    svp_status st = axis_init(width, rx, boundary, margin, &f->nx, &f->off_x, &f->src_x);
    if (st == SVP_OK) st = axis_init(height, ry, boundary, margin, &f->ny, &f->off_y, &f->src_y);
    if (st == SVP_OK) st = svp_fft_plan_get(f->ny, f->nx, &f->plan);
    if (st != SVP_OK) {
        svp_frame_release(f);
        return st;
    }
    f->ncx = f->nx / 2 + 1;
    return SVP_OK;
}

svp_status svp_frame_init(svp_frame *f, int width, int height, int rx, int ry,
                          svp_boundary boundary)
{
    return frame_init(f, width, height, rx, ry, boundary, 0);
}

/* The frame frame_init would make, its size only (no plans, no OTF). */
static svp_status frame_size(int width, int height, int rx, int ry, svp_boundary boundary,
                             int margin, int *nx, int *ny)
{
    int off;
    SVP_CHECK(axis_init(width, rx, boundary, margin, nx, &off, NULL));
    return axis_init(height, ry, boundary, margin, ny, &off, NULL);
}

svp_status svp_frame_size(int width, int height, int rx, int ry, svp_boundary boundary, int *nx,
                          int *ny)
{
    return frame_size(width, height, rx, ry, boundary, 0, nx, ny);
}

svp_status svp_frame_size_view(int width, int height, int rx, int ry, int margin, int *nx,
                               int *ny)
{
    return frame_size(width, height, rx, ry, SVP_BOUNDARY_ZERO, margin, nx, ny);
}

void svp_frame_release(svp_frame *f)
{
    free(f->src_x);
    free(f->src_y);
    svp_free(f->otf);
    svp_free(f->otf_re);
    memset(f, 0, sizeof *f);
}

size_t svp_frame_memory(const svp_frame *f)
{
    const size_t value = f->otf_re ? sizeof(double) : sizeof(fftw_complex);
    return (size_t)f->ny * f->ncx * value + (size_t)(f->nx + f->ny) * sizeof(int);
}

int svp_spectrum_is_real(const fftw_complex *z, size_t n)
{
    const double *restrict d = (const double *)z;
    double re = 0, im = 0;
    for (size_t i = 0; i < n; i++) {
        const double a = fabs(d[2 * i]), b = fabs(d[2 * i + 1]);
        re = a > re ? a : re;
        im = b > im ? b : im;
    }
    return im <= 1e-12 * (re > im ? re : im);
}

double *svp_spectrum_real_part(const fftw_complex *z, size_t n)
{
    double *re = svp_alloc(n * sizeof(double));
    if (re)
        for (size_t i = 0; i < n; i++) re[i] = creal(z[i]);
    return re;
}

int svp_frame_keep_real(svp_frame *f)
{
    const size_t n = (size_t)f->ny * f->ncx;
    if (!f->otf || !svp_spectrum_is_real(f->otf, n)) return 0;
    double *re = svp_spectrum_real_part(f->otf, n);
    if (!re) return 0; /* the complex OTF stays: slower, not wrong */
    svp_free(f->otf);
    f->otf = NULL;
    f->otf_re = re;
    return 1;
}

void svp_spectrum_scale(const double *restrict o, double *restrict s, size_t n, double scale)
{
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN / 2)
    for (size_t i = 0; i < n; i++) {
        const double g = scale * o[i];
        s[2 * i] *= g;
        s[2 * i + 1] *= g;
    }
}

void svp_spectrum_scale_f(const float *restrict o, float *restrict s, size_t n)
{
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN / 2)
    for (size_t i = 0; i < n; i++) {
        s[2 * i] *= o[i];
        s[2 * i + 1] *= o[i];
    }
}

static int wrap(int d, int n)
{
    d %= n;
    return d < 0 ? d + n : d;
}

svp_status svp_frame_set_kernel(svp_frame *f, const svp_image *kernel, int cx, int cy,
                                svp_boundary boundary)
{
    svp_free(f->otf_re);
    f->otf_re = NULL;
    double *placed = svp_calloc((size_t)f->ny * f->nx, sizeof(double));
    if (!f->otf) f->otf = svp_alloc((size_t)f->ny * f->ncx * sizeof(fftw_complex));
    if (!placed || !f->otf) {
        svp_free(placed);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d OTF", f->nx, f->ny);
    }
    const int kw = kernel->width, kh = kernel->height;
    /* Serial over rows: aliased offsets add into the same cell. */
    for (int y = 0; y < kh; y++) {
        int dy = y - cy;
        if (boundary == SVP_BOUNDARY_ZERO && abs(dy) > f->height - f->margin - 1) continue;
        int fy = wrap(dy, f->ny);
        double *row = placed + (size_t)fy * f->nx;
        const double *krow = kernel->data + (size_t)y * kw;
        for (int x = 0; x < kw; x++) {
            int dx = x - cx;
            if (boundary == SVP_BOUNDARY_ZERO && abs(dx) > f->width - f->margin - 1) continue;
            row[wrap(dx, f->nx)] += krow[x];
        }
    }
    svp_fft_forward(f->plan, placed, f->otf);
    svp_free(placed);
    return SVP_OK;
}

/* Frame-sized loops run in parallel above SVP_PARALLEL_MIN values. */
#define SVP_FRAME_BIG(f) ((size_t)(f)->nx * (f)->ny > SVP_PARALLEL_MIN)

/* _Pragma inside a macro is beyond clang-format: this block is laid out by hand */
/* clang-format off */
/* E, C, Cᵀ and Eᵀ between a double image and a frame of element type FT (double for the
 * operator's own frames, float for its single-precision transforms); the zero-boundary load
 * (rows 0 .. height − 1 = the image rows zero-padded to nx, rows height .. rows − 1 zero);
 * and the in-place spectral product s *= scale · otf (conj(otf) when conjugate), written out
 * in real arithmetic: C99 complex products carry a NaN fix-up branch (__muldc3) that keeps
 * the loop from vectorising. */
#define SVP_FRAME_OPS(EXTEND, CROP, EMBED, FOLD, ZERO_LOAD, PRODUCT, FT)                           \
    void EXTEND(const svp_frame *f, const double *restrict image, FT *restrict frame)              \
    {                                                                                              \
        const int nx = f->nx, w = f->width;                                                        \
        const int *sx = f->src_x, *sy = f->src_y;                                                  \
        _Pragma("omp parallel for schedule(static) if (SVP_FRAME_BIG(f))")                         \
        for (int j = 0; j < f->ny; j++) {                                                          \
            FT *out = frame + (size_t)j * nx;                                                      \
            if (sy[j] < 0) {                                                                       \
                memset(out, 0, (size_t)nx * sizeof(FT));                                           \
                continue;                                                                          \
            }                                                                                      \
            const double *in = image + (size_t)sy[j] * w;                                          \
            /* the image row itself is one contiguous copy; only the margins look up src */        \
            const int lo = f->off_x, hi = f->off_x + w;                                            \
            for (int i = 0; i < lo; i++) out[i] = sx[i] >= 0 ? (FT)in[sx[i]] : (FT)0;              \
            for (int i = 0; i < w; i++) out[lo + i] = (FT)in[i];                                   \
            for (int i = hi; i < nx; i++) out[i] = sx[i] >= 0 ? (FT)in[sx[i]] : (FT)0;             \
        }                                                                                          \
    }                                                                                              \
    void CROP(const svp_frame *f, const FT *restrict frame, double *restrict image)                \
    {                                                                                              \
        const int w = f->width;                                                                    \
        _Pragma("omp parallel for schedule(static) if (SVP_FRAME_BIG(f))")                         \
        for (int y = 0; y < f->height; y++) {                                                      \
            const FT *in = frame + (size_t)(y + f->off_y) * f->nx + f->off_x;                      \
            double *out = image + (size_t)y * w;                                                   \
            for (int i = 0; i < w; i++) out[i] = (double)in[i];                                    \
        }                                                                                          \
    }                                                                                              \
    void EMBED(const svp_frame *f, const double *restrict image, FT *restrict frame)               \
    {                                                                                              \
        const int w = f->width, nx = f->nx;                                                        \
        _Pragma("omp parallel for schedule(static) if (SVP_FRAME_BIG(f))")                         \
        for (int j = 0; j < f->ny; j++) {                                                          \
            FT *out = frame + (size_t)j * nx;                                                      \
            memset(out, 0, (size_t)nx * sizeof(FT));                                               \
            int y = j - f->off_y;                                                                  \
            if (y >= 0 && y < f->height) {                                                         \
                const double *in = image + (size_t)y * w;                                          \
                for (int i = 0; i < w; i++) out[f->off_x + i] = (FT)in[i];                         \
            }                                                                                      \
        }                                                                                          \
    }                                                                                              \
    void FOLD(const svp_frame *f, const FT *restrict frame, double *restrict image)                \
    {                                                                                              \
        const int w = f->width, h = f->height, nx = f->nx;                                         \
        const int *sx = f->src_x, *sy = f->src_y;                                                  \
        /* each image row gathers the frame rows that copy it, in frame order (deterministic) */   \
        _Pragma("omp parallel for schedule(static) if (SVP_FRAME_BIG(f))")                         \
        for (int y = 0; y < h; y++) {                                                              \
            double *out = image + (size_t)y * w;                                                   \
            memset(out, 0, (size_t)w * sizeof(double));                                            \
            for (int j = 0; j < f->ny; j++) {                                                      \
                if (sy[j] != y) continue;                                                          \
                const FT *in = frame + (size_t)j * nx;                                             \
                const int lo = f->off_x, hi = f->off_x + w;                                        \
                for (int i = 0; i < w; i++) out[i] += (double)in[lo + i];                          \
                for (int i = 0; i < lo; i++)                                                       \
                    if (sx[i] >= 0) out[sx[i]] += (double)in[i];                                   \
                for (int i = hi; i < nx; i++)                                                      \
                    if (sx[i] >= 0) out[sx[i]] += (double)in[i];                                   \
            }                                                                                      \
        }                                                                                          \
    }                                                                                              \
    void ZERO_LOAD(const svp_frame *f, int rows, const double *restrict image, FT *restrict frame) \
    {                                                                                              \
        const int w = f->width, nx = f->nx;                                                        \
        _Pragma("omp parallel for schedule(static) if (SVP_FRAME_BIG(f))")                         \
        for (int j = 0; j < rows; j++) {                                                           \
            FT *out = frame + (size_t)j * nx;                                                      \
            if (j < f->height) {                                                                   \
                const double *in = image + (size_t)j * w;                                          \
                for (int i = 0; i < w; i++) out[i] = (FT)in[i];                                    \
                memset(out + w, 0, (size_t)(nx - w) * sizeof(FT));                                 \
            } else {                                                                               \
                memset(out, 0, (size_t)nx * sizeof(FT));                                           \
            }                                                                                      \
        }                                                                                          \
    }                                                                                              \
    void PRODUCT(const FT *restrict otf, FT *restrict s, size_t n, int conjugate, FT scale)        \
    {                                                                                              \
        const FT sign = conjugate ? (FT)-1 : (FT)1;                                                \
        _Pragma("omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN / 2)")                 \
        for (size_t i = 0; i < n; i++) {                                                           \
            const FT pr = scale * otf[2 * i], pi = sign * scale * otf[2 * i + 1];                  \
            const FT sr = s[2 * i], si = s[2 * i + 1];                                             \
            s[2 * i] = pr * sr - pi * si;                                                          \
            s[2 * i + 1] = pr * si + pi * sr;                                                      \
        }                                                                                          \
    }

SVP_FRAME_OPS(svp_frame_extend, svp_frame_crop, svp_frame_embed, svp_frame_fold, svp_frame_zero_load,
              svp_spectrum_product, double)
SVP_FRAME_OPS(svp_frame_extend_f, svp_frame_crop_f, svp_frame_embed_f, svp_frame_fold_f,
              svp_frame_zero_load_f, svp_spectrum_product_f, float)
/* clang-format on */

void svp_frame_filter(const svp_frame *f, const svp_fft_pruned *pruned, double *frame,
                      fftw_complex *spectrum, int adjoint)
{
    if (pruned)
        svp_fft_forward_pruned(pruned, frame, spectrum);
    else
        svp_fft_forward(f->plan, frame, spectrum);
    svp_frame_multiply(f, spectrum, adjoint, 1.0 / ((double)f->nx * f->ny));
    if (pruned)
        svp_fft_inverse_pruned_unscaled(pruned, spectrum, frame);
    else
        svp_fft_inverse_unscaled(f->plan, spectrum, frame);
}

void svp_frame_multiply(const svp_frame *f, fftw_complex *restrict spectrum, int conjugate,
                        double scale)
{
    if (f->otf_re)
        svp_spectrum_scale(f->otf_re, (double *)spectrum, (size_t)f->ny * f->ncx, scale);
    else
        svp_spectrum_product((const double *)f->otf, (double *)spectrum, (size_t)f->ny * f->ncx,
                             conjugate, scale);
}

/* ---- the operator ------------------------------------------------------------------------ */

/* The kernel's radii: the largest offset from its centre on each axis. */
static void kernel_radii(const svp_blur *b, int *rx, int *ry)
{
    *rx = svp_kernel_reach(b->kernel->width, b->kcx);
    *ry = svp_kernel_reach(b->kernel->height, b->kcy);
}

/* The frame of an invariant operator (margin > 0: for data on the inner view), its OTF (real
 * when the kernel is point-symmetric) and, in zero mode with rows below the image, the pruned
 * plan (*pruned NULL otherwise). */
static svp_status invariant_frame(const svp_blur *b, int margin, svp_frame *f,
                                  const svp_fft_pruned **pruned)
{
    /* with a tail on a coarse grid the frame is the core's */
    const svp_image *k = b->core ? b->core : b->kernel;
    const int kcx = b->core ? b->core_cx : b->kcx, kcy = b->core ? b->core_cy : b->kcy;
    const int rx = svp_kernel_reach(k->width, kcx), ry = svp_kernel_reach(k->height, kcy);
    *pruned = NULL;
    svp_status st = frame_init(f, b->width, b->height, rx, ry, b->boundary, margin);
    if (st == SVP_OK) st = svp_frame_set_kernel(f, k, kcx, kcy, b->boundary);
    if (st == SVP_OK) svp_frame_keep_real(f);
    /* zero mode: the image fills only the first height rows of the frame */
    if (st == SVP_OK && b->boundary == SVP_BOUNDARY_ZERO && f->ny > b->height)
        st = svp_fft_pruned_get(f->ny, f->nx, b->height, pruned);
    if (st != SVP_OK) svp_frame_release(f);
    return st;
}

/* The frame invariant_frame would make for `margin`, its size only (no plans, no OTF). */
static svp_status frame_dims(const svp_blur *b, int margin, int *nx, int *ny)
{
    int rx, ry;
    kernel_radii(b, &rx, &ry);
    return frame_size(b->width, b->height, rx, ry, b->boundary, margin, nx, ny);
}

/* The frame is made on first use (svp_blur_ready), when it is known whether the full grid's or
 * a view's is wanted; its geometry is checked now. */
static svp_status blur_finish(svp_blur *b, svp_blur **out)
{
    int nx, ny;
    svp_status st = frame_dims(b, 0, &nx, &ny);
    if (st != SVP_OK) {
        svp_blur_free(b);
        return st;
    }
    *out = b;
    return SVP_OK;
}

svp_status svp_blur_check_geometry(int width, int height, svp_boundary boundary)
{
    if (width < 1 || height < 1)
        return svp_fail(SVP_ERR_INVALID, "image size %d x %d: both must be at least 1", width,
                        height);
    if (boundary != SVP_BOUNDARY_ZERO && boundary != SVP_BOUNDARY_MIRROR &&
        boundary != SVP_BOUNDARY_PERIODIC)
        return svp_fail(SVP_ERR_INVALID, "unknown boundary mode %d", (int)boundary);
    return SVP_OK;
}

svp_status svp_blur_new(const svp_psf *psf, int width, int height, svp_boundary boundary,
                        svp_blur **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_blur_new: out is NULL");
    *out = NULL;
    SVP_CHECK(svp_psf_validate(psf));
    SVP_CHECK(svp_blur_check_geometry(width, height, boundary));
    /* Default support: every offset that joins two pixels of the field of view. */
    int rx = width - 1, ry = height - 1;
    if (psf->support > 0) {
        rx = (int)ceil(psf->support);
        ry = rx;
        if (boundary == SVP_BOUNDARY_ZERO) {
            /* offsets beyond the image never connect two pixels, but normalisation is over
             * the whole support: render it whole, the frame drops what cannot reach. */
        }
    }
    svp_blur *b = calloc(1, sizeof *b);
    if (!b) return svp_fail(SVP_ERR_NOMEM, "out of memory for a blur operator");
    b->kind = SVP_BLUR_INVARIANT;
    b->ops = &svp_invariant_ops;
    b->width = width;
    b->height = height;
    b->boundary = boundary;
    b->halo = psf->halo;
    b->has_model = 1;
    b->psf = *psf;
    svp_status st = svp_psf_render(psf, rx, ry, &b->kernel);
    if (st != SVP_OK) {
        free(b);
        return st;
    }
    b->kcx = rx;
    b->kcy = ry;
    return blur_finish(b, out);
}

svp_status svp_blur_new_kernel(const svp_image *kernel, int cx, int cy, int normalise, int width,
                               int height, svp_boundary boundary, svp_blur **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_blur_new_kernel: out is NULL");
    *out = NULL;
    if (!kernel || !kernel->data) return svp_fail(SVP_ERR_INVALID, "kernel is missing");
    SVP_CHECK(svp_blur_check_geometry(width, height, boundary));
    if (cx < 0 && cy < 0) {
        cx = kernel->width / 2;
        cy = kernel->height / 2;
    }
    if (cx < 0 || cy < 0 || cx >= kernel->width || cy >= kernel->height)
        return svp_fail(SVP_ERR_INVALID, "kernel centre (%d, %d) is outside the %d x %d kernel", cx,
                        cy, kernel->width, kernel->height);
    size_t n = (size_t)kernel->width * kernel->height;
    if (svp_image_count_nonfinite(kernel))
        return svp_fail(SVP_ERR_INVALID, "kernel has NaN or Inf values");
    double sum = svp_sum(kernel->data, n);
    if (normalise && !(sum > 0)) /* dividing by a negative sum would flip the PSF's sign */
        return svp_fail(SVP_ERR_INVALID,
                        "kernel sums to %g: it cannot be normalised to unit flux (a PSF's light "
                        "sums to a positive total)",
                        sum);
    svp_blur *b = calloc(1, sizeof *b);
    if (!b) return svp_fail(SVP_ERR_NOMEM, "out of memory for a blur operator");
    b->kind = SVP_BLUR_INVARIANT;
    b->ops = &svp_invariant_ops;
    b->width = width;
    b->height = height;
    b->boundary = boundary;
    b->kcx = cx;
    b->kcy = cy;
    svp_status st = svp_image_copy(kernel, &b->kernel);
    if (st != SVP_OK) {
        free(b);
        return st;
    }
    if (normalise)
        for (size_t i = 0; i < n; i++) b->kernel->data[i] /= sum;
    return blur_finish(b, out);
}

svp_blur *svp_blur_copy_header(const svp_blur *b)
{
    svp_blur *c = calloc(1, sizeof *c);
    if (!c) return NULL;
    c->kind = b->kind;
    c->ops = b->ops;
    c->width = b->width;
    c->height = b->height;
    c->boundary = b->boundary;
    c->halo = b->halo;
    c->has_model = b->has_model;
    c->psf = b->psf;
    c->kcx = b->kcx;
    c->kcy = b->kcy;
    c->kernel = b->kernel; /* b's, read only: b must outlive the copy */
    c->kernel_borrowed = 1;
    return c;
}

svp_status svp_blur_clone_invariant(const svp_blur *b, svp_blur **out)
{
    *out = NULL;
    if (!b || b->kind != SVP_BLUR_INVARIANT)
        return svp_fail(SVP_ERR_UNSUPPORTED, "only an invariant operator can be cloned");
    svp_blur *c = svp_blur_copy_header(b);
    if (!c) return svp_fail(SVP_ERR_NOMEM, "out of memory for a blur operator");
    c->view_margin = b->view_margin;
    c->single = b->single;
    c->tail_tol = b->tail_tol;
    c->tail_for = b->tail_for;
    c->tail_s = b->tail_s;
    c->tail_r0 = b->tail_r0;
    c->tail_err = b->tail_err;
    *out = c;
    return SVP_OK;
}

int svp_blur_clonable(const svp_blur *b)
{
    if (!b) return 0;
    if (b->kind == SVP_BLUR_INVARIANT) return 1;
    return (b->ops == &svp_tent_ops || b->ops == &svp_lowrank_ops || b->ops == &svp_regions_ops) &&
           !b->single && svp_blur_has_double(b);
}

svp_status svp_blur_clone(const svp_blur *b, svp_blur **out)
{
    if (b && b->kind != SVP_BLUR_INVARIANT) return svp_variant_clone(b, out);
    return svp_blur_clone_invariant(b, out);
}

void svp_blur_free(svp_blur *b)
{
    if (!b) return;
    if (b->ops) b->ops->release(b);
    if (b->restore.release) b->restore.release(b->restore.data);
    svp_frame_release(&b->frame);
    svp_tail_free(b->tail);
    svp_image_free(b->core);
    if (!b->kernel_borrowed) svp_image_free(b->kernel);
    svp_free(b->work_r);
    svp_free(b->work_c);
    svp_free(b->work_rf);
    svp_free(b->work_cf);
    svp_free(b->otf_f);
    free(b);
}

int svp_blur_width(const svp_blur *b) { return b->width; }
int svp_blur_height(const svp_blur *b) { return b->height; }
svp_boundary svp_blur_boundary(const svp_blur *b) { return b->boundary; }
double svp_blur_halo(const svp_blur *b) { return b->halo; }

size_t svp_blur_memory(const svp_blur *b)
{
    const size_t cache = b->restore.memory ? b->restore.memory(b->restore.data) : 0;
    return b->ops->memory(b) + cache;
}

static svp_status check_io(const svp_blur *b, const svp_image *in, const svp_image *out,
                           const char *what)
{
    if (!b || !in || !out) return svp_fail(SVP_ERR_INVALID, "%s: NULL argument", what);
    if (in->width != b->width || in->height != b->height || out->width != b->width ||
        out->height != b->height)
        return svp_fail(SVP_ERR_SIZE,
                        "%s: operator is %d x %d but input is %d x %d and output %d x %d", what,
                        b->width, b->height, in->width, in->height, out->width, out->height);
    if (in->data == out->data)
        return svp_fail(SVP_ERR_INVALID, "%s: input and output must not alias", what);
    return SVP_OK;
}

/* out = (1 − α) conv + α <in> (the halo term is its own adjoint). */
static void add_halo(const svp_blur *b, const double *in, double *out)
{
    const size_t n = (size_t)b->width * b->height;
    if (b->halo == 0) return;
    const double mean = svp_sum(in, n) / (double)n;
    const double keep = 1.0 - b->halo, add = b->halo * mean;
#pragma omp parallel for schedule(static) if (n > 65536)
    for (size_t i = 0; i < n; i++) out[i] = keep * out[i] + add;
}

void svp_blur_spectrum_in(svp_blur *b, const double *restrict image, int adjoint_side)
{
    const svp_frame *f = &b->frame;
    if (b->boundary == SVP_BOUNDARY_ZERO)
        /* E and Cᵀ coincide (src = identity, off = 0); with the pruned transform the rows
         * below the image are never read, without it they are zeroed */
        svp_frame_zero_load(f, b->pruned ? f->height : f->ny, image, b->work_r);
    else if (adjoint_side)
        svp_frame_embed(f, image, b->work_r);
    else
        svp_frame_extend(f, image, b->work_r);
    if (b->pruned)
        svp_fft_forward_pruned(b->pruned, b->work_r, b->work_c);
    else
        svp_fft_forward(f->plan, b->work_r, b->work_c);
}

void svp_blur_spectrum_out(svp_blur *b, double *restrict image, int adjoint_side)
{
    const svp_frame *f = &b->frame;
    if (b->pruned)
        svp_fft_inverse_pruned_unscaled(b->pruned, b->work_c, b->work_r);
    else
        svp_fft_inverse_unscaled(f->plan, b->work_c, b->work_r);
    /* zero mode: Eᵀ is the crop (every image pixel has exactly one copy, at its own place) */
    if (adjoint_side && b->boundary != SVP_BOUNDARY_ZERO)
        svp_frame_fold(f, b->work_r, image);
    else
        svp_frame_crop(f, b->work_r, image);
}

/* ---- single precision ---------------------------------------------------------------------- */

svp_status svp_blur_set_single(svp_blur *b, int on)
{
    if (!b) return svp_fail(SVP_ERR_INVALID, "svp_blur_set_single: the operator is NULL");
    if (b->kind != SVP_BLUR_INVARIANT) return svp_variant_set_single(b, on);
    if (on != b->single) b->rows_held = 0;
    if (!on) {
        b->single = 0;
        return SVP_OK;
    }
    if (!b->frame.plan) { /* the frame first, which then makes the float state for it */
        b->single = 1;
        const svp_status st = svp_blur_ready(b);
        if (st != SVP_OK) b->single = 0;
        return st;
    }
    const svp_frame *f = &b->frame;
    if (!b->rows_f) {
        /* zero mode: only the image's rows are non-zero in, and kept out */
        const int rows = b->boundary == SVP_BOUNDARY_ZERO ? f->height : f->ny;
        const size_t nc = (size_t)f->ny * f->ncx;
        const int real = f->otf_re != NULL; /* a real OTF: its real parts only */
        float *r = svp_alloc((size_t)f->ny * f->nx * sizeof(float));
        fftwf_complex *c = svp_alloc(nc * sizeof(fftwf_complex));
        float *o = svp_alloc(nc * (real ? 1 : 2) * sizeof(float));
        const svp_fftf_rows *plan = NULL;
        svp_status st = (!r || !c || !o) ? svp_fail(SVP_ERR_NOMEM,
                                                    "out of memory for the %d x "
                                                    "%d float frame",
                                                    f->nx, f->ny)
                                         : svp_fftf_rows_get(f->ny, f->nx, rows, &plan);
        if (st != SVP_OK) {
            svp_free(r);
            svp_free(c);
            svp_free(o);
            return st;
        }
        const double scale = 1.0 / ((double)f->nx * f->ny);
        float *restrict of = o;
        for (size_t i = 0; i < nc; i++) {
            if (real) {
                of[i] = (float)(scale * f->otf_re[i]);
                continue;
            }
            const double complex z = svp_frame_otf(f, i);
            of[2 * i] = (float)(scale * creal(z));
            of[2 * i + 1] = (float)(scale * cimag(z));
        }
        b->rows_f = plan;
        b->work_rf = r;
        b->work_cf = c;
        b->otf_f = o;
        b->otf_f_real = real;
    }
    b->single = 1;
    return SVP_OK;
}

/* The float frame, spectrum and OTF freed (svp_blur_set_single makes them again, for the frame
 * then in use); the plans stay in the cache. */
static void drop_single(svp_blur *b)
{
    svp_free(b->work_rf);
    svp_free(b->work_cf);
    svp_free(b->otf_f);
    b->work_rf = NULL;
    b->work_cf = NULL;
    b->otf_f = NULL;
    b->otf_f_real = 0;
    b->rows_f = NULL;
}

/* An invariant operator's frame, work buffers and float state freed: the next use makes the
 * frame for b->view_margin (svp_blur_ready). The plans stay in the cache. */
static void drop_frame(svp_blur *b)
{
    svp_frame_release(&b->frame);
    svp_tail_free(b->tail);
    b->tail = NULL;
    svp_image_free(b->core);
    b->core = NULL;
    b->pruned = NULL;
    svp_free(b->work_r);
    svp_free(b->work_c);
    b->work_r = NULL;
    b->work_c = NULL;
    b->rows_held = 0;
    drop_single(b);
}

/* The tail an invariant zero-boundary operator with tail_tol > 0 takes for its frame in use
 * (svp_tail_choose against that frame's plain size): *s 0 for none. */
static svp_status tail_choice(svp_blur *b, int *s, int *r0, double *err)
{
    int nx = 0, ny = 0;
    *s = 0;
    *r0 = 0;
    *err = 0;
    if (!(b->tail_tol > 0) || b->boundary != SVP_BOUNDARY_ZERO) return SVP_OK;
    if (b->tail_for != b->view_margin + 1) { /* tail_for holds the margin + 1, 0: none yet */
        SVP_CHECK(frame_dims(b, b->view_margin, &nx, &ny));
        SVP_CHECK(svp_tail_choose(b->kernel, b->kcx, b->kcy, b->width, b->height,
                                  b->view_margin, b->tail_tol, nx, ny, &b->tail_s, &b->tail_r0,
                                  &b->tail_err));
        b->tail_for = b->view_margin + 1;
    }
    *s = b->tail_s;
    *r0 = b->tail_r0;
    *err = b->tail_err;
    return SVP_OK;
}

svp_status svp_blur_ready(svp_blur *b)
{
    if (b->kind != SVP_BLUR_INVARIANT || b->frame.plan) return SVP_OK;
    svp_status st = SVP_OK;
    if (b->tail_tol > 0 && b->boundary == SVP_BOUNDARY_ZERO) {
        int s = 0, r0 = 0;
        double err;
        st = tail_choice(b, &s, &r0, &err);
        if (st == SVP_OK && s > 0)
            st = svp_tail_core(b->kernel, b->kcx, b->kcy, r0, &b->core, &b->core_cx,
                               &b->core_cy);
        if (st == SVP_OK && s > 0)
            st = svp_tail_new(b->kernel, b->kcx, b->kcy, b->width, b->height, b->view_margin, s,
                              r0, err, &b->tail);
    }
    if (st == SVP_OK) st = invariant_frame(b, b->view_margin, &b->frame, &b->pruned);
    if (st == SVP_OK) {
        b->frames_built++;
        b->work_r = svp_alloc((size_t)b->frame.ny * b->frame.nx * sizeof(double));
        b->work_c = svp_alloc((size_t)b->frame.ny * b->frame.ncx * sizeof(fftw_complex));
        if (!b->work_r || !b->work_c)
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for the %d x %d blur buffers", b->frame.nx,
                          b->frame.ny);
    }
    if (st == SVP_OK && b->single) st = svp_blur_set_single(b, 1);
    if (st != SVP_OK) drop_frame(b);
    return st;
}

svp_status svp_blur_set_view(svp_blur *b, int margin, int *applied)
{
    *applied = 0;
    if (!b || margin < 0)
        return svp_fail(SVP_ERR_INVALID, "svp_blur_set_view: no operator, or margin %d < 0",
                        margin);
    int view = 0; /* the margin whose frame is wanted, 0 for the full grid's */
    if (margin > 0 && b->kind == SVP_BLUR_INVARIANT && b->boundary == SVP_BOUNDARY_ZERO) {
        if (2 * margin >= b->width || 2 * margin >= b->height)
            return svp_fail(SVP_ERR_INVALID,
                            "svp_blur_set_view: a margin of %d pixels leaves no view of the %d "
                            "x %d grid",
                            margin, b->width, b->height);
        int nx = 0, ny = 0, vx = 0, vy = 0;
        SVP_CHECK(frame_dims(b, 0, &nx, &ny));
        SVP_CHECK(frame_dims(b, margin, &vx, &vy));
        if ((size_t)vx * vy < (size_t)nx * ny) view = margin; /* else nothing to gain */
    }
    if (view != b->view_margin) { /* the frame in use goes; the wanted one comes on first use */
        drop_frame(b);
        b->view_margin = view;
    }
    *applied = view > 0;
    return SVP_OK;
}

svp_status svp_blur_set_tail(svp_blur *blur, double tol)
{
    if (!blur || !(tol >= 0 && tol < 1))
        return svp_fail(SVP_ERR_INVALID, "svp_blur_set_tail: no operator, or tolerance %g not in "
                                         "[0, 1)",
                        tol);
    if (blur->kind != SVP_BLUR_INVARIANT || blur->boundary != SVP_BOUNDARY_ZERO) return SVP_OK;
    if (tol != blur->tail_tol) { /* the frame in use goes; the wanted one comes on first use */
        drop_frame(blur);
        blur->tail_tol = tol;
        blur->tail_for = 0;
    }
    return SVP_OK;
}

double svp_blur_tail_tol(const svp_blur *blur) { return blur ? blur->tail_tol : 0.0; }

svp_status svp_blur_tail_info(svp_blur *blur, int *step, int *split, double *error)
{
    if (!blur || !step || !split || !error)
        return svp_fail(SVP_ERR_INVALID, "svp_blur_tail_info: NULL argument");
    *step = 0;
    *split = 0;
    *error = 0;
    if (blur->kind != SVP_BLUR_INVARIANT) return svp_variant_tail_info(blur, step, split, error);
    if (!(blur->tail_tol > 0)) return SVP_OK;
    if (!blur->frame.plan) /* what svp_blur_ready would choose, without making the frame */
        return tail_choice(blur, step, split, error);
    if (blur->tail) {
        *step = svp_tail_step(blur->tail);
        *split = svp_tail_split(blur->tail);
        *error = svp_tail_error(blur->tail);
    }
    return SVP_OK;
}

svp_status svp_blur_set_precision(svp_blur *blur, int single)
{
    return svp_blur_set_single(blur, single != 0);
}

/* The float spectrum times the float OTF (adjoint: its conjugate). */
static void single_product(svp_blur *b, int adjoint)
{
    const size_t n = (size_t)b->frame.ny * b->frame.ncx;
    if (b->otf_f_real) /* the conjugate of a real OTF is itself */
        svp_spectrum_scale_f(b->otf_f, (float *)b->work_cf, n);
    else
        svp_spectrum_product_f(b->otf_f, (float *)b->work_cf, n, adjoint, 1.0f);
}

/* H (adjoint 0) or Hᵀ (1) of an invariant operator with float transforms: the image goes into
 * the float frame as svp_blur_spectrum_in places it (zero padding, E or Cᵀ), and comes back
 * as svp_blur_spectrum_out takes it (C or Eᵀ), converted on the way. */
static void apply_single(svp_blur *b, const double *restrict in, double *restrict out, int adjoint)
{
    const svp_frame *f = &b->frame;
    const svp_fftf_rows *p = b->rows_f;
    float *restrict fr = b->work_rf;
    if (b->boundary == SVP_BOUNDARY_ZERO)
        svp_frame_zero_load_f(f, p->rows, in, fr);
    else if (adjoint)
        svp_frame_embed_f(f, in, fr);
    else
        svp_frame_extend_f(f, in, fr);
    /* the tail from and into the float frame, as svp_blur_rows does it */
    if (b->tail) svp_tail_gather_f(b->tail, fr, (size_t)f->nx, adjoint);
    svp_fftf_forward_rows(p, fr, b->work_cf);
    single_product(b, adjoint);
    svp_fftf_inverse_rows_unscaled(p, b->work_cf, fr);
    if (b->tail) svp_tail_spread_f(b->tail, fr, (size_t)f->nx);
    if (adjoint && b->boundary != SVP_BOUNDARY_ZERO)
        svp_frame_fold_f(f, fr, out);
    else
        svp_frame_crop_f(f, fr, out);
}

/* ---- row-wise H and Hᵀ (svp_blur_rows) ------------------------------------------------------ */

/* _Pragma inside a macro is beyond clang-format: this block is laid out by hand */
/* clang-format off */
/* svp_blur_rows' two passes over a frame of element type FT in zero mode, each thread with its
 * own row of `stride` doubles in tmp: LOAD fills rows 0 .. height − 1 as svp_frame_zero_load
 * does from the rows `load` writes (chained: from the frame's own rows, converted as
 * svp_frame_crop does); STORE hands `store` the rows svp_frame_crop would give. */
#define SVP_ROWS_PASSES(LOAD, STORE, FT)                                                           \
    static void LOAD(const svp_frame *f, FT *restrict frame, int chained, svp_blur_row_fn load,    \
                     void *user, double *tmp, size_t stride)                                       \
    {                                                                                              \
        const int w = f->width, nx = f->nx;                                                        \
        _Pragma("omp parallel if (SVP_FRAME_BIG(f))")                                              \
        {                                                                                          \
            double *restrict row = tmp + stride * (size_t)omp_get_thread_num();                    \
            _Pragma("omp for schedule(static)")                                                    \
            for (int y = 0; y < f->height; y++) {                                                  \
                FT *out = frame + (size_t)y * nx;                                                  \
                if (chained)                                                                       \
                    for (int i = 0; i < w; i++) row[i] = (double)out[i];                           \
                load(user, y, row);                                                                \
                for (int i = 0; i < w; i++) out[i] = (FT)row[i];                                   \
                memset(out + w, 0, (size_t)(nx - w) * sizeof(FT));                                 \
            }                                                                                      \
        }                                                                                          \
    }                                                                                              \
    static void STORE(const svp_frame *f, const FT *restrict frame, svp_blur_row_fn store,         \
                      int every, void *user, double *tmp, size_t stride)                           \
    {                                                                                              \
        const int w = f->width, nx = f->nx;                                                        \
        _Pragma("omp parallel if (SVP_FRAME_BIG(f))")                                              \
        {                                                                                          \
            double *restrict row = tmp + stride * (size_t)omp_get_thread_num();                    \
            _Pragma("omp for schedule(static)")                                                    \
            for (int y = 0; y < f->height; y++) {                                                  \
                if (y % every) continue;                                                           \
                const FT *in = frame + (size_t)y * nx;                                             \
                for (int i = 0; i < w; i++) row[i] = (double)in[i];                                \
                store(user, y, row);                                                               \
            }                                                                                      \
        }                                                                                          \
    }

SVP_ROWS_PASSES(rows_load, rows_store, double)
SVP_ROWS_PASSES(rows_load_f, rows_store_f, float)
/* clang-format on */

int svp_blur_rows_ok(const svp_blur *b)
{
    return b && b->kind == SVP_BLUR_INVARIANT && b->boundary == SVP_BOUNDARY_ZERO && b->halo == 0;
}

/* The frame's transforms between svp_blur_rows' passes, as invariant_apply / _adjoint do them
 * in zero mode (rows height .. of the frame: none, or pruned). */
static void rows_transform(svp_blur *b, int adjoint)
{
    const svp_frame *f = &b->frame;
    if (b->single) {
        svp_fftf_forward_rows(b->rows_f, b->work_rf, b->work_cf);
        single_product(b, adjoint);
        svp_fftf_inverse_rows_unscaled(b->rows_f, b->work_cf, b->work_rf);
        return;
    }
    svp_frame_filter(f, b->pruned, b->work_r, b->work_c, adjoint);
}

svp_status svp_blur_rows(svp_blur *b, int adjoint, int chained, svp_blur_row_fn load,
                         svp_blur_row_fn store, int store_every, void *user)
{
    if (!svp_blur_rows_ok(b) || !load || store_every < 1)
        return svp_fail(SVP_ERR_INVALID, "svp_blur_rows: not an invariant zero-boundary operator "
                                         "without halo, or no load, or store_every < 1");
    SVP_CHECK(svp_blur_ready(b));
    if (chained && !b->rows_held)
        return svp_fail(SVP_ERR_INTERNAL, "svp_blur_rows: chained, but the frame does not hold "
                                          "the last output");
    const svp_frame *f = &b->frame;
    /* a 64-byte multiple per thread: the threads' rows share no cache line */
    const size_t stride = ((size_t)f->width + 7) & ~(size_t)7;
    double *tmp = svp_alloc(stride * (size_t)omp_get_max_threads() * sizeof(double));
    if (!tmp) return svp_fail(SVP_ERR_NOMEM, "svp_blur_rows: out of memory for row buffers");
    b->rows_held = 0;
    if (b->single)
        rows_load_f(f, b->work_rf, chained, load, user, tmp, stride);
    else
        rows_load(f, b->work_r, chained, load, user, tmp, stride);
    /* the tail's nodes from the input rows before the transforms overwrite them */
    if (b->tail && b->single)
        svp_tail_gather_f(b->tail, b->work_rf, (size_t)f->nx, adjoint);
    else if (b->tail)
        svp_tail_gather(b->tail, b->work_r, (size_t)f->nx, adjoint);
    rows_transform(b, adjoint);
    if (b->tail && b->single)
        svp_tail_spread_f(b->tail, b->work_rf, (size_t)f->nx);
    else if (b->tail)
        svp_tail_spread(b->tail, b->work_r, (size_t)f->nx);
    if (store && b->single)
        rows_store_f(f, b->work_rf, store, store_every, user, tmp, stride);
    else if (store)
        rows_store(f, b->work_r, store, store_every, user, tmp, stride);
    svp_free(tmp);
    b->rows_held = 1;
    return SVP_OK;
}

/* ---- the invariant representation ----------------------------------------------------- */

/* out += the tail's part of H in (adjoint: of Hᵀ), when the operator has one. */
static void add_tail(svp_blur *b, const double *in, double *out, int adjoint)
{
    if (!b->tail) return;
    svp_tail_gather(b->tail, in, (size_t)b->width, adjoint);
    svp_tail_spread(b->tail, out, (size_t)b->width);
}

/* H in (adjoint 0) or Hᵀ in (1): the frame's convolution, the tail's part and the halo. */
static svp_status invariant_run(svp_blur *b, const double *restrict in, double *restrict out,
                                int adjoint)
{
    SVP_CHECK(svp_blur_ready(b));
    b->rows_held = 0;
    if (b->single) {
        apply_single(b, in, out, adjoint); /* with the tail */
    } else {
        svp_frame *f = &b->frame;
        svp_blur_spectrum_in(b, in, adjoint);
        svp_frame_multiply(f, b->work_c, adjoint, 1.0 / ((double)f->nx * f->ny));
        svp_blur_spectrum_out(b, out, adjoint);
        add_tail(b, in, out, adjoint);
    }
    add_halo(b, in, out);
    return SVP_OK;
}

static svp_status invariant_apply(svp_blur *b, const double *restrict x, double *restrict y)
{
    return invariant_run(b, x, y, 0);
}

static svp_status invariant_adjoint(svp_blur *b, const double *restrict y, double *restrict x)
{
    return invariant_run(b, y, x, 1);
}

static size_t invariant_memory(const svp_blur *b)
{
    const size_t kernel =
        b->kernel_borrowed ? 0 : (size_t)b->kernel->width * b->kernel->height * sizeof(double);
    const svp_frame *f = &b->frame;
    if (!f->plan) return kernel; /* no frame made yet (svp_blur_ready) */
    /* the float frame, spectrum and OTF, once used */
    size_t single = 0;
    if (b->rows_f)
        single = (size_t)f->ny * f->nx * sizeof(float) +
                 (size_t)f->ny * f->ncx * (sizeof(fftwf_complex) + sizeof(float) *
                                                                 (b->otf_f_real ? 1 : 2));
    const size_t core = b->core ? (size_t)b->core->width * b->core->height * sizeof(double) : 0;
    return svp_frame_memory(f) + (size_t)f->ny * f->nx * sizeof(double) +
           (size_t)f->ny * f->ncx * sizeof(fftw_complex) + kernel + single + core +
           svp_tail_memory(b->tail);
}

static void invariant_release(svp_blur *b) { (void)b; }

const svp_blur_ops svp_invariant_ops = {"invariant",      invariant_apply,   invariant_adjoint,
                                        invariant_memory, invariant_release, NULL};

svp_status svp_blur_apply(svp_blur *b, const svp_image *x, svp_image *y)
{
    SVP_CHECK(check_io(b, x, y, "svp_blur_apply"));
    return b->ops->apply(b, x->data, y->data);
}

svp_status svp_blur_adjoint(svp_blur *b, const svp_image *y, svp_image *x)
{
    SVP_CHECK(check_io(b, y, x, "svp_blur_adjoint"));
    return b->ops->adjoint(b, y->data, x->data);
}
