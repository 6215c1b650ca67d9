/* The region representation of the space-variant operator (SVP_VARIANT_REGIONS, docs/model.md
 * §9 "Region maps"): exact against the per-source operator on sharp maps, equal to the explicit
 * sum of per-label invariant operators on sharp and blended maps, adjoint, unit flux, the error
 * estimate on blended maps, the automatic choice, single precision, bad input. */
#include "test_helpers.h"

#include "psf/field_internal.h"

#include <stdint.h>
#include <stdio.h>

static const svp_boundary modes[] = {SVP_BOUNDARY_ZERO, SVP_BOUNDARY_MIRROR, SVP_BOUNDARY_PERIODIC};
static const char *mode_names[] = {"zero", "mirror", "periodic"};

static svp_psf moffat(double fwhm, double fwhm_minor, double angle, double beta, double halo)
{
    svp_psf p;
    svp_psf_defaults(&p);
    p.model = SVP_PSF_MOFFAT;
    p.fwhm = fwhm;
    p.fwhm_minor = fwhm_minor;
    p.angle = angle;
    p.beta = beta;
    p.halo = halo;
    return p;
}

/* Three regions on w x h (oxide background, a metal strip, a metal disc; an unused fourth
 * label when `unused`): FWHM 2.2 / 4.5 / 3.2 px, β 2.5 / 1.4 / 1.8, the strip elliptical, a
 * halo on the disc when `halo`. Support `support` px. */
static svp_psf_field *three_regions(int w, int h, double transition, int halo, double support,
                                    int unused)
{
    int *labels = malloc((size_t)w * h * sizeof(int));
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            int l = x >= w / 3 && x < w / 3 + w / 5;
            const double dx = x - 0.72 * w, dy = y - 0.4 * h;
            if (dx * dx + dy * dy < 0.04 * w * h) l = 2;
            labels[(size_t)y * w + x] = l;
        }
    svp_psf rp[4] = {moffat(2.2, 0, 0, 2.5, 0), moffat(4.5, 3.6, 0.4, 1.4, 0),
                     moffat(3.2, 0, 0, 1.8, halo ? 0.2 : 0), moffat(6.0, 0, 0, 1.2, 0)};
    for (int k = 0; k < 4; k++) rp[k].support = support;
    svp_psf_field *f = NULL;
    ASSERT_OK(svp_psf_field_new_regions(w, h, labels, unused ? 4 : 3, rp, transition, &f));
    free(labels);
    return f;
}

/* The six images of an H / Hᵀ comparison: im[0] = x and im[1] = y random (seeds seed, seed + 1),
 * im[2], im[3] the two H x, im[4], im[5] the two Hᵀ y. */
static void images_new(int w, int h, uint64_t seed, svp_image **im)
{
    im[0] = test_random_image(w, h, seed);
    im[1] = test_random_image(w, h, seed + 1);
    for (int i = 2; i < 6; i++) im[i] = test_image(w, h);
}

static void images_free(svp_image **im)
{
    for (int i = 0; i < 6; i++) svp_image_free(im[i]);
}

static svp_variant_options regions_options(void)
{
    svp_variant_options o;
    svp_variant_defaults(&o);
    o.representation = SVP_VARIANT_REGIONS;
    return o;
}

/* (a), (b): on a sharp 3-label map (96 x 88, with and without a halo, every boundary) H and Hᵀ
 * equal the exact per-source operator's to 1e-12 of their peak, <Hx, y> = <x, Hᵀy>, and the
 * operator reports one kernel per used label (an unused label has no term). */
