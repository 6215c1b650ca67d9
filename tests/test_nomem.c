/* Allocation failures: the library's answer to running out of memory is a status, never a crash,
 * a leak or a wrong result.
 *
 * This suite is linked with -Wl,--wrap for malloc, calloc, realloc, posix_memalign and
 * aligned_alloc (tests/meson.build), so every allocation the library's own objects make (they are
 * linked in statically from libsvpsf_internal) goes through the wrappers below; FFTW's, OpenMP's
 * and libc's internal ones do not. A sweep arms the wrappers to fail the k-th allocation of one
 * call, for k = 0, 1, 2, ... until a call makes fewer than k + 1 allocations, and asserts for
 * every k: the call returns SVP_OK or SVP_ERR_NOMEM with a message (no other status: a NOMEM
 * turned into INVALID or INTERNAL would mislead the user), and an SVP_OK result equals the one
 * computed without a failure. The ASan build of this suite adds: no crash, no use of freed or
 * uninitialised memory and no leak on any of these paths.
 *
 * T⁻¹ side by side (src/restore/transform.c) falls back to the runs in order, on the one frame,
 * when a worker's copy of the operator cannot be allocated; test_inverse_side_by_side asserts
 * that this fallback ran (an allocation failed and the call still returned SVP_OK) and gave the
 * same result. */
#include <stdatomic.h>
#include <stdio.h>
#include <unistd.h>

#include "test_helpers.h"

#include "core/internal.h"

/* ---- the wrappers ---------------------------------------------------------------------------- */

void *__real_malloc(size_t size);
void *__real_calloc(size_t count, size_t size);
void *__real_realloc(void *p, size_t size);
int __real_posix_memalign(void **p, size_t align, size_t size);
void *__real_aligned_alloc(size_t align, size_t size);
void *__wrap_malloc(size_t size);
void *__wrap_calloc(size_t count, size_t size);
void *__wrap_realloc(void *p, size_t size);
int __wrap_posix_memalign(void **p, size_t align, size_t size);
void *__wrap_aligned_alloc(size_t align, size_t size);

static atomic_int armed; /* 1: count allocations, fail the one at index `fail_at` */
static atomic_long seen; /* allocations since arming */
static atomic_long fail_at;
static atomic_int failed; /* 1: the armed failure happened */

static int fail_now(void)
{
    if (!atomic_load(&armed)) return 0;
    if (atomic_fetch_add(&seen, 1) != atomic_load(&fail_at)) return 0;
    atomic_store(&failed, 1);
    return 1;
}

void *__wrap_malloc(size_t size) { return fail_now() ? NULL : __real_malloc(size); }

void *__wrap_calloc(size_t count, size_t size)
{
    return fail_now() ? NULL : __real_calloc(count, size);
}

void *__wrap_realloc(void *p, size_t size) { return fail_now() ? NULL : __real_realloc(p, size); }

int __wrap_posix_memalign(void **p, size_t align, size_t size)
{
    return fail_now() ? 12 /* ENOMEM */ : __real_posix_memalign(p, align, size);
}

void *__wrap_aligned_alloc(size_t align, size_t size)
{
    return fail_now() ? NULL : __real_aligned_alloc(align, size);
}

static void arm(long k)
{
    atomic_store(&seen, 0);
    atomic_store(&fail_at, k);
    atomic_store(&failed, 0);
    atomic_store(&armed, 1);
}

/* Disarms; returns the allocations the call made. */
static long disarm(void)
{
    atomic_store(&armed, 0);
    return atomic_load(&seen);
}

/* ---- the sweep ------------------------------------------------------------------------------- */

/* One call under test: runs with whatever the wrappers do, returns its status; `check` compares
 * an SVP_OK result with the reference (made by the same call unarmed) and returns its largest
 * difference. */
typedef struct sweep_case {
    const char *name;
    svp_status (*run)(void *ctx);
    double (*check)(void *ctx);
    void *ctx;
    double bound; /* largest difference accepted for an SVP_OK result */
} sweep_case;

typedef struct sweep_result {
    long allocations; /* in the unarmed call */
    int ok_after_failure, nomem;
} sweep_result;

static sweep_result sweep(const sweep_case *c)
{
    sweep_result res = {0};
    for (long k = 0;; k++) {
        svp_clear_error();
        arm(k);
        const svp_status st = c->run(c->ctx);
        const long made = disarm();
        if (!atomic_load(&failed)) {
            /* fewer than k + 1 allocations: this was an unharmed call, the last of the sweep */
            if (st != SVP_OK) fail_msg("%s: unarmed call failed: %s", c->name, svp_last_error());
            res.allocations = made;
            break;
        }
        if (st == SVP_ERR_NOMEM) {
            if (!svp_last_error()[0])
                fail_msg("%s: allocation %ld: NOMEM without a message", c->name, k);
            res.nomem++;
            continue;
        }
        if (st != SVP_OK)
            fail_msg("%s: allocation %ld failed and the call returned status %d (%s), not "
                     "SVP_ERR_NOMEM",
                     c->name, k, (int)st, svp_last_error());
        const double d = c->check(c->ctx);
        if (!(d <= c->bound))
            fail_msg("%s: allocation %ld failed, the call returned SVP_OK with a result %.3g from "
                     "the reference (bound %.3g)",
                     c->name, k, d, c->bound);
        res.ok_after_failure++;
    }
    print_message("%s: %ld allocations; a failure at each gave NOMEM %d times, a correct result "
                  "%d times\n",
                  c->name, res.allocations, res.nomem, res.ok_after_failure);
    return res;
}

