/* The space-invariant blur operator: against a direct sum, adjointness, flux, linearity; FFT
 * planning (the plan callback) and wisdom files. */
#include "test_helpers.h"

#include "blur/blur_internal.h"

#include <dirent.h>
#include <sys/stat.h>
#include <unistd.h>

static const svp_boundary modes[] = {SVP_BOUNDARY_ZERO, SVP_BOUNDARY_MIRROR, SVP_BOUNDARY_PERIODIC};
static const char *mode_names[] = {"zero", "mirror", "periodic"};

static int reflect_ref(int t, int n)
{
    /* symmetric extension by repeated unfolding, written independently of operator.c */
    while (t < 0 || t >= n) t = t < 0 ? -t - 1 : 2 * n - 1 - t;
    return t;
}

static double ext_value(const svp_image *x, int i, int j, svp_boundary b)
{
    int w = x->width, h = x->height;
    switch (b) {
    case SVP_BOUNDARY_ZERO:
        if (i < 0 || j < 0 || i >= w || j >= h) return 0;
        break;
    case SVP_BOUNDARY_PERIODIC:
        i = ((i % w) + w) % w;
        j = ((j % h) + h) % h;
        break;
    case SVP_BOUNDARY_MIRROR:
        i = reflect_ref(i, w);
        j = reflect_ref(j, h);
        break;
    }
    return x->data[(size_t)j * w + i];
}

/* y(i) = Σ_d k(d) x_ext(i − d) + halo, summed directly. */
static void direct_blur(const svp_image *k, int cx, int cy, double halo, const svp_image *x,
                        svp_boundary b, svp_image *y)
{
    double mean = test_sum(x) / ((double)x->width * x->height);
    for (int j = 0; j < x->height; j++)
        for (int i = 0; i < x->width; i++) {
            double s = 0;
            for (int v = 0; v < k->height; v++)
                for (int u = 0; u < k->width; u++)
                    s += k->data[(size_t)v * k->width + u] *
                         ext_value(x, i - (u - cx), j - (v - cy), b);
            y->data[(size_t)j * x->width + i] = (1 - halo) * s + halo * mean;
        }
}

static void test_matches_direct_sum(void **state)
{
    (void)state;
    const int sizes[][2] = {{1, 1}, {2, 3}, {7, 5}, {16, 9}, {13, 13}};
    for (size_t s = 0; s < sizeof sizes / sizeof sizes[0]; s++) {
        int w = sizes[s][0], h = sizes[s][1];
        for (int m = 0; m < 3; m++) {
            /* an asymmetric random kernel, larger than the image in one case */
            for (int big = 0; big < 2; big++) {
                int kw = big ? 2 * w + 3 : 5, kh = big ? 2 * h + 1 : 3;
                svp_image *k = test_random_image(kw, kh, 7 + s);
                svp_image *x = test_random_image(w, h, 11 + s);
                svp_image *y = test_image(w, h), *ref = test_image(w, h);
                svp_blur *op = NULL;
                int cx = kw / 2 - (big ? 1 : 0), cy = kh / 2;
                ASSERT_OK(svp_blur_new_kernel(k, cx, cy, 0, w, h, modes[m], &op));
                ASSERT_OK(svp_blur_apply(op, x, y));
                direct_blur(k, cx, cy, 0, x, modes[m], ref);
                double err = test_max_abs_diff(y, ref);
                if (err > 1e-12 * (1 + test_max_abs(ref)))
                    fail_msg("%s %dx%d kernel %dx%d: max error %.3g", mode_names[m], w, h, kw, kh,
                             err);
                svp_blur_free(op);
                svp_image_free(k);
                svp_image_free(x);
                svp_image_free(y);
                svp_image_free(ref);
            }
        }
    }
}

static void test_adjoint_identity(void **state)
{
    (void)state;
    const int sizes[][2] = {{1, 1}, {2, 3}, {31, 17}, {64, 48}};
    for (size_t s = 0; s < sizeof sizes / sizeof sizes[0]; s++) {
        int w = sizes[s][0], h = sizes[s][1];
        for (int m = 0; m < 3; m++) {
            svp_psf psf;
            svp_psf_defaults(&psf);
            psf.model = SVP_PSF_MOFFAT;
            psf.fwhm = 3.5;
            psf.fwhm_minor = 2.0;
            psf.angle = 0.4;
            psf.beta = 1.1;
            psf.halo = 0.3;
            svp_blur *op = NULL;
            ASSERT_OK(svp_blur_new(&psf, w, h, modes[m], &op));
            svp_image *x = test_random_image(w, h, 3), *y = test_random_image(w, h, 5);
            svp_image *hx = test_image(w, h), *hty = test_image(w, h);
            ASSERT_OK(svp_blur_apply(op, x, hx));
            ASSERT_OK(svp_blur_adjoint(op, y, hty));
            double a = test_dot(hx, y), b = test_dot(x, hty);
            if (fabs(a - b) > 1e-12 * fabs(a))
                fail_msg("%s %dx%d: <Hx,y> = %.17g, <x,H'y> = %.17g", mode_names[m], w, h, a, b);
            svp_blur_free(op);
            svp_image_free(x);
            svp_image_free(y);
            svp_image_free(hx);
            svp_image_free(hty);
        }
    }
}

/* Periodic and mirror operators keep all light in the image; zero keeps it when the source is
 * far from the edges (with a kernel support that stays inside). */