static void test_sharp_exact(void **state)
{
    (void)state;
    const int w = 96, h = 88;
    double worst = 0;
    for (int halo = 0; halo < 2; halo++) {
        svp_psf_field *f = three_regions(w, h, 0, halo, 10, 1);
        svp_image *im[6];
        images_new(w, h, 11, im);
        svp_image *x = im[0], *yv = im[1], *hr = im[2], *he = im[3], *tr = im[4], *te = im[5];
        for (int m = 0; m < 3; m++) {
            svp_variant_options o = regions_options();
            svp_blur *b = NULL, *ex = NULL;
            ASSERT_OK(svp_blur_new_field(f, w, h, modes[m], &o, &b));
            ASSERT_OK(svp_blur_new_exact(f, w, h, modes[m], 0, &ex));
            svp_variant_info info;
            ASSERT_OK(svp_blur_variant_info(b, &info));
            assert_int_equal(info.representation, SVP_VARIANT_REGIONS);
            assert_int_equal(info.rank, 3); /* label 3 has no pixel */
            assert_int_equal(info.grid_x, 0);
            assert_true(info.memory_bytes == svp_blur_memory(b));
            ASSERT_OK(svp_blur_apply(b, x, hr));
            ASSERT_OK(svp_blur_apply(ex, x, he));
            ASSERT_OK(svp_blur_adjoint(b, yv, tr));
            ASSERT_OK(svp_blur_adjoint(ex, yv, te));
            const double e1 = test_max_abs_diff(hr, he) / test_max_abs(he);
            const double e2 = test_max_abs_diff(tr, te) / test_max_abs(te);
            if (!(e1 <= 1e-12 && e2 <= 1e-12))
                fail_msg("%s, halo %d: regions vs exact %.3g (H), %.3g (Ht)", mode_names[m], halo,
                         e1, e2);
            worst = fmax(worst, fmax(e1, e2));
            const double a = test_dot(hr, yv), c = test_dot(x, tr);
            if (!(fabs(a - c) <= 1e-12 * fabs(a)))
                fail_msg("%s, halo %d: <Hx,y> = %.17g, <x,Hty> = %.17g", mode_names[m], halo, a, c);
            svp_blur_free(ex);
            svp_blur_free(b);
        }
        images_free(im);
        svp_psf_field_free(f);
    }
    print_message("regions vs exact, sharp 3-label map 96 x 88: at most %.2g of the peak\n", worst);
}

/* The explicit sum (12r) with one invariant operator per label, the reference of
 * test_explicit_sum: H x = Σ_k I_k (w_k s ⊙ x) + <α x>, Hᵀ y = Σ_k w_k s ⊙ I_kᵀ y + α <y>, I_k
 * svp_blur_new of label k's PSF without its halo (the same support), w_k the field's blend
 * weights, α the field's halo per pixel (svp_psf_field_params_at), s = 1 − α. */
static void explicit_sum(const svp_psf_field *f, int w, int h, svp_boundary mode,
                         const svp_image *x, const svp_image *y, svp_image *hx, svp_image *ty)
{
    const size_t n = (size_t)w * h;
    double *alpha = malloc(n * sizeof(double));
    for (int r = 0; r < h; r++)
        for (int c = 0; c < w; c++) {
            double p[SVP_FIELD_NPARAM];
            ASSERT_OK(svp_psf_field_params_at(f, c, r, p));
            alpha[(size_t)r * w + c] = p[SVP_FIELD_HALO];
        }
    double ax = 0, my = 0;
    for (size_t i = 0; i < n; i++) {
        ax += alpha[i] * x->data[i];
        my += y->data[i];
        hx->data[i] = 0;
        ty->data[i] = 0;
    }
    svp_image *in = test_image(w, h), *out = test_image(w, h);
    double *wk = malloc(n * sizeof(double));
    for (int k = 0; k < f->n_labels; k++) {
        size_t count = 0;
        ASSERT_OK(svp_psf_field_region_weight(f, k, wk, &count));
        if (!count) continue;
        svp_psf p;
        svp_psf_field_region_psf(f, k, &p);
        p.halo = 0;
        svp_blur *ik = NULL;
        ASSERT_OK(svp_blur_new(&p, w, h, mode, &ik));
        for (size_t i = 0; i < n; i++) in->data[i] = wk[i] * (1 - alpha[i]) * x->data[i];
        ASSERT_OK(svp_blur_apply(ik, in, out));
        for (size_t i = 0; i < n; i++) hx->data[i] += out->data[i];
        ASSERT_OK(svp_blur_adjoint(ik, y, out));
        for (size_t i = 0; i < n; i++) ty->data[i] += wk[i] * (1 - alpha[i]) * out->data[i];
        svp_blur_free(ik);
    }
    for (size_t i = 0; i < n; i++) {
        hx->data[i] += ax / (double)n;
        ty->data[i] += alpha[i] * my / (double)n;
    }
    free(wk);
    free(alpha);
    svp_image_free(in);
    svp_image_free(out);
}

