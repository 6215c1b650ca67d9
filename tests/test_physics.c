/* Physics: source fields against closed forms and a Biot–Savart sum, every sign of the
 * reconstruction pinned against the closed-form strip and flake, the ODMR centroid against
 * eq. (3). Frame: x along columns, y along rows (down), z = x × y; sensor on +z for side +1. */
#include "test_helpers.h"

#include <omp.h>

#include <stdio.h>

#include "core/internal.h" /* svp_fft_cleanup */

#define MU0 1.25663706212e-6

/* ---- independent references ------------------------------------------------------------- */

/* Field of the strip from a sum of straight filaments (Biot–Savart for infinite wires:
 * B = μ0 dI (u × r⊥) / (2π |r⊥|²)), written without the library's n = u × z or its closed
 * form. Point (px, py) and strip centre in metres, sensor at z = side · h. */
static void strip_biot_savart(double width, double J, double cx, double cy, double angle,
                              double h, int side, double px, double py, double b[3])
{
    const int n = 40000;
    double ux = cos(angle), uy = sin(angle);
    /* the filaments sit across the strip: along the in-plane perpendicular (−u_y, u_x) */
    double ex = -uy, ey = ux;
    b[0] = b[1] = b[2] = 0;
    double deta = width / n;
    for (int k = 0; k < n; k++) {
        double eta = -0.5 * width + (k + 0.5) * deta;
        double rx = px - (cx + eta * ex), ry = py - (cy + eta * ey), rz = side * h;
        double along = rx * ux + ry * uy;
        rx -= along * ux;
        ry -= along * uy;
        double r2 = rx * rx + ry * ry + rz * rz;
        double c = MU0 * J * deta / (2 * M_PI * r2);
        /* u × r⊥ with u_z = 0 */
        b[0] += c * (uy * rz);
        b[1] += c * (-ux * rz);
        b[2] += c * (ux * ry - uy * rx);
    }
}

/* Exact field of a uniformly magnetised thin rectangle [x1, x2] × [y1, y2] (areal moment m, A)
 * at (x, y, z): a dipole sheet, φ = m Ω / 4π with Ω the solid angle; H = −∇φ summed over the
 * corners (−1)^(i+j). Written from the solid angle atan(XY / (z r)), not from Fourier space. */
static void rectangle_field(double m, double x1, double x2, double y1, double y2, double x,
                            double y, double z, double b[3])
{
    const double xs[2] = {x1 - x, x2 - x}, ys[2] = {y1 - y, y2 - y};
    double hx = 0, hy = 0, hz = 0;
    for (int i = 0; i < 2; i++)
        for (int j = 0; j < 2; j++) {
            double sg = (i == j) ? 1 : -1;
            double X = xs[i], Y = ys[j], r = sqrt(X * X + Y * Y + z * z);
            hz += sg * X * Y * (r * r + z * z) / (r * (X * X + z * z) * (Y * Y + z * z));
            hx += sg * Y * z / (r * (X * X + z * z));
            hy += sg * X * z / (r * (Y * Y + z * z));
        }
    double c = MU0 * m / (4 * M_PI);
    b[0] = c * hx;
    b[1] = c * hy;
    b[2] = c * hz;
}

/* B_z on the pixel centres of img (pixel size px) of a square flake of 1 mA covering
 * [x1, x2]² pixels, at height z; returns the largest |B_z|. */
static double square_flake_bz(svp_image *img, double px, double x1, double x2, double z)
{
    double peak = 0;
    for (int j = 0; j < img->height; j++)
        for (int i = 0; i < img->width; i++) {
            double v[3];
            rectangle_field(1e-3, x1 * px, x2 * px, x1 * px, x2 * px, i * px, j * px, z, v);
            img->data[(size_t)j * img->width + i] = v[2];
            peak = fmax(peak, fabs(v[2]));
        }
    return peak;
}

static svp_sensor sensor_of(double pixel, double h, int side)
{
    svp_sensor s;
    svp_sensor_defaults(&s);
    s.pixel_m = pixel;
    s.standoff_m = h;
    s.side = side;
    return s;
}

static double at(const svp_image *img, int i, int j) { return img->data[(size_t)j * img->width + i]; }

/* ---- strip ------------------------------------------------------------------------------ */

static void test_strip_closed_form(void **state)
{
    (void)state;
    const double h = 100e-9, pixel = 100e-9, J = 200, w = 40e-6;
    svp_sensor s = sensor_of(pixel, h, 1);
    svp_strip st;
    svp_strip_defaults(&st);
    ASSERT_CLOSE(st.width_m, w, 0);
    ASSERT_CLOSE(st.sheet_current, J, 0);
    st.centre_x = 300;
    st.centre_y = 1;
    svp_image *bx = test_image(601, 3), *by = test_image(601, 3), *bz = test_image(601, 3);
    ASSERT_OK(svp_strip_field(&st, &s, bx, by, bz));
    /* at the centre: (μ0 J / π) atan(w / 2h), to 1e-6 relative */
    double expect = MU0 * J / M_PI * atan(w / (2 * h));
    double got = at(bx, 300, 1);
    if (!(fabs(got - expect) <= 1e-6 * expect))
        fail_msg("strip B_x at the centre %.12g T, closed form %.12g T", got, expect);
    /* far inside a wide strip → μ0 J / 2 (126 µT); the centre is 2/(π·200) = 0.32 % below */
    ASSERT_CLOSE(got / (0.5 * MU0 * J), 1 - 2 / (M_PI * 200), 1e-6);
    ASSERT_CLOSE(0.5 * MU0 * J, 125.66e-6, 0.01e-6);
    /* current along +y: B_y = 0, B_z < 0 on the +x side, > 0 on the −x side, 0 at the centre */
    ASSERT_CLOSE(test_max_abs(by), 0, 1e-20);
    if (!(at(bz, 450, 1) < 0 && at(bz, 150, 1) > 0))
        fail_msg("strip B_z signs: +x side %g, -x side %g", at(bz, 450, 1), at(bz, 150, 1));
    ASSERT_CLOSE(at(bz, 300, 1), 0, 1e-18);
    svp_image_free(bx);
    svp_image_free(by);
    svp_image_free(bz);
}

/* Rotated strips, both sensor sides, against the filament sum: pins the angle convention, the
 * y orientation (rows down) and the side. */
static void test_strip_biot_savart(void **state)
{
    (void)state;
    const double h = 100e-9, pixel = 50e-9, J = 200, w = 2e-6;
    const double angles[] = {0, M_PI / 6, M_PI / 2, 2.0};
    double worst = 0;
    for (int side = -1; side <= 1; side += 2) {
        for (size_t a = 0; a < sizeof angles / sizeof angles[0]; a++) {
            svp_sensor s = sensor_of(pixel, h, side);
            svp_strip st;
            svp_strip_defaults(&st);
            st.width_m = w;
            st.angle = angles[a];
            st.centre_x = 30.3;
            st.centre_y = 28.7;
            svp_image *b[3] = {test_image(64, 64), test_image(64, 64), test_image(64, 64)};
            ASSERT_OK(svp_strip_field(&st, &s, b[0], b[1], b[2]));
            const int pts[][2] = {{30, 28}, {5, 9}, {50, 60}, {33, 31}, {12, 40}, {45, 20}};
            for (size_t p = 0; p < sizeof pts / sizeof pts[0]; p++) {
                int i = pts[p][0], j = pts[p][1];
                double ref[3];
                strip_biot_savart(w, J, st.centre_x * pixel, st.centre_y * pixel, st.angle, h,
                                  side, i * pixel, j * pixel, ref);
                for (int c = 0; c < 3; c++) {
                    double err = fabs(at(b[c], i, j) - ref[c]) / (0.5 * MU0 * J);
                    if (err > worst) worst = err;
                    if (err > 1e-4)
                        fail_msg("side %d angle %g pixel (%d, %d) component %d: closed form %g, "
                                 "Biot-Savart %g", side, st.angle, i, j, c, at(b[c], i, j),
                                 ref[c]);
                }
            }
            for (int c = 0; c < 3; c++) svp_image_free(b[c]);
        }
    }
    print_message("strip closed form vs filament sum: max error %.2e of mu0 J/2\n", worst);
}

/* Current along +x (angle 0), sensor above: by the right-hand rule B_z > 0 on the rows below
 * the wire (larger row index) and B_y < 0 over it. */
static void test_strip_y_orientation(void **state)
{
    (void)state;
    svp_sensor s = sensor_of(100e-9, 100e-9, 1);
    svp_strip st;
    svp_strip_defaults(&st);
    st.width_m = 1e-6;
    st.angle = 0;
    st.centre_x = 10;
    st.centre_y = 20;
    svp_image *by = test_image(21, 41), *bz = test_image(21, 41), *bx = test_image(21, 41);
    ASSERT_OK(svp_strip_field(&st, &s, bx, by, bz));
    if (!(at(bz, 10, 30) > 0 && at(bz, 10, 10) < 0))
        fail_msg("B_z below the wire (row 30) %g should be > 0, above (row 10) %g < 0",
                 at(bz, 10, 30), at(bz, 10, 10));
    if (!(at(by, 10, 20) < 0)) fail_msg("B_y over the wire %g should be < 0", at(by, 10, 20));
    ASSERT_CLOSE(test_max_abs(bx), 0, 1e-20);
    svp_image_free(bx);
    svp_image_free(by);
    svp_image_free(bz);
}

/* The strip's closed form at a plane, written here from docs/model.md §11, eq. 16 (current along +y). */
static void strip_plane(double xi, double w, double J, double h, double *bxv, double *bzv)
{
    double a = 0.5 * w;
    *bxv = MU0 * J / (2 * M_PI) * (atan((a + xi) / h) + atan((a - xi) / h));
    *bzv = MU0 * J / (4 * M_PI) * log(((xi - a) * (xi - a) + h * h) / ((xi + a) * (xi + a) + h * h));
}

static void test_strip_nv_layer(void **state)
{
    (void)state;
    const double h = 100e-9, t = 60e-9, pixel = 20e-9, J = 200, w = 1e-6;
    svp_sensor s = sensor_of(pixel, h, 1);
    s.nv_thickness_m = t;
    svp_strip st;
    svp_strip_defaults(&st);
    st.width_m = w;
    st.angle = M_PI / 2;
    st.centre_x = 40;
    svp_image *ax = test_image(81, 1), *az = test_image(81, 1);
    ASSERT_OK(svp_strip_field(&st, &s, ax, NULL, az));
    /* reference: the plane field averaged over the layer by 4000-point midpoint quadrature */
    const int nq = 4000;
    double worst = 0;
    for (int i = 0; i < 81; i++) {
        double sx = 0, sz = 0, vx, vz;
        for (int q = 0; q < nq; q++) {
            strip_plane((i - 40) * pixel, w, J, h - 0.5 * t + (q + 0.5) * t / nq, &vx, &vz);
            sx += vx / nq;
            sz += vz / nq;
        }
        worst = fmax(worst, fmax(fabs(ax->data[i] - sx), fabs(az->data[i] - sz)));
    }
    print_message("strip averaged over a 60 nm NV layer: max difference from quadrature %.2e "
                  "of mu0 J/2\n", worst / (0.5 * MU0 * J));
    if (worst > 1e-6 * 0.5 * MU0 * J) fail_msg("layer average: max difference %g T", worst);
    svp_image_free(ax);
    svp_image_free(az);
}

/* ---- shapes ----------------------------------------------------------------------------- */

static void test_raster_shapes(void **state)
{
    (void)state;
    svp_image *img = test_image(40, 30);
    const double tri[] = {3.2, 4.1, 30.7, 8.9, 12.4, 25.3};
    ASSERT_OK(svp_raster_polygon(img, tri, 3, 2.0));
    double area = 0.5 * fabs((30.7 - 3.2) * (25.3 - 4.1) - (12.4 - 3.2) * (8.9 - 4.1));
    ASSERT_CLOSE(test_sum(img), 2 * area, 1e-10);
    memset(img->data, 0, 40 * 30 * sizeof(double));
    /* a concave polygon (an L) and the reverse orientation */
    const double ell[] = {2, 2, 20, 2, 20, 8, 8, 8, 8, 20, 2, 20};
    ASSERT_OK(svp_raster_polygon(img, ell, 6, 1.0));
    ASSERT_CLOSE(test_sum(img), 18 * 6 + 6 * 12, 1e-10);
    memset(img->data, 0, 40 * 30 * sizeof(double));
    ASSERT_OK(svp_raster_rectangle(img, 20.3, 14.6, 12.5, 7.25, 0.4, 1.0));
    ASSERT_CLOSE(test_sum(img), 12.5 * 7.25, 1e-10);
    for (size_t p = 0; p < 40 * 30; p++)
        if (img->data[p] < -1e-15 || img->data[p] > 1 + 1e-12) fail_msg("coverage %g", img->data[p]);
    memset(img->data, 0, 40 * 30 * sizeof(double));
    ASSERT_OK(svp_raster_disk(img, 19.7, 15.2, 9.3, 1.0));
    ASSERT_CLOSE(test_sum(img) / (M_PI * 9.3 * 9.3), 1, 1e-3);
    assert_int_equal(svp_raster_polygon(img, tri, 2, 1.0), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "polygon: 2 vertices, at least 3 needed");
    svp_image_free(img);
}

/* ---- flake ------------------------------------------------------------------------------ */

/* A 10 x 6 µm flake, M_z t = 1 mA, h = 100 nm, 50 nm pixels, edges on pixel boundaries. */
#define FL_N 384
#define FL_PIX 50e-9
#define FL_H 100e-9
static const double fl_x1 = 91.5, fl_x2 = 291.5, fl_y1 = 131.5, fl_y2 = 251.5; /* pixels */

