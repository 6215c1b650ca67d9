/* Registration (svp_register, docs/api.md): phase correlation and ECC against scenes
 * rendered analytically at known transforms, the coordinate convention, warping of label
 * masks, and bad input. Measured numbers are printed (print_message) and stated in comments;
 * the asserted tolerances are the issue's. */
#include "test_helpers.h"

#include <stdio.h>

#include "core/internal.h" /* svp_fft_cleanup */

/* ---- an analytic textured scene -------------------------------------------------------------
 * Smooth random blobs (Gaussians of sigma 1.5–4.5 px) spread 20 px beyond the frame, so
 * content enters at the edges as it does when a camera moves. */
#define MAX_BLOBS 160
typedef struct scene {
    int n;
    double x[MAX_BLOBS], y[MAX_BLOBS], s[MAX_BLOBS], a[MAX_BLOBS];
} scene;

static void scene_init(scene *sc, int w, int h, int n, uint64_t seed)
{
    uint64_t st = seed * 0x9E3779B97F4A7C15ULL + 12345;
    sc->n = n;
    for (int i = 0; i < n; i++) {
        sc->x[i] = test_rand(&st) * (w + 40) - 20;
        sc->y[i] = test_rand(&st) * (h + 40) - 20;
        sc->s[i] = 1.5 + 3 * test_rand(&st);
        sc->a[i] = 0.5 + test_rand(&st);
    }
}

static double scene_at(const scene *sc, double x, double y)
{
    double v = 0;
    for (int i = 0; i < sc->n; i++) {
        const double dx = x - sc->x[i], dy = y - sc->y[i];
        v += sc->a[i] * exp(-(dx * dx + dy * dy) / (2 * sc->s[i] * sc->s[i]));
    }
    return v;
}

/* The inverse of a 2 x 3 affine, written here independently of svp_affine_invert. */
static void invert_affine(const double a[6], double inv[6])
{
    const double det = a[0] * a[4] - a[1] * a[3];
    inv[0] = a[4] / det;
    inv[1] = -a[1] / det;
    inv[3] = -a[3] / det;
    inv[4] = a[0] / det;
    inv[2] = -(inv[0] * a[2] + inv[1] * a[5]);
    inv[5] = -(inv[3] * a[2] + inv[4] * a[5]);
}

/* reference(x) = scene(x); moving(q) = scene(A⁻¹ q), so that moving(A x) = reference(x): A maps
 * reference coordinates to moving coordinates (the library's convention). */
static void render_pair(const scene *sc, const double A[6], svp_image *ref, svp_image *mov)
{
    double inv[6];
    invert_affine(A, inv);
    for (int y = 0; y < ref->height; y++)
        for (int x = 0; x < ref->width; x++)
            ref->data[(size_t)y * ref->width + x] = scene_at(sc, x, y);
    for (int y = 0; y < mov->height; y++)
        for (int x = 0; x < mov->width; x++) {
            const double rx = inv[0] * x + inv[1] * y + inv[2];
            const double ry = inv[3] * x + inv[4] * y + inv[5];
            mov->data[(size_t)y * mov->width + x] = scene_at(sc, rx, ry);
        }
}

/* Rotation by theta (from +x towards +y) and scale s about the image centre, then a shift. */
static void similarity(int w, int h, double theta, double s, double tx, double ty, double A[6])
{
    const double cx = (w - 1) / 2.0, cy = (h - 1) / 2.0;
    A[0] = s * cos(theta);
    A[1] = -s * sin(theta);
    A[3] = s * sin(theta);
    A[4] = s * cos(theta);
    A[2] = cx - A[0] * cx - A[1] * cy + tx;
    A[5] = cy - A[3] * cx - A[4] * cy + ty;
}

/* Largest distance between where A and B send the four image corners, pixels. */
static double corner_error(const double A[6], const double B[6], int w, int h)
{
    double worst = 0;
    const double xs[2] = {0, w - 1}, ys[2] = {0, h - 1};
    for (int i = 0; i < 2; i++)
        for (int j = 0; j < 2; j++) {
            const double ex = (A[0] - B[0]) * xs[i] + (A[1] - B[1]) * ys[j] + (A[2] - B[2]);
            const double ey = (A[3] - B[3]) * xs[i] + (A[4] - B[4]) * ys[j] + (A[5] - B[5]);
            worst = fmax(worst, hypot(ex, ey));
        }
    return worst;
}

/* ---- phase correlation -------------------------------------------------------------------- */

/* Sub-pixel translations, including sub-0.1 px, half-pixel and large ones, on a non-square
 * frame (x and y cannot be swapped unnoticed). Measured: max error 2.5e-3 px, at (−5.5, 0.25)
 * (asserted 0.05); below 1e-4 px for the shifts under 1 px. */
static void test_phase_subpixel(void **state)
{
    (void)state;
    const int w = 128, h = 112;
    const double shifts[][2] = {{2.37, -1.61}, {-5.5, 0.25}, {0.1, 0.03},
                                {12.3, 7.8},   {-0.5, -0.5}, {31.42, -20.71}};
    scene sc;
    scene_init(&sc, w, h, 120, 1);
    svp_image *ref = test_image(w, h), *mov = test_image(w, h);
    svp_register_options o;
    svp_register_defaults(&o);
    double worst = 0, worst_resp = 1;
    for (size_t k = 0; k < sizeof shifts / sizeof shifts[0]; k++) {
        const double dx = shifts[k][0], dy = shifts[k][1];
        const double A[6] = {1, 0, dx, 0, 1, dy};
        render_pair(&sc, A, ref, mov);
        svp_register_result r;
        ASSERT_OK(svp_register(ref, mov, &o, &r));
        const double err = hypot(r.affine[2] - dx, r.affine[5] - dy);
        worst = fmax(worst, err);
        worst_resp = fmin(worst_resp, r.response);
        if (!(err < 0.05))
            fail_msg("shift (%g, %g): found (%.4f, %.4f), error %.4f px > 0.05", dx, dy,
                     r.affine[2], r.affine[5], err);
        /* a translation: the linear part is exactly the identity */
        assert_true(r.affine[0] == 1 && r.affine[1] == 0 && r.affine[3] == 0 &&
                    r.affine[4] == 1);
        ASSERT_CLOSE(r.shift_x, dx, 1e-12 + err);
        ASSERT_CLOSE(r.shift_y, dy, 1e-12 + err);
        ASSERT_CLOSE(r.rotation, 0, 1e-15);
        ASSERT_CLOSE(r.scale, 1, 1e-15);
        assert_int_equal(r.low_significance, 0);
        assert_int_equal(r.iterations, 0);
        /* the residual over the overlap is only the bilinear interpolation error of a smooth
         * scene (largest at half-pixel shifts: 0.061 measured) */
        if (!(r.correlation > 0.999 && r.residual_rms < 0.1))
            fail_msg("shift (%g, %g): correlation %.5f, residual %.4f", dx, dy, r.correlation,
                     r.residual_rms);
        /* the overlap is the part of the frame that stays inside the moving image */
        const double overlap = (w - ceil(fabs(dx) - 0.5)) * (h - ceil(fabs(dy) - 0.5)) /
                               ((double)w * h);
        ASSERT_CLOSE(r.overlap, overlap, 2.0 / w + 2.0 / h);
    }
    print_message("phase correlation: max translation error %.2e px over %zu shifts "
                  "(smallest response %.3f)\n",
                  worst, sizeof shifts / sizeof shifts[0], worst_resp);
    svp_image_free(ref);
    svp_image_free(mov);
}