/* (a') H x and Hᵀ y equal the explicit sum of per-label invariant operators (explicit_sum) to
 * 1e-12 of their peak, in double, and to 2e-6 in single precision: sharp and blended maps (the
 * blend makes every weight map non-zero on many rows), a halo, odd sizes (61 x 53, 45 x 39),
 * a compact support (9 px: the frame's margin rows are copies of image rows in mirror mode,
 * zero rows in zero mode) and the whole field, every boundary. */
static void test_explicit_sum(void **state)
{
    (void)state;
    const int sizes[2][2] = {{61, 53}, {45, 39}};
    double worst = 0, worst_f = 0;
    for (int c = 0; c < 4; c++) {
        const int w = sizes[c >> 1][0], h = sizes[c >> 1][1];
        const double transition = c & 1 ? 5.0 : 0.0, support = c >> 1 ? 0.0 : 9.0;
        svp_psf_field *f = three_regions(w, h, transition, 1, support, 1);
        svp_image *im[6];
        images_new(w, h, 41, im);
        svp_image *x = im[0], *yv = im[1], *hr = im[2], *he = im[3], *tr = im[4], *te = im[5];
        for (int m = 0; m < 3; m++) {
            explicit_sum(f, w, h, modes[m], x, yv, he, te);
            svp_variant_options o = regions_options();
            svp_blur *b = NULL;
            ASSERT_OK(svp_blur_new_field(f, w, h, modes[m], &o, &b));
            for (int single = 0; single < 2; single++) {
                ASSERT_OK(svp_blur_set_precision(b, single));
                ASSERT_OK(svp_blur_apply(b, x, hr));
                ASSERT_OK(svp_blur_adjoint(b, yv, tr));
                const double e1 = test_max_abs_diff(hr, he) / test_max_abs(he);
                const double e2 = test_max_abs_diff(tr, te) / test_max_abs(te);
                const double bound = single ? 2e-6 : 1e-12;
                if (!(e1 <= bound && e2 <= bound))
                    fail_msg("%d x %d, %s, transition %g, support %g, %s: regions vs explicit sum "
                             "%.3g (H), %.3g (Ht)",
                             w, h, mode_names[m], transition, support, single ? "single" : "double",
                             e1, e2);
                double *wst = single ? &worst_f : &worst;
                *wst = fmax(*wst, fmax(e1, e2));
            }
            svp_blur_free(b);
        }
        images_free(im);
        svp_psf_field_free(f);
    }
    print_message("regions vs explicit per-label sum: at most %.2g (double), %.2g (single) of the "
                  "peak\n",
                  worst, worst_f);
}

/* (b), (c): blended map too: adjointness, and unit flux for every source at once (periodic
 * boundary, no halo: Hᵀ1 = 1 at every pixel, i.e. Σ_o H(o, s) = 1), also with whole-field
 * kernels. */
static void test_flux_and_adjoint(void **state)
{
    (void)state;
    const int w = 64, h = 60;
    for (int c = 0; c < 4; c++) {
        const double transition = c & 1 ? 6.0 : 0.0, support = c & 2 ? 0.0 : 9.0;
        svp_psf_field *f = three_regions(w, h, transition, 0, support, 0);
        svp_variant_options o = regions_options();
        svp_blur *b = NULL;
        ASSERT_OK(svp_blur_new_field(f, w, h, SVP_BOUNDARY_PERIODIC, &o, &b));
        svp_image *one = test_image(w, h), *t = test_image(w, h), *x = test_random_image(w, h, 5);
        svp_image *y = test_random_image(w, h, 6), *hx = test_image(w, h);
        for (size_t i = 0; i < (size_t)w * h; i++) one->data[i] = 1;
        ASSERT_OK(svp_blur_adjoint(b, one, t));
        double dev = 0;
        for (size_t i = 0; i < (size_t)w * h; i++) dev = fmax(dev, fabs(t->data[i] - 1));
        if (!(dev <= 1e-12))
            fail_msg("transition %g, support %g: max |flux - 1| = %.3g", transition, support, dev);
        ASSERT_OK(svp_blur_apply(b, x, hx));
        ASSERT_OK(svp_blur_adjoint(b, y, t));
        const double a = test_dot(hx, y), d = test_dot(x, t);
        if (!(fabs(a - d) <= 1e-12 * fabs(a)))
            fail_msg("transition %g: <Hx,y> = %.17g, <x,Hty> = %.17g", transition, a, d);
        svp_image_free(one);
        svp_image_free(t);
        svp_image_free(x);
        svp_image_free(y);
        svp_image_free(hx);
        svp_blur_free(b);
        svp_psf_field_free(f);
    }
}

