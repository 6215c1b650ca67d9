/* The result of a scene run (result.c), shared by the runner, the metrics and the report. */
#ifndef SVP_SCENE_RESULT_H
#define SVP_SCENE_RESULT_H

#include "../core/internal.h"

struct svp_scene_result {
    int n_stages;
    double *seconds; /* per plan stage */
    int n_maps, cap_maps;
    char **map_names;
    svp_image **maps;
    int n_values, cap_values;
    char **keys;
    double *values;
};

/* Takes ownership of img (replacing a map of the same name). */
svp_status scene_result_put(struct svp_scene_result *r, const char *name, svp_image *img);
/* A new zero map registered under name; NULL (and a message) on failure. */
svp_image *scene_result_new_map(struct svp_scene_result *r, const char *name, int w, int h);
svp_image *scene_result_get(const struct svp_scene_result *r, const char *name);
svp_status scene_result_set(struct svp_scene_result *r, const char *key, double value);

#endif
