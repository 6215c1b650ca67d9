/*
 * Shared helpers of the svpsf command-line program.
 *
 * Adding a command (docs/architecture.md, "Adding a CLI command"):
 *   1. write `int cmd_NAME(int argc, char **argv)` in tools/svpsf/cmd_NAME.c and declare it
 *      below; argv[0] is the command name, the options follow;
 *   2. add ONE line to the `commands` table in tools/svpsf/main.c:
 *          {"fit-psf", "fit a Moffat PSF to a spot image pair", cmd_fit_psf},
 *      The table is what `svpsf --help` lists and what `svpsf NAME` dispatches to; a command
 *      that is not in the table does not exist for the user.
 *
 * The shape of a command (cmd_deconvolve.c and cmd_correct.c are complete ones): it parses
 * into a struct of its arguments, then runs (see cli_parsed_status below):
 *
 *   static int parse_NAME_args(cli_run *run, struct NAME_args *a)
 *   {
 *       static const struct option own[] = {{"pl", required_argument, NULL, OPT_PL}, ...,
 *                                           CLI_DECONV_LONGOPTS, {0}};
 *       ... defaults, cli_deconv_init(&a->deconv, &library_defaults) ...
 *       int c;
 *       while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
 *           if (c == CLI_OPTION_HELP) { print_help(run, stdout); return CLI_OPTION_HELP; }
 *           if (c == CLI_OPTION_ERROR || NAME_option(run, a, c)) return CLI_EXIT_USAGE;
 *       }
 *       ... positional arguments (cli_one_argument), the combinations refused ...
 *   }
 *
 * where NAME_option switches over the command's own options and passes the others to its
 * groups' cli_X_option (each returns -1 for an option that is not its own). run_NAME then
 * reads inputs with cli_read_image / cli_psf_load (they record them for the summary), plans
 * every output with cli_output_in_dir / cli_output_file, then cli_outputs_check (no file is
 * written before all are known to be writable), computes inside cli_stage_begin /
 * cli_stage_end, writes with cli_write_image, cli_summary_write, and returns the status;
 * each stage is a function of its own (none over 150 lines: tools/check/funclen.py).
 *
 * Conventions every command follows (docs/cli.md):
 *   - exit 0 ok, 1 bad usage or bad input (CLI_EXIT_USAGE), 2 runtime failure;
 *   - every message is one line on stderr prefixed "svpsf COMMAND: " and names the file or
 *     option at fault;
 *   - outputs are written atomically (temporary name, then rename) and never overwrite an
 *     existing file unless --force;
 *   - progress goes to stderr only for work that lasts more than about a second, as a bar
 *     with ETA on a terminal, as plain lines every 10 % otherwise, never with --quiet.
 */
#ifndef SVPSF_CLI_H
#define SVPSF_CLI_H

#include "svpsf.h"

#include <getopt.h>
#include <stddef.h>
#include <stdio.h>

/* ---- commands ----------------------------------------------------------------------------- */

typedef int (*cli_command_fn)(int argc, char **argv);

typedef struct cli_command {
    const char *name;    /* as typed: "forward", "fit-psf" */
    const char *summary; /* one line for `svpsf --help` */
    cli_command_fn run;
} cli_command;

int cmd_forward(int argc, char **argv);
int cmd_correct(int argc, char **argv);
int cmd_deconvolve(int argc, char **argv);
int cmd_psf(int argc, char **argv);
int cmd_demo(int argc, char **argv);
int cmd_simulate(int argc, char **argv);
int cmd_fit_psf(int argc, char **argv);
int cmd_map_psf(int argc, char **argv);
int cmd_psf_compare(int argc, char **argv);
int cmd_reconstruct(int argc, char **argv);
int cmd_register(int argc, char **argv);
int cmd_fit_odmr(int argc, char **argv);

/* ---- exit codes ---------------------------------------------------------------------------- */

enum {
    CLI_EXIT_OK = 0,
    CLI_EXIT_USAGE = 1,  /* bad usage or bad input: the message names the file or option */
    CLI_EXIT_RUNTIME = 2, /* a runtime failure (memory, numerics, a bug) */
    CLI_EXIT_DOUBTFUL = 3 /* a result the program cannot vouch for: nothing written */
};

