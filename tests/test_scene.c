/* Scenes (src/scene): the plan holds exactly the stages a scene asks for; bad scene files fail
 * with the exact status and file:line:col; a small scene end to end agrees with the transforms
 * run directly; reconstructions through a scene; noise; the cube path against the closed form;
 * outputs written as listed. Small images throughout (<= 96²). */
#include "test_helpers.h"

#include "core/internal.h"
#include "figure/figure.h"
#include "scene/scene_internal.h"

#include <cairo.h>
#include <stdint.h>

#include <stdio.h>
#include <sys/stat.h>
#include <unistd.h>

/* ---- helpers ---------------------------------------------------------------------------- */

static svp_scene *load(const char *name, const char *text)
{
    svp_scene *s = NULL;
    svp_status st = svp_scene_load_string(name, text, strlen(text), &s);
    if (st != SVP_OK) fail_msg("scene did not load: %s", svp_last_error());
    return s;
}

/* "grid,sources,..." */
static void plan_string(const svp_scene *s, char *buf, size_t size)
{
    const svp_scene_stage *st = NULL;
    int n = svp_scene_plan(s, &st);
    buf[0] = '\0';
    for (int i = 0; i < n; i++) {
        strncat(buf, i ? "," : "", size - strlen(buf) - 1);
        strncat(buf, st[i].name, size - strlen(buf) - 1);
    }
}

static void assert_plan(const char *text, const char *expected)
{
    svp_scene *s = load("plan.yaml", text);
    char buf[512];
    plan_string(s, buf, sizeof buf);
    if (strcmp(buf, expected) != 0) fail_msg("plan\n  got      %s\n  expected %s", buf, expected);
    svp_scene_free(s);
}

static svp_scene_result *run_nowrite(const svp_scene *s)
{
    svp_scene_options o;
    svp_scene_defaults(&o);
    o.write = 0;
    svp_scene_result *r = NULL;
    ASSERT_OK(svp_scene_run(s, NULL, &o, &r));
    return r;
}

/* The status of a run that writes nothing (its result freed): for the runs that must fail. */
static svp_status run_nowrite_status(const svp_scene *s)
{
    svp_scene_options o;
    svp_scene_defaults(&o);
    o.write = 0;
    svp_scene_result *r = NULL;
    svp_status st = svp_scene_run(s, NULL, &o, &r);
    svp_scene_result_free(r);
    return st;
}

static const svp_image *map(const svp_scene_result *r, const char *name)
{
    const svp_image *m = svp_scene_result_map(r, name);
    if (!m) fail_msg("no map %s", name);
    return m;
}

static double value(const svp_scene_result *r, const char *key)
{
    double v = 0;
    if (!svp_scene_result_value(r, key, &v)) fail_msg("no value %s", key);
    return v;
}

#define FLAKE_SCENE_HEAD                                                                           \
    "grid: {pixel_um: 0.1, size_um: [6.4, 6.4]}\n"                                                 \
    "sources:\n"                                                                                   \
    "  - flake: {shape: rectangle, size_um: [3.2, 3.2], magnetisation_A_per_m: 1.0e6,\n"           \
    "            thickness_nm: 1, standoff_nm: 100}\n"

/* ---- plans ------------------------------------------------------------------------------ */

