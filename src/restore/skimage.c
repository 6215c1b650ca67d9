#include "../blur/blur_internal.h"
svp_status svp_skimage_wiener(const svp_image *image, const svp_image *psf, double balance, svp_image *out) { (void)image; (void)psf; (void)balance; (void)out; return svp_fail(SVP_ERR_UNSUPPORTED, "not yet"); }
svp_status svp_skimage_richardson_lucy(const svp_image *image, const svp_image *psf, int num_iter, svp_progress_fn p, void *u, svp_image *out) { (void)image; (void)psf; (void)num_iter; (void)p; (void)u; (void)out; return svp_fail(SVP_ERR_UNSUPPORTED, "not yet"); }