/* INVALID, IO, FORMAT, SIZE, EXISTS → 1 (the user can fix the input); others → 2. */
int cli_exit_code(svp_status status);

/* ---- versions ------------------------------------------------------------------------------ */

typedef struct cli_versions {
    const char *svpsf, *fftw, *opencv, *libyaml;
} cli_versions;
void cli_get_versions(cli_versions *v);

/* The whole command line as typed (main.c records it; the summary repeats it). */
void cli_set_program_args(int argc, char **argv);

/* ---- the run: common options, inputs, outputs, stages, summary ----------------------------- */

/* Which of the common options a command accepts (bit set). --help, --quiet and --threads are
 * always accepted. */
enum {
    CLI_COMMON_OUTPUT = 1u << 0, /* -o/--output PATH, --force */
    CLI_COMMON_FORMAT = 1u << 1, /* --format tif|npy|txt (default tif) */
    CLI_COMMON_FFT = 1u << 2,    /* --wisdom FILE, --fft estimate|measure, --no-wisdom-cache */
    CLI_COMMON_OUTPUT_DIR = CLI_COMMON_OUTPUT | CLI_COMMON_FORMAT | CLI_COMMON_FFT
};

/* Codes cli_next_option returns besides a command's own option values. Commands give their
 * own options values from CLI_OPTION_FIRST upwards (or a plain short-option character). */
enum {
    CLI_OPTIONS_DONE = -1,
    CLI_OPTION_ERROR = -2, /* a message was printed; exit CLI_EXIT_USAGE */
    CLI_OPTION_HELP = -3,  /* --help/-h: print the help on stdout and exit 0 */
    CLI_OPTION_FIRST = 1000
};

typedef struct cli_kv cli_kv;         /* a named value of the summary (opaque) */
typedef struct cli_input cli_input;   /* an input file and what was read from it */
typedef struct cli_output cli_output; /* a planned output file */
typedef struct cli_stage cli_stage;   /* a timed stage */

typedef struct cli_run {
    const char *command; /* "forward" */
    int argc;
    char **argv; /* argv[0] = the command name */
    unsigned common;

    /* common options (after parsing) */
    const char *output;     /* -o: directory or file, NULL when not given */
    svp_file_format format; /* --format: default SVP_FORMAT_TIFF */
    int format_given;
    int force;          /* --force */
    int quiet;          /* --quiet: no progress, no notes */
    int threads;        /* --threads: 0 = library default (all cores) */
    const char *wisdom; /* --wisdom FILE: loaded before, saved after the run */
    int fft_measure;    /* --fft: 1 measure (default), 0 estimate */

    int stderr_tty;
    double t_start; /* monotonic seconds */

    /* what the run read, will write, did (for the checks and the summary) */
    cli_input *inputs;
    int n_inputs;
    cli_output *outputs;
    int n_outputs;
    cli_stage *stages;
    int n_stages;
    int stage_open;
    cli_kv *settings;
    int n_settings;
    cli_kv *results;
    int n_results;

    /* progress state */
    const char *progress_label;
    double progress_t0, progress_last_draw;
    int progress_shown, progress_last_decile;

    /* the FFTW wisdom cache (cli_machine.c) */
    int no_wisdom_cache; /* --no-wisdom-cache, or SVPSF_NO_WISDOM_CACHE set */
    char *wisdom_cache;  /* the cache file in use; NULL when none */
    int fft_planned;     /* FFT plans were measured in this run (the cache is saved) */
} cli_run;

/* Starts a run: records the command, applies nothing yet. `common` is a CLI_COMMON_* set. */
void cli_run_init(cli_run *run, const char *command, int argc, char **argv, unsigned common);
/* Saves FFTW wisdom when asked, frees what the run holds and returns exit_code (so
 * `return cli_run_finish(&run, code);`). */
int cli_run_finish(cli_run *run, int exit_code);

/* getopt_long over run->argv with the command's own options (terminated by a zero entry)
 * plus the common ones. Handles the common options itself; returns the command's option
 * value (optarg holds its argument), CLI_OPTION_HELP, CLI_OPTION_ERROR or CLI_OPTIONS_DONE.
 * After DONE, run->argv[optind .. argc-1] are the positional arguments. When DONE is
 * returned the common settings are applied (threads, FFT effort, wisdom loaded): a failure
 * there returns CLI_OPTION_ERROR. */
