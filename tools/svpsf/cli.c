/* Shared helpers of the svpsf command-line program (see cli.h for how a command uses them). */
#include "cli.h"

#include "io/image_io.h"
#include "io/json.h"
#include "io/mat.h"
#include "io/yaml.h"

#include <errno.h>
#include <yaml.h>
#include <limits.h>
#include <math.h>
#include <signal.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

/* ---- private record types ------------------------------------------------------------------ */

typedef enum kv_kind { KV_STR, KV_NUM, KV_INT } kv_kind;

struct cli_kv {
    char *key;
    kv_kind kind;
    char *str;
    double num;
    long long integer;
};

struct cli_input {
    char *role;
    char *path;
    int width, height; /* 0 when not an image */
    long long bytes;   /* file size, -1 when unknown */
    long long n_nonfinite;
    double pixel_um; /* a MATLAB file's `step`, 0 otherwise */
};

struct cli_output {
    char *role;
    char *path;
    int exact;   /* planned by exact path: its own extension decides the format */
    int existed; /* -1 not checked yet; 0 absent when cli_outputs_check ran (a failed run
                  * removes it again: all or none); 1 present then (overwritten with --force) */
};

struct cli_stage {
    char *name;
    double seconds;
};

static int program_argc;
static char **program_argv;

void cli_set_program_args(int argc, char **argv)
{
    /* a copy of the pointers: getopt_long permutes argv while parsing */
    static char *copy[256];
    if (argc > 255) argc = 255;
    for (int i = 0; i < argc; i++) copy[i] = argv[i];
    copy[argc] = NULL;
    program_argc = argc;
    program_argv = copy;
}

/* Out of memory in the CLI's own bookkeeping is not worth a recovery path. */
static void *xrealloc(void *p, size_t size)
{
    void *q = realloc(p, size ? size : 1);
    if (!q) {
        fputs("svpsf: out of memory\n", stderr);
        exit(CLI_EXIT_RUNTIME);
    }
    return q;
}

static char *xstrdup(const char *s)
{
    size_t n = strlen(s ? s : "") + 1;
    char *d = xrealloc(NULL, n);
    memcpy(d, s ? s : "", n);
    return d;
}

/* ---- exit codes, versions ------------------------------------------------------------------ */

int cli_exit_code(svp_status status)
{
    switch (status) {
    case SVP_OK: return CLI_EXIT_OK;
    case SVP_ERR_INVALID:
    case SVP_ERR_IO:
    case SVP_ERR_FORMAT:
    case SVP_ERR_SIZE:
    case SVP_ERR_EXISTS: return CLI_EXIT_USAGE;
    case SVP_ERR_DOUBTFUL: return CLI_EXIT_DOUBTFUL;
    default: return CLI_EXIT_RUNTIME;
    }
}

void cli_get_versions(cli_versions *v)
{
    v->svpsf = svp_version();
    v->fftw = svp_fftw_version();
    v->opencv = svp_io_opencv_version();
    v->libyaml = yaml_get_version_string();
}

/* ---- the run -------------------------------------------------------------------------------- */

double cli_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* SIGTERM, SIGINT, SIGHUP, SIGQUIT: the temporary files of writes under way are removed, then
 * the signal ends the process as it would have (docs/reliability.md, interrupted runs). */
static void remove_temps_and_die(int sig)
{
    svp_io_temp_remove_all(); /* unlink() only: async-signal-safe */
    raise(sig);               /* SA_RESETHAND: the default action now */
}

static void install_temp_cleanup(void)
{
    static int installed;
    if (installed) return;
    installed = 1;
    static const int sigs[] = {SIGTERM, SIGINT, SIGHUP, SIGQUIT};
    for (size_t i = 0; i < sizeof sigs / sizeof sigs[0]; i++) {
        struct sigaction old, sa;
        /* a signal ignored on entry (nohup, a background shell) stays ignored */
        if (sigaction(sigs[i], NULL, &old) != 0 || old.sa_handler == SIG_IGN) continue;
        memset(&sa, 0, sizeof sa);
        sa.sa_handler = remove_temps_and_die;
        sa.sa_flags = SA_RESETHAND;
        sigemptyset(&sa.sa_mask);
        sigaction(sigs[i], &sa, NULL);
    }
}

void cli_run_init(cli_run *run, const char *command, int argc, char **argv, unsigned common)
{
    install_temp_cleanup();
    memset(run, 0, sizeof *run);
    run->command = command;
    run->argc = argc;
    run->argv = argv;
    run->common = common;
    run->format = SVP_FORMAT_TIFF;
    run->fft_measure = 1;
    run->stderr_tty = isatty(STDERR_FILENO);
    run->t_start = cli_now();
    run->progress_last_decile = -1;
}

static void free_kvs(cli_kv *kv, int n)
{
    for (int i = 0; i < n; i++) {
        free(kv[i].key);
        free(kv[i].str);
    }
    free(kv);
}

/* A run that fails after writing some of its outputs (a later output not representable in its
 * format, a full disk) removes the ones it created, so that a failed run leaves nothing behind
 * (all or none, docs/cli.md). Files that existed before (overwritten with --force) stay. */
static void remove_partial_outputs(const cli_run *run)
{
    int n_removed = 0;
    for (int i = 0; i < run->n_outputs; i++) {
        if (run->outputs[i].existed != 0) continue;
        const char *path = run->outputs[i].path;
        char mfile[PATH_MAX], mvar[64];
        int bad = 0;
        if (svp_io_mat_path(path, mfile, sizeof mfile, mvar, sizeof mvar, &bad)) path = mfile;
        if (unlink(path) == 0) n_removed++;
    }
    if (n_removed)
        cli_note(run, "removed the %d output%s written before the failure (a failed run leaves "
                 "nothing behind)", n_removed, n_removed == 1 ? "" : "s");
}

int cli_run_finish(cli_run *run, int exit_code)
{
    if (run->stage_open) cli_stage_end(run);
    svp_set_fft_plan_callback(NULL, NULL);
    if (run->wisdom && exit_code == CLI_EXIT_OK) {
        svp_status st = svp_fft_wisdom_save(run->wisdom);
        if (st != SVP_OK) exit_code = cli_fail(run, st, "--wisdom");
    }
    /* measured plans are good whatever the outcome: kept for the next run */
    cli_wisdom_cache_save(run);
    if (exit_code != CLI_EXIT_OK) remove_partial_outputs(run);
    free(run->wisdom_cache);
    run->wisdom_cache = NULL;
    for (int i = 0; i < run->n_inputs; i++) {
        free(run->inputs[i].role);
        free(run->inputs[i].path);
    }
    free(run->inputs);
    for (int i = 0; i < run->n_outputs; i++) {
        free(run->outputs[i].role);
        free(run->outputs[i].path);
    }
    free(run->outputs);
    for (int i = 0; i < run->n_stages; i++) free(run->stages[i].name);
    free(run->stages);
    free_kvs(run->settings, run->n_settings);
    free_kvs(run->results, run->n_results);
    run->inputs = NULL;
    run->outputs = NULL;
    run->stages = NULL;
    run->settings = run->results = NULL;
    run->n_inputs = run->n_outputs = run->n_stages = run->n_settings = run->n_results = 0;
    return exit_code;
}

/* ---- messages ------------------------------------------------------------------------------- */

int cli_error(const cli_run *run, const char *fmt, ...)
{
    va_list ap;
    fflush(stdout);
    fprintf(stderr, "svpsf %s: ", run->command);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
    return CLI_EXIT_USAGE;
}

void cli_note(const cli_run *run, const char *fmt, ...)
{
    if (run->quiet) return;
    va_list ap;
    fflush(stdout);
    fprintf(stderr, "svpsf %s: ", run->command);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
}

void cli_warn(const cli_run *run, const char *fmt, ...)
{
    va_list ap;
    fflush(stdout);
    fprintf(stderr, "svpsf %s: warning: ", run->command);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
}

int cli_fail(const cli_run *run, svp_status status, const char *context)
{
    const char *msg = svp_last_error();
    if (!msg || !msg[0]) msg = svp_status_string(status);
    char mfile[PATH_MAX], mvar[64];
    int bad = 0;
    if (context && svp_io_mat_path(context, mfile, sizeof mfile, mvar, sizeof mvar, &bad) &&
        strstr(msg, mfile))
        context = NULL; /* "X.mat:VAR": the message names X.mat (and the variable) */
    if (context && context[0] && !strstr(msg, context))
        cli_error(run, "%s: %s", context, msg);
    else
        cli_error(run, "%s", msg);
    return cli_exit_code(status);
}

/* ---- option parsing ------------------------------------------------------------------------ */

enum {
    OPT_FORMAT = 900,
    OPT_FORCE,
    OPT_THREADS,
    OPT_WISDOM,
    OPT_FFT,
    OPT_NO_WISDOM_CACHE,
};

#define MAX_OPTIONS 64

int cli_parse_double(const cli_run *run, const char *option, const char *text, double *out)
{
    char *end = NULL;
    errno = 0;
    double v = strtod(text, &end);
    if (end == text || *end != '\0' || !isfinite(v) || errno == ERANGE)
        return cli_error(run, "%s: '%s' is not a finite number", option, text);
    *out = v;
    return 0;
}

int cli_parse_double_in(const cli_run *run, const char *option, const char *text, double lo,
                        int lo_closed, double hi, int hi_closed, double *out)
{
    double v = 0;
    if (cli_parse_double(run, option, text, &v)) return CLI_EXIT_USAGE;
    const int lo_ok = isinf(lo) || (lo_closed ? v >= lo : v > lo);
    const int hi_ok = isinf(hi) || (hi_closed ? v <= hi : v < hi);
    if (lo_ok && hi_ok) {
        *out = v;
        return 0;
    }
    if (isinf(hi))
        return cli_error(run, "%s %s: must be %s %g", option, text, lo_closed ? ">=" : ">", lo);
    if (isinf(lo))
        return cli_error(run, "%s %s: must be %s %g", option, text, hi_closed ? "<=" : "<", hi);
    return cli_error(run, "%s %s: must be in %c%g, %g%c", option, text, lo_closed ? '[' : '(', lo,
                     hi, hi_closed ? ']' : ')');
}

