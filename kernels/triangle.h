/* triangle.h - the two ray/triangle intersectors.
 *
 * Both return 1 and set *t_out when the ray meets the triangle at some
 * t in (0, t_max).  Neither uses an absolute epsilon: a scale-dependent
 * tolerance would break scenes scaled by 1e-20 or 1e20.  A degenerate
 * (zero-area) triangle is never hit (see GC_DET_ULPS).
 */
#ifndef GC_TRIANGLE_H
#define GC_TRIANGLE_H

#include "gc_internal.h"

/* Rounding-error bound on a determinant, in units of the magnitudes of the
 * products it sums (a few ulps: each product and sum rounds once).  A
 * determinant at or below it is rounding noise: the triangle is degenerate
 * (zero area) or the ray lies in its plane, and the test reports no hit
 * rather than a t made of noise.  Relative, so scenes scaled by 1e-20 or
 * 1e20 behave alike. */
#define GC_DET_ULPS (8.0 * 2.220446049250313e-16)

/* Moller and Trumbore, "Fast, minimum storage ray-triangle intersection",
 * JGT 2(1) 1997.  Not watertight: rays through shared edges or vertices can
 * slip between the two triangles when rounding disagrees. */
GC_INLINE int gc_isect_moller_trumbore(const gc_ray *r, const gc_tri *tri, double t_max,
                                       double *t_out)
{
    const double *v0 = tri->v0, *v1 = tri->v1, *v2 = tri->v2;
    double e1[3] = {v1[0] - v0[0], v1[1] - v0[1], v1[2] - v0[2]};
    double e2[3] = {v2[0] - v0[0], v2[1] - v0[1], v2[2] - v0[2]};
    double p[3] = {r->d[1] * e2[2] - r->d[2] * e2[1], r->d[2] * e2[0] - r->d[0] * e2[2],
                   r->d[0] * e2[1] - r->d[1] * e2[0]};
    double det = e1[0] * p[0] + e1[1] * p[1] + e1[2] * p[2];
    double s[3] = {r->o[0] - v0[0], r->o[1] - v0[1], r->o[2] - v0[2]};
    double q[3] = {s[1] * e1[2] - s[2] * e1[1], s[2] * e1[0] - s[0] * e1[2],
                   s[0] * e1[1] - s[1] * e1[0]};
    /* Barycentrics and t scaled by det, compared with det's sign folded in, so
     * the test divides only on a hit and decides everything without a branch:
     * whether a test hits is unpredictable, and a mispredicted branch costs as
     * much as the test. */
    const double sgn = det < 0.0 ? -1.0 : 1.0;
    const double adet = det * sgn;
    const double u = (s[0] * p[0] + s[1] * p[1] + s[2] * p[2]) * sgn;
    const double v = (r->d[0] * q[0] + r->d[1] * q[1] + r->d[2] * q[2]) * sgn;
    const double tt = (e2[0] * q[0] + e2[1] * q[1] + e2[2] * q[2]) * sgn;
    /* det = e1 . (d x e2): its rounding is bounded by the magnitudes of every product in it */
    const double mag = (fabs(e1[0]) + fabs(e1[1]) + fabs(e1[2])) *
                       (fabs(r->d[0]) + fabs(r->d[1]) + fabs(r->d[2])) *
                       (fabs(e2[0]) + fabs(e2[1]) + fabs(e2[2]));
    const int ok = (adet > GC_DET_ULPS * mag) & (u >= 0.0) & (v >= 0.0) & (u + v <= adet) & (tt > 0.0) &
                   (tt < t_max * adet);
    if (!ok) {
        return 0;
    }
    const double t = tt / adet;
    if (!(t > 0.0 && t < t_max)) { /* the scaled comparison can round the other way */
        return 0;
    }
    *t_out = t;
    return 1;
}

/* Woop, Benthin and Wald, "Watertight Ray/Triangle Intersection", JCGT 2(1)
 * 2013.  Vertices are translated to the ray origin and sheared so the ray runs
 * along +z; the 2D edge functions U, V, W of a shared edge are then computed
 * from identical operands in both triangles and are exact negations of each
 * other, so no ray slips through an edge or a vertex.  In double precision the
 * paper's fallback for an exactly zero edge function is not needed: zero is
 * handled consistently by the inclusive sign test.  Requires -ffp-contract=off
 * (a fused multiply-add would break the negation symmetry). */
GC_INLINE int gc_isect_watertight(const gc_ray *r, const gc_tri *tri, double t_max,
                                  double *t_out)
{
    const int kx = r->kx, ky = r->ky, kz = r->kz;
    double a[3] = {tri->v0[0] - r->o[0], tri->v0[1] - r->o[1], tri->v0[2] - r->o[2]};
    double b[3] = {tri->v1[0] - r->o[0], tri->v1[1] - r->o[1], tri->v1[2] - r->o[2]};
    double c[3] = {tri->v2[0] - r->o[0], tri->v2[1] - r->o[1], tri->v2[2] - r->o[2]};
    double ax = a[kx] - r->sx * a[kz], ay = a[ky] - r->sy * a[kz];
    double bx = b[kx] - r->sx * b[kz], by = b[ky] - r->sy * b[kz];
    double cx = c[kx] - r->sx * c[kz], cy = c[ky] - r->sy * c[kz];
    double u = cx * by - cy * bx;
    double v = ax * cy - ay * cx;
    double w = bx * ay - by * ax;
    double det = u + v + w;
    /* Rounding bound of det.  Each sheared coordinate (e.g. ax = a[kx] - sx a[kz])
     * carries an error of about one ulp of the magnitudes it was made from
     * (max_ = |a[kx]| + |sx a[kz]|), which can exceed what is left of it after
     * cancellation; a product p q then errs by about m_p |q| + |p| m_q. */
    const double max_ = fabs(a[kx]) + fabs(r->sx * a[kz]), may = fabs(a[ky]) + fabs(r->sy * a[kz]);
    const double mbx = fabs(b[kx]) + fabs(r->sx * b[kz]), mby = fabs(b[ky]) + fabs(r->sy * b[kz]);
    const double mcx = fabs(c[kx]) + fabs(r->sx * c[kz]), mcy = fabs(c[ky]) + fabs(r->sy * c[kz]);
    const double mag = mcx * fabs(by) + fabs(cx) * mby + mcy * fabs(bx) + fabs(cy) * mbx + max_ * fabs(cy) +
                       fabs(ax) * mcy + may * fabs(cx) + fabs(ay) * mcx + mbx * fabs(ay) + fabs(bx) * may +
                       mby * fabs(ax) + fabs(by) * max_;
    double az = r->sz * a[kz], bz = r->sz * b[kz], cz = r->sz * c[kz];
    double tt = u * az + v * bz + w * cz;
    /* The paper's sign tests, with det's sign folded into T so that nothing
     * divides before a hit and nothing branches before the verdict. */
    const double sgn = det < 0.0 ? -1.0 : 1.0;
    const double adet = det * sgn;
    const double ts = tt * sgn;
    const int inside = ((u >= 0.0) & (v >= 0.0) & (w >= 0.0)) | ((u <= 0.0) & (v <= 0.0) & (w <= 0.0));
    const int ok = inside & (adet > GC_DET_ULPS * mag) & (ts > 0.0) & (ts < t_max * adet);
    if (!ok) {
        return 0;
    }
    const double t = ts / adet;
    if (!(t > 0.0 && t < t_max)) {
        return 0;
    }
    *t_out = t;
    return 1;
}

#endif /* GC_TRIANGLE_H */
