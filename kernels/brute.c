/* brute.c - the reference: every ray against every triangle. */
#include "gc_internal.h"
#include "triangle.h"

gc_status gc_brute_force(const gc_mesh *mesh, gc_intersector intersector, int64_t n,
                         const double *origins, const double *directions, double *t, int32_t *prim,
                         char *err)
{
    gc_status st = gc_check_mesh(mesh, 1, NULL, NULL, err);
    if (st != GC_OK) {
        return st;
    }
    st = gc_check_rays(n, origins, directions, err);
    if (st != GC_OK) {
        return st;
    }
    for (int64_t k = 0; k < n; ++k) {
        gc_ray r;
        gc_ray_prepare(&r, origins + 3 * k, directions + 3 * k);
        double best = INFINITY;
        int32_t best_prim = -1;
        for (int64_t f = 0; f < mesh->n_faces; ++f) {
            gc_pack tri; /* lane 0 holds the triangle */
            for (int c = 0; c < 9; ++c) {
                tri.c[c][0] = mesh->vertices[3 * mesh->faces[3 * f + c / 3] + c % 3];
            }
            double th;
            int hit = intersector == GC_WATERTIGHT ? gc_isect_watertight(&r, &tri.c[0][0], best, &th)
                                                   : gc_isect_moller_trumbore(&r, &tri.c[0][0], best, &th);
            if (hit) {
                best = th;
                best_prim = (int32_t)f;
            }
        }
        t[k] = best;
        prim[k] = best_prim;
    }
    return GC_OK;
}
