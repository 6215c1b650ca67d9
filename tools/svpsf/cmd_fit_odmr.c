/* svpsf fit-odmr: per-pixel Lorentzian fits of a measured ODMR stack (svp_odmr_fit_maps) into
 * the maps `svpsf correct` takes: field (+ its σ for --field-sigma) and the PL. */
#include "cli.h"
#include "io/mat.h"

#include <errno.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

enum {
    OPT_FREQUENCIES = CLI_OPTION_FIRST,
    OPT_FREQ_UNIT,
    OPT_LINES,
    OPT_LINE,
    OPT_ZERO_FIELD,
    OPT_GAMMA,
    OPT_LINEWIDTH,
    OPT_BASELINE_FRAMES,
    OPT_MAX_ITERATIONS,
    OPT_UNIT,
    OPT_FAILED,
    OPT_REGISTER,
    OPT_DRIFT_DEGREE,
    OPT_ALIGN_TO,
    OPT_PSF,
    OPT_ITERATIONS,
    OPT_TAIL_TOL,
    OPT_MARGIN,
    OPT_SAVE_STACK
};

static const char *const lines_names[] = {"pair", "two", "one", NULL};
static const char *const line_names[] = {"upper", "lower", NULL};
static const char *const unit_names[] = {"T", "mT", "uT", "nT", NULL};
static const double unit_scale[] = {1, 1e3, 1e6, 1e9}; /* file value = tesla × scale */
static const char *const freq_unit_names[] = {"Hz", "kHz", "MHz", "GHz", NULL};
static const double freq_unit_hz[] = {1, 1e3, 1e6, 1e9};
static const char *const failed_names[] = {"nan", "keep", NULL};

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf fit-odmr STACK --frequencies F.txt|START:STOP:N -o DIR [options]\n"
          "\n"
          "Fits every pixel's ODMR spectrum of a measured stack (one camera frame per microwave\n"
          "frequency) with Lorentzian dips (docs/model.md section 10) and writes the maps that\n"
          "`svpsf correct` takes: the field, its 1-sigma uncertainty (for --field-sigma) and the\n"
          "PL (the off-resonance baseline), with the contrast, the linewidth, their\n"
          "uncertainties and a fit-quality map.\n"
          "\n"
          "inputs:\n"
          "  STACK                 a multi-page TIFF (one page per frequency; 8/16/32-bit\n"
          "                        integer or float pages), or a .npy of shape (frames, height,\n"
          "                        width)\n"
          "  --frequencies F|START:STOP:N  the frame frequencies: a text file (.txt/.csv/.dat,\n"
          "                        one value per frame, in order, as numpy.savetxt writes\n"
          "                        them) or N equally spaced values from START to STOP; a\n"
          "                        decreasing sweep is put in increasing order\n"
          "  --frequency-unit Hz|kHz|MHz|GHz  unit of --frequencies (default Hz)\n"
          "model (the sign conventions of docs/model.md section 10):\n"
          "  --lines pair|two|one  pair (default): both lines of one NV axis at D +/- gamma B\n"
          "                        about the given D, sharing contrast and width: field = |B|;\n"
          "                        two: two dips at free frequencies f- < f+: field =\n"
          "                        (f+ - f-) / (2 gamma), independent of shifts of D, and\n"
          "                        field_lower = (D - f-) / gamma, field_upper =\n"
          "                        (f+ - D) / gamma per resonance;\n"
          "                        one: the sweep holds one line: field = s (f0 - D) / gamma\n"
          "  --line upper|lower    with --lines one: the line swept, s = +1 (upper, at\n"
          "                        D + gamma B, default) or -1 (lower)\n"
          "  --zero-field HZ       D (default 2.870e9)\n"
          "  --gamma HZ_PER_T      gamma_NV / 2 pi (default 28.033e9)\n"
          "  --linewidth HZ        starting FWHM of a dip (default 1e6); the fit frees it\n"
          "  --baseline-frames N   frames at each end averaged for the starting baseline\n"
          "                        (default 3)\n"
          "  --max-iterations N    Levenberg-Marquardt steps per pixel (default 200)\n"
          ,
          out);
    fputs("drift (docs/model.md section 10, \"Drift\"):\n"
          "  --register            align the frames before the fit: each is registered on the\n"
          "                        mean frame (phase correlation, translation) and moved by\n"
          "                        Fourier interpolation; the shifts go to DIR/drift.csv.\n"
          "                        A sample that drifts by a few hundredths of a pixel during\n"
          "                        the sweep already moves its PL edges by more than the dips\n"
          "                        are deep. A frame that correlates with the mean frame\n"
          "                        below 0.5 (too little texture above the noise) is an\n"
          "                        error (exit 3)\n"
          "  --drift-degree N      the drift applied is a polynomial of degree N in the frame\n"
          "                        index, fitted robustly to the measured shifts (the frames on\n"
          "                        a resonance are pulled by their dips); -1: each frame its\n"
          "                        own measured shift (default 1: a steady drift)\n"
          "  --align-to mean|K     where the frames go: the sweep's mean position (default;\n"
          "                        each frame moves by at most half the drift) or the\n"
          "                        position of the stack's frame K (0 = the first), e.g. where\n"
          "                        a reference image was taken\n"
          "blur (docs/model.md section 10, \"Blur before the estimate\"):\n"
          "  --psf FILE            deconvolve every frame by this PSF (a PSF file, a PSF map\n"
          "                        or a kernel image, as `correct` takes) before the fit:\n"
          "                        Richardson-Lucy on the frame plus a margin, the margin's\n"
          "                        light explained by sources outside the view. The fit then\n"
          "                        sees each pixel's own spectrum, where T^-1 on fitted maps\n"
          "                        (`correct`) assumes the PL-weighted mean field, which a fit\n"
          "                        of mixed dips is not\n"
          "  --iterations N        Richardson-Lucy iterations per frame (default 75)\n"
          "  --margin auto|PX      the margin (default auto: the PSF's reach, 0 with a halo;\n"
          "                        0 for a PSF map, whose edge PSFs a margin carries outward;\n"
          "                        auto there: the map's widest PSF's reach)\n"
          "  --tail-tol TOL        one PSF or a low-rank or region map: its far tail on a\n"
          "                        coarser grid when cheaper and within TOL (default 1e-3;\n"
          "                        0: never; as `correct`)\n",
          out);
    cli_print_variant_help(out, 1e-2);
    fputs("outputs:\n"
          "  -o, --output DIR      output folder, created when missing (required)\n"
          "  --unit T|mT|uT|nT     unit of the field maps written (default T)\n"
          "  --save-stack FILE.npy  also write the stack as fitted (after --register and\n"
          "                        --psf) as a float64 .npy (frames, height, width), in the\n"
          "                        stack's order, for other tools\n"
          "  --failed nan|keep     pixels whose fit did not converge: NaN in the field maps\n"
          "                        (default; `correct` treats them as missing data) or the\n"
          "                        last parameters\n",
          out);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs in DIR: field.EXT, field_sigma.EXT (and with --lines two field_lower,\n"
          "field_lower_sigma, field_upper, field_upper_sigma), pl.EXT, pl_sigma.EXT,\n"
          "contrast.EXT, contrast_sigma.EXT, linewidth.EXT (Hz), linewidth_sigma.EXT,\n"
          "quality.EXT (R^2 of each fit: 1 perfect, near 0 no dip), summary.json (and with\n"
          "--register drift.csv). Then:\n"
          "  svpsf correct --pl DIR/pl.tif --field DIR/field.tif \\\n"
          "                --field-sigma DIR/field_sigma.tif --psf PSF -o OUT\n"
          "exit status: 0 ok, 1 bad usage or bad input, 2 runtime failure, 3 a frame that\n"
          "--register cannot align (nothing written).\n",
          out);
}