/* ---- scenes ---------------------------------------------------------------------------------- */

/* A Gaussian spot times a chessboard of levels 0.1 / 1 (square px), and two smooth fields. */
static svp_image *pl_scene(int w, int h, int square)
{
    svp_image *pl = test_image(w, h);
    const double cx = 0.5 * (w - 1), cy = 0.5 * (h - 1), s = 0.45 * (w > h ? w : h);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            const double r2 = (x - cx) * (x - cx) + (y - cy) * (y - cy);
            const int dark = ((x / square) + (y / square)) % 2;
            pl->data[(size_t)y * w + x] = exp(-0.5 * r2 / (s * s)) * (dark ? 0.1 : 1.0);
        }
    return pl;
}

static svp_image *field_scene(int w, int h, int component)
{
    svp_image *b = test_image(w, h);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            const double u = (x + 0.5) / w, v = (y + 0.5) / h;
            b->data[(size_t)y * w + x] =
                component == 0 ? cos(M_PI * u) * (1 + 0.5 * v) - 0.2 : 0.7 * cos(2 * M_PI * v) * u;
        }
    return b;
}

/* Every operator of the suite: Moffat, FWHM 3 px, β 1.5 (and two nodes of corner_map). */
static svp_psf moffat_psf(void)
{
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_MOFFAT;
    psf.fwhm = 3.0;
    psf.beta = 1.5;
    return psf;
}

static svp_blur *moffat_blur(int w, int h)
{
    const svp_psf psf = moffat_psf();
    svp_blur *op = NULL;
    ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_ZERO, &op));
    return op;
}

/* A PSF map: moffat_psf() at two opposite corners of a 2 x 2 node grid, FWHM 4.5 px at the
 * other two. */
static svp_psf_field *corner_map(int w, int h)
{
    const svp_psf base = moffat_psf();
    svp_psf corner = base;
    corner.fwhm = 4.5;
    const svp_psf nodes[4] = {base, corner, corner, base};
    const double nx[2] = {0, w - 1}, ny[2] = {0, h - 1};
    svp_psf_field *map = NULL;
    ASSERT_OK(svp_psf_field_new_grid(w, h, 2, 2, nx, ny, nodes, &map));
    return map;
}

/* ---- T⁻¹ ------------------------------------------------------------------------------------- */

#define NF 2

typedef struct inverse_ctx {
    svp_blur *blur;
    const svp_image *pl_app;
    const svp_image *field_app[NF];
    svp_correct_options opt;
    svp_image *pl, *field[NF], *valid;             /* the call's outputs */
    svp_image *ref_pl, *ref_field[NF], *ref_valid; /* the unharmed call's */
    svp_correct_summary sum;
    int fallbacks;   /* armed calls that returned SVP_OK with side_by_side_fallback set */
    double progress; /* the call's last progress fraction */
    int backwards;   /* 1 once the call's progress went back */
} inverse_ctx;

static int track_progress(void *user, double fraction)
{
    inverse_ctx *c = user;
    if (fraction < c->progress) c->backwards = 1;
    c->progress = fraction;
    return 0;
}

static svp_status inverse_call(void *user)
{
    inverse_ctx *c = user;
    c->progress = 0;
    c->backwards = 0;
    return svp_inverse_transform(c->blur, c->pl_app, c->field_app, NF, &c->opt, c->pl, c->field,
                                 c->valid, NULL);
}

static double inverse_diff(void *user)
{
    inverse_ctx *c = user;
    c->fallbacks += c->sum.side_by_side_fallback;
    /* progress monotone to 1, through a fallback too */
    if (c->backwards || c->progress != 1.0)
        fail_msg("progress went back or ended at %.17g (fallback %d)", c->progress,
                 c->sum.side_by_side_fallback);
    double d = test_max_abs_diff(c->pl, c->ref_pl) / test_max_abs(c->ref_pl);
    for (int k = 0; k < NF; k++)
        d = fmax(d,
                 test_max_abs_diff(c->field[k], c->ref_field[k]) / test_max_abs(c->ref_field[k]));
    return fmax(d, test_max_abs_diff(c->valid, c->ref_valid));
}

static void auto_balance(svp_correct_options *o)
{
    o->balance_auto = 1;
    o->pl_gain = 1e-3;
    o->keep_doubtful = 1;
}

static void auto_iterations(svp_correct_options *o)
{
    o->auto_iterations = 1;
    o->pl_gain = 1e-3;
    o->keep_doubtful = 1;
}