static void test_plan_closed_form(void **state)
{
    (void)state;
    /* no spectrum, no noise, no margin, nothing to correct: the bare closed form */
    assert_plan(FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n",
                "grid,sources,emission,operator,forward,metrics,figures,write");
    /* margin, noise, two corrections, a reconstruction; no figures */
    assert_plan("grid: {pixel_um: 0.1, size_um: [6.4, 6.4], margin_um: 1}\n"
                "sources:\n"
                "  - strip: {width_um: 2, sheet_current_A_per_m: 200, standoff_nm: 100}\n"
                "field: {components: [x, z]}\n"
                "emission: [{gaussian: {fwhm_um: 5}}]\n"
                "psf: {model: lorentzian, fwhm_um: 0.5}\n"
                "effects: {noise: {photons_per_pixel: 1.0e6}}\n"
                "correct: [{method: rw}, {method: w}]\n"
                "reconstruct: current_from_bxy\n"
                "outputs: {figures: false}\n",
                "grid,sources,emission,operator,forward,crop,noise,correct,correct,reconstruct,"
                "metrics,write");
    /* an NV axis adds the projection */
    assert_plan(FLAKE_SCENE_HEAD "field: {nv_axis: [1, 1, 1]}\n"
                                 "psf: {model: gaussian, fwhm_um: 0.3}\n",
                "grid,sources,projection,emission,operator,forward,metrics,figures,write");
    svp_scene *s = load("plan.yaml", FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n");
    assert_int_equal(svp_scene_has_stage(s, "cube"), 0);
    assert_int_equal(svp_scene_has_stage(s, "noise"), 0);
    assert_int_equal(svp_scene_has_stage(s, "forward"), 1);
    svp_scene_free(s);
}

static void test_plan_spectrum(void **state)
{
    (void)state;
    /* the cube replaces the closed form; the closed form only as the comparison */
    assert_plan(FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                                 "effects: {spectrum: {points: 20}}\n",
                "grid,sources,emission,operator,cube,estimate,compare,metrics,figures,write");
    assert_plan(FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                                 "effects:\n"
                                 "  spectrum: {points: 20, estimator: lorentzian_fit}\n"
                                 "  drift: {total_um: [0.1, 0]}\n"
                                 "  noise: {photons_per_pixel: 1.0e7, seed: 3}\n"
                                 "reconstruct: magnetisation\n",
                "grid,sources,emission,operator,cube,drift,noise,estimate,compare,reconstruct,"
                "metrics,figures,write");
    svp_scene *s = load("plan.yaml", FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                                                      "effects: {spectrum: {points: 20}}\n");
    assert_int_equal(svp_scene_has_stage(s, "forward"), 0);
    assert_int_equal(svp_scene_has_stage(s, "noise"), 0);
    assert_int_equal(svp_scene_has_stage(s, "drift"), 0);
    svp_scene_free(s);
}

/* ---- bad scene files -------------------------------------------------------------------- */

typedef struct bad_case {
    const char *text;
    svp_status status;
    const char *where;   /* "bad.yaml:L:C:" */
    const char *message; /* a substring */
} bad_case;

static void test_bad_scenes(void **state)
{
    (void)state;
    static const bad_case cases[] = {
        /* unknown key (a typo) */
        {"grid: {pixel_um: 0.1, size_um: [6.4, 6.4]}\ngird: 1\n", SVP_ERR_FORMAT,
         "bad.yaml:2:1:", "unknown key 'gird'"},
        /* a length with the wrong unit */
        {"grid: {pixel_um: 0.1, size_um: [6.4, 6.4]}\n"
         "sources:\n"
         "  - flake: {shape: disk, diameter_um: 2, magnetisation_A_per_m: 1.0e6,\n"
         "            thickness_nm: 1, standoff_um: 0.1}\n",
         SVP_ERR_FORMAT, "bad.yaml:4:30:", "wrong or missing unit"},
        /* a bare key without its unit */
        {"grid: {pixel: 0.1, size_um: [6.4, 6.4]}\n", SVP_ERR_FORMAT,
         "bad.yaml:1:8:", "grid.pixel: wrong or missing unit: this value is given as 'pixel_um'"},
        /* wrong type */
        {"grid: {pixel_um: abc, size_um: [6.4, 6.4]}\n", SVP_ERR_FORMAT,
         "bad.yaml:1:18:", "must be a number"},
        /* a value with its unit written in */
        {"grid: {pixel_um: 0.1 um, size_um: [6.4, 6.4]}\n", SVP_ERR_FORMAT,
         "bad.yaml:1:18:", "must be a number"},
        /* wrong list length */
        {"grid: {pixel_um: 0.1, size_um: [6.4]}\n", SVP_ERR_FORMAT,
         "bad.yaml:1:32:", "size_um must be a list of 2 numbers"},
        /* impossible values */
        {"grid: {pixel_um: -0.1, size_um: [6.4, 6.4]}\n", SVP_ERR_INVALID,
         "bad.yaml:1:18:", "must be >= 1e-06"},
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: -1}\n", SVP_ERR_INVALID,
         "bad.yaml:5:33:", "psf.fwhm_um must be > 0"},
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "emission: [{quench: {under: flakes, factor: 1.5}}]\n",
         SVP_ERR_INVALID, "bad.yaml:6:45:", "factor must be in [0, 1]"},
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "metrics: {line_cuts: [{from_um: [-9, 0], to_um: [1, 0]}]}\n",
         SVP_ERR_INVALID, "bad.yaml:6:33:", "lies outside the view"},
        {"grid: {pixel_um: 0.1, size_um: [6.4, 6.4]}\n"
         "sources:\n"
         "  - flake: {shape: disk, diameter_um: 9, magnetisation_A_per_m: 1.0e6,\n"
         "            thickness_nm: 1, standoff_nm: 100}\n"
         "psf: {model: gaussian, fwhm_um: 0.3}\n",
         SVP_ERR_INVALID, "bad.yaml:3:12:", "reaches beyond the canvas"},
        /* an effect without what it needs */
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "effects: {drift: {total_um: [0.1, 0]}}\n",
         SVP_ERR_INVALID, "bad.yaml:6:18:", "drift needs effects.spectrum"},
        {FLAKE_SCENE_HEAD "field: {components: [x]}\n"
                          "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "reconstruct: magnetisation\n",
         SVP_ERR_INVALID, "bad.yaml:7:14:", "needs B_z"},
        /* a missing key */
        {FLAKE_SCENE_HEAD, SVP_ERR_FORMAT, "bad.yaml:1:1:", "missing required key 'psf'"},
        /* a missing file (relative to the scene file) */
        {"grid: {pixel_um: 0.1, size_um: [6.4, 6.4]}\n"
         "sources:\n"
         "  - field_file: {path: no_such_field.npy, component: z, unit: uT}\n"
         "psf: {model: gaussian, fwhm_um: 0.3}\n",
         SVP_ERR_IO, "bad.yaml:3:24:", "no_such_field.npy: no such file"},
        /* a wrong choice */
        {FLAKE_SCENE_HEAD "psf: {model: gauss, fwhm_um: 0.3}\n", SVP_ERR_INVALID,
         "bad.yaml:5:14:", "must be one of gaussian, lorentzian, moffat"},
        /* a correction's margin: negative, or a word other than auto; an unknown precision */
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "correct: {method: r, margin: -1}\n",
         SVP_ERR_INVALID, "bad.yaml:6:30:", "correct.margin must be in [0, 10000], got -1"},
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "correct: {method: r, margin: wide}\n",
         SVP_ERR_FORMAT, "bad.yaml:6:30:", "must be a number"},
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "correct: {method: r, precision: half}\n",
         SVP_ERR_INVALID, "bad.yaml:6:33:", "must be one of double, single"},
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "correct: {method: r, acceleration: nesterov}\n",
         SVP_ERR_INVALID, "bad.yaml:6:36:", "must be one of none, biggs-andrews"},
        {FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                          "correct: {method: r, tail_tol: 1}\n",
         SVP_ERR_INVALID, "bad.yaml:6:32:", "correct.tail_tol must be in [0, 1), got 1"},
        /* malformed YAML */
        {"grid: {pixel_um: 0.1, size_um: [6.4, 6.4]\n", SVP_ERR_FORMAT, "bad.yaml:", ""},
    };
    int failures = 0;
    for (size_t i = 0; i < sizeof cases / sizeof cases[0]; i++) {
        svp_scene *s = NULL;
        svp_status st = svp_scene_load_string("bad.yaml", cases[i].text, strlen(cases[i].text), &s);
        const char *msg = svp_last_error();
        if (st != cases[i].status) {
            print_error("case %zu: status %d, expected %d (%s)\n", i, st, cases[i].status, msg);
            failures++;
        } else if (strncmp(msg, cases[i].where, strlen(cases[i].where)) != 0 ||
                   !strstr(msg, cases[i].message)) {
            print_error("case %zu: message '%s' lacks '%s' ... '%s'\n", i, msg, cases[i].where,
                        cases[i].message);
            failures++;
        }
        assert_null(s);
    }
    if (failures) fail_msg("%d bad scene(s) not reported as expected", failures);
}

/* ---- end to end against the transforms run directly -------------------------------------- */

