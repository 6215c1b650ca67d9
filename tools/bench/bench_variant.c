/* Benchmark of the space-variant operator (docs/model.md §9): what accuracy costs in time. One JSON
 * object per line on stdout.
 *
 *   bench_variant apply --size N --variation mild|strong [--exact 0|1] [--reps R]
 *                       [--support S] [--budget-mb M]
 *       For tent grids 1², 2², 4², 8², 16² and low ranks 1..12 (16 x 16 PSF samples): build
 *       time, best-of-R time of one application, the same run's best-of-R time of (K + 1)
 *       real FFTs of the operator's padded frame (K forward, 1 inverse, the cached plans the
 *       operator uses), their ratio, the best-of-R time of one adjoint application (Hᵀ of the
 *       same image) and its ratio to the same bound (one forward + K inverse FFTs), memory of the K spectra and of the whole operator, and
 *       with --exact 1 the relative L2 error against the exact per-source operator
 *       (svp_blur_new_exact) on a random image (uniform in [0, 1)). Configurations whose
 *       spectra exceed --budget-mb (default 6000) are reported as skipped.
 *   bench_variant inverse --size N --variation mild|strong [--iterations a,b,c]
 *       T⁻¹ end to end: a true PL (fringes and a dark quenched stripe) and field, T computed
 *       with the exact operator, then T⁻¹ (method R: RL on PL and on the shifted numerator)
 *       with each representation (and a single central PSF) for each iteration count. Reports
 *       time and the max / rms error of the corrected field over lit pixels relative to the
 *       field's peak.
 *   bench_variant ops --map MAP.yaml [--reprs auto:1e-3,t8,r4x8,...] [--reps R] [--probes P]
 *                     [--rl-reps R] [--ref-x X.npy --ref-y Y.npy]
 *       The operators of a PSF-map file (square, its own size, zero boundary): first the
 *       invariant operator of the centre PSF, then per representation (auto:TOL = chosen by
 *       the error budget TOL, tN = tent N x N, rR or rRxS = low rank R on S x S samples,
 *       regions = one kernel per region of a region map) what
 *       was built, its build time, best-of-R application / adjoint times and (K + 1) FFTs of
 *       its frame (as apply), memory, the estimated operator error and the error measured
 *       against the exact per-source operator at P probe sources (one application each, the
 *       exact column rendered over the operator's whole support; --probes 0: none), with
 *       --ref-x X.npy --ref-y Y.npy the relative error of H X against Y (a reference's blur
 *       of X), and the time of one Richardson-Lucy iteration (best of R runs of 6 iterations
 *       minus best of R runs of 2, over 4; R = --rl-reps, default --reps, 0: not timed) beside
 *       its bound, 2 (K + 1) real FFTs of the frame.
 *   bench_variant cost --size N [--reps R] [--what tent,lowrank,regions] [--samples 8,16]
 *       The cost model's calibration (src/blur/choose.c, cost_of) in CPU time of this process
 *       (CLOCK_PROCESS_CPUTIME_ID, 1 thread, FFTW plans made by an untimed first build): per
 *       representation of a whole-field map at N² (zero boundary) the build and one H + Hᵀ
 *       pair (best of R), each also in units of one real FFT of the operator's frame (the
 *       best of R forward + inverse pairs on the same plan, / 2, timed between them), beside
 *       the chooser's model of both (svp_variant_cost). Maps: the smooth circular Moffat map of
 *       tools/bench/variant_data.py (FWHM 8 ± 2.5 px, β 1.6 ∓ 0.4: octant fold) for tent
 *       1², 2², 4² and low rank 3 / 8 on 8² / 16² samples built with the octant fold and with
 *       the point symmetry only (build 2); two-region maps (metal strip 10.5 px β 1.25, oxide
 *       7 px β 1.9; sharp and blended over 10 px) for the region operator.
 *   bench_variant params --map MAP.yaml --out STEM
 *       The map's FWHM (px) and beta at every pixel: STEM.fwhm.npy, STEM.beta.npy.
 *   bench_variant plot OUT.png [=TITLE] @LABEL t e t e ... [@LABEL t e ...]
 *       Error versus time per application, log-log (log10 of both on linear axes), one curve
 *       per @LABEL (up to 10), drawn with the library's own cairo line plot.
 * Fields (support S px, default 16; kernels normalised over it): FWHM and beta linear in the
 * normalised position u, v in [-1, 1]:
 *   strong: FWHM 3 → 6 px along x (2×), beta 3 → 1.1 along y;
 *   mild:   FWHM 4.3 → 4.7 px along x (1.1×), beta 2.6 → 2.4 along y.
 */
#include "bench_common.h"
#include "svpsf.h"

#include "blur/blur_internal.h"
#include "figure/figure.h"
#include "psf/field_internal.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *arg_str(int argc, char **argv, const char *name, const char *def)
{
    for (int i = 2; i + 1 < argc; i++)
        if (!strcmp(argv[i], name)) return argv[i + 1];
    return def;
}

static double arg_num(int argc, char **argv, const char *name, double def)
{
    const char *s = arg_str(argc, argv, name, NULL);
    return s ? atof(s) : def;
}

/* A JSON number, null for NaN / Inf (one of eight rotating buffers). */
static const char *jnum(double v)
{
    static char buf[8][32];
    static int k;
    k = (k + 1) & 7;
    if (isfinite(v))
        snprintf(buf[k], sizeof buf[k], "%.6g", v);
    else
        snprintf(buf[k], sizeof buf[k], "null");
    return buf[k];
}

static int fail(const char *what)
{
    printf("{\"error\": \"failed\", \"message\": \"%s: %s\"}\n", what, svp_last_error());
    return 2;
}

static svp_psf_field *make_field(int n, int strong, double support)
{
    svp_psf base;
    svp_psf_defaults(&base);
    base.model = SVP_PSF_MOFFAT;
    base.support = support;
    const int nt = svp_psf_field_poly_terms(1); /* 1, u, v */
    double c[SVP_FIELD_NPARAM * 3] = {0};
    c[SVP_FIELD_FWHM * nt + 0] = strong ? 4.5 : 4.5;
    c[SVP_FIELD_FWHM * nt + 1] = strong ? 1.5 : 0.2;
    c[SVP_FIELD_BETA * nt + 0] = strong ? 2.05 : 2.5;
    c[SVP_FIELD_BETA * nt + 2] = strong ? -0.95 : -0.1;
    svp_psf_field *f = NULL;
    if (svp_psf_field_new_poly(&base, n, n, 1, c, &f) != SVP_OK) return NULL;
    return f;
}

