/* FFT engine: cached FFTW plans per size, wisdom, threads, smooth sizes. */
#include "internal.h"

#include <ctype.h>
#include <errno.h>
#include <omp.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "svpsf_version.h"

/* The thread count and the plan cache are the library's only global mutable state. */
static pthread_mutex_t fft_lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_once_t fft_once = PTHREAD_ONCE_INIT;
static int fft_threads_ok;
static int n_threads; /* 0 = not set yet: all cores */
/* svp_fft_local_threads: the calling thread's plan threads (0: svp_get_threads()) */
static _Thread_local int local_threads;
static svp_fft_effort fft_effort = SVP_FFT_MEASURE;

typedef struct plan_entry {
    svp_fft_plan plan;
    int threads;
    struct plan_entry *next;
} plan_entry;
static plan_entry *plan_cache;
static svp_fft_plan_fn plan_callback; /* svp_set_fft_plan_callback */
static void *plan_callback_user;

void svp_set_fft_plan_callback(svp_fft_plan_fn callback, void *user)
{
    pthread_mutex_lock(&fft_lock);
    plan_callback = callback;
    plan_callback_user = user;
    pthread_mutex_unlock(&fft_lock);
}

/* The planning flags, and whether to try FFTW_WISDOM_ONLY first: measured plans are first
 * asked of the wisdom alone (free when it has them); only when that fails is the caller told
 * (plan_measuring) and the measuring done. Called under fft_lock. */
static unsigned plan_flags(int *wisdom_first)
{
    *wisdom_first = fft_effort == SVP_FFT_MEASURE;
    return fft_effort == SVP_FFT_MEASURE ? FFTW_MEASURE : FFTW_ESTIMATE;
}

static void plan_measuring(int ny, int nx, int single_precision)
{
    if (plan_callback) plan_callback(plan_callback_user, ny, nx, single_precision);
}

static void fft_init(void)
{
    fft_threads_ok = fftw_init_threads() != 0 && fftwf_init_threads() != 0;
}

const char *svp_version(void) { return SVPSF_VERSION; }
const char *svp_fftw_version(void) { return fftw_version; }

void svp_set_threads(int n)
{
    pthread_mutex_lock(&fft_lock);
    n_threads = n < 1 ? 1 : n;
    pthread_mutex_unlock(&fft_lock);
    omp_set_num_threads(n < 1 ? 1 : n);
}

int svp_get_threads(void)
{
    pthread_mutex_lock(&fft_lock);
    int n = n_threads;
    pthread_mutex_unlock(&fft_lock);
    return n > 0 ? n : omp_get_max_threads();
}

void svp_set_fft_effort(svp_fft_effort effort)
{
    pthread_mutex_lock(&fft_lock);
    fft_effort = effort;
    pthread_mutex_unlock(&fft_lock);
}

svp_fft_effort svp_get_fft_effort(void)
{
    pthread_mutex_lock(&fft_lock);
    svp_fft_effort e = fft_effort;
    pthread_mutex_unlock(&fft_lock);
    return e;
}

/* FFTW trusts the numbers of a wisdom record: fftw_import_wisdom_from_string aborts the
 * process (an assertion, FFTW 3.3.10) when a record's flag words do not fit the planner's bit
 * fields (l and u 20 bits, the time-limit field 9 bits). A file is therefore checked first:
 * whitespace-separated blocks "(fftw-<version> fftw[f]_wisdom #x.. #x.. #x.. #x.." of records
 * "(<name> <int> #x<l> #x<u> #x<t> #x.. #x.. #x.. #x..)" closed by ")", numbers of at most 8
 * hex digits, l, u, t in range. Returns the offset of the first fault, or -1 when well-formed. */
#define SVP_WISDOM_MAX_BYTES (16 << 20) /* docs/reliability.md */

static const char *wisdom_space(const char *p)
{
    while (*p == ' ' || *p == '\t' || *p == '\n' || *p == '\r') p++;
    return p;
}

/* a token of 1..63 characters other than space, parentheses and NUL */
static const char *wisdom_token(const char *p)
{
    const char *q = p;
    while (*q && !strchr(" \t\n\r()", *q)) q++;
    return q > p && q - p < 64 ? q : NULL;
}

