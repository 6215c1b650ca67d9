/* svpsf psf-compare: compare two PSF maps (or PSF files): parameter differences over the
 * field, and how much the corrected field of a reference scene changes between them. */
#include "cli.h"

#include "core/internal.h"
#include "figure/figure.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

enum { OPT_SIZE = CLI_OPTION_FIRST, OPT_SCENE_SIZE };

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf psf-compare A.yaml B.yaml [-o DIR] [--size WxH] [--scene-size N]\n"
          "\n"
          "Compares two PSF maps (PSF-map files or plain PSF files; e.g. the maps of two\n"
          "samples from svpsf map-psf):\n"
          "  1. parameter differences B - A at every pixel of the field: max and mean |dFWHM|\n"
          "     (um and relative to A), |dbeta|, |de| (ellipticity);\n"
          "  2. a reference scene: a built-in micromagnet-like field (a 1 mT out-of-plane flake\n"
          "     with a -0.4 mT return rim, PL 0.3 on the flake, 1 elsewhere) of N x N pixels at\n"
          "     the field's centre is blurred with map A (space-variant, eq. 3), then corrected\n"
          "     (T^-1 with the defaults of svpsf correct) once with A and once with B: the\n"
          "     relative rms and max difference of the two corrected fields, and each one's\n"
          "     error to the truth.\n"
          "\n"
          "  A.yaml, B.yaml        the maps; they must share the pixel size and (when both have\n"
          "                        one) the field size\n"
          "  -o, --output DIR      write dfwhm.EXT, dbeta.EXT (B - A over the field), dfwhm.png,\n"
          "                        dbeta.png, the corrected fields corrected_a.EXT,\n"
          "                        corrected_b.EXT and summary.json into DIR (default: print\n"
          "                        only)\n"
          "  --size WxH            the field size when both are uniform (default 256x256)\n"
          "  --scene-size N        side of the reference scene, px, 16..1024 (default 128;\n"
          "                        at most the field: a larger N is reduced to it, with a\n"
          "                        note)\n",
          out);
    cli_print_common_help(run, out);
}

static int load(cli_run *run, const char *path, svp_psf_field **f, double *um)
{
    svp_status st = svp_psf_field_read(path, f, um);
    if (st != SVP_OK) return cli_fail(run, st, path);
    cli_record_input(run, "psf map", path, svp_psf_field_width(*f), svp_psf_field_height(*f));
    cli_psf_map_range_warning(run, path, *f, *um);
    return 0;
}

/* An N x N grid field (8 x 8 nodes) sampling `f` over the window at (ox, oy). */
static svp_status window_field(const svp_psf_field *f, int ox, int oy, int n, svp_psf_field **out)
{
    enum { G = 8 };
    svp_psf nodes[G * G];
    for (int j = 0; j < G; j++)
        for (int i = 0; i < G; i++) {
            double x = (i + 0.5) * n / G - 0.5, y = (j + 0.5) * n / G - 0.5;
            svp_status st = svp_psf_field_at(f, ox + x, oy + y, &nodes[j * G + i]);
            if (st != SVP_OK) return st;
        }
    return svp_psf_field_new_grid(n, n, G, G, NULL, NULL, nodes, out);
}

struct psf_compare_args {
    const char *pa, *pb; /* A.yaml, B.yaml */
    int w, h;            /* --size WxH; 0 when not given */
    int scene_n;         /* --scene-size */
    int scene_given;
};

/* What a run holds (released by run_psf_compare). */
struct psf_compare_job {
    svp_psf_field *fa, *fb, *wa, *wb;
    double um;
    int w, h, scene_n; /* the field, the scene's side */
    svp_image *dfw, *dbe, *btrue, *pltrue, *plapp, *bapp, *plc, *bc_a, *bc_b;
    svp_blur *ha, *hb;
    double max_df, max_db; /* the largest |dFWHM| (um) and |dbeta|, for the figures' scales */
    svp_correct_summary sum_a, sum_b; /* the two corrections' doubts */
    const char *out_dfw, *out_dbe, *png_dfw, *png_dbe, *out_ca, *out_cb, *out_sum;
};

