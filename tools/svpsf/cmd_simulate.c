/* svpsf simulate: run a scene file (docs/scenes.md): true and apparent maps, corrections,
 * reconstructions, metrics, figures, report. The library does the work (svp_scene_*); this
 * command parses options, shows the plan and progress, and says where the results are. */
#include "cli.h"
#include "svpsf_version.h"

#include "figure/figure.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum { OPT_DRY_RUN = CLI_OPTION_FIRST };

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf simulate SCENE.yaml -o DIR [options]\n"
          "       svpsf simulate SCENE.yaml --dry-run\n"
          "\n"
          "Runs a scene: a sample (magnetic flakes, current strips, field maps), its emission\n"
          "pattern and PSF, the effects it asks for (noise, the full ODMR spectrum, drift), then\n"
          "the corrections (T^-1), source reconstructions, error metrics and figures it lists.\n"
          "The scene compiles to a plan of only the stages it needs: without `spectrum` the\n"
          "closed form (eq. 3) replaces the spectral cube, without `noise` no random number is\n"
          "drawn. Scene keys: docs/scenes.md; shipped scenes: docs/scenes/*.yaml (an installed\n"
          "copy keeps docs/ in " SVPSF_DOCDIR ").\n"
          "\n"
          "options:\n"
          "  -o, --output DIR      output folder, created when missing (required unless\n"
          "                        --dry-run)\n"
          "  --dry-run             check the scene, print its plan and the files it would write;\n"
          "                        run nothing, write nothing\n",
          out);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs in DIR: report.md (plan with timings, error tables, figures), summary.json\n"
          "(plan, stage times, settings, every metric), maps/*.EXT (true, apparent, corrected,\n"
          "reconstructed, relative-error maps, masks; format from the scene's outputs.format),\n"
          "figures/*.png, tables/metrics.csv, tables/histograms.csv, tables/cut_*.csv.\n"
          "Errors in the scene file are reported as FILE:LINE:COLUMN: message (exit 1).\n",
          out);
}

static int on_stage(void *user, int index, int n_stages, const svp_scene_stage *stage)
{
    cli_run *run = user;
    (void)index;
    (void)n_stages;
    run->progress_label = stage->name;
    return 0;
}

/* A warning for each correction in doubt (kept by the scene, its doubtful pixels at validity 0;
 * docs/scenes.md). */
static void warn_doubts(const cli_run *run, const svp_scene_result *result)
{
    for (int i = 0; i < svp_scene_result_n_values(result); i++) {
        double d = 0;
        const char *k = svp_scene_result_value_at(result, i, &d);
        const size_t kl = strlen(k);
        if (strncmp(k, "correct/", 8) != 0 || kl < 16 || strcmp(k + kl - 7, "/doubts") != 0 ||
            !(d > 0))
            continue;
        char list[256];
        svp_doubt_list((unsigned)d, list, sizeof list);
        cli_warn(run,
                 "correction '%.*s' is in doubt (%s): the scene keeps it, its doubtful pixels "
                 "with validity 0 (summary.json: correct/%.*s/doubts)",
                 (int)(kl - 15), k + 8, list, (int)(kl - 15), k + 8);
    }
}

/* The most telling number of each correction: the median |relative error| of the first
 * reconstruction (else the first field component) over the first mask other than "view"; a
 * correction in doubt says so. */
