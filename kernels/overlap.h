/* overlap.h - the exact triangle/box overlap of overlap.c for one triangle
 * against many boxes, as the build uses it.
 *
 * Everything that depends on the triangle alone (its bounds, the axes and the
 * vertices' projections on them) is formed once by gc_tri_box_prepare.
 * Coordinates are taken relative to the triangle's first vertex, so the
 * projections keep the precision of the triangle's and the box's extents
 * wherever the scene lies.  An edge axis (box axis x edge) has a zero
 * component, left out of every product.  The boxes come as scalars (bounds,
 * centre, half size per axis) so that the parts of the test that depend on one
 * axis only are hoisted out of the build's loop over the other.
 */
#ifndef GC_OVERLAP_H
#define GC_OVERLAP_H

#include "gc_internal.h"

typedef struct {
    double o[3];                   /* the first vertex: the local origin */
    double bmin[3], bmax[3];       /* the triangle's bounds */
    double n[3], n_abs[3];         /* the normal */
    double nmin, nmax;             /* projections of the local vertices on the normal */
    double e[3][3], e_abs[3][3];   /* the edges */
    double emin[3][3], emax[3][3]; /* [edge][box axis]: projections on box axis x edge */
} gc_tri_box_prep;

/* What both tests take from the triangle: the local origin o (its first vertex), the
 * other vertices relative to it (w1, w2), the edges e and the bounds. */
GC_INLINE void gc_tri_local(const double v0[3], const double v1[3], const double v2[3], double o[3],
                            double w1[3], double w2[3], double e[3][3], double bmin[3], double bmax[3])
{
    for (int i = 0; i < 3; ++i) {
        o[i] = v0[i];
        w1[i] = v1[i] - v0[i];
        w2[i] = v2[i] - v0[i];
        bmin[i] = GC_MIN(v0[i], GC_MIN(v1[i], v2[i]));
        bmax[i] = GC_MAX(v0[i], GC_MAX(v1[i], v2[i]));
        e[0][i] = w1[i];
        e[1][i] = v2[i] - v1[i];
        e[2][i] = v0[i] - v2[i];
    }
}

GC_INLINE void gc_tri_box_prepare(gc_tri_box_prep *p, const double v0[3], const double v1[3],
                                  const double v2[3])
{
    double w1[3], w2[3], e[3][3];
    gc_tri_local(v0, v1, v2, p->o, w1, w2, e, p->bmin, p->bmax);
    double *n = p->n;
    n[0] = e[0][1] * e[1][2] - e[0][2] * e[1][1];
    n[1] = e[0][2] * e[1][0] - e[0][0] * e[1][2];
    n[2] = e[0][0] * e[1][1] - e[0][1] * e[1][0];
    const double n1 = n[0] * w1[0] + n[1] * w1[1] + n[2] * w1[2];
    const double n2 = n[0] * w2[0] + n[1] * w2[1] + n[2] * w2[2];
    p->nmin = GC_MIN(0.0, GC_MIN(n1, n2));
    p->nmax = GC_MAX(0.0, GC_MAX(n1, n2));
    for (int i = 0; i < 3; ++i) {
        p->n_abs[i] = fabs(n[i]);
    }
    for (int k = 0; k < 3; ++k) {
        const double *f = e[k];
        /* x x f = (0, -f2, f1), y x f = (f2, 0, -f0), z x f = (-f1, f0, 0) */
        const double q[3][2] = {{-f[2] * w1[1] + f[1] * w1[2], -f[2] * w2[1] + f[1] * w2[2]},
                                {f[2] * w1[0] - f[0] * w1[2], f[2] * w2[0] - f[0] * w2[2]},
                                {-f[1] * w1[0] + f[0] * w1[1], -f[1] * w2[0] + f[0] * w2[1]}};
        for (int j = 0; j < 3; ++j) {
            p->emin[k][j] = GC_MIN(0.0, GC_MIN(q[j][0], q[j][1]));
            p->emax[k][j] = GC_MAX(0.0, GC_MAX(q[j][0], q[j][1]));
            p->e[k][j] = f[j];
            p->e_abs[k][j] = fabs(f[j]);
        }
    }
}

/* The box face normals, the first axes of both tests below: the triangle's bounds
 * [bmin, bmax] miss the box [lo, hi]. */
GC_INLINE int gc_bounds_apart(const double bmin[3], const double bmax[3], double lo0, double lo1, double lo2,
                              double hi0, double hi1, double hi2)
{
    return (bmin[0] > hi0) | (bmax[0] < lo0) | (bmin[1] > hi1) | (bmax[1] < lo1) | (bmin[2] > hi2) |
           (bmax[2] < lo2);
}

/* The separating-axis test of gc_triangle_box_overlap for a prepared triangle
 * and the box [lo, hi] with centre m and half size h (m = (lo + hi) / 2 and
 * h = (hi - lo) / 2, per axis). */