static void test_end_to_end_matches_transforms(void **state)
{
    (void)state;
    svp_scene *s = load("e2e.yaml", FLAKE_SCENE_HEAD
                        "emission:\n"
                        "  - gaussian: {fwhm_um: 6}\n"
                        "  - chessboard: {square_um: 0.8, levels: [0.1, 0.8, 1.0], seed: 2}\n"
                        "psf: {model: lorentzian, fwhm_um: 0.4}\n"
                        "correct: {method: rw, iterations: 10, balance: 0.01}\n"
                        "reconstruct: magnetisation\n"
                        "metrics:\n"
                        "  masks: [{name: flake, inside: flakes, erode_um: 0.3}]\n");
    svp_scene_result *r = run_nowrite(s);
    const svp_image *pl = map(r, "pl_true"), *bz = map(r, "B_z_true");
    const int w = pl->width, h = pl->height;
    /* a space-invariant PSF: one OTF, no variant operator */
    assert_true(value(r, "operator/variant") == 0);
    assert_int_equal(w, 64);
    assert_int_equal(h, 64);
    /* every map finite except the relative-error maps (NaN marks "undefined") */
    for (int i = 0; i < 64; i++) {
        const char *names[] = {"pl_apparent",      "B_z_apparent", "pl_corrected_rw",
                               "B_z_corrected_rw", "m_z_true",     "m_z_apparent",
                               "m_z_corrected_rw", "validity_rw",  NULL};
        if (!names[i]) break;
        if (!test_all_finite(map(r, names[i]))) fail_msg("%s has NaN/Inf", names[i]);
    }
    /* T run directly on the scene's true maps */
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_LORENTZIAN;
    psf.beta = 1;
    psf.fwhm = 4;
    svp_blur *blur = NULL;
    ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_ZERO, &blur));
    svp_image *pla = test_image(w, h), *bza = test_image(w, h);
    const svp_image *ft[1] = {bz};
    svp_image *fa[1] = {bza};
    ASSERT_OK(svp_forward_transform(blur, pl, ft, 1, pla, fa, NULL));
    double e_pl = test_max_abs_diff(pla, map(r, "pl_apparent"));
    double e_bz = test_max_abs_diff(bza, map(r, "B_z_apparent"));
    if (e_pl > 1e-14 || e_bz > 1e-12 * test_max_abs(bz))
        fail_msg("scene T differs from svp_forward_transform: PL %.3g, B_z %.3g T", e_pl, e_bz);
    /* T⁻¹ run directly */
    svp_correct_options o;
    svp_correct_defaults(&o);
    o.method = SVP_METHOD_RW;
    o.deconv.iterations = 10;
    o.deconv.balance = 0.01;
    svp_image *plc = test_image(w, h), *bzc = test_image(w, h), *val = test_image(w, h);
    const svp_image *fa2[1] = {map(r, "B_z_apparent")};
    svp_image *fc[1] = {bzc};
    ASSERT_OK(svp_inverse_transform(blur, map(r, "pl_apparent"), fa2, 1, &o, plc, fc, val, NULL));
    double e_c = test_max_abs_diff(bzc, map(r, "B_z_corrected_rw"));
    if (e_c > 1e-12 * test_max_abs(bz)) fail_msg("scene T^-1 differs by %.3g T", e_c);
    /* metrics from the maps, computed independently */
    const svp_image *mask = map(r, "mask_flake"), *mt = map(r, "m_z_true"),
                    *ma = map(r, "m_z_apparent");
    /* the eroded 3.2 µm square: 32 − 2·3 = 26 pixels a side (erosion by 0.3 µm = 3 px) */
    double n_mask = test_sum(mask);
    ASSERT_CLOSE(n_mask, 26 * 26, 0);
    double mt_peak = test_max_abs(mt);
    double *err = malloc(sizeof(double) * w * h);
    int n = 0;
    double sum_abs_app = 0, sum_abs_true = 0, pk_app = 0;
    for (int i = 0; i < w * h; i++)
        if (mask->data[i] != 0) {
            sum_abs_app += fabs(ma->data[i]);
            sum_abs_true += fabs(mt->data[i]);
            pk_app = fmax(pk_app, fabs(ma->data[i]));
            if (fabs(mt->data[i]) >= 0.05 * mt_peak)
                err[n++] = 100 * fabs(ma->data[i] - mt->data[i]) / fabs(mt->data[i]);
        }
    /* median by selection sort on a copy (n ≤ 676) */
    for (int i = 0; i < n; i++)
        for (int j = i + 1; j < n; j++)
            if (err[j] < err[i]) {
                double t = err[i];
                err[i] = err[j];
                err[j] = t;
            }
    double median = n % 2 ? err[n / 2] : 0.5 * (err[n / 2 - 1] + err[n / 2]);
    free(err);
    ASSERT_CLOSE(value(r, "m_z/flake/apparent/median_abs_rel_err_pct"), median, 1e-9 * median);
    ASSERT_CLOSE(value(r, "m_z/flake/apparent/mean_reduction_pct"),
                 100 * (1 - sum_abs_app / sum_abs_true), 1e-9);
    ASSERT_CLOSE(value(r, "m_z/flake/apparent/peak_abs"), pk_app, 1e-15);
    /* the magnetisation from the true field, inside the flake: 1 mA within 5 % */
    double mean_true = value(r, "m_z/flake/true/mean");
    if (fabs(mean_true - 1e-3) > 0.05e-3) fail_msg("m_z inside the flake %.4g mA", 1e3 * mean_true);
    /* the correction helps: measured median |error| of m_z */
    double e_app = value(r, "m_z/flake/apparent/median_abs_rel_err_pct");
    double e_cor = value(r, "m_z/flake/corrected_rw/median_abs_rel_err_pct");
    print_message("m_z inside the flake: true %.4g mA; median |rel. err.| apparent %.3g %%, "
                  "corrected (rw) %.3g %%\n",
                  1e3 * mean_true, e_app, e_cor);
    if (!(e_cor < e_app))
        fail_msg("the correction did not reduce the error (%g -> %g)", e_app, e_cor);
    svp_blur_free(blur);
    svp_image_free(pla);
    svp_image_free(bza);
    svp_image_free(plc);
    svp_image_free(bzc);
    svp_image_free(val);
    svp_scene_result_free(r);
    svp_scene_free(s);
}

/* Corrections with a margin: `auto` is the PSF's reach at 1 % of its peak (at most a quarter of
 * the view), a number is µm; each equals svp_inverse_transform run directly on an operator of the
 * view plus that margin (the third with Biggs–Andrews acceleration, as `acceleration:` asks;
 * the fourth on the plain frame, as `tail_tol: 0` asks). */
static void test_correct_margin(void **state)
{
    (void)state;
    svp_scene *s = load("margin.yaml",
                        "grid: {pixel_um: 0.1, size_um: [6.4, 6.4], margin_um: 1}\n"
                        "sources:\n"
                        "  - flake: {shape: rectangle, size_um: [3.2, 3.2], "
                        "magnetisation_A_per_m: 1.0e6,\n"
                        "            thickness_nm: 1, standoff_nm: 100}\n"
                        "emission: [{gaussian: {fwhm_um: 6}}]\n"
                        "psf: {model: moffat, fwhm_um: 0.3, beta: 2}\n"
                        "correct:\n"
                        "  - {method: r, iterations: 20, margin: auto, name: auto}\n"
                        "  - {method: r, iterations: 20, margin: 0.5, name: half_um,"
                        " precision: single}\n"
                        "  - {method: r, iterations: 20, margin: auto, name: accelerated,"
                        " acceleration: biggs-andrews}\n"
                        "  - {method: r, iterations: 20, margin: auto, name: plain_frame,"
                        " tail_tol: 0}\n");
    svp_scene_result *r = run_nowrite(s);
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_MOFFAT;
    psf.fwhm = 3;
    psf.beta = 2;
    /* Moffat: r0 √(100^(1/β) − 1) = r0 · 3 with r0 = 1.5 / √(√2 − 1) */
    const double reach = 1.5 / sqrt(sqrt(2.0) - 1) * 3;
    ASSERT_CLOSE(svp_psf_reach(&psf, 0.01), reach, 1e-12 * reach);
    const int m_auto = (int)ceil(reach);
    assert_int_equal((int)value(r, "correct/auto/margin_px"), m_auto);
    assert_int_equal((int)value(r, "correct/half_um/margin_px"), 5);
    const svp_image *pla = map(r, "pl_apparent");
    const int w = pla->width, h = pla->height;
    /* the library's rule: the reach rounded up, at most a quarter of the view, 0 with a halo */
    assert_int_equal(svp_psf_auto_margin(&psf, w, h), m_auto);
    assert_int_equal(svp_psf_auto_margin(&psf, 20, 12), 5);
    svp_psf haloed = psf;
    haloed.halo = 0.2;
    assert_int_equal(svp_psf_auto_margin(&haloed, w, h), 0);
    const int margins[4] = {m_auto, 5, m_auto, m_auto};
    const char *names[4] = {"B_z_corrected_auto", "B_z_corrected_half_um",
                            "B_z_corrected_accelerated", "B_z_corrected_plain_frame"};
    /* tail_tol: 0 keeps the plain frame (the key reached T⁻¹) */
    assert_int_equal((int)value(r, "correct/plain_frame/tail_step_px"), 0);
    /* the accelerated correction is not the plain one: the key reached the solver */
    const double plain_peak = test_max_abs(map(r, names[0]));
    if (test_max_abs_diff(map(r, names[0]), map(r, names[2])) < 1e-6 * plain_peak)
        fail_msg("acceleration: biggs-andrews gave the plain correction");
    for (int k = 0; k < 4; k++) {
        svp_blur *blur = NULL;
        ASSERT_OK(svp_blur_new(&psf, w + 2 * margins[k], h + 2 * margins[k], SVP_BOUNDARY_ZERO,
                               &blur));
        svp_correct_options o;
        svp_correct_defaults(&o);
        o.method = SVP_METHOD_R;
        o.deconv.iterations = 20;
        o.deconv.balance = 1;
        o.deconv.single_precision = k == 1;
        o.deconv.acceleration = k == 2 ? SVP_RL_BIGGS_ANDREWS : SVP_RL_PLAIN;
        o.margin = margins[k];
        if (k == 3) o.tail_tol = 0;
        o.keep_doubtful = 1;
        svp_image *plc = test_image(w, h), *bzc = test_image(w, h), *val = test_image(w, h);
        const svp_image *fa[1] = {map(r, "B_z_apparent")};
        svp_image *fc[1] = {bzc};
        ASSERT_OK(svp_inverse_transform(blur, pla, fa, 1, &o, plc, fc, val, NULL));
        const double e = test_max_abs_diff(bzc, map(r, names[k]));
        if (e > 1e-12 * test_max_abs(bzc)) fail_msg("%s differs by %.3g T", names[k], e);
        svp_blur_free(blur);
        svp_image_free(plc);
        svp_image_free(bzc);
        svp_image_free(val);
    }
    svp_scene_result_free(r);
    svp_scene_free(s);
}

