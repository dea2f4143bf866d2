/* box.h - ray/box slab test.
 *
 * Robust to direction components of +0 and -0 (the ray lies in the slab or
 * misses it; 0 * inf never forms) and to origins inside or on the box.  Every
 * comparison is written so that a NaN makes it fail.
 */
#ifndef GC_BOX_H
#define GC_BOX_H

#include "gc_internal.h"

/* Each slab's [t_near, t_far] is widened by this many ulps of its values, so
 * a ray that grazes the box along an edge or through a corner, where rounding
 * can make one slab's exit fall a hair before another's entry, still enters
 * (pbrt widens t_far by 1 + 2 gamma(3) for the same reason). */
#define GC_SLAB_WIDEN (4.0 * 2.220446049250313e-16)

/* Clip the ray's interval [*t0, *t1] to the box [lo, hi].  Returns 1 if a
 * non-empty interval remains (a ray touching the box in one point counts).
 * A ray parallel to a slab counts as inside it within a few ulps of the
 * slab's planes, for the same reason. */
GC_INLINE int gc_ray_box_clip(const gc_ray *r, const double lo[3], const double hi[3],
                              double *t0, double *t1)
{
    double ta = *t0, tb = *t1;
    for (int i = 0; i < 3; ++i) {
        if (r->d[i] == 0.0) {
            /* parallel to the slab: inside it for every t, or never */
            const double pad = GC_SLAB_WIDEN * fmax(fabs(lo[i]), fabs(hi[i]));
            if (!(r->o[i] >= lo[i] - pad && r->o[i] <= hi[i] + pad)) {
                return 0;
            }
            continue;
        }
        double tn = (lo[i] - r->o[i]) * r->inv_d[i];
        double tf = (hi[i] - r->o[i]) * r->inv_d[i];
        /* minima and maxima, not branches: which slab plane comes first is a
         * coin toss for the branch predictor when rays go every way */
        const double t_lo = tn > tf ? tf : tn, t_hi = tn > tf ? tn : tf;
        const double wn = t_lo - GC_SLAB_WIDEN * fabs(t_lo);
        const double wf = t_hi + GC_SLAB_WIDEN * fabs(t_hi);
        ta = wn > ta ? wn : ta;
        tb = wf < tb ? wf : tb;
    }
    if (!(ta <= tb)) {
        return 0;
    }
    *t0 = ta;
    *t1 = tb;
    return 1;
}

#endif /* GC_BOX_H */