/* whitespace, "#x", 1..8 hex digits; *v = the value */
static const char *wisdom_hex(const char *p, unsigned long *v)
{
    p = wisdom_space(p);
    if (p[0] != '#' || p[1] != 'x') return NULL;
    p += 2;
    int n = 0;
    *v = 0;
    while (isxdigit((unsigned char)*p)) {
        if (++n > 8) return NULL;
        *v = *v * 16 + (unsigned long)(isdigit((unsigned char)*p) ? *p - '0'
                                                                     : (*p | 0x20) - 'a' + 10);
        p++;
    }
    return n ? p : NULL;
}

static long wisdom_check(const char *text)
{
    const char *p = wisdom_space(text);
    int blocks = 0;
    unsigned long v;
    while (*p) {
        if (*p != '(' || ++blocks > 2) return p - text;
        const char *q = wisdom_token(p + 1); /* fftw-3.3.10 */
        if (!q || strncmp(p + 1, "fftw", 4)) return p - text;
        p = wisdom_space(q);
        q = wisdom_token(p); /* fftw_wisdom | fftwf_wisdom */
        if (!q || (strncmp(p, "fftw_wisdom", 11) && strncmp(p, "fftwf_wisdom", 12)))
            return p - text;
        p = q;
        for (int i = 0; i < 4; i++)
            if (!(p = wisdom_hex(q = p, &v))) return q - text;
        for (;;) {
            p = wisdom_space(p);
            if (*p == ')') break;
            if (*p != '(' || !(q = wisdom_token(p + 1))) return p - text;
            p = wisdom_space(q);
            if (*p == '-') p++;
            int digits = 0;
            while (isdigit((unsigned char)*p) && digits < 10) p++, digits++;
            if (!digits || isdigit((unsigned char)*p)) return p - text;
            for (int i = 0; i < 7; i++) {
                if (!(p = wisdom_hex(q = p, &v))) return q - text;
                if ((i < 2 && v >= 1ul << 20) || (i == 2 && v >= 1ul << 9)) return q - text;
            }
            p = wisdom_space(p);
            if (*p != ')') return p - text;
            p++;
        }
        p = wisdom_space(p + 1);
    }
    return blocks ? -1 : 0;
}

/* A wisdom file holds FFTW's double-precision wisdom and, after it, the single-precision one
 * (each an s-expression starting "(fftw-<version> fftw_wisdom" / "fftwf_wisdom"); files with
 * the double part only (older ones) load as before. */
svp_status svp_fft_wisdom_load(const char *path)
{
    pthread_once(&fft_once, fft_init);
    FILE *fp = fopen(path, "rb");
    if (!fp) return svp_fail(SVP_ERR_IO, "%s: cannot read FFTW wisdom: %s", path, strerror(errno));
    char *text = NULL;
    long size = -1;
    if (fseek(fp, 0, SEEK_END) == 0) size = ftell(fp);
    if (size > SVP_WISDOM_MAX_BYTES) {
        fclose(fp);
        return svp_fail(SVP_ERR_IO, "%s: %ld bytes, larger than the %d MiB an FFTW wisdom file may have",
                        path, size, SVP_WISDOM_MAX_BYTES >> 20);
    }
    if (size >= 0 && fseek(fp, 0, SEEK_SET) == 0) text = malloc((size_t)size + 1);
    size_t got = text ? fread(text, 1, (size_t)size, fp) : 0;
    fclose(fp);
    if (!text || got != (size_t)size) {
        free(text);
        return svp_fail(SVP_ERR_IO, "%s: cannot read FFTW wisdom", path);
    }
    text[got] = '\0';
    long bad = memchr(text, '\0', got) ? (long)((char *)memchr(text, '\0', got) - text)
                                       : wisdom_check(text);
    if (bad >= 0) {
        free(text);
        return svp_fail(SVP_ERR_IO, "%s: not an FFTW wisdom file (malformed at byte offset %ld)",
                        path, bad);
    }
    /* the single-precision part starts at the "(" before " fftwf_wisdom" */
    char *single = strstr(text, " fftwf_wisdom");
    while (single && single > text && *single != '(') single--;
    if (single && *single != '(') single = NULL;
    /* a double part precedes it unless the file holds single-precision wisdom only */
    const int has_double = !single || memchr(text, '(', (size_t)(single - text)) != NULL;
    int ok = 1;
    pthread_mutex_lock(&fft_lock);
    if (single) {
        char keep = *single;
        *single = '\0';
        if (has_double) ok = fftw_import_wisdom_from_string(text);
        *single = keep;
        ok = ok && fftwf_import_wisdom_from_string(single);
    } else {
        ok = fftw_import_wisdom_from_string(text);
    }
    pthread_mutex_unlock(&fft_lock);
    free(text);
    if (!ok) return svp_fail(SVP_ERR_IO, "%s: not an FFTW wisdom file of this FFTW", path);
    return SVP_OK;
}

