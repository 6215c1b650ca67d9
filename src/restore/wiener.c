#include "../blur/blur_internal.h"
void svp_deconv_defaults(svp_deconv_options *o) { o->balance = 1e-3; o->iterations = 50; o->floor = 1e-9; o->boundary_weights = 1; o->progress = NULL; o->progress_user = NULL; }
svp_status svp_deconv_wiener(svp_blur *b, const svp_image *y, const svp_deconv_options *o, svp_image *x) { (void)b; (void)y; (void)o; (void)x; return svp_fail(SVP_ERR_UNSUPPORTED, "not yet"); }
