/* Inputs and checks for odmr_cli_test.sh (svpsf fit-odmr):
 *   odmr_cli_make stack OUT.tif FREQ.txt TRUTH.npy PL.npy W H NF SEED
 *       an ODMR stack written here: per pixel two Lorentzian dips at D' ∓ γ B (D' = D + 0.5 MHz,
 *       B known, between 1 and 3 mT), FWHM 5 MHz, contrast 3 %, PL 800..1200 counts, Gaussian
 *       noise σ = 3 counts; as a multi-page float32 TIFF built byte by byte (not by OpenCV),
 *       the frequencies (Hz, one per line), the true field (T) and PL as .npy
 *   odmr_cli_make drift OUT.tif FREQ.txt TRUTH.npy PL.npy W H NF SEED DX DY
 *       the same lines about D (field 1..3 mT, PL 400..1600 counts: 40 random blobs squashed
 *       by tanh; uniform 1000 when DX = DY = 0), noise σ = 1 count, while the sample drifts
 *       linearly from 0 to (DX, DY) px over the sweep; each frame rendered analytically at its
 *       position; truth and PL at the mean position (DX, DY) / 2
 *   odmr_cli_make blurred OUT.tif FREQ.txt TRUTH.npy PL.npy W H NF SEED SIGMA
 *       a sweep blurred by a Gaussian of σ = SIGMA px by direct convolution here, on a canvas
 *       10 px beyond the view: blobs of PL 400..1600 counts, a field step of 240 µT (1 MHz
 *       lines 3 % deep), noise σ = 1 count; truth and PL unblurred
 *   odmr_cli_make pages OUT.tif N          a 16-bit TIFF of N 8 x 6 pages
 *   odmr_cli_make nanframe IN OUT.npy K [N]  the stack IN with frames K .. K+N-1 (N: 1) NaN
 *                                          at every pixel
 *   odmr_cli_make dropframe IN OUT.npy K   the stack IN without frame K
 *   odmr_cli_make compare EST.npy TRUTH.npy SCALE MEAN_TOL MAX_TOL [SIGMA.npy]
 *       EST / SCALE against TRUTH: mean and max |difference| within the tolerances (NaN pixels
 *       fail), and with SIGMA (same unit as EST) the rms of (EST − TRUTH) / SIGMA in [0.8, 1.25]
 * Exit 0 when the files were written / the check passed; the numbers go to stdout. */
#include "svpsf.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static uint64_t rng = 1;
static double uniform(void)
{
    rng = rng * 6364136223846793005ULL + 1442695040888963407ULL;
    return ((rng >> 11) + 0.5) / 9007199254740992.0;
}
static double gauss(void)
{
    return sqrt(-2 * log(uniform())) * cos(2 * M_PI * uniform());
}

static void le(unsigned char *p, uint32_t v, int n)
{
    for (int k = 0; k < n; k++) p[k] = (unsigned char)(v >> (8 * k));
}

/* A classic little-endian TIFF: every page's strip, then its directory (bits 16 or 32, sample
 * format 1 = unsigned or 3 = float). pixels[p] holds page p's w * h values (as float or
 * uint16 by bits). */
static int write_tiff(const char *path, int w, int h, int n, int bits, const void *pixels)
{
    const size_t bytes = (size_t)w * h * (size_t)(bits / 8);
    const size_t page = bytes + 2 + 12 * 10 + 4 + 1;
    unsigned char *buf = calloc(1, 8 + (size_t)n * page);
    if (!buf) return 1;
    memcpy(buf, "II*\0", 4);
    size_t pos = 8, link = 4;
    for (int p = 0; p < n; p++) {
        memcpy(buf + pos, (const unsigned char *)pixels + (size_t)p * bytes, bytes);
        size_t data = pos, ifd = pos + bytes;
        ifd += ifd & 1;
        le(buf + link, (uint32_t)ifd, 4);
        const uint32_t e[10][3] = {{256, 3, (uint32_t)w}, {257, 3, (uint32_t)h},
                                   {258, 3, (uint32_t)bits}, {259, 3, 1},
                                   {262, 3, 1}, {273, 4, (uint32_t)data},
                                   {277, 3, 1}, {278, 3, (uint32_t)h},
                                   {279, 4, (uint32_t)bytes}, {339, 3, bits == 32 ? 3u : 1u}};
        le(buf + ifd, 10, 2);
        for (int k = 0; k < 10; k++) {
            unsigned char *q = buf + ifd + 2 + 12 * k;
            le(q, e[k][0], 2);
            le(q + 2, e[k][1], 2);
            le(q + 4, 1, 4);
            le(q + 8, e[k][2], e[k][1] == 3 ? 2 : 4);
        }
        link = ifd + 2 + 12 * 10;
        le(buf + link, 0, 4);
        pos = link + 4;
    }
    FILE *f = fopen(path, "wb");
    int bad = !f || fwrite(buf, 1, pos, f) != pos;
    if (f) bad |= fclose(f) != 0;
    free(buf);
    if (bad) fprintf(stderr, "cannot write %s\n", path);
    return bad;
}

