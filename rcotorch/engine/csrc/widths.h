/* lanes.h compiled for every lane width (VL = 1, 4, 8, 16) with the instruction set ISA: engine.c includes
 * this file once per instruction set. LANE_WIDTHS in engine.c lists the same widths. */
#define VL 1
#include "lanes.h"
#undef VL
#define VL 4
#include "lanes.h"
#undef VL
#define VL 8
#include "lanes.h"
#undef VL
#define VL 16
#include "lanes.h"
#undef VL