static double rel_l2(const svp_image *a, const svp_image *ref)
{
    double num = 0, den = 0;
    for (size_t i = 0; i < (size_t)a->width * a->height; i++) {
        double d = a->data[i] - ref->data[i];
        num += d * d;
        den += ref->data[i] * ref->data[i];
    }
    return sqrt(num / den);
}

static svp_image *random_image(int n, uint64_t seed)
{
    svp_image *x = NULL;
    if (svp_image_new(n, n, &x) != SVP_OK) return NULL;
    uint64_t s = seed * 0x9E3779B97F4A7C15ULL + 1;
    for (size_t i = 0; i < (size_t)n * n; i++) {
        s ^= s >> 12;
        s ^= s << 25;
        s ^= s >> 27;
        x->data[i] = (double)((s * 0x2545F4914F6CDD1DULL) >> 11) * (1.0 / 9007199254740992.0);
    }
    return x;
}

/* Timings of one operator against its bound, interleaved: each repetition times one
 * application H x, one adjoint Hᵀ x and then K forward + 1 inverse real FFTs of the
 * operator's frame (the cached plans the operator uses, buffers of its work buffers' sizes),
 * after one untimed warm-up round, so a change of machine load hits all three alike. Best =
 * the fastest repetition; the ratios' medians are the medians of the per-repetition ratios. */
typedef struct timing {
    double apply, apply_med, adjoint, adjoint_med, ffts, ffts_med, ratio_med, adjoint_ratio_med;
} timing;

static int time_interleaved(svp_blur *b, int K, const svp_image *in, svp_image *out,
                            svp_image *back, int reps, timing *tm)
{
    if (svp_blur_ready(b) != SVP_OK) return 0; /* an invariant frame is made on first use */
    const svp_frame *f = &b->frame;
    const size_t nr = (size_t)f->ny * f->nx, nc = (size_t)f->ny * f->ncx;
    double *r = svp_alloc(nr * sizeof(double));
    fftw_complex *c = svp_alloc(nc * sizeof(fftw_complex));
    double ta[64], tj[64], tf[64], ra[64], rj[64];
    if (reps > 64) reps = 64;
    int ok = r && c;
    for (int rep = -1; ok && rep < reps; rep++) {               /* rep −1: warm-up */
        for (size_t i = 0; i < nr; i++) r[i] = (double)(i % 7); /* keep the data finite */
        double t0 = bench_now();
        ok = svp_blur_apply(b, in, out) == SVP_OK;
        const double t1 = bench_now();
        ok = ok && svp_blur_adjoint(b, in, back) == SVP_OK;
        const double t2 = bench_now();
        for (int k = 0; k < K; k++) svp_fft_forward(f->plan, r, c);
        svp_fft_inverse_unscaled(f->plan, c, r);
        const double t3 = bench_now();
        if (rep < 0) continue;
        ta[rep] = t1 - t0;
        tj[rep] = t2 - t1;
        tf[rep] = t3 - t2;
        ra[rep] = ta[rep] / tf[rep];
        rj[rep] = tj[rep] / tf[rep];
    }
    svp_free(r);
    svp_free(c);
    if (!ok) return 0;
    tm->ratio_med = bench_median(ra, reps);
    tm->adjoint_ratio_med = bench_median(rj, reps);
    tm->apply_med = bench_median(ta, reps); /* sorts: [0] is then the best */
    tm->apply = ta[0];
    tm->adjoint_med = bench_median(tj, reps);
    tm->adjoint = tj[0];
    tm->ffts_med = bench_median(tf, reps);
    tm->ffts = tf[0];
    return 1;
}

