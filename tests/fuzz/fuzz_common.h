/* Shared by the libFuzzer targets (docs/reliability.md): the readers take paths, so each input
 * is written to a file in a private temporary folder (on /dev/shm when there is one) under the
 * extension that selects the reader. */
#ifndef SVP_FUZZ_COMMON_H
#define SVP_FUZZ_COMMON_H

#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static char fuzz_dir[256];

/* The readers check the memory a file claims against SVPSF_MAX_MEMORY before allocating it
 * (docs/reliability.md): 1 GiB keeps every accepted input under the runs' 2 GiB RSS limit, so
 * an input that claims more is refused like on a machine with 1 GiB free, not an OOM finding. */
__attribute__((constructor)) static void fuzz_memory_budget(void)
{
    setenv("SVPSF_MAX_MEMORY", "1G", 0);
}

static char fuzz_made[8][512]; /* the files written, removed at exit with the folder */
static int fuzz_nmade;

static void fuzz_cleanup(void)
{
    for (int i = 0; i < fuzz_nmade; i++) remove(fuzz_made[i]);
    if (fuzz_dir[0]) rmdir(fuzz_dir);
}

/* The path of `name` in the private folder (made on first use; removed at exit). */
static inline const char *fuzz_path(const char *name)
{
    static char path[512];
    if (!fuzz_dir[0]) {
        const char *base = access("/dev/shm", W_OK) == 0 ? "/dev/shm" : "/tmp";
        snprintf(fuzz_dir, sizeof fuzz_dir, "%s/svpsf-fuzz.XXXXXX", base);
        if (!mkdtemp(fuzz_dir)) abort();
        atexit(fuzz_cleanup);
    }
    snprintf(path, sizeof path, "%s/%s", fuzz_dir, name);
    return path;
}

/* Writes the input to `name` in the private folder; returns its path. */
static inline const char *fuzz_write(const char *name, const uint8_t *data, size_t size)
{
    const char *path = fuzz_path(name);
    int known = 0;
    for (int i = 0; i < fuzz_nmade; i++) known |= !strcmp(fuzz_made[i], path);
    if (!known && fuzz_nmade < 8) snprintf(fuzz_made[fuzz_nmade++], sizeof fuzz_made[0], "%s", path);
    FILE *f = fopen(path, "wb");
    if (!f) abort();
    if (size && fwrite(data, 1, size, f) != size) abort();
    if (fclose(f) != 0) abort();
    return path;
}

#endif
