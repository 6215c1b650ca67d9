/* Good behaviour on a shared machine (docs/cli.md, "Shared machines"): a passive OpenMP wait
 * policy unless the user chose one, the FFTW wisdom cache, and a note while FFTs are measured. */
#include "cli.h"

#include <errno.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* Set in the environment of the re-executed program: it was started by svpsf itself with
 * OMP_WAIT_POLICY=passive (so it never re-executes twice). */
#define REEXEC_MARKER "SVPSF_OMP_PASSIVE"

void cli_openmp_passive(char **argv)
{
    /* libgomp reads these when it is loaded, before main(): setting them here is too late for
     * this process, so the program runs itself again with them set (once) */
    if (getenv("OMP_WAIT_POLICY") || getenv("GOMP_SPINCOUNT") || getenv(REEXEC_MARKER)) return;
    if (setenv(REEXEC_MARKER, "1", 1) != 0) return;
    if (setenv("OMP_WAIT_POLICY", "passive", 1) != 0) return;
    fflush(NULL);
    execv("/proc/self/exe", argv);
    /* no /proc, or not executable: run on with libgomp's default (threads spin-wait) */
    unsetenv("OMP_WAIT_POLICY");
}

const char *cli_omp_wait_policy(const char **source)
{
    const char *policy = getenv("OMP_WAIT_POLICY");
    const char *marker = getenv(REEXEC_MARKER);
    if (source)
        *source = !policy ? "unset (libgomp's default: threads spin before they sleep)"
                  : marker && strcmp(policy, "passive") == 0 ? "svpsf"
                                                             : "environment";
    return policy ? policy : "";
}

/* ---- the FFTW wisdom cache --------------------------------------------------------------- */

/* $XDG_CACHE_HOME/svpsf (an absolute XDG_CACHE_HOME only, as the XDG base directory
 * specification asks), else $HOME/.cache/svpsf; 0 when neither is known. */
static int cache_dir(char *dir, size_t size)
{
    const char *xdg = getenv("XDG_CACHE_HOME");
    if (xdg && xdg[0] == '/') return snprintf(dir, size, "%s/svpsf", xdg) < (int)size;
    const char *home = getenv("HOME");
    if (home && home[0] == '/') return snprintf(dir, size, "%s/.cache/svpsf", home) < (int)size;
    return 0;
}

/* mkdir -p with mode 0700 (the specification's mode for the cache base); 0 on success. */
static int make_dirs(const char *path)
{
    char buf[PATH_MAX];
    if (snprintf(buf, sizeof buf, "%s", path) >= (int)sizeof buf) {
        errno = ENAMETOOLONG;
        return -1;
    }
    for (char *p = buf + 1;; p++) {
        if (*p == '/' || *p == '\0') {
            const char keep = *p;
            *p = '\0';
            if (mkdir(buf, 0700) != 0 && errno != EEXIST) return -1;
            *p = keep;
            if (!keep) break;
        }
    }
    struct stat st;
    if (stat(path, &st) != 0) return -1;
    if (!S_ISDIR(st.st_mode)) {
        errno = ENOTDIR;
        return -1;
    }
    return 0;
}

int cli_wisdom_cache_disabled(void)
{
    const char *v = getenv("SVPSF_NO_WISDOM_CACHE");
    return v && v[0] && strcmp(v, "0") != 0;
}

void cli_wisdom_cache_open(cli_run *run)
{
    char dir[PATH_MAX], path[PATH_MAX + 16];
    if (!cache_dir(dir, sizeof dir)) return; /* no home: no cache */
    if (make_dirs(dir) != 0) {
        cli_note(run, "no FFTW wisdom cache: cannot create %s (%s); plans are measured again "
                      "next run (--no-wisdom-cache silences this)",
                 dir, strerror(errno));
        return;
    }
    snprintf(path, sizeof path, "%s/wisdom", dir);
    run->wisdom_cache = strdup(path);
    if (!run->wisdom_cache || access(path, F_OK) != 0) return;
    /* a cache that cannot be read is never fatal: the plans are measured and it is replaced */
    if (svp_fft_wisdom_load(path) != SVP_OK)
        cli_warn(run, "ignoring the FFTW wisdom cache: %s; it is replaced after this run",
                 svp_last_error());
}

void cli_wisdom_cache_save(cli_run *run)
{
    if (!run->wisdom_cache || !run->fft_planned) return;
    /* what concurrent runs added since this one started is merged in first (a file that
     * does not load was warned about and is replaced) */
    if (access(run->wisdom_cache, F_OK) == 0) (void)svp_fft_wisdom_load(run->wisdom_cache);
    if (svp_fft_wisdom_save(run->wisdom_cache) != SVP_OK)
        cli_warn(run, "cannot save the FFTW wisdom cache: %s", svp_last_error());
}

/* ---- planning notes ---------------------------------------------------------------------- */

/* Measuring the plans of a frame this large takes a noticeable time on 2 cores (measured
 * with 2 threads on a busy machine: 1.4 s at 512 x 512, 1.8 s at 1024 x 1024, 3.2 s at
 * 2048 x 2048 for one pair of double-precision plans); smaller ones pass without a note. */
#define PLAN_NOTE_MIN_PIXELS (512 * 512)

void cli_plan_callback(void *user, int ny, int nx, int single_precision)
{
    cli_run *run = user;
    run->fft_planned = 1;
    if (run->quiet || (long long)ny * nx < PLAN_NOTE_MIN_PIXELS) return;
    /* one note per size and precision */
    typedef struct noted_size {
        int ny, nx, single;
    } noted_size;
    static noted_size noted[32];
    static int n_noted;
    for (int i = 0; i < n_noted; i++)
        if (noted[i].ny == ny && noted[i].nx == nx && noted[i].single == single_precision) return;
    if (n_noted < 32) noted[n_noted++] = (noted_size){ny, nx, single_precision};
    char where[PATH_MAX + 64];
    if (run->wisdom)
        snprintf(where, sizeof where, "kept in %s after the run", run->wisdom);
    else if (run->wisdom_cache)
        snprintf(where, sizeof where, "cached afterwards in %s", run->wisdom_cache);
    else
        snprintf(where, sizeof where, "not cached: measured again next run");
    cli_note(run, "planning %sFFTs for %d x %d (first run of this size on this machine; %s)",
             single_precision ? "single-precision " : "", nx, ny, where);
}