static int cmd_apply(int argc, char **argv)
{
    const int n = (int)arg_num(argc, argv, "--size", 256);
    const int strong = strcmp(arg_str(argc, argv, "--variation", "strong"), "mild") != 0;
    const int exact = (int)arg_num(argc, argv, "--exact", n <= 256);
    const int reps = (int)arg_num(argc, argv, "--reps", 3);
    const double support = arg_num(argc, argv, "--support", 16);
    const double budget = arg_num(argc, argv, "--budget-mb", 6000);
    const char *only = arg_str(argc, argv, "--only", NULL);
    svp_psf_field *f = make_field(n, strong, support);
    if (!f) return fail("field");
    svp_image *x = random_image(n, 1), *y = NULL, *ye = NULL, *xa = NULL;
    if (!x || svp_image_new(n, n, &y) != SVP_OK || svp_image_new(n, n, &ye) != SVP_OK ||
        svp_image_new(n, n, &xa) != SVP_OK)
        return fail("images");
    double t_exact = NAN;
    if (exact) {
        svp_blur *ex = NULL;
        if (svp_blur_new_exact(f, n, n, SVP_BOUNDARY_MIRROR, 0, &ex) != SVP_OK)
            return fail("exact operator");
        double t0 = bench_now();
        if (svp_blur_apply(ex, x, ye) != SVP_OK) return fail("exact apply");
        t_exact = bench_now() - t0;
        svp_blur_free(ex);
    }
    const char *var = strong ? "strong" : "mild";
    printf("{\"kind\": \"exact\", \"size\": %d, \"variation\": \"%s\", \"support_px\": %g, "
           "\"time_s\": %s}\n",
           n, var, support, jnum(t_exact));
    fflush(stdout);
    if (!only || strstr("invariant", only)) {
        /* the floor: the space-invariant operator of the central PSF (extend, 1 forward FFT,
         * product, 1 inverse, crop) against its 2 FFTs */
        svp_psf pc;
        svp_blur *b = NULL;
        if (svp_psf_field_at(f, 0.5 * (n - 1), 0.5 * (n - 1), &pc) != SVP_OK ||
            svp_blur_new(&pc, n, n, SVP_BOUNDARY_MIRROR, &b) != SVP_OK)
            return fail("invariant operator");
        timing tm;
        if (!time_interleaved(b, 1, x, y, xa, reps, &tm)) return fail("invariant operator");
        printf("{\"kind\": \"invariant\", \"label\": \"invariant (central PSF)\", \"K\": 1, "
               "\"size\": %d, \"variation\": \"%s\", \"frame\": [%d, %d], \"apply_s\": %.6g, "
               "\"ffts_s\": %.6g, \"ratio\": %.4g, \"apply_median_s\": %.6g, "
               "\"ffts_median_s\": %.6g, \"ratio_median\": %.4g, \"adjoint_s\": %.6g, "
               "\"adjoint_ratio\": %.4g, \"adjoint_median_s\": %.6g, "
               "\"adjoint_ratio_median\": %.4g, \"threads\": %d}\n",
               n, var, b->frame.nx, b->frame.ny, tm.apply, tm.ffts, tm.apply / tm.ffts,
               tm.apply_med, tm.ffts_med, tm.ratio_med, tm.adjoint, tm.adjoint / tm.ffts,
               tm.adjoint_med, tm.adjoint_ratio_med, svp_get_threads());
        fflush(stdout);
        svp_blur_free(b);
    }
    enum { NG = 5, NR = 12 };
    const int grids[NG] = {1, 2, 4, 8, 16};
    for (int c = 0; c < NG + NR; c++) {
        const int tent = c < NG;
        svp_variant_options o;
        svp_variant_defaults(&o);
        int K;
        if (tent) {
            o.grid_x = o.grid_y = grids[c];
            K = grids[c] * grids[c];
        } else {
            o.representation = SVP_VARIANT_LOWRANK;
            o.samples_x = o.samples_y = 16;
            o.rank = c - NG + 1;
            K = o.rank;
        }
        /* spectra of the padded frame: (n + 2 r) x (n + 2 r) for mirror with support r */
        const int side = n + 2 * (int)ceil(support);
        const double spec_mb = (double)K * side * (side / 2 + 1) * 16.0 / 1048576.0;
        char label[32];
        snprintf(label, sizeof label, tent ? "tent %dx%d" : "low rank %d", tent ? grids[c] : o.rank,
                 tent ? grids[c] : 0);
        if (only && !strstr(label, only)) continue;
        if (spec_mb > budget) {
            printf("{\"kind\": \"%s\", \"label\": \"%s\", \"K\": %d, \"size\": %d, "
                   "\"variation\": \"%s\", \"skipped\": \"the %d spectra need %.0f MB > budget "
                   "%.0f MB\", \"spectra_mb\": %.1f}\n",
                   tent ? "tent" : "lowrank", label, K, n, var, K, spec_mb, budget, spec_mb);
            fflush(stdout);
            continue;
        }
        svp_blur *b = NULL;
        double t0 = bench_now();
        if (svp_blur_new_field(f, n, n, SVP_BOUNDARY_MIRROR, &o, &b) != SVP_OK) return fail(label);
        const double t_build = bench_now() - t0;
        timing tm;
        if (!time_interleaved(b, K, x, y, xa, reps, &tm)) return fail(label);
        const double err = exact ? rel_l2(y, ye) : NAN;
        const svp_frame *fr = &b->frame;
        const int real = svp_variant_real_spectra(b); /* real parts only: 8 bytes a value */
        const double spectra = (double)K * fr->ny * fr->ncx *
                               (real ? sizeof(double) : sizeof(fftw_complex)) / 1048576.0;
        printf("{\"kind\": \"%s\", \"label\": \"%s\", \"K\": %d, \"size\": %d, \"variation\": "
               "\"%s\", \"frame\": [%d, %d], \"build_s\": %.6g, \"apply_s\": %.6g, "
               "\"ffts_s\": %.6g, \"ratio\": %.4g, \"apply_median_s\": %.6g, "
               "\"ffts_median_s\": %.6g, \"ratio_median\": %.4g, \"adjoint_s\": %.6g, "
               "\"adjoint_ratio\": %.4g, \"adjoint_median_s\": %.6g, "
               "\"adjoint_ratio_median\": %.4g, \"rel_err\": %s, \"spectra_mb\": %.2f, "
               "\"real_spectra\": %d, \"operator_mb\": %.2f, \"peak_rss_mb\": %.1f, "
               "\"threads\": %d}\n",
               tent ? "tent" : "lowrank", label, K, n, var, fr->nx, fr->ny, t_build, tm.apply,
               tm.ffts, tm.apply / tm.ffts, tm.apply_med, tm.ffts_med, tm.ratio_med, tm.adjoint,
               tm.adjoint / tm.ffts, tm.adjoint_med, tm.adjoint_ratio_med, jnum(err), spectra, real,
               svp_blur_memory(b) / 1048576.0, bench_maxrss_mb(), svp_get_threads());
        fflush(stdout);
        svp_blur_free(b);
    }
    svp_image_free(x);
    svp_image_free(y);
    svp_image_free(ye);
    svp_image_free(xa);
    svp_psf_field_free(f);
    return 0;
}

/* True PL: fringes along x and a quenched stripe (15 %) down the middle; true field: a smooth
 * signed pattern. */
static void scene(int n, svp_image *pl, svp_image *b)
{
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            double u = (double)x / n, v = (double)y / n;
            double metal = 0.5 * (tanh((x - 0.42 * n) / 1.5) - tanh((x - 0.58 * n) / 1.5));
            pl->data[(size_t)y * n + x] =
                (0.6 + 0.4 * cos(2 * M_PI * 3 * u)) * (1 - 0.85 * metal) * (0.8 + 0.2 * v);
            b->data[(size_t)y * n + x] = 0.3 + sin(2 * M_PI * u) * cos(2 * M_PI * 0.7 * v) +
                                         0.5 * exp(-((u - 0.5) * (u - 0.5)) / 0.005);
        }
}