/* A margin with region PSFs (the scene's map carried onto the margin from its edge,
 * svp_psf_field_pad): `auto` is the map's widest PSF's reach (svp_psf_field_auto_margin), and
 * the correction equals svp_inverse_transform on the padded map's tent operator; with the
 * mirror boundary an explicit margin is refused. */
static void test_correct_margin_regions(void **state)
{
    (void)state;
    static const char *const scene_text =
        "grid: {pixel_um: 0.1, size_um: [6.4, 6.4], margin_um: 1}\n"
        "sources:\n"
        "  - flake: {shape: rectangle, size_um: [3.2, 3.2], magnetisation_A_per_m: 1.0e6,\n"
        "            thickness_nm: 1, standoff_nm: 100}\n"
        "emission: [{gaussian: {fwhm_um: 6}}]\n"
        "psf: {model: moffat, fwhm_um: 0.3, beta: 2, nodes: 4,\n"
        "      regions: [{under: flakes, fwhm_um: 0.5, beta: 1.5}]}\n"
        "correct:\n"
        "  - {method: r, iterations: 20, margin: auto, name: auto}\n";
    svp_scene *s = load("margin_regions.yaml", scene_text);
    svp_scene_result *r = run_nowrite(s);
    const svp_image *pla = map(r, "pl_apparent");
    const int w = pla->width, h = pla->height; /* 64 x 64: the flake covers pixels 16..47 */
    svp_psf base, flake;
    svp_psf_defaults(&base);
    base.model = SVP_PSF_MOFFAT;
    base.fwhm = 3;
    base.beta = 2;
    flake = base;
    flake.fwhm = 5;
    flake.beta = 1.5;
    int *labels = malloc((size_t)w * h * sizeof(int));
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++)
            labels[y * w + x] = x >= 16 && x < 48 && y >= 16 && y < 48;
    svp_psf psfs[2] = {base, flake};
    svp_psf_field *field = NULL, *padded = NULL;
    ASSERT_OK(svp_psf_field_new_regions(w, h, labels, 2, psfs, 0, &field));
    free(labels);
    const int m = svp_psf_field_auto_margin(field, w, h);
    assert_int_equal(m, svp_psf_auto_margin(&flake, w, h)); /* the wider PSF's */
    assert_true(m > svp_psf_auto_margin(&base, w, h));
    assert_int_equal((int)value(r, "correct/auto/margin_px"), m);
    ASSERT_OK(svp_psf_field_pad(field, m, &padded));
    svp_variant_options vo;
    svp_variant_defaults(&vo);
    vo.representation = SVP_VARIANT_TENT;
    vo.grid_x = vo.grid_y = 4;
    svp_blur *blur = NULL;
    ASSERT_OK(svp_blur_new_field(padded, w + 2 * m, h + 2 * m, SVP_BOUNDARY_ZERO, &vo, &blur));
    svp_correct_options o;
    svp_correct_defaults(&o);
    o.method = SVP_METHOD_R;
    o.deconv.iterations = 20;
    o.margin = m;
    o.keep_doubtful = 1;
    svp_image *plc = test_image(w, h), *bzc = test_image(w, h), *val = test_image(w, h);
    const svp_image *fa[1] = {map(r, "B_z_apparent")};
    svp_image *fc[1] = {bzc};
    ASSERT_OK(svp_inverse_transform(blur, pla, fa, 1, &o, plc, fc, val, NULL));
    const double e = test_max_abs_diff(bzc, map(r, "B_z_corrected_auto"));
    if (e > 1e-12 * test_max_abs(bzc)) fail_msg("the scene's correction differs by %.3g T", e);
    svp_blur_free(blur);
    svp_image_free(plc);
    svp_image_free(bzc);
    svp_image_free(val);
    svp_psf_field_free(padded);
    svp_psf_field_free(field);
    svp_scene_result_free(r);
    svp_scene_free(s);
    /* the mirror boundary has no outside: an explicit margin is refused, auto gives none */
    s = load("margin_mirror.yaml",
             "grid: {pixel_um: 0.1, size_um: [6.4, 6.4]}\n"
             "sources:\n"
             "  - flake: {shape: rectangle, size_um: [3.2, 3.2], magnetisation_A_per_m: 1.0e6,\n"
             "            thickness_nm: 1, standoff_nm: 100}\n"
             "psf: {model: moffat, fwhm_um: 0.3, beta: 2, boundary: mirror,\n"
             "      regions: [{under: flakes, fwhm_um: 0.5, beta: 1.5}]}\n"
             "correct: [{method: r, iterations: 5, margin: 0.5}]\n");
    svp_scene_options so;
    svp_scene_defaults(&so);
    so.write = 0;
    r = NULL;
    assert_int_equal(svp_scene_run(s, NULL, &so, &r), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "a margin needs the zero boundary"));
    svp_scene_result_free(r);
    svp_scene_free(s);
}

/* The strip through a scene: current density from B_x in the middle of the strip. */
static void test_strip_reconstruction(void **state)
{
    (void)state;
    svp_scene *s = load("strip.yaml",
                        "grid: {pixel_um: 0.1, size_um: [9.6, 6.4]}\n"
                        "sources:\n"
                        "  - strip: {width_um: 4, sheet_current_A_per_m: 200, standoff_nm: 100}\n"
                        "field: {components: [x, z]}\n"
                        "psf: {model: gaussian, fwhm_um: 0.3}\n"
                        "reconstruct: current_from_bxy\n"
                        "metrics:\n"
                        "  masks: [{name: middle, inside: strips, erode_um: 1.5}]\n");
    svp_scene_result *r = run_nowrite(s);
    double j = value(r, "J_bxy/middle/true/mean");
    print_message("strip: |J| from B_x in the middle %.4g A/m (200 A/m)\n", j);
    if (fabs(j - 200) > 4) fail_msg("|J| in the middle %.4g A/m, not within 2 %% of 200", j);
    /* B_x at the centre of the strip against the closed form (µ0 J / π) atan(w / 2h) */
    const svp_image *bx = map(r, "B_x_true");
    double centre = 0.5 * (bx->data[31 * 96 + 47] + bx->data[31 * 96 + 48]);
    /* the strip is centred between pixels 47 and 48 (view centre); the mean of the two
     * neighbours differs from the centre value by far less than 1e-4 for w = 4 µm */
    double expect = 4e-7 * 200 * atan(2.0 / 0.1);
    ASSERT_CLOSE(centre, expect, 1e-4 * expect);
    svp_scene_result_free(r);
    svp_scene_free(s);
}