/* The direction, pinned on a scene anyone can check by eye: a bright spot at (35, 33) in the
 * reference is at (40, 30) in the moving image → affine translation (+5, −3), and warping the
 * moving image with it puts the spot back at (35, 33). */
static void test_direction(void **state)
{
    (void)state;
    const int w = 64, h = 64;
    svp_image *ref = test_image(w, h), *mov = test_image(w, h), *back = test_image(w, h);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            const double r2 = (x - 35.0) * (x - 35.0) + (y - 33.0) * (y - 33.0);
            const double m2 = (x - 40.0) * (x - 40.0) + (y - 30.0) * (y - 30.0);
            ref->data[y * w + x] = exp(-r2 / 8);
            mov->data[y * w + x] = exp(-m2 / 8);
        }
    svp_register_options o;
    svp_register_defaults(&o);
    svp_register_result r;
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    ASSERT_CLOSE(r.affine[2], 5, 0.01);
    ASSERT_CLOSE(r.affine[5], -3, 0.01);
    ASSERT_OK(svp_warp(mov, r.affine, SVP_INTERP_LINEAR, 0, back));
    size_t peak = 0;
    for (size_t i = 1; i < (size_t)w * h; i++)
        if (back->data[i] > back->data[peak]) peak = i;
    assert_int_equal((int)(peak % w), 35);
    assert_int_equal((int)(peak / w), 33);
    /* the same convention through ECC */
    o.method = SVP_REGISTER_ECC;
    o.motion = SVP_MOTION_AFFINE;
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    ASSERT_CLOSE(r.affine[2], 5, 0.02);
    ASSERT_CLOSE(r.affine[5], -3, 0.02);
    svp_image_free(ref);
    svp_image_free(mov);
    svp_image_free(back);
}

/* Pair images: an excitation spot (Moffat beta 3.3, FWHM 3 px: Gaussian-like) and the
 * wider emission spot (beta 1.1, FWHM 5 px) of the same focus, offset by a sub-pixel shift.
 * The spots differ in shape but both are symmetric, so the cross-power phase is the shift's.
 * Measured: window off 1.2e-5 px, window on 1.7e-2 px (asserted 0.05): for isolated spots on a
 * flat background switch the window off (the spots are not exact shifted copies, so the
 * window cannot be made to move with them). */
static double moffat(double r2, double fwhm, double beta)
{
    const double r0 = fwhm / (2 * sqrt(pow(2, 1 / beta) - 1));
    return pow(1 + r2 / (r0 * r0), -beta);
}

static void test_spot_pair(void **state)
{
    (void)state;
    const int w = 64, h = 64;
    const double cx = 30.4, cy = 33.1, dx = 1.37, dy = -0.82;
    svp_image *exc = test_image(w, h), *pl = test_image(w, h);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            const double r2 = (x - cx) * (x - cx) + (y - cy) * (y - cy);
            const double q2 = (x - cx - dx) * (x - cx - dx) + (y - cy - dy) * (y - cy - dy);
            exc->data[y * w + x] = 1000 * moffat(r2, 3, 3.3) + 10;
            pl->data[y * w + x] = 300 * moffat(q2, 5, 1.1) + 12;
        }
    double err[2];
    for (int win = 0; win < 2; win++) {
        svp_register_options o;
        svp_register_defaults(&o);
        o.window = win;
        svp_register_result r;
        ASSERT_OK(svp_register(exc, pl, &o, &r));
        err[win] = hypot(r.affine[2] - dx, r.affine[5] - dy);
        if (!(err[win] < 0.05))
            fail_msg("spot pair, window %d: found (%.4f, %.4f) for (%g, %g)", win, r.affine[2],
                     r.affine[5], dx, dy);
    }
    print_message("spot pair (beta 3.3 / 1.1): error %.2e px without window, %.2e px with\n",
                  err[0], err[1]);
    svp_image_free(exc);
    svp_image_free(pl);
}

/* ---- ECC ------------------------------------------------------------------------------------ */

/* Rotation 2°, scale 1.02 about the centre, shift (1.3, −0.7): ECC affine recovers the
 * matrix. Measured: linear part 1.1e-4, corners 0.011 px, rotation 8e-4°, scale 6.5e-5, in 5
 * iterations (OpenCV interpolates in float with 1/32-px tables: that sets the floor).
 * Asserted: linear part 1e-3, corners 0.05 px, rotation 0.02°, scale 2e-4. */
static void test_ecc_affine(void **state)
{
    (void)state;
    const int w = 128, h = 128;
    const double theta = 2 * M_PI / 180, s = 1.02;
    double A[6];
    similarity(w, h, theta, s, 1.3, -0.7, A);
    scene sc;
    scene_init(&sc, w, h, 130, 2);
    svp_image *ref = test_image(w, h), *mov = test_image(w, h);
    render_pair(&sc, A, ref, mov);
    svp_register_options o;
    svp_register_defaults(&o);
    o.method = SVP_REGISTER_ECC;
    o.motion = SVP_MOTION_AFFINE;
    svp_register_result r;
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    double lin = 0;
    for (int i = 0; i < 6; i++)
        if (i != 2 && i != 5) lin = fmax(lin, fabs(r.affine[i] - A[i]));
    const double corners = corner_error(r.affine, A, w, h);
    print_message("ECC affine: linear part error %.2e, corners %.4f px, rotation %.2e deg, "
                  "scale %.2e, %d iterations, correlation %.5f, residual %.4f, phase start "
                  "response %.3f\n",
                  lin, corners, fabs(r.rotation - theta) * 180 / M_PI, fabs(r.scale - s),
                  r.iterations, r.correlation, r.residual_rms, r.response);
    if (!(lin < 1e-3 && corners < 0.05))
        fail_msg("ECC affine: linear error %.3g, corner error %.3g px", lin, corners);
    ASSERT_CLOSE(r.rotation, theta, 0.02 * M_PI / 180);
    ASSERT_CLOSE(r.scale, s, 2e-4);
    /* shift of the centre = the shift applied after the rotation about the centre */
    ASSERT_CLOSE(r.shift_x, 1.3, 0.05);
    ASSERT_CLOSE(r.shift_y, -0.7, 0.05);
    assert_true(r.iterations >= 2 && r.iterations <= o.iterations);
    assert_true(r.correlation > 0.99);

    /* phase correlation alone cannot follow the rotation: its residual is far larger */
    svp_register_options p;
    svp_register_defaults(&p);
    svp_register_result rp;
    ASSERT_OK(svp_register(ref, mov, &p, &rp));
    print_message("same pair by phase correlation: residual %.4f vs ECC %.4f\n",
                  rp.residual_rms, r.residual_rms);
    assert_true(rp.residual_rms > 5 * r.residual_rms);
    svp_image_free(ref);
    svp_image_free(mov);
}