static int cmd_inverse(int argc, char **argv)
{
    const int n = (int)arg_num(argc, argv, "--size", 256);
    const int strong = strcmp(arg_str(argc, argv, "--variation", "strong"), "mild") != 0;
    const double support = arg_num(argc, argv, "--support", 16);
    const char *its_s = arg_str(argc, argv, "--iterations", "10,30,100");
    const char *reps_s = arg_str(argc, argv, "--reprs", "single,t1,t2,t4,t8,t16,r2,r4,r8,r12");
    const int max_k_its = (int)arg_num(argc, argv, "--max-k-iterations", 3000);
    svp_psf_field *f = make_field(n, strong, support);
    if (!f) return fail("field");
    svp_image *pl = NULL, *b = NULL, *pla = NULL, *ba = NULL, *plr = NULL, *br = NULL;
    svp_image *val = NULL;
    if (svp_image_new(n, n, &pl) || svp_image_new(n, n, &b) || svp_image_new(n, n, &pla) ||
        svp_image_new(n, n, &ba) || svp_image_new(n, n, &plr) || svp_image_new(n, n, &br) ||
        svp_image_new(n, n, &val))
        return fail("images");
    scene(n, pl, b);
    svp_blur *ex = NULL;
    if (svp_blur_new_exact(f, n, n, SVP_BOUNDARY_MIRROR, 0, &ex) != SVP_OK) return fail("exact");
    const svp_image *fin[1] = {b};
    svp_image *fout[1] = {ba};
    if (svp_forward_transform(ex, pl, fin, 1, pla, fout, NULL) != SVP_OK) return fail("T");
    svp_blur_free(ex);
    double bmax = 0, plmax = 0;
    for (size_t i = 0; i < (size_t)n * n; i++) {
        bmax = fmax(bmax, fabs(b->data[i]));
        plmax = fmax(plmax, pl->data[i]);
    }
    /* the apparent error, for reference */
    double emax = 0, esq = 0;
    size_t nlit = 0;
    for (size_t i = 0; i < (size_t)n * n; i++)
        if (pl->data[i] >= 0.5 * plmax) {
            double d = fabs(ba->data[i] - b->data[i]);
            emax = fmax(emax, d);
            esq += d * d;
            nlit++;
        }
    const char *var = strong ? "strong" : "mild";
    printf("{\"kind\": \"apparent\", \"size\": %d, \"variation\": \"%s\", \"max_err\": %.6g, "
           "\"rms_err\": %.6g, \"lit_pixels\": %zu}\n",
           n, var, emax / bmax, sqrt(esq / nlit) / bmax, nlit);
    fflush(stdout);
    char reps[256];
    snprintf(reps, sizeof reps, "%s", reps_s);
    for (char *tok = strtok(reps, ","); tok; tok = strtok(NULL, ",")) {
        svp_blur *op = NULL;
        int K = 1;
        double t0 = bench_now();
        svp_status st;
        if (!strcmp(tok, "single")) {
            svp_psf c;
            if (svp_psf_field_at(f, 0.5 * (n - 1), 0.5 * (n - 1), &c) != SVP_OK) return fail(tok);
            st = svp_blur_new(&c, n, n, SVP_BOUNDARY_MIRROR, &op);
        } else {
            svp_variant_options o;
            svp_variant_defaults(&o);
            if (tok[0] == 't') {
                o.grid_x = o.grid_y = atoi(tok + 1);
                K = o.grid_x * o.grid_y;
            } else {
                o.representation = SVP_VARIANT_LOWRANK;
                o.samples_x = o.samples_y = 16;
                o.rank = K = atoi(tok + 1);
            }
            st = svp_blur_new_field(f, n, n, SVP_BOUNDARY_MIRROR, &o, &op);
        }
        if (st != SVP_OK) return fail(tok);
        const double t_build = bench_now() - t0;
        char its[128];
        snprintf(its, sizeof its, "%s", its_s);
        char *save = NULL;
        for (char *it = strtok_r(its, ",", &save); it; it = strtok_r(NULL, ",", &save)) {
            const int iterations = atoi(it);
            if ((long)K * iterations > max_k_its) {
                printf("{\"kind\": \"inverse\", \"repr\": \"%s\", \"K\": %d, \"iterations\": %d, "
                       "\"skipped\": \"K x iterations > %d\"}\n",
                       tok, K, iterations, max_k_its);
                continue;
            }
            svp_correct_options co;
            svp_correct_defaults(&co);
            co.method = SVP_METHOD_R;
            co.deconv.iterations = iterations;
            const svp_image *ain[1] = {ba};
            svp_image *aout[1] = {br};
            t0 = bench_now();
            if (svp_inverse_transform(op, pla, ain, 1, &co, plr, aout, val, NULL) != SVP_OK)
                return fail("T^-1");
            const double t = bench_now() - t0;
            emax = 0;
            esq = 0;
            for (size_t i = 0; i < (size_t)n * n; i++)
                if (pl->data[i] >= 0.5 * plmax) {
                    double d = fabs(br->data[i] - b->data[i]);
                    emax = fmax(emax, d);
                    esq += d * d;
                }
            printf("{\"kind\": \"inverse\", \"repr\": \"%s\", \"K\": %d, \"size\": %d, "
                   "\"variation\": \"%s\", \"iterations\": %d, \"build_s\": %.6g, \"time_s\": "
                   "%.6g, \"max_err\": %.6g, \"rms_err\": %.6g, \"peak_rss_mb\": %.1f}\n",
                   tok, K, n, var, iterations, t_build, t, emax / bmax, sqrt(esq / nlit) / bmax,
                   bench_maxrss_mb());
            fflush(stdout);
        }
        svp_blur_free(op);
    }
    svp_image_free(pl);
    svp_image_free(b);
    svp_image_free(pla);
    svp_image_free(ba);
    svp_image_free(plr);
    svp_image_free(br);
    svp_image_free(val);
    svp_psf_field_free(f);
    return 0;
}

/* Relative operator error of b against the exact per-source operator of field f, sampled at
 * `probes` sources (a jittered grid, none of the chooser's probe lattice): for each, H e_s
 * against the exact column, the kernel of the PSF at s over every offset the operator's
 * support reaches (radius rx, ry: the whole view for support 0), normalised there and cropped
 * by the zero boundary: sqrt(Σ ‖H e_s − k_s‖² / Σ ‖k_s‖²). */