static void print_headline(const svp_scene_result *result)
{
    const char *quantities[] = {"m_z", "J_bxy", "J_bz", "B_z", "B_x", "B_y", "B_nv"};
    const char *tail = "/apparent/median_abs_rel_err_pct";
    for (size_t qi = 0; qi < sizeof quantities / sizeof *quantities; qi++) {
        char mask[64] = "";
        size_t ql = strlen(quantities[qi]);
        for (int pass = 0; pass < 2 && !mask[0]; pass++)
            for (int i = 0; i < svp_scene_result_n_values(result) && !mask[0]; i++) {
                const char *k = svp_scene_result_value_at(result, i, NULL);
                size_t kl = strlen(k), tl = strlen(tail);
                if (strncmp(k, quantities[qi], ql) != 0 || k[ql] != '/' || kl <= ql + 1 + tl ||
                    strcmp(k + kl - tl, tail) != 0)
                    continue;
                int len = (int)(kl - tl - ql - 1);
                if (len >= (int)sizeof mask) continue;
                snprintf(mask, sizeof mask, "%.*s", len, k + ql + 1);
                if (pass == 0 && strcmp(mask, "view") == 0) mask[0] = '\0';
            }
        if (!mask[0]) continue;
        char key[160];
        double v = 0;
        snprintf(key, sizeof key, "%s/%s%s", quantities[qi], mask, tail);
        svp_scene_result_value(result, key, &v);
        if (isnan(v)) { /* the metrics' relative errors are undefined where the truth is 0 */
            printf("  %s over mask '%s': no relative error (the true %s is 0 there)\n",
                   quantities[qi], mask, quantities[qi]);
            return;
        }
        printf("  %s over mask '%s': median |relative error| %.3g %% apparent", quantities[qi],
               mask, v);
        char prefix[160];
        snprintf(prefix, sizeof prefix, "%s/%s/corrected_", quantities[qi], mask);
        size_t pl = strlen(prefix);
        for (int i = 0; i < svp_scene_result_n_values(result); i++) {
            double x = 0;
            const char *k = svp_scene_result_value_at(result, i, &x);
            if (strncmp(k, prefix, pl) != 0) continue;
            const char *rest = k + pl, *slash = strchr(rest, '/');
            if (!slash || strcmp(slash, "/median_abs_rel_err_pct") != 0) continue;
            const int nl = (int)(slash - rest);
            char key_d[160], list[256] = "";
            double d = 0;
            snprintf(key_d, sizeof key_d, "correct/%.*s/doubts", nl, rest);
            if (svp_scene_result_value(result, key_d, &d) && d > 0)
                svp_doubt_list((unsigned)d, list, sizeof list);
            printf(", %.3g %% corrected (%.*s%s%s)", x, nl, rest, list[0] ? ", in doubt: " : "",
                   list);
        }
        printf("\n");
        return;
    }
}

struct simulate_args {
    int dry_run;      /* --dry-run */
    const char *path; /* the scene file */
};

static int parse_simulate_args(cli_run *run, struct simulate_args *a)
{
    static const struct option own[] = {
        {"dry-run", no_argument, NULL, OPT_DRY_RUN},
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        switch (c) {
        case CLI_OPTION_HELP: print_help(run, stdout); return CLI_OPTION_HELP;
        case CLI_OPTION_ERROR: return CLI_EXIT_USAGE;
        case OPT_DRY_RUN: a->dry_run = 1; break;
        default: return cli_error(run, "internal: option %d", c);
        }
    }
    if (optind >= run->argc) return cli_error(run, "a scene file is required (see --help)");
    if (optind + 1 < run->argc)
        return cli_error(run, "one scene file at a time (got '%s' and '%s')", run->argv[optind],
                         run->argv[optind + 1]);
    a->path = run->argv[optind];
    if (!a->dry_run && !run->output) return cli_error(run, "-o DIR is required (or --dry-run)");
    return 0;
}

/* --dry-run: the scene, its plan and the files it would write; nothing computed. */
static void simulate_dry_run(const cli_run *run, const svp_scene *scene, const char *path)
{
    const svp_scene_stage *stages = NULL;
    const int n = svp_scene_plan(scene, &stages);
    double pixel_um = 0;
    int vw = 0, vh = 0, cw = 0, ch = 0;
    svp_scene_geometry(scene, &pixel_um, &vw, &vh, &cw, &ch);
    printf("scene %s (%s): view %d x %d px of %g um, canvas %d x %d, memory about %.2g GB\n",
           svp_scene_name(scene), path, vw, vh, pixel_um, cw, ch, svp_scene_memory(scene) / 1e9);
    printf("plan (%d stages):\n", n);
    for (int i = 0; i < n; i++)
        printf("  %2d. %-12s %s\n", i + 1, stages[i].name, stages[i].detail);
    int no = svp_scene_n_outputs(scene);
    printf("outputs (%d files%s%s):\n", no, run->output ? " in " : "",
           run->output ? run->output : "");
    for (int i = 0; i < no; i++) printf("  %s\n", svp_scene_output(scene, i));
    printf("dry run: nothing was computed or written\n");
}