/* Writes d and f to fp; 0 on success. */
static int wisdom_write(FILE *fp, const char *d, const char *f)
{
    int bad = fputs(d, fp) < 0 || fputs(f, fp) < 0;
    bad = fflush(fp) != 0 || bad;
    return bad;
}

svp_status svp_fft_wisdom_save(const char *path)
{
    if (!path || !path[0]) return svp_fail(SVP_ERR_INVALID, "FFTW wisdom: no file name");
    pthread_once(&fft_once, fft_init);
    pthread_mutex_lock(&fft_lock);
    char *d = fftw_export_wisdom_to_string();
    char *f = fftwf_export_wisdom_to_string();
    pthread_mutex_unlock(&fft_lock);
    svp_status st = SVP_OK;
    if (!d || !f) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: cannot write FFTW wisdom: out of memory", path);
        goto done;
    }
    /* a temporary file next to the target, renamed into place: readers (a concurrent run
     * loading the same cache) see the old file or the new one, never a part */
    const size_t n = strlen(path);
    char *tmp = malloc(n + 8);
    if (!tmp) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: cannot write FFTW wisdom: out of memory", path);
        goto done;
    }
    memcpy(tmp, path, n);
    memcpy(tmp + n, ".XXXXXX", 8);
    int fd = mkstemp(tmp);
    if (fd >= 0) {
        /* mkstemp makes 0600; keep the mode of the file it replaces, else 0644 */
        struct stat old;
        fchmod(fd, stat(path, &old) == 0 ? (old.st_mode & 07777) : 0644);
        FILE *fp = fdopen(fd, "wb");
        int bad = !fp || wisdom_write(fp, d, f);
        bad = (fp ? fclose(fp) != 0 : close(fd) != 0) || bad;
        if (bad || rename(tmp, path) != 0) {
            st = svp_fail(SVP_ERR_IO, "%s: cannot write FFTW wisdom: %s", path,
                          errno ? strerror(errno) : "write failed");
            unlink(tmp);
        }
    } else if (errno == EACCES || errno == EROFS || errno == EPERM) {
        /* a folder that is not writable: the file itself may be (written in place) */
        FILE *fp = fopen(path, "wb");
        if (!fp) {
            st = svp_fail(SVP_ERR_IO, "%s: cannot write FFTW wisdom: %s", path, strerror(errno));
        } else {
            int bad = wisdom_write(fp, d, f);
            if (fclose(fp) != 0 || bad)
                st = svp_fail(SVP_ERR_IO, "%s: cannot write FFTW wisdom: %s", path,
                              strerror(errno));
        }
    } else {
        st = svp_fail(SVP_ERR_IO, "%s: cannot write FFTW wisdom: %s", path, strerror(errno));
    }
    free(tmp);
done:
    if (d) fftw_free(d);
    if (f) fftwf_free(f);
    return st;
}

/* Even sizes only: FFTW's transforms of an odd length ran 1.6–2× slower than the next even
 * smooth size on this project's machine (FFTW 3.3.10, FFTW_ESTIMATE, one r2c + c2r pair, one
 * thread: 625² 10.2 ms against 630² 6.5 ms, 1125² 37.6 against 1134² 19.0, 1225² 38.9 against
 * 1250² 34.0), and its threaded plans of them far more (625² on two threads 26 ms, 630² 2.9). */
