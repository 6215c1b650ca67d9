/* Scenes: the parsed scene file, its plan, and the pieces the runner, the metrics and the
 * figures share. Library-internal (docs/scenes.md describes the file; include/svpsf.h the API).
 *
 * Geometry. The view is view_w x view_h pixels of pixel_um; the canvas adds margin_px on every
 * side. Positions in the file are micrometres from the centre of the view, +x along the
 * columns (right), +y along the rows (down), the frame of the physics section of svpsf.h.
 * Canvas pixel (i, j) has its centre at
 *     x_um = (i - (canvas_w - 1) / 2) pixel_um,   y_um = (j - (canvas_h - 1) / 2) pixel_um. */
#ifndef SVP_SCENE_INTERNAL_H
#define SVP_SCENE_INTERNAL_H

#include "../core/internal.h"
#include "result.h"

#include <stdint.h>

#define SCENE_MAX_FIELDS 4  /* x, y, z, nv */
#define SCENE_MAX_LEVELS 16 /* chessboard levels */
#define SCENE_MAX_CORRECT 8 /* corrections compared in one scene */
#define SCENE_MAX_RECON 3   /* reconstructions */
#define SCENE_MAX_MASKS 16
#define SCENE_MAX_CUTS 16
#define SCENE_WHERE 48 /* "file:line:col" of a node, for run-time messages */

/* ---- sources ------------------------------------------------------------------------------ */
typedef enum { SRC_FLAKE = 0, SRC_STRIP = 1, SRC_FIELD_FILE = 2 } scene_source_kind;
typedef enum { SHAPE_RECTANGLE = 0, SHAPE_DISK = 1, SHAPE_POLYGON = 2, SHAPE_MASK = 3 } scene_shape;

typedef struct scene_source {
    scene_source_kind kind;
    char where[SCENE_WHERE];
    double standoff_nm; /* flake and strip */
    /* flake */
    scene_shape shape;
    double size_um[2];  /* rectangle */
    double diameter_um; /* disk */
    double angle_deg;   /* rectangle rotation; strip: current direction */
    double centre_um[2];
    double *vertices_um; /* polygon: x0, y0, x1, y1, ... */
    int n_vertices;
    char *mask_path;       /* mask image (resolved path) */
    double mask_threshold; /* coverage = clamp(value / mask_scale); see docs */
    double magnetisation_A_per_m;
    double thickness_nm;
    /* strip */
    double width_um;
    double sheet_current_A_per_m; /* J = I / w when given as current_mA */
    /* field file */
    char *path;
    int component;   /* 0 x, 1 y, 2 z */
    double to_tesla; /* unit factor */
} scene_source;

/* ---- emission ----------------------------------------------------------------------------- */
typedef enum {
    EM_UNIFORM = 0,
    EM_GAUSSIAN = 1,
    EM_CHESSBOARD = 2,
    EM_QUENCH = 3,
    EM_IMAGE = 4,
    EM_FRINGES = 5
} scene_emission_kind;

typedef enum { UNDER_SOURCES = 0, UNDER_FLAKES = 1, UNDER_STRIPS = 2, UNDER_MASK = 3 } scene_under;

typedef struct scene_factor {
    scene_emission_kind kind;
    char where[SCENE_WHERE];
    double level;   /* uniform */
    double fwhm_um; /* gaussian */
    double centre_um[2];
    double square_um; /* chessboard */
    double levels[SCENE_MAX_LEVELS];
    int n_levels;
    uint64_t seed;
    double offset_um[2];
    scene_under under; /* quench */
    double factor;
    char *path;       /* quench mask / emission image (resolved) */
    double period_um; /* fringes: I = 1 + V cos(2π ξ / period + φ) along angle_deg, with ξ
                                clamped to [from_um, to_um] (flat beyond the ramp) */
    double visibility;
    double angle_deg;
    double phase_deg;
    double from_um, to_um;
} scene_factor;

/* ---- the PSF and corrections --------------------------------------------------------------- */
typedef struct scene_psf {
    int from_file; /* 1: psf file or PSF-map file (svp_psf_field_read) */
    char *path;
    svp_psf psf; /* inline model, pixels */
    svp_boundary boundary;
    char where[SCENE_WHERE];
    char describe[160]; /* "lorentzian FWHM 1 um" */
    /* region-dependent PSF (psf.regions, docs/model.md §9): label k + 1 = pixels under region_under[k]
     * (coverage >= 0.5, later regions win), label 0 = `psf`; built at run time as a regions
     * field blended over transition_px and a tent operator on nodes_x x nodes_y nodes */
    int n_regions;
    svp_psf region_psf[4];
    scene_under region_under[4];
    double transition_px;
    int nodes_x, nodes_y;
} scene_psf;