/* START:STOP:N → 1 with the values, 0 when text is not of that form. */
static int parse_range(const char *text, double *start, double *stop, long *count)
{
    char *end;
    errno = 0;
    *start = strtod(text, &end);
    if (end == text || *end != ':') return 0;
    const char *p = end + 1;
    *stop = strtod(p, &end);
    if (end == p || *end != ':') return 0;
    p = end + 1;
    *count = strtol(p, &end, 10);
    if (end == p || *end) return 0;
    return 1;
}

static int read_frequencies(cli_run *run, const char *arg, double unit, int n_frames,
                            const char *stack_path, double *freq)
{
    double start, stop;
    long count;
    struct stat sb;
    if (stat(arg, &sb) != 0 && parse_range(arg, &start, &stop, &count)) {
        if (!isfinite(start) || !isfinite(stop) || start == stop)
            return cli_error(run, "--frequencies %s: START and STOP must be finite and differ",
                             arg);
        if (count != n_frames)
            return cli_error(run, "--frequencies %s: %ld frequencies for a stack of %d frames "
                             "(%s)",
                             arg, count, n_frames, stack_path);
        for (int f = 0; f < n_frames; f++)
            freq[f] = unit * (start + (stop - start) * f / (double)(n_frames - 1));
        return 0;
    }
    char mfile[4096], mvar[64];
    int mbad = 0;
    if (stat(arg, &sb) != 0 && strchr(arg, ':') &&
        !svp_io_mat_path(arg, mfile, sizeof mfile, mvar, sizeof mvar, &mbad))
        return cli_error(run,
                         "--frequencies %s: neither a file nor START:STOP:N (two numbers and a "
                         "whole count of frames, e.g. 2.8e9:2.94e9:60)",
                         arg);
    svp_image *values = NULL;
    int code = cli_read_image(run, "frequencies", arg, &values);
    if (code) return code;
    const size_t n = (size_t)values->width * values->height;
    if (values->width != 1 && values->height != 1) {
        code = cli_error(run, "%s: %d x %d values: the frequencies must be one row or one "
                         "column",
                         arg, values->width, values->height);
    } else if (n != (size_t)n_frames) {
        code = cli_error(run, "%s: %zu frequencies for a stack of %d frames (%s)", arg, n,
                         n_frames, stack_path);
    } else {
        for (size_t f = 0; f < n && !code; f++) {
            freq[f] = unit * values->data[f];
            if (!isfinite(freq[f]))
                code = cli_error(run, "%s: frequency %zu is not a finite number", arg, f + 1);
        }
    }
    svp_image_free(values);
    return code;
}

