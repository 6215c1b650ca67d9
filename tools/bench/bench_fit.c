/* Benchmark of PSF spot fits and PSF maps (docs/model.md §8). One JSON object per line on stdout.
 *
 *   bench_fit spots --size N [--count K] [--threads T] [--reps R]
 *       K Poisson Moffat spots of N x N px (elliptical, FWHM ~ N/6, beta 2.5, peak 5000 photons
 *       over 100), fitted by svp_spot_fit in parallel over spots (OpenMP, T threads). Reports the
 *       best of R wall times, fits per second, the mean LM iterations, the recovery error
 *       (rms relative FWHM and beta error), and a checksum of the fitted values (equal across
 *       thread counts: each fit is independent and deterministic).
 *   bench_fit map [--count K] [--threads T] [--reps R]
 *       a 1000 x 1000 field, K spots (31 x 31 cut-outs on a grid) whose FWHM varies linearly and
 *       beta quadratically; end to end: fit every spot, svp_psf_map_poly (degree by
 *       cross-validation), svp_psf_field_write + svp_psf_field_read. Times per stage, peak
 *       memory, worst map error over the field.
 *   bench_fit write-field DIR [--count K]
 *       writes DIR/field.npy (the same 1000 x 1000 field with K spots in one image) and
 *       DIR/field.yaml (for `svpsf map-psf`: spots detected, 31 x 31 windows), so the section
 *       script can time the command line end to end (reading, detection, fits, map, writing).
 */
#include "bench_common.h"
#include "svpsf.h"

#include <math.h>
#include <omp.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static double rnd(uint64_t *s)
{
    uint64_t x = *s;
    x ^= x >> 12;
    x ^= x << 25;
    x ^= x >> 27;
    *s = x;
    return (double)((x * 0x2545F4914F6CDD1DULL) >> 11) * (1.0 / 9007199254740992.0);
}

static double poisson(uint64_t *s, double mean)
{
    if (mean > 50) {
        double u1 = rnd(s), u2 = rnd(s);
        double v =
            floor(mean + sqrt(mean) * sqrt(-2 * log(u1 + 1e-300)) * cos(2 * M_PI * u2) + 0.5);
        return v < 0 ? 0 : v;
    }
    double l = exp(-mean), p = 1;
    int k = 0;
    do {
        k++;
        p *= rnd(s);
    } while (p > l);
    return k - 1;
}

static void make_spot(svp_image *img, const svp_psf *p, double cx, double cy, uint64_t *s)
{
    for (int y = 0; y < img->height; y++)
        for (int x = 0; x < img->width; x++) {
            double acc = 0;
            for (int j = 0; j < 2; j++)
                for (int i = 0; i < 2; i++)
                    acc += svp_psf_profile(p, x - cx + (i - 0.5) / 2, y - cy + (j - 0.5) / 2);
            img->data[(size_t)y * img->width + x] = poisson(s, 100 + 5000 * acc / 4);
        }
}

static int parse(int argc, char **argv, const char *name, int def)
{
    for (int i = 2; i + 1 < argc; i++)
        if (strcmp(argv[i], name) == 0) return atoi(argv[i + 1]);
    return def;
}

static int bench_spots(int argc, char **argv)
{
    const int N = parse(argc, argv, "--size", 31), K = parse(argc, argv, "--count", 200);
    const int T = parse(argc, argv, "--threads", 1), R = parse(argc, argv, "--reps", 3);
    svp_image **img = calloc((size_t)K, sizeof *img);
    svp_spot_result *res = calloc((size_t)K, sizeof *res);
    double *tf = calloc((size_t)K, sizeof *tf), *tb = calloc((size_t)K, sizeof *tb);
    uint64_t s = 99;
    for (int k = 0; k < K; k++) {
        svp_psf p;
        svp_psf_defaults(&p);
        p.model = SVP_PSF_MOFFAT;
        tf[k] = N / 6.0 * (0.9 + 0.2 * rnd(&s));
        p.fwhm = tf[k] * 1.1;
        p.fwhm_minor = tf[k] * 0.9;
        p.angle = rnd(&s) * M_PI;
        p.beta = tb[k] = 2.0 + rnd(&s);
        if (svp_image_new(N, N, &img[k]) != SVP_OK) return 2;
        make_spot(img[k], &p, 0.5 * (N - 1) + rnd(&s) - 0.5, 0.5 * (N - 1) + rnd(&s) - 0.5, &s);
    }
    omp_set_num_threads(T);
    svp_spot_options o;
    svp_spot_defaults(&o);
    double best = INFINITY;
    int failed = 0;
    for (int r = 0; r < R; r++) {
        failed = 0;
        double t0 = bench_now();
#pragma omp parallel for schedule(dynamic) reduction(+ : failed)
        for (int k = 0; k < K; k++)
            failed += svp_spot_fit(img[k], &o, &res[k], NULL, NULL) != SVP_OK;
        best = fmin(best, bench_now() - t0);
    }
    double ef = 0, eb = 0, it = 0, checksum = 0;
    for (int k = 0; k < K; k++) {
        double mean_true = tf[k]; /* (1.1 + 0.9) / 2 × tf */
        ef += pow(res[k].fwhm / mean_true - 1, 2);
        eb += pow(res[k].beta / tb[k] - 1, 2);
        it += res[k].iterations;
        checksum += res[k].fwhm * (k + 1) + res[k].beta;
    }
    printf("{\"mode\": \"spots\", \"size\": %d, \"count\": %d, \"threads\": %d, \"reps\": %d, "
           "\"seconds\": %.6f, \"fits_per_s\": %.2f, \"ms_per_fit\": %.4f, \"mean_iterations\": "
           "%.2f, \"failed\": %d, \"rms_rel_fwhm_error\": %.5f, \"rms_rel_beta_error\": %.5f, "
           "\"checksum\": %.12e, \"peak_mb\": %.1f}\n",
           N, K, T, R, best, K / best, 1e3 * best / K, it / K, failed, sqrt(ef / K), sqrt(eb / K),
           checksum, bench_maxrss_mb());
    for (int k = 0; k < K; k++) svp_image_free(img[k]);
    free(img);
    free(res);
    free(tf);
    free(tb);
    return failed ? 1 : 0;
}

