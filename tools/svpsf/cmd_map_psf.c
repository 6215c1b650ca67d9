/* svpsf map-psf (under construction) */
#include "cli.h"
int cmd_map_psf(int argc, char **argv)
{
    (void)argc;
    (void)argv;
    return 2;
}