/* A wire without current is still metal: it quenches the emission under it and its 'strips'
 * mask exists (both came from |J| / J, so a current of 0 made neither: no quench, and an
 * empty default mask that stopped the run) */
static void test_strip_without_current(void **state)
{
    (void)state;
    svp_scene *s = load("dark_wire.yaml",
                        FLAKE_SCENE_HEAD
                        "  - strip: {width_um: 1, current_mA: 0, standoff_nm: 60, angle_deg: 90,\n"
                        "            centre_um: [-2.5, 0]}\n"
                        "emission:\n"
                        "  - quench: {under: strips, factor: 0.1}\n"
                        "psf: {model: gaussian, fwhm_um: 0.3}\n"
                        "metrics:\n"
                        "  masks: [{name: wire, inside: strips}]\n");
    svp_scene_result *r = run_nowrite(s);
    const svp_image *pl = map(r, "pl_true"), *wire = map(r, "mask_wire");
    size_t n_wire = 0;
    const size_t n = (size_t)pl->width * pl->height;
    for (size_t p = 0; p < n; p++)
        if (wire->data[p] != 0) {
            n_wire++;
            ASSERT_CLOSE(pl->data[p], 0.1, 1e-12);
        }
    /* 1 µm wide (10 px) across the 64 px view */
    assert_int_equal(n_wire, 10 * 64);
    svp_scene_result_free(r);
    svp_scene_free(s);
    /* a wire outside the view leaves its default mask empty: named as a default, not as
     * "s.yaml: : mask" */
    s = load("far_wire.yaml", "grid: {pixel_um: 0.1, size_um: [6.4, 6.4]}\n"
                              "sources:\n"
                              "  - strip: {width_um: 1, current_mA: 1, standoff_nm: 60,\n"
                              "            angle_deg: 90, centre_um: [100, 0]}\n"
                              "psf: {model: gaussian, fwhm_um: 0.3}\n");
    assert_int_equal(run_nowrite_status(s), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "the default mask 'strip' holds no pixel"));
    assert_non_null(strstr(svp_last_error(), "are the sources inside the view?"));
    svp_scene_free(s);
}

/* Failed per-pixel fits of a spectrum are missing data (NaN), as `svpsf fit-odmr` writes them
 * by default: the corrections treat them as missing, the reconstructions fill them and give
 * NaN there, the metrics skip them. Before, a fit's last parameters (up to 1e95 T at 10
 * photons) went on as data. A measurement whose fits mostly fail is refused. */
#define NOISY_SPECTRUM(photons)                                                                    \
    "grid: {pixel_um: 0.1, size_um: [4, 4]}\n"                                                     \
    "sources:\n"                                                                                   \
    "  - flake: {shape: rectangle, size_um: [2, 2], magnetisation_A_per_m: 1.0e5,\n"               \
    "            thickness_nm: 1, standoff_nm: 100}\n"                                             \
    "psf: {model: gaussian, fwhm_um: 0.3}\n"                                                       \
    "effects:\n"                                                                                   \
    "  spectrum: {points: 50, linewidth_MHz: 1, contrast: 0.02, estimator: lorentzian_fit}\n"      \
    "  noise: {photons_per_pixel: " photons ", seed: 1}\n"                                         \
    "correct:\n"                                                                                   \
    "  - {method: r, iterations: 10}\n"                                                            \
    "reconstruct: magnetisation\n"

static void test_failed_fits_are_missing(void **state)
{
    (void)state;
    svp_scene *s = load("noisy.yaml", NOISY_SPECTRUM("1e7"));
    svp_scene_result *r = run_nowrite(s);
    const double failed = value(r, "cube/z/fits_not_converged");
    const svp_image *app = map(r, "B_z_apparent"), *mz = map(r, "m_z_apparent");
    const size_t n = (size_t)app->width * app->height;
    size_t n_nan = 0, n_mz_nan = 0;
    for (size_t p = 0; p < n; p++) {
        n_nan += isnan(app->data[p]) != 0;
        n_mz_nan += isnan(mz->data[p]) != 0;
    }
    print_message("1e7 photons: %.0f of %zu fits failed, %zu NaN in B_z_apparent; m_z filled at "
                  "%.0f pixels\n",
                  failed, n, n_nan, value(r, "reconstruct/m_z/apparent/filled_pixels"));
    assert_true(failed > 0 && failed < 0.5 * (double)n);
    assert_int_equal(n_nan, (size_t)failed);
    assert_int_equal(n_mz_nan, (size_t)failed);
    ASSERT_CLOSE(value(r, "reconstruct/m_z/apparent/filled_pixels"), failed, 0);
    const svp_image *corr = map(r, "B_z_corrected_r");
    for (size_t p = 0; p < n; p++) assert_true(isfinite(corr->data[p]));
    svp_scene_result_free(r);
    svp_scene_free(s);
    /* 10 photons: nearly every fit fails */
    s = load("hopeless.yaml", NOISY_SPECTRUM("10"));
    assert_int_equal(run_nowrite_status(s), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "pixel fits of B_z did not converge"));
    assert_non_null(strstr(svp_last_error(), "raise effects.noise.photons_per_pixel"));
    svp_scene_free(s);
}

/* ---- noise -------------------------------------------------------------------------------- */

static void test_noise(void **state)
{
    (void)state;
    /* the noise-free correction, then shot noise at falling photon counts: the corrected maps
     * stay finite, the noise part of their error (noisy − noise-free correction) grows as
     * 1/sqrt(photons), and the total error against the truth grows too once the noise
     * dominates the correction's own (systematic) error */
    const double photons[] = {0, 1e6, 1e5, 1e4, 1e3};
    svp_image *clean = NULL;
    double prev_noise = 0, prev_total = 0;
    for (int k = 0; k < 5; k++) {
        char text[1024], effects[128] = "";
        if (photons[k] > 0)
            snprintf(effects, sizeof effects,
                     "effects: {noise: {photons_per_pixel: %g, seed: 7}}\n", photons[k]);
        snprintf(text, sizeof text,
                 FLAKE_SCENE_HEAD "emission: [{gaussian: {fwhm_um: 6}}]\n"
                                  "psf: {model: gaussian, fwhm_um: 0.3}\n"
                                  "%s"
                                  "correct: {method: rw, iterations: 10, balance: 0.01}\n"
                                  "metrics: {masks: [{name: view}]}\n",
                 effects);
        svp_scene *s = load("noise.yaml", text);
        svp_scene_result *r = run_nowrite(s);
        const svp_image *corr = map(r, "B_z_corrected_rw");
        assert_true(test_all_finite(corr));
        assert_true(test_all_finite(map(r, "pl_corrected_rw")));
        double total = value(r, "B_z/view/corrected_rw/rms_rel_err_pct");
        if (k == 0) {
            ASSERT_OK(svp_image_copy(corr, &clean));
            print_message("noise: none: rms error of corrected B_z %.4g %% of the peak\n", total);
        } else {
            double peak = test_max_abs(map(r, "B_z_true")), d2 = 0;
            for (int i = 0; i < corr->width * corr->height; i++)
                d2 += pow(corr->data[i] - clean->data[i], 2);
            double noise = 100 * sqrt(d2 / (corr->width * corr->height)) / peak;
            print_message("noise: %g photons, field SNR %.3g: rms error of corrected B_z %.4g %% "
                          "of the peak, of which noise %.4g %%\n",
                          photons[k], value(r, "noise/field_snr"), total, noise);
            if (k > 1) {
                double ratio = noise / prev_noise;
                if (!(ratio > 2 && ratio < 5))
                    fail_msg("noise part grew by %.3g for 10x fewer photons (sqrt(10) = 3.16)",
                             ratio);
            }
            if (k >= 4 && !(total > prev_total))
                fail_msg("total error did not grow as the SNR fell: %g -> %g", prev_total, total);
            prev_noise = noise;
        }
        prev_total = total;
        svp_scene_result_free(r);
        svp_scene_free(s);
    }
    svp_image_free(clean);
}