int svp_fft_good_size(int n)
{
    if (n <= 1) return 1;
    for (int m = n + (n & 1);; m += 2) {
        int r = m;
        while (r % 2 == 0) r /= 2;
        while (r % 3 == 0) r /= 3;
        while (r % 5 == 0) r /= 5;
        while (r % 7 == 0) r /= 7;
        if (r == 1) return m;
    }
}

void svp_fft_local_threads(int n) { local_threads = n > 0 ? n : 0; }

/* The threads of a plan for ny x nx points made by the calling thread. Threads cost more than
 * they save on small transforms (and oversubscribe badly). */
static int plan_threads(int ny, int nx)
{
    if ((size_t)ny * nx < SVP_PARALLEL_MIN) return 1;
    return local_threads > 0 ? local_threads : svp_get_threads();
}

svp_status svp_fft_plan_get(int ny, int nx, const svp_fft_plan **out)
{
    if (ny < 1 || nx < 1) return svp_fail(SVP_ERR_INVALID, "FFT size %d x %d", ny, nx);
    pthread_once(&fft_once, fft_init);
    const int threads = plan_threads(ny, nx);
    pthread_mutex_lock(&fft_lock);
    for (plan_entry *e = plan_cache; e; e = e->next) {
        if (e->plan.ny == ny && e->plan.nx == nx && e->threads == threads) {
            *out = &e->plan;
            pthread_mutex_unlock(&fft_lock);
            return SVP_OK;
        }
    }
    svp_status status = SVP_OK;
    int ncx = nx / 2 + 1;
    size_t nreal = (size_t)ny * nx, ncomplex = (size_t)ny * ncx;
    double *r = svp_alloc(nreal * sizeof(double));
    fftw_complex *c = svp_alloc(ncomplex * sizeof(fftw_complex));
    plan_entry *e = calloc(1, sizeof *e);
    if (!r || !c || !e) {
        status = svp_fail(SVP_ERR_NOMEM, "out of memory planning a %d x %d FFT", ny, nx);
        goto cleanup;
    }
    if (fft_threads_ok) fftw_plan_with_nthreads(threads);
    int wisdom_first;
    const unsigned flags = plan_flags(&wisdom_first);
    e->plan.ny = ny;
    e->plan.nx = nx;
    e->plan.ncx = ncx;
    e->threads = threads;
    for (;;) {
        const unsigned f = wisdom_first ? flags | FFTW_WISDOM_ONLY : flags;
        e->plan.r2c = fftw_plan_dft_r2c_2d(ny, nx, r, c, f);
        e->plan.c2r = fftw_plan_dft_c2r_2d(ny, nx, c, r, f);
        if (e->plan.r2c && e->plan.c2r) break;
        if (e->plan.r2c) fftw_destroy_plan(e->plan.r2c);
        if (e->plan.c2r) fftw_destroy_plan(e->plan.c2r);
        e->plan.r2c = e->plan.c2r = NULL;
        if (!wisdom_first) {
            status =
                svp_fail(SVP_ERR_INTERNAL, "FFTW could not plan a %d x %d transform", ny, nx);
            goto cleanup;
        }
        wisdom_first = 0;
        plan_measuring(ny, nx, 0);
    }
    e->next = plan_cache;
    plan_cache = e;
    *out = &e->plan;
    e = NULL;
cleanup:
    pthread_mutex_unlock(&fft_lock);
    free(e);
    svp_free(r);
    svp_free(c);
    return status;
}

void svp_fft_forward(const svp_fft_plan *plan, double *in, fftw_complex *out)
{
    fftw_execute_dft_r2c(plan->r2c, in, out);
}

void svp_fft_inverse(const svp_fft_plan *plan, fftw_complex *in, double *out)
{
    fftw_execute_dft_c2r(plan->c2r, in, out);
    const double scale = 1.0 / ((double)plan->ny * plan->nx);
    const size_t n = (size_t)plan->ny * plan->nx;
#pragma omp parallel for schedule(static) if (n > 65536)
    for (size_t i = 0; i < n; i++) out[i] *= scale;
}