/* The view's apparent maps from a (w + 2m)² scene blurred on its own grid, cropped to the view. */
static void inverse_setup(inverse_ctx *c, int w, int h, int margin, svp_method method,
                          int iterations, void (*more)(svp_correct_options *o))
{
    const int gw = w + 2 * margin, gh = h + 2 * margin;
    svp_blur *grid = moffat_blur(gw, gh);
    svp_image *pl = pl_scene(gw, gh, 8), *b[NF] = {field_scene(gw, gh, 0), field_scene(gw, gh, 1)};
    svp_image *pl_app = test_image(gw, gh), *valid = test_image(gw, gh);
    svp_image *b_app[NF] = {test_image(gw, gh), test_image(gw, gh)};
    ASSERT_OK(
        svp_forward_transform(grid, pl, (const svp_image *const *)b, NF, pl_app, b_app, valid));
    svp_image *view_pl = test_image(w, h), *view_b[NF] = {test_image(w, h), test_image(w, h)};
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            const size_t i = (size_t)y * w + x, g = (size_t)(y + margin) * gw + x + margin;
            view_pl->data[i] = pl_app->data[g];
            for (int k = 0; k < NF; k++) view_b[k]->data[i] = b_app[k]->data[g];
        }
    view_b[0]->data[5 * w + 7] = NAN; /* a missing pixel: the validity map's coverage path */
    c->blur = margin ? grid : moffat_blur(w, h);
    if (margin == 0) svp_blur_free(grid);
    c->pl_app = view_pl;
    for (int k = 0; k < NF; k++) c->field_app[k] = view_b[k];
    svp_correct_defaults(&c->opt);
    c->opt.method = method;
    c->opt.deconv.iterations = iterations;
    c->opt.margin = margin;
    c->opt.summary = &c->sum;
    c->opt.deconv.progress = track_progress;
    c->opt.deconv.progress_user = c;
    if (more) more(&c->opt); /* options beyond these */
    c->pl = test_image(w, h);
    c->valid = test_image(w, h);
    c->ref_pl = test_image(w, h);
    c->ref_valid = test_image(w, h);
    for (int k = 0; k < NF; k++) {
        c->field[k] = test_image(w, h);
        c->ref_field[k] = test_image(w, h);
    }
    ASSERT_OK(svp_inverse_transform(c->blur, c->pl_app, c->field_app, NF, &c->opt, c->ref_pl,
                                    c->ref_field, c->ref_valid, NULL));
    svp_image_free(pl);
    svp_image_free(pl_app);
    svp_image_free(valid);
    for (int k = 0; k < NF; k++) {
        svp_image_free(b[k]);
        svp_image_free(b_app[k]);
    }
}

static void inverse_free(inverse_ctx *c)
{
    svp_blur_free(c->blur);
    svp_image_free((svp_image *)c->pl_app);
    svp_image_free(c->pl);
    svp_image_free(c->valid);
    svp_image_free(c->ref_pl);
    svp_image_free(c->ref_valid);
    for (int k = 0; k < NF; k++) {
        svp_image_free((svp_image *)c->field_app[k]);
        svp_image_free(c->field[k]);
        svp_image_free(c->ref_field[k]);
    }
}

/* One T⁻¹ swept: name, the view, margin, method, iterations and any further options;
 * *fallbacks (may be NULL): the armed calls that returned SVP_OK after the side-by-side runs'
 * fallback to the runs in order (svp_correct_summary.side_by_side_fallback). */
static sweep_result sweep_inverse(const char *name, int w, int h, int margin, svp_method method,
                                  int iterations, void (*more)(svp_correct_options *o),
                                  int *fallbacks)
{
    inverse_ctx c = {0};
    inverse_setup(&c, w, h, margin, method, iterations, more);
    const sweep_case sc = {name, inverse_call, inverse_diff, &c, 1e-10};
    const sweep_result r = sweep(&sc);
    assert_true(r.allocations > 10 && r.nomem > 0);
    if (fallbacks) *fallbacks = c.fallbacks;
    inverse_free(&c);
    return r;
}

/* Method R with 2 threads on a 128² view: the PL's and the two numerators' RL side by side, each
 * worker on its own copy of the operator. A failure among the copies' or the workers'
 * allocations must fall back to the runs in order (two-thread plans: the same result to
 * round-off, bound 1e-10), so at least one armed call returns SVP_OK. */
static void test_inverse_side_by_side(void **state)
{
    (void)state;
    svp_set_threads(2);
    int fallbacks = 0;
    const sweep_result r = sweep_inverse("T⁻¹ R, 2 threads, side by side", 128, 128, 0,
                                         SVP_METHOD_R, 4, NULL, &fallbacks);
    /* the fallback to the runs in order ran, and the summary said so */
    assert_true(r.ok_after_failure > 0 && fallbacks > 0);
    print_message("  of which %d through the fallback to the runs in order\n", fallbacks);
    svp_set_threads(1);
}

static void tail_loose(svp_correct_options *o) { o->tail_tol = 2e-2; }

/* The same with the PSF's far tail on a coarse grid (docs/model.md §5): the tail's choice, its
 * nodes, frames and the copies' tails fail as the frames do. */
static void test_inverse_tail(void **state)
{
    (void)state;
    const int n = 160;
    svp_blur *op = moffat_blur(n, n);
    int step = 0, split = 0;
    double est = 0;
    ASSERT_OK(svp_blur_set_tail(op, 2e-2));
    ASSERT_OK(svp_blur_tail_info(op, &step, &split, &est));
    assert_true(step > 0); /* the sweep below runs with a tail */
    svp_blur_free(op);
    svp_set_threads(2);
    sweep_inverse("T⁻¹ R, 2 threads, tail on a coarse grid", n, n, 0, SVP_METHOD_R, 3,
                  tail_loose, NULL);
    svp_set_threads(1);
    sweep_inverse("T⁻¹ R, 1 thread, tail on a coarse grid, margin 8", n, n, 8, SVP_METHOD_R, 3,
                  tail_loose, NULL);
}

/* The same with a low-rank PSF map: the workers' copies share its term spectra
 * (svp_blur_clone), their own accumulators and frames fail as the invariant copies do. */
