/* Helper of register_cli_test.sh.
 *   register_cli_make DIR         writes the test images into DIR (.npy, float64):
 *       ref.npy       a smooth textured scene (Gaussian blobs), 96 x 80
 *       mov.npy       the same scene displaced by (+2.4, −1.3) px: mov(x) = ref(x − d)
 *       ref_mask.npy  a label mask (0 bare, 1 strip, 2 disc) on the reference grid
 *       mov_mask.npy  the same layout in the moving frame
 *       other.npy     an unrelated scene; flat.npy a constant image; wide.npy 97 x 80
 *       wire_pl.npy   a PL image: a Gaussian beam, a metal wire and its pad dark on it
 *                     (absorbing 70 %, edges 4 x 4 supersampled), 2 % noise
 *       wire_mask.npy the wire's label mask (1 wire, 2 pad, 0 bare) in a moving frame
 *                     displaced by (+4.6, −2.3) px: mask(x) = label(x − d)
 *       wire_ref_mask.npy  the label mask on the PL's grid (what --warp should give)
 *       noise_a.npy, noise_b.npy  two unrelated white-noise images (no common texture)
 *   register_cli_make compare A B   prints the fraction of pixels where A and B differ and
 *                                   exits 1 when above 2 % (or the sizes differ). */
#include "svpsf.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum { W = 96, H = 80, NB = 70 };

static double rnd(uint64_t *s)
{
    uint64_t x = *s;
    x ^= x >> 12;
    x ^= x << 25;
    x ^= x >> 27;
    *s = x;
    return (double)((x * 0x2545F4914F6CDD1DULL) >> 11) * (1.0 / 9007199254740992.0);
}

typedef struct {
    double x[NB], y[NB], s[NB], a[NB];
} blobs;

static void blobs_init(blobs *b, uint64_t seed)
{
    uint64_t st = seed * 0x9E3779B97F4A7C15ULL + 7;
    for (int i = 0; i < NB; i++) {
        b->x[i] = rnd(&st) * (W + 40) - 20;
        b->y[i] = rnd(&st) * (H + 40) - 20;
        b->s[i] = 1.5 + 3 * rnd(&st);
        b->a[i] = 100 + 100 * rnd(&st);
    }
}

static double blobs_at(const blobs *b, double x, double y)
{
    double v = 10;
    for (int i = 0; i < NB; i++) {
        double dx = x - b->x[i], dy = y - b->y[i];
        v += b->a[i] * exp(-(dx * dx + dy * dy) / (2 * b->s[i] * b->s[i]));
    }
    return v;
}

static int label_at(double x, double y)
{
    if (hypot(x - 60, y - 40) < 15) return 2;
    if (fabs(x - 25) < 6) return 1;
    return 0;
}

/* An L-shaped wire (vertical from the top, then to the right) ending in a square pad. */
static int wire_at(double x, double y)
{
    if (fabs(x - 70) < 7 && fabs(y - 52) < 7) return 2;
    if (fabs(x - 30) < 2.5 && y < 54.5) return 1;
    if (fabs(y - 52) < 2.5 && x > 27.5 && x < 70) return 1;
    return 0;
}

static double gauss(uint64_t *s)
{
    double u = rnd(s), v = rnd(s);
    return sqrt(-2 * log(u + 1e-300)) * cos(2 * M_PI * v);
}

static int save(const char *dir, const char *name, const svp_image *img)
{
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    if (svp_image_write(path, img, SVP_FORMAT_NPY, 1) != SVP_OK) {
        fprintf(stderr, "register_cli_make: %s\n", svp_last_error());
        return 1;
    }
    return 0;
}