struct fit_odmr_args {
    const char *stack_path;                                    /* STACK */
    const char *freq_arg;                                      /* --frequencies */
    int freq_unit, lines, line, line_given, unit, failed_mode; /* indices in the name tables */
    int align, drift_degree, drift_degree_given;              /* --register, --drift-degree */
    int align_to, align_to_given;                             /* --align-to: -1 mean, k frame */
    const char *psf_path;                                     /* --psf */
    svp_variant_options variant; /* a PSF map's operator (--nodes, --rank, ...) */
    const char *save_stack;      /* --save-stack FILE.npy */
    int variant_given;
    int iterations, iterations_given, margin, margin_auto, margin_given;
    double tail_tol; /* --tail-tol */
    svp_odmr od;              /* --zero-field, --gamma, --linewidth */
    svp_odmr_fit_options opt; /* --baseline-frames, --max-iterations; lines and line */
};

enum { N_MAPS = 15 };

/* What a run holds (released by run_fit_odmr). */
struct fit_odmr_job {
    svp_stack *stack;
    int nf, w, h;
    double *freq;       /* increasing, Hz */
    svp_image **frames; /* in the order of freq */
    svp_image *img[N_MAPS];
    const char *paths[N_MAPS], *summary_path, *drift_path, *stack_out;
    size_t n_failed;
    double fit_seconds;
    double *shift_x, *shift_y; /* --register: each frame's, in the order of freq */
    cli_psf psf;               /* --psf */
    int psf_loaded, margin;
    int decreasing;            /* the stack's frames were in decreasing frequency */
};

/* The stack's frames as the library's cube (in the order of freq; not copied). */
static svp_cube job_cube(const struct fit_odmr_job *job)
{
    return (svp_cube){
        .width = job->w, .height = job->h, .n_freq = job->nf, .freq = job->freq,
        .frame = job->frames};
}

static int fit_odmr_option(cli_run *run, struct fit_odmr_args *a, int c)
{
    svp_odmr *od = &a->od;
    switch (c) {
    case OPT_FREQUENCIES: a->freq_arg = optarg; return 0;
    case OPT_FREQ_UNIT:
        return cli_parse_choice(run, "--frequency-unit", optarg, freq_unit_names, &a->freq_unit);
    case OPT_LINES: return cli_parse_choice(run, "--lines", optarg, lines_names, &a->lines);
    case OPT_LINE:
        a->line_given = 1;
        return cli_parse_choice(run, "--line", optarg, line_names, &a->line);
    case OPT_ZERO_FIELD:
        return cli_parse_double_in(run, "--zero-field", optarg, 0, 0, INFINITY, 0,
                                   &od->zero_field_hz);
    case OPT_GAMMA:
        return cli_parse_double_in(run, "--gamma", optarg, 0, 0, INFINITY, 0, &od->gamma_hz_per_t);
    case OPT_LINEWIDTH:
        return cli_parse_double_in(run, "--linewidth", optarg, 0, 0, INFINITY, 0,
                                   &od->linewidth_hz);
    case OPT_BASELINE_FRAMES:
        return cli_parse_int(run, "--baseline-frames", optarg, 1, 1000000, &a->opt.baseline_frames);
    case OPT_MAX_ITERATIONS:
        return cli_parse_int(run, "--max-iterations", optarg, 1, 1000000,
                             &a->opt.lm.max_iterations);
    case OPT_UNIT: return cli_parse_choice(run, "--unit", optarg, unit_names, &a->unit);
    case OPT_FAILED:
        return cli_parse_choice(run, "--failed", optarg, failed_names, &a->failed_mode);
    case OPT_REGISTER: a->align = 1; return 0;
    case OPT_DRIFT_DEGREE:
        a->drift_degree_given = 1;
        return cli_parse_int(run, "--drift-degree", optarg, -1, 5, &a->drift_degree);
    case OPT_PSF: a->psf_path = optarg; return 0;
    case OPT_SAVE_STACK: a->save_stack = optarg; return 0;
    case OPT_ITERATIONS:
        a->iterations_given = 1;
        return cli_parse_int(run, "--iterations", optarg, 1, 1000000, &a->iterations);
    case OPT_TAIL_TOL:
        return cli_parse_double_in(run, "--tail-tol", optarg, 0, 1, 1, 0, &a->tail_tol);
    case OPT_MARGIN:
        a->margin_given = 1;
        a->margin_auto = strcmp(optarg, "auto") == 0;
        return a->margin_auto ? 0 : cli_parse_int(run, "--margin", optarg, 0, 100000, &a->margin);
    case OPT_ALIGN_TO:
        a->align_to_given = 1;
        if (!strcmp(optarg, "mean")) {
            a->align_to = -1;
            return 0;
        }
        return cli_parse_int(run, "--align-to", optarg, 0, 1000000000, &a->align_to);
    default:
        if (c >= CLI_OPT_NODES && c <= CLI_OPT_REGIONS) {
            a->variant_given = 1;
            return cli_variant_option(run, &a->variant, c, optarg);
        }
        return cli_error(run, "internal: option %d", c);
    }
}

