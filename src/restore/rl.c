#include "../blur/blur_internal.h"
svp_status svp_deconv_rl(svp_blur *b, const svp_image *y, const svp_deconv_options *o, svp_image *x) { (void)b; (void)y; (void)o; (void)x; return svp_fail(SVP_ERR_UNSUPPORTED, "not yet"); }