static void truth(double x, double y, int W, double *F, double *B)
{
    double u = (2 * x - (W - 1)) / (W - 1), v = (2 * y - (W - 1)) / (W - 1);
    *F = 5.0 + 1.0 * u + 0.4 * v;
    *B = 2.2 + 0.8 * u * u + 0.3 * v;
}

static int bench_map(int argc, char **argv)
{
    enum { W = 1000, CUT = 31 };
    const int K = parse(argc, argv, "--count", 100), T = parse(argc, argv, "--threads", 1);
    const int R = parse(argc, argv, "--reps", 3);
    const int g = (int)ceil(sqrt(K));
    svp_image **img = calloc((size_t)K, sizeof *img);
    svp_psf_sample *smp = calloc((size_t)K, sizeof *smp);
    double *ox = calloc((size_t)K, sizeof *ox), *oy = calloc((size_t)K, sizeof *oy);
    uint64_t s = 7;
    for (int k = 0; k < K; k++) {
        double cx = (k % g + 0.5) * W / g + 4 * (rnd(&s) - 0.5);
        double cy = (k / g + 0.5) * W / g + 4 * (rnd(&s) - 0.5);
        double F, B;
        truth(cx, cy, W, &F, &B);
        svp_psf p;
        svp_psf_defaults(&p);
        p.model = SVP_PSF_MOFFAT;
        p.fwhm = F;
        p.beta = B;
        ox[k] = floor(cx) - CUT / 2;
        oy[k] = floor(cy) - CUT / 2;
        if (svp_image_new(CUT, CUT, &img[k]) != SVP_OK) return 2;
        make_spot(img[k], &p, cx - ox[k], cy - oy[k], &s);
    }
    omp_set_num_threads(T);
    svp_spot_options o;
    svp_spot_defaults(&o);
    char path[256];
    snprintf(path, sizeof path, "/tmp/bench_fit_map_%ld.yaml", (long)getpid());
    double best_total = INFINITY, t_fit = 0, t_map = 0, t_io = 0, worst_f = 0, worst_b = 0;
    int used_f = 0, deg_f = -1, deg_b = -1;
    for (int r = 0; r < R; r++) {
        double t0 = bench_now();
        int failed = 0;
#pragma omp parallel for schedule(dynamic) reduction(+ : failed)
        for (int k = 0; k < K; k++) {
            failed += svp_spot_fit(img[k], &o, &smp[k].fit, NULL, NULL) != SVP_OK;
            smp[k].x = ox[k] + smp[k].fit.x0;
            smp[k].y = oy[k] + smp[k].fit.y0;
        }
        double t1 = bench_now();
        svp_psf_field *field = NULL, *back = NULL;
        svp_map_report *rep = NULL;
        if (failed || svp_psf_map_poly(smp, K, W, W, NULL, &field, &rep) != SVP_OK) {
            printf("{\"mode\": \"map\", \"error\": \"%s\"}\n",
                   failed ? "fit failed" : svp_last_error());
            return 1;
        }
        double t2 = bench_now();
        if (svp_psf_field_write(path, field, 0.05, "bench_fit", 1) != SVP_OK ||
            svp_psf_field_read(path, &back, NULL) != SVP_OK) {
            printf("{\"mode\": \"map\", \"error\": \"%s\"}\n", svp_last_error());
            return 1;
        }
        double t3 = bench_now();
        if (t3 - t0 < best_total) {
            best_total = t3 - t0;
            t_fit = t1 - t0;
            t_map = t2 - t1;
            t_io = t3 - t2;
        }
        worst_f = worst_b = 0;
        for (int j = 0; j <= 10; j++)
            for (int i = 0; i <= 10; i++) {
                double x = W / (2.0 * g) + i * (W - W / (double)g) / 10;
                double y = W / (2.0 * g) + j * (W - W / (double)g) / 10;
                double F, B, p[SVP_FIELD_NPARAM];
                truth(x, y, W, &F, &B);
                svp_psf_field_params_at(back, x, y, p);
                worst_f = fmax(worst_f, fabs(p[SVP_FIELD_FWHM] / F - 1));
                worst_b = fmax(worst_b, fabs(p[SVP_FIELD_BETA] / B - 1));
            }
        used_f = rep->n_used[SVP_FIELD_FWHM];
        deg_f = rep->degree[SVP_FIELD_FWHM];
        deg_b = rep->degree[SVP_FIELD_BETA];
        svp_psf_field_free(field);
        svp_psf_field_free(back);
        svp_map_report_free(rep);
    }
    remove(path);
    printf("{\"mode\": \"map\", \"count\": %d, \"threads\": %d, \"reps\": %d, \"seconds\": %.6f, "
           "\"fit_seconds\": %.6f, \"map_seconds\": %.6f, \"io_seconds\": %.6f, \"spots_used\": "
           "%d, \"degree_fwhm\": %d, \"degree_beta\": %d, \"worst_rel_fwhm_error\": %.5f, "
           "\"worst_rel_beta_error\": %.5f, \"peak_mb\": %.1f}\n",
           K, T, R, best_total, t_fit, t_map, t_io, used_f, deg_f, deg_b, worst_f, worst_b,
           bench_maxrss_mb());
    for (int k = 0; k < K; k++) svp_image_free(img[k]);
    free(img);
    free(smp);
    free(ox);
    free(oy);
    return 0;
}