static void test_unit_flux(void **state)
{
    (void)state;
    const int w = 40, h = 30;
    for (int m = 0; m < 3; m++) {
        svp_psf psf;
        svp_psf_defaults(&psf);
        psf.model = SVP_PSF_LORENTZIAN;
        psf.fwhm = 2.5;
        psf.halo = 0.5;
        if (modes[m] == SVP_BOUNDARY_ZERO) psf.support = 9;
        svp_blur *op = NULL;
        ASSERT_OK(svp_blur_new(&psf, w, h, modes[m], &op));
        svp_image *x = test_image(w, h), *y = test_image(w, h);
        x->data[15 * w + 20] = 1.0;
        ASSERT_OK(svp_blur_apply(op, x, y));
        ASSERT_CLOSE(test_sum(y), 1.0, 1e-12);
        for (size_t i = 0; i < (size_t)w * h; i++)
            if (y->data[i] < -1e-15) fail_msg("%s: negative output %g", mode_names[m], y->data[i]);
        svp_blur_free(op);
        svp_image_free(x);
        svp_image_free(y);
    }
}

static void test_linearity_and_delta(void **state)
{
    (void)state;
    const int w = 23, h = 19;
    svp_image *x1 = test_random_image(w, h, 1), *x2 = test_random_image(w, h, 2);
    svp_image *comb = test_image(w, h), *y1 = test_image(w, h), *y2 = test_image(w, h),
              *yc = test_image(w, h);
    for (size_t i = 0; i < (size_t)w * h; i++)
        comb->data[i] = 2.5 * x1->data[i] - 0.75 * x2->data[i];
    for (int m = 0; m < 3; m++) {
        svp_psf psf;
        svp_psf_defaults(&psf);
        psf.model = SVP_PSF_GAUSSIAN;
        psf.fwhm = 4;
        svp_blur *op = NULL;
        ASSERT_OK(svp_blur_new(&psf, w, h, modes[m], &op));
        ASSERT_OK(svp_blur_apply(op, x1, y1));
        ASSERT_OK(svp_blur_apply(op, x2, y2));
        ASSERT_OK(svp_blur_apply(op, comb, yc));
        for (size_t i = 0; i < (size_t)w * h; i++)
            ASSERT_CLOSE(yc->data[i], 2.5 * y1->data[i] - 0.75 * y2->data[i], 1e-13);
        svp_blur_free(op);
        /* a 1x1 kernel is the identity */
        svp_image *delta = test_image(1, 1);
        delta->data[0] = 1;
        ASSERT_OK(svp_blur_new_kernel(delta, -1, -1, 1, w, h, modes[m], &op));
        ASSERT_OK(svp_blur_apply(op, x1, y1));
        assert_true(test_max_abs_diff(y1, x1) < 1e-14);
        svp_blur_free(op);
        svp_image_free(delta);
    }
    svp_image_free(x1);
    svp_image_free(x2);
    svp_image_free(comb);
    svp_image_free(y1);
    svp_image_free(y2);
    svp_image_free(yc);
}

static void test_bad_arguments(void **state)
{
    (void)state;
    svp_psf psf;
    svp_psf_defaults(&psf);
    svp_blur *op = NULL;
    assert_int_equal(svp_blur_new(&psf, 0, 5, SVP_BOUNDARY_ZERO, &op), SVP_ERR_INVALID);
    psf.fwhm = -1;
    assert_int_equal(svp_blur_new(&psf, 5, 5, SVP_BOUNDARY_ZERO, &op), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "FWHM"));
    svp_psf_defaults(&psf);
    ASSERT_OK(svp_blur_new(&psf, 8, 8, SVP_BOUNDARY_ZERO, &op));
    svp_image *x = test_image(8, 8), *y = test_image(7, 8);
    assert_int_equal(svp_blur_apply(op, x, y), SVP_ERR_SIZE);
    assert_int_equal(svp_blur_apply(op, x, x), SVP_ERR_INVALID);
    svp_blur_free(op);
    /* a kernel summing to -0.5 cannot be normalised (it was, by -2: a PSF of flipped sign that
     * made fields 8 times the input's largest); unnormalised it is the caller's */
    svp_image *k = test_image(3, 3);
    for (int i = 0; i < 9; i++) k->data[i] = i == 4 ? 7.5 : -1.0;
    op = NULL;
    assert_int_equal(svp_blur_new_kernel(k, -1, -1, 1, 8, 8, SVP_BOUNDARY_ZERO, &op),
                     SVP_ERR_INVALID);
    assert_null(op);
    assert_non_null(strstr(svp_last_error(), "kernel sums to -0.5: it cannot be normalised"));
    ASSERT_OK(svp_blur_new_kernel(k, -1, -1, 0, 8, 8, SVP_BOUNDARY_ZERO, &op));
    svp_blur_free(op);
    svp_image_free(k);
    svp_image_free(x);
    svp_image_free(y);
}

/* A point-symmetric kernel (k(d) = k(−d)) has a real OTF, which the operator keeps as real
 * parts only (half the memory and product traffic); an asymmetric one keeps its complex OTF.
 * Both still match the direct sum (and the adjoint identity) in every boundary mode. */
static void test_real_otf(void **state)
{
    (void)state;
    const int w = 13, h = 10, kw = 7, kh = 5;
    for (int sym = 0; sym < 2; sym++) {
        svp_image *k = test_random_image(kw, kh, 21);
        const size_t m = (size_t)kw * kh;
        if (sym)
            for (size_t i = 0; i < m / 2; i++) k->data[m - 1 - i] = k->data[i];
        svp_image *x = test_random_image(w, h, 22), *yv = test_random_image(w, h, 23);
        svp_image *y = test_image(w, h), *ref = test_image(w, h), *xt = test_image(w, h);
        for (int mo = 0; mo < 3; mo++) {
            svp_blur *op = NULL;
            ASSERT_OK(svp_blur_new_kernel(k, kw / 2, kh / 2, 0, w, h, modes[mo], &op));
            ASSERT_OK(svp_blur_ready(op));
            if (sym ? !op->frame.otf_re || op->frame.otf : op->frame.otf_re || !op->frame.otf)
                fail_msg("%s, %s kernel: otf_re %p, otf %p", mode_names[mo],
                         sym ? "symmetric" : "asymmetric", (void *)op->frame.otf_re,
                         (void *)op->frame.otf);
            ASSERT_OK(svp_blur_apply(op, x, y));
            direct_blur(k, kw / 2, kh / 2, 0, x, modes[mo], ref);
            ASSERT_CLOSE(test_max_abs_diff(y, ref) / test_max_abs(ref), 0, 1e-13);
            ASSERT_OK(svp_blur_adjoint(op, yv, xt));
            const double a = test_dot(y, yv), b = test_dot(x, xt);
            ASSERT_CLOSE(a, b, 1e-12 * fabs(a));
            svp_blur_free(op);
        }
        svp_image_free(k);
        svp_image_free(x);
        svp_image_free(yv);
        svp_image_free(y);
        svp_image_free(ref);
        svp_image_free(xt);
    }
}