/* ‖(H − H_exact) x‖ / ‖H_exact x‖ over four white-noise images: its expected square is the
 * squared Frobenius ratio that the estimate targets. */
static double measured_error(svp_blur *b, svp_blur *ex, int w, int h)
{
    svp_image *x = test_image(w, h), *y = test_image(w, h), *ye = test_image(w, h);
    uint64_t s = 4242;
    double e2 = 0, n2 = 0;
    for (int k = 0; k < 4; k++) {
        for (size_t i = 0; i < (size_t)w * h; i++) { /* Box-Muller, one value a pair */
            const double u = test_rand(&s) + 1e-300, v = test_rand(&s);
            x->data[i] = sqrt(-2 * log(u)) * cos(2 * M_PI * v);
        }
        ASSERT_OK(svp_blur_apply(b, x, y));
        ASSERT_OK(svp_blur_apply(ex, x, ye));
        for (size_t i = 0; i < (size_t)w * h; i++) {
            e2 += pow(y->data[i] - ye->data[i], 2);
            n2 += ye->data[i] * ye->data[i];
        }
    }
    svp_image_free(x);
    svp_image_free(y);
    svp_image_free(ye);
    return sqrt(e2 / n2);
}

/* (d) Blended maps (transition 4 and 10 px, 112 x 104): the field blends PSF parameters, the
 * representation kernels, so it is an approximation; svp_variant_estimate's estimate is within
 * 2x of the error measured against the exact operator. A sharp map estimates 0. */
static void test_blended_estimate(void **state)
{
    (void)state;
    const int w = 112, h = 104;
    const double transitions[] = {4.0, 10.0};
    for (int c = 0; c < 2; c++) {
        svp_psf_field *f = three_regions(w, h, transitions[c], 1, 10, 0);
        svp_variant_options o = regions_options();
        double est = -1;
        ASSERT_OK(svp_variant_estimate(f, w, h, SVP_BOUNDARY_ZERO, &o, &est));
        svp_blur *b = NULL, *ex = NULL;
        ASSERT_OK(svp_blur_new_field(f, w, h, SVP_BOUNDARY_ZERO, &o, &b));
        ASSERT_OK(svp_blur_new_exact(f, w, h, SVP_BOUNDARY_ZERO, 0, &ex));
        const double meas = measured_error(b, ex, w, h);
        print_message("blended over %g px: estimated %.3g %%, measured %.3g %%\n", transitions[c],
                      100 * est, 100 * meas);
        if (!(meas > 1e-6 && est <= 2 * meas && est >= 0.5 * meas))
            fail_msg("transition %g: estimate %.3g, measured %.3g", transitions[c], est, meas);
        svp_blur_free(b);
        svp_blur_free(ex);
        svp_psf_field_free(f);
    }
    svp_psf_field *f = three_regions(w, h, 0, 1, 10, 0);
    svp_variant_options o = regions_options();
    double est = -1;
    ASSERT_OK(svp_variant_estimate(f, w, h, SVP_BOUNDARY_ZERO, &o, &est));
    assert_true(est == 0);
    svp_psf_field_free(f);
}

/* (e) SVP_VARIANT_AUTO on a sharp map at the default budget 1e-3 picks regions (no tent grid or
 * low rank reaches it on a sharp boundary) and meets it against the exact operator, on a blended
 * one the same operator as forced (the chooser's weight maps reused); with max_memory below the
 * region operator's need it is not a candidate. */