static void test_inverse_map_side_by_side(void **state)
{
    (void)state;
    svp_set_threads(2);
    const int n = 128;
    inverse_ctx c = {0};
    inverse_setup(&c, n, n, 0, SVP_METHOD_R, 4, NULL);
    svp_blur_free(c.blur);
    svp_psf_field *map = corner_map(n, n);
    svp_variant_options vo;
    svp_variant_defaults(&vo);
    vo.representation = SVP_VARIANT_LOWRANK;
    vo.rank = 2;
    vo.samples_x = vo.samples_y = 3;
    ASSERT_OK(svp_blur_new_field(map, n, n, SVP_BOUNDARY_ZERO, &vo, &c.blur));
    ASSERT_OK(svp_inverse_transform(c.blur, c.pl_app, c.field_app, NF, &c.opt, c.ref_pl,
                                    c.ref_field, c.ref_valid, NULL));
    const sweep_case sc = {"T⁻¹ R, 2 threads, low-rank map side by side", inverse_call,
                           inverse_diff, &c, 1e-10};
    const sweep_result r = sweep(&sc);
    assert_true(r.allocations > 10 && r.nomem > 0 && r.ok_after_failure > 0 && c.fallbacks > 0);
    print_message("  of which %d through the fallback to the runs in order\n", c.fallbacks);
    inverse_free(&c);
    svp_psf_field_free(map);
    svp_set_threads(1);
}

/* The same in order (1 thread), with a margin (the view's frame) and method RW (RL on the PL,
 * the zero-boundary Wiener's CG on the numerators). */
static void test_inverse_in_order(void **state)
{
    (void)state;
    sweep_inverse("T⁻¹ R, 1 thread, margin 6", 48, 40, 6, SVP_METHOD_R, 4, NULL, NULL);
    sweep_inverse("T⁻¹ RW, 1 thread", 48, 40, 0, SVP_METHOD_RW, 4, NULL, NULL);
}

/* The automatic choices, whose searches allocate on their own: method W with the discrepancy
 * balance, and R with automatic iterations, both with a PL gain (a result they doubt is kept,
 * validity 0, so that the unharmed call returns SVP_OK). */
static void test_inverse_automatic(void **state)
{
    (void)state;
    sweep_inverse("T⁻¹ W, balance auto", 48, 40, 0, SVP_METHOD_W, 4, auto_balance, NULL);
    sweep_inverse("T⁻¹ R, iterations auto", 48, 40, 0, SVP_METHOD_R, 40, auto_iterations, NULL);
}

/* ---- operators and deconvolutions -------------------------------------------------------------- */

typedef struct deconv_ctx {
    const svp_image *y;
    svp_deconv_options opt;
    int single, variant;
    svp_psf_field *field;
    svp_image *x, *ref;
} deconv_ctx;

/* Builds the operator inside the call, and the FFT plans anew (the cache emptied; no operator
 * outside the call holds one), so their allocations are swept too. */
static svp_status deconv_call(void *user)
{
    deconv_ctx *c = user;
    svp_fft_cleanup();
    const int w = c->y->width, h = c->y->height;
    svp_blur *op = NULL;
    svp_status st;
    if (c->variant) {
        svp_variant_options vo;
        svp_variant_defaults(&vo);
        vo.representation = SVP_VARIANT_LOWRANK;
        vo.rank = 2;
        vo.samples_x = vo.samples_y = 3;
        st = svp_blur_new_field(c->field, w, h, SVP_BOUNDARY_ZERO, &vo, &op);
    } else {
        const svp_psf psf = moffat_psf();
        st = svp_blur_new(&psf, w, h, SVP_BOUNDARY_ZERO, &op);
    }
    if (st == SVP_OK && c->single) st = svp_blur_set_precision(op, 1);
    if (st == SVP_OK) st = svp_deconv_rl(op, c->y, &c->opt, c->x);
    svp_blur_free(op);
    return st;
}

static double deconv_diff(void *user)
{
    deconv_ctx *c = user;
    return test_max_abs_diff(c->x, c->ref) / test_max_abs(c->ref);
}

static void deconv_sweep(const char *name, int single, int variant, svp_rl_acceleration accel)
{
    const int w = 40, h = 36;
    deconv_ctx c = {0};
    svp_image *y = pl_scene(w, h, 6);
    c.y = y;
    svp_deconv_defaults(&c.opt);
    c.opt.iterations = 6;
    c.opt.acceleration = accel;
    c.single = single;
    c.variant = variant;
    if (variant) c.field = corner_map(w, h);
    c.x = test_image(w, h);
    c.ref = test_image(w, h);
    svp_image *keep = c.x;
    c.x = c.ref;
    ASSERT_OK(deconv_call(&c));
    c.x = keep;
    sweep_case sc = {name, deconv_call, deconv_diff, &c, 1e-12};
    sweep_result r = sweep(&sc);
    assert_true(r.allocations > 5 && r.nomem > 0);
    svp_psf_field_free(c.field);
    svp_image_free(c.x);
    svp_image_free(c.ref);
    svp_image_free(y);
}

static void test_deconv_rl(void **state)
{
    (void)state;
    deconv_sweep("RL, double, plain", 0, 0, SVP_RL_PLAIN);
    deconv_sweep("RL, single, Biggs-Andrews", 1, 0, SVP_RL_BIGGS_ANDREWS);
    deconv_sweep("RL, PSF map (low rank 2), single", 1, 1, SVP_RL_PLAIN);
}

/* ---- readers and the PSF fit ------------------------------------------------------------------ */

typedef struct read_ctx {
    char path[64], yaml[64];
    const svp_image *ref;
    svp_image *got;
    svp_psf psf;
} read_ctx;