/* The bytes an invariant operator's frame in use holds (svp_blur_memory's count, re-derived):
 * its geometry and OTF, the double work frame and spectrum, the float ones and float OTF when
 * single precision was used, and the kernel. */
static size_t frame_bytes(const svp_blur *op)
{
    const svp_frame *f = &op->frame;
    const size_t cells = (size_t)f->ny * f->nx, spectrum = (size_t)f->ny * f->ncx;
    size_t bytes = svp_frame_memory(f) + cells * sizeof(double) + spectrum * sizeof(fftw_complex);
    if (op->rows_f)
        bytes += cells * sizeof(float) + spectrum * sizeof(fftwf_complex) +
                 spectrum * sizeof(float) * (op->otf_f_real ? 1 : 2);
    return bytes + (size_t)op->kernel->width * op->kernel->height * sizeof(double);
}

/* An operator makes its frame on first use, for the view when svp_blur_set_view came first: a
 * whole-grid kernel on 23 x 17 used only on the view 3 pixels in (single and double, H and Hᵀ)
 * makes one frame, the view's 40 x 28 (the full one is 48 x 36: even sizes), and
 * svp_blur_memory counts that frame only, less than an operator used on the full grid; margin 0
 * frees it, and the next use makes the full frame, whose H x is bit-identical to a fresh
 * operator's. */
static void test_view_only_frame(void **state)
{
    (void)state;
    const int w = 23, h = 17, kw = 2 * w - 1, kh = 2 * h - 1, m = 3;
    svp_image *k = test_random_image(kw, kh, 41), *x = test_random_image(w, h, 42);
    svp_image *y = test_image(w, h), *xt = test_image(w, h), *ref = test_image(w, h);
    const size_t kernel_bytes = (size_t)kw * kh * sizeof(double);
    svp_blur *full = NULL, *op = NULL;
    ASSERT_OK(svp_blur_new_kernel(k, kw / 2, kh / 2, 1, w, h, SVP_BOUNDARY_ZERO, &full));
    ASSERT_OK(svp_blur_apply(full, x, ref));
    ASSERT_OK(svp_blur_set_single(full, 1));
    assert_true(full->frame.nx == 48 && full->frame.ny == 36 && full->frames_built == 1);
    ASSERT_OK(svp_blur_new_kernel(k, kw / 2, kh / 2, 1, w, h, SVP_BOUNDARY_ZERO, &op));
    assert_true(!op->frame.plan && op->frames_built == 0);
    assert_true(svp_blur_memory(op) == kernel_bytes); /* nothing made yet */
    int applied = -1;
    ASSERT_OK(svp_blur_set_view(op, m, &applied));
    assert_int_equal(applied, 1);
    assert_int_equal(op->frames_built, 0);
    ASSERT_OK(svp_blur_set_single(op, 1));
    ASSERT_OK(svp_blur_apply(op, x, y));
    ASSERT_OK(svp_blur_adjoint(op, x, xt));
    ASSERT_OK(svp_blur_set_single(op, 0));
    ASSERT_OK(svp_blur_apply(op, x, y));
    ASSERT_OK(svp_blur_adjoint(op, x, xt));
    assert_int_equal(op->frames_built, 1);
    assert_true(op->frame.nx == 40 && op->frame.ny == 28 && op->rows_f);
    assert_true(svp_blur_memory(op) == frame_bytes(op));
    assert_true(svp_blur_memory(op) < svp_blur_memory(full));
    ASSERT_OK(svp_blur_set_view(op, 0, &applied));
    assert_int_equal(applied, 0);
    assert_true(!op->frame.plan && svp_blur_memory(op) == kernel_bytes);
    ASSERT_OK(svp_blur_apply(op, x, y));
    assert_int_equal(op->frames_built, 2);
    assert_true(op->frame.nx == 48 && op->frame.ny == 36);
    assert_true(svp_blur_memory(op) == frame_bytes(op));
    assert_true(memcmp(y->data, ref->data, (size_t)w * h * sizeof(double)) == 0);
    svp_blur_free(full);
    svp_blur_free(op);
    svp_image_free(k);
    svp_image_free(x);
    svp_image_free(y);
    svp_image_free(xt);
    svp_image_free(ref);
}

/* svp_blur_rows' callbacks for the tests: load copies the rows of `in` (chained: keeps the row
 * it is given, and records that it arrived holding `expect`'s row), store copies into `out` and
 * counts the rows it saw */
typedef struct rows_ctx {
    const svp_image *in, *expect;
    svp_image *out;
    int stored, chained_ok;
} rows_ctx;

static void rows_load(void *user, int y, double *restrict row)
{
    rows_ctx *c = user;
    const int w = c->out->width;
    if (c->expect) {
        if (memcmp(row, c->expect->data + (size_t)y * w, (size_t)w * sizeof(double)))
#pragma omp atomic write
            c->chained_ok = 0;
        return;
    }
    memcpy(row, c->in->data + (size_t)y * w, (size_t)w * sizeof(double));
}