/* The stack as a float32 TIFF (a[0]) and the truth and PL as .npy (a[2], a[3]); frees the
 * three. */
static int write_sweep(char **a, int w, int h, int nf, float *pix, svp_image *truth,
                       svp_image *pl)
{
    int bad = write_tiff(a[0], w, h, nf, 32, pix);
    bad |= svp_image_write(a[2], truth, SVP_FORMAT_NPY, 1) != SVP_OK;
    bad |= svp_image_write(a[3], pl, SVP_FORMAT_NPY, 1) != SVP_OK;
    free(pix);
    svp_image_free(truth);
    svp_image_free(pl);
    return bad;
}

static int make_stack(char **a)
{
    const char *freq_path = a[1];
    const int w = atoi(a[4]), h = atoi(a[5]), nf = atoi(a[6]);
    rng = strtoull(a[7], NULL, 10);
    const double D = 2.870e9 + 0.5e6, g = 28.033e9, fwhm = 5e6, C = 0.03, noise = 3;
    const size_t n = (size_t)w * h;
    svp_image *truth = NULL, *pl = NULL;
    if (svp_image_new(w, h, &truth) || svp_image_new(w, h, &pl)) return 1;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            truth->data[y * w + x] = 1e-3 + 2e-3 * (0.5 + 0.5 * sin(0.3 * x) * cos(0.2 * y));
            pl->data[y * w + x] = 1000 + 200 * cos(0.15 * (x + y));
        }
    float *pix = malloc(n * (size_t)nf * sizeof(float));
    FILE *ff = fopen(freq_path, "w");
    if (!pix || !ff) return 1;
    for (int f = 0; f < nf; f++) {
        const double wf = 2.870e9 - 120e6 + 240e6 * f / (nf - 1);
        fprintf(ff, "%.17g\n", wf);
        for (size_t p = 0; p < n; p++) {
            const double h2 = 0.25 * fwhm * fwhm, s = g * truth->data[p];
            const double lo = wf - (D - s), hi = wf - (D + s);
            const double dip = h2 / (lo * lo + h2) + h2 / (hi * hi + h2);
            pix[(size_t)f * n + p] = (float)(pl->data[p] * (1 - C * dip) + noise * gauss());
        }
    }
    if (fclose(ff)) return 1;
    return write_sweep(a, w, h, nf, pix, truth, pl);
}

/* A sweep during which the sample drifts linearly from 0 to (dx, dy) px: PL (a textured
 * pattern of tanh edges) and field rendered analytically at each frame's position, so no
 * interpolation of the library's is involved; the truth maps are at the mean position
 * (dx, dy) / 2, where svp_cube_align brings the frames. */
static int make_drift(char **a)
{
    const char *freq_path = a[1];
    const int w = atoi(a[4]), h = atoi(a[5]), nf = atoi(a[6]);
    rng = strtoull(a[7], NULL, 10);
    const double ddx = atof(a[8]), ddy = atof(a[9]);
    const double D = 2.870e9, g = 28.033e9, fwhm = 5e6, C = 0.03, noise = 1;
    const size_t n = (size_t)w * h;
    svp_image *truth = NULL, *pl = NULL;
    if (svp_image_new(w, h, &truth) || svp_image_new(w, h, &pl)) return 1;
    float *pix = malloc(n * (size_t)nf * sizeof(float));
    FILE *ff = fopen(freq_path, "w");
    if (!pix || !ff) return 1;
    /* the texture: 40 blobs (σ 1.5..4 px) placed at random over and around the view */
    double bx[40], by[40], bs[40], ba[40];
    for (int k = 0; k < 40; k++) {
        bx[k] = uniform() * (w + 10) - 5;
        by[k] = uniform() * (h + 10) - 5;
        bs[k] = 1.5 + 2.5 * uniform();
        ba[k] = uniform() - 0.5;
    }
    for (int f = -1; f < nf; f++) { /* f = -1: the truth at the mean position */
        const double t = f < 0 ? 0.5 : (double)f / (nf - 1);
        const double wf = 2.870e9 - 120e6 + 240e6 * (f < 0 ? 0 : f) / (nf - 1);
        if (f >= 0) fprintf(ff, "%.17g\n", wf);
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                const double sx = x - t * ddx, sy = y - t * ddy;
                const double b = 1e-3 + 2e-3 * (0.5 + 0.5 * sin(0.3 * sx) * cos(0.2 * sy));
                double u = 0;
                for (int k = 0; k < 40; k++)
                    u += ba[k] * exp(-((sx - bx[k]) * (sx - bx[k]) + (sy - by[k]) * (sy - by[k])) /
                                     (2 * bs[k] * bs[k]));
                const double p = ddx == 0 && ddy == 0 ? 1000 : 1000 + 600 * tanh(2 * u);
                const size_t i = (size_t)y * w + x;
                if (f < 0) {
                    truth->data[i] = b;
                    pl->data[i] = p;
                    continue;
                }
                const double h2 = 0.25 * fwhm * fwhm, s = g * b;
                const double lo = wf - (D - s), hi = wf - (D + s);
                const double dip = h2 / (lo * lo + h2) + h2 / (hi * hi + h2);
                pix[(size_t)f * n + i] = (float)(p * (1 - C * dip) + noise * gauss());
            }
    }
    if (fclose(ff)) return 1;
    return write_sweep(a, w, h, nf, pix, truth, pl);
}