static svp_status read_call(void *user)
{
    read_ctx *c = user;
    svp_image_free(c->got);
    c->got = NULL;
    SVP_CHECK(svp_image_read(c->path, &c->got));
    double pixel_um = 0;
    svp_boundary b;
    return svp_psf_file_read(c->yaml, &c->psf, &pixel_um, &b);
}

static double read_diff(void *user)
{
    read_ctx *c = user;
    const double psf_err = fabs(c->psf.fwhm - 6.1) + fabs(c->psf.beta - 1.1);
    return fmax(test_max_abs_diff(c->got, c->ref), psf_err);
}

/* An .npy image and a PSF file (YAML) read back: the library's own parsing and buffers. */
static void test_readers(void **state)
{
    (void)state;
    read_ctx c = {0};
    snprintf(c.path, sizeof c.path, "nomem_%ld.npy", (long)getpid());
    snprintf(c.yaml, sizeof c.yaml, "nomem_%ld.yaml", (long)getpid());
    svp_image *img = test_random_image(33, 17, 4);
    ASSERT_OK(svp_image_write(c.path, img, SVP_FORMAT_NPY, 1));
    FILE *f = fopen(c.yaml, "w");
    assert_non_null(f);
    fputs("pixel_um: 0.1\npsf: {model: moffat, fwhm_um: 0.61, beta: 1.1}\n", f);
    fclose(f);
    c.ref = img;
    sweep_case sc = {"read .npy and a PSF file", read_call, read_diff, &c, 1e-12};
    sweep_result r = sweep(&sc);
    assert_true(r.allocations > 0 && r.nomem > 0);
    assert_true(read_diff(&c) <= 1e-12);
    remove(c.path);
    remove(c.yaml);
    svp_image_free(c.got);
    svp_image_free(img);
}

/* A MATLAB file (libmatio underneath: its own allocations are not swept, svpsf's checks of the
 * file are) and a 3-D .npy stack. */
typedef struct mat_ctx {
    char mat[64], npy[64];
    const svp_image *ref;
    svp_image *got;
    svp_stack *stack;
} mat_ctx;

static svp_status mat_call(void *user)
{
    mat_ctx *c = user;
    svp_image_free(c->got);
    svp_stack_free(c->stack);
    c->got = NULL;
    c->stack = NULL;
    SVP_CHECK(svp_mat_read(c->mat, "Bz", &c->got, NULL));
    return svp_stack_read(c->npy, &c->stack);
}

static double mat_diff(void *user)
{
    mat_ctx *c = user;
    if (c->stack->n_frames != 3) return INFINITY;
    return fmax(test_max_abs_diff(c->got, c->ref), test_max_abs_diff(c->stack->frame[2], c->ref));
}

static void test_mat_and_stack(void **state)
{
    (void)state;
    mat_ctx c = {0};
    snprintf(c.mat, sizeof c.mat, "nomem_%ld.mat", (long)getpid());
    snprintf(c.npy, sizeof c.npy, "nomem_%ld_stack.npy", (long)getpid());
    const int w = 21, h = 13, n = 3;
    svp_image *img = test_random_image(w, h, 8);
    const char *names[1] = {"Bz"};
    ASSERT_OK(svp_mat_write(c.mat, 1, names, (const svp_image *const *)&img, 0.1, 1));
    /* a 3-D float64 .npy (n, h, w), every frame the image */
    FILE *f = fopen(c.npy, "wb");
    assert_non_null(f);
    char header[128];
    int len =
        snprintf(header, sizeof header,
                 "{'descr': '<f8', 'fortran_order': False, 'shape': (%d, %d, %d), }", n, h, w);
    while ((10 + len + 1) % 64) header[len++] = ' ';
    header[len++] = '\n';
    const unsigned char magic[10] = {
        0x93, 'N', 'U', 'M', 'P', 'Y', 1, 0, (unsigned char)(len & 255), (unsigned char)(len >> 8)};
    fwrite(magic, 1, sizeof magic, f);
    fwrite(header, 1, (size_t)len, f);
    for (int k = 0; k < n; k++) fwrite(img->data, sizeof(double), (size_t)w * h, f);
    fclose(f);
    c.ref = img;
    const sweep_case sc = {".mat map and a 3-D .npy stack read", mat_call, mat_diff, &c, 0.0};
    const sweep_result r = sweep(&sc);
    assert_true(r.allocations > 0 && r.nomem > 0);
    assert_true(mat_diff(&c) == 0.0);
    remove(c.mat);
    remove(c.npy);
    svp_image_free(c.got);
    svp_stack_free(c.stack);
    svp_image_free(img);
}

/* Per-pixel ODMR fits of a small simulated cube (one LM workspace per thread). */
typedef struct odmr_ctx {
    svp_odmr odmr;
    svp_cube *cube;
    svp_image *field, *ref;
} odmr_ctx;

static svp_status odmr_call(void *user)
{
    odmr_ctx *c = user;
    svp_odmr_fit_options o;
    svp_odmr_fit_defaults(&o);
    size_t failed = 0;
    return svp_odmr_fit(&c->odmr, c->cube, &o, c->field, NULL, NULL, NULL, &failed);
}

static double odmr_diff(void *user)
{
    odmr_ctx *c = user;
    return test_max_abs_diff(c->field, c->ref) / test_max_abs(c->ref);
}

