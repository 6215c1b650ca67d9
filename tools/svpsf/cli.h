/* Shared helpers of the svpsf command-line program. */
#ifndef SVPSF_CLI_H
#define SVPSF_CLI_H
#include "svpsf.h"
#endif