/* Euclidean (−3° + shift) and translation motions. Measured: rotation error 2.4e-3°, corners
 * 0.011 px; translation 0.012 px (asserted 0.02°, 0.05 px). */
static void test_ecc_euclidean_translation(void **state)
{
    (void)state;
    const int w = 96, h = 80;
    scene sc;
    scene_init(&sc, w, h, 90, 3);
    svp_image *ref = test_image(w, h), *mov = test_image(w, h);
    svp_register_options o;
    svp_register_defaults(&o);
    o.method = SVP_REGISTER_ECC;
    svp_register_result r;

    double A[6];
    similarity(w, h, -3 * M_PI / 180, 1, -2.2, 0.6, A);
    render_pair(&sc, A, ref, mov);
    o.motion = SVP_MOTION_EUCLIDEAN;
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    const double ce = corner_error(r.affine, A, w, h);
    print_message("ECC euclidean: rotation error %.2e deg, corners %.4f px, scale %.17g\n",
                  fabs(r.rotation + 3 * M_PI / 180) * 180 / M_PI, ce, r.scale);
    ASSERT_CLOSE(r.rotation, -3 * M_PI / 180, 0.02 * M_PI / 180);
    ASSERT_CLOSE(r.scale, 1, 1e-6); /* a rotation has no scale */
    assert_true(ce < 0.05);

    const double T[6] = {1, 0, 4.71, 0, 1, -3.33};
    render_pair(&sc, T, ref, mov);
    o.motion = SVP_MOTION_TRANSLATION;
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    const double te = hypot(r.affine[2] - 4.71, r.affine[5] + 3.33);
    print_message("ECC translation: error %.2e px\n", te);
    assert_true(te < 0.05);
    assert_true(r.affine[0] == 1 && r.affine[1] == 0 && r.affine[3] == 0 && r.affine[4] == 1);
    svp_image_free(ref);
    svp_image_free(mov);
}

/* ---- warping a label mask -------------------------------------------------------------------
 * Labels of a layout: 0 bare, 1 a metal strip, 2 an oxide disc, in continuous coordinates.
 * dist_to_edge: distance from (x, y) to the nearest label boundary. */
static int layout_label(double x, double y)
{
    if (hypot(x - 70, y - 50) < 22) return 2;
    if (fabs((x - 0.3 * y) - 30) < 7) return 1;
    return 0;
}

static double layout_edge_distance(double x, double y)
{
    const double disc = fabs(hypot(x - 70, y - 50) - 22);
    const double strip = fmin(fabs((x - 0.3 * y) - 23), fabs((x - 0.3 * y) - 37)) /
                         sqrt(1 + 0.09);
    return fmin(disc, strip);
}

/* The moving mask is the layout drawn at the moving pose; the transform is estimated from the
 * textured images, and the moving mask warped back (nearest) must equal the reference mask
 * except within 1 px of an edge. Measured: 83 of 11647 compared pixels differ (0.71 %), all
 * within 0.48 px of an edge (asserted: all within 1 px, fewer than 2 %). */
static void test_mask_warp(void **state)
{
    (void)state;
    const int w = 120, h = 100;
    double A[6], inv[6];
    similarity(w, h, 1.5 * M_PI / 180, 0.99, 2.6, 1.8, A);
    invert_affine(A, inv);
    scene sc;
    scene_init(&sc, w, h, 110, 4);
    svp_image *ref = test_image(w, h), *mov = test_image(w, h);
    svp_image *ref_mask = test_image(w, h), *mov_mask = test_image(w, h);
    svp_image *back = test_image(w, h);
    render_pair(&sc, A, ref, mov);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            ref_mask->data[y * w + x] = layout_label(x, y);
            const double rx = inv[0] * x + inv[1] * y + inv[2];
            const double ry = inv[3] * x + inv[4] * y + inv[5];
            mov_mask->data[y * w + x] = layout_label(rx, ry);
        }
    svp_register_options o;
    svp_register_defaults(&o);
    o.method = SVP_REGISTER_ECC;
    o.motion = SVP_MOTION_AFFINE;
    svp_register_result r;
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    ASSERT_OK(svp_warp(mov_mask, r.affine, SVP_INTERP_NEAREST, -1, back));
    size_t compared = 0, differ = 0, outside = 0;
    double worst_edge = 0;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            const double v = back->data[y * w + x];
            if (v == -1) {
                outside++;
                continue;
            }
            /* nearest keeps labels: no value that is not a label */
            assert_true(v == 0 || v == 1 || v == 2);
            compared++;
            if (v != ref_mask->data[y * w + x]) {
                differ++;
                const double d = layout_edge_distance(x, y);
                worst_edge = fmax(worst_edge, d);
                if (!(d <= 1))
                    fail_msg("pixel (%d, %d): label %g, reference %g, %.2f px from an edge", x,
                             y, v, ref_mask->data[y * w + x], d);
            }
        }
    print_message("mask warp: %zu of %zu pixels differ (%.2f %%), farthest %.2f px from an "
                  "edge; %zu pixels map outside the moving frame\n",
                  differ, compared, 100.0 * differ / compared, worst_edge, outside);
    /* the pixels outside are the strip the shift and rotation move out of view */
    assert_true(outside > 0 && outside < (size_t)(0.1 * w * h));
    assert_true(differ < compared / 50);
    svp_image_free(ref);
    svp_image_free(mov);
    svp_image_free(ref_mask);
    svp_image_free(mov_mask);
    svp_image_free(back);
}

/* ---- svp_warp on its own --------------------------------------------------------------------- */