/* Without noise two runs are bit-identical; the same seed repeats the noise exactly, another
 * seed changes it. */
static void test_determinism(void **state)
{
    (void)state;
    const char *texts[3] = {
        FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n",
        FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                         "effects: {noise: {photons_per_pixel: 1.0e6, seed: 1}}\n",
        FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                         "effects: {noise: {photons_per_pixel: 1.0e6, seed: 2}}\n",
    };
    svp_scene_result *r[4];
    for (int i = 0; i < 4; i++) {
        svp_scene *s = load("det.yaml", texts[i < 2 ? 0 : i - 1]);
        if (i == 1) {
            svp_set_threads(1);
            r[i] = run_nowrite(s);
            svp_set_threads(2);
        } else {
            r[i] = run_nowrite(s);
        }
        svp_scene_free(s);
    }
    assert_true(test_max_abs_diff(map(r[0], "B_z_apparent"), map(r[1], "B_z_apparent")) <=
                1e-15 * test_max_abs(map(r[0], "B_z_apparent")));
    svp_scene *s = load("det.yaml", texts[1]);
    svp_scene_result *again = run_nowrite(s);
    svp_scene_free(s);
    assert_true(test_max_abs_diff(map(r[2], "B_z_apparent"), map(again, "B_z_apparent")) == 0);
    assert_true(test_max_abs_diff(map(r[2], "B_z_apparent"), map(r[3], "B_z_apparent")) > 0);
    svp_scene_result_free(again);
    for (int i = 0; i < 4; i++) svp_scene_result_free(r[i]);
}

/* ---- the cube ----------------------------------------------------------------------------- */

#define CUBE_HEAD                                                                                  \
    "grid: {pixel_um: 0.1, size_um: [3.2, 3.2]}\n"                                                 \
    "sources:\n"                                                                                   \
    "  - flake: {shape: rectangle, size_um: [1.6, 1.6], magnetisation_A_per_m: 1.0e4,\n"           \
    "            thickness_nm: 1, standoff_nm: 100}\n"                                             \
    "emission:\n"                                                                                  \
    "  - gaussian: {fwhm_um: 3}\n"                                                                 \
    "  - chessboard: {square_um: 0.4, levels: [0.2, 1.0], seed: 4}\n"                              \
    "psf: {model: lorentzian, fwhm_um: 0.3}\n"

/* The centroid of the blurred cube equals the closed form (eq. 3) with B = the centroid of the
 * unblurred cube and I_m = its weight, to round-off: both centroid sums are linear in the
 * frames. Rebuilt here from the scene's true maps with the library's ODMR functions. */
static void test_cube_centroid_is_closed_form(void **state)
{
    (void)state;
    svp_scene *s = load("cube.yaml", CUBE_HEAD "effects: {spectrum: {points: 40}}\n");
    svp_scene_result *r = run_nowrite(s);
    const svp_image *pl = map(r, "pl_true"), *bz = map(r, "B_z_true");
    const int w = pl->width, h = pl->height, nf = 40;
    const size_t n = (size_t)w * h;
    double bias = value(r, "cube/z/bias_T"), bmax = test_max_abs(bz);
    svp_odmr odmr;
    svp_odmr_defaults(&odmr);
    odmr.linewidth_hz = 1e6;
    odmr.contrast = 0.02;
    double freq[40];
    double lo = 2.87e9 + 28.033e9 * (bias - bmax) - 6e6,
           hi = 2.87e9 + 28.033e9 * (bias + bmax) + 6e6;
    for (int f = 0; f < nf; f++) freq[f] = lo + (hi - lo) * f / (nf - 1);
    ASSERT_CLOSE(freq[1] - freq[0], value(r, "cube/z/frequency_step_Hz"), 1e-6);
    svp_cube *cube = NULL;
    ASSERT_OK(svp_cube_new(w, h, nf, freq, &cube));
    svp_image *bnv = test_image(w, h), *base = test_image(w, h), *b0 = test_image(w, h),
              *w0 = test_image(w, h);
    for (size_t i = 0; i < n; i++) bnv->data[i] = bz->data[i] + bias;
    ASSERT_OK(svp_odmr_simulate(&odmr, pl, bnv, NULL, NULL, cube));
    for (size_t i = 0; i < n; i++) {
        double b = 0;
        for (int e = 0; e < 3; e++) b += cube->frame[e]->data[i] + cube->frame[nf - 1 - e]->data[i];
        base->data[i] = b / 6;
    }
    ASSERT_OK(svp_odmr_centroid(&odmr, cube, base, 0, 0, b0, w0));
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_LORENTZIAN;
    psf.beta = 1;
    psf.fwhm = 3;
    svp_blur *blur = NULL;
    ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_ZERO, &blur));
    svp_image *wa = test_image(w, h), *ba = test_image(w, h);
    const svp_image *ft[1] = {b0};
    svp_image *fa[1] = {ba};
    ASSERT_OK(svp_forward_transform(blur, w0, ft, 1, wa, fa, NULL));
    const svp_image *cube_est = map(r, "B_z_apparent");
    double err = 0;
    for (size_t i = 0; i < n; i++) err = fmax(err, fabs(cube_est->data[i] + bias - ba->data[i]));
    print_message("centroid of the blurred cube vs closed form (eq. 3, I_m = centroid weight): "
                  "max |diff| %.3g T on |B| + bias %.3g T\n",
                  err, bias + bmax);
    if (err > 1e-10 * (bias + bmax)) fail_msg("cube centroid vs closed form: %.3g T", err);
    svp_cube_free(cube);
    svp_blur_free(blur);
    svp_image_free(bnv);
    svp_image_free(base);
    svp_image_free(b0);
    svp_image_free(w0);
    svp_image_free(wa);
    svp_image_free(ba);
    svp_scene_result_free(r);
    svp_scene_free(s);
}

/* effects.drift.register: a drift of 20 nm (a fifth of a pixel) across the sweep ruins the
 * centroid map (the PL at a pixel changes by gradient × drift, read as dip depth); with the
 * frames aligned (svp_cube_align, to frame 0, where the true maps are) the cube estimate is
 * close to the closed form of the drift-free cube: on this 32² view, mean |cube − closed
 * form| 1.7 µT against 262 µT without registration and 0.15 µT without drift (the rest is the
 * view's outermost pixels, where the shift brings in what the view did not see; on the 240²
 * view of docs/scenes/spectrum-drift.yaml 0.30 against 0.29 µT), every frame's shift within
 * 1.7e-4 px of the drift (asserted 0.01). Asserted: 50× better than unregistered. */