int cli_parse_balance(const cli_run *run, const char *text, double *balance, int *is_auto)
{
    *is_auto = strcmp(text, "auto") == 0;
    if (*is_auto) return 0;
    if (cli_parse_double(run, "--balance", text, balance)) return CLI_EXIT_USAGE;
    if (!(*balance >= 0)) return cli_error(run, "--balance %s: must be >= 0 or auto", text);
    return 0;
}

const char *cli_balance_bound_check(const cli_run *run, const char *what, double balance,
                                    double sigma)
{
    /* the bisection ends within a factor 1.002 of the crossing; 1.01 tells an end from that */
    if (balance <= 1.01 * CLI_BALANCE_AUTO_MIN) {
        cli_warn(run,
                 "--balance auto: the balance for %s ended on the lower end of its search, "
                 "%g: even that leaves more residual than noise sigma %g explains (sigma too "
                 "small?); the result is barely regularised",
                 what, balance, sigma);
        return "lower";
    }
    if (balance >= CLI_BALANCE_AUTO_MAX / 1.01) {
        cli_warn(run,
                 "--balance auto: the balance for %s ended on the upper end of its search, "
                 "%g: even that leaves less residual than noise sigma %g explains (sigma too "
                 "large?); the result is smoothed more than the noise asks",
                 what, balance, sigma);
        return "upper";
    }
    return NULL;
}

int cli_parse_int(const cli_run *run, const char *option, const char *text, int min, int max,
                  int *out)
{
    char *end = NULL;
    errno = 0;
    long v = strtol(text, &end, 10);
    if (end == text || *end != '\0' || errno == ERANGE)
        return cli_error(run, "%s: '%s' is not an integer", option, text);
    if (v < min || v > max)
        return cli_error(run, "%s: %ld is out of range (%d to %d)", option, v, min, max);
    *out = (int)v;
    return 0;
}

int cli_parse_choice(const cli_run *run, const char *option, const char *text,
                     const char *const *choices, int *out)
{
    char list[256] = "";
    for (int i = 0; choices[i]; i++) {
        if (strcmp(text, choices[i]) == 0) {
            *out = i;
            return 0;
        }
        size_t n = strlen(list);
        snprintf(list + n, sizeof list - n, "%s%s", i ? ", " : "", choices[i]);
    }
    return cli_error(run, "%s: unknown value '%s' (expected one of: %s)", option, text, list);
}

static const char *const boundary_names[] = {"zero", "mirror", "periodic", NULL};

int cli_parse_boundary(const cli_run *run, const char *option, const char *text, svp_boundary *out)
{
    int i = 0;
    if (cli_parse_choice(run, option, text, boundary_names, &i)) return CLI_EXIT_USAGE;
    *out = (svp_boundary)i;
    return 0;
}

const char *cli_boundary_name(svp_boundary b)
{
    return (unsigned)b < 3 ? boundary_names[b] : "unknown";
}

static void dir_of(const char *path, char *dir, size_t size);

/* Applies --threads, --fft and --wisdom once all options are known. */
static int apply_common(cli_run *run)
{
    if (run->threads > 0) svp_set_threads(run->threads);
    svp_set_fft_effort(run->fft_measure ? SVP_FFT_MEASURE : SVP_FFT_ESTIMATE);
    svp_set_fft_plan_callback(cli_plan_callback, run);
    if (run->wisdom) {
        /* the wisdom is saved at the end of a successful run: a path that cannot be written is
         * refused now, before any work or output, not after all outputs were written */
        struct stat st_w;
        if (stat(run->wisdom, &st_w) == 0) {
            if (S_ISDIR(st_w.st_mode))
                return cli_error(run, "--wisdom %s: is a folder, not a file", run->wisdom);
            if (access(run->wisdom, R_OK | W_OK) != 0)
                return cli_error(run,
                                 "--wisdom %s: the wisdom file is not readable and writable (%s)",
                                 run->wisdom, strerror(errno));
        } else {
            char dir[PATH_MAX];
            dir_of(run->wisdom, dir, sizeof dir);
            struct stat st_d;
            if (stat(dir, &st_d) != 0 || !S_ISDIR(st_d.st_mode))
                return cli_error(run,
                                 "--wisdom %s: the folder %s does not exist (the wisdom file is "
                                 "saved there after the run; it is not created)",
                                 run->wisdom, dir);
            if (access(dir, W_OK | X_OK) != 0)
                return cli_error(run, "--wisdom %s: the folder %s is not writable (%s)",
                                 run->wisdom, dir, strerror(errno));
        }
    }
    if (run->wisdom && access(run->wisdom, F_OK) == 0) {
        svp_status st = svp_fft_wisdom_load(run->wisdom);
        if (st != SVP_OK) return cli_fail(run, st, run->wisdom);
    }
    /* the wisdom cache: commands that take --fft, when measuring, without --wisdom FILE */
    if ((run->common & CLI_COMMON_FFT) && run->fft_measure && !run->wisdom &&
        !run->no_wisdom_cache && !cli_wisdom_cache_disabled())
        cli_wisdom_cache_open(run);
    return 0;
}

int cli_next_option(cli_run *run, const struct option *own)
{
    struct option opts[MAX_OPTIONS];
    int n = 0;
    for (; own && own[n].name && n < MAX_OPTIONS - 12; n++) opts[n] = own[n];
    opts[n++] = (struct option){"help", no_argument, NULL, 'h'};
    opts[n++] = (struct option){"quiet", no_argument, NULL, 'q'};
    opts[n++] = (struct option){"threads", required_argument, NULL, OPT_THREADS};
    if (run->common & CLI_COMMON_OUTPUT) {
        opts[n++] = (struct option){"output", required_argument, NULL, 'o'};
        opts[n++] = (struct option){"force", no_argument, NULL, OPT_FORCE};
    }
    if (run->common & CLI_COMMON_FORMAT)
        opts[n++] = (struct option){"format", required_argument, NULL, OPT_FORMAT};
    if (run->common & CLI_COMMON_FFT) {
        opts[n++] = (struct option){"wisdom", required_argument, NULL, OPT_WISDOM};
        opts[n++] = (struct option){"fft", required_argument, NULL, OPT_FFT};
        opts[n++] = (struct option){"no-wisdom-cache", no_argument, NULL, OPT_NO_WISDOM_CACHE};
    }
    opts[n] = (struct option){NULL, 0, NULL, 0};
    const char *shorts = (run->common & CLI_COMMON_OUTPUT) ? ":hqo:" : ":hq";

    if (run->argc > 0 && optind == 0) optind = 1;
    opterr = 0;
    for (;;) {
        int c = getopt_long(run->argc, run->argv, shorts, opts, NULL);
        const char *text = optind > 0 && optind <= run->argc ? run->argv[optind - 1] : "?";
        switch (c) {
        case -1: return apply_common(run) ? CLI_OPTION_ERROR : CLI_OPTIONS_DONE;
        case '?':
            if (optopt && optopt < 256 && text[0] == '-' && text[1] != '-')
                cli_error(run, "unknown option -%c (see svpsf %s --help)", optopt, run->command);
            else
                cli_error(run, "unknown option %s (see svpsf %s --help)", text, run->command);
            return CLI_OPTION_ERROR;
        case ':':
            cli_error(run, "option %s needs a value (see svpsf %s --help)", text, run->command);
            return CLI_OPTION_ERROR;
        case 'h': return CLI_OPTION_HELP;
        case 'q': run->quiet = 1; break;
        case 'o': run->output = optarg; break;
        case OPT_FORCE: run->force = 1; break;
        case OPT_THREADS:
            if (cli_parse_int(run, "--threads", optarg, 1, 4096, &run->threads))
                return CLI_OPTION_ERROR;
            break;
        case OPT_FORMAT: {
            static const char *const names[] = {"tif", "npy", "txt", "tiff", "mat", NULL};
            static const svp_file_format formats[] = {SVP_FORMAT_TIFF, SVP_FORMAT_NPY,
                                                      SVP_FORMAT_TXT, SVP_FORMAT_TIFF,
                                                      SVP_FORMAT_MAT};
            int i = 0;
            if (cli_parse_choice(run, "--format", optarg, names, &i)) return CLI_OPTION_ERROR;
            run->format = formats[i];
            run->format_given = 1;
            break;
        }
        case OPT_WISDOM: run->wisdom = optarg; break;
        case OPT_NO_WISDOM_CACHE: run->no_wisdom_cache = 1; break;
        case OPT_FFT: {
            static const char *const names[] = {"estimate", "measure", NULL};
            int i = 0;
            if (cli_parse_choice(run, "--fft", optarg, names, &i)) return CLI_OPTION_ERROR;
            run->fft_measure = i;
            break;
        }
        default: return c;
        }
    }
}

void cli_print_common_help(const cli_run *run, FILE *out)
{
    if (run->common & CLI_COMMON_FORMAT)
        fputs("  --format tif|npy|txt|mat  format of the image outputs: float32 TIFF, float64\n"
              "                        .npy, numpy.savetxt text, or MATLAB .mat (one variable\n"
              "                        named after the file; default tif)\n",
              out);
    if (run->common & CLI_COMMON_OUTPUT)
        fputs("  --force               overwrite existing outputs (default: refuse, and write\n"
              "                        nothing when any output exists)\n",
              out);
    fprintf(out,
            "  --threads N           threads for FFTs and loops (default: all cores, %d here)\n",
            svp_get_threads());
    if (run->common & CLI_COMMON_FFT)
        fprintf(out,
                "  --fft estimate|measure  FFT planning: measure is slower to plan, faster to\n"
                "                        run (default %s)\n"
                "  --wisdom FILE         load FFTW wisdom from FILE when it exists and save it\n"
                "                        there after a successful run; FILE's folder must\n"
                "                        exist (checked before any work) (default: the cache)\n"
                "  --no-wisdom-cache     do not load or save the FFTW wisdom cache\n"
                "                        ($XDG_CACHE_HOME/svpsf/wisdom, else\n"
                "                        ~/.cache/svpsf/wisdom; also SVPSF_NO_WISDOM_CACHE=1),\n"
                "                        used when measuring without --wisdom\n",
                run->fft_measure ? "measure" : "estimate");
    fputs("  -q, --quiet           no progress and no notes on stderr (errors still shown)\n"
          "  -h, --help            this help\n",
          out);
}