static void rows_store(void *user, int y, double *restrict row)
{
    rows_ctx *c = user;
    const int w = c->out->width;
    memcpy(c->out->data + (size_t)y * w, row, (size_t)w * sizeof(double));
#pragma omp atomic
    c->stored++;
}

/* svp_blur_rows is bit-identical to svp_blur_apply / _adjoint (zero boundary, with the view's
 * pruned frame and without, symmetric and asymmetric kernels, double and single precision, on
 * 1 and 2 threads); chained, Hᵀ receives H's output rows from the frame and Hᵀ H x is
 * bit-identical to the two calls; store_every stores only those rows; chained after another
 * use of the frame is SVP_ERR_INTERNAL; mirror and halo operators are refused. */
static void test_blur_rows(void **state)
{
    (void)state;
    const int w = 23, h = 17, kw = 2 * w - 1, kh = 2 * h - 1;
    const size_t bytes = (size_t)w * h * sizeof(double);
    svp_image *x = test_random_image(w, h, 51), *ref = test_image(w, h), *ref2 = test_image(w, h);
    svp_image *out = test_image(w, h), *out2 = test_image(w, h);
    const int threads = svp_get_threads();
    for (int sym = 0; sym < 2; sym++) {
        svp_image *k = test_random_image(kw, kh, 52);
        const size_t m = (size_t)kw * kh;
        if (sym)
            for (size_t i = 0; i < m / 2; i++) k->data[m - 1 - i] = k->data[i];
        for (int variant = 0; variant < 4; variant++) {
            const int single = variant & 1, view = variant >> 1;
            svp_set_threads(1 + (variant + sym) % 2);
            svp_blur *op = NULL;
            ASSERT_OK(svp_blur_new_kernel(k, kw / 2, kh / 2, 1, w, h, SVP_BOUNDARY_ZERO, &op));
            assert_true(svp_blur_rows_ok(op));
            int applied = 0;
            if (view) ASSERT_OK(svp_blur_set_view(op, 3, &applied));
            ASSERT_OK(svp_blur_set_single(op, single));
            for (int adjoint = 0; adjoint < 2; adjoint++) {
                rows_ctx c = {x, NULL, out, 0, 1};
                ASSERT_OK(adjoint ? svp_blur_adjoint(op, x, ref) : svp_blur_apply(op, x, ref));
                ASSERT_OK(svp_blur_rows(op, adjoint, 0, rows_load, rows_store, 1, &c));
                assert_int_equal(c.stored, h);
                if (memcmp(out->data, ref->data, bytes))
                    fail_msg("rows differ from %s: symmetric %d, single %d, view %d",
                             adjoint ? "adjoint" : "apply", sym, single, view);
            }
            /* chained: Hᵀ H x, H's output stored every 4th row only */
            ASSERT_OK(svp_blur_apply(op, x, ref));
            ASSERT_OK(svp_blur_adjoint(op, ref, ref2));
            rows_ctx c = {x, NULL, out, 0, 1};
            memset(out->data, 0, bytes);
            ASSERT_OK(svp_blur_rows(op, 0, 0, rows_load, rows_store, 4, &c));
            assert_int_equal(c.stored, (h + 3) / 4);
            for (int y = 0; y < h; y++)
                for (int i = 0; i < w; i++) {
                    const size_t at = (size_t)y * w + i;
                    assert_true(y % 4 ? out->data[at] == 0 : out->data[at] == ref->data[at]);
                }
            rows_ctx c2 = {NULL, ref, out2, 0, 1};
            ASSERT_OK(svp_blur_rows(op, 1, 1, rows_load, rows_store, 1, &c2));
            assert_true(c2.chained_ok && c2.stored == h);
            assert_true(memcmp(out2->data, ref2->data, bytes) == 0);
            /* the frame used since: no chaining */
            ASSERT_OK(svp_blur_apply(op, x, ref));
            assert_int_equal(svp_blur_rows(op, 1, 1, rows_load, rows_store, 1, &c2),
                             SVP_ERR_INTERNAL);
            svp_blur_free(op);
        }
        svp_image_free(k);
    }
    svp_set_threads(threads);
    svp_blur *op = NULL;
    svp_image *k = test_random_image(5, 5, 53);
    ASSERT_OK(svp_blur_new_kernel(k, 2, 2, 1, w, h, SVP_BOUNDARY_MIRROR, &op));
    rows_ctx c = {x, NULL, out, 0, 1};
    assert_false(svp_blur_rows_ok(op));
    assert_int_equal(svp_blur_rows(op, 0, 0, rows_load, rows_store, 1, &c), SVP_ERR_INVALID);
    svp_blur_free(op);
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.halo = 0.1;
    ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_ZERO, &op));
    assert_false(svp_blur_rows_ok(op));
    svp_blur_free(op);
    svp_image_free(k);
    svp_image_free(x);
    svp_image_free(ref);
    svp_image_free(ref2);
    svp_image_free(out);
    svp_image_free(out2);
}

/* The ℓ1 norm of column `at` of H_tail − H (the responses to a unit pixel), over the rows
 * `rows` (1: all; else only the view `margin` in), per unit of the kernel's flux. */
static double tail_column_error(svp_blur *plain, svp_blur *tail, int at, int margin)
{
    const int w = plain->width, h = plain->height;
    svp_image *d = test_image(w, h), *a = test_image(w, h), *b = test_image(w, h);
    d->data[at] = 1;
    ASSERT_OK(svp_blur_apply(plain, d, a));
    ASSERT_OK(svp_blur_apply(tail, d, b));
    double e = 0;
    for (int y = margin; y < h - margin; y++)
        for (int x = margin; x < w - margin; x++) {
            const size_t i = (size_t)y * w + x;
            e += fabs(a->data[i] - b->data[i]);
            assert_true(b->data[i] >= -1e-15); /* non-negative for a non-negative kernel */
        }
    svp_image_free(d);
    svp_image_free(a);
    svp_image_free(b);
    double flux = 0;
    const size_t n = (size_t)plain->kernel->width * plain->kernel->height;
    for (size_t i = 0; i < n; i++) flux += fabs(plain->kernel->data[i]);
    return e / flux;
}