static int parse_fit_odmr_args(cli_run *run, struct fit_odmr_args *a)
{
    static const struct option own[] = {
        {"frequencies", required_argument, NULL, OPT_FREQUENCIES},
        {"frequency-unit", required_argument, NULL, OPT_FREQ_UNIT},
        {"lines", required_argument, NULL, OPT_LINES},
        {"line", required_argument, NULL, OPT_LINE},
        {"zero-field", required_argument, NULL, OPT_ZERO_FIELD},
        {"gamma", required_argument, NULL, OPT_GAMMA},
        {"linewidth", required_argument, NULL, OPT_LINEWIDTH},
        {"baseline-frames", required_argument, NULL, OPT_BASELINE_FRAMES},
        {"max-iterations", required_argument, NULL, OPT_MAX_ITERATIONS},
        {"unit", required_argument, NULL, OPT_UNIT},
        {"failed", required_argument, NULL, OPT_FAILED},
        {"register", no_argument, NULL, OPT_REGISTER},
        {"drift-degree", required_argument, NULL, OPT_DRIFT_DEGREE},
        {"align-to", required_argument, NULL, OPT_ALIGN_TO},
        {"psf", required_argument, NULL, OPT_PSF},
        {"save-stack", required_argument, NULL, OPT_SAVE_STACK},
        {"iterations", required_argument, NULL, OPT_ITERATIONS},
        {"tail-tol", required_argument, NULL, OPT_TAIL_TOL},
        {"margin", required_argument, NULL, OPT_MARGIN},
        CLI_VARIANT_LONGOPTS,
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    a->drift_degree = 1;
    a->align_to = -1;
    a->iterations = 75;
    a->tail_tol = SVP_TAIL_TOL_DEFAULT;
    a->margin_auto = 1;
    cli_variant_defaults(&a->variant);
    a->variant.tolerance = 1e-2; /* as correct's: the deconvolution's own error dominates */
    svp_odmr_defaults(&a->od);
    svp_odmr_fit_defaults(&a->opt);
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        if (c == CLI_OPTION_HELP) {
            print_help(run, stdout);
            return CLI_OPTION_HELP;
        }
        if (c == CLI_OPTION_ERROR || fit_odmr_option(run, a, c)) return CLI_EXIT_USAGE;
    }
    a->stack_path = cli_one_argument(run, "STACK is required (see --help)", " (one STACK)");
    if (!a->stack_path) return CLI_EXIT_USAGE;
    if (!a->freq_arg) return cli_error(run, "--frequencies is required (a file or START:STOP:N)");
    if (!run->output) return cli_error(run, "-o DIR is required");
    if (a->line_given && a->lines != 2)
        return cli_error(run, "--line %s needs --lines one", line_names[a->line]);
    if (a->drift_degree_given && !a->align)
        return cli_error(run, "--drift-degree needs --register");
    if (a->align_to_given && !a->align) return cli_error(run, "--align-to needs --register");
    if ((a->iterations_given || a->margin_given || a->variant_given) && !a->psf_path)
        return cli_error(run, "--%s needs --psf",
                         a->iterations_given ? "iterations"
                         : a->margin_given   ? "margin"
                                             : "nodes / --rank / --regions / --operator-tol");
    a->opt.lines = a->lines == 1   ? SVP_ODMR_LINES_TWO
                   : a->lines == 2 ? SVP_ODMR_LINES_ONE
                                   : SVP_ODMR_LINES_PAIR;
    a->opt.line_sign = a->line == 1 ? -1 : 1;
    return 0;
}

/* The frequencies of the frames, in increasing order (a decreasing sweep reverses the frames
 * too); anything else is refused. */