void svp_fft_inverse_unscaled(const svp_fft_plan *plan, fftw_complex *in, double *out)
{
    fftw_execute_dft_c2r(plan->c2r, in, out);
}

/* _Pragma inside a macro is beyond clang-format: this block is laid out by hand */
/* clang-format off */
/* Row-then-column plans (svp_fft_pruned, svp_fftf_rows): one template for both precisions. T
 * the plan struct, R / C its real and complex types, P the FFTW prefix (fftw_ or fftwf_). */
#define SVP_ROWS_PLANS(T, ENTRY, CACHE, DESTROY, GET, FORWARD, INVERSE, R, C, P, WHAT)             \
    typedef struct ENTRY {                                                                         \
        T plan;                                                                                    \
        int threads;                                                                               \
        struct ENTRY *next;                                                                        \
    } ENTRY;                                                                                       \
    static ENTRY *CACHE;                                                                           \
                                                                                                   \
    static void DESTROY(T *p)                                                                      \
    {                                                                                              \
        if (p->rows_r2c) P##destroy_plan(p->rows_r2c);                                             \
        if (p->cols_fwd) P##destroy_plan(p->cols_fwd);                                             \
        if (p->cols_bwd) P##destroy_plan(p->cols_bwd);                                             \
        if (p->rows_c2r) P##destroy_plan(p->rows_c2r);                                             \
    }                                                                                              \
                                                                                                   \
    svp_status GET(int ny, int nx, int rows, const T **out)                                        \
    {                                                                                              \
        if (ny < 1 || nx < 1 || rows < 0 || rows > ny)                                             \
            return svp_fail(SVP_ERR_INVALID, WHAT " FFT size %d x %d with %d rows", ny, nx, rows); \
        pthread_once(&fft_once, fft_init);                                                         \
        const int threads = plan_threads(ny, nx);                                                  \
        pthread_mutex_lock(&fft_lock);                                                             \
        for (ENTRY *e = CACHE; e; e = e->next) {                                                   \
            if (e->plan.ny == ny && e->plan.nx == nx && e->plan.rows == rows &&                    \
                e->threads == threads) {                                                           \
                *out = &e->plan;                                                                   \
                pthread_mutex_unlock(&fft_lock);                                                   \
                return SVP_OK;                                                                     \
            }                                                                                      \
        }                                                                                          \
        svp_status status = SVP_OK;                                                                \
        int ncx = nx / 2 + 1;                                                                      \
        R *r = svp_alloc((size_t)ny * nx * sizeof(R));                                             \
        C *c = svp_alloc((size_t)ny * ncx * sizeof(C));                                            \
        ENTRY *e = calloc(1, sizeof *e);                                                           \
        if (!r || !c || !e) {                                                                      \
            status = svp_fail(SVP_ERR_NOMEM, "out of memory planning a %d x %d " WHAT " FFT", ny,  \
                              nx);                                                                 \
            goto cleanup;                                                                          \
        }                                                                                          \
        if (fft_threads_ok) P##plan_with_nthreads(threads);                                        \
        int wisdom_first;                                                                          \
        const unsigned flags = plan_flags(&wisdom_first);                                          \
        T *p = &e->plan;                                                                           \
        p->ny = ny;                                                                                \
        p->nx = nx;                                                                                \
        p->ncx = ncx;                                                                              \
        p->rows = rows;                                                                            \
        e->threads = threads;                                                                      \
        for (;;) {                                                                                 \
            const unsigned f = wisdom_first ? flags | FFTW_WISDOM_ONLY : flags;                    \
            if (rows > 0) { /* rows = 0: the column plans only */                                  \
                p->rows_r2c = P##plan_many_dft_r2c(1, &nx, rows, r, NULL, 1, nx, c, NULL, 1, ncx,  \
                                                   f);                                             \
                p->rows_c2r = P##plan_many_dft_c2r(1, &nx, rows, c, NULL, 1, ncx, r, NULL, 1, nx,  \
                                                   f);                                             \
            }                                                                                      \
            p->cols_fwd = P##plan_many_dft(1, &ny, ncx, c, NULL, ncx, 1, c, NULL, ncx, 1,          \
                                           FFTW_FORWARD, f);                                       \
            p->cols_bwd = P##plan_many_dft(1, &ny, ncx, c, NULL, ncx, 1, c, NULL, ncx, 1,          \
                                           FFTW_BACKWARD, f);                                      \
            if (!((rows > 0 && (!p->rows_r2c || !p->rows_c2r)) || !p->cols_fwd || !p->cols_bwd))   \
                break;                                                                             \
            DESTROY(p);                                                                            \
            p->rows_r2c = p->rows_c2r = p->cols_fwd = p->cols_bwd = NULL;                          \
            if (!wisdom_first) {                                                                   \
                status = svp_fail(SVP_ERR_INTERNAL, "FFTW could not plan a " WHAT " %d x %d "      \
                                  "transform", ny, nx);                                            \
                goto cleanup;                                                                      \
            }                                                                                      \
            wisdom_first = 0;                                                                      \
            plan_measuring(ny, nx, sizeof(R) == sizeof(float));                                    \
        }                                                                                          \
        e->next = CACHE;                                                                           \
        CACHE = e;                                                                                 \
        *out = p;                                                                                  \
        e = NULL;                                                                                  \
    cleanup:                                                                                       \
        pthread_mutex_unlock(&fft_lock);                                                           \
        free(e);                                                                                   \
        svp_free(r);                                                                               \
        svp_free(c);                                                                               \
        return status;                                                                             \
    }                                                                                              \
                                                                                                   \
    void FORWARD(const T *p, R *in, C *out)                                                        \
    {                                                                                              \
        P##execute_dft_r2c(p->rows_r2c, in, out);                                                  \
        const int ny = p->ny, ncx = p->ncx;                                                        \
        const int big = (size_t)(ny - p->rows) * ncx > SVP_PARALLEL_MIN;                           \
        _Pragma("omp parallel for schedule(static) if (big)")                                      \
        for (int j = p->rows; j < ny; j++)                                                         \
            memset(out + (size_t)j * ncx, 0, (size_t)ncx * sizeof(C));                             \
        P##execute_dft(p->cols_fwd, out, out);                                                     \
    }                                                                                              \
                                                                                                   \
    void INVERSE(const T *p, C *in, R *out)                                                        \
    {                                                                                              \
        P##execute_dft(p->cols_bwd, in, in);                                                       \
        P##execute_dft_c2r(p->rows_c2r, in, out);                                                  \
    }