int cli_next_option(cli_run *run, const struct option *own);

/* Prints the help lines of the common options the run accepts (with their defaults). */
void cli_print_common_help(const cli_run *run, FILE *out);

/* "svpsf COMMAND: message\n" on stderr. Returns CLI_EXIT_USAGE for `return cli_error(...)`. */
int cli_error(const cli_run *run, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
/* A warning on stderr ("svpsf COMMAND: warning: ..."), printed even with --quiet. */
void cli_warn(const cli_run *run, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
/* A note on stderr ("svpsf COMMAND: ..."), silent with --quiet. */
void cli_note(const cli_run *run, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
/* Prints svp_last_error() (prefixed with `context: ` when context is not NULL and the message
 * does not already contain it) and returns cli_exit_code(status). */
int cli_fail(const cli_run *run, svp_status status, const char *context);

/* Number parsing with errors naming the option: "--balance: 'x' is not a number". */
int cli_parse_double(const cli_run *run, const char *option, const char *text, double *out);
/* Integer in [min, max]; the message states the range. */
int cli_parse_int(const cli_run *run, const char *option, const char *text, int min, int max,
                  int *out);
/* One of `choices` (NULL-terminated); *out = its index. */
int cli_parse_choice(const cli_run *run, const char *option, const char *text,
                     const char *const *choices, int *out);
/* A finite number in an interval: lo < x (lo <= x when lo_closed) and x < hi (x <= hi when
 * hi_closed); a bound of -INFINITY / INFINITY is no bound. The message names the option and
 * the interval: "--gain -1: must be >= 0", "--halo 2: must be in [0, 1)". */
int cli_parse_double_in(const cli_run *run, const char *option, const char *text, double lo,
                        int lo_closed, double hi, int hi_closed, double *out);
/* --balance L|auto (correct, deconvolve): *is_auto = 1 for "auto", else L >= 0 in *balance. */
int cli_parse_balance(const cli_run *run, const char *text, double *balance, int *is_auto);
/* --balance auto searches λ in [CLI_BALANCE_AUTO_MIN, CLI_BALANCE_AUTO_MAX] (the library's
 * svp_wiener_balance_discrepancy interval). When the chosen λ is at an end (within the
 * bisection's resolution), the search was cut short by its bound, not met by the noise:
 * warns on stderr naming `what` (the image) and the noise σ, and returns "lower" or "upper"
 * for summary.json; NULL when λ lies inside. */
#define CLI_BALANCE_AUTO_MIN 1e-12
#define CLI_BALANCE_AUTO_MAX 1e2
const char *cli_balance_bound_check(const cli_run *run, const char *what, double balance,
                                    double sigma);
/* zero | mirror | periodic. */
int cli_parse_boundary(const cli_run *run, const char *option, const char *text, svp_boundary *out);
const char *cli_boundary_name(svp_boundary b);
/* The file name without folders and without its last extension ("a/b/Bz.npy" → "Bz"). */
void cli_path_stem(const char *path, char *stem, size_t size);
/* path without its .yaml/.yml extension, followed by ext ("a/psf.yaml", ".summary.json" →
 * "a/psf.summary.json"; a path without that extension keeps it whole). */
void cli_path_sibling(const char *path, const char *ext, char *buf, size_t size);
/* The length of path's ".yaml" or ".yml" ending (5 or 4; case-sensitive, not the whole name),
 * else 0: what cli_path_sibling strips and what fit-psf/map-psf require of -o. */
size_t cli_yaml_extension(const char *path);
/* The PSF model names indexed by svp_psf_model, NULL-terminated (for cli_parse_choice). */
extern const char *const cli_psf_model_names[];
/* --precision double|single (deconvolve, correct): index 1 = single_precision. */
extern const char *const cli_precision_names[];

/* ---- inputs ------------------------------------------------------------------------------ */

/* Reads an image (svp_image_read) and records it as an input with `role` ("pl", "field").
 * On failure prints the message (it names the file) and returns the exit code; 0 on success. */
int cli_read_image(cli_run *run, const char *role, const char *path, svp_image **out);
/* The same, and what a MATLAB file holds beside the map (its `step`, `h`; zeros for other
 * formats) into *info (may be NULL). */
int cli_read_image_info(cli_run *run, const char *role, const char *path, svp_image **out,
                        svp_mat_info *info);
/* Reads a stack (svp_stack_read; a .mat through svp_mat_read_stack, its `step` recorded as
 * cli_read_image does) and records it as an input with `role`; the exit code, 0 on success. */
int cli_read_stack(cli_run *run, const char *role, const char *path, svp_stack **out);
/* A MATLAB input whose `step` (its pixel size, recorded by cli_read_image) differs from the PSF
 * file's pixel size by more than CLI_PIXEL_AGREE: an error naming both (the PSF would act at the
 * wrong scale). Nothing to check without a PSF pixel size (a kernel image) or a `step`. */
#define CLI_PIXEL_AGREE 0.01
int cli_check_input_pixels(cli_run *run, double psf_pixel_um, const char *psf_path);
/* Records a non-image input (a YAML file) for the summary. */
void cli_record_input(cli_run *run, const char *role, const char *path, int width, int height);
/* "size mismatch: ROLE_A PATH_A is W x H but ROLE_B PATH_B is W x H" → exit 1; 0 if equal. */
int cli_check_same_size(const cli_run *run, const svp_image *a, const char *role_a,
                        const char *path_a, const svp_image *b, const char *role_b,
                        const char *path_b);

/* A PSF given either as a YAML PSF file (.yaml/.yml) or as a kernel image (.npy, .tif, .txt,
 * ...). A kernel image is normalised to unit sum with its centre at the middle pixel
 * (width / 2, height / 2); `kernel_raw` keeps it as read (for --compat skimage). */
typedef struct cli_psf {
    const char *path;
    int is_model;          /* 1: YAML model, 0: kernel image */
    svp_psf model;         /* when is_model (lengths in pixels) */
    double pixel_um;       /* from the YAML file; 0 for a kernel image */
    int has_boundary;      /* the YAML file names a boundary */
    svp_boundary boundary; /* that boundary */
    svp_image *kernel_raw; /* when !is_model: the kernel as read */
    double kernel_sum;     /* its sum */
    svp_psf_field *field;  /* a non-uniform PSF map (cli_psf_load_map); is_model is 0 */
    /* a PSF map's operator representation (cli_variant_option) */
    svp_variant_options variant;
} cli_psf;

int cli_psf_load(cli_run *run, const char *path, cli_psf *psf);
/* The blur operator for a width x height image (boundary as decided by the caller). */
int cli_psf_blur(cli_run *run, const cli_psf *psf, int width, int height, svp_boundary boundary,
                 svp_blur **out);
void cli_psf_release(cli_psf *psf);
/* Records the PSF's description in the summary settings (model, FWHM, beta, ...). */
void cli_psf_describe(cli_run *run, const cli_psf *psf);
/* --margin auto (correct, fit-odmr --psf): the PSF's significant reach (svp_psf_reach: the
 * radius where the profile falls to 1 % of its peak; a kernel image: its half-width; a PSF
 * map: its widest PSF's, svp_psf_field_auto_margin), at most a quarter of the view's larger
 * side; 0 for a PSF with a halo (docs/model.md §3). */
int cli_auto_margin(const cli_psf *psf, int w, int h);
/* A PSF map's field carried `margin` pixels beyond the view on every side
 * (svp_psf_field_pad), for an operator on the view plus the margin; no-op for a single PSF
 * or margin 0. 0, or the exit status after a message naming the file. */
int cli_psf_pad(cli_run *run, cli_psf *psf, int margin);

/* PSF maps (forward, correct): --psf may also be a PSF-map file (svp_psf_field_read; a map of
 * kind uniform or a plain PSF file is the single-PSF case above). A command adds
 * CLI_VARIANT_LONGOPTS to its option table, calls cli_variant_defaults once, passes
 * CLI_OPT_NODES / CLI_OPT_RANK / CLI_OPT_REGIONS to cli_variant_option, loads with cli_psf_load_map and prints
 * cli_print_variant_help in its --help. --nodes NxM: tent node grid (default 8x8; "N" = NxN);
 * --rank R: low rank with R eigen-PSFs sampled on the --nodes grid instead; --regions: one
 * kernel per region of a map of kind regions (not with --nodes / --rank); none: the
 * representation chosen by --operator-tol TOL (default 1e-3); --max-memory BYTES (or the
 * environment's SVPSF_MAX_MEMORY) bounds the operator's memory. */
enum { CLI_OPT_NODES = 1900, CLI_OPT_RANK, CLI_OPT_OPERATOR_TOL, CLI_OPT_MAX_MEMORY, CLI_OPT_REGIONS };
/* clang-format off */
#define CLI_VARIANT_LONGOPTS \
    {"nodes", required_argument, NULL, CLI_OPT_NODES}, {"rank", required_argument, NULL, CLI_OPT_RANK}, \
    {"operator-tol", required_argument, NULL, CLI_OPT_OPERATOR_TOL}, \
    {"max-memory", required_argument, NULL, CLI_OPT_MAX_MEMORY}, \
    {"regions", no_argument, NULL, CLI_OPT_REGIONS}
/* clang-format on */
void cli_variant_defaults(svp_variant_options *variant);
/* 0, or CLI_EXIT_USAGE after a message naming the option. */
int cli_variant_option(const cli_run *run, svp_variant_options *variant, int option,
                       const char *arg);
/* default_tol: the command's --operator-tol default (forward 1e-3, correct 1e-2). */
void cli_print_variant_help(FILE *out, double default_tol);
/* " Operator: ..." for the report paragraph (the representation, its estimated error, build
 * time, the time of one application and adjoint when cli_psf_blur measured them, and memory);
 * "" for operators that are not space-variant. */
void cli_variant_sentence(const svp_blur *blur, char *buf, size_t size);
/* The H + Hᵀ pairs a correction with options o on n_fields field maps runs (the cost model of
 * the representation's choice, svp_variant_options.applications): Richardson-Lucy iterations
 * per RL deconvolution, about 40 CG steps per Wiener one (17 solves with balance auto). */
int cli_correct_applications(const svp_correct_options *o, int n_fields);
int cli_psf_load_map(cli_run *run, const char *path, const svp_variant_options *variant,
                     cli_psf *psf);
/* The parameters out of range in r, each with its worst value, pixel and bound, "; "-separated
 * (FWHMs in um). */
void cli_psf_range_text(const svp_psf_field_range *r, double pixel_um, char *what, size_t size);
/* A warning when the map's parameters leave their valid range inside its image
 * (svp_psf_field_check_range): where, how far, and what to do. */
void cli_psf_map_range_warning(const cli_run *run, const char *path, const svp_psf_field *field,
                               double pixel_um);
/* Before any output is written: a PSF map fits a width x height image and its options are
 * valid (0, or CLI_EXIT_USAGE after a message naming the file). No-op for a single PSF. */
int cli_psf_check(const cli_run *run, const cli_psf *psf, int width, int height);

/* ---- outputs ----------------------------------------------------------------------------- */

/* The extension of a format ("tif", "npy", "txt"). */
const char *cli_format_extension(svp_file_format format);
/* The format of a file name's extension, SVP_FORMAT_AUTO when unknown. */
svp_file_format cli_format_of_path(const char *path);

/* Plans output DIR/NAME.EXT (EXT from --format; `name` may carry its own extension, e.g.
 * "summary.json", when ext_from_format is 0). Returns the path (owned by the run). */
const char *cli_output_in_dir(cli_run *run, const char *role, const char *name,
                              int ext_from_format);
/* Plans an output at an exact path. */
const char *cli_output_file(cli_run *run, const char *role, const char *path);
/* Checks every planned output at once: no two the same, none existing unless --force, the
 * output directory creatable (it is created here when missing). Prints the fault and returns
 * the exit code; 0 when all can be written. Call before any computation that writes. */
int cli_outputs_check(cli_run *run);
/* A failed run writes nothing: the folders cli_outputs_check created are recorded, and main()
 * calls cli_remove_created_dirs() when a command exits nonzero, removing those still empty
 * (deepest first; a folder that existed before the run or holds a file is never removed).
 * cli_expect_dirs records the folders of `path` that do not exist yet, for a command whose
 * folders the library creates (simulate). */
void cli_expect_dirs(const char *path);
void cli_remove_created_dirs(void);
/* Writes an image to a planned output path with the run's format (or the path's extension
 * when the run planned an exact file), atomically, overwriting only with --force. */
int cli_write_image(cli_run *run, const char *path, const svp_image *image);
/* Writes a text file atomically (temporary name + rename), overwriting only with --force. */
int cli_write_text(cli_run *run, const char *path, const char *text);

/* ---- timing, progress, summary ------------------------------------------------------------ */

double cli_now(void); /* monotonic seconds */
/* Timed stages for the summary ("read", "plan", "transform", "write"). Beginning one ends the
 * one that is open. */
void cli_stage_begin(cli_run *run, const char *name);
void cli_stage_end(cli_run *run);
double cli_stage_seconds(const cli_run *run, const char *name); /* 0 when absent */

/* Progress: an svp_progress_fn whose user pointer is the run; fractions of the whole job.
 * Nothing is drawn during the first second of the job, or with --quiet. */
void cli_progress_start(cli_run *run, const char *label);
int cli_progress(void *run, double fraction);
void cli_progress_done(cli_run *run);

/* Named values for summary.json: "settings" (what was asked) and "results" (what came out). */
void cli_setting_str(cli_run *run, const char *key, const char *value);
void cli_setting_num(cli_run *run, const char *key, double value);
void cli_setting_int(cli_run *run, const char *key, long long value);
void cli_result_str(cli_run *run, const char *key, const char *value);
void cli_result_num(cli_run *run, const char *key, double value);
void cli_result_int(cli_run *run, const char *key, long long value);

/* Writes the planned "summary" output (a JSON object: command, command line, working
 * directory, inputs with sizes, outputs, settings, results, versions, threads, timings per
 * stage, peak memory). */
int cli_summary_write(cli_run *run, const char *path);

/* ---- shared machines (cli_machine.c; docs/cli.md, "Shared machines") ---------------------- */

/* Called first in main(): unless OMP_WAIT_POLICY or GOMP_SPINCOUNT is set, sets
 * OMP_WAIT_POLICY=passive and runs the program again (/proc/self/exe, once: libgomp reads it
 * only when it loads), so idle OpenMP threads sleep instead of spinning on cores that another
 * program needs. Returns (and runs on) when it does nothing or the exec fails. */
void cli_openmp_passive(char **argv);
/* OMP_WAIT_POLICY as this process saw it ("" when unset); *source: "svpsf" (set by
 * cli_openmp_passive), "environment", or a note that it is unset. */
const char *cli_omp_wait_policy(const char **source);
/* SVPSF_NO_WISDOM_CACHE set (and not "0"). */
int cli_wisdom_cache_disabled(void);
/* Loads the wisdom cache ($XDG_CACHE_HOME/svpsf/wisdom, else ~/.cache/svpsf/wisdom) into
 * the process, creating its folder; sets run->wisdom_cache. A cache that does not load is
 * warned about and replaced, never fatal. */
void cli_wisdom_cache_open(cli_run *run);
/* When plans were measured: merges the cache file's current content, saves atomically. */
void cli_wisdom_cache_save(cli_run *run);
/* svp_fft_plan_fn for svp_set_fft_plan_callback, user = the run: records that plans were
 * measured and notes a large size on stderr (once per size; not with --quiet). */
void cli_plan_callback(void *user, int ny, int nx, int single_precision);

/* ---- field + PL map sets (forward, correct; reusable by simulate) ------------------------- */

#define CLI_MAX_FIELDS 16

/* One or several field-component maps sharing one PL map, and where each goes. */
typedef struct cli_maps {
    int n_fields;
    const char *field_paths[CLI_MAX_FIELDS]; /* --field, in order */
    const char *pl_path;                     /* --pl */
    const char *psf_path;                    /* --psf */
    svp_variant_options variant;             /* --nodes / --rank */
    int variant_given;
    svp_boundary boundary; /* --boundary, else the PSF file's (cli_maps_open), else zero */
    int boundary_given;
    svp_image *fields[CLI_MAX_FIELDS];
    svp_image *pl;
    /* planned outputs (cli_maps_plan) */
    const char *field_out[CLI_MAX_FIELDS];
    const char *pl_out, *validity_out, *summary_out;
} cli_maps;

/* The options forward and correct share: add CLI_MAPS_LONGOPTS to the option table and pass
 * every option the command does not handle itself to cli_maps_option. */
enum { CLI_OPT_FIELD = 1910, CLI_OPT_PL, CLI_OPT_PSF, CLI_OPT_BOUNDARY };
/* clang-format off */
#define CLI_MAPS_LONGOPTS \
    {"field", required_argument, NULL, CLI_OPT_FIELD}, {"pl", required_argument, NULL, CLI_OPT_PL}, \
    {"psf", required_argument, NULL, CLI_OPT_PSF}, \
    {"boundary", required_argument, NULL, CLI_OPT_BOUNDARY}, CLI_VARIANT_LONGOPTS
/* clang-format on */
void cli_maps_init(cli_maps *maps);
/* 0 when handled, CLI_EXIT_USAGE after a message, -1 when `option` is not one of them. */
int cli_maps_option(cli_run *run, cli_maps *maps, int option, const char *arg);
/* The front of forward and correct after their options: --field, --pl, --psf and -o given and
 * no stray argument; reads the PSF (or PSF map) and the maps, plans and checks every output,
 * and records the PSF, boundary, n_fields and format in the settings. 0, or the exit code
 * after a message. */
int cli_maps_open(cli_run *run, cli_maps *maps, cli_psf *psf);
/* Writes pl, every field and validity to the planned outputs, then summary.json. */
int cli_maps_write(cli_run *run, const cli_maps *maps, const svp_image *pl,
                   svp_image *const *fields, const svp_image *validity);
/* Adds a --field path (at most CLI_MAX_FIELDS). */
int cli_maps_add_field(cli_run *run, cli_maps *maps, const char *path);
/* Reads --pl and every --field and checks that all have the PL's size. */
int cli_maps_read(cli_run *run, cli_maps *maps);
/* Plans DIR/pl, DIR/field (or DIR/field_<stem> per input when several), DIR/validity,
 * DIR/summary.json, refusing two inputs with the same stem. */
int cli_maps_plan(cli_run *run, cli_maps *maps);
void cli_maps_release(cli_maps *maps);

/* ---- option groups -------------------------------------------------------------------------
 *
 * An option group is a set of options several commands share, in four pieces: codes (an enum
 * from its own base), a CLI_X_LONGOPTS list to put in the command's getopt table, a struct the
 * options parse into (cli_X_init sets the defaults) and cli_X_option(run, group, option, arg),
 * which returns 0 when it handled the option, CLI_EXIT_USAGE after a message naming it, and -1
 * when the option is not one of the group's (so a command tries its groups in turn). A group
 * whose help lines mean the same in every command prints them with cli_print_X_help. The
 * groups: the common ones of cli_run (-o/--force, --format, --threads, --wisdom/--fft,
 * --quiet, handled by cli_next_option itself), CLI_VARIANT (a PSF map's operator), CLI_MAPS
 * (field and PL maps with their PSF), CLI_DECONV (the deconvolution settings of deconvolve
 * and correct) and CLI_SPOT (the spot fit of fit-psf and map-psf). */

/* The deconvolution settings deconvolve and correct share. Each command states in its own
 * help what they apply to (one image; the PL and field x PL), and which combinations it
 * refuses. */
typedef struct cli_deconv_args {
    int iterations;      /* --iterations N (default: svp_deconv_defaults) */
    int iterations_auto; /* --iterations auto */
    double balance;      /* --balance L */
    int balance_auto;    /* --balance auto */
    int balance_given;   /* --balance given at all */
    double noise;        /* --noise SIGMA; 0 = estimated */
    int cg_max_steps;    /* --cg-max-steps N */
    int precision;       /* --precision: index in cli_precision_names */
    int precision_given; /* --precision given at all */
    int acceleration;    /* --acceleration: index in cli_acceleration_names */
    int keep_doubtful;   /* --keep-doubtful */
} cli_deconv_args;
enum {
    CLI_OPT_ITERATIONS = 1920,
    CLI_OPT_BALANCE,
    CLI_OPT_NOISE,
    CLI_OPT_CG_MAX_STEPS,
    CLI_OPT_PRECISION,
    CLI_OPT_ACCELERATION,
    CLI_OPT_KEEP_DOUBTFUL
};
/* clang-format off */
#define CLI_DECONV_LONGOPTS \
    {"iterations", required_argument, NULL, CLI_OPT_ITERATIONS}, \
    {"balance", required_argument, NULL, CLI_OPT_BALANCE}, \
    {"noise", required_argument, NULL, CLI_OPT_NOISE}, \
    {"cg-max-steps", required_argument, NULL, CLI_OPT_CG_MAX_STEPS}, \
    {"precision", required_argument, NULL, CLI_OPT_PRECISION}, \
    {"acceleration", required_argument, NULL, CLI_OPT_ACCELERATION}, \
    {"keep-doubtful", no_argument, NULL, CLI_OPT_KEEP_DOUBTFUL}
/* clang-format on */
/* Defaults from the library's options (svp_deconv_defaults, svp_correct_defaults' deconv). */
void cli_deconv_init(cli_deconv_args *args, const svp_deconv_options *defaults);
int cli_deconv_option(const cli_run *run, cli_deconv_args *args, int option, const char *arg);
/* Copies iterations, balance, CG cap, acceleration and precision into the library's options
 * (auto_stop from --iterations auto; the noise and --balance auto are the caller's). */
void cli_deconv_apply(const cli_deconv_args *args, svp_deconv_options *opt);
/* The --cg-max-steps help lines (the same in both commands) with its default. */
void cli_print_deconv_help(FILE *out, const svp_deconv_options *defaults);
/* --acceleration: indexed by svp_rl_acceleration. */
extern const char *const cli_acceleration_names[];
/* svp_deconv_report.stop as the summary names it. */
extern const char *const cli_rl_stop_names[];

/* The spot fit fit-psf and map-psf share: --model, --circular, --gain (photons per data unit,
 * >= 0). */
typedef struct cli_spot_args {
    int model;      /* index in cli_psf_model_names (default moffat) */
    int elliptical; /* 0 with --circular */
    double gain;    /* --gain (default: the library's) */
} cli_spot_args;
enum { CLI_OPT_MODEL = 1930, CLI_OPT_CIRCULAR, CLI_OPT_GAIN };
/* clang-format off */
#define CLI_SPOT_LONGOPTS \
    {"model", required_argument, NULL, CLI_OPT_MODEL}, \
    {"circular", no_argument, NULL, CLI_OPT_CIRCULAR}, \
    {"gain", required_argument, NULL, CLI_OPT_GAIN}
/* clang-format on */
/* Defaults from the library's options (svp_spot_defaults). */
void cli_spot_init(cli_spot_args *args, const svp_spot_options *defaults);
int cli_spot_option(const cli_run *run, cli_spot_args *args, int option, const char *arg);
/* Sets model, elliptical and noise.gain of the library's spot options. */
void cli_spot_apply(const cli_spot_args *args, svp_spot_options *opt);
/* The --model help line. */
void cli_print_spot_help(FILE *out);

/* A command in two halves: `int parse_X_args(cli_run *run, struct X_args *args)` reads the
 * options into the command's struct (its own and its groups') and checks them, returning 0 to
 * go on, CLI_OPTION_HELP after printing the help, or the exit status after a message; then
 * `int run_X(cli_run *run, const struct X_args *args)` does the work in the command's own
 * stages (read, plan, compute, write, report) and returns the exit status. cmd_X is then
 *     int code = parse_X_args(&run, &args);
 *     if (code == 0) code = run_X(&run, &args);
 *     return cli_run_finish(&run, cli_parsed_status(code));
 * cli_parsed_status maps CLI_OPTION_HELP to 0 and keeps any other status. */
int cli_parsed_status(int code);

/* The positional arguments after the options: exactly one, else an error. `missing` is the
 * message when there is none; a second one is "unexpected argument 'X'" followed by
 * `extra_note` (may be ""). Returns the argument, or NULL after the message. */
const char *cli_one_argument(const cli_run *run, const char *missing, const char *extra_note);

#endif
