/* Cross-check of the image readers and writers against numpy, tifffile and Pillow (driven by
 * io_numpy_check.py, which writes the Python side's files and reads ours).
 *   io_numpy_check read DIR    reads every file listed in DIR/manifest.txt ("name kind" lines,
 *                              kind = float | signed | unsigned) and compares it with formula()
 *   io_numpy_check write DIR   writes DIR/out.npy, out.txt, out.csv, out.tif (float formula) and
 *                              out.png (unsigned formula, 16-bit scaled from [0, 199]), and
 *                              out_div.png / out_seq.png: colour maps of -2, -1, 0, 1, 2, NaN;
 *                              out.yaml and out.json for Python's yaml and json modules
 * Exit 0 when everything matches exactly, 1 otherwise (with a message per mismatch). */
#include "svpsf.h"
#include "io/image_io.h"
#include "io/json.h"
#include "io/yaml.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

enum { W = 13, H = 7 };

/* The image both sides compute: integers in 0..199 (unsigned) or -100..99 (signed); the float
 * variant adds quarters, exact in float32. Must match formula() in io_numpy_check.py. */
static double formula(int y, int x, const char *kind)
{
    double v = (y * 37 + x * 11) % 200;
    if (strcmp(kind, "unsigned") != 0) v -= 100;
    if (strcmp(kind, "float") == 0) v += 0.25 * (x % 4);
    return v;
}

static int check(const char *path, const char *kind)
{
    svp_image *img = NULL;
    if (svp_image_read(path, &img) != SVP_OK) {
        fprintf(stderr, "FAIL %s: %s\n", path, svp_last_error());
        return 1;
    }
    int bad = 0;
    if (img->width != W || img->height != H) {
        fprintf(stderr, "FAIL %s: size %d x %d, expected %d x %d\n", path, img->width, img->height,
                W, H);
        bad = 1;
    }
    for (int y = 0; !bad && y < H; y++)
        for (int x = 0; !bad && x < W; x++)
            if (img->data[y * W + x] != formula(y, x, kind)) {
                fprintf(stderr, "FAIL %s: pixel (x %d, y %d) = %.17g, expected %.17g\n", path, x, y,
                        img->data[y * W + x], formula(y, x, kind));
                bad = 1;
            }
    if (!bad) printf("ok   %s (%s)\n", path, kind);
    svp_image_free(img);
    return bad;
}

int main(int argc, char **argv)
{
    if (argc != 3) {
        fprintf(stderr, "usage: %s read|write DIR\n", argv[0]);
        return 2;
    }
    char path[4096];
    if (!strcmp(argv[1], "read")) {
        snprintf(path, sizeof path, "%s/manifest.txt", argv[2]);
        FILE *f = fopen(path, "r");
        if (!f) {
            fprintf(stderr, "cannot open %s\n", path);
            return 2;
        }
        char name[256], kind[32];
        int failures = 0, count = 0;
        while (fscanf(f, "%255s %31s", name, kind) == 2) {
            snprintf(path, sizeof path, "%s/%s", argv[2], name);
            failures += check(path, kind);
            count++;
        }
        fclose(f);
        printf("%d of %d Python-written files read exactly\n", count - failures, count);
        return failures || count == 0 ? 1 : 0;
    }
    if (!strcmp(argv[1], "write")) {
        svp_image *fl = NULL, *un = NULL;
        if (svp_image_new(W, H, &fl) || svp_image_new(W, H, &un)) return 2;
        for (int y = 0; y < H; y++)
            for (int x = 0; x < W; x++) {
                fl->data[y * W + x] = formula(y, x, "float");
                un->data[y * W + x] = formula(y, x, "unsigned");
            }
        const char *names[] = {"out.npy", "out.txt", "out.csv", "out.tif"};
        for (int i = 0; i < 4; i++) {
            snprintf(path, sizeof path, "%s/%s", argv[2], names[i]);
            if (svp_image_write(path, fl, SVP_FORMAT_AUTO, 1) != SVP_OK) {
                fprintf(stderr, "FAIL writing %s: %s\n", path, svp_last_error());
                return 1;
            }
        }
        snprintf(path, sizeof path, "%s/out.png", argv[2]);
        if (svp_image_write(path, un, SVP_FORMAT_PNG16, 1) != SVP_OK) {
            fprintf(stderr, "FAIL writing %s: %s\n", path, svp_last_error());
            return 1;
        }
        /* colour maps for figures: values -2, -1, 0, 1, 2, NaN (auto range) */
        svp_image *row = NULL;
        if (svp_image_new(6, 1, &row)) return 2;
        for (int i = 0; i < 5; i++) row->data[i] = i - 2.0;
        row->data[5] = NAN;
        for (int diverging = 0; diverging <= 1; diverging++) {
            snprintf(path, sizeof path, "%s/%s", argv[2],
                     diverging ? "out_div.png" : "out_seq.png");
            if (svp_io_write_colormap_png(path, row, 0, 0, diverging, 1) != SVP_OK) {
                fprintf(stderr, "FAIL writing %s: %s\n", path, svp_last_error());
                return 1;
            }
        }
        svp_image_free(row);
        /* YAML and JSON for Python's yaml and json modules */
        const double grid[3] = {0.1, -2e-300, 1.0 / 3.0};
        svp_yaml_writer *yw = NULL;
        if (svp_yaml_writer_new(&yw)) return 2;
        svp_yaml_write_comment(yw, "written by io_numpy_check");
        svp_yaml_begin_mapping(yw);
        svp_yaml_write_key_number(yw, "pixel_um", 0.1);
        svp_yaml_write_key_string(yw, "text", "a: \"b\" # c\n\\ yes");
        svp_yaml_write_key_string(yw, "word", "yes");
        svp_yaml_write_key_number_list(yw, "grid", grid, 3);
        svp_yaml_write_key(yw, "regions");
        svp_yaml_begin_sequence(yw);
        svp_yaml_begin_mapping(yw);
        svp_yaml_write_key_int(yw, "label", 2);
        svp_yaml_write_key_bool(yw, "metal", 1);
        svp_yaml_end_mapping(yw);
        svp_yaml_end_sequence(yw);
        svp_yaml_end_mapping(yw);
        snprintf(path, sizeof path, "%s/out.yaml", argv[2]);
        if (svp_yaml_writer_write_file(yw, path, 1) != SVP_OK) {
            fprintf(stderr, "FAIL writing %s: %s\n", path, svp_last_error());
            return 1;
        }
        svp_yaml_writer_free(yw);
        svp_json *js = NULL;
        if (svp_json_new(&js)) return 2;
        svp_json_begin_object(js);
        svp_json_key_string(js, "text", "a \"b\" \\ \n \x01 \xc2\xb5m");
        svp_json_key_number(js, "nan", NAN);
        svp_json_key(js, "grid");
        svp_json_number_array(js, grid, 3);
        svp_json_end_object(js);
        snprintf(path, sizeof path, "%s/out.json", argv[2]);
        if (svp_json_write_file(js, path, 1) != SVP_OK) {
            fprintf(stderr, "FAIL writing %s: %s\n", path, svp_last_error());
            return 1;
        }
        svp_json_free(js);
        svp_image_free(fl);
        svp_image_free(un);
        return 0;
    }
    fprintf(stderr, "usage: %s read|write DIR\n", argv[0]);
    return 2;
}
