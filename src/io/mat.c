/* MATLAB .mat files through libmatio: the v5/v7 MAT-files MATLAB's save writes by default and
 * QDMlab's maps are (B111dataToPlot.mat, Bz_uc0.mat, the raw run_0000N.mat stacks). Which
 * variables are read and written: docs/cli.md "MATLAB / QDMlab files"; limits:
 * docs/reliability.md.
 *
 * Only files with a v5 header (128 bytes, version 0x0100, "IM"/"MI") reach libmatio: v7.3
 * (HDF5) and v4 files are refused from the header before any parser sees them. Before a
 * variable's data is read, its class, rank and size are checked against the file: a variable
 * may not claim more elements than the file could hold (one byte per element stored plainly,
 * 1032 per byte compressed: deflate's largest ratio), so a small file cannot make libmatio
 * allocate gigabytes. libmatio's log goes to svp_last_error(), never to the terminal. */
#include "mat.h"

#include "../core/internal.h"
#include "image_io.h"

#include <errno.h>
#include <limits.h>
#include <math.h>
#include <matio.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/stat.h>
#include <unistd.h>

/* Largest number of variables listed from one file (a QDMlab file has about ten). */
#define MAT_MAX_VARIABLES 4096
/* deflate's largest compression ratio (RFC 1951 blocks: 258-byte matches in 2 bits... about
 * 1032:1), bounding the elements a compressed variable of n bytes can hold. */
#define MAT_DEFLATE_MAX_RATIO 1032

/* ---- libmatio's log --------------------------------------------------------------------------- */

static _Thread_local char matio_message[256];
static pthread_once_t matio_log_once = PTHREAD_ONCE_INIT;

static void matio_log(int level, char *message)
{
    /* errors and critical messages become the reason in svpsf's message; the rest is dropped */
    if ((level & (MATIO_LOG_LEVEL_ERROR | MATIO_LOG_LEVEL_CRITICAL)) && message)
        snprintf(matio_message, sizeof matio_message, "%s", message);
}

static void matio_log_init(void) { Mat_LogInitFunc("svpsf", matio_log); }

static void matio_begin(void)
{
    pthread_once(&matio_log_once, matio_log_init);
    matio_message[0] = '\0';
}

/* " (libmatio: <message>)" when libmatio said something, else "" */
static const char *matio_reason(char *buf, size_t size)
{
    if (!matio_message[0]) return "";
    snprintf(buf, size, " (libmatio: %s)", matio_message);
    return buf;
}

/* ---- paths ------------------------------------------------------------------------------------- */

