/* svpsf psf-compare (under construction) */
#include "cli.h"
int cmd_psf_compare(int argc, char **argv)
{
    (void)argc;
    (void)argv;
    return 2;
}
