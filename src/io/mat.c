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
#include <zlib.h>

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
    long long pos, size; /* the variable's data element in the file: offset and bytes */
} var_info;

typedef struct mat_file {
    const char *path;
    long long bytes;
    int big_endian;
    mat_t *mat;     /* libmatio on the extract (extract_vars), NULL before */
    char *extract;  /* that file's path */
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

/* Bytes of one value of a stored data type (miINT8 ... miUINT64), 0 for other types. */
static size_t type_bytes(uint32_t t)
{
    switch (t) {
    case MAT_T_INT8:
    case MAT_T_UINT8: return 1;
    case MAT_T_INT16:
    case MAT_T_UINT16: return 2;
    case MAT_T_INT32:
    case MAT_T_UINT32:
    case MAT_T_SINGLE: return 4;
    case MAT_T_DOUBLE:
    case MAT_T_INT64:
    case MAT_T_UINT64: return 8;
    default: return 0;
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

static const var_info *find_var(const mat_file *f, const char *name)
{
    for (int i = 0; i < f->n_vars; i++)
        if (!strcmp(f->vars[i].name, name)) return &f->vars[i];
    return NULL;
}

static void mat_file_close(mat_file *f)
{
    if (f->mat) Mat_Close(f->mat);
    if (f->extract) {
        unlink(f->extract);
        free(f->extract);
    }
    free(f->vars);
    f->mat = NULL;
    f->extract = NULL;
    f->vars = NULL;
}

/* ---- the file's structure, checked before libmatio sees any of it ------------------------------
 * A v5 MAT-file is a 128-byte header and a sequence of data elements, each an 8-byte tag (type,
 * byte count) and its bytes: miMATRIX (a variable) or miCOMPRESSED (a zlib stream holding one
 * miMATRIX). A variable starts with sub-elements: array flags (class, complex, logical), the
 * dimensions (int32), the name, then the data. svpsf reads these headers itself (inflating
 * the start of a compressed variable) to list the variables and check every count against the
 * bytes that hold it; only the variables it reads are copied, unchanged, into a private
 * MAT-file that libmatio then reads. libmatio never parses a variable svpsf does not read (cell
 * arrays, structs, objects), and never an element whose counts do not fit. */

/* Enough inflated bytes for the tag, flags, up to 32 dimensions, a 63-byte name and the data
 * tag. */
#define MAT_HEAD_BYTES 512
#define MAT_MAX_RANK 32

static uint32_t get_u32(const unsigned char *p, int big)
{
    return big ? (uint32_t)p[0] << 24 | (uint32_t)p[1] << 16 | (uint32_t)p[2] << 8 | p[3]
               : (uint32_t)p[3] << 24 | (uint32_t)p[2] << 16 | (uint32_t)p[1] << 8 | p[0];
}

/* The start of element `index` (n bytes at pos + 8): for miMATRIX its first bytes, for
 * miCOMPRESSED the first bytes inflated. *head gets the matrix's sub-elements (after its own
 * tag), *head_n their count, *total the bytes the matrix claims. */
static svp_status element_head(const mat_file *f, FILE *fp, int index, long long pos,
                               uint32_t type, uint32_t n, unsigned char *head, size_t *head_n,
                               uint64_t *total)
{
    *head_n = 0;
    *total = n;
    if (type == MAT_T_MATRIX) {
        size_t want = n < MAT_HEAD_BYTES ? n : MAT_HEAD_BYTES;
        if (fseeko(fp, (off_t)(pos + 8), SEEK_SET) != 0 || fread(head, 1, want, fp) != want)
            return svp_fail(SVP_ERR_IO, "%s: read error", f->path);
        *head_n = want;
        return SVP_OK;
    }
    /* miCOMPRESSED: inflate until the matrix tag and MAT_HEAD_BYTES are out, or the stream or
     * the element ends */
    unsigned char out[8 + MAT_HEAD_BYTES], in[4096];
    z_stream z;
    memset(&z, 0, sizeof z);
    if (inflateInit(&z) != Z_OK) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", f->path);
    z.next_out = out;
    z.avail_out = sizeof out;
    uint64_t left = n;
    int rc = Z_OK;
    if (fseeko(fp, (off_t)(pos + 8), SEEK_SET) != 0) rc = Z_ERRNO;
    while (rc == Z_OK && z.avail_out > 0 && left > 0) {
        size_t chunk = left < sizeof in ? (size_t)left : sizeof in;
        if (fread(in, 1, chunk, fp) != chunk) {
            rc = Z_ERRNO;
            break;
        }
        left -= chunk;
        z.next_in = in;
        z.avail_in = (uInt)chunk;
        while (z.avail_in > 0 && z.avail_out > 0 && rc == Z_OK) rc = inflate(&z, Z_NO_FLUSH);
        if (rc == Z_BUF_ERROR) rc = Z_OK; /* needs more input */
    }
    size_t got = sizeof out - z.avail_out;
    inflateEnd(&z);
    if (rc != Z_OK && rc != Z_STREAM_END)
        return svp_fail(SVP_ERR_FORMAT, "%s: data element %d (at byte %lld): corrupt compressed "
                                        "data",
                        f->path, index, pos);
    if (got < 8)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: data element %d (at byte %lld): compressed data too short", f->path,
                        index, pos);
    if (get_u32(out, f->big_endian) != MAT_T_MATRIX)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: data element %d (at byte %lld): the compressed data is not a "
                        "variable (type %u)",
                        f->path, index, pos, get_u32(out, f->big_endian));
    *total = get_u32(out + 4, f->big_endian);
    size_t have = got - 8;
    if (have > *total) have = (size_t)*total;
    memcpy(head, out + 8, have);
    *head_n = have;
    return SVP_OK;
}

/* Parses a variable's flags, dimensions and name from its head (`total` bytes claimed), and
 * for a real numeric variable the tag of its data. *listed = 0 for an element to pass over
 * (an empty matrix element, or a name MATLAB does not give variables, as its own
 * "__function_workspace__"). */
static svp_status parse_head(const mat_file *f, int index, long long pos,
                             const unsigned char *h, size_t hn, uint64_t total, int compressed,
                             uint32_t stored, var_info *v, int *listed)
{
    const int big = f->big_endian;
    *listed = 0;
    memset(v, 0, sizeof *v);
    if (total == 0) return SVP_OK;
#define BAD(...)                                                                               \
    do {                                                                                       \
        char what_[160];                                                                       \
        snprintf(what_, sizeof what_, __VA_ARGS__);                                            \
        return svp_fail(SVP_ERR_FORMAT, "%s: data element %d (at byte %lld): %s", f->path,     \
                        index, pos, what_);                                                    \
    } while (0)
    if (hn < 24 || total < 24) BAD("too short for a variable");
    if (get_u32(h, big) != MAT_T_UINT32 || get_u32(h + 4, big) != 8) BAD("no array flags");
    uint32_t flags = get_u32(h + 8, big);
    unsigned cls = flags & 0xff;
    if (cls < MAT_C_CELL || cls > MAT_C_OPAQUE) BAD("unknown class %u", cls);
    v->cls = (enum matio_classes)cls;
    v->is_complex = (flags & MAT_F_COMPLEX) != 0;
    v->logical = (flags & MAT_F_LOGICAL) != 0;
    v->compressed = compressed;
    v->pos = pos;
    v->size = 8 + (long long)stored;
    if (cls == MAT_C_OPAQUE) { /* MATLAB objects of new classes: no dimension list */
        v->rank = 2;
        v->dims_ok = 1;
        snprintf(v->name, sizeof v->name, "(object)");
        return SVP_OK; /* not listed: nothing svpsf can read */
    }
    if (get_u32(h + 16, big) != MAT_T_INT32) BAD("no dimensions");
    uint32_t dbytes = get_u32(h + 20, big);
    if (dbytes % 4 || dbytes < 8 || dbytes > 4 * MAT_MAX_RANK)
        BAD("a dimension list of %u bytes (expected 2 to %d dimensions)", dbytes, MAT_MAX_RANK);
    size_t q = 24 + ((dbytes + 7) & ~7u);
    if (q + 8 > hn || q + 8 > total) BAD("too short for its dimensions and name");
    int rank = (int)(dbytes / 4);
    size_t dims[MAT_MAX_RANK];
    v->dims_ok = 1;
    v->n = 1;
    for (int i = 0; i < rank; i++) {
        int32_t d = (int32_t)get_u32(h + 24 + 4 * i, big);
        if (d < 0) BAD("negative dimension %d", (int)d);
        dims[i] = (size_t)d;
        if (dims[i] && v->n > SIZE_MAX / dims[i])
            v->dims_ok = 0;
        else
            v->n *= dims[i];
    }
    while (rank > 2 && dims[rank - 1] == 1) rank--;
    v->rank = rank;
    for (int i = 0; i < rank && i < 3; i++) v->dims[i] = dims[i];
    /* the name: small element (type and length in one word, up to 4 bytes) or miINT8 */
    uint32_t w = get_u32(h + q, big), ntype, nlen;
    size_t at;
    if (w >> 16) {
        ntype = w & 0xffff;
        nlen = w >> 16;
        at = q + 4;
        if (nlen > 4) BAD("a malformed name");
    } else {
        ntype = w;
        nlen = get_u32(h + q + 4, big);
        at = q + 8;
    }
    if (ntype != MAT_T_INT8 && ntype != MAT_T_UINT8) BAD("a malformed name");
    if (nlen > 63) BAD("a name of %u bytes (MATLAB's names have at most 63)", nlen);
    if (at + nlen > hn || at + nlen > total) BAD("too short for its name");
    memcpy(v->name, h + at, nlen);
    v->name[nlen] = '\0';
    if (!is_matlab_name(v->name)) return SVP_OK;
    *listed = 1;
    /* a real numeric array: its data must be there, whole, in a numeric type */
    if (!class_bytes(v->cls) || v->is_complex) return SVP_OK;
    size_t r = nlen > 0 && (w >> 16) ? q + 8 : at + ((nlen + 7) & ~7u);
    if (r + 8 > hn || r + 8 > total) BAD("variable %s has no data", v->name);
    uint32_t dw = get_u32(h + r, big), dtype, dn;
    size_t data_at;
    if (dw >> 16) {
        dtype = dw & 0xffff;
        dn = dw >> 16;
        data_at = r + 4;
        if (dn > 4) BAD("variable %s: malformed data", v->name);
    } else {
        dtype = dw;
        dn = get_u32(h + r + 4, big);
        data_at = r + 8;
    }
    size_t tb = type_bytes(dtype);
    if (!tb) BAD("variable %s: data of type %u (expected a numeric type)", v->name, dtype);
    if (!v->dims_ok || v->n > UINT32_MAX / tb || (uint64_t)v->n * tb != dn)
        BAD("variable %s: %u bytes of data for %zu values of %zu bytes", v->name, dn, v->n, tb);
    if ((uint64_t)data_at + dn > total)
        BAD("variable %s: its data run past the variable's end", v->name);
#undef BAD
    return SVP_OK;
}

static svp_status parse_elements(mat_file *f)
{
    FILE *fp = fopen(f->path, "rb");
    if (!fp) return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", f->path, strerror(errno));
    long long pos = 128;
    int index = 0, cap = 0;
    svp_status st = SVP_OK;
    unsigned char head[MAT_HEAD_BYTES];
    while (pos < f->bytes && st == SVP_OK) {
        unsigned char t[8];
        index++;
        if (f->bytes - pos < 8 || fseeko(fp, (off_t)pos, SEEK_SET) != 0 ||
            fread(t, 1, 8, fp) != 8) {
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: truncated: the file ends inside the tag of data element %d (byte "
                          "%lld of %lld)",
                          f->path, index, pos, f->bytes);
            break;
        }
        uint32_t type = get_u32(t, f->big_endian), n = get_u32(t + 4, f->big_endian);
        long long end = pos + 8 + (long long)n;
        if (end > f->bytes) {
            /* libmatio would read a variable cut short as if it were whole */
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: truncated: data element %d (at byte %lld) needs %lld bytes, the "
                          "file ends at %lld",
                          f->path, index, pos, end, f->bytes);
            break;
        }
        if (type != MAT_T_MATRIX && type != MAT_T_COMPRESSED) {
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: data element %d (at byte %lld) has type %u (expected a variable)",
                          f->path, index, pos, type);
            break;
        }
        size_t hn = 0;
        uint64_t total = 0;
        int listed = 0;
        var_info v;
        st = element_head(f, fp, index, pos, type, n, head, &hn, &total);
        if (st == SVP_OK)
            st = parse_head(f, index, pos, head, hn, total, type == MAT_T_COMPRESSED, n, &v,
                            &listed);
        if (st == SVP_OK && listed) {
            if (find_var(f, v.name)) {
                st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s appears twice", f->path, v.name);
                break;
            }
            if (f->n_vars == MAT_MAX_VARIABLES) {
                st = svp_fail(SVP_ERR_FORMAT, "%s: more than %d variables", f->path,
                              MAT_MAX_VARIABLES);
                break;
            }
            if (f->n_vars == cap) {
                int bigger = cap ? 2 * cap : 16;
                var_info *vars = realloc(f->vars, (size_t)bigger * sizeof *vars);
                if (!vars) {
                    st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", f->path);
                    break;
                }
                f->vars = vars;
                cap = bigger;
            }
            f->vars[f->n_vars++] = v;
        }
        pos = end;
    }
    fclose(fp);
    return st;
}