static void test_odmr_fit(void **state)
{
    (void)state;
    const int w = 6, h = 5, nf = 41;
    odmr_ctx c = {0};
    svp_odmr_defaults(&c.odmr);
    double freq[41];
    ASSERT_OK(svp_odmr_sweep(&c.odmr, 100e-6, 4, nf, freq));
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &c.cube));
    svp_image *pl = pl_scene(w, h, 2), *b = field_scene(w, h, 0);
    for (size_t i = 0; i < (size_t)w * h; i++) b->data[i] *= 50e-6;
    ASSERT_OK(svp_odmr_simulate(&c.odmr, pl, b, NULL, NULL, c.cube));
    c.ref = c.field = test_image(w, h);
    ASSERT_OK(odmr_call(&c));
    c.field = test_image(w, h);
    const sweep_case sc = {"ODMR fits, 6 x 5 pixels", odmr_call, odmr_diff, &c, 1e-12};
    const sweep_result r = sweep(&sc);
    assert_true(r.allocations > 0 && r.nomem > 0);
    svp_image_free(c.field);
    svp_image_free(c.ref);
    svp_image_free(pl);
    svp_image_free(b);
    svp_cube_free(c.cube);
}

/* Frames of a drifting sweep aligned (svp_cube_align: registrations, the drift fit, Fourier
 * shifts; the FFT plans made in the call). */
typedef struct align_ctx {
    svp_cube *drifted, *work, *ref;
} align_ctx;

static svp_status align_call(void *user)
{
    align_ctx *c = user;
    svp_fft_cleanup();
    const size_t n = (size_t)c->work->width * c->work->height;
    for (int f = 0; f < c->work->n_freq; f++)
        memcpy(c->work->frame[f]->data, c->drifted->frame[f]->data, n * sizeof(double));
    return svp_cube_align(c->work, NULL, NULL, NULL, NULL, NULL, NULL);
}

/* The largest difference between two cubes' frames. */
static double cube_diff(const svp_cube *a, const svp_cube *b)
{
    double d = 0;
    for (int f = 0; f < a->n_freq; f++) d = fmax(d, test_max_abs_diff(a->frame[f], b->frame[f]));
    return d;
}

static double align_diff(void *user)
{
    align_ctx *c = user;
    return cube_diff(c->work, c->ref);
}

static void test_align(void **state)
{
    (void)state;
    const int w = 24, h = 20, nf = 8;
    double freq[8];
    for (int f = 0; f < nf; f++) freq[f] = 2.8e9 + 1e6 * f;
    align_ctx c = {0};
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &c.drifted));
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &c.work));
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &c.ref));
    svp_image *pl = pl_scene(w, h, 5);
    for (int f = 0; f < nf; f++) ASSERT_OK(svp_shift(pl, 0.05 * f, -0.02 * f, c.drifted->frame[f]));
    svp_cube *keep = c.work;
    c.work = c.ref;
    ASSERT_OK(align_call(&c));
    c.work = keep;
    const sweep_case sc = {"cube alignment, 8 frames of 24 x 20", align_call, align_diff, &c, 1e-12};
    const sweep_result r = sweep(&sc);
    assert_true(r.allocations > 0 && r.nomem > 0);
    svp_image_free(pl);
    svp_cube_free(c.drifted);
    svp_cube_free(c.work);
    svp_cube_free(c.ref);
}

/* Every frame of a cube deconvolved (svp_cube_deconvolve: copies of the operator per worker on
 * 2 threads, RL per frame; the FFT plans made in the call). */
typedef struct cubedec_ctx {
    svp_cube *blurred, *work, *ref;
    svp_psf psf;
    int margin;
} cubedec_ctx;

static svp_status cubedec_call(void *user)
{
    cubedec_ctx *c = user;
    svp_fft_cleanup();
    const int w = c->work->width, h = c->work->height;
    for (int f = 0; f < c->work->n_freq; f++)
        memcpy(c->work->frame[f]->data, c->blurred->frame[f]->data, (size_t)w * h * sizeof(double));
    svp_blur *op = NULL;
    svp_status st = svp_blur_new(&c->psf, w + 2 * c->margin, h + 2 * c->margin,
                                 SVP_BOUNDARY_ZERO, &op);
    svp_deconv_options o;
    svp_deconv_defaults(&o);
    o.iterations = 5;
    if (st == SVP_OK) st = svp_cube_deconvolve(op, c->work, c->margin, &o, NULL, NULL, NULL);
    svp_blur_free(op);
    return st;
}

static double cubedec_diff(void *user)
{
    cubedec_ctx *c = user;
    return cube_diff(c->work, c->ref);
}

static void test_cube_deconvolve(void **state)
{
    (void)state;
    const int w = 20, h = 16, nf = 4;
    double freq[4] = {2.86e9, 2.865e9, 2.87e9, 2.875e9};
    cubedec_ctx c = {0};
    svp_psf_defaults(&c.psf);
    c.psf.model = SVP_PSF_GAUSSIAN;
    c.psf.fwhm = 3;
    c.margin = 3;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &c.blurred));
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &c.work));
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &c.ref));
    svp_image *pl = pl_scene(w, h, 4);
    for (int f = 0; f < nf; f++)
        for (size_t i = 0; i < (size_t)w * h; i++)
            c.blurred->frame[f]->data[i] = pl->data[i] * (1 - 0.01 * f);
    const int threads = svp_get_threads();
    svp_set_threads(2);
    svp_cube *keep = c.work;
    c.work = c.ref;
    ASSERT_OK(cubedec_call(&c));
    c.work = keep;
    const sweep_case sc = {"cube deconvolution, 4 frames of 20 x 16, 2 threads", cubedec_call,
                           cubedec_diff, &c, 1e-12};
    const sweep_result r = sweep(&sc);
    svp_set_threads(threads);
    assert_true(r.allocations > 0 && r.nomem > 0);
    svp_image_free(pl);
    svp_cube_free(c.blurred);
    svp_cube_free(c.work);
    svp_cube_free(c.ref);
}