static int is_matlab_name(const char *s)
{
    size_t n = strlen(s);
    if (n < 1 || n > 63) return 0;
    if (!((s[0] >= 'A' && s[0] <= 'Z') || (s[0] >= 'a' && s[0] <= 'z'))) return 0;
    for (size_t i = 1; i < n; i++) {
        char c = s[i];
        if (!((c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') ||
              c == '_'))
            return 0;
    }
    return 1;
}

int svp_io_mat_path(const char *path, char *file, size_t file_size, char *var, size_t var_size,
                    int *bad_var)
{
    *bad_var = 0;
    if (!path) return 0;
    const char *slash = strrchr(path, '/');
    const char *base = slash ? slash + 1 : path;
    size_t len = strlen(path);
    /* "FILE.mat:VAR": the last ".mat:" in the file name */
    const char *split = NULL;
    for (const char *p = base; (p = strchr(p, ':')) != NULL; p++)
        if (p - base >= 5 && !strncasecmp(p - 4, ".mat", 4)) split = p;
    if (split) {
        size_t flen = (size_t)(split - path);
        if (flen + 1 > file_size || strlen(split + 1) + 1 > var_size) {
            *bad_var = 1;
            snprintf(file, file_size, "%.*s", (int)(file_size ? file_size - 1 : 0), path);
            if (var_size) var[0] = '\0';
            return 1;
        }
        memcpy(file, path, flen);
        file[flen] = '\0';
        strcpy(var, split + 1);
        *bad_var = !is_matlab_name(var);
        return 1;
    }
    if (len - (size_t)(base - path) >= 5 && !strcasecmp(path + len - 4, ".mat")) {
        if (len + 1 > file_size) return 0;
        strcpy(file, path);
        if (var_size) var[0] = '\0';
        return 1;
    }
    return 0;
}

/* ---- the variables of a file ---------------------------------------------------------------- */

typedef struct var_info {
    char name[64];
    enum matio_classes cls;
    int is_complex, logical, compressed;
    int rank;       /* after dropping trailing dimensions of 1 (at least 2) */
    size_t dims[3]; /* the first three dimensions (rank <= 3) */
    int dims_ok;    /* the dimensions' product fits size_t */
    size_t n;       /* elements */
} var_info;

typedef struct mat_file {
    const char *path;
    long long bytes;
    mat_t *mat;
    var_info *vars;
    int n_vars;
} mat_file;

static const char *class_name(enum matio_classes c)
{
    switch (c) {
    case MAT_C_EMPTY: return "empty";
    case MAT_C_CELL: return "cell array";
    case MAT_C_STRUCT: return "struct";
    case MAT_C_OBJECT: return "object";
    case MAT_C_CHAR: return "char";
    case MAT_C_SPARSE: return "sparse";
    case MAT_C_DOUBLE: return "double";
    case MAT_C_SINGLE: return "single";
    case MAT_C_INT8: return "int8";
    case MAT_C_UINT8: return "uint8";
    case MAT_C_INT16: return "int16";
    case MAT_C_UINT16: return "uint16";
    case MAT_C_INT32: return "int32";
    case MAT_C_UINT32: return "uint32";
    case MAT_C_INT64: return "int64";
    case MAT_C_UINT64: return "uint64";
    case MAT_C_FUNCTION: return "function handle";
    case MAT_C_OPAQUE: return "opaque object";
    }
    return "unknown class";
}

static size_t class_bytes(enum matio_classes c)
{
    switch (c) {
    case MAT_C_DOUBLE: return 8;
    case MAT_C_SINGLE: return 4;
    case MAT_C_INT8:
    case MAT_C_UINT8: return 1;
    case MAT_C_INT16:
    case MAT_C_UINT16: return 2;
    case MAT_C_INT32:
    case MAT_C_UINT32: return 4;
    case MAT_C_INT64:
    case MAT_C_UINT64: return 8;
    default: return 0; /* not a numeric class */
    }
}

static double element(const void *data, enum matio_classes c, size_t i)
{
    switch (c) {
    case MAT_C_DOUBLE: return ((const double *)data)[i];
    case MAT_C_SINGLE: return ((const float *)data)[i];
    case MAT_C_INT8: return ((const int8_t *)data)[i];
    case MAT_C_UINT8: return ((const uint8_t *)data)[i];
    case MAT_C_INT16: return ((const int16_t *)data)[i];
    case MAT_C_UINT16: return ((const uint16_t *)data)[i];
    case MAT_C_INT32: return ((const int32_t *)data)[i];
    case MAT_C_UINT32: return ((const uint32_t *)data)[i];
    case MAT_C_INT64: return (double)((const int64_t *)data)[i];
    case MAT_C_UINT64: return (double)((const uint64_t *)data)[i];
    default: return NAN;
    }
}

static void info_of(const matvar_t *v, var_info *out)
{
    memset(out, 0, sizeof *out);
    snprintf(out->name, sizeof out->name, "%s", v->name ? v->name : "");
    out->cls = v->class_type;
    out->is_complex = v->isComplex != 0;
    out->logical = v->isLogical != 0;
    out->compressed = v->compression != MAT_COMPRESSION_NONE;
    int rank = v->dims ? v->rank : 0;
    out->dims_ok = 1;
    out->n = 1;
    for (int i = 0; i < rank; i++) {
        size_t d = v->dims[i];
        if (d && out->n > SIZE_MAX / d)
            out->dims_ok = 0;
        else
            out->n *= d;
    }
    while (rank > 2 && v->dims[rank - 1] == 1) rank--;
    out->rank = rank;
    for (int i = 0; i < rank && i < 3; i++) out->dims[i] = v->dims[i];
}

static const var_info *find_var(const mat_file *f, const char *name)
{
    for (int i = 0; i < f->n_vars; i++)
        if (!strcmp(f->vars[i].name, name)) return &f->vars[i];
    return NULL;
}

static void mat_file_close(mat_file *f)
{
    if (f->mat) Mat_Close(f->mat);
    free(f->vars);
    f->mat = NULL;
    f->vars = NULL;
}

/* The top-level data elements after the header: each an 8-byte tag (type, byte count) and
 * its bytes (miMATRIX or miCOMPRESSED), the last ending at the end of the file.
 * libmatio reads a variable cut short as if it were whole (the missing values left as they
 * were in memory), so a file that ends inside an element is refused here. */
static svp_status check_elements(const char *path, long long bytes, int big_endian)
{
    FILE *fp = fopen(path, "rb");
    if (!fp) return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", path, strerror(errno));
    long long pos = 128;
    int index = 0;
    svp_status st = SVP_OK;
    while (pos < bytes) {
        unsigned char t[8];
        index++;
        if (bytes - pos < 8 || fseeko(fp, (off_t)pos, SEEK_SET) != 0 || fread(t, 1, 8, fp) != 8) {
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: truncated: the file ends inside the tag of data element %d (byte "
                          "%lld of %lld)",
                          path, index, pos, bytes);
            break;
        }
        uint32_t type, n;
        if (big_endian) {
            type = (uint32_t)t[0] << 24 | (uint32_t)t[1] << 16 | (uint32_t)t[2] << 8 | t[3];
            n = (uint32_t)t[4] << 24 | (uint32_t)t[5] << 16 | (uint32_t)t[6] << 8 | t[7];
        } else {
            type = (uint32_t)t[3] << 24 | (uint32_t)t[2] << 16 | (uint32_t)t[1] << 8 | t[0];
            n = (uint32_t)t[7] << 24 | (uint32_t)t[6] << 16 | (uint32_t)t[5] << 8 | t[4];
        }
        long long end = pos + 8 + (long long)n; /* n counts a plain matrix's own padding */
        (void)type;
        if (end > bytes) {
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: truncated: data element %d (at byte %lld) needs %lld bytes, the "
                          "file ends at %lld",
                          path, index, pos, end, bytes);
            break;
        }
        pos = end;
    }
    fclose(fp);
    return st;
}