typedef struct scene_correct {
    char name[32]; /* "rw", "w", ... unique; names the outputs */
    svp_method method;
    int iterations; /* RL */
    double balance; /* Wiener */
    double pl_floor;
    int margin_px; /* object estimated on the view plus this margin; -1 = auto (the PSF's reach,
                      as `svpsf correct --margin auto`); 0 (default) = the view only */
    int single;    /* 1: single-precision transforms for RL (as `--precision single`) */
    int accelerated; /* 1: Biggs–Andrews extrapolation for RL (as `--acceleration biggs-andrews`) */
    double tail_tol; /* RL (r, rl_signed, cube): the PSF's far tail on a coarse grid within this
                        error (as `--tail-tol`; 0: never); default SVP_TAIL_TOL_DEFAULT */
    int has_psf; /* an assumed PSF different from the scene's */
    scene_psf psf;
    int cube;    /* method cube: every frame of the cube deconvolved (RL, `iterations`, the
                    margin) before the estimate (svp_cube_deconvolve; fit-odmr --psf), not T⁻¹
                    on the estimated maps; needs effects.spectrum */
    char where[SCENE_WHERE];
} scene_correct;

typedef enum {
    RECON_MAGNETISATION = 0,
    RECON_CURRENT_BZ = 1,
    RECON_CURRENT_BXY = 2
} scene_recon_kind;

typedef struct scene_recon {
    scene_recon_kind kind;
    char name[16]; /* "m_z", "J_bz", "J_bxy": names the outputs */
    double standoff_nm;
    double cutoff_per_um; /* k_c in rad/µm; 0 = 2π / standoff */
    int window;           /* Hann window on (default 1) */
    svp_pad_mode pad;
    svp_recon_method method; /* magnetisation: Fourier (default) or support */
    char where[SCENE_WHERE];
} scene_recon;

/* ---- metrics ------------------------------------------------------------------------------- */
typedef enum {
    MASK_ALL = 0,
    MASK_SOURCES = 1,
    MASK_FLAKES = 2,
    MASK_STRIPS = 3,
    MASK_FILE = 4,
    MASK_NONE_REGION = 5
} scene_mask_region;

typedef struct scene_mask {
    char name[32];
    scene_mask_region inside; /* region the pixel must be inside (coverage >= 0.5) */
    int outside;              /* 1: invert the region */
    double erode_um;          /* shrink the region by this distance (>= 0) */
    double lit_above;         /* true PL >= lit_above · max (0 = no condition) */
    char *path;               /* inside: file */
    char where[SCENE_WHERE];
} scene_mask;

typedef struct scene_cut {
    char name[32];
    double from_um[2], to_um[2];
    char where[SCENE_WHERE];
} scene_cut;

/* ---- the scene ----------------------------------------------------------------------------- */
/* The stages a plan may hold (docs/scenes.md describes each; plan.c puts them in order for a
 * scene): one row per stage, X(ENUM, "name", function). The name is the plan's, the report's
 * and summary.json's; the function (static in run.c, the only place that expands the third
 * column) runs the stage. */
#define SCENE_STAGES(X)                                                                          \
    X(GRID, "grid", stage_grid)                                                                  \
    X(SOURCES, "sources", stage_sources)                                                         \
    X(PROJECTION, "projection", stage_projection)                                                \
    X(EMISSION, "emission", stage_emission)                                                      \
    X(OPERATOR, "operator", stage_operator)                                                      \
    X(FORWARD, "forward", stage_forward)                                                         \
    X(CUBE, "cube", stage_cube)                                                                  \
    X(DRIFT, "drift", stage_drift)                                                               \
    X(ESTIMATE, "estimate", stage_estimate)                                                      \
    X(CROP, "crop", stage_crop)                                                                  \
    X(NOISE, "noise", stage_noise)                                                               \
    X(COMPARE, "compare", stage_compare)                                                         \
    X(CORRECT, "correct", stage_correct)                                                         \
    X(RECONSTRUCT, "reconstruct", stage_reconstruct)                                             \
    X(METRICS, "metrics", stage_metrics)                                                         \
    X(FIGURES, "figures", stage_figures)                                                         \
    X(WRITE, "write", stage_write)