static int parse_psf_compare_args(cli_run *run, struct psf_compare_args *a)
{
    static const struct option own[] = {
        {"size", required_argument, NULL, OPT_SIZE},
        {"scene-size", required_argument, NULL, OPT_SCENE_SIZE},
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    a->scene_n = 128;
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        switch (c) {
        case CLI_OPTION_HELP: print_help(run, stdout); return CLI_OPTION_HELP;
        case CLI_OPTION_ERROR: return CLI_EXIT_USAGE;
        case OPT_SIZE:
            if (sscanf(optarg, "%dx%d", &a->w, &a->h) != 2 || a->w < 8 || a->h < 8 ||
                a->w > 16384 || a->h > 16384)
                return cli_error(run, "--size %s: expected WxH, 8..16384 each (e.g. 256x256)",
                                 optarg);
            break;
        case OPT_SCENE_SIZE:
            if (cli_parse_int(run, "--scene-size", optarg, 16, 1024, &a->scene_n))
                return CLI_EXIT_USAGE;
            a->scene_given = 1;
            break;
        default: return cli_error(run, "internal: option %d", c);
        }
    }
    if (run->argc - optind != 2)
        return cli_error(run, "two PSF maps A.yaml B.yaml are required (see --help)");
    a->pa = run->argv[optind];
    a->pb = run->argv[optind + 1];
    return 0;
}

/* The two maps (same pixel size, same field when both have one), the field and scene sizes,
 * the outputs planned. */
static int psf_compare_read(cli_run *run, const struct psf_compare_args *a,
                            struct psf_compare_job *job)
{
    const char *pa = a->pa, *pb = a->pb;
    double ua = 0, ub = 0;
    int code;
    cli_stage_begin(run, "read");
    if ((code = load(run, pa, &job->fa, &ua)) || (code = load(run, pb, &job->fb, &ub))) return code;
    if (fabs(ua - ub) > 1e-9 * ua)
        return cli_error(run,
                         "%s: pixel_um %g differs from %s's %g: the maps must share the "
                         "pixel size",
                         pb, ub, pa, ua);
    int aw = svp_psf_field_width(job->fa), ah = svp_psf_field_height(job->fa);
    int bw = svp_psf_field_width(job->fb), bh = svp_psf_field_height(job->fb);
    if (aw && bw && (aw != bw || ah != bh))
        return cli_error(run, "size mismatch: %s maps a %d x %d field but %s a %d x %d one", pa, aw,
                         ah, pb, bw, bh);
    int w = a->w, h = a->h;
    if (w && (aw || bw) && (w != (aw ? aw : bw) || h != (aw ? ah : bh)))
        return cli_error(run,
                         "--size %dx%d: %s maps a %d x %d field; --size applies only when both "
                         "maps are uniform (drop it)",
                         w, h, aw ? pa : pb, aw ? aw : bw, aw ? ah : bh);
    if (aw)
        w = aw, h = ah;
    else if (bw)
        w = bw, h = bh;
    else if (!w)
        w = h = 256;
    /* the scene is at most the field (as --help says); an explicit larger N is noted */
    int scene_n = a->scene_n;
    if (scene_n > w) scene_n = w;
    if (scene_n > h) scene_n = h;
    if (a->scene_given && scene_n < a->scene_n)
        cli_note(run, "--scene-size %d is larger than the %d x %d field: the scene is %d x %d",
                 a->scene_n, w, h, scene_n, scene_n);
    job->w = w;
    job->h = h;
    job->scene_n = scene_n;
    job->um = ua;
    if (run->output) {
        job->out_dfw = cli_output_in_dir(run, "dfwhm", "dfwhm", 1);
        job->out_dbe = cli_output_in_dir(run, "dbeta", "dbeta", 1);
        job->png_dfw = cli_output_in_dir(run, "figure", "dfwhm.png", 0);
        job->png_dbe = cli_output_in_dir(run, "figure", "dbeta.png", 0);
        job->out_ca = cli_output_in_dir(run, "corrected_a", "corrected_a", 1);
        job->out_cb = cli_output_in_dir(run, "corrected_b", "corrected_b", 1);
        job->out_sum = cli_output_in_dir(run, "summary", "summary.json", 0);
        if ((code = cli_outputs_check(run))) return code;
    }
    cli_setting_num(run, "pixel_um", job->um);
    cli_setting_int(run, "width", w);
    cli_setting_int(run, "height", h);
    cli_setting_int(run, "scene_size", scene_n);
    return 0;
}