static svp_image *flake_moment(void)
{
    svp_image *m = test_image(FL_N, FL_N);
    const double xy[] = {fl_x1, fl_y1, fl_x2, fl_y1, fl_x2, fl_y2, fl_x1, fl_y2};
    ASSERT_OK(svp_raster_polygon(m, xy, 4, 1e-3));
    return m;
}

static void flake_exact(int side, svp_image *b[3])
{
    for (int j = 0; j < FL_N; j++)
        for (int i = 0; i < FL_N; i++) {
            double v[3];
            rectangle_field(1e-3, fl_x1 * FL_PIX, fl_x2 * FL_PIX, fl_y1 * FL_PIX,
                            fl_y2 * FL_PIX, i * FL_PIX, j * FL_PIX, side * FL_H, v);
            for (int c = 0; c < 3; c++) b[c]->data[(size_t)j * FL_N + i] = v[c];
        }
}

static void test_flake_fourier_vs_closed_form(void **state)
{
    (void)state;
    svp_image *m = flake_moment();
    for (int side = -1; side <= 1; side += 2) {
        svp_sensor s = sensor_of(FL_PIX, FL_H, side);
        svp_image *b[3], *e[3];
        for (int c = 0; c < 3; c++) {
            b[c] = test_image(FL_N, FL_N);
            e[c] = test_image(FL_N, FL_N);
        }
        ASSERT_OK(svp_flake_field(m, 0, &s, 2, b[0], b[1], b[2]));
        flake_exact(side, e);
        double peak = test_max_abs(e[2]);
        /* B_z peaks near 2 mT at the edges (μ0 m / (π h) · ½ for a straight edge ≈ 2 mT) */
        if (!(peak > 1.5e-3 && peak < 2.5e-3)) fail_msg("flake peak B_z %g T", peak);
        /* compare everywhere and away from the edges (>= 4 h) */
        double worst_all = 0, worst_far = 0;
        for (int j = 0; j < FL_N; j++)
            for (int i = 0; i < FL_N; i++) {
                double dx = fmin(fabs(i - fl_x1), fabs(i - fl_x2));
                double dy = fmin(fabs(j - fl_y1), fabs(j - fl_y2));
                int near = (dx < 8 && j > fl_y1 - 8 && j < fl_y2 + 8) ||
                           (dy < 8 && i > fl_x1 - 8 && i < fl_x2 + 8);
                for (int c = 0; c < 3; c++) {
                    double d = fabs(at(b[c], i, j) - at(e[c], i, j)) / peak;
                    worst_all = fmax(worst_all, d);
                    if (!near) worst_far = fmax(worst_far, d);
                }
            }
        print_message("flake side %+d: Fourier vs exact, max error %.2e of the peak (all), "
                      "%.2e (>= 4h from edges)\n", side, worst_all, worst_far);
        if (worst_far > 2e-3 || worst_all > 0.1)
            fail_msg("side %d: Fourier flake field differs from the exact one: %g (far), %g",
                     side, worst_far, worst_all);
        /* docs/model.md §11 signs, M_z > 0: B_z > 0 just inside an edge, < 0 just outside; the same on
         * both sides. In-plane: above (+z), B_x points outwards across the right edge. */
        int yc = (int)(0.5 * (fl_y1 + fl_y2)), xr = (int)(fl_x2 + 0.5);
        if (!(at(b[2], xr - 2, yc) > 0 && at(b[2], xr + 2, yc) < 0))
            fail_msg("B_z inside %g / outside %g the right edge", at(b[2], xr - 2, yc),
                     at(b[2], xr + 2, yc));
        if (!(side * at(b[0], xr, yc) > 0))
            fail_msg("side %d: B_x at the right edge %g", side, at(b[0], xr, yc));
        int xc = (int)(0.5 * (fl_x1 + fl_x2)), yb = (int)(fl_y2 + 0.5);
        if (!(side * at(b[1], xc, yb) > 0))
            fail_msg("side %d: B_y at the bottom edge %g", side, at(b[1], xc, yb));
        /* ∫ B_z over the view: the flux that leaves the view is missing from both alike */
        double sum = test_sum(b[2]), sum_exact = test_sum(e[2]), sabs = 0;
        for (size_t p = 0; p < (size_t)FL_N * FL_N; p++) sabs += fabs(b[2]->data[p]);
        print_message("flake side %+d: sum B_z / sum |B_z| = %.3e (exact field: %.3e) over a "
                      "%.1f um view\n", side, sum / sabs, sum_exact / sabs, FL_N * FL_PIX * 1e6);
        /* the periodic canvas (2x padded) has exactly zero flux, so it also folds in the flux
         * beyond the canvas: about 10 % of the (already small) missing flux, see
         * test_flake_flux */
        if (!(fabs(sum - sum_exact) < 0.15 * fabs(sum_exact)))
            fail_msg("flux %g vs exact %g", sum, sum_exact);
        for (int c = 0; c < 3; c++) {
            svp_image_free(b[c]);
            svp_image_free(e[c]);
        }
    }
    svp_image_free(m);
}

/* The flux vanishes over the whole plane: over a view much larger than the flake only the
 * dipole far field outside the view is missing, and that is known: a view of side L holds the
 * flux of a point dipole M = m π a² through an L x L square (exact for the dipole: the flux
 * kernel is rectangle_field's with source and field point swapped), -> 0 as L grows. */
static void test_flake_flux(void **state)
{
    (void)state;
    const double pixel = 100e-9, h = 100e-9, a = 10, m = 1e-3;
    const int sizes[] = {128, 384};
    double prev = 0;
    for (int k = 0; k < 2; k++) {
        const int n = sizes[k];
        svp_image *mz = test_image(n, n), *bz = test_image(n, n), *bz2 = test_image(n, n);
        double c = 0.5 * (n - 1);
        ASSERT_OK(svp_raster_disk(mz, c, c, a, m));
        svp_sensor s = sensor_of(pixel, h, 1);
        /* pad 8: the periodic canvas's own zero flux then hides < 1 % of the far field */
        ASSERT_OK(svp_flake_field(mz, 1e-9, &s, k == 0 ? 8 : 4, NULL, NULL, bz));
        ASSERT_OK(svp_flake_field(mz, 1e-9, &s, 2, NULL, NULL, bz2));
        double sum = test_sum(bz), sabs = 0;
        for (size_t p = 0; p < (size_t)n * n; p++) sabs += fabs(bz->data[p]);
        double moment = test_sum(mz) * pixel * pixel, dip[3];
        double half = 0.5 * n * pixel;
        rectangle_field(1.0, -half, half, -half, half, 0, 0, h, dip);
        double flux = sum * pixel * pixel, flux_dipole = moment * dip[2];
        print_message("1 um-radius disc in a %.1f um view: sum B_z / sum |B_z| = %.2e; flux "
                      "%.4e T m^2 (pad 2: %.4e), point dipole through the view %.4e T m^2\n",
                      n * pixel * 1e6, sum / sabs, flux, test_sum(bz2) * pixel * pixel,
                      flux_dipole);
        if (!(fabs(flux - flux_dipole) < 0.02 * fabs(flux_dipole)))
            fail_msg("view %d: flux %g vs dipole %g", n, flux, flux_dipole);
        if (k > 0 && !(fabs(sum / sabs) < 0.45 * prev)) /* ~ 1/L: a third */
            fail_msg("the flux did not shrink with the view: %g then %g", prev, sum / sabs);
        prev = fabs(sum / sabs);
        svp_image_free(mz);
        svp_image_free(bz);
        svp_image_free(bz2);
    }
}

/* Finite thickness: (1 − e^(−kt)) / (kt) equals averaging the thin-film field over the depth. */
static void test_flake_thickness(void **state)
{
    (void)state;
    const int n = 96;
    svp_image *m = test_image(n, n), *thick = test_image(n, n), *avg = test_image(n, n);
    svp_image *one = test_image(n, n);
    ASSERT_OK(svp_raster_disk(m, 47.5, 47.5, 20, 1e-3));
    const double t = 80e-9, h = 100e-9;
    svp_sensor s = sensor_of(50e-9, h, 1);
    ASSERT_OK(svp_flake_field(m, t, &s, 2, NULL, NULL, thick));
    /* 8-point Gauss–Legendre over the depth [h, h + t] (e^(−kz) is smooth there) */
    const double gx[4] = {0.1834346424956498, 0.5255324099163290, 0.7966664774136267,
                          0.9602898564975363};
    const double gw[4] = {0.3626837833783620, 0.3137066458778873, 0.2223810344533745,
                          0.1012285362903763};
    for (int q = 0; q < 8; q++) {
        double x = (q < 4 ? -1 : 1) * gx[q % 4], wq = gw[q % 4];
        s.standoff_m = h + 0.5 * t * (1 + x);
        ASSERT_OK(svp_flake_field(m, 0, &s, 2, NULL, NULL, one));
        for (size_t p = 0; p < (size_t)n * n; p++) avg->data[p] += 0.5 * wq * one->data[p];
    }
    double err = test_max_abs_diff(thick, avg) / test_max_abs(avg);
    print_message("flake thickness factor vs depth average: %.2e of the peak\n", err);
    if (err > 1e-8) fail_msg("thickness factor vs depth average: %g", err);
    /* NV layer: sinh(a)/a equals averaging the plane field over [h − t_NV/2, h + t_NV/2] */
    const double tnv = 120e-9;
    s.standoff_m = h;
    s.nv_thickness_m = tnv;
    ASSERT_OK(svp_flake_field(m, 0, &s, 2, NULL, NULL, thick));
    s.nv_thickness_m = 0;
    memset(avg->data, 0, (size_t)n * n * sizeof(double));
    for (int q = 0; q < 8; q++) {
        double x = (q < 4 ? -1 : 1) * gx[q % 4], wq = gw[q % 4];
        s.standoff_m = h + 0.5 * tnv * x;
        ASSERT_OK(svp_flake_field(m, 0, &s, 2, NULL, NULL, one));
        for (size_t p = 0; p < (size_t)n * n; p++) avg->data[p] += 0.5 * wq * one->data[p];
    }
    err = test_max_abs_diff(thick, avg) / test_max_abs(avg);
    print_message("NV layer factor vs layer average: %.2e of the peak\n", err);
    if (err > 1e-8) fail_msg("NV layer factor vs layer average: %g", err);
    /* and the reconstruction divides it out: periodic round trip, no window */
    s.standoff_m = h;
    s.nv_thickness_m = tnv;
    ASSERT_OK(svp_flake_field(m, t, &s, 1, NULL, NULL, thick));
    svp_recon_options o;
    svp_recon_defaults(&o);
    o.sensor = s;
    o.source_thickness_m = t;
    o.pad = SVP_PAD_NONE;
    o.window = 0;
    ASSERT_OK(svp_reconstruct_magnetisation(thick, &o, avg));
    err = test_max_abs_diff(avg, m);
    print_message("round trip with t = 80 nm, t_NV = 120 nm: max |error| %.2e mA\n", err * 1e3);
    if (err > 1e-12) fail_msg("round trip with thicknesses: %g A", err);
    svp_image_free(m);
    svp_image_free(thick);
    svp_image_free(avg);
    svp_image_free(one);
}

/* In-plane from out-of-plane: the exact B_z of the flake through −i s (k/k) gives the exact
 * B_x and B_y (pins the sign of the relation for both sides). */
static void test_inplane_from_bz(void **state)
{
    (void)state;
    for (int side = -1; side <= 1; side += 2) {
        svp_image *e[3], *bx = test_image(FL_N, FL_N), *by = test_image(FL_N, FL_N);
        for (int c = 0; c < 3; c++) e[c] = test_image(FL_N, FL_N);
        flake_exact(side, e);
        svp_recon_options o;
        svp_recon_defaults(&o);
        o.sensor = sensor_of(FL_PIX, FL_H, side);
        o.window = 0;
        ASSERT_OK(svp_inplane_from_bz(e[2], &o, bx, by));
        double peak = test_max_abs(e[0]), worst = 0;
        for (int j = 40; j < FL_N - 40; j++)
            for (int i = 40; i < FL_N - 40; i++) {
                worst = fmax(worst, fabs(at(bx, i, j) - at(e[0], i, j)));
                worst = fmax(worst, fabs(at(by, i, j) - at(e[1], i, j)));
            }
        print_message("in-plane from B_z, side %+d: max error %.2e of the peak B_x\n", side,
                      worst / peak);
        if (worst > 0.02 * peak) fail_msg("side %d: in-plane error %g of %g", side, worst, peak);
        for (int c = 0; c < 3; c++) svp_image_free(e[c]);
        svp_image_free(bx);
        svp_image_free(by);
    }
}

/* ---- reconstruction --------------------------------------------------------------------- */