static void test_auto_picks_regions(void **state)
{
    (void)state;
    const int w = 96, h = 96;
    svp_psf_field *f = three_regions(w, h, 0, 0, 10, 0);
    svp_variant_options o;
    svp_variant_defaults(&o);
    assert_true(o.tolerance == 1e-3);
    svp_blur *b = NULL, *ex = NULL;
    ASSERT_OK(svp_blur_new_field(f, w, h, SVP_BOUNDARY_MIRROR, &o, &b));
    svp_variant_info info;
    ASSERT_OK(svp_blur_variant_info(b, &info));
    assert_int_equal(info.representation, SVP_VARIANT_REGIONS);
    assert_int_equal(info.rank, 3);
    assert_true(info.tolerance_met);
    assert_true(info.estimated_error == 0);
    ASSERT_OK(svp_blur_new_exact(f, w, h, SVP_BOUNDARY_MIRROR, 0, &ex));
    const double meas = measured_error(b, ex, w, h);
    print_message("auto on a sharp map: regions (%d kernels, %d candidates), measured %.3g\n",
                  info.rank, info.candidates, meas);
    assert_true(meas <= 1e-3);
    assert_true(meas <= 1e-12);
    svp_blur_free(b);
    /* a blended map over 4 px at a budget of 5 %: regions too (estimated 3.3 %) */
    svp_psf_field *fb = three_regions(w, h, 4, 0, 10, 0);
    o.tolerance = 0.05;
    ASSERT_OK(svp_blur_new_field(fb, w, h, SVP_BOUNDARY_MIRROR, &o, &b));
    ASSERT_OK(svp_blur_variant_info(b, &info));
    assert_int_equal(info.representation, SVP_VARIANT_REGIONS);
    assert_true(info.tolerance_met && info.estimated_error > 0 && info.estimated_error <= 0.05);
    /* the build takes the chooser's smoothed weight maps over (smoothed once): the operator is
     * the forced one's bit for bit, H and Hᵀ */
    {
        svp_variant_options fo = regions_options();
        svp_blur *bf = NULL;
        ASSERT_OK(svp_blur_new_field(fb, w, h, SVP_BOUNDARY_MIRROR, &fo, &bf));
        svp_image *x = test_random_image(w, h, 31), *ya = test_image(w, h), *yf = test_image(w, h);
        const size_t bytes = (size_t)w * h * sizeof(double);
        ASSERT_OK(svp_blur_apply(b, x, ya));
        ASSERT_OK(svp_blur_apply(bf, x, yf));
        assert_memory_equal(ya->data, yf->data, bytes);
        ASSERT_OK(svp_blur_adjoint(b, x, ya));
        ASSERT_OK(svp_blur_adjoint(bf, x, yf));
        assert_memory_equal(ya->data, yf->data, bytes);
        svp_image_free(x);
        svp_image_free(ya);
        svp_image_free(yf);
        svp_blur_free(bf);
    }
    svp_blur_free(b);
    svp_psf_field_free(fb);
    /* forced, over the memory limit: refused before the build, naming the representation */
    o = regions_options();
    o.max_memory = 1e5;
    assert_int_equal(svp_blur_new_field(f, w, h, SVP_BOUNDARY_MIRROR, &o, &b), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "regions, 3 region kernels"));
    svp_blur_free(ex);
    svp_psf_field_free(f);
}

/* (f) Single precision (svp_blur_set_single, and built in single): within 2e-6 of the peak of
 * the double result (the bound of test_variant's single-precision test), sharp and blended,
 * with a halo, every boundary. */
