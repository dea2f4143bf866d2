/* box.h - ray/box slab test.
 *
 * Robust to direction components of +0 and -0 (the ray lies in the slab or
 * misses it; 0 * inf never forms) and to origins inside or on the box.  Every
 * comparison is written so that a NaN makes it fail.
 */
#ifndef GC_BOX_H
#define GC_BOX_H

#include "gc_internal.h"

/* Clip the ray's interval [*t0, *t1] to the box [lo, hi].  Returns 1 if a
 * non-empty interval remains (a ray touching the box in one point counts). */
GC_INLINE int gc_ray_box_clip(const gc_ray *r, const double lo[3], const double hi[3],
                              double *t0, double *t1)
{
    double ta = *t0, tb = *t1;
    for (int i = 0; i < 3; ++i) {
        if (r->d[i] == 0.0) {
            /* parallel to the slab: inside it for every t, or never */
            if (!(r->o[i] >= lo[i] && r->o[i] <= hi[i])) {
                return 0;
            }
            continue;
        }
        double tn = (lo[i] - r->o[i]) * r->inv_d[i];
        double tf = (hi[i] - r->o[i]) * r->inv_d[i];
        if (tn > tf) {
            double tmp = tn;
            tn = tf;
            tf = tmp;
        }
        if (tn > ta) {
            ta = tn;
        }
        if (tf < tb) {
            tb = tf;
        }
    }
    if (!(ta <= tb)) {
        return 0;
    }
    *t0 = ta;
    *t1 = tb;
    return 1;
}

#endif /* GC_BOX_H */