/* 1. The parameter differences B - A at every pixel of the field. */
static int psf_compare_parameters(cli_run *run, const struct psf_compare_args *a,
                                  struct psf_compare_job *job)
{
    const int w = job->w, h = job->h;
    const double um = job->um;
    svp_status st;
    cli_stage_begin(run, "parameters");
    if ((st = svp_image_new(w, h, &job->dfw)) != SVP_OK ||
        (st = svp_image_new(w, h, &job->dbe)) != SVP_OK)
        return cli_fail(run, st, NULL);
    double max_df = 0, sum_df = 0, max_rel = 0, max_db = 0, sum_db = 0, max_de = 0;
    /* beta compares between Moffat and Lorentzian (beta = 1) maps, not with a Gaussian one */
    svp_psf ma, mb;
    if ((st = svp_psf_field_at(job->fa, 0, 0, &ma)) != SVP_OK ||
        (st = svp_psf_field_at(job->fb, 0, 0, &mb)) != SVP_OK)
        return cli_fail(run, st, NULL);
    const int beta_comparable = ma.model != SVP_PSF_GAUSSIAN && mb.model != SVP_PSF_GAUSSIAN;
    if (ma.model != mb.model)
        cli_note(run, "the maps use different models (A %s, B %s)%s", cli_psf_model_names[ma.model],
                 cli_psf_model_names[mb.model], beta_comparable ? "" : ": beta is not compared");
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double p[SVP_FIELD_NPARAM], q[SVP_FIELD_NPARAM];
            if ((st = svp_psf_field_params_at(job->fa, x, y, p)) != SVP_OK ||
                (st = svp_psf_field_params_at(job->fb, x, y, q)) != SVP_OK)
                return cli_fail(run, st, NULL);
            size_t i = (size_t)y * w + x;
            double df = (q[SVP_FIELD_FWHM] - p[SVP_FIELD_FWHM]) * um;
            job->dfw->data[i] = df;
            max_df = fmax(max_df, fabs(df));
            sum_df += fabs(df);
            max_rel = fmax(max_rel, fabs(df) / (p[SVP_FIELD_FWHM] * um));
            double db = NAN;
            if (beta_comparable) {
                double ba = ma.model == SVP_PSF_LORENTZIAN ? 1.0 : p[SVP_FIELD_BETA];
                double bb = mb.model == SVP_PSF_LORENTZIAN ? 1.0 : q[SVP_FIELD_BETA];
                db = bb - ba;
                max_db = fmax(max_db, fabs(db));
                sum_db += fabs(db);
            }
            job->dbe->data[i] = db;
            max_de = fmax(max_de, hypot(q[SVP_FIELD_E1] - p[SVP_FIELD_E1],
                                        q[SVP_FIELD_E2] - p[SVP_FIELD_E2]));
        }
    const double n_px = (double)w * h;
    printf("PSF maps %s (A) and %s (B), %d x %d field, pixel %g um:\n", a->pa, a->pb, w, h, um);
    printf("  |dFWHM|  max %.5f um (%.2f %% of A), mean %.5f um\n", max_df, 100 * max_rel,
           sum_df / n_px);
    if (beta_comparable)
        printf("  |dbeta|  max %.4f, mean %.4f\n", max_db, sum_db / n_px);
    else
        printf("  |dbeta|  not compared (a Gaussian map has no beta; dbeta is NaN)\n");
    printf("  |de|     max %.4f\n", max_de);
    cli_result_num(run, "max_abs_dfwhm_um", max_df);
    cli_result_num(run, "mean_abs_dfwhm_um", sum_df / n_px);
    cli_result_num(run, "max_rel_dfwhm", max_rel);
    if (beta_comparable) {
        cli_result_num(run, "max_abs_dbeta", max_db);
        cli_result_num(run, "mean_abs_dbeta", sum_db / n_px);
    }
    cli_result_num(run, "max_abs_de", max_de);
    job->max_df = max_df;
    job->max_db = max_db;
    return 0;
}

/* The reference scene's truth: a flake, a square of side n/2 with edges smoothed over 1 px;
 * a -0.4 mT rim decaying over n/16 px outside it; PL 0.3 on the flake. */
