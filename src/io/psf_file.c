#include "../core/internal.h"
