/* Status codes and the thread-local error message; the parallel runner of independent items,
 * which carries each item's error message back to the calling thread (svp_items_parallel). */
#include "internal.h"

#include <omp.h>
#include <stdatomic.h>

#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static _Thread_local char last_error[SVP_ERROR_LEN];

const char *svp_status_string(svp_status status)
{
    switch (status) {
    case SVP_OK: return "ok";
    case SVP_ERR_INVALID: return "invalid argument";
    case SVP_ERR_IO: return "input/output error";
    case SVP_ERR_FORMAT: return "malformed file";
    case SVP_ERR_SIZE: return "size mismatch";
    case SVP_ERR_NOMEM: return "out of memory";
    case SVP_ERR_EXISTS: return "output exists";
    case SVP_ERR_CANCELLED: return "cancelled";
    case SVP_ERR_NUMERIC: return "numerical failure";
    case SVP_ERR_UNSUPPORTED: return "unsupported";
    case SVP_ERR_INTERNAL: return "internal error";
    case SVP_ERR_DOUBTFUL: return "result in doubt";
    }
    return "unknown status";
}

const char *svp_last_error(void) { return last_error; }

void svp_clear_error(void) { last_error[0] = '\0'; }

svp_status svp_fail(svp_status status, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(last_error, sizeof last_error, fmt, ap);
    va_end(ap);
    return status;
}

svp_status svp_fail_context(svp_status status, const char *fmt, ...)
{
    char previous[SVP_ERROR_LEN];
    char context[SVP_ERROR_LEN];
    memcpy(previous, last_error, sizeof previous);
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(context, sizeof context, fmt, ap);
    va_end(ap);
    size_t n = strlen(context);
    if (n > sizeof last_error - 1) n = sizeof last_error - 1;
    memcpy(last_error, context, n);
    if (previous[0] && n + 2 < sizeof last_error) {
        memcpy(last_error + n, ": ", 2);
        n += 2;
        size_t m = strlen(previous);
        if (m > sizeof last_error - 1 - n) m = sizeof last_error - 1 - n;
        memcpy(last_error + n, previous, m);
        n += m;
    }
    last_error[n] = '\0';
    return status;
}

svp_status svp_report_progress(svp_progress_fn fn, void *user, double fraction)
{
    if (fn && fn(user, fraction)) return svp_fail(SVP_ERR_CANCELLED, "cancelled by the caller");
    return SVP_OK;
}

int svp_progress_share_fn(void *share, double fraction)
{
    const svp_progress_share *s = share;
    if (fraction < 0) fraction = 0;
    if (fraction > 1) fraction = 1;
    return s->fn(s->user, s->base + s->span * fraction);
}

svp_status svp_items_parallel(int n, int workers, svp_status (*fn)(void *ctx, int worker, int item),
                              void *ctx, svp_progress_fn progress, void *progress_user, double base,
                              double span)
{
    if (workers > n) workers = n;
    if (workers < 1) workers = 1;
    svp_status *status = malloc((size_t)(n > 0 ? n : 1) * sizeof *status);
    char *msg = malloc((size_t)(n > 0 ? n : 1) * SVP_ERROR_LEN);
    if (!status || !msg) {
        free(status);
        free(msg);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for %d items' status", n);
    }
    atomic_int done = 0, stop = 0, cancelled = 0;
#pragma omp parallel num_threads(workers)
    {
        const int worker = omp_get_thread_num();
        svp_fft_local_threads(1);
#pragma omp for schedule(dynamic, 1)
        for (int i = 0; i < n; i++) {
            status[i] = SVP_OK;
            msg[(size_t)i * SVP_ERROR_LEN] = '\0';
            if (atomic_load(&stop)) continue;
            svp_clear_error();
            status[i] = fn(ctx, worker, i);
            if (status[i] != SVP_OK) {
                snprintf(msg + (size_t)i * SVP_ERROR_LEN, SVP_ERROR_LEN, "%s", svp_last_error());
                atomic_store(&stop, 1);
            }
            const int k = atomic_fetch_add(&done, 1) + 1;
            if (worker == 0 && progress && !atomic_load(&stop) &&
                progress(progress_user, base + span * k / n)) {
                atomic_store(&cancelled, 1);
                atomic_store(&stop, 1);
            }
        }
        svp_fft_local_threads(0);
    }
    svp_status st = SVP_OK;
    for (int i = 0; i < n && st == SVP_OK; i++)
        if (status[i] != SVP_OK) st = svp_fail(status[i], "%s", msg + (size_t)i * SVP_ERROR_LEN);
    if (st == SVP_OK && atomic_load(&cancelled)) st = svp_fail(SVP_ERR_CANCELLED, "cancelled");
    if (st == SVP_OK) st = svp_report_progress(progress, progress_user, base + span);
    free(status);
    free(msg);
    return st;
}