/* svp_blur_set_tail: the PSF's far tail on a coarse grid (docs/model.md §5). A β 1.1 Moffat
 * with whole-field support (every offset the grid uses: the tail is continued beyond the
 * kernel) and one truncated at radius 280 (its edge counted): the tail is taken, its measured
 * ‖ΔH‖₁ per unit flux for unit pixels at every phase against the nodes, at the edges and
 * corners, on the whole grid and on a view, is at most the estimate (and the estimate at most
 * the tolerance); Hᵀ is H's adjoint to round-off; svp_blur_rows gives apply's result bit for
 * bit in double and single precision, single within 1e-5 of double, 1 and 2 threads the same
 * bits (also with the passes threaded, from 2^20 pixels); the tolerance 0 brings the plain
 * frame back; bad tolerances and other boundaries. */
static void test_tail(void **state)
{
    (void)state;
    const int w = 300, h = 260, threads = svp_get_threads();
    svp_image *x = test_random_image(w, h, 71), *y = test_random_image(w, h, 72);
    svp_image *hx = test_image(w, h), *hty = test_image(w, h), *ref = test_image(w, h);
    svp_image *out = test_image(w, h);
    const size_t bytes = (size_t)w * h * sizeof(double);
    for (int kind = 0; kind < 2; kind++) {
        for (int margin = 0; margin <= 20; margin += 20) {
            svp_psf psf;
            svp_psf_defaults(&psf);
            psf.model = SVP_PSF_MOFFAT;
            psf.fwhm = 4;
            psf.beta = 1.1;
            if (kind) psf.support = 280;
            svp_blur *plain = NULL, *tail = NULL;
            ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_ZERO, &plain));
            ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_ZERO, &tail));
            int applied = 0;
            if (margin) {
                ASSERT_OK(svp_blur_set_view(plain, margin, &applied));
                ASSERT_OK(svp_blur_set_view(tail, margin, &applied));
            }
            const double tol = 3e-3;
            ASSERT_OK(svp_blur_set_tail(tail, tol));
            int step = 0, split = 0;
            double est = 0;
            ASSERT_OK(svp_blur_tail_info(tail, &step, &split, &est));
            if (step == 0) fail_msg("no tail taken: kind %d, margin %d", kind, margin);
            assert_true(est > 0 && est <= tol);
            /* the chooser's estimate is svp_tail_estimate's for the pair it took */
            ASSERT_CLOSE(svp_tail_estimate(tail->kernel, tail->kcx, tail->kcy, w, h, margin, step,
                                           split),
                         est, 1e-12 * est);
            ASSERT_OK(svp_blur_ready(tail));
            assert_true((size_t)tail->frame.nx * tail->frame.ny <
                        (size_t)(plain->frame.nx ? plain->frame.nx : 2 * w) * 2 * h);
            double worst = 0;
            const int px[] = {0, 1, step / 2, step - 1, w / 2, w / 2 + 1, w - 1};
            const int py[] = {0, h / 2 + step / 2, h / 3 + 1, h - 1};
            for (size_t a = 0; a < sizeof px / sizeof *px; a++)
                for (size_t c = 0; c < sizeof py / sizeof *py; c++)
                    worst = fmax(worst, tail_column_error(plain, tail, py[c] * w + px[a], margin));
            if (!(worst <= est && worst > 0))
                fail_msg("kind %d margin %d: measured %g against the estimate %g (s %d, r0 %d)",
                         kind, margin, worst, est, step, split);
            print_message("tail kind %d margin %d: s %d r0 %d measured %.3g estimate %.3g\n", kind, margin, step, split, worst, est);
            /* adjoint (for data on the view only, with a margin) */
            svp_image *yv = test_image(w, h);
            for (int j = margin; j < h - margin; j++)
                for (int i = margin; i < w - margin; i++)
                    yv->data[(size_t)j * w + i] = y->data[(size_t)j * w + i];
            ASSERT_OK(svp_blur_apply(tail, x, hx));
            ASSERT_OK(svp_blur_adjoint(tail, yv, hty));
            double lhs = 0;
            for (int j = margin; j < h - margin; j++)
                for (int i = margin; i < w - margin; i++)
                    lhs += hx->data[(size_t)j * w + i] * yv->data[(size_t)j * w + i];
            ASSERT_CLOSE(lhs, test_dot(x, hty), 1e-12 * fabs(lhs));
            /* rows = apply, bit for bit; single near double; threads */
            for (int single = 0; single < 2; single++) {
                ASSERT_OK(svp_blur_set_single(tail, single));
                for (int adjoint = 0; adjoint < 2; adjoint++) {
                    svp_image *in = adjoint ? yv : x;
                    svp_set_threads(1);
                    ASSERT_OK(adjoint ? svp_blur_adjoint(tail, in, ref)
                                      : svp_blur_apply(tail, in, ref));
                    if (single)
                        ASSERT_CLOSE(test_max_abs_diff(ref, adjoint ? hty : hx) /
                                         test_max_abs(ref),
                                     0, 1e-5);
                    svp_set_threads(2);
                    rows_ctx c = {in, NULL, out, 0, 1};
                    ASSERT_OK(svp_blur_rows(tail, adjoint, 0, rows_load, rows_store, 1, &c));
                    if (memcmp(out->data, ref->data, bytes))
                        fail_msg("tail: rows (2 threads) differ from %s (1 thread): single %d",
                                 adjoint ? "adjoint" : "apply", single);
                }
            }
            svp_set_threads(threads);
            ASSERT_OK(svp_blur_set_single(tail, 0));
            /* tolerance 0: the plain operator again */
            ASSERT_OK(svp_blur_set_tail(tail, 0));
            ASSERT_OK(svp_blur_tail_info(tail, &step, &split, &est));
            assert_int_equal(step, 0);
            ASSERT_OK(svp_blur_apply(tail, x, hx));
            ASSERT_OK(svp_blur_apply(plain, x, ref));
            assert_true(memcmp(hx->data, ref->data, bytes) == 0);
            svp_image_free(yv);
            svp_blur_free(plain);
            svp_blur_free(tail);
        }
    }
    /* from 2^20 pixels the gather and spread run on several threads: the same bits as on one */
    {
        const int bw = 1040, bh = 1024;
        svp_psf psf;
        svp_psf_defaults(&psf);
        psf.model = SVP_PSF_MOFFAT;
        psf.fwhm = 4;
        psf.beta = 1.1;
        svp_blur *big = NULL;
        ASSERT_OK(svp_blur_new(&psf, bw, bh, SVP_BOUNDARY_ZERO, &big));
        ASSERT_OK(svp_blur_set_tail(big, 1e-3));
        int step = 0, split = 0;
        double est = 0;
        ASSERT_OK(svp_blur_tail_info(big, &step, &split, &est));
        assert_true(step > 0);
        svp_image *bx = test_random_image(bw, bh, 73), *b1 = test_image(bw, bh);
        svp_image *b2 = test_image(bw, bh);
        for (int adjoint = 0; adjoint < 2; adjoint++) {
            svp_set_threads(1);
            ASSERT_OK(adjoint ? svp_blur_adjoint(big, bx, b1) : svp_blur_apply(big, bx, b1));
            svp_set_threads(2);
            ASSERT_OK(adjoint ? svp_blur_adjoint(big, bx, b2) : svp_blur_apply(big, bx, b2));
            assert_true(memcmp(b1->data, b2->data, (size_t)bw * bh * sizeof(double)) == 0);
        }
        svp_set_threads(threads);
        svp_image_free(bx);
        svp_image_free(b1);
        svp_image_free(b2);
        svp_blur_free(big);
    }
    svp_blur *op = NULL;
    svp_psf psf;
    svp_psf_defaults(&psf);
    ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_MIRROR, &op));
    assert_int_equal(svp_blur_set_tail(op, -1), SVP_ERR_INVALID);
    assert_int_equal(svp_blur_set_tail(op, 1), SVP_ERR_INVALID);
    assert_int_equal(svp_blur_set_tail(NULL, 0.1), SVP_ERR_INVALID);
    ASSERT_OK(svp_blur_set_tail(op, 0.1)); /* other boundaries: ignored */
    int step = -1, split = -1;
    double est = -1;
    ASSERT_OK(svp_blur_tail_info(op, &step, &split, &est));
    assert_true(step == 0 && split == 0 && est == 0);
    svp_blur_free(op);
    svp_image_free(x);
    svp_image_free(y);
    svp_image_free(hx);
    svp_image_free(hty);
    svp_image_free(ref);
    svp_image_free(out);
}

