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