/* The scene run into run->output, with progress and the whole command line in summary.json. */
static int simulate_run_scene(cli_run *run, const svp_scene *scene, const char *path)
{
    const svp_scene_stage *stages = NULL;
    const int n = svp_scene_plan(scene, &stages);
    double pixel_um = 0;
    int vw = 0, vh = 0, cw = 0, ch = 0;
    svp_scene_geometry(scene, &pixel_um, &vw, &vh, &cw, &ch);
    svp_scene_options o;
    svp_scene_defaults(&o);
    o.overwrite = run->force;
    o.keep_maps = 0;
    o.progress = cli_progress;
    o.progress_user = run;
    o.on_stage = on_stage;
    o.stage_user = run;
    /* the whole command line, as typed, goes into summary.json */
    char **full = malloc((size_t)(run->argc + 2) * sizeof *full);
    if (full) {
        full[0] = "svpsf";
        for (int i = 0; i < run->argc; i++) full[i + 1] = run->argv[i];
        o.argc = run->argc + 1;
        o.argv = full;
    }
    /* the library creates DIR and its maps/, figures/, tables/: recorded so that a failed run
     * leaves none of them behind when empty (cli_remove_created_dirs) */
    cli_expect_dirs(run->output);
    static const char *const subdirs[] = {"maps", "figures", "tables"};
    for (int i = 0; i < 3; i++) {
        char sub[4096];
        snprintf(sub, sizeof sub, "%s/%s", run->output, subdirs[i]);
        cli_expect_dirs(sub);
    }
    svp_scene_result *result = NULL;
    cli_progress_start(run, "simulate");
    double t0 = cli_now();
    svp_status st = svp_scene_run(scene, run->output, &o, &result);
    cli_progress_done(run);
    free(full);
    if (st != SVP_OK) return cli_fail(run, st, path);
    printf("svpsf simulate: scene %s, %d stages in %.2f s (view %d x %d, canvas %d x %d)\n",
           svp_scene_name(scene), n, cli_now() - t0, vw, vh, cw, ch);
    print_headline(result);
    warn_doubts(run, result);
    printf("  report:  %s/report.md\n", run->output);
    int has_figures = 0; /* outputs: {figures: false} writes none */
    for (int i = 0; i < svp_scene_n_outputs(scene) && !has_figures; i++)
        has_figures = strncmp(svp_scene_output(scene, i), "figures/", 8) == 0;
    if (has_figures) printf("  figures: %s/figures/\n", run->output);
    printf("  summary: %s/summary.json (plan, stage times, every metric)\n", run->output);
    svp_scene_result_free(result);
    return 0;
}

static int run_simulate(cli_run *run, const struct simulate_args *a)
{
    svp_scene *scene = NULL;
    svp_status st = svp_scene_load(a->path, &scene);
    if (st != SVP_OK) return cli_fail(run, st, NULL);
    int code = 0;
    if (a->dry_run)
        simulate_dry_run(run, scene, a->path);
    else
        code = simulate_run_scene(run, scene, a->path);
    svp_scene_free(scene);
    if (!a->dry_run) svp_figure_cleanup(); /* cairo's font caches: a clean exit for leak checkers */
    return code;
}

int cmd_simulate(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "simulate", argc, argv, CLI_COMMON_OUTPUT | CLI_COMMON_FFT);
    run.fft_measure = 0; /* many one-off sizes: planning by measurement would not pay */
    struct simulate_args args;
    int code = parse_simulate_args(&run, &args);
    if (code == 0) code = run_simulate(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