/* The v5 header: 116 bytes of text, 8 of subsystem offset, version and endian indicator. */
static svp_status check_header(const char *path, long long bytes)
{
    unsigned char h[128];
    FILE *fp = fopen(path, "rb");
    if (!fp) return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", path, strerror(errno));
    size_t got = fread(h, 1, sizeof h, fp);
    fclose(fp);
    if (got < sizeof h || bytes < 128)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: not a MATLAB .mat file (shorter than the 128-byte MAT-file header)",
                        path);
    int version;
    if (h[126] == 'I' && h[127] == 'M')
        version = h[124] | h[125] << 8;
    else if (h[126] == 'M' && h[127] == 'I')
        version = h[124] << 8 | h[125];
    else
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: not a MATLAB v5/v7 .mat file (no MAT-file header; v4 files are "
                        "not read)",
                        path);
    if (version == 0x0200)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: a MATLAB v7.3 (HDF5) file: not read; svpsf reads the v5/v7 files "
                        "MATLAB's save writes by default (in MATLAB: save(FILE, ..., '-v7'))",
                        path);
    if (version != 0x0100)
        return svp_fail(SVP_ERR_FORMAT, "%s: unknown MAT-file version 0x%04x (expected 0x0100)",
                        path, (unsigned)version);
    return check_elements(path, bytes, h[126] == 'M');
}

static svp_status mat_file_open(const char *path, mat_file *f)
{
    memset(f, 0, sizeof *f);
    f->path = path;
    struct stat sb;
    if (stat(path, &sb) != 0) {
        if (errno == ENOENT || errno == ENOTDIR)
            return svp_fail(SVP_ERR_IO, "%s: no such file", path);
        return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", path, strerror(errno));
    }
    if (S_ISDIR(sb.st_mode)) return svp_fail(SVP_ERR_IO, "%s: is a directory", path);
    f->bytes = (long long)sb.st_size;
    SVP_CHECK(check_header(path, f->bytes));
    matio_begin();
    char why[300];
    f->mat = Mat_Open(path, MAT_ACC_RDONLY);
    if (!f->mat)
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot read as a MATLAB .mat file%s", path,
                        matio_reason(why, sizeof why));
    if (Mat_GetVersion(f->mat) != MAT_FT_MAT5) {
        mat_file_close(f);
        return svp_fail(SVP_ERR_FORMAT, "%s: not a MATLAB v5/v7 .mat file", path);
    }
    /* the list of variables, from their headers only */
    int cap = 0;
    matvar_t *v;
    while ((v = Mat_VarReadNextInfo(f->mat)) != NULL) {
        if (f->n_vars == MAT_MAX_VARIABLES) {
            Mat_VarFree(v);
            mat_file_close(f);
            return svp_fail(SVP_ERR_FORMAT, "%s: more than %d variables", path,
                            MAT_MAX_VARIABLES);
        }
        if (f->n_vars == cap) {
            int bigger = cap ? 2 * cap : 16;
            var_info *vars = realloc(f->vars, (size_t)bigger * sizeof *vars);
            if (!vars) {
                Mat_VarFree(v);
                mat_file_close(f);
                return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
            }
            f->vars = vars;
            cap = bigger;
        }
        info_of(v, &f->vars[f->n_vars]);
        if (f->vars[f->n_vars].name[0]) f->n_vars++;
        Mat_VarFree(v);
    }
    return SVP_OK;
}