/* svp_blur_set_view (zero boundary): on the frame for the view `m` pixels in from every side,
 * H x agrees with the full frame's on the view and Hᵀ y, for y zero outside the view, on the
 * whole grid; the frame is smaller (full-grid reach: 40 x 28 for 48 x 36); margin 0 brings the
 * full frame back, exact everywhere again; single precision follows the frame. A kernel whose
 * reach is below the margin, an asymmetric one, and a mirror operator (no view frame). */
static void test_view_frame(void **state)
{
    (void)state;
    const int w = 23, h = 17;
    svp_image *x = test_random_image(w, h, 31), *yv = test_random_image(w, h, 32);
    svp_image *full_h = test_image(w, h), *full_t = test_image(w, h);
    svp_image *y = test_image(w, h), *xt = test_image(w, h);
    for (int kind = 0; kind < 2; kind++) {
        /* 0: every offset of the grid (2w − 1 x 2h − 1), 1: radius 2 */
        const int kw = kind ? 5 : 2 * w - 1, kh = kind ? 5 : 2 * h - 1;
        svp_image *k = test_random_image(kw, kh, 33 + kind);
        for (int m = 3; m <= 7; m += 4) {
            svp_blur *op = NULL;
            ASSERT_OK(svp_blur_new_kernel(k, kw / 2, kh / 2, 1, w, h, SVP_BOUNDARY_ZERO, &op));
            ASSERT_OK(svp_blur_ready(op));
            const int nx = op->frame.nx, ny = op->frame.ny;
            /* y zero outside the view */
            svp_image *yview = test_image(w, h);
            for (int j = m; j < h - m; j++)
                for (int i = m; i < w - m; i++)
                    yview->data[(size_t)j * w + i] = yv->data[(size_t)j * w + i];
            ASSERT_OK(svp_blur_apply(op, x, full_h));
            ASSERT_OK(svp_blur_adjoint(op, yview, full_t));
            for (int single = 0; single < 2; single++) {
                const double tol = single ? 1e-5 : 1e-13;
                ASSERT_OK(svp_blur_set_single(op, single));
                int applied = -1;
                ASSERT_OK(svp_blur_set_view(op, m, &applied));
                assert_int_equal(applied, 1);
                ASSERT_OK(svp_blur_ready(op));
                assert_true((size_t)op->frame.nx * op->frame.ny < (size_t)nx * ny);
                if (!kind && m == 3) assert_true(op->frame.nx == 40 && op->frame.ny == 28);
                assert_int_equal(op->single, single);
                ASSERT_OK(svp_blur_apply(op, x, y));
                double d = 0;
                for (int j = m; j < h - m; j++)
                    for (int i = m; i < w - m; i++)
                        d = fmax(
                            d, fabs(y->data[(size_t)j * w + i] - full_h->data[(size_t)j * w + i]));
                ASSERT_CLOSE(d / test_max_abs(full_h), 0, tol);
                ASSERT_OK(svp_blur_adjoint(op, yview, xt));
                ASSERT_CLOSE(test_max_abs_diff(xt, full_t) / test_max_abs(full_t), 0, tol);
                ASSERT_OK(svp_blur_set_view(op, 0, &applied));
                assert_int_equal(applied, 0);
                assert_int_equal(op->single, single);
                ASSERT_OK(svp_blur_apply(op, x, y));
                assert_true(op->frame.nx == nx && op->frame.ny == ny);
                ASSERT_CLOSE(test_max_abs_diff(y, full_h) / test_max_abs(full_h), 0, tol);
            }
            ASSERT_OK(svp_blur_set_single(op, 0));
            int applied = -1;
            assert_int_equal(svp_blur_set_view(op, (w + 1) / 2, &applied), SVP_ERR_INVALID);
            assert_int_equal(applied, 0);
            assert_true(op->frame.nx == nx && op->frame.ny == ny);
            svp_image_free(yview);
            svp_blur_free(op);
        }
        svp_blur *mirror = NULL;
        ASSERT_OK(svp_blur_new_kernel(k, kw / 2, kh / 2, 1, w, h, SVP_BOUNDARY_MIRROR, &mirror));
        int applied = -1;
        ASSERT_OK(svp_blur_set_view(mirror, 3, &applied));
        assert_int_equal(applied, 0);
        svp_blur_free(mirror);
        svp_image_free(k);
    }
    svp_image_free(x);
    svp_image_free(yv);
    svp_image_free(full_h);
    svp_image_free(full_t);
    svp_image_free(y);
    svp_image_free(xt);
}

