/* (command under construction) */
#include "cli.h"
