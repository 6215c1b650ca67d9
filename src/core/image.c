/* svp_image: aligned row-major doubles, and deterministic reductions. */
#include "internal.h"

#include <math.h>
#include <omp.h>
#include <stdlib.h>
#include <stdint.h>
#include <string.h>

void *svp_alloc(size_t bytes)
{
    void *p = NULL;
    /* round up so vector loops may read a whole last cache line */
    size_t rounded = (bytes + SVP_ALIGN - 1) / SVP_ALIGN * SVP_ALIGN;
    if (posix_memalign(&p, SVP_ALIGN, rounded ? rounded : SVP_ALIGN) != 0) return NULL;
    return p;
}

void *svp_calloc(size_t count, size_t size)
{
    if (size && count > SIZE_MAX / size) return NULL;
    void *p = svp_alloc(count * size);
    if (p) memset(p, 0, count * size);
    return p;
}

void svp_free(void *p)
{
    free(p);
}

svp_status svp_image_new(int width, int height, svp_image **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_image_new: out is NULL");
    *out = NULL;
    if (width < 1 || height < 1)
        return svp_fail(SVP_ERR_INVALID, "image size %d x %d: both must be at least 1", width,
                        height);
    if ((size_t)width > SIZE_MAX / sizeof(double) / (size_t)height)
        return svp_fail(SVP_ERR_NOMEM, "image size %d x %d is too large", width, height);
    svp_image *img = malloc(sizeof *img);
    if (!img) return svp_fail(SVP_ERR_NOMEM, "out of memory for an image header");
    img->width = width;
    img->height = height;
    img->data = svp_calloc((size_t)width * (size_t)height, sizeof(double));
    if (!img->data) {
        free(img);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d image", width, height);
    }
    *out = img;
    return SVP_OK;
}

svp_status svp_image_copy(const svp_image *src, svp_image **out)
{
    if (!src) return svp_fail(SVP_ERR_INVALID, "svp_image_copy: source is NULL");
    SVP_CHECK(svp_image_new(src->width, src->height, out));
    memcpy((*out)->data, src->data, (size_t)src->width * src->height * sizeof(double));
    return SVP_OK;
}

void svp_image_free(svp_image *image)
{
    if (!image) return;
    svp_free(image->data);
    free(image);
}

svp_status svp_image_same_size(const svp_image *a, const svp_image *b, const char *what_a,
                               const char *what_b)
{
    if (!a || !b)
        return svp_fail(SVP_ERR_INVALID, "%s is missing", !a ? what_a : what_b);
    if (a->width != b->width || a->height != b->height)
        return svp_fail(SVP_ERR_SIZE, "%s is %d x %d but %s is %d x %d", what_a, a->width,
                        a->height, what_b, b->width, b->height);
    return SVP_OK;
}

svp_status svp_image_check_scale(const svp_image *image, const char *what)
{
    if (!image || !image->data) return svp_fail(SVP_ERR_INVALID, "%s is NULL", what);
    const double top = svp_max_abs(image->data, (size_t)image->width * image->height);
    if (top == 0 || (top >= SVP_VALUE_MIN && top <= SVP_VALUE_MAX)) return SVP_OK;
    return svp_fail(SVP_ERR_INVALID,
                    "%s: its largest |value| %.3g lies outside [%g, %g], where the solvers' sums "
                    "of squares %s; rescale it (other units)",
                    what, top, SVP_VALUE_MIN, SVP_VALUE_MAX,
                    top < SVP_VALUE_MIN ? "underflow" : "overflow");
}

size_t svp_image_count_nonfinite(const svp_image *image)
{
    size_t n = (size_t)image->width * image->height, count = 0;
    for (size_t i = 0; i < n; i++) count += !isfinite(image->data[i]);
    return count;
}

/* Fixed-size blocks make the summation order independent of the thread count. */
#define SUM_BLOCK 4096

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* svp_fill_nan (internal.h) */
svp_status svp_fill_nan(double *restrict v, int w, int h, int max_passes, double fallback)
{
    const size_t n = (size_t)w * h;
    double *prev = svp_alloc(n * sizeof(double));
    if (!prev) return svp_fail(SVP_ERR_NOMEM, "out of memory filling missing pixels");
    for (int pass = 0; pass < max_passes; pass++) {
        memcpy(prev, v, n * sizeof(double));
        size_t left = 0;
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                if (!isnan(prev[(size_t)y * w + x])) continue;
                double sum = 0;
                int count = 0;
                for (int j = y - 1; j <= y + 1; j++)
                    for (int i = x - 1; i <= x + 1; i++)
                        if (i >= 0 && i < w && j >= 0 && j < h &&
                            !isnan(prev[(size_t)j * w + i])) {
                            sum += prev[(size_t)j * w + i];
                            count++;
                        }
                if (count)
                    v[(size_t)y * w + x] = sum / count;
                else
                    left++;
            }
        if (!left) break;
    }
    for (size_t i = 0; i < n; i++)
        if (isnan(v[i])) v[i] = fallback;
    svp_free(prev);
    return SVP_OK;
}