/* The row-block transforms (SVP_FFT_BLOCK rows and a one-row tail, rows bx apart) with a
 * frame's column plans equal FFTW's 2-D r2c and c2r, for odd and even widths and heights that
 * are and are not a multiple of the block. */
static void test_block_transforms(void **state)
{
    (void)state;
    const int sizes[][2] = {{45, 35}, {288, 16}, {27, 9}, {1, 3}};
    for (size_t s = 0; s < sizeof sizes / sizeof sizes[0]; s++) {
        const int nx = sizes[s][0], ny = sizes[s][1], ncx = nx / 2 + 1, B = SVP_FFT_BLOCK;
        const svp_fft_plan *full = NULL;
        const svp_fft_pruned *cols = NULL;
        const svp_fft_block *blk = NULL;
        ASSERT_OK(svp_fft_plan_get(ny, nx, &full));
        ASSERT_OK(svp_fft_pruned_get(ny, nx, ny, &cols));
        ASSERT_OK(svp_fft_block_get(nx, &blk));
        assert_int_equal(blk->bx, nx + (nx & 1));
        svp_image *r = test_random_image(nx, ny, 31 + s);
        fftw_complex *ref = svp_alloc((size_t)ny * ncx * sizeof(fftw_complex));
        fftw_complex *got = svp_alloc((size_t)ny * ncx * sizeof(fftw_complex));
        double *rows = svp_alloc((size_t)B * blk->bx * sizeof(double));
        double *frame = svp_alloc((size_t)ny * nx * sizeof(double));
        double *back = svp_alloc((size_t)ny * nx * sizeof(double));
        assert_true(ref && got && rows && frame && back);
        memcpy(frame, r->data, (size_t)ny * nx * sizeof(double));
        svp_fft_forward(full, frame, ref);
        double peak = 0;
        for (size_t i = 0; i < (size_t)ny * ncx; i++) peak = fmax(peak, cabs(ref[i]));
        for (int t0 = 0; t0 < ny; t0 += B) {
            const int nb = ny - t0 < B ? ny - t0 : B;
            for (int t = 0; t < nb; t++)
                memcpy(rows + (size_t)t * blk->bx, r->data + (size_t)(t0 + t) * nx,
                       (size_t)nx * sizeof(double));
            svp_fft_block_forward(blk, nb, rows, got + (size_t)t0 * ncx);
        }
        fftw_execute_dft(cols->cols_fwd, got, got);
        for (size_t i = 0; i < (size_t)ny * ncx; i++)
            if (!(cabs(got[i] - ref[i]) <= 1e-13 * peak))
                fail_msg("%d x %d forward: bin %zu differs by %g", nx, ny, i,
                         cabs(got[i] - ref[i]));
        /* back: columns, then row blocks; against FFTW's 2-D c2r of the same spectrum */
        svp_fft_inverse_unscaled(full, ref, frame); /* destroys ref */
        fftw_execute_dft(cols->cols_bwd, got, got);
        for (int t0 = 0; t0 < ny; t0 += B) {
            const int nb = ny - t0 < B ? ny - t0 : B;
            svp_fft_block_inverse(blk, nb, got + (size_t)t0 * ncx, rows);
            for (int t = 0; t < nb; t++)
                memcpy(back + (size_t)(t0 + t) * nx, rows + (size_t)t * blk->bx,
                       (size_t)nx * sizeof(double));
        }
        for (size_t i = 0; i < (size_t)ny * nx; i++)
            if (!(fabs(back[i] - frame[i]) <= 1e-12 * nx * ny))
                fail_msg("%d x %d inverse: pixel %zu differs by %g", nx, ny, i,
                         fabs(back[i] - frame[i]));
        svp_image_free(r);
        svp_free(ref);
        svp_free(got);
        svp_free(rows);
        svp_free(frame);
        svp_free(back);
    }
}

/* FFT planning: a measured plan that no wisdom covers is announced once through the plan
 * callback (with its size and precision), never for a cached plan or one the wisdom holds;
 * svp_fft_wisdom_save writes atomically (no temporary file left; the new file 0644, a
 * replaced one keeps its mode) and what it wrote, loaded into a process that forgot its
 * wisdom, makes measuring unnecessary again. */