SVP_ROWS_PLANS(svp_fft_pruned, pruned_entry, pruned_cache, pruned_destroy, svp_fft_pruned_get,
               svp_fft_forward_pruned, svp_fft_inverse_pruned_unscaled, double, fftw_complex,
               fftw_, "pruned")
SVP_ROWS_PLANS(svp_fftf_rows, rowsf_entry, rowsf_cache, rowsf_destroy, svp_fftf_rows_get,
               svp_fftf_forward_rows, svp_fftf_inverse_rows_unscaled, float, fftwf_complex,
               fftwf_, "float")
/* clang-format on */

typedef struct block_entry {
    svp_fft_block plan;
    struct block_entry *next;
} block_entry;
static block_entry *block_cache;

static void block_destroy(svp_fft_block *p)
{
    if (p->r2c) fftw_destroy_plan(p->r2c);
    if (p->c2r) fftw_destroy_plan(p->c2r);
    if (p->r2c1) fftw_destroy_plan(p->r2c1);
    if (p->c2r1) fftw_destroy_plan(p->c2r1);
}

svp_status svp_fft_block_get(int nx, const svp_fft_block **out)
{
    if (nx < 1) return svp_fail(SVP_ERR_INVALID, "row-block FFT width %d", nx);
    pthread_once(&fft_once, fft_init);
    pthread_mutex_lock(&fft_lock);
    for (block_entry *e = block_cache; e; e = e->next)
        if (e->plan.nx == nx) {
            *out = &e->plan;
            pthread_mutex_unlock(&fft_lock);
            return SVP_OK;
        }
    svp_status status = SVP_OK;
    const int ncx = nx / 2 + 1, B = SVP_FFT_BLOCK, bx = nx + (nx & 1);
    /* planned 16 bytes past a 64-byte boundary: FFTW then picks no codelet that needs more
     * than 16-byte alignment, and the rows of a frame (ncx complex apart) qualify */
    double *r = svp_alloc(((size_t)B * bx + 2) * sizeof(double));
    fftw_complex *c = svp_alloc(((size_t)B * ncx + 1) * sizeof(fftw_complex));
    block_entry *e = calloc(1, sizeof *e);
    if (!r || !c || !e) {
        status = svp_fail(SVP_ERR_NOMEM, "out of memory planning %d-wide row FFTs", nx);
        goto cleanup;
    }
    if (fft_threads_ok) fftw_plan_with_nthreads(1); /* run inside the caller's threads */
    int wisdom_first;
    const unsigned flags = plan_flags(&wisdom_first);
    svp_fft_block *p = &e->plan;
    p->nx = nx;
    p->ncx = ncx;
    p->bx = bx;
    double *r16 = r ? r + 2 : NULL;
    fftw_complex *c16 = c ? c + 1 : NULL;
    for (;;) {
        const unsigned f = wisdom_first ? flags | FFTW_WISDOM_ONLY : flags;
        p->r2c = fftw_plan_many_dft_r2c(1, &nx, B, r16, NULL, 1, bx, c16, NULL, 1, ncx, f);
        p->c2r = fftw_plan_many_dft_c2r(1, &nx, B, c16, NULL, 1, ncx, r16, NULL, 1, bx, f);
        p->r2c1 = fftw_plan_dft_r2c_1d(nx, r16, c16, f);
        p->c2r1 = fftw_plan_dft_c2r_1d(nx, c16, r16, f);
        if (p->r2c && p->c2r && p->r2c1 && p->c2r1) break;
        block_destroy(p);
        p->r2c = p->c2r = p->r2c1 = p->c2r1 = NULL;
        if (!wisdom_first) {
            status = svp_fail(SVP_ERR_INTERNAL, "FFTW could not plan %d-wide row transforms", nx);
            goto cleanup;
        }
        wisdom_first = 0;
        plan_measuring(1, nx, 0);
    }
    e->next = block_cache;
    block_cache = e;
    *out = p;
    e = NULL;
cleanup:
    pthread_mutex_unlock(&fft_lock);
    free(e);
    svp_free(r);
    svp_free(c);
    return status;
}