typedef enum scene_stage {
#define SCENE_STAGE_ENUM(e, name, fn) SCENE_STAGE_##e,
    SCENE_STAGES(SCENE_STAGE_ENUM)
#undef SCENE_STAGE_ENUM
        SCENE_STAGE_COUNT
} scene_stage;

static inline const char *scene_stage_name(scene_stage stage)
{
    switch (stage) {
#define SCENE_STAGE_NAME(e, name, fn)                                                            \
    case SCENE_STAGE_##e: return name;
        SCENE_STAGES(SCENE_STAGE_NAME)
#undef SCENE_STAGE_NAME
    case SCENE_STAGE_COUNT: break;
    }
    return "?";
}

/* The estimated peak memory of a run in bytes (run.c; checked against the budget before it
 * starts, shown by the dry run). */
double scene_memory_estimate(const svp_scene *s);

typedef struct scene_stage_entry {
    scene_stage stage;
    int index;     /* correct, reconstruct: which correction / reconstruction of the scene */
    char name[32]; /* scene_stage_name(stage), for the public view (svp_scene_stage) */
    char detail[200];
} scene_stage_entry;

struct svp_scene {
    char *path; /* the scene file as given */
    char *dir;  /* its folder: relative paths start here */
    char *name; /* name: or the file stem */
    char *description;

    /* grid */
    double pixel_um;
    double size_um[2];
    double margin_um;
    int view_w, view_h, margin_px, canvas_w, canvas_h;

    /* sensor */
    double nv_thickness_nm;
    int side; /* +1 above, -1 below */

    scene_source *sources;
    int n_sources, n_flakes, n_strips, n_files;

    /* measured field components: 0 x, 1 y, 2 z, 3 nv (projection on nv_axis) */
    int n_fields;
    int field_comp[SCENE_MAX_FIELDS];
    double nv_axis[3];

    scene_factor *emission;
    int n_emission;

    scene_psf psf;

    /* effects */
    int noise;
    double photons; /* photons at the brightest apparent pixel, whole measurement */
    uint64_t noise_seed;
    double noise_linewidth_hz, noise_contrast;
    int spectrum;
    int spectrum_points;
    double linewidth_hz, contrast, zero_field_hz, bias_t, span_linewidths;
    int estimator; /* 0 centroid, 1 lorentzian_fit */
    scene_factor *contrast_pattern;
    int n_contrast_pattern;
    int drift;
    double drift_um[2];
    int drift_register; /* effects.drift.register: the view's frames aligned before the
                           estimate (svp_cube_align, to frame 0's position) */

    scene_correct correct[SCENE_MAX_CORRECT];
    int n_correct;
    scene_recon recon[SCENE_MAX_RECON];
    int n_recon;

    scene_mask masks[SCENE_MAX_MASKS];
    int n_masks;
    scene_cut cuts[SCENE_MAX_CUTS];
    int n_cuts;
    int hist_bins;
    double hist_range_pct; /* 0 = automatic */
    double local_floor;

    /* outputs */
    int write_maps, write_figures, write_canvas;
    svp_file_format format;

    /* the plan (compiled at load) and the public view of it */
    scene_stage_entry *plan;
    svp_scene_stage *stages;
    int n_stages;
    /* files a run writes, relative to the output folder */
    char **outputs;
    int n_outputs;
};

/* ---- quantities and versions (shared by plan, runner, metrics, figures) ------------------- */
#define SCENE_MAX_QUANTITIES 12
#define SCENE_MAX_VERSIONS (2 + SCENE_MAX_CORRECT)

typedef struct scene_quantity {
    char name[24];        /* "pl", "B_z", "B_nv", "m_z", "J_bz", "J_bxy" (|J|) */
    char label[48];       /* axis label: "B_z", "m_z = M_z t", "|J|" */
    char unit[12];        /* display unit, UTF-8: "µT", "mA", "A/m", "a.u." */
    double display_scale; /* SI value × scale = displayed value */
    int diverging;        /* signed quantity: diverging colour map centred on zero */
    int ref_local;        /* relative error against the local true value (else the view's peak) */
    int field;            /* index into the measured components, or -1 */
    int recon;            /* index into recon[], or -1 */
} scene_quantity;