typedef struct plan_calls {
    int n, ny, nx, single;
} plan_calls;

static void count_plans(void *user, int ny, int nx, int single_precision)
{
    plan_calls *c = user;
    c->n++;
    c->ny = ny;
    c->nx = nx;
    c->single = single_precision;
}

static int count_files(const char *dir)
{
    DIR *d = opendir(dir);
    int n = 0;
    for (struct dirent *e; d && (e = readdir(d));)
        if (strcmp(e->d_name, ".") && strcmp(e->d_name, "..")) n++;
    if (d) closedir(d);
    return n;
}

/* svp_dots: several dot products in one pass, each bit-equal to svp_dot's (the same block
 * order; Biggs–Andrews' α depends on it), across block boundaries and thread counts, and equal
 * to a long-double sum to round-off. */
static void test_dots(void **state)
{
    (void)state;
    const size_t sizes[] = {1, 4095, 4096, 4097, 3 * 4096 + 5, 200000};
    const int saved = svp_get_threads();
    for (size_t t = 0; t < sizeof sizes / sizeof *sizes; t++) {
        const size_t n = sizes[t];
        double *v[3], *scratch = malloc(n * sizeof(double));
        uint64_t seed = 77 + t;
        for (int k = 0; k < 3; k++) {
            v[k] = malloc(n * sizeof(double));
            for (size_t i = 0; i < n; i++) v[k][i] = test_rand(&seed) - 0.3;
        }
        const double *a[4] = {v[0], v[0], v[1], v[2]}, *b[4] = {v[1], v[0], v[2], v[2]};
        for (int threads = 1; threads <= 2; threads++) {
            svp_set_threads(threads);
            double d[4];
            svp_dots(a, b, 4, n, d);
            for (int j = 0; j < 4; j++) {
                const double one = svp_dot(a[j], b[j], scratch, n);
                assert_true(d[j] == one);
                long double ref = 0;
                for (size_t i = 0; i < n; i++) ref += (long double)a[j][i] * b[j][i];
                ASSERT_CLOSE(d[j], (double)ref, 1e-12 * (1 + fabs((double)ref)));
            }
        }
        for (int k = 0; k < 3; k++) free(v[k]);
        free(scratch);
    }
    svp_set_threads(saved);
}

static void test_plan_callback_and_wisdom(void **state)
{
    (void)state;
    char dir[] = "/tmp/svpsf-test-wisdom-XXXXXX", path[64];
    assert_non_null(mkdtemp(dir));
    snprintf(path, sizeof path, "%s/wisdom", dir);
    svp_fft_cleanup();
    fftw_forget_wisdom();
    fftwf_forget_wisdom();
    plan_calls c = {0, 0, 0, -1};
    svp_set_fft_plan_callback(count_plans, &c);
    const svp_fft_plan *p;
    svp_set_fft_effort(SVP_FFT_ESTIMATE); /* estimate: nothing measured, nothing announced */
    ASSERT_OK(svp_fft_plan_get(36, 44, &p));
    assert_int_equal(c.n, 0);
    svp_set_fft_effort(SVP_FFT_MEASURE);
    ASSERT_OK(svp_fft_plan_get(40, 48, &p));
    assert_int_equal(c.n, 1);
    assert_true(c.ny == 40 && c.nx == 48 && c.single == 0);
    ASSERT_OK(svp_fft_plan_get(40, 48, &p)); /* the cached plan */
    svp_fft_cleanup();
    ASSERT_OK(svp_fft_plan_get(40, 48, &p)); /* a new plan, from the wisdom in memory */
    assert_int_equal(c.n, 1);

    ASSERT_OK(svp_fft_wisdom_save(path));
    struct stat st;
    assert_int_equal(stat(path, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0644);
    assert_int_equal(count_files(dir), 1); /* no temporary file left */
    assert_int_equal(chmod(path, 0600), 0);
    ASSERT_OK(svp_fft_wisdom_save(path));
    assert_int_equal(stat(path, &st), 0);
    assert_int_equal(st.st_mode & 0777, 0600);
    assert_int_equal(count_files(dir), 1);

    svp_fft_cleanup();
    fftw_forget_wisdom();
    ASSERT_OK(svp_fft_plan_get(40, 48, &p)); /* forgotten: measured and announced again */
    assert_int_equal(c.n, 2);
    svp_fft_cleanup();
    fftw_forget_wisdom();
    ASSERT_OK(svp_fft_wisdom_load(path));
    ASSERT_OK(svp_fft_plan_get(40, 48, &p)); /* from the file */
    assert_int_equal(c.n, 2);
    const svp_fftf_rows *pf;
    ASSERT_OK(svp_fftf_rows_get(40, 48, 40, &pf)); /* float plans: not in the file */
    assert_int_equal(c.n, 3);
    assert_true(c.ny == 40 && c.nx == 48 && c.single == 1);

    svp_set_fft_plan_callback(NULL, NULL);
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    svp_fft_cleanup();
    unlink(path);
    rmdir(dir);
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_matches_direct_sum), cmocka_unit_test(test_adjoint_identity),
        cmocka_unit_test(test_unit_flux),          cmocka_unit_test(test_linearity_and_delta),
        cmocka_unit_test(test_real_otf),           cmocka_unit_test(test_block_transforms),
        cmocka_unit_test(test_bad_arguments),      cmocka_unit_test(test_plan_callback_and_wisdom),
        cmocka_unit_test(test_view_frame),         cmocka_unit_test(test_view_only_frame),
        cmocka_unit_test(test_blur_rows),          cmocka_unit_test(test_dots),
        cmocka_unit_test(test_tail),
    };
    int rc = cmocka_run_group_tests_name("operator", tests, NULL, NULL);
    svp_fft_cleanup();
    return rc;
}