/* The v5 header: 116 bytes of text, 8 of subsystem offset, version and endian indicator. */
static svp_status check_header(mat_file *f)
{
    const char *path = f->path;
    unsigned char h[128];
    FILE *fp = fopen(path, "rb");
    if (!fp) return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", path, strerror(errno));
    size_t got = fread(h, 1, sizeof h, fp);
    fclose(fp);
    if (got < sizeof h || f->bytes < 128)
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
    f->big_endian = h[126] == 'M';
    return SVP_OK;
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
    SVP_CHECK(check_header(f));
    svp_status st = parse_elements(f);
    if (st != SVP_OK) mat_file_close(f);
    return st;
}

/* Copies the header and the data elements of `want` (NULL entries skipped) into a private
 * MAT-file and opens it with libmatio (f->mat). */
static svp_status extract_vars(mat_file *f, const var_info *const *want, int n_want)
{
    const char *base = getenv("TMPDIR");
    if (!base || !*base) base = "/tmp";
    size_t len = strlen(base) + 32;
    f->extract = malloc(len);
    if (!f->extract) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", f->path);
    snprintf(f->extract, len, "%s/svpsf-mat-XXXXXX", base);
    int fd = mkstemp(f->extract);
    if (fd < 0) {
        free(f->extract);
        f->extract = NULL;
        return svp_fail(SVP_ERR_IO, "%s: cannot make a temporary file in %s (%s)", f->path,
                        base, strerror(errno));
    }
    FILE *out = fdopen(fd, "wb");
    FILE *in = fopen(f->path, "rb");
    svp_status st = SVP_OK;
    if (!out || !in) st = svp_fail(SVP_ERR_IO, "%s: cannot read (%s)", f->path, strerror(errno));
    unsigned char buf[1 << 16];
    for (int i = -1; i < n_want && st == SVP_OK; i++) {
        long long from = 0, left = 128; /* i == -1: the header */
        if (i >= 0) {
            if (!want[i]) continue;
            from = want[i]->pos;
            left = want[i]->size;
        }
        if (fseeko(in, (off_t)from, SEEK_SET) != 0) st = svp_fail(SVP_ERR_IO, "%s: read error", f->path);
        while (st == SVP_OK && left > 0) {
            size_t chunk = left < (long long)sizeof buf ? (size_t)left : sizeof buf;
            if (fread(buf, 1, chunk, in) != chunk)
                st = svp_fail(SVP_ERR_IO, "%s: read error", f->path);
            else if (fwrite(buf, 1, chunk, out) != chunk)
                st = svp_fail(SVP_ERR_IO, "%s: cannot write a temporary file (%s)", f->path,
                              strerror(errno));
            left -= (long long)chunk;
        }
    }
    if (in) fclose(in);
    if (out) {
        if (fclose(out) != 0 && st == SVP_OK)
            st = svp_fail(SVP_ERR_IO, "%s: cannot write a temporary file (%s)", f->path,
                          strerror(errno));
    } else {
        close(fd);
    }
    if (st != SVP_OK) return st;
    matio_begin();
    char why[300];
    f->mat = Mat_Open(f->extract, MAT_ACC_RDONLY);
    if (!f->mat)
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot read as a MATLAB .mat file%s", f->path,
                        matio_reason(why, sizeof why));
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