/* A sweep blurred by a Gaussian of σ = SIGMA px with the test's own direct convolution, on a
 * canvas 10 px beyond the view (light from outside), then cropped: PL of bright and dark blobs
 * (400..1600 counts), a field step of 240 µT across a few pixels (the fit of a blurred pixel
 * sees separated dips), two dips of 3 % and 1 MHz, noise σ = 1 count; truth and PL unblurred. */
static int make_blurred(char **a)
{
    const char *freq_path = a[1];
    const int w = atoi(a[4]), h = atoi(a[5]), nf = atoi(a[6]), pad = 10;
    rng = strtoull(a[7], NULL, 10);
    const double sigma = atof(a[8]), D = 2.870e9, g = 28.033e9, fwhm = 1e6, C = 0.03;
    const int cw = w + 2 * pad, ch = h + 2 * pad, r = (int)ceil(4 * sigma);
    svp_image *truth = NULL, *pl = NULL;
    if (svp_image_new(w, h, &truth) || svp_image_new(w, h, &pl)) return 1;
    float *pix = malloc((size_t)w * h * nf * sizeof(float));
    double *cv = malloc((size_t)cw * ch * sizeof(double)), *tmp = malloc((size_t)cw * ch * sizeof(double));
    double *k1 = malloc((size_t)(2 * r + 1) * sizeof(double)), ks = 0;
    FILE *ff = fopen(freq_path, "w");
    if (!pix || !cv || !tmp || !k1 || !ff) return 1;
    for (int i = -r; i <= r; i++) ks += k1[i + r] = exp(-0.5 * i * i / (sigma * sigma));
    for (int i = 0; i <= 2 * r; i++) k1[i] /= ks;
    double bx[12], by[12], ba[12];
    for (int k = 0; k < 12; k++) {
        bx[k] = uniform() * (w + 10) - 5;
        by[k] = uniform() * (h + 10) - 5;
        ba[k] = uniform() - 0.5;
    }
    for (int f = 0; f < nf; f++) {
        const double wf = D - 12e6 + 24e6 * f / (nf - 1);
        fprintf(ff, "%.17g\n", wf);
        for (int y = 0; y < ch; y++)
            for (int x = 0; x < cw; x++) {
                const double sx = x - pad, sy = y - pad;
                double u = 0;
                for (int k = 0; k < 12; k++)
                    u += ba[k] * exp(-((sx - bx[k]) * (sx - bx[k]) + (sy - by[k]) * (sy - by[k])) / 30.0);
                const double p = 1000 + 600 * tanh(2 * u);
                const double b = 150e-6 + 120e-6 * tanh((sx + 0.3 * sy - 0.6 * w) / 1.5);
                const double h2 = 0.25 * fwhm * fwhm, s = g * b;
                const double lo = wf - (D - s), hi = wf - (D + s);
                cv[(size_t)y * cw + x] = p * (1 - C * (h2 / (lo * lo + h2) + h2 / (hi * hi + h2)));
                if (f == 0 && x >= pad && y >= pad && x < pad + w && y < pad + h) {
                    truth->data[(size_t)(y - pad) * w + x - pad] = b;
                    pl->data[(size_t)(y - pad) * w + x - pad] = p;
                }
            }
        for (int y = 0; y < ch; y++)
            for (int x = 0; x < cw; x++) {
                double v = 0;
                for (int i = -r; i <= r; i++)
                    if (x + i >= 0 && x + i < cw) v += k1[i + r] * cv[(size_t)y * cw + x + i];
                tmp[(size_t)y * cw + x] = v;
            }
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                double v = 0;
                for (int i = -r; i <= r; i++)
                    if (y + pad + i >= 0 && y + pad + i < ch)
                        v += k1[i + r] * tmp[(size_t)(y + pad + i) * cw + x + pad];
                pix[(size_t)f * w * h + (size_t)y * w + x] = (float)(v + gauss());
            }
    }
    free(cv);
    free(tmp);
    free(k1);
    if (fclose(ff)) return 1;
    return write_sweep(a, w, h, nf, pix, truth, pl);
}