/* The quantities of a scene, in a fixed order: pl, the field components, the reconstructions. */
int scene_quantities(const struct svp_scene *s, scene_quantity *q);
/* Version names: "true", "apparent", "corrected_<name>" per correction. Returns the count. */
int scene_versions(const struct svp_scene *s, char names[][48]);

/* ---- shared helpers ---------------------------------------------------------------------- */

/* Canvas pixel centre in µm from the view centre. */
static inline double scene_x_um(const struct svp_scene *s, double i)
{
    return (i - 0.5 * (s->canvas_w - 1)) * s->pixel_um;
}
static inline double scene_y_um(const struct svp_scene *s, double j)
{
    return (j - 0.5 * (s->canvas_h - 1)) * s->pixel_um;
}
/* µm → canvas pixel coordinate. */
static inline double scene_i_px(const struct svp_scene *s, double x_um)
{
    return x_um / s->pixel_um + 0.5 * (s->canvas_w - 1);
}
static inline double scene_j_px(const struct svp_scene *s, double y_um)
{
    return y_um / s->pixel_um + 0.5 * (s->canvas_h - 1);
}

/* Whether the scene measures field component comp (0 x, 1 y, 2 z, 3 nv). */
static inline int scene_has_component(const struct svp_scene *s, int comp)
{
    for (int k = 0; k < s->n_fields; k++)
        if (s->field_comp[k] == comp) return 1;
    return 0;
}

/* The scene file's names of svp_psf_model and svp_boundary values (NULL-terminated). */
#define SCENE_PSF_MODEL_NAMES {"gaussian", "lorentzian", "moffat", NULL}
#define SCENE_BOUNDARY_NAMES {"zero", "mirror", "periodic", NULL}

/* Names of field components ("x", "y", "z", "nv"). */
const char *scene_component_name(int comp);

/* Compiles the plan of a parsed scene (plan.c). */
svp_status scene_compile_plan(struct svp_scene *s);

/* ---- metrics (metrics.c), figures and report (report.c; drawn by src/figure) ------------- */
typedef struct scene_hist {
    int q, m;      /* quantity and mask */
    double lo, hi; /* bin range, percent */
    int bins;
    double *fraction; /* (n_versions − 1) × bins: fraction of the mask's used pixels */
    int n_used;
} scene_hist;

typedef struct scene_cutdata {
    int n;
    double *s_um, *x_um, *y_um;
    double *values; /* [q][v][n], display units */
} scene_cutdata;

typedef struct scene_analysis {
    int nq, nv;
    scene_quantity q[SCENE_MAX_QUANTITIES];
    char versions[SCENE_MAX_VERSIONS][48];
    scene_hist *hists; /* nq × n_masks, index q * n_masks + m */
    int n_hists;
    scene_cutdata cuts[SCENE_MAX_CUTS];
    double err_range_pct[SCENE_MAX_QUANTITIES]; /* colour range of the error maps */
    double map_lo[SCENE_MAX_QUANTITIES], map_hi[SCENE_MAX_QUANTITIES]; /* display units */
    char *metrics_csv, *hist_csv, *cut_csv[SCENE_MAX_CUTS];
} scene_analysis;

/* Masks ("mask_<name>", view-sized) from the run's maps: "canvas_cover_flakes",
 * "canvas_cover_strips" (coverage), "pl_true". Idempotent. */
svp_status scene_make_masks(const struct svp_scene *s, struct svp_scene_result *r);
/* Relative-error maps, statistics, histograms, line cuts, CSV texts; values into r. */
svp_status scene_analyse(const struct svp_scene *s, struct svp_scene_result *r, scene_analysis *a);
void scene_analysis_free(scene_analysis *a);
/* Every figure of the plan into out_dir/figures/ (through src/figure/figure.h). */
svp_status scene_figures(const struct svp_scene *s, const struct svp_scene_result *r,
                         const scene_analysis *a, const char *out_dir, int overwrite,
                         svp_progress_fn progress, void *progress_user);
/* report.md text (malloc'd). */
svp_status scene_report_text(const struct svp_scene *s, const struct svp_scene_result *r,
                             const scene_analysis *a, char **text);

/* Deterministic standard normal number for (seed, stream, index): counter-based, so the noise
 * is the same for every thread count and order of evaluation. */
double scene_gauss(uint64_t seed, uint64_t stream, uint64_t index);

#endif
