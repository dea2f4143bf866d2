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
    /* det = e1 . (d x e2): bound its rounding by the magnitudes of every product in it */
    double mag = (fabs(e1[0]) + fabs(e1[1]) + fabs(e1[2])) * (fabs(r->d[0]) + fabs(r->d[1]) + fabs(r->d[2])) *
                 (fabs(e2[0]) + fabs(e2[1]) + fabs(e2[2]));
    if (!(fabs(det) > GC_DET_ULPS * mag)) {
        return 0;
    }
    double inv_det = 1.0 / det;
    double s[3] = {r->o[0] - v0[0], r->o[1] - v0[1], r->o[2] - v0[2]};
    double u = (s[0] * p[0] + s[1] * p[1] + s[2] * p[2]) * inv_det;
    if (!(u >= 0.0 && u <= 1.0)) {
        return 0;
    }
    double q[3] = {s[1] * e1[2] - s[2] * e1[1], s[2] * e1[0] - s[0] * e1[2],
                   s[0] * e1[1] - s[1] * e1[0]};
    double v = (r->d[0] * q[0] + r->d[1] * q[1] + r->d[2] * q[2]) * inv_det;
    if (!(v >= 0.0 && u + v <= 1.0)) {
        return 0;
    }
    double t = (e2[0] * q[0] + e2[1] * q[1] + e2[2] * q[2]) * inv_det;
    if (!(t > 0.0 && t < t_max)) {
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
    if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) {
        return 0;
    }
    double det = u + v + w;
    double mag = fabs(cx * by) + fabs(cy * bx) + fabs(ax * cy) + fabs(ay * cx) + fabs(bx * ay) + fabs(by * ax);
    if (!(fabs(det) > GC_DET_ULPS * mag)) {
        return 0;
    }
    double az = r->sz * a[kz], bz = r->sz * b[kz], cz = r->sz * c[kz];
    double tt = u * az + v * bz + w * cz;
    double t = tt / det;
    if (!(t > 0.0 && t < t_max)) {
        return 0;
    }
    *t_out = t;
    return 1;
}

#endif /* GC_TRIANGLE_H */