static double probe_error(svp_blur *b, const svp_psf_field *f, int n, double support, int probes,
                          double *seconds)
{
    const double t0 = bench_now();
    const int r = support > 0 && ceil(support) < n - 1 ? (int)ceil(support) : n - 1;
    svp_image *x = NULL, *y = NULL;
    if (svp_image_new(n, n, &x) != SVP_OK || svp_image_new(n, n, &y) != SVP_OK) return NAN;
    int side = 1;
    while (side * side < probes) side++;
    double e2 = 0, n2 = 0;
    for (int p = 0; p < probes; p++) {
        /* cell (p % side, p / side) of a side x side grid, jittered inside it */
        const double jx = fmod(0.31 + 0.7548776662466927 * (p + 1), 1.0);
        const double jy = fmod(0.47 + 0.5698402909980532 * (p + 1), 1.0);
        const int sx = (int)(((p % side) + 0.15 + 0.7 * jx) * n / side);
        const int sy = (int)(((p / side) + 0.15 + 0.7 * jy) * n / side);
        memset(x->data, 0, (size_t)n * n * sizeof(double));
        x->data[(size_t)sy * n + sx] = 1;
        svp_psf ps;
        svp_image *k = NULL;
        if (svp_blur_apply(b, x, y) != SVP_OK || svp_psf_field_at(f, sx, sy, &ps) != SVP_OK)
            return NAN;
        ps.support = support;
        if (svp_psf_render(&ps, r, r, &k) != SVP_OK) return NAN;
        const int kw = 2 * r + 1;
        for (int Y = 0; Y < n; Y++) {
            const int dy = Y - sy;
            for (int X = 0; X < n; X++) {
                const int dx = X - sx;
                const double ke = abs(dx) <= r && abs(dy) <= r
                                      ? k->data[(size_t)(dy + r) * kw + (dx + r)]
                                      : 0.0;
                const double d = y->data[(size_t)Y * n + X] - ke;
                e2 += d * d;
                n2 += ke * ke;
            }
        }
        svp_image_free(k);
    }
    svp_image_free(x);
    svp_image_free(y);
    *seconds = bench_now() - t0;
    return sqrt(e2 / n2);
}

/* Seconds of one Richardson-Lucy iteration on b: (best of `reps` runs of 6 iterations − best
 * of `reps` runs of 2) / 4, the runs interleaved after an untimed one of each; *bound = the
 * best time of 2 (K + 1) real FFTs of b's frame (H and Hᵀ), taken between them. */
static double rl_iteration(svp_blur *b, int K, const svp_image *y, svp_image *x, int reps,
                           double *bound)
{
    if (svp_blur_ready(b) != SVP_OK) return NAN; /* an invariant frame is made on first use */
    const svp_frame *f = &b->frame;
    double *r = svp_alloc((size_t)f->ny * f->nx * sizeof(double));
    fftw_complex *c = svp_alloc((size_t)f->ny * f->ncx * sizeof(fftw_complex));
    double best[2] = {INFINITY, INFINITY}, bbest = INFINITY;
    int ok = r && c;
    for (int rep = -1; ok && rep < reps; rep++) {
        for (int k = 0; k < 2 && ok; k++) {
            svp_deconv_options o;
            svp_deconv_defaults(&o);
            o.iterations = k ? 6 : 2;
            const double t0 = bench_now();
            ok = svp_deconv_rl(b, y, &o, x) == SVP_OK;
            if (rep >= 0) best[k] = fmin(best[k], bench_now() - t0);
        }
        for (size_t i = 0; i < (size_t)f->ny * f->nx; i++) r[i] = (double)(i % 7);
        const double t0 = bench_now();
        for (int k = 0; k < 2 * K + 1; k++) svp_fft_forward(f->plan, r, c);
        svp_fft_inverse_unscaled(f->plan, c, r);
        if (rep >= 0) bbest = fmin(bbest, bench_now() - t0);
    }
    svp_free(r);
    svp_free(c);
    *bound = bbest;
    return ok ? (best[1] - best[0]) / 4 : NAN;
}

/* ‖H x − y_ref‖ / ‖y_ref‖ for the images in files x_path, y_path (NaN when absent). */
static double ref_error(svp_blur *b, const char *x_path, const char *y_path)
{
    if (!x_path || !y_path) return NAN;
    svp_image *x = NULL, *yr = NULL, *y = NULL;
    double e = NAN;
    if (svp_image_read(x_path, &x) == SVP_OK && svp_image_read(y_path, &yr) == SVP_OK &&
        svp_image_new(x->width, x->height, &y) == SVP_OK && svp_blur_apply(b, x, y) == SVP_OK)
        e = rel_l2(y, yr);
    svp_image_free(x);
    svp_image_free(yr);
    svp_image_free(y);
    return e;
}

/* One representation of `ops`: "auto:TOL", "tN" (tent N x N), "rR" / "rRxS" (low rank R on
 * S x S samples, default 8) or "regions" (one kernel per region of a region map). */
static int parse_repr(const char *tok, svp_variant_options *o, char *label, size_t size)
{
    svp_variant_defaults(o);
    if (!strcmp(tok, "regions")) {
        o->representation = SVP_VARIANT_REGIONS;
        snprintf(label, size, "regions");
    } else if (!strncmp(tok, "auto:", 5)) {
        o->representation = SVP_VARIANT_AUTO;
        o->tolerance = atof(tok + 5);
        snprintf(label, size, "auto %s", tok + 5);
    } else if (tok[0] == 't') {
        o->representation = SVP_VARIANT_TENT;
        o->grid_x = o->grid_y = atoi(tok + 1);
        snprintf(label, size, "tent %dx%d", o->grid_x, o->grid_y);
    } else if (tok[0] == 'r') {
        o->representation = SVP_VARIANT_LOWRANK;
        int s = 8;
        const char *xs = strchr(tok, 'x');
        if (xs) s = atoi(xs + 1);
        o->rank = atoi(tok + 1);
        o->samples_x = o->samples_y = s;
        snprintf(label, size, "low rank %d (%dx%d)", o->rank, s, s);
    } else
        return 0;
    return 1;
}