/* "Bz (300 x 480 double), step (1 x 1 double), ..." into buf */
static const char *var_list(const mat_file *f, char *buf, size_t size)
{
    size_t at = 0;
    buf[0] = '\0';
    if (f->n_vars == 0) {
        snprintf(buf, size, "none");
        return buf;
    }
    for (int i = 0; i < f->n_vars && at + 1 < size; i++) {
        const var_info *v = &f->vars[i];
        char dims[96] = "";
        size_t d = 0;
        for (int k = 0; k < v->rank && k < 3 && d + 1 < sizeof dims; k++)
            d += (size_t)snprintf(dims + d, sizeof dims - d, "%s%zu", k ? " x " : "", v->dims[k]);
        if (v->rank > 3 && d + 1 < sizeof dims) snprintf(dims + d, sizeof dims - d, " x ...");
        int n = snprintf(buf + at, size - at, "%s%s (%s %s%s)", i ? ", " : "", v->name, dims,
                         v->is_complex ? "complex " : "",
                         v->logical ? "logical" : class_name(v->cls));
        if (n < 0 || (size_t)n >= size - at) {
            /* out of room: end with "..." */
            if (size >= 4) strcpy(buf + size - 4, "...");
            break;
        }
        at += (size_t)n;
    }
    return buf;
}

/* Why a variable cannot be read as numbers, or NULL when it can (shape checked elsewhere). */
static const char *not_numeric(const var_info *v)
{
    if (v->cls == MAT_C_SPARSE) return "a sparse matrix (save it with full(...))";
    if (v->cls == MAT_C_CELL) return "a cell array";
    if (v->cls == MAT_C_STRUCT) return "a struct";
    if (v->cls == MAT_C_CHAR) return "text (char)";
    if (!class_bytes(v->cls)) return "not a numeric array";
    if (v->is_complex) return "complex";
    return NULL;
}

static int is_numeric_real(const var_info *v) { return !not_numeric(v) && v->dims_ok; }

/* Reads a numeric real scalar variable into *value. */
static svp_status read_scalar(mat_file *f, const char *name, double *value)
{
    matio_begin();
    char why[300];
    matvar_t *m = Mat_VarRead(f->mat, name);
    if (!m || !m->data || m->isComplex || !class_bytes(m->class_type) ||
        m->nbytes < class_bytes(m->class_type)) {
        if (m) Mat_VarFree(m);
        return svp_fail(SVP_ERR_FORMAT, "%s: variable %s cannot be read%s", f->path, name,
                        matio_reason(why, sizeof why));
    }
    *value = element(m->data, m->class_type, 0);
    Mat_VarFree(m);
    return SVP_OK;
}

/* The optional scalar `name`: *present = 0 when absent or not a real numeric scalar. */
static svp_status optional_scalar(mat_file *f, const char *name, double *value, int *present)
{
    *present = 0;
    const var_info *v = find_var(f, name);
    if (!v || !is_numeric_real(v) || v->n != 1) return SVP_OK;
    SVP_CHECK(read_scalar(f, name, value));
    *present = 1;
    return SVP_OK;
}

/* The pixel size (`step`) and stand-off (`h`) of QDMlab's Bz files into info. */
static svp_status read_geometry(mat_file *f, svp_mat_info *info)
{
    double value;
    int present;
    SVP_CHECK(optional_scalar(f, "step", &value, &present));
    if (present) {
        if (!isfinite(value) || value <= 0)
            return svp_fail(SVP_ERR_FORMAT, "%s: step = %g is not a pixel size (expected > 0)",
                            f->path, value);
        /* QDMlab writes metres (4.7e-6); some of its files hold micrometres (4.68): a pixel
         * below 1 mm is taken as metres, one of 1 or more as micrometres */
        info->pixel_um = value < 1e-3 ? value * 1e6 : value;
        if (info->pixel_um < SVP_PIXEL_UM_MIN)
            return svp_fail(SVP_ERR_FORMAT, "%s: step = %g m is below the %g um a pixel may be",
                            f->path, value, SVP_PIXEL_UM_MIN);
    }
    SVP_CHECK(optional_scalar(f, "h", &value, &present));
    if (present) {
        if (!isfinite(value) || value < 0 || value > 1)
            return svp_fail(SVP_ERR_FORMAT,
                            "%s: h = %g is not a sensor-sample distance in metres", f->path,
                            value);
        info->standoff_um = value * 1e6;
    }
    return SVP_OK;
}

/* The raw QDMlab layout: imgStackN of numFreqs x (imgNumRows * imgNumCols), each row one
 * frame written row after row (pixel (r, c) of frame k at column r * imgNumCols + c). */