/* The magnetisation reconstructed from B_z (padded FFTs; the Fourier and the support method)
 * and T with a tent PSF map built in the call. */
typedef struct physics_ctx {
    svp_image *bz, *pl, *mz, *ref_mz, *mz_support, *ref_mz_support;
    svp_psf_field *map;
    svp_image *pl_app, *b_app, *ref_pl, *ref_b;
} physics_ctx;

static svp_status physics_call(void *user)
{
    physics_ctx *c = user;
    svp_fft_cleanup();
    svp_recon_options ro;
    svp_recon_defaults(&ro);
    ro.sensor.pixel_m = 1e-7;
    ro.sensor.standoff_m = 1e-7;
    SVP_CHECK(svp_reconstruct_magnetisation(c->bz, &ro, c->mz));
    ro.method = SVP_RECON_SUPPORT;
    SVP_CHECK(svp_reconstruct_magnetisation(c->bz, &ro, c->mz_support));
    svp_variant_options vo;
    svp_variant_defaults(&vo);
    vo.representation = SVP_VARIANT_TENT;
    vo.grid_x = vo.grid_y = 2;
    svp_blur *op = NULL;
    const int w = c->bz->width, h = c->bz->height;
    svp_status st = svp_blur_new_field(c->map, w, h, SVP_BOUNDARY_ZERO, &vo, &op);
    if (st == SVP_OK)
        st = svp_forward_transform(op, c->pl, (const svp_image *const *)&c->bz, 1, c->pl_app,
                                   &c->b_app, NULL);
    svp_blur_free(op);
    return st;
}

static double physics_diff(void *user)
{
    physics_ctx *c = user;
    double d = test_max_abs_diff(c->mz, c->ref_mz) / test_max_abs(c->ref_mz);
    d = fmax(d, test_max_abs_diff(c->mz_support, c->ref_mz_support) /
                    test_max_abs(c->ref_mz_support));
    d = fmax(d, test_max_abs_diff(c->pl_app, c->ref_pl) / test_max_abs(c->ref_pl));
    return fmax(d, test_max_abs_diff(c->b_app, c->ref_b) / test_max_abs(c->ref_b));
}

static void test_physics(void **state)
{
    (void)state;
    const int w = 40, h = 36;
    physics_ctx c = {0};
    c.bz = field_scene(w, h, 0);
    for (size_t i = 0; i < (size_t)w * h; i++) c.bz->data[i] *= 1e-5;
    c.pl = pl_scene(w, h, 4);
    c.map = corner_map(w, h);
    c.mz = c.ref_mz = test_image(w, h);
    c.mz_support = c.ref_mz_support = test_image(w, h);
    c.pl_app = c.ref_pl = test_image(w, h);
    c.b_app = c.ref_b = test_image(w, h);
    ASSERT_OK(physics_call(&c));
    c.mz = test_image(w, h);
    c.mz_support = test_image(w, h);
    c.pl_app = test_image(w, h);
    c.b_app = test_image(w, h);
    const sweep_case sc = {"magnetisation from B_z (Fourier, support); T with a tent PSF map", physics_call,
                           physics_diff, &c, 1e-12};
    const sweep_result r = sweep(&sc);
    assert_true(r.allocations > 0 && r.nomem > 0);
    svp_image *all[10] = {c.bz,     c.pl,    c.mz,     c.ref_mz, c.mz_support,
                          c.ref_mz_support, c.pl_app, c.b_app, c.ref_pl, c.ref_b};
    for (int k = 0; k < 10; k++) svp_image_free(all[k]);
    svp_psf_field_free(c.map);
}

/* A scene file (the reference study's uniform micromagnet, docs/scenes/) parsed and checked. */
static const char scene_text[] =
    "name: nomem\n"
    "grid: {pixel_um: 0.2, size_um: [12, 12], margin_um: 1}\n"
    "sources:\n"
    "  - flake: {shape: rectangle, size_um: [8, 8], centre_um: [0, 0],\n"
    "            magnetisation_A_per_m: 1.0e6, thickness_nm: 1, standoff_nm: 100}\n"
    "field: {components: [z]}\n"
    "emission:\n"
    "  - uniform: {level: 1}\n"
    "psf: {model: gaussian, fwhm_um: 1.0}\n"
    "correct:\n"
    "  - {method: r, iterations: 15}\n"
    "  - {method: r, iterations: 75, margin: auto, precision: single, name: default}\n"
    "reconstruct: magnetisation\n"
    "metrics:\n"
    "  masks:\n"
    "    - {name: view}\n"
    "    - {name: flake, inside: flakes, erode_um: 2}\n"
    "  line_cuts:\n"
    "    - {name: across, from_um: [-5.9, 0.1], to_um: [5.9, 0.1]}\n";

static svp_status scene_call(void *user)
{
    int *stages = user;
    svp_scene *scene = NULL;
    svp_status st = svp_scene_load_string("nomem.yaml", scene_text, strlen(scene_text), &scene);
    if (st == SVP_OK) *stages = svp_scene_plan(scene, NULL);
    svp_scene_free(scene);
    return st;
}

static double scene_diff(void *user)
{
    int *stages = user;
    return fabs((double)*stages - (double)stages[1]);
}

