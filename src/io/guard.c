/* What keeps a read or a run from ending in an out-of-memory kill or leaving debris behind
 * (docs/reliability.md): the memory budget (SVPSF_MAX_MEMORY, else the memory the kernel
 * reports available), the largest image a reader accepts, and the registry of the temporary
 * files of atomic writes (removed by a signal handler; stale ones of dead processes removed by
 * the next write of the same output). */
#include "../core/internal.h"
#include "image_io.h"

#include <ctype.h>
#include <dirent.h>
#include <errno.h>
#include <limits.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/types.h>
#include <unistd.h>

/* ---- memory budget --------------------------------------------------------------------------- */

/* MemAvailable from /proc/meminfo in bytes; the free physical pages where there is no such
 * line; 0 when neither is known. */
static double memory_available(void)
{
    FILE *f = fopen("/proc/meminfo", "r");
    if (f) {
        char line[256];
        double kib = -1;
        while (fgets(line, sizeof line, f))
            if (!strncmp(line, "MemAvailable:", 13)) {
                kib = strtod(line + 13, NULL);
                break;
            }
        fclose(f);
        if (kib >= 0) return kib * 1024.0;
    }
#ifdef _SC_AVPHYS_PAGES
    long pages = sysconf(_SC_AVPHYS_PAGES), page = sysconf(_SC_PAGESIZE);
    if (pages > 0 && page > 0) return (double)pages * (double)page;
#endif
    return 0;
}

/* Parses "512M", "4G", "1.5GiB", "1073741824" (binary units K, M, G, T; B/iB optional). */
static int parse_size(const char *text, double *bytes)
{
    char *end = NULL;
    errno = 0;
    double v = strtod(text, &end);
    if (end == text || errno || !(v > 0) || v > 1e18) return 0;
    double unit = 1;
    switch (toupper((unsigned char)*end)) {
    case 'K':
        unit = 0x1p10;
        end++;
        break;
    case 'M':
        unit = 0x1p20;
        end++;
        break;
    case 'G':
        unit = 0x1p30;
        end++;
        break;
    case 'T':
        unit = 0x1p40;
        end++;
        break;
    default: break;
    }
    if (unit > 1 && (*end == 'i' || *end == 'I')) end++;
    if (*end == 'B' || *end == 'b') end++;
    if (*end) return 0;
    *bytes = v * unit;
    return 1;
}

svp_status svp_io_memory_budget(double *bytes, char *source, size_t source_size)
{
    const char *env = getenv("SVPSF_MAX_MEMORY");
    if (env && *env) {
        if (!parse_size(env, bytes))
            return svp_fail(SVP_ERR_INVALID,
                            "SVPSF_MAX_MEMORY=%.40s is not a memory size (e.g. 512M, 4G; "
                            "docs/reliability.md)",
                            env);
        snprintf(source, source_size, "SVPSF_MAX_MEMORY=%s", env);
        return SVP_OK;
    }
    *bytes = memory_available();
    snprintf(source, source_size, "available memory");
    return SVP_OK;
}

static void format_bytes(double b, char *buf, size_t size)
{
    if (b >= 0x1p30)
        snprintf(buf, size, "%.2f GiB", b / 0x1p30);
    else if (b >= 0x1p20)
        snprintf(buf, size, "%.1f MiB", b / 0x1p20);
    else
        snprintf(buf, size, "%.0f KiB", b / 0x1p10);
}

svp_status svp_io_check_memory(const char *path, const char *what, double bytes)
{
    /* below this the check costs more than it saves (and /proc may be missing) */
    if (bytes < 0x1p24 && !getenv("SVPSF_MAX_MEMORY")) return SVP_OK;
    double budget = 0;
    char source[96];
    SVP_CHECK(svp_io_memory_budget(&budget, source, sizeof source));
    if (budget <= 0 || bytes <= budget) return SVP_OK; /* unknown: no check */
    char need[32], have[32];
    format_bytes(bytes, need, sizeof need);
    format_bytes(budget, have, sizeof have);
    return svp_fail(SVP_ERR_INVALID,
                    "%s%s%s needs %s of memory, more than the %s allowed (%s; "
                    "docs/reliability.md)",
                    path ? path : "", path ? ": " : "", what, need, have, source);
}

svp_status svp_io_check_image_size(const char *path, const char *where, long long width,
                                   long long height)
{
    if (width > SVP_IO_MAX_SIDE || height > SVP_IO_MAX_SIDE ||
        (width > 0 && height > SVP_IO_MAX_PIXELS / width))
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: %s%lld x %lld pixels: larger than an image may be (each side at "
                        "most %d, at most %lld pixels, e.g. 16384 x 16384; docs/reliability.md)",
                        path, where ? where : "", width, height, SVP_IO_MAX_SIDE,
                        (long long)SVP_IO_MAX_PIXELS);
    return SVP_OK;
}

/* ---- temporary files --------------------------------------------------------------------------
 * Each slot: 0 free, 1 being filled or emptied, 2 holds the name of a temporary file that
 * exists. The signal handler only reads slots in state 2 and calls unlink(): async-signal-safe. */
#define TEMP_SLOTS 64
static char temp_names[TEMP_SLOTS][PATH_MAX];
static atomic_int temp_state[TEMP_SLOTS];

int svp_io_temp_register(const char *name)
{
    if (strlen(name) >= PATH_MAX) return -1;
    for (int i = 0; i < TEMP_SLOTS; i++) {
        int expected = 0;
        if (atomic_compare_exchange_strong(&temp_state[i], &expected, 1)) {
            strcpy(temp_names[i], name);
            atomic_store(&temp_state[i], 2);
            return i;
        }
    }
    return -1; /* all slots taken (64 writes at once): the file is still removed on failure */
}

void svp_io_temp_release(int slot)
{
    if (slot >= 0 && slot < TEMP_SLOTS) atomic_store(&temp_state[slot], 0);
}

void svp_io_temp_remove_all(void)
{
    for (int i = 0; i < TEMP_SLOTS; i++)
        if (atomic_load(&temp_state[i]) == 2) unlink(temp_names[i]);
}

/* "<prefix><pid>-XXXXXX": the PID of a stale temporary file's writer, or 0 */
static long temp_pid(const char *name, const char *prefix)
{
    size_t n = strlen(prefix);
    if (strncmp(name, prefix, n) != 0) return 0;
    char *end = NULL;
    errno = 0;
    long pid = strtol(name + n, &end, 10);
    if (errno || pid <= 0 || !end || *end != '-' || strlen(end + 1) != 6) return 0;
    return pid;
}

void svp_io_temp_remove_stale(const char *folder, const char *base)
{
    char prefix[NAME_MAX + 2];
    if (snprintf(prefix, sizeof prefix, ".%s" SVP_IO_TEMP_TAG, base) >= (int)sizeof prefix) return;
    DIR *d = opendir(folder && *folder ? folder : ".");
    if (!d) return;
    const long self = (long)getpid();
    struct dirent *e;
    while ((e = readdir(d))) {
        long pid = temp_pid(e->d_name, prefix);
        if (pid <= 0 || pid == self) continue;
        /* a process that no longer exists (ESRCH) cannot finish its write; EPERM: it exists */
        if (pid > INT_MAX || (kill((pid_t)pid, 0) != 0 && errno == ESRCH)) {
            char path[PATH_MAX];
            if (snprintf(path, sizeof path, "%s/%s", folder && *folder ? folder : ".", e->d_name) <
                (int)sizeof path)
                unlink(path);
        }
    }
    closedir(d);
}