static void test_reconstruct_magnetisation(void **state)
{
    (void)state;
    /* 20 µm square flake, 1 mA, h = 100 nm, 100 nm pixels, 512² view (51.2 µm), exact B_z */
    const int n = 512;
    const double pixel = 100e-9, h = 100e-9;
    const double x1 = 155.5, x2 = 355.5;
    svp_image *bz = test_image(n, n), *mz = test_image(n, n), *mz0 = test_image(n, n);
    square_flake_bz(bz, pixel, x1, x2, h);
    svp_recon_options o;
    svp_recon_defaults(&o);
    o.sensor = sensor_of(pixel, h, 1);
    const char *modes[] = {"taper", "mean", "none"};
    for (int pad = 0; pad < 3; pad++) {
        o.pad = (svp_pad_mode)pad;
        /* the k = 0-only variant for the default padding; the others with the border zero */
        for (int zb = pad == SVP_PAD_TAPER ? 0 : 1; zb < 2; zb++) {
            o.zero_border = zb;
            ASSERT_OK(svp_reconstruct_magnetisation(bz, &o, zb ? mz : mz0));
        }
        /* inside the flake, >= 1 µm from its edges */
        double lo = INFINITY, hi = -INFINITY, lo0 = INFINITY, hi0 = -INFINITY, out = 0;
        for (int j = 0; j < n; j++)
            for (int i = 0; i < n; i++) {
                int inside = i > x1 + 10 && i < x2 - 10 && j > x1 + 10 && j < x2 - 10;
                int outside = i < x1 - 10 || i > x2 + 10 || j < x1 - 10 || j > x2 + 10;
                double v = at(mz, i, j), v0 = at(mz0, i, j);
                if (inside) {
                    lo = fmin(lo, v);
                    hi = fmax(hi, v);
                    lo0 = fmin(lo0, v0);
                    hi0 = fmax(hi0, v0);
                }
                if (outside) out = fmax(out, fabs(v));
            }
        print_message("m_z inside the flake, pad %s: [%.4f, %.4f] mA (zero_border); "
                      "|m_z| outside <= %.4f mA\n", modes[pad], lo * 1e3, hi * 1e3, out * 1e3);
        if (pad == SVP_PAD_TAPER)
            print_message("  k = 0 dropped only: [%.4f, %.4f] mA\n", lo0 * 1e3, hi0 * 1e3);
        if (pad == SVP_PAD_TAPER && !(lo > 0.95e-3 && hi < 1.05e-3))
            fail_msg("pad %s: m_z inside in [%g, %g], not within 5 %% of 1 mA", modes[pad], lo,
                     hi);
        /* without the border reference the level is off by the lost mean, but flat */
        if (pad == SVP_PAD_TAPER && !(hi0 - lo0 < 0.01e-3))
            fail_msg("k = 0 dropped: m_z inside in [%g, %g] is not flat", lo0, hi0);
    }
    /* round trip through the library's own forward model */
    svp_image *m = test_image(n, n);
    const double sq[] = {x1, x1, x2, x1, x2, x2, x1, x2};
    ASSERT_OK(svp_raster_polygon(m, sq, 4, 1e-3));
    ASSERT_OK(svp_flake_field(m, 0, &o.sensor, 2, NULL, NULL, bz));
    o.pad = SVP_PAD_TAPER;
    o.zero_border = 1;
    ASSERT_OK(svp_reconstruct_magnetisation(bz, &o, mz));
    print_message("round trip through svp_flake_field: m_z at the centre %.4f mA\n",
                  at(mz, 255, 255) * 1e3);
    ASSERT_CLOSE(at(mz, 255, 255), 1e-3, 0.05e-3);
    /* periodic forward and inverse without a window are exact inverses apart from k = 0,
     * which the border reference restores here (m_z = 0 on the border) */
    ASSERT_OK(svp_flake_field(m, 0, &o.sensor, 1, NULL, NULL, bz));
    o.pad = SVP_PAD_NONE;
    o.window = 0;
    ASSERT_OK(svp_reconstruct_magnetisation(bz, &o, mz));
    double err = test_max_abs_diff(mz, m);
    print_message("periodic round trip without a window: max |error| %.2e mA\n", err * 1e3);
    if (err > 1e-12) fail_msg("periodic round trip error %g A", err);
    svp_image_free(m);
    svp_image_free(bz);
    svp_image_free(mz);
    svp_image_free(mz0);
}

/* J from the strip's closed-form field, J_y at the middle of the strip. */
static void strip_recon(int n, double pixel, double w, int side, int from_bz, svp_pad_mode pad,
                        int pad_factor, double *jy_mid, double *jx_mid, double *div_rel)
{
    const double h = 100e-9;
    svp_sensor s = sensor_of(pixel, h, side);
    svp_strip st;
    svp_strip_defaults(&st);
    st.width_m = w;
    st.centre_x = 0.5 * (n - 1);
    st.centre_y = 0.5 * (n - 1);
    svp_image *bx = test_image(n, n), *by = test_image(n, n), *bz = test_image(n, n);
    svp_image *jx = test_image(n, n), *jy = test_image(n, n), *dv = test_image(n, n);
    ASSERT_OK(svp_strip_field(&st, &s, bx, by, bz));
    svp_recon_options o;
    svp_recon_defaults(&o);
    o.sensor = s;
    o.pad = pad;
    o.pad_factor = pad_factor;
    if (from_bz) ASSERT_OK(svp_reconstruct_current_from_bz(bz, &o, jx, jy));
    else ASSERT_OK(svp_reconstruct_current_from_bxy(bx, by, &o, jx, jy));
    /* the middle: the mean over the central 5 x 5 pixels */
    double sy = 0, sx = 0;
    for (int j = n / 2 - 2; j <= n / 2 + 2; j++)
        for (int i = n / 2 - 2; i <= n / 2 + 2; i++) {
            sy += at(jy, i, j) / 25;
            sx += at(jx, i, j) / 25;
        }
    *jy_mid = sy;
    *jx_mid = sx;
    /* ∇·J over the central half of the view, relative to J / pixel */
    ASSERT_OK(svp_current_divergence(jx, jy, pixel, dv));
    double dmax = 0;
    for (int j = n / 4; j < 3 * n / 4; j++)
        for (int i = n / 4; i < 3 * n / 4; i++) dmax = fmax(dmax, fabs(at(dv, i, j)));
    *div_rel = dmax * pixel / 200;
    svp_image_free(bx);
    svp_image_free(by);
    svp_image_free(bz);
    svp_image_free(jx);
    svp_image_free(jy);
    svp_image_free(dv);
}

/* m_z on the view by least squares (SVP_RECON_SUPPORT) against the Fourier method, on the
 * closed-form field of a thin rectangle (not the library's forward model): the level inside,
 * a bad outermost pixel ring, the report, threads, refusals. */
static void test_reconstruct_support(void **state)
{
    (void)state;
    /* 12.85 µm square flake of 1 mA in a 25.6 µm view, h = 100 nm, 100 nm pixels; its edges
     * a quarter pixel off the pixel boundaries, so the method's pixel-uniform m_z is a model,
     * not the data's own discretisation */
    const int n = 256;
    const double pixel = 100e-9, h = 100e-9, x1 = 63.25, x2 = 191.75;
    svp_image *bz = test_image(n, n), *bad = test_image(n, n);
    svp_image *mf = test_image(n, n), *ms = test_image(n, n);
    svp_image *mf_bad = test_image(n, n), *ms_bad = test_image(n, n), *ms1 = test_image(n, n);
    const double peak = square_flake_bz(bz, pixel, x1, x2, h);
    /* the outermost pixel ring off by 10⁻³ of the peak (a bad edge, a deconvolution's border) */
    memcpy(bad->data, bz->data, (size_t)n * n * sizeof(double));
    for (int k = 0; k < n; k++) {
        bad->data[k] += 1e-3 * peak;
        bad->data[(size_t)(n - 1) * n + k] += 1e-3 * peak;
        if (k > 0 && k < n - 1) {
            bad->data[(size_t)k * n] += 1e-3 * peak;
            bad->data[(size_t)k * n + n - 1] += 1e-3 * peak;
        }
    }
    svp_recon_options o;
    svp_recon_defaults(&o);
    o.sensor = sensor_of(pixel, h, 1);
    ASSERT_OK(svp_reconstruct_magnetisation(bz, &o, mf));
    ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, mf_bad));
    o.method = SVP_RECON_SUPPORT;
    svp_recon_report rep;
    ASSERT_OK(svp_reconstruct_magnetisation_report(bz, &o, ms, &rep));
    print_message("support: %d CG steps, relative residual %.2e\n", rep.iterations, rep.residual);
    assert_true(rep.iterations > 0 && rep.iterations < o.max_iterations);
    assert_true(rep.residual <= o.tolerance);
    ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, ms_bad));
    /* inside the flake (>= 1 µm from its edges): the level, and the bad ring's effect */
    double ef = 0, es = 0, df = 0, ds = 0, out_s = 0;
    for (int j = 0; j < n; j++)
        for (int i = 0; i < n; i++) {
            int inside = i > x1 + 10 && i < x2 - 10 && j > x1 + 10 && j < x2 - 10;
            int outside = (i < x1 - 10 || i > x2 + 10 || j < x1 - 10 || j > x2 + 10) && i > 10 &&
                          i < n - 11 && j > 10 && j < n - 11;
            if (inside) {
                ef = fmax(ef, fabs(at(mf, i, j) - 1e-3));
                es = fmax(es, fabs(at(ms, i, j) - 1e-3));
                df = fmax(df, fabs(at(mf_bad, i, j) - at(mf, i, j)));
                ds = fmax(ds, fabs(at(ms_bad, i, j) - at(ms, i, j)));
            }
            if (outside) out_s = fmax(out_s, fabs(at(ms, i, j)));
        }
    print_message("m_z inside, max |error|: Fourier %.4f %%, support %.4f %% of 1 mA; "
                  "|m_z| outside (support) <= %.4f %%\n",
                  ef * 1e5, es * 1e5, out_s * 1e5);
    print_message("outermost ring off by 1e-3 of the peak: m_z inside moves by %.4f %% "
                  "(Fourier), %.5f %% (support)\n",
                  df * 1e5, ds * 1e5);
    if (!(es < 0.5 * ef)) fail_msg("support error %g not below half the Fourier's %g", es, ef);
    if (!(es < 0.01e-3)) fail_msg("support error inside %g A above 1 %%", es);
    if (!(out_s < 0.01e-3)) fail_msg("support |m_z| outside %g A above 1 %%", out_s);
    if (!(ds < 0.01 * df)) fail_msg("bad ring: support moved %g, Fourier %g", ds, df);
    /* the same bits on one thread */
    int threads = omp_get_max_threads();
    omp_set_num_threads(1);
    ASSERT_OK(svp_reconstruct_magnetisation(bz, &o, ms1));
    omp_set_num_threads(threads);
    double dt = test_max_abs_diff(ms1, ms);
    print_message("1 against %d threads: max |difference| %.2e A\n", threads, dt);
    assert_true(dt <= 1e-12 * 1e-3);
    /* linear at any scale: B_z times 2^±960 (about 10^±289; its sums of squares far outside
     * double's range) gives m_z times the same, to the bit (not zeros, not overflow) */
    for (int sgn = -1; sgn <= 1; sgn += 2) {
        for (size_t p = 0; p < (size_t)n * n; p++) bad->data[p] = ldexp(bz->data[p], 960 * sgn);
        ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, ms1));
        double worst = 0;
        for (size_t p = 0; p < (size_t)n * n; p++)
            worst = fmax(worst, fabs(ldexp(ms1->data[p], -960 * sgn) - ms->data[p]));
        print_message("B_z times 2^%+d: m_z differs from the unscaled one's times the same by "
                      "%.2e A\n",
                      960 * sgn, worst);
        if (!(worst == 0)) fail_msg("B_z times 2^%+d: m_z off by %g A", 960 * sgn, worst);
    }
    /* white noise of 1 % of the peak (uniform, rms 0.577 %): rms error of m_z inside */
    {
        uint64_t seed = 0x5eed;
        for (size_t p = 0; p < (size_t)n * n; p++)
            bad->data[p] = bz->data[p] + 0.02 * peak * (test_rand(&seed) - 0.5);
        ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, ms1));
        o.method = SVP_RECON_FOURIER;
        ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, mf_bad));
        o.method = SVP_RECON_SUPPORT;
        double rs = 0, rf = 0;
        int count = 0;
        for (int j = (int)x1 + 10; j < x2 - 10; j++)
            for (int i = (int)x1 + 10; i < x2 - 10; i++, count++) {
                rs += (at(ms1, i, j) - 1e-3) * (at(ms1, i, j) - 1e-3);
                rf += (at(mf_bad, i, j) - 1e-3) * (at(mf_bad, i, j) - 1e-3);
            }
        rs = sqrt(rs / count);
        rf = sqrt(rf / count);
        print_message("noise of 1 %% of the peak: rms error of m_z inside %.4f %% (support), "
                      "%.4f %% (Fourier)\n",
                      rs * 1e5, rf * 1e5);
        if (!(rs < 0.5 * rf)) fail_msg("noisy: support rms %g, Fourier %g", rs, rf);
    }
    /* a second flake 7.35 µm beyond the view's right edge, its stray field entering the view:
     * both methods assume no sources outside; the support method suffers less */
    {
        for (int j = 0; j < n; j++)
            for (int i = 0; i < n; i++) {
                double v[3];
                rectangle_field(1e-3, (n + 9.25) * pixel, (n + 109.75) * pixel, x1 * pixel,
                                x2 * pixel, i * pixel, j * pixel, h, v);
                bad->data[(size_t)j * n + i] = bz->data[(size_t)j * n + i] + v[2];
            }
        ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, ms1));
        o.method = SVP_RECON_FOURIER;
        ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, mf_bad));
        o.method = SVP_RECON_SUPPORT;
        double eo = 0, eof = 0;
        for (int j = (int)x1 + 10; j < x2 - 10; j++)
            for (int i = (int)x1 + 10; i < x2 - 10; i++) {
                eo = fmax(eo, fabs(at(ms1, i, j) - 1e-3));
                eof = fmax(eof, fabs(at(mf_bad, i, j) - 1e-3));
            }
        print_message("a flake outside the view: m_z inside, max |error| %.3f %% (support), "
                      "%.3f %% (Fourier)\n",
                      eo * 1e5, eof * 1e5);
        if (!(eo < 0.85 * eof)) fail_msg("source outside: support %g, Fourier %g", eo, eof);
    }
    /* an NV layer 60 nm thick and a 20 nm thick source: the data averaged over both depths
     * by the midpoint rule (24 x 24 layers), the method's kernel by Gauss–Legendre */
    {
        const double t_nv = 60e-9, t_src = 20e-9;
        const int layers = 24;
        for (int j = 0; j < n; j++)
            for (int i = 0; i < n; i++) {
                double sum = 0;
                for (int a = 0; a < layers; a++)
                    for (int b = 0; b < layers; b++) {
                        double z = h - 0.5 * t_nv + (a + 0.5) * t_nv / layers +
                                   (b + 0.5) * t_src / layers;
                        double v[3];
                        rectangle_field(1e-3, x1 * pixel, x2 * pixel, x1 * pixel, x2 * pixel,
                                        i * pixel, j * pixel, z, v);
                        sum += v[2];
                    }
                bad->data[(size_t)j * n + i] = sum / (layers * layers);
            }
        o.sensor.nv_thickness_m = t_nv;
        o.source_thickness_m = t_src;
        ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, ms1));
        o.method = SVP_RECON_FOURIER;
        ASSERT_OK(svp_reconstruct_magnetisation(bad, &o, mf_bad));
        o.method = SVP_RECON_SUPPORT;
        o.sensor.nv_thickness_m = 0;
        o.source_thickness_m = 0;
        double et = 0, etf = 0;
        for (int j = (int)x1 + 10; j < x2 - 10; j++)
            for (int i = (int)x1 + 10; i < x2 - 10; i++) {
                et = fmax(et, fabs(at(ms1, i, j) - 1e-3));
                etf = fmax(etf, fabs(at(mf_bad, i, j) - 1e-3));
            }
        print_message("NV layer 60 nm, source 20 nm thick: m_z inside, max |error| %.4f %% "
                      "(support), %.4f %% (Fourier)\n",
                      et * 1e5, etf * 1e5);
        if (!(et < 0.01e-3 && et < 0.5 * etf))
            fail_msg("thick layers: support error %g, Fourier %g", et, etf);
    }
    /* a cap it cannot converge within: in doubt, the steps reported */
    o.max_iterations = 2;
    assert_int_equal(svp_reconstruct_magnetisation_report(bz, &o, ms1, &rep), SVP_ERR_DOUBTFUL);
    assert_int_equal(rep.iterations, 2);
    assert_true(rep.residual > o.tolerance);
    /* refusals: the currents, no padding, a bad cap, an unknown method, NaN */
    svp_recon_defaults(&o);
    o.sensor = sensor_of(pixel, h, 1);
    o.method = SVP_RECON_SUPPORT;
    assert_int_equal(svp_reconstruct_current_from_bz(bz, &o, mf, ms1), SVP_ERR_INVALID);
    o.pad = SVP_PAD_NONE;
    assert_int_equal(svp_reconstruct_magnetisation(bz, &o, ms1), SVP_ERR_INVALID);
    o.pad = SVP_PAD_TAPER;
    o.max_iterations = 0;
    assert_int_equal(svp_reconstruct_magnetisation(bz, &o, ms1), SVP_ERR_INVALID);
    o.max_iterations = 200;
    o.method = (svp_recon_method)7;
    assert_int_equal(svp_reconstruct_magnetisation(bz, &o, ms1), SVP_ERR_INVALID);
    o.method = SVP_RECON_SUPPORT;
    bad->data[5] = NAN;
    assert_int_equal(svp_reconstruct_magnetisation(bad, &o, ms1), SVP_ERR_INVALID);
    svp_image *imgs[] = {bz, bad, mf, ms, mf_bad, ms_bad, ms1};
    for (size_t k = 0; k < sizeof imgs / sizeof *imgs; k++) svp_image_free(imgs[k]);
}