/* bench_variant ops: a PSF-map file's operators, see the head of this file. */
static int cmd_ops(int argc, char **argv)
{
    const char *map = arg_str(argc, argv, "--map", NULL);
    const int reps = (int)arg_num(argc, argv, "--reps", 3);
    const int probes = (int)arg_num(argc, argv, "--probes", 12);
    const int rl_reps = (int)arg_num(argc, argv, "--rl-reps", reps);
    const char *reprs_s = arg_str(argc, argv, "--reprs", "auto:1e-3");
    const char *ref_x = arg_str(argc, argv, "--ref-x", NULL);
    const char *ref_y = arg_str(argc, argv, "--ref-y", NULL);
    if (!map) return fprintf(stderr, "bench_variant ops: --map FILE is required\n"), 1;
    svp_psf_field *f = NULL;
    double pixel_um = 0;
    if (svp_psf_field_read(map, &f, &pixel_um) != SVP_OK) return fail(map);
    const int n = svp_psf_field_width(f);
    if (n != svp_psf_field_height(f)) return fail("ops: a square map");
    const double support = svp_psf_field_base(f)->support;
    svp_image *x = random_image(n, 1), *y = NULL, *xa = NULL;
    if (!x || svp_image_new(n, n, &y) != SVP_OK || svp_image_new(n, n, &xa) != SVP_OK)
        return fail("images");
    {
        /* the floor: the invariant operator of the centre PSF against its 2 FFTs */
        svp_psf pc;
        svp_blur *b = NULL;
        double t0 = bench_now();
        if (svp_psf_field_at(f, 0.5 * (n - 1), 0.5 * (n - 1), &pc) != SVP_OK ||
            svp_blur_new(&pc, n, n, SVP_BOUNDARY_ZERO, &b) != SVP_OK)
            return fail("invariant operator");
        const double t_build = bench_now() - t0;
        timing tm;
        if (!time_interleaved(b, 1, x, y, xa, reps, &tm)) return fail("invariant operator");
        double rl_bound = NAN;
        const double rl_it = rl_reps > 0 ? rl_iteration(b, 1, x, xa, rl_reps, &rl_bound) : NAN;
        printf("{\"kind\": \"invariant\", \"label\": \"centre PSF\", \"K\": 1, \"size\": %d, "
               "\"build_s\": %.6g, \"apply_s\": %.6g, \"adjoint_s\": %.6g, \"ffts_s\": %.6g, "
               "\"rl_iteration_s\": %s, \"rl_bound_s\": %s, \"ref_error\": %s, "
               "\"operator_mb\": %.2f, \"threads\": %d}\n",
               n, t_build, tm.apply, tm.adjoint, tm.ffts, jnum(rl_it), jnum(rl_bound),
               jnum(ref_error(b, ref_x, ref_y)), svp_blur_memory(b) / 1048576.0,
               svp_get_threads());
        fflush(stdout);
        svp_blur_free(b);
    }
    char buf[512];
    snprintf(buf, sizeof buf, "%s", reprs_s);
    char *save = NULL;
    for (char *tok = strtok_r(buf, ",", &save); tok; tok = strtok_r(NULL, ",", &save)) {
        svp_variant_options o;
        char label[64];
        if (!parse_repr(tok, &o, label, sizeof label)) return fail("ops: unknown representation");
        svp_blur *b = NULL;
        const double t0 = bench_now();
        if (svp_blur_new_field(f, n, n, SVP_BOUNDARY_ZERO, &o, &b) != SVP_OK) {
            printf("{\"kind\": \"variant\", \"label\": \"%s\", \"size\": %d, \"skipped\": "
                   "\"%s\"}\n",
                   label, n, svp_last_error());
            fflush(stdout);
            continue;
        }
        const double t_build = bench_now() - t0;
        svp_variant_info in;
        if (svp_blur_variant_info(b, &in) != SVP_OK) return fail("info");
        const int K = in.representation == SVP_VARIANT_LOWRANK || in.representation == SVP_VARIANT_REGIONS
                          ? in.rank
                          : in.grid_x * in.grid_y;
        if (!isfinite(in.estimated_error)) {
            svp_variant_options forced = o;
            if (o.representation == SVP_VARIANT_AUTO) { /* not reached: auto estimates */
                forced.representation = in.representation;
            }
            if (svp_variant_estimate(f, n, n, SVP_BOUNDARY_ZERO, &forced, &in.estimated_error) !=
                SVP_OK)
                in.estimated_error = NAN;
        }
        timing tm;
        if (!time_interleaved(b, K, x, y, xa, reps, &tm)) return fail(label);
        double t_probe = 0, rl_bound = NAN;
        const double err = probes > 0 ? probe_error(b, f, n, support, probes, &t_probe) : NAN;
        const double rl_it = rl_reps > 0 ? rl_iteration(b, K, x, xa, rl_reps, &rl_bound) : NAN;
        const double rerr = ref_error(b, ref_x, ref_y);
        char chosen[64];
        if (in.representation == SVP_VARIANT_REGIONS)
            snprintf(chosen, sizeof chosen, "regions (%d kernels)", in.rank);
        else if (in.representation == SVP_VARIANT_LOWRANK)
            snprintf(chosen, sizeof chosen, "low rank %d (%dx%d)", in.rank, in.grid_x, in.grid_y);
        else
            snprintf(chosen, sizeof chosen, "tent %dx%d", in.grid_x, in.grid_y);
        printf("{\"kind\": \"variant\", \"label\": \"%s\", \"chosen\": \"%s\", \"K\": %d, "
               "\"size\": %d, \"tolerance\": %s, \"estimated_error\": %s, \"probe_error\": %s, "
               "\"probes\": %d, \"probe_s\": %.3g, \"ref_error\": %s, \"rl_iteration_s\": %s, "
               "\"rl_bound_s\": %s, \"tolerance_met\": %d, \"build_s\": %.6g, \"estimate_s\": %.6g, "
               "\"apply_s\": %.6g, \"adjoint_s\": %.6g, \"ffts_s\": %.6g, \"operator_mb\": %.2f, "
               "\"peak_estimate_mb\": %.1f, \"peak_rss_mb\": %.1f, \"threads\": %d}\n",
               label, chosen, K, n, jnum(o.representation == SVP_VARIANT_AUTO ? o.tolerance : NAN),
               jnum(in.estimated_error), jnum(err), probes, t_probe, jnum(rerr), jnum(rl_it),
               jnum(rl_bound), in.tolerance_met, t_build,
               in.estimate_seconds, tm.apply, tm.adjoint, tm.ffts,
               svp_blur_memory(b) / 1048576.0, in.peak_bytes / 1048576.0, bench_maxrss_mb(),
               svp_get_threads());
        fflush(stdout);
        svp_blur_free(b);
    }
    svp_image_free(x);
    svp_image_free(y);
    svp_image_free(xa);
    svp_psf_field_free(f);
    return 0;
}

