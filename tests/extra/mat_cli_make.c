/* Inputs and checks for tests/extra/mat_cli_test.sh:
 *   mat_cli_make qdm DIR W H      QDMlab's files written with libmatio: DIR/Bz_uc0.mat (Bz in
 *                                 tesla, Bt, h, step, corners, newLED; compressed as MATLAB's
 *                                 save), DIR/B111dataToPlot.mat (B111ferro, B111para in gauss,
 *                                 negDiff, posDiff, ledImg), and the same Bz and LED image as
 *                                 DIR/Bz.npy, DIR/led.npy
 *   mat_cli_make compare A B      exit 0 when images A and B (any format svpsf reads) are
 *                                 equal value for value (NaN equal to NaN)
 *   mat_cli_make info FILE[:VAR]  prints "variable W H pixel_um standoff_um" (svp_mat_read) */
#include "svpsf.h"

#include <math.h>
#include <matio.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int put(mat_t *mat, const char *name, const double *rowmajor, size_t rows, size_t cols)
{
    double *col = malloc(rows * cols * sizeof *col);
    if (!col) return 1;
    for (size_t r = 0; r < rows; r++)
        for (size_t c = 0; c < cols; c++) col[r + rows * c] = rowmajor[r * cols + c];
    size_t dims[2] = {rows, cols};
    matvar_t *v = Mat_VarCreate(name, MAT_C_DOUBLE, MAT_T_DOUBLE, 2, dims, col, 0);
    int rc = !v || Mat_VarWrite(mat, v, MAT_COMPRESSION_ZLIB) != 0;
    Mat_VarFree(v);
    free(col);
    return rc;
}

static int qdm(const char *dir, int w, int h)
{
    svp_image *bz, *led, *other;
    if (svp_image_new(w, h, &bz) || svp_image_new(w, h, &led) || svp_image_new(w, h, &other))
        return 1;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double dx = x - 0.6 * w, dy = y - 0.4 * h;
            bz->data[y * w + x] = 2e-6 * exp(-(dx * dx + dy * dy) / 18.0) * (1 + 0.01 * x) +
                                  1e-8 * y;
            led->data[y * w + x] = 150 + 40 * sin(x / 5.0) * cos(y / 7.0) + 0.5 * y;
            other->data[y * w + x] = 1e4 * bz->data[y * w + x]; /* gauss */
        }
    char path[1024];
    snprintf(path, sizeof path, "%s/Bz_uc0.mat", dir);
    mat_t *mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    if (!mat) return 1;
    double h_m = 5e-6, step_m = 4.7e-6, corners[4] = {1, 1, (double)h, (double)w};
    int rc = put(mat, "Bz", bz->data, (size_t)h, (size_t)w) ||
             put(mat, "Bt", other->data, (size_t)h, (size_t)w) ||
             put(mat, "h", &h_m, 1, 1) || put(mat, "step", &step_m, 1, 1) ||
             put(mat, "corners", corners, 2, 2) ||
             put(mat, "newLED", led->data, (size_t)h, (size_t)w);
    Mat_Close(mat);
    snprintf(path, sizeof path, "%s/B111dataToPlot.mat", dir);
    mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    if (!mat) return 1;
    rc = rc || put(mat, "negDiff", other->data, (size_t)h, (size_t)w) ||
         put(mat, "posDiff", other->data, (size_t)h, (size_t)w) ||
         put(mat, "B111ferro", other->data, (size_t)h, (size_t)w) ||
         put(mat, "B111para", bz->data, (size_t)h, (size_t)w) ||
         put(mat, "ledImg", led->data, (size_t)h, (size_t)w);
    Mat_Close(mat);
    snprintf(path, sizeof path, "%s/Bz.npy", dir);
    rc = rc || svp_image_write(path, bz, SVP_FORMAT_NPY, 1);
    snprintf(path, sizeof path, "%s/led.npy", dir);
    rc = rc || svp_image_write(path, led, SVP_FORMAT_NPY, 1);
    svp_image_free(bz);
    svp_image_free(led);
    svp_image_free(other);
    return rc;
}

static int compare(const char *a_path, const char *b_path)
{
    svp_image *a = NULL, *b = NULL;
    if (svp_image_read(a_path, &a) || svp_image_read(b_path, &b)) {
        fprintf(stderr, "%s\n", svp_last_error());
        return 2;
    }
    if (a->width != b->width || a->height != b->height) {
        fprintf(stderr, "%s is %d x %d, %s is %d x %d\n", a_path, a->width, a->height, b_path,
                b->width, b->height);
        return 1;
    }
    size_t n = (size_t)a->width * a->height, diff = 0;
    for (size_t i = 0; i < n; i++)
        if (!(a->data[i] == b->data[i] || (isnan(a->data[i]) && isnan(b->data[i])))) diff++;
    if (diff) fprintf(stderr, "%s and %s differ at %zu of %zu pixels\n", a_path, b_path, diff, n);
    else printf("%s == %s (%d x %d, every value)\n", a_path, b_path, a->width, a->height);
    svp_image_free(a);
    svp_image_free(b);
    return diff != 0;
}

int main(int argc, char **argv)
{
    if (argc == 5 && !strcmp(argv[1], "qdm")) return qdm(argv[2], atoi(argv[3]), atoi(argv[4]));
    if (argc == 4 && !strcmp(argv[1], "compare")) return compare(argv[2], argv[3]);
    if (argc == 3 && !strcmp(argv[1], "info")) {
        svp_image *img = NULL;
        svp_mat_info info;
        if (svp_mat_read(argv[2], NULL, &img, &info)) {
            fprintf(stderr, "%s\n", svp_last_error());
            return 1;
        }
        printf("%s %d %d %.17g %.17g\n", info.variable, img->width, img->height, info.pixel_um,
               info.standoff_um);
        svp_image_free(img);
        return 0;
    }
    fprintf(stderr, "usage: see the comment at the top of mat_cli_make.c\n");
    return 2;
}
