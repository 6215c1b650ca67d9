/* Helper of psf_cli_test.sh (PSF fitting and mapping from the command line).
 *   psf_cli_make DIR      writes the synthetic inputs into DIR (.npy, float64, Poisson counts):
 *     spot.npy        41 x 41 elliptical Moffat, FWHM 6.0 / 5.0 px, angle 0.4 rad, beta 2.5,
 *                     centre (20.3, 19.6), peak 5000 photons over 100
 *     empty.npy       background only;  border.npy the spot centred 3 px from the left edge
 *     saturated.npy   spot.npy clipped at 3000;  wide.npy 43 x 41
 *     double.npy      two such spots 16 px apart (one Moffat cannot describe them)
 *     exc.npy, pl.npy an excitation/emission pair, 50 nm pixels, 72 x 72: I_G Moffat beta 3.3,
 *                     FWHM 480 nm; p Moffat beta 1.1, FWHM 610 nm; I_PL = I_G (*) p, shifted by
 *                     (+2.4, -1.3) px; empty72.npy background only, 72 x 72
 *     field.npy       400 x 400 with 25 spots on a 5 x 5 grid: FWHM linear, beta quadratic in
 *                     the normalised position (truth below), round
 *     cut_KK.npy      the same 25 spots as 29 x 29 cut-outs, and spots.yaml listing them
 *                     (origin of each cut-out in the field); field.yaml (the one image)
 *     labels.npy      400 x 400: 0 left half (oxide), 1 right half (metal)
 *     regions_same.npy / regions_diff.npy: 400 x 400, 36 spots, 18 per half, the same PSF in
 *                     both halves / FWHM 5.0 vs 6.0 px (and regions_same.yaml, regions_diff.yaml)
 *   psf_cli_make check-map MAP.yaml   compares a polynomial map with the truth of field.npy over
 *                     the spots' area; prints the worst relative errors; exits 1 beyond 2 %
 *                     (FWHM) or 5 % (beta)
 *   psf_cli_make check-regions MAP.yaml GROUPS   reads a region map: prints the FWHM at
 *                     (100, 200) and (300, 200), exits 1 unless GROUPS = 2 and they differ by
 *                     > 0.5 px, or GROUPS = 1 and they are equal
 */
#include "svpsf.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static uint64_t state = 12345;

static double rnd(void)
{
    uint64_t x = state;
    x ^= x >> 12;
    x ^= x << 25;
    x ^= x >> 27;
    state = x;
    return (double)((x * 0x2545F4914F6CDD1DULL) >> 11) * (1.0 / 9007199254740992.0);
}

static double poisson(double mean)
{
    if (mean <= 0) return 0;
    if (mean > 50) {
        double u1 = rnd(), u2 = rnd();
        double z = sqrt(-2 * log(u1 + 1e-300)) * cos(2 * M_PI * u2);
        double v = floor(mean + sqrt(mean) * z + 0.5);
        return v < 0 ? 0 : v;
    }
    double l = exp(-mean), p = 1;
    int k = 0;
    do {
        k++;
        p *= rnd();
    } while (p > l);
    return k - 1;
}

static svp_psf moffat(double fa, double fb, double angle, double beta)
{
    svp_psf p;
    svp_psf_defaults(&p);
    p.model = SVP_PSF_MOFFAT;
    p.fwhm = fa;
    p.fwhm_minor = fb;
    p.angle = angle;
    p.beta = beta;
    return p;
}

/* adds amp × profile (integrated over 4 x 4 sub-pixels, peak 1) centred at (cx, cy), within
 * 40 px of the centre (the tails beyond are below 1e-3 of the peak for beta >= 1.8) */
static void add_spot(svp_image *img, const svp_psf *p, double cx, double cy, double amp)
{
    const int x0 = fmax(0, floor(cx - 40)), x1 = fmin(img->width - 1, ceil(cx + 40));
    const int y0 = fmax(0, floor(cy - 40)), y1 = fmin(img->height - 1, ceil(cy + 40));
    for (int y = y0; y <= y1; y++)
        for (int x = x0; x <= x1; x++) {
            double acc = 0;
            for (int j = 0; j < 4; j++)
                for (int i = 0; i < 4; i++)
                    acc += svp_psf_profile(p, x - cx + (i - 1.5) / 4, y - cy + (j - 1.5) / 4);
            img->data[(size_t)y * img->width + x] += amp * acc / 16;
        }
}

static void noisy(svp_image *img, double bg)
{
    for (size_t i = 0; i < (size_t)img->width * img->height; i++)
        img->data[i] = poisson(bg + img->data[i]);
}

static int save(const char *dir, const char *name, const svp_image *img)
{
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    if (svp_image_write(path, img, SVP_FORMAT_NPY, 1) != SVP_OK) {
        fprintf(stderr, "psf_cli_make: %s\n", svp_last_error());
        return 1;
    }
    return 0;
}

static void truth(double x, double y, double *fwhm, double *beta)
{
    double u = (2 * x - 399) / 399, v = (2 * y - 399) / 399;
    *fwhm = 5.0 + 1.0 * u + 0.4 * v;
    *beta = 2.2 + 0.8 * u * u + 0.3 * v;
}

