/* libFuzzer target: svp_scene_load_string (a scene file, docs/scenes.md), then its plan. */
#include "fuzz_common.h"
#include "svpsf.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    svp_scene *scene = NULL;
    /* the scene's relative paths resolve against the name's folder: the private one */
    const char *name = fuzz_path("scene.yaml");
    svp_status st = svp_scene_load_string(name, (const char *)data, size, &scene);
    if (st != SVP_OK) {
        if (scene) abort();
        const char *msg = svp_last_error();
        if (!msg || !*msg) abort();
        return 0;
    }
    const svp_scene_stage *stages = NULL;
    int n = svp_scene_plan(scene, &stages);
    if (n < 0 || (n > 0 && !stages) || !svp_scene_name(scene)) abort();
    svp_scene_free(scene);
    return 0;
}