/* The first n elements of variable name (which holds at least n). */
static svp_status read_elements(mat_file *f, const char *name, double *values, size_t n)
{
    matio_begin();
    char why[300];
    matvar_t *m = Mat_VarRead(f->mat, name);
    if (!m || !m->data || m->isComplex || !class_bytes(m->class_type) ||
        m->nbytes < n * class_bytes(m->class_type)) {
        if (m) Mat_VarFree(m);
        return svp_fail(SVP_ERR_FORMAT, "%s: variable %s cannot be read%s", f->path, name,
                        matio_reason(why, sizeof why));
    }
    for (size_t i = 0; i < n; i++) values[i] = element(m->data, m->class_type, i);
    Mat_VarFree(m);
    return SVP_OK;
}

/* Reads a numeric real scalar variable into *value. */
static svp_status read_scalar(mat_file *f, const char *name, double *value)
{
    return read_elements(f, name, value, 1);
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
    const var_info *step = find_var(f, "step");
    if (step) info->step_elements = step->n > INT_MAX ? INT_MAX : (int)step->n;
    if (!present && step && is_numeric_real(step) && step->n == 2) {
        /* [dx dy]: square pixels are one pixel size, others none (svpsf's pixels are square) */
        double pair[2];
        SVP_CHECK(read_elements(f, "step", pair, 2));
        if (pair[0] == pair[1]) {
            value = pair[0];
            present = 1;
        }
    }
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

/* The variable to read (var, else the default for an image or a stack), checked to be a real
 * numeric, non-empty array of 2 (or, for a stack, 3) dimensions. */
static svp_status pick_var(mat_file *f, const char *file, const char *var, int stack,
                           const var_info **out)
{
    const var_info *v;
    svp_status st = SVP_OK;
    char list[1024];
    *out = NULL;
    if (var && *var) {
        v = find_var(f, var);
        if (!v) {
            st = svp_fail(SVP_ERR_FORMAT, "%s: no variable '%s' (the file holds: %s)", file, var,
                          var_list(f, list, sizeof list));
            return st;
        }
    } else {
        v = default_var(f, stack);
        if (!v) {
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: no variable to read by default (Bz, B111ferro, B111para%s, or the "
                          "only 2-D numeric array); name one as %s:VAR (the file holds: %s)",
                          file, stack ? ", the only 3-D array, imgStack1" : "", file,
                          var_list(f, list, sizeof list));
            return st;
        }
    }
    const char *bad = not_numeric(v);
    if (bad) {
        st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s is %s: expected a real numeric array",
                      file, v->name, bad);
        return st;
    }
    if (!v->dims_ok || v->rank > 3) {
        st = svp_fail(SVP_ERR_FORMAT,
                      "%s: variable %s has %d dimensions: expected a 2-D image%s", file,
                      v->name, v->rank, stack ? " or a 3-D stack" : "");
        return st;
    }
    if (v->n == 0) {
        if (v->rank == 3)
            st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s is empty (%zu x %zu x %zu)", file,
                          v->name, v->dims[0], v->dims[1], v->dims[2]);
        else
            st = svp_fail(SVP_ERR_FORMAT, "%s: variable %s is empty (%zu x %zu)", file, v->name,
                          v->dims[0], v->dims[1]);
        return st;
    }
    *out = v;
    return SVP_OK;
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
    char why[300];
    matvar_t *m = NULL;
    svp_image **out = NULL;
    int n_out = 0;

    const var_info *v = NULL;
    if ((st = pick_var(&f, file, var, stack, &v)) != SVP_OK) goto done;
    snprintf(info.variable, sizeof info.variable, "%s", v->name);
    {
        /* libmatio reads a private copy holding this variable and the scalars used with it */
        static const char *const extras[] = {"step", "h", "imgNumRows", "imgNumCols"};
        const var_info *want[5] = {v, NULL, NULL, NULL, NULL};
        for (int i = 0; i < 4; i++) {
            const var_info *x = find_var(&f, extras[i]);
            if (x && x != v && is_numeric_real(x) && (x->n == 1 || (i == 0 && x->n == 2)))
                want[1 + i] = x; /* scalars, and `step` as [dx dy] */
        }
        if ((st = extract_vars(&f, want, 5)) != SVP_OK) goto done;
    }
    long long rows = (long long)v->dims[0], cols = (long long)v->dims[1], nf = 1;
    int is_raw = 0;
    if ((st = raw_layout(&f, v, &rows, &cols, &is_raw)) != SVP_OK) goto done;
    if (stack && !is_raw && v->rank == 2 && strncmp(v->name, "imgStack", 8) == 0) {
        /* QDMlab's raw layout without its sizes: read as one frame, the error said "1 frame" */
        st = svp_fail(SVP_ERR_FORMAT,
                      "%s: variable %s (%zu x %zu) is QDMlab's raw stack, one frame per row, but "
                      "the file holds no %s: the frames' size is unknown (add imgNumRows and "
                      "imgNumCols, or save the stack as a 3-D array)",
                      file, v->name, v->dims[0], v->dims[1],
                      find_var(&f, "imgNumRows") ? "imgNumCols" : find_var(&f, "imgNumCols")
                                                                      ? "imgNumRows"
                                                                      : "imgNumRows / imgNumCols");
        goto done;
    }
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
    /* a compressed variable holds at most 1032 bytes per byte (deflate's largest ratio): one
     * that claims more elements is corrupt, and is refused before libmatio allocates them (a
     * plain variable's data were checked against its bytes in parse_head) */
    if (v->compressed && (long double)v->n > (long double)v->size * MAT_DEFLATE_MAX_RATIO) {
        st = svp_fail(SVP_ERR_FORMAT,
                      "%s: variable %s claims %zu elements, more than its %lld compressed bytes "
                      "can hold (corrupt)",
                      file, v->name, v->n, v->size);
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
    size_t got_n = 1;
    for (int i = 0; i < m->rank; i++) got_n *= m->dims[i];
    if (m->rank < 2 || got_n != v->n || m->dims[0] != v->dims[0] || m->dims[1] != v->dims[1]) {
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