static void test_warp_properties(void **state)
{
    (void)state;
    const int w = 50, h = 40;
    svp_image *src = test_random_image(w, h, 5), *out = test_image(w, h);
    /* identity, both methods: exact copies */
    const double id[6] = {1, 0, 0, 0, 1, 0};
    ASSERT_OK(svp_warp(src, id, SVP_INTERP_NEAREST, 0, out));
    assert_true(test_max_abs_diff(src, out) == 0);
    ASSERT_OK(svp_warp(src, id, SVP_INTERP_LINEAR, 0, out));
    assert_true(test_max_abs_diff(src, out) == 0);
    /* integer translation (+3, −2): out(x, y) = src(x + 3, y − 2), border 7 elsewhere */
    const double t[6] = {1, 0, 3, 0, 1, -2};
    for (int m = 0; m < 2; m++) {
        ASSERT_OK(svp_warp(src, t, m ? SVP_INTERP_LINEAR : SVP_INTERP_NEAREST, 7, out));
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                const int sx = x + 3, sy = y - 2;
                const double expect =
                    sx < w && sy >= 0 ? src->data[sy * w + sx] : 7.0;
                assert_true(out->data[y * w + x] == expect);
            }
    }
    /* bilinear reproduces a linear function exactly (any affine, different sizes) */
    svp_image *ramp = test_image(70, 60), *small = test_image(33, 21);
    for (int y = 0; y < 60; y++)
        for (int x = 0; x < 70; x++) ramp->data[y * 70 + x] = 2 * x - 3 * y + 1;
    const double a[6] = {1.1, 0.2, 5.3, -0.15, 0.95, 12.7};
    ASSERT_OK(svp_warp(ramp, a, SVP_INTERP_LINEAR, NAN, small));
    double worst = 0;
    for (int y = 0; y < 21; y++)
        for (int x = 0; x < 33; x++) {
            const double qx = a[0] * x + a[1] * y + a[2], qy = a[3] * x + a[4] * y + a[5];
            assert_true(qx > 0 && qx < 69 && qy > 0 && qy < 59);
            worst = fmax(worst, fabs(small->data[y * 33 + x] - (2 * qx - 3 * qy + 1)));
        }
    assert_true(worst < 1e-12);
    /* domain: [−0.5, w − 0.5); the outer half pixel repeats the edge value */
    const double half[6] = {1, 0, -0.5, 0, 1, 0};
    ASSERT_OK(svp_warp(ramp, half, SVP_INTERP_LINEAR, NAN, out));
    assert_true(out->data[0] == ramp->data[0]);            /* x = −0.5: inside, edge value */
    ASSERT_CLOSE(out->data[1], 0.5 * (ramp->data[0] + ramp->data[1]), 1e-15);
    const double beyond[6] = {1, 0, -0.5001, 0, 1, 0};
    ASSERT_OK(svp_warp(ramp, beyond, SVP_INTERP_NEAREST, NAN, out));
    assert_true(isnan(out->data[0]) && !isnan(out->data[1]));
    /* NaN: used neighbours give NaN, zero-weight neighbours do not */
    svp_image *holes = test_image(4, 4), *o4 = test_image(4, 4);
    for (int i = 0; i < 16; i++) holes->data[i] = i;
    holes->data[5] = NAN;
    const double right_half[6] = {1, 0, 0.5, 0, 1, 0};
    ASSERT_OK(svp_warp(holes, id, SVP_INTERP_LINEAR, 0, o4));
    assert_true(isnan(o4->data[5]) && o4->data[4] == 4 && o4->data[6] == 6);
    ASSERT_OK(svp_warp(holes, right_half, SVP_INTERP_LINEAR, 0, o4));
    assert_true(isnan(o4->data[4]) && isnan(o4->data[5]) && o4->data[6] == 6.5);
    /* bad arguments */
    assert_int_equal(svp_warp(src, id, SVP_INTERP_LINEAR, 0, src), SVP_ERR_INVALID);
    const double bad[6] = {1, 0, NAN, 0, 1, 0};
    assert_int_equal(svp_warp(src, bad, SVP_INTERP_LINEAR, 0, out), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "element 2"));
    assert_int_equal(svp_warp(src, id, (svp_interpolation)7, 0, out), SVP_ERR_INVALID);
    svp_image_free(src);
    svp_image_free(out);
    svp_image_free(ramp);
    svp_image_free(small);
    svp_image_free(holes);
    svp_image_free(o4);
}

static void test_affine_invert(void **state)
{
    (void)state;
    const double a[6] = {1.02, -0.05, 3.5, 0.04, 0.98, -7.25};
    double inv[6], again[6];
    ASSERT_OK(svp_affine_invert(a, inv));
    /* a(inv(p)) = p */
    const double px = 17.5, py = -3.25;
    const double qx = inv[0] * px + inv[1] * py + inv[2], qy = inv[3] * px + inv[4] * py + inv[5];
    ASSERT_CLOSE(a[0] * qx + a[1] * qy + a[2], px, 1e-12);
    ASSERT_CLOSE(a[3] * qx + a[4] * qy + a[5], py, 1e-12);
    ASSERT_OK(svp_affine_invert(inv, again));
    for (int i = 0; i < 6; i++) ASSERT_CLOSE(again[i], a[i], 1e-12);
    const double singular[6] = {1, 2, 0, 2, 4, 0};
    assert_int_equal(svp_affine_invert(singular, inv), SVP_ERR_NUMERIC);
    assert_non_null(strstr(svp_last_error(), "singular"));
}

/* ---- bad input ------------------------------------------------------------------------------- */

