#include "../blur/blur_internal.h"