static void test_single_precision(void **state)
{
    (void)state;
    const int w = 48, h = 40;
    double worst = 0;
    for (int c = 0; c < 2; c++) {
        svp_psf_field *f = three_regions(w, h, c ? 5.0 : 0.0, 1, c ? 0 : 8, 0);
        svp_image *x = test_random_image(w, h, 21), *yv = test_random_image(w, h, 22);
        svp_image *hd = test_image(w, h), *hs = test_image(w, h), *td = test_image(w, h);
        svp_image *ts = test_image(w, h), *hb = test_image(w, h);
        for (int m = 0; m < 3; m++) {
            svp_variant_options o = regions_options();
            svp_blur *b = NULL, *bs = NULL;
            ASSERT_OK(svp_blur_new_field(f, w, h, modes[m], &o, &b));
            ASSERT_OK(svp_blur_apply(b, x, hd));
            ASSERT_OK(svp_blur_adjoint(b, yv, td));
            ASSERT_OK(svp_blur_set_precision(b, 1));
            ASSERT_OK(svp_blur_apply(b, x, hs));
            ASSERT_OK(svp_blur_adjoint(b, yv, ts));
            const double e1 = test_max_abs_diff(hs, hd) / test_max_abs(hd);
            const double e2 = test_max_abs_diff(ts, td) / test_max_abs(td);
            if (!(e1 <= 2e-6 && e2 <= 2e-6 && e1 > 0))
                fail_msg("%s, transition %d: single vs double %.3g (H), %.3g (Ht)", mode_names[m],
                         c, e1, e2);
            worst = fmax(worst, fmax(e1, e2));
            o.single_precision = 1;
            ASSERT_OK(svp_blur_new_field(f, w, h, modes[m], &o, &bs));
            ASSERT_OK(svp_blur_apply(bs, x, hb));
            assert_true(test_max_abs_diff(hb, hs) == 0);
            assert_true(svp_blur_memory(bs) < svp_blur_memory(b));
            svp_blur_free(bs);
            svp_blur_free(b);
        }
        svp_image_free(x);
        svp_image_free(yv);
        svp_image_free(hd);
        svp_image_free(hs);
        svp_image_free(td);
        svp_image_free(ts);
        svp_image_free(hb);
        svp_psf_field_free(f);
    }
    print_message("regions, single vs double: at most %.2g of the peak\n", worst);
}

/* (g) Regions forced on a field that is not a region map: SVP_ERR_INVALID saying so, from the
 * build and from the estimate; an unknown representation is refused too. */
static void test_not_a_region_map(void **state)
{
    (void)state;
    const int w = 32, h = 32;
    svp_psf base = moffat(3, 0, 0, 2, 0);
    const int nt = svp_psf_field_poly_terms(1);
    double c[SVP_FIELD_NPARAM * 3] = {0};
    c[SVP_FIELD_FWHM * nt] = 3;
    c[SVP_FIELD_FWHM * nt + 1] = 0.5;
    c[SVP_FIELD_BETA * nt] = 2;
    svp_psf_field *f = NULL;
    ASSERT_OK(svp_psf_field_new_poly(&base, w, h, 1, c, &f));
    svp_variant_options o = regions_options();
    svp_blur *b = NULL;
    assert_int_equal(svp_blur_new_field(f, w, h, SVP_BOUNDARY_ZERO, &o, &b), SVP_ERR_INVALID);
    assert_null(b);
    assert_non_null(strstr(svp_last_error(), "kind regions"));
    assert_non_null(strstr(svp_last_error(), "kind poly"));
    double e = 0;
    assert_int_equal(svp_variant_estimate(f, w, h, SVP_BOUNDARY_ZERO, &o, &e), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "kind regions"));
    o.representation = (svp_variant_repr)4;
    assert_int_equal(svp_blur_new_field(f, w, h, SVP_BOUNDARY_ZERO, &o, &b), SVP_ERR_INVALID);
    /* automatic on a poly field: never regions */
    svp_variant_defaults(&o);
    o.tolerance = 1e-2;
    ASSERT_OK(svp_blur_new_field(f, w, h, SVP_BOUNDARY_ZERO, &o, &b));
    svp_variant_info info;
    ASSERT_OK(svp_blur_variant_info(b, &info));
    assert_true(info.representation != SVP_VARIANT_REGIONS);
    svp_blur_free(b);
    svp_psf_field_free(f);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_sharp_exact),        cmocka_unit_test(test_explicit_sum),
        cmocka_unit_test(test_flux_and_adjoint),   cmocka_unit_test(test_blended_estimate),
        cmocka_unit_test(test_auto_picks_regions), cmocka_unit_test(test_single_precision),
        cmocka_unit_test(test_not_a_region_map),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