void cli_path_stem(const char *path, char *stem, size_t size)
{
    char file[PATH_MAX], var[64];
    int bad = 0;
    if (svp_io_mat_path(path, file, sizeof file, var, sizeof var, &bad) && var[0]) {
        /* "DIR/Q.mat:Bz" -> "Q_Bz" */
        char fstem[256];
        cli_path_stem(file, fstem, sizeof fstem);
        snprintf(stem, size, "%s_%s", fstem, var);
        return;
    }
    const char *base = strrchr(path, '/');
    base = base ? base + 1 : path;
    const char *dot = strrchr(base, '.');
    size_t n = dot && dot != base ? (size_t)(dot - base) : strlen(base);
    if (n >= size) n = size - 1;
    memcpy(stem, base, n);
    stem[n] = '\0';
}

size_t cli_yaml_extension(const char *path)
{
    size_t n = strlen(path);
    if (n > 5 && strcmp(path + n - 5, ".yaml") == 0) return 5;
    if (n > 4 && strcmp(path + n - 4, ".yml") == 0) return 4;
    return 0;
}

void cli_path_sibling(const char *path, const char *ext, char *buf, size_t size)
{
    snprintf(buf, size, "%.*s%s", (int)(strlen(path) - cli_yaml_extension(path)), path, ext);
}

const char *const cli_psf_model_names[] = {"gaussian", "lorentzian", "moffat", NULL};
const char *const cli_precision_names[] = {"double", "single", NULL};

/* ---- inputs --------------------------------------------------------------------------------- */

static long long file_size(const char *path)
{
    struct stat st;
    char file[PATH_MAX], var[64];
    int bad = 0;
    if (stat(path, &st) != 0 && svp_io_mat_path(path, file, sizeof file, var, sizeof var, &bad))
        path = file; /* "FILE.mat:VAR" */
    return stat(path, &st) == 0 ? (long long)st.st_size : -1;
}

void cli_record_input(cli_run *run, const char *role, const char *path, int width, int height)
{
    run->inputs = xrealloc(run->inputs, (size_t)(run->n_inputs + 1) * sizeof *run->inputs);
    cli_input *in = &run->inputs[run->n_inputs++];
    in->role = xstrdup(role);
    in->path = xstrdup(path);
    in->width = width;
    in->height = height;
    in->bytes = file_size(path);
    in->n_nonfinite = 0;
    in->pixel_um = 0;
}

/* Whether path names a MATLAB file (FILE.mat[:VAR]): read through svp_mat_read(_stack), which
 * also say its pixel size (`step`). A malformed ":VAR" is left to the generic reader's message. */
static int is_mat_input(const char *path)
{
    char file[PATH_MAX], var[64];
    int bad = 0;
    return svp_io_mat_path(path, file, sizeof file, var, sizeof var, &bad) && !bad;
}

/* A read input recorded with its size and a MATLAB file's pixel size; the new record. */
static cli_input *record_read(cli_run *run, const char *role, const char *path, int width,
                              int height, double pixel_um)
{
    cli_record_input(run, role, path, width, height);
    cli_input *in = &run->inputs[run->n_inputs - 1];
    in->pixel_um = pixel_um;
    return in;
}

int cli_read_image_info(cli_run *run, const char *role, const char *path, svp_image **out,
                        svp_mat_info *info_out)
{
    *out = NULL;
    svp_mat_info info;
    memset(&info, 0, sizeof info);
    svp_status st = is_mat_input(path) ? svp_mat_read(path, NULL, out, &info)
                                       : svp_image_read(path, out);
    if (info_out) *info_out = info;
    if (st != SVP_OK) return cli_fail(run, st, path);
    record_read(run, role, path, (*out)->width, (*out)->height, info.pixel_um)->n_nonfinite =
        (long long)svp_image_count_nonfinite(*out);
    return 0;
}

int cli_read_image(cli_run *run, const char *role, const char *path, svp_image **out)
{
    return cli_read_image_info(run, role, path, out, NULL);
}

int cli_read_stack(cli_run *run, const char *role, const char *path, svp_stack **out)
{
    *out = NULL;
    svp_mat_info info = {.pixel_um = 0};
    svp_status st = is_mat_input(path) ? svp_mat_read_stack(path, NULL, out, &info)
                                       : svp_stack_read(path, out);
    if (st != SVP_OK) return cli_fail(run, st, path);
    record_read(run, role, path, (*out)->width, (*out)->height, info.pixel_um);
    return 0;
}

int cli_check_input_pixels(cli_run *run, double psf_pixel_um, const char *psf_path)
{
    if (!(psf_pixel_um > 0)) return 0;
    for (int i = 0; i < run->n_inputs; i++) {
        const cli_input *in = &run->inputs[i];
        if (in->pixel_um > 0 && fabs(in->pixel_um / psf_pixel_um - 1) > CLI_PIXEL_AGREE)
            return cli_error(run,
                             "%s %s holds `step` = %g um (its pixel size), but the PSF file %s "
                             "is for pixels of %g um: the PSF would be applied at the wrong "
                             "scale (give a PSF file for the map's pixels)",
                             in->role, in->path, in->pixel_um, psf_path, psf_pixel_um);
    }
    return 0;
}

int cli_check_same_size(const cli_run *run, const svp_image *a, const char *role_a,
                        const char *path_a, const svp_image *b, const char *role_b,
                        const char *path_b)
{
    if (a->width == b->width && a->height == b->height) return 0;
    return cli_error(run, "size mismatch: %s %s is %d x %d (width x height) but %s %s is %d x %d",
                     role_a, path_a, a->width, a->height, role_b, path_b, b->width, b->height);
}

static int has_extension(const char *path, const char *ext)
{
    const char *dot = strrchr(path, '.');
    const char *slash = strrchr(path, '/');
    if (!dot || (slash && dot < slash)) return 0;
    return strcasecmp(dot + 1, ext) == 0;
}

/* A YAML PSF file is a PSF map when it has a top-level `kind` (svp_psf_field_read), else a
 * plain PSF file (svp_psf_file_read): *is_map says which. Returns the exit code (0: read). */
static int yaml_is_psf_map(cli_run *run, const char *path, int *is_map)
{
    svp_yaml_doc *doc = NULL;
    svp_status st = svp_yaml_load_file(path, &doc);
    if (st != SVP_OK) return cli_fail(run, st, path);
    *is_map = svp_yaml_get(svp_yaml_root(doc), "kind") != NULL;
    svp_yaml_free(doc);
    return 0;
}

/* A PSF map of kind uniform as one PSF (the invariant operator); frees the field. */
static int uniform_map_psf(cli_run *run, const char *path, svp_psf_field *field, cli_psf *psf)
{
    svp_status st = svp_psf_field_at(field, 0, 0, &psf->model);
    svp_psf_field_free(field);
    if (st != SVP_OK) return cli_fail(run, st, path);
    psf->is_model = 1;
    psf->boundary = SVP_BOUNDARY_ZERO;
    return 0;
}

int cli_psf_load(cli_run *run, const char *path, cli_psf *psf)
{
    memset(psf, 0, sizeof *psf);
    psf->path = path;
    if (has_extension(path, "yaml") || has_extension(path, "yml")) {
        int is_map = 0, code = yaml_is_psf_map(run, path, &is_map);
        if (code) return code;
        if (is_map) {
            /* of kind uniform it is one PSF (as for forward/correct); a map that varies is
             * refused with what to do instead */
            svp_psf_field *field = NULL;
            svp_status st = svp_psf_field_read(path, &field, &psf->pixel_um);
            if (st != SVP_OK) return cli_fail(run, st, path);
            static const char *const kinds[] = {"uniform", "grid", "poly", "regions"};
            const svp_psf_field_kind kind = svp_psf_field_get_kind(field);
            if (kind == SVP_FIELD_UNIFORM) {
                code = uniform_map_psf(run, path, field, psf);
                if (!code) cli_record_input(run, "psf", path, 0, 0);
                return code;
            }
            svp_psf_field_free(field);
            return cli_error(run,
                             "%s is a PSF map (kind %s: a PSF that may vary across the field); "
                             "svpsf %s takes a single PSF file (pixel_um and psf) or a kernel "
                             "image; PSF maps are taken by svpsf forward --psf MAP.yaml and "
                             "svpsf correct --psf MAP.yaml (docs/cli.md, PSF-map files)",
                             path, kinds[kind & 3], run->command);
        }
        svp_psf_defaults(&psf->model);
        psf->boundary = (svp_boundary)-1;
        svp_status st = svp_psf_file_read(path, &psf->model, &psf->pixel_um, &psf->boundary);
        if (st != SVP_OK) return cli_fail(run, st, path);
        psf->is_model = 1;
        psf->has_boundary = (unsigned)psf->boundary < 3;
        if (!psf->has_boundary) psf->boundary = SVP_BOUNDARY_ZERO;
        cli_record_input(run, "psf", path, 0, 0);
        return 0;
    }
    int code = cli_read_image(run, "psf", path, &psf->kernel_raw);
    if (code) return code;
    const svp_image *k = psf->kernel_raw;
    size_t n = (size_t)k->width * k->height;
    if (svp_image_count_nonfinite(k))
        return cli_error(run, "%s: the PSF kernel has NaN or Inf pixels", path);
    double sum = 0;
    for (size_t i = 0; i < n; i++) sum += k->data[i];
    if (!(sum > 0))
        return cli_error(run,
                         "%s: the PSF kernel sums to %g: it cannot be normalised to unit "
                         "sum",
                         path, sum);
    psf->kernel_sum = sum;
    size_t n_neg = 0;
    double neg = 0, lowest = 0;
    for (size_t i = 0; i < n; i++)
        if (k->data[i] < 0) {
            n_neg++;
            neg -= k->data[i];
            lowest = fmin(lowest, k->data[i]);
        }
    if (n_neg)
        cli_warn(run,
                 "%s: the PSF kernel has %zu negative pixels (down to %.3g; together %.3g of its "
                 "sum): Richardson-Lucy assumes a non-negative PSF, and a negative ring can make "
                 "it lose the light (docs/model.md §3); subtract less background or clip them",
                 path, n_neg, lowest, neg / sum);
    if (k->width % 2 == 0 || k->height % 2 == 0)
        cli_warn(run,
                 "%s: the kernel is %d x %d: an even side has no middle pixel, so its centre is "
                 "taken as pixel (%d, %d), half a pixel from its geometric centre (odd sizes are "
                 "symmetric; docs/cli.md)",
                 path, k->width, k->height, k->width / 2, k->height / 2);
    return 0;
}