static void test_reconstruct_current(void **state)
{
    (void)state;
    double jy, jx, dv;
    /* from B_x: the reference study's 40 µm strip, J = 200 A/m, h = 100 nm, 100 nm pixels, in a
     * 51.2 µm view; both sensor sides */
    for (int side = -1; side <= 1; side += 2) {
        strip_recon(512, 100e-9, 40e-6, side, 0, SVP_PAD_TAPER, 2, &jy, &jx, &dv);
        print_message("40 um strip, J from B_x (side %+d): J_y = %.3f A/m, J_x = %.2e A/m at "
                      "the middle; max |div J| dx / J = %.2e\n", side, jy, jx, dv);
        if (!(fabs(jy - 200) < 0.02 * 200)) fail_msg("J_y from B_x %g A/m, not 200 +- 2 %%", jy);
        ASSERT_CLOSE(jx, 0, 1e-6);
    }
    /* from B_z: the inversion needs the field's 1/x tails, which a finite view cuts: the strip
     * must be narrow against the view (w/L = 0.039 here) */
    /* (B_z, hence J from B_z, is the same for both sides: one side suffices) */
    strip_recon(1024, 50e-9, 2e-6, 1, 1, SVP_PAD_TAPER, 2, &jy, &jx, &dv);
    print_message("2 um strip in a 51.2 um view, J from B_z: J_y = %.3f A/m, J_x = %.2e A/m; "
                  "max |div J| dx / J = %.2e\n", jy, jx, dv);
    if (!(fabs(jy - 200) < 0.02 * 200)) fail_msg("J_y from B_z %g A/m, not 200 +- 2 %%", jy);
    ASSERT_CLOSE(jx, 0, 1e-3);
    if (!(dv < 1e-6)) fail_msg("div J from B_z: %g", dv);
    /* and how the 40 µm strip fares from B_z in 51.2 µm (documented limitation) */
    strip_recon(512, 100e-9, 40e-6, 1, 1, SVP_PAD_TAPER, 2, &jy, &jx, &dv);
    print_message("40 um strip in a 51.2 um view from B_z: J_y = %.1f A/m (the cut 1/x tails; "
                  "4w/(pi^2 L) = %.0f %%)\n", jy, 400 * 40 / (M_PI * M_PI * 51.2));
    if (!(jy > 0 && jy < 200)) fail_msg("J_y from B_z of the wide strip %g", jy);
}

/* A rotated strip: the reconstructed current points along the strip's direction (sign pin for
 * J_x and the y orientation). */
static void test_reconstruct_current_direction(void **state)
{
    (void)state;
    const int n = 256;
    const double pixel = 50e-9, h = 100e-9;
    const double angles[] = {0, M_PI / 3, -2.2};
    for (size_t a = 0; a < sizeof angles / sizeof angles[0]; a++) {
        svp_sensor s = sensor_of(pixel, h, 1);
        svp_strip st;
        svp_strip_defaults(&st);
        st.width_m = 3e-6;
        st.angle = angles[a];
        st.centre_x = st.centre_y = 127.5;
        svp_image *bx = test_image(n, n), *by = test_image(n, n), *bz = test_image(n, n);
        svp_image *jx = test_image(n, n), *jy = test_image(n, n);
        ASSERT_OK(svp_strip_field(&st, &s, bx, by, bz));
        svp_recon_options o;
        svp_recon_defaults(&o);
        o.sensor = s;
        for (int src = 0; src < 2; src++) {
            if (src) ASSERT_OK(svp_reconstruct_current_from_bz(bz, &o, jx, jy));
            else ASSERT_OK(svp_reconstruct_current_from_bxy(bx, by, &o, jx, jy));
            double vx = at(jx, 128, 128), vy = at(jy, 128, 128);
            double along = vx * cos(st.angle) + vy * sin(st.angle);
            double across = -vx * sin(st.angle) + vy * cos(st.angle);
            if (!(along > 150 && fabs(across) < 0.05 * along))
                fail_msg("angle %g from %s: J = (%g, %g) A/m, along %g, across %g", st.angle,
                         src ? "bz" : "bxy", vx, vy, along, across);
        }
        svp_image_free(bx);
        svp_image_free(by);
        svp_image_free(bz);
        svp_image_free(jx);
        svp_image_free(jy);
    }
}

/* ---- ODMR ------------------------------------------------------------------------------- */

static void test_centroid_closed_form(void **state)
{
    (void)state;
    const int w = 48, h = 40, nf = 161;
    svp_odmr od;
    svp_odmr_defaults(&od);
    ASSERT_CLOSE(od.gamma_hz_per_t, 28.033e9, 0);
    ASSERT_CLOSE(od.zero_field_hz, 2.870e9, 0);
    /* a widefield CW linewidth; the round-off of the cube path grows like
     * eps sqrt(n_freq) span / (C Γ): far-off frames add only FFT noise to the sums */
    od.linewidth_hz = 4e6;
    /* PL: a Gaussian spot times a chessboard of levels {0.1, 0.8, 1}; field: a 3 mT bias on
     * the NV axis plus a flake-like step; contrast varies independently of the PL */
    svp_image *pl = test_image(w, h), *field = test_image(w, h), *contrast = test_image(w, h);
    const double levels[] = {0.1, 0.8, 1.0};
    uint64_t seed = 12345;
    int board[8][8];
    for (int a = 0; a < 8; a++)
        for (int b = 0; b < 8; b++) board[a][b] = (int)(3 * test_rand(&seed));
    for (int j = 0; j < h; j++)
        for (int i = 0; i < w; i++) {
            size_t p = (size_t)j * w + i;
            double r2 = (i - 23.5) * (i - 23.5) + (j - 19.5) * (j - 19.5);
            pl->data[p] = 1000 * exp(-r2 / (2 * 15.0 * 15.0)) * levels[board[j / 6][i / 6]];
            field->data[p] = 3e-3 + ((i > 14 && i < 34 && j > 10 && j < 30) ? 0.8e-3 : -0.2e-3);
            contrast->data[p] = 0.015 + 0.01 * (i % 7) / 6.0;
        }
    double *freq = malloc(nf * sizeof(double));
    ASSERT_OK(svp_odmr_sweep(&od, 4e-3, 25, nf, freq));
    svp_cube *cube = NULL, *blurred = NULL;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &cube));
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &blurred));
    ASSERT_OK(svp_odmr_simulate(&od, pl, field, contrast, NULL, cube));
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_LORENTZIAN;
    psf.fwhm = 3;
    psf.halo = 0.2;
    svp_blur *blur = NULL;
    ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_ZERO, &blur));
    for (int f = 0; f < nf; f++) ASSERT_OK(svp_blur_apply(blur, cube->frame[f], blurred->frame[f]));
    svp_image *pl_b = test_image(w, h);
    ASSERT_OK(svp_blur_apply(blur, pl, pl_b));
    /* the estimator on the true and on the blurred cube */
    svp_image *b_true = test_image(w, h), *wt_true = test_image(w, h);
    svp_image *b_cube = test_image(w, h), *wt_cube = test_image(w, h);
    ASSERT_OK(svp_odmr_centroid(&od, cube, pl, 0, 0, b_true, wt_true));
    ASSERT_OK(svp_odmr_centroid(&od, blurred, pl_b, 0, 0, b_cube, wt_cube));
    /* eq. (3): B̃ = H(B I_m) / H(I_m) with I_m the estimator's weight */
    svp_image *num = test_image(w, h), *num_b = test_image(w, h), *den_b = test_image(w, h);
    for (size_t p = 0; p < (size_t)w * h; p++) num->data[p] = b_true->data[p] * wt_true->data[p];
    ASSERT_OK(svp_blur_apply(blur, num, num_b));
    ASSERT_OK(svp_blur_apply(blur, wt_true, den_b));
    /* Round-off: the blurred frames carry FFT errors ~ eps max(I) everywhere, and the depth
     * b − I is 1.5–2.5 % of I, so dim pixels lose digits: compare relative to the field where
     * the blurred PL is >= 10 % of its peak, and state the worst pixel. */
    double worst = 0, worst_dim = 0, bmax = test_max_abs(b_cube), plmax = test_max_abs(pl_b);
    for (size_t p = 0; p < (size_t)w * h; p++) {
        double d = fabs(num_b->data[p] / den_b->data[p] - b_cube->data[p]);
        if (pl_b->data[p] >= 0.1 * plmax) worst = fmax(worst, d);
        else worst_dim = fmax(worst_dim, d);
    }
    print_message("centroid of the blurred cube vs eq. (3): max difference %.2e relative where "
                  "the PL >= 10 %% of its peak, %.2e in dimmer pixels\n", worst / bmax,
                  worst_dim / bmax);
    if (worst > 1e-12 * bmax) fail_msg("centroid vs closed form: %g T of %g T", worst, bmax);
    if (worst_dim > 1e-10 * bmax) fail_msg("centroid vs closed form: %g T of %g T", worst_dim, bmax);
    /* the estimator on the unblurred cube against the true field, and its weight against
     * PL · C (the dip area): both hold to the Lorentzian tail truncation */
    double bias = 0, wdev = 0, wref = 0;
    for (size_t p = 0; p < (size_t)w * h; p++) {
        bias = fmax(bias, fabs(b_true->data[p] - field->data[p]));
        double ratio = wt_true->data[p] / (pl->data[p] * contrast->data[p]);
        if (p == 0) wref = ratio;
        wdev = fmax(wdev, fabs(ratio / wref - 1));
    }
    print_message("centroid of the true cube vs the true field: max |bias| %.2f uT (linewidth "
                  "%.1f MHz, sweep +-%.0f MHz); weight / (PL C) constant to %.1e\n", bias * 1e6,
                  od.linewidth_hz * 1e-6, (freq[nf - 1] - freq[0]) * 0.5e-6, wdev);
    if (bias > 0.05 * 3e-3) fail_msg("centroid bias %g T", bias);
    svp_blur_free(blur);
    svp_cube_free(cube);
    svp_cube_free(blurred);
    free(freq);
    svp_image *all[] = {pl, field, contrast, pl_b, b_true, wt_true, b_cube, wt_cube, num, num_b, den_b};
    for (size_t k = 0; k < sizeof all / sizeof all[0]; k++) svp_image_free(all[k]);
}