static void test_bad_input(void **state)
{
    (void)state;
    const int w = 64, h = 48;
    scene sc;
    scene_init(&sc, w, h, 60, 5);
    svp_image *ref = test_image(w, h), *mov = test_image(w, h);
    const double T[6] = {1, 0, 1.25, 0, 1, -2.5};
    render_pair(&sc, T, ref, mov);
    svp_register_options o;
    svp_register_defaults(&o);
    svp_register_result r;

    /* constant image: no texture */
    svp_image *flat = test_image(w, h);
    for (int i = 0; i < w * h; i++) flat->data[i] = 3.5;
    assert_int_equal(svp_register(ref, flat, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "moving image is constant"));
    assert_non_null(strstr(svp_last_error(), "3.5"));
    assert_int_equal(svp_register(flat, mov, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "reference image is constant"));
    /* the caller's names for the images (the CLI passes the files) */
    o.reference_name = "flat.tif";
    o.moving_name = "mov.tif";
    assert_int_equal(svp_register(flat, mov, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "flat.tif is constant"));
    o.reference_name = o.moving_name = NULL;
    /* a textured image in absurd units (× 2^-1000, about 1e-301): refused for its magnitude,
     * not called constant (its variance underflowed) */
    svp_image *scaled = test_image(w, h);
    for (int i = 0; i < w * h; i++) scaled->data[i] = ldexp(mov->data[i], -1000);
    assert_int_equal(svp_register(ref, scaled, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "moving image: its largest |value|"));
    svp_image_free(scaled);

    /* unrelated images: a result, flagged by its significance (measured 4.84, the more
     * significant of the peak and the trough (contrast AUTO), against 24.2 for
     * the shifted pair; the response alone does not separate them: 0.53 against 1.00) */
    scene other;
    scene_init(&other, w, h, 60, 99);
    svp_image *unrelated = test_image(w, h), *dummy = test_image(w, h);
    const double id[6] = {1, 0, 0, 0, 1, 0};
    render_pair(&other, id, unrelated, dummy);
    ASSERT_OK(svp_register(ref, unrelated, &o, &r));
    svp_register_result good;
    ASSERT_OK(svp_register(ref, mov, &o, &good));
    print_message("unrelated images: significance %.2f (flag %d), response %.3f; shifted pair: "
                  "significance %.2f (flag %d), response %.3f\n",
                  r.significance, r.low_significance, r.response, good.significance,
                  good.low_significance, good.response);
    assert_int_equal(r.low_significance, 1);
    assert_int_equal(good.low_significance, 0);
    assert_true(r.significance < o.min_significance && good.significance > 2 * o.min_significance);

    /* size mismatch */
    svp_image *wide = test_image(w + 1, h);
    assert_int_equal(svp_register(ref, wide, &o, &r), SVP_ERR_SIZE);
    assert_non_null(strstr(svp_last_error(), "reference is 64 x 48 but moving is 65 x 48"));

    /* NaN pixels: filled from their neighbours, counted, left out of the residual; the shift
     * holds (measured 4.2e-4 px; 3.4e-2 px when they were set to the image mean instead) */
    svp_image *holey = NULL;
    ASSERT_OK(svp_image_copy(mov, &holey));
    uint64_t st = 77;
    size_t holes = 0;
    while (holes < 40) {
        size_t i = (size_t)(test_rand(&st) * w * h);
        if (!isnan(holey->data[i])) {
            holey->data[i] = holes % 2 ? NAN : INFINITY;
            holes++;
        }
    }
    ASSERT_OK(svp_register(ref, holey, &o, &r));
    assert_int_equal(r.nonfinite_moving, 40);
    assert_int_equal(r.nonfinite_reference, 0);
    const double err = hypot(r.affine[2] - 1.25, r.affine[5] + 2.5);
    print_message("40 NaN/Inf pixels in the moving image: shift error %.2e px, residual %.4f, "
                  "overlap %.4f\n",
                  err, r.residual_rms, r.overlap);
    assert_true(err < 0.05);
    assert_true(isfinite(r.residual_rms) && isfinite(r.correlation));
    /* ~4 reference pixels lose their sample per NaN neighbour set: the overlap shrinks */
    assert_true(r.overlap < good.overlap);
    for (int i = 0; i < w * h; i++) holey->data[i] = NAN;
    assert_int_equal(svp_register(ref, holey, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "moving image: no finite pixel"));

    /* options */
    o.motion = SVP_MOTION_AFFINE;
    assert_int_equal(svp_register(ref, mov, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "translation only"));
    svp_register_defaults(&o);
    o.smooth_sigma = -1;
    assert_int_equal(svp_register(ref, mov, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "smooth_sigma"));
    svp_register_defaults(&o);
    o.method = SVP_REGISTER_ECC;
    o.iterations = 1;
    assert_int_equal(svp_register(ref, mov, &o, &r), SVP_ERR_INVALID);
    svp_image *tiny = test_image(6, 6);
    svp_register_defaults(&o);
    assert_int_equal(svp_register(tiny, tiny, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "at least 8 x 8"));
    assert_int_equal(svp_register(NULL, mov, &o, &r), SVP_ERR_INVALID);
    assert_int_equal(svp_register(ref, mov, &o, NULL), SVP_ERR_INVALID);

    svp_image_free(flat);
    svp_image_free(unrelated);
    svp_image_free(dummy);
    svp_image_free(wide);
    svp_image_free(holey);
    svp_image_free(tiny);
    svp_image_free(ref);
    svp_image_free(mov);
}

/* ECC that runs out of iterations, ECC on images that share nothing, and cancellation. */
static int cancel_at_three(void *user, double fraction)
{
    (void)fraction;
    return ++*(int *)user >= 3;
}

static void test_ecc_failures(void **state)
{
    (void)state;
    const int w = 96, h = 96;
    double A[6];
    similarity(w, h, 2.5 * M_PI / 180, 1.01, 1.5, 1, A);
    scene sc;
    scene_init(&sc, w, h, 100, 6);
    svp_image *ref = test_image(w, h), *mov = test_image(w, h);
    render_pair(&sc, A, ref, mov);
    svp_register_options o;
    svp_register_defaults(&o);
    o.method = SVP_REGISTER_ECC;
    o.motion = SVP_MOTION_AFFINE;
    o.iterations = 2;
    o.epsilon = 1e-12;
    svp_register_result r;
    assert_int_equal(svp_register(ref, mov, &o, &r), SVP_ERR_NUMERIC);
    assert_non_null(strstr(svp_last_error(), "did not converge after 2 iterations"));
    assert_non_null(strstr(svp_last_error(), "correlation 0."));
    assert_int_equal(r.iterations, 2);

    svp_register_defaults(&o);
    o.method = SVP_REGISTER_ECC;
    o.motion = SVP_MOTION_AFFINE;
    int calls = 0;
    o.progress = cancel_at_three;
    o.progress_user = &calls;
    assert_int_equal(svp_register(ref, mov, &o, &r), SVP_ERR_CANCELLED);
    assert_int_equal(calls, 3);

    /* a starting transform given by the caller: used as is, no phase response */
    svp_register_defaults(&o);
    o.method = SVP_REGISTER_ECC;
    o.motion = SVP_MOTION_AFFINE;
    const double start[6] = {1, 0, 1, 0, 1, 1};
    o.initial_affine = start;
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    assert_true(isnan(r.response));
    assert_true(corner_error(r.affine, A, w, h) < 0.05);
    svp_image_free(ref);
    svp_image_free(mov);
}