/* BYTES with an optional suffix k, M, G, T (powers of 1024): 0, else 1. */
static int parse_bytes(const char *arg, double *bytes)
{
    char *end = NULL;
    double v = strtod(arg, &end);
    if (end == arg || !(v > 0) || !isfinite(v)) return 1;
    static const char suffix[] = "kMGT";
    if (*end) {
        const char *q = strchr(suffix, *end == 'K' ? 'k' : *end);
        if (!q || end[1] != '\0') return 1;
        v *= pow(1024.0, (double)(q - suffix + 1));
    }
    *bytes = v;
    return 0;
}

/* The memory building a space-variant operator needs, estimated from below before it is built
 * (docs/reliability.md): one spectrum per term (tent node or eigen-PSF) of a frame at least the
 * image plus the kernel radius, twice over while they are made, the low-rank build's eigen-PSF
 * halves, and ten images for the solvers. A representation chosen by --operator-tol is sized
 * by the library itself (svp_variant_info.peak_bytes against max_memory). */
static svp_status check_variant_memory(const cli_psf *psf, int width, int height)
{
    const svp_variant_options *v = &psf->variant;
    const double w = width, h = height;
    const double gx = v->grid_x < width ? v->grid_x : width;
    const double gy = v->grid_y < height ? v->grid_y : height;
    const int lowrank = v->representation == SVP_VARIANT_LOWRANK;
    const double terms = lowrank ? v->rank : gx * gy;
    double r = v->support;
    svp_psf centre;
    if (!(r > 0) && svp_psf_field_at(psf->field, (w - 1) / 2, (h - 1) / 2, &centre) == SVP_OK)
        r = centre.support;
    const double rx = r > 0 && ceil(r) < w - 1 ? ceil(r) : w - 1;
    const double ry = r > 0 && ceil(r) < h - 1 ? ceil(r) : h - 1;
    const double frame = (w + rx) * (h + ry);
    double bytes = 2.0 * terms * 8.0 * frame + 10.0 * 8.0 * w * h;
    if (lowrank) bytes += terms * (2 * rx + 1) * (ry + 1) * 8.0;
    char what[160];
    snprintf(what, sizeof what,
             "building the space-variant operator (%.0f %s on a frame of at least %.0f x %.0f "
             "pixels)",
             terms, lowrank ? "eigen-PSFs" : "tent nodes", w + rx, h + ry);
    return svp_io_check_memory(psf->path, what, bytes);
}

/* The memory an invariant operator and the deconvolutions on it need, estimated from below
 * before anything is built (docs/reliability.md): the rendered kernel (every offset its support
 * reaches, at most the view's), the OTF and two FFT work frames of at least the image plus that
 * radius, and twelve images for the solvers (RL's iterate, ratio and acceleration buffers, the
 * maps in and out). */
static svp_status check_invariant_memory(const cli_psf *psf, int width, int height)
{
    const double w = width, h = height;
    double rx = w - 1, ry = h - 1;
    if (psf->is_model && psf->model.support > 0) {
        rx = fmin(rx, ceil(psf->model.support));
        ry = fmin(ry, ceil(psf->model.support));
    } else if (!psf->is_model && psf->kernel_raw) {
        rx = fmin(rx, psf->kernel_raw->width / 2);
        ry = fmin(ry, psf->kernel_raw->height / 2);
    }
    const double frame = (w + rx) * (h + ry);
    const double bytes = 8.0 * (2 * rx + 1) * (2 * ry + 1) + 8.0 * frame * 3 + 12.0 * 8.0 * w * h;
    char what[160];
    snprintf(what, sizeof what,
             "the blur operator and its deconvolutions (a frame of at least %.0f x %.0f pixels)",
             w + rx, h + ry);
    return svp_io_check_memory(psf->path, what, bytes);
}

/* The last space-variant operator's measured application and adjoint times (cli_psf_blur), for
 * its report sentence (cli_variant_sentence). */
static struct {
    const svp_blur *blur;
    double apply_s, adjoint_s;
} last_times;

/* One application H x and one adjoint Hᵀ x of a space-variant operator, timed on a constant
 * image (the cost does not depend on the values): what one of the correction's iterations
 * costs, recorded in the summary and the report. */
static void time_variant_apply(cli_run *run, svp_blur *blur)
{
    svp_image *x = NULL, *y = NULL;
    const int w = svp_blur_width(blur), h = svp_blur_height(blur);
    if (svp_image_new(w, h, &x) != SVP_OK || svp_image_new(w, h, &y) != SVP_OK) {
        svp_image_free(x);
        return; /* only a figure of the report is lost */
    }
    for (size_t i = 0; i < (size_t)w * h; i++) x->data[i] = 1.0;
    const double t0 = cli_now();
    const int ok = svp_blur_apply(blur, x, y) == SVP_OK;
    const double t1 = cli_now();
    const int ok_adj = ok && svp_blur_adjoint(blur, x, y) == SVP_OK;
    const double t2 = cli_now();
    svp_image_free(x);
    svp_image_free(y);
    if (!ok || !ok_adj) return;
    last_times.blur = blur;
    last_times.apply_s = t1 - t0;
    last_times.adjoint_s = t2 - t1;
    cli_setting_num(run, "operator_apply_s", t1 - t0);
    cli_setting_num(run, "operator_adjoint_s", t2 - t1);
}

int cli_correct_applications(const svp_correct_options *o, int n_fields)
{
    /* a Wiener deconvolution of a space-variant operator is CG on the normal equations: about
     * 40 steps of one H and one Hᵀ each (20-80 measured, docs/model.md §6), 17 solves with
     * the discrepancy principle's search */
    const int cg = 40 * (o->balance_auto ? 17 : 1);
    const int rl = o->deconv.iterations;
    long pairs;
    switch (o->method) {
    case SVP_METHOD_RW: pairs = rl + (long)n_fields * cg; break;
    case SVP_METHOD_W: pairs = (long)(1 + n_fields) * cg; break;
    default: pairs = (long)(1 + n_fields) * rl; break; /* R, RL_SIGNED */
    }
    return pairs > 1000000 ? 1000000 : (int)(pairs > 1 ? pairs : 1);
}

int cli_psf_blur(cli_run *run, const cli_psf *psf, int width, int height, svp_boundary boundary,
                 svp_blur **out)
{
    if (!psf->field) {
        svp_status mst = check_invariant_memory(psf, width, height);
        if (mst != SVP_OK) return cli_fail(run, mst, NULL);
    }
    svp_status st;
    if (psf->field) {
        svp_variant_options vo = psf->variant;
        const char *env = getenv("SVPSF_MAX_MEMORY");
        if (vo.max_memory == 0 && env && *env && parse_bytes(env, &vo.max_memory))
            return cli_error(run,
                             "SVPSF_MAX_MEMORY='%s' is not a size in bytes (a number > 0, "
                             "optionally with k, M, G or T: powers of 1024)",
                             env);
        /* automatic and regions: sized by the library itself (peak_bytes vs max_memory) */
        if (vo.representation != SVP_VARIANT_AUTO && vo.representation != SVP_VARIANT_REGIONS &&
            (st = check_variant_memory(psf, width, height)) != SVP_OK)
            return cli_fail(run, st, NULL);
        st = svp_blur_new_field(psf->field, width, height, boundary, &vo, out);
        svp_variant_info in;
        if (st == SVP_OK && svp_blur_variant_info(*out, &in) == SVP_OK) {
            const int lowrank = in.representation == SVP_VARIANT_LOWRANK;
            const int regions = in.representation == SVP_VARIANT_REGIONS;
            char buf[64];
            if (!isfinite(in.estimated_error) &&
                svp_variant_estimate(psf->field, width, height, boundary, &vo,
                                     &in.estimated_error) != SVP_OK)
                in.estimated_error = NAN;
            cli_setting_int(run, "psf_operator_bytes", (long long)in.memory_bytes);
            cli_setting_str(run, "psf_representation",
                            regions ? "regions" : lowrank ? "low rank" : "tent");
            cli_setting_str(run, "psf_representation_chosen_by",
                            vo.representation == SVP_VARIANT_AUTO ? "operator-tol" : "option");
            snprintf(buf, sizeof buf, "%d x %d", in.grid_x, in.grid_y);
            if (regions)
                cli_setting_int(run, "psf_region_kernels", in.rank);
            else
                cli_setting_str(run, lowrank ? "psf_samples" : "psf_nodes", buf);
            if (lowrank) cli_setting_int(run, "psf_rank", in.rank);
            if (vo.representation == SVP_VARIANT_AUTO) {
                cli_setting_num(run, "operator_tolerance", in.tolerance);
                cli_setting_int(run, "operator_tolerance_met", in.tolerance_met);
                cli_setting_int(run, "operator_candidates", in.candidates);
                cli_setting_num(run, "operator_estimate_s", in.estimate_seconds);
            }
            if (isfinite(in.estimated_error))
                cli_setting_num(run, "operator_estimated_error", in.estimated_error);
            cli_setting_num(run, "operator_build_s", in.build_seconds);
            cli_setting_int(run, "operator_peak_bytes_estimate", (long long)in.peak_bytes);
            if (vo.max_memory > 0) cli_setting_num(run, "max_memory_bytes", vo.max_memory);
            cli_setting_int(run, "operator_applications", vo.applications);
            if (vo.applications > 1) time_variant_apply(run, *out);
        }
    } else if (psf->is_model)
        st = svp_blur_new(&psf->model, width, height, boundary, out);
    else
        st = svp_blur_new_kernel(psf->kernel_raw, -1, -1, 1, width, height, boundary, out);
    if (st != SVP_OK) return cli_fail(run, st, psf->path);
    return 0;
}

void cli_psf_release(cli_psf *psf)
{
    svp_image_free(psf->kernel_raw);
    psf->kernel_raw = NULL;
    svp_psf_field_free(psf->field);
    psf->field = NULL;
}