/* A symmetric line inside its half of the window on a flat baseline: the split centroid is
 * exact. Lines built by hand (triangular dips), not by svp_odmr_simulate. */
static void test_centroid_exact_symmetric(void **state)
{
    (void)state;
    svp_odmr od;
    svp_odmr_defaults(&od);
    const int nf = 401;
    double freq[401];
    for (int f = 0; f < nf; f++) freq[f] = od.zero_field_hz - 200e6 + f * 1e6;
    svp_cube *cube = NULL;
    ASSERT_OK(svp_cube_new(3, 1, nf, freq, &cube));
    svp_image *base = test_image(3, 1), *b = test_image(3, 1);
    const double fields[3] = {2e-3, 3.3e-3, 5.01e-3};
    for (int p = 0; p < 3; p++) {
        base->data[p] = 100 + p;
        double split = od.gamma_hz_per_t * fields[p];
        for (int f = 0; f < nf; f++) {
            double u = freq[f] - od.zero_field_hz;
            double tri = fmax(0, 1 - fabs(fabs(u) - split) / 20e6);
            cube->frame[f]->data[p] = base->data[p] * (1 - 0.03 * tri);
        }
    }
    ASSERT_OK(svp_odmr_centroid(&od, cube, base, 0, 0, b, NULL));
    for (int p = 0; p < 3; p++) ASSERT_CLOSE(b->data[p], fields[p], 1e-12 * fields[p]);
    svp_cube_free(cube);
    svp_image_free(base);
    svp_image_free(b);
}


/* The per-pixel Lorentzian fit: exact on the model's own spectra; on a blurred cube it differs
 * from the PL-weighted closed form (eq. 3 with I_m = PL) where the contrast varies, and by how
 * much. A 50 µT field step (1.4 MHz, below the 4 MHz linewidth: the fit stays in its linear
 * regime) at column 20; contrast 1 % | 3 % across that step on the upper rows, uniform 2 % on
 * the lower rows; uniform PL. */
static void test_fit_vs_centroid(void **state)
{
    (void)state;
    const int w = 40, h = 32, nf = 121;
    svp_odmr od;
    svp_odmr_defaults(&od);
    od.linewidth_hz = 4e6;
    svp_image *pl = test_image(w, h), *field = test_image(w, h), *contrast = test_image(w, h);
    for (int j = 0; j < h; j++)
        for (int i = 0; i < w; i++) {
            size_t p = (size_t)j * w + i;
            pl->data[p] = 1000;
            field->data[p] = i >= 20 ? 3.05e-3 : 3e-3;
            contrast->data[p] = j >= 16 ? 0.02 : (i >= 20 ? 0.03 : 0.01);
        }
    double *freq = malloc(nf * sizeof(double));
    ASSERT_OK(svp_odmr_sweep(&od, 3.05e-3, 15, nf, freq));
    svp_cube *cube = NULL, *blurred = NULL;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &cube));
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &blurred));
    ASSERT_OK(svp_odmr_simulate(&od, pl, field, contrast, NULL, cube));
    svp_image *fit = test_image(w, h), *fc = test_image(w, h), *fg = test_image(w, h);
    size_t failed = 99;
    ASSERT_OK(svp_odmr_fit(&od, cube, NULL, fit, fc, NULL, fg, &failed));
    assert_int_equal(failed, 0);
    double err = test_max_abs_diff(fit, field), cerr = test_max_abs_diff(fc, contrast);
    print_message("Lorentzian fit of the true cube: max |B - B_true| = %.2e T, |C - C_true| = "
                  "%.2e\n", err, cerr);
    if (err > 1e-9 || cerr > 1e-9) fail_msg("fit of the exact model: %g T, %g", err, cerr);
    /* blur every frame (Gaussian, FWHM 4 px, mirror boundary), then estimate */
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.fwhm = 4;
    svp_blur *blur = NULL;
    ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_MIRROR, &blur));
    for (int f = 0; f < nf; f++) ASSERT_OK(svp_blur_apply(blur, cube->frame[f], blurred->frame[f]));
    svp_image *pl_b = test_image(w, h), *cen = test_image(w, h), *num = test_image(w, h);
    svp_image *num_b = test_image(w, h);
    ASSERT_OK(svp_blur_apply(blur, pl, pl_b));
    ASSERT_OK(svp_odmr_centroid(&od, blurred, pl_b, 0, 0, cen, NULL));
    ASSERT_OK(svp_odmr_fit(&od, blurred, NULL, fit, NULL, NULL, NULL, &failed));
    assert_int_equal(failed, 0);
    /* the closed form a scene uses without a cube: eq. (3) with the PL as I_m */
    for (size_t p = 0; p < (size_t)w * h; p++) num->data[p] = field->data[p] * pl->data[p];
    ASSERT_OK(svp_blur_apply(blur, num, num_b));
    double far = 0, fit_uni = 0, fit_var = 0, cen_uni = 0, cen_var = 0, fc_uni = 0, fc_var = 0;
    for (int j = 0; j < h; j++)
        for (int i = 0; i < w; i++) {
            size_t p = (size_t)j * w + i;
            double closed = num_b->data[p] / pl_b->data[p];
            if (i < 8 || i > 31) far = fmax(far, fabs(fit->data[p] - field->data[p]));
            double dfit = fabs(fit->data[p] - closed), dcen = fabs(cen->data[p] - closed);
            double dfc = fabs(fit->data[p] - cen->data[p]);
            if (j < 10) {
                fit_var = fmax(fit_var, dfit);
                cen_var = fmax(cen_var, dcen);
                fc_var = fmax(fc_var, dfc);
            } else if (j >= 22) {
                fit_uni = fmax(fit_uni, dfit);
                cen_uni = fmax(cen_uni, dcen);
                fc_uni = fmax(fc_uni, dfc);
            }
        }
    print_message("blurred cube, 50 uT step: fit exact to %.1e T away from it; vs the "
                  "PL-weighted closed form: fit %.2f uT, centroid %.2f uT where the contrast "
                  "is uniform; fit %.2f uT, centroid %.2f uT where it steps 1 -> 3 %%; "
                  "|fit - centroid| %.2f / %.2f uT\n", far, fit_uni * 1e6, cen_uni * 1e6,
                  fit_var * 1e6, cen_var * 1e6, fc_uni * 1e6, fc_var * 1e6);
    if (far > 1e-8) fail_msg("fit away from the step: %g T", far);
    /* uniform contrast: the fit follows the closed form to its nonlinearity (a few % of the
     * step); stepped contrast: it leaves it by ~ 1/4 of the step (weights PL·C, not PL). The
     * centroid's numbers include its Lorentzian-tail bias (the same on both halves). */
    if (!(fit_uni < 2.5e-6 && fit_var > 8e-6 && fit_var > 5 * fit_uni))
        fail_msg("fit vs closed form: %g T (uniform contrast), %g T (stepped)", fit_uni,
                 fit_var);
    svp_blur_free(blur);
    svp_cube_free(cube);
    svp_cube_free(blurred);
    free(freq);
    svp_image *all[] = {pl, field, contrast, fit, fc, fg, pl_b, cen, num, num_b};
    for (size_t k = 0; k < sizeof all / sizeof all[0]; k++) svp_image_free(all[k]);
}

/* The reference for the dedicated 4-parameter LM of svp_odmr_fit: the same model written
 * here (forward-difference Jacobian) and solved by the generic svp_lm_solve. */
typedef struct ref_odmr {
    const double *freq;
    double D, gamma;
} ref_odmr;

static int ref_odmr_model(void *user, const double *th, int n_params, int n_points, double *model,
                          double *jac)
{
    (void)n_params;
    (void)jac;
    const ref_odmr *r = user;
    const double hw = 0.5 * th[3];
    if (!(hw > 0)) return 1;
    for (int i = 0; i < n_points; i++) {
        double lo = r->freq[i] - (r->D - r->gamma * th[2]),
               hi = r->freq[i] - (r->D + r->gamma * th[2]);
        model[i] =
            th[0] * (1 - th[1] * (hw * hw / (lo * lo + hw * hw) + hw * hw / (hi * hi + hw * hw)));
    }
    return 0;
}

/* Spectra of noise alone (no dip): a fit may converge to a "line" far outside the sweep (B of
 * 10⁹ T was seen), to a single sample or to a dip of a few σ; every such fit is failed: every
 * pixel whose fitted line (the field map keeps the last parameters) lies outside the swept
 * range has converged 0 and is counted, and no fit of noise passes. */
static void test_fit_noise_only(void **state)
{
    (void)state;
    const int w = 16, h = 16, nf = 20;
    svp_odmr od;
    svp_odmr_defaults(&od);
    double freq[20];
    for (int f = 0; f < nf; f++) freq[f] = 2.80e9 + 0.14e9 * f / (nf - 1);
    svp_cube *cube = NULL;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &cube));
    uint64_t seed = 7;
    for (int f = 0; f < nf; f++)
        for (size_t p = 0; p < (size_t)w * h; p++)
            cube->frame[f]->data[p] = 1000 + 60 * (test_rand(&seed) - 0.5);
    svp_image *fit = test_image(w, h), *converged = test_image(w, h);
    const svp_odmr_maps maps = {.field = fit, .converged = converged};
    size_t failed = 0;
    ASSERT_OK(svp_odmr_fit_maps(&od, cube, NULL, &maps, &failed));
    size_t outside = 0, outside_converged = 0, not_converged = 0;
    for (size_t p = 0; p < (size_t)w * h; p++) {
        const double s = od.gamma_hz_per_t * fabs(fit->data[p]);
        const double lo = od.zero_field_hz - s, hi = od.zero_field_hz + s;
        const int in = (lo >= freq[0] && lo <= freq[nf - 1]) ||
                       (hi >= freq[0] && hi <= freq[nf - 1]);
        outside += !in;
        outside_converged += !in && converged->data[p] != 0;
        not_converged += converged->data[p] == 0;
    }
    print_message("noise only: %zu of %d fits failed, %zu with no line in the sweep\n", failed,
                  w * h, outside);
    /* every pixel whose line is outside the sweep is marked not converged, and counted */
    assert_int_equal(outside_converged, 0);
    assert_int_equal(failed, not_converged);
    assert_true(outside > 0); /* the case arises: without the rule these were "converged" */
    /* and no fit to noise passes: inside the sweep they were single samples (widths of kHz at
     * a 7.4 MHz step) or dips of 3 σ at most; 201 of 256 passed before those rules */
    assert_int_equal(failed, (size_t)w * h);
    /* a pixel without light (a masked one: all frames 0) has no dip: it converged to a made-up
     * field of 2.5 mT before */
    for (int f = 0; f < nf; f++) cube->frame[f]->data[5] = 0;
    ASSERT_OK(svp_odmr_fit_maps(&od, cube, NULL, &maps, &failed));
    assert_true(converged->data[5] == 0);
    /* frequencies must be positive: an ODMR line lies at D ± γB > 0 */
    for (int f = 0; f < nf; f++) cube->freq[f] = -2.94e9 + 0.14e9 * f / (nf - 1);
    assert_int_equal(svp_odmr_fit_maps(&od, cube, NULL, &maps, &failed), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "frequencies must be > 0 Hz"));
    svp_image_free(fit);
    svp_image_free(converged);
    svp_cube_free(cube);
}

/* Noisy spectra: the fit must not fall into wrong minima (a centroid start did, for ~2 % of
 * the pixels, ~1 mT off). Uniform noise of ±1 count on a 1000-count PL with 2 % contrast,
 * Γ = 4 MHz, 100 frames: the statistical error is a few µT at 3 mT. */
static void test_fit_noisy(void **state)
{
    (void)state;
    const int w = 48, h = 32, nf = 100;
    svp_odmr od;
    svp_odmr_defaults(&od);
    od.linewidth_hz = 4e6;
    svp_image *pl = test_image(w, h), *field = test_image(w, h), *fit = test_image(w, h);
    for (size_t p = 0; p < (size_t)w * h; p++) {
        pl->data[p] = 1000;
        field->data[p] = 3e-3 + 1e-4 * sin(0.01 * (double)p);
    }
    double *freq = malloc(nf * sizeof(double));
    ASSERT_OK(svp_odmr_sweep(&od, 3.2e-3, 15, nf, freq));
    svp_cube *cube = NULL;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &cube));
    ASSERT_OK(svp_odmr_simulate(&od, pl, field, NULL, NULL, cube));
    uint64_t seed = 99;
    for (int f = 0; f < nf; f++)
        for (size_t p = 0; p < (size_t)w * h; p++)
            cube->frame[f]->data[p] += 2 * test_rand(&seed) - 1;
    size_t failed = 99;
    ASSERT_OK(svp_odmr_fit(&od, cube, NULL, fit, NULL, NULL, NULL, &failed));
    double worst = 0, mean = 0;
    for (size_t p = 0; p < (size_t)w * h; p++) {
        double d = fabs(fit->data[p] - field->data[p]);
        worst = fmax(worst, d);
        mean += d / ((double)w * h);
    }
    print_message("noisy fits: %zu not converged, mean |error| %.2f uT, max %.2f uT\n", failed,
                  mean * 1e6, worst * 1e6);
    assert_int_equal(failed, 0);
    /* the same minima as the generic LM on an independently written model (started at the
     * truth, so it cannot fall into another minimum) */
    {
        ref_odmr ref = {.freq = freq, .D = od.zero_field_hz, .gamma = od.gamma_hz_per_t};
        const double lower[4] = {-INFINITY, 0, -INFINITY, 0};
        const double upper[4] = {INFINITY, 1, INFINITY, INFINITY};
        double *y = malloc(nf * sizeof(double));
        svp_lm_workspace *ws = NULL;
        ASSERT_OK(svp_lm_workspace_new(4, nf, &ws));
        svp_lm_problem prob = {.n_params = 4,
                               .n_points = nf,
                               .model = ref_odmr_model,
                               .user = &ref,
                               .data = y,
                               .lower = lower,
                               .upper = upper};
        svp_lm_options lo;
        svp_lm_defaults(&lo);
        lo.xtol = 1e-12;
        lo.ftol = 1e-14;
        double dmax = 0;
        for (size_t p = 0; p < (size_t)w * h; p += 7) {
            for (int f = 0; f < nf; f++) y[f] = cube->frame[f]->data[p];
            double th[4] = {1000, 0.02, field->data[p], 4e6};
            ASSERT_OK(svp_lm_solve(ws, &prob, &lo, th, NULL, NULL));
            dmax = fmax(dmax, fabs(fabs(th[2]) - fit->data[p]));
        }
        /* both stop at ftol = 1e-8 on χ² or tighter: a parameter offset ~ 1e-4 of its
         * statistical error (measured 1.6e-10 T on 2.2 uT) */
        print_message("noisy fits vs the generic LM on the test's own model: max |dB| %.2e T "
                      "(%.1e of the mean |error|)\n",
                      dmax, dmax / mean);
        if (dmax > 1e-3 * mean)
            fail_msg("the ODMR fit and the generic LM differ by %g T (noise %g T)", dmax, mean);
        svp_lm_workspace_free(ws);
        free(y);
    }
    if (!(worst < 20e-6 && mean < 5e-6)) fail_msg("noisy fits: mean %g T, max %g T", mean, worst);
    svp_cube_free(cube);
    free(freq);
    svp_image_free(pl);
    svp_image_free(field);
    svp_image_free(fit);
}