static int write_field(int argc, char **argv)
{
    enum { W = 1000 };
    const char *dir = argv[2];
    const int K = parse(argc, argv, "--count", 100), g = (int)ceil(sqrt(K));
    svp_image *img = NULL, *cut = NULL;
    if (svp_image_new(W, W, &img) != SVP_OK || svp_image_new(41, 41, &cut) != SVP_OK) return 2;
    uint64_t s = 7;
    for (int k = 0; k < K; k++) {
        double cx = (k % g + 0.5) * W / g + 4 * (rnd(&s) - 0.5);
        double cy = (k / g + 0.5) * W / g + 4 * (rnd(&s) - 0.5);
        double F, B;
        truth(cx, cy, W, &F, &B);
        svp_psf p;
        svp_psf_defaults(&p);
        p.model = SVP_PSF_MOFFAT;
        p.fwhm = F;
        p.beta = B;
        int ox = (int)floor(cx) - 20, oy = (int)floor(cy) - 20;
        uint64_t s2 = s + (uint64_t)k;
        make_spot(cut, &p, cx - ox, cy - oy, &s2); /* Poisson over 100 inside the 41² box */
        for (int y = 0; y < 41; y++)
            for (int x = 0; x < 41; x++)
                if (ox + x >= 0 && oy + y >= 0 && ox + x < W && oy + y < W)
                    img->data[(size_t)(oy + y) * W + ox + x] = cut->data[y * 41 + x];
    }
    uint64_t s3 = 11;
    for (size_t i = 0; i < (size_t)W * W; i++)
        if (img->data[i] == 0) img->data[i] = poisson(&s3, 100);
    char path[4096];
    snprintf(path, sizeof path, "%s/field.npy", dir);
    if (svp_image_write(path, img, SVP_FORMAT_NPY, 1) != SVP_OK) {
        fprintf(stderr, "bench_fit: %s\n", svp_last_error());
        return 1;
    }
    snprintf(path, sizeof path, "%s/field.yaml", dir);
    FILE *f = fopen(path, "w");
    if (!f) return 1;
    fprintf(f, "pixel_um: 0.05\nimage: field.npy\nwindow: 31\n");
    fclose(f);
    printf("{\"mode\": \"write-field\", \"count\": %d, \"width\": %d}\n", K, W);
    svp_image_free(img);
    svp_image_free(cut);
    return 0;
}

int main(int argc, char **argv)
{
    if (argc >= 3 && strcmp(argv[1], "write-field") == 0) return write_field(argc, argv);
    if (argc >= 2 && strcmp(argv[1], "spots") == 0) return bench_spots(argc, argv);
    if (argc >= 2 && strcmp(argv[1], "map") == 0) return bench_map(argc, argv);
    fprintf(stderr, "usage: bench_fit spots --size N [--count K] [--threads T] [--reps R]\n"
                    "       bench_fit map [--count K] [--threads T] [--reps R]\n");
    return 2;
}