void cli_variant_sentence(const svp_blur *blur, char *buf, size_t size)
{
    svp_variant_info in;
    buf[0] = '\0';
    if (!blur || svp_blur_variant_info(blur, &in) != SVP_OK) {
        return;
    }
    char what[96], err[96] = "";
    if (in.representation == SVP_VARIANT_REGIONS)
        snprintf(what, sizeof what, "regions (%d region kernel%s)", in.rank,
                 in.rank == 1 ? "" : "s");
    else if (in.representation == SVP_VARIANT_LOWRANK)
        snprintf(what, sizeof what, "low rank %d (%d x %d samples)", in.rank, in.grid_x,
                 in.grid_y);
    else
        snprintf(what, sizeof what, "tent %d x %d", in.grid_x, in.grid_y);
    if (isfinite(in.estimated_error) && in.tolerance > 0)
        snprintf(err, sizeof err, ", estimated error %.2g (budget %.2g%s)", in.estimated_error,
                 in.tolerance, in.tolerance_met ? "" : ", not met: the cheapest near the smallest error");
    else if (isfinite(in.estimated_error))
        snprintf(err, sizeof err, ", estimated error %.2g", in.estimated_error);
    char apply[96] = "";
    if (last_times.blur == blur)
        snprintf(apply, sizeof apply, ", one application %.3f s (adjoint %.3f s)",
                 last_times.apply_s, last_times.adjoint_s);
    snprintf(buf, size, " Operator: %s%s, built in %.2f s%s, %.0f MB.", what, err,
             in.build_seconds, apply, in.memory_bytes / 1e6);
}

void cli_variant_defaults(svp_variant_options *variant)
{
    svp_variant_defaults(variant);
    variant->samples_x = variant->grid_x;
    variant->samples_y = variant->grid_y;
}

int cli_variant_option(const cli_run *run, svp_variant_options *variant, int option,
                       const char *arg)
{
    if (option == CLI_OPT_REGIONS) {
        if (variant->representation == SVP_VARIANT_TENT ||
            variant->representation == SVP_VARIANT_LOWRANK)
            return cli_error(run, "--regions cannot be combined with --nodes or --rank");
        variant->representation = SVP_VARIANT_REGIONS;
        return 0;
    }
    if ((option == CLI_OPT_RANK || option == CLI_OPT_NODES) &&
        variant->representation == SVP_VARIANT_REGIONS)
        return cli_error(run, "%s cannot be combined with --regions",
                         option == CLI_OPT_RANK ? "--rank" : "--nodes");
    if (option == CLI_OPT_RANK) {
        if (cli_parse_int(run, "--rank", arg, 1, 4096, &variant->rank)) return CLI_EXIT_USAGE;
        variant->representation = SVP_VARIANT_LOWRANK;
        return 0;
    }
    if (option == CLI_OPT_OPERATOR_TOL) {
        char *end = NULL;
        const double t = strtod(arg, &end);
        if (end == arg || *end != '\0' || !(t > 0) || !(t < 1))
            return cli_error(run, "--operator-tol: '%s' is not a number in (0, 1)", arg);
        variant->tolerance = t;
        return 0;
    }
    if (option == CLI_OPT_MAX_MEMORY) {
        if (parse_bytes(arg, &variant->max_memory))
            return cli_error(run,
                             "--max-memory: '%s' is not a size in bytes (a number > 0, optionally "
                             "with k, M, G or T: powers of 1024)",
                             arg);
        return 0;
    }
    /* --nodes N or NxM */
    int nx = 0, ny = 0, used = 0;
    if (sscanf(arg, "%d%n", &nx, &used) == 1 && arg[used] == '\0')
        ny = nx;
    else if (!(sscanf(arg, "%dx%d%n", &nx, &ny, &used) == 2 && arg[used] == '\0'))
        return cli_error(run, "--nodes: '%s' is not N or NxM (e.g. 8x8)", arg);
    if (nx < 1 || ny < 1 || nx > 64 || ny > 64)
        return cli_error(run, "--nodes %s: each side must be in 1..64", arg);
    if (variant->representation != SVP_VARIANT_LOWRANK) variant->representation = SVP_VARIANT_TENT;
    variant->grid_x = variant->samples_x = nx;
    variant->grid_y = variant->samples_y = ny;
    return 0;
}

void cli_print_variant_help(FILE *out, double default_tol)
{
    fputs("PSF maps (--psf a PSF-map YAML file of kind grid, poly or regions; docs/cli.md):\n"
          "  --nodes NxM           tent node grid of the space-variant operator (default 8x8;\n"
          "                        N alone = NxN; error falls as the node spacing squared)\n"
          "  --rank R              use the low-rank (eigen-PSF) operator with R terms instead,\n"
          "                        the PSF sampled on the --nodes grid (R <= N M)\n"
          "  --regions             one kernel per region (label) of a map of kind regions:\n"
          "                        exact for sharp region boundaries\n"
          "  --operator-tol TOL    without --nodes / --rank / --regions: the cheapest tent\n"
          "                        grid, low rank or (region maps) regions whose estimated\n"
          "                        relative operator error is <= TOL (default\n",
          out);
    fprintf(out, "                        %g; docs/model.md section 9)\n", default_tol);
    fputs("  --max-memory BYTES    refuse an operator needing more (suffix k, M, G, T; default\n"
          "                        $SVPSF_MAX_MEMORY, else the physical memory)\n",
          out);
}

int cli_psf_pad(cli_run *run, cli_psf *psf, int margin)
{
    if (!psf->field || margin <= 0) return 0;
    svp_psf_field *padded = NULL;
    svp_status st = svp_psf_field_pad(psf->field, margin, &padded);
    if (st != SVP_OK) return cli_fail(run, st, psf->path);
    svp_psf_field_free(psf->field);
    psf->field = padded;
    return 0;
}

int cli_psf_check(const cli_run *run, const cli_psf *psf, int width, int height)
{
    if (!psf->field) return 0;
    const int fw = svp_psf_field_width(psf->field), fh = svp_psf_field_height(psf->field);
    if (fw != 0 && (fw != width || fh != height))
        return cli_error(run,
                         "%s: the PSF map is for a %d x %d image but the inputs are %d x %d "
                         "(width x height)",
                         psf->path, fw, fh, width, height);
    const svp_variant_options *v = &psf->variant;
    if (v->representation == SVP_VARIANT_LOWRANK && v->rank > v->samples_x * v->samples_y)
        return cli_error(run,
                         "%s: low rank %d: must be in 1..%d (the number of sampled PSFs, %d x %d; "
                         "see --nodes)",
                         psf->path, v->rank, v->samples_x * v->samples_y, v->samples_x,
                         v->samples_y);
    return 0;
}

void cli_psf_range_text(const svp_psf_field_range *r, double pixel_um, char *what, size_t size)
{
    static const char *const names[SVP_FIELD_NPARAM] = {"the FWHM", "the ellipticity", "",
                                                        "beta", "the halo"};
    size_t at = 0;
    what[0] = '\0';
    for (int q = 0; q < SVP_FIELD_NPARAM && at < size; q++) {
        if (!r->count[q]) continue;
        const char *dir = r->value[q] < r->bound[q] ? "down" : "up";
        if (q == SVP_FIELD_FWHM)
            at += (size_t)snprintf(what + at, size - at,
                                   "%s%s %s to %.3g um at pixel (%d, %d), clamped to %.3g um",
                                   at ? "; " : "", names[q], dir, r->value[q] * pixel_um, r->x[q],
                                   r->y[q], r->bound[q] * pixel_um);
        else
            at += (size_t)snprintf(what + at, size - at,
                                   "%s%s %s to %.3g at pixel (%d, %d), clamped to %.3g",
                                   at ? "; " : "", names[q], dir, r->value[q], r->x[q], r->y[q],
                                   r->bound[q]);
    }
}

void cli_psf_map_range_warning(const cli_run *run, const char *path, const svp_psf_field *field,
                               double pixel_um)
{
    svp_psf_field_range r;
    if (svp_psf_field_check_range(field, NULL, &r) != SVP_OK || !r.clamped) return;
    char what[700];
    cli_psf_range_text(&r, pixel_um, what, sizeof what);
    cli_warn(run,
             "%s: the PSF map's parameters leave their valid range on %.3g %% of its pixels and "
             "are clamped there (%s): a polynomial extrapolated beyond the spots it was fitted "
             "to? The PSF there is not the file's; map with spots that cover the view, a lower "
             "degree, or a grid map",
             path, 100.0 * (double)r.clamped / (double)r.sampled, what);
}

int cli_psf_load_map(cli_run *run, const char *path, const svp_variant_options *variant,
                     cli_psf *psf)
{
    if (!(has_extension(path, "yaml") || has_extension(path, "yml")))
        return cli_psf_load(run, path, psf);
    /* a plain PSF file (it may name a boundary) as one PSF; a PSF map */
    int is_map = 0, code = yaml_is_psf_map(run, path, &is_map);
    if (code) return code;
    if (!is_map) return cli_psf_load(run, path, psf);
    memset(psf, 0, sizeof *psf);
    psf->path = path;
    psf->variant = *variant;
    psf->boundary = SVP_BOUNDARY_ZERO;
    svp_psf_field *field = NULL;
    svp_status st = svp_psf_field_read(path, &field, &psf->pixel_um);
    if (st != SVP_OK) return cli_fail(run, st, path);
    cli_record_input(run, "psf", path, svp_psf_field_width(field), svp_psf_field_height(field));
    cli_psf_map_range_warning(run, path, field, psf->pixel_um);
    /* one PSF everywhere: the invariant operator */
    if (svp_psf_field_get_kind(field) == SVP_FIELD_UNIFORM)
        return uniform_map_psf(run, path, field, psf);
    psf->field = field;
    return 0;
}