void svp_fft_block_forward(const svp_fft_block *p, int rows, double *in, fftw_complex *out)
{
    if (rows == SVP_FFT_BLOCK) {
        fftw_execute_dft_r2c(p->r2c, in, out);
        return;
    }
    for (int t = 0; t < rows; t++)
        fftw_execute_dft_r2c(p->r2c1, in + (size_t)t * p->bx, out + (size_t)t * p->ncx);
}

void svp_fft_block_inverse(const svp_fft_block *p, int rows, fftw_complex *in, double *out)
{
    if (rows == SVP_FFT_BLOCK) {
        fftw_execute_dft_c2r(p->c2r, in, out);
        return;
    }
    for (int t = 0; t < rows; t++)
        fftw_execute_dft_c2r(p->c2r1, in + (size_t)t * p->ncx, out + (size_t)t * p->bx);
}

void svp_fft_cleanup(void)
{
    pthread_mutex_lock(&fft_lock);
    while (block_cache) {
        block_entry *next = block_cache->next;
        block_destroy(&block_cache->plan);
        free(block_cache);
        block_cache = next;
    }
    while (rowsf_cache) {
        rowsf_entry *next = rowsf_cache->next;
        rowsf_destroy(&rowsf_cache->plan);
        free(rowsf_cache);
        rowsf_cache = next;
    }
    while (pruned_cache) {
        pruned_entry *next = pruned_cache->next;
        pruned_destroy(&pruned_cache->plan);
        free(pruned_cache);
        pruned_cache = next;
    }
    while (plan_cache) {
        plan_entry *next = plan_cache->next;
        fftw_destroy_plan(plan_cache->plan.r2c);
        fftw_destroy_plan(plan_cache->plan.c2r);
        free(plan_cache);
        plan_cache = next;
    }
    pthread_mutex_unlock(&fft_lock);
}