static svp_status raw_layout(mat_file *f, const var_info *v, long long *rows, long long *cols,
                             int *is_raw)
{
    *is_raw = 0;
    if (strncmp(v->name, "imgStack", 8) != 0 || v->rank != 2) return SVP_OK;
    double r, c;
    int have_r, have_c;
    SVP_CHECK(optional_scalar(f, "imgNumRows", &r, &have_r));
    SVP_CHECK(optional_scalar(f, "imgNumCols", &c, &have_c));
    if (!have_r || !have_c) return SVP_OK;
    if (!(r >= 1 && c >= 1 && r <= INT_MAX && c <= INT_MAX && r == floor(r) && c == floor(c)))
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: imgNumRows = %g, imgNumCols = %g is not an image size", f->path, r,
                        c);
    if ((double)v->dims[1] != r * c)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: %s is %zu x %zu but imgNumRows x imgNumCols = %.0f x %.0f = %.0f "
                        "pixels per frame",
                        f->path, v->name, v->dims[0], v->dims[1], r, c, r * c);
    *rows = (long long)r;
    *cols = (long long)c;
    *is_raw = 1;
    return SVP_OK;
}

/* The default variable: see svpsf.h (svp_mat_read). */
static const var_info *default_var(const mat_file *f, int stack)
{
    static const char *const preferred[] = {"Bz", "B111ferro", "B111para"};
    const var_info *only = NULL;
    int n_candidates = 0;
    if (stack) {
        for (int i = 0; i < f->n_vars; i++)
            if (is_numeric_real(&f->vars[i]) && f->vars[i].rank == 3) {
                only = &f->vars[i];
                n_candidates++;
            }
        if (n_candidates == 1) return only;
        if (n_candidates > 1) return NULL;
        const var_info *raw = find_var(f, "imgStack1");
        if (raw && find_var(f, "imgNumRows") && find_var(f, "imgNumCols")) return raw;
    }
    for (size_t k = 0; k < sizeof preferred / sizeof *preferred; k++) {
        const var_info *v = find_var(f, preferred[k]);
        if (v) return v;
    }
    only = NULL;
    n_candidates = 0;
    for (int i = 0; i < f->n_vars; i++) {
        const var_info *v = &f->vars[i];
        if (is_numeric_real(v) && v->rank == 2 && v->n > 1) {
            only = v;
            n_candidates++;
        }
    }
    return n_candidates == 1 ? only : NULL;
}