void cli_psf_describe(cli_run *run, const cli_psf *psf)
{
    cli_setting_str(run, "psf_file", psf->path);
    if (psf->field) {
        static const char *kinds[] = {"uniform", "grid", "poly", "regions"};
        const svp_variant_options *v = &psf->variant;
        const int lowrank = v->representation == SVP_VARIANT_LOWRANK;
        char buf[64];
        svp_psf centre;
        cli_setting_str(run, "psf_kind", "map");
        cli_setting_str(run, "psf_map_kind", kinds[svp_psf_field_get_kind(psf->field) & 3]);
        cli_setting_num(run, "pixel_um", psf->pixel_um);
        if (svp_psf_field_at(psf->field, 0.5 * (svp_psf_field_width(psf->field) - 1),
                             0.5 * (svp_psf_field_height(psf->field) - 1), &centre) == SVP_OK) {
            cli_setting_str(run, "psf_model", cli_psf_model_names[centre.model]);
            cli_setting_num(run, "psf_centre_fwhm_px", centre.fwhm);
            if (centre.model == SVP_PSF_MOFFAT)
                cli_setting_num(run, "psf_centre_beta", centre.beta);
            cli_setting_num(run, "psf_support_px", centre.support);
        }
        if (v->representation == SVP_VARIANT_AUTO) {
            cli_setting_str(run, "psf_representation", "chosen by --operator-tol");
            return; /* the choice is recorded when the operator is built (cli_psf_blur) */
        }
        if (v->representation == SVP_VARIANT_REGIONS) {
            cli_setting_str(run, "psf_representation", "regions");
            return; /* the number of kernels is recorded when it is built (cli_psf_blur) */
        }
        cli_setting_str(run, "psf_representation", lowrank ? "low rank" : "tent");
        snprintf(buf, sizeof buf, "%d x %d", lowrank ? v->samples_x : v->grid_x,
                 lowrank ? v->samples_y : v->grid_y);
        cli_setting_str(run, lowrank ? "psf_samples" : "psf_nodes", buf);
        if (lowrank) cli_setting_int(run, "psf_rank", v->rank);
        return;
    }
    if (!psf->is_model) {
        char buf[64];
        snprintf(buf, sizeof buf, "%d x %d", psf->kernel_raw->width, psf->kernel_raw->height);
        cli_setting_str(run, "psf_kind", "kernel image");
        cli_setting_str(run, "psf_kernel_size", buf);
        cli_setting_num(run, "psf_kernel_sum_as_read", psf->kernel_sum);
        return;
    }
    const svp_psf *p = &psf->model;
    cli_setting_str(run, "psf_kind", "model");
    cli_setting_str(run, "psf_model", cli_psf_model_names[p->model]);
    cli_setting_num(run, "pixel_um", psf->pixel_um);
    cli_setting_num(run, "psf_fwhm_px", p->fwhm);
    if (p->fwhm_minor > 0) {
        cli_setting_num(run, "psf_fwhm_minor_px", p->fwhm_minor);
        cli_setting_num(run, "psf_angle_deg", p->angle * 180.0 / M_PI);
    }
    if (p->model == SVP_PSF_MOFFAT) cli_setting_num(run, "psf_beta", p->beta);
    cli_setting_num(run, "psf_halo", p->halo);
    cli_setting_num(run, "psf_support_px", p->support);
}

/* ---- outputs -------------------------------------------------------------------------------- */

const char *cli_format_extension(svp_file_format format)
{
    switch (format) {
    case SVP_FORMAT_NPY: return "npy";
    case SVP_FORMAT_TXT: return "txt";
    case SVP_FORMAT_MAT: return "mat";
    case SVP_FORMAT_PNG16: return "png";
    default: return "tif";
    }
}

svp_file_format cli_format_of_path(const char *path)
{
    if (has_extension(path, "tif") || has_extension(path, "tiff")) return SVP_FORMAT_TIFF;
    if (has_extension(path, "npy")) return SVP_FORMAT_NPY;
    if (has_extension(path, "txt") || has_extension(path, "csv") || has_extension(path, "dat"))
        return SVP_FORMAT_TXT;
    if (has_extension(path, "png")) return SVP_FORMAT_PNG16;
    if (has_extension(path, "mat")) return SVP_FORMAT_MAT;
    {
        /* "OUT.mat:VAR" names the variable */
        char file[PATH_MAX], var[64];
        int bad = 0;
        if (svp_io_mat_path(path, file, sizeof file, var, sizeof var, &bad)) return SVP_FORMAT_MAT;
    }
    return SVP_FORMAT_AUTO;
}

static const char *add_output(cli_run *run, const char *role, char *path, int exact)
{
    run->outputs = xrealloc(run->outputs, (size_t)(run->n_outputs + 1) * sizeof *run->outputs);
    cli_output *o = &run->outputs[run->n_outputs++];
    o->role = xstrdup(role);
    o->path = path;
    o->exact = exact;
    o->existed = -1;
    return path;
}

const char *cli_output_in_dir(cli_run *run, const char *role, const char *name, int ext_from_format)
{
    const char *dir = run->output ? run->output : ".";
    size_t n = strlen(dir) + strlen(name) + 8;
    char *path = xrealloc(NULL, n);
    int slash = dir[0] && dir[strlen(dir) - 1] == '/';
    if (ext_from_format)
        snprintf(path, n, "%s%s%s.%s", dir, slash ? "" : "/", name,
                 cli_format_extension(run->format));
    else
        snprintf(path, n, "%s%s%s", dir, slash ? "" : "/", name);
    return add_output(run, role, path, 0);
}

const char *cli_output_file(cli_run *run, const char *role, const char *path)
{
    return add_output(run, role, xstrdup(path), 1);
}

/* The folders this process created, in creation order (parents before children): a run that
 * fails removes those still empty (cli_remove_created_dirs), so a failed run writes nothing. */
static char **created_dirs;
static int n_created_dirs;

static void record_created_dir(const char *path)
{
    for (int i = 0; i < n_created_dirs; i++)
        if (strcmp(created_dirs[i], path) == 0) return;
    created_dirs = xrealloc(created_dirs, (size_t)(n_created_dirs + 1) * sizeof *created_dirs);
    created_dirs[n_created_dirs++] = xstrdup(path);
}

void cli_expect_dirs(const char *path)
{
    char buf[PATH_MAX];
    if (!path || !*path || strlen(path) >= sizeof buf) return;
    strcpy(buf, path);
    for (char *p = buf + 1;; p++) {
        if (*p == '/' || *p == '\0') {
            char saved = *p;
            *p = '\0';
            struct stat st;
            if (buf[0] && stat(buf, &st) != 0 && errno == ENOENT) record_created_dir(buf);
            *p = saved;
            if (saved == '\0') break;
        }
    }
}

void cli_remove_created_dirs(void)
{
    /* deepest first; rmdir removes only empty folders, so nothing written is ever lost */
    for (int i = n_created_dirs - 1; i >= 0; i--) {
        rmdir(created_dirs[i]);
        free(created_dirs[i]);
    }
    free(created_dirs);
    created_dirs = NULL;
    n_created_dirs = 0;
}

/* mkdir -p for the folder part of `path` (dir_itself: path is the folder). */
static int make_dirs(const cli_run *run, const char *path)
{
    char buf[PATH_MAX];
    if (strlen(path) >= sizeof buf) return cli_error(run, "%s: path too long", path);
    strcpy(buf, path);
    for (char *p = buf + 1;; p++) {
        if (*p == '/' || *p == '\0') {
            char saved = *p;
            *p = '\0';
            if (buf[0] && mkdir(buf, 0777) == 0)
                record_created_dir(buf);
            else if (buf[0] && errno != EEXIST)
                return cli_error(run, "%s: cannot create the output folder (%s)", buf,
                                 strerror(errno));
            struct stat st;
            if (buf[0] && (stat(buf, &st) != 0 || !S_ISDIR(st.st_mode)))
                return cli_error(run, "%s exists and is not a folder", buf);
            *p = saved;
            if (saved == '\0') break;
        }
    }
    return 0;
}

static void dir_of(const char *path, char *dir, size_t size)
{
    const char *slash = strrchr(path, '/');
    if (!slash) {
        snprintf(dir, size, ".");
        return;
    }
    size_t n = (size_t)(slash - path);
    if (n == 0) n = 1; /* "/file" */
    if (n >= size) n = size - 1;
    memcpy(dir, path, n);
    dir[n] = '\0';
}

int cli_outputs_check(cli_run *run)
{
    for (int i = 0; i < run->n_outputs; i++)
        for (int j = 0; j < i; j++)
            if (strcmp(run->outputs[i].path, run->outputs[j].path) == 0)
                return cli_error(run, "two outputs (%s and %s) would both be written to %s",
                                 run->outputs[j].role, run->outputs[i].role, run->outputs[i].path);
    int n_existing = 0;
    const char *first = NULL;
    for (int i = 0; i < run->n_outputs; i++) {
        struct stat st;
        const char *path = run->outputs[i].path;
        char mfile[PATH_MAX], mvar[64];
        int bad = 0;
        if (svp_io_mat_path(path, mfile, sizeof mfile, mvar, sizeof mvar, &bad))
            path = mfile; /* "OUT.mat:VAR" is written to OUT.mat */
        run->outputs[i].existed = stat(path, &st) == 0;
        if (!run->outputs[i].existed) continue;
        if (S_ISDIR(st.st_mode)) return cli_error(run, "%s exists and is a folder", path);
        if (!run->force && n_existing++ == 0) {
            static char first_path[PATH_MAX];
            snprintf(first_path, sizeof first_path, "%s", path);
            first = first_path;
        }
    }
    if (n_existing == 1)
        return cli_error(run, "%s exists (use --force to overwrite); nothing was written", first);
    if (n_existing > 1)
        return cli_error(run,
                         "%s exists, and %d more of the %d outputs (use --force to "
                         "overwrite); nothing was written",
                         first, n_existing - 1, run->n_outputs);
    for (int i = 0; i < run->n_outputs; i++) {
        char dir[PATH_MAX];
        dir_of(run->outputs[i].path, dir, sizeof dir);
        int code = make_dirs(run, dir);
        if (code) return code;
        if (access(dir, W_OK) != 0)
            return cli_error(run, "%s: the output folder is not writable (%s)", dir,
                             strerror(errno));
    }
    return 0;
}

static const cli_output *find_output(const cli_run *run, const char *path)
{
    for (int i = 0; i < run->n_outputs; i++)
        if (strcmp(run->outputs[i].path, path) == 0) return &run->outputs[i];
    return NULL;
}

int cli_write_image(cli_run *run, const char *path, const svp_image *image)
{
    const cli_output *o = find_output(run, path);
    svp_file_format format = run->format;
    if (!o || o->exact) format = cli_format_of_path(path);
    if (format == SVP_FORMAT_AUTO) format = run->format;
    svp_status st = svp_image_write(path, image, format, run->force);
    if (st != SVP_OK) return cli_fail(run, st, path);
    return 0;
}

int cli_write_text(cli_run *run, const char *path, const char *text)
{
    svp_status st = svp_io_atomic_write_text(path, text, run->force);
    if (st != SVP_OK) return cli_fail(run, st, path);
    return 0;
}

/* ---- stages --------------------------------------------------------------------------------- */

static double stage_t0;