static void flake_scene(int n, svp_image *btrue, svp_image *pltrue)
{
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            double dx = fabs(x - 0.5 * (n - 1)) - 0.25 * n, dy = fabs(y - 0.5 * (n - 1)) - 0.25 * n;
            double d = fmax(dx, dy); /* < 0 inside */
            double inside = 0.5 * (1 - tanh(d));
            double rim = d > 0 ? -0.4 * exp(-d / (n / 16.0)) * (1 - inside) : 0;
            btrue->data[(size_t)y * n + x] = inside + rim;
            pltrue->data[(size_t)y * n + x] = 1.0 - 0.7 * inside;
        }
}

/* The scene blurred with A, corrected with A and with B. */
static int psf_compare_transforms(cli_run *run, struct psf_compare_job *job)
{
    const int n = job->scene_n;
    svp_variant_options vo;
    svp_variant_defaults(&vo);
    svp_correct_options co, cb;
    svp_correct_defaults(&co);
    /* the two corrections are the long part: each reports half of the stage's progress */
    svp_progress_share half_a = {cli_progress, run, 0.0, 0.5},
                       half_b = {cli_progress, run, 0.5, 0.5};
    /* a correction in doubt is part of the comparison (correcting A's blur with B can blow
     * up): kept, and reported with the numbers */
    co.keep_doubtful = 1;
    cb = co;
    co.summary = &job->sum_a;
    cb.summary = &job->sum_b;
    co.deconv.progress = cb.deconv.progress = svp_progress_share_fn;
    co.deconv.progress_user = &half_a;
    cb.deconv.progress_user = &half_b;
    cli_progress_start(run, "reference scene");
    svp_status st;
    if ((st = svp_blur_new_field(job->wa, n, n, SVP_BOUNDARY_ZERO, &vo, &job->ha)) != SVP_OK ||
        (st = svp_blur_new_field(job->wb, n, n, SVP_BOUNDARY_ZERO, &vo, &job->hb)) != SVP_OK ||
        (st = svp_forward_transform(job->ha, job->pltrue, (const svp_image *const *)&job->btrue, 1,
                                    job->plapp, &job->bapp, NULL)) != SVP_OK ||
        (st = svp_inverse_transform(job->ha, job->plapp, (const svp_image *const *)&job->bapp, 1,
                                    &co, job->plc, &job->bc_a, NULL, NULL)) != SVP_OK ||
        (st = svp_inverse_transform(job->hb, job->plapp, (const svp_image *const *)&job->bapp, 1,
                                    &cb, job->plc, &job->bc_b, NULL, NULL)) != SVP_OK) {
        cli_progress_done(run);
        return cli_fail(run, st, "reference scene");
    }
    cli_progress_done(run);
    return 0;
}

/* 2. The reference scene: how much the corrected field changes between A and B. */
static int psf_compare_scene(cli_run *run, struct psf_compare_job *job)
{
    const int n = job->scene_n, ox = (job->w - n) / 2, oy = (job->h - n) / 2;
    svp_status st;
    int code;
    cli_stage_begin(run, "scene");
    if ((st = window_field(job->fa, ox, oy, n, &job->wa)) != SVP_OK ||
        (st = window_field(job->fb, ox, oy, n, &job->wb)) != SVP_OK)
        return cli_fail(run, st, NULL);
    svp_image **imgs[] = {&job->btrue, &job->pltrue, &job->plapp, &job->bapp,
                          &job->plc,   &job->bc_a,   &job->bc_b};
    for (size_t k = 0; k < sizeof imgs / sizeof imgs[0]; k++)
        if ((st = svp_image_new(n, n, imgs[k])) != SVP_OK) return cli_fail(run, st, NULL);
    flake_scene(n, job->btrue, job->pltrue);
    if ((code = psf_compare_transforms(run, job))) return code;
    double s_ab = 0, s_a = 0, s_at = 0, s_bt = 0, s_t = 0, m_ab = 0, m_t = 0, s_pt = 0;
    for (size_t i = 0; i < (size_t)n * n; i++) {
        double a = job->bc_a->data[i], b = job->bc_b->data[i], t = job->btrue->data[i];
        s_pt += (job->bapp->data[i] - t) * (job->bapp->data[i] - t);
        s_ab += (b - a) * (b - a);
        s_a += a * a;
        s_at += (a - t) * (a - t);
        s_bt += (b - t) * (b - t);
        s_t += t * t;
        m_ab = fmax(m_ab, fabs(b - a));
        m_t = fmax(m_t, fabs(t));
    }
    const double rel = sqrt(s_ab / s_a), rel_a = sqrt(s_at / s_t), rel_b = sqrt(s_bt / s_t),
                 rel_app = sqrt(s_pt / s_t);
    printf("reference scene (%d x %d px at (%d, %d), micromagnet-like flake, blurred with A):\n", n,
           n, ox, oy);
    printf("  corrected with B vs with A: relative rms difference %.4f, max |difference| %.4f of "
           "the field's peak\n",
           rel, m_ab / m_t);
    printf("  relative rms error to the truth: corrected with A %.4f, with B %.4f; uncorrected "
           "%.4f\n",
           rel_a, rel_b, rel_app);
    cli_result_num(run, "scene_rel_rms_error_uncorrected", rel_app);
    const svp_correct_summary *sums[2] = {&job->sum_a, &job->sum_b};
    for (int k = 0; k < 2; k++) {
        char list[256];
        svp_doubt_list(sums[k]->doubts, list, sizeof list);
        if (sums[k]->doubts)
            printf("  the correction with %c is in doubt (%s; %zu implausible pixels): %s\n",
                   'A' + k, list, sums[k]->n_implausible,
                   k ? "correcting A's blur with B's PSF is what blows up or loses the signal"
                     : "the reference correction itself");
        cli_result_str(run, k ? "scene_doubts_b" : "scene_doubts_a", list);
    }
    cli_result_num(run, "scene_rel_rms_difference", rel);
    cli_result_num(run, "scene_max_difference_of_peak", m_ab / m_t);
    cli_result_num(run, "scene_rel_rms_error_a", rel_a);
    cli_result_num(run, "scene_rel_rms_error_b", rel_b);
    return 0;
}