static int make_pages(char **a)
{
    const int n = atoi(a[1]);
    uint16_t *pix = malloc((size_t)n * 48 * sizeof(uint16_t));
    for (int k = 0; k < n * 48; k++) pix[k] = (uint16_t)(100 + k % 977);
    int bad = write_tiff(a[0], 8, 6, n, 16, pix);
    free(pix);
    return bad;
}

static int compare(int argc, char **a)
{
    svp_image *est = NULL, *truth = NULL, *sigma = NULL;
    int rc = 1;
    if (svp_image_read(a[0], &est) || svp_image_read(a[1], &truth) ||
        (argc > 5 && svp_image_read(a[5], &sigma))) {
        fprintf(stderr, "%s\n", svp_last_error());
        goto done;
    }
    const double scale = atof(a[2]), mean_tol = atof(a[3]), max_tol = atof(a[4]);
    const size_t n = (size_t)est->width * est->height;
    if (truth->width != est->width || truth->height != est->height) {
        fprintf(stderr, "size mismatch\n");
        goto done;
    }
    double mean = 0, worst = 0, pull = 0;
    for (size_t p = 0; p < n; p++) {
        double d = est->data[p] / scale - truth->data[p];
        if (!isfinite(d)) {
            printf("pixel %zu is not finite\n", p);
            goto done;
        }
        mean += fabs(d) / (double)n;
        worst = fmax(worst, fabs(d));
        if (sigma) pull += pow((est->data[p] - scale * truth->data[p]) / sigma->data[p], 2) / (double)n;
    }
    pull = sqrt(pull);
    printf("mean |error| %.4g, max %.4g (tolerances %g, %g)", mean, worst, mean_tol, max_tol);
    if (sigma) printf(", rms (est - truth) / sigma %.3f", pull);
    printf("\n");
    rc = !(mean <= mean_tol && worst <= max_tol && (!sigma || (pull > 0.8 && pull < 1.25)));
done: /* freed, so the sanitizer build's leak check passes */
    svp_image_free(est);
    svp_image_free(truth);
    svp_image_free(sigma);
    return rc;
}

/* IN (a stack) with frames K .. K + N − 1 set to NaN at every pixel (drop = 0), or without
 * frame K (drop = 1), as a float64 .npy OUT */
static int edit_frames(char **a, int n_nan, int drop)
{
    svp_stack *st = NULL;
    if (svp_stack_read(a[0], &st) != SVP_OK) {
        fprintf(stderr, "%s\n", svp_last_error());
        return 1;
    }
    const int k = atoi(a[2]);
    int rc = k < 0 || k + (drop ? 1 : n_nan) > st->n_frames || n_nan < 1;
    if (!rc && drop) {
        svp_image *gone = st->frame[k];
        for (int f = k; f < st->n_frames - 1; f++) st->frame[f] = st->frame[f + 1];
        st->frame[--st->n_frames] = gone; /* freed with the stack */
    } else if (!rc) {
        for (int f = k; f < k + n_nan; f++)
            for (size_t p = 0; p < (size_t)st->width * st->height; p++)
                st->frame[f]->data[p] = NAN;
    }
    if (!rc)
        rc = svp_stack_write(a[1], (const svp_image *const *)st->frame, st->n_frames, 1) != SVP_OK;
    if (drop && !rc) st->n_frames++;
    svp_stack_free(st);
    return rc;
}

int main(int argc, char **argv)
{
    if (argc == 10 && !strcmp(argv[1], "stack")) return make_stack(argv + 2);
    if (argc == 4 && !strcmp(argv[1], "pages")) return make_pages(argv + 2);
    if ((argc == 5 || argc == 6) && !strcmp(argv[1], "nanframe"))
        return edit_frames(argv + 2, argc == 6 ? atoi(argv[5]) : 1, 0);
    if (argc == 5 && !strcmp(argv[1], "dropframe")) return edit_frames(argv + 2, 1, 1);
    if (argc == 12 && !strcmp(argv[1], "drift")) return make_drift(argv + 2);
    if (argc == 11 && !strcmp(argv[1], "blurred")) return make_blurred(argv + 2);
    if ((argc == 7 || argc == 8) && !strcmp(argv[1], "compare")) return compare(argc - 2, argv + 2);
    fprintf(stderr, "usage: see the comment at the top of odmr_cli_make.c\n");
    return 2;
}
