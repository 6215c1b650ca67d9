#include "svpsf.h"
#include <stdio.h>
int main(void) { printf("svpsf %s\n", svp_version()); return 0; }