/* ---- svp_odmr_fit_maps: free lines, uncertainties, progress -------------------------------- */

/* Spectra written here, not by svp_odmr_simulate: dips at f_lo, f_hi (either may be NAN = absent)
 * with FWHM gamma_w and depth C, on the baseline b, plus Gaussian noise of σ = noise. */
static double test_gauss(uint64_t *seed)
{
    double u1 = test_rand(seed), u2 = test_rand(seed);
    if (u1 < 1e-300) u1 = 1e-300;
    return sqrt(-2 * log(u1)) * cos(2 * M_PI * u2);
}

static double own_spectrum(double w, double b, double C, double f_lo, double f_hi, double fwhm)
{
    double h2 = 0.25 * fwhm * fwhm, s = 0;
    if (!isnan(f_lo)) s += h2 / ((w - f_lo) * (w - f_lo) + h2);
    if (!isnan(f_hi)) s += h2 / ((w - f_hi) * (w - f_hi) + h2);
    return b * (1 - C * s);
}

typedef struct fit_maps_set {
    svp_image *field, *field_sigma, *lo, *lo_sigma, *hi, *hi_sigma, *b, *b_sigma, *c, *c_sigma,
        *g, *g_sigma, *quality, *conv;
} fit_maps_set;

static svp_odmr_maps maps_of(fit_maps_set *m, int w, int h, int two)
{
    svp_image **all[] = {&m->field, &m->field_sigma, &m->lo, &m->lo_sigma, &m->hi, &m->hi_sigma,
                         &m->b,     &m->b_sigma,     &m->c,  &m->c_sigma,  &m->g,  &m->g_sigma,
                         &m->quality, &m->conv};
    for (size_t k = 0; k < sizeof all / sizeof all[0]; k++)
        *all[k] = (k >= 2 && k < 6 && !two) ? NULL : test_image(w, h);
    svp_odmr_maps maps = {.field = m->field, .field_sigma = m->field_sigma,
                          .field_lower = m->lo, .field_lower_sigma = m->lo_sigma,
                          .field_upper = m->hi, .field_upper_sigma = m->hi_sigma,
                          .baseline = m->b, .baseline_sigma = m->b_sigma, .contrast = m->c,
                          .contrast_sigma = m->c_sigma, .linewidth = m->g,
                          .linewidth_sigma = m->g_sigma, .quality = m->quality,
                          .converged = m->conv};
    return maps;
}

static void maps_free(fit_maps_set *m)
{
    svp_image *all[] = {m->field, m->field_sigma, m->lo, m->lo_sigma, m->hi, m->hi_sigma, m->b,
                        m->b_sigma, m->c, m->c_sigma, m->g, m->g_sigma, m->quality, m->conv};
    for (size_t k = 0; k < sizeof all / sizeof all[0]; k++) svp_image_free(all[k]);
}

/* rms of (estimate − truth) / σ over the pixels: 1 when σ is the true scatter */
static double pull_rms(const svp_image *est, const double *truth, const svp_image *sigma)
{
    double s = 0;
    size_t n = (size_t)est->width * est->height;
    for (size_t p = 0; p < n; p++) {
        double z = (est->data[p] - truth[p]) / sigma->data[p];
        s += z * z;
    }
    return sqrt(s / (double)n);
}

typedef struct progress_log {
    int calls, cancel_at;
    double last;
    int monotone, other_thread;
} progress_log;

static int log_progress(void *user, double fraction)
{
    progress_log *l = user;
    l->calls++;
    if (omp_get_thread_num() != 0) l->other_thread++; /* the calling thread is thread 0 */
    if (fraction < l->last) l->monotone = 0;
    l->last = fraction;
    return l->cancel_at > 0 && l->calls >= l->cancel_at;
}

static void test_fit_maps_lines(void **state)
{
    (void)state;
    const int w = 40, h = 30, nf = 100;
    const size_t n = (size_t)w * h;
    svp_odmr od;
    svp_odmr_defaults(&od);
    od.linewidth_hz = 4e6;
    const double D = od.zero_field_hz, g = od.gamma_hz_per_t, fwhm = 5e6, C = 0.025, b = 1000;
    const double noise = 2.0, shift = 0.7e6; /* D shifted by 0.7 MHz (temperature) */
    double *truth = malloc(n * sizeof(double));
    for (size_t p = 0; p < n; p++) truth[p] = 1.5e-3 + 1e-3 * (double)(p % w) / w;
    double freq[100];
    for (int f = 0; f < nf; f++) freq[f] = D - 110e6 + 220e6 * f / (nf - 1);
    svp_cube *cube = NULL;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &cube));
    uint64_t seed = 7;
    for (int f = 0; f < nf; f++)
        for (size_t p = 0; p < n; p++)
            cube->frame[f]->data[p] =
                own_spectrum(freq[f], b, C, D + shift - g * truth[p], D + shift + g * truth[p],
                             fwhm) +
                noise * test_gauss(&seed);

    /* TWO: the projected field ignores the shift of D; per resonance B ∓ shift / γ */
    svp_odmr_fit_options opt;
    svp_odmr_fit_defaults(&opt);
    assert_int_equal(opt.lines, SVP_ODMR_LINES_PAIR);
    assert_int_equal(opt.line_sign, 1);
    opt.lines = SVP_ODMR_LINES_TWO;
    progress_log log = {.monotone = 1};
    opt.progress = log_progress;
    opt.progress_user = &log;
    fit_maps_set m;
    svp_odmr_maps maps = maps_of(&m, w, h, 1);
    size_t failed = 99;
    ASSERT_OK(svp_odmr_fit_maps(&od, cube, &opt, &maps, &failed));
    assert_int_equal(failed, 0);
    assert_true(log.calls >= 2 && log.monotone && log.last == 1.0 && !log.other_thread);
    double err = 0, worst = 0, *t_lo = malloc(n * sizeof(double)), *t_hi = malloc(n * sizeof(double));
    double *t_b = malloc(n * sizeof(double)), *t_c = malloc(n * sizeof(double)),
           *t_g = malloc(n * sizeof(double));
    for (size_t p = 0; p < n; p++) {
        double d = fabs(m.field->data[p] - truth[p]);
        err += d / (double)n;
        worst = fmax(worst, d);
        t_lo[p] = truth[p] - shift / g;
        t_hi[p] = truth[p] + shift / g;
        t_b[p] = b;
        t_c[p] = C;
        t_g[p] = fwhm;
        assert_true(m.conv->data[p] == 1);
        assert_true(m.quality->data[p] > 0.5 && m.quality->data[p] <= 1);
    }
    const double pulls[5] = {pull_rms(m.field, truth, m.field_sigma),
                             pull_rms(m.lo, t_lo, m.lo_sigma), pull_rms(m.hi, t_hi, m.hi_sigma),
                             pull_rms(m.c, t_c, m.c_sigma), pull_rms(m.g, t_g, m.g_sigma)};
    print_message("two free lines (D shifted 0.7 MHz, noise %.0f on a %.0f-count dip): mean "
                  "|dB| %.2f uT, max %.2f uT; rms (est - truth) / sigma: B %.3f, B- %.3f, "
                  "B+ %.3f, C %.3f, G %.3f\n",
                  noise, b * C, err * 1e6, worst * 1e6, pulls[0], pulls[1], pulls[2], pulls[3],
                  pulls[4]);
    /* statistical error: σ_B ~ 3 uT here; the stated tolerance: mean 6 uT, max 30 uT */
    if (!(err < 6e-6 && worst < 30e-6)) fail_msg("TWO: mean %g T, max %g T", err, worst);
    /* σ is the scatter: 1200 pulls give the rms to ~2 %; allow 0.85 .. 1.2 */
    for (int k = 0; k < 5; k++)
        if (!(pulls[k] > 0.85 && pulls[k] < 1.2)) fail_msg("TWO: pull rms %d = %g", k, pulls[k]);
    assert_true(fabs(pull_rms(m.b, t_b, m.b_sigma) - 1) < 0.2);

    /* the same maps whatever the thread count (each pixel is fitted alone) */
    {
        fit_maps_set m1;
        svp_odmr_maps maps1 = maps_of(&m1, w, h, 1);
        opt.progress = NULL;
        int threads = omp_get_max_threads();
        omp_set_num_threads(1);
        ASSERT_OK(svp_odmr_fit_maps(&od, cube, &opt, &maps1, NULL));
        omp_set_num_threads(threads);
        assert_memory_equal(m1.field->data, m.field->data, n * sizeof(double));
        assert_memory_equal(m1.field_sigma->data, m.field_sigma->data, n * sizeof(double));
        assert_memory_equal(m1.quality->data, m.quality->data, n * sizeof(double));
        maps_free(&m1);
    }
    /* cancelled at the third report */
    log = (progress_log){.cancel_at = 3, .monotone = 1};
    opt.progress = log_progress;
    assert_int_equal(svp_odmr_fit_maps(&od, cube, &opt, &maps, NULL), SVP_ERR_CANCELLED);
    assert_int_equal(log.calls, 3);
    opt.progress = NULL;

    /* the same cube in absurd units (× 2^-1000, about 1e-298): refused, the frame named (the
     * fits' sums of squares underflow: a stack of 1e-300 gave fields wrong by 64 % of their
     * range, exit 0) */
    for (int f = 0; f < nf; f++)
        for (size_t p = 0; p < n; p++)
            cube->frame[f]->data[p] = ldexp(cube->frame[f]->data[p], -1000);
    assert_int_equal(svp_odmr_fit_maps(&od, cube, &opt, &maps, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "ODMR fit: frame 0: its largest |value|"));
    for (int f = 0; f < nf; f++)
        for (size_t p = 0; p < n; p++)
            cube->frame[f]->data[p] = ldexp(cube->frame[f]->data[p], 1000);

    /* PAIR about the nominal D on the same cube: it cannot follow the shift (a worse fit), and
     * field_lower is refused */
    opt.lines = SVP_ODMR_LINES_PAIR;
    assert_int_equal(svp_odmr_fit_maps(&od, cube, &opt, &maps, NULL), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "ODMR fit: field_lower / field_upper are given by two "
                                          "free resonances only (SVP_ODMR_LINES_TWO)");
    svp_image *two_quality = m.quality;
    fit_maps_set mp;
    svp_odmr_maps mapsp = maps_of(&mp, w, h, 0);
    ASSERT_OK(svp_odmr_fit_maps(&od, cube, &opt, &mapsp, NULL));
    double q_two = test_sum(two_quality) / (double)n, q_pair = test_sum(mp.quality) / (double)n;
    print_message("mean R^2: two free lines %.4f, pair about the nominal D %.4f\n", q_two, q_pair);
    assert_true(q_pair < q_two);
    maps_free(&mp);

    /* PAIR on a cube without the shift: its σ is the scatter too, and svp_odmr_fit returns the
     * same field */
    seed = 8;
    for (int f = 0; f < nf; f++)
        for (size_t p = 0; p < n; p++)
            cube->frame[f]->data[p] =
                own_spectrum(freq[f], b, C, D - g * truth[p], D + g * truth[p], fwhm) +
                noise * test_gauss(&seed);
    mapsp = maps_of(&mp, w, h, 0);
    ASSERT_OK(svp_odmr_fit_maps(&od, cube, &opt, &mapsp, &failed));
    assert_int_equal(failed, 0);
    double pull_pair = pull_rms(mp.field, truth, mp.field_sigma);
    svp_image *plain = test_image(w, h);
    ASSERT_OK(svp_odmr_fit(&od, cube, &opt, plain, NULL, NULL, NULL, NULL));
    assert_memory_equal(plain->data, mp.field->data, n * sizeof(double));
    print_message("pair about D: rms (est - truth) / sigma of B %.3f\n", pull_pair);
    if (!(pull_pair > 0.85 && pull_pair < 1.2)) fail_msg("PAIR: pull rms %g", pull_pair);
    maps_free(&mp);
    svp_image_free(plain);

    /* ONE: a sweep over one line only; the upper line gives +B, the lower one (line_sign −1)
     * gives +B too */
    opt.lines = SVP_ODMR_LINES_ONE;
    for (int sign = 1; sign >= -1; sign -= 2) {
        double fr[100];
        for (int f = 0; f < nf; f++) fr[f] = D + sign * (g * 2e-3) - 40e6 + 80e6 * f / (nf - 1);
        svp_cube *one = NULL;
        ASSERT_OK(svp_cube_new(w, h, nf, fr, &one));
        for (int f = 0; f < nf; f++)
            for (size_t p = 0; p < n; p++)
                one->frame[f]->data[p] =
                    own_spectrum(fr[f], b, C, sign < 0 ? D - g * truth[p] : NAN,
                                 sign > 0 ? D + g * truth[p] : NAN, fwhm) +
                    noise * test_gauss(&seed);
        opt.line_sign = sign;
        fit_maps_set mo;
        svp_odmr_maps mapso = maps_of(&mo, w, h, 0);
        ASSERT_OK(svp_odmr_fit_maps(&od, one, &opt, &mapso, &failed));
        assert_int_equal(failed, 0);
        double e1 = 0;
        for (size_t p = 0; p < n; p++) e1 += fabs(mo.field->data[p] - truth[p]) / (double)n;
        double pull1 = pull_rms(mo.field, truth, mo.field_sigma);
        print_message("one line (sign %+d): mean |dB| %.2f uT, rms pull %.3f\n", sign, e1 * 1e6,
                      pull1);
        if (!(e1 < 8e-6)) fail_msg("ONE sign %d: mean error %g T", sign, e1);
        if (!(pull1 > 0.85 && pull1 < 1.2)) fail_msg("ONE sign %d: pull rms %g", sign, pull1);
        /* the wrong sign gives −B */
        opt.line_sign = -sign;
        ASSERT_OK(svp_odmr_fit_maps(&od, one, &opt, &mapso, NULL));
        for (size_t p = 0; p < n; p += 97) assert_true(mo.field->data[p] < 0);
        maps_free(&mo);
        svp_cube_free(one);
    }
    opt.line_sign = 0;
    assert_int_equal(svp_odmr_fit_maps(&od, cube, &opt, &maps, NULL), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "ODMR fit: line_sign 0 must be +1 or -1");
    maps_free(&m);
    svp_cube_free(cube);
    free(truth);
    free(t_lo);
    free(t_hi);
    free(t_b);
    free(t_c);
    free(t_g);
}