svp_status svp_io_mat_read(const char *file, const char *var, int stack, svp_image ***frames,
                           int *n_frames, svp_mat_info *info_out)
{
    *frames = NULL;
    *n_frames = 0;
    svp_mat_info info;
    memset(&info, 0, sizeof info);
    mat_file f;
    SVP_CHECK(mat_file_open(file, &f));
    info.n_variables = f.n_vars;
    svp_status st = SVP_OK;
    char list[1024], why[300];
    matvar_t *m = NULL;
    svp_image **out = NULL;
    int n_out = 0;

    const var_info *v;
    if (var && *var) {
        v = find_var(&f, var);
        if (!v) {
            st = svp_fail(SVP_ERR_FORMAT, "%s: no variable '%s' (the file holds: %s)", file, var,
                          var_list(&f, list, sizeof list));
            goto done;
        }
    } else {
        v = default_var(&f, stack);
        if (!v) {
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: no variable to read by default (Bz, B111ferro, B111para%s, or the "
                          "only 2-D numeric array); name one as %s:VAR (the file holds: %s)",
                          file, stack ? ", the only 3-D array, imgStack1" : "", file,
                          var_list(&f, list, sizeof list));
            goto done;
        }
    }
    snprintf(info.variable, sizeof info.variable, "%s", v->name);
    const char *bad = not_numeric(v);
    if (bad) {
        st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s is %s: expected a real numeric array",
                      file, v->name, bad);
        goto done;
    }
    if (!v->dims_ok || v->rank > 3) {
        st = svp_fail(SVP_ERR_FORMAT,
                      "%s: variable %s has %d dimensions: expected a 2-D image%s", file,
                      v->name, v->rank, stack ? " or a 3-D stack" : "");
        goto done;
    }
    if (v->n == 0) {
        if (v->rank == 3)
            st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s is empty (%zu x %zu x %zu)", file,
                          v->name, v->dims[0], v->dims[1], v->dims[2]);
        else
            st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s is empty (%zu x %zu)", file, v->name,
                          v->dims[0], v->dims[1]);
        goto done;
    }
    long long rows = (long long)v->dims[0], cols = (long long)v->dims[1], nf = 1;
    int is_raw = 0;
    if ((st = raw_layout(&f, v, &rows, &cols, &is_raw)) != SVP_OK) goto done;
    if (is_raw)
        nf = (long long)v->dims[0];
    else if (v->rank == 3)
        nf = (long long)v->dims[2];
    if (nf > 1 && !stack) {
        if (is_raw)
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: variable %s is a stack of %lld frames (QDMlab's raw layout, %lld x "
                          "%lld pixels): expected one image (a stack is read as an ODMR stack by "
                          "svp_stack_read / svpsf fit-odmr)",
                          file, v->name, nf, rows, cols);
        else
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: variable %s is a stack of %lld frames (3-D array of %zu x %zu x "
                          "%zu): expected one image (a stack is read as an ODMR stack by "
                          "svp_stack_read / svpsf fit-odmr)",
                          file, v->name, nf, v->dims[0], v->dims[1], v->dims[2]);
        goto done;
    }
    if (rows > INT_MAX || cols > INT_MAX || nf > INT_MAX) {
        st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s (%lld x %lld, %lld frames) is too large",
                      file, v->name, rows, cols, nf);
        goto done;
    }
    /* the elements must fit in the file: at least one byte each as stored, or 1/1032 byte
     * compressed (deflate's largest ratio) */
    long double room = (long double)f.bytes * (v->compressed ? MAT_DEFLATE_MAX_RATIO : 1);
    if ((long double)v->n > room) {
        st = svp_fail(SVP_ERR_FORMAT,
                      "%s: variable %s claims %zu elements, more than the file's %lld bytes can "
                      "hold (truncated or corrupt)",
                      file, v->name, v->n, f.bytes);
        goto done;
    }
    if ((st = read_geometry(&f, &info)) != SVP_OK) goto done;

    matio_begin();
    m = Mat_VarRead(f.mat, v->name);
    size_t esize = class_bytes(v->cls);
    if (!m || !m->data || m->class_type != v->cls || m->isComplex || !m->dims ||
        m->nbytes / esize < v->n) {
        st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s cannot be read (truncated or corrupt)%s",
                      file, v->name, matio_reason(why, sizeof why));
        goto done;
    }
    var_info got;
    info_of(m, &got);
    if (got.n != v->n || got.dims[0] != v->dims[0] || got.dims[1] != v->dims[1]) {
        st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s changed shape between reads (corrupt)",
                      file, v->name);
        goto done;
    }
    out = calloc((size_t)nf, sizeof *out);
    if (!out) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", file);
        goto done;
    }
    size_t plane = (size_t)rows * (size_t)cols;
    for (long long k = 0; k < nf; k++) {
        if ((st = svp_image_new((int)cols, (int)rows, &out[k])) != SVP_OK) goto done;
        n_out++;
        double *d = out[k]->data;
        if (is_raw) /* element (k, r * cols + c) of an nf x (rows * cols) column-major array */
            for (long long r = 0; r < rows; r++)
                for (long long c = 0; c < cols; c++)
                    d[r * cols + c] = element(m->data, v->cls,
                                              (size_t)k + (size_t)nf * ((size_t)r * (size_t)cols +
                                                                        (size_t)c));
        else /* element (r, c, k) of a rows x cols x nf column-major array */
            for (long long r = 0; r < rows; r++)
                for (long long c = 0; c < cols; c++)
                    d[r * cols + c] =
                        element(m->data, v->cls, (size_t)r + (size_t)rows * (size_t)c + plane * (size_t)k);
    }
    *frames = out;
    *n_frames = (int)nf;
    out = NULL;
    if (info_out) *info_out = info;
done:
    if (out) {
        for (int i = 0; i < n_out; i++) svp_image_free(out[i]);
        free(out);
    }
    if (m) Mat_VarFree(m);
    mat_file_close(&f);
    return st;
}

/* ---- public reading --------------------------------------------------------------------------- */

/* Splits an optional ":VAR" off path into file/var (a variable argument wins over it). */
static svp_status split_path(const char *path, const char *variable, char *file, size_t fsize,
                             char *var, size_t vsize)
{
    int bad = 0;
    if (!svp_io_mat_path(path, file, fsize, var, vsize, &bad)) {
        if (strlen(path) + 1 > fsize) return svp_fail(SVP_ERR_INVALID, "%s: path too long", path);
        strcpy(file, path);
        var[0] = '\0';
    } else if (bad) {
        return svp_fail(SVP_ERR_INVALID,
                        "%s: '%s' is not a MATLAB variable name (a letter, then letters, digits "
                        "or '_', at most 63)",
                        path, strrchr(path, ':') + 1);
    }
    if (variable && *variable) {
        if (!is_matlab_name(variable))
            return svp_fail(SVP_ERR_INVALID, "%s: '%s' is not a MATLAB variable name", path,
                            variable);
        snprintf(var, vsize, "%s", variable);
    }
    return SVP_OK;
}