/* CPU seconds of this process (all threads). */
static double cpu_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* The smooth map of tools/bench/variant_data.py in pixels (0.1 µm), whole field. */
static svp_psf_field *smooth_map(int n)
{
    svp_psf base;
    svp_psf_defaults(&base);
    base.model = SVP_PSF_MOFFAT;
    base.support = 0;
    const int nt = svp_psf_field_poly_terms(2);
    double c[SVP_FIELD_NPARAM * 6] = {0};
    c[SVP_FIELD_FWHM * nt + 0] = 8.0;
    c[SVP_FIELD_FWHM * nt + 1] = 2.0;
    c[SVP_FIELD_FWHM * nt + 5] = 0.5;
    c[SVP_FIELD_BETA * nt + 0] = 1.6;
    c[SVP_FIELD_BETA * nt + 1] = -0.3;
    c[SVP_FIELD_BETA * nt + 2] = -0.1;
    svp_psf_field *f = NULL;
    if (svp_psf_field_new_poly(&base, n, n, 2, c, &f) != SVP_OK) return NULL;
    return f;
}

/* A metal strip (a tenth of the width, at the middle) in oxide, whole field. */
static svp_psf_field *strip_map(int n, double blend)
{
    int *labels = malloc((size_t)n * n * sizeof(int));
    if (!labels) return NULL;
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++)
            labels[(size_t)y * n + x] = x >= n / 2 - n / 20 && x < n / 2 + n / 20;
    svp_psf rp[2];
    for (int k = 0; k < 2; k++) {
        svp_psf_defaults(&rp[k]);
        rp[k].model = SVP_PSF_MOFFAT;
        rp[k].support = 0;
    }
    rp[0].fwhm = 7.0;
    rp[0].beta = 1.9;
    rp[1].fwhm = 10.5;
    rp[1].beta = 1.25;
    svp_psf_field *f = NULL;
    svp_status st = svp_psf_field_new_regions(n, n, labels, 2, rp, blend, &f);
    free(labels);
    return st == SVP_OK ? f : NULL;
}

/* One calibration row of `cost`: the build (its second run: the first made the plans) and the
 * best of `reps` H + Hᵀ pairs, in CPU seconds and in FFTs of the frame. */
static int cost_row(const svp_psf_field *f, int n, const char *map, const svp_variant_options *o,
                    int build, int reps, const svp_image *x, svp_image *y)
{
    svp_blur *b = NULL;
    if (svp_blur_new_field_build(f, n, n, SVP_BOUNDARY_ZERO, o, build, &b) != SVP_OK)
        return fail("cost: build");
    svp_blur_free(b);
    b = NULL;
    double t0 = cpu_now();
    if (svp_blur_new_field_build(f, n, n, SVP_BOUNDARY_ZERO, o, build, &b) != SVP_OK)
        return fail("cost: build");
    const double t_build = cpu_now() - t0;
    if (svp_blur_ready(b) != SVP_OK) return fail("cost: frame");
    const svp_frame *fr = &b->frame;
    double *r = svp_alloc((size_t)fr->ny * fr->nx * sizeof(double));
    fftw_complex *c = svp_alloc((size_t)fr->ny * fr->ncx * sizeof(fftw_complex));
    if (!r || !c) return fail("cost: buffers");
    double best_pair = INFINITY, best_fft = INFINITY;
    for (int rep = -1; rep < reps; rep++) {
        for (size_t i = 0; i < (size_t)fr->ny * fr->nx; i++) r[i] = (double)(i % 7);
        t0 = cpu_now();
        svp_fft_forward(fr->plan, r, c);
        svp_fft_inverse_unscaled(fr->plan, c, r);
        const double t1 = cpu_now();
        if (svp_blur_apply(b, x, y) != SVP_OK || svp_blur_adjoint(b, x, y) != SVP_OK)
            return fail("cost: apply");
        const double t2 = cpu_now();
        if (rep < 0) continue;
        best_fft = fmin(best_fft, 0.5 * (t1 - t0));
        best_pair = fmin(best_pair, t2 - t1);
    }
    svp_free(r);
    svp_free(c);
    svp_variant_info in;
    if (svp_blur_variant_info(b, &in) != SVP_OK) return fail("cost: info");
    const int regions = in.representation == SVP_VARIANT_REGIONS;
    const int lowrank = in.representation == SVP_VARIANT_LOWRANK;
    const int K = lowrank || regions ? in.rank : in.grid_x * in.grid_y;
    const int S = lowrank ? in.grid_x * in.grid_y : 0;
    double m_build = NAN, m_apply = NAN;
    svp_variant_cost(f, n, n, SVP_BOUNDARY_ZERO, o, build == 2, &m_build, &m_apply);
    printf("{\"kind\": \"cost\", \"map\": \"%s\", \"size\": %d, \"frame\": [%d, %d], "
           "\"representation\": \"%s\", \"K\": %d, \"S\": %d, \"fold\": \"%s\", "
           "\"fft_cpu_s\": %.6g, \"build_cpu_s\": %.6g, \"pair_cpu_s\": %.6g, "
           "\"build_ffts\": %.4g, \"pair_ffts\": %.4g, \"model_build_ffts\": %s, "
           "\"model_pair_ffts\": %s}\n",
           map, n, fr->nx, fr->ny, regions ? "regions" : lowrank ? "lowrank" : "tent", K, S,
           !lowrank ? "-" : build == 2 ? "half" : "fold", best_fft, t_build, best_pair,
           t_build / best_fft, best_pair / best_fft, jnum(m_build), jnum(m_apply));
    fflush(stdout);
    svp_blur_free(b);
    return 0;
}