GC_INLINE int gc_tri_box_prepared_overlap(const gc_tri_box_prep *p, double lo0, double lo1, double lo2,
                                          double hi0, double hi1, double hi2, double m0, double m1,
                                          double m2, double h0, double h1, double h2)
{
    if (gc_bounds_apart(p->bmin, p->bmax, lo0, lo1, lo2, hi0, hi1, hi2)) { /* box face normals */
        return 0;
    }
    const double c0 = m0 - p->o[0], c1 = m1 - p->o[1], c2 = m2 - p->o[2];
    { /* the triangle's normal: its plane meets the box */
        const double d = p->n[0] * c0 + p->n[1] * c1 + p->n[2] * c2;
        const double rad = p->n_abs[0] * h0 + p->n_abs[1] * h1 + p->n_abs[2] * h2;
        if ((p->nmin - d > rad) | (p->nmax - d < -rad)) {
            return 0;
        }
    }
    for (int k = 0; k < 3; ++k) { /* the nine edge axes */
        const double *f = p->e[k], *fa = p->e_abs[k], *mn = p->emin[k], *mx = p->emax[k];
        const double dx = -f[2] * c1 + f[1] * c2, rx = fa[2] * h1 + fa[1] * h2;
        const double dy = f[2] * c0 - f[0] * c2, ry = fa[2] * h0 + fa[0] * h2;
        const double dz = -f[1] * c0 + f[0] * c1, rz = fa[1] * h0 + fa[0] * h1;
        if ((mn[0] - dx > rx) | (mx[0] - dx < -rx) | (mn[1] - dy > ry) | (mx[1] - dy < -ry) |
            (mn[2] - dz > rz) | (mx[2] - dz < -rz)) {
            return 0;
        }
    }
    return 1;
}

/* A triangle within one slab of cells along axis a (its bounds inside the slab's
 * widened bounds on a) meets a box of that slab exactly where its projection on
 * the other two axes (u, v) = (a + 1, a + 2) meets the box's.  Of the 3D test's
 * thirteen axes, that leaves the box's u and v axes and the three axes a x edge,
 * which gc_tri_slab_prepare and gc_tri_slab_prepared_overlap compute as
 * gc_tri_box_prepare and gc_tri_box_prepared_overlap do, operation for operation:
 * a box the 3D test accepts is accepted, and one it rejects only by the axes left
 * out would need the triangle to leave the slab. */
typedef struct {
    double o[3];               /* the first vertex: the local origin */
    double bmin[3], bmax[3];   /* the triangle's bounds */
    double f[3][2], fa[3][2];  /* the edges' u and v components, and their magnitudes */
    double pmin[3], pmax[3];   /* projections of the local vertices on a x edge */
    int u, v;
} gc_tri_slab_prep;

GC_INLINE void gc_tri_slab_prepare(gc_tri_slab_prep *p, const double v0[3], const double v1[3],
                                   const double v2[3], int a)
{
    const int u = (a + 1) % 3, v = (a + 2) % 3;
    double w1[3], w2[3], e[3][3];
    gc_tri_local(v0, v1, v2, p->o, w1, w2, e, p->bmin, p->bmax);
    for (int k = 0; k < 3; ++k) {
        /* a x f has components -f_v on u and f_u on v */
        const double q1 = -e[k][v] * w1[u] + e[k][u] * w1[v], q2 = -e[k][v] * w2[u] + e[k][u] * w2[v];
        p->pmin[k] = GC_MIN(0.0, GC_MIN(q1, q2));
        p->pmax[k] = GC_MAX(0.0, GC_MAX(q1, q2));
        p->f[k][0] = e[k][u];
        p->f[k][1] = e[k][v];
        p->fa[k][0] = fabs(e[k][u]);
        p->fa[k][1] = fabs(e[k][v]);
    }
    p->u = u;
    p->v = v;
}

/* The test for a prepared slab triangle and the box [lo, hi] with centre m and half
 * size h, per axis, as gc_tri_box_prepared_overlap takes them. */
GC_INLINE int gc_tri_slab_prepared_overlap(const gc_tri_slab_prep *p, double lo0, double lo1, double lo2,
                                           double hi0, double hi1, double hi2, double m0, double m1,
                                           double m2, double h0, double h1, double h2)
{
    if (gc_bounds_apart(p->bmin, p->bmax, lo0, lo1, lo2, hi0, hi1, hi2)) {
        return 0;
    }
    const double m[3] = {m0, m1, m2}, h[3] = {h0, h1, h2};
    const int u = p->u, v = p->v;
    const double cu = m[u] - p->o[u], cv = m[v] - p->o[v];
    for (int k = 0; k < 3; ++k) {
        const double d = -p->f[k][1] * cu + p->f[k][0] * cv, r = p->fa[k][1] * h[u] + p->fa[k][0] * h[v];
        if ((p->pmin[k] - d > r) | (p->pmax[k] - d < -r)) {
            return 0;
        }
    }
    return 1;
}

#endif /* GC_OVERLAP_H */
