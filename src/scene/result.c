/* The result of a scene run: its maps by name, its values by key, the seconds of each plan
 * stage (the container the stages (run.c), the metrics (metrics.c) and the report (report.c)
 * all fill and read; svp_scene_result_* in svpsf.h read it). */
#include "result.h"

#include <stdlib.h>
#include <string.h>

static char *dup_text(const char *s)
{
    size_t n = strlen(s);
    char *c = malloc(n + 1);
    if (c) memcpy(c, s, n + 1);
    return c;
}

svp_status scene_result_put(svp_scene_result *r, const char *name, svp_image *img)
{
    for (int i = 0; i < r->n_maps; i++)
        if (strcmp(r->map_names[i], name) == 0) {
            svp_image_free(r->maps[i]);
            r->maps[i] = img;
            return SVP_OK;
        }
    if (r->n_maps == r->cap_maps) {
        int cap = r->cap_maps ? 2 * r->cap_maps : 64;
        char **names = realloc(r->map_names, (size_t)cap * sizeof *names);
        if (!names) goto nomem;
        r->map_names = names;
        svp_image **maps = realloc(r->maps, (size_t)cap * sizeof *maps);
        if (!maps) goto nomem;
        r->maps = maps;
        r->cap_maps = cap;
    }
    r->map_names[r->n_maps] = dup_text(name);
    if (!r->map_names[r->n_maps]) goto nomem;
    r->maps[r->n_maps++] = img;
    return SVP_OK;
nomem:
    svp_image_free(img);
    return svp_fail(SVP_ERR_NOMEM, "out of memory (scene map %s)", name);
}

svp_image *scene_result_new_map(svp_scene_result *r, const char *name, int w, int h)
{
    svp_image *img = NULL;
    if (svp_image_new(w, h, &img) != SVP_OK) return NULL;
    if (scene_result_put(r, name, img) != SVP_OK) return NULL;
    return img;
}

svp_image *scene_result_get(const svp_scene_result *r, const char *name)
{
    for (int i = 0; i < r->n_maps; i++)
        if (strcmp(r->map_names[i], name) == 0) return r->maps[i];
    return NULL;
}

svp_status scene_result_set(svp_scene_result *r, const char *key, double value)
{
    for (int i = 0; i < r->n_values; i++)
        if (strcmp(r->keys[i], key) == 0) {
            r->values[i] = value;
            return SVP_OK;
        }
    if (r->n_values == r->cap_values) {
        int cap = r->cap_values ? 2 * r->cap_values : 256;
        char **keys = realloc(r->keys, (size_t)cap * sizeof *keys);
        if (!keys) return svp_fail(SVP_ERR_NOMEM, "out of memory");
        r->keys = keys;
        double *values = realloc(r->values, (size_t)cap * sizeof *values);
        if (!values) return svp_fail(SVP_ERR_NOMEM, "out of memory");
        r->values = values;
        r->cap_values = cap;
    }
    if (!(r->keys[r->n_values] = dup_text(key))) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    r->values[r->n_values++] = value;
    return SVP_OK;
}

void svp_scene_result_free(svp_scene_result *r)
{
    if (!r) return;
    for (int i = 0; i < r->n_maps; i++) {
        free(r->map_names[i]);
        svp_image_free(r->maps[i]);
    }
    free(r->map_names);
    free(r->maps);
    for (int i = 0; i < r->n_values; i++) free(r->keys[i]);
    free(r->keys);
    free(r->values);
    free(r->seconds);
    free(r);
}

double svp_scene_result_stage_seconds(const svp_scene_result *r, int index)
{
    return r && index >= 0 && index < r->n_stages ? r->seconds[index] : 0;
}

const svp_image *svp_scene_result_map(const svp_scene_result *r, const char *name)
{
    return r && name ? scene_result_get(r, name) : NULL;
}

int svp_scene_result_value(const svp_scene_result *r, const char *key, double *value)
{
    if (!r || !key) return 0;
    for (int i = 0; i < r->n_values; i++)
        if (strcmp(r->keys[i], key) == 0) {
            if (value) *value = r->values[i];
            return 1;
        }
    return 0;
}

int svp_scene_result_n_values(const svp_scene_result *r) { return r ? r->n_values : 0; }

const char *svp_scene_result_value_at(const svp_scene_result *r, int index, double *value)
{
    if (!r || index < 0 || index >= r->n_values) return NULL;
    if (value) *value = r->values[index];
    return r->keys[index];
}