static int write_text(const char *dir, const char *name, const char *text)
{
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    FILE *f = fopen(path, "w");
    if (!f) return 1;
    fputs(text, f);
    return fclose(f) != 0;
}

static int make(const char *dir)
{
    svp_image *img = NULL;
    int rc = 0;
    /* single spots */
    svp_psf s = moffat(6.0, 5.0, 0.4, 2.5);
    svp_image_new(41, 41, &img);
    add_spot(img, &s, 20.3, 19.6, 5000);
    noisy(img, 100);
    rc |= save(dir, "spot.npy", img);
    for (size_t i = 0; i < 41 * 41; i++) img->data[i] = fmin(img->data[i], 3000);
    rc |= save(dir, "saturated.npy", img);
    for (size_t i = 0; i < 41 * 41; i++) img->data[i] = poisson(100);
    rc |= save(dir, "empty.npy", img);
    memset(img->data, 0, 41 * 41 * sizeof(double));
    add_spot(img, &s, 3.0, 20.0, 5000);
    noisy(img, 100);
    rc |= save(dir, "border.npy", img);
    memset(img->data, 0, 41 * 41 * sizeof(double));
    add_spot(img, &s, 12.0, 20.0, 5000);
    add_spot(img, &s, 28.0, 20.0, 5000);
    noisy(img, 100);
    rc |= save(dir, "double.npy", img);
    svp_image_free(img);
    svp_image_new(43, 41, &img);
    rc |= save(dir, "wide.npy", img);
    svp_image_free(img);

    /* the pair (direct sum; p untruncated over the image) */
    {
        enum { W = 72 };
        svp_psf pg = moffat(9.6, 9.6, 0, 3.3), pp = moffat(12.2, 12.2, 0, 1.1);
        svp_image *g = NULL, *pl = NULL;
        svp_image_new(W, W, &g);
        svp_image_new(W, W, &pl);
        const double cx = 35.3, cy = 36.2, sx = 2.4, sy = -1.3;
        add_spot(g, &pg, cx, cy, 1.0);
        double gmax = 0, plmax = 0;
        for (int y = 0; y < W; y++)
            for (int x = 0; x < W; x++) {
                double acc = 0;
                for (int v = 0; v < W; v++)
                    for (int u = 0; u < W; u++)
                        acc += g->data[v * W + u] * svp_psf_profile(&pp, x - u - sx, y - v - sy);
                pl->data[y * W + x] = acc;
            }
        for (size_t i = 0; i < W * W; i++) {
            gmax = fmax(gmax, g->data[i]);
            plmax = fmax(plmax, pl->data[i]);
        }
        for (size_t i = 0; i < W * W; i++) {
            g->data[i] = poisson(100 + 5000 * g->data[i] / gmax);
            pl->data[i] = poisson(100 + 5000 * pl->data[i] / plmax);
        }
        rc |= save(dir, "exc.npy", g);
        for (size_t i = 0; i < W * W; i++) g->data[i] = poisson(100);
        rc |= save(dir, "empty72.npy", g);
        rc |= save(dir, "pl.npy", pl);
        svp_image_free(g);
        svp_image_free(pl);
    }

    /* the field: 25 spots, as one image and as cut-outs */
    {
        enum { W = 400, CUT = 29 };
        svp_image *field = NULL, *cut = NULL;
        svp_image_new(W, W, &field);
        svp_image_new(CUT, CUT, &cut);
        char *yaml = malloc(8192);
        int n = snprintf(yaml, 8192,
                         "# 25 spot cut-outs of field.npy\npixel_um: 0.05\n"
                         "field: {width: 400, height: 400}\nspots:\n");
        for (int k = 0; k < 25; k++) {
            double cx = 40 + 80 * (k % 5) + 10 * (rnd() - 0.5);
            double cy = 40 + 80 * (k / 5) + 10 * (rnd() - 0.5);
            double F, B;
            truth(cx, cy, &F, &B);
            svp_psf p = moffat(F, F, 0, B);
            add_spot(field, &p, cx, cy, 5000);
            int ox = (int)floor(cx) - CUT / 2, oy = (int)floor(cy) - CUT / 2;
            memset(cut->data, 0, sizeof(double) * CUT * CUT);
            add_spot(cut, &p, cx - ox, cy - oy, 5000);
            noisy(cut, 100);
            char name[64];
            snprintf(name, sizeof name, "cut_%02d.npy", k);
            rc |= save(dir, name, cut);
            n += snprintf(yaml + n, 8192 - (size_t)n, "  - {file: %s, origin: [%d, %d]}\n", name,
                          ox, oy);
        }
        noisy(field, 100);
        rc |= save(dir, "field.npy", field);
        rc |= write_text(dir, "spots.yaml", yaml);
        rc |= write_text(dir, "field.yaml",
                         "# one image with 25 spots to detect\npixel_um: 0.05\nimage: field.npy\n"
                         "window: 31\n");
        free(yaml);
        /* labels: oxide | metal */
        for (int y = 0; y < W; y++)
            for (int x = 0; x < W; x++) field->data[y * W + x] = x < W / 2 ? 0 : 1;
        rc |= save(dir, "labels.npy", field);
        /* region sets */
        for (int differ = 0; differ < 2; differ++) {
            memset(field->data, 0, sizeof(double) * W * W);
            for (int k = 0; k < 36; k++) {
                double cx = 33 + 66 * (k % 6) + 6 * (rnd() - 0.5);
                double cy = 33 + 66 * (k / 6) + 6 * (rnd() - 0.5);
                double F = differ && cx > 200 ? 6.0 : 5.0;
                svp_psf p = moffat(F, F, 0, 2.5);
                add_spot(field, &p, cx, cy, 5000);
            }
            noisy(field, 100);
            rc |= save(dir, differ ? "regions_diff.npy" : "regions_same.npy", field);
            rc |= write_text(dir, differ ? "regions_diff.yaml" : "regions_same.yaml",
                             differ ? "pixel_um: 0.05\nimage: regions_diff.npy\nwindow: 31\n"
                                    : "pixel_um: 0.05\nimage: regions_same.npy\nwindow: 31\n");
        }
        svp_image_free(field);
        svp_image_free(cut);
    }
    /* 16 spots on a 4 x 4 grid (200 x 200, FWHM 5 + x / 100 px, beta 2.5): four distinct
     * positions per axis cannot determine a degree-4 surface, whose u⁴ term then follows the
     * noise of the fitted centres (FWHM surfaces below 0 between the spots) */
    {
        svp_image *grid = NULL;
        svp_image_new(200, 200, &grid);
        for (int j = 0; j < 4; j++)
            for (int i = 0; i < 4; i++) {
                const double cx = 25 + 50 * i, cy = 25 + 50 * j;
                svp_psf p = moffat(5 + cx / 100, 5 + cx / 100, 0, 2.5);
                add_spot(grid, &p, cx, cy, 3000);
            }
        noisy(grid, 10);
        rc |= save(dir, "grid16.npy", grid);
        rc |= write_text(dir, "grid16.yaml", "pixel_um: 0.05\nimage: grid16.npy\n");
        svp_image_free(grid);
    }
    return rc;
}