double svp_median(double *v, size_t n)
{
    qsort(v, n, sizeof *v, cmp_double);
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

double svp_sum(const double *restrict x, size_t n)
{
    size_t nblocks = (n + SUM_BLOCK - 1) / SUM_BLOCK;
    if (nblocks <= 1) {
        double s = 0;
        for (size_t i = 0; i < n; i++) s += x[i];
        return s;
    }
    double *partial = malloc(nblocks * sizeof *partial);
    if (!partial) { /* fall back to a serial sum in the same block order */
        double s = 0;
        for (size_t b = 0; b < nblocks; b++) {
            double sb = 0;
            size_t end = (b + 1) * SUM_BLOCK < n ? (b + 1) * SUM_BLOCK : n;
            for (size_t i = b * SUM_BLOCK; i < end; i++) sb += x[i];
            s += sb;
        }
        return s;
    }
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (size_t b = 0; b < nblocks; b++) {
        double sb = 0;
        size_t end = (b + 1) * SUM_BLOCK < n ? (b + 1) * SUM_BLOCK : n;
        for (size_t i = b * SUM_BLOCK; i < end; i++) sb += x[i];
        partial[b] = sb;
    }
    double s = 0;
    for (size_t b = 0; b < nblocks; b++) s += partial[b];
    free(partial);
    return s;
}

double svp_dot(const double *a, const double *b, double *restrict prod, size_t n)
{
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (size_t i = 0; i < n; i++) prod[i] = a[i] * b[i];
    return svp_sum(prod, n);
}

/* Block b's m sums Σ a_j b_j in index order (svp_sum's order within a block). */
static void dots_block(const double *const *a, const double *const *b, int m, size_t i0,
                       size_t i1, double *out)
{
    for (int j = 0; j < m; j++) {
        const double *restrict x = a[j], *restrict y = b[j];
        double s = 0;
        for (size_t i = i0; i < i1; i++) s += x[i] * y[i];
        out[j] = s;
    }
}

void svp_dots(const double *const *a, const double *const *b, int m, size_t n, double *out)
{
    const size_t nblocks = n ? (n + SUM_BLOCK - 1) / SUM_BLOCK : 1;
    double *partial = nblocks > 1 ? malloc(nblocks * (size_t)m * sizeof *partial) : NULL;
    if (!partial) { /* one block, or no room: serially, in the same block order */
        for (int j = 0; j < m; j++) out[j] = 0;
        for (size_t blk = 0; blk < nblocks; blk++) {
            double sb[SVP_DOTS_MAX];
            const size_t end = (blk + 1) * SUM_BLOCK < n ? (blk + 1) * SUM_BLOCK : n;
            dots_block(a, b, m, blk * SUM_BLOCK, end, sb);
            for (int j = 0; j < m; j++) out[j] += sb[j]; /* 0 + s is s: svp_sum's sums */
        }
        return;
    }
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (size_t blk = 0; blk < nblocks; blk++) {
        const size_t end = (blk + 1) * SUM_BLOCK < n ? (blk + 1) * SUM_BLOCK : n;
        dots_block(a, b, m, blk * SUM_BLOCK, end, partial + blk * (size_t)m);
    }
    for (int j = 0; j < m; j++) {
        double s = 0;
        for (size_t blk = 0; blk < nblocks; blk++) s += partial[blk * (size_t)m + j];
        out[j] = s;
    }
    free(partial);
}

double svp_max(const double *restrict x, size_t n)
{
    double m = -INFINITY;
    for (size_t i = 0; i < n; i++)
        if (isfinite(x[i]) && x[i] > m) m = x[i];
    return m;
}

double svp_max_abs(const double *restrict x, size_t n)
{
    double m = 0;
    for (size_t i = 0; i < n; i++)
        if (isfinite(x[i]) && fabs(x[i]) > m) m = fabs(x[i]);
    return m;
}

int svp_unit_exponent(const double *restrict x, size_t n, int bits)
{
    const double top = svp_max_abs(x, n);
    if (top == 0 || (top >= ldexp(1.0, -bits) && top <= ldexp(1.0, bits))) return 0;
    return -ilogb(top);
}

double svp_min(const double *restrict x, size_t n)
{
    double m = INFINITY;
    for (size_t i = 0; i < n; i++)
        if (isfinite(x[i]) && x[i] < m) m = x[i];
    return m;
}

/* Hoare's quickselect: O(n), so the statistics of a 10⁶-pixel mask need no sort. */
double svp_select_kth(double *a, size_t n, size_t k)
{
    ptrdiff_t lo = 0, hi = (ptrdiff_t)n - 1, kk = (ptrdiff_t)k;
    while (lo < hi) {
        double pivot = a[lo + (hi - lo) / 2];
        ptrdiff_t i = lo, j = hi;
        while (i <= j) {
            while (a[i] < pivot) i++;
            while (a[j] > pivot) j--;
            if (i <= j) {
                double t = a[i];
                a[i] = a[j];
                a[j] = t;
                i++;
                j--;
            }
        }
        if (kk <= j)
            hi = j;
        else if (kk >= i)
            lo = i;
        else
            break;
    }
    return a[kk];
}