/* Inverted contrast: a moving image that is a negative of the shifted reference (moving =
 * 5 − 2 · scene(x − d), as a mask of regions that are dark in the PL) is detected from the
 * correlation's trough and registered as well as a positive; forcing SAME finds no significant
 * peak; forcing INVERTED gives the AUTO answer; ECC works on the inverted image. A positive
 * pair keeps SAME. */
static void test_inverted_contrast(void **state)
{
    (void)state;
    const int w = 96, h = 80;
    scene sc;
    scene_init(&sc, w, h, 70, 3);
    svp_image *ref = test_image(w, h), *mov = test_image(w, h);
    const double T[6] = {1, 0, 3.7, 0, 1, -2.2};
    render_pair(&sc, T, ref, mov);
    for (int i = 0; i < w * h; i++) mov->data[i] = 5 - 2 * mov->data[i];
    svp_register_options o;
    svp_register_defaults(&o);
    assert_int_equal(o.contrast, SVP_CONTRAST_AUTO);
    svp_register_result r, forced, same;
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    const double err = hypot(r.affine[2] - 3.7, r.affine[5] + 2.2);
    print_message("inverted pair: error %.2e px, significance %.1f (peak %.1f), correlation "
                  "%.4f\n",
                  err, r.significance, r.significance_other, r.correlation);
    assert_int_equal(r.inverted, 1);
    assert_int_equal(r.low_significance, 0);
    assert_true(err < 0.05);
    assert_true(r.significance > 2 * o.min_significance && r.significance_other < 10);
    assert_true(r.correlation > 0.99); /* of the inverted moving image */

    o.contrast = SVP_CONTRAST_INVERTED;
    ASSERT_OK(svp_register(ref, mov, &o, &forced));
    assert_int_equal(forced.inverted, 1);
    assert_true(forced.affine[2] == r.affine[2] && forced.affine[5] == r.affine[5]);
    assert_true(forced.significance == r.significance);

    o.contrast = SVP_CONTRAST_SAME; /* the sign-blind search of before: a wrong answer, flagged */
    ASSERT_OK(svp_register(ref, mov, &o, &same));
    print_message("inverted pair registered as the same contrast: significance %.1f\n",
                  same.significance);
    assert_int_equal(same.inverted, 0);
    assert_int_equal(same.low_significance, 1);

    o.contrast = SVP_CONTRAST_AUTO;
    o.method = SVP_REGISTER_ECC;
    o.motion = SVP_MOTION_TRANSLATION;
    ASSERT_OK(svp_register(ref, mov, &o, &forced));
    assert_int_equal(forced.inverted, 1);
    assert_true(hypot(forced.affine[2] - 3.7, forced.affine[5] + 2.2) < 0.05);

    /* the positive pair: SAME detected */
    render_pair(&sc, T, ref, mov);
    svp_register_defaults(&o);
    ASSERT_OK(svp_register(ref, mov, &o, &r));
    assert_int_equal(r.inverted, 0);
    assert_true(r.significance > 2 * o.min_significance && r.significance_other < 10);
    assert_true(hypot(r.affine[2] - 3.7, r.affine[5] + 2.2) < 0.05);

    o.contrast = (svp_register_contrast)7;
    assert_int_equal(svp_register(ref, mov, &o, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "contrast 7"));
    svp_image_free(ref);
    svp_image_free(mov);
}

/* ---- sub-pixel shifts and cube alignment ---------------------------------------------------- */

/* svp_shift against the scene rendered analytically at the shifted position: Fourier
 * interpolation is exact for a band-limited image, bilinear (svp_warp) smooths. Measured on the
 * interior (8 px from the edges; the blobs reach beyond the frame, so the edge pixels are the
 * mirror's): max error 2.1e-4 of the range against 2.1e-2 bilinear for (0.37, −0.81). Also: a
 * shift and its inverse give the image back; a NaN pixel moves with the content; bad input. */
static void test_shift_fourier(void **state)
{
    (void)state;
    const int w = 96, h = 80, m = 8;
    scene sc;
    scene_init(&sc, w, h, 90, 7);
    svp_image *img = test_image(w, h), *truth = test_image(w, h), *out = test_image(w, h);
    svp_image *bil = test_image(w, h), *back = test_image(w, h);
    const double shifts[][2] = {{0.37, -0.81}, {-0.5, 0.5}, {2.25, 1.1}, {0.02, 0}};
    for (size_t k = 0; k < sizeof shifts / sizeof shifts[0]; k++) {
        const double dx = shifts[k][0], dy = shifts[k][1];
        double lo = INFINITY, hi = -INFINITY;
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                const double v = scene_at(&sc, x, y);
                img->data[(size_t)y * w + x] = v;
                truth->data[(size_t)y * w + x] = scene_at(&sc, x - dx, y - dy);
                lo = fmin(lo, v);
                hi = fmax(hi, v);
            }
        ASSERT_OK(svp_shift(img, dx, dy, out));
        const double A[6] = {1, 0, -dx, 0, 1, -dy}; /* out(x) = img(x − d) */
        ASSERT_OK(svp_warp(img, A, SVP_INTERP_LINEAR, 0, bil));
        double e_f = 0, e_b = 0, e_back = 0, e_edge = 0;
        ASSERT_OK(svp_shift(out, -dx, -dy, back));
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                const size_t i = (size_t)y * w + x;
                if (x < m || y < m || x >= w - m || y >= h - m) {
                    e_edge = fmax(e_edge, fabs(out->data[i] - truth->data[i]));
                    continue;
                }
                e_f = fmax(e_f, fabs(out->data[i] - truth->data[i]));
                e_b = fmax(e_b, fabs(bil->data[i] - truth->data[i]));
                e_back = fmax(e_back, fabs(back->data[i] - img->data[i]));
            }
        e_f /= hi - lo, e_b /= hi - lo, e_back /= hi - lo, e_edge /= hi - lo;
        print_message("shift (%g, %g): Fourier %.2e (%.2e in the %d px at the edges), bilinear "
                      "%.2e, there and back %.2e of the range\n",
                      dx, dy, e_f, e_edge, m, e_b, e_back);
        assert_true(e_f < 2e-3);
        assert_true(e_back < 2e-3);
        if (fabs(dx - round(dx)) > 0.1) assert_true(e_f < 0.1 * e_b);
    }
    /* in place, and a NaN pixel moves with the content (to the nearest pixel) */
    img->data[(size_t)40 * w + 30] = NAN;
    ASSERT_OK(svp_shift(img, 2.3, -1.2, img));
    size_t n_nan = 0;
    for (size_t i = 0; i < (size_t)w * h; i++) n_nan += isnan(img->data[i]);
    assert_int_equal(n_nan, 1);
    assert_true(isnan(img->data[(size_t)39 * w + 32]));
    /* bad input */
    assert_int_equal(svp_shift(img, w, 0, out), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "below the size"));
    assert_int_equal(svp_shift(img, NAN, 0, out), SVP_ERR_INVALID);
    svp_image *small = test_image(8, 8);
    assert_int_equal(svp_shift(img, 0, 0, small), SVP_ERR_SIZE);
    svp_image_free(small);
    svp_image_free(img);
    svp_image_free(truth);
    svp_image_free(out);
    svp_image_free(bil);
    svp_image_free(back);
}