static int make(const char *dir)
{
    const double dx = 2.4, dy = -1.3;
    blobs b, o;
    blobs_init(&b, 1);
    blobs_init(&o, 2);
    svp_image *ref, *mov, *rm, *mm, *other, *flat, *wide;
    if (svp_image_new(W, H, &ref) || svp_image_new(W, H, &mov) || svp_image_new(W, H, &rm) ||
        svp_image_new(W, H, &mm) || svp_image_new(W, H, &other) || svp_image_new(W, H, &flat) ||
        svp_image_new(W + 1, H, &wide))
        return 1;
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            size_t i = (size_t)y * W + x;
            ref->data[i] = blobs_at(&b, x, y);
            mov->data[i] = blobs_at(&b, x - dx, y - dy);
            rm->data[i] = label_at(x, y);
            mm->data[i] = label_at(x - dx, y - dy);
            other->data[i] = blobs_at(&o, x, y);
            flat->data[i] = 42;
        }
    for (size_t i = 0; i < (size_t)(W + 1) * H; i++) wide->data[i] = (double)(i % 7);
    svp_image *wpl, *wmask, *wref, *na, *nb;
    if (svp_image_new(W, H, &wpl) || svp_image_new(W, H, &wmask) || svp_image_new(W, H, &wref) ||
        svp_image_new(W, H, &na) || svp_image_new(W, H, &nb))
        return 1;
    uint64_t seed = 12345;
    const double wdx = 4.6, wdy = -2.3;
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            size_t i = (size_t)y * W + x;
            double dark = 0; /* the fraction of the pixel the wire or pad covers */
            for (int sy = 0; sy < 4; sy++)
                for (int sx = 0; sx < 4; sx++)
                    dark += wire_at(x - 0.375 + 0.25 * sx, y - 0.375 + 0.25 * sy) != 0;
            dark /= 16;
            const double bx = x - 0.5 * W, by = y - 0.5 * H;
            const double beam = 1000 * exp(-(bx * bx + by * by) / (2 * 45.0 * 45.0));
            wpl->data[i] = beam * (1 - 0.7 * dark) + 20 * gauss(&seed);
            wmask->data[i] = wire_at(x - wdx, y - wdy);
            wref->data[i] = wire_at(x, y);
            na->data[i] = gauss(&seed);
            nb->data[i] = gauss(&seed);
        }
    int bad_wire = save(dir, "wire_pl.npy", wpl) || save(dir, "wire_mask.npy", wmask) ||
                   save(dir, "wire_ref_mask.npy", wref) ||
                   save(dir, "noise_a.npy", na) || save(dir, "noise_b.npy", nb);
    svp_image_free(wpl);
    svp_image_free(wmask);
    svp_image_free(wref);
    svp_image_free(na);
    svp_image_free(nb);
    if (bad_wire) return 1;
    int bad = save(dir, "ref.npy", ref) || save(dir, "mov.npy", mov) ||
              save(dir, "ref_mask.npy", rm) || save(dir, "mov_mask.npy", mm) ||
              save(dir, "other.npy", other) || save(dir, "flat.npy", flat) ||
              save(dir, "wide.npy", wide);
    svp_image_free(ref);
    svp_image_free(mov);
    svp_image_free(rm);
    svp_image_free(mm);
    svp_image_free(other);
    svp_image_free(flat);
    svp_image_free(wide);
    return bad;
}

static int compare(const char *pa, const char *pb)
{
    svp_image *a = NULL, *b = NULL;
    if (svp_image_read(pa, &a) || svp_image_read(pb, &b)) {
        fprintf(stderr, "register_cli_make: %s\n", svp_last_error());
        return 1;
    }
    if (a->width != b->width || a->height != b->height) {
        fprintf(stderr, "register_cli_make: sizes differ\n");
        return 1;
    }
    size_t n = (size_t)a->width * a->height, differ = 0;
    for (size_t i = 0; i < n; i++)
        if (a->data[i] != b->data[i]) differ++;
    double f = (double)differ / n;
    printf("%zu of %zu pixels differ (%.2f %%)\n", differ, n, 100 * f);
    svp_image_free(a);
    svp_image_free(b);
    return f > 0.02;
}

int main(int argc, char **argv)
{
    if (argc == 2) return make(argv[1]);
    if (argc == 4 && strcmp(argv[1], "compare") == 0) return compare(argv[2], argv[3]);
    fprintf(stderr, "usage: register_cli_make DIR | register_cli_make compare A B\n");
    return 2;
}