svp_status svp_mat_read(const char *path, const char *variable, svp_image **out,
                        svp_mat_info *info)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_mat_read: out is NULL");
    *out = NULL;
    if (!path || !*path) return svp_fail(SVP_ERR_INVALID, "svp_mat_read: no path given");
    char file[PATH_MAX], var[64];
    SVP_CHECK(split_path(path, variable, file, sizeof file, var, sizeof var));
    svp_image **frames = NULL;
    int n = 0;
    SVP_CHECK(svp_io_mat_read(file, var, 0, &frames, &n, info));
    *out = frames[0];
    free(frames);
    return SVP_OK;
}

svp_status svp_mat_read_stack(const char *path, const char *variable, svp_stack **out,
                              svp_mat_info *info)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_mat_read_stack: out is NULL");
    *out = NULL;
    if (!path || !*path) return svp_fail(SVP_ERR_INVALID, "svp_mat_read_stack: no path given");
    char file[PATH_MAX], var[64];
    SVP_CHECK(split_path(path, variable, file, sizeof file, var, sizeof var));
    svp_stack *s = calloc(1, sizeof *s);
    if (!s) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
    svp_status st = svp_io_mat_read(file, var, 1, &s->frame, &s->n_frames, info);
    if (st != SVP_OK) {
        free(s);
        return st;
    }
    s->width = s->frame[0]->width;
    s->height = s->frame[0]->height;
    *out = s;
    return SVP_OK;
}

/* ---- writing ----------------------------------------------------------------------------------- */

/* The bytes of a whole file (the writer's temporary file). */
static svp_status slurp(const char *path, unsigned char **bytes, size_t *size)
{
    *bytes = NULL;
    *size = 0;
    FILE *fp = fopen(path, "rb");
    if (!fp) return svp_fail(SVP_ERR_IO, "%s: cannot read back (%s)", path, strerror(errno));
    struct stat sb;
    if (fstat(fileno(fp), &sb) != 0 || sb.st_size < 0) {
        fclose(fp);
        return svp_fail(SVP_ERR_IO, "%s: cannot read back", path);
    }
    size_t n = (size_t)sb.st_size;
    unsigned char *b = malloc(n ? n : 1);
    if (!b) {
        fclose(fp);
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
    }
    size_t got = fread(b, 1, n, fp);
    fclose(fp);
    if (got != n) {
        free(b);
        return svp_fail(SVP_ERR_IO, "%s: cannot read back", path);
    }
    *bytes = b;
    *size = n;
    return SVP_OK;
}

/* One double variable rows x cols (column-major, as MATLAB holds it) into mat. */
static svp_status write_var(mat_t *mat, const char *path, const char *name, const double *data,
                            size_t rows, size_t cols)
{
    size_t dims[2] = {rows, cols};
    char why[300];
    matio_begin();
    matvar_t *v = Mat_VarCreate(name, MAT_C_DOUBLE, MAT_T_DOUBLE, 2, dims, (void *)data,
                                MAT_F_DONT_COPY_DATA);
    if (!v)
        return svp_fail(SVP_ERR_IO, "%s: cannot write variable %s%s", path, name,
                        matio_reason(why, sizeof why));
    int rc = Mat_VarWrite(mat, v, MAT_COMPRESSION_ZLIB);
    Mat_VarFree(v); /* MAT_F_DONT_COPY_DATA: the data stay ours */
    if (rc != 0)
        return svp_fail(SVP_ERR_IO, "%s: cannot write variable %s%s", path, name,
                        matio_reason(why, sizeof why));
    return SVP_OK;
}

