/* Library-internal side of the MATLAB .mat reader and writer (mat.c, through libmatio). Not
 * installed. docs/cli.md "MATLAB / QDMlab files" says which variables are read and written. */
#ifndef SVP_MAT_H
#define SVP_MAT_H

#include "svpsf.h"

#include <stddef.h>

/* Does `path` name a .mat file, "FILE.mat" or "FILE.mat:VAR" (the extension in any case)?
 * Returns 1 and splits it into file (the path without ":VAR") and var ("" without one);
 * returns 0 for any other path. A ":VAR" that is not a MATLAB variable name (a letter, then
 * letters, digits or '_', at most 63 in all) still returns 1, with *bad_var set, so that the
 * caller refuses it by name. */
int svp_io_mat_path(const char *path, char *file, size_t file_size, char *var, size_t var_size,
                    int *bad_var);

/* Reads one variable of a v5/v7 MAT-file as frames: with stack == 0 exactly one 2-D frame
 * (a 3-D variable is refused naming its frame count), with stack != 0 a 3-D variable's
 * frames, QDMlab's raw imgStackN layout, or a 2-D variable as one frame. `var` NULL or ""
 * picks the default (svpsf.h, svp_mat_read). *frames gets *n_frames new images (free each,
 * then the array with free()). info may be NULL. */
svp_status svp_io_mat_read(const char *file, const char *var, int stack, svp_image ***frames,
                           int *n_frames, svp_mat_info *info);

/* svp_image_write's .mat case: "OUT.mat" (the variable named after the file, e.g.
 * field_corrected) or "OUT.mat:VAR"; one double variable, v7 (zlib-compressed), atomic. */
svp_status svp_io_mat_write_image(const char *path, const svp_image *image, int overwrite);

#endif