static int fit_odmr_frequencies(cli_run *run, const struct fit_odmr_args *a,
                                struct fit_odmr_job *job)
{
    const int nf = job->nf;
    double *freq = job->freq;
    int code;
    if ((code = read_frequencies(run, a->freq_arg, freq_unit_hz[a->freq_unit], nf, a->stack_path,
                                 freq)))
        return code;
    const int decreasing = job->decreasing = freq[nf - 1] < freq[0];
    for (int f = 0; f < nf; f++) {
        job->frames[f] = job->stack->frame[decreasing ? nf - 1 - f : f];
        if (decreasing && f < nf / 2) {
            double t = freq[f];
            freq[f] = freq[nf - 1 - f];
            freq[nf - 1 - f] = t;
        }
    }
    for (int f = 1; f < nf; f++)
        if (!(freq[f] > freq[f - 1]))
            return cli_error(run,
                             "--frequencies %s: not monotonic: frame %d at %.9g Hz after "
                             "%.9g Hz",
                             a->freq_arg, decreasing ? nf - f : f + 1, freq[f], freq[f - 1]);
    /* NV lines lie at D ± γB: tens of MHz and up (the lower one reaches 0 only at 102 mT);
     * frequencies <= 0 are the library's to refuse */
    if (freq[0] > 0 && !(freq[nf - 1] >= 1e6))
        return cli_error(run,
                         "--frequencies %s: the sweep ends at %.6g Hz, below 1 MHz where no NV "
                         "line lies: give their unit with --frequency-unit (kHz, MHz, GHz)",
                         a->freq_arg, freq[nf - 1]);
    return 0;
}

/* The stack (enough frames for the fit and the baseline) and its frequencies. */
static int fit_odmr_read(cli_run *run, const struct fit_odmr_args *a, struct fit_odmr_job *job)
{
    const char *stack_path = a->stack_path;
    cli_stage_begin(run, "read");
    int code = cli_read_stack(run, "stack", stack_path, &job->stack);
    if (code) return code;
    const int nf = job->nf = job->stack->n_frames;
    job->w = job->stack->width;
    job->h = job->stack->height;
    const int np = a->opt.lines == SVP_ODMR_LINES_TWO ? 5 : 4;
    if (nf < 5 || nf <= np)
        return cli_error(run,
                         "%s: %d frame%s: a Lorentzian fit (--lines %s) needs at least %d "
                         "(one per frequency)",
                         stack_path, nf, nf == 1 ? "" : "s", lines_names[a->lines],
                         np + 1 > 5 ? np + 1 : 5);
    if (2 * a->opt.baseline_frames > nf)
        return cli_error(run, "--baseline-frames %d: at most %d for a stack of %d frames",
                         a->opt.baseline_frames, nf / 2, nf);
    job->freq = malloc((size_t)nf * sizeof(double));
    job->frames = malloc((size_t)nf * sizeof *job->frames);
    if (!job->freq || !job->frames) return cli_error(run, "out of memory");
    return fit_odmr_frequencies(run, a, job);
}