void cli_stage_begin(cli_run *run, const char *name)
{
    if (run->stage_open) cli_stage_end(run);
    run->stages = xrealloc(run->stages, (size_t)(run->n_stages + 1) * sizeof *run->stages);
    run->stages[run->n_stages].name = xstrdup(name);
    run->stages[run->n_stages].seconds = 0;
    run->n_stages++;
    run->stage_open = 1;
    stage_t0 = cli_now();
}

void cli_stage_end(cli_run *run)
{
    if (!run->stage_open) return;
    run->stages[run->n_stages - 1].seconds = cli_now() - stage_t0;
    run->stage_open = 0;
}

double cli_stage_seconds(const cli_run *run, const char *name)
{
    double s = 0;
    for (int i = 0; i < run->n_stages; i++)
        if (strcmp(run->stages[i].name, name) == 0) s += run->stages[i].seconds;
    return s;
}

/* ---- progress ------------------------------------------------------------------------------ */

void cli_progress_start(cli_run *run, const char *label)
{
    run->progress_label = label;
    run->progress_t0 = cli_now();
    run->progress_last_draw = 0;
    run->progress_shown = 0;
    run->progress_last_decile = -1;
}

static void format_seconds(double s, char *buf, size_t size)
{
    if (s < 60)
        snprintf(buf, size, "%.0f s", s);
    else if (s < 3600)
        snprintf(buf, size, "%d min %02d s", (int)(s / 60), (int)fmod(s, 60));
    else
        snprintf(buf, size, "%d h %02d min", (int)(s / 3600), (int)fmod(s / 60, 60));
}

int cli_progress(void *user, double fraction)
{
    cli_run *run = user;
    if (run->quiet || !run->progress_label) return 0;
    const double f = fraction < 0 ? 0 : fraction > 1 ? 1 : fraction;
    double now = cli_now(), elapsed = now - run->progress_t0;
    /* Only work that lasts: nothing in the first second. */
    if (elapsed < 1.0 || f <= 0) return 0;
    char eta[32] = "";
    if (f < 1) format_seconds(elapsed * (1 - f) / f, eta, sizeof eta);
    if (run->stderr_tty) {
        if (now - run->progress_last_draw < 0.1 && f < 1) return 0;
        enum { WIDTH = 30 };
        int filled = (int)(f * WIDTH + 0.5);
        char bar[WIDTH + 1];
        for (int i = 0; i < WIDTH; i++) bar[i] = i < filled ? '#' : '.';
        bar[WIDTH] = '\0';
        fprintf(stderr, "\r%s [%s] %3.0f %%%s%s   ", run->progress_label, bar, 100 * f,
                eta[0] ? "  ETA " : "", eta);
        fflush(stderr);
        run->progress_last_draw = now;
        run->progress_shown = 1;
    } else {
        int decile = (int)floor(f * 10 + 1e-9);
        if (decile == 0 || decile <= run->progress_last_decile) return 0;
        run->progress_last_decile = decile;
        fprintf(stderr, "svpsf %s: %s %3.0f %%%s%s\n", run->command, run->progress_label,
                10.0 * decile, eta[0] ? ", ETA " : "", eta);
        run->progress_shown = 1;
    }
    return 0;
}

void cli_progress_done(cli_run *run)
{
    if (run->progress_shown && !run->quiet) {
        if (run->stderr_tty) {
            cli_progress(run, 1.0);
            fputc('\n', stderr);
        } else if (run->progress_last_decile < 10) {
            fprintf(stderr, "svpsf %s: %s 100 %%\n", run->command, run->progress_label);
        }
    }
    run->progress_label = NULL;
    run->progress_shown = 0;
}

/* ---- summary values ------------------------------------------------------------------------- */

static cli_kv *kv_add(cli_kv **list, int *n, const char *key)
{
    for (int i = 0; i < *n; i++)
        if (strcmp((*list)[i].key, key) == 0) { /* a later value replaces an earlier one */
            free((*list)[i].str);
            (*list)[i].str = NULL;
            return &(*list)[i];
        }
    *list = xrealloc(*list, (size_t)(*n + 1) * sizeof **list);
    cli_kv *kv = &(*list)[(*n)++];
    memset(kv, 0, sizeof *kv);
    kv->key = xstrdup(key);
    return kv;
}

static void kv_str(cli_kv **list, int *n, const char *key, const char *value)
{
    cli_kv *kv = kv_add(list, n, key);
    kv->kind = KV_STR;
    kv->str = xstrdup(value);
}

static void kv_num(cli_kv **list, int *n, const char *key, double value)
{
    cli_kv *kv = kv_add(list, n, key);
    kv->kind = KV_NUM;
    kv->num = value;
}

static void kv_int(cli_kv **list, int *n, const char *key, long long value)
{
    cli_kv *kv = kv_add(list, n, key);
    kv->kind = KV_INT;
    kv->integer = value;
}

void cli_setting_str(cli_run *run, const char *key, const char *value)
{
    kv_str(&run->settings, &run->n_settings, key, value);
}

void cli_setting_num(cli_run *run, const char *key, double value)
{
    kv_num(&run->settings, &run->n_settings, key, value);
}

void cli_setting_int(cli_run *run, const char *key, long long value)
{
    kv_int(&run->settings, &run->n_settings, key, value);
}

void cli_result_str(cli_run *run, const char *key, const char *value)
{
    kv_str(&run->results, &run->n_results, key, value);
}

void cli_result_num(cli_run *run, const char *key, double value)
{
    kv_num(&run->results, &run->n_results, key, value);
}

void cli_result_int(cli_run *run, const char *key, long long value)
{
    kv_int(&run->results, &run->n_results, key, value);
}

/* ---- summary.json --------------------------------------------------------------------------- */

static void json_kvs(svp_json *j, const char *name, const cli_kv *kv, int n)
{
    svp_json_key(j, name);
    svp_json_begin_object(j);
    for (int i = 0; i < n; i++) {
        svp_json_key(j, kv[i].key);
        switch (kv[i].kind) {
        case KV_STR: svp_json_string(j, kv[i].str); break;
        case KV_NUM: svp_json_number(j, kv[i].num); break;
        case KV_INT: svp_json_int(j, kv[i].integer); break;
        }
    }
    svp_json_end_object(j);
}

int cli_summary_write(cli_run *run, const char *path)
{
    if (run->stage_open) cli_stage_end(run);
    double total = cli_now() - run->t_start;

    svp_json *j = NULL;
    svp_status st = svp_json_new(&j);
    if (st != SVP_OK) return cli_fail(run, st, path);
    svp_json_begin_object(j);
    svp_json_key(j, "svpsf_summary");
    svp_json_int(j, 1);
    svp_json_key(j, "command");
    svp_json_string(j, run->command);
    svp_json_key(j, "command_line");
    svp_json_begin_array(j);
    if (program_argv)
        for (int i = 0; i < program_argc; i++) svp_json_string(j, program_argv[i]);
    else
        for (int i = 0; i < run->argc; i++) svp_json_string(j, run->argv[i]);
    svp_json_end_array(j);
    svp_json_key_working_directory(j);
    svp_json_key_started_utc(j, total);

    svp_json_key(j, "inputs");
    svp_json_begin_array(j);
    for (int i = 0; i < run->n_inputs; i++) {
        const cli_input *in = &run->inputs[i];
        svp_json_begin_object(j);
        svp_json_key(j, "role");
        svp_json_string(j, in->role);
        svp_json_key(j, "path");
        svp_json_string(j, in->path);
        svp_json_key(j, "bytes");
        svp_json_int(j, in->bytes);
        if (in->width > 0) {
            svp_json_key(j, "width");
            svp_json_int(j, in->width);
            svp_json_key(j, "height");
            svp_json_int(j, in->height);
            svp_json_key(j, "n_nonfinite");
            svp_json_int(j, in->n_nonfinite);
        }
        svp_json_end_object(j);
    }
    svp_json_end_array(j);

    svp_json_key(j, "outputs");
    svp_json_begin_object(j);
    for (int i = 0; i < run->n_outputs; i++) {
        svp_json_key(j, run->outputs[i].role);
        svp_json_string(j, run->outputs[i].path);
    }
    svp_json_end_object(j);

    json_kvs(j, "settings", run->settings, run->n_settings);
    json_kvs(j, "results", run->results, run->n_results);

    svp_json_key_versions(j);

    svp_json_key(j, "threads");
    svp_json_int(j, svp_get_threads());
    svp_json_key(j, "fft_planning");
    svp_json_string(j, run->fft_measure ? "measure" : "estimate");
    svp_json_key(j, "fft_wisdom");
    svp_json_string(j, run->wisdom ? run->wisdom : run->wisdom_cache ? run->wisdom_cache : "");
    const char *policy_source = NULL;
    const char *policy = cli_omp_wait_policy(&policy_source);
    svp_json_key(j, "omp_wait_policy");
    svp_json_string(j, policy);
    svp_json_key(j, "omp_wait_policy_from");
    svp_json_string(j, policy_source);

    svp_json_key(j, "timings_s");
    svp_json_begin_object(j);
    for (int i = 0; i < run->n_stages; i++) {
        /* repeated stage names add up */
        int first = 1;
        for (int k = 0; k < i; k++)
            if (strcmp(run->stages[k].name, run->stages[i].name) == 0) first = 0;
        if (!first) continue;
        svp_json_key(j, run->stages[i].name);
        svp_json_number(j, cli_stage_seconds(run, run->stages[i].name));
    }
    svp_json_key(j, "total");
    svp_json_number(j, total);
    svp_json_end_object(j);

    svp_json_key_peak_memory(j);
    svp_json_end_object(j);

    const char *text = NULL;
    st = svp_json_finish(j, &text);
    int code = st != SVP_OK ? cli_fail(run, st, path) : cli_write_text(run, path, text);
    svp_json_free(j);
    return code;
}

/* ---- field + PL map sets -------------------------------------------------------------------- */

int cli_maps_add_field(cli_run *run, cli_maps *maps, const char *path)
{
    if (maps->n_fields >= CLI_MAX_FIELDS)
        return cli_error(run, "--field: at most %d field maps per run", CLI_MAX_FIELDS);
    maps->field_paths[maps->n_fields++] = path;
    return 0;
}