/* The default NV with a 4 MHz starting linewidth, and nf frequencies over D ± 60 MHz. */
static void sweep_120mhz(svp_odmr *od, int nf, double *freq)
{
    svp_odmr_defaults(od);
    od->linewidth_hz = 4e6;
    for (int f = 0; f < nf; f++) freq[f] = od->zero_field_hz - 60e6 + 120e6 * f / (nf - 1);
}

/* A pixel whose best contrast is on a bound has no σ from the curvature: INFINITY in every σ
 * map. A frame read as 0 (a dropped frame) in a flat spectrum is fitted by one line as a
 * narrow dip of depth 1 — with R² near 1, so only σ tells; where the fit lands exactly on
 * C = 1 every σ must be INFINITY; a real dip keeps finite σ. */
static void test_fit_maps_bound(void **state)
{
    (void)state;
    const int nf = 80, w = 25;
    svp_odmr od;
    double freq[80];
    sweep_120mhz(&od, nf, freq);
    const double D = od.zero_field_hz, g = od.gamma_hz_per_t;
    svp_cube *cube = NULL;
    ASSERT_OK(svp_cube_new(w, 1, nf, freq, &cube));
    uint64_t seed = 11;
    for (int f = 0; f < nf; f++) {
        cube->frame[f]->data[0] =
            own_spectrum(freq[f], 1000, 0.03, NAN, D + g * 1e-3, 5e6) + test_gauss(&seed);
        for (int p = 1; p < w; p++) /* the dropped frame at 20 + 1.5 p */
            cube->frame[f]->data[p] = f == 20 + 3 * p / 2 ? 0 : 1000 + cos(1.7 * f + p);
    }
    svp_odmr_fit_options opt;
    svp_odmr_fit_defaults(&opt);
    opt.lines = SVP_ODMR_LINES_ONE;
    fit_maps_set m;
    svp_odmr_maps maps = maps_of(&m, w, 1, 0);
    ASSERT_OK(svp_odmr_fit_maps(&od, cube, &opt, &maps, NULL));
    assert_true(fabs(m.field->data[0] - 1e-3) < 20e-6 && m.quality->data[0] > 0.9);
    svp_image *sig[] = {m.field_sigma, m.b_sigma, m.c_sigma, m.g_sigma};
    int on_bound = 0;
    for (int p = 0; p < w; p++) {
        const int bound = m.c->data[p] == 0 || m.c->data[p] == 1;
        on_bound += bound;
        if (p > 0) assert_true(m.c->data[p] > 0.99 && m.quality->data[p] > 0.99);
        for (int k = 0; k < 4; k++) /* (elsewhere JᵀJ may be singular: INFINITY too) */
            if (bound || p == 0) assert_true(isinf(sig[k]->data[p]) == bound);
    }
    print_message("dropped frames: %d of %d fits end on C = 1 (sigma INFINITY)\n", on_bound,
                  w - 1);
    assert_true(on_bound >= 1 && m.c->data[0] < 1);
    maps_free(&m);
    svp_cube_free(cube);
}

/* Missing samples (NaN in some frames of a pixel): the pixel is fitted on its finite samples,
 * to the bit as the stack without those frames fits it; with more than half missing it is
 * missing (NaN maps, not converged). */
static void test_fit_maps_missing(void **state)
{
    (void)state;
    const int nf = 60, w = 6;
    svp_odmr od;
    double freq[60], freq_kept[60];
    sweep_120mhz(&od, nf, freq);
    const double D = od.zero_field_hz, g = od.gamma_hz_per_t;
    svp_cube *cube = NULL, *kept = NULL;
    ASSERT_OK(svp_cube_new(w, 1, nf, freq, &cube));
    uint64_t seed = 21;
    for (int f = 0; f < nf; f++)
        for (int p = 0; p < w; p++)
            cube->frame[f]->data[p] = own_spectrum(freq[f], 1000, 0.03, D - g * (1e-3 + 1e-4 * p),
                                                   D + g * (1e-3 + 1e-4 * p), 5e6) +
                                      3 * test_gauss(&seed);
    /* pixels 0..4: frames 7 and 33 missing (33 inside the lower dip, at D - 28 MHz); pixel 5:
     * 31 of 60 missing */
    const int gone[2] = {7, 33};
    int nk = 0;
    for (int f = 0; f < nf; f++)
        if (f != gone[0] && f != gone[1]) freq_kept[nk++] = freq[f];
    ASSERT_OK(svp_cube_new(w, 1, nk, freq_kept, &kept));
    for (int f = 0, k = 0; f < nf; f++) {
        const int drop = f == gone[0] || f == gone[1];
        for (int p = 0; p < w; p++) {
            if (!drop) kept->frame[k]->data[p] = cube->frame[f]->data[p];
            if (drop && p < 5) cube->frame[f]->data[p] = NAN;
            if (p == 5 && f % 2 == 0) cube->frame[f]->data[p] = f == 0 ? INFINITY : NAN;
        }
        k += !drop;
    }
    cube->frame[nf - 1]->data[5] = NAN; /* 31 missing */
    assert_int_equal(svp_odmr_fit_min_finite(nf, NULL), 30);
    svp_odmr_fit_options few;
    svp_odmr_fit_defaults(&few);
    few.lines = SVP_ODMR_LINES_TWO;
    assert_int_equal(svp_odmr_fit_min_finite(9, &few), 6);  /* the 5 parameters + 1 */
    few.baseline_frames = 4;
    assert_int_equal(svp_odmr_fit_min_finite(9, &few), 8);  /* twice the baseline frames */
    for (int two = 0; two < 2; two++) { /* the pair model, and two free lines (5 parameters) */
        svp_odmr_fit_options opt;
        svp_odmr_fit_defaults(&opt);
        if (two) opt.lines = SVP_ODMR_LINES_TWO;
        fit_maps_set m, mk;
        svp_odmr_maps maps = maps_of(&m, w, 1, two), maps_k = maps_of(&mk, w, 1, two);
        size_t n_failed = 0, n_failed_k = 0;
        ASSERT_OK(svp_odmr_fit_maps(&od, cube, &opt, &maps, &n_failed));
        ASSERT_OK(svp_odmr_fit_maps(&od, kept, &opt, &maps_k, &n_failed_k));
        svp_image *a[] = {m.field, m.field_sigma, m.b, m.b_sigma, m.c,  m.c_sigma,
                          m.g,     m.g_sigma,     m.quality, m.conv, m.lo, m.hi};
        svp_image *b[] = {mk.field, mk.field_sigma, mk.b, mk.b_sigma, mk.c,  mk.c_sigma,
                          mk.g,     mk.g_sigma,     mk.quality, mk.conv, mk.lo, mk.hi};
        const size_t n_maps = two ? 12 : 10;
        for (int p = 0; p < 5; p++) {
            for (size_t k = 0; k < n_maps; k++)
                if (memcmp(&a[k]->data[p], &b[k]->data[p], sizeof(double)) != 0)
                    fail_msg("%s, pixel %d, map %zu: %.17g with NaN frames, %.17g without them",
                             two ? "two lines" : "pair", p, k, a[k]->data[p], b[k]->data[p]);
            assert_true(m.conv->data[p] == 1 &&
                        fabs(m.field->data[p] - 1e-3 - 1e-4 * p) < 20e-6);
        }
        print_message("%s: 2 of 60 frames missing: pixels 0-4 fitted, the same bits as without "
                      "those frames (field of pixel 0 %.6g T); 31 missing: NaN\n",
                      two ? "two lines" : "pair", m.field->data[0]);
        assert_true(isnan(m.field->data[5]) && isnan(m.b->data[5]) && m.conv->data[5] == 0);
        assert_int_equal(n_failed, n_failed_k + 1);
        maps_free(&m);
        maps_free(&mk);
    }
    /* every pixel missing (31 of 60 frames NaN everywhere): nothing to fit, refused naming
     * a frame that holds no value (it returned maps of NaN, n_failed = every pixel) */
    for (int f = 0; f < 31; f++)
        for (int p = 0; p < w; p++) cube->frame[f]->data[p] = NAN;
    fit_maps_set mn;
    svp_odmr_maps maps_n = maps_of(&mn, w, 1, 0);
    assert_int_equal(svp_odmr_fit_maps(&od, cube, NULL, &maps_n, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "every one of the 6 pixels holds NaN or Inf in more "
                                             "than 30 of its 60 frames"));
    assert_non_null(strstr(svp_last_error(), "(the frame at 2.81 GHz is NaN or Inf at every"));
    maps_free(&mn);
    svp_cube_free(cube);
    svp_cube_free(kept);
}

/* ---- bad input -------------------------------------------------------------------------- */

static void test_bad_input(void **state)
{
    (void)state;
    svp_image *a = test_image(8, 8), *b = test_image(9, 8);
    svp_sensor s = sensor_of(100e-9, 100e-9, 1);
    s.standoff_m = -1;
    assert_int_equal(svp_flake_field(a, 0, &s, 2, NULL, NULL, a), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "sensor standoff_m -1: must be a finite length > 0 m");
    s = sensor_of(100e-9, 100e-9, 0);
    assert_int_equal(svp_sensor_validate(&s), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "sensor side 0: must be +1 (above) or -1 (below)");
    s = sensor_of(100e-9, 100e-9, 1);
    s.nv_thickness_m = 300e-9;
    assert_int_equal(svp_sensor_validate(&s), SVP_ERR_INVALID);
    s = sensor_of(100e-9, 100e-9, 1);
    assert_int_equal(svp_flake_field(a, 0, &s, 2, NULL, NULL, b), SVP_ERR_SIZE);
    svp_recon_options o;
    svp_recon_defaults(&o);
    o.pad_factor = 1;
    assert_int_equal(svp_reconstruct_magnetisation(a, &o, a), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "reconstruction pad_factor 1: must be in [2, 16]");
    svp_recon_defaults(&o);
    a->data[3] = NAN;
    assert_int_equal(svp_reconstruct_current_from_bz(a, &o, b, NULL), SVP_ERR_SIZE);
    svp_image *c = test_image(8, 8);
    assert_int_equal(svp_reconstruct_current_from_bz(a, &o, c, NULL), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "reconstruction input bz has NaN or Inf pixels");
    /* a map with no interior, and filters that would pass nothing but the mean, are refused:
     * they returned m_z = 0 (or ~1e-13 of the true value) */
    svp_image *thin = test_image(8, 2), *thin_out = test_image(8, 2);
    assert_int_equal(svp_reconstruct_magnetisation(thin, &o, thin_out), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "reconstruction input bz is 8 x 2 pixels: a "
                                          "reconstruction from B_z needs a map of at least 3 x 3");
    assert_int_equal(svp_inplane_from_bz(thin, &o, thin_out, NULL), SVP_ERR_INVALID);
    /* the in-plane relation is local: a 8 x 2 map of B_x gives J_y = s (2/μ0) W(0) B_x's mean */
    ASSERT_OK(svp_reconstruct_current_from_bxy(thin, NULL, &o, NULL, thin_out));
    svp_image_free(thin);
    svp_image_free(thin_out);
    a->data[3] = 1;
    for (size_t p = 0; p < 64; p++) a->data[p] = 1e-6 * sin(0.7 * (double)p);
    /* 8 x 8 px of 100 nm padded to 16 x 16: the lowest frequency 2π / 1.6 µm */
    const double kmin = 2 * M_PI / (16 * 100e-9);
    o.cutoff = 0.99 * kmin;
    assert_int_equal(svp_reconstruct_magnetisation(a, &o, c), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "lies below the lowest frequency of the 16 x 16"));
    o.cutoff = 1.01 * kmin; /* the lowest frequency passes (W ≈ 2.5e-4): a non-zero map */
    ASSERT_OK(svp_reconstruct_magnetisation(a, &o, c));
    double peak = 0;
    for (size_t p = 0; p < 64; p++) peak = fmax(peak, fabs(c->data[p]));
    assert_true(peak > 0);
    svp_recon_defaults(&o);
    o.window = 0;
    o.sensor.standoff_m = 1e-2; /* e^(k h) at the lowest frequency: e^39000 */
    assert_int_equal(svp_reconstruct_current_from_bz(a, &o, c, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "exceeds e^700"));
    svp_recon_defaults(&o);
    const double axis[3] = {0, 0.5, 1};
    assert_int_equal(svp_field_project(NULL, NULL, c, axis, c), SVP_ERR_INVALID);
    svp_odmr od;
    svp_odmr_defaults(&od);
    double freq[2] = {2.8e9, 2.9e9};
    svp_cube *cube = NULL;
    ASSERT_OK(svp_cube_new(8, 8, 2, freq, &cube));
    double drift[4] = {0};
    a->data[3] = 1;
    assert_int_equal(svp_odmr_simulate(&od, a, c, NULL, drift, cube), SVP_ERR_UNSUPPORTED);
    assert_int_equal(svp_odmr_centroid(&od, cube, a, 3e9, 3.1e9, c, NULL), SVP_ERR_INVALID);
    freq[1] = 2.8e9;
    svp_cube *bad = NULL;
    assert_int_equal(svp_cube_new(8, 8, 2, freq, &bad), SVP_ERR_INVALID);
    assert_null(bad);
    od.contrast = 0.7;
    assert_int_equal(svp_odmr_simulate(&od, a, c, NULL, NULL, cube), SVP_ERR_INVALID);
    assert_string_equal(svp_last_error(), "ODMR contrast 0.7: must be in [0, 0.5]");
    svp_cube_free(cube);
    svp_image_free(a);
    svp_image_free(b);
    svp_image_free(c);
}