/* Every output planned and checked, the maps allocated, the settings recorded. */
static int fit_odmr_plan(cli_run *run, const struct fit_odmr_args *a, struct fit_odmr_job *job)
{
    static const char *const names[N_MAPS] = {
        "field",       "field_sigma",       "field_lower", "field_lower_sigma",
        "field_upper", "field_upper_sigma", "pl",          "pl_sigma",
        "contrast",    "contrast_sigma",    "linewidth",   "linewidth_sigma",
        "quality",     "converged",         NULL};
    const svp_odmr *od = &a->od;
    const svp_odmr_fit_options *opt = &a->opt;
    int code;
    for (int k = 0; k < 13; k++) {
        if (opt->lines != SVP_ODMR_LINES_TWO && k >= 2 && k < 6) continue;
        job->paths[k] = cli_output_in_dir(run, names[k], names[k], 1);
    }
    job->summary_path = cli_output_in_dir(run, "summary", "summary.json", 0);
    if (a->align) {
        job->drift_path = cli_output_in_dir(run, "drift", "drift.csv", 0);
        job->shift_x = malloc(2 * (size_t)job->nf * sizeof(double));
        if (!job->shift_x) return cli_error(run, "out of memory");
        job->shift_y = job->shift_x + job->nf;
        if (job->nf <= a->drift_degree + 1)
            return cli_error(run, "--drift-degree %d: a stack of %d frames fits at most degree %d",
                             a->drift_degree, job->nf, job->nf - 2);
        if (a->align_to >= job->nf)
            return cli_error(run, "--align-to %d: the stack's frames are 0 to %d", a->align_to,
                             job->nf - 1);
    }
    if (a->save_stack) {
        const char *dot = strrchr(a->save_stack, '.');
        if (!dot || strcmp(dot, ".npy") != 0)
            return cli_error(run, "--save-stack %s: the stack is written as a 3-D .npy (the name "
                             "must end in .npy)", a->save_stack);
        job->stack_out = cli_output_file(run, "stack", a->save_stack);
    }
    if (a->psf_path) {
        if ((code = cli_psf_load_map(run, a->psf_path, &a->variant, &job->psf))) return code;
        if ((code = cli_check_input_pixels(run, job->psf.pixel_um, a->psf_path))) return code;
        job->psf_loaded = 1;
        job->psf.boundary = SVP_BOUNDARY_ZERO;
        if (a->variant_given && !job->psf.field)
            cli_note(run, "--nodes / --rank / --regions ignored: %s is a single PSF, not a "
                     "space-variant map", a->psf_path);
        /* default: auto with one PSF, 0 for a map (as correct's) */
        if (job->psf.field && !a->margin_given) job->margin = 0;
        else if (a->margin_auto) job->margin = cli_auto_margin(&job->psf, job->w, job->h);
        else job->margin = a->margin;
        if ((code = cli_psf_check(run, &job->psf, job->w, job->h))) return code;
        svp_status ms = svp_correct_check_margin(job->margin, job->w, job->h);
        if (ms != SVP_OK) return cli_fail(run, ms, a->psf_path);
        /* a map carried onto the margin from its edge (svp_psf_field_pad) */
        if ((code = cli_psf_pad(run, &job->psf, job->margin))) return code;
    }
    if ((code = cli_outputs_check(run))) return code;
    svp_status st = SVP_OK;
    for (int k = 0; k < 14 && st == SVP_OK; k++)
        if (job->paths[k] || k == 13) st = svp_image_new(job->w, job->h, &job->img[k]);
    if (st != SVP_OK) return cli_fail(run, st, NULL);

    cli_setting_int(run, "n_frames", job->nf);
    cli_setting_num(run, "frequency_first_hz", job->freq[0]);
    cli_setting_num(run, "frequency_last_hz", job->freq[job->nf - 1]);
    cli_setting_str(run, "lines", lines_names[a->lines]);
    if (opt->lines == SVP_ODMR_LINES_ONE) cli_setting_str(run, "line", line_names[a->line]);
    cli_setting_num(run, "zero_field_hz", od->zero_field_hz);
    cli_setting_num(run, "gamma_hz_per_t", od->gamma_hz_per_t);
    cli_setting_num(run, "linewidth_start_hz", od->linewidth_hz);
    cli_setting_int(run, "baseline_frames", opt->baseline_frames);
    cli_setting_int(run, "max_iterations", opt->lm.max_iterations);
    cli_setting_str(run, "unit", unit_names[a->unit]);
    cli_setting_str(run, "failed", failed_names[a->failed_mode]);
    cli_setting_int(run, "register", a->align);
    if (a->align) cli_setting_int(run, "drift_degree", a->drift_degree);
    if (a->align) cli_setting_int(run, "align_to", a->align_to);
    if (a->psf_path) {
        cli_psf_describe(run, &job->psf);
        cli_setting_int(run, "iterations", a->iterations);
        cli_setting_num(run, "tail_tol", a->tail_tol);
        cli_setting_int(run, "margin", job->margin);
    }
    return 0;
}

/* --psf: every frame deconvolved (svp_cube_deconvolve) before the fit. */
static int fit_odmr_deconvolve(cli_run *run, const struct fit_odmr_args *a,
                               struct fit_odmr_job *job)
{
    if (!a->psf_path) return 0;
    cli_stage_begin(run, "deconvolve");
    svp_blur *blur = NULL;
    const int m = job->margin;
    /* a map's representation is chosen for this many H + Hᵀ pairs */
    const long pairs = (long)a->iterations * job->nf;
    job->psf.variant.applications = pairs < 1000000 ? (int)pairs : 1000000;
    job->psf.variant.tail_tol = a->tail_tol; /* a map's far tail (low rank, regions) */
    int code = cli_psf_blur(run, &job->psf, job->w + 2 * m, job->h + 2 * m, SVP_BOUNDARY_ZERO,
                            &blur);
    if (code) return code;
    /* one PSF: its far tail on a coarse grid when cheaper (docs/model.md §5) */
    int step = 0, split = 0;
    double tail_err = 0;
    svp_status st = svp_blur_set_tail(blur, a->tail_tol);
    if (st == SVP_OK) st = svp_blur_tail_info(blur, &step, &split, &tail_err);
    if (st != SVP_OK) {
        svp_blur_free(blur);
        return cli_fail(run, st, a->psf_path);
    }
    cli_result_int(run, "deconvolve_tail_step_px", step);
    if (step > 0) {
        cli_result_int(run, "deconvolve_tail_split_px", split);
        cli_result_num(run, "deconvolve_tail_error", tail_err);
    }
    svp_cube cube = job_cube(job);
    svp_deconv_options o;
    svp_deconv_defaults(&o);
    o.iterations = a->iterations;
    cli_progress_start(run, "deconvolving frames");
    size_t negative = 0;
    st = svp_cube_deconvolve(blur, &cube, m, &o, &negative, cli_progress, run);
    cli_progress_done(run);
    svp_blur_free(blur);
    if (st != SVP_OK) return cli_fail(run, st, a->stack_path);
    if (negative)
        cli_note(run, "%zu of %zu stack values were below 0 and were taken as 0 for the "
                 "deconvolution (Richardson-Lucy needs data >= 0)", negative,
                 (size_t)job->w * job->h * (size_t)job->nf);
    cli_result_int(run, "deconvolve_negative_values", (long long)negative);
    return 0;
}