static void test_scene_load(void **state)
{
    (void)state;
    int stages[2] = {0, 0};
    ASSERT_OK(scene_call(stages));
    stages[1] = stages[0];
    assert_true(stages[1] > 3);
    sweep_case sc = {"scene file", scene_call, scene_diff, stages, 0.0};
    sweep_result r = sweep(&sc);
    assert_true(r.allocations > 10 && r.nomem > 0);
}

typedef struct fit_ctx {
    const svp_image *spot;
    svp_spot_options opt;
    svp_spot_result res, ref;
} fit_ctx;

static svp_status fit_call(void *user)
{
    fit_ctx *c = user;
    return svp_spot_fit(c->spot, &c->opt, &c->res, NULL, NULL);
}

static double fit_diff(void *user)
{
    fit_ctx *c = user;
    return fmax(fabs(c->res.fwhm - c->ref.fwhm) / c->ref.fwhm,
                fabs(c->res.beta - c->ref.beta) / c->ref.beta);
}

/* A 31² Moffat spot (β 1.8) on a background of 5 with uniform noise, off the pixel grid. */
static svp_image *moffat_spot(void)
{
    const int n = 31;
    svp_image *spot = test_image(n, n);
    uint64_t s = 11;
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            const double r2 = (x - 15.3) * (x - 15.3) + (y - 14.8) * (y - 14.8);
            spot->data[(size_t)y * n + x] = 5 + 900 * pow(1 + r2 / 9.0, -1.8) + test_rand(&s);
        }
    return spot;
}

/* A Moffat spot fitted (Levenberg–Marquardt, LAPACKE): workspace, clipping, covariance. */
static void test_spot_fit(void **state)
{
    (void)state;
    svp_image *spot = moffat_spot();
    fit_ctx c = {.spot = spot};
    svp_spot_defaults(&c.opt);
    ASSERT_OK(svp_spot_fit(spot, &c.opt, &c.ref, NULL, NULL));
    sweep_case sc = {"spot fit (Moffat, elliptical)", fit_call, fit_diff, &c, 1e-12};
    sweep_result r = sweep(&sc);
    assert_true(r.allocations > 0 && r.nomem > 0);
    svp_image_free(spot);
}

/* A polynomial PSF map from 30 spot fits (the fit above as the template, FWHM and β varying
 * smoothly over a 400² field; one outlier): the fits, the surfaces' degrees chosen by the
 * library, the outlier clipped, the report. */
typedef struct map_ctx {
    svp_psf_sample samples[30];
    svp_psf ref_centre, got_centre;
} map_ctx;

static svp_status map_call(void *user)
{
    map_ctx *c = user;
    svp_psf_field *field = NULL;
    svp_map_report *rep = NULL;
    svp_status st = svp_psf_map_poly(c->samples, 30, 400, 400, NULL, &field, &rep);
    if (st == SVP_OK) st = svp_psf_field_at(field, 200, 150, &c->got_centre);
    svp_psf_field_free(field);
    svp_map_report_free(rep);
    return st;
}

static double map_diff(void *user)
{
    map_ctx *c = user;
    return fmax(fabs(c->got_centre.fwhm - c->ref_centre.fwhm),
                fabs(c->got_centre.beta - c->ref_centre.beta));
}

static void test_map_poly(void **state)
{
    (void)state;
    svp_image *spot = moffat_spot();
    svp_spot_options so;
    svp_spot_defaults(&so);
    svp_spot_result fit;
    ASSERT_OK(svp_spot_fit(spot, &so, &fit, NULL, NULL));
    map_ctx c;
    for (int k = 0; k < 30; k++) {
        const double u = (k % 6) / 5.0, v = (k / 6) / 4.0;
        c.samples[k].x = 20 + 360 * u;
        c.samples[k].y = 20 + 360 * v;
        c.samples[k].fit = fit;
        c.samples[k].fit.fwhm *= 1 + 0.2 * u + 0.1 * v;
        c.samples[k].fit.beta *= 1 + 0.1 * v;
    }
    c.samples[7].fit.fwhm *= 1.5; /* an outlier */
    ASSERT_OK(map_call(&c));
    c.ref_centre = c.got_centre;
    const sweep_case sc = {"polynomial PSF map from 30 spot fits", map_call, map_diff, &c, 1e-12};
    const sweep_result r = sweep(&sc);
    assert_true(r.allocations > 5 && r.nomem > 0);
    svp_image_free(spot);
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    svp_set_threads(1);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_inverse_side_by_side),
        cmocka_unit_test(test_inverse_tail),
        cmocka_unit_test(test_inverse_map_side_by_side),
        cmocka_unit_test(test_inverse_in_order),
        cmocka_unit_test(test_inverse_automatic),
        cmocka_unit_test(test_deconv_rl),
        cmocka_unit_test(test_readers),
        cmocka_unit_test(test_spot_fit),
        cmocka_unit_test(test_scene_load),
        cmocka_unit_test(test_mat_and_stack),
        cmocka_unit_test(test_odmr_fit),
        cmocka_unit_test(test_align),
        cmocka_unit_test(test_cube_deconvolve),
        cmocka_unit_test(test_physics),
        cmocka_unit_test(test_map_poly),
    };
    if (getenv("SVP_TEST_FILTER")) cmocka_set_test_filter(getenv("SVP_TEST_FILTER"));
    int rc = cmocka_run_group_tests_name("nomem", tests, NULL, NULL);
    svp_fft_cleanup();
    return rc;
}