static int check_map(const char *path)
{
    svp_psf_field *f = NULL;
    double um = 0;
    if (svp_psf_field_read(path, &f, &um) != SVP_OK) {
        fprintf(stderr, "check-map: %s\n", svp_last_error());
        return 1;
    }
    double wf = 0, wb = 0;
    for (int j = 0; j <= 8; j++)
        for (int i = 0; i <= 8; i++) {
            double x = 40 + 40 * i, y = 40 + 40 * j, F, B, p[SVP_FIELD_NPARAM];
            truth(x, y, &F, &B);
            if (svp_psf_field_params_at(f, x, y, p) != SVP_OK) return 1;
            wf = fmax(wf, fabs(p[SVP_FIELD_FWHM] / F - 1));
            wb = fmax(wb, fabs(p[SVP_FIELD_BETA] / B - 1));
        }
    printf(
        "check-map %s: kind %d, pixel %.3g um, worst relative error FWHM %.2f %%, beta %.2f %%\n",
        path, (int)svp_psf_field_get_kind(f), um, 100 * wf, 100 * wb);
    svp_psf_field_free(f);
    return wf < 0.02 && wb < 0.05 && fabs(um - 0.05) < 1e-12 ? 0 : 1;
}

static int check_regions(const char *path, int groups)
{
    svp_psf_field *f = NULL;
    if (svp_psf_field_read(path, &f, NULL) != SVP_OK) {
        fprintf(stderr, "check-regions: %s\n", svp_last_error());
        return 1;
    }
    double a[SVP_FIELD_NPARAM], b[SVP_FIELD_NPARAM];
    if (svp_psf_field_params_at(f, 100, 200, a) != SVP_OK ||
        svp_psf_field_params_at(f, 300, 200, b) != SVP_OK)
        return 1;
    printf("check-regions %s: kind %d, FWHM left %.4f px, right %.4f px\n", path,
           (int)svp_psf_field_get_kind(f), a[0], b[0]);
    int ok = svp_psf_field_get_kind(f) == SVP_FIELD_REGIONS &&
             (groups == 2 ? fabs(b[0] - 6.0) < 0.15 && fabs(a[0] - 5.0) < 0.15
                          : a[0] == b[0] && fabs(a[0] - 5.0) < 0.15);
    svp_psf_field_free(f);
    return ok ? 0 : 1;
}

int main(int argc, char **argv)
{
    if (argc == 2) return make(argv[1]);
    if (argc == 3 && strcmp(argv[1], "check-map") == 0) return check_map(argv[2]);
    if (argc == 4 && strcmp(argv[1], "check-regions") == 0)
        return check_regions(argv[2], atoi(argv[3]));
    fprintf(stderr, "usage: psf_cli_make DIR | check-map MAP.yaml | check-regions MAP.yaml N\n");
    return 2;
}