static void test_cube_drift_register(void **state)
{
    (void)state;
    double diff[3], err = 0;
    const char *effects[3] = {
        "effects: {spectrum: {points: 40}}\n",
        "effects: {spectrum: {points: 40}, drift: {total_um: [0.02, 0.01]}}\n",
        "effects: {spectrum: {points: 40}, drift: {total_um: [0.02, 0.01], register: true}}\n"};
    for (int k = 0; k < 3; k++) {
        char text[1024];
        snprintf(text, sizeof text, "%s%s", CUBE_HEAD, effects[k]);
        svp_scene *s = load("drift.yaml", text);
        svp_scene_result *r = run_nowrite(s);
        diff[k] = value(r, "cube_vs_closed_form/B_z/mean_abs_T");
        if (k == 2) {
            err = value(r, "cube/z/register_shift_error_px");
            ASSERT_CLOSE(value(r, "cube/z/register_max_shift_px"), hypot(0.2, 0.1), 0.01);
        }
        svp_scene_result_free(r);
        svp_scene_free(s);
    }
    print_message("cube centroid vs closed form: mean |diff| %.3g uT without drift, %.3g uT with "
                  "a 20 nm drift, %.3g uT drift registered (shifts within %.2g px)\n",
                  1e6 * diff[0], 1e6 * diff[1], 1e6 * diff[2], err);
    assert_true(err < 0.01);
    assert_true(diff[1] > 100 * diff[0]);
    assert_true(diff[2] < 0.02 * diff[1]);
}

/* correct: method cube deconvolves the cube's frames before the estimate (svp_cube_deconvolve):
 * on a Lorentzian-fit scene (the fit of a blurred pixel's mixed dips is not the PL-weighted
 * mean field T⁻¹ assumes) its B_z is closer to the truth than the apparent map and than T⁻¹
 * (R, 75 iterations) on the fitted maps. Measured median |error| of B_z over the view:
 * apparent 11 %, T⁻¹ 5.04 %, cube 3.54 %. A scene without the cube is refused. */
static void test_cube_correction(void **state)
{
    (void)state;
    svp_scene *s =
        load("cubefix.yaml", CUBE_HEAD
             "effects: {spectrum: {points: 60, estimator: lorentzian_fit}}\n"
             "correct:\n"
             "  - {method: r, iterations: 75, margin: auto, name: default}\n"
             "  - {method: cube, iterations: 75, margin: auto, name: cube}\n"
             "metrics: {masks: [{name: view}]}\n");
    svp_scene_result *r = run_nowrite(s);
    const double app = value(r, "B_z/view/apparent/median_abs_rel_err_pct");
    const double t = value(r, "B_z/view/corrected_default/median_abs_rel_err_pct");
    const double cube = value(r, "B_z/view/corrected_cube/median_abs_rel_err_pct");
    print_message("Lorentzian-fit scene, B_z median |error| over the view: apparent %.3g %%, "
                  "T^-1 %.3g %%, cube %.3g %%\n",
                  app, t, cube);
    assert_true(cube < app && cube < t);
    assert_true(value(r, "correct/cube/seconds") > 0);
    assert_true(test_all_finite(map(r, "B_z_corrected_cube")));
    svp_scene_result_free(r);
    svp_scene_free(s);
    /* the method needs the cube */
    svp_scene *bad = NULL;
    const char *text = CUBE_HEAD "correct: {method: cube}\n";
    assert_int_equal(svp_scene_load_string("nocube.yaml", text, strlen(text), &bad), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "method cube deconvolves the frames"));
}

/* The Lorentzian fit of a blurred cube whose contrast varies departs from the closed form
 * (which weights by the PL alone) where blurring mixes different contrasts. */
static void test_cube_fit_contrast(void **state)
{
    (void)state;
    svp_scene *s =
        load("fit.yaml", "grid: {pixel_um: 0.1, size_um: [3.2, 3.2]}\n"
                         "sources:\n"
                         "  - flake: {shape: rectangle, size_um: [1.6, 1.6],\n"
                         "            magnetisation_A_per_m: 1.0e4, thickness_nm: 1,\n"
                         "            standoff_nm: 100}\n"
                         "emission: [{gaussian: {fwhm_um: 3}}]\n"
                         "psf: {model: gaussian, fwhm_um: 0.3}\n"
                         "effects:\n"
                         "  spectrum:\n"
                         "    points: 40\n"
                         "    estimator: lorentzian_fit\n"
                         "    contrast_pattern: [{chessboard: {square_um: 1.2, levels: [0.3, 1], "
                         "offset_um: [0.3, 0.5], seed: 9}}]\n");
    svp_scene_result *r = run_nowrite(s);
    double mix = value(r, "cube_vs_closed_form/B_z/contrast_varies/mean_abs_T");
    double flat = value(r, "cube_vs_closed_form/B_z/contrast_uniform/mean_abs_T");
    double frac = value(r, "cube_vs_closed_form/contrast_varies_fraction");
    assert_true(frac > 0 && frac < 1);
    print_message("Lorentzian fit vs closed form: mean |diff| %.3g uT where the contrast varies "
                  "(mixing > 10 %%, %.0f %% of the view), %.3g uT where it is uniform (< 2 %%)\n",
                  1e6 * mix, 100 * frac, 1e6 * flat);
    assert_true(test_all_finite(map(r, "B_z_apparent")));
    if (!(mix > 2 * flat)) fail_msg("no excess difference where the contrast varies");
    svp_scene_result_free(r);
    svp_scene_free(s);
}

/* ---- figures ------------------------------------------------------------------------------ */

/* RGB of figure pixel (x, y) */
static void png_rgb(cairo_surface_t *png, int x, int y, int rgb[3])
{
    const unsigned char *d = cairo_image_surface_get_data(png);
    uint32_t v =
        *(const uint32_t *)(const void *)(d + (size_t)y * cairo_image_surface_get_stride(png) +
                                          4 * (size_t)x);
    rgb[0] = (int)(v >> 16 & 255), rgb[1] = (int)(v >> 8 & 255), rgb[2] = (int)(v & 255);
}

/* A signed map drawn by the scene figures: the diverging colour map is white at zero, red for
 * positive and blue for negative values, and the colour bar beside the map runs from red (top,
 * the maximum) through white to blue (bottom). Layout of svp_figure_map: the map scaled to
 * 560 px on its long side at (20, 48), the colour bar 16 px to its right, 18 px wide. */