/* --register: the frames aligned on the mean frame (svp_cube_align); a frame it cannot vouch
 * for stops the run (exit 3). */
static int fit_odmr_align(cli_run *run, const struct fit_odmr_args *a, struct fit_odmr_job *job)
{
    if (!a->align) return 0;
    cli_stage_begin(run, "register");
    svp_cube cube = job_cube(job);
    svp_align_info info;
    cli_progress_start(run, "aligning frames");
    svp_align_options ao;
    svp_align_defaults(&ao);
    ao.degree = a->drift_degree;
    /* the stack's frame k is frame nf − 1 − k of the cube when the sweep decreased */
    ao.reference_frame = a->align_to < 0 ? -1 : job->decreasing ? job->nf - 1 - a->align_to
                                                                : a->align_to;
    svp_status st =
        svp_cube_align(&cube, &ao, job->shift_x, job->shift_y, &info, cli_progress, run);
    cli_progress_done(run);
    if (st != SVP_OK) return cli_fail(run, st, a->stack_path);
    const int nf = job->nf;
    const int worst = info.worst_frame < 0 ? 0 : info.worst_frame;
    if (info.n_low_correlation) {
        cli_error(run,
                  "%s: --register: %d of %d frames correlate too weakly with the mean frame to "
                  "be aligned (weakest: frame %d of the stack, correlation %.2f < %g): the PL "
                  "has too little texture above the noise, or the frames do not show one "
                  "scene; nothing written (run without --register)",
                  a->stack_path, info.n_low_correlation, nf,
                  job->decreasing ? nf - 1 - worst : worst, info.min_correlation,
                  SVP_ALIGN_MIN_CORRELATION);
        return CLI_EXIT_DOUBTFUL;
    }
    cli_result_num(run, "register_max_shift_px", info.max_shift);
    cli_result_num(run, "register_median_deviation_px", info.median_deviation);
    cli_result_num(run, "register_max_deviation_px", info.max_deviation);
    cli_result_num(run, "register_min_correlation", info.min_correlation);
    cli_result_num(run, "register_min_significance", info.min_significance);
    cli_note(run,
             "frames aligned: largest drift %.3g px; the measured shifts lie %.2g px (median) "
             "from the degree-%d drift",
             info.max_shift, info.median_deviation, a->drift_degree);
    return 0;
}

/* DIR/drift.csv: each frame's shift, in the stack's order. */
static int fit_odmr_write_drift(cli_run *run, const struct fit_odmr_job *job)
{
    const int nf = job->nf;
    const size_t cap = 64 + 96 * (size_t)nf;
    char *text = malloc(cap);
    if (!text) return cli_error(run, "out of memory");
    size_t len = (size_t)snprintf(text, cap, "frame,frequency_hz,shift_x_px,shift_y_px\n");
    for (int k = 0; k < nf; k++) {
        const int f = job->decreasing ? nf - 1 - k : k; /* k: the stack's frame */
        len += (size_t)snprintf(text + len, cap - len, "%d,%.10g,%.6g,%.6g\n", k, job->freq[f],
                                job->shift_x[f], job->shift_y[f]);
    }
    const int code = cli_write_text(run, job->drift_path, text);
    free(text);
    return code;
}

/* The per-pixel fits. */
static int fit_odmr_fit(cli_run *run, const struct fit_odmr_args *a, struct fit_odmr_job *job)
{
    svp_image **img = job->img;
    cli_stage_begin(run, "fit");
    svp_cube cube = job_cube(job);
    svp_odmr_maps maps = {.field = img[0],
                          .field_sigma = img[1],
                          .field_lower = img[2],
                          .field_lower_sigma = img[3],
                          .field_upper = img[4],
                          .field_upper_sigma = img[5],
                          .baseline = img[6],
                          .baseline_sigma = img[7],
                          .contrast = img[8],
                          .contrast_sigma = img[9],
                          .linewidth = img[10],
                          .linewidth_sigma = img[11],
                          .quality = img[12],
                          .converged = img[13]};
    svp_odmr_fit_options opt = a->opt;
    opt.progress = cli_progress;
    opt.progress_user = run;
    cli_progress_start(run, "fitting");
    const double t_fit = cli_now();
    svp_status st = svp_odmr_fit_maps(&a->od, &cube, &opt, &maps, &job->n_failed);
    job->fit_seconds = cli_now() - t_fit;
    cli_progress_done(run);
    if (st != SVP_OK) return cli_fail(run, st, a->stack_path);
    const size_t n = (size_t)job->w * job->h;
    if (job->n_failed == n) { /* maps of NaN only: nothing to vouch for */
        cli_error(run,
                  "%s: none of the %zu pixel fits found a dip in the sweep (%.6g to %.6g GHz): "
                  "no light, no dip above the noise, lines outside the sweep, or frequencies in "
                  "another unit than Hz; nothing written",
                  a->stack_path, n, job->freq[0] * 1e-9, job->freq[job->nf - 1] * 1e-9);
        return CLI_EXIT_DOUBTFUL;
    }
    return 0;
}

