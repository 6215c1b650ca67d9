/* (module under construction) */
#include "../core/internal.h"
