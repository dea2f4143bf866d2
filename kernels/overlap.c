/* overlap.c - exact triangle/axis-aligned-box overlap by the separating axis
 * theorem (Akenine-Moller, "Fast 3D triangle-box overlap testing", JGT 2001):
 * the box's three face normals, the triangle's normal and the nine cross
 * products of box axes with triangle edges.  Touching counts as overlapping,
 * so a triangle lying in a shared cell face belongs to both cells.
 */
#include "gc_internal.h"

/* Project the triangle (centred on the box) on an axis and compare with the
 * box's projection radius. */
static int separated(const double a[3], const double v0[3], const double v1[3],
                     const double v2[3], const double half[3])
{
    double p0 = a[0] * v0[0] + a[1] * v0[1] + a[2] * v0[2];
    double p1 = a[0] * v1[0] + a[1] * v1[1] + a[2] * v1[2];
    double p2 = a[0] * v2[0] + a[1] * v2[1] + a[2] * v2[2];
    double mn = fmin(p0, fmin(p1, p2)), mx = fmax(p0, fmax(p1, p2));
    double rad = half[0] * fabs(a[0]) + half[1] * fabs(a[1]) + half[2] * fabs(a[2]);
    return mn > rad || mx < -rad;
}

int gc_triangle_box_overlap(const double tv0[3], const double tv1[3], const double tv2[3],
                            const double lo[3], const double hi[3])
{
    double c[3], half[3], v0[3], v1[3], v2[3];
    for (int i = 0; i < 3; ++i) {
        c[i] = 0.5 * (lo[i] + hi[i]);
        half[i] = 0.5 * (hi[i] - lo[i]);
        v0[i] = tv0[i] - c[i];
        v1[i] = tv1[i] - c[i];
        v2[i] = tv2[i] - c[i];
    }
    /* box face normals: the bounding boxes overlap */
    for (int i = 0; i < 3; ++i) {
        double mn = fmin(v0[i], fmin(v1[i], v2[i])), mx = fmax(v0[i], fmax(v1[i], v2[i]));
        if (mn > half[i] || mx < -half[i]) {
            return 0;
        }
    }
    double e[3][3];
    for (int i = 0; i < 3; ++i) {
        e[0][i] = v1[i] - v0[i];
        e[1][i] = v2[i] - v1[i];
        e[2][i] = v0[i] - v2[i];
    }
    /* triangle normal: the plane meets the box */
    double n[3] = {e[0][1] * e[1][2] - e[0][2] * e[1][1], e[0][2] * e[1][0] - e[0][0] * e[1][2],
                   e[0][0] * e[1][1] - e[0][1] * e[1][0]};
    if (separated(n, v0, v1, v2, half)) {
        return 0;
    }
    /* the nine edge cross products (axis x edge) */
    for (int k = 0; k < 3; ++k) {
        const double *f = e[k];
        double a0[3] = {0.0, -f[2], f[1]};
        double a1[3] = {f[2], 0.0, -f[0]};
        double a2[3] = {-f[1], f[0], 0.0};
        if (separated(a0, v0, v1, v2, half) || separated(a1, v0, v1, v2, half) ||
            separated(a2, v0, v1, v2, half)) {
            return 0;
        }
    }
    return 1;
}

/* The same test for one triangle against many boxes: everything that depends
 * on the triangle alone (its bounds, the thirteen axes and the vertices'
 * projections on them) is formed once.  Coordinates are taken relative to the
 * triangle's first vertex, so the projections keep the precision of the
 * triangle's and the box's extents wherever the scene lies. */
void gc_tri_box_prepare(gc_tri_box_prep *p, const double v0[3], const double v1[3], const double v2[3])
{
    double w1[3], w2[3], e[3][3];
    for (int i = 0; i < 3; ++i) {
        p->o[i] = v0[i];
        w1[i] = v1[i] - v0[i];
        w2[i] = v2[i] - v0[i];
        p->bmin[i] = GC_MIN(v0[i], GC_MIN(v1[i], v2[i]));
        p->bmax[i] = GC_MAX(v0[i], GC_MAX(v1[i], v2[i]));
        e[0][i] = w1[i];
        e[1][i] = v2[i] - v1[i];
        e[2][i] = v0[i] - v2[i];
    }
    double (*ax)[3] = p->axis;
    ax[0][0] = e[0][1] * e[1][2] - e[0][2] * e[1][1]; /* the normal */
    ax[0][1] = e[0][2] * e[1][0] - e[0][0] * e[1][2];
    ax[0][2] = e[0][0] * e[1][1] - e[0][1] * e[1][0];
    for (int k = 0; k < 3; ++k) { /* box axis x edge */
        const double *f = e[k];
        double *a0 = ax[1 + 3 * k], *a1 = ax[2 + 3 * k], *a2 = ax[3 + 3 * k];
        a0[0] = 0.0, a0[1] = -f[2], a0[2] = f[1];
        a1[0] = f[2], a1[1] = 0.0, a1[2] = -f[0];
        a2[0] = -f[1], a2[1] = f[0], a2[2] = 0.0;
    }
    for (int k = 0; k < GC_TRI_BOX_AXES; ++k) {
        const double p1 = ax[k][0] * w1[0] + ax[k][1] * w1[1] + ax[k][2] * w1[2];
        const double p2 = ax[k][0] * w2[0] + ax[k][1] * w2[1] + ax[k][2] * w2[2];
        p->pmin[k] = GC_MIN(0.0, GC_MIN(p1, p2));
        p->pmax[k] = GC_MAX(0.0, GC_MAX(p1, p2));
        for (int i = 0; i < 3; ++i) {
            p->axis_abs[k][i] = fabs(ax[k][i]);
        }
    }
}

int gc_tri_box_prepared_overlap(const gc_tri_box_prep *p, const double lo[3], const double hi[3])
{
    for (int i = 0; i < 3; ++i) { /* box face normals: the bounding boxes overlap */
        if (p->bmin[i] > hi[i] || p->bmax[i] < lo[i]) {
            return 0;
        }
    }
    double c[3], half[3];
    for (int i = 0; i < 3; ++i) {
        c[i] = 0.5 * (lo[i] + hi[i]) - p->o[i];
        half[i] = 0.5 * (hi[i] - lo[i]);
    }
    for (int k = 0; k < GC_TRI_BOX_AXES; ++k) { /* the normal, then the nine edge axes */
        const double d = p->axis[k][0] * c[0] + p->axis[k][1] * c[1] + p->axis[k][2] * c[2];
        const double rad = p->axis_abs[k][0] * half[0] + p->axis_abs[k][1] * half[1] + p->axis_abs[k][2] * half[2];
        if (p->pmin[k] - d > rad || p->pmax[k] - d < -rad) {
            return 0;
        }
    }
    return 1;
}