/* An ODMR sweep during which the sample drifts: every frame is the scene (PL and field)
 * rendered analytically at its own position d_f, with two Lorentzian dips of 3 % contrast at
 * D ± γB(x) (B up to 120 µT). `still` is the same sweep without drift, at the mean position;
 * `drifted` gets the drift: (0.3, −0.12) px × t, t = f / (nf − 1) (linear) or × t²
 * (quadratic). */
#define ALIGN_W 72
#define ALIGN_H 64
#define ALIGN_NF 60
static void drift_sweep(const scene *sc, const svp_odmr *od, const double *freq, int quadratic,
                        double *dx, double *dy, svp_cube *still, svp_cube *drifted)
{
    const int w = ALIGN_W, h = ALIGN_H, nf = ALIGN_NF;
    double mx = 0, my = 0;
    for (int f = 0; f < nf; f++) {
        const double t = (double)f / (nf - 1), u = quadratic ? t * t : t;
        dx[f] = 0.3 * u;
        dy[f] = -0.12 * u;
        mx += dx[f] / nf;
        my += dy[f] / nf;
    }
    for (int f = 0; f < nf; f++) {
        dx[f] -= mx; /* from now on: the displacement from the mean position */
        dy[f] -= my;
    }
    const double g = od->gamma_hz_per_t, D = od->zero_field_hz, G = od->linewidth_hz / 2;
    for (int f = 0; f < nf; f++)
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++)
                for (int k = 0; k < 2; k++) {
                    const double sx = x - (k ? dx[f] : 0), sy = y - (k ? dy[f] : 0);
                    const double pl = 0.2 + scene_at(sc, sx, sy);
                    const double r2 = (sx - 36) * (sx - 36) + (sy - 30) * (sy - 30);
                    const double b = 120e-6 * exp(-r2 / (2 * 12.0 * 12.0));
                    double dip = 0;
                    for (int s = -1; s <= 1; s += 2) {
                        const double v = freq[f] - (D + s * g * b);
                        dip += G * G / (v * v + G * G);
                    }
                    (k ? drifted : still)->frame[f]->data[(size_t)y * w + x] =
                        pl * (1 - od->contrast * dip);
                }
}

/* The centroid field of a cube, its baseline from 3 frames at each end. */
static void centroid_of(const svp_odmr *od, const svp_cube *c, svp_image *base, svp_image *field)
{
    const int nf = c->n_freq;
    for (size_t p = 0; p < (size_t)c->width * c->height; p++) {
        double b = 0;
        for (int e = 0; e < 3; e++) b += c->frame[e]->data[p] + c->frame[nf - 1 - e]->data[p];
        base->data[p] = b / 6;
    }
    ASSERT_OK(svp_odmr_centroid(od, c, base, 0, 0, field, NULL));
}

static double interior_rms(const svp_image *a, const svp_image *b, int m)
{
    double e = 0, n = 0;
    for (int y = m; y < a->height - m; y++)
        for (int x = m; x < a->width - m; x++) {
            const size_t i = (size_t)y * a->width + x;
            e += (a->data[i] - b->data[i]) * (a->data[i] - b->data[i]);
            n++;
        }
    return sqrt(e / n);
}

/* svp_cube_align on the drifting sweeps. A frame on a resonance is pulled off by its dips (up
 * to 0.024 px measured frame by frame, degree −1); the robust polynomial drift puts every
 * frame within 3.6e-4 px (linear drift, degree 1) and 9.4e-4 px (quadratic drift, degree 2)
 * of its true displacement (asserted 2e-3), and the centroid field of the aligned cube matches
 * the drift-free sweep: interior rms error (6 px from the edges) 0.099 µT against 9.05 µT
 * drifted (linear), 2.0 µT against 503 µT (quadratic: a drift symmetric about the sweep's
 * middle does not cancel in the centroid's |ω − D| weights; the fit's residual there is the
 * extrapolation over the resonance frames); asserted 3× better. Frame by frame (degree −1)
 * 4.9 µT: the dips' pull. */