int cli_maps_read(cli_run *run, cli_maps *maps)
{
    int code = cli_read_image(run, "pl", maps->pl_path, &maps->pl);
    if (code) return code;
    for (int i = 0; i < maps->n_fields; i++) {
        code = cli_read_image(run, "field", maps->field_paths[i], &maps->fields[i]);
        if (code) return code;
        code = cli_check_same_size(run, maps->fields[i], "field", maps->field_paths[i], maps->pl,
                                   "PL", maps->pl_path);
        if (code) return code;
    }
    return 0;
}

int cli_maps_plan(cli_run *run, cli_maps *maps)
{
    maps->pl_out = cli_output_in_dir(run, "pl", "pl", 1);
    if (maps->n_fields == 1) {
        maps->field_out[0] = cli_output_in_dir(run, "field", "field", 1);
    } else {
        char stems[CLI_MAX_FIELDS][256];
        for (int i = 0; i < maps->n_fields; i++) {
            cli_path_stem(maps->field_paths[i], stems[i], sizeof stems[i]);
            for (int k = 0; k < i; k++)
                if (strcmp(stems[i], stems[k]) == 0)
                    return cli_error(run,
                                     "--field %s and --field %s have the same name '%s': their "
                                     "outputs field_%s would collide (rename one)",
                                     maps->field_paths[k], maps->field_paths[i], stems[i],
                                     stems[i]);
            char name[300];
            snprintf(name, sizeof name, "field_%s", stems[i]);
            maps->field_out[i] = cli_output_in_dir(run, name, name, 1);
        }
    }
    maps->validity_out = cli_output_in_dir(run, "validity", "validity", 1);
    maps->summary_out = cli_output_in_dir(run, "summary", "summary.json", 0);
    return 0;
}

void cli_maps_release(cli_maps *maps)
{
    svp_image_free(maps->pl);
    maps->pl = NULL;
    for (int i = 0; i < maps->n_fields; i++) {
        svp_image_free(maps->fields[i]);
        maps->fields[i] = NULL;
    }
}

void cli_maps_init(cli_maps *maps)
{
    memset(maps, 0, sizeof *maps);
    cli_variant_defaults(&maps->variant);
    maps->boundary = SVP_BOUNDARY_ZERO;
}

int cli_maps_option(cli_run *run, cli_maps *maps, int option, const char *arg)
{
    switch (option) {
    case CLI_OPT_FIELD: return cli_maps_add_field(run, maps, arg);
    case CLI_OPT_PL: maps->pl_path = arg; return 0;
    case CLI_OPT_PSF: maps->psf_path = arg; return 0;
    case CLI_OPT_BOUNDARY:
        maps->boundary_given = 1;
        return cli_parse_boundary(run, "--boundary", arg, &maps->boundary);
    case CLI_OPT_NODES:
    case CLI_OPT_RANK:
    case CLI_OPT_OPERATOR_TOL:
    case CLI_OPT_MAX_MEMORY:
    case CLI_OPT_REGIONS:
        maps->variant_given = 1;
        return cli_variant_option(run, &maps->variant, option, arg);
    default: return -1;
    }
}

int cli_maps_open(cli_run *run, cli_maps *maps, cli_psf *psf)
{
    const char *psf_path = maps->psf_path;
    if (optind < run->argc)
        return cli_error(run,
                         "unexpected argument '%s' (inputs are given with --field, --pl and "
                         "--psf)",
                         run->argv[optind]);
    if (maps->n_fields == 0) return cli_error(run, "--field is required (see --help)");
    if (!maps->pl_path) return cli_error(run, "--pl is required");
    if (!psf_path) return cli_error(run, "--psf is required");
    if (!run->output) return cli_error(run, "-o DIR is required");

    /* Everything that can be wrong with the inputs or outputs is found before any work. */
    int code;
    cli_stage_begin(run, "read");
    if ((code = cli_psf_load_map(run, psf_path, &maps->variant, psf))) return code;
    if (maps->variant_given && !psf->field)
        cli_note(run, "--nodes / --rank / --regions ignored: %s is a single PSF, not a space-variant map",
                 psf_path);
    if ((code = cli_maps_read(run, maps))) return code;
    if ((code = cli_check_input_pixels(run, psf->pixel_um, psf_path))) return code;
    if (!maps->boundary_given && psf->has_boundary) maps->boundary = psf->boundary;
    if ((code = cli_maps_plan(run, maps))) return code;
    if ((code = cli_psf_check(run, psf, maps->pl->width, maps->pl->height))) return code;
    if ((code = cli_outputs_check(run))) return code;

    cli_psf_describe(run, psf);
    cli_setting_str(run, "boundary", cli_boundary_name(maps->boundary));
    cli_setting_int(run, "n_fields", maps->n_fields);
    cli_setting_str(run, "format", cli_format_extension(run->format));
    return 0;
}

int cli_maps_write(cli_run *run, const cli_maps *maps, const svp_image *pl,
                   svp_image *const *fields, const svp_image *validity)
{
    int code;
    cli_stage_begin(run, "write");
    if ((code = cli_write_image(run, maps->pl_out, pl))) return code;
    for (int i = 0; i < maps->n_fields; i++)
        if ((code = cli_write_image(run, maps->field_out[i], fields[i]))) return code;
    if ((code = cli_write_image(run, maps->validity_out, validity))) return code;
    cli_stage_end(run);
    return cli_summary_write(run, maps->summary_out);
}

/* ---- option groups: deconvolution, spot fit; one positional argument ---------------------- */

const char *const cli_acceleration_names[] = {"none", "biggs-andrews", NULL};
const char *const cli_rl_stop_names[] = {"count", "discrepancy", "stalled", "cap"};

void cli_deconv_init(cli_deconv_args *args, const svp_deconv_options *defaults)
{
    memset(args, 0, sizeof *args);
    args->iterations = defaults->iterations;
    args->balance = defaults->balance;
    args->cg_max_steps = defaults->cg_max_steps;
    args->acceleration = (int)defaults->acceleration;
    args->precision = defaults->single_precision ? 1 : 0;
}

int cli_deconv_option(const cli_run *run, cli_deconv_args *args, int option, const char *arg)
{
    switch (option) {
    case CLI_OPT_ITERATIONS:
        if (strcmp(arg, "auto") == 0) {
            args->iterations_auto = 1;
            return 0;
        }
        return cli_parse_int(run, "--iterations", arg, 1, 100000, &args->iterations);
    case CLI_OPT_BALANCE:
        args->balance_given = 1;
        return cli_parse_balance(run, arg, &args->balance, &args->balance_auto);
    case CLI_OPT_NOISE:
        return cli_parse_double_in(run, "--noise", arg, 0, 0, INFINITY, 0, &args->noise);
    case CLI_OPT_CG_MAX_STEPS:
        return cli_parse_int(run, "--cg-max-steps", arg, 1, 100000, &args->cg_max_steps);
    case CLI_OPT_PRECISION:
        args->precision_given = 1;
        return cli_parse_choice(run, "--precision", arg, cli_precision_names, &args->precision);
    case CLI_OPT_ACCELERATION:
        return cli_parse_choice(run, "--acceleration", arg, cli_acceleration_names,
                                &args->acceleration);
    case CLI_OPT_KEEP_DOUBTFUL: args->keep_doubtful = 1; return 0;
    default: return -1;
    }
}

void cli_deconv_apply(const cli_deconv_args *args, svp_deconv_options *opt)
{
    opt->iterations = args->iterations;
    opt->auto_stop = args->iterations_auto;
    opt->balance = args->balance;
    opt->cg_max_steps = args->cg_max_steps;
    opt->acceleration = (svp_rl_acceleration)args->acceleration;
    opt->single_precision = args->precision == 1;
}

void cli_print_deconv_help(FILE *out, const svp_deconv_options *defaults)
{
    fprintf(out,
            "  --cg-max-steps N      step cap of the zero-boundary Wiener solve (conjugate\n"
            "                        gradients; default %d); a solve that stops there above\n"
            "                        its tolerance is warned about and recorded\n",
            defaults->cg_max_steps);
}

void cli_spot_init(cli_spot_args *args, const svp_spot_options *defaults)
{
    args->model = SVP_PSF_MOFFAT;
    args->elliptical = defaults->elliptical;
    args->gain = defaults->noise.gain;
}

int cli_spot_option(const cli_run *run, cli_spot_args *args, int option, const char *arg)
{
    switch (option) {
    case CLI_OPT_MODEL:
        return cli_parse_choice(run, "--model", arg, cli_psf_model_names, &args->model);
    case CLI_OPT_CIRCULAR: args->elliptical = 0; return 0;
    case CLI_OPT_GAIN:
        return cli_parse_double_in(run, "--gain", arg, 0, 1, INFINITY, 0, &args->gain);
    default: return -1;
    }
}

void cli_spot_apply(const cli_spot_args *args, svp_spot_options *opt)
{
    opt->model = (svp_psf_model)args->model;
    opt->elliptical = args->elliptical;
    opt->noise.gain = args->gain;
}

void cli_print_spot_help(FILE *out)
{
    fputs("  --model M             moffat (default), gaussian or lorentzian\n", out);
}

const char *cli_one_argument(const cli_run *run, const char *missing, const char *extra_note)
{
    if (optind >= run->argc) {
        cli_error(run, "%s", missing);
        return NULL;
    }
    if (optind + 1 < run->argc) {
        cli_error(run, "unexpected argument '%s'%s", run->argv[optind + 1], extra_note);
        return NULL;
    }
    return run->argv[optind];
}

int cli_parsed_status(int code) { return code == CLI_OPTION_HELP ? 0 : code; }

/* --margin auto: the PSF's significant reach (svp_psf_reach: the radius where the profile falls
 * to 1 % of its peak along the major axis; Gaussian 1.29 FWHM, Moffat β 1.1 4.3 FWHM; a kernel
 * image: its half-width), at most a quarter of the view's larger side; 0 for a PSF with a halo,
 * whose margin unknowns can take up halo flux (docs/model.md §3). */
int cli_auto_margin(const cli_psf *psf, int w, int h)
{
    if (psf->field) return svp_psf_field_auto_margin(psf->field, w, h);
    if (psf->is_model) return svp_psf_auto_margin(&psf->model, w, h);
    if (!psf->kernel_raw) return 0;
    const int cap = (w > h ? w : h) / 4;
    const int kw = psf->kernel_raw->width, kh = psf->kernel_raw->height;
    const int m = (int)ceil(0.5 * (kw > kh ? kw : kh));
    return m < cap ? m : cap;
}