/* With -o: the difference maps, the corrected fields, the figures and summary.json. */
static int psf_compare_write(cli_run *run, struct psf_compare_job *job)
{
    const double um = job->um;
    svp_status st;
    int code;
    cli_stage_begin(run, "write");
    double lim_f = job->max_df > 0 ? job->max_df : 1e-6,
           lim_b = job->max_db > 0 ? job->max_db : 1e-6;
    if ((code = cli_write_image(run, job->out_dfw, job->dfw)) ||
        (code = cli_write_image(run, job->out_dbe, job->dbe)) ||
        (code = cli_write_image(run, job->out_ca, job->bc_a)) ||
        (code = cli_write_image(run, job->out_cb, job->bc_b)))
        return code;
    if ((st = svp_figure_map(job->png_dfw, job->dfw, 1000, -lim_f * 1000, lim_f * 1000, 1,
                               "FWHM of B - FWHM of A", "dFWHM (nm)", um, run->force)) != SVP_OK ||
        (st = svp_figure_map(job->png_dbe, job->dbe, 1, -lim_b, lim_b, 1, "beta of B - beta of A",
                               "dbeta", um, run->force)) != SVP_OK)
        return cli_fail(run, st, "figures");
    cli_stage_end(run);
    if ((code = cli_summary_write(run, job->out_sum))) return code;
    printf("svpsf psf-compare: maps and summary written to %s\n", run->output);
    return 0;
}

static int run_psf_compare(cli_run *run, const struct psf_compare_args *a)
{
    struct psf_compare_job job;
    memset(&job, 0, sizeof job);
    int code = psf_compare_read(run, a, &job);
    if (!code) code = psf_compare_parameters(run, a, &job);
    if (!code) code = psf_compare_scene(run, &job);
    if (!code && run->output) code = psf_compare_write(run, &job);
    svp_blur_free(job.ha);
    svp_blur_free(job.hb);
    svp_psf_field_free(job.fa);
    svp_psf_field_free(job.fb);
    svp_psf_field_free(job.wa);
    svp_psf_field_free(job.wb);
    svp_image *imgs[] = {job.dfw,  job.dbe, job.btrue, job.pltrue, job.plapp,
                         job.bapp, job.plc, job.bc_a,  job.bc_b};
    for (size_t k = 0; k < sizeof imgs / sizeof imgs[0]; k++) svp_image_free(imgs[k]);
    svp_figure_cleanup();
    return code;
}

int cmd_psf_compare(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "psf-compare", argc, argv, CLI_COMMON_OUTPUT_DIR);
    struct psf_compare_args args;
    int code = parse_psf_compare_args(&run, &args);
    if (code == 0) code = run_psf_compare(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