static void test_cube_align(void **state)
{
    (void)state;
    const int w = ALIGN_W, h = ALIGN_H, nf = ALIGN_NF;
    scene sc;
    scene_init(&sc, w, h, 70, 11);
    svp_odmr od;
    svp_odmr_defaults(&od);
    od.contrast = 0.03;
    double freq[ALIGN_NF], dx[ALIGN_NF], dy[ALIGN_NF], sx[ALIGN_NF], sy[ALIGN_NF];
    ASSERT_OK(svp_odmr_sweep(&od, 150e-6, 6, nf, freq));
    svp_cube *drifted = NULL, *still = NULL;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &drifted));
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &still));
    svp_image *base = test_image(w, h), *b_still = test_image(w, h), *b_drift = test_image(w, h);
    svp_image *b_aligned = test_image(w, h);
    const int cases[][2] = {{0, 1}, {1, 2}, {0, -1}}; /* quadratic?, degree */
    for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        const int degree = cases[c][1];
        drift_sweep(&sc, &od, freq, cases[c][0], dx, dy, still, drifted);
        centroid_of(&od, still, base, b_still);
        centroid_of(&od, drifted, base, b_drift);
        svp_align_info info;
        svp_align_options ao;
        svp_align_defaults(&ao);
        ao.degree = degree;
        ASSERT_OK(svp_cube_align(drifted, &ao, sx, sy, &info, NULL, NULL));
        centroid_of(&od, drifted, base, b_aligned);
        double worst = 0, largest = 0;
        for (int f = 0; f < nf; f++) {
            worst = fmax(worst, hypot(sx[f] - dx[f], sy[f] - dy[f]));
            largest = fmax(largest, hypot(dx[f], dy[f]));
        }
        const double e_drift = interior_rms(b_drift, b_still, 6);
        const double e_aligned = interior_rms(b_aligned, b_still, 6);
        print_message("cube alignment, %s drift, degree %d: shifts within %.1e px (largest "
                      "%.3f px; measured shifts off the fit by up to %.3f px, typically %.1e; "
                      "lowest correlation %.4f); centroid rms error %.2f uT drifted, %.3f uT "
                      "aligned\n",
                      cases[c][0] ? "quadratic" : "linear", degree, worst, info.max_shift,
                      info.max_deviation, info.median_deviation, info.min_correlation,
                      e_drift * 1e6, e_aligned * 1e6);
        ASSERT_CLOSE(info.max_shift, largest, 2e-3);
        assert_int_equal(info.n_low_correlation, 0);
        assert_true(info.min_correlation > 0.99);
        assert_true(e_drift > 5e-6);
        if (degree >= 0) {
            assert_true(worst < 2e-3);
            assert_true(e_aligned < e_drift / 3);
        } else {
            assert_true(info.max_deviation == 0 && info.median_deviation == 0);
        }
    }
    /* 1 and 2 threads: the same frames bit for bit (one-thread transforms either way);
     * progress monotone to 1, from the calling thread; a cancel stops the call */
    svp_cube *two = NULL;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &two));
    drift_sweep(&sc, &od, freq, 0, dx, dy, still, drifted);
    for (int f = 0; f < nf; f++)
        memcpy(two->frame[f]->data, drifted->frame[f]->data, (size_t)w * h * sizeof(double));
    const int threads = svp_get_threads();
    svp_set_threads(1);
    ASSERT_OK(svp_cube_align(drifted, NULL, NULL, NULL, NULL, NULL, NULL));
    svp_set_threads(2);
    test_progress_rec prog = {.monotone = 1};
    ASSERT_OK(svp_cube_align(two, NULL, NULL, NULL, NULL, test_progress_record, &prog));
    svp_set_threads(threads);
    for (int f = 0; f < nf; f++)
        assert_memory_equal(two->frame[f]->data, drifted->frame[f]->data,
                            (size_t)w * h * sizeof(double));
    assert_true(prog.calls > 0 && prog.monotone && prog.last == 1.0);
    prog = (test_progress_rec){.cancel_at = 5, .monotone = 1};
    assert_int_equal(svp_cube_align(two, NULL, NULL, NULL, NULL, test_progress_record, &prog),
                     SVP_ERR_CANCELLED);
    svp_cube_free(two);
    /* to frame 0's position: the shifts relative to frame 0's, and the frames at the drift's
     * start (frame 0 of the freshly drifted cube is then moved by 0) */
    drift_sweep(&sc, &od, freq, 0, dx, dy, still, drifted);
    svp_align_options ao;
    svp_align_defaults(&ao);
    ao.reference_frame = 0;
    svp_image *frame0 = test_image(w, h);
    memcpy(frame0->data, drifted->frame[0]->data, (size_t)w * h * sizeof(double));
    ASSERT_OK(svp_cube_align(drifted, &ao, sx, sy, NULL, NULL, NULL));
    assert_true(sx[0] == 0 && sy[0] == 0);
    double worst = 0;
    for (int f = 0; f < nf; f++)
        worst = fmax(worst, hypot(sx[f] - (dx[f] - dx[0]), sy[f] - (dy[f] - dy[0])));
    assert_true(worst < 2e-3);
    for (size_t i = 0; i < (size_t)w * h; i++) ASSERT_CLOSE(drifted->frame[0]->data[i], frame0->data[i], 1e-9);
    svp_image_free(frame0);
    /* a missing frame (NaN at every pixel, a failed frame): it has no say in the drift, stays
     * NaN, and gets the polynomial's shift at its place in the sweep; the other frames' shifts
     * as good as without it. With degree -1 it has no shift of its own: as the reference it is
     * refused */
    drift_sweep(&sc, &od, freq, 0, dx, dy, still, drifted);
    for (size_t i = 0; i < (size_t)w * h; i++) drifted->frame[17]->data[i] = NAN;
    svp_align_info info;
    svp_align_defaults(&ao);
    ASSERT_OK(svp_cube_align(drifted, &ao, sx, sy, &info, NULL, NULL));
    worst = 0;
    for (int f = 0; f < nf; f++) worst = fmax(worst, hypot(sx[f] - dx[f], sy[f] - dy[f]));
    print_message("a missing frame: shifts within %.1e px (frame 17 %.4f, %.4f px on the "
                  "polynomial; true %.4f, %.4f), lowest correlation %.4f\n",
                  worst, sx[17], sy[17], dx[17], dy[17], info.min_correlation);
    assert_true(worst < 2e-3 && info.n_low_correlation == 0 && info.min_correlation > 0.99);
    assert_int_equal(svp_image_count_nonfinite(drifted->frame[17]), (size_t)w * h);
    ao.degree = -1;
    ao.reference_frame = 17;
    assert_int_equal(svp_cube_align(drifted, &ao, NULL, NULL, NULL, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "reference frame 17 has no finite pixel"));
    svp_align_defaults(&ao);
    /* only translations; too few frames for the degree; a degree or reference out of range */
    svp_register_options o;
    svp_register_defaults(&o);
    o.motion = SVP_MOTION_AFFINE;
    ao.registration = &o;
    assert_int_equal(svp_cube_align(drifted, &ao, NULL, NULL, NULL, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "translation only"));
    svp_align_defaults(&ao);
    ao.degree = 2;
    drifted->n_freq = 3;
    assert_int_equal(svp_cube_align(drifted, &ao, NULL, NULL, NULL, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "at least 4 needed"));
    drifted->n_freq = nf;
    ao.degree = 6;
    assert_int_equal(svp_cube_align(drifted, &ao, NULL, NULL, NULL, NULL, NULL), SVP_ERR_INVALID);
    ao.degree = 1;
    ao.reference_frame = nf;
    assert_int_equal(svp_cube_align(drifted, &ao, NULL, NULL, NULL, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "reference frame 60 of 60"));
    svp_image_free(base);
    svp_image_free(b_still);
    svp_image_free(b_drift);
    svp_image_free(b_aligned);
    svp_cube_free(drifted);
    svp_cube_free(still);
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_phase_subpixel),
        cmocka_unit_test(test_direction),
        cmocka_unit_test(test_spot_pair),
        cmocka_unit_test(test_ecc_affine),
        cmocka_unit_test(test_ecc_euclidean_translation),
        cmocka_unit_test(test_mask_warp),
        cmocka_unit_test(test_warp_properties),
        cmocka_unit_test(test_affine_invert),
        cmocka_unit_test(test_bad_input),
        cmocka_unit_test(test_ecc_failures),
        cmocka_unit_test(test_inverted_contrast),
        cmocka_unit_test(test_shift_fourier),
        cmocka_unit_test(test_cube_align),
    };
    int failed = cmocka_run_group_tests(tests, NULL, NULL);
    svp_fft_cleanup();
    return failed;
}