/* bench_variant cost: the cost model's calibration, see the head of this file. */
static int cmd_cost(int argc, char **argv)
{
    const int n = (int)arg_num(argc, argv, "--size", 256);
    const int reps = (int)arg_num(argc, argv, "--reps", 3);
    const char *what = arg_str(argc, argv, "--what", "tent,lowrank,regions");
    const char *samples = arg_str(argc, argv, "--samples", "8,16");
    svp_set_threads(1);
    svp_image *x = random_image(n, 1), *y = NULL;
    if (!x || svp_image_new(n, n, &y) != SVP_OK) return fail("images");
    svp_psf_field *f = smooth_map(n);
    if (!f) return fail("smooth map");
    int rc = 0;
    if (strstr(what, "tent")) {
        const int grids[] = {1, 2, 4};
        for (int i = 0; i < 3 && !rc; i++) {
            svp_variant_options o;
            svp_variant_defaults(&o);
            o.representation = SVP_VARIANT_TENT;
            o.grid_x = o.grid_y = grids[i];
            rc = cost_row(f, n, "smooth", &o, 0, reps, x, y);
        }
    }
    if (strstr(what, "lowrank")) {
        const int ranks[] = {3, 8};
        for (const char *p = samples; p && *p && !rc;
             p = strchr(p, ',') ? strchr(p, ',') + 1 : NULL) {
            const int s = atoi(p);
            if (s < 1) continue;
            for (int i = 0; i < 2 && !rc; i++)
                for (int build = 0; build <= 2 && !rc; build += 2) {
                    svp_variant_options o;
                    svp_variant_defaults(&o);
                    o.representation = SVP_VARIANT_LOWRANK;
                    o.samples_x = o.samples_y = s;
                    o.rank = ranks[i];
                    o.lowrank_mean = 1;
                    rc = cost_row(f, n, "smooth", &o, build, reps, x, y);
                }
        }
    }
    svp_psf_field_free(f);
    if (strstr(what, "regions"))
        for (int k = 0; k < 2 && !rc; k++) {
            svp_psf_field *g = strip_map(n, k ? 10.0 : 0.0);
            if (!g) return fail("region map");
            svp_variant_options o;
            svp_variant_defaults(&o);
            o.representation = SVP_VARIANT_REGIONS;
            rc = cost_row(g, n, k ? "regions, blended 10 px" : "regions, sharp", &o, 0, reps, x,
                          y);
            svp_psf_field_free(g);
        }
    svp_image_free(x);
    svp_image_free(y);
    return rc;
}

/* bench_variant params: the map's FWHM (px) and beta at every pixel, as two .npy images. */
static int cmd_params(int argc, char **argv)
{
    const char *map = arg_str(argc, argv, "--map", NULL);
    const char *out = arg_str(argc, argv, "--out", NULL);
    if (!map || !out) return fprintf(stderr, "bench_variant params --map F --out STEM\n"), 1;
    svp_psf_field *f = NULL;
    double pixel_um = 0;
    if (svp_psf_field_read(map, &f, &pixel_um) != SVP_OK) return fail(map);
    const int w = svp_psf_field_width(f), h = svp_psf_field_height(f);
    svp_image *fw = NULL, *be = NULL;
    if (svp_image_new(w, h, &fw) != SVP_OK || svp_image_new(w, h, &be) != SVP_OK)
        return fail("images");
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double p[SVP_FIELD_NPARAM];
            if (svp_psf_field_params_at(f, x, y, p) != SVP_OK) return fail("params");
            fw->data[(size_t)y * w + x] = p[SVP_FIELD_FWHM];
            be->data[(size_t)y * w + x] = p[SVP_FIELD_BETA];
        }
    char path[1024];
    snprintf(path, sizeof path, "%s.fwhm.npy", out);
    if (svp_image_write(path, fw, SVP_FORMAT_NPY, 1) != SVP_OK) return fail(path);
    snprintf(path, sizeof path, "%s.beta.npy", out);
    if (svp_image_write(path, be, SVP_FORMAT_NPY, 1) != SVP_OK) return fail(path);
    printf("{\"kind\": \"params\", \"width\": %d, \"height\": %d}\n", w, h);
    svp_image_free(fw);
    svp_image_free(be);
    svp_psf_field_free(f);
    return 0;
}

static int cmd_plot(int argc, char **argv)
{
    if (argc < 4) return fprintf(stderr, "bench_variant plot OUT.png @LABEL t e ...\n"), 1;
    double *x[10], *y[10];
    int n[10] = {0}, ns = -1;
    const char *labels[10];
    const char *title = "space-variant operator: accuracy vs time";
    for (int a = 3; a < argc; a++) {
        if (argv[a][0] == '=') {
            title = argv[a] + 1;
            continue;
        }
        if (argv[a][0] == '@') {
            if (++ns >= 10) return fprintf(stderr, "bench_variant plot: at most 10 curves\n"), 1;
            labels[ns] = argv[a] + 1;
            x[ns] = calloc((size_t)argc, sizeof(double));
            y[ns] = calloc((size_t)argc, sizeof(double));
            if (!x[ns] || !y[ns]) return 2;
        } else if (ns >= 0 && a + 1 < argc) {
            const double t = atof(argv[a]), e = atof(argv[a + 1]);
            a++;
            if (!(t > 0 && e > 0)) continue;
            x[ns][n[ns]] = log10(t);
            y[ns][n[ns]] = log10(e);
            n[ns]++;
        }
    }
    if (ns < 0) return fprintf(stderr, "bench_variant plot: no curve\n"), 1;
    svp_status st = svp_figure_line_plot(
        argv[2], title, "log10 time per application (s)", "log10 relative L2 error vs exact",
        ns + 1, (const double *const *)x, (const double *const *)y, n, labels, NULL, 1);
    for (int k = 0; k <= ns; k++) {
        free(x[k]);
        free(y[k]);
    }
    if (st != SVP_OK) return fail("plot");
    printf("{\"kind\": \"plot\", \"path\": \"%s\", \"curves\": %d}\n", argv[2], ns + 1);
    return 0;
}

int main(int argc, char **argv)
{
    if (argc < 2) {
        fprintf(stderr, "usage: bench_variant apply|inverse|ops|cost|params|plot [options] (see the source)\n");
        return 1;
    }
    svp_set_fft_effort(SVP_FFT_MEASURE);
    int rc;
    if (!strcmp(argv[1], "apply"))
        rc = cmd_apply(argc, argv);
    else if (!strcmp(argv[1], "inverse"))
        rc = cmd_inverse(argc, argv);
    else if (!strcmp(argv[1], "ops"))
        rc = cmd_ops(argc, argv);
    else if (!strcmp(argv[1], "cost"))
        rc = cmd_cost(argc, argv);
    else if (!strcmp(argv[1], "params"))
        rc = cmd_params(argc, argv);
    else if (!strcmp(argv[1], "plot"))
        rc = cmd_plot(argc, argv);
    else {
        fprintf(stderr, "bench_variant: unknown command '%s'\n", argv[1]);
        rc = 1;
    }
    svp_fft_cleanup();
    return rc;
}