svp_status svp_mat_write(const char *path, int n, const char *const *names,
                         const svp_image *const *images, double pixel_um, int overwrite)
{
    if (!path || !*path) return svp_fail(SVP_ERR_INVALID, "svp_mat_write: no path given");
    if (n < 1 || !names || !images)
        return svp_fail(SVP_ERR_INVALID, "%s: no variables to write", path);
    if (!(pixel_um == 0 || (isfinite(pixel_um) && pixel_um >= SVP_PIXEL_UM_MIN)))
        return svp_fail(SVP_ERR_INVALID, "%s: pixel size %g um (expected 0 for none, or >= %g)",
                        path, pixel_um, SVP_PIXEL_UM_MIN);
    for (int i = 0; i < n; i++) {
        if (!names[i] || !is_matlab_name(names[i]))
            return svp_fail(SVP_ERR_INVALID,
                            "%s: '%s' is not a MATLAB variable name (a letter, then letters, "
                            "digits or '_', at most 63)",
                            path, names[i] ? names[i] : "(null)");
        if (pixel_um > 0 && !strcmp(names[i], "step"))
            return svp_fail(SVP_ERR_INVALID,
                            "%s: variable 'step' would be written twice (it holds the pixel size)",
                            path);
        for (int j = 0; j < i; j++)
            if (!strcmp(names[i], names[j]))
                return svp_fail(SVP_ERR_INVALID, "%s: variable '%s' given twice", path,
                                names[i]);
        const svp_image *im = images[i];
        if (!im || !im->data || im->width < 1 || im->height < 1)
            return svp_fail(SVP_ERR_INVALID, "%s: no image for variable %s", path, names[i]);
    }
    /* libmatio writes to a path: a hidden temporary file beside the output, read back and
     * written atomically like every other output (svp_io_atomic_write_bytes) */
    const char *slash = strrchr(path, '/');
    size_t folder_len = slash ? (size_t)(slash - path) + 1 : 0;
    size_t tsize = strlen(path) + 24;
    char *tmp = malloc(tsize);
    if (!tmp) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
    snprintf(tmp, tsize, "%.*s.%s.matioXXXXXX", (int)folder_len, path, path + folder_len);
    int fd = mkstemp(tmp);
    if (fd < 0) {
        svp_status st = svp_fail(SVP_ERR_IO, "%s: cannot write (%s)", path, strerror(errno));
        free(tmp);
        return st;
    }
    close(fd);
    svp_status st = SVP_OK;
    double *col = NULL;
    unsigned char *bytes = NULL;
    size_t size = 0;
    char header[116], why[300];
    snprintf(header, sizeof header, "MATLAB 5.0 MAT-file, written by svpsf %s", svp_version());
    matio_begin();
    mat_t *mat = Mat_CreateVer(tmp, header, MAT_FT_MAT5);
    if (!mat) {
        st = svp_fail(SVP_ERR_IO, "%s: cannot write%s", path, matio_reason(why, sizeof why));
        goto done;
    }
    for (int i = 0; i < n && st == SVP_OK; i++) {
        const svp_image *im = images[i];
        size_t w = (size_t)im->width, h = (size_t)im->height;
        free(col);
        col = malloc(w * h * sizeof *col);
        if (!col) {
            st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
            break;
        }
        for (size_t y = 0; y < h; y++) /* row-major -> column-major */
            for (size_t x = 0; x < w; x++) col[y + h * x] = im->data[y * w + x];
        st = write_var(mat, path, names[i], col, h, w);
    }
    if (st == SVP_OK && pixel_um > 0) {
        double step = pixel_um / 1e6; /* metres, as QDMlab writes it */
        st = write_var(mat, path, "step", &step, 1, 1);
    }
    if (Mat_Close(mat) != 0 && st == SVP_OK)
        st = svp_fail(SVP_ERR_IO, "%s: cannot write%s", path, matio_reason(why, sizeof why));
    if (st == SVP_OK) st = slurp(tmp, &bytes, &size);
    if (st == SVP_OK) st = svp_io_atomic_write_bytes(path, bytes, size, overwrite);
done:
    unlink(tmp);
    free(tmp);
    free(col);
    free(bytes);
    return st;
}

/* svp_image_write's .mat case: "OUT.mat:VAR", or the variable named after the file
 * ("field_corrected.mat" -> field_corrected; characters MATLAB does not allow become '_', and a
 * name that does not start with a letter gets an 'x' in front). */
svp_status svp_io_mat_write_image(const char *path, const svp_image *image, int overwrite)
{
    char file[PATH_MAX], var[64];
    int bad = 0;
    if (!svp_io_mat_path(path, file, sizeof file, var, sizeof var, &bad)) {
        if (strlen(path) + 1 > sizeof file)
            return svp_fail(SVP_ERR_INVALID, "%s: path too long", path);
        strcpy(file, path);
        var[0] = '\0';
    } else if (bad) {
        return svp_fail(SVP_ERR_INVALID,
                        "%s: '%s' is not a MATLAB variable name (a letter, then letters, digits "
                        "or '_', at most 63)",
                        path, strrchr(path, ':') + 1);
    }
    if (!var[0]) {
        const char *slash = strrchr(file, '/');
        const char *base = slash ? slash + 1 : file;
        const char *dot = strrchr(base, '.');
        size_t len = dot && dot > base ? (size_t)(dot - base) : strlen(base);
        size_t k = 0;
        if (!len || !((base[0] >= 'A' && base[0] <= 'Z') || (base[0] >= 'a' && base[0] <= 'z')))
            var[k++] = 'x';
        for (size_t i = 0; i < len && k < 63; i++) {
            char c = base[i];
            int ok = (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9');
            var[k++] = ok ? c : '_';
        }
        var[k] = '\0';
    }
    const char *names[1] = {var};
    const svp_image *images[1] = {image};
    return svp_mat_write(file, 1, names, images, 0, overwrite);
}