/* Units and failed pixels; statistics over the converged pixels. */
static void fit_odmr_report(cli_run *run, const struct fit_odmr_args *a, struct fit_odmr_job *job)
{
    svp_image **img = job->img;
    const size_t n = (size_t)job->w * job->h, n_failed = job->n_failed;
    double sum_q = 0, sum_sigma = 0;
    size_t n_ok = 0;
    for (size_t p = 0; p < n; p++) {
        const int ok = img[13]->data[p] == 1;
        for (int k = 0; k < 6; k++) {
            if (!img[k]) continue;
            img[k]->data[p] *= unit_scale[a->unit];
            if (!ok && a->failed_mode == 0) img[k]->data[p] = NAN;
        }
        if (ok) {
            n_ok++;
            sum_q += img[12]->data[p];
            sum_sigma += img[1]->data[p];
        }
    }
    cli_result_int(run, "n_pixels", (long long)n);
    cli_result_int(run, "n_failed", (long long)n_failed);
    cli_result_num(run, "failed_fraction", (double)n_failed / (double)n);
    if (n_ok) {
        cli_result_num(run, "mean_quality", sum_q / (double)n_ok);
        char key[64];
        snprintf(key, sizeof key, "mean_field_sigma_%s", unit_names[a->unit]);
        cli_result_num(run, key, sum_sigma / (double)n_ok);
    }
    cli_result_num(run, "fits_per_second", job->fit_seconds > 0 ? (double)n / job->fit_seconds : 0);
    if (n_failed)
        cli_note(run, "%zu of %zu pixel fits did not converge (%s in the field maps)", n_failed, n,
                 a->failed_mode == 0 ? "NaN" : "kept");
}

/* The maps, summary.json and the line on stdout. */
static int fit_odmr_write(cli_run *run, const struct fit_odmr_args *a, struct fit_odmr_job *job)
{
    const size_t n = (size_t)job->w * job->h;
    const int nf = job->nf;
    int code = 0;
    cli_stage_begin(run, "write");
    for (int k = 0; k < 13 && !code; k++)
        if (job->paths[k]) code = cli_write_image(run, job->paths[k], job->img[k]);
    if (!code && job->drift_path) code = fit_odmr_write_drift(run, job);
    if (!code && job->stack_out) {
        /* the frames as fitted (aligned, deconvolved), in the stack's order */
        const svp_image **frames = malloc((size_t)nf * sizeof *frames);
        if (!frames) return cli_error(run, "out of memory");
        for (int k = 0; k < nf; k++) frames[k] = job->frames[job->decreasing ? nf - 1 - k : k];
        svp_status st = svp_stack_write(job->stack_out, frames, nf, run->force);
        free(frames);
        if (st != SVP_OK) code = cli_fail(run, st, job->stack_out);
    }
    if (!code) code = cli_summary_write(run, job->summary_path);
    if (code) return code;
    cli_stage_end(run);
    printf("svpsf fit-odmr: %d x %d, %d frequencies (%.6g to %.6g GHz), lines %s: %zu of %zu "
           "fits converged (%.3g fits/s); maps written to %s in %.2f s\n",
           job->w, job->h, nf, job->freq[0] * 1e-9, job->freq[nf - 1] * 1e-9, lines_names[a->lines],
           n - job->n_failed, n, job->fit_seconds > 0 ? (double)n / job->fit_seconds : 0,
           run->output, cli_now() - run->t_start);
    return 0;
}

static int run_fit_odmr(cli_run *run, const struct fit_odmr_args *a)
{
    struct fit_odmr_job job;
    memset(&job, 0, sizeof job);
    int code = fit_odmr_read(run, a, &job);
    if (!code) code = fit_odmr_plan(run, a, &job);
    if (!code) code = fit_odmr_align(run, a, &job);
    if (!code) code = fit_odmr_deconvolve(run, a, &job);
    if (!code) code = fit_odmr_fit(run, a, &job);
    if (!code) {
        fit_odmr_report(run, a, &job);
        code = fit_odmr_write(run, a, &job);
    }
    for (int k = 0; k < N_MAPS; k++) svp_image_free(job.img[k]);
    free(job.frames);
    free(job.freq);
    free(job.shift_x);
    if (job.psf_loaded) cli_psf_release(&job.psf);
    svp_stack_free(job.stack);
    return code;
}

int cmd_fit_odmr(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "fit-odmr", argc, argv, CLI_COMMON_OUTPUT_DIR);
    run.fft_measure = 0; /* --register's transforms: one size, as `register`: not worth it */
    struct fit_odmr_args args;
    int code = parse_fit_odmr_args(&run, &args);
    if (code == 0) code = run_fit_odmr(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