static void test_figure_diverging(void **state)
{
    (void)state;
    const int w = 64, h = 32;
    svp_image *img = test_image(w, h);
    for (int j = 0; j < h; j++)
        for (int i = 0; i < w; i++) img->data[(size_t)j * w + i] = (i - 31.5) / 31.5;
    char dir[] = "/tmp/svpsf_fig_XXXXXX", path[64];
    assert_non_null(mkdtemp(dir));
    snprintf(path, sizeof path, "%s/map.png", dir);
    ASSERT_OK(svp_figure_map(path, img, 1, -1, 1, 1, "a signed map", "B_z (uT)", 0.1, 0));
    cairo_surface_t *png = cairo_image_surface_create_from_png(path);
    assert_int_equal(cairo_surface_status(png), CAIRO_STATUS_SUCCESS);
    cairo_surface_flush(png);
    const int fw = cairo_image_surface_get_width(png), fh = cairo_image_surface_get_height(png);
    /* the map (560 x 280) plus the colour bar and its labels */
    assert_true(fw > 20 + 560 + 16 + 18 && fh > 48 + 280);
    int c[3], l[3], r[3], top[3], mid[3], bot[3];
    png_rgb(png, 20 + 280, 48 + 140, c);
    png_rgb(png, 20 + 4, 48 + 140, l);
    png_rgb(png, 20 + 556, 48 + 140, r);
    const int bx = 20 + 560 + 16 + 9;
    png_rgb(png, bx, 48 + 3, top);
    png_rgb(png, bx, 48 + 140, mid);
    png_rgb(png, bx, 48 + 277, bot);
    print_message("map: zero (%d %d %d), -1 (%d %d %d), +1 (%d %d %d); bar: top (%d %d %d), "
                  "middle (%d %d %d), bottom (%d %d %d)\n",
                  c[0], c[1], c[2], l[0], l[1], l[2], r[0], r[1], r[2], top[0], top[1], top[2],
                  mid[0], mid[1], mid[2], bot[0], bot[1], bot[2]);
    assert_true(c[0] > 220 && c[1] > 220 && c[2] > 220);       /* zero: white */
    assert_true(l[2] > l[0] + 50 && r[0] > r[2] + 50);         /* blue < 0 < red */
    assert_true(mid[0] > 220 && mid[1] > 220 && mid[2] > 220); /* the bar centred on zero */
    assert_true(top[0] > top[2] + 50 && bot[2] > bot[0] + 50);
    cairo_surface_destroy(png);
    unlink(path);
    rmdir(dir);
    svp_image_free(img);
}

/* ---- outputs ------------------------------------------------------------------------------- */

static void test_outputs_written(void **state)
{
    (void)state;
    char dir[] = "/tmp/svpsf_scene_XXXXXX";
    assert_non_null(mkdtemp(dir));
    svp_scene *s = load("out.yaml", FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                                                     "correct: {method: w, balance: 0.01}\n"
                                                     "reconstruct: magnetisation\n");
    svp_scene_options o;
    svp_scene_defaults(&o);
    o.keep_maps = 0;
    ASSERT_OK(svp_scene_run(s, dir, &o, NULL));
    int n = svp_scene_n_outputs(s);
    assert_true(n > 20);
    for (int i = 0; i < n; i++) {
        char path[512];
        snprintf(path, sizeof path, "%s/%s", dir, svp_scene_output(s, i));
        struct stat st;
        if (stat(path, &st) != 0 || st.st_size == 0) fail_msg("output %s missing or empty", path);
    }
    /* a second run refuses before any work, and names the file */
    svp_status st = svp_scene_run(s, dir, &o, NULL);
    assert_int_equal(st, SVP_ERR_EXISTS);
    assert_non_null(strstr(svp_last_error(), "--force"));
    o.overwrite = 1;
    ASSERT_OK(svp_scene_run(s, dir, &o, NULL));
    for (int i = 0; i < n; i++) {
        char path[512];
        snprintf(path, sizeof path, "%s/%s", dir, svp_scene_output(s, i));
        unlink(path);
    }
    const char *sub[] = {"maps", "figures", "tables"};
    for (int i = 0; i < 3; i++) {
        char path[512];
        snprintf(path, sizeof path, "%s/%s", dir, sub[i]);
        rmdir(path);
    }
    rmdir(dir);
    svp_scene_free(s);
}

/* cancels the run as its last stage begins, counting the outputs already written then */
typedef struct {
    const svp_scene *s;
    const char *dir;
    int written_before_cancel;
} cancel_late;

static int cancel_at_last_stage(void *user, int index, int n_stages, const svp_scene_stage *stage)
{
    (void)stage;
    cancel_late *c = user;
    if (index < n_stages - 1) return 0;
    for (int i = 0; i < svp_scene_n_outputs(c->s); i++) {
        char path[512];
        struct stat st;
        snprintf(path, sizeof path, "%s/%s", c->dir, svp_scene_output(c->s, i));
        c->written_before_cancel += stat(path, &st) == 0;
    }
    return 1;
}

/* a run that fails after writing some outputs removes them (all or none); a file that was there
 * before the run stays */
static void test_failed_run_leaves_nothing(void **state)
{
    (void)state;
    char dir[] = "/tmp/svpsf_scene_XXXXXX";
    assert_non_null(mkdtemp(dir));
    svp_scene *s = load("late.yaml", FLAKE_SCENE_HEAD "psf: {model: gaussian, fwhm_um: 0.3}\n"
                                                      "correct: {method: w, balance: 0.01}\n");
    const svp_scene_stage *stages = NULL;
    int n_stages = svp_scene_plan(s, &stages);
    assert_string_equal(stages[n_stages - 1].name, "write"); /* after the figures */
    char keep[600];
    snprintf(keep, sizeof keep, "%s/mine.txt", dir);
    FILE *f = fopen(keep, "w");
    assert_non_null(f);
    fputs("the user's file\n", f);
    fclose(f);
    cancel_late c = {s, dir, 0};
    svp_scene_options o;
    svp_scene_defaults(&o);
    o.on_stage = cancel_at_last_stage;
    o.stage_user = &c;
    assert_int_equal(svp_scene_run(s, dir, &o, NULL), SVP_ERR_CANCELLED);
    assert_true(c.written_before_cancel > 3); /* the figures were written */
    for (int i = 0; i < svp_scene_n_outputs(s); i++) {
        char path[512];
        struct stat st;
        snprintf(path, sizeof path, "%s/%s", dir, svp_scene_output(s, i));
        if (stat(path, &st) == 0) fail_msg("%s was left behind by a failed run", path);
    }
    struct stat st;
    assert_int_equal(stat(keep, &st), 0);
    unlink(keep);
    const char *sub[] = {"maps", "figures", "tables"};
    for (int i = 0; i < 3; i++) {
        char path[512];
        snprintf(path, sizeof path, "%s/%s", dir, sub[i]);
        rmdir(path);
    }
    assert_int_equal(rmdir(dir), 0); /* empty: nothing else was left */
    svp_scene_free(s);
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    svp_set_threads(2);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_plan_closed_form),
        cmocka_unit_test(test_plan_spectrum),
        cmocka_unit_test(test_bad_scenes),
        cmocka_unit_test(test_end_to_end_matches_transforms),
        cmocka_unit_test(test_correct_margin),
        cmocka_unit_test(test_correct_margin_regions),
        cmocka_unit_test(test_strip_reconstruction),
        cmocka_unit_test(test_strip_without_current),
        cmocka_unit_test(test_failed_fits_are_missing),
        cmocka_unit_test(test_noise),
        cmocka_unit_test(test_determinism),
        cmocka_unit_test(test_cube_centroid_is_closed_form),
        cmocka_unit_test(test_cube_fit_contrast),
        cmocka_unit_test(test_cube_drift_register),
        cmocka_unit_test(test_cube_correction),
        cmocka_unit_test(test_figure_diverging),
        cmocka_unit_test(test_outputs_written),
        cmocka_unit_test(test_failed_run_leaves_nothing),
    };
    int rc = cmocka_run_group_tests_name("scene", tests, NULL, NULL);
    svp_figure_cleanup();
    svp_fft_cleanup();
    return rc;
}