/* svp_cube_deconvolve against foreign data: a sweep rendered by the test on a canvas 8 px
 * beyond a 48² view (light from outside), every frame blurred by the test's own direct
 * convolution with a Gaussian of σ = 1.7 px, then cropped: a field step of 240 µT (6.7
 * linewidths) across a few pixels under a PL of bright and dark blobs, so a blurred pixel holds
 * separated dips and the Lorentzian fit picks one of them, which T⁻¹ on the fitted maps (its
 * model is the PL-weighted mean field) cannot undo. Measured rms field error: fit of the
 * blurred cube 10.7 µT, T⁻¹ (default R, 75 iterations, auto margin) on its maps 43.8 µT
 * (worse: its model does not hold), fit of the cube deconvolved frame by frame (RL, 75
 * iterations, the same margin) 2.0 µT; asserted: the cube's below half the blurred fit's and
 * below T⁻¹'s. 1 and 2 threads give the same
 * frames bit for bit, a missing frame (NaN) staying NaN; a value below zero is deconvolved as 0 and counted; an operator of the
 * wrong size is refused. */
#define CD_W 48
#define CD_PAD 8
#define CD_NF 40
static double cd_pl(double x, double y)
{
    const double bx[5] = {10, 30, 40, 18, 52}, by[5] = {12, 8, 30, 40, 50};
    const double ba[5] = {1.0, -0.7, 0.8, -0.6, 0.9};
    double u = 0;
    for (int k = 0; k < 5; k++)
        u += ba[k] * exp(-((x - bx[k]) * (x - bx[k]) + (y - by[k]) * (y - by[k])) / 40.0);
    return 1.0 + 0.8 * tanh(2 * u);
}
static double cd_field(double x, double y) { return 150e-6 + 120e-6 * tanh((x + 0.3 * y - 36) / 1.5); }

static void test_cube_deconvolve(void **state)
{
    (void)state;
    const int w = CD_W, cw = CD_W + 2 * CD_PAD, nf = CD_NF;
    const double sigma = 1.7;
    svp_odmr od;
    svp_odmr_defaults(&od);
    od.contrast = 0.03;
    double freq[CD_NF];
    ASSERT_OK(svp_odmr_sweep(&od, 300e-6, 4, nf, freq));
    svp_cube *cube = NULL, *copy = NULL;
    ASSERT_OK(svp_cube_new(w, w, nf, freq, &cube));
    ASSERT_OK(svp_cube_new(w, w, nf, freq, &copy));
    /* the test's own blur: direct convolution with a normalised Gaussian of radius 7 px */
    const int r = 7;
    double k1[15], ks = 0;
    for (int i = -r; i <= r; i++) ks += k1[i + r] = exp(-0.5 * i * i / (sigma * sigma));
    for (int i = 0; i < 2 * r + 1; i++) k1[i] /= ks;
    svp_image *canvas = test_image(cw, cw), *tmp = test_image(cw, cw);
    const double G = od.linewidth_hz / 2;
    for (int f = 0; f < nf; f++) {
        for (int y = 0; y < cw; y++)
            for (int x = 0; x < cw; x++) {
                const double sx = x - CD_PAD, sy = y - CD_PAD, b = cd_field(sx, sy);
                double dip = 0;
                for (int s = -1; s <= 1; s += 2) {
                    const double u = freq[f] - (od.zero_field_hz + s * od.gamma_hz_per_t * b);
                    dip += G * G / (u * u + G * G);
                }
                canvas->data[(size_t)y * cw + x] = cd_pl(sx, sy) * (1 - od.contrast * dip);
            }
        for (int y = 0; y < cw; y++) /* separable: rows, then columns (zero outside) */
            for (int x = 0; x < cw; x++) {
                double v = 0;
                for (int i = -r; i <= r; i++)
                    if (x + i >= 0 && x + i < cw) v += k1[i + r] * canvas->data[(size_t)y * cw + x + i];
                tmp->data[(size_t)y * cw + x] = v;
            }
        for (int y = 0; y < w; y++)
            for (int x = 0; x < w; x++) {
                double v = 0;
                for (int i = -r; i <= r; i++)
                    v += k1[i + r] * tmp->data[(size_t)(y + CD_PAD + i) * cw + x + CD_PAD];
                cube->frame[f]->data[(size_t)y * w + x] = v;
            }
    }
    for (int f = 0; f < nf; f++)
        memcpy(copy->frame[f]->data, cube->frame[f]->data, (size_t)w * w * sizeof(double));
    /* the maps: fit of the blurred cube, T⁻¹ on them, fit of the deconvolved cube */
    svp_image *b_app = test_image(w, w), *pl_app = test_image(w, w), *b_cube = test_image(w, w);
    svp_image *b_t = test_image(w, w), *pl_t = test_image(w, w), *truth = test_image(w, w);
    for (int y = 0; y < w; y++)
        for (int x = 0; x < w; x++) truth->data[(size_t)y * w + x] = cd_field(x, y);
    ASSERT_OK(svp_odmr_fit(&od, cube, NULL, b_app, NULL, pl_app, NULL, NULL));
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_GAUSSIAN;
    psf.fwhm = 2.3548200450309493 * sigma;
    const int m = svp_psf_auto_margin(&psf, w, w);
    svp_blur *blur = NULL;
    ASSERT_OK(svp_blur_new(&psf, w + 2 * m, w + 2 * m, SVP_BOUNDARY_ZERO, &blur));
    svp_correct_options co;
    svp_correct_defaults(&co);
    co.margin = m;
    const svp_image *fa[1] = {b_app};
    svp_image *fc[1] = {b_t};
    ASSERT_OK(svp_inverse_transform(blur, pl_app, fa, 1, &co, pl_t, fc, NULL, NULL));
    svp_deconv_options dopt;
    svp_deconv_defaults(&dopt);
    dopt.iterations = 75;
    /* two frames of the blurred cube, one with a value below 0: taken as 0 and counted */
    svp_cube *neg = NULL, *zero = NULL;
    ASSERT_OK(svp_cube_new(w, w, 2, freq, &neg));
    ASSERT_OK(svp_cube_new(w, w, 2, freq, &zero));
    for (int f = 0; f < 2; f++) {
        memcpy(neg->frame[f]->data, cube->frame[3 + f]->data, (size_t)w * w * sizeof(double));
        memcpy(zero->frame[f]->data, cube->frame[3 + f]->data, (size_t)w * w * sizeof(double));
    }
    neg->frame[1]->data[10] = -1;
    zero->frame[1]->data[10] = 0;
    const int threads = svp_get_threads();
    svp_set_threads(2);
    size_t negative = 7;
    ASSERT_OK(svp_cube_deconvolve(blur, cube, m, &dopt, &negative, NULL, NULL));
    assert_int_equal(negative, 0);
    svp_set_threads(1);
    /* on one thread, with frame 5 missing (NaN at every pixel): it stays NaN, the others are
     * the same bits */
    for (size_t i = 0; i < (size_t)w * w; i++) copy->frame[5]->data[i] = NAN;
    ASSERT_OK(svp_cube_deconvolve(blur, copy, m, &dopt, NULL, NULL, NULL));
    svp_set_threads(threads);
    for (int f = 0; f < nf; f++)
        if (f != 5)
            assert_memory_equal(cube->frame[f]->data, copy->frame[f]->data,
                                (size_t)w * w * sizeof(double));
    assert_int_equal(svp_image_count_nonfinite(copy->frame[5]), (size_t)w * w);
    ASSERT_OK(svp_odmr_fit(&od, cube, NULL, b_cube, NULL, NULL, NULL, NULL));
    double e[3] = {0, 0, 0};
    const svp_image *est[3] = {b_app, b_t, b_cube};
    for (int k = 0; k < 3; k++) {
        for (size_t i = 0; i < (size_t)w * w; i++)
            e[k] += pow(est[k]->data[i] - truth->data[i], 2) / (double)(w * w);
        e[k] = sqrt(e[k]);
    }
    print_message("cube deconvolution: rms field error %.1f uT fitted from the blurred cube, "
                  "%.1f uT after T^-1 on the maps, %.1f uT fitted from the deconvolved cube\n",
                  1e6 * e[0], 1e6 * e[1], 1e6 * e[2]);
    assert_true(e[2] < 0.5 * e[0]);
    assert_true(e[2] < e[1]);
    /* refused: the wrong operator size */
    assert_int_equal(svp_cube_deconvolve(blur, cube, m + 1, &dopt, NULL, NULL, NULL),
                     SVP_ERR_SIZE);
    /* a value below 0 is deconvolved as 0, and counted */
    ASSERT_OK(svp_cube_deconvolve(blur, neg, m, &dopt, &negative, NULL, NULL));
    assert_int_equal(negative, 1);
    ASSERT_OK(svp_cube_deconvolve(blur, zero, m, &dopt, &negative, NULL, NULL));
    assert_int_equal(negative, 0);
    for (int f = 0; f < 2; f++)
        assert_memory_equal(neg->frame[f]->data, zero->frame[f]->data,
                            (size_t)w * w * sizeof(double));
    svp_cube_free(neg);
    svp_cube_free(zero);
    svp_blur_free(blur);
    svp_cube_free(cube);
    svp_cube_free(copy);
    svp_image_free(canvas);
    svp_image_free(tmp);
    svp_image_free(b_app);
    svp_image_free(pl_app);
    svp_image_free(b_cube);
    svp_image_free(b_t);
    svp_image_free(pl_t);
    svp_image_free(truth);
}

static void test_projection(void **state)
{
    (void)state;
    svp_image *bx = test_random_image(5, 4, 1), *by = test_random_image(5, 4, 2);
    svp_image *bz = test_random_image(5, 4, 3), *out = test_image(5, 4);
    const double axis[3] = {1, -2, 2}; /* |axis| = 3 */
    ASSERT_OK(svp_field_project(bx, by, bz, axis, out));
    for (size_t p = 0; p < 20; p++)
        ASSERT_CLOSE(out->data[p], (bx->data[p] - 2 * by->data[p] + 2 * bz->data[p]) / 3, 1e-15);
    svp_image_free(bx);
    svp_image_free(by);
    svp_image_free(bz);
    svp_image_free(out);
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_strip_closed_form),
        cmocka_unit_test(test_strip_biot_savart),
        cmocka_unit_test(test_strip_y_orientation),
        cmocka_unit_test(test_strip_nv_layer),
        cmocka_unit_test(test_raster_shapes),
        cmocka_unit_test(test_flake_fourier_vs_closed_form),
        cmocka_unit_test(test_flake_flux),
        cmocka_unit_test(test_flake_thickness),
        cmocka_unit_test(test_inplane_from_bz),
        cmocka_unit_test(test_reconstruct_magnetisation),
        cmocka_unit_test(test_reconstruct_support),
        cmocka_unit_test(test_reconstruct_current),
        cmocka_unit_test(test_reconstruct_current_direction),
        cmocka_unit_test(test_centroid_closed_form),
        cmocka_unit_test(test_centroid_exact_symmetric),
        cmocka_unit_test(test_fit_vs_centroid),
        cmocka_unit_test(test_fit_noisy),
        cmocka_unit_test(test_fit_noise_only),
        cmocka_unit_test(test_fit_maps_lines),
        cmocka_unit_test(test_fit_maps_bound),
        cmocka_unit_test(test_fit_maps_missing),
        cmocka_unit_test(test_projection),
        cmocka_unit_test(test_cube_deconvolve),
        cmocka_unit_test(test_bad_input),
    };
    int rc = cmocka_run_group_tests_name("physics", tests, NULL, NULL);
    svp_fft_cleanup();
    return rc;
}
